// Elementwise kernels that NumPy cannot do accurately by itself.
//
// GELU, exact erf form (SPEC.md §3): gelu(x) = x * Phi(x), Phi the standard normal CDF.
// Phi is computed as 0.5 * erfc(-x / sqrt(2)), never as 0.5 * (1 + erf(x / sqrt(2))): for
// x <= -6 the latter loses every digit (Phi(-6) = 9.9e-10, Phi(-9) = 1e-19 < eps) while erfc
// keeps its relative accuracy down to the underflow. NumPy has no erf/erfc; std::erfc (C99) is
// accurate to a few ulp.
//     forward:  y  = x * Phi(x)
//     backward: dx = dy * (Phi(x) + x * phi(x)),   phi(x) = exp(-x^2 / 2) / sqrt(2 pi)
// Arrays are flat, any size, one dtype. Accuracy: a few ulp down to x ~ -38 (float64) and
// ~ -13 (float32), where the result underflows. Test: tests/test_layers.py (torch's exact gelu,
// mpmath in the tail, where torch's own erf form returns 0).
#include <cmath>
#include <cstdint>

#include "elementwise.h"

namespace pyvf {

namespace {

// 1/sqrt(2) = kS_hi + kS_lo to ~2^-106; 2/sqrt(pi); 1/sqrt(2 pi)
constexpr double kS_hi = 0.70710678118654757;
constexpr double kS_lo = -4.8336466567264567e-17;
constexpr double k2_SqrtPi = 1.1283791670955126;
constexpr double kInvSqrt2Pi = 0.3989422804014327;

// Phi(x) and phi(x) in double, with the two roundings that the tail amplifies compensated:
// z = -x/sqrt(2) is carried as z + dz (fma), and erfc(z + dz) = erfc(z) - 2/sqrt(pi) e^(-z^2) dz;
// x^2 = h + l exactly (fma), and e^(-(h + l)/2) = e^(-h/2) (1 - l/2). Without these, for x ~ -37
// the relative error of Phi is x^2 * eps = 1400 ulp (the conditioning of erfc at its argument).
inline void normal_cdf_pdf(double x, double& cdf, double& pdf) {
    const double z = -x * kS_hi;
    const double dz = std::fma(-x, kS_hi, -z) - x * kS_lo;
    cdf = 0.5 * (std::erfc(z) - k2_SqrtPi * std::exp(-z * z) * dz);
    const double h = x * x;
    const double l = std::fma(x, x, -h);
    // e^(-h/2) underflows to 0 for h > 1490; past that (and where h overflows) pdf is 0
    pdf = h > 1500.0 ? 0.0 : kInvSqrt2Pi * std::exp(-0.5 * h) * (1.0 - 0.5 * l);
}

}  // namespace

// float32 evaluates in double and rounds once (<= 1 ulp); float64 compensates as above.
template <typename T> void gelu_forward(T* y, const T* x, int64_t n) {
#pragma omp parallel for schedule(static) if (n > 65536)
    for (int64_t i = 0; i < n; ++i) {
        double cdf, pdf;
        normal_cdf_pdf((double)x[i], cdf, pdf);
        y[i] = (T)((double)x[i] * cdf);
    }
}

template <typename T> void gelu_backward(T* dx, const T* dy, const T* x, int64_t n) {
#pragma omp parallel for schedule(static) if (n > 65536)
    for (int64_t i = 0; i < n; ++i) {
        const double xi = x[i];
        double cdf, pdf;
        normal_cdf_pdf(xi, cdf, pdf);
        dx[i] = (T)((double)dy[i] * (cdf + xi * pdf));
    }
}

template void gelu_forward<float>(float*, const float*, int64_t);
template void gelu_forward<double>(double*, const double*, int64_t);
template void gelu_backward<float>(float*, const float*, const float*, int64_t);
template void gelu_backward<double>(double*, const double*, const double*, int64_t);

}  // namespace pyvf
