// Nearest code (docs/math.md §4): for each row x_m of x (M, D), the index of the nearest row e_k of
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
//      the input dtype on codes packed in panels of 2 vectors, |e'_k|^2 in double;
//   2. a rigorous bound err on every score's error, one per row: a dot product of D terms
//      accumulated in order has |fl(x.e) - x.e| <= gamma_D |x| |e| (Cauchy-Schwarz),
//      gamma_D = D u / (1 - D u), u the dtype's unit roundoff, taken with the largest |e'_k|;
//      plus the double roundings, what rounding the shifted vectors to the dtype can move the
//      distance, the dtype's underflow (D smallest subnormals), and a factor 2 of margin;
//   3. every code with s_k <= min_j s_j + 2 err may be the nearest: those candidates are
//      re-ranked by their exact distances (one on well separated data; up to all of them far
//      from the codes: slower, never wrong; all where a score overflows).
//   The re-rank reads the original values: exactness never depends on the shift. Its exact
//   distance is sum_i (x_i - e_i)^2 in double, every operation rounded once (vq_exact.cpp, no
//   fused multiply-add, so the same on every path); where the vectors' largest component is beyond
//   2^+-400 (only float64 inputs get there) both are first multiplied by a power of two, so the
//   comparison neither overflows nor underflows. The returned distance is that sum rounded to
//   the dtype: inf exactly when the true distance exceeds the dtype's range (float32 vectors
//   ~1e20 apart, float64 ~1e154), 0 when it is below the smallest subnormal.
// Memory: the packed shifted codes and one double per code; per thread a block of shifted rows
// (64, D), its scores against a chunk of at most 2048 codes, and each row's candidates (at most
// K). Each row is computed by one thread in a fixed order: the same for any thread count.
// Test: tests/test_vq.py. Benchmark: pyvf bench vq.
#include "kernels.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <new>
#include <utility>
#include <vector>

#include "buffers.h"
#include "simd.h"
#include "threads.h"

