// LayerNorm over the last axis, forward and backward (docs/math.md §3; pyvf/nn/layers.py has
// the checks and the published semantics: eps inside the square root, as TF's LayerNormalization).
//
// Rows of d elements, each normalised alone:
//     forward:  mean = sum(x) / d               (double, rounded to T; a float64 row whose sum
//                                                 overflows: the mean of x 2^-k, times 2^k)
//               xc = x - mean; xc -= sum(xc) / d  (a second centring: the rounded mean can be
//                                                 an ulp off, which 1/sqrt(eps) = 316 amplifies)
//               rstd = 1 / sqrt(sum(xc^2) / d + eps)   (double)
//               xhat = xc rstd,  y = xhat gamma + beta
//     backward: g = dy gamma;  dx = rstd (g - mean(g) - xhat mean(g xhat))
//               dgamma = sum over rows of dy xhat, dbeta = sum over rows of dy
// Every row sum is a double sum in 8 lanes (the lanes added in order at the end). A constant
// row gives xc = 0 and y = beta exactly. Where the squares of a float64 row overflow (|xc| >
// 1e154) the row is scaled by 2^-k (max |xc| < 2^k, exact) before squaring; float32 squares in
// double never overflow.
//
// Threads: blocks of kRows rows, fixed whatever the thread count; dgamma and dbeta are summed
// per block in double and the blocks' sums added in block order, so every output is bitwise
// the same for any thread count.
//
// Why a kernel: the NumPy version took 0.9 s of a 34 s paper-size transformer step on one core
// whatever the thread count (nine passes over the activations, each a fresh temporary).
#include "layernorm.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include "threads.h"

