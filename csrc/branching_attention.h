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

}  // namespace pyvf
