// Branching attention kernels (SPEC.md §2).
//
// Shapes: q, k, v, o, do are (R, B, H, N, L, dh), C order; block (r, i) of head (b, h) is the
// (L, dh) matrix at ((((r*B + b)*H + h)*N + i) * L*dh. lse is (R, B, H, N, L) float64.
//
// Which keys a query sees. Query block (r, i) attends, every key of each block fully:
//     trunk blocks (0, j) for j < i,   and its own block (r, i).
// For the trunk (r = 0) that is blocks 0..i (block-causal); for a branch r >= 1 it is the
// strictly earlier trunk blocks and branch r's own block i. Every other key is excluded
// exactly: it is never computed, not given a -1e4 logit. So the work is the attended blocks
// only: N(N+1)/2 block pairs for the trunk and for each branch, against (R*N)^2 dense.
//
// Forward (attn_forward): one task per query block, an online softmax over its key blocks
// (FlashAttention): running max m and sum l per query row, accumulator acc (L, dh) rescaled
// by exp(m_old - m_new) at each block. Extra memory: k transposed block by block (as large
// as k), lse, and per thread s (L, L), acc (L, dh): O(T*dh), never O(T^2), T = R*N*L.
//
// Backward (attn_backward): one task per head (b, h), so that every dk, dv, dq block is
// written by one thread in a fixed order (bitwise reproducible, no atomics). For each key
// block, for each query block that attends it: P^T = exp(scale*K Q^T - lse) recomputed from
// the saved lse, dV += P^T dO, dP^T = V dO^T, dS^T = P^T * (dP^T - D) with D = rowsum(dO*O),
// dK += scale dS^T Q, dQ += scale dS K. Extra memory: per thread q and do of one head
// transposed, D, lse split in two, three (L, L) buffers: O(T*dh).
//
// Precision of the float32 path: every dot product (q.k, p.v and the backward products) is
// accumulated in float32, in increasing index order, with FMA where the CPU has it; the
// running max and the exp are float32; the softmax denominator l and lse are float64. lse is
// kept in float64 because with unscaled logits of size 1e6 one float32 ulp of lse is 0.06,
// i.e. a 6% error in every recomputed probability; the backward splits it into a float32
// hi + lo pair so that (s - hi) - lo is exact where it matters. The error this gives is
// measured by tools/bench_attention.py and bounded in tests/test_attention.py.
//
// Test: tests/test_attention.py (NumPy dense reference, torch, finite differences, the
// plain loops below). Benchmark: python tools/bench_attention.py.
#include "branching_attention.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#ifdef PYVF_OPENMP
#include <omp.h>
#endif

#include "simd.h"

