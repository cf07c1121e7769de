// The kernels' declarations, shared by their files and the bindings (module.cpp). Outputs are
// overwritten, never accumulated into; the bindings check every size, the kernels trust them.
#pragma once

#include <cstdint>

namespace pyvf {

// What a kernel returns (module.cpp raises it): out of memory; an attended logit not finite (the
// attention's o, lse unspecified); a conv output not finite (y, or the backward's dx, dw, db).
enum Status : int { kOk, kAttnLogitOverflow, kOutOfMemory, kConvNonFinite, kConvNonFiniteDw, kConvNonFiniteDb };

// Branching attention (branching_attention.cpp, docs/math.md §2). q, k, v, o, do, dq, dk, dv:
// (R, B, H, N, L, dh), C order; row 0 is the trunk, rows 1..R-1 the branches; block (r, i) is
// the L tokens of view i in row r. lse (R, B, H, N, L) float64: log sum_k exp(scale * q.k) over
// the attended keys.
struct AttnDims {
    int64_t R, B, H, N, L, dh;
    // index of block (r, b, h, i); multiply by L*dh for q/k/v, by L for lse
    int64_t blk(int64_t r, int64_t b, int64_t h, int64_t i) const { return ((r * B + b) * H + h) * N + i; }
    int64_t bs() const { return L * dh; }
    int64_t nblk() const { return R * B * H * N; }
};
template <typename T>
int attn_forward(T* o, double* lse, const T* q, const T* k, const T* v, AttnDims d, T scale);
template <typename T>
int attn_backward(T* dq, T* dk, T* dv, const double* lse, const T* q, const T* k, const T* v,
                  const T* o, const T* dout, AttnDims d, T scale);
// Plain loops, O(T) per query, double accumulators: the C++ oracle of the two above.
template <typename T>
int attn_forward_plain(T* o, double* lse, const T* q, const T* k, const T* v, AttnDims d, T scale);
template <typename T>
int attn_backward_plain(T* dq, T* dk, T* dv, const double* lse, const T* q, const T* k,
                        const T* v, const T* o, const T* dout, AttnDims d, T scale);

// conv2d (conv.cpp), torch's cross-correlation: x (B, C, Hi, Wi), w (Co, C, kh, kw) (K = C*kh*kw
// numbers per output channel), b (Co,), y (B, Co, Ho, Wo), Ho = (Hi + pt + pb - kh) / stride + 1,
// Wo = (Wi + pl + pr - kw) / stride + 1; zero padding top pt, bottom pb, left pl, right pr (the
// Downsample's (0, 1, 0, 1), docs/math.md §4). Every count (K, C, Co, Hi*Wi, Ho*Wo) below 2^31.
struct ConvDims {
    int64_t B, C, Hi, Wi, Co, kh, kw, stride, pt, pb, pl, pr, Ho, Wo;
};
template <typename T> int conv2d_forward(T* y, const T* x, const T* w, const T* b, const ConvDims& d);
template <typename T>
int conv2d_backward(T* dx, T* dw, T* db, const T* x, const T* w, const T* dy, const ConvDims& d);

// GELU (gelu.cpp): flat arrays of n elements.
template <typename T> void gelu_forward(T* y, const T* x, int64_t n);
template <typename T> void gelu_backward(T* dx, const T* dy, const T* x, int64_t n);

// c (nb, M, N) = op(a) @ op(b) per entry (matmul.cpp): a (nb, M, K), or (nb, K, M) when ta; b (nb, K, N),
// or (nb, N, K) when tb; bias (N,) or nullptr, added to every row of c after its sum. Counts below 2^31.
template <typename T>
int matmul_batched(T* c, const T* a, const T* b, int64_t nb, int64_t M, int64_t N, int64_t K, bool ta, bool tb,
                   const T* bias = nullptr);

// Nearest code (vq.cpp): index (M,) int64 and sq_dist (M,) of x (M, D) among codes (K, D).
template <typename T>
void vq_nearest(int64_t* index, T* sq_dist, const T* x, const T* codes, int64_t M, int64_t K, int64_t D);
// The re-rank's exact distance sum_i (x_i - e_i)^2 in double, every operation rounded once, and
// the same of both vectors times 2^p (vq_exact.cpp, compiled without fused multiply-adds).
template <typename T> double exact_sq_distance(const T* x, const T* e, int64_t D);
template <typename T> double exact_sq_distance_scaled(const T* x, const T* e, int64_t D, int p);

}  // namespace pyvf
