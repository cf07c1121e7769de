// The kernels' threads (threads.cpp): how many, and whether a call is worth more than one.
#pragma once

#include <atomic>
#include <cstdint>

namespace pyvf {

// OpenMP's thread count for the kernels (1 without OpenMP), and setting it.
int num_threads();
void set_num_threads(int n);

// Whether this process's threads are kept off the CPUs they want: its threads waited on a run
// queue for more than a fifth of the time they ran (/proc/self/task/*/schedstat, read at most
// every kBusyRefreshMs, a reading costs ~30 us; the ratio averaged over the readings, half the
// weight on the newest). Busy processes of the same or
// higher priority on the same cores do that; niced background jobs do not (the scheduler gives
// them the cores only when pyvf's threads leave them). Then a short parallel region loses more
// to a descheduled thread (its barrier waits a scheduler time slice) than the second thread
// gains. False where /proc cannot be read.
constexpr int64_t kBusyRefreshMs = 50;
bool oversubscribed();

// Every kernel's choice of its threads: work (in the kernel's own units) at least `threshold`,
// and, while oversubscribed(), at least kBusyFactor times that (a few ms of work). No result
// depends on it: every kernel's result is the same on any thread count.
constexpr int64_t kBusyFactor = 64;
// For the tests: while set, every call with any work runs on the threads (the thresholds are
// skipped), so that the tests' small shapes run the parallel loops too. One flag per path module.
inline std::atomic<bool> g_force_parallel{false};
inline bool parallel_work(int64_t work, int64_t threshold) {
    if (g_force_parallel.load(std::memory_order_relaxed)) return work > 0;
    return work >= threshold && (work >= threshold * kBusyFactor || !oversubscribed());
}

}  // namespace pyvf
