// Nearest code (SPEC.md §4): for each row x_m of x (M, D), the index of the nearest row e_k of
// codes (K, D) in squared Euclidean distance, and that distance.
//
// The answer is the argmin of the exact distances d_k = sum_i (x_i - e_i)^2, summed in double
// in increasing i from the given values, ties to the smallest index: not the argmin of the
// published |x|^2 - 2 x.e + |e|^2 in float32, which picks the wrong code once |x| is large
// beside the gaps between codes (the terms cancel).
//
// Algorithm:
//   0. x and the codes are shifted by the codes' centroid c (in double, then rounded to the
//      dtype): distances do not change, and vectors far from the origin no longer cancel;
//   1. fast scores s_k = |e'_k|^2 - 2 x'.e'_k (d_k - |x'|^2), x'.e'_k by the blocked SIMD gemm in
//      the input dtype, |e'_k|^2 in double;
//   2. a rigorous bound on each score's rounding error: a dot product of D terms accumulated in
//      order has |fl(x.e) - x.e| <= gamma_D sum |x_i e_i| <= gamma_D |x| |e_k| (Cauchy-Schwarz),
//      gamma_D = D u / (1 - D u), u the dtype's unit roundoff; so err_k = 2 gamma_D |x'| |e'_k|,
//      plus the double roundings, plus what rounding the shifted vectors to the dtype can move
//      the distance (below), and a factor 2 of margin;
//   3. every code whose interval [s_k - err_k, s_k + err_k] reaches below the smallest upper end
//      min_j (s_j + err_j) may be the nearest: those candidates are re-ranked by their exact
//      distances. Well separated data has one candidate (the exact distance is computed for it
//      anyway, to return it); data far from the codes (not just from the origin) widens the
//      intervals and more codes are re-ranked, up to all of them: slower, never wrong.
//   The re-rank reads the original values: exactness never depends on the shift.
// Memory: the shifted codes and their transpose, their norms, per thread a block of shifted
// rows (MB, D) and of scores (MB, K).
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

    // the centroid of the codes: x and the codes are scored shifted by it (distances do not
    // change), so that vectors far from the origin do not cancel in the fast scores
    std::vector<double> c(D, 0.0);
    for (int64_t k = 0; k < K; ++k)
        for (int64_t i = 0; i < D; ++i) c[i] += (double)codes[k * D + i];
    for (int64_t i = 0; i < D; ++i) c[i] /= (double)K;

    std::vector<T> cs(K * D);  // shifted codes, rounded to T
    for (int64_t k = 0; k < K; ++k)
        for (int64_t i = 0; i < D; ++i) cs[k * D + i] = (T)((double)codes[k * D + i] - c[i]);
    std::vector<T> et(D * K);  // shifted codes^T (D, K)
    transpose(et.data(), cs.data(), (int)K, (int)D);
    std::vector<double> e2(K), en(K), esh(K);  // |e'_k|^2, |e'_k| of the rounded shifted codes; |e_k - c|
    for (int64_t k = 0; k < K; ++k) {
        double s = 0, t = 0;
        for (int64_t i = 0; i < D; ++i) {
            s += (double)cs[k * D + i] * (double)cs[k * D + i];
            const double r = (double)codes[k * D + i] - c[i];
            t += r * r;
        }
        e2[k] = s;
        en[k] = std::sqrt(s);
        esh[k] = std::sqrt(t);
    }

    int64_t reranked = 0;  // how many exact distances were computed beyond one per row
    const int64_t nblocks = (M + MB - 1) / MB;
