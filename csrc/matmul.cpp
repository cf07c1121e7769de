// pyvf's GEMM: c (nb, M, N) = op(a) @ op(b) [+ bias] per batch entry, float32 and float64: the
// products of the transformer's linear layers and tied logits and of the codebook's AttnBlock
// (pyvf/nn/layers.py matmul; its reference is the expression itself, matmul_numpy).
// Not NumPy's BLAS: its threads spin on the cores the kernels' threads run on, and its results
// change with its thread count for some shapes.
//
// Tasks of (entry, kMatRows rows, kMatCols columns), each writing its own block of c; inside a
// task k runs in chunks of kMatDepth, each continuing the last one's sums (CONT). A chunk's panels
// of a and b are packed in the register tile's order (contiguous loads, b's panel in L2); the edges
// past the last packed tile run unpacked. Every element of c is one sum in increasing k, or, split
// along k, its parts' sums added in order: bitwise the same for any thread count. A transposed b
// is first copied into (K, N) order; a bias is added to every row after its sums.
//
// Test: pytest tests/test_layers.py -k matmul. Benchmark: pyvf bench transformer.
#include "kernels.h"

#include <algorithm>
#include <memory>
#include <new>

#include "buffers.h"
#include "simd.h"
#include "threads.h"

namespace pyvf {

namespace {


constexpr int64_t kMatRows = 96;    // whole register tiles on every path (8, 6 and 4 rows)
constexpr int64_t kMatCols = 192;   // a multiple of the packed tile's columns on every path (96, 48, 16, 8, 4)
constexpr int64_t kMatDepth = 256;  // panels: b's 256 x 192 (192 KiB of floats), a's 96 x 256 (96 KiB)
// Split along k: a product with fewer than kMatMinTasks blocks of c and K of at least 2 *
// kMatSplitDepth (the tiny transformer's weight gradients: c 128 x 512, K = 9216) is cut into
// parts of whole kMatDepth chunks, at least kMatSplitDepth deep, about kMatMinTasks tasks in all;
// c = ((part 0 + part 1) + part 2) + ... The parts follow from the shapes alone.
constexpr int64_t kMatMinTasks = 64;
constexpr int64_t kMatSplitDepth = 1024;

// The packed tile: AVX-512's 32 registers hold 4 rows x 6 vectors (4 broadcasts per 24 FMAs);
// AVX2 6 x 2, SSE2/NEON 4 x 2.
constexpr int kPackMR = kVecBytes >= 64 ? 4 : kVecBytes == 32 ? 6 : 4;
constexpr int kPackNV = kVecBytes >= 64 ? 6 : 2;

// One task's block: c (m, n) (leading dimension ldc) = op(a) @ b over k in [0, K), op(a)[i, k]
// = A[k * lda + i] when ta, else A[i * lda + k]; b (K, n) with leading dimension ldb; ap and bp
// the packing buffers (kMatRows * kMatDepth and kMatDepth * kMatCols).
template <typename T, bool TA>
void matmul_block(int64_t m, int64_t n, int64_t K, const T* A, long lda, const T* B, long ldb, T* C, long ldc, T* ap,
                  T* bp) {
    const long sa_i = TA ? 1 : lda, sa_k = TA ? lda : 1;
    constexpr int MR = kPackMR;
    constexpr int NB = kPackNV * kW<T>;
    const int64_t ng = m / MR, nt = n / NB, mf = ng * MR, nf = nt * NB;
    for (int64_t k0 = 0; k0 < K; k0 += kMatDepth) {
        const int kc = (int)std::min(kMatDepth, K - k0);
        const T* Ak = A + k0 * sa_k;
        const T* Bk = B + k0 * ldb;
        for (int64_t t = 0; t < nt; ++t)  // bp[t][k][0:NB] = b[k0 + k, t*NB : (t+1)*NB]
            for (int k = 0; k < kc; ++k) {
                T* dst = bp + (t * kc + k) * NB;
                const T* src = Bk + k * ldb + t * NB;
                for (int v = 0; v < NB; v += kW<T>) vstore<T>(dst + v, vload<T>(src + v));
            }
        for (int64_t g = 0; g < ng; ++g)  // ap[g][k][0:MR] = op(a)[g*MR : (g+1)*MR, k0 + k]
            for (int k = 0; k < kc; ++k)
                for (int i = 0; i < MR; ++i) ap[(g * kc + k) * MR + i] = Ak[(g * MR + i) * sa_i + k * sa_k];
        for (int64_t t = 0; t < nt; ++t)
            for (int64_t g = 0; g < ng; ++g) {
                T* c = C + g * MR * ldc + t * NB;
                const T* At = ap + g * kc * MR;  // op(a)[i, k] at At[k * MR + i]
                const T* Bt = bp + t * kc * NB;  // b[k, v * W + l] at Bt[k * NB + v * W + l]
                if (k0 == 0) gemm_tile<T, MR, kPackNV, false, false>(kc, MatA<T>{At, 1, MR}, MatB<T>{Bt, NB}, c, ldc);
                else gemm_tile<T, MR, kPackNV, false, true>(kc, MatA<T>{At, 1, MR}, MatB<T>{Bt, NB}, c, ldc);
            }
        // the edges, unpacked: the last rows under the packed columns, then every row of the last columns
        if (mf < m) {
            if (k0 == 0) gemm<T, false, TA>((int)(m - mf), (int)nf, kc, Ak + mf * sa_i, lda, Bk, ldb, C + mf * ldc, ldc);
            else gemm<T, false, TA, true>((int)(m - mf), (int)nf, kc, Ak + mf * sa_i, lda, Bk, ldb, C + mf * ldc, ldc);
        }
        if (nf < n) {
            if (k0 == 0) gemm<T, false, TA>((int)m, (int)(n - nf), kc, Ak, lda, Bk + nf, ldb, C + nf, ldc);
            else gemm<T, false, TA, true>((int)m, (int)(n - nf), kc, Ak, lda, Bk + nf, ldb, C + nf, ldc);
        }
    }
}

}  // namespace

template <typename T>
int matmul_batched(T* c, const T* a, const T* b, int64_t nb, int64_t M, int64_t N, int64_t K, bool ta, bool tb,
                   const T* bias) {
    const int64_t nmb = ceil_div(M, kMatRows), nnb = ceil_div(N, kMatCols), per = nmb * nnb;
    if (nb == 0 || M == 0 || N == 0) return kOk;
    if (K == 0) {
        for (int64_t r = 0; r < nb * M; ++r)
            for (int64_t j = 0; j < N; ++j) c[r * N + j] = bias ? T(0) + bias[j] : T(0);
        return kOk;
    }
    std::unique_ptr<T[]> bt;  // a transposed b in (K, N) order: b is a weight matrix where pyvf asks for tb
    if (tb) {
        bt.reset(new (std::nothrow) T[nb * K * N]);  // not initialised: every element is written below
        if (!bt) return kOutOfMemory;
        constexpr int64_t kT = 32;  // tiles of 32 x 32: the reads and the writes both stay in L1
        const int64_t nj = ceil_div(N, kT);
#pragma omp parallel num_threads(num_threads()) if (parallel_work(nb * K * N, kParallelFlops / 8))
        {
#pragma omp for schedule(static) nowait
            for (int64_t t = 0; t < nb * nj; ++t) {
                const int64_t bi = t / nj, j0 = (t % nj) * kT;
                for (int64_t k0 = 0; k0 < K; k0 += kT)
                    for (int64_t j = j0; j < std::min(N, j0 + kT); ++j)
                        for (int64_t k = k0; k < std::min(K, k0 + kT); ++k)
                            bt[(bi * K + k) * N + j] = b[(bi * N + j) * K + k];
            }
        }
        b = bt.get();
    }
    // the parts along k (kMatMinTasks): shapes alone decide them
    int64_t parts = 1;
    if (nb * per < kMatMinTasks && K >= 2 * kMatSplitDepth)
        parts = std::min(K / kMatSplitDepth, ceil_div(kMatMinTasks, nb * per));
    const int64_t span = round_up(ceil_div(K, parts), kMatDepth);  // k per part, whole chunks
    parts = ceil_div(K, span);
    std::unique_ptr<T[]> more;  // parts 1 .. parts - 1, each (nb, M, N)
    if (parts > 1) {
        more.reset(new (std::nothrow) T[(parts - 1) * nb * M * N]);
        if (!more) return kOutOfMemory;
    }
    // the panels as large as this product needs (a small product zero-fills little)
    const int64_t rows = std::min(M, kMatRows), depth = std::min(span, kMatDepth), cols = std::min(N, kMatCols);
    int status = kOk;
#pragma omp parallel num_threads(num_threads()) if (parallel_work(nb * M * N * K, kParallelFlops))
    {
        Buf<T> ap, bp;
        bool ok = false;
        PYVF_TRY_ALLOC(status, ap.resize(rows * depth); bp.resize(depth * cols); ok = true)
#pragma omp for schedule(dynamic, 1) nowait
        for (int64_t t = 0; t < parts * nb * per; ++t) {
            if (!ok) continue;
            const int64_t s = t / (nb * per), q = t % (nb * per);  // part s, block q
            const int64_t bi = q / per, i0 = (q % per % nmb) * kMatRows, j0 = (q % per / nmb) * kMatCols;
            const int64_t m = std::min(kMatRows, M - i0), n = std::min(kMatCols, N - j0);
            const int64_t k0 = s * span, kk = std::min(span, K - k0);
            const T* ab = a + bi * M * K;
            const T* bb = b + (bi * K + k0) * N + j0;
            T* cb = (s == 0 ? c : more.get() + (s - 1) * nb * M * N) + (bi * M + i0) * N + j0;
            // consecutive tasks: the same columns, so that b's panels come from L2 while its rows pass;
            // op(a)[i, k] = a_b[k, i] (stored (K, M)) when ta, else a_b[i, k] (stored (M, K))
            if (ta) matmul_block<T, true>(m, n, kk, ab + k0 * M + i0, (long)M, bb, (long)N, cb, (long)N, ap.data(),
                                          bp.data());
            else matmul_block<T, false>(m, n, kk, ab + i0 * K + k0, (long)K, bb, (long)N, cb, (long)N, ap.data(),
                                        bp.data());
            if (bias && parts == 1)  // the bias after the whole sum: (sum) + bias[j], one rounding each, as NumPy's x @ w + b
                for (int64_t i = 0; i < m; ++i)
                    for (int64_t j = 0; j < n; ++j) cb[i * N + j] += bias[j0 + j];
        }
        // the parts wait for every task (parts is the same on every thread, so all or none meet
        // the barrier); after it every thread sees the same status (a worksharing loop must be
        // met by all threads or none). One part: the region's end is the only barrier.
        if (parts > 1) {
#pragma omp barrier
            if (status == kOk) {  // c = ((part 0 + part 1) + part 2) + ... (+ bias), row by row
#pragma omp for schedule(static) nowait
                for (int64_t r = 0; r < nb * M; ++r) {
                    T* cr = c + r * N;
                    for (int64_t s = 1; s < parts; ++s) {
                        const T* pr = more.get() + ((s - 1) * nb * M + r) * N;
                        for (int64_t j = 0; j < N; ++j) cr[j] += pr[j];
                    }
                    if (bias)
                        for (int64_t j = 0; j < N; ++j) cr[j] += bias[j];
                }
            }
        }
    }
    return status;
}

template int matmul_batched<float>(float*, const float*, const float*, int64_t, int64_t, int64_t, int64_t, bool,
                                   bool, const float*);
template int matmul_batched<double>(double*, const double*, const double*, int64_t, int64_t, int64_t, int64_t,
                                    bool, bool, const double*);

}  // namespace pyvf
