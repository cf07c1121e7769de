// The re-rank's exact squared distances of vq_nearest (vq.cpp): sum_i (x_i - e_i)^2 in double,
// in increasing i, every difference, product and sum rounded once. Its own file because it is
// compiled with -ffp-contract=off (CMakeLists.txt): with GCC's default the avx2 and avx512 paths
// fused t * t + s into one FMA and the baseline path did not, so a float64 row on a tie of this
// sum went to another code on another path (float32 inputs were unaffected: their differences
// and squares are exact in double). -fno-lto keeps the option.
//
// Test: tests/test_vq.py (test_float64_rerank_is_the_plain_sum_on_every_path).
#include "vq.h"

#include <cmath>

namespace pyvf {

template <typename T> double exact_sq_distance(const T* x, const T* e, int64_t D) {
    double s = 0;
    for (int64_t i = 0; i < D; ++i) {
        const double t = (double)x[i] - (double)e[i];
        s += t * t;
    }
    return s;
}

// The same sum with both vectors multiplied by 2^p (exact, unless a component falls below the
// smallest subnormal, far below what decides the sum), for vectors whose distance would overflow
// or underflow double. By ldexp, not a product with 2^p: for float64 subnormals p exceeds 1023
// and 2^p itself is inf (which gave NaN distances and wrong codes).
template <typename T> double exact_sq_distance_scaled(const T* x, const T* e, int64_t D, int p) {
    double s = 0;
    for (int64_t i = 0; i < D; ++i) {
        const double t = std::ldexp((double)x[i], p) - std::ldexp((double)e[i], p);
        s += t * t;
    }
    return s;
}

template double exact_sq_distance<float>(const float*, const float*, int64_t);
template double exact_sq_distance<double>(const double*, const double*, int64_t);
template double exact_sq_distance_scaled<float>(const float*, const float*, int64_t, int);
template double exact_sq_distance_scaled<double>(const double*, const double*, int64_t, int);

}  // namespace pyvf
