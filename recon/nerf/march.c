/* Front-to-back marching through an occupancy grid and a multi-level dense density grid, one ray at a time.
 *
 * The same samples as recon.nerf.occupancy.march_front_to_back with the fast model's density
 * (recon.nerf.fast.FastModel._sigma_unit on dense scalar grids): uniform steps t_k = t_near + (k + u) * step,
 * kept when the step's midpoint lies in an occupied cell, densities summed over the levels (trilinear,
 * "align corners"), and a ray stops before the first sample whose optical depth so far reaches log_min_t.
 * In torch that march is ~25 passes over every candidate step; here a candidate costs a few flops and an
 * empty step never leaves the registers. Plain C (no Python or torch headers): it builds in a second,
 * and recon.nerf.native falls back to the torch marcher wherever it does not build.
 *
 * Returns the number of samples of these rays. Samples are written while they fit in `capacity`; a
 * return value above it asks the caller to call again with that capacity.
 */
#include <math.h>
#include <stdint.h>

static inline float clamp01(float v) { return v < 0.0f ? 0.0f : (v > 1.0f ? 1.0f : v); }

/* Trilinear read of a (res, res, res) table indexed [ix][iy][iz] at unit coordinates (u in [0, 1]^3). */
static inline float trilinear(const float *table, int64_t res, float ux, float uy, float uz) {
    float px = ux * (float)(res - 1), py = uy * (float)(res - 1), pz = uz * (float)(res - 1);
    int64_t ix = (int64_t)floorf(px), iy = (int64_t)floorf(py), iz = (int64_t)floorf(pz);
    if (ix > res - 2) ix = res - 2;
    if (iy > res - 2) iy = res - 2;
    if (iz > res - 2) iz = res - 2;
    if (ix < 0) ix = 0;
    if (iy < 0) iy = 0;
    if (iz < 0) iz = 0;
    float fx = px - (float)ix, fy = py - (float)iy, fz = pz - (float)iz;
    const int64_t sx = res * res, sy = res;
    const float *c = table + ix * sx + iy * sy + iz;
    float c00 = c[0] * (1.0f - fz) + c[1] * fz;
    float c01 = c[sy] * (1.0f - fz) + c[sy + 1] * fz;
    float c10 = c[sx] * (1.0f - fz) + c[sx + 1] * fz;
    float c11 = c[sx + sy] * (1.0f - fz) + c[sx + sy + 1] * fz;
    float c0 = c00 * (1.0f - fy) + c01 * fy;
    float c1 = c10 * (1.0f - fy) + c11 * fy;
    return c0 * (1.0f - fx) + c1 * fx;
}

