// conv2d, forward and backward, float32 and float64: torch's cross-correlation with any kernel,
// stride and per-side zero padding (the codebook's: 3x3 stride 1 pad 1, the Downsample's 3x3
// stride 2 padded (0, 1, 0, 1), 1x1), docs/math.md §4.
//
// Shapes (kernels.h, ConvDims): x (B, C, Hi, Wi), w (Co, C, kh, kw), b (Co,), y (B, Co, Ho, Wo);
// K = C*kh*kw, P = Ho*Wo. w is read as the matrix w2 (Co, K), columns in (c, i, j) order, and
// cols_b (K, P), cols_b[(c,i,j), (u,v)] = xpad[b, c, stride*u + i, stride*v + j], is the im2col
// matrix of image b, xpad x with its zero padding.
//
// Algorithm: implicit GEMM on simd.h's register tile, never BLAS, Winograd or FFT (which change
// the rounding); cols is never stored whole. Every y and dx element is one dot product in T in
// increasing (c, i, j) order (FMA where the path has it).
//   forward  y_b = w2 @ cols_b + b. Task = (image, tile of output rows or pixels, block of output
//            channels), each writing its own block of y (ConvTasks).
//            stride 1: the R + kh - 1 input rows that R output rows read are copied once, zero
//            padded, into a (C, R + kh - 1, Wo + kw - 1) tile; row (c, i, j) of cols is a shifted
//            window of it, read in place through a table of offsets: the input is copied once, not
//            kh*kw times, and the tile stays in L2. One product per output row, straight into y
//            (rows narrower than 2 vectors: one product over the tile).
//            stride > 1: im2col tiles of about kTileBytes, then the product straight into y.
//   dx       stride 1: the transposed conv is a stride-1 conv, dx = conv(dy, wf) with wf[c, o, i, j]
//            = w[o, c, kh-1-i, kw-1-j] padded (kh-1-pt, kh-1-pb, kw-1-pl, kw-1-pr) (a negative
//            padding crops): the forward's tasks, wf read in place from w through a column table.
//            stride > 1 (the Downsample): dcols = w2[:, blk]^T @ dy tile, then col2im adds each row
//            onto its strided slab of dx; task = (image, block of kCB channels) (StridedDxTasks).
//   dw       dw2^T (K, Co) = sum_b cols_b @ dyT_b, dyT = dy copied channels-last with Co rounded up
//            to whole vectors by zero columns (DwTasks): one broadcast of cols[k, p] times a vector
//            of output channels. cols is read in place from a padded-row tile taken as rows of
//            Wo + kw - 1 pixels (stride 1; dyT gets zero pixels there) or from im2col tiles. Each
//            dw element is summed per (image, tile, chunk of kDwChunk pixels), in that order, a
//            fresh register sum per chunk. Task = (block of kCB input channels, block of output
//            channels).
//   db       sum over images and pixels of dy, in double.
// Threads: one OpenMP region per call; the backward's runs the dw and dx tasks as one dynamic loop.
// The tiles depend on the shapes only and every output element is written by one task in one fixed
// order: bitwise the same for any thread count. Each task checks what it wrote for overflow.
// Reference: pyvf/nn/conv.py conv2d_forward_numpy, conv2d_backward_numpy.
// Test: pytest tests/test_conv.py. Benchmark: pyvf bench codebook.
#include "kernels.h"

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

constexpr int64_t kTileBytes = 128 << 10;     // an im2col tile, or the dw's padded-row tile (L2)
constexpr int64_t kRowTileBytes = 256 << 10;  // the forward's padded-row tile
constexpr int64_t kCB = 8;                    // input channels per dw and strided-dx task
constexpr int64_t kDwChunk = 256;             // pixels per register sum of the dw

