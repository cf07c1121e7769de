// Branching attention kernels (docs/math.md §2).
//
// Shapes (kernels.h): block (r, i) of head (b, h) is the (L, dh) matrix at ((((r*B + b)*H + h)*N
// + i) * L*dh. Query block (r, i) attends every key of trunk blocks (0, j), j < i, and of its own
// block (r, i) (attends() below); every other key is never computed (exact exclusion), so the work
// is N(N+1)/2 block pairs for the trunk and for each branch, against (R*N)^2 dense.
//
// Everything is computed transposed, keys as rows and queries as columns (s^T = k q^T):
// then each query's softmax statistics live in a column and the max, exp, sum and rescale
// are elementwise vector operations across L queries at once, with no horizontal reductions.
//
// Forward (attn_forward): one task per query block, an online softmax over its key blocks
// (FlashAttention): running max m and sum l per query, accumulator acc (Lq, dh) rescaled by
// c = exp(m_old - m_new) at each block, acc += p v, with p^T read transposed by the gemm.
// Extra memory: lse and per thread q^T, s^T (L, L), acc: O(T), never O(T^2), T = R*N*L.
//
// Backward (attn_backward): one task per head (b, h), so that every dk, dv, dq block is
// written by one thread in a fixed order (bitwise reproducible, no atomics). For each key
// block, for each query block that attends it: p^T = exp(scale * k q^T - lse) recomputed from
// the saved lse, dv += p^T do, dp^T = v do^T, ds^T = p^T * (dp^T - D) with D = rowsum(do * o),
// dk += scale ds^T q, dq += scale (ds^T)^T k. Extra memory: per thread q and do of one head
// transposed, D, lse split in two, three (L, L) buffers: O(T*dh).
//
// Precision of the float32 path: every dot product (q.k, p.v and the backward products) is
// accumulated in float32, in increasing index order, with FMA where the CPU has it; the
// running max, the exp and the softmax denominator l are float32; lse is computed and kept
// in float64 (m + log l): with logits of size 1e6 one float32 ulp of lse is a 6% error in every
// recomputed probability. The backward splits it into a float32 hi + lo pair, (s - hi) - lo.
//
// Test: tests/test_attention.py. Benchmark: pyvf bench attention.
#include "kernels.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <new>
#include <vector>

#include "buffers.h"
#include "simd.h"
#include "threads.h"

