/* Normal equations of one residual term of the SDF tracker (see eslam_core/tracking/sdf_tracker.py for the math and
 * the reference implementation in torch): H = sum_i w_i J_i^T J_i and b = sum_i w_i J_i^T r_i over rows
 * J_i = [g_i, x_i x g_i], in one pass over the points instead of the ~10 tensor operations (and the N x 6 Jacobian)
 * of the torch version. Points of weight 0 are skipped. */
#include <stdint.h>

/* x, g (N, 3), r, w (N,) -> H (6, 6) row-major, b (6,). */
void normal_equations(const double *x, const double *r, const double *g, const double *w, int64_t N, double *H,
                      double *b) {
    double h[6][6] = {{0}}, s[6] = {0};
    for (int64_t i = 0; i < N; ++i) {
        const double wi = w[i];
        if (wi == 0.0) continue;
        const double *p = x + 3 * i, *q = g + 3 * i;
        const double J[6] = {q[0], q[1], q[2], p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2],
                             p[0] * q[1] - p[1] * q[0]};
        for (int a = 0; a < 6; ++a) {
            const double wa = wi * J[a];
            s[a] += wa * r[i];
            for (int c = 0; c <= a; ++c) h[a][c] += wa * J[c];
        }
    }
    for (int a = 0; a < 6; ++a) {
        b[a] = s[a];
        for (int c = 0; c <= a; ++c) H[6 * a + c] = H[6 * c + a] = h[a][c];
    }
}
