// The optimiser's update, fused (optim.cpp). Flat arrays of n elements, one dtype.
#pragma once

#include <cstdint>

namespace pyvf {

// The scalars of one Adam/AdamW update, already rounded to the parameters' dtype T (as NumPy
// rounds a Python float that meets a float32 array): b1, 1 - b1, b2, 1 - b2; torch: a = lr / bc1,
// sbc2 = sqrt(bc2); keras: a = lr sqrt(bc2) / bc1 (sbc2 unused); eps; decay = 1 - lr wd.
template <typename T> struct AdamScalars {
    T b1, c1, b2, c2, a, sbc2, eps, decay;
    bool keras, decayed;
};

// Whether the update of every element is finite (nothing written).
template <typename T> bool adam_check(const T* p, const T* m, const T* v, const T* g, int64_t n,
                                      const AdamScalars<T>& s);
// The update in place: p, m and v overwritten.
template <typename T> void adam_apply(T* p, T* m, T* v, const T* g, int64_t n, const AdamScalars<T>& s);

// Gradient clipping: sumsq = sum of x_i^2 in double (bitwise the same for any thread count),
// amax = max |x_i|; and x *= c in place.
template <typename T> void sum_squares(const T* x, int64_t n, double* amax, double* sumsq);
template <typename T> void scale_by(T* x, int64_t n, T c);

}  // namespace pyvf
