// LayerNorm over the last axis (layernorm.cpp). M rows of d elements, C order; outputs overwritten.
#pragma once

#include <cstdint>

namespace pyvf {

// y, xhat (M, d), rstd (M,). Returns the number of rows where x - mean(x) overflows T (their
// outputs are then unspecified).
template <typename T>
int64_t layernorm_forward(T* y, T* xhat, T* rstd, const T* x, const T* gamma, const T* beta, int64_t M, int64_t d,
                          double eps);
// dx (M, d), dgamma, dbeta (d,).
template <typename T>
void layernorm_backward(T* dx, T* dgamma, T* dbeta, const T* dy, const T* xhat, const T* rstd, const T* gamma,
                        int64_t M, int64_t d);

}  // namespace pyvf
