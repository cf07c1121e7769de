// pyvf._core: the kernels' bindings. pyvf/ checks the arguments; these refuse (TypeError) any array
// not exactly of the dtype and C layout asked for, and check the sizes (a wrong one would read or
// write out of bounds). Order (STYLE.md): outputs (overwritten), saved buffers, inputs, scalars.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <initializer_list>
#include <limits>
#include <optional>
#include <new>
#include <stdexcept>
#include <string>

#include "kernels.h"
#include "simd.h"
#include "threads.h"

namespace py = pybind11;
using namespace pyvf;

namespace {

template <typename T> using Arr = py::array_t<T, py::array::c_style>;

// f() with the GIL released: the kernels touch no Python object
template <typename F> int nogil(F f) {
    py::gil_scoped_release released;
    return f();
}

AttnDims dims_of(const py::array& a) {
    if (a.ndim() != 6) throw std::invalid_argument("pyvf._core: expected a 6-d array (R, B, H, N, L, dh)");
    AttnDims d{a.shape(0), a.shape(1), a.shape(2), a.shape(3), a.shape(4), a.shape(5)};
    if (d.R < 1 || d.B < 1 || d.H < 1 || d.N < 1 || d.L < 1 || d.dh < 1)
        throw std::invalid_argument("pyvf._core: every dimension must be at least 1");
    if (d.L > (1 << 20) || d.dh > (1 << 20))
        throw std::invalid_argument("pyvf._core: L and dh must be below 2^20");
    return d;
}

bool has_shape(const py::array& a, std::initializer_list<int64_t> want) {
    bool ok = a.ndim() == (py::ssize_t)want.size();
    int k = 0;
    for (int64_t n : want) ok = ok && a.shape(k++) == n;
    return ok;
}

// every array's shape (R, B, H, N, L, dh), lse's (R, B, H, N, L)
void attn_shapes(const AttnDims& d, const py::array& lse, std::initializer_list<py::array> arrays) {
    for (const py::array& a : arrays)
        if (!has_shape(a, {d.R, d.B, d.H, d.N, d.L, d.dh}))
            throw std::invalid_argument("pyvf._core: q, k, v, o, do, dq, dk, dv must have one shape");
    if (!has_shape(lse, {d.R, d.B, d.H, d.N, d.L}))
        throw std::invalid_argument("pyvf._core: lse must have shape (R, B, H, N, L)");
}

// A kernel's status as an exception: MemoryError, or ValueError naming what is not finite.
template <typename T> void raise_status(int status, const std::string& what, const char* name) {
    if (status == kOutOfMemory) {
        PyErr_SetString(PyExc_MemoryError, (what + ": not enough memory for the kernel's work buffers").c_str());
        throw py::error_already_set();
    }
    if (status == kConvNonFiniteDw) name = "dw";
    if (status == kConvNonFiniteDb) name = "db";
    if (status != kOk)
        throw py::value_error(what + ": " + name + " is not finite: it overflowed " +
                              (sizeof(T) == 4 ? "float32" : "float64") +
                              " (inputs too large for the dtype; rescale them, or use float64)");
}

template <typename T, bool PLAIN>
void forward(Arr<T> o, Arr<double> lse, Arr<T> q, Arr<T> k, Arr<T> v, double scale) {
    const AttnDims d = dims_of(q);
    attn_shapes(d, lse, {k, v, o});
    T* po = o.mutable_data();
    double* pl = lse.mutable_data();
    const T *pq = q.data(), *pk = k.data(), *pv = v.data();
    raise_status<T>(nogil([&] {
        return PLAIN ? attn_forward_plain<T>(po, pl, pq, pk, pv, d, (T)scale)
                     : attn_forward<T>(po, pl, pq, pk, pv, d, (T)scale);
    }), "branching_attention", "a logit scale * (q . k)");
}

template <typename T, bool PLAIN>
void backward(Arr<T> dq, Arr<T> dk, Arr<T> dv, Arr<double> lse, Arr<T> q, Arr<T> k, Arr<T> v,
              Arr<T> o, Arr<T> dout, double scale) {
    const AttnDims d = dims_of(q);
    attn_shapes(d, lse, {k, v, o, dout, dq, dk, dv});
    T *pdq = dq.mutable_data(), *pdk = dk.mutable_data(), *pdv = dv.mutable_data();
    const double* pl = lse.data();
    const T *pq = q.data(), *pk = k.data(), *pv = v.data(), *po = o.data(), *pd = dout.data();
    raise_status<T>(nogil([&] {
        return PLAIN ? attn_backward_plain<T>(pdq, pdk, pdv, pl, pq, pk, pv, po, pd, d, (T)scale)
                     : attn_backward<T>(pdq, pdk, pdv, pl, pq, pk, pv, po, pd, d, (T)scale);
    }), "branching_attention", "a logit scale * (q . k)");
}

// GELU (gelu.cpp): y = gelu(x); dx = dy * gelu'(x); flat, one size, overwritten
template <typename T> void gelu(Arr<T> y, Arr<T> x) {
    if (y.size() != x.size()) throw std::invalid_argument("pyvf._core.gelu: x and y differ in size");
    T* py_ = y.mutable_data();
    py::gil_scoped_release released;
    gelu_forward<T>(py_, x.data(), x.size());
}

template <typename T> void gelu_bwd(Arr<T> dx, Arr<T> dy, Arr<T> x) {
    if (dx.size() != x.size() || dy.size() != x.size())
        throw std::invalid_argument("pyvf._core.gelu_backward: dx, dy and x differ in size");
    T* pdx = dx.mutable_data();
    py::gil_scoped_release released;
    gelu_backward<T>(pdx, dy.data(), x.data(), x.size());
}

// y = exp(x) by the kernels' vectorised exp (for x <= 0), to test its accuracy.
template <typename T> void exp_kernel(Arr<T> y, Arr<T> x) {
    if (x.size() != y.size()) throw std::invalid_argument("pyvf._core.exp: x and y differ in size");
    const T* px = x.data();
    T* py_ = y.mutable_data();
    for (py::ssize_t i = 0; i < x.size(); ++i) py_[i] = exp_scalar<T>(px[i]);
}

// True when every element is finite, allocating nothing (np.isfinite(x).all() would allocate a
// bool array as large as x). Blocks of 64 Ki elements, on the threads from 4 blocks on.
template <typename T> bool all_finite(Arr<T> x) {
    const T* p = x.data();
    const int64_t n = x.size();
    py::gil_scoped_release released;
    constexpr int64_t kBlock = 1 << 16;
    const int64_t blocks = (n + kBlock - 1) / kBlock;
    bool ok = true;
#pragma omp parallel for schedule(static) num_threads(num_threads()) reduction(&& : ok) if (parallel_work(blocks, 4))
    for (int64_t b = 0; b < blocks; ++b) ok = finite_run(p + b * kBlock, std::min(kBlock, n - b * kBlock)) && ok;
    return ok;
}

template <typename T> void nearest(Arr<int64_t> index, Arr<T> sq_dist, Arr<T> x, Arr<T> codes) {
    if (x.ndim() != 2 || codes.ndim() != 2 || x.shape(1) != codes.shape(1) || codes.shape(0) < 1)
        throw std::invalid_argument("pyvf._core.vq_nearest: x (M, D) and codes (K >= 1, D)");
    if (index.ndim() != 1 || sq_dist.ndim() != 1 || index.shape(0) != x.shape(0) || sq_dist.shape(0) != x.shape(0))
        throw std::invalid_argument("pyvf._core.vq_nearest: index and sq_dist must be (M,)");
    int64_t* pi = index.mutable_data();
    T* pd = sq_dist.mutable_data();
    const T *px = x.data(), *pc = codes.data();
    const int64_t M = x.shape(0), K = codes.shape(0), D = x.shape(1);
    py::gil_scoped_release released;
    vq_nearest<T>(pi, pd, px, pc, M, K, D);  // std::bad_alloc: MemoryError
}

// c (nb, M, N) = op(a) @ op(b) [+ bias (N,)] per entry (kernels.h)
template <typename T> void matmul(Arr<T> c, Arr<T> a, Arr<T> b, bool ta, bool tb, std::optional<Arr<T>> bias) {
    if (a.ndim() != 3 || b.ndim() != 3 || c.ndim() != 3) throw py::value_error("pyvf._core.matmul: a, b and c must be 3-D");
    const int64_t nb = a.shape(0), M = a.shape(ta ? 2 : 1), K = a.shape(ta ? 1 : 2), N = b.shape(tb ? 1 : 2);
    const int64_t most = std::numeric_limits<int>::max();  // the register tiles index with int
    if (b.shape(0) != nb || b.shape(tb ? 2 : 1) != K || c.shape(0) != nb || c.shape(1) != M || c.shape(2) != N ||
        (bias && (bias->ndim() != 1 || bias->shape(0) != N)) || M * K > most || K * N > most || M * N > most)
        throw py::value_error("pyvf._core.matmul: the shapes of a, b, c and bias do not agree (or exceed 2^31)");
    T* pc = c.mutable_data();
    const T *pa = a.data(), *pb = b.data(), *pbias = bias ? bias->data() : nullptr;
    raise_status<T>(nogil([&] { return matmul_batched<T>(pc, pa, pb, nb, M, N, K, ta, tb, pbias); }), "matmul", "c");
}

[[noreturn]] void conv_bad(const std::string& what) { throw py::value_error("pyvf._core.conv2d: " + what); }

// The sizes of (x, w, stride, padding); every count the kernels index with int below 2^31.
ConvDims conv_dims(const py::array& x, const py::array& w, int64_t stride, int64_t pt, int64_t pb, int64_t pl,
                   int64_t pr) {
    if (x.ndim() != 4 || w.ndim() != 4 || w.shape(1) != x.shape(1))
        conv_bad("x (B, C, Hi, Wi) and w (Co, C, kh, kw) must be 4-D with the same C");
    ConvDims d{x.shape(0), x.shape(1), x.shape(2), x.shape(3), w.shape(0), w.shape(2), w.shape(3),
               stride,     pt,         pb,         pl,         pr,         0,          0};
    const double most = std::numeric_limits<int>::max();
    auto over = [&](std::initializer_list<int64_t> factors) {  // in double: a product cannot wrap
        double n = 1;
        for (int64_t f : factors) n *= (double)f;
        return n > most;
    };
    if (stride < 1 || std::min({pt, pb, pl, pr}) < 0 || over({stride}) || over({std::max({pt, pb, pl, pr})}))
        conv_bad("stride must be in [1, 2^31), every padding in [0, 2^31)");
    if (d.kh < 1 || d.kw < 1 || d.Hi + pt + pb < d.kh || d.Wi + pl + pr < d.kw)
        conv_bad("w: the kernel must be at least 1x1 and fit the padded image");
    d.Ho = (d.Hi + pt + pb - d.kh) / stride + 1;
    d.Wo = (d.Wi + pl + pr - d.kw) / stride + 1;
    if (over({d.C, d.kh, d.kw}) || over({d.Co}) || over({d.Hi}) || over({d.Wi}) || over({d.Hi, d.Wi}) ||
        over({d.Ho, d.Wo}))
        conv_bad("C*kh*kw, Co, Hi*Wi and Ho*Wo must be below 2^31, the kernel's int indexing");
    return d;
}

void conv_shape(const py::array& a, const char* name, std::initializer_list<int64_t> want) {
    if (!has_shape(a, want)) conv_bad(std::string(name) + " has the wrong shape");
}

template <typename T>
void conv_forward(Arr<T> y, Arr<T> x, Arr<T> w, Arr<T> b, int64_t stride, int64_t pt, int64_t pb, int64_t pl,
                  int64_t pr) {
    const ConvDims d = conv_dims(x, w, stride, pt, pb, pl, pr);
    conv_shape(b, "b", {d.Co});
    conv_shape(y, "y", {d.B, d.Co, d.Ho, d.Wo});
    T* py_ = y.mutable_data();
    const T *px = x.data(), *pw = w.data(), *pbias = b.data();
    raise_status<T>(nogil([&] { return conv2d_forward<T>(py_, px, pw, pbias, d); }), "conv2d_forward", "y");
}

template <typename T>
void conv_backward(Arr<T> dx, Arr<T> dw, Arr<T> db, Arr<T> x, Arr<T> w, Arr<T> dy, int64_t stride, int64_t pt,
                   int64_t pb, int64_t pl, int64_t pr) {
    const ConvDims d = conv_dims(x, w, stride, pt, pb, pl, pr);
    conv_shape(dy, "dy", {d.B, d.Co, d.Ho, d.Wo});
    conv_shape(dx, "dx", {d.B, d.C, d.Hi, d.Wi});
    conv_shape(dw, "dw", {d.Co, d.C, d.kh, d.kw});
    conv_shape(db, "db", {d.Co});
    T *pdx = dx.mutable_data(), *pdw = dw.mutable_data(), *pdb = db.mutable_data();
    const T *px = x.data(), *pw = w.data(), *pdy = dy.data();
    raise_status<T>(nogil([&] { return conv2d_backward<T>(pdx, pdw, pdb, px, pw, pdy, d); }), "conv2d_backward", "dx");
}

py::arg nc(const char* name) { return py::arg(name).noconvert(); }  // no cast, no copy

template <typename T> void bind_dtype(py::module_& m) {
    m.def("conv2d_forward", &conv_forward<T>,
          "y (B, Co, Ho, Wo) = conv2d(x (B, C, Hi, Wi), w (Co, C, kh, kw)) + b (Co,), overwritten", nc("y"), nc("x"),
          nc("w"), nc("b"), py::arg("stride"), py::arg("pt"), py::arg("pb"), py::arg("pl"), py::arg("pr"));
    m.def("conv2d_backward", &conv_backward<T>, "dx, dw, db (overwritten) of y = conv2d(x, w) + b under the upstream gradient dy",
          nc("dx"), nc("dw"), nc("db"), nc("x"), nc("w"), nc("dy"), py::arg("stride"), py::arg("pt"), py::arg("pb"),
          py::arg("pl"), py::arg("pr"));
    m.def("attn_forward", &forward<T, false>, nc("o"), nc("lse"), nc("q"), nc("k"), nc("v"), py::arg("scale"));
    m.def("attn_forward_plain", &forward<T, true>, nc("o"), nc("lse"), nc("q"), nc("k"), nc("v"), py::arg("scale"));
    m.def("attn_backward", &backward<T, false>, nc("dq"), nc("dk"), nc("dv"), nc("lse"), nc("q"), nc("k"), nc("v"),
          nc("o"), nc("do"), py::arg("scale"));
    m.def("attn_backward_plain", &backward<T, true>, nc("dq"), nc("dk"), nc("dv"), nc("lse"), nc("q"), nc("k"),
          nc("v"), nc("o"), nc("do"), py::arg("scale"));
    m.def("exp", &exp_kernel<T>, nc("y"), nc("x"));
    m.def("all_finite", &all_finite<T>, nc("x"));
    m.def("vq_nearest", &nearest<T>, nc("index"), nc("sq_dist"), nc("x"), nc("codes"));
    m.def("gelu", &gelu<T>, "y = gelu(x), overwritten", nc("y"), nc("x"));
    m.def("gelu_backward", &gelu_bwd<T>, "dx = dy * gelu'(x), overwritten", nc("dx"), nc("dy"), nc("x"));
    m.def("matmul", &matmul<T>, nc("c"), nc("a"), nc("b"), py::arg("ta"), py::arg("tb") = false,
          nc("bias") = py::none());
}

// What this CPU and its operating system can run (cpuid, xgetbv); called from the baseline module.
py::dict cpu_features() {
    py::dict f;
#if defined(__x86_64__) || defined(__i386__)
    __builtin_cpu_init();
    f["avx2"] = (bool)__builtin_cpu_supports("avx2");
    f["fma"] = (bool)__builtin_cpu_supports("fma");
    f["avx512f"] = (bool)__builtin_cpu_supports("avx512f");
    f["avx512dq"] = (bool)__builtin_cpu_supports("avx512dq");
    f["avx512bw"] = (bool)__builtin_cpu_supports("avx512bw");
    f["avx512vl"] = (bool)__builtin_cpu_supports("avx512vl");
#endif
    return f;
}

}  // namespace

// One module per instruction-set path (CMakeLists.txt): PYVF_MODULE is _core_<path>.
PYBIND11_MODULE(PYVF_MODULE, m) {
    m.doc() = "pyvf compiled kernels for one instruction-set path (pyvf._core picks the module; "
              "use the functions in pyvf, which check their arguments)";
    m.attr("path") = PYVF_PATH_NAME;
    m.def("cpu_features", &cpu_features, "what the CPU supports: {feature: bool} (x86-64; empty elsewhere)");
    bind_dtype<float>(m);
    bind_dtype<double>(m);
    m.def("num_threads", &num_threads, "threads the kernels use (OpenMP; 1 without OpenMP)");
    m.def("set_num_threads", &set_num_threads, py::arg("n"));
    m.def("set_force_parallel", [](bool on) { g_force_parallel.store(on); }, py::arg("on"),
          "tests only: while on, every kernel call with any work runs on the threads (no size threshold)");
    m.def("force_parallel", []() { return g_force_parallel.load(); });
    m.attr("simd_bytes") = kVecBytes;
#ifdef PYVF_OPENMP
    m.attr("openmp") = true;
#else
    m.attr("openmp") = false;
#endif
}
