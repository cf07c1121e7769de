// Adam / AdamW, one fused pass over a parameter p, its moments m and v and its gradient g
// (docs/math.md §4; pyvf/train/optim.py says the update and its two eps conventions):
//
//     m' = b1 m + (1 - b1) g
//     v' = b2 v + ((1 - b2) g) g
//     torch:  u = a (m' / (sqrt(v') / sbc2 + eps))        a = lr / bc1, sbc2 = sqrt(bc2)
//     keras:  u = (m' a) / (sqrt(v') + eps)                a = lr sqrt(bc2) / bc1
//     p' = p decay - u   (decayed parameters)   or   p - u
//
// Each operation rounds once, in the written order, in the parameters' dtype: the same
// operations NumPy's array expressions perform one by one, so the result is bitwise the
// NumPy formula's (tests/test_optim.py holds it to that). This file is compiled with
// -ffp-contract=off (CMakeLists.txt): a fused multiply-add would round b1 m + c1 g once instead
// of three times. Elementwise, so bitwise the same for any thread count.
//
// Why a kernel: NumPy evaluated the update as ten array expressions, each a pass over memory
// with a fresh temporary, on one core: 0.8 s of a 34 s paper-size transformer step, the same on
// 2 threads as on 1. Here it is one pass (two with the check), on every thread, over every
// tensor of the step at once.
#include "optim.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <utility>
#include <vector>

#include "threads.h"

