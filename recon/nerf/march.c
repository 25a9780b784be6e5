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
 * Rendering (no gradients) composites here too and hands back only the samples worth coloring.
 *
 * Entry points return how many samples they have for these rays; samples are written while they fit in
 * `capacity`, and a return value above it asks the caller to call again with that capacity.
 */
#include <math.h>
#include <stdint.h>

static inline float clamp01(float v) { return v < 0.0f ? 0.0f : (v > 1.0f ? 1.0f : v); }

/* The 8 corner values of the cell a level read last: consecutive samples of a ray are half a finest voxel apart,
 * so most reads (nearly all on the coarse levels) find their cell here instead of in memory. */
typedef struct {
    int64_t cell;
    float c[8];
} corner_cache;

#define MAX_CACHED_LEVELS 8

/* Trilinear read of a (res, res, res) table indexed [ix][iy][iz] at unit coordinates (u in [0, 1]^3). */
static inline float trilinear(const float *table, int64_t res, float ux, float uy, float uz, corner_cache *cache) {
    float px = ux * (float)(res - 1), py = uy * (float)(res - 1), pz = uz * (float)(res - 1);
    int64_t ix = (int64_t)floorf(px), iy = (int64_t)floorf(py), iz = (int64_t)floorf(pz);
    if (ix > res - 2) ix = res - 2;
    if (iy > res - 2) iy = res - 2;
    if (iz > res - 2) iz = res - 2;
    if (ix < 0) ix = 0;
    if (iy < 0) iy = 0;
    if (iz < 0) iz = 0;
    float fx = px - (float)ix, fy = py - (float)iy, fz = pz - (float)iz;
    const int64_t sx = res * res, sy = res, cell = ix * sx + iy * sy + iz;
    float local[8];
    float *v = cache ? cache->c : local;
    if (!cache || cache->cell != cell) {
        const float *c = table + cell;
        v[0] = c[0], v[1] = c[1], v[2] = c[sy], v[3] = c[sy + 1];
        v[4] = c[sx], v[5] = c[sx + 1], v[6] = c[sx + sy], v[7] = c[sx + sy + 1];
        if (cache) cache->cell = cell;
    }
    float c00 = v[0] * (1.0f - fz) + v[1] * fz;
    float c01 = v[2] * (1.0f - fz) + v[3] * fz;
    float c10 = v[4] * (1.0f - fz) + v[5] * fz;
    float c11 = v[6] * (1.0f - fz) + v[7] * fz;
    float c0 = c00 * (1.0f - fy) + c01 * fy;
    float c1 = c10 * (1.0f - fy) + c11 * fy;
    return c0 * (1.0f - fx) + c1 * fx;
}

/* The march shared by both entry points. Samples mode (render == 0): every kept sample's t_start, t_end, ray and
 * density go to out_ts/out_te/out_ri/out_sigma. Render mode (render != 0): each ray's opacity (sum of weights),
 * weighted depth (sum of weight * midpoint) and sample count go to ray_opacity/ray_depth/ray_samples, and only the
 * samples whose weight exceeds color_min_weight are written: their unit grid point (3 floats) to out_u, weight to
 * out_w, ray to out_ri. Weights as recon.nerf.render.render_weights_packed: T (float64 optical depth, exp, then
 * float32) times -expm1(-tau). Returns the number of samples (samples mode) or of colored samples (render mode). */
