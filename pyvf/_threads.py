"""The threads of this process's numerical work: pyvf's C++ kernels (OpenMP) and numpy's BLAS pool,
set together so that the two never run more threads than asked for between them. Re-exported by
pyvf (`pyvf.set_num_threads`, `with pyvf.threads(n):`, `pyvf.num_threads`); a root helper, so that
any home may use it without importing the public facade.
"""

import os

from . import _core

__all__ = ["blas_limit", "blas_num_threads", "cores", "num_threads", "set_num_threads", "threads"]


def cores():
    """The CPUs this process may run on: its affinity mask (a container's or taskset's share),
    not the machine's count; os.cpu_count() where the platform has no affinity."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def blas_num_threads():
    """Threads of numpy's BLAS pool now (threadpoolctl; the largest if several BLAS are loaded)."""
    from threadpoolctl import threadpool_info
    return max((i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"), default=1)


def num_threads():
    """Threads the C++ kernels use (OpenMP; PYVF_NUM_THREADS, else OMP_NUM_THREADS, sets the default)."""
    return _core.num_threads()


def blas_limit(n):
    """Limit numpy's BLAS pool to n threads (threadpoolctl), pyvf's kernels as they are; returns
    the limiter, also a context (`with blas_limit(1):`; its restore_original_limits() puts the
    previous counts back), or None without threadpoolctl."""
    try:
        from threadpoolctl import threadpool_limits  # a dependency; imported when threads are set
    except ImportError:  # pragma: no cover - installed with pyvf
        return None
    return threadpool_limits(limits=n, user_api="blas")


def set_num_threads(n):
    """Set the threads of this process's numerical work: pyvf's C++ kernels and numpy's BLAS pool
    together, so that the two never run more threads than asked for between them (BLAS threads
    left at the core count spin against the kernels' on a busy machine). For a block only:
    `with pyvf.threads(n): ...`."""
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n < 2 ** 31:
        raise ValueError(f"n must be a positive integer below 2^31, got {n!r}")
    _core.set_num_threads(n)
    blas_limit(n)


class threads:
    """`with pyvf.threads(n):` pyvf's kernels and numpy's BLAS on n threads inside the block, both
    put back as they were after it. n=None changes nothing."""

    def __init__(self, n):
        if n is not None and (isinstance(n, bool) or not isinstance(n, int) or not 1 <= n < 2 ** 31):
            raise ValueError(f"n must be a positive integer below 2^31 or None, got {n!r}")
        self.n, self._old, self._blas = n, None, None

    def __enter__(self):
        if self.n is not None:
            self._old = _core.num_threads()
            _core.set_num_threads(self.n)
            self._blas = blas_limit(self.n)
        return self

    def __exit__(self, *exc):
        if self._old is not None:
            if self._blas is not None:  # first: threadpoolctl's restore may touch OpenMP's count too
                self._blas.restore_original_limits()
            _core.set_num_threads(self._old)
        return False
