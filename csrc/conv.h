// The codebook's conv2d kernel (conv.cpp);
// declarations shared by the kernels and the bindings (conv_bind.cpp).
#pragma once

#include <cstdint>

namespace pyvf {

// Sizes of one conv2d, torch's cross-correlation:
//   x  (B, C, Hi, Wi)      input images, C order
//   w  (Co, C, kh, kw)     weights, C order; one output channel's weights are K = C*kh*kw numbers
//   b  (Co,)               bias
//   y  (B, Co, Ho, Wo)     Ho = (Hi + pt + pb - kh) / stride + 1, Wo = (Wi + pl + pr - kw) / stride + 1
// Zero padding on each side separately: top pt, bottom pb, left pl, right pr (the Downsample's
// (0, 1, 0, 1) pads only bottom and right, docs/math.md §4). The bindings check every size; the
// kernels assume them consistent and every count (K, C, Co, Hi*Wi, Ho*Wo) below 2^31.
struct ConvDims {
    int64_t B, C, Hi, Wi, Co, kh, kw, stride, pt, pb, pl, pr, Ho, Wo;
};

// Status codes returned by the kernels (0 = ok); the bindings raise kConvOutOfMemory as MemoryError
// and kConvNonFinite (conv2d and GroupNorm: y, or the backward's dx, not finite: finite inputs
// overflowed, or an input held NaN or inf; each task checks what it wrote while it is still in
// cache), kConvNonFiniteDw and kConvNonFiniteDb (the conv2d backward's dw, db, checked the same
// way; dx first, then dw, then db) as ValueError, naming the output (pyvf/conv.py then names the
// input, if one is to blame).
enum ConvStatus : int {
    kConvOk = 0,
    kConvOutOfMemory = 2,
    kConvNonFinite = 3,
    kConvNonFiniteDw = 4,
    kConvNonFiniteDb = 5,
};

// Fast kernels: implicit GEMM on the gemm micro-kernel of simd.h, OpenMP over (image, pixel
// tile) or (channel block) tasks; results bitwise the same for any thread count.
//   forward:  y (B, Co, Ho, Wo) overwritten.
//   backward: dx (B, C, Hi, Wi), dw (Co, C, kh, kw), db (Co,) overwritten (never accumulated).
template <typename T> int conv2d_forward(T* y, const T* x, const T* w, const T* b, const ConvDims& d);
template <typename T>
int conv2d_backward(T* dx, T* dw, T* db, const T* x, const T* w, const T* dy, const ConvDims& d);

}  // namespace pyvf

// The Python bindings (conv_bind.cpp), called from module.cpp's PYBIND11_MODULE. Declared only
// where pybind11 is already included, so the kernels above stay plain C++.
#ifdef PYBIND11_VERSION_MAJOR
namespace pyvf {
void bind_conv(pybind11::module_& m);
}
#endif
