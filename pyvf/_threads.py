"""The threads of this process's numerical work: pyvf's C++ kernels (OpenMP) and numpy's BLAS pool,
set together (`pyvf.set_num_threads`, `with pyvf.threads(n):`, `pyvf.num_threads`)."""

import numbers
import os

from threadpoolctl import threadpool_limits

from . import _core

__all__ = ["num_threads", "set_from_environment", "set_num_threads", "threads"]

# The most threads a count may ask for: the OpenMP runtime ends the process where it cannot create them.
MAX_THREADS = 1024


def num_threads():
    """Threads the C++ kernels use, in every Python thread."""
    return _core.num_threads()


def _count(n):
    """n: a thread count, a Python or NumPy integer (not bool) in [1, MAX_THREADS] -> int."""
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or not 1 <= n <= MAX_THREADS:
        raise ValueError(f"n must be a positive integer of at most {MAX_THREADS}, got {n!r}")
    return int(n)


def set_num_threads(n):
    """Set the threads of pyvf's kernels and numpy's BLAS together (idle BLAS threads spin against the kernels')."""
    n = _count(n)
    _core.set_num_threads(n)
    threadpool_limits(limits=n, user_api="blas")


def set_from_environment(environ=None):
    """pyvf's threads at import: PYVF_NUM_THREADS, where set (else OpenMP's and BLAS's defaults, one
    thread per CPU of the process's affinity). Returns the count set, or None."""
    value = (os.environ if environ is None else environ).get("PYVF_NUM_THREADS", "").strip()
    if not value:
        return None
    if not value.isdecimal() or not 1 <= int(value) <= MAX_THREADS:  # isdecimal: int() refuses '³'
        raise ImportError(f"PYVF_NUM_THREADS={value!r} is not a positive integer of at most {MAX_THREADS}")
    set_num_threads(int(value))
    return int(value)


class threads:
    """`with pyvf.threads(n):` kernels and BLAS on n threads inside the block (n=None: unchanged)."""

    def __init__(self, n):
        self.n, self._old, self._blas = None if n is None else _count(n), None, None

    def __enter__(self):
        if self.n is not None:
            self._old = _core.num_threads()
            _core.set_num_threads(self.n)
            self._blas = threadpool_limits(limits=self.n, user_api="blas")
        return self

    def __exit__(self, *exc):
        if self._old is not None:
            self._blas.restore_original_limits()  # first: it may touch OpenMP's count too
            _core.set_num_threads(self._old)
        return False
