// The kernels' threads: how many, and whether a call is worth more than one.
#pragma once

#include <atomic>
#include <cstdint>

#ifdef PYVF_OPENMP
#include <omp.h>
#endif

namespace pyvf {

// The kernels' thread count (1 without OpenMP) for the whole process, named by every parallel
// region (omp_set_num_threads would set the calling thread's only). 0: OpenMP's default.
inline std::atomic<int> g_num_threads{0};
inline int num_threads() {
#ifdef PYVF_OPENMP
    const int n = g_num_threads.load(std::memory_order_relaxed);
    return n > 0 ? n : omp_get_max_threads();
#else
    return 1;
#endif
}
inline void set_num_threads(int n) { g_num_threads.store(n > 0 ? n : 0, std::memory_order_relaxed); }

// A call goes parallel when its work (in the kernel's units) reaches `threshold` (no result depends
// on it). g_force_parallel: the tests' small shapes run the parallel loops too.
inline std::atomic<bool> g_force_parallel{false};
// Below this many multiply-adds (about 50 us on one core) a product runs on one thread.
constexpr int64_t kParallelFlops = 1 << 20;
inline bool parallel_work(int64_t work, int64_t threshold) {
    return g_force_parallel.load(std::memory_order_relaxed) ? work > 0 : work >= threshold;
}

}  // namespace pyvf
