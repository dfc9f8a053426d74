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

/* The per-point work below is written for channel counts that are a multiple of VEC (the planes' 32, a tracker's
 * folded 16) with 16-float vectors (GCC / Clang vector extensions: AVX-512, two AVX registers or four NEON ones,
 * whatever the CPU has), and inlined with the count as a constant: accumulators stay in registers along the
 * channels. Left to itself the compiler vectorised across the 12 corners with gathers: 2x slower. Other channel
 * counts take the scalar loops. 4-byte alignment: a row starts at any float. */
#define VEC 16
typedef float vecf __attribute__((vector_size(4 * VEC), aligned(4)));
#define INLINE static inline __attribute__((always_inline))

/* o = sum_j w_j row_j */
INLINE void gather_rows(const float *table, const Corners *c, int64_t C, float *o) {
    if (C % VEC) {
        memset(o, 0, sizeof(float) * C);
        for (int j = 0; j < 12; ++j)
            for (int64_t ch = 0; ch < C; ++ch) o[ch] += c->w[j] * table[c->rows[j] * C + ch];
        return;
    }
    vecf acc[C / VEC];
    for (int k = 0; k < C / VEC; ++k) acc[k] = (vecf){0.f};
    for (int j = 0; j < 12; ++j) {
        const vecf *r = (const vecf *)(table + c->rows[j] * C);
        for (int k = 0; k < C / VEC; ++k) acc[k] += c->w[j] * r[k];
    }
    for (int k = 0; k < C / VEC; ++k) ((vecf *)o)[k] = acc[k];
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
            if (C == 32) gather_rows(table, &c, 32, o);
            else if (C == 16) gather_rows(table, &c, 16, o);
            else gather_rows(table, &c, C, o);
        }
    }
}

/* d (grad_out . feature) / d point along each axis, without the slope dg: the sum over the corners of the planes
 * spanning that axis of dw * (grad_out . row). Per axis, one channel vector (vector FMAs) and one dot product with
 * grad_out, instead of one horizontal reduction per corner. */
INLINE void point_gradient(const float *table, const Corners *c, int64_t C, const float *go, float out[3]) {
    if (C % VEC) {
        for (int ax = 0; ax < 3; ++ax) out[ax] = 0.f;
        for (int k = 0; k < 3; ++k)
            for (int q = 0; q < 4; ++q) {
                int j = 4 * k + q;
                float dot = 0.f;
                for (int64_t ch = 0; ch < C; ++ch) dot += go[ch] * table[c->rows[j] * C + ch];
                out[AXIS_A[k]] += c->dw_da[j] * dot;
                out[AXIS_B[k]] += c->dw_db[j] * dot;
            }
        return;
    }
    vecf acc[3][C / VEC];
    for (int ax = 0; ax < 3; ++ax)
        for (int v = 0; v < C / VEC; ++v) acc[ax][v] = (vecf){0.f};
    for (int k = 0; k < 3; ++k)
        for (int q = 0; q < 4; ++q) {
            const int j = 4 * k + q;
            const vecf *r = (const vecf *)(table + c->rows[j] * C);
            for (int v = 0; v < C / VEC; ++v) {
                acc[AXIS_A[k]][v] += c->dw_da[j] * r[v];
                acc[AXIS_B[k]][v] += c->dw_db[j] * r[v];
            }
        }
    for (int ax = 0; ax < 3; ++ax) {
        vecf d = (vecf){0.f};
        for (int v = 0; v < C / VEC; ++v) d += ((const vecf *)go)[v] * acc[ax][v];
        float dot = 0.f;
        for (int e = 0; e < VEC; ++e) dot += d[e];
        out[ax] = dot;
    }
}

