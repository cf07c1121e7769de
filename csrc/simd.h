// simd.h: the vector primitives of the kernels. A vector is a GCC/Clang vector extension of the
// target's widest width (64 bytes with AVX-512, 32 with AVX, 16 otherwise), operated on with the
// plain C++ operators, loaded and stored through memcpy (unaligned, no aliasing trouble). Also the
// register tile (gemm) and an exp that vectorises (exp_vec; std::exp does not without fast-math).
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>

namespace pyvf {

#if defined(__AVX512F__)
constexpr int kVecBytes = 64;
#elif defined(__AVX__)
constexpr int kVecBytes = 32;
#else
constexpr int kVecBytes = 16;
#endif

template <typename T> struct Simd;
template <> struct Simd<float> {
    typedef float V __attribute__((vector_size(kVecBytes)));
    typedef int32_t I __attribute__((vector_size(kVecBytes)));
    static constexpr int W = kVecBytes / 4;
};
template <> struct Simd<double> {
    typedef double V __attribute__((vector_size(kVecBytes)));
    typedef int64_t I __attribute__((vector_size(kVecBytes)));
    static constexpr int W = kVecBytes / 8;
};

template <typename T> constexpr int64_t kW = Simd<T>::W;

inline int64_t ceil_div(int64_t a, int64_t b) { return (a + b - 1) / b; }
inline int64_t round_up(int64_t a, int64_t b) { return ceil_div(a, b) * b; }

template <typename T> inline typename Simd<T>::V vload(const T* p) {
    typename Simd<T>::V v;
    std::memcpy(&v, p, sizeof v);
    return v;
}
template <typename T> inline void vstore(T* p, typename Simd<T>::V v) { std::memcpy(p, &v, sizeof v); }
template <typename T> inline typename Simd<T>::V vset1(T a) {
    typename Simd<T>::V v = {};
    return v + a;
}
template <typename T> inline typename Simd<T>::V vmax(typename Simd<T>::V a, typename Simd<T>::V b) {
    return a > b ? a : b;
}
template <typename T> inline T hsum(typename Simd<T>::V v) {
    T s = 0;
    for (int i = 0; i < Simd<T>::W; ++i) s += v[i];
    return s;
}
// ---------------------------------------------------------------------------------------
// exp for x <= 0 (all the softmax needs: x = logit - running max), vectorised.
// Cody-Waite range reduction x = n*ln2 + r, |r| <= ln2/2, then a polynomial (float: the
// Cephes expf minimax polynomial, degree 6; double: the Cephes exp Pade form), then 2^n
// built in the exponent bits. About 1 ulp (tests/test_attention.py). Below the smallest normal
// result it returns 0 (invisible beside the softmax's max term, exp(0) = 1); -inf gives 0.

inline Simd<float>::V exp_vec(Simd<float>::V x) {
    using V = Simd<float>::V;
    using I = Simd<float>::I;
    const V lo = vset1<float>(-87.33654f);  // exp(lo) = 2^-126, the smallest normal float
    const V xc = x > lo ? x : lo;
    // n = round(x / ln2): adding 1.5*2^23 rounds to an integer in the mantissa
    const V magic = vset1<float>(12582912.0f);
    const V n = (xc * 1.44269504088896341f + magic) - magic;
    V r = xc - n * 0.693359375f;        // ln2 split in two (Cody-Waite), hi part exact in n*hi
    r = r - n * -2.12194440e-4f;
    V p = vset1<float>(1.9875691500e-4f);
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * (r * r) + r + 1.0f;
    const I e = (__builtin_convertvector(n, I) + 127) << 23;  // 2^n, n >= -126
    V two_n;
    std::memcpy(&two_n, &e, sizeof e);
    const V y = p * two_n;
    return x < lo ? vset1<float>(0.0f) : y;
}

inline Simd<double>::V exp_vec(Simd<double>::V x) {
    using V = Simd<double>::V;
    using I = Simd<double>::I;
    const V lo = vset1<double>(-708.3964185322641);  // 2^-1022
    const V xc = x > lo ? x : lo;
    const V magic = vset1<double>(6755399441055744.0);  // 1.5*2^52
    const V n = (xc * 1.4426950408889634073599 + magic) - magic;
    V r = xc - n * 6.93145751953125e-1;
    r = r - n * 1.42860682030941723212e-6;
    // Cephes exp: e^r = 1 + 2 r P(r^2) / (Q(r^2) - r P(r^2))
    const V rr = r * r;
    V P = vset1<double>(1.26177193074810590878e-4);
    P = P * rr + 3.02994407707441961300e-2;
    P = P * rr + 9.99999999999999999910e-1;
    V Q = vset1<double>(3.00198505138664455042e-6);
    Q = Q * rr + 2.52448340349684104192e-3;
    Q = Q * rr + 2.27265548208155028766e-1;
    Q = Q * rr + 2.00000000000000000009e0;
    const V px = r * P;
    const V p = 1.0 + 2.0 * (px / (Q - px));
    const I e = (__builtin_convertvector(n, I) + 1023) << 52;
    V two_n;
    std::memcpy(&two_n, &e, sizeof e);
    const V y = p * two_n;
    return x < lo ? vset1<double>(0.0) : y;
}

// exp of one scalar by the same formula (for tails shorter than a vector).
template <typename T> inline T exp_scalar(T x) {
    typename Simd<T>::V v = vset1<T>(x);
    return exp_vec(v)[0];
}

// ---------------------------------------------------------------------------------------
// gemm: C (M, N) = op(A) (M, K) @ B (K, N), overwritten (ACC false) or added to (ACC true).
// Operands through accessors (conv.cpp passes matrices found through tables): A(i, k) is op(A)'s
// element, A.from(i) the matrix from row i on; B(k) points to row k, B.at(j) is the matrix from
// column j on. Register tile: MR rows of C times NV vectors; for each k, C[i, j..j+NV*W) +=
// A(i, k) * B(k)[j..j+NV*W): every element one sum in increasing k whatever the tile. CONT: the
// accumulators start from C, so a product split along k is bitwise the unsplit one.
template <typename T> struct MatA {  // op(A)[i, k] = p[i * si + k * sk]: A (sk = 1) or a transposed A (si = 1)
    const T* p;
    long si, sk;
    T operator()(int i, int k) const { return p[i * si + k * sk]; }
    MatA from(int i) const { return {p + i * si, si, sk}; }
};
template <typename T> struct MatB {  // row k at p + k * ld
    const T* p;
    long ld;
    const T* operator()(int k) const { return p + k * ld; }
    MatB at(int j) const { return {p + j, ld}; }
};

template <typename T, int MR, int NV, bool ACC, bool CONT, typename A_, typename B_>
inline void gemm_tile(int K, A_ A, B_ B, T* C, long ldc) {
    using V = typename Simd<T>::V;
    constexpr int W = Simd<T>::W;
    V acc[MR][NV];
#pragma GCC unroll 16
    for (int i = 0; i < MR; ++i)
#pragma GCC unroll 8
        for (int v = 0; v < NV; ++v) acc[i][v] = CONT ? vload<T>(C + i * ldc + v * W) : V{};
    for (int k = 0; k < K; ++k) {
        const T* bk = B(k);
        V b[NV];
#pragma GCC unroll 8
        for (int v = 0; v < NV; ++v) b[v] = vload<T>(bk + v * W);
#pragma GCC unroll 16
        for (int i = 0; i < MR; ++i) {
            const T a = A(i, k);
#pragma GCC unroll 8
            for (int v = 0; v < NV; ++v) acc[i][v] += a * b[v];
        }
    }
#pragma GCC unroll 16
    for (int i = 0; i < MR; ++i)
#pragma GCC unroll 8
        for (int v = 0; v < NV; ++v) {
            T* c = C + i * ldc + v * W;
            vstore<T>(c, ACC && !CONT ? vload<T>(c) + acc[i][v] : acc[i][v]);
        }
}

template <typename T, int MR, bool ACC, bool CONT, typename A_, typename B_>
inline void gemm_rows(int N, int K, A_ A, B_ B, T* C, long ldc) {
    constexpr int W = Simd<T>::W;
    int j = 0;
    for (; j + 2 * W <= N; j += 2 * W) gemm_tile<T, MR, 2, ACC, CONT>(K, A, B.at(j), C + j, ldc);
    for (; j + W <= N; j += W) gemm_tile<T, MR, 1, ACC, CONT>(K, A, B.at(j), C + j, ldc);
    // columns past the last full vector: scalar sums in increasing k
    for (; j < N; ++j)
        for (int i = 0; i < MR; ++i) {
            T s = CONT ? C[i * ldc + j] : T(0);
            for (int k = 0; k < K; ++k) s += A(i, k) * B(k)[j];
            C[i * ldc + j] = ACC && !CONT ? C[i * ldc + j] + s : s;
        }
}

// Rows in tiles of MR (2*MR accumulators and 2 vectors of B: AVX-512's 32 registers hold 8 rows,
// AVX2's 16 hold 6, SSE2/NEON 4), the rest as one tile of M % MR rows.
constexpr int kGemmMR = kVecBytes >= 64 ? 8 : kVecBytes == 32 ? 6 : 4;

template <typename T, bool ACC, bool CONT = false, int MR = kGemmMR, typename A_, typename B_>
inline void gemm_ops(int M, int N, int K, A_ A, B_ B, T* C, long ldc) {
    int i = 0;
    for (; i + MR <= M; i += MR) gemm_rows<T, MR, ACC, CONT>(N, K, A.from(i), B, C + i * ldc, ldc);
    A = A.from(i);
    C += i * ldc;
    switch (M - i) {
        case 0: break;
        case 1: gemm_rows<T, 1, ACC, CONT>(N, K, A, B, C, ldc); break;
        case 2: gemm_rows<T, 2, ACC, CONT>(N, K, A, B, C, ldc); break;
        case 3: gemm_rows<T, 3, ACC, CONT>(N, K, A, B, C, ldc); break;
        case 4: if constexpr (MR > 4) gemm_rows<T, 4, ACC, CONT>(N, K, A, B, C, ldc); break;
        case 5: if constexpr (MR > 5) gemm_rows<T, 5, ACC, CONT>(N, K, A, B, C, ldc); break;
        case 6: if constexpr (MR > 6) gemm_rows<T, 6, ACC, CONT>(N, K, A, B, C, ldc); break;
        case 7: if constexpr (MR > 7) gemm_rows<T, 7, ACC, CONT>(N, K, A, B, C, ldc); break;
        case 8: if constexpr (MR > 8) gemm_rows<T, 8, ACC, CONT>(N, K, A, B, C, ldc); break;
        case 9: if constexpr (MR > 9) gemm_rows<T, 9, ACC, CONT>(N, K, A, B, C, ldc); break;
        case 10: if constexpr (MR > 10) gemm_rows<T, 10, ACC, CONT>(N, K, A, B, C, ldc); break;
        case 11: if constexpr (MR > 11) gemm_rows<T, 11, ACC, CONT>(N, K, A, B, C, ldc); break;
    }
}

// gemm_ops on row-major matrices: op(A) = A, stored (M, K), or A^T (TA), A stored (K, M); B (K, N).
template <typename T, bool ACC, bool TA = false, bool CONT = false>
inline void gemm(int M, int N, int K, const T* A, long lda, const T* B, long ldb, T* C, long ldc) {
    gemm_ops<T, ACC, CONT>(M, N, K, MatA<T>{A, TA ? 1 : lda, TA ? lda : 1}, MatB<T>{B, ldb}, C, ldc);
}

// Whether p[0:n) is all finite: x * 0 is 0 for finite x, NaN for inf and NaN. Four accumulators,
// so that the adds' latency does not bound the scan.
template <typename T> inline bool finite_run(const T* p, int64_t n) {
    constexpr int W = Simd<T>::W;
    typename Simd<T>::V a0 = {}, a1 = {}, a2 = {}, a3 = {};
    int64_t i = 0;
    for (; i + 4 * W <= n; i += 4 * W) {
        a0 += vload<T>(p + i) * T(0);
        a1 += vload<T>(p + i + W) * T(0);
        a2 += vload<T>(p + i + 2 * W) * T(0);
        a3 += vload<T>(p + i + 3 * W) * T(0);
    }
    for (; i + W <= n; i += W) a0 += vload<T>(p + i) * T(0);
    T tail = 0;
    for (; i < n; ++i) tail += p[i] * T(0);
    return hsum<T>((a0 + a1) + (a2 + a3)) + tail == 0;
}

// out (cols, rows) = in (rows, cols)^T
template <typename T> inline void transpose(T* out, const T* in, int rows, int cols) {
    for (int i = 0; i < rows; ++i)
        for (int j = 0; j < cols; ++j) out[j * rows + i] = in[i * cols + j];
}

}  // namespace pyvf
