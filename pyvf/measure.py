"""The old home of the benchmarks' time and memory helpers, now pyvf/bench/common.py (and rel_err
pyvf/verify/compare.py, public as pyvf.rel_err): kept so that `from pyvf.measure import
peak_memory` (the tests' memory checks) goes on working. New code imports pyvf.bench.common."""

from .bench.common import cpu_name, format_bytes, median_time, memory_method, peak_memory
from .verify.compare import rel_err

__all__ = ["median_time", "peak_memory", "memory_method", "format_bytes", "rel_err", "cpu_name"]
