// GELU, exact erf form (docs/math.md §3), the one elementwise kernel NumPy cannot do by itself (it
// has no erfc); its reference is pyvf/nn/layers.py gelu_forward_numpy (Python's erfc per element).
//     forward:  y  = x * Phi(x),                     Phi the standard normal CDF
//     backward: dx = dy * (Phi(x) + x * phi(x)),   phi(x) = exp(-x^2 / 2) / sqrt(2 pi)
// Phi is computed as 0.5 * erfc(-x / sqrt(2)), never as 0.5 * (1 + erf(x / sqrt(2))): for
// x <= -6 the latter loses every digit (Phi(-6) = 9.9e-10, Phi(-9) = 1e-19 < eps) while erfc
// keeps its relative accuracy down to the underflow. Every element in double (std::erfc, C99,
// accurate to a few ulp), rounded once to the array's dtype. Flat arrays, any size; outputs
// overwritten.
// Test: tests/test_layers.py (torch's exact gelu, mpmath in the tail, where torch's own erf form
// returns 0).
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <cmath>
#include <cstdint>
#include <stdexcept>

#include "threads.h"

namespace py = pybind11;

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

template <typename T> using Arr = py::array_t<T, py::array::c_style>;

// y = gelu(x), or with dy: dx = dy * gelu'(x); y, x, dy of one size (the binding checks)
template <typename T> void gelu_map(T* y, const T* x, const T* dy, int64_t n) {
#pragma omp parallel for schedule(static) num_threads(pyvf::num_threads()) if (pyvf::parallel_work(n, 65537))
    for (int64_t i = 0; i < n; ++i) {
        const double xi = x[i];
        double cdf, pdf;
        normal_cdf_pdf(xi, cdf, pdf);
        y[i] = dy ? (T)((double)dy[i] * (cdf + xi * pdf)) : (T)(xi * cdf);
    }
}

template <typename T> void gelu(Arr<T> y, Arr<T> x) {
    if (y.size() != x.size()) throw std::invalid_argument("pyvf._core.gelu: x and y differ in size");
    T* py_ = y.mutable_data();
    py::gil_scoped_release nogil;
    gelu_map<T>(py_, x.data(), nullptr, x.size());
}

template <typename T> void gelu_backward(Arr<T> dx, Arr<T> dy, Arr<T> x) {
    if (dx.size() != x.size() || dy.size() != x.size())
        throw std::invalid_argument("pyvf._core.gelu_backward: dx, dy and x differ in size");
    T* pdx = dx.mutable_data();
    py::gil_scoped_release nogil;
    gelu_map<T>(pdx, x.data(), dy.data(), x.size());
}

template <typename T> void bind(py::module_& m) {
    m.def("gelu", &gelu<T>, "y = gelu(x), overwritten", py::arg("y").noconvert(), py::arg("x").noconvert());
    m.def("gelu_backward", &gelu_backward<T>, "dx = dy * gelu'(x), overwritten", py::arg("dx").noconvert(),
          py::arg("dy").noconvert(), py::arg("x").noconvert());
}

}  // namespace

void bind_gelu(py::module_& m) {  // called from module.cpp's PYBIND11_MODULE
    bind<float>(m);
    bind<double>(m);
}
