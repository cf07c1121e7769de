// The kernels' threads: how many, and whether a call is worth more than one.
#pragma once

#include <atomic>
#include <cstdint>

#ifdef PYVF_OPENMP
#include <omp.h>
#endif

namespace pyvf {

// The kernels' thread count (1 without OpenMP), for the whole process: every parallel region
// names it (`num_threads(num_threads())`), so that it holds whichever Python thread calls a
// kernel (omp_set_num_threads sets the calling thread's count only). 0 (the start): OpenMP's
// default, the affinity's CPUs or OMP_NUM_THREADS. One count per path module; pyvf._core's
// set_num_threads sets every module loaded and each one loaded later.
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

// A call goes parallel when its work (in the kernel's own units) reaches `threshold`: below it
// waking the threads costs more than they gain. No result depends on it: every kernel's result
// is the same on any thread count. For the tests, g_force_parallel runs every call with any work
// on the threads, so that their small shapes run the parallel loops too (one flag per module).
inline std::atomic<bool> g_force_parallel{false};
// Below this many multiply-adds (about 50 us on one core) a product runs on one thread.
constexpr int64_t kParallelFlops = 1 << 20;
inline bool parallel_work(int64_t work, int64_t threshold) {
    return g_force_parallel.load(std::memory_order_relaxed) ? work > 0 : work >= threshold;
}

}  // namespace pyvf
