"""The machine's facts and a timer, for every home that says where and how fast it ran
(pyvf/bench/common.py re-exports them): the standard library only."""

import platform
import statistics
import time

__all__ = ["median_time", "cpu_name"]


def median_time(fn, repeat=5, warmup=1):
    """(median, times): the wall seconds of `repeat` calls of fn() after `warmup` untimed calls."""
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

