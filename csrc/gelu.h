// GELU (gelu.cpp). Flat arrays of n elements; outputs overwritten.
#pragma once

#include <cstdint>

namespace pyvf {

template <typename T> void gelu_forward(T* y, const T* x, int64_t n);
template <typename T> void gelu_backward(T* dx, const T* dy, const T* x, int64_t n);

}  // namespace pyvf
