// conv2d, forward and backward, float32 and float64: torch's cross-correlation with any kernel,
// stride and per-side zero padding (the codebook's: 3x3 stride 1 pad 1, the Downsample's 3x3
// stride 2 padded (0, 1, 0, 1), 1x1), docs/math.md §4.
//
// Shapes (conv.h, ConvDims): x (B, C, Hi, Wi), w (Co, C, kh, kw), b (Co,), y (B, Co, Ho, Wo);
// K = C*kh*kw, P = Ho*Wo. w is read as the matrix w2 (Co, K), columns in (c, i, j) order, and
// cols_b (K, P), cols_b[(c,i,j), (u,v)] = xpad[b, c, stride*u + i, stride*v + j], is the im2col
// matrix of image b, xpad x with its zero padding.
//
// Algorithm: implicit GEMM, never BLAS, never Winograd or FFT (which change the rounding): every
// y and dx element is one dot product accumulated in T in increasing (c, i, j) order (FMA where
// the path has it); every dw element a sum over pixels in W vector lanes, the lanes added at the
// end. cols is never stored whole.
//   forward   y_b = w2 @ cols_b + b, by tasks (image, tile of output pixels, block of output
//             channels), each writing its own block of y (ConvTasks):
//             stride 1: the R + kh - 1 input rows that R output rows read are copied
//             once, zero padded, into a (C, R + kh - 1, Wo + kw - 1) tile; each cols row is then a
//             shifted window of it, read in place through a table of row offsets (tab_gemm, the
//             register tile of simd.h's gemm with B's rows found through the table). 1x the input
//             copied instead of kh*kw x, and the tile stays in L1/L2. Rows of >= 2 vectors: one
//             product per output row, straight into y; narrower (8x8): one product over the tile
//             taken as rows of Wo + kw - 1 pixels, the kw - 1 extra columns dropped.
//             stride > 1: im2col tiles of about kTileBytes (L2) in a per-thread buffer, gemm_mr
//             (simd.h's gemm) straight into y's slab. 1x1, stride 1, unpadded: x itself is cols.
//   dx        stride 1: the transposed conv is itself a stride-1 conv: dx = conv(dy, wf) with
//             wf[c, o, i, j] = w[o, c, kh-1-i, kw-1-j] and padding (kh-1-pt, kh-1-pb, kw-1-pl,
//             kw-1-pr) (a negative one crops), so it runs the forward's tasks: each dx element
//             is one dot product of Co*kh*kw terms, a gather, no scatter. wf is never stored: the
//             tasks read it in place from w through a table of column offsets.
//             stride > 1 (the Downsample): dcols (K_blk, np) = w2[:, blk]^T @ dy tile, then col2im
//             adds each row onto its strided slab of dx. Task = (image, block of kCB channels),
//             its tiles in order, so no two tasks write the same dx element (StridedDxTasks).
//   dw        dw2[o, k] = sum over images and pixels p of dy_b[o, p] cols_b[k, p]. Co >= W
//             (DwGemmTasks): dw2^T (K, Co) = sum_b cols_b @ dyT_b, dyT = dy copied channels-last, on
//             the gemm register tile (one broadcast of cols[k, p] times a vector of output
//             channels), cols read in place from a padded-row tile taken as rows of Wp pixels
//             (stride 1; dyT gets zero columns there) or from im2col tiles; the pixels summed in
//             chunks of kDwChunk, each a fresh register sum added to the entry (two levels).
//             Co < W (conv_out's 3 channels), and unpadded 1x1 from 32x32 pixels on (DwLanesTasks): dot
//             products along the pixels of two row-major operands (dot_lanes: MR rows of cols
//             times 4 rows of dy per register tile), neither transposed, dy read in place, one
//             vector of lane sums per entry added up at the end. Both: task = (block of input
//             channels, kCB or (DwGemmTasks, from kDwWideC channels on) 2 kCB, block of output
//             channels), owning those entries of dw, every image's every tile summed in a fixed order.
//   db        sum over images and pixels of dy, in double, per output channel.
// Threads: one OpenMP region per call (each region, and each barrier in it, wakes the sleeping
// threads under OMP_WAIT_POLICY=PASSIVE: 35-50 us on a 2-core VM). The backward's region copies
// dy channels-last, meets its one barrier, then runs the dw tasks and the
// dx tasks as one dynamic loop, so that the dx tasks fill the threads the dw tasks leave idle
// (the tiny codebook's 32-channel dw has 8 tasks), and db.
// Determinism: the tiles depend only on the shapes; every output element is computed by one
// task in one fixed order (the dw's output-channel blocks follow the thread count, but a pair
// (k, o)'s sums are the same in any block): bitwise the same results for any number of threads
// (tests/test_conv.py checks 1 and 2). Gradients are written, never accumulated.
//
// Overflow: each task checks the part of y (the backward: of dx) it wrote while it is in cache and
// the kernel returns kConvNonFinite, which the bindings raise naming the output (a separate pass
// over a paper codebook's activations from memory cost ~1% of its training step).
//
// Its reference, the same layer in NumPy: pyvf/nn/conv.py conv2d_forward_numpy and
// conv2d_backward_numpy (im2col columns times the weights), the tests' plain version.
//
// Measured (AMD EPYC, AVX2, one thread's CPU time, B = 16, 32 -> 32 channels, 64x64, 3x3 pad 1,
// float32): forward 15.1 ms (80 GFLOP/s), backward 31 ms; torch 2.13 15 ms and 70 ms for both.
// DwGemmTasks (Intel Xeon, AVX-512, 2 threads, B = 2, 3x3 pad 1, float32): the backward of 512 -> 512
// channels on 8x8 22.6 -> 9.3 ms, 128 -> 128 on 128x128 89.5 -> 86.6 ms (torch 5.4 and 71 ms).
//
// Test: pytest tests/test_conv.py (the kernel vs NumPy vs torch float64, every shape family and
// code path, the padding trap, 1 vs 2 threads bitwise, float32 vs float64).
// Benchmark: pyvf bench codebook --quick (the time per layer type).
#include "conv.h"

#include <algorithm>
#include <cstring>
#include <memory>
#include <new>
#include <vector>

#include "buffers.h"
#include "simd.h"
#include "threads.h"

