"""Time and memory of one call, measured: what the demo (pyvf demo) and the benchmarks
(pyvf bench ..., pyvf/bench/) print. NumPy and the standard library only.

    seconds, times = median_time(fn, repeat=5, warmup=1)
    result, extra = peak_memory(fn)   # bytes of resident memory fn() needed above what was resident before
    memory_method()                   # how peak_memory measures, for printing beside its numbers

peak_memory measures the process's resident memory (Linux VmHWM), so it covers every
allocation the call makes: NumPy arrays, C++ std::vector workspace, torch tensors. It counts
the call's outputs too (they are still alive when fn returns), and nothing allocated before
the call: allocate the inputs first, then measure.
"""

import ctypes
import gc
import platform
import statistics
import time
import tracemalloc

import numpy as np

__all__ = ["median_time", "peak_memory", "memory_method", "format_bytes", "rel_err", "cpu_name"]

_STATUS = "/proc/self/status"
_CLEAR_REFS = "/proc/self/clear_refs"


def median_time(fn, repeat=5, warmup=1):
    """Median wall time in seconds of `repeat` calls of fn(), after `warmup` untimed calls.

    Returns (median, times), times the list of every timed call's seconds (time.perf_counter).
    """
    if repeat < 1:
        raise ValueError(f"repeat must be at least 1, got {repeat}")
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


# ---------------------------------------------------------------------------------------
# peak memory


def _status_bytes(field):
    """A memory field of /proc/self/status ("VmRSS", "VmHWM"), in bytes."""
    with open(_STATUS) as f:
        for line in f:
            if line.startswith(field + ":"):
                value, unit = line.split()[1:3]
                assert unit == "kB", line
                return int(value) * 1024
    raise OSError(f"{field} not in {_STATUS}")


def _reset_hwm():
    """Reset the kernel's peak-resident counter VmHWM to the current VmRSS (Linux >= 4.0)."""
    with open(_CLEAR_REFS, "w") as f:
        f.write("5")


def _hwm_available():
    try:
        _reset_hwm()
        return _status_bytes("VmHWM") > 0 and _status_bytes("VmRSS") > 0
    except OSError:
        return False


_M_MMAP_THRESHOLD = -3  # glibc <malloc.h>
_MMAP_THRESHOLD = 128 * 1024  # glibc's initial value
_malloc_fixed = False


def _fresh_pages():
    """Make the measured call fault in fresh pages for what it allocates (glibc; elsewhere a no-op).

    glibc keeps freed memory for reuse: its mmap threshold grows (up to 32 MiB) as blocks are
    freed, and a thread's arena keeps its top chunk, which malloc_trim does not release. A call
    that reuses what an earlier call freed would then look as if it needed nothing: measured, the
    second OpenMP thread's backward workspace vanished from the second call on. So on first use
    this fixes the mmap threshold at its initial 128 KiB, for the rest of the process: every block
    of 128 KiB or more is then mapped fresh and unmapped on free (the price: page faults on every
    call, ~3-5% of the attention kernel's time), and trims the heap's free pages before each call.
    """
    global _malloc_fixed
    try:
        libc = ctypes.CDLL(None)
        if not _malloc_fixed:
            libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD)
            _malloc_fixed = True
        libc.malloc_trim(0)
    except (OSError, AttributeError, TypeError):  # not glibc (TypeError: Windows' CDLL(None))
        pass


_HWM = _hwm_available()


def memory_method():
    """One line saying how peak_memory measures on this machine."""
    if _HWM:
        return ("resident memory, Linux VmHWM reset through /proc/self/clear_refs: every "
                "allocation counts (NumPy, C++ workspace, torch); outputs included; blocks >= 128 KiB "
                "mapped fresh on every call (glibc mmap threshold fixed)")
    return ("tracemalloc (no /proc/self/clear_refs here): NumPy and Python allocations only, "
            "C++ workspace and torch are NOT counted; outputs included")


def peak_memory(fn):
    """Run fn() once; return (result, extra_peak_bytes).

    extra_peak_bytes is the peak resident memory of the process while fn ran minus the resident
    memory just before it: the memory the call needed, its outputs included (they are alive when
    fn returns). Inputs allocated before the call do not count. On Linux this reads VmHWM after
    resetting it (every allocation counts, at page granularity, 4 KiB; the kernel's per-CPU
    RSS counters lag by up to a few dozen pages per CPU, so below ~1 MiB it is approximate); elsewhere it falls
    back to tracemalloc, which sees NumPy's allocations only (memory_method() says which).
    Call fn once before measuring to keep one-time costs (thread pools, lazy imports) out.
    On glibc the first call changes malloc's policy for the rest of the process: see _fresh_pages.
    """
    gc.collect()
    _fresh_pages()
    if _HWM:
        before = _status_bytes("VmRSS")
        _reset_hwm()
        result = fn()
        peak = _status_bytes("VmHWM")
        return result, max(peak - before, 0)
    started = not tracemalloc.is_tracing()
    if started:
        tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        before = tracemalloc.get_traced_memory()[0]
        result = fn()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        if started:
            tracemalloc.stop()
    return result, max(peak - before, 0)


# ---------------------------------------------------------------------------------------
# printing helpers


def format_bytes(n):
    """1536 -> '1.5 KiB'; powers of 1024, three significant figures."""
    n = float(n)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(n) < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.3g} {unit}"
        n /= 1024
    raise AssertionError("unreachable")


def rel_err(x, ref):
    """max |x - ref| / max |ref|: the largest error relative to the largest reference entry
    (an elementwise relative error is meaningless where ref is near 0). Computed in float64."""
    x = np.asarray(x, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    if x.shape != ref.shape:
        raise ValueError(f"shapes differ: {x.shape} vs {ref.shape}")
    scale = np.abs(ref).max()
    return float(np.abs(x - ref).max() / (scale if scale > 0 else 1.0))


def run_worker(module, *args):
    """Run `python -m module *args` in a fresh process and return the JSON object printed on its
    last line: for benchmarks that keep each framework's thread pools in a process of its own.

    The worker starts in the folder that holds this process's pyvf package, so that it imports
    the same pyvf (`python -m` puts the working folder first on sys.path: started from a source
    checkout, it would import the unbuilt source tree)."""
    import json
    import os
    import subprocess
    import sys

    import pyvf
    holds_pyvf = os.path.dirname(os.path.dirname(os.path.abspath(pyvf.__file__)))
    cmd = [sys.executable, "-m", module, *map(str, args)]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=holds_pyvf)
    if proc.returncode:
        raise RuntimeError(f"worker {' '.join(cmd[1:])} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def cpu_name():
    """The processor's model name (/proc/cpuinfo's "model name"; platform.processor() elsewhere)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"
