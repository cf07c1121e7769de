// Branching attention (docs/math.md §2): declarations shared by the kernel and the bindings.
#pragma once

#include <cstdint>

namespace pyvf {

// Sizes of q, k, v, o, do: (R, B, H, N, L, dh), C order. Row 0 is the trunk, rows 1..R-1
// the branches; block (r, i) is the L tokens of view i in row r.
struct AttnDims {
    int64_t R, B, H, N, L, dh;
};

// Status codes returned by the kernels (0 = ok).
enum AttnStatus : int { kAttnOk = 0, kAttnLogitOverflow = 1, kAttnOutOfMemory = 2 };

// Fast kernel: online softmax over the attended blocks only.
//   o   (R, B, H, N, L, dh)  output, overwritten
//   lse (R, B, H, N, L)      float64, overwritten: log sum_k exp(scale * q.k) over attended keys
// Returns kAttnLogitOverflow (and leaves o, lse unspecified) when a logit is not finite.
template <typename T>
int attn_forward(T* o, double* lse, const T* q, const T* k, const T* v, AttnDims d, T scale);

// Fast backward: dq, dk, dv (R, B, H, N, L, dh) are overwritten (not accumulated).
template <typename T>
int attn_backward(T* dq, T* dk, T* dv, const double* lse, const T* q, const T* k, const T* v,
                  const T* o, const T* dout, AttnDims d, T scale);

// Plain loops, obviously correct, O(T) per query, double accumulators: the C++ oracle for the
// fast kernel (tests compare the two). Same arguments and outputs.
template <typename T>
int attn_forward_plain(T* o, double* lse, const T* q, const T* k, const T* v, AttnDims d, T scale);
template <typename T>
int attn_backward_plain(T* dq, T* dk, T* dv, const double* lse, const T* q, const T* k,
                        const T* v, const T* o, const T* dout, AttnDims d, T scale);

// The scene cache's softmax (pyvf/nn/attention.py context_attention_forward), in place. The
// logits of R query rows' blocks, for G = B H heads, kept transposed (keys as rows, queries as
// columns) in two parts: sc (G, C, R L) against the C cached context keys and so (R G, L, L)
// against each block's own L keys (block r G + g). Every logit s becomes exp(s - m), m the
// largest logit of its query over both parts; m and denom (the sum of the exps, accumulated in
// double) are written, (R G, L) each.
template <typename T>
void context_softmax(T* sc, T* so, T* m, T* denom, int64_t R, int64_t G, int64_t L, int64_t C);

}  // namespace pyvf
