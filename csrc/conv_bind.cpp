// Python bindings of the conv2d kernels (conv.cpp), called from module.cpp's PYBIND11_MODULE.
// The layers that call them are in pyvf/nn/conv.py;
// these take arrays of exactly one dtype in C layout (.noconvert(), c_style: a wrong dtype or
// layout is a TypeError, never a silent cast or copy) and check every size again, since a wrong
// one would read or write out of bounds.
//
// Argument order (STYLE.md): outputs, saved buffers, inputs, then sizes. Outputs are overwritten,
// never accumulated into.
//     conv2d_forward(y, x, w, b, stride, pt, pb, pl, pr)
//     conv2d_backward(dx, dw, db, x, w, dy, stride, pt, pb, pl, pr)
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <initializer_list>
#include <limits>
#include <string>

#include "conv.h"

namespace py = pybind11;

namespace pyvf {

namespace {

template <typename T> using Arr = py::array_t<T, py::array::c_style>;

constexpr int64_t kIntMax = std::numeric_limits<int>::max();  // the gemm's sizes are int

[[noreturn]] void bad(const std::string& what) { throw py::value_error("pyvf._core.conv2d: " + what); }

// a product of sizes (each >= 0) must fit the kernels' int: exact in 128 bits, so nothing wraps
void check_count(const char* arg, const char* what, std::initializer_list<int64_t> factors) {
    const __int128 big = (__int128)1 << 63;
    __int128 n = 1;
    for (int64_t f : factors) n = std::min(n * f, big);  // n, f < 2^63: the product fits 128 bits
    if (n > kIntMax)
        bad(std::string(arg) + ": " + what + " = " + (n < big ? std::to_string((int64_t)n) : "2^63 or more") +
            " exceeds 2^31 - 1, the kernel's int indexing; split the batch or the image");
}

// Sizes of (x, w, stride, padding), every count checked against int overflow; `y` is the shape the
// output (or dy) must have.
ConvDims dims_of(const py::array& x, const py::array& w, int64_t stride, int64_t pt, int64_t pb, int64_t pl,
                 int64_t pr) {
    if (x.ndim() != 4) bad("x must be 4-D (B, C, Hi, Wi)");
    if (w.ndim() != 4) bad("w must be 4-D (Co, C, kh, kw)");
    if (w.shape(1) != x.shape(1)) bad("w.shape[1] must equal x.shape[1] (the input channels)");
    if (stride < 1) bad("stride must be at least 1");
    if (pt < 0 || pb < 0 || pl < 0 || pr < 0) bad("padding must be non-negative");
    for (int64_t p : {pt, pb, pl, pr})
        if (p > kIntMax) bad("padding: " + std::to_string(p) + " exceeds 2^31 - 1");
    if (stride > kIntMax) bad("stride exceeds 2^31 - 1");
    ConvDims d{};
    d.B = x.shape(0), d.C = x.shape(1), d.Hi = x.shape(2), d.Wi = x.shape(3);
    d.Co = w.shape(0), d.kh = w.shape(2), d.kw = w.shape(3);
    d.stride = stride, d.pt = pt, d.pb = pb, d.pl = pl, d.pr = pr;
    if (d.kh < 1 || d.kw < 1) bad("w: the kernel must be at least 1x1");
    for (int64_t n : {d.Hi, d.Wi, d.kh, d.kw})
        if (n > kIntMax) bad("x, w: every image and kernel side must be below 2^31");
    if (d.Hi + pt + pb < d.kh || d.Wi + pl + pr < d.kw) bad("the kernel does not fit the padded image");
    d.Ho = (d.Hi + pt + pb - d.kh) / stride + 1;
    d.Wo = (d.Wi + pl + pr - d.kw) / stride + 1;
    check_count("w", "C*kh*kw", {d.C, d.kh, d.kw});
    check_count("w", "Co (w.shape[0])", {d.Co});
    check_count("x", "Hi*Wi", {d.Hi, d.Wi});
    check_count("padding", "Ho*Wo (the output's pixels)", {d.Ho, d.Wo});
    return d;
}

void check_shape(const py::array& a, const char* name, std::initializer_list<int64_t> want) {
    bool ok = a.ndim() == (py::ssize_t)want.size();
    int k = 0;
    for (int64_t n : want) ok = ok && a.shape(k++) == n;
    if (!ok) {
        std::string s = "(";
        for (int64_t n : want) s += std::to_string(n) + ", ";
        bad(std::string(name) + " must have shape " + s.substr(0, s.size() - 2) + ")");
    }
}

const char* kConvMemory =
    "conv2d: not enough memory for the kernel's work buffers (per thread about 128 KiB of columns, and w's "
    "size for the flipped kernel of the backward)";

void raise_status(int status) {
    if (status == kConvOutOfMemory) {
        PyErr_SetString(PyExc_MemoryError, kConvMemory);
        throw py::error_already_set();
    }
}

// kConvNonFinite (and the backward's kConvNonFiniteDw, kConvNonFiniteDb): the message of
// pyvf._checks.finite_result, naming the function and the output (name: kConvNonFinite's)
template <typename T> void raise_nonfinite(int status, const char* what, const char* name) {
    if (status == kConvNonFiniteDw) name = "dw";
    if (status == kConvNonFiniteDb) name = "db";
    if (status == kConvNonFinite || status == kConvNonFiniteDw || status == kConvNonFiniteDb)
        throw py::value_error(std::string(what) + ": " + name + " is not finite: it overflowed " +
                              (sizeof(T) == 4 ? "float32" : "float64") +
                              " (inputs too large for the dtype; rescale them, or use float64)");
    raise_status(status);
}

template <typename T>
void forward(Arr<T> y, Arr<T> x, Arr<T> w, Arr<T> b, int64_t stride, int64_t pt, int64_t pb, int64_t pl,
             int64_t pr) {
    const ConvDims d = dims_of(x, w, stride, pt, pb, pl, pr);
    check_shape(b, "b", {d.Co});
    check_shape(y, "y", {d.B, d.Co, d.Ho, d.Wo});
    T* py_ = y.mutable_data();
    const T *px = x.data(), *pw = w.data(), *pbias = b.data();
    int status;
    {
        py::gil_scoped_release nogil;
        status = conv2d_forward<T>(py_, px, pw, pbias, d);
    }
    raise_nonfinite<T>(status, "conv2d_forward", "y");
}

template <typename T>
void backward(Arr<T> dx, Arr<T> dw, Arr<T> db, Arr<T> x, Arr<T> w, Arr<T> dy, int64_t stride, int64_t pt,
              int64_t pb, int64_t pl, int64_t pr) {
    const ConvDims d = dims_of(x, w, stride, pt, pb, pl, pr);
    check_shape(dy, "dy", {d.B, d.Co, d.Ho, d.Wo});
    check_shape(dx, "dx", {d.B, d.C, d.Hi, d.Wi});
    check_shape(dw, "dw", {d.Co, d.C, d.kh, d.kw});
    check_shape(db, "db", {d.Co});
    T *pdx = dx.mutable_data(), *pdw = dw.mutable_data(), *pdb = db.mutable_data();
    const T *px = x.data(), *pw = w.data(), *pdy = dy.data();
    int status;
    {
        py::gil_scoped_release nogil;
        status = conv2d_backward<T>(pdx, pdw, pdb, px, pw, pdy, d);
    }
    raise_nonfinite<T>(status, "conv2d_backward", "dx");
}

template <typename T> void bind_dtype(py::module_& m) {
    m.def("conv2d_forward", &forward<T>,
          "y (B, Co, Ho, Wo) = conv2d(x (B, C, Hi, Wi), w (Co, C, kh, kw)) + b (Co,), overwritten",
          py::arg("y").noconvert(), py::arg("x").noconvert(), py::arg("w").noconvert(), py::arg("b").noconvert(),
          py::arg("stride"), py::arg("pt"), py::arg("pb"), py::arg("pl"), py::arg("pr"));
    m.def("conv2d_backward", &backward<T>, "dx, dw, db (overwritten) of y = conv2d(x, w) + b under the upstream gradient dy",
          py::arg("dx").noconvert(), py::arg("dw").noconvert(), py::arg("db").noconvert(), py::arg("x").noconvert(),
          py::arg("w").noconvert(), py::arg("dy").noconvert(), py::arg("stride"), py::arg("pt"), py::arg("pb"),
          py::arg("pl"), py::arg("pr"));
}

}  // namespace

void bind_conv(py::module_& m) {
    bind_dtype<float>(m);
    bind_dtype<double>(m);
}

}  // namespace pyvf
