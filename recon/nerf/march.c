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
 * Unbounded scenes (contracted != 0) take recon.nerf.contraction.contracted_intervals' steps instead: constant length
 * in contracted space, exact on the piecewise-linear L-inf radius along the ray, with the same float64/float32
 * split as torch; each midpoint is contracted before the occupancy lookup (the grid spans the contracted cube) and
 * the density read, and the torch reference is contracted_intervals, OccupancyGrid.query and the transmittance cut.
 *
 * Rendering (no gradients) composites here too and hands back only the samples worth coloring.
 *
 * Entry points return how many samples they have for these rays; samples are written while they fit in
 * `capacity`, and a return value above it asks the caller to call again with that capacity.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

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

#define N_BREAKS 17 /* recon.nerf.contraction.N_BREAKS: 3 zeros, 6 axis crossings, 6 crossings of +-1, near, far */

/* One ray's contracted steps: the breakpoints of r(t) = max(1, ||o + t d||_inf) in [t_near, t_far], r at each, and
 * the cumulative step count at each (scaled down when the ray's count is capped). */
typedef struct {
    float b32[N_BREAKS], rho32[N_BREAKS];
    double cum[N_BREAKS];
    float lam_scale; /* step * scale, in float32 as torch multiplies it */
    int piece;       /* the piece the last boundary fell in (boundaries only move forward) */
} contracted_ray;

static inline double finite_or_zero(double v) { return isfinite(v) ? v : 0.0; }

/* recon.nerf.contraction._norm_breaks and the counts of contracted_intervals for one ray; returns its step count. */
static int64_t contracted_setup(const float *o32, const float *d32, float tn32, float tf32, double step,
                                int64_t max_samples, contracted_ray *cr)
{
    double o[3], d[3], b[N_BREAKS], rho[N_BREAKS];
    for (int a = 0; a < 3; ++a) o[a] = (double)o32[a], d[a] = (double)d32[a];
    const double tn = (double)tn32, tf = (double)tf32;
    int n = 0;
    b[n++] = tn;
    for (int a = 0; a < 3; ++a) b[n++] = finite_or_zero(-o[a] / d[a]);
    static const int pairs[3][2] = {{0, 1}, {0, 2}, {1, 2}};
    for (int p = 0; p < 3; ++p) {
        const int j = pairs[p][0], k = pairs[p][1];
        b[n++] = finite_or_zero(-(o[j] - o[k]) / (d[j] - d[k]));
        b[n++] = finite_or_zero(-(o[j] + o[k]) / (d[j] + d[k]));
    }
    for (int a = 0; a < 3; ++a) b[n++] = finite_or_zero((1.0 - o[a]) / d[a]);
    for (int a = 0; a < 3; ++a) b[n++] = finite_or_zero((-1.0 - o[a]) / d[a]);
    b[n++] = tf;
    for (int i = 1; i < N_BREAKS - 1; ++i) b[i] = fmin(fmax(b[i], tn), tf);
    for (int i = 1; i < N_BREAKS; ++i) { /* insertion sort: 17 values */
        const double v = b[i];
        int j = i - 1;
        while (j >= 0 && b[j] > v) b[j + 1] = b[j], --j;
        b[j + 1] = v;
    }
    for (int i = 0; i < N_BREAKS; ++i) {
        double r = 0.0;
        for (int a = 0; a < 3; ++a) {
            const double x = fabs(o[a] + b[i] * d[a]);
            if (x > r || isnan(x)) r = x;
        }
        rho[i] = r < 1.0 ? 1.0 : r;
    }
    cr->cum[0] = 0.0;
    for (int i = 0; i + 1 < N_BREAKS; ++i) cr->cum[i + 1] = cr->cum[i] + (b[i + 1] - b[i]) / (step * rho[i] * rho[i + 1]);
    const double total = cr->cum[N_BREAKS - 1];
    double count = ceil(total);
    if (count > (double)max_samples) count = (double)max_samples;
    const double scale = total > (double)max_samples ? total / (double)max_samples : 1.0;
    for (int i = 0; i < N_BREAKS; ++i) {
        cr->cum[i] /= scale;
        cr->b32[i] = (float)b[i];
        cr->rho32[i] = (float)rho[i];
    }
    cr->lam_scale = (float)step * (float)scale;
    cr->piece = 0;
    return tf32 > tn32 ? (int64_t)count : 0;
}

/* Boundary k of the ray's intervals (at cumulative step count k + u): contracted_intervals' inverse of the count
 * on the piece it falls in (float32 within the piece, as torch). */
static inline float contracted_boundary(contracted_ray *cr, int64_t k, double u) {
    double s = (double)k + u;
    if (s > cr->cum[N_BREAKS - 1]) s = cr->cum[N_BREAKS - 1];
    int j = cr->piece;
    while (j + 1 < N_BREAKS && cr->cum[j + 1] <= s) ++j;
    cr->piece = j;
    if (j > N_BREAKS - 2) j = N_BREAKS - 2;
    const float ta = cr->b32[j], tb = cr->b32[j + 1], ra = cr->rho32[j];
    float span = tb - ta;
    if (span < 1e-30f) span = 1e-30f;
    const float beta = (cr->rho32[j + 1] - ra) / span;
    const float lam = (float)(s - cr->cum[j]) * cr->lam_scale;
    float den = 1.0f - lam * ra * beta;
    if (den < 1e-12f) den = 1e-12f;
    const float t = ta + lam * ra * ra / den;
    return t < tb ? t : tb;
}

/* recon.nerf.contraction.contract of one point (float32, as torch computes it). */
static inline void contract_point(const float x[3], float c[3]) {
    float n = 0.0f;
    float y[3];
    for (int a = 0; a < 3; ++a) {
        y[a] = x[a] > 3.4028234663852886e38f ? 3.4028234663852886e38f : (x[a] < -3.4028234663852886e38f ? -3.4028234663852886e38f : x[a]);
        const float v = fabsf(y[a]);
        if (v > n || isnan(v)) n = v;
    }
    if (n <= 1.0f) {
        c[0] = y[0], c[1] = y[1], c[2] = y[2];
        return;
    }
    const float f = 2.0f - 1.0f / n;
    for (int a = 0; a < 3; ++a) c[a] = f * (y[a] / n);
}

/* A ray's uniform steps between tn and tf (at most max_samples, also for an infinite far): the most samples it can
 * keep. */