// The register tile's operands found through tables (simd.h's gemm_ops):
template <typename T> struct ColTableA {  // A(i, k) = p[i * ld + off[k]]: the flipped weights wf, in place in w
    const T* p;
    long ld;
    const int64_t* off;
    T operator()(int i, int k) const { return p[i * ld + off[k]]; }
    ColTableA from(int i) const { return {p + i * ld, ld, off}; }
};
template <typename T> struct RowPtrA {  // A(i, k) = r[i][k]: the dw's rows of cols
    const T* const* r;
    T operator()(int i, int k) const { return r[i][k]; }
    RowPtrA from(int i) const { return {r + i}; }
};
template <typename T> struct TableB {  // row k at p + off[k]: cols, shifted windows of a padded-row tile
    const T* p;
    const int64_t* off;
    const T* operator()(int k) const { return p + off[k]; }
    TableB at(int j) const { return {p + j, off}; }
};

// Output channels per forward task when (image, pixel tile) tasks are fewer than four per thread:
// blocks of whole register tiles (24 rows) making about four tasks per thread.
inline int64_t out_channel_block(int64_t Co, int64_t tasks) {
    const int64_t want = std::clamp<int64_t>(ceil_div(4 * num_threads(), std::max<int64_t>(tasks, 1)), 1,
                                             std::max<int64_t>(ceil_div(Co, 24), 1));
    return std::max<int64_t>(round_up(ceil_div(Co, want), 24), 24);
}

// Pixels per im2col tile of `rows` rows: about kTileBytes, a multiple of 2 vectors, at most P; the
// ceil(P / np) tiles balanced (a last tile of a few pixels runs at a fraction of the speed).
template <typename T> int64_t tile_pixels(int64_t rows, int64_t P) {
    const int64_t step = 2 * kW<T>;
    if (P <= 0) return 1;
    const int64_t most = std::max(step, kTileBytes / (std::max<int64_t>(rows, 1) * (int64_t)sizeof(T)) / step * step);
    const int64_t np = round_up(ceil_div(P, ceil_div(P, most)), step);
    return std::min(np, std::max<int64_t>(P, 1));
}

// out[q] = 0 for q < lo and hi <= q < m, src[q - lo] for lo <= q < hi.
// Inline vector copy: the rows are short (an image row), a memcpy call costs more than the copy;
// the last partial vector is stored overlapping the one before (same values, no scalar tail).
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

