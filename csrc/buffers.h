// Aligned work buffers of the kernels, and their allocation failures.
#pragma once

#include <cstddef>
#include <new>
#include <vector>

#include "kernels.h"

namespace pyvf {

// An exception must not leave an OpenMP region (the process would abort): an allocation failure
// inside one is caught and recorded, and the kernel returns kOutOfMemory.
#define PYVF_TRY_ALLOC(status, ...)                         \
    try {                                                   \
        __VA_ARGS__;                                        \
    } catch (const std::bad_alloc&) {                       \
        _Pragma("omp atomic write") status = kOutOfMemory;  \
    }
// The same outside a region: the kernel returns kOutOfMemory.
#define PYVF_OR_OOM(...)                                    \
    try {                                                   \
        __VA_ARGS__;                                        \
    } catch (const std::bad_alloc&) {                       \
        return kOutOfMemory;                                \
    }

// Work buffers on a cache line; failure throws std::bad_alloc. A Buf's resize zeroes new elements;
// a RawBuf's leaves them unset, for buffers first written inside a parallel region.
template <typename T, bool Zero = true> struct Aligned64 {
    typedef T value_type;
    template <typename U> struct rebind {
        typedef Aligned64<U, Zero> other;
    };
    Aligned64() = default;
    template <typename U> Aligned64(const Aligned64<U, Zero>&) {}
    T* allocate(size_t n) { return static_cast<T*>(::operator new(n * sizeof(T), std::align_val_t(64))); }
    void deallocate(T* p, size_t) { ::operator delete(p, std::align_val_t(64)); }
    // resize's construction of a new element: value-initialised (0) or default (nothing)
    template <typename U> void construct(U* p) {
        if constexpr (Zero)
            ::new ((void*)p) U();
        else
            ::new ((void*)p) U;
    }
    template <typename U> bool operator==(const Aligned64<U, Zero>&) const { return true; }
    template <typename U> bool operator!=(const Aligned64<U, Zero>&) const { return false; }
};
template <typename T> using Buf = std::vector<T, Aligned64<T>>;
template <typename T> using RawBuf = std::vector<T, Aligned64<T, false>>;

}  // namespace pyvf
