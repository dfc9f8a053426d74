/* Fused feature-plane lookup for ESLAM (see eslam_core/planes.py for the math and the reference implementation).
 *
 * For each point and scale: bilinear interpolation (align_corners, border clamp) on the xy, xz and yz planes,
 * summed over the planes. All planes live in one row-major table of `C` channels per cell. The backward pass gives
 * the gradient of the table (scatter) and of the points (through the bilinear weights), in one sweep each, without
 * the intermediate index / weight tensors a pure-torch version needs.
 */
#include <stdint.h>
#include <math.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif

static const int AXIS_A[3] = {0, 0, 1}; /* column axis of the xy, xz, yz planes */
static const int AXIS_B[3] = {1, 2, 2}; /* row axis */

typedef struct {
    int64_t rows[12];  /* 3 planes x 4 bilinear corners */
    float w[12];       /* bilinear weights */
    float dw_da[12];   /* d weight / d fraction along the plane's column axis */
    float dw_db[12];   /* d weight / d fraction along the plane's row axis */
} Corners;

/* Grid coordinate of a point at one scale: lower corner, fraction and d(grid coordinate)/d(point). */
static inline void grid_coords(const float *p, const float *bmin, const float *ext, const int64_t *n,
                               int64_t base[3], float frac[3], float dg_dp[3]) {
    for (int ax = 0; ax < 3; ++ax) {
        float u = (p[ax] - bmin[ax]) / ext[ax];
        float slope = (float)(n[ax] - 1) / ext[ax];
        if (u < 0.f) { u = 0.f; slope = 0.f; }
        if (u > 1.f) { u = 1.f; slope = 0.f; }
        float g = u * (float)(n[ax] - 1);
        int64_t b = (int64_t)g;
        if (b > n[ax] - 2) b = n[ax] - 2;
        base[ax] = b;
        frac[ax] = g - (float)b;
        dg_dp[ax] = slope;
    }
}

static inline void plane_corners(const int64_t base[3], const float frac[3], const int64_t *n, const int64_t *off,
                                 Corners *c) {
    for (int k = 0; k < 3; ++k) {
        int a = AXIS_A[k], b = AXIS_B[k];
        int64_t r0 = off[k] + base[b] * n[a] + base[a];
        float fa = frac[a], fb = frac[b];
        int j = 4 * k;
        c->rows[j] = r0;            c->rows[j + 1] = r0 + 1;
        c->rows[j + 2] = r0 + n[a]; c->rows[j + 3] = r0 + n[a] + 1;
        c->w[j] = (1 - fa) * (1 - fb); c->w[j + 1] = fa * (1 - fb);
        c->w[j + 2] = (1 - fa) * fb;   c->w[j + 3] = fa * fb;
        c->dw_da[j] = -(1 - fb); c->dw_da[j + 1] = 1 - fb; c->dw_da[j + 2] = -fb;     c->dw_da[j + 3] = fb;
        c->dw_db[j] = -(1 - fa); c->dw_db[j + 1] = -fa;    c->dw_db[j + 2] = 1 - fa;  c->dw_db[j + 3] = fa;
    }
}

/* out: (N, S, C) */
void plane_forward(const float *points, int64_t N, const float *table, int64_t C, int64_t S, const int64_t *sizes,
                   const int64_t *offsets, const float *bmin, const float *ext, float *out, int threads) {
    #pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t i = 0; i < N; ++i) {
        for (int64_t s = 0; s < S; ++s) {
            int64_t base[3]; float frac[3], dg[3]; Corners c;
            grid_coords(points + 3 * i, bmin, ext, sizes + 3 * s, base, frac, dg);
            plane_corners(base, frac, sizes + 3 * s, offsets + 3 * s, &c);
            float *o = out + (i * S + s) * C;
            memset(o, 0, sizeof(float) * C);
            for (int j = 0; j < 12; ++j) {
                const float *r = table + c.rows[j] * C;
                const float w = c.w[j];
                for (int64_t ch = 0; ch < C; ++ch) o[ch] += w * r[ch];
            }
        }
    }
}

/* grad_points (N, 3): accumulated (+=).
 * d feature / d point along axis x = dg[x] * sum over the corners of the planes spanning x of dw_x * row, so each
 * axis gets one channel vector (vector FMAs) and one dot product with grad_out, instead of one horizontal reduction
 * per corner. */