namespace pyvf {

namespace {

template <typename T> constexpr double unit_roundoff();
template <> constexpr double unit_roundoff<float>() { return 0x1p-24; }
template <> constexpr double unit_roundoff<double>() { return 0x1p-53; }

}  // namespace

template <typename T>
void vq_nearest(int64_t* index, T* sq_dist, const T* x, const T* codes, int64_t M, int64_t K, int64_t D) {
    using V = typename Simd<T>::V;
    using VD = Simd<double>::V;
    constexpr int W = Simd<T>::W, WD = Simd<double>::W;
    constexpr int64_t NB = 2 * W;    // codes per packed panel (the gemm's widest tile)
    // rows per block: 64, or fewer where that leaves threads idle (the paper codebook's 128 rows
    // made 2 blocks for 16 threads), at least 8; each row's answer is the exact argmin over a
    // candidate set that always holds it, whatever the block, so the result does not depend on MB
    const int64_t nthr = num_threads();
    const int64_t MB = std::clamp<int64_t>(((M + 4 * nthr - 1) / (4 * nthr) + 7) / 8 * 8, 8, 64);
    const int64_t KC = std::min<int64_t>(((K + NB - 1) / NB) * NB, 2048);  // codes per chunk, a multiple of NB
    const int64_t npanel = (K + NB - 1) / NB, Kp = npanel * NB;
    const double u = unit_roundoff<T>();
    const double gamma = D * u / (1.0 - D * u);
    const double ud = unit_roundoff<double>();
    const double tiny = (double)std::numeric_limits<T>::denorm_min();

    // the centroid of the codes: x and the codes are scored shifted by it (distances do not
    // change), so that vectors far from the origin do not cancel in the fast scores. The mean
    // as a sum of e/K: no overflow even for codes near the dtype's largest value.
    std::vector<double> c(D, 0.0);
    for (int64_t k = 0; k < K; ++k)
        for (int64_t i = 0; i < D; ++i) c[i] += (double)codes[k * D + i] / (double)K;

    // the shifted codes, rounded to T, transposed and packed in panels of NB codes: panel p is
    // (D, NB), contiguous, so the gemm streams it; codes past K are zero and never read back.
    // Per code only |e'_k|^2 is kept; the error bound uses the largest |e'_k| and |e_k - c|.
    std::vector<T> et(Kp * D, T(0));
    std::vector<double> e2(Kp, 0.0);
    double en_max = 0, e2_max = 0, esh_max = 0;
    for (int64_t k = 0; k < K; ++k) {
        T* panel = et.data() + (k / NB) * D * NB + k % NB;
        double s = 0, t = 0;
        for (int64_t i = 0; i < D; ++i) {
            const double r = (double)codes[k * D + i] - c[i];
            const T cs = (T)r;
            panel[i * NB] = cs;
            s += (double)cs * (double)cs;
            t += r * r;
        }
        e2[k] = s;
        e2_max = std::max(e2_max, s);
        esh_max = std::max(esh_max, t);
    }
    en_max = std::sqrt(e2_max);
    esh_max = std::sqrt(esh_max);

    const int64_t nblocks = (M + MB - 1) / MB;
    int status = kOk;
#pragma omp parallel num_threads(num_threads()) if (parallel_work(M * K * D, (1 << 22) + 1))
    {
        std::vector<T> xs, s;  // a block of shifted rows (MB, D); its scores against a chunk (MB, KC)
        std::vector<double> thr2(MB), best(MB);
        std::vector<std::vector<std::pair<double, int64_t>>> cand(MB);  // per row: (score, k)
        std::vector<char> wild(MB);
        bool ok = false;
        PYVF_TRY_ALLOC(status, xs.resize(MB * D); s.resize(MB * KC); ok = true)
#pragma omp for schedule(dynamic, 1) nowait
        for (int64_t blk = 0; blk < nblocks; ++blk) {
            if (!ok) continue;
            try {
            const int64_t m0 = blk * MB, mb = std::min(MB, M - m0);
            for (int64_t r = 0; r < mb; ++r) {
                const T* xr = x + (m0 + r) * D;
                double x2 = 0, xt = 0;  // |x'|^2 of the rounded shifted row; |x - c| exactly shifted
                for (int64_t i = 0; i < D; ++i) {
                    const double t = (double)xr[i] - c[i];
                    const T xsi = (T)t;
                    xs[r * D + i] = xsi;
                    x2 += (double)xsi * (double)xsi;
                    xt += t * t;
                }
                const double xn = std::sqrt(x2);
                xt = std::sqrt(xt);
                // score_k = |e'_k|^2 - 2 x'.e'_k = d'_k - |x'|^2, d'_k the distance of the rounded
                // shifted vectors. Its error against d_k - |x'|^2 (d_k the true distance), with
                // the largest code norms (one bound per row, valid for every code):
                //   the dot product: 2 gamma |x'| |e'|, the double sums: (D + 2) ud (...);
                //   the rounding of the shift: |sqrt d'_k - sqrt d_k| <= eta = 2 u (|x - c| + |e - c|)
                //   (factor 2: the double subtraction before the rounding), so
                //   |d'_k - d_k| <= eta (2 sqrt d_k + eta), and sqrt d_k <= |x'| + |e'| + eta.
                // Everything times 2 for margin. The nearest code has score <= min_k score_k + err,
                // so every code with score_k <= min + 2 err is a candidate.
                // Underflow: each of the D products may also lose up to the dtype's smallest
                // subnormal (absolute), and each rounded shifted component half of it.
                const double fast = 2.0 * gamma * xn * en_max + (D + 2) * ud * (e2_max + 2.0 * xn * en_max + x2)
                                    + 2.0 * D * tiny;
                const double eta = 2.0 * u * (xt + esh_max) + std::sqrt((double)D) * tiny;
                const double err = 2.0 * (fast + eta * (2.0 * (xn + en_max + eta) + eta));
                thr2[r] = 2.0 * err;
                best[r] = std::numeric_limits<double>::infinity();
                cand[r].clear();
                wild[r] = !std::isfinite(err);  // overflow: every code is a candidate
            }
            for (int64_t k0 = 0; k0 < K; k0 += KC) {
                const int64_t kc = std::min(KC, K - k0), np = (kc + NB - 1) / NB;
                for (int64_t p = 0; p < np; ++p)  // s = x' e'^T for this chunk, panel by panel
                    gemm<T, false>((int)mb, (int)NB, (int)D, xs.data(), D, et.data() + (k0 / NB + p) * D * NB, NB,
                                   s.data() + p * NB, KC);
                for (int64_t r = 0; r < mb; ++r) {
                    if (wild[r]) continue;
                    const T* sr = s.data() + r * KC;
                    const double* e2c = e2.data() + k0;
                    // this chunk's smallest score; chk: NaN or inf anywhere (an overflowed product)
                    VD vmin = vset1<double>(best[r]), chk = {};
                    int64_t k = 0;
                    for (; k + WD <= kc; k += WD) {
                        VD sk;
                        for (int l = 0; l < WD; ++l) sk[l] = (double)sr[k + l];
                        const VD sc = vload<double>(e2c + k) - 2.0 * sk;
                        chk += sc * 0.0;
                        vmin = sc < vmin ? sc : vmin;
                    }
                    double mn = vmin[0];
                    for (int l = 1; l < WD; ++l) mn = std::min(mn, (double)vmin[l]);
                    double tail = 0;
                    for (; k < kc; ++k) {
                        const double sc = e2c[k] - 2.0 * (double)sr[k];
                        tail += sc * 0.0;
                        mn = std::min(mn, sc);
                    }
                    if (!(hsum<double>(chk) + tail == 0)) {
                        wild[r] = 1;
                        continue;
                    }
                    best[r] = mn;
                    const double thr = mn + thr2[r];
                    for (k = 0; k < kc; ++k) {  // candidates so far, in increasing k
                        const double sc = e2c[k] - 2.0 * (double)sr[k];
                        if (sc <= thr) cand[r].push_back({sc, k0 + k});
                    }
                }
            }
            for (int64_t r = 0; r < mb; ++r) {
                const T* xr = x + (m0 + r) * D;
                auto& cr = cand[r];
                const double thr = best[r] + thr2[r];
                int64_t n = 0;  // keep the candidates under the final threshold
                if (!wild[r])
                    for (const auto& sk : cr)
                        if (sk.first <= thr) cr[n++] = sk;
                const int64_t ncand = wild[r] ? K : n;
                auto code_of = [&](int64_t j) { return wild[r] ? j : cr[j].second; };
                // exact distances of the original values, in double, a tie keeps the smaller k;
                // where they would overflow or underflow double, scaled by a power of two first
                double mx = 0;
                for (int64_t i = 0; i < D; ++i) mx = std::max(mx, std::fabs((double)xr[i]));
                for (int64_t j = 0; j < ncand; ++j)
                    for (int64_t i = 0; i < D; ++i) mx = std::max(mx, std::fabs((double)codes[code_of(j) * D + i]));
                const int ex = mx > 0 ? std::ilogb(mx) : 0;
                const bool scaled = ex > 400 || ex < -400;
                int64_t bi = -1;
                double bd = std::numeric_limits<double>::infinity();
                for (int64_t j = 0; j < ncand; ++j) {
                    const int64_t k = code_of(j);
                    const double dk = scaled ? exact_sq_distance_scaled(xr, codes + k * D, D, -ex)
                                             : exact_sq_distance(xr, codes + k * D, D);
                    if (bi < 0 || dk < bd) {
                        bd = dk;
                        bi = k;
                    }
                }
                index[m0 + r] = bi;
                sq_dist[m0 + r] = scaled ? (T)std::ldexp(bd, 2 * ex) : (T)bd;
            }
            } catch (const std::bad_alloc&) {
#pragma omp atomic write
                status = kOutOfMemory;
            }
        }
    }
    if (status != kOk) throw std::bad_alloc();
}

template void vq_nearest<float>(int64_t*, float*, const float*, const float*, int64_t, int64_t, int64_t);
template void vq_nearest<double>(int64_t*, double*, const double*, const double*, int64_t, int64_t, int64_t);

}  // namespace pyvf