namespace pyvf {

namespace {

constexpr int64_t kRows = 16;  // rows per block (the unit of work and of dgamma's partial sums)
constexpr int L = 8;           // lanes of the row sums

// sum over i < d of f(i), in L double lanes then the lanes in order
template <typename F> inline double lane_sum(int64_t d, F f) {
    double acc[L] = {};
    int64_t i = 0;
    for (; i + L <= d; i += L)
        for (int l = 0; l < L; ++l) acc[l] += f(i + l);
    for (int l = 0; i < d; ++i, ++l) acc[l] += f(i);
    double t = 0;
    for (int l = 0; l < L; ++l) t += acc[l];
    return t;
}

// One row; returns false where x - mean overflows T (nothing else written then).
template <typename T>
bool forward_row(T* y, T* xhat, T& rstd, const T* x, const T* gamma, const T* beta, int64_t d, double eps) {
    const double sum = lane_sum(d, [&](int64_t i) { return static_cast<double>(x[i]); });
    double m = sum / d;
    if (!std::isfinite(sum)) {  // a float64 row summing beyond 1.8e308, its mean finite: the mean of x 2^-k, 2^k >= 2d
        const int k = 1 + static_cast<int>(std::ceil(std::log2(static_cast<double>(d))));
        m = std::ldexp(lane_sum(d, [&](int64_t i) { return std::ldexp(static_cast<double>(x[i]), -k); }) / d, k);
    }
    const T mean = static_cast<T>(m);
    for (int64_t i = 0; i < d; ++i) xhat[i] = x[i] - mean;  // xhat holds xc until the end
    const double r = lane_sum(d, [&](int64_t i) { return static_cast<double>(xhat[i]); });
    if (!std::isfinite(r)) return false;
    const T rmean = static_cast<T>(r / d);
    for (int64_t i = 0; i < d; ++i) xhat[i] -= rmean;
    double ss = lane_sum(d, [&](int64_t i) { return static_cast<double>(xhat[i]) * xhat[i]; });
    double scale = 1.0, r1;
    if (std::isfinite(ss)) {
        r1 = 1.0 / std::sqrt(ss / d + eps);
    } else {  // float64 rows beyond 1e154: xs = xc 2^-k in [-1, 1], eps 2^-2k underflows harmlessly
        double amax = 0;
        for (int64_t i = 0; i < d; ++i) amax = std::max(amax, std::fabs(static_cast<double>(xhat[i])));
        int k;
        std::frexp(amax, &k);
        scale = std::ldexp(1.0, -k);
        ss = lane_sum(d, [&](int64_t i) {
            const double s = static_cast<double>(xhat[i]) * scale;
            return s * s;
        });
        r1 = 1.0 / std::sqrt(ss / d + eps * scale * scale);
    }
    rstd = static_cast<T>(scale * r1);
    for (int64_t i = 0; i < d; ++i) {
        xhat[i] = static_cast<T>(static_cast<double>(xhat[i]) * scale * r1);
        y[i] = xhat[i] * gamma[i] + beta[i];
    }
    return true;
}

}  // namespace

template <typename T>
int64_t layernorm_forward(T* y, T* xhat, T* rstd, const T* x, const T* gamma, const T* beta, int64_t M, int64_t d,
                          double eps) {
    const int64_t blocks = (M + kRows - 1) / kRows;
    int64_t bad = 0;
    RegionEnd end;
#pragma omp parallel num_threads(num_threads()) reduction(+ : bad) if (parallel_work(M * d, 16384))
    {
#pragma omp for schedule(static) nowait
        for (int64_t b = 0; b < blocks; ++b)
            for (int64_t r = b * kRows; r < std::min(M, (b + 1) * kRows); ++r)
                bad += !forward_row(y + r * d, xhat + r * d, rstd[r], x + r * d, gamma, beta, d, eps);
        end.arrive();
    }
    return bad;
}

template <typename T>
void layernorm_backward(T* dx, T* dgamma, T* dbeta, const T* dy, const T* xhat, const T* rstd, const T* gamma,
                        int64_t M, int64_t d) {
    const int64_t blocks = (M + kRows - 1) / kRows;
    std::vector<double> pg(blocks * d), pb(blocks * d);  // per block: sums of dy xhat and of dy
    RegionEnd end;
#pragma omp parallel num_threads(num_threads()) if (parallel_work(M * d, 16384))
    {
#pragma omp for schedule(static) nowait
        for (int64_t b = 0; b < blocks; ++b) {
            double* sg = pg.data() + b * d;
            double* sb = pb.data() + b * d;
            std::fill(sg, sg + d, 0.0);
            std::fill(sb, sb + d, 0.0);
            for (int64_t r = b * kRows; r < std::min(M, (b + 1) * kRows); ++r) {
                const T *gy = dy + r * d, *xh = xhat + r * d;
                const double m1 = lane_sum(d, [&](int64_t i) { return static_cast<double>(gy[i]) * gamma[i]; }) / d;
                const double m2 =
                    lane_sum(d, [&](int64_t i) { return static_cast<double>(gy[i]) * gamma[i] * xh[i]; }) / d;
                const double s = rstd[r];
                T* out = dx + r * d;
                for (int64_t i = 0; i < d; ++i) {
                    const double g = static_cast<double>(gy[i]) * gamma[i];
                    out[i] = static_cast<T>(s * (g - m1 - xh[i] * m2));
                    sg[i] += static_cast<double>(gy[i]) * xh[i];
                    sb[i] += gy[i];
                }
            }
        }
        end.arrive();
    }
    for (int64_t i = 0; i < d; ++i) {  // the blocks' sums in block order
        double g = 0, s = 0;
        for (int64_t b = 0; b < blocks; ++b) {
            g += pg[b * d + i];
            s += pb[b * d + i];
        }
        dgamma[i] = static_cast<T>(g);
        dbeta[i] = static_cast<T>(s);
    }
}

template int64_t layernorm_forward<float>(float*, float*, float*, const float*, const float*, const float*, int64_t,
                                          int64_t, double);
template int64_t layernorm_forward<double>(double*, double*, double*, const double*, const double*, const double*,
                                           int64_t, int64_t, double);
template void layernorm_backward<float>(float*, float*, float*, const float*, const float*, const float*,
                                        const float*, int64_t, int64_t);
template void layernorm_backward<double>(double*, double*, double*, const double*, const double*, const double*,
                                         const double*, int64_t, int64_t);

}  // namespace pyvf
