// Elementwise kernels (elementwise.cpp). Flat arrays of n elements; outputs overwritten.
#pragma once

#include <cstdint>

namespace pyvf {

template <typename T> void gelu_forward(T* y, const T* x, int64_t n);
template <typename T> void gelu_backward(T* dx, const T* dy, const T* x, int64_t n);

// The attention's heads (pyvf/nn/attention.py): a token-major array tok (T tokens, ld columns)
// and a head-major one hd (RB, H, NL, dh), T = RB NL; columns col + h dh ... of token t of
// group rb (t = rb NL + nl) are hd[rb, h, nl, :]. split copies tok into hd, merge hd into tok.
template <typename T> void heads_split(T* hd, const T* tok, int64_t RB, int64_t NL, int64_t H, int64_t dh, int64_t ld,
                                       int64_t col);
template <typename T> void heads_merge(T* tok, const T* hd, int64_t RB, int64_t NL, int64_t H, int64_t dh, int64_t ld,
                                       int64_t col);

// out = a + b (n elements; out may be a or b); out (N,) = a (M, N) summed over its rows in
// increasing row (0 when M = 0).
template <typename T> void add(T* out, const T* a, const T* b, int64_t n);
template <typename T> void column_sums(T* out, const T* a, int64_t M, int64_t N);
// Nearest-neighbour x2 upsampling of `rows` rows of w pixels (y: 2 rows x 2 w per row of x), and
// its backward (dx: the sum of each 2x2 block of dy).
template <typename T> void upsample2x(T* y, const T* x, int64_t rows, int64_t w);
template <typename T> void upsample2x_backward(T* dx, const T* dy, int64_t rows, int64_t w);

}  // namespace pyvf
