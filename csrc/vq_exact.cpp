// The re-rank's exact squared distances of vq_nearest (vq.cpp): sum_i (x_i - e_i)^2 in double,
// in increasing i, every operation rounded once. Its own file, compiled with -ffp-contract=off
// (CMakeLists.txt), so that no path fuses t * t + s and a float64 tie picks one code on every path.
#include "kernels.h"

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

// The same sum with both vectors times 2^p (exact but below the smallest subnormal), for vectors
// whose distance would overflow or underflow double. By ldexp: for float64 subnormals p > 1023.
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
