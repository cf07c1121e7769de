// The codebook's conv2d kernel (conv.cpp): declarations shared by the kernel and its bindings
// (module.cpp).
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

// Status codes (0 = ok): out of memory (MemoryError), or y (the backward: dx, then dw, then db) not
// finite: finite inputs overflowed, or an input held NaN or inf (ValueError naming the output).
enum ConvStatus : int {
    kConvOk = 0,
    kConvOutOfMemory = 2,
    kConvNonFinite = 3,
    kConvNonFiniteDw = 4,
    kConvNonFiniteDb = 5,
};

// The kernels (implicit GEMM, bitwise the same results for any thread count): forward overwrites y
// (B, Co, Ho, Wo); backward overwrites dx (B, C, Hi, Wi), dw (Co, C, kh, kw), db (Co,).
template <typename T> int conv2d_forward(T* y, const T* x, const T* w, const T* b, const ConvDims& d);
template <typename T>
int conv2d_backward(T* dx, T* dw, T* db, const T* x, const T* w, const T* dy, const ConvDims& d);

}  // namespace pyvf
