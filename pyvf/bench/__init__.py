"""pyvf's benchmarks: attention, vq, steps (transformer and codebook), scaling, accuracy, hardcases,
report, each a module whose run() returns its report (a dict, JSON-able), called by `pyvf bench
NAME` (pyvf/cli/bench.py); common.py holds what they share. Every benchmark validates its results
before it times them. torch is imported only inside the functions that use it.
"""

from .common import BLAS_THREAD_VARS

__all__ = ["BLAS_THREAD_VARS"]