/* The tracker's TSDF and its gradient in the points, one sweep per point (FrozenField.sdf_with_gradient): the
 * decoder's first layer is folded into `table` (C = its width per scale: pre-activation = bias1 + the sum over the
 * scales of the lookups), then L later layers (ReLU before each; layer l is dims[l+1] x dims[l], packed one after
 * the other: `weights` row-major, `weights_t` the same layers transposed, `biases`; dims[0] = C, dims[L] = 1) and
 * tanh. Back through the same layers to the first one's pre-activation, whose gradient is the same for every
 * scale, then through the bilinear weights to the point. Widths up to MAX_WIDTH, S up to MAX_SCALES, L up to
 * MAX_LAYERS. Layers of width VEC (the `fast` decoders' 16) run as vector FMAs: a column of W (a row of W^T) per
 * input forward, a row of W per output backward. */
#define MAX_WIDTH 64
#define MAX_SCALES 4
#define MAX_LAYERS 7

/* out = W x + b, W (out x in) given as W^T (in x out). */
INLINE void dense(const float *Wt, const float *b, const float *x, int64_t in, int64_t out, float *y) {
    if (out == VEC) {
        vecf acc = *(const vecf *)b;
        for (int64_t k = 0; k < in; ++k) acc += x[k] * ((const vecf *)(Wt + k * VEC))[0];
        *(vecf *)y = acc;
        return;
    }
    for (int64_t j = 0; j < out; ++j) y[j] = b[j];
    for (int64_t k = 0; k < in; ++k)
        for (int64_t j = 0; j < out; ++j) y[j] += x[k] * Wt[k * out + j];
}

/* gin = W^T g, W (out x in) row-major. */
INLINE void dense_back(const float *W, const float *g, int64_t in, int64_t out, float *gin) {
    if (in == VEC) {
        vecf acc = (vecf){0.f};
        for (int64_t j = 0; j < out; ++j) acc += g[j] * ((const vecf *)(W + j * VEC))[0];
        *(vecf *)gin = acc;
        return;
    }
    for (int64_t k = 0; k < in; ++k) gin[k] = 0.f;
    for (int64_t j = 0; j < out; ++j)
        for (int64_t k = 0; k < in; ++k) gin[k] += g[j] * W[j * in + k];
}

INLINE void tsdf_point(const float *p, const float *table, int64_t C, int64_t S, const int64_t *sizes,
                       const int64_t *offsets, const float *bmin, const float *ext, const float *bias1, int64_t L,
                       const int64_t *dims, const float *weights, const float *weights_t, const float *biases,
                       float *sdf, float grad[3]) {
    Corners c[MAX_SCALES];
    float dg[MAX_SCALES][3];
    float pre[(MAX_LAYERS + 1) * MAX_WIDTH];  /* each layer's input before its ReLU, layer after layer */
    float row[MAX_WIDTH], x[MAX_WIDTH];
    memcpy(pre, bias1, sizeof(float) * C);
    for (int64_t s = 0; s < S; ++s) {
        int64_t base[3]; float frac[3];
        grid_coords(p, bmin, ext, sizes + 3 * s, base, frac, dg[s]);
        plane_corners(base, frac, sizes + 3 * s, offsets + 3 * s, &c[s]);
        if (C == 16) gather_rows(table, &c[s], 16, row);
        else gather_rows(table, &c[s], C, row);
        for (int64_t k = 0; k < C; ++k) pre[k] += row[k];
    }
    int64_t w_at = 0, b_at = 0, at = 0;  /* layer l's weights, biases and input */
    for (int64_t l = 0; l < L; ++l) {
        const int64_t in = dims[l], out = dims[l + 1];
        for (int64_t k = 0; k < in; ++k) x[k] = pre[at + k] > 0.f ? pre[at + k] : 0.f;
        dense(weights_t + w_at, biases + b_at, x, in, out, pre + at + in);
        w_at += out * in; b_at += out; at += in;
    }
    const float y = tanhf(pre[at]);
    *sdf = y;
    /* backward: g = d y / d (the current layer's output), from the last layer to the first one's pre-activation */
    float g[MAX_WIDTH], gin[MAX_WIDTH];
    g[0] = 1.f - y * y;
    for (int64_t l = L - 1; l >= 0; --l) {
        const int64_t in = dims[l], out = dims[l + 1];
        w_at -= out * in; at -= in;
        dense_back(weights + w_at, g, in, out, gin);
        for (int64_t k = 0; k < in; ++k) g[k] = pre[at + k] > 0.f ? gin[k] : 0.f;
    }
    grad[0] = grad[1] = grad[2] = 0.f;
    for (int64_t s = 0; s < S; ++s) {
        float d[3];
        if (C == 16) point_gradient(table, &c[s], 16, g, d);
        else point_gradient(table, &c[s], C, g, d);
        for (int ax = 0; ax < 3; ++ax) grad[ax] += d[ax] * dg[s][ax];
    }
}

