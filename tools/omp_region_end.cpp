// What a parallel region costs over its work under OMP_WAIT_POLICY=PASSIVE, with and without the
// master arriving last at the closing barrier (csrc/threads.h, RegionEnd): the measurement behind
// RegionEnd. A loop of regions, each 4 x P tasks of work/4 us on P threads (so `work` us per
// thread) after `gap` us of other work on the master (the Python between two kernel calls).
//
//     g++ -O2 -fopenmp tools/omp_region_end.cpp -o /tmp/region_end
//     for mode in 0 1 0 1; do OMP_WAIT_POLICY=PASSIVE OMP_NUM_THREADS=2 /tmp/region_end 50 $mode 30; done
//
// mode 0: the plain region (a thread that ends its share first sleeps in the closing barrier,
// and the master is woken by a futex when it was not the last); mode 1: the master spins until
// the others have arrived (RegionEnd's rule, without its 100 us cap and its load check). Prints
// the median of 400 regions and its excess over the work. Run on an otherwise idle machine.
#include <omp.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <vector>

static double now_us() {
    return std::chrono::duration<double, std::micro>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

static volatile double sink;

static void work(double us) {  // busy for `us` microseconds
    const double t0 = now_us();
    double s = 0;
    while (now_us() - t0 < us) s += 1;
    sink = s;
}

int main(int argc, char** argv) {
    if (argc != 4) {
        std::fprintf(stderr, "usage: %s WORK_US MODE(0|1) GAP_US\n", argv[0]);
        return 2;
    }
    const double us = std::atof(argv[1]), gap = std::atof(argv[3]);
    const int mode = std::atoi(argv[2]), P = omp_get_max_threads();
    std::vector<double> ts;
    for (int it = 0; it < 400; ++it) {
        work(gap);
        std::atomic<int> arrived{0};
        const double t0 = now_us();
#pragma omp parallel
        {
#pragma omp for schedule(dynamic, 1) nowait
            for (int t = 0; t < 4 * P; ++t) work(us / 4);
            if (mode == 1) {
                if (omp_get_thread_num() == 0)
                    while (arrived.load(std::memory_order_acquire) < omp_get_num_threads() - 1) {
                    }
                else
                    arrived.fetch_add(1, std::memory_order_release);
            }
        }
        ts.push_back(now_us() - t0);
    }
    std::sort(ts.begin(), ts.end());
    const double med = ts[ts.size() / 2];
    std::printf("threads %d, work %.0f us per thread, mode %d, gap %.0f us: median %.1f us, %.1f us over the work\n", P,
                us, mode, gap, med, med - us);
    return 0;
}