#pragma omp parallel reduction(+ : reranked) if (M * K * D > (1 << 22))
    {
        std::vector<T> xs(MB * D);  // a block of shifted rows
        std::vector<T> s(MB * K);   // x'.e' for the block (MB, K)
        std::vector<double> score(K), err(K);
        std::vector<int64_t> cand;
        cand.reserve(16);
#pragma omp for schedule(dynamic, 1)
        for (int64_t blk = 0; blk < nblocks; ++blk) {
            const int64_t m0 = blk * MB, mb = std::min(MB, M - m0);
            for (int64_t r = 0; r < mb; ++r)
                for (int64_t i = 0; i < D; ++i) xs[r * D + i] = (T)((double)x[(m0 + r) * D + i] - c[i]);
            gemm<T, false>((int)mb, (int)K, (int)D, xs.data(), D, et.data(), K, s.data(), K);  // s = x' e'^T
            for (int64_t r = 0; r < mb; ++r) {
                const T* xr = x + (m0 + r) * D;
                double x2 = 0, xt = 0;  // |x'|^2 of the rounded shifted row; |x - c| exactly shifted
                for (int64_t i = 0; i < D; ++i) {
                    x2 += (double)xs[r * D + i] * (double)xs[r * D + i];
                    const double t = (double)xr[i] - c[i];
                    xt += t * t;
                }
                const double xn = std::sqrt(x2);
                xt = std::sqrt(xt);
                const T* sr = s.data() + r * K;
                // score_k = |e'_k|^2 - 2 x'.e'_k = d'_k - |x'|^2, d'_k the distance of the rounded
                // shifted vectors. Its error against d_k - |x'|^2 (d_k the true distance):
                //   the dot product: gamma |x'| |e'_k| (times 2), the double sums: (D + 2) ud (...);
                //   the rounding of the shift: |sqrt d'_k - sqrt d_k| <= eta_k = 2 u (|x - c| + |e_k - c|)
                //   (factor 2: the double subtraction before the rounding), so
                //   |d'_k - d_k| <= eta_k (2 sqrt d_k + eta_k), and sqrt d_k <= sqrt d'_k + eta_k
                //   <= |x'| + |e'_k| + eta_k (triangle inequality: no square root per code).
                // Everything times 2 for margin. Vectorised over k; upper = min_k (score_k + err_k).
                const double g2 = 2.0 * gamma * xn, cd = (D + 2) * ud, u2 = 2.0 * u;
                using VD = Simd<double>::V;
                constexpr int WD = Simd<double>::W;
                VD vup = vset1<double>(std::numeric_limits<double>::infinity());
                int64_t k = 0;
                auto bound = [&](double e2k, double enk, double eshk, double sk, double& errk) {
                    const double fast = g2 * enk + cd * (e2k + 2.0 * xn * enk + x2);
                    const double eta = u2 * (xt + eshk);
                    errk = 2.0 * (fast + eta * (2.0 * (xn + enk + eta) + eta));
                    return sk + errk;
                };
                for (; k < K; ++k) score[k] = e2[k] - 2.0 * (double)sr[k];
                for (k = 0; k + WD <= K; k += WD) {
                    const VD e2k = vload<double>(&e2[k]), enk = vload<double>(&en[k]), eshk = vload<double>(&esh[k]);
                    const VD fast = g2 * enk + cd * (e2k + 2.0 * xn * enk + x2);
                    const VD eta = u2 * (xt + eshk);
                    const VD ek = 2.0 * (fast + eta * (2.0 * (xn + enk + eta) + eta));
                    vstore<double>(&err[k], ek);
                    const VD up = vload<double>(&score[k]) + ek;
                    vup = up < vup ? up : vup;
                }
                double upper = vup[0];
                for (int i = 1; i < WD; ++i) upper = std::min(upper, (double)vup[i]);
                for (; k < K; ++k) upper = std::min(upper, bound(e2[k], en[k], esh[k], score[k], err[k]));
                cand.clear();
                for (int64_t k = 0; k < K; ++k)
                    if (score[k] - err[k] <= upper) cand.push_back(k);
                int64_t best = -1;
                double best_d = std::numeric_limits<double>::infinity();
                for (int64_t k : cand) {  // exact distances of the original values; a tie keeps the smaller k
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
