// Python bindings of the GELU kernel (elementwise.cpp: the math, its accuracy, its test), called
// from module.cpp's PYBIND11_MODULE. Reference: pyvf/nn/layers.py gelu_forward_numpy.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <cstdint>
#include <stdexcept>

#include "elementwise.h"

namespace py = pybind11;

namespace {

template <typename T> using Arr = py::array_t<T, py::array::c_style>;

template <typename T> void gelu(Arr<T> y, Arr<T> x) {
    if (y.size() != x.size()) throw std::invalid_argument("pyvf._core.gelu: x and y differ in size");
    T* py_ = y.mutable_data();
    py::gil_scoped_release nogil;
    pyvf::gelu_forward<T>(py_, x.data(), x.size());
}

template <typename T> void gelu_backward(Arr<T> dx, Arr<T> dy, Arr<T> x) {
    if (dx.size() != x.size() || dy.size() != x.size())
        throw std::invalid_argument("pyvf._core.gelu_backward: dx, dy and x differ in size");
    T* pdx = dx.mutable_data();
    py::gil_scoped_release nogil;
    pyvf::gelu_backward<T>(pdx, dy.data(), x.data(), x.size());
}

template <typename T> void bind(py::module_& m) {
    m.def("gelu", &gelu<T>, "y = gelu(x), overwritten", py::arg("y").noconvert(), py::arg("x").noconvert());
    m.def("gelu_backward", &gelu_backward<T>, "dx = dy * gelu'(x), overwritten", py::arg("dx").noconvert(),
          py::arg("dy").noconvert(), py::arg("x").noconvert());
}

}  // namespace

void bind_gelu(py::module_& m) {
    bind<float>(m);
    bind<double>(m);
}
