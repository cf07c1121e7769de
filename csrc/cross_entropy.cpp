// Softmax cross-entropy with label smoothing, forward and backward (docs/math.md §3;
// pyvf/nn/losses.py has the checks and the published semantics).
//
// M rows of V logits x (C order), targets t (int64 in [0, V), checked by the caller), label
// smoothing eps in [0, 1]; the target distribution q_i = (1 - eps) [i = t] + eps / V.
//   forward   m = max_i x_i;  z_i = x_i - m in T (<= 0);  s = sum_i exp(z_i), exp in T (simd.h's
//             exp_vec, about 1 ulp), the sum in double;  ls = log(s) in double, so log p_i =
//             z_i - ls and
//                 loss = -sum_i q_i log p_i = (1 - eps) (ls - z_t) + eps (ls - sum_i z_i / V),
//             in double from the double differences x_i - m, rounded once. Saved per row: m (T)
//             and ls (double); the logits themselves are the caller's.
//   backward  dx_i = (p_i - q_i) dloss in T, p_i = exp(z_i - ls) with the argument rounded to
//             T, into the subnormals (as NumPy's exp); q_i rounded to T from double.
// The NumPy version (logits - max, exp, sum, log, subtract; exp again in the backward) made a
// temporary of the logits' size at each of its eight passes, on one core, and summed in T:
// 2.5x torch's time on (2048, 1024), and a larger error.
// Threads: one row is one task's work in a fixed order, so every output is bitwise the same for
// any thread count. Test: tests/test_model_layers.py (torch float64, finite differences, hard
// cases: logits spanning the dtype, ties, V = 1). Benchmark: pyvf bench accuracy (cross_entropy).
#include "cross_entropy.h"

#include <algorithm>
#include <cmath>

#include "simd.h"
#include "threads.h"

namespace pyvf {

namespace {

template <typename T> using V = typename Simd<T>::V;
using VD = Simd<double>::V;

template <typename T> inline T row_max(const T* x, int64_t n) {
    constexpr int W = Simd<T>::W;
    int64_t i = 0;
    T m = n ? x[0] : T(0);
    if (n >= W) {
        V<T> vm = vload<T>(x);
        for (i = W; i + W <= n; i += W) vm = vmax<T>(vm, vload<T>(x + i));
        for (int l = 0; l < W; ++l) m = std::max(m, vm[l]);
    }
    for (; i < n; ++i) m = std::max(m, x[i]);
    return m;
}

// (sum_i exp(x_i - m), sum_i (x_i - m)) in double: the exp of the T differences, the second sum of
// the double ones
template <typename T> inline void exp_sums(const T* x, int64_t n, T m, double& s, double& zs) {
    constexpr int W = Simd<T>::W, WD = Simd<double>::W;
    VD se[W / WD] = {}, sz[W / WD] = {};
    int64_t i = 0;
    for (; i + W <= n; i += W) {
        const V<T> xv = vload<T>(x + i);
        VD e[W / WD], xd[W / WD];
        widen_to_double<T>(exp_vec(xv - m), e);
        widen_to_double<T>(xv, xd);
        for (int q = 0; q < W / WD; ++q) {
            se[q] += e[q];
            sz[q] += xd[q] - (double)m;
        }
    }
    s = 0, zs = 0;
    for (int q = 0; q < W / WD; ++q) {
        s += hsum<double>(se[q]);
        zs += hsum<double>(sz[q]);
    }
    for (; i < n; ++i) {
        s += (double)exp_scalar<T>(x[i] - m);
        zs += (double)x[i] - (double)m;
    }
}

// p = exp((x - m) - ls) of one element, by the vector code (so a tail element and a target get
// the bits a vector lane would)
template <typename T> inline T prob(T x, T m, T ls) { return exp_vec_subnormal<T>(vset1<T>((x - m) - ls))[0]; }

}  // namespace

template <typename T>
void cross_entropy_forward(T* loss, T* rowmax, double* logsum, const T* x, const int64_t* targets, int64_t M,
                           int64_t n, double eps) {
    RegionEnd end;
#pragma omp parallel num_threads(num_threads()) if (parallel_work(M * n, 16384))
    {
#pragma omp for schedule(static) nowait
        for (int64_t r = 0; r < M; ++r) {
            const T* xr = x + r * n;
            const T m = row_max(xr, n);
            double s, zs;
            exp_sums(xr, n, m, s, zs);
            const double ls = std::log(s), zt = (double)xr[targets[r]] - (double)m;
            const double l = (1.0 - eps) * (ls - zt) + (eps ? eps * (ls - zs / (double)n) : 0.0);
            loss[r] = (T)l;
            rowmax[r] = m;
            logsum[r] = ls;
        }
        end.arrive();
    }
}

template <typename T>
void cross_entropy_backward(T* dx, const T* dloss, const T* x, const T* rowmax, const double* logsum,
                            const int64_t* targets, int64_t M, int64_t n, double eps) {
    constexpr int W = Simd<T>::W;
    const T qo = (T)(eps / (double)n), qt = (T)((1.0 - eps) + eps / (double)n);
    RegionEnd end;
#pragma omp parallel num_threads(num_threads()) if (parallel_work(M * n, 16384))
    {
#pragma omp for schedule(static) nowait
        for (int64_t r = 0; r < M; ++r) {
            const T *xr = x + r * n, m = rowmax[r], ls = (T)logsum[r], dl = dloss[r];
            T* o = dx + r * n;
            int64_t i = 0;
            for (; i + W <= n; i += W)
                vstore<T>(o + i, (exp_vec_subnormal<T>((vload<T>(xr + i) - m) - ls) - qo) * dl);
            for (; i < n; ++i) o[i] = (prob(xr[i], m, ls) - qo) * dl;
            const int64_t t = targets[r];
            o[t] = (prob(xr[t], m, ls) - qt) * dl;
        }
        end.arrive();
    }
}

template void cross_entropy_forward<float>(float*, float*, double*, const float*, const int64_t*, int64_t, int64_t,
                                           double);
template void cross_entropy_forward<double>(double*, double*, double*, const double*, const int64_t*, int64_t,
                                            int64_t, double);
template void cross_entropy_backward<float>(float*, const float*, const float*, const float*, const double*,
                                            const int64_t*, int64_t, int64_t, double);
template void cross_entropy_backward<double>(double*, const double*, const double*, const double*, const double*,
                                             const int64_t*, int64_t, int64_t, double);

}  // namespace pyvf
