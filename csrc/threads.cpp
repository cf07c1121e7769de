// The kernels' threads (threads.h).
#include "threads.h"

#include <chrono>
#include <cstdio>
#include <cstdlib>

#ifdef __linux__
#include <fcntl.h>
#include <sys/syscall.h>
#include <unistd.h>
#endif

#ifdef PYVF_OPENMP
#include <omp.h>
#endif

namespace pyvf {

int num_threads() {
#ifdef PYVF_OPENMP
    const int n = g_num_threads.load(std::memory_order_relaxed);
    return n > 0 ? n : omp_get_max_threads();
#else
    return 1;
#endif
}

void set_num_threads(int n) { g_num_threads.store(n > 0 ? n : 0, std::memory_order_relaxed); }

#ifdef __linux__
namespace {

// The calling thread's time on a CPU and waiting on a run queue (ns, the first two fields of
// /proc/self/task/<tid>/schedstat); false where it cannot be read.
bool thread_schedstat(int64_t& run, int64_t& wait) {
    char path[64], buf[128];
    std::snprintf(path, sizeof path, "/proc/self/task/%ld/schedstat", (long)::syscall(SYS_gettid));
    const int fd = ::open(path, O_RDONLY);
    if (fd < 0) return false;
    const ssize_t n = ::read(fd, buf, sizeof buf - 1);
    ::close(fd);
    if (n <= 0) return false;
    buf[n] = 0;
    char* end;
    run = std::strtoll(buf, &end, 10);
    wait = std::strtoll(end, nullptr, 10);
    return true;
}

}  // namespace

bool oversubscribed() {
    using clock = std::chrono::steady_clock;
    constexpr int64_t kMinRunNs = 2000000;  // a reading over less CPU time than 2 ms keeps the last answer
    // each calling thread's own readings (several Python threads may call the kernels)
    thread_local int64_t next = 0, last_run = -1, last_wait = 0;
    thread_local double ratio = 0;  // wait / run, averaged over the readings
    thread_local bool busy = false;
    const int64_t now = std::chrono::duration_cast<std::chrono::milliseconds>(clock::now().time_since_epoch()).count();
    if (now < next) return busy;
    next = now + kBusyRefreshMs;
    int64_t run, wait;
    if (!thread_schedstat(run, wait)) return busy;
    const int64_t dr = run - last_run, dw = wait - last_wait;  // one thread's counters only grow
    if (last_run < 0) {  // the first reading: start from it
        last_run = run;
        last_wait = wait;
    } else if (dr >= kMinRunNs) {
        // the ratio averaged over the readings, half the weight on the newest: one window in
        // which the other processes happened to be off the cores does not end it
        ratio = 0.5 * ratio + 0.5 * (double)dw / (double)dr;
        busy = ratio > 0.2;
        last_run = run;
        last_wait = wait;
    }
    return busy;
}
#else
bool oversubscribed() { return false; }  // no /proc: the kernels' thresholds as on a quiet machine
#endif

void RegionEnd::arrive() {
#ifdef PYVF_OPENMP
    const int others = omp_get_num_threads() - 1;
    if (others == 0) return;
    if (omp_get_thread_num() != 0) {
        arrived_.fetch_add(1, std::memory_order_release);
        return;
    }
    if (oversubscribed()) return;
    using clock = std::chrono::steady_clock;
    const auto give_up = clock::now() + std::chrono::nanoseconds(kMasterSpinNs);
    while (arrived_.load(std::memory_order_acquire) < others) {
        for (int i = 0; i < 64 && arrived_.load(std::memory_order_relaxed) < others; ++i) {
#if defined(__x86_64__) || defined(__i386__)
            __builtin_ia32_pause();
#elif defined(__aarch64__)
            asm volatile("yield");
#endif
        }
        if (clock::now() > give_up) return;
    }
#endif
}

}  // namespace pyvf
