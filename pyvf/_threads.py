"""The threads of this process's numerical work: pyvf's C++ kernels (OpenMP) and numpy's BLAS pool,
set together so that the two never run more threads than asked for between them. Re-exported by
pyvf (`pyvf.set_num_threads`, `with pyvf.threads(n):`, `pyvf.num_threads`); a root helper, so that
any home may use it without importing the public facade.
"""

import math
import numbers
import os
import re

from . import _core

__all__ = ["affinity", "blas_limit", "blas_num_threads", "cores", "cpu_limit", "cpu_limits_text", "num_threads",
           "set_from_environment", "set_num_threads", "threads"]


def cores():
    """The CPUs this process may use: its affinity mask (a container's or taskset's share, not
    the machine's count; os.cpu_count() where the platform has none), and no more than a
    control group's CPU limit allows (cpu_limit(), rounded down, at least 1): a container run
    with `--cpus 2` on a 16-core machine has 16 CPUs in its affinity but the time of 2."""
    n, limit = affinity(), cpu_limit()
    return n if limit is None else max(1, min(n, math.floor(limit)))


def affinity():
    """The CPUs in this process's affinity mask (os.cpu_count() where the platform has none)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def cpu_limits_text():
    """What cores() is taken from, for `pyvf config`: "16 in its affinity, a CPU limit of 2"
    (or "..., no CPU limit")."""
    limit = cpu_limit()
    return f"{affinity()} in its affinity, {'no CPU limit' if limit is None else f'a CPU limit of {limit:g}'}"


def cpu_limit(proc="/proc/self"):
    """The CPU time this process's control groups allow, in CPUs (quota / period), or None where
    none is set or none can be read. cgroup v2's cpu.max and v1's cpu.cfs_quota_us /
    cpu.cfs_period_us, each the smallest along the path from the process's group up to its
    hierarchy's mounted root (a parent's limit binds its children). Neither OpenMP nor numpy's
    BLAS reads them. proc: where mountinfo and cgroup are read (a test's fake tree)."""
    try:
        with open(os.path.join(proc, "mountinfo")) as f:
            mounts = f.read().splitlines()
        with open(os.path.join(proc, "cgroup")) as f:
            groups = [line.split(":", 2) for line in f.read().splitlines()]
    except OSError:  # not Linux, or no /proc
        return None
    limits = []
    for line in mounts:
        # "id parent major:minor root mountpoint options [optional...] - fstype source superoptions"
        pre, sep, post = line.partition(" - ")
        pre, post = pre.split(), post.split()
        if not sep or len(pre) < 5 or len(post) < 3:
            continue
        root, point, fstype = _unescape(pre[3]), _unescape(pre[4]), post[0]
        if fstype == "cgroup2":
            path = next((g[2] for g in groups if len(g) == 3 and g[0] == "0" and g[1] == ""), None)
            read = _v2_limit
        elif fstype == "cgroup" and "cpu" in post[2].split(","):
            path = next((g[2] for g in groups if len(g) == 3 and "cpu" in g[1].split(",")), None)
            read = _v1_limit
        else:
            continue
        if path is None:
            continue
        # the group's folder under the mount point; a group outside the mount's root (a
        # container's view of the host's hierarchy) is read from the mount point itself
        rel = path if root == "/" else path[len(root):] if path == root or path.startswith(root + "/") else ""
        folder = os.path.normpath(point + "/" + rel.strip("/"))
        while True:
            limit = read(folder)
            if limit is not None:
                limits.append(limit)
            if folder == point or len(folder) <= len(point):
                break
            folder = os.path.dirname(folder)
    return min(limits, default=None)


def _unescape(field):
    """mountinfo's octal escapes (a space is \\040) decoded."""
    return re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), field)


def _read_numbers(path):
    try:
        with open(path) as f:
            return f.read().split()
    except OSError:
        return None


