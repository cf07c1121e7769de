// The optimiser's update, fused (optim.cpp). Flat arrays of n elements, one dtype.
#pragma once

#include <cstdint>

namespace pyvf {

// The scalars of one Adam/AdamW update, already rounded to the parameters' dtype T (as NumPy
// rounds a Python float that meets a float32 array): b1, 1 - b1, b2, 1 - b2; torch: a = lr / bc1,
// sbc2 = sqrt(bc2); keras: a = lr sqrt(bc2) / bc1 (sbc2 unused); eps; decay = 1 - lr wd.
template <typename T> struct AdamScalars {
    T b1, c1, b2, c2, a, sbc2, eps, decay;
    bool keras;
};

// One parameter tensor of the update: n elements of p, its moments m, v and its gradient g,
// and whether it is decayed.
template <typename T> struct AdamTensor {
    T *p, *m, *v;
    const T* g;
    int64_t n;
    bool decayed;
};

// Whether the update of every element of tensor i is finite: ok[i] (nothing written).
template <typename T> void adam_check(const AdamTensor<T>* t, int64_t count, const AdamScalars<T>& s, bool* ok);
// The update in place: every tensor's p, m and v overwritten.
template <typename T> void adam_apply(const AdamTensor<T>* t, int64_t count, const AdamScalars<T>& s);

// Gradient clipping: sumsq = sum of x_i^2 in double (bitwise the same for any thread count),
// amax = max |x_i|; and x *= c in place.
template <typename T> void sum_squares(const T* x, int64_t n, double* amax, double* sumsq);
template <typename T> void scale_by(T* x, int64_t n, T c);

}  // namespace pyvf
