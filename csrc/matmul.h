// pyvf's GEMM (matmul.cpp), bound in module.cpp.
#pragma once

#include <cstdint>

namespace pyvf {

enum MatStatus : int { kMatOk = 0, kMatOutOfMemory = 2 };

// c (nb, M, N) = op(a) @ op(b) per entry: a (nb, M, K), or (nb, K, M) transposed when ta; b (nb, K, N),
// or (nb, N, K) transposed when tb; c overwritten; bias (N,) or nullptr, added to every row of c
// after its sum. Every count below 2^31 (the binding checks). Returns kMatOk or kMatOutOfMemory.
template <typename T>
int matmul_batched(T* c, const T* a, const T* b, int64_t nb, int64_t M, int64_t N, int64_t K, bool ta, bool tb,
                   const T* bias = nullptr);

}  // namespace pyvf
