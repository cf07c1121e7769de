// Elementwise kernels that NumPy cannot do accurately by itself.
//
// GELU, exact erf form (SPEC.md §3): gelu(x) = x * Phi(x), Phi the standard normal CDF.
// Phi is computed as 0.5 * erfc(-x / sqrt(2)), never as 0.5 * (1 + erf(x / sqrt(2))): for
// x <= -6 the latter cancels to 0 (Phi(-6) = 9.9e-10) while erfc keeps full relative accuracy
// down to the underflow (x ~ -38 in float64). NumPy has no erf/erfc; std::erfc (C99) is
// accurate to a few ulp.
//     forward:  y  = x * Phi(x)
//     backward: dx = dy * (Phi(x) + x * phi(x)),   phi(x) = exp(-x^2 / 2) / sqrt(2 pi)
// Arrays are flat, any size, one dtype; float32 evaluates in float32 (erfcf, expf).
// Test: tests/test_layers.py (against torch's exact gelu in float64 and mpmath-free closed
// values in the tail).
#include <cmath>
#include <cstdint>

#include "elementwise.h"

namespace pyvf {

namespace {
template <typename T> constexpr T kInvSqrt2 = T(0.70710678118654752440084436210484903928);
template <typename T> constexpr T kInvSqrt2Pi = T(0.39894228040143267793994605993438186848);
}  // namespace

template <typename T> void gelu_forward(T* y, const T* x, int64_t n) {
#pragma omp parallel for schedule(static) if (n > 65536)
    for (int64_t i = 0; i < n; ++i) {
        const T xi = x[i];
        y[i] = xi * (T(0.5) * std::erfc(-xi * kInvSqrt2<T>));
    }
}

template <typename T> void gelu_backward(T* dx, const T* dy, const T* x, int64_t n) {
#pragma omp parallel for schedule(static) if (n > 65536)
    for (int64_t i = 0; i < n; ++i) {
        const T xi = x[i];
        const T cdf = T(0.5) * std::erfc(-xi * kInvSqrt2<T>);
        const T pdf = kInvSqrt2Pi<T> * std::exp(T(-0.5) * xi * xi);
        dx[i] = dy[i] * (cdf + xi * pdf);
    }
}

template void gelu_forward<float>(float*, const float*, int64_t);
template void gelu_forward<double>(double*, const double*, int64_t);
template void gelu_backward<float>(float*, const float*, const float*, int64_t);
template void gelu_backward<double>(double*, const double*, const double*, int64_t);

}  // namespace pyvf