def _quota(quota, period):
    """quota / period in CPUs, None for no limit (v2 "max", v1 -1) or a malformed file."""
    try:
        q, p = int(quota), int(period)
    except (TypeError, ValueError):
        return None
    return q / p if q > 0 and p > 0 else None


def _v2_limit(folder):
    words = _read_numbers(os.path.join(folder, "cpu.max"))  # "max 100000" or "200000 100000"
    return _quota(words[0], words[1]) if words and len(words) == 2 and words[0] != "max" else None


def _v1_limit(folder):
    quota = _read_numbers(os.path.join(folder, "cpu.cfs_quota_us"))
    period = _read_numbers(os.path.join(folder, "cpu.cfs_period_us"))
    return _quota(quota[0], period[0]) if quota and period else None


def blas_num_threads():
    """Threads of numpy's BLAS pool now (threadpoolctl; the largest if several BLAS are loaded)."""
    from threadpoolctl import threadpool_info
    return max((i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"), default=1)


def num_threads():
    """Threads the C++ kernels use, in every Python thread (OpenMP; the default: PYVF_NUM_THREADS,
    else OMP_NUM_THREADS, else cores(), set_from_environment)."""
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
    left at the core count spin against the kernels' on a busy machine). One count for the
    process: a kernel called from any Python thread runs on it. For a block only:
    `with pyvf.threads(n): ...`."""
    n = _count(n)
    _core.set_num_threads(n)
    blas_limit(n)


# The most threads a count may ask for. The OpenMP runtime creates them at the next parallel
# region, and where it cannot (the process's thread or memory limits: 100000 threads under a 3 GB
# address-space limit) it ends the process, so a count beyond any machine pyvf runs on is refused
# when it is set. Above the core count is allowed (oversubscription is a thing to measure).
MAX_THREADS = 1024


def _count(n, alternatives=""):
    """n: a thread count, a Python or NumPy integer (not bool) in [1, MAX_THREADS] -> int; else
    ValueError naming n (numbers.Integral: numpy's integers are registered there, numpy's bool is not)."""
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or not 1 <= n <= MAX_THREADS:
        raise ValueError(f"n must be a positive integer of at most {MAX_THREADS}{alternatives}, got {n!r}")
    return int(n)


def set_from_environment(environ=None):
    """pyvf's threads at import (pyvf/__init__.py calls it once): PYVF_NUM_THREADS sets the
    kernels and numpy's BLAS pool (a value that is not a positive integer is an ImportError naming
    it); without it, and unless OMP_NUM_THREADS chose the kernels' count, both are kept to cores()
    where that is fewer than the OpenMP runtime's count or the BLAS pool's (the affinity: a
    container's CPU limit is read by neither OpenMP nor the BLAS, and threads beyond it are
    throttled mid-region; numpy's BLAS counted the CPUs when numpy was imported).
    Returns the count set, or None where nothing was set."""
    environ = os.environ if environ is None else environ
    value = environ.get("PYVF_NUM_THREADS", "").strip()
    if value:  # one setting for the kernels and numpy's BLAS, for a whole process
        # isdecimal, not isdigit: superscripts ('³') are digits that int() refuses
        if not value.isdecimal() or not 1 <= int(value) <= MAX_THREADS:
            raise ImportError(f"PYVF_NUM_THREADS={value!r} is not a positive integer of at most {MAX_THREADS}")
        n = int(value)
    elif environ.get("OMP_NUM_THREADS", "").strip():
        return None
    else:
        n = cores()
        # numpy's BLAS too: it sized its pool when numpy was imported, which may have been before
        # this process was pinned to fewer CPUs (OpenMP reads the affinity later, at pyvf's import)
        if n >= _core.num_threads() and n >= blas_num_threads():
            return None
    set_num_threads(n)
    return n


class threads:
    """`with pyvf.threads(n):` pyvf's kernels and numpy's BLAS on n threads inside the block, both
    put back as they were after it. n=None changes nothing."""

    def __init__(self, n):
        self.n, self._old, self._blas = None if n is None else _count(n, " or None"), None, None

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