void plane_backward_points(const float *points, int64_t N, const float *table, int64_t C, int64_t S,
                           const int64_t *sizes, const int64_t *offsets, const float *bmin, const float *ext,
                           const float *grad_out, float *grad_points, int threads) {
    #pragma omp parallel num_threads(threads)
    {
        float acc[3 * C];
        #pragma omp for schedule(static)
        for (int64_t i = 0; i < N; ++i) {
            float gp[3] = {0.f, 0.f, 0.f};
            for (int64_t s = 0; s < S; ++s) {
                int64_t base[3]; float frac[3], dg[3]; Corners c;
                grid_coords(points + 3 * i, bmin, ext, sizes + 3 * s, base, frac, dg);
                plane_corners(base, frac, sizes + 3 * s, offsets + 3 * s, &c);
                for (int64_t ch = 0; ch < 3 * C; ++ch) acc[ch] = 0.f;
                for (int k = 0; k < 3; ++k) {
                    float *va = acc + AXIS_A[k] * C, *vb = acc + AXIS_B[k] * C;
                    for (int q = 0; q < 4; ++q) {
                        int j = 4 * k + q;
                        const float *r = table + c.rows[j] * C;
                        const float da = c.dw_da[j], db = c.dw_db[j];
                        #pragma omp simd
                        for (int64_t ch = 0; ch < C; ++ch) { va[ch] += da * r[ch]; vb[ch] += db * r[ch]; }
                    }
                }
                const float *go = grad_out + (i * S + s) * C;
                for (int ax = 0; ax < 3; ++ax) {
                    const float *v = acc + ax * C;
                    float dot = 0.f;
                    #pragma omp simd reduction(+:dot)
                    for (int64_t ch = 0; ch < C; ++ch) dot += go[ch] * v[ch];
                    gp[ax] += dot * dg[ax];
                }
            }
            grad_points[3 * i] += gp[0]; grad_points[3 * i + 1] += gp[1]; grad_points[3 * i + 2] += gp[2];
        }
    }
}

/* grad_table (rows, C): accumulated (+=). Threads own disjoint row ranges, so the scatter needs no atomics.
 * touched (rows, may be NULL): set to 1 for every row the scatter reaches. */
void plane_backward_table(const float *points, int64_t N, int64_t rows, int64_t C, int64_t S, const int64_t *sizes,
                          const int64_t *offsets, const float *bmin, const float *ext, const float *grad_out,
                          float *grad_table, uint8_t *touched, int threads) {
    #pragma omp parallel num_threads(threads)
    {
        int nt = 1, t = 0;
#ifdef _OPENMP
        nt = omp_get_num_threads(); t = omp_get_thread_num();
#endif
        int64_t lo = rows * t / nt, hi = rows * (t + 1) / nt;
        for (int64_t i = 0; i < N; ++i) {
            for (int64_t s = 0; s < S; ++s) {
                int64_t base[3]; float frac[3], dg[3]; Corners c;
                grid_coords(points + 3 * i, bmin, ext, sizes + 3 * s, base, frac, dg);
                plane_corners(base, frac, sizes + 3 * s, offsets + 3 * s, &c);
                const float *go = grad_out + (i * S + s) * C;
                for (int j = 0; j < 12; ++j) {
                    int64_t row = c.rows[j];
                    if (row < lo || row >= hi) continue;
                    float *g = grad_table + row * C;
                    const float w = c.w[j];
                    if (touched) touched[row] = 1;
                    for (int64_t ch = 0; ch < C; ++ch) g[ch] += w * go[ch];
                }
            }
        }
    }
}

/* Adam on the listed rows of a (rows, C) table, in torch's arithmetic (its fused CPU Adam, no weight decay):
 * m += (1 - b1) (g - m), v = b2 v + (1 - b2) g^2, p -= step m / (sqrt(v) / bias2_sqrt + eps), with
 * step = lr / (1 - b1^t) and bias2_sqrt = sqrt(1 - b2^t). Each listed gradient row is zeroed once used, so the
 * gradient buffer holds zeros again for the next backward pass. */
void adam_rows(float *param, float *grad, float *m, float *v, const int64_t *list, int64_t n, int64_t C, float step,
               float beta1, float beta2, float eps, float bias2_sqrt, int threads) {
    #pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t k = 0; k < n; ++k) {
        const int64_t o = list[k] * C;
        float *p = param + o, *g = grad + o, *mr = m + o, *vr = v + o;
        #pragma omp simd
        for (int64_t ch = 0; ch < C; ++ch) {
            const float gc = g[ch];
            mr[ch] += (1.f - beta1) * (gc - mr[ch]);
            vr[ch] = beta2 * vr[ch] + (1.f - beta2) * gc * gc;
            p[ch] -= step * mr[ch] / (sqrtf(vr[ch]) / bias2_sqrt + eps);
            g[ch] = 0.f;
        }
    }
}