int64_t recon_march_dense(
    int64_t n_rays, const float *rays_o, const float *rays_d, const float *t_near, const float *t_far,
    const float *jitter,                                   /* (n_rays,) or NULL */
    const uint8_t *occupied, int64_t occ_res, const float *occ_lo, const float *occ_hi,
    float step, int64_t max_samples, double log_min_t,
    int64_t n_levels, const float *const *tables, const int64_t *level_res,
    const float *grid_lo, const float *grid_hi,
    float bias, float density_scale, int32_t exp_activation, float sigma_max, float tau_max,
    int64_t capacity, float *out_ts, float *out_te, int64_t *out_ri, float *out_sigma, int64_t ray_base)
{
    int64_t m = 0;
    float scale[3], gsize[3];
    for (int a = 0; a < 3; ++a) {
        scale[a] = (float)occ_res / (occ_hi[a] - occ_lo[a]);
        gsize[a] = grid_hi[a] - grid_lo[a];
    }
    const float cells = (float)occ_res;
    for (int64_t r = 0; r < n_rays; ++r) {
        const float tn = t_near[r], tf = t_far[r];
        if (!(tf > tn)) continue;
        int64_t count = (int64_t)ceilf((tf - tn) / step);
        if (count > max_samples) count = max_samples;
        const float u = jitter ? jitter[r] : 0.0f;
        const float *o = rays_o + 3 * r, *d = rays_d + 3 * r;
        float po[3], pd[3];
        for (int a = 0; a < 3; ++a) {
            po[a] = (o[a] - occ_lo[a]) * scale[a];
            pd[a] = d[a] * scale[a];
        }
        double depth = 0.0;
        for (int64_t k = 0; k < count; ++k) {
            const float ts = tn + ((float)k + u) * step;
            if (!(ts < tf)) break;
            float te = ts + step;
            if (te > tf) te = tf;
            const float tm = 0.5f * (ts + te);
            const float px = po[0] + pd[0] * tm, py = po[1] + pd[1] * tm, pz = po[2] + pd[2] * tm;
            if (!(px >= 0.0f && px <= cells && py >= 0.0f && py <= cells && pz >= 0.0f && pz <= cells)) continue;
            int64_t ix = (int64_t)floorf(px), iy = (int64_t)floorf(py), iz = (int64_t)floorf(pz);
            if (ix > occ_res - 1) ix = occ_res - 1;
            if (iy > occ_res - 1) iy = occ_res - 1;
            if (iz > occ_res - 1) iz = occ_res - 1;
            if (!occupied[(ix * occ_res + iy) * occ_res + iz]) continue;
            if (!(depth < log_min_t)) break; /* transmittance at this sample's start is below the bar */
            const float ux = clamp01((o[0] + d[0] * tm - grid_lo[0]) / gsize[0]);
            const float uy = clamp01((o[1] + d[1] * tm - grid_lo[1]) / gsize[1]);
            const float uz = clamp01((o[2] + d[2] * tm - grid_lo[2]) / gsize[2]);
            float raw = 0.0f;
            for (int64_t l = 0; l < n_levels; ++l) raw += trilinear(tables[l], level_res[l], ux, uy, uz);
            raw += bias;
            float sigma;
            if (exp_activation) sigma = expf(raw < 15.0f ? raw : 15.0f);
            else sigma = raw > 20.0f ? raw : log1pf(expf(raw)); /* torch's softplus (threshold 20) */
            sigma *= density_scale;
            if (m < capacity) {
                out_ts[m] = ts;
                out_te[m] = te;
                out_ri[m] = ray_base + r;
                out_sigma[m] = sigma;
            }
            ++m;
            float s = sigma < 0.0f ? 0.0f : (sigma > sigma_max ? sigma_max : sigma);
            float tau = s * (te - ts > 0.0f ? te - ts : 0.0f);
            if (tau > tau_max) tau = tau_max;
            depth += (double)tau;
        }
    }
    return m;
}

/* Trilinear features of n points (unit coordinates u (n, 3), clamped to [0, 1]) from a channels-last
 * (res³, channels) table indexed [ix][iy][iz]: out (n, channels). recon.nerf.grid.DenseGrid.forward without
 * gradients; the torch path builds (n, 8) corner rows and weights first and gathers with embedding_bag. */
void recon_trilinear_features(int64_t n, const float *u, const float *table, int64_t res, int64_t channels, float *out)
{
    const int64_t sx = res * res * channels, sy = res * channels, sz = channels;
    for (int64_t i = 0; i < n; ++i) {
        float p[3];
        int64_t c[3];
        for (int a = 0; a < 3; ++a) {
            p[a] = clamp01(u[3 * i + a]) * (float)(res - 1);
            c[a] = (int64_t)floorf(p[a]);
            if (c[a] > res - 2) c[a] = res - 2;
            if (c[a] < 0) c[a] = 0;
            p[a] -= (float)c[a];
        }
        const float fx = p[0], fy = p[1], fz = p[2];
        const float w[8] = {
            (1 - fx) * (1 - fy) * (1 - fz), (1 - fx) * (1 - fy) * fz, (1 - fx) * fy * (1 - fz), (1 - fx) * fy * fz,
            fx * (1 - fy) * (1 - fz), fx * (1 - fy) * fz, fx * fy * (1 - fz), fx * fy * fz,
        };
        const float *base = table + c[0] * sx + c[1] * sy + c[2] * sz;
        const float *corner[8] = {base, base + sz, base + sy, base + sy + sz,
                                  base + sx, base + sx + sz, base + sx + sy, base + sx + sy + sz};
        float *o = out + i * channels;
        for (int64_t ch = 0; ch < channels; ++ch) {
            float acc = 0.0f;
            for (int k = 0; k < 8; ++k) acc += w[k] * corner[k][ch];
            o[ch] = acc;
        }
    }
}
