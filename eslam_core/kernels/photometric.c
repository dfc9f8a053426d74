/* Photometric residuals against a reference keyframe, in one pass (see eslam_core/tracking/photometric.py for the
 * math and the reference implementation in torch, which this matches to rounding).
 *
 * Per world point x: the point in the reference camera p = R^T (x - t), its pixel (u, v), the bilinear sample of
 * one pyramid level (grey, dI/du, dI/dv; border clamp, level coordinate (u + 0.5) / scale - 0.5), the residual
 * against the current frame's grey level, its gradient in x and whether the reference saw the same surface there.
 * The torch version takes ~25 small tensor operations per call, whose overhead dominates at 1000-2000 points.
 */
#include <stdint.h>
#include <math.h>

static inline void bilinear3(const float *level, int64_t h, int64_t w, double lu, double lv, double s[3]) {
    lu = fmin(fmax(lu, 0.0), (double)(w - 1));
    lv = fmin(fmax(lv, 0.0), (double)(h - 1));
    int64_t u0 = (int64_t)floor(lu), v0 = (int64_t)floor(lv);
    int64_t u1 = u0 + 1 < w ? u0 + 1 : u0, v1 = v0 + 1 < h ? v0 + 1 : v0;
    double a = lu - (double)u0, b = lv - (double)v0;
    double w00 = (1 - a) * (1 - b), w01 = a * (1 - b), w10 = (1 - a) * b, w11 = a * b;
    for (int c = 0; c < 3; ++c) {
        const float *L = level + c * h * w;
        s[c] = w00 * L[v0 * w + u0] + w01 * L[v0 * w + u1] + w10 * L[v1 * w + u0] + w11 * L[v1 * w + u1];
    }
}

/* x (N, 3), pose (4, 4) camera-to-world row-major, depth (H, W) metres, level (3, h, w), grey (N,)
 * -> residual (N,), grad (N, 3), valid (N,) bytes. */
void photometric_residuals(const double *x, int64_t N, const double *pose, double fx, double fy, double cx,
                           double cy, int64_t W, int64_t H, const float *depth, const float *level, int64_t h,
                           int64_t w, double scale, const double *grey, double occlusion, double *residual,
                           double *grad, uint8_t *valid) {
    const double R[9] = {pose[0], pose[1], pose[2], pose[4], pose[5], pose[6], pose[8], pose[9], pose[10]};
    const double t[3] = {pose[3], pose[7], pose[11]};
    const double inv_scale = 1.0 / scale;
    for (int64_t i = 0; i < N; ++i) {
        const double d[3] = {x[3 * i] - t[0], x[3 * i + 1] - t[1], x[3 * i + 2] - t[2]};
        double p[3];
        for (int j = 0; j < 3; ++j) p[j] = R[j] * d[0] + R[3 + j] * d[1] + R[6 + j] * d[2];
        const double z = p[2], inv_z = 1.0 / fmax(z, 1e-6);
        const double u = fx * p[0] * inv_z + cx, v = fy * p[1] * inv_z + cy;
        int ok = z > 0.05 && u >= 1 && u <= (double)(W - 2) && v >= 1 && v <= (double)(H - 2);
        const int64_t ui = (int64_t)fmin(fmax(nearbyint(u), 0.0), (double)(W - 1));
        const int64_t vi = (int64_t)fmin(fmax(nearbyint(v), 0.0), (double)(H - 1));
        const double d_ref = depth[vi * W + ui];
        ok = ok && d_ref > 0 && fabs(d_ref - z) < occlusion;
        double s[3];
        bilinear3(level, h, w, (u + 0.5) * inv_scale - 0.5, (v + 0.5) * inv_scale - 0.5, s);
        residual[i] = s[0] - grey[i];
        const double gc[3] = {s[1] * fx * inv_z, s[2] * fy * inv_z,
                              -(s[1] * fx * p[0] + s[2] * fy * p[1]) * inv_z * inv_z};
        for (int j = 0; j < 3; ++j) grad[3 * i + j] = R[3 * j] * gc[0] + R[3 * j + 1] * gc[1] + R[3 * j + 2] * gc[2];
        valid[i] = (uint8_t)ok;
    }
}