namespace pyvf {

namespace {

// Does query block (r, i) attend key block (kr, j)?
inline bool attends(int64_t r, int64_t i, int64_t kr, int64_t j) {
    return (kr == 0 && j < i) || (kr == r && j == i);
}

// Threads only when the attended block pairs hold at least ~4M multiply-adds (a wake-up costs us).
inline bool worth_threads(const AttnDims& d) {
    const double pairs = (double)d.B * d.H * d.R * d.N * (d.N + 1) / 2;  // attended block pairs
    return parallel_work((int64_t)(pairs * d.L * d.L * d.dh), 4000000);
}

// Elementwise helpers on one row of n values (a vector loop and a scalar tail). In the
// kernels a row holds one key's logits against L queries, so per-query statistics (max,
// sum, rescale factor) are elementwise across rows: no horizontal reductions.

// x[0:n) *= scale; chk += x * 0, which stays 0 for finite x and becomes NaN for inf or NaN.
template <typename T> inline void row_scale(T* x, int64_t n, T scale, typename Simd<T>::V& chk) {
    constexpr int W = Simd<T>::W;
    int64_t c = 0;
    for (; c + W <= n; c += W) {
        const typename Simd<T>::V y = vload<T>(x + c) * scale;
        vstore<T>(x + c, y);
        chk += y * T(0);
    }
    for (; c < n; ++c) {
        x[c] *= scale;
        chk[0] += x[c] * T(0);
    }
}

// x[0:n) *= scale and m[0:n) = max(m, x), in one pass (row_scale, then row_max)
template <typename T> inline void row_scale_max(T* x, T* m, int64_t n, T scale, typename Simd<T>::V& chk) {
    constexpr int W = Simd<T>::W;
    int64_t c = 0;
    for (; c + W <= n; c += W) {
        const typename Simd<T>::V y = vload<T>(x + c) * scale;
        vstore<T>(x + c, y);
        chk += y * T(0);
        vstore<T>(m + c, vmax<T>(vload<T>(m + c), y));
    }
    for (; c < n; ++c) {
        x[c] *= scale;
        chk[0] += x[c] * T(0);
        m[c] = x[c] > m[c] ? x[c] : m[c];
    }
}

// p[0:n) = exp(x - a) and s[0:n) += p, in one pass (row_exp, then row_add)
template <typename T> inline void row_exp_sum(T* p, const T* x, const T* a, T* s, int64_t n) {
    constexpr int W = Simd<T>::W;
    int64_t c = 0;
    for (; c + W <= n; c += W) {
        const typename Simd<T>::V e = exp_vec(vload<T>(x + c) - vload<T>(a + c));
        vstore<T>(p + c, e);
        vstore<T>(s + c, vload<T>(s + c) + e);
    }
    for (; c < n; ++c) {
        p[c] = exp_scalar<T>(x[c] - a[c]);
        s[c] += p[c];
    }
}

// p[0:n) = exp((x - a) - b)   (b = nullptr: exp(x - a)); x <= a + b up to rounding
template <typename T> inline void row_exp(T* p, const T* x, const T* a, const T* b, int64_t n) {
    constexpr int W = Simd<T>::W;
    int64_t c = 0;
    for (; c + W <= n; c += W) {
        typename Simd<T>::V y = vload<T>(x + c) - vload<T>(a + c);
        if (b) y = y - vload<T>(b + c);
        vstore<T>(p + c, exp_vec(y));
    }
    for (; c < n; ++c) p[c] = exp_scalar<T>(b ? (x[c] - a[c]) - b[c] : x[c] - a[c]);
}

// y[0:n) += x
template <typename T> inline void row_add(T* y, const T* x, int64_t n) {
    constexpr int W = Simd<T>::W;
    int64_t c = 0;
    for (; c + W <= n; c += W) vstore<T>(y + c, vload<T>(y + c) + vload<T>(x + c));
    for (; c < n; ++c) y[c] += x[c];
}

// y[0:n) *= x
template <typename T> inline void row_mul(T* y, const T* x, int64_t n) {
    constexpr int W = Simd<T>::W;
    int64_t c = 0;
    for (; c + W <= n; c += W) vstore<T>(y + c, vload<T>(y + c) * vload<T>(x + c));
    for (; c < n; ++c) y[c] *= x[c];
}

}  // namespace

// A block of L tokens is processed in tiles of at most kTile queries times kTile keys, so the
// per-thread buffers are O(kTile^2 + kTile*dh) whatever L is. For L <= kTile (the model's 64) a
// tile is the whole block.
constexpr int64_t kTile = 256;

// =========================================================================================
// Fast forward

template <typename T>
int attn_forward(T* o, double* lse, const T* q, const T* k, const T* v, AttnDims d, T scale) {
    const int64_t L = d.L, dh = d.dh, bs = d.bs(), N = d.N, R = d.R, H = d.H;
    const int64_t TQ = std::min(L, kTile), TK = TQ;
    const int64_t ntile = (L + TQ - 1) / TQ;  // query tiles per block
    const int64_t ntask = d.nblk() * ntile;

    int status = kOk;
#pragma omp parallel num_threads(num_threads()) if (worth_threads(d))
    {
        // per thread: q^T (dh, TQ); s^T, then p^T (TK, TQ); the accumulator acc (TQ, dh); per
        // query: running max m, new max mn, rescale factor c, sum l, this tile's sum ls
        std::vector<T> qt, st, acc, m, mn, c, l, ls;
        bool ok = false;
        PYVF_TRY_ALLOC(status, qt.resize(dh * TQ); st.resize(TK * TQ); acc.resize(TQ * dh); m.resize(TQ);
                       mn.resize(TQ); c.resize(TQ); l.resize(TQ); ls.resize(TQ); ok = true)
        typename Simd<T>::V chk = {};
        // one task per query tile of a block (r, b, h, i); the views with the most key blocks first
#pragma omp for schedule(dynamic, 1) nowait
        for (int64_t t = 0; t < ntask; ++t) {
            if (!ok) continue;
            const int64_t qa = (t % ntile) * TQ, nq = std::min(TQ, L - qa);  // the tile's queries
            int64_t rest = t / ntile;
            const int64_t i = N - 1 - rest % N;
            rest /= N;
            const int64_t r = rest % R;
            rest /= R;
            const int64_t h = rest % H, b = rest / H;
            const int64_t qx = d.blk(r, b, h, i);
            transpose(qt.data(), q + qx * bs + qa * dh, (int)nq, (int)dh);  // q^T (dh, nq)

            std::fill(m.begin(), m.end(), -std::numeric_limits<T>::infinity());
            std::fill(l.begin(), l.end(), T(0));
            std::fill(acc.begin(), acc.end(), T(0));
            for (int64_t j = 0; j <= i; ++j) {
                // key blocks: trunk 0..i-1, then the query's own block (r, i)
                const int64_t kx = j < i ? d.blk(0, b, h, j) : qx;
                for (int64_t ka = 0; ka < L; ka += TK) {
                    const int64_t nk = std::min(TK, L - ka);
                    const T* K = k + kx * bs + ka * dh;  // (nk, dh)
                    // s^T = k q^T (nk, nq): row a holds key a's logits against every query
                    gemm<T, false>((int)nk, (int)nq, (int)dh, K, dh, qt.data(), nq, st.data(), nq);
                    std::copy(m.begin(), m.end(), mn.begin());
                    for (int64_t a = 0; a < nk; ++a)  // s = scale * q.k; m_new = max(m, max_k s)
                        row_scale_max<T>(st.data() + a * nq, mn.data(), nq, scale, chk);
                    row_exp<T>(c.data(), m.data(), mn.data(), nullptr, nq);  // c = exp(m - m_new), 0 at the first tile
                    std::fill(ls.begin(), ls.end(), T(0));
                    for (int64_t a = 0; a < nk; ++a) {  // p = exp(s - m_new); ls = sum_k p
                        T* pa = st.data() + a * nq;
                        row_exp_sum<T>(pa, pa, mn.data(), ls.data(), nq);
                    }
                    row_mul<T>(l.data(), c.data(), nq);  // l = l * c + sum_k p
                    row_add<T>(l.data(), ls.data(), nq);
                    std::swap(m, mn);
                    for (int64_t a = 0; a < nq; ++a) {  // acc *= c, row by row
                        const T ca = c[a];
                        for (int64_t e = 0; e < dh; ++e) acc[a * dh + e] *= ca;
                    }
                    // acc += p v = (p^T)^T v: p^T is what we hold, read transposed by the gemm
                    gemm<T, true, true>((int)nq, (int)dh, (int)nk, st.data(), nq, v + kx * bs + ka * dh, dh,
                                        acc.data(), dh);
                }
            }
            T* O = o + qx * bs + qa * dh;
            double* lse_q = lse + qx * L + qa;
            for (int64_t a = 0; a < nq; ++a) {
                for (int64_t e = 0; e < dh; ++e) O[a * dh + e] = acc[a * dh + e] / l[a];  // o = acc / l
                lse_q[a] = (double)m[a] + std::log((double)l[a]);
            }
        }
        if (hsum<T>(chk) != 0) {  // a lane of chk is NaN
#pragma omp atomic write
            status = kAttnLogitOverflow;
        }
    }
    return status;
}

// =========================================================================================
// Fast backward

// How many groups the key blocks of one head are split into: enough tasks (B*H*G >= 16) for
// every thread even when B*H is small, at most 8 and at most the R*N key blocks. It depends
// on the shape only, never on the thread count, so the result stays bitwise the same for any
// thread count. Group g > 0 accumulates its dq into a buffer of its own (one head's dq), added
// to dq in the order g = 1, 2, ... after all groups finish: (G-1)*B*H*R*N*L*dh extra elements,
// at most 7 times dq (and none when B*H >= 16).
inline int64_t key_groups(const AttnDims& d) {
    const int64_t bh = d.B * d.H;
    int64_t g = bh >= 16 ? 1 : (16 + bh - 1) / bh;
    return std::max<int64_t>(1, std::min<int64_t>({g, 8, d.R * d.N}));
}

// group[x] for each key block x = kr*N + j of a head: balanced by the number of query blocks
// that attend it (trunk block j: (N - j) trunk + (R-1)(N-1-j) branch views; a branch block: 1),
// largest first, each to the least loaded group (ties: the lower group).
inline std::vector<int> assign_groups(const AttnDims& d, int64_t G) {
    const int64_t nk = d.R * d.N;
    std::vector<int64_t> cost(nk), order(nk);
    for (int64_t kr = 0; kr < d.R; ++kr)
        for (int64_t j = 0; j < d.N; ++j)
            cost[kr * d.N + j] = kr == 0 ? (d.N - j) + (d.R - 1) * (d.N - 1 - j) : 1;
    for (int64_t x = 0; x < nk; ++x) order[x] = x;
    std::stable_sort(order.begin(), order.end(), [&](int64_t a, int64_t b) { return cost[a] > cost[b]; });
    std::vector<int64_t> load(G, 0);
    std::vector<int> group(nk);
    for (int64_t x : order) {
        const int64_t g = std::min_element(load.begin(), load.end()) - load.begin();
        group[x] = (int)g;
        load[g] += cost[x];
    }
    return group;
}

template <typename T>
int attn_backward(T* dq, T* dk, T* dv, const double* lse, const T* q, const T* k, const T* v,
                  const T* o, const T* dout, AttnDims d, T scale) {
    using V = typename Simd<T>::V;
    constexpr int W = Simd<T>::W;
    const int64_t L = d.L, dh = d.dh, bs = d.bs(), N = d.N, R = d.R, H = d.H, B = d.B;
    const int64_t RN = R * N, head = RN * bs;  // one head's elements in q (and dq)
    const int64_t TQ = std::min(L, kTile), TK = TQ;
    const int64_t G = key_groups(d);
    std::vector<int> group;
    RawBuf<T> dq_extra;  // (B*H, G-1, head): the dq of groups 1..G-1, each block zeroed by its task
    PYVF_OR_OOM(group = assign_groups(d, G); dq_extra.resize((size_t)(B * H * (G - 1) * head)))

    int status = kOk;
    const bool threads = worth_threads(d);
#pragma omp parallel num_threads(num_threads()) if (threads)
    {
        // per thread, for one head: q and do transposed per block (dh, L); D = rowsum(do * o)
        // and the lse hi/lo split per query; p^T, dp^T, ds^T (TK, TQ).
        std::vector<T> qt, dot, D, lhi, llo, st, dpt, dst;
        bool ok = false;
        PYVF_TRY_ALLOC(status, qt.resize(head); dot.resize(head); D.resize(RN * L); lhi.resize(RN * L);
                       llo.resize(RN * L); st.resize(TK * TQ); dpt.resize(TK * TQ); dst.resize(TK * TQ); ok = true)
        V chk = V{};
        // one task per (head, group of its key blocks)
#pragma omp for schedule(dynamic, 1) nowait
        for (int64_t task = 0; task < B * H * G; ++task) {
            if (!ok) continue;
            const int64_t bh = task / G, g = task % G;
            const int64_t b = bh / H, h = bh % H;
            // where this group's dq of block x = (r, b, h, i), y = r*N + i, goes: dq itself for
            // group 0, else block y of the group's own buffer (one head, (R, N, L, dh))
            T* extra = g == 0 ? nullptr : dq_extra.data() + (bh * (G - 1) + g - 1) * head;
            auto dq_block = [&](int64_t x, int64_t y) { return extra ? extra + y * bs : dq + x * bs; };
            for (int64_t r = 0; r < R; ++r)
                for (int64_t i = 0; i < N; ++i) {
                    const int64_t x = d.blk(r, b, h, i), y = r * N + i;
                    transpose(qt.data() + y * bs, q + x * bs, (int)L, (int)dh);
                    transpose(dot.data() + y * bs, dout + x * bs, (int)L, (int)dh);
                    for (int64_t a = 0; a < L; ++a) {
                        const T* oa = o + x * bs + a * dh;
                        const T* da = dout + x * bs + a * dh;
                        // D = rowsum(do * o), summed in T in increasing e, as the gemm sums dp = do . v
                        T acc = 0;
                        for (int64_t e = 0; e < dh; ++e) acc += da[e] * oa[e];
                        D[y * L + a] = acc;
                        const double lx = lse[x * L + a];
                        lhi[y * L + a] = (T)lx;
                        llo[y * L + a] = (T)(lx - (double)(T)lx);
                    }
                    std::fill(dq_block(x, y), dq_block(x, y) + bs, T(0));
                }

            for (int64_t kr = 0; kr < R; ++kr)
                for (int64_t j = 0; j < N; ++j) {
                    if (group[kr * N + j] != g) continue;
                    const int64_t kx = d.blk(kr, b, h, j);
                    T* dK = dk + kx * bs;
                    T* dV = dv + kx * bs;
                    std::fill(dK, dK + bs, T(0));
                    std::fill(dV, dV + bs, T(0));

                    // one query block (r, i) that attends key block (kr, j), tile by tile
                    auto visit = [&](int64_t r, int64_t i) {
                        const int64_t x = d.blk(r, b, h, i), y = r * N + i;
                        for (int64_t ka = 0; ka < L; ka += TK)
                            for (int64_t qa = 0; qa < L; qa += TQ) {
                                const int64_t nk = std::min(TK, L - ka), nq = std::min(TQ, L - qa);
                                const T* K = k + kx * bs + ka * dh;    // (nk, dh)
                                const T* Vb = v + kx * bs + ka * dh;   // (nk, dh)
                                const T* Qt = qt.data() + y * bs + qa;  // q^T (dh, nq), leading dimension L
                                // forward: p = exp(scale * q.k - lse); here transposed, rows = keys
                                gemm<T, false>((int)nk, (int)nq, (int)dh, K, dh, Qt, L, st.data(), nq);  // s^T = k q^T
                                for (int64_t a = 0; a < nk; ++a) {
                                    T* pa = st.data() + a * nq;
                                    row_scale<T>(pa, nq, scale, chk);  // same bits as the forward's logits
                                    row_exp<T>(pa, pa, lhi.data() + y * L + qa, llo.data() + y * L + qa, nq);  // p = exp((s - hi) - lo)
                                }
                                // forward: o = p v, so dv = p^T do
                                gemm<T, true>((int)nk, (int)dh, (int)nq, st.data(), nq, dout + x * bs + qa * dh, dh,
                                              dV + ka * dh, dh);
                                // dp = do v^T, here transposed: dp^T = v do^T (nk, nq)
                                gemm<T, false>((int)nk, (int)nq, (int)dh, Vb, dh, dot.data() + y * bs + qa, L, dpt.data(), nq);
                                // softmax backward: ds = p * (dp - D), D = rowsum(do * o); times scale
                                const T* Dy = D.data() + y * L + qa;
                                for (int64_t a = 0; a < nk; ++a) {
                                    const T* pa = st.data() + a * nq;
                                    const T* dpa = dpt.data() + a * nq;
                                    T* dsa = dst.data() + a * nq;
                                    int64_t c = 0;
                                    for (; c + W <= nq; c += W) {
                                        const V val = vload<T>(pa + c) * (vload<T>(dpa + c) - vload<T>(Dy + c));
                                        vstore<T>(dsa + c, val * scale);
                                    }
                                    for (; c < nq; ++c) dsa[c] = pa[c] * (dpa[c] - Dy[c]) * scale;
                                }
                                // forward: s = scale * q k^T, so dk = ds^T q and dq = ds k = (ds^T)^T k
                                gemm<T, true>((int)nk, (int)dh, (int)nq, dst.data(), nq, q + x * bs + qa * dh, dh,
                                              dK + ka * dh, dh);
                                gemm<T, true, true>((int)nq, (int)dh, (int)nk, dst.data(), nq, K, dh,
                                                    dq_block(x, y) + qa * dh, dh);
                            }
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
        if (hsum<T>(chk) != 0) {  // a lane of chk is NaN
#pragma omp atomic write
            status = kAttnLogitOverflow;
        }
        // dq += the other groups' dq, in group order; one task per (head, block), so each dq
        // element has one writer. The barrier (met by every thread or none: G is the shape's)
        // waits for every group and makes status the same for every thread here; one group
        // (16 or more heads): the region's end is the only barrier.
        if (G > 1) {
#pragma omp barrier
            if (status == kOk) {
#pragma omp for schedule(static) nowait
                for (int64_t t = 0; t < B * H * RN; ++t) {
                    const int64_t bh = t / RN, y = t % RN;
                    const int64_t b = bh / H, h = bh % H, x = d.blk(y / N, b, h, y % N);
                    for (int64_t g = 1; g < G; ++g)
                        row_add<T>(dq + x * bs, dq_extra.data() + (bh * (G - 1) + g - 1) * head + y * bs, bs);
                }
            }
        }
    }
    return status;
}

// =========================================================================================
// Plain loops: one query row at a time, every key tested with attends(), double accumulators.

template <typename T>
int attn_forward_plain(T* o, double* lse, const T* q, const T* k, const T* v, AttnDims d, T scale) {
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
    return kOk;
}

template <typename T>
int attn_backward_plain(T* dq, T* dk, T* dv, const double* lse, const T* q, const T* k,
                        const T* v, const T* o, const T* dout, AttnDims d, T scale) {
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
    return kOk;
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