static int64_t march(
    int render, int64_t n_rays, const float *rays_o, const float *rays_d, const float *t_near, const float *t_far,
    const float *jitter, const uint8_t *occupied, int64_t occ_res, const float *occ_lo, const float *occ_hi,
    const uint8_t *blocks, int64_t block, float step, int64_t max_samples, double log_min_t,
    int64_t n_levels, const float *const *tables, const int64_t *level_res, const float *grid_lo, const float *grid_hi,
    float bias, float density_scale, int32_t exp_activation, float sigma_max, float tau_max,
    int64_t capacity, float *out_ts, float *out_te, int64_t *out_ri, float *out_sigma, int64_t ray_base,
    float color_min_weight, float *ray_opacity, float *ray_depth, int64_t *ray_samples, float *out_u, float *out_w)
{
    int64_t m = 0;
    float scale[3], gsize[3];
    for (int a = 0; a < 3; ++a) {
        scale[a] = (float)occ_res / (occ_hi[a] - occ_lo[a]);
        gsize[a] = grid_hi[a] - grid_lo[a];
    }
    const float cells = (float)occ_res;
    corner_cache caches[MAX_CACHED_LEVELS];
    for (int l = 0; l < MAX_CACHED_LEVELS; ++l) caches[l].cell = -1;
    for (int64_t r = 0; r < n_rays; ++r) {
        const float tn = t_near[r], tf = t_far[r];
        float opacity = 0.0f, depth_sum = 0.0f;
        int64_t kept = 0;
        int64_t count = tf > tn ? (int64_t)ceilf((tf - tn) / step) : 0;
        if (count > max_samples) count = max_samples;
        const float u = jitter ? jitter[r] : 0.0f;
        const float *o = rays_o + 3 * r, *d = rays_d + 3 * r;
        float po[3], pd[3];
        for (int a = 0; a < 3; ++a) {
            po[a] = (o[a] - occ_lo[a]) * scale[a];
            pd[a] = d[a] * scale[a];
        }
        double depth = 0.0, trans = 1.0; /* optical depth and transmittance at the next sample's start */
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
            if (!occupied[(ix * occ_res + iy) * occ_res + iz]) {
                /* in an empty block, jump to the last step whose midpoint is surely still in it (in an occupied
                   block, stepping on is cheaper than computing where an empty cell ends) */
                if (!blocks) continue;
                const int64_t nb = occ_res / block, bx = ix / block, by = iy / block, bz = iz / block;
                if (blocks[(bx * nb + by) * nb + bz]) continue;
                const float lo[3] = {(float)(bx * block), (float)(by * block), (float)(bz * block)};
                const float size = (float)block, p[3] = {px, py, pz};
                float t_exit = INFINITY;
                for (int a = 0; a < 3; ++a) {
                    float t_a = INFINITY;
                    if (pd[a] > 1e-12f) t_a = tm + (lo[a] + size - p[a]) / pd[a];
                    else if (pd[a] < -1e-12f) t_a = tm + (lo[a] - p[a]) / pd[a];
                    if (t_a < t_exit) t_exit = t_a;
                }
                /* step j's midpoint is tn + (j + u + 0.5) step: steps up to last (one step of margin for rounding)
                   lie inside the region and are empty */
                const float last = floorf((t_exit - tn) / step - u - 0.5f) - 1.0f;
                if (last > (float)k && last < (float)count) k = (int64_t)last;
                continue;
            }
            if (!(depth < log_min_t)) break; /* transmittance at this sample's start is below the bar */
            const float ux = clamp01((o[0] + d[0] * tm - grid_lo[0]) / gsize[0]);
            const float uy = clamp01((o[1] + d[1] * tm - grid_lo[1]) / gsize[1]);
            const float uz = clamp01((o[2] + d[2] * tm - grid_lo[2]) / gsize[2]);
            float raw = 0.0f;
            for (int64_t l = 0; l < n_levels; ++l)
                raw += trilinear(tables[l], level_res[l], ux, uy, uz, l < MAX_CACHED_LEVELS ? &caches[l] : 0);
            raw += bias;
            float sigma;
            if (exp_activation) sigma = expf(raw < 15.0f ? raw : 15.0f);
            else sigma = raw > 20.0f ? raw : log1pf(expf(raw)); /* torch's softplus (threshold 20) */
            sigma *= density_scale;
            float s = sigma < 0.0f ? 0.0f : (sigma > sigma_max ? sigma_max : sigma);
            float tau = s * (te - ts > 0.0f ? te - ts : 0.0f);
            if (tau > tau_max) tau = tau_max;
            if (!render) {
                if (m < capacity) {
                    out_ts[m] = ts;
                    out_te[m] = te;
                    out_ri[m] = ray_base + r;
                    out_sigma[m] = sigma;
                }
                ++m;
            } else {
                const float alpha = -expm1f(-tau);
                const float w = (float)trans * alpha;
                trans *= 1.0 - (double)alpha; /* exp(-depth) without an exp per sample */
                opacity += w;
                depth_sum += w * tm;
                ++kept;
                if (w > color_min_weight) {
                    if (m < capacity) {
                        out_u[3 * m] = ux;
                        out_u[3 * m + 1] = uy;
                        out_u[3 * m + 2] = uz;
                        out_w[m] = w;
                        out_ri[m] = ray_base + r;
                    }
                    ++m;
                }
            }
            depth += (double)tau;
        }
        if (render) {
            ray_opacity[r] = opacity;
            ray_depth[r] = depth_sum;
            ray_samples[r] = kept;
        }
    }
    return m;
}

/* The samples themselves (for training, which evaluates their densities again with gradients). */
int64_t recon_march_dense(
    int64_t n_rays, const float *rays_o, const float *rays_d, const float *t_near, const float *t_far,
    const float *jitter, const uint8_t *occupied, int64_t occ_res, const float *occ_lo, const float *occ_hi,
    const uint8_t *blocks, int64_t block, float step, int64_t max_samples, double log_min_t,
    int64_t n_levels, const float *const *tables, const int64_t *level_res, const float *grid_lo, const float *grid_hi,
    float bias, float density_scale, int32_t exp_activation, float sigma_max, float tau_max,
    int64_t capacity, float *out_ts, float *out_te, int64_t *out_ri, float *out_sigma, int64_t ray_base)
{
    return march(0, n_rays, rays_o, rays_d, t_near, t_far, jitter, occupied, occ_res, occ_lo, occ_hi, blocks, block,
                 step, max_samples,
                 log_min_t, n_levels, tables, level_res, grid_lo, grid_hi, bias, density_scale, exp_activation,
                 sigma_max, tau_max, capacity, out_ts, out_te, out_ri, out_sigma, ray_base, 0.0f, 0, 0, 0, 0, 0);
}