/* sdf (N,) in units of the truncation, grad (N, 3); returns 0, or -1 for sizes beyond the limits above. */
int tsdf_with_gradient(const float *points, int64_t N, const float *table, int64_t C, int64_t S,
                       const int64_t *sizes, const int64_t *offsets, const float *bmin, const float *ext,
                       const float *bias1, int64_t L, const int64_t *dims, const float *weights,
                       const float *weights_t, const float *biases, float *sdf, float *grad, int threads) {
    if (S > MAX_SCALES || L < 1 || L > MAX_LAYERS || dims[0] != C || dims[L] != 1) return -1;
    for (int64_t l = 0; l <= L; ++l)
        if (dims[l] < 1 || dims[l] > MAX_WIDTH) return -1;
    #pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t i = 0; i < N; ++i)
        tsdf_point(points + 3 * i, table, C, S, sizes, offsets, bmin, ext, bias1, L, dims, weights, weights_t,
                   biases, sdf + i, grad + 3 * i);
    return 0;
}

/* grad_points (N, 3): accumulated (+=). */
void plane_backward_points(const float *points, int64_t N, const float *table, int64_t C, int64_t S,
                           const int64_t *sizes, const int64_t *offsets, const float *bmin, const float *ext,
                           const float *grad_out, float *grad_points, int threads) {
    #pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t i = 0; i < N; ++i) {
        float gp[3] = {0.f, 0.f, 0.f};
        for (int64_t s = 0; s < S; ++s) {
            int64_t base[3]; float frac[3], dg[3], d[3]; Corners c;
            grid_coords(points + 3 * i, bmin, ext, sizes + 3 * s, base, frac, dg);
            plane_corners(base, frac, sizes + 3 * s, offsets + 3 * s, &c);
            const float *go = grad_out + (i * S + s) * C;
            if (C == 32) point_gradient(table, &c, 32, go, d);
            else if (C == 16) point_gradient(table, &c, 16, go, d);
            else point_gradient(table, &c, C, go, d);
            for (int ax = 0; ax < 3; ++ax) gp[ax] += d[ax] * dg[ax];
        }
        grad_points[3 * i] += gp[0]; grad_points[3 * i + 1] += gp[1]; grad_points[3 * i + 2] += gp[2];
    }
}

/* grad_table rows += w_j grad_out for the corners in [lo, hi); marks them in `touched` (may be NULL) after the
 * update (a byte store may alias any float). */
INLINE void scatter_rows(float *grad_table, const Corners *c, int64_t C, const float *go, int64_t lo, int64_t hi,
                         uint8_t *touched) {
    for (int j = 0; j < 12; ++j) {
        const int64_t row = c->rows[j];
        if (row < lo || row >= hi) continue;
        float *g = grad_table + row * C;
        if (C % VEC) {
            for (int64_t ch = 0; ch < C; ++ch) g[ch] += c->w[j] * go[ch];
        } else {
            for (int v = 0; v < C / VEC; ++v) ((vecf *)g)[v] += c->w[j] * ((const vecf *)go)[v];
        }
        if (touched) touched[row] = 1;
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
                if (C == 32) scatter_rows(grad_table, &c, 32, go, lo, hi, touched);
                else if (C == 16) scatter_rows(grad_table, &c, 16, go, lo, hi, touched);
                else scatter_rows(grad_table, &c, C, go, lo, hi, touched);
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
