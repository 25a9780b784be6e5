/* The z-buffer of recon/geometry/raster.py's rasterize in C: the same faces, culling, bounds, pixels and arithmetic,
 * one face after another (raster.py's numpy code is the reference; tests/test_geometry_raster.py holds the two
 * together). Built and loaded by recon.nerf.native.load_c_library; plain C, no Python headers. */
#include <math.h>
#include <stdint.h>

/* Faces 0..n_faces) in order, each three indices into xy (V, 2) pixel coordinates and depth (V,) (NULL: every vertex
 * at depth 1, a flat layout). A face is drawn when its corners are finite, its doubled area exceeds 1e-12 in size, its
 * nearest corner lies beyond 1e-9 and its bounds meet the width x height image. A pixel takes a face when its centre
 * is inside or on an edge (weights >= -1e-12) and the face is strictly nearer than what the pixel holds: of faces at
 * equal depth the earlier one keeps it, as in the numpy code. */
void recon_rasterize(int64_t n_faces, const int64_t *faces, const double *xy, const double *depth, int64_t width,
                     int64_t height, int64_t *face_id, double *bary, double *zbuf)
{
    for (int64_t f = 0; f < n_faces; f++) {
        double t[6], w[3];
        int finite = 1;
        for (int i = 0; i < 3; i++) {
            const int64_t v = faces[3 * f + i];
            t[2 * i] = xy[2 * v];
            t[2 * i + 1] = xy[2 * v + 1];
            w[i] = depth ? depth[v] : 1.0;
            finite &= isfinite(t[2 * i]) && isfinite(t[2 * i + 1]) && isfinite(w[i]);
        }
        if (!finite)
            continue;
        const double ar = (t[2] - t[0]) * (t[5] - t[1]) - (t[3] - t[1]) * (t[4] - t[0]);
        const double nearest = fmin(fmin(w[0], w[1]), w[2]);
        if (!(fabs(ar) > 1e-12) || !(nearest > 1e-9))
            continue;
        /* pixel centres c + 0.5 inside the bounds: c in [ceil(min - 0.5), floor(max - 0.5)], clipped to the image */
        const double lx = fmax(ceil(fmin(fmin(t[0], t[2]), t[4]) - 0.5), 0.0);
        const double ly = fmax(ceil(fmin(fmin(t[1], t[3]), t[5]) - 0.5), 0.0);
        const double hx = fmin(floor(fmax(fmax(t[0], t[2]), t[4]) - 0.5), (double)(width - 1));
        const double hy = fmin(floor(fmax(fmax(t[1], t[3]), t[5]) - 0.5), (double)(height - 1));
        if (hx < lx || hy < ly)
            continue;
        for (int64_t py = (int64_t)ly; py <= (int64_t)hy; py++) {
            const double cy = (double)py + 0.5;
            for (int64_t px = (int64_t)lx; px <= (int64_t)hx; px++) {
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
                const double d = 1.0 / s;
                const int64_t p = py * width + px;
                if (d < zbuf[p]) {
                    zbuf[p] = d;
                    face_id[p] = f;
                    bary[3 * p] = i0 / s;
                    bary[3 * p + 1] = i1 / s;
                    bary[3 * p + 2] = i2 / s;
                }
            }
        }
    }
}
