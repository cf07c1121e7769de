// Nearest code (vq.cpp): outputs index (M,) int64 and sq_dist (M,), overwritten; inputs x (M, D),
// codes (K, D).
#pragma once

#include <cstdint>

namespace pyvf {

template <typename T>
void vq_nearest(int64_t* index, T* sq_dist, const T* x, const T* codes, int64_t M, int64_t K, int64_t D);

// The re-rank's exact distance sum_i (x_i - e_i)^2 in double, every operation rounded once, and
// the same of both vectors times 2^p (vq_exact.cpp, compiled without fused multiply-adds).
template <typename T> double exact_sq_distance(const T* x, const T* e, int64_t D);
template <typename T> double exact_sq_distance_scaled(const T* x, const T* e, int64_t D, int p);

}  // namespace pyvf