/* Compositing too, for rendering without gradients: per-ray opacity, weighted depth and sample count, and the
 * samples worth coloring (see march). No jitter: renders are deterministic. */
int64_t recon_march_render(
    int64_t n_rays, const float *rays_o, const float *rays_d, const float *t_near, const float *t_far,
    const uint8_t *occupied, int64_t occ_res, const float *occ_lo, const float *occ_hi,
    const uint8_t *blocks, int64_t block, float step, int64_t max_samples, double log_min_t,
    int64_t n_levels, const float *const *tables, const int64_t *level_res, const float *grid_lo, const float *grid_hi,
    float bias, float density_scale, int32_t exp_activation, float sigma_max, float tau_max,
    int64_t capacity, float *out_u, float *out_w, int64_t *out_ri, int64_t ray_base,
    float color_min_weight, float *ray_opacity, float *ray_depth, int64_t *ray_samples)
{
    return march(1, n_rays, rays_o, rays_d, t_near, t_far, 0, occupied, occ_res, occ_lo, occ_hi, blocks, block,
                 step, max_samples,
                 log_min_t, n_levels, tables, level_res, grid_lo, grid_hi, bias, density_scale, exp_activation,
                 sigma_max, tau_max, capacity, 0, 0, out_ri, 0, ray_base, color_min_weight, ray_opacity, ray_depth,
                 ray_samples, out_u, out_w);
}

/* Point i's cell in a (res³, channels) channels-last table: the offset of its lower corner's first channel, the
 * eight corners' offsets from it and their trilinear weights (corner bit 2 = x high, bit 1 = y, bit 0 = z, as in
 * recon.nerf.grid.corner_weights). Unit coordinates are clamped to [0, 1]. */
static inline int64_t cell_weights(const float *u, int64_t res, int64_t channels, int64_t corner[8], float w[8]) {
    float p[3];
    int64_t c[3];
    for (int a = 0; a < 3; ++a) {
        p[a] = clamp01(u[a]) * (float)(res - 1);
        c[a] = (int64_t)floorf(p[a]);
        if (c[a] > res - 2) c[a] = res - 2;
        if (c[a] < 0) c[a] = 0;
        p[a] -= (float)c[a];
    }
    const float fx = p[0], fy = p[1], fz = p[2];
    w[0] = (1 - fx) * (1 - fy) * (1 - fz), w[1] = (1 - fx) * (1 - fy) * fz;
    w[2] = (1 - fx) * fy * (1 - fz), w[3] = (1 - fx) * fy * fz;
    w[4] = fx * (1 - fy) * (1 - fz), w[5] = fx * (1 - fy) * fz;
    w[6] = fx * fy * (1 - fz), w[7] = fx * fy * fz;
    const int64_t sx = res * res * channels, sy = res * channels, sz = channels;
    corner[0] = 0, corner[1] = sz, corner[2] = sy, corner[3] = sy + sz;
    corner[4] = sx, corner[5] = sx + sz, corner[6] = sx + sy, corner[7] = sx + sy + sz;
    return c[0] * sx + c[1] * sy + c[2] * sz;
}

/* Trilinear features of n points (unit coordinates u (n, 3)) from a channels-last (res³, channels) table indexed
 * [ix][iy][iz]: out (n, channels). recon.nerf.grid.DenseGrid.forward; the torch path builds (n, 8) corner rows and
 * weights first and gathers with embedding_bag (or grid_sample for one channel). */
void recon_trilinear_features(int64_t n, const float *u, const float *table, int64_t res, int64_t channels, float *out)
{
    int64_t corner[8];
    float w[8];
    for (int64_t i = 0; i < n; ++i) {
        const float *base = table + cell_weights(u + 3 * i, res, channels, corner, w);
        float *o = out + i * channels;
        for (int64_t ch = 0; ch < channels; ++ch) {
            float acc = 0.0f;
            for (int k = 0; k < 8; ++k) acc += w[k] * base[corner[k] + ch];
            o[ch] = acc;
        }
    }
}

/* The backward of recon_trilinear_features for the table: grad_table (res³, channels) += each point's upstream
 * gradient grad_out (n, channels) spread over its cell's corners by the trilinear weights. One thread: the
 * scatter is cheaper than the zeroed copy a second thread would need. */
void recon_trilinear_backward(int64_t n, const float *u, const float *grad_out, int64_t res, int64_t channels,
                              float *grad_table)
{
    int64_t corner[8];
    float w[8];
    for (int64_t i = 0; i < n; ++i) {
        float *base = grad_table + cell_weights(u + 3 * i, res, channels, corner, w);
        const float *g = grad_out + i * channels;
        for (int k = 0; k < 8; ++k)
            for (int64_t ch = 0; ch < channels; ++ch) base[corner[k] + ch] += w[k] * g[ch];
    }
}
