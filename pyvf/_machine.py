"""The machine's facts and a timer: what every home needs to say where and how fast it ran
(the benchmarks' pyvf/bench/common.py re-exports these beside its memory and report helpers).
The standard library and the compiled kernels' module only, so that any home
may import it.

    seconds, times = median_time(fn, repeat=5, warmup=1)   # the one timing helper
    cpu_name()      # the processor's model name
    kernel_line()   # the line every demo starts with: the kernels' instruction-set path
"""

import platform
import statistics
import time

from . import _core

__all__ = ["median_time", "cpu_name", "kernel_line"]


def median_time(fn, repeat=5, warmup=1):
    """Median wall time in seconds of `repeat` calls of fn(), after `warmup` untimed calls.

    Returns (median, times), times the list of every timed call's seconds (time.perf_counter).
    """
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


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


def kernel_line():
    """The line every pyvf demo starts with: which instruction-set path the C++ kernels run
    (pyvf.kernel_path() and pyvf.kernel_paths(), read from _core as they do)."""
    return (f"pyvf kernels: path {_core.current_path()} (this CPU runs {', '.join(_core.available_paths())}; "
            "PYVF_ISA=<path> forces one; `pyvf config` for details)")
