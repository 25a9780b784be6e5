/* The z-buffer of recon/geometry/raster.py's rasterize in C: the same faces, pixels and arithmetic, one face after
 * another (raster.py's numpy code is the reference; tests/test_geometry_raster.py holds the two together). Built
 * and loaded by recon.nerf.native.load_c_library; plain C, no Python headers. */
#include <stdint.h>

/* Faces ids[0..n) in order; tri (F, 3, 2) pixel coordinates, tri_w (F, 3) depths, area (F,) signed doubled areas;
 * lo, hi (n, 2) each face's first and last pixel column and row. A pixel takes a face when its centre is inside or
 * on an edge (weights >= -1e-12) and the face is strictly nearer than what the pixel holds: of faces at equal depth
 * the earlier one keeps it, as in the numpy code. */
void recon_rasterize(int64_t n, const int64_t *ids, const double *tri, const double *tri_w, const double *area,
                     const int64_t *lo, const int64_t *hi, int64_t width, int64_t *face_id, double *bary, double *zbuf)
{
    for (int64_t k = 0; k < n; k++) {
        const int64_t f = ids[k];
        const double *t = tri + 6 * f, *w = tri_w + 3 * f;
        const double ar = area[f];
        for (int64_t py = lo[2 * k + 1]; py <= hi[2 * k + 1]; py++) {
            const double cy = (double)py + 0.5;
            for (int64_t px = lo[2 * k]; px <= hi[2 * k]; px++) {
                const double cx = (double)px + 0.5;
                double b[3];
                for (int i = 0; i < 3; i++) {
                    const double *a = t + 2 * ((i + 1) % 3), *c = t + 2 * ((i + 2) % 3);
                    b[i] = ((a[0] - cx) * (c[1] - cy) - (a[1] - cy) * (c[0] - cx)) / ar;
                }
                if (b[0] < -1e-12 || b[1] < -1e-12 || b[2] < -1e-12)
                    continue;
                const double i0 = b[0] / w[0], i1 = b[1] / w[1], i2 = b[2] / w[2];
                const double s = i0 + i1 + i2;
                const double depth = 1.0 / s;
                const int64_t p = py * width + px;
                if (depth < zbuf[p]) {
                    zbuf[p] = depth;
                    face_id[p] = f;
                    bary[3 * p] = i0 / s;
                    bary[3 * p + 1] = i1 / s;
                    bary[3 * p + 2] = i2 / s;
                }
            }
        }
    }
}
