/* The compiled reference of bench/identify.py: Eq. 15 for P second-order filters (Eq. 11), the
 * plain loop a C programmer writes: per particle, the difference equation of
 * lfilter(B[p], A[p], x) from rest and the mean squared error against y.
 * B, A: (P, 3) row-major, ascending powers of z^-1; x, y: (M,); out: (P,). */
#include <stddef.h>

void swarm_mse(const double *B, const double *A, const double *x, const double *y,
               ptrdiff_t P, ptrdiff_t M, double *out) {
    for (ptrdiff_t p = 0; p < P; ++p) {
        const double inv = 1.0 / A[3 * p];
        const double b0 = B[3 * p] * inv, b1 = B[3 * p + 1] * inv, b2 = B[3 * p + 2] * inv;
        const double a1 = A[3 * p + 1] * inv, a2 = A[3 * p + 2] * inv;
        double x1 = 0.0, x2 = 0.0, y1 = 0.0, y2 = 0.0, s = 0.0;
        for (ptrdiff_t t = 0; t < M; ++t) {
            const double yt = b0 * x[t] + b1 * x1 + b2 * x2 - a1 * y1 - a2 * y2;
            const double e = yt - y[t];
            s += e * e;
            x2 = x1;
            x1 = x[t];
            y2 = y1;
            y1 = yt;
        }
        out[p] = s / (double)M;
    }
}
