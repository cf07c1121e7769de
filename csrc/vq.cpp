// Nearest code (SPEC.md §4): for each row x_m of x (M, D), the index of the nearest row e_k of
// codes (K, D) in squared Euclidean distance, and that distance.
//
// The answer is the argmin of the exact distances d_k = sum_i (x_i - e_i)^2, summed in double
// in increasing i from the given values, ties to the smallest index: not the argmin of the
// published |x|^2 - 2 x.e + |e|^2 in float32, which picks the wrong code once |x| is large
// beside the gaps between codes (the terms cancel).
//
// Algorithm:
//   1. fast scores s_k = |e_k|^2 - 2 x.e_k (d_k - |x|^2), x.e_k by the blocked SIMD gemm in the
//      input dtype, |e_k|^2 in double;
//   2. a rigorous bound on each score's rounding error: a dot product of D terms accumulated in
//      order has |fl(x.e) - x.e| <= gamma_D sum |x_i e_i| <= gamma_D |x| |e_k| (Cauchy-Schwarz),
//      gamma_D = D u / (1 - D u), u the dtype's unit roundoff; so err_k = 2 gamma_D |x| |e_k|
//      plus the double rounding of |e_k|^2 and of the sum, and a factor 2 of margin;
//   3. every code whose interval [s_k - err_k, s_k + err_k] reaches below the smallest upper end
//      min_j (s_j + err_j) may be the nearest: those candidates are re-ranked by their exact
//      distances. Well separated data has one candidate (the exact distance is computed for it
//      anyway, to return it); at large offsets the intervals widen and more codes are re-ranked,
//      up to all of them: slower, never wrong.
// Memory: codes transposed (D, K) and their norms, per thread a block of scores (MB, K).
// Rows are split across threads; each row is computed by one thread in a fixed order, so the
// result is the same for any thread count.
//
// Test: tests/test_vq.py (float64 brute force, cancellation cases, exact ties, duplicated
// codes). Benchmark: python tools/bench_vq.py.
#include "vq.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include "simd.h"

namespace pyvf {

namespace {

template <typename T> constexpr double unit_roundoff();
template <> constexpr double unit_roundoff<float>() { return 0x1p-24; }
template <> constexpr double unit_roundoff<double>() { return 0x1p-53; }

template <typename T> double exact_sq_distance(const T* x, const T* e, int64_t D) {
    double s = 0;
    for (int64_t i = 0; i < D; ++i) {
        const double t = (double)x[i] - (double)e[i];
        s += t * t;
    }
    return s;
}

}  // namespace

template <typename T>
int64_t vq_nearest(int64_t* index, T* sq_dist, const T* x, const T* codes, int64_t M, int64_t K, int64_t D) {
    constexpr int64_t MB = 64;  // rows per block
    const double u = unit_roundoff<T>();
    const double gamma = D * u / (1.0 - D * u);
    const double ud = unit_roundoff<double>();

    std::vector<T> et(D * K);  // codes^T (D, K)
    transpose(et.data(), codes, (int)K, (int)D);
    std::vector<double> e2(K), en(K);  // |e_k|^2, |e_k|
    for (int64_t k = 0; k < K; ++k) {
        double s = 0;
        for (int64_t i = 0; i < D; ++i) s += (double)codes[k * D + i] * (double)codes[k * D + i];
        e2[k] = s;
        en[k] = std::sqrt(s);
    }

    int64_t reranked = 0;  // how many exact distances were computed beyond one per row
    const int64_t nblocks = (M + MB - 1) / MB;
#pragma omp parallel reduction(+ : reranked) if (M * K * D > (1 << 22))
    {
        std::vector<T> s(MB * K);          // x.e for a block of rows (MB, K)
        std::vector<int64_t> cand;
        cand.reserve(16);
#pragma omp for schedule(dynamic, 1)
        for (int64_t blk = 0; blk < nblocks; ++blk) {
            const int64_t m0 = blk * MB, mb = std::min(MB, M - m0);
            gemm<T, false>((int)mb, (int)K, (int)D, x + m0 * D, D, et.data(), K, s.data(), K);  // s = x e^T
            for (int64_t r = 0; r < mb; ++r) {
                const T* xr = x + (m0 + r) * D;
                double x2 = 0;
                for (int64_t i = 0; i < D; ++i) x2 += (double)xr[i] * (double)xr[i];
                const double xn = std::sqrt(x2);
                const T* sr = s.data() + r * K;
                // error of score k: dot product (gamma |x||e|, times 2), |e|^2 in double, the sum
                auto err = [&](int64_t k) {
                    const double dot_bound = gamma * xn * en[k];
                    return 2.0 * (2.0 * dot_bound + (D + 2) * ud * (e2[k] + 2.0 * xn * en[k]));
                };
                double upper = std::numeric_limits<double>::infinity();  // min_k (s_k + err_k)
                for (int64_t k = 0; k < K; ++k) {
                    const double sk = e2[k] - 2.0 * (double)sr[k];
                    upper = std::min(upper, sk + err(k));
                }
                cand.clear();
                for (int64_t k = 0; k < K; ++k) {
                    const double sk = e2[k] - 2.0 * (double)sr[k];
                    if (sk - err(k) <= upper) cand.push_back(k);
                }
                int64_t best = -1;
                double best_d = std::numeric_limits<double>::infinity();
                for (int64_t k : cand) {  // increasing k: a tie keeps the smaller index
                    const double dk = exact_sq_distance(xr, codes + k * D, D);
                    if (dk < best_d) {
                        best_d = dk;
                        best = k;
                    }
                }
                reranked += (int64_t)cand.size() - 1;
                index[m0 + r] = best;
                sq_dist[m0 + r] = (T)best_d;
            }
        }
    }
    return reranked;
}

template int64_t vq_nearest<float>(int64_t*, float*, const float*, const float*, int64_t, int64_t, int64_t);
template int64_t vq_nearest<double>(int64_t*, double*, const double*, const double*, int64_t, int64_t, int64_t);

}  // namespace pyvf
