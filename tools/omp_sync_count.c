/* How many times one call of pyvf wakes its OpenMP threads: the parallel regions whose if clause
 * held (they ran on the threads), and the barriers met inside regions (GOMP_barrier and the end of
 * a worksharing loop without nowait, GOMP_loop_end, each called by every thread; a region's
 * closing barrier is not counted). Under OMP_WAIT_POLICY=PASSIVE each of them
 * is a futex wake of sleeping threads (csrc/threads.h, RegionEnd), so this count times the wake
 * cost is what a call loses to synchronisation. An LD_PRELOAD shim over libgomp:
 *
 *     gcc -O2 -shared -fPIC tools/omp_sync_count.c -o /tmp/omp_sync_count.so -ldl
 *     cd /tmp && LD_PRELOAD=/tmp/omp_sync_count.so python3 -c '
 *     import ctypes, pyvf; from pyvf.bench import threads
 *     lib = ctypes.CDLL("/tmp/omp_sync_count.so"); lib.omp_sync_regions.restype = lib.omp_sync_barriers.restype = ctypes.c_long
 *     pyvf.set_num_threads(2)
 *     step, _ = threads.prepared(threads.SCALING_CALLS["codebook step, tiny"][0](False))
 *     r, b = lib.omp_sync_regions(), lib.omp_sync_barriers(); step()
 *     print("regions", lib.omp_sync_regions() - r, "barriers per thread", (lib.omp_sync_barriers() - b) / 2)'
 *
 * (the barriers are counted on every thread that meets one, also in regions that ran on one
 * thread, where they cost nothing: divide by the thread count for an upper bound per region.)
 * Needs the source tree only as a developer's measurement. */
#define _GNU_SOURCE
#include <dlfcn.h>

static long n_regions = 0, n_barriers = 0;
static unsigned last_threads = 0; /* the thread count the last region asked for (0: OpenMP's default) */

static void* libgomp(void) {
    static void* h = 0;
    if (!h) h = dlopen("libgomp.so.1", RTLD_NOW | RTLD_NOLOAD);
    return h;
}

void GOMP_parallel(void (*fn)(void*), void* data, unsigned num_threads, unsigned flags) {
    static void (*real)(void (*)(void*), void*, unsigned, unsigned) = 0;
    if (!real) real = (void (*)(void (*)(void*), void*, unsigned, unsigned))dlsym(libgomp(), "GOMP_parallel");
    if (num_threads != 1) __atomic_add_fetch(&n_regions, 1, __ATOMIC_RELAXED); /* 1: the if clause was false */
    __atomic_store_n(&last_threads, num_threads, __ATOMIC_RELAXED);
    real(fn, data, num_threads, flags);
}

void GOMP_barrier(void) {
    static void (*real)(void) = 0;
    if (!real) real = (void (*)(void))dlsym(libgomp(), "GOMP_barrier");
    __atomic_add_fetch(&n_barriers, 1, __ATOMIC_RELAXED);
    real();
}

/* the barrier that ends a worksharing loop without nowait (a dynamic loop's end; a static loop's
 * is a GOMP_barrier) */
void GOMP_loop_end(void) {
    static void (*real)(void) = 0;
    if (!real) real = (void (*)(void))dlsym(libgomp(), "GOMP_loop_end");
    __atomic_add_fetch(&n_barriers, 1, __ATOMIC_RELAXED);
    real();
}

long omp_sync_regions(void) { return n_regions; }
long omp_sync_barriers(void) { return n_barriers; }
long omp_sync_last_threads(void) { return last_threads; }
