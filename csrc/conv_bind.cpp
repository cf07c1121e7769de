// Python bindings of the conv2d and GEMM kernels (conv.cpp), called from module.cpp's
// PYBIND11_MODULE.
// The layers that call them are in pyvf/nn/conv.py and pyvf/nn/layers.py;
// these take arrays of exactly one dtype in C layout (.noconvert(), c_style: a wrong dtype or
// layout is a TypeError, never a silent cast or copy) and check every size again, since a wrong
// one would read or write out of bounds.
//
// Argument order (STYLE.md): outputs, saved buffers, inputs, then sizes. Outputs are overwritten,
// never accumulated into.
//     conv2d_forward(y, x, w, b, stride, pt, pb, pl, pr)
//     conv2d_backward(dx, dw, db, x, w, dy, stride, pt, pb, pl, pr)
// and the same with _plain: the plain-loop oracle;
//     matmul(c, a, b, ta, tb=False, bias=None): c (nb, M, N) = op(a) @ op(b) [+ bias (N,)] per
//     image, a (nb, M, K) or (nb, K, M) if ta, b (nb, K, N) or (nb, N, K) if tb
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <optional>
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
const char* kMatMemory =
    "matmul: not enough memory for the transposed copy of b (b's size) and the packed panels (per thread up to "
    "288 KiB of float32, 576 KiB of float64)";

void raise_status(int status, const char* memory_message = kConvMemory) {
    if (status == kConvOutOfMemory) {
        PyErr_SetString(PyExc_MemoryError, memory_message);
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

template <typename T, bool PLAIN>
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
        status = PLAIN ? conv2d_forward_plain<T>(py_, px, pw, pbias, d) : conv2d_forward<T>(py_, px, pw, pbias, d);
    }
    raise_nonfinite<T>(status, "conv2d_forward", "y");
}

template <typename T, bool PLAIN>
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
        status = PLAIN ? conv2d_backward_plain<T>(pdx, pdw, pdb, px, pw, pdy, d)
                       : conv2d_backward<T>(pdx, pdw, pdb, px, pw, pdy, d);
    }
    raise_nonfinite<T>(status, "conv2d_backward", "dx");
}

template <typename T> void matmul(Arr<T> c, Arr<T> a, Arr<T> b, bool ta, bool tb, std::optional<Arr<T>> bias) {
    auto fail = [](const std::string& what) { throw py::value_error("pyvf._core.matmul: " + what); };
    if (a.ndim() != 3 || b.ndim() != 3 || c.ndim() != 3) fail("a, b and c must be 3-D (batch, rows, columns)");
    const int64_t nb = a.shape(0), M = ta ? a.shape(2) : a.shape(1), K = ta ? a.shape(1) : a.shape(2);
    const int64_t N = tb ? b.shape(1) : b.shape(2);
    auto shape = [](const py::array& x) {
        std::string s = "(";
        for (py::ssize_t d = 0; d < x.ndim(); ++d) s += (d ? ", " : "") + std::to_string(x.shape(d));
        return s + (x.ndim() == 1 ? ",)" : ")");
    };
    const std::string want_k = " with a's batch " + std::to_string(nb) + " and K = " + std::to_string(K);
    if (b.shape(0) != nb || (tb ? b.shape(2) : b.shape(1)) != K)
        fail(std::string(tb ? "b must have shape (batch, N, K)" : "b must have shape (batch, K, N)") + want_k +
             ", got " + shape(b));
    if (c.shape(0) != nb || c.shape(1) != M || c.shape(2) != N)
        fail("c must have shape (batch, M, N) = (" + std::to_string(nb) + ", " + std::to_string(M) + ", " +
             std::to_string(N) + "), got " + shape(c));
    for (int64_t n : {M, N, K})
        if (n > kIntMax) fail("every side must be below 2^31");
    check_count("a", "M*K", {M, K});
    check_count("b", "K*N", {K, N});
    check_count("c", "M*N", {M, N});
    if (bias && (bias->ndim() != 1 || bias->shape(0) != N))
        fail("bias must have shape (N,) = (" + std::to_string(N) + ",), got " + shape(*bias));
    T* pc = c.mutable_data();
    const T *pa = a.data(), *pb = b.data(), *pbias = bias ? bias->data() : nullptr;
    int status;
    {
        py::gil_scoped_release nogil;
        status = matmul_batched<T>(pc, pa, pb, nb, M, N, K, ta, tb, pbias);
    }
    raise_status(status, kMatMemory);
}

template <typename T> void bind_dtype(py::module_& m) {
    m.def("matmul", &matmul<T>,
          "c (nb, M, N) = op(a) @ op(b) [+ bias (N,)] per image, op = transpose of a if ta, of b if tb; c overwritten",
          py::arg("c").noconvert(), py::arg("a").noconvert(), py::arg("b").noconvert(), py::arg("ta"),
          py::arg("tb") = false, py::arg("bias").noconvert() = py::none());
    const char* doc_f = "y (B, Co, Ho, Wo) = conv2d(x (B, C, Hi, Wi), w (Co, C, kh, kw)) + b (Co,), overwritten";
    const char* doc_b = "dx, dw, db (overwritten) of y = conv2d(x, w) + b under the upstream gradient dy";
    m.def("conv2d_forward", &forward<T, false>, doc_f, py::arg("y").noconvert(), py::arg("x").noconvert(),
          py::arg("w").noconvert(), py::arg("b").noconvert(), py::arg("stride"), py::arg("pt"), py::arg("pb"),
          py::arg("pl"), py::arg("pr"));
    m.def("conv2d_forward_plain", &forward<T, true>, doc_f, py::arg("y").noconvert(), py::arg("x").noconvert(),
          py::arg("w").noconvert(), py::arg("b").noconvert(), py::arg("stride"), py::arg("pt"), py::arg("pb"),
          py::arg("pl"), py::arg("pr"));
    m.def("conv2d_backward", &backward<T, false>, doc_b, py::arg("dx").noconvert(), py::arg("dw").noconvert(),
          py::arg("db").noconvert(), py::arg("x").noconvert(), py::arg("w").noconvert(), py::arg("dy").noconvert(),
          py::arg("stride"), py::arg("pt"), py::arg("pb"), py::arg("pl"), py::arg("pr"));
    m.def("conv2d_backward_plain", &backward<T, true>, doc_b, py::arg("dx").noconvert(), py::arg("dw").noconvert(),
          py::arg("db").noconvert(), py::arg("x").noconvert(), py::arg("w").noconvert(), py::arg("dy").noconvert(),
          py::arg("stride"), py::arg("pt"), py::arg("pb"), py::arg("pl"), py::arg("pr"));
}

}  // namespace

void bind_conv(py::module_& m) {
    bind_dtype<float>(m);
    bind_dtype<double>(m);
}

}  // namespace pyvf
