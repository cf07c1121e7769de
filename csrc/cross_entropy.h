// Softmax cross-entropy with label smoothing (cross_entropy.cpp). M rows of n logits, C order;
// targets int64 in [0, n); outputs overwritten.
#pragma once

#include <cstdint>

namespace pyvf {

// loss, rowmax (M,), logsum (M,) double: what the backward needs besides the logits.
template <typename T>
void cross_entropy_forward(T* loss, T* rowmax, double* logsum, const T* x, const int64_t* targets, int64_t M,
                           int64_t n, double eps);
// dx (M, n) from dloss (M,) and the forward's logits, rowmax and logsum.
template <typename T>
void cross_entropy_backward(T* dx, const T* dloss, const T* x, const T* rowmax, const double* logsum,
                            const int64_t* targets, int64_t M, int64_t n, double eps);

}  // namespace pyvf