namespace pyvf {

namespace {

// Tile sizes and path choices, measured on the codebook's shapes (AMD EPYC, AVX2, 32 KiB L1d and
// 512 KiB L2 per core; tests/test_conv.py's shapes run every path):
// the im2col column tile of the forward and of the stride > 1 dx, bytes (64..256 KiB within 5%);
constexpr int64_t kTileBytes = 128 << 10;
// the dw's column tile or padded-row tile, bytes (32..128 KiB within 5%);
constexpr int64_t kDwTileBytes = 128 << 10;
// the stride-1 forward's padded-row tile, bytes;
constexpr int64_t kRowTileBytes = 256 << 10;
// the forward's padded-row tile is multiplied one output row at a time when a row has at least
// kRowsMinVectors vectors, else as one wide product (8x8 images: 25% faster than im2col, which
// was 35% slower than the per-row products on 16x16); the dw reads the padded-row tile when a row
// has at least kDwRowsMinVectors vectors, else im2col tiles (25% faster on 16x16 and 8x8 rows).
constexpr int64_t kRowsMinVectors = 2, kDwRowsMinVectors = 4;
// Channels per task of the dw and stride > 1 dx loops; DwGemmTasks takes twice as many where x
// has at least kDwWideC channels (each pass over dyT then feeds twice the multiply-adds: the
// 128-channel 128x128 backward 4-6% faster on one thread; with 32 or 64 channels it makes too
// few tasks: 16 x 32 x 64 x 64 was 20% slower in an earlier trial). Its tiles stay those of kCB
// channels, so every dw element's sums, and so the results, are the same whatever the block.
constexpr int64_t kCB = 8, kDwWideC = 128;
// Below this many multiply-adds (about 50 us on one core) a call runs on one thread: starting the
// team costs microseconds on a quiet machine, and on a busy one each parallel region can wait a
// scheduler time slice for a descheduled thread.
constexpr int64_t kParallelFlops = 1 << 20;

// An exception must not leave an OpenMP region (the process would abort): allocations inside
// one are caught, recorded, and the kernel returns kConvOutOfMemory.
#define PYVF_CONV_TRY_ALLOC(status, ...)                        \
    try {                                                       \
        __VA_ARGS__;                                            \
    } catch (const std::bad_alloc&) {                           \
        _Pragma("omp atomic write") status = kConvOutOfMemory;  \
    }
// The same outside a region: the kernel returns kConvOutOfMemory.
#define PYVF_CONV_OR_OOM(...)                 \
    try {                                     \
        __VA_ARGS__;                          \
    } catch (const std::bad_alloc&) {         \
        return kConvOutOfMemory;              \
    }

template <typename T> constexpr int64_t kW = Simd<T>::W;

inline int64_t ceil_div(int64_t a, int64_t b) { return (a + b - 1) / b; }

inline int64_t round_up(int64_t a, int64_t b) { return ceil_div(a, b) * b; }

// Output channels per task of a forward product (ConvTasks) that has `tasks` (image, pixel tile)
// tasks: all of them where those are at least four per thread, else blocks of whole register
// tiles (24 rows: 3 of AVX-512's 8, 4 of AVX2's 6, 6 of SSE2's 4) making about four tasks per
// thread (two left 16 threads a third idle on the 8x8 layers). A row's sums are the same in any
// block, so the results do not depend on the thread count.
inline int64_t out_channel_block(int64_t Co, int64_t tasks) {
    const int64_t want = std::clamp<int64_t>(ceil_div(4 * num_threads(), std::max<int64_t>(tasks, 1)), 1,
                                             std::max<int64_t>(ceil_div(Co, 24), 1));
    return std::max<int64_t>(round_up(ceil_div(Co, want), 24), 24);
}

// Pixels per tile for a tile of `rows` rows: about kTileBytes, a multiple of gemm's widest
// column tile (2 vectors), at most P. Depends on the shape only.
// The tiles of P pixels are balanced: ceil(P / np) tiles of about equal size (a last tile of a
// few pixels would run at a fraction of the speed).
template <typename T> int64_t tile_pixels(int64_t rows, int64_t P, int64_t bytes = kTileBytes) {
    const int64_t step = 2 * kW<T>;
    if (P <= 0) return 1;
    const int64_t most = std::max(step, bytes / (std::max<int64_t>(rows, 1) * (int64_t)sizeof(T)) / step * step);
    const int64_t np = round_up(ceil_div(P, ceil_div(P, most)), step);
    return std::min(np, std::max<int64_t>(P, 1));
}

// out[q] = 0 for q < lo and hi <= q < m, src[q - lo] for lo <= q < hi.
// Inline vector copy: the rows are short (an image row), a memcpy call costs more than the copy;
// the last partial vector is stored overlapping the one before (same values, no scalar tail).
// (Aligning the stores instead, with scalar edges, measured 20% slower.)
template <typename T> inline void copy_between_zeros(T* out, const T* src, int64_t lo, int64_t hi, int64_t m) {
    constexpr int64_t W = kW<T>;
    std::fill(out, out + lo, T(0));
    T* dst = out + lo;
    const int64_t n = hi - lo;
    if (n < W) {
        for (int64_t q = 0; q < n; ++q) dst[q] = src[q];
    } else {
        int64_t q = 0;
        for (; q + W <= n; q += W) vstore<T>(dst + q, vload<T>(src + q));
        if (q < n) vstore<T>(dst + n - W, vload<T>(src + n - W));  // overlaps the previous vector
    }
    std::fill(out + hi, out + m, T(0));
}

// C (M, N) = A (M, K) @ Bt (K, N), where row k of the implicit matrix Bt starts at B + boff[k]:
// rows of a zero-padded image tile, shifted per kernel tap, so that Bt is the im2col matrix of
// one output row without ever being written. Otherwise simd.h's gemm_tile/gemm_rows: the same
// sums in the same order, so the result is bitwise the one im2col + gemm gives.
// A's element (i, k) is A[i * lda + k], or with AT A[i * lda + aoff[k]]: a matrix whose columns
// are found through a table too (the dx's flipped weights, read in place from w; aoff is not read
// without AT).
template <typename T, int MR, int NV, bool AT>
inline void tab_tile(int K, const T* A, long lda, const int64_t* aoff, const T* B, const int64_t* boff, T* C,
                     long ldc) {
    using V = typename Simd<T>::V;
    constexpr int W = Simd<T>::W;
    V acc[MR][NV];
#pragma GCC unroll 16
    for (int i = 0; i < MR; ++i)
#pragma GCC unroll 4
        for (int v = 0; v < NV; ++v) acc[i][v] = V{};
    for (int k = 0; k < K; ++k) {
        const T* bk = B + boff[k];
        const T* ak = A + (AT ? aoff[k] : k);
        V bv[NV];
#pragma GCC unroll 4
        for (int v = 0; v < NV; ++v) bv[v] = vload<T>(bk + v * W);
#pragma GCC unroll 16
        for (int i = 0; i < MR; ++i) {
            const T a = ak[i * lda];
#pragma GCC unroll 4
            for (int v = 0; v < NV; ++v) acc[i][v] += a * bv[v];
        }
    }
#pragma GCC unroll 16
    for (int i = 0; i < MR; ++i)
#pragma GCC unroll 4
        for (int v = 0; v < NV; ++v) vstore<T>(C + i * ldc + v * W, acc[i][v]);
}

template <typename T, int MR, bool AT>
inline void tab_rows(int N, int K, const T* A, long lda, const int64_t* aoff, const T* B, const int64_t* boff, T* C,
                     long ldc) {
    constexpr int W = Simd<T>::W;
    int j = 0;
    for (; j + 2 * W <= N; j += 2 * W) tab_tile<T, MR, 2, AT>(K, A, lda, aoff, B + j, boff, C + j, ldc);
    for (; j + W <= N; j += W) tab_tile<T, MR, 1, AT>(K, A, lda, aoff, B + j, boff, C + j, ldc);
    for (; j < N; ++j)  // columns past the last full vector
        for (int i = 0; i < MR; ++i) {
            T s = 0;
            for (int k = 0; k < K; ++k) s += A[i * lda + (AT ? aoff[k] : k)] * B[boff[k] + j];
            C[i * ldc + j] = s;
        }
}

// Register tile: MR rows of A times 2 vectors. AVX-512: 12 rows, 24 accumulators of its 32
// registers (8 rows made the 3x3 convs' forward 7-9% slower on the codebook's shapes: one load of B
// served fewer FMAs); AVX2's 16 registers hold 6 rows, SSE2/NEON 4. The rows past the last whole
// tile: 8-row tiles (AVX-512), then one of the rest. A row's sums are the same in any tile.
template <typename T, bool AT>
void tab_gemm(int M, int N, int K, const T* A, long lda, const int64_t* aoff, const T* B, const int64_t* boff, T* C,
              long ldc) {
    constexpr int MR = kVecBytes >= 64 ? 12 : kVecBytes == 32 ? 6 : 4;
    // AVX-512: M % 12 == 4 (Co = 64, 256) as two 8-row tiles in place of a 12 and a 4
    const int full = MR > 8 && M % MR == 4 && M >= MR ? M - MR - 4 : M - M % MR;
    int i = 0;
    for (; i < full; i += MR) tab_rows<T, MR, AT>(N, K, A + i * lda, lda, aoff, B, boff, C + i * ldc, ldc);
    if constexpr (MR > 8)
        while (i + 8 <= M) {
            tab_rows<T, 8, AT>(N, K, A + i * lda, lda, aoff, B, boff, C + i * ldc, ldc);
            i += 8;
        }
    A += i * lda;
    C += i * ldc;
    switch (M - i) {
        case 0: break;
        case 1: tab_rows<T, 1, AT>(N, K, A, lda, aoff, B, boff, C, ldc); break;
        case 2: tab_rows<T, 2, AT>(N, K, A, lda, aoff, B, boff, C, ldc); break;
        case 3: tab_rows<T, 3, AT>(N, K, A, lda, aoff, B, boff, C, ldc); break;
        case 4: if constexpr (MR > 4) tab_rows<T, 4, AT>(N, K, A, lda, aoff, B, boff, C, ldc); break;
        case 5: if constexpr (MR > 5) tab_rows<T, 5, AT>(N, K, A, lda, aoff, B, boff, C, ldc); break;
        case 6: if constexpr (MR > 6) tab_rows<T, 6, AT>(N, K, A, lda, aoff, B, boff, C, ldc); break;
        case 7: if constexpr (MR > 7) tab_rows<T, 7, AT>(N, K, A, lda, aoff, B, boff, C, ldc); break;
    }
}

// acc[(i, o), :] += lane sums of A_i[r, 0:w] * D[o, r, 0:w] over r < nr, for i < M, o < N: per
// pair one vector accumulator, lane l summing the products at p = l mod W of each row r (a row's
// last w % W pixels are read through zero-padded copies: 0 * finite adds exactly 0).
// Row r of A_i starts at A + aoff[i] + r * ars (im2col rows: aoff[i] = i * lda, nr = 1; a padded
// image tile: aoff[i] the kernel tap's shift, ars its row length); row r of D_o at
// D + o * ldd + r * drs. acc is (M, ldacc, W).
// Register tile: MR rows of A times NO rows of D, MR + NO vector loads per MR * NO FMAs, both
// operands read along their rows, so neither is transposed.
template <typename T, int MR, int NO>
inline void dot_tile(int64_t nr, int64_t w, const T* A, const int64_t* aoff, int64_t ars, const T* D, int64_t ldd,
                     int64_t drs, T* acc, int64_t ldacc) {
    using V = typename Simd<T>::V;
    constexpr int W = Simd<T>::W;
    V s[MR][NO];
#pragma GCC unroll 8
    for (int i = 0; i < MR; ++i)
#pragma GCC unroll 8
        for (int o = 0; o < NO; ++o) s[i][o] = V{};
    const T* Ai[MR];
    for (int i = 0; i < MR; ++i) Ai[i] = A + aoff[i];
    const int64_t wv = w - w % W;  // the whole vectors of a row
    for (int64_t r = 0; r < nr; ++r)
        for (int64_t p = 0; p < wv; p += W) {
            V a[MR];
#pragma GCC unroll 8
            for (int i = 0; i < MR; ++i) a[i] = vload<T>(Ai[i] + r * ars + p);
#pragma GCC unroll 8
            for (int o = 0; o < NO; ++o) {
                const V b = vload<T>(D + o * ldd + r * drs + p);
#pragma GCC unroll 8
                for (int i = 0; i < MR; ++i) s[i][o] += a[i] * b;
            }
        }
    // the rows' last w - wv < W pixels, zero-padded; a separate loop, so that the one above keeps
    // its accumulators in registers from row to row (with the tail inside it they were spilled)
    if (wv < w)
        for (int64_t r = 0; r < nr; ++r) {
            const int64_t p = wv;
            T ta[MR][W] = {}, tb[W] = {};
            for (int i = 0; i < MR; ++i)
                for (int64_t q = p; q < w; ++q) ta[i][q - p] = Ai[i][r * ars + q];
            for (int o = 0; o < NO; ++o) {
                for (int64_t q = p; q < w; ++q) tb[q - p] = D[o * ldd + r * drs + q];
                const V b = vload<T>(tb);
                for (int i = 0; i < MR; ++i) s[i][o] += vload<T>(ta[i]) * b;
            }
        }
#pragma GCC unroll 8
    for (int i = 0; i < MR; ++i)
#pragma GCC unroll 8
        for (int o = 0; o < NO; ++o) {
            T* q = acc + (i * ldacc + o) * W;
            vstore<T>(q, vload<T>(q) + s[i][o]);
        }
}

template <typename T, int MR>
inline void dot_rows(int64_t N, int64_t nr, int64_t w, const T* A, const int64_t* aoff, int64_t ars, const T* D,
                     int64_t ldd, int64_t drs, T* acc, int64_t ldacc) {
    constexpr int W = Simd<T>::W;
    int64_t o = 0;
    for (; o + 4 <= N; o += 4) dot_tile<T, MR, 4>(nr, w, A, aoff, ars, D + o * ldd, ldd, drs, acc + o * W, ldacc);
    switch (N - o) {
        case 0: break;
        case 1: dot_tile<T, MR, 1>(nr, w, A, aoff, ars, D + o * ldd, ldd, drs, acc + o * W, ldacc); break;
        case 2: dot_tile<T, MR, 2>(nr, w, A, aoff, ars, D + o * ldd, ldd, drs, acc + o * W, ldacc); break;
        case 3: dot_tile<T, MR, 3>(nr, w, A, aoff, ars, D + o * ldd, ldd, drs, acc + o * W, ldacc); break;
    }
}

// Every (row of A, row of D) pair: M rows of A in blocks of MR (3 with 16 vector registers: 12
// accumulators + 3 + 1; 4 with AVX-512's 32), N rows of D in blocks of 4. Which block a pair falls
// in changes no result: each pair's lanes are the same sums in the same order.
template <typename T>
void dot_lanes(int64_t M, int64_t N, int64_t nr, int64_t w, const T* A, const int64_t* aoff, int64_t ars,
               const T* D, int64_t ldd, int64_t drs, T* acc, int64_t ldacc) {
    constexpr int W = Simd<T>::W;
    constexpr int MR = kVecBytes >= 64 ? 4 : 3;
    int64_t i = 0;
    for (; i + MR <= M; i += MR)
        dot_rows<T, MR>(N, nr, w, A, aoff + i, ars, D, ldd, drs, acc + i * ldacc * W, ldacc);
    aoff += i;
    acc += i * ldacc * W;
    switch (M - i) {
        case 0: break;
        case 1: dot_rows<T, 1>(N, nr, w, A, aoff, ars, D, ldd, drs, acc, ldacc); break;
        case 2: dot_rows<T, 2>(N, nr, w, A, aoff, ars, D, ldd, drs, acc, ldacc); break;
        case 3: if constexpr (MR > 3) dot_rows<T, 3>(N, nr, w, A, aoff, ars, D, ldd, drs, acc, ldacc); break;
    }
}

// C (M, N) += A (M, K) @ B (K, N), row i of A at arow[i] (K contiguous numbers), B and C row-major
// (ldb, ldc). The register tile of simd.h's gemm_tile (MR rows of C times NV vectors, one broadcast
// of A times a vector of B per k), with A's rows found through the pointers: each C element gets one
// fresh sum over its K terms in increasing k, added to it at the end, so a caller that splits K
// into chunks sums in two levels. Which tile a column falls in changes no result (NV = 2 or 1: the
// same vector FMAs); the columns past the last whole vector are scalar (the same columns for any
// split of N into blocks of whole vectors).
template <typename T, int MR, int NV>
inline void ptr_tile(int K, const T* const* arow, const T* B, long ldb, T* C, long ldc) {
    using V = typename Simd<T>::V;
    constexpr int W = Simd<T>::W;
    V acc[MR][NV];
    const T* a[MR];
#pragma GCC unroll 16
    for (int i = 0; i < MR; ++i) {
        a[i] = arow[i];
#pragma GCC unroll 4
        for (int v = 0; v < NV; ++v) acc[i][v] = V{};
    }
    for (int k = 0; k < K; ++k) {
        V b[NV];
#pragma GCC unroll 4
        for (int v = 0; v < NV; ++v) b[v] = vload<T>(B + k * ldb + v * W);
#pragma GCC unroll 16
        for (int i = 0; i < MR; ++i) {
            const T av = a[i][k];
#pragma GCC unroll 4
            for (int v = 0; v < NV; ++v) acc[i][v] += av * b[v];
        }
    }
#pragma GCC unroll 16
    for (int i = 0; i < MR; ++i)
#pragma GCC unroll 4
        for (int v = 0; v < NV; ++v) {
            T* c = C + i * ldc + v * W;
            vstore<T>(c, vload<T>(c) + acc[i][v]);
        }
}

// Every row tile of one column tile of NV vectors (the rows past the last whole tile as one tile).
template <typename T, int NV>
inline void ptr_cols(int M, int K, const T* const* arow, const T* B, long ldb, T* C, long ldc) {
    constexpr int MR = kVecBytes >= 64 ? 8 : kVecBytes == 32 ? 6 : 4;
    int i = 0;
    for (; i + MR <= M; i += MR) ptr_tile<T, MR, NV>(K, arow + i, B, ldb, C + i * ldc, ldc);
    arow += i;
    C += i * ldc;
    switch (M - i) {
        case 0: break;
        case 1: ptr_tile<T, 1, NV>(K, arow, B, ldb, C, ldc); break;
        case 2: ptr_tile<T, 2, NV>(K, arow, B, ldb, C, ldc); break;
        case 3: ptr_tile<T, 3, NV>(K, arow, B, ldb, C, ldc); break;
        case 4: if constexpr (MR > 4) ptr_tile<T, 4, NV>(K, arow, B, ldb, C, ldc); break;
        case 5: if constexpr (MR > 5) ptr_tile<T, 5, NV>(K, arow, B, ldb, C, ldc); break;
        case 6: if constexpr (MR > 6) ptr_tile<T, 6, NV>(K, arow, B, ldb, C, ldc); break;
        case 7: if constexpr (MR > 7) ptr_tile<T, 7, NV>(K, arow, B, ldb, C, ldc); break;
    }
}

// The column tiles outermost: a column tile's K rows of B (the dw's chunk of dyT, 256 pixels x 2
// vectors = 32 KiB in float32) stay in L1 while every row tile of A passes (A's rows, 8 KiB a tile,
// are the ones read from L2). Row tiles outermost re-read B from L2 for each (the 3x3 backward was
// 1-5% slower on the codebook's shapes, Intel Xeon AVX-512, medians of interleaved runs).
template <typename T>
void ptr_gemm(int M, int N, int K, const T* const* arow, const T* B, long ldb, T* C, long ldc) {
    constexpr int W = Simd<T>::W;
    int j = 0;
    for (; j + 2 * W <= N; j += 2 * W) ptr_cols<T, 2>(M, K, arow, B + j, ldb, C + j, ldc);
    for (; j + W <= N; j += W) ptr_cols<T, 1>(M, K, arow, B + j, ldb, C + j, ldc);
    for (; j < N; ++j)  // columns past the last full vector
        for (int i = 0; i < M; ++i) {
            T s = 0;
            for (int k = 0; k < K; ++k) s += arow[i][k] * B[k * ldb + j];
            C[i * ldc + j] += s;
        }
}

// tile[c, rr, cc] = x[c0 + c, u0 + rr - pt, cc - pl] for c < nc, rr < nrr, cc < Wp, 0 outside x:
// the zero-padded input rows that output rows u0.. of a stride-1 conv read. tile is (nc, Rp, Wp).
template <typename T>
void pad_rows(T* tile, const T* x, const ConvDims& d, int64_t c0, int64_t nc, int64_t u0, int64_t nrr, int64_t Rp,
              int64_t Wp) {
    const int64_t HWi = d.Hi * d.Wi;
    const int64_t lo = std::clamp<int64_t>(d.pl, 0, Wp), hi = std::clamp<int64_t>(d.pl + d.Wi, lo, Wp);
    for (int64_t c = 0; c < nc; ++c)
        for (int64_t rr = 0; rr < nrr; ++rr) {
            T* out = tile + (c * Rp + rr) * Wp;
            const int64_t yi = u0 + rr - d.pt;
            if (yi < 0 || yi >= d.Hi)
                std::fill(out, out + Wp, T(0));
            else
                copy_between_zeros(out, x + (c0 + c) * HWi + yi * d.Wi + (lo - d.pl), lo, hi, Wp);
        }
}

// The output columns v + q, 0 <= q < m, whose tap j reads inside x: xi = s*(v + q) + j - pl in
// [0, Wi) for exactly lo <= q < hi (0 <= lo <= hi <= m).
inline void inside(const ConvDims& d, int64_t s, int64_t j, int64_t v, int64_t m, int64_t& lo, int64_t& hi) {
    const int64_t a = d.pl - j, e = d.Wi - 1 + d.pl - j;  // a <= s*(v + q) <= e
    const int64_t first = a <= 0 ? 0 : ceil_div(a, s);    // smallest v + q with s*(v + q) >= a
    const int64_t last = e < 0 ? -1 : e / s;              // largest v + q with s*(v + q) <= e
    lo = std::clamp<int64_t>(first - v, 0, m);
    hi = std::clamp<int64_t>(last + 1 - v, lo, m);
}

// cols (nc*kh*kw, n), rows ld apart: the im2col rows of channels [c0, c0 + nc) of one image x (C, Hi, Wi), for
// the n output pixels p0 .. p0 + n (p = u*Wo + v):
//     cols[(c - c0, i, j), p - p0] = x[c, stride*u + i - pt, stride*v + j - pl], 0 outside x.
// Works for negative padding too (the stride-1 dx conv's, which crops).
template <typename T>
void im2col(T* cols, const T* x, const ConvDims& d, int64_t c0, int64_t nc, int64_t p0, int64_t n, int64_t ld) {
    const int64_t s = d.stride, HWi = d.Hi * d.Wi, u0 = p0 / d.Wo, v0 = p0 % d.Wo;
    for (int64_t c = 0; c < nc; ++c)
        for (int64_t i = 0; i < d.kh; ++i)
            for (int64_t j = 0; j < d.kw; ++j) {
                T* row = cols + ((c * d.kh + i) * d.kw + j) * ld;
                const T* xc = x + (c0 + c) * HWi;
                // one segment of output row u per step (no division in the loop: it would cost
                // more than a segment's copy)
                for (int64_t p = p0, u = u0, v = v0; p < p0 + n; p += d.Wo - v, v = 0, ++u) {
                    const int64_t m = std::min(d.Wo - v, p0 + n - p);
                    T* out = row + (p - p0);
                    const int64_t yi = s * u + i - d.pt;
                    if (yi < 0 || yi >= d.Hi) {
                        std::fill(out, out + m, T(0));
                    } else {
                        // xi = s*(v + q) + j - pl is inside x for lo <= q < hi
                        int64_t lo, hi;
                        inside(d, s, j, v, m, lo, hi);
                        const T* xr = xc + yi * d.Wi + (s * (v + lo) + j - d.pl);
                        if (s == 1) {  // one copy between two runs of zeros
                            copy_between_zeros(out, xr, lo, hi, m);
                        } else {
                            std::fill(out, out + lo, T(0));
                            for (int64_t q = lo; q < hi; ++q) out[q] = xr[s * (q - lo)];
                            std::fill(out + hi, out + m, T(0));
                        }
                    }
                }
            }
}

// The inverse scatter: dx[c0 + c, stride*u + i - pt, stride*v + j - pl] += dcols[(c, i, j), p - p0]
// for every in-image position, rows in (c, i, j) order, pixels in order.
template <typename T>
void col2im_add(T* dx, const T* dcols, const ConvDims& d, int64_t c0, int64_t nc, int64_t p0, int64_t n) {
    const int64_t s = d.stride, HWi = d.Hi * d.Wi, u0 = p0 / d.Wo, v0 = p0 % d.Wo;
    for (int64_t c = 0; c < nc; ++c)
        for (int64_t i = 0; i < d.kh; ++i)
            for (int64_t j = 0; j < d.kw; ++j) {
                const T* row = dcols + ((c * d.kh + i) * d.kw + j) * n;
                T* dxc = dx + (c0 + c) * HWi;
                for (int64_t p = p0, u = u0, v = v0; p < p0 + n; p += d.Wo - v, v = 0, ++u) {
                    const int64_t m = std::min(d.Wo - v, p0 + n - p);
                    const int64_t yi = s * u + i - d.pt;
                    if (yi >= 0 && yi < d.Hi) {
                        int64_t lo, hi;
                        inside(d, s, j, v, m, lo, hi);
                        T* dr = dxc + yi * d.Wi + (s * (v + lo) + j - d.pl);
                        const T* in = row + (p - p0);
                        for (int64_t q = lo; q < hi; ++q) dr[s * (q - lo)] += in[q];
                    }
                }
            }
}

bool worth_threads(const ConvDims& d) { return parallel_work(d.B * d.Co * d.Ho * d.Wo * d.C * d.kh * d.kw, kParallelFlops); }

// y[o, 0:n] += b[o] for the Co rows of y (leading dimension ld)
template <typename T> inline void add_bias_rows(T* y, const T* b, int64_t Co, int64_t ld, int64_t n) {
    for (int64_t o = 0; o < Co; ++o) {
        T* r = y + o * ld;
        const T bo = b[o];
        for (int64_t q = 0; q < n; ++q) r[q] += bo;
    }
}

// Whether the rows y[o, 0:n) (leading dimension ld) are all finite, for the m rows: each task checks
// what it wrote while it is in cache (the bindings raise kConvNonFinite), instead of a pass over
// the whole output from memory afterwards.
template <typename T> inline bool rows_finite(const T* y, int64_t m, int64_t ld, int64_t n) {
    bool ok = true;
    for (int64_t o = 0; o < m; ++o) ok = finite_run(y + o * ld, n) && ok;
    return ok;
}

// y = conv(x, w) (+ b when b is not null) as a set of tasks: the forward, and the stride-1 dx
// (flipped: y = dx, x = dy, and w the forward's weights (C, Co, kh, kw) in this struct's names,
// read in place as the flipped kernel wf[o, c, i', j'] = w[c, o, kh-1-i', kw-1-j'] through a
// table of columns, aoff: never copied, which for a 512-channel 3x3 layer saved writing and
// reading 9 MiB per backward). Task = (image, tile of output rows or pixels, block of output
// channels), each writing its own block of y; run(t) may be called by any thread, in any order,
// with that thread's Scratch (made once by scratch()).
//   Stride 1, not 1x1-direct (the codebook's 3x3 pad 1, and every 3x3 dx): per task the R + kh - 1
//   input rows that its R output rows read are copied once, zero padded, into a (C, R + kh - 1,
//   Wp) tile, Wp = Wo + kw - 1, and w2 (Co, K) @ Bt is computed with Bt[(c,i,j), (r,v)] =
//   tile[c, r + i, v + j] read in place by tab_gemm: 1x the input copied instead of kh*kw x for
//   im2col, and the tile stays in L1/L2.
//     rows of at least kRowsMinVectors vectors: one tab_gemm per output row, N = Wo, straight
//     into y;
//     narrower rows (8x8 images, "wide"): one tab_gemm over the whole tile taken as rows of Wp
//     pixels, N = (nr - 1)*Wp + Wo rounded up to whole vectors: the kw - 1 columns past each
//     row's end (and the rounding) are computed and dropped, and the Wo real ones copied into y.
//     The tile has W elements of slack so that those columns read inside it.
//   Otherwise (stride > 1, 1x1): im2col tiles of about kTileBytes in the thread's buffer, gemm_mr
//   straight into y's slab; unpadded 1x1 stride 1 ("direct"): x itself is cols.
template <typename T> struct ConvTasks {
    struct Scratch {
        Buf<T> tile, out;  // rows: the padded rows (C, Rp, Wp) + W slack, and (wide) the product
    };                     // (cob, nwide); else the cols tile (K, np) (none when direct)
    T* y;
    const T *x, *w, *b;
    ConvDims d;
    int64_t K, P, HWi, Wp = 0, R = 0, Rp = 0, np = 0, nwide = 0, ntile, cob, ncob, ntask;
    int64_t lda;  // w2's element (o, k) is w[o * lda + k], flipped w[o * lda + aoff[k]]
    bool flipped, direct, rows, wide = false;
    std::vector<int64_t> boff;  // rows: row k = (c, i, j) of Bt starts at tile + boff[k] (+ r*Wp for row r)
    std::vector<int64_t> aoff;  // flipped: column k = (c, i', j') of wf starts at w + aoff[k]

    // throws std::bad_alloc; flipped only with stride 1 (the dx)
    ConvTasks(T* y_, const T* x_, const T* w_, const T* b_, const ConvDims& d_, bool flipped_ = false)
        : y(y_), x(x_), w(w_), b(b_), d(d_), flipped(flipped_) {
        constexpr int64_t W = kW<T>;
        const int64_t khw = d.kh * d.kw;
        K = d.C * khw, P = d.Ho * d.Wo, HWi = d.Hi * d.Wi;
        lda = flipped ? khw : K;
        if (flipped) {  // wf[o, (c, q)] = w[c, o, khw-1-q] at w + o * khw + c * Co * khw + khw-1-q
            aoff.resize(K);
            for (int64_t k = 0; k < K; ++k) aoff[k] = (k / khw) * d.Co * khw + khw - 1 - k % khw;
        }
        direct = d.kh == 1 && d.kw == 1 && d.stride == 1 && !d.pt && !d.pb && !d.pl && !d.pr;
        rows = !direct && d.stride == 1;
        if (rows) {
            Wp = d.Wo + d.kw - 1;
            // tiles of at most kRowTileBytes, balanced: ceil(Ho / R) tiles of about equal rows (a
            // 64-row image made 29 + 29 + 6, now 22 + 22 + 20). Each output element is one dot
            // product whatever its tile, so the tiles change no bit.
            R = std::clamp<int64_t>(kRowTileBytes / (std::max<int64_t>(d.C, 1) * Wp * (int64_t)sizeof(T)) - (d.kh - 1),
                                    1, d.Ho);
            ntile = ceil_div(d.Ho, R), R = ceil_div(d.Ho, ntile), Rp = R + d.kh - 1;
            wide = d.Wo < kRowsMinVectors * W;
            nwide = round_up((R - 1) * Wp + d.Wo, W);  // columns of the widest wide product
            boff.resize(K);
            for (int64_t c = 0; c < d.C; ++c)
                for (int64_t i = 0; i < d.kh; ++i)
                    for (int64_t j = 0; j < d.kw; ++j) boff[(c * d.kh + i) * d.kw + j] = (c * Rp + i) * Wp + j;
        } else {
            np = tile_pixels<T>(K, P), ntile = ceil_div(P, np);
        }
        // output-channel blocks where images x tiles are few (an 8x8 image is one tile)
        cob = out_channel_block(d.Co, d.B * ntile), ncob = ceil_div(d.Co, cob), ntask = d.B * ntile * ncob;
    }

    // throws std::bad_alloc
    void scratch(Scratch& s) const {
        if (rows) {
            s.tile.resize(d.C * Rp * Wp + kW<T>);
            if (wide) s.out.resize(std::min(cob, d.Co) * nwide);
        } else if (!direct) {
            s.tile.resize(K * np);
        }
    }

    // C (no, n) = rows of w2 from wb (no, K) @ Bt (K, n) read from the tile B through boff (rows)
    void tab(int64_t no, int64_t n, const T* wb, const T* B, T* C, int64_t ldc) const {
        if (flipped)
            tab_gemm<T, true>((int)no, (int)n, (int)K, wb, lda, aoff.data(), B, boff.data(), C, ldc);
        else
            tab_gemm<T, false>((int)no, (int)n, (int)K, wb, lda, nullptr, B, boff.data(), C, ldc);
    }

    // task t; false when what it wrote is not finite
    bool run(int64_t t, Scratch& s) const {
        constexpr int64_t W = kW<T>;
        const int64_t bt = t / ncob, bi = bt / ntile, o0 = (t % ncob) * cob, no = std::min(cob, d.Co - o0);
        const T* xb = x + bi * d.C * HWi;  // (C, Hi, Wi)
        const T* wb = w + o0 * lda;        // rows o0 .. o0 + no of w2 (flipped: of wf)
        if (rows) {
            const int64_t u0 = (bt % ntile) * R, nr = std::min(R, d.Ho - u0);
            pad_rows(s.tile.data(), xb, d, 0, d.C, u0, nr + d.kh - 1, Rp, Wp);
            T* yb = y + (bi * d.Co + o0) * P;  // rows o0 .. o0 + no of y_b
            if (wide) {
                const int64_t n = round_up((nr - 1) * Wp + d.Wo, W);
                tab(no, n, wb, s.tile.data(), s.out.data(), n);
                for (int64_t o = 0; o < no; ++o)
                    for (int64_t r = 0; r < nr; ++r)
                        std::copy_n(s.out.data() + o * n + r * Wp, d.Wo, yb + o * P + (u0 + r) * d.Wo);
            } else {
                for (int64_t r = 0; r < nr; ++r)  // y_b[o0:o0+no, u0 + r, :] = w2[o0:o0+no] @ Bt(row r)
                    tab(no, d.Wo, wb, s.tile.data() + r * Wp, yb + (u0 + r) * d.Wo, P);
            }
            if (b) add_bias_rows(yb + u0 * d.Wo, b + o0, no, P, nr * d.Wo);
            return rows_finite(yb + u0 * d.Wo, no, P, nr * d.Wo);
        }
        const int64_t p0 = (bt % ntile) * np, n = std::min(np, P - p0);
        T* yb = y + (bi * d.Co + o0) * P + p0;  // (no, n) of (Co, P)
        const T* src = xb + p0;                 // direct: the columns are x_b's own pixels
        int64_t ldb = P;
        if (!direct) {
            im2col(s.tile.data(), xb, d, 0, d.C, p0, n, n);
            src = s.tile.data();
            ldb = n;
        }
        // y_b[o0:o0+no, p0:p0+n] = w2[o0:o0+no] (no, K) @ cols (K, n); flipped (1x1): wf = w^T, (no, K)
        // read from w's columns o0.., lda apart
        if (flipped)
            gemm_mr<T, false, true>((int)no, (int)n, (int)K, w + o0, d.Co, src, ldb, yb, P);
        else
            gemm_mr<T, false>((int)no, (int)n, (int)K, wb, K, src, ldb, yb, P);
        if (b) add_bias_rows(yb, b + o0, no, P, n);
        return rows_finite(yb, no, P, n);
    }
};

// Where row k = (c, i, j) of a dw task's cols starts, for its nc input channels: in x itself (1x1
// direct: channel c's pixels), in a padded-row tile (nc, Rp, Wp) (tap (i, j) shifts channel c's
// rows), or in an im2col tile of np pixels per row.
inline void cols_row_offsets(int64_t* aoff, const ConvDims& d, int64_t nc, bool direct, bool rows, int64_t Rp,
                             int64_t Wp, int64_t np) {
    for (int64_t c = 0; c < nc; ++c)
        for (int64_t i = 0; i < d.kh; ++i)
            for (int64_t j = 0; j < d.kw; ++j)
                aoff[(c * d.kh + i) * d.kw + j] = direct ? c * d.Hi * d.Wi
                                                  : rows ? (c * Rp + i) * Wp + j
                                                         : ((c * d.kh + i) * d.kw + j) * np;
}

// The W / WD double vectors of the elements of a T vector, in order (float -> double is exact):
// whole-vector conversions (filling a double vector lane by lane compiles to a scalar insert per
// lane, which dominated the sums).
template <typename T> inline void widen_to_double(typename Simd<T>::V v, typename Simd<double>::V* out) {
    if constexpr (sizeof(T) == sizeof(double)) {
        out[0] = v;
    } else {
        using VD = typename Simd<double>::V;
        typedef float H __attribute__((vector_size(Simd<double>::W * sizeof(float))));  // half a float vector
        H lo, hi;
        std::memcpy(&lo, &v, sizeof lo);
        std::memcpy(&hi, reinterpret_cast<const char*>(&v) + sizeof lo, sizeof hi);
        out[0] = __builtin_convertvector(lo, VD);
        out[1] = __builtin_convertvector(hi, VD);
    }
}

// db[o] = sum over images and pixels of dy[b, o, :, :], in double (forward was y = ... + b[o]);
// false when it is not finite.
template <typename T> bool db_sum(T* db, const T* dy, const ConvDims& d, int64_t o) {
    const int64_t P = d.Ho * d.Wo;
    using VD = Simd<double>::V;
    constexpr int WD = Simd<double>::W;
    VD a0 = {}, a1 = {};
    double tail = 0;
    for (int64_t bi = 0; bi < d.B; ++bi) {
        const T* r = dy + (bi * d.Co + o) * P;
        int64_t p = 0;
        for (; p + 2 * WD <= P; p += 2 * WD) {  // elements p .. p + WD into a0, the next WD into a1
            constexpr int per = Simd<T>::W / WD;    // double vectors per T vector: 2 (float) or 1
            VD v[2];
            for (int q = 0; q < 2 / per; ++q) widen_to_double<T>(vload<T>(r + p + q * Simd<T>::W), v + q * per);
            a0 += v[0];
            a1 += v[1];
        }
        for (; p < P; ++p) tail += (double)r[p];
    }
    db[o] = (T)(hsum<double>(a0 + a1) + tail);
    return finite_run(db + o, 1);
}

// dw when Co >= W (one vector of output channels): dw2^T (K, Co) = sum over images b of cols_b
// (K, P) @ dyT_b (P, Co), dyT the channels-last copy of dy, as products on the register tile of
// ptr_gemm: one broadcast of cols[k, p] times a vector of dyT[p, o0 ..], so the o's lie along the
// vectors and no horizontal sum is needed (the lanes path, DwLanesTasks, 2-5x slower on the
// codebook's shapes with 32..512 channels, stays for Co < W, where a row of dyT is less than a
// vector). Stride 1, not 1x1-direct: cols is read in place from a padded-row tile of R + kh - 1
// input rows, its row k = (c, i, j) the tile's contiguous numbers from (c, i, j) on, taken as rows
// of Wp = Wo + kw - 1 pixels: so dyT's rows are padded to Wp with zero columns, whose products
// (with finite numbers of the tile) add exactly 0. Otherwise im2col tiles (or x itself, 1x1).
// Summation: each dw element is a sum over (image, tile, chunk of at most kDwChunk pixels) in
// that order of a fresh register sum over the chunk's pixels in order (two levels), the tiles
// those of kCB channels. Tasks: (block of cb input channels, block of whole vectors of output
// channels), each owning its entries of dw: bitwise the same for any thread count (a column is in
// a vector or in the scalar tail whatever the blocks); run(t) returns false when an entry it
// wrote is not finite (checked while in cache, so that no pass over dw follows). Before the
// tasks, prep(i) for i < nprep fills dyT's row i (every row before any task).
constexpr int64_t kDwChunk = 256;

// A dw task's block: dw[o, r] = value(r, o) for its no output channels (rows ld apart) and kb
// columns; false when an entry written is not finite (checked while in cache).
template <typename T, typename F> bool store_dw(T* dw, int64_t ld, int64_t no, int64_t kb, F value) {
    bool ok = true;
    for (int64_t o = 0; o < no; ++o) {
        T* row = dw + o * ld;
        for (int64_t r = 0; r < kb; ++r) row[r] = value(r, o);
        ok = finite_run(row, kb) && ok;
    }
    return ok;
}

template <typename T> struct DwGemmTasks {
    struct Scratch {
        Buf<T> buf, acc;  // the padded rows (nc, Rp, Wq) or the cols tile (kb, np); acc (kb, ow)
        std::vector<int64_t> aoff;
        std::vector<const T*> arow;
    };
    T* dw;
    const T *x, *dy;
    ConvDims d;
    int64_t cb, khw, K, P, HWi, Wq, nc_max, kb_max, R, Rp, np, ntile, ncb, ow, nob, ntask, ldt, nprep;
    bool direct, rows;
    RawBuf<T> dyT;  // (B, Ho, Wq, ldt): o < Co written by prep, zero where v >= Wo; o >= Co never read

    // throws std::bad_alloc
    DwGemmTasks(T* dw_, const T* x_, const T* dy_, const ConvDims& d_) : dw(dw_), x(x_), dy(dy_), d(d_) {
        constexpr int64_t W = kW<T>;
        cb = d.C >= kDwWideC ? 2 * kCB : kCB;  // input channels per task
        khw = d.kh * d.kw, K = d.C * khw, P = d.Ho * d.Wo, HWi = d.Hi * d.Wi;
        direct = d.kh == 1 && d.kw == 1 && d.stride == 1 && !d.pt && !d.pb && !d.pl && !d.pr;
        rows = !direct && d.stride == 1;
        Wq = rows ? d.Wo + d.kw - 1 : d.Wo;  // dyT's row length (pixels)
        nc_max = std::min(d.C, cb), kb_max = nc_max * khw;
        const int64_t nc_tile = std::min(d.C, kCB);  // the tiles: as for kCB channels, whatever cb
        R = std::clamp<int64_t>(
            kDwTileBytes / (std::max<int64_t>(nc_tile, 1) * Wq * (int64_t)sizeof(T)) - (d.kh - 1), 1, d.Ho);
        Rp = R + d.kh - 1;
        np = rows ? R * d.Wo : tile_pixels<T>(direct ? 0 : nc_tile * khw, P, kDwTileBytes);
        ntile = rows ? ceil_div(d.Ho, R) : ceil_div(P, np);
        ncb = ceil_div(d.C, cb);
        // output-channel blocks of whole vectors: at least two tasks per thread where the input
        // channels alone do not make that many, at most 64 channels
        const int64_t nob_want =
            std::max(ceil_div(d.Co, 64), std::min(ceil_div(d.Co, W), ceil_div(2 * num_threads(), ncb)));
        ow = round_up(ceil_div(d.Co, std::max<int64_t>(nob_want, 1)), W), nob = ceil_div(d.Co, ow);
        ntask = ncb * nob;
        // dyT's rows are ldt apart: Co rounded up to whole vectors plus one more, so that rows
        // 2^n bytes apart (Co = 128, 256, 512) do not fall into a few sets of the L1 cache (that
        // alone made the 8x8, 512-channel dw 2x slower)
        ldt = round_up(d.Co, W) + W;
        nprep = d.B * d.Ho;
        dyT.resize(d.B * d.Ho * Wq * ldt);
    }

    // dyT[b, u, v, o] = dy[b, o, u, v] for row bu = (b, u), 16 o at a time, and 0 for the
    // padding pixels v >= Wo (the tasks read o < Co only: the columns o >= Co stay unset)
    void prep(int64_t bu) {
        const int64_t bi = bu / d.Ho, u = bu % d.Ho;
        const T* src = dy + bi * d.Co * P + u * d.Wo;
        T* dst = dyT.data() + bu * Wq * ldt;
        for (int64_t o0 = 0; o0 < d.Co; o0 += 16)
            for (int64_t v = 0; v < d.Wo; ++v)
                for (int64_t o = o0; o < std::min(o0 + 16, d.Co); ++o) dst[v * ldt + o] = src[o * P + v];
        for (int64_t v = d.Wo; v < Wq; ++v) std::fill(dst + v * ldt, dst + v * ldt + d.Co, T(0));
    }

    // throws std::bad_alloc
    void scratch(Scratch& s) const {
        s.buf.resize(direct ? 0 : rows ? nc_max * Rp * Wq : kb_max * np);
        s.acc.resize(kb_max * ow);
        s.aoff.resize(kb_max);
        s.arow.resize(kb_max);
    }

    bool run(int64_t t, Scratch& s) const {
        const int64_t c0 = (t / nob) * cb, nc = std::min(cb, d.C - c0), kb = nc * khw;
        const int64_t o0 = (t % nob) * ow, no = std::min(ow, d.Co - o0);
        cols_row_offsets(s.aoff.data(), d, nc, direct, rows, Rp, Wq, np);
        std::fill(s.acc.begin(), s.acc.end(), T(0));
        for (int64_t bi = 0; bi < d.B; ++bi)
            for (int64_t tile = 0; tile < ntile; ++tile) {
                const T* xb = x + bi * d.C * HWi;
                const T* base;
                const T* Bt;  // dyT's row of the tile's first pixel, column o0
                int64_t nq;   // pixels of the tile (rows: with the zero columns between its rows)
                if (rows) {
                    const int64_t u0 = tile * R, nr = std::min(R, d.Ho - u0);
                    pad_rows(s.buf.data(), xb, d, c0, nc, u0, nr + d.kh - 1, Rp, Wq);
                    base = s.buf.data();
                    nq = (nr - 1) * Wq + d.Wo;
                    Bt = dyT.data() + ((bi * d.Ho + u0) * Wq) * ldt + o0;
                } else {
                    const int64_t p0 = tile * np;
                    nq = std::min(np, P - p0);
                    base = xb + c0 * HWi + p0;
                    if (!direct) {
                        im2col(s.buf.data(), xb, d, c0, nc, p0, nq, np);
                        base = s.buf.data();
                    }
                    Bt = dyT.data() + (bi * P + p0) * ldt + o0;
                }
                for (int64_t q0 = 0; q0 < nq; q0 += kDwChunk) {
                    for (int64_t k = 0; k < kb; ++k) s.arow[k] = base + s.aoff[k] + q0;
                    // acc (kb, no) += cols[:, q0:q0+n] @ dyT[q0:q0+n, o0:o0+no]
                    ptr_gemm<T>((int)kb, (int)no, (int)std::min(kDwChunk, nq - q0), s.arow.data(), Bt + q0 * ldt,
                                ldt, s.acc.data(), ow);
                }
            }
        return store_dw(dw + o0 * K + c0 * khw, K, no, kb, [&](int64_t r, int64_t o) { return s.acc[r * ow + o]; });
    }
};

// dw when Co < W (conv_out's 3 channels), and unpadded 1x1 from 32x32 pixels on: forward was
// y_b = w2 @ cols_b, so dw2[o, k] = sum over b, p of dy_b[o, p] cols_b[k, p]: dot products along
// the pixels of two row-major operands (dot_lanes: MR rows of cols times 4 rows of dy per register
// tile), neither transposed, dy read in place, one vector of lane sums per entry added up at the
// end. Tasks as DwGemmTasks': (block of kCB input channels, block of output channels), every
// image's every tile summed in a fixed order; run(t) checks what it wrote, as DwGemmTasks'.
// Nothing to prepare (nprep = 0).
template <typename T> struct DwLanesTasks {
    struct Scratch {
        // buf: the cols tile (kb, np) or the padded rows (nc, Rp, Wp); aoff: where each row of cols
        // starts in it; acc (kb, ow, W): per (k, o) one vector of lane sums, lane l summing the
        // pixels p = l mod W of every tile row, added up lane by lane at the end
        Buf<T> buf, acc;
        std::vector<int64_t> aoff;
    };
    T* dw;
    const T *x, *dy;
    ConvDims d;
    int64_t khw, K, P, HWi, Wp, nc_max, kb_max, R, Rp, np, ntile, ncb, ow, nob, ntask, nprep = 0;
    bool direct, rows;

    DwLanesTasks(T* dw_, const T* x_, const T* dy_, const ConvDims& d_) : dw(dw_), x(x_), dy(dy_), d(d_) {
        khw = d.kh * d.kw, K = d.C * khw, P = d.Ho * d.Wo, HWi = d.Hi * d.Wi;
        ncb = ceil_div(d.C, kCB);
        // output-channel blocks: at least two tasks per thread where the input channels alone do
        // not make that many (each block re-reads its rows of cols), blocks of at least 4 and at
        // most 64 channels (the lane accumulators, kb * ow vectors, stay in L2). The blocks may
        // depend on the thread count: a pair (k, o)'s lane sums are the same whatever block o
        // falls in.
        const int64_t nob_want =
            std::max(ceil_div(d.Co, 64), std::min(ceil_div(d.Co, 4), ceil_div(2 * num_threads(), ncb)));
        ow = ceil_div(d.Co, std::max<int64_t>(nob_want, 1)), nob = ceil_div(d.Co, std::max<int64_t>(ow, 1));
        ntask = ncb * nob;
        // the padded-row tile where a row has at least kDwRowsMinVectors vectors
        direct = d.kh == 1 && d.kw == 1 && d.stride == 1 && !d.pt && !d.pb && !d.pl && !d.pr;
        rows = !direct && d.stride == 1 && d.Wo >= kDwRowsMinVectors * kW<T>;
        nc_max = std::min(d.C, kCB), kb_max = nc_max * khw, Wp = d.Wo + d.kw - 1;
        R = std::clamp<int64_t>(kDwTileBytes / (std::max<int64_t>(nc_max, 1) * Wp * (int64_t)sizeof(T)) - (d.kh - 1), 1,
                                d.Ho);
        Rp = R + d.kh - 1;
        np = rows ? R * d.Wo : tile_pixels<T>(direct ? 0 : kb_max, P, kDwTileBytes);
        ntile = rows ? ceil_div(d.Ho, R) : ceil_div(P, np);
    }

    void prep(int64_t) {}

    // throws std::bad_alloc
    void scratch(Scratch& s) const {
        s.buf.resize(direct ? 0 : rows ? nc_max * Rp * Wp : kb_max * np);
        s.acc.resize(kb_max * ow * kW<T>);
        s.aoff.resize(kb_max);
    }

    bool run(int64_t t, Scratch& s) const {
        const int64_t c0 = (t / nob) * kCB, nc = std::min(kCB, d.C - c0), kb = nc * khw;
        const int64_t o0 = (t % nob) * ow, no = std::min(ow, d.Co - o0);
        cols_row_offsets(s.aoff.data(), d, nc, direct, rows, Rp, Wp, np);
        std::fill(s.acc.begin(), s.acc.end(), T(0));
        for (int64_t bi = 0; bi < d.B; ++bi)
            for (int64_t tile = 0; tile < ntile; ++tile) {
                const T* xb = x + bi * d.C * HWi;
                const T* dyb = dy + (bi * d.Co + o0) * P;
                // acc[k, o, :] += lanes of cols[k, p] * dy_b[o0 + o, p] over the tile's pixels p
                if (rows) {
                    const int64_t u0 = tile * R, nr = std::min(R, d.Ho - u0);
                    pad_rows(s.buf.data(), xb, d, c0, nc, u0, nr + d.kh - 1, Rp, Wp);
                    dot_lanes<T>(kb, no, nr, d.Wo, s.buf.data(), s.aoff.data(), Wp, dyb + u0 * d.Wo, P, d.Wo,
                                 s.acc.data(), ow);
                } else {
                    const int64_t p0 = tile * np, n = std::min(np, P - p0);
                    const T* A = xb + c0 * HWi + p0;
                    if (!direct) {
                        im2col(s.buf.data(), xb, d, c0, nc, p0, n, np);
                        A = s.buf.data();
                    }
                    dot_lanes<T>(kb, no, 1, n, A, s.aoff.data(), 0, dyb + p0, P, 0, s.acc.data(), ow);
                }
            }
        return store_dw(dw + o0 * K + c0 * khw, K, no, kb,
                        [&](int64_t r, int64_t o) { return hsum<T>(vload<T>(s.acc.data() + (r * ow + o) * kW<T>)); });
    }
};

// dx of a stride > 1 conv (the Downsample): forward was y_b = w2 @ cols_b, so dcols_b = w2^T @
// dy_b, then col2im adds each row onto its strided slab of dx. Task = (image, block of kCB
// channels), its tiles in order, so no two tasks write the same dx element; false when what it
// wrote is not finite.
template <typename T> struct StridedDxTasks {
    struct Scratch {
        Buf<T> dcols;  // (kCB*kh*kw, np)
    };
    T* dx;
    const T *w, *dy;
    ConvDims d;
    int64_t khw, K, P, HWi, ncb, ntask, np, ntile;

    StridedDxTasks(T* dx_, const T* w_, const T* dy_, const ConvDims& d_) : dx(dx_), w(w_), dy(dy_), d(d_) {
        khw = d.kh * d.kw, K = d.C * khw, P = d.Ho * d.Wo, HWi = d.Hi * d.Wi;
        ncb = ceil_div(d.C, kCB), ntask = d.B * ncb;
        np = tile_pixels<T>(std::min(d.C, kCB) * khw, P), ntile = ceil_div(P, np);
    }

    // throws std::bad_alloc
    void scratch(Scratch& s) const { s.dcols.resize(std::min(d.C, kCB) * khw * np); }

    bool run(int64_t t, Scratch& s) const {
        const int64_t bi = t / ncb, c0 = (t % ncb) * kCB, nc = std::min(kCB, d.C - c0);
        T* dxb = dx + bi * d.C * HWi;
        std::fill(dxb + c0 * HWi, dxb + (c0 + nc) * HWi, T(0));
        for (int64_t tile = 0; tile < ntile; ++tile) {
            const int64_t p0 = tile * np, n = std::min(np, P - p0);
            // dcols (nc*kh*kw, n) = w2[:, c0*khw : (c0+nc)*khw]^T @ dy_b[:, p0:p0+n]
            gemm_mr<T, false, true>((int)(nc * khw), (int)n, (int)d.Co, w + c0 * khw, K, dy + bi * d.Co * P + p0, P,
                                    s.dcols.data(), n);
            col2im_add(dxb, s.dcols.data(), d, c0, nc, p0, n);
        }
        return finite_run(dxb + c0 * HWi, nc * HWi);
    }
};

// The status of a kernel from its allocation status and whether every task's output was finite.
inline int conv_status(int status, int nonfinite) {
    return status != kConvOk ? status : nonfinite ? kConvNonFinite : kConvOk;
}

// A backward's: dx's, then dw's, then db's.
inline int backward_status(int status, int nonfinite_dx, int nonfinite_dw, int nonfinite_db) {
    status = conv_status(status, nonfinite_dx);
    return status != kConvOk ? status : nonfinite_dw ? kConvNonFiniteDw : nonfinite_db ? kConvNonFiniteDb : kConvOk;
}

// y = conv(x, w) (+ b): ConvTasks in one parallel region, each thread's scratch made once.
template <typename T> int conv_gemm(T* y, const T* x, const T* w, const T* b, const ConvDims& d) {
    std::unique_ptr<ConvTasks<T>> p;
    PYVF_CONV_OR_OOM(p.reset(new ConvTasks<T>(y, x, w, b, d)))
    int status = kConvOk, nonfinite = 0;
#pragma omp parallel num_threads(num_threads()) if (worth_threads(d))
    {
        typename ConvTasks<T>::Scratch s;
        bool ok = false;
        PYVF_CONV_TRY_ALLOC(status, p->scratch(s); ok = true)
#pragma omp for schedule(dynamic, 1) nowait
        for (int64_t t = 0; t < p->ntask; ++t)
            if (ok && !p->run(t, s)) {
#pragma omp atomic write
                nonfinite = 1;
            }
    }
    return conv_status(status, nonfinite);
}

// The backward in one parallel region: the dw tasks' preparation (dyT), one barrier, then the dw
// tasks and the dx tasks as one dynamic loop, and db. Both task sets share the same multiply-adds
// (stride 1: B*Co*P*C*kh*kw), so the set with fewer tasks has the longer ones: it goes first, and
// the other's short tasks fill the threads' tails (a 128-channel 128x128 layer: 32 dw tasks, then 256 dx tasks; a 512-channel
// 8x8 layer: 44 dx tasks, then 512 dw tasks on 16 threads). Every output element is still written
// by one task in one fixed order, so the results are those of the tasks run one after another, on
// any number of threads.
template <typename T, typename Dx, typename Dw>
int backward_tasks(const Dx& dxt, Dw& dwt, T* db, const T* dy, const ConvDims& d) {
    int status = kConvOk, nonfinite = 0, nonfinite_dw = 0, nonfinite_db = 0;
#pragma omp parallel num_threads(num_threads()) if (worth_threads(d))
    {
#pragma omp for schedule(static) nowait
        for (int64_t i = 0; i < dwt.nprep; ++i) dwt.prep(i);
        typename Dx::Scratch sx;
        typename Dw::Scratch sw;
        bool ok = false;
        PYVF_CONV_TRY_ALLOC(status, dxt.scratch(sx); dwt.scratch(sw); ok = true)
#pragma omp barrier
        const bool dw_first = dwt.ntask <= dxt.ntask;
        const int64_t first = dw_first ? dwt.ntask : dxt.ntask;  // tasks t < first: the first set's
#pragma omp for schedule(dynamic, 1) nowait
        for (int64_t t = 0; t < dwt.ntask + dxt.ntask; ++t) {
            if (!ok) continue;
            const int64_t i = t < first ? t : t - first;
            if ((t < first) == dw_first) {
                if (!dwt.run(i, sw)) {
#pragma omp atomic write
                    nonfinite_dw = 1;
                }
            } else if (!dxt.run(i, sx)) {
#pragma omp atomic write
                nonfinite = 1;
            }
        }
#pragma omp for schedule(static) nowait
        for (int64_t o = 0; o < d.Co; ++o)
            if (!db_sum(db, dy, d, o)) {
#pragma omp atomic write
                nonfinite_db = 1;
            }
    }
    return backward_status(status, nonfinite, nonfinite_dw, nonfinite_db);
}

// The dx task set of a backward (ConvTasks on the flipped weights for stride 1, else
// StridedDxTasks), then backward_tasks with the dw task set Dw.
template <typename T, typename Dw>
int backward_with(T* dx, T* dw, T* db, const T* x, const T* w, const T* dy, const ConvDims& d) {
    std::unique_ptr<Dw> dwt;
    PYVF_CONV_OR_OOM(dwt.reset(new Dw(dw, x, dy, d)))
    if (d.stride == 1) {
        // forward was y[o, u, v] = sum w[o, c, i, j] x[c, u + i - pt, v + j - pl], so
        // dx[c, yy, xx] = sum over o, i, j of w[o, c, i, j] dy[o, yy + pt - i, xx + pl - j]
        //              = conv(dy, wf)[c, yy, xx], wf[c, o, i', j'] = w[o, c, kh-1-i', kw-1-j'],
        // padded (kh-1-pt, kh-1-pb, kw-1-pl, kw-1-pr): dy's rows yy + i' - (kh-1-pt).
        const ConvDims t{d.B,  d.Co, d.Ho, d.Wo, d.C, d.kh, d.kw, 1, d.kh - 1 - d.pt, d.kh - 1 - d.pb,
                         d.kw - 1 - d.pl, d.kw - 1 - d.pr, d.Hi, d.Wi};
        // (wf read in place from w by the tasks: ConvTasks' flipped)
        std::unique_ptr<ConvTasks<T>> dxt;
        PYVF_CONV_OR_OOM(dxt.reset(new ConvTasks<T>(dx, dy, w, nullptr, t, true)))
        return backward_tasks(*dxt, *dwt, db, dy, d);
    }
    std::unique_ptr<StridedDxTasks<T>> dxt;
    PYVF_CONV_OR_OOM(dxt.reset(new StridedDxTasks<T>(dx, w, dy, d)))
    return backward_tasks(*dxt, *dwt, db, dy, d);
}

}  // namespace

// =========================================================================================
// Fast kernels

template <typename T> int conv2d_forward(T* y, const T* x, const T* w, const T* b, const ConvDims& d) {
    return conv_gemm<T>(y, x, w, b, d);
}

template <typename T>
int conv2d_backward(T* dx, T* dw, T* db, const T* x, const T* w, const T* dy, const ConvDims& d) {
    // dw on the register tile of ptr_gemm where Co fills a vector, except an unpadded 1x1 on
    // images of >= 32x32 pixels, where the lane sums over x read in place measured faster
    // (1.3-1.4x; 1.2-2.2x slower below)
    if (d.B * d.C * d.Hi * d.Wi == 0) {
        // x empty (B or C = 0, or an image side 0 that padding alone covers): y was b alone, so
        // dx has no elements, dw = 0 and db the sums of dy. The task sets below divide by C and
        // by the tiles' pixels, so they never see these shapes.
        std::fill(dw, dw + d.Co * d.C * d.kh * d.kw, T(0));
        int nonfinite_db = 0;
        for (int64_t o = 0; o < d.Co; ++o) nonfinite_db |= !db_sum(db, dy, d, o);
        return backward_status(kConvOk, 0, 0, nonfinite_db);
    }
    const bool direct = d.kh == 1 && d.kw == 1 && d.stride == 1 && !d.pt && !d.pb && !d.pl && !d.pr;
    if (d.Co >= kW<T> && !(direct && d.Ho * d.Wo >= 1024))
        return backward_with<T, DwGemmTasks<T>>(dx, dw, db, x, w, dy, d);
    return backward_with<T, DwLanesTasks<T>>(dx, dw, db, x, w, dy, d);
}

template int conv2d_forward<float>(float*, const float*, const float*, const float*, const ConvDims&);
template int conv2d_forward<double>(double*, const double*, const double*, const double*, const ConvDims&);
template int conv2d_backward<float>(float*, float*, float*, const float*, const float*, const float*,
                                    const ConvDims&);
template int conv2d_backward<double>(double*, double*, double*, const double*, const double*, const double*,
                                     const ConvDims&);

}  // namespace pyvf
