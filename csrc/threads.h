// The kernels' threads (threads.cpp): how many, and whether a call is worth more than one.
#pragma once

#include <atomic>
#include <cstdint>

namespace pyvf {

// The kernels' thread count (1 without OpenMP), and setting it for the whole process: every
// parallel region names it (`num_threads(num_threads())`), so that it holds for the kernels
// whichever thread calls them (omp_set_num_threads sets the calling thread's count only, and a
// Python thread other than the one that set it would get OpenMP's default). 0 (the start):
// OpenMP's default, the affinity's CPUs or OMP_NUM_THREADS. One count per path module; pyvf's
// _core.set_num_threads sets every module loaded and each one loaded later.
inline std::atomic<int> g_num_threads{0};
int num_threads();
void set_num_threads(int n);

// Whether other processes keep the calling thread off the CPU it wants: it waited on a run queue
// for more than a fifth of the time it ran (/proc/self/task/<tid>/schedstat, read at most every
// kBusyRefreshMs; the ratio averaged over the readings, half the weight on the newest; each
// calling thread its own). Busy processes of the same or higher priority on the same cores do
// that; niced background jobs do not (the scheduler gives them the cores only when pyvf's threads
// leave them). Then a short parallel region loses more to a descheduled thread (its barrier waits
// a scheduler time slice) than the second thread gains. The calling thread's waits alone: the
// other threads of the team sleep between regions, and each wake-up waits on a run queue (a few
// us on the 2-core VM, more where an idle core must first wake), a wait that grows with the thread
// count on an idle machine (15 wake-ups a region on 16 threads) where the caller, which never
// sleeps between regions, has none. Measured on the 2-core EPYC VM (2 threads, a tiny codebook
// step and a cached render + localize): the caller's wait/run idle 0.002-0.013 (all threads
// 0.002-0.015), beside 2 busy processes 0.67-0.84 (0.80-0.88), beside 2 niced ones 0.014-0.022
// (0.016-0.025). False where /proc cannot be read.
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

// The end of a parallel region, for the caller's sake. Under OMP_WAIT_POLICY=PASSIVE a thread
// that reaches the region's closing barrier before the others sleeps there until the last one
// wakes it (a futex wake, 20-40 us on a VM); for the master thread that wake is on the caller's
// path, the call returns that much later, and the more threads the likelier the master is not
// the last (1 in 16 on 16). So every thread calls arrive() as the last thing it does in the
// region, and the master spins there until every other thread has arrived (at most
// kMasterSpinNs; not while oversubscribed(), when a spinning master would hold a core another
// process wants): it reaches the barrier last and passes it without sleeping. Measured on the
// 2-core EPYC VM by tools/omp_region_end.cpp (2 threads, 30 us of other work between regions),
// the time of a region over its work: 41-43 -> 26-30 us (50 us of work per thread), 48-67 ->
// 26-32 us (100 us), 45-48 -> 22-27 us (400 us). No result depends on it.
//     RegionEnd end;                   // before the region
//     #pragma omp parallel num_threads(num_threads()) if (...)
//     { ... #pragma omp for nowait ...; end.arrive(); }
constexpr int64_t kMasterSpinNs = 100000;
class RegionEnd {
  public:
    void arrive();

  private:
    std::atomic<int> arrived_{0};  // threads other than the master that have arrived
};

}  // namespace pyvf
