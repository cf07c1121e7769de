// Elementwise kernels (elementwise.cpp). Flat arrays of n elements; outputs overwritten.
#pragma once

#include <cstdint>

namespace pyvf {

template <typename T> void gelu_forward(T* y, const T* x, int64_t n);
template <typename T> void gelu_backward(T* dx, const T* dy, const T* x, int64_t n);

// Nearest-neighbour x2 upsampling of `rows` rows of w pixels (y: 2 rows x 2 w per row of x), and
// its backward (dx: the sum of each 2x2 block of dy).
template <typename T> void upsample2x(T* y, const T* x, int64_t rows, int64_t w);
template <typename T> void upsample2x_backward(T* dx, const T* dy, int64_t rows, int64_t w);

}  // namespace pyvf