// tile[c, rr, cc] = x[c0 + c, u0 + rr - pt, cc - pl] for c < nc, rr < nrr, cc < Wp, 0 outside x:
// the zero-padded input rows that output rows u0.. of a stride-1 conv read (a negative padding, the
// dx conv's, crops). tile is (nc, Rp, Wp).
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
template <typename T>
void im2col(T* cols, const T* x, const ConvDims& d, int64_t c0, int64_t nc, int64_t p0, int64_t n, int64_t ld) {
    const int64_t s = d.stride, HWi = d.Hi * d.Wi, u0 = p0 / d.Wo, v0 = p0 % d.Wo;
    for (int64_t c = 0; c < nc; ++c)
        for (int64_t i = 0; i < d.kh; ++i)
            for (int64_t j = 0; j < d.kw; ++j) {
                T* row = cols + ((c * d.kh + i) * d.kw + j) * ld;
                const T* xc = x + (c0 + c) * HWi;
                // one segment of output row u per step
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
                        std::fill(out, out + lo, T(0));
                        for (int64_t q = lo; q < hi; ++q) out[q] = xr[s * (q - lo)];
                        std::fill(out + hi, out + m, T(0));
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

// Whether the m rows y[o, 0:n) (leading dimension ld) are all finite.
template <typename T> inline bool rows_finite(const T* y, int64_t m, int64_t ld, int64_t n) {
    bool ok = true;
    for (int64_t o = 0; o < m; ++o) ok = finite_run(y + o * ld, n) && ok;
    return ok;
}


// y = conv(x, w) (+ b when b is not null), stride 1 or more, as a set of tasks (the header's
// forward); run(t) may be called by any thread, in any order, with that thread's scratch. Also the
// stride-1 dx (flipped: y = dx, x = dy, w the forward's weights (C, Co, kh, kw) in these names,
// read as wf[o, c, i', j'] = w[c, o, kh-1-i', kw-1-j'] through the column table aoff).
// Stride 1, rows narrower than 2 vectors (8x8 images; a 1x1 image): one product over the whole
// tile taken as rows of Wp pixels into the scratch, its kw - 1 columns past each row's end
// dropped, so that the register tile still runs on whole vectors.
template <typename T> struct ConvTasks {
    // stride 1: the padded rows (C, Rp, Wp) + W slack, then (narrow rows) the product (cob, nwide);
    // else an im2col tile (K, np)
    using Scratch = Buf<T>;
    T* y;
    const T *x, *w, *b;
    ConvDims d;
    int64_t K, P, HWi, Wp = 0, R = 0, Rp = 0, np = 0, ntile, cob, ncob, ntask, tile_size, nwide = 0;
    int64_t lda;  // w2's element (o, k) is w[o * lda + k], flipped w[o * lda + aoff[k]]
    bool flipped, rows, narrow = false;
    std::vector<int64_t> boff;  // stride 1: row k = (c, i, j) of cols starts at tile + boff[k] (+ r*Wp for row r)
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
        rows = d.stride == 1;
        if (rows) {
            Wp = d.Wo + d.kw - 1;
            // tiles of at most kRowTileBytes, ceil(Ho / R) of about equal rows
            R = std::clamp<int64_t>(kRowTileBytes / (std::max<int64_t>(d.C, 1) * Wp * (int64_t)sizeof(T)) - (d.kh - 1),
                                    1, d.Ho);
            ntile = ceil_div(d.Ho, R), R = ceil_div(d.Ho, ntile), Rp = R + d.kh - 1;
            narrow = d.Wo < 2 * W;
            nwide = round_up((R - 1) * Wp + d.Wo, W);  // columns of the widest narrow-row product
            tile_size = d.C * Rp * Wp + W;
            boff.resize(K);
            for (int64_t c = 0; c < d.C; ++c)
                for (int64_t i = 0; i < d.kh; ++i)
                    for (int64_t j = 0; j < d.kw; ++j) boff[(c * d.kh + i) * d.kw + j] = (c * Rp + i) * Wp + j;
        } else {
            np = tile_pixels<T>(K, P), ntile = ceil_div(P, np), tile_size = K * np;
        }
        cob = out_channel_block(d.Co, d.B * ntile), ncob = ceil_div(d.Co, cob), ntask = d.B * ntile * ncob;
    }

    // throws std::bad_alloc
    void scratch(Scratch& s) const { s.resize(tile_size + (narrow ? std::min(cob, d.Co) * nwide : 0)); }

    // y_b's rows o0 .. o0 + no (at yb), output rows u0 .. u0 + nr (u0 * Wo at yu), from the padded rows in s
    template <typename A_> void row_products(A_ A, int64_t no, int64_t nr, Scratch& s, T* yu) const {
        // AVX-512: 12 rows of C per register tile (a load of B serves more FMAs than with 8)
        constexpr int MR = kVecBytes >= 64 ? 12 : kGemmMR;
        if (narrow) {  // out (no, n) = w2[o0:o0+no] @ cols over the tile's rows of Wp pixels
            const int64_t n = round_up((nr - 1) * Wp + d.Wo, kW<T>);
            T* out = s.data() + tile_size;
            gemm_ops<T, false, false, MR>((int)no, (int)n, (int)K, A, TableB<T>{s.data(), boff.data()}, out, n);
            for (int64_t o = 0; o < no; ++o)
                for (int64_t r = 0; r < nr; ++r) std::copy_n(out + o * n + r * Wp, d.Wo, yu + o * P + r * d.Wo);
            return;
        }
        for (int64_t r = 0; r < nr; ++r)  // y_b[o0:o0+no, u0 + r, :] = w2[o0:o0+no] @ cols(row r)
            gemm_ops<T, false, false, MR>((int)no, (int)d.Wo, (int)K, A, TableB<T>{s.data() + r * Wp, boff.data()},
                                          yu + r * d.Wo, P);
    }

    // task t; false when what it wrote is not finite
    bool run(int64_t t, Scratch& s) const {
        const int64_t bt = t / ncob, bi = bt / ntile, o0 = (t % ncob) * cob, no = std::min(cob, d.Co - o0);
        const T* xb = x + bi * d.C * HWi;  // (C, Hi, Wi)
        const T* wb = w + o0 * lda;        // rows o0 .. o0 + no of w2 (flipped: of wf)
        int64_t p0, n;                     // the task's output pixels
        if (rows) {
            const int64_t u0 = (bt % ntile) * R, nr = std::min(R, d.Ho - u0);
            p0 = u0 * d.Wo, n = nr * d.Wo;
            pad_rows(s.data(), xb, d, 0, d.C, u0, nr + d.kh - 1, Rp, Wp);
            T* yu = y + (bi * d.Co + o0) * P + p0;
            if (flipped)
                row_products(ColTableA<T>{wb, lda, aoff.data()}, no, nr, s, yu);
            else
                row_products(MatA<T>{wb, K, 1}, no, nr, s, yu);
        } else {
            p0 = (bt % ntile) * np, n = std::min(np, P - p0);
            im2col(s.data(), xb, d, 0, d.C, p0, n, n);
            // y_b[o0:o0+no, p0:p0+n] = w2[o0:o0+no] (no, K) @ cols (K, n)
            gemm<T, false>((int)no, (int)n, (int)K, wb, K, s.data(), n, y + (bi * d.Co + o0) * P + p0, P);
        }
        T* yb = y + (bi * d.Co + o0) * P + p0;
        if (b) add_bias_rows(yb, b + o0, no, P, n);
        return rows_finite(yb, no, P, n);
    }
};

// The W / WD double vectors of the elements of a T vector, in order (float -> double is exact), by
// whole-vector conversions (lane by lane compiles to a scalar insert per lane).
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


// dw (the header's): dw2^T (K, Co) = sum over images b of cols_b (K, P) @ dyT_b (P, Co). Stride 1:
// cols is read in place from a padded-row tile of R + kh - 1 input rows, its row k = (c, i, j)
// the tile's contiguous numbers from (c, i, j) on taken as rows of Wq = Wo + kw - 1 pixels, so
// dyT's rows are padded to Wq pixels with zeros, whose products (with finite numbers of the tile)
// add exactly 0. Otherwise im2col tiles. Tasks: (block of kCB input channels, block of whole
// vectors of output channels), each owning its entries of dw. Before the tasks, prep(i) for
// i < nprep fills dyT's row i.
template <typename T> struct DwTasks {
    struct Scratch {
        Buf<T> buf, acc;  // the padded rows (nc, Rp, Wq) or the cols tile (kb, np); acc (kb, ow)
        std::vector<int64_t> aoff;
        std::vector<const T*> arow;
    };
    T* dw;
    const T *x, *dy;
    ConvDims d;
    int64_t khw, K, P, HWi, Wq, Cv, nc_max, kb_max, R, Rp, np, ntile, ncb, ow, nob, ntask, ldt, nprep;
    bool rows;
    RawBuf<T> dyT;  // (B, Ho, Wq, ldt): o < Cv written by prep, zero where o >= Co or v >= Wo

    // throws std::bad_alloc
    DwTasks(T* dw_, const T* x_, const T* dy_, const ConvDims& d_) : dw(dw_), x(x_), dy(dy_), d(d_) {
        constexpr int64_t W = kW<T>;
        khw = d.kh * d.kw, K = d.C * khw, P = d.Ho * d.Wo, HWi = d.Hi * d.Wi;
        rows = d.stride == 1;
        Wq = rows ? d.Wo + d.kw - 1 : d.Wo;  // dyT's row length (pixels)
        Cv = round_up(d.Co, W);              // the output channels computed: whole vectors
        nc_max = std::min(d.C, kCB), kb_max = nc_max * khw;
        R = std::clamp<int64_t>(kTileBytes / (nc_max * Wq * (int64_t)sizeof(T)) - (d.kh - 1), 1, d.Ho);
        Rp = R + d.kh - 1;
        np = rows ? R * d.Wo : tile_pixels<T>(kb_max, P);
        ntile = rows ? ceil_div(d.Ho, R) : ceil_div(P, np);
        ncb = ceil_div(d.C, kCB);
        // output-channel blocks of whole vectors, at most 64 channels: at least two tasks per
        // thread where the input channels alone do not make that many
        const int64_t nob_want =
            std::max<int64_t>({ceil_div(d.Co, 64), std::min(Cv / W, ceil_div(2 * num_threads(), ncb)), 1});
        ow = round_up(std::max<int64_t>(ceil_div(d.Co, nob_want), 1), W), nob = ceil_div(d.Co, ow);
        ntask = ncb * nob;
        // rows ldt apart, one vector more than Cv: rows 2^n bytes apart would fall into a few sets
        // of the L1 cache
        ldt = Cv + W;
        nprep = d.B * d.Ho;
        dyT.resize(d.B * d.Ho * Wq * ldt);
    }

    // dyT[b, u, v, o] = dy[b, o, u, v] for row bu = (b, u), 16 o at a time; 0 for o >= Co and for
    // the padding pixels v >= Wo
    void prep(int64_t bu) {
        const int64_t bi = bu / d.Ho, u = bu % d.Ho;
        const T* src = dy + bi * d.Co * P + u * d.Wo;
        T* dst = dyT.data() + bu * Wq * ldt;
        for (int64_t o0 = 0; o0 < d.Co; o0 += 16)
            for (int64_t v = 0; v < d.Wo; ++v)
                for (int64_t o = o0; o < std::min(o0 + 16, d.Co); ++o) dst[v * ldt + o] = src[o * P + v];
        for (int64_t v = 0; v < Wq; ++v) std::fill(dst + v * ldt + (v < d.Wo ? d.Co : 0), dst + v * ldt + Cv, T(0));
    }

    // throws std::bad_alloc
    void scratch(Scratch& s) const {
        s.buf.resize(rows ? nc_max * Rp * Wq : kb_max * np);
        s.acc.resize(kb_max * ow);
        s.aoff.resize(kb_max);
        s.arow.resize(kb_max);
    }

    // false when an entry it wrote is not finite
    bool run(int64_t t, Scratch& s) const {
        const int64_t c0 = (t / nob) * kCB, nc = std::min(kCB, d.C - c0), kb = nc * khw;
        const int64_t o0 = (t % nob) * ow, no = std::min(ow, d.Co - o0), nv = std::min(ow, Cv - o0);
        for (int64_t k = 0; k < kb; ++k) {  // where row k = (c, i, j) of cols starts in buf
            const int64_t c = k / khw, i = k % khw / d.kw, j = k % d.kw;
            s.aoff[k] = rows ? (c * Rp + i) * Wq + j : k * np;
        }
        std::fill(s.acc.begin(), s.acc.end(), T(0));
        for (int64_t bi = 0; bi < d.B; ++bi)
            for (int64_t tile = 0; tile < ntile; ++tile) {
                const T* xb = x + bi * d.C * HWi;
                const T* Bt;  // dyT's row of the tile's first pixel, column o0
                int64_t nq;   // pixels of the tile (rows: with the zero pixels between its rows)
                if (rows) {
                    const int64_t u0 = tile * R, nr = std::min(R, d.Ho - u0);
                    pad_rows(s.buf.data(), xb, d, c0, nc, u0, nr + d.kh - 1, Rp, Wq);
                    nq = (nr - 1) * Wq + d.Wo;
                    Bt = dyT.data() + ((bi * d.Ho + u0) * Wq) * ldt + o0;
                } else {
                    const int64_t p0 = tile * np;
                    nq = std::min(np, P - p0);
                    im2col(s.buf.data(), xb, d, c0, nc, p0, nq, np);
                    Bt = dyT.data() + (bi * P + p0) * ldt + o0;
                }
                for (int64_t q0 = 0; q0 < nq; q0 += kDwChunk) {
                    for (int64_t k = 0; k < kb; ++k) s.arow[k] = s.buf.data() + s.aoff[k] + q0;
                    // acc (kb, nv) += cols[:, q0:q0+n] @ dyT[q0:q0+n, o0:o0+nv]
                    gemm_ops<T, true>((int)kb, (int)nv, (int)std::min(kDwChunk, nq - q0), RowPtrA<T>{s.arow.data()},
                                      MatB<T>{Bt + q0 * ldt, ldt}, s.acc.data(), ow);
                }
            }
        bool ok = true;  // dw[o0 + o, c0*khw + r] = acc[r, o]
        for (int64_t o = 0; o < no; ++o) {
            T* row = dw + (o0 + o) * K + c0 * khw;
            for (int64_t r = 0; r < kb; ++r) row[r] = s.acc[r * ow + o];
            ok = finite_run(row, kb) && ok;
        }
        return ok;
    }
};

// dx of a stride > 1 conv (the Downsample): forward was y_b = w2 @ cols_b, so dcols_b = w2^T @
// dy_b, then col2im adds each row onto its strided slab of dx. Task = (image, block of kCB
// channels), its tiles in order, so no two tasks write the same dx element.
template <typename T> struct StridedDxTasks {
    using Scratch = Buf<T>;  // dcols (kCB*kh*kw, np)
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
    void scratch(Scratch& s) const { s.resize(std::min(d.C, kCB) * khw * np); }

    // false when what it wrote is not finite
    bool run(int64_t t, Scratch& s) const {
        const int64_t bi = t / ncb, c0 = (t % ncb) * kCB, nc = std::min(kCB, d.C - c0);
        T* dxb = dx + bi * d.C * HWi;
        std::fill(dxb + c0 * HWi, dxb + (c0 + nc) * HWi, T(0));
        for (int64_t tile = 0; tile < ntile; ++tile) {
            const int64_t p0 = tile * np, n = std::min(np, P - p0);
            // dcols (nc*kh*kw, n) = w2[:, c0*khw : (c0+nc)*khw]^T @ dy_b[:, p0:p0+n]
            gemm<T, false, true>((int)(nc * khw), (int)n, (int)d.Co, w + c0 * khw, K, dy + bi * d.Co * P + p0, P,
                                 s.data(), n);
            col2im_add(dxb, s.data(), d, c0, nc, p0, n);
        }
        return finite_run(dxb + c0 * HWi, nc * HWi);
    }
};

// A backward's status: the allocations', then dx's, dw's, db's finiteness.
inline int backward_status(int status, int nonfinite_dx, int nonfinite_dw, int nonfinite_db) {
    if (status != kOk) return status;
    return nonfinite_dx ? kConvNonFinite : nonfinite_dw ? kConvNonFiniteDw : nonfinite_db ? kConvNonFiniteDb : kOk;
}

// The backward in one parallel region: dyT, one barrier, then the dw and dx tasks as one dynamic
// loop (the set with fewer, so longer, tasks first, the other's filling the threads' tails), and db.
template <typename T, typename Dx>
int backward_tasks(const Dx& dxt, DwTasks<T>& dwt, T* db, const T* dy, const ConvDims& d) {
    int status = kOk, nonfinite = 0, nonfinite_dw = 0, nonfinite_db = 0;
#pragma omp parallel num_threads(num_threads()) if (worth_threads(d))
    {
#pragma omp for schedule(static) nowait
        for (int64_t i = 0; i < dwt.nprep; ++i) dwt.prep(i);
        typename Dx::Scratch sx;
        typename DwTasks<T>::Scratch sw;
        bool ok = false;
        PYVF_TRY_ALLOC(status, dxt.scratch(sx); dwt.scratch(sw); ok = true)
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

}  // namespace

template <typename T> int conv2d_forward(T* y, const T* x, const T* w, const T* b, const ConvDims& d) {
    std::unique_ptr<ConvTasks<T>> p;
    PYVF_OR_OOM(p.reset(new ConvTasks<T>(y, x, w, b, d)))
    int status = kOk, nonfinite = 0;
#pragma omp parallel num_threads(num_threads()) if (worth_threads(d))
    {
        typename ConvTasks<T>::Scratch s;
        bool ok = false;
        PYVF_TRY_ALLOC(status, p->scratch(s); ok = true)
#pragma omp for schedule(dynamic, 1) nowait
        for (int64_t t = 0; t < p->ntask; ++t)
            if (ok && !p->run(t, s)) {
#pragma omp atomic write
                nonfinite = 1;
            }
    }
    return backward_status(status, nonfinite, 0, 0);
}

template <typename T>
int conv2d_backward(T* dx, T* dw, T* db, const T* x, const T* w, const T* dy, const ConvDims& d) {
    if (d.B * d.C * d.Hi * d.Wi == 0) {
        // x empty (B or C = 0, or an image side 0 that padding alone covers): y was b alone, so
        // dx has no elements, dw = 0 and db the sums of dy (the tasks divide by C and by pixels)
        std::fill(dw, dw + d.Co * d.C * d.kh * d.kw, T(0));
        int nonfinite_db = 0;
        for (int64_t o = 0; o < d.Co; ++o) nonfinite_db |= !db_sum(db, dy, d, o);
        return backward_status(kOk, 0, 0, nonfinite_db);
    }
    std::unique_ptr<DwTasks<T>> dwt;
    PYVF_OR_OOM(dwt.reset(new DwTasks<T>(dw, x, dy, d)))
    if (d.stride == 1) {
        // forward was y[o, u, v] = sum w[o, c, i, j] x[c, u + i - pt, v + j - pl], so
        // dx[c, yy, xx] = sum over o, i, j of w[o, c, i, j] dy[o, yy + pt - i, xx + pl - j]
        //              = conv(dy, wf)[c, yy, xx], wf[c, o, i', j'] = w[o, c, kh-1-i', kw-1-j'],
        // padded (kh-1-pt, kh-1-pb, kw-1-pl, kw-1-pr): dy's rows yy + i' - (kh-1-pt).
        const ConvDims t{d.B,  d.Co, d.Ho, d.Wo, d.C, d.kh, d.kw, 1, d.kh - 1 - d.pt, d.kh - 1 - d.pb,
                         d.kw - 1 - d.pl, d.kw - 1 - d.pr, d.Hi, d.Wi};
        std::unique_ptr<ConvTasks<T>> dxt;
        PYVF_OR_OOM(dxt.reset(new ConvTasks<T>(dx, dy, w, nullptr, t, true)))
        return backward_tasks(*dxt, *dwt, db, dy, d);
    }
    std::unique_ptr<StridedDxTasks<T>> dxt;
    PYVF_OR_OOM(dxt.reset(new StridedDxTasks<T>(dx, w, dy, d)))
    return backward_tasks(*dxt, *dwt, db, dy, d);
}

template int conv2d_forward<float>(float*, const float*, const float*, const float*, const ConvDims&);
template int conv2d_forward<double>(double*, const double*, const double*, const double*, const ConvDims&);
template int conv2d_backward<float>(float*, float*, float*, const float*, const float*, const float*,
                                    const ConvDims&);
template int conv2d_backward<double>(double*, double*, double*, const double*, const double*, const double*,
                                     const ConvDims&);

}  // namespace pyvf