static inline int64_t uniform_steps(float tn, float tf, float step, int64_t max_samples) {
    if (!(tf > tn)) return 0;
    const float steps = ceilf((tf - tn) / step);
    return steps < (float)max_samples ? (int64_t)steps : max_samples;
}

/* The march shared by both entry points. Samples mode (render == 0): every kept sample's t_start, t_end, ray and
 * density go to out_ts/out_te/out_ri/out_sigma. Render mode (render != 0): each ray's opacity (sum of weights),
 * weighted depth (sum of weight * midpoint) and sample count go to ray_opacity/ray_depth/ray_samples, and only the
 * samples whose weight exceeds color_min_weight are written: their unit grid point (3 floats) to out_u, weight to
 * out_w, ray to out_ri. Weights as recon.nerf.render.render_weights_packed: T (float64 optical depth, exp, then
 * float32) times -expm1(-tau). Returns the number of samples (samples mode) or of colored samples (render mode). */
static int64_t march(
    int render, int64_t n_rays, const float *rays_o, const float *rays_d, const float *t_near, const float *t_far,
    const double *jitter, const uint8_t *occupied, int64_t occ_res, const float *occ_lo, const float *occ_hi,
    const uint8_t *blocks, int64_t block, float step, int64_t max_samples, double log_min_t,
    int64_t n_levels, const float *const *tables, const int64_t *level_res, const float *grid_lo, const float *grid_hi,
    float bias, float density_scale, int32_t exp_activation, float sigma_max, float tau_max, int32_t contracted,
    int64_t capacity, float *out_ts, float *out_te, int64_t *out_ri, float *out_sigma, int64_t ray_base,
    float color_min_weight, float *ray_opacity, float *ray_depth, int64_t *ray_samples, float *out_u, float *out_w)
{
    int64_t m = 0;
    float scale[3], gsize[3], osize[3];
    for (int a = 0; a < 3; ++a) {
        scale[a] = (float)occ_res / (occ_hi[a] - occ_lo[a]);
        gsize[a] = grid_hi[a] - grid_lo[a];
        osize[a] = occ_hi[a] - occ_lo[a];
    }
    contracted_ray cr = {.lam_scale = 0.0f, .piece = 0};
    const float cells = (float)occ_res;
    corner_cache caches[MAX_CACHED_LEVELS];
    for (int l = 0; l < MAX_CACHED_LEVELS; ++l) caches[l].cell = -1;
    for (int64_t r = 0; r < n_rays; ++r) {
        const float tn = t_near[r], tf = t_far[r];
        float opacity = 0.0f, depth_sum = 0.0f;
        int64_t kept = 0;
        const float *o = rays_o + 3 * r, *d = rays_d + 3 * r;
        const int64_t count = contracted ? contracted_setup(o, d, tn, tf, (double)step, max_samples, &cr)
                                         : uniform_steps(tn, tf, step, max_samples);
        const float u = jitter ? (float)jitter[r] : 0.0f;
        const double u64 = jitter ? jitter[r] : 0.0;
        float t_next = contracted && count > 0 ? contracted_boundary(&cr, 0, u64) : 0.0f;
        float po[3], pd[3];
        for (int a = 0; a < 3; ++a) {
            po[a] = (o[a] - occ_lo[a]) * scale[a];
            pd[a] = d[a] * scale[a];
        }
        double depth = 0.0, trans = 1.0; /* optical depth and transmittance at the next sample's start */
        for (int64_t k = 0; k < count; ++k) {
            float ts, te, ux, uy, uz, px, py, pz;
            if (contracted) { /* interval k spans boundaries k and k + 1; empty ones (clipped at far) are skipped */
                ts = t_next;
                te = t_next = contracted_boundary(&cr, k + 1, u64);
                if (!(te > ts)) continue;
            } else {
                ts = tn + ((float)k + u) * step;
                if (!(ts < tf)) break;
                te = ts + step;
                if (te > tf) te = tf;
            }
            const float tm = 0.5f * (ts + te);
            if (contracted) { /* occupancy and density at the contracted midpoint, as OccupancyGrid.query does */
                const float x[3] = {o[0] + d[0] * tm, o[1] + d[1] * tm, o[2] + d[2] * tm};
                float c[3];
                contract_point(x, c);
                const float qx = (c[0] - occ_lo[0]) / osize[0], qy = (c[1] - occ_lo[1]) / osize[1],
                            qz = (c[2] - occ_lo[2]) / osize[2];
                if (!(qx >= 0.0f && qx <= 1.0f && qy >= 0.0f && qy <= 1.0f && qz >= 0.0f && qz <= 1.0f)) continue;
                px = qx * cells, py = qy * cells, pz = qz * cells;
                ux = clamp01((c[0] - grid_lo[0]) / gsize[0]);
                uy = clamp01((c[1] - grid_lo[1]) / gsize[1]);
                uz = clamp01((c[2] - grid_lo[2]) / gsize[2]);
            } else {
                px = po[0] + pd[0] * tm, py = po[1] + pd[1] * tm, pz = po[2] + pd[2] * tm;
                if (!(px >= 0.0f && px <= cells && py >= 0.0f && py <= cells && pz >= 0.0f && pz <= cells)) continue;
                ux = clamp01((o[0] + d[0] * tm - grid_lo[0]) / gsize[0]);
                uy = clamp01((o[1] + d[1] * tm - grid_lo[1]) / gsize[1]);
                uz = clamp01((o[2] + d[2] * tm - grid_lo[2]) / gsize[2]);
            }
            int64_t ix = (int64_t)floorf(px), iy = (int64_t)floorf(py), iz = (int64_t)floorf(pz);
            if (ix > occ_res - 1) ix = occ_res - 1;
            if (iy > occ_res - 1) iy = occ_res - 1;
            if (iz > occ_res - 1) iz = occ_res - 1;
            if (!occupied[(ix * occ_res + iy) * occ_res + iz]) {
                /* in an empty block, jump to the last step whose midpoint is surely still in it (in an occupied
                   block, stepping on is cheaper than computing where an empty cell ends) */
                if (!blocks || contracted) continue; /* contracted steps are not uniform in t: no jumps */
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
                    if (out_u) {
                        out_u[3 * m] = ux;
                        out_u[3 * m + 1] = uy;
                        out_u[3 * m + 2] = uz;
                    }
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

/* The samples themselves, for training: their densities and (when out_u is not NULL) their points in the density
 * grids' unit cube, which a training step takes as its loss's densities instead of reading the levels again. */
int64_t recon_march_dense(
    int64_t n_rays, const float *rays_o, const float *rays_d, const float *t_near, const float *t_far,
    const double *jitter, const uint8_t *occupied, int64_t occ_res, const float *occ_lo, const float *occ_hi,
    const uint8_t *blocks, int64_t block, float step, int64_t max_samples, double log_min_t,
    int64_t n_levels, const float *const *tables, const int64_t *level_res, const float *grid_lo, const float *grid_hi,
    float bias, float density_scale, int32_t exp_activation, float sigma_max, float tau_max, int32_t contracted,
    int64_t capacity, float *out_ts, float *out_te, int64_t *out_ri, float *out_sigma, float *out_u, int64_t ray_base)
{
    return march(0, n_rays, rays_o, rays_d, t_near, t_far, jitter, occupied, occ_res, occ_lo, occ_hi, blocks, block,
                 step, max_samples,
                 log_min_t, n_levels, tables, level_res, grid_lo, grid_hi, bias, density_scale, exp_activation,
                 sigma_max, tau_max, contracted, capacity, out_ts, out_te, out_ri, out_sigma, ray_base, 0.0f, 0, 0, 0,
                 out_u, 0);
}

/* Compositing too, for rendering without gradients: per-ray opacity, weighted depth and sample count, and the
 * samples worth coloring (see march). No jitter: renders are deterministic. */
int64_t recon_march_render(
    int64_t n_rays, const float *rays_o, const float *rays_d, const float *t_near, const float *t_far,
    const uint8_t *occupied, int64_t occ_res, const float *occ_lo, const float *occ_hi,
    const uint8_t *blocks, int64_t block, float step, int64_t max_samples, double log_min_t,
    int64_t n_levels, const float *const *tables, const int64_t *level_res, const float *grid_lo, const float *grid_hi,
    float bias, float density_scale, int32_t exp_activation, float sigma_max, float tau_max, int32_t contracted,
    int64_t capacity, float *out_u, float *out_w, int64_t *out_ri, int64_t ray_base,
    float color_min_weight, float *ray_opacity, float *ray_depth, int64_t *ray_samples)
{
    return march(1, n_rays, rays_o, rays_d, t_near, t_far, 0, occupied, occ_res, occ_lo, occ_hi, blocks, block,
                 step, max_samples,
                 log_min_t, n_levels, tables, level_res, grid_lo, grid_hi, bias, density_scale, exp_activation,
                 sigma_max, tau_max, contracted, capacity, 0, 0, out_ri, 0, ray_base, color_min_weight, ray_opacity, ray_depth,
                 ray_samples, out_u, out_w);
}

/* A point's cell in a grid of res vertices a side: its lower vertex c (each in [0, res - 2]) and the eight corners'
 * trilinear weights (corner bit 2 = x high, bit 1 = y, bit 0 = z, as in recon.nerf.grid.corner_weights), from unit
 * coordinates clamped to [0, 1]: recon.nerf.grid.axis_cells's arithmetic, in its order. */
static inline void unit_cell(const float *u, int64_t res, int64_t c[3], float w[8]) {
    float p[3];
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
}

/* Point i's cell in a (res³, channels) channels-last table: the offset of its lower corner's first channel, the
 * eight corners' offsets from it and their trilinear weights (unit_cell's). */
static inline int64_t cell_weights(const float *u, int64_t res, int64_t channels, int64_t corner[8], float w[8]) {
    int64_t c[3];
    unit_cell(u, res, c, w);
    const int64_t sx = res * res * channels, sy = res * channels, sz = channels;
    corner[0] = 0, corner[1] = sz, corner[2] = sy, corner[3] = sy + sz;
    corner[4] = sx, corner[5] = sx + sz, corner[6] = sx + sy, corner[7] = sx + sy + sz;
    return c[0] * sx + c[1] * sy + c[2] * sz;
}

/* recon_trilinear_features for one number of channels: called with a constant, the compiler unrolls and vectorizes
 * the channel loop (each value's sum is still taken over the corners in order, so the results are the same). */
static inline void features_of(int64_t n, const float *u, const float *table, int64_t res, const int64_t channels,
                               float *out)
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

/* Trilinear features of n points (unit coordinates u (n, 3)) from a channels-last (res³, channels) table indexed
 * [ix][iy][iz]: out (n, channels). recon.nerf.grid.DenseGrid.forward; the torch path builds (n, 8) corner rows and
 * weights first and gathers with embedding_bag (or grid_sample for one channel). A density grid's one channel and
 * the fast model's 12 feature channels (FastConfig.feature_dim) get their own build of the loop. */
void recon_trilinear_features(int64_t n, const float *u, const float *table, int64_t res, int64_t channels, float *out)
{
    switch (channels) {
    case 1: features_of(n, u, table, res, 1, out); break;
    case 12: features_of(n, u, table, res, 12, out); break;
    default: features_of(n, u, table, res, channels, out);
    }
}

#define ADAM_BLOCK 64

/* Flag the blocks of ADAM_BLOCK values that a row of `width` values starting at value `first` lies in (recon_adam
 * then visits only flagged blocks). A relaxed atomic store: threads adding into different rows may share a block,
 * and all of them store the same 1. */
static inline void flag_blocks(uint8_t *touched, int64_t first, int64_t width) {
    const uint64_t last = (uint64_t)(first + width - 1) / ADAM_BLOCK;
    for (uint64_t b = (uint64_t)first / ADAM_BLOCK; b <= last; ++b)
        __atomic_store_n(touched + b, (uint8_t)1, __ATOMIC_RELAXED);
}

/* The backward of recon_trilinear_features for the table: grad_table (res³, channels) += each point's upstream
 * gradient grad_out (n, channels) spread over its cell's corners by the trilinear weights; `touched` (or NULL):
 * the blocks added into are flagged. Part `part` of `parts` adds only into the x-planes ix with ix % parts == part:
 * the parts run on threads of their own without sharing a value, and every value still takes its points' terms in
 * their order, so the sums are the same for any number of parts (with two, a cell's two x-planes go one to each).
 * A density grid's one channel gets its own build of the loop (features_of's reason; with 12 channels that build
 * measured slower). */
static inline void backward_of(int64_t n, const float *u, const float *grad_out, int64_t res, const int64_t channels,
                               float *grad_table, uint8_t *touched, int64_t part, int64_t parts)
{
    int64_t corner[8];
    float w[8];
    const int64_t plane = res * res * channels;
    for (int64_t i = 0; i < n; ++i) {
        const int64_t first = cell_weights(u + 3 * i, res, channels, corner, w);
        const int64_t ix = first / plane;
        float *base = grad_table + first;
        const float *g = grad_out + i * channels;
        for (int x = 0; x < 2; ++x) { /* corners 4x .. 4x + 3 lie in the x-plane ix + x */
            if (parts > 1 && (ix + x) % parts != part) continue;
            for (int k = 4 * x; k < 4 * x + 4; ++k)
                for (int64_t ch = 0; ch < channels; ++ch) base[corner[k] + ch] += w[k] * g[ch];
            if (touched)  /* corners 2j and 2j + 1 are neighbouring rows (z): one range each pair */
                for (int k = 4 * x; k < 4 * x + 4; k += 2) flag_blocks(touched, first + corner[k], 2 * channels);
        }
    }
}

void recon_trilinear_backward(int64_t n, const float *u, const float *grad_out, int64_t res, int64_t channels,
                              float *grad_table, uint8_t *touched, int64_t part, int64_t parts)
{
    if (channels == 1)
        backward_of(n, u, grad_out, res, 1, grad_table, touched, part, parts);
    else
        backward_of(n, u, grad_out, res, channels, grad_table, touched, part, parts);
}

/* The table rows of the eight corners of a hash grid's level (its first row `offset`, `res` vertices a side): the
 * dense row (ix * res + iy) * res + iz, or where `hashed` instant-ngp's hash (ix * 1 ^ iy * 2654435761 ^
 * iz * 805459861) & mask, in unsigned 64-bit arithmetic whose low bits are torch's int64 ones
 * (recon.nerf.grid.HashGrid.level_rows). */
static inline void hash_corner_rows(const int64_t c[3], int64_t res, int64_t offset, int32_t hashed, uint64_t mask,
                                    int64_t row[8]) {
    for (int k = 0; k < 8; ++k) {
        const uint64_t ix = (uint64_t)(c[0] + ((k >> 2) & 1)), iy = (uint64_t)(c[1] + ((k >> 1) & 1)),
                       iz = (uint64_t)(c[2] + (k & 1));
        row[k] = offset + (hashed ? (int64_t)((ix ^ (iy * 2654435761ull) ^ (iz * 805459861ull)) & mask)
                                  : (int64_t)((ix * (uint64_t)res + iy) * (uint64_t)res + iz));
    }
}

/* A hash grid's features of n points (unit coordinates u (n, 3)): every level's trilinear read of the one
 * (rows, features) table, out (n, levels * features) level-major. res, offset, hashed: (levels,) per level.
 * recon.nerf.grid.HashGrid.forward; the torch path gathers 8 rows a level through index tensors. */
void recon_hash_features(int64_t n, const float *u, const float *table, int64_t levels, const int64_t *res,
                         const int64_t *offset, const int64_t *hashed, int64_t log2_table, int64_t features,
                         float *out)
{
    const uint64_t mask = (1ull << log2_table) - 1;
    int64_t c[3], row[8];
    float w[8];
    for (int64_t lv = 0; lv < levels; ++lv) {
        for (int64_t i = 0; i < n; ++i) {
            float *o = out + (i * levels + lv) * features;
            unit_cell(u + 3 * i, res[lv], c, w);
            hash_corner_rows(c, res[lv], offset[lv], (int32_t)hashed[lv], mask, row);
            for (int64_t f = 0; f < features; ++f) {
                float acc = 0.0f;
                for (int k = 0; k < 8; ++k) acc += w[k] * table[row[k] * features + f];
                o[f] = acc;
            }
        }
    }
}

/* The backward of recon_hash_features for the table: grad_table (rows, features) += each point's upstream gradient
 * of a level spread over that level's corner rows by the trilinear weights, for levels first, first + step, ...
 * below levels: levels own disjoint rows, so threads taking different levels never write the same value. */
void recon_hash_backward(int64_t n, const float *u, const float *grad_out, int64_t levels, const int64_t *res,
                         const int64_t *offset, const int64_t *hashed, int64_t log2_table, int64_t features,
                         int64_t first, int64_t step, float *grad_table, uint8_t *touched)
{
    const uint64_t mask = (1ull << log2_table) - 1;
    int64_t c[3], row[8];
    float w[8];
    for (int64_t lv = first; lv < levels; lv += step) {
        for (int64_t i = 0; i < n; ++i) {
            const float *g = grad_out + (i * levels + lv) * features;
            unit_cell(u + 3 * i, res[lv], c, w);
            hash_corner_rows(c, res[lv], offset[lv], (int32_t)hashed[lv], mask, row);
            for (int k = 0; k < 8; ++k) {
                for (int64_t f = 0; f < features; ++f) grad_table[row[k] * features + f] += w[k] * g[f];
                if (touched) flag_blocks(touched, row[k] * features, features);
            }
        }
    }
}

/* `a` where `keep` is all ones, else `b`, bit for bit. Written with integer masks because GCC leaves a float
 * `keep ? a : b` in a loop unvectorized (masked Adam's update ran four times slower for it). */
static inline float bit_select(uint32_t keep, float a, float b) {
    uint32_t ua, ub;
    memcpy(&ua, &a, sizeof ua);
    memcpy(&ub, &b, sizeof ub);
    const uint32_t picked = (ua & keep) | (ub & ~keep);
    float out;
    memcpy(&out, &picked, sizeof out);
    return out;
}

/* One Adam step (torch.optim.Adam's, without weight decay) over n values, skipping every value whose gradient is
 * exactly 0 when `masked` (DVGO's masked Adam: a dense grid's entries that no ray of the step touched keep their
 * value and moments). step_size = lr / (1 - beta1^t), bias2_sqrt = sqrt(1 - beta2^t), as torch computes them;
 * one_minus_beta1 and one_minus_beta2 come rounded from double (1.0f - 0.999f is 0.00100005f, not 0.001f).
 * Blocks of ADAM_BLOCK values: a block without a gradient is skipped after one (vectorized) look, and a block with
 * one is updated without branches (bit_select), so the compiler vectorizes both loops. With `clear` (masked only)
 * the gradients it used are set to 0, so the whole gradient is 0 afterwards and the next backward can add into it
 * unzeroed. `touched` (masked and clear only; or NULL): a flag per block, set where the grids' backward added into
 * it, so the gradient of an unflagged block is known to be 0 without looking (eight flags read at once); the flags
 * visited are cleared. n is then a whole number of blocks, or the parameter's end. */
void recon_adam(int64_t n, float *restrict param, float *restrict grad, float *restrict exp_avg,
                float *restrict exp_avg_sq, float one_minus_beta1, float beta2, float one_minus_beta2, float step_size,
                float bias2_sqrt, float eps, int32_t masked, int32_t clear, uint8_t *touched)
{
    for (int64_t lo = 0; lo < n; lo += ADAM_BLOCK) {
        const int64_t len = n - lo < ADAM_BLOCK ? n - lo : ADAM_BLOCK;
        float *g = grad + lo;
        float *p = param + lo, *m = exp_avg + lo, *v = exp_avg_sq + lo;
        if (touched) {
            const int64_t b = lo / ADAM_BLOCK;
            if ((b & 7) == 0 && n - lo >= 8 * ADAM_BLOCK) {  /* eight flags at a time: most blocks have none */
                uint64_t eight;
                memcpy(&eight, touched + b, sizeof eight);
                if (!eight) {
                    lo += 7 * ADAM_BLOCK;
                    continue;
                }
            }
            if (!touched[b]) continue;
            touched[b] = 0;
        } else if (masked) {
            int any = 0;
            for (int64_t j = 0; j < len; ++j) any |= g[j] != 0.0f;
            if (!any) continue;
        }
        for (int64_t j = 0; j < len; ++j) {
            const float gj = g[j], mj = m[j], vj = v[j], pj = p[j];
            const uint32_t keep = -(uint32_t)(!masked | (gj != 0.0f));
            const float m_new = mj + (gj - mj) * one_minus_beta1;
            const float v_new = vj * beta2 + one_minus_beta2 * gj * gj;
            const float p_new = pj - step_size * m_new / (sqrtf(v_new) / bias2_sqrt + eps);
            m[j] = bit_select(keep, m_new, mj);
            v[j] = bit_select(keep, v_new, vj);
            p[j] = bit_select(keep, p_new, pj);
        }
        if (masked && clear)
            for (int64_t j = 0; j < len; ++j) g[j] = 0.0f;
    }
}

/* ------------------------------------------------------------------------------------------------------------------
 * A training batch's rays and the box they meet: one pass a ray instead of ~40 tensor operations on a few thousand
 * rays (the references: recon.nerf.fitting.RayBatcher._rays, recon.nerf.rays.ray_aabb). */

/* NaN-propagating min and max, as torch.minimum, torch.maximum, amin and amax. */
static inline float min_nan(float a, float b) { const float m = b < a ? b : a; return b != b ? b : m; }
static inline float max_nan(float a, float b) { const float m = b > a ? b : a; return b != b ? b : m; }

/* recon.nerf.rays.ray_aabb for one ray: the slab method, an axis the ray runs parallel to decided by its origin. */
static inline uint8_t ray_box(const float *o, const float *d, const float *box, float *t_near, float *t_far)
{
    float lo = 0.0f, hi = 0.0f;
    for (int a = 0; a < 3; ++a) {
        float l, h;
        if (d[a] == 0.0f) {
            const float always = (o[a] >= box[a] && o[a] <= box[3 + a]) ? INFINITY : -INFINITY;
            l = -always, h = always;
        } else {
            const float t0 = (box[a] - o[a]) / d[a], t1 = (box[3 + a] - o[a]) / d[a];
            l = min_nan(t0, t1), h = max_nan(t0, t1);
        }
        lo = a ? max_nan(lo, l) : l, hi = a ? min_nan(hi, h) : h;
    }
    lo = max_nan(lo, 0.0f); /* clamp_min(0) */
    const uint8_t hit = hi > lo;
    *t_near = hit ? lo : 0.0f, *t_far = hit ? hi : 0.0f;
    return hit;
}

/* ray_aabb for n rays o, d (n, 3) and a box (2, 3); hit may be NULL. Given near and far (n,) (not NULL), t_near and
 * t_far are each ray's [near, far] clipped to the box instead (recon.nerf.fast.FastModel.render_rays: a ray that
 * misses it gets an empty interval at its near end). */
void recon_ray_box(int64_t n, const float *o, const float *d, const float *box, const float *near, const float *far,
                   float *t_near, float *t_far, uint8_t *hit)
{
    for (int64_t r = 0; r < n; ++r) {
        float tn, tf;
        const uint8_t h = ray_box(o + 3 * r, d + 3 * r, box, &tn, &tf);
        if (near) {
            tn = max_nan(near[r], tn);
            tf = h ? min_nan(far[r], tf) : tn;
        }
        t_near[r] = tn, t_far[r] = tf;
        if (hit) hit[r] = h;
    }
}

/* The rays through flat pixel indices into photos stacked one after another (photo k's pixels from offsets[k], row
 * by row, widths[k] a row): each pixel's photo (out_img) and the ray through its centre (camera-to-world c2w (photos,
 * 3, 4), OpenGL axes; intrinsics (photos, 4) = fl_x, fl_y, cx, cy) with a unit direction; with a box (2, 3), where
 * the ray meets it (ray_aabb), else its photo's near and far from near_far (photos, 2). */
void recon_pixel_rays(int64_t n, const int64_t *flat, int64_t photos, const int64_t *offsets, const int64_t *widths,
                      const float *c2w, const float *intrinsics, const float *box, const float *near_far,
                      float *out_o, float *out_d, float *out_near, float *out_far, uint8_t *out_hit, int64_t *out_img)
{
    for (int64_t r = 0; r < n; ++r) {
        const int64_t f = flat[r];
        int64_t lo = 0; /* the last photo starting at or before f (searchsorted(offsets, f, right) - 1), branch-free */
        for (int64_t half = photos / 2, len = photos; len > 1; len -= half, half = len / 2)
            lo = offsets[lo + half] <= f ? lo + half : lo;
        const int64_t local = f - offsets[lo], w = widths[lo], row = local / w;
        const float px = (float)(local - row * w) + 0.5f, py = (float)row + 0.5f;
        const float *k = intrinsics + 4 * lo, *m = c2w + 12 * lo;
        const float x = (px - k[2]) / k[0], y = -((py - k[3]) / k[1]);
        float *o = out_o + 3 * r, *d = out_d + 3 * r;
        for (int a = 0; a < 3; ++a) {
            o[a] = m[4 * a + 3];
            d[a] = m[4 * a] * x + m[4 * a + 1] * y - m[4 * a + 2];
        }
        const float norm = sqrtf(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        for (int a = 0; a < 3; ++a) d[a] /= norm;
        if (box) {
            out_hit[r] = ray_box(o, d, box, out_near + r, out_far + r);
        } else {
            out_near[r] = near_far[2 * lo], out_far[r] = near_far[2 * lo + 1];
            out_hit[r] = out_far[r] > out_near[r];
        }
        out_img[r] = lo;
    }
}

/* ------------------------------------------------------------------------------------------------------------------
 * The `_all` entry points: a native call's parts on OpenMP's threads, in one call from Python. Built with -fopenmp,
 * this library shares torch's OpenMP runtime (the same libgomp), so its parts run on the threads torch's own
 * operations left spinning instead of on threads of recon's competing with them for the cores; built without, the
 * parts run in order on the calling thread (recon.nerf.native then splits the work over threads of its own). Each
 * part computes what the same part called alone computes: the results do not depend on the build. */

/* Whether the `_all` entry points below run their parts in parallel (built with OpenMP). */
int32_t recon_openmp(void)
{
#ifdef _OPENMP
    return 1;
#else
    return 0;
#endif
}

/* Part s of n items cut into `slices` contiguous slices: [slice_lo(n, s), slice_lo(n, s + 1)). */
static inline int64_t slice_lo(int64_t n, int64_t s, int64_t slices) { return n * s / slices; }

/* Where each of `slices` slices of the rays writes its samples and how many it may: from offsets[s] to
 * offsets[s + 1], each ray given its uniform step count (the most samples it can keep; a contracted ray, whose count
 * takes its breakpoints, max_samples), at most `cap`. */
void recon_march_offsets(int64_t n_rays, const float *t_near, const float *t_far, float step, int64_t max_samples,
                         int32_t contracted, int64_t cap, int64_t slices, int64_t *offsets)
{
    int64_t total = 0;
    offsets[0] = 0;
    for (int64_t s = 0; s < slices; ++s) {
        for (int64_t r = slice_lo(n_rays, s, slices); r < slice_lo(n_rays, s + 1, slices); ++r) {
            const int64_t count = contracted ? max_samples : uniform_steps(t_near[r], t_far[r], step, max_samples);
            total += count < cap ? count : cap;
        }
        offsets[s + 1] = total;
    }
}

/* recon_march_dense over `slices` slices of the rays: slice s writes its samples from sample offsets[s] on, at most
 * offsets[s + 1] - offsets[s] of them (recon_march_offsets), and its count to counts[s] (a count above that room
 * asks the caller to march that slice again with more). out_u may be NULL. */
void recon_march_dense_all(
    int64_t n_rays, const float *rays_o, const float *rays_d, const float *t_near, const float *t_far,
    const double *jitter, const uint8_t *occupied, int64_t occ_res, const float *occ_lo, const float *occ_hi,
    const uint8_t *blocks, int64_t block, float step, int64_t max_samples, double log_min_t,
    int64_t n_levels, const float *const *tables, const int64_t *level_res, const float *grid_lo, const float *grid_hi,
    float bias, float density_scale, int32_t exp_activation, float sigma_max, float tau_max, int32_t contracted,
    int64_t slices, int64_t threads, const int64_t *offsets, float *out_ts, float *out_te, int64_t *out_ri,
    float *out_sigma, float *out_u, int64_t *counts)
{
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
    for (int64_t s = 0; s < slices; ++s) {
        const int64_t lo = slice_lo(n_rays, s, slices), hi = slice_lo(n_rays, s + 1, slices), at = offsets[s];
        counts[s] = recon_march_dense(
            hi - lo, rays_o + 3 * lo, rays_d + 3 * lo, t_near + lo, t_far + lo, jitter ? jitter + lo : 0, occupied,
            occ_res, occ_lo, occ_hi, blocks, block, step, max_samples, log_min_t, n_levels, tables, level_res, grid_lo,
            grid_hi, bias, density_scale, exp_activation, sigma_max, tau_max, contracted, offsets[s + 1] - at,
            out_ts + at, out_te + at, out_ri + at, out_sigma + at, out_u ? out_u + 3 * at : 0, lo);
    }
}

/* recon_march_render over `slices` slices of the rays, as recon_march_dense_all (the per-ray sums are each ray's). */
void recon_march_render_all(
    int64_t n_rays, const float *rays_o, const float *rays_d, const float *t_near, const float *t_far,
    const uint8_t *occupied, int64_t occ_res, const float *occ_lo, const float *occ_hi,
    const uint8_t *blocks, int64_t block, float step, int64_t max_samples, double log_min_t,
    int64_t n_levels, const float *const *tables, const int64_t *level_res, const float *grid_lo, const float *grid_hi,
    float bias, float density_scale, int32_t exp_activation, float sigma_max, float tau_max, int32_t contracted,
    int64_t slices, int64_t threads, const int64_t *offsets, float *out_u, float *out_w, int64_t *out_ri,
    float color_min_weight, float *ray_opacity, float *ray_depth, int64_t *ray_samples, int64_t *counts)
{
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
    for (int64_t s = 0; s < slices; ++s) {
        const int64_t lo = slice_lo(n_rays, s, slices), hi = slice_lo(n_rays, s + 1, slices), at = offsets[s];
        counts[s] = recon_march_render(
            hi - lo, rays_o + 3 * lo, rays_d + 3 * lo, t_near + lo, t_far + lo, occupied, occ_res, occ_lo, occ_hi,
            blocks, block, step, max_samples, log_min_t, n_levels, tables, level_res, grid_lo, grid_hi, bias,
            density_scale, exp_activation, sigma_max, tau_max, contracted, offsets[s + 1] - at, out_u + 3 * at,
            out_w + at, out_ri + at, lo, color_min_weight, ray_opacity + lo, ray_depth + lo, ray_samples + lo);
    }
}

void recon_trilinear_features_all(int64_t n, const float *u, const float *table, int64_t res, int64_t channels,
                                  float *out, int64_t slices, int64_t threads)
{
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
    for (int64_t s = 0; s < slices; ++s) {
        const int64_t lo = slice_lo(n, s, slices), hi = slice_lo(n, s + 1, slices);
        recon_trilinear_features(hi - lo, u + 3 * lo, table, res, channels, out + lo * channels);
    }
}

/* recon_trilinear_backward's `parts` parts (a thread each). */
void recon_trilinear_backward_all(int64_t n, const float *u, const float *grad_out, int64_t res, int64_t channels,
                                  float *grad_table, uint8_t *touched, int64_t parts)
{
#pragma omp parallel for num_threads(parts) schedule(static, 1)
    for (int64_t part = 0; part < parts; ++part)
        recon_trilinear_backward(n, u, grad_out, res, channels, grad_table, touched, part, parts);
}

/* recon_trilinear_backward of one-channel grids (levels) at the same points with the same gradient, a level a part
 * (the finest first, as given): separate tables, so the parts share nothing and each level's sums are its own. */
void recon_trilinear_backward_levels_all(int64_t n, const float *u, const float *grad_out, int64_t n_levels,
                                         const int64_t *res, float *const *grad_tables, uint8_t *const *touched,
                                         int64_t threads)
{
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
    for (int64_t level = 0; level < n_levels; ++level)
        recon_trilinear_backward(n, u, grad_out, res[level], 1, grad_tables[level], touched[level], 0, 1);
}

void recon_hash_features_all(int64_t n, const float *u, const float *table, int64_t levels, const int64_t *res,
                             const int64_t *offset, const int64_t *hashed, int64_t log2_table, int64_t features,
                             float *out, int64_t slices, int64_t threads)
{
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
    for (int64_t s = 0; s < slices; ++s) {
        const int64_t lo = slice_lo(n, s, slices), hi = slice_lo(n, s + 1, slices);
        recon_hash_features(hi - lo, u + 3 * lo, table, levels, res, offset, hashed, log2_table, features,
                            out + lo * levels * features);
    }
}

/* recon_hash_backward with the levels dealt out to `parts` parts (a thread each). */
void recon_hash_backward_all(int64_t n, const float *u, const float *grad_out, int64_t levels, const int64_t *res,
                             const int64_t *offset, const int64_t *hashed, int64_t log2_table, int64_t features,
                             int64_t parts, float *grad_table, uint8_t *touched)
{
#pragma omp parallel for num_threads(parts) schedule(static, 1)
    for (int64_t part = 0; part < parts; ++part)
        recon_hash_backward(n, u, grad_out, levels, res, offset, hashed, log2_table, features, part, parts, grad_table,
                            touched);
}

/* recon_adam over `slices` slices of whole blocks, so that each slice's flags start at its own. */
void recon_adam_all(int64_t n, float *param, float *grad, float *exp_avg, float *exp_avg_sq, float one_minus_beta1,
                    float beta2, float one_minus_beta2, float step_size, float bias2_sqrt, float eps, int32_t masked,
                    int32_t clear, uint8_t *touched, int64_t slices, int64_t threads)
{
    const int64_t blocks = (n + ADAM_BLOCK - 1) / ADAM_BLOCK;
#pragma omp parallel for num_threads(threads) schedule(dynamic, 1)
    for (int64_t s = 0; s < slices; ++s) {
        const int64_t b = slice_lo(blocks, s, slices), lo = b * ADAM_BLOCK;
        int64_t hi = slice_lo(blocks, s + 1, slices) * ADAM_BLOCK;
        if (hi > n) hi = n;
        if (hi > lo)
            recon_adam(hi - lo, param + lo, grad + lo, exp_avg + lo, exp_avg_sq + lo, one_minus_beta1, beta2,
                       one_minus_beta2, step_size, bias2_sqrt, eps, masked, clear, touched ? touched + b : 0);
    }
}

/* ------------------------------------------------------------------------------------------------------------------
 * Compositing packed samples and the distortion loss, forward and backward, a ray at a time (the references:
 * recon.nerf.render.render_weights_packed with accumulate_packed, and distortion_packed; on CUDA the same sums are
 * recon/nerf/triton_kernels.py's composite_* and distortion_*). Ray r's samples are offsets[r]:offsets[r + 1].
 * Running sums along a ray are doubles, as the references' cumulative sums are. */

/* optical_thickness: clamp(clamp(sigma, 0, sigma_max) * max(delta, 0), 0, tau_max), NaN kept. */
static inline float thickness(float sigma, float delta, float sigma_max, float tau_max)
{
    const float s = sigma != sigma ? sigma : (sigma < 0.0f ? 0.0f : (sigma > sigma_max ? sigma_max : sigma));
    const float d = delta != delta ? delta : (delta < 0.0f ? 0.0f : delta);
    const float p = s * d;
    return p != p ? p : (p < 0.0f ? 0.0f : (p > tau_max ? tau_max : p));
}

/* Rays [lo, hi): weights w_i = T_i (1 - exp(-tau_i)), transmittance T_i = exp(-sum_{j<i} tau_j), and each ray's
 * opacity sum w_i and depth sum w_i t_i. */
static void composite_rays(int64_t lo, int64_t hi, const int64_t *offsets, const float *sigma, const float *delta,
                     const float *t, float sigma_max, float tau_max, float *weights, float *trans, float *opacity,
                     float *depth)
{
    for (int64_t r = lo; r < hi; ++r) {
        double before = 0.0;
        float op = 0.0f, dep = 0.0f;
        for (int64_t i = offsets[r]; i < offsets[r + 1]; ++i) {
            const float tau = thickness(sigma[i], delta[i], sigma_max, tau_max);
            const float tr = (float)exp(-(before > 0.0 ? before : 0.0));
            const float w = tr * -expm1f(-tau);
            trans[i] = tr, weights[i] = w;
            before += (double)tau;
            op += w, dep += w * t[i];
        }
        opacity[r] = op, depth[r] = dep;
    }
}

/* Gradients of the compositing to sigma, delta and t, given those of the weights and the transmittance (g_w, g_trans,
 * each may be NULL), the opacity and the depth sum. With G_i = dL/dw_i + dL/dopacity + dL/ddepth t_i:
 * dL/dtau_k = G_k T_k exp(-tau_k) - sum_{i>k} (G_i w_i + dL/dT_i T_i), then through the clamps as torch's clamp
 * passes gradients (inside its closed range). */
static void composite_backward_rays(int64_t lo, int64_t hi, const int64_t *offsets, const float *sigma,
                                    const float *delta, const float *t, const float *weights, const float *trans,
                                    const float *g_w, const float *g_trans,
                                    const float *g_op, const float *g_dep, float sigma_max, float tau_max,
                                    float *g_sigma, float *g_delta, float *g_t)
{
    for (int64_t r = lo; r < hi; ++r) {
        double later = 0.0;
        for (int64_t i = offsets[r + 1] - 1; i >= offsets[r]; --i) {
            const float g = (g_w ? g_w[i] : 0.0f) + g_op[r] + g_dep[r] * t[i];
            const float s = sigma[i] < 0.0f ? 0.0f : (sigma[i] > sigma_max ? sigma_max : sigma[i]);
            const float d = delta[i] < 0.0f ? 0.0f : delta[i];
            const float p = s * d, tau = p < 0.0f ? 0.0f : (p > tau_max ? tau_max : p);
            float g_tau = (float)((double)(g * trans[i] * expf(-tau)) - later);
            if (!(p >= 0.0f && p <= tau_max)) g_tau = 0.0f;
            g_sigma[i] = (sigma[i] >= 0.0f && sigma[i] <= sigma_max) ? g_tau * d : 0.0f;
            g_delta[i] = delta[i] >= 0.0f ? g_tau * s : 0.0f;
            g_t[i] = g_dep[r] * weights[i];
            later += (double)(g * weights[i]) + (g_trans ? (double)(g_trans[i] * trans[i]) : 0.0);
        }
    }
}

/* Rays [lo, hi): each ray's distortion loss sum_i 2 w_i (m_i W_<i - (wm)_<i) + w_i^2 d_i / 3 (midpoints m sorted
 * along the ray, taken from its first: the loss depends only on their differences). */
static void distortion_rays(int64_t lo, int64_t hi, const int64_t *offsets, const float *w, const float *m,
                            const float *d, float *loss)
{
    for (int64_t r = lo; r < hi; ++r) {
        const int64_t start = offsets[r], end = offsets[r + 1];
        double before_w = 0.0, before_wm = 0.0, acc = 0.0;
        for (int64_t i = start; i < end; ++i) {
            const double wi = w[i], mi = (double)m[i] - (double)m[start];
            acc += 2.0 * wi * (mi * before_w - before_wm) + wi * wi * (double)d[i] / 3.0;
            before_w += wi, before_wm += wi * mi;
        }
        loss[r] = (float)acc;
    }
}

/* Gradients of recon_distortion, given the losses' (g_loss); with W_>i and (wm)_>i the later samples' sums:
 * dL/dw_i = 2 (m_i W_<i - (wm)_<i) + 2 ((wm)_>i - m_i W_>i) + 2/3 w_i d_i, dL/dm_i = 2 w_i (W_<i - W_>i),
 * dL/dd_i = w_i^2 / 3. */
static void distortion_backward_rays(int64_t lo, int64_t hi, const int64_t *offsets, const float *w, const float *m,
                               const float *d, const float *g_loss, float *g_w, float *g_m, float *g_d)
{
    for (int64_t r = lo; r < hi; ++r) {
        const int64_t start = offsets[r], end = offsets[r + 1];
        double total_w = 0.0, total_wm = 0.0;
        for (int64_t i = start; i < end; ++i)
            total_w += w[i], total_wm += (double)w[i] * ((double)m[i] - (double)m[start]);
        double before_w = 0.0, before_wm = 0.0;
        const double g = g_loss[r];
        for (int64_t i = start; i < end; ++i) {
            const double wi = w[i], mi = (double)m[i] - (double)m[start];
            const double after_w = total_w - before_w - wi, after_wm = total_wm - before_wm - wi * mi;
            g_w[i] = (float)(g * (2.0 * (mi * before_w - before_wm) + 2.0 * (after_wm - mi * after_w) +
                                  wi * (double)d[i] * (2.0 / 3.0)));
            g_m[i] = (float)(g * 2.0 * wi * (before_w - after_w));
            g_d[i] = (float)(g * wi * wi / 3.0);
            before_w += wi, before_wm += wi * mi;
        }
    }
}

/* The four above over the rays cut into `slices` slices, on OpenMP's threads where built with it. */
#define OVER_SLICES(n_rays, slices, threads, call)                                                                   \
    _Pragma("omp parallel for num_threads(threads) schedule(dynamic, 1)")                                           \
    for (int64_t s = 0; s < slices; ++s) {                                                                          \
        const int64_t lo = slice_lo(n_rays, s, slices), hi = slice_lo(n_rays, s + 1, slices);                       \
        call;                                                                                                       \
    }

void recon_composite_all(int64_t n_rays, const int64_t *offsets, const float *sigma, const float *delta,
                         const float *t, float sigma_max, float tau_max, float *weights, float *trans, float *opacity,
                         float *depth, int64_t slices, int64_t threads)
{
    OVER_SLICES(n_rays, slices, threads, composite_rays(lo, hi, offsets, sigma, delta, t, sigma_max, tau_max, weights,
                                                        trans, opacity, depth))
}

void recon_composite_backward_all(int64_t n_rays, const int64_t *offsets, const float *sigma, const float *delta,
                                  const float *t, const float *weights, const float *trans, const float *g_w,
                                  const float *g_trans, const float *g_op, const float *g_dep, float sigma_max,
                                  float tau_max, float *g_sigma, float *g_delta, float *g_t, int64_t slices,
                                  int64_t threads)
{
    OVER_SLICES(n_rays, slices, threads, composite_backward_rays(lo, hi, offsets, sigma, delta, t, weights, trans, g_w,
                                                                 g_trans, g_op, g_dep, sigma_max, tau_max, g_sigma,
                                                                 g_delta, g_t))
}

void recon_distortion_all(int64_t n_rays, const int64_t *offsets, const float *w, const float *m, const float *d,
                          float *loss, int64_t slices, int64_t threads)
{
    OVER_SLICES(n_rays, slices, threads, distortion_rays(lo, hi, offsets, w, m, d, loss))
}

void recon_distortion_backward_all(int64_t n_rays, const int64_t *offsets, const float *w, const float *m,
                                   const float *d, const float *g_loss, float *g_w, float *g_m, float *g_d,
                                   int64_t slices, int64_t threads)
{
    OVER_SLICES(n_rays, slices, threads, distortion_backward_rays(lo, hi, offsets, w, m, d, g_loss, g_w, g_m, g_d))
}