namespace pyvf {

int num_threads() {
#ifdef PYVF_OPENMP
    return omp_get_max_threads();
#else
    return 1;
#endif
}

void set_num_threads(int n) {
#ifdef PYVF_OPENMP
    omp_set_num_threads(n);
#else
    (void)n;
#endif
}

namespace {

// Does query block (r, i) attend key block (kr, j)?
inline bool attends(int64_t r, int64_t i, int64_t kr, int64_t j) {
    return (kr == 0 && j < i) || (kr == r && j == i);
}

struct Layout {
    int64_t R, B, H, N, L, dh;
    explicit Layout(AttnDims d) : R(d.R), B(d.B), H(d.H), N(d.N), L(d.L), dh(d.dh) {}
    // index of block (r, b, h, i); multiply by L*dh for q/k/v, by L for lse
    int64_t blk(int64_t r, int64_t b, int64_t h, int64_t i) const { return ((r * B + b) * H + h) * N + i; }
    int64_t bs() const { return L * dh; }
    int64_t nblk() const { return R * B * H * N; }
};

// s[0:n) *= scale; returns max s; sets bad if any scaled logit is NaN or +-inf.
template <typename T> T scale_rowmax(T* s, int64_t n, T scale, int& bad) {
    using V = typename Simd<T>::V;
    using I = typename Simd<T>::I;
    constexpr int W = Simd<T>::W;
    V mx = vset1<T>(-std::numeric_limits<T>::infinity());
    I nonfinite = I{};
    int64_t j = 0;
    for (; j + W <= n; j += W) {
        const V x = vload<T>(s + j) * scale;
        vstore<T>(s + j, x);
        mx = vmax<T>(mx, x);
        nonfinite |= (x - x) != 0;  // inf - inf and NaN - NaN are NaN
    }
    T m = hmax<T>(mx);
    for (int i = 0; i < W; ++i) bad |= nonfinite[i] != 0;
    for (; j < n; ++j) {
        s[j] *= scale;
        bad |= !std::isfinite(s[j]);
        m = s[j] > m ? s[j] : m;
    }
    return m;
}

// s[0:n) <- exp(s - m); returns the sum (lanes summed in T, then the lanes in order).
template <typename T> T exp_rowsum(T* s, int64_t n, T m) {
    using V = typename Simd<T>::V;
    constexpr int W = Simd<T>::W;
    V acc = V{};
    int64_t j = 0;
    for (; j + W <= n; j += W) {
        const V p = exp_vec(vload<T>(s + j) - m);
        vstore<T>(s + j, p);
        acc += p;
    }
    T sum = hsum<T>(acc);
    for (; j < n; ++j) {
        s[j] = exp_scalar<T>(s[j] - m);
        sum += s[j];
    }
    return sum;
}

}  // namespace

// =========================================================================================
// Fast forward

template <typename T>
int attn_forward(T* o, double* lse, const T* q, const T* k, const T* v, AttnDims dims, T scale) {
    const Layout d(dims);
    const int64_t L = d.L, dh = d.dh, bs = d.bs(), N = d.N, R = d.R, H = d.H;
    const int64_t nblk = d.nblk();

    // kt: every key block transposed, (dh, L), so that s = q @ kt is a row-major product.
    std::vector<T> kt(nblk * bs);
#pragma omp parallel for schedule(static)
    for (int64_t x = 0; x < nblk; ++x) transpose(kt.data() + x * bs, k + x * bs, (int)L, (int)dh);

    int status = kAttnOk;
#pragma omp parallel
    {
        std::vector<T> s(L * L), acc(L * dh), m(L);  // per thread
        std::vector<double> l(L);
        int bad = 0;
        // one task per query block (r, b, h, i); the views with the most key blocks first
#pragma omp for schedule(dynamic, 1)
        for (int64_t t = 0; t < nblk; ++t) {
            const int64_t i = N - 1 - t % N;
            int64_t rest = t / N;
            const int64_t r = rest % R;
            rest /= R;
            const int64_t h = rest % H, b = rest / H;
            const int64_t qx = d.blk(r, b, h, i);
            const T* Q = q + qx * bs;  // (L, dh)

            std::fill(m.begin(), m.end(), -std::numeric_limits<T>::infinity());
            std::fill(l.begin(), l.end(), 0.0);
            std::fill(acc.begin(), acc.end(), T(0));
            for (int64_t j = 0; j <= i; ++j) {
                // key blocks: trunk 0..i-1, then the query's own block (r, i)
                const int64_t kx = j < i ? d.blk(0, b, h, j) : qx;
                gemm<T, false>((int)L, (int)L, (int)dh, Q, dh, kt.data() + kx * bs, L, s.data(), L);  // s = q k^T (L, L)
                for (int64_t a = 0; a < L; ++a) {
                    T* sa = s.data() + a * L;
                    const T mx = scale_rowmax<T>(sa, L, scale, bad);  // s = scale * q.k
                    const T mnew = std::max(m[a], mx);
                    const T c = exp_scalar<T>(m[a] - mnew);  // 0 at the first block (m = -inf)
                    const T rowsum = exp_rowsum<T>(sa, L, mnew);  // s <- p = exp(s - m_new)
                    l[a] = l[a] * c + rowsum;
                    m[a] = mnew;
                    T* acc_a = acc.data() + a * dh;
                    for (int64_t e = 0; e < dh; ++e) acc_a[e] *= c;
                }
                gemm<T, true>((int)L, (int)dh, (int)L, s.data(), L, v + kx * bs, dh, acc.data(), dh);  // acc += p v
            }
            T* O = o + qx * bs;
            double* lse_q = lse + qx * L;
            for (int64_t a = 0; a < L; ++a) {
                const T la = (T)l[a];
                for (int64_t e = 0; e < dh; ++e) O[a * dh + e] = acc[a * dh + e] / la;
                lse_q[a] = (double)m[a] + std::log(l[a]);
            }
        }
        if (bad) {
#pragma omp atomic write
            status = kAttnLogitOverflow;
        }
    }
    return status;
}

// =========================================================================================
// Fast backward

template <typename T>
int attn_backward(T* dq, T* dk, T* dv, const double* lse, const T* q, const T* k, const T* v,
                  const T* o, const T* dout, AttnDims dims, T scale) {
    using V = typename Simd<T>::V;
    constexpr int W = Simd<T>::W;
    const Layout d(dims);
    const int64_t L = d.L, dh = d.dh, bs = d.bs(), N = d.N, R = d.R, H = d.H, B = d.B;
    const int64_t RN = R * N;

    int status = kAttnOk;
#pragma omp parallel
    {
        // per thread, for one head: q and do transposed per block (dh, L); D and the lse
        // hi/lo split per query row; s, dp, ds (L, L).
        std::vector<T> qt(RN * bs), dot(RN * bs), D(RN * L), lhi(RN * L), llo(RN * L);
        std::vector<T> s(L * L), dp(L * L), ds(L * L);
        int bad = 0;
#pragma omp for schedule(dynamic, 1)
        for (int64_t bh = 0; bh < B * H; ++bh) {
            const int64_t b = bh / H, h = bh % H;
            for (int64_t r = 0; r < R; ++r)
                for (int64_t i = 0; i < N; ++i) {
                    const int64_t x = d.blk(r, b, h, i), y = r * N + i;
                    transpose(qt.data() + y * bs, q + x * bs, (int)L, (int)dh);
                    transpose(dot.data() + y * bs, dout + x * bs, (int)L, (int)dh);
                    for (int64_t a = 0; a < L; ++a) {
                        const T* oa = o + x * bs + a * dh;
                        const T* da = dout + x * bs + a * dh;
                        double acc = 0;  // D = rowsum(do * o), a dot product of length dh
                        for (int64_t e = 0; e < dh; ++e) acc += (double)da[e] * (double)oa[e];
                        D[y * L + a] = (T)acc;
                        const double lx = lse[x * L + a];
                        lhi[y * L + a] = (T)lx;
                        llo[y * L + a] = (T)(lx - (double)(T)lx);
                    }
                    std::fill(dq + x * bs, dq + (x + 1) * bs, T(0));
                }

            for (int64_t kr = 0; kr < R; ++kr)
                for (int64_t j = 0; j < N; ++j) {
                    const int64_t kx = d.blk(kr, b, h, j);
                    const T* K = k + kx * bs;   // (L, dh)
                    const T* Vb = v + kx * bs;  // (L, dh)
                    T* dK = dk + kx * bs;
                    T* dV = dv + kx * bs;
                    std::fill(dK, dK + bs, T(0));
                    std::fill(dV, dV + bs, T(0));

                    // one query block (r, i) that attends key block (kr, j)
                    auto visit = [&](int64_t r, int64_t i) {
                        const int64_t x = d.blk(r, b, h, i), y = r * N + i;
                        // forward: p = exp(scale * q.k - lse); here transposed, rows = keys
                        gemm<T, false>((int)L, (int)L, (int)dh, K, dh, qt.data() + y * bs, L, s.data(), L);  // s = k q^T (Lk, Lq)
                        const T* hi = lhi.data() + y * L;
                        const T* lo = llo.data() + y * L;
                        const T* Dy = D.data() + y * L;
                        for (int64_t a = 0; a < L; ++a) {
                            T* sa = s.data() + a * L;
                            scale_rowmax<T>(sa, L, scale, bad);  // s = scale * k.q (same bits as the forward)
                            int64_t c = 0;
                            for (; c + W <= L; c += W)
                                vstore<T>(sa + c, exp_vec((vload<T>(sa + c) - vload<T>(hi + c)) - vload<T>(lo + c)));
                            for (; c < L; ++c) sa[c] = exp_scalar<T>((sa[c] - hi[c]) - lo[c]);
                        }
                        // forward: o = p v, so dv = p^T do
                        gemm<T, true>((int)L, (int)dh, (int)L, s.data(), L, dout + x * bs, dh, dV, dh);
                        // dp = do v^T, here transposed: dp^T = v do^T (Lk, Lq)
                        gemm<T, false>((int)L, (int)L, (int)dh, Vb, dh, dot.data() + y * bs, L, dp.data(), L);
                        // softmax backward: ds = p * (dp - D), D = rowsum(do * o); times scale
                        for (int64_t a = 0; a < L; ++a) {
                            const T* pa = s.data() + a * L;
                            const T* dpa = dp.data() + a * L;
                            T* dsa = ds.data() + a * L;
                            int64_t c = 0;
                            for (; c + W <= L; c += W) {
                                const V val = vload<T>(pa + c) * (vload<T>(dpa + c) - vload<T>(Dy + c));
                                vstore<T>(dsa + c, val * scale);
                            }
                            for (; c < L; ++c) dsa[c] = pa[c] * (dpa[c] - Dy[c]) * scale;
                        }
                        // forward: s = scale * q k^T, so dk = ds^T q and dq = ds k
                        gemm<T, true>((int)L, (int)dh, (int)L, ds.data(), L, q + x * bs, dh, dK, dh);
                        transpose(dp.data(), ds.data(), (int)L, (int)L);  // dp <- ds (Lq, Lk)
                        gemm<T, true>((int)L, (int)dh, (int)L, dp.data(), L, K, dh, dq + x * bs, dh);
                    };
                    if (kr == 0) {  // a trunk block: trunk views i >= j, branch views i > j
                        for (int64_t i = j; i < N; ++i) visit(0, i);
                        for (int64_t r = 1; r < R; ++r)
                            for (int64_t i = j + 1; i < N; ++i) visit(r, i);
                    } else {  // a branch block: only its own query block
                        visit(kr, j);
                    }
                }
        }
        if (bad) {
#pragma omp atomic write
            status = kAttnLogitOverflow;
        }
    }
    return status;
}

// =========================================================================================
// Plain loops: one query row at a time, every key tested with attends(), double accumulators.

template <typename T>
int attn_forward_plain(T* o, double* lse, const T* q, const T* k, const T* v, AttnDims dims, T scale) {
    const Layout d(dims);
    const int64_t L = d.L, dh = d.dh;
    std::vector<double> logit(d.R * d.N * L), acc(dh);
    for (int64_t b = 0; b < d.B; ++b)
        for (int64_t h = 0; h < d.H; ++h)
            for (int64_t r = 0; r < d.R; ++r)
                for (int64_t i = 0; i < d.N; ++i)
                    for (int64_t a = 0; a < L; ++a) {
                        const int64_t row = d.blk(r, b, h, i) * L + a;  // query row
                        const T* qa = q + row * dh;
                        double m = -std::numeric_limits<double>::infinity();
                        for (int64_t kr = 0; kr < d.R; ++kr)
                            for (int64_t j = 0; j < d.N; ++j) {
                                if (!attends(r, i, kr, j)) continue;
                                for (int64_t c = 0; c < L; ++c) {
                                    const T* kc = k + (d.blk(kr, b, h, j) * L + c) * dh;
                                    double dot = 0;
                                    for (int64_t e = 0; e < dh; ++e) dot += (double)qa[e] * (double)kc[e];
                                    const double x = (double)scale * dot;
                                    if (!std::isfinite(x)) return kAttnLogitOverflow;
                                    logit[(kr * d.N + j) * L + c] = x;
                                    m = std::max(m, x);
                                }
                            }
                        double sum = 0;
                        std::fill(acc.begin(), acc.end(), 0.0);
                        for (int64_t kr = 0; kr < d.R; ++kr)
                            for (int64_t j = 0; j < d.N; ++j) {
                                if (!attends(r, i, kr, j)) continue;
                                for (int64_t c = 0; c < L; ++c) {
                                    const double p = std::exp(logit[(kr * d.N + j) * L + c] - m);
                                    const T* vc = v + (d.blk(kr, b, h, j) * L + c) * dh;
                                    sum += p;
                                    for (int64_t e = 0; e < dh; ++e) acc[e] += p * (double)vc[e];
                                }
                            }
                        for (int64_t e = 0; e < dh; ++e) o[row * dh + e] = (T)(acc[e] / sum);
                        lse[row] = m + std::log(sum);
                    }
    return kAttnOk;
}

template <typename T>
int attn_backward_plain(T* dq, T* dk, T* dv, const double* lse, const T* q, const T* k,
                        const T* v, const T* o, const T* dout, AttnDims dims, T scale) {
    const Layout d(dims);
    const int64_t L = d.L, dh = d.dh, n = d.nblk() * L * dh;
    std::vector<double> gq(n, 0.0), gk(n, 0.0), gv(n, 0.0);
    for (int64_t b = 0; b < d.B; ++b)
        for (int64_t h = 0; h < d.H; ++h)
            for (int64_t r = 0; r < d.R; ++r)
                for (int64_t i = 0; i < d.N; ++i)
                    for (int64_t a = 0; a < L; ++a) {
                        const int64_t row = d.blk(r, b, h, i) * L + a;
                        const T* qa = q + row * dh;
                        const T* da = dout + row * dh;
                        double D = 0;  // rowsum(do * o)
                        for (int64_t e = 0; e < dh; ++e) D += (double)da[e] * (double)o[row * dh + e];
                        for (int64_t kr = 0; kr < d.R; ++kr)
                            for (int64_t j = 0; j < d.N; ++j) {
                                if (!attends(r, i, kr, j)) continue;
                                for (int64_t c = 0; c < L; ++c) {
                                    const int64_t col = d.blk(kr, b, h, j) * L + c;  // key row
                                    const T* kc = k + col * dh;
                                    const T* vc = v + col * dh;
                                    double dot = 0, dp = 0;
                                    for (int64_t e = 0; e < dh; ++e) {
                                        dot += (double)qa[e] * (double)kc[e];
                                        dp += (double)da[e] * (double)vc[e];
                                    }
                                    const double x = (double)scale * dot;
                                    if (!std::isfinite(x)) return kAttnLogitOverflow;
                                    const double p = std::exp(x - lse[row]);
                                    const double ds = p * (dp - D) * (double)scale;
                                    for (int64_t e = 0; e < dh; ++e) {
                                        gv[col * dh + e] += p * (double)da[e];
                                        gk[col * dh + e] += ds * (double)qa[e];
                                        gq[row * dh + e] += ds * (double)kc[e];
                                    }
                                }
                            }
                    }
    for (int64_t x = 0; x < n; ++x) {
        dq[x] = (T)gq[x];
        dk[x] = (T)gk[x];
        dv[x] = (T)gv[x];
    }
    return kAttnOk;
}

#define PYVF_INSTANTIATE(T)                                                                        \
    template int attn_forward<T>(T*, double*, const T*, const T*, const T*, AttnDims, T);          \
    template int attn_backward<T>(T*, T*, T*, const double*, const T*, const T*, const T*,         \
                                  const T*, const T*, AttnDims, T);                                \
    template int attn_forward_plain<T>(T*, double*, const T*, const T*, const T*, AttnDims, T);    \
    template int attn_backward_plain<T>(T*, T*, T*, const double*, const T*, const T*, const T*,   \
                                        const T*, const T*, AttnDims, T);
PYVF_INSTANTIATE(float)
PYVF_INSTANTIATE(double)

}  // namespace pyvf