namespace pyvf {

namespace {

constexpr int64_t kBlock = 1 << 14;  // elements a thread takes at a time

template <typename T> struct Update {
    T p, m, v;
};

// K: the Keras convention; D: decayed. Compile-time, so that each loop below is one straight
// loop without branches, for the vectoriser
template <typename T, bool K, bool D> inline Update<T> update(T p, T m, T v, T g, const AdamScalars<T>& s) {
    const T m1 = m * s.b1 + s.c1 * g;
    const T v1 = v * s.b2 + (s.c2 * g) * g;
    const T u = K ? (m1 * s.a) / (std::sqrt(v1) + s.eps) : s.a * (m1 / (std::sqrt(v1) / s.sbc2 + s.eps));
    const T p1 = (D ? p * s.decay : p) - u;
    return {p1, m1, v1};
}

// Whether every update of elements [lo, hi) is finite. |x| <= max is false for inf and NaN; an
// integer OR vectorises (a float sum would not: its order is fixed without -ffast-math).
template <typename T, bool K, bool D>
bool check_run(const T* p, const T* m, const T* v, const T* g, int64_t lo, int64_t hi, const AdamScalars<T>& s) {
    const T big = std::numeric_limits<T>::max();
    int bad = 0;
    for (int64_t i = lo; i < hi; ++i) {
        const Update<T> r = update<T, K, D>(p[i], m[i], v[i], g[i], s);
        bad |= !(std::fabs(r.p) <= big) | !(std::fabs(r.m) <= big) | !(std::fabs(r.v) <= big);
    }
    return !bad;
}

template <typename T, bool K, bool D>
void apply_run(T* __restrict p, T* __restrict m, T* __restrict v, const T* __restrict g, int64_t lo, int64_t hi,
               const AdamScalars<T>& s) {
    for (int64_t i = lo; i < hi; ++i) {
        const Update<T> r = update<T, K, D>(p[i], m[i], v[i], g[i], s);
        p[i] = r.p;
        m[i] = r.m;
        v[i] = r.v;
    }
}

}  // namespace

namespace {

// f(i, tensor i, lo, hi) for every block [lo, hi) of kBlock elements of every tensor, on the
// threads: the whole update is one parallel region, however many tensors. A paper codebook has
// 342, most of them small; with a region (and a Python call) each, its optimiser ran only 3.4x
// faster on 16 threads than on 1, and one call for all of them was 20% faster on 2 threads.
template <typename T, typename F> void each_block(const AdamTensor<T>* t, int64_t count, F f) {
    std::vector<std::pair<int64_t, int64_t>> tasks;  // (tensor, first element), in tensor order
    for (int64_t i = 0; i < count; ++i)
        for (int64_t lo = 0; lo < t[i].n; lo += kBlock) tasks.emplace_back(i, lo);
    const int64_t nt = static_cast<int64_t>(tasks.size());
    RegionEnd end;
#pragma omp parallel num_threads(num_threads()) if (parallel_work(nt, 2))
    {
#pragma omp for schedule(static) nowait
        for (int64_t k = 0; k < nt; ++k) {
            const auto [i, lo] = tasks[k];
            f(i, t[i], lo, std::min(t[i].n, lo + kBlock));
        }
        end.arrive();
    }
}

}  // namespace

template <typename T> void adam_check(const AdamTensor<T>* t, int64_t count, const AdamScalars<T>& s, bool* ok) {
    std::vector<char> bad(count, 0);
    each_block(t, count, [&](int64_t i, const AdamTensor<T>& a, int64_t lo, int64_t hi) {
        const auto run = s.keras ? (a.decayed ? check_run<T, true, true> : check_run<T, true, false>)
                                 : (a.decayed ? check_run<T, false, true> : check_run<T, false, false>);
        if (!run(a.p, a.m, a.v, a.g, lo, hi, s)) {
#pragma omp atomic write
            bad[i] = 1;
        }
    });
    for (int64_t i = 0; i < count; ++i) ok[i] = !bad[i];
}

template <typename T> void adam_apply(const AdamTensor<T>* t, int64_t count, const AdamScalars<T>& s) {
    each_block(t, count, [&](int64_t, const AdamTensor<T>& a, int64_t lo, int64_t hi) {
        const auto run = s.keras ? (a.decayed ? apply_run<T, true, true> : apply_run<T, true, false>)
                                 : (a.decayed ? apply_run<T, false, true> : apply_run<T, false, false>);
        run(a.p, a.m, a.v, a.g, lo, hi, s);
    });
}

// ---------------------------------------------------------------------------------------
// Gradient clipping's two passes (pyvf/train/optim.py clip_grad_norm): the sum of squares in
// float64 and the rescaling.
//
// sum_squares: sum of x_i^2 in double, and max |x_i|. The sum is the same for any thread count:
// each block of kBlock elements is summed alone, in 8 double lanes then the lanes in order, and
// the blocks' sums are added in order afterwards. A float32 x squared in double neither
// overflows nor underflows (2^256 and 2^-298 are in range); a float64 x beyond 1e+-100 is
// rescaled by the caller instead.
// Error: |computed - exact| <= (kBlock / W + W + n / kBlock) u sum, u = 2^-53 (the three levels
// of the sum), below 1e-12 relative for a billion elements.
template <typename T> void sum_squares(const T* x, int64_t n, double* amax, double* sumsq) {
    const int64_t blocks = (n + kBlock - 1) / kBlock;
    std::vector<double> part(blocks), top(blocks);
    RegionEnd end;
#pragma omp parallel num_threads(num_threads()) if (parallel_work(blocks, 2))
    {
#pragma omp for schedule(static) nowait
        for (int64_t b = 0; b < blocks; ++b) {
            const int64_t lo = b * kBlock, hi = std::min(n, lo + kBlock);
            constexpr int L = 8;  // lanes: independent sums the compiler keeps in registers
            double acc[L] = {}, mx[L] = {};
            int64_t i = lo;
            for (; i + L <= hi; i += L)
                for (int l = 0; l < L; ++l) {
                    const double y = static_cast<double>(x[i + l]);
                    acc[l] += y * y;
                    mx[l] = std::max(mx[l], std::fabs(y));
                }
            for (int l = 0; i < hi; ++i, ++l) {
                const double y = static_cast<double>(x[i]);
                acc[l] += y * y;
                mx[l] = std::max(mx[l], std::fabs(y));
            }
            double t = 0, m = 0;
            for (int l = 0; l < L; ++l) {
                t += acc[l];
                m = std::max(m, mx[l]);
            }
            part[b] = t;
            top[b] = m;
        }
        end.arrive();
    }
    double t = 0, m = 0;
    for (int64_t b = 0; b < blocks; ++b) {
        t += part[b];
        m = std::max(m, top[b]);
    }
    *sumsq = t;
    *amax = m;
}

// x *= c in place, c already rounded to T (as NumPy's g *= c rounds a Python float).
template <typename T> void scale_by(T* x, int64_t n, T c) {
    const int64_t blocks = (n + kBlock - 1) / kBlock;
    RegionEnd end;
#pragma omp parallel num_threads(num_threads()) if (parallel_work(blocks, 2))
    {
#pragma omp for schedule(static) nowait
        for (int64_t b = 0; b < blocks; ++b) {
            const int64_t lo = b * kBlock, hi = std::min(n, lo + kBlock);
            for (int64_t i = lo; i < hi; ++i) x[i] *= c;
        }
        end.arrive();
    }
}

template void adam_check<float>(const AdamTensor<float>*, int64_t, const AdamScalars<float>&, bool*);
template void adam_check<double>(const AdamTensor<double>*, int64_t, const AdamScalars<double>&, bool*);
template void adam_apply<float>(const AdamTensor<float>*, int64_t, const AdamScalars<float>&);
template void adam_apply<double>(const AdamTensor<double>*, int64_t, const AdamScalars<double>&);
template void sum_squares<float>(const float*, int64_t, double*, double*);
template void sum_squares<double>(const double*, int64_t, double*, double*);
template void scale_by<float>(float*, int64_t, float);
template void scale_by<double>(double*, int64_t, double);

}  // namespace pyvf
