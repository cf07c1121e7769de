"""glibc malloc's policy for freed memory: kept for the next allocations (reuse_freed_memory, for
speed: every pyvf command calls it; else glibc unmaps large blocks on free and every training step
page-faults its activations in again), or mapped fresh (map_fresh_pages, for measuring memory)."""

import ctypes
import platform

__all__ = ["reuse_freed_memory", "map_fresh_pages"]

# glibc <malloc.h>, and its initial values
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4
_DEFAULT_THRESHOLD, _DEFAULT_MMAP_MAX = 128 * 1024, 65536


def _glibc():
    """This process's C library when it is glibc (its mallopt typed), else None."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    libc = ctypes.CDLL(None)
    libc.mallopt.argtypes, libc.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return libc


def reuse_freed_memory():
    """Large blocks from the heap, never returned (mallopt M_MMAP_MAX = 0, M_TRIM_THRESHOLD = -1):
    resident memory stays at its peak. Returns True when in effect, False where libc is not glibc."""
    libc = _glibc()
    return libc is not None and libc.mallopt(_M_MMAP_MAX, 0) == 1 and libc.mallopt(_M_TRIM_THRESHOLD, -1) == 1


def map_fresh_pages():
    """For pyvf.bench.common.peak_memory: blocks of 128 KiB or more mmapped fresh (the threshold
    fixed) and the heap's free pages returned now, so that a call cannot reuse what an earlier one
    freed. For the rest of the process (reuse_freed_memory undone); a no-op without glibc."""
    libc = _glibc()
    if libc is not None:
        for param, value in ((_M_MMAP_MAX, _DEFAULT_MMAP_MAX), (_M_MMAP_THRESHOLD, _DEFAULT_THRESHOLD),
                             (_M_TRIM_THRESHOLD, _DEFAULT_THRESHOLD)):
            libc.mallopt(param, value)
        libc.malloc_trim(0)
