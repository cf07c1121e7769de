"""glibc malloc's policy for the memory a process frees: kept for its next allocations
(reuse_freed_memory, for speed; every pyvf command calls it), or mapped fresh for each
(map_fresh_pages, for measuring the memory a call needs).

Why: glibc serves each allocation above 32 MiB (and smaller ones once the heap's free top passes
its trim threshold) with a fresh mmap and unmaps it on free, so every training step page-faults its
large activations in again (a paper-size transformer step on 2 cores: 2.9 s of its 17 s, 0.3 s
with reuse_freed_memory on).
"""

import ctypes
import platform

__all__ = ["reuse_freed_memory", "map_fresh_pages"]

# glibc <malloc.h>, and its initial values
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4
_DEFAULT_THRESHOLD, _DEFAULT_MMAP_MAX = 128 * 1024, 65536

_state = {"on": False, "fresh": False}


def _glibc():
    """This process's C library when it is glibc (its mallopt typed), else None."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    libc = ctypes.CDLL(None)
    libc.mallopt.argtypes, libc.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return libc


def reuse_freed_memory():
    """Keep the memory this process frees for its next allocations: large blocks from the heap,
    not fresh mmaps, and the heap's free top never returned (mallopt M_MMAP_MAX = 0,
    M_TRIM_THRESHOLD = -1); the resident memory stays at its peak. Returns True when in effect,
    False where the C library is not glibc (nothing changed)."""
    if _state["on"]:
        return True
    libc = _glibc()
    if libc is None:
        return False
    _state["on"] = libc.mallopt(_M_MMAP_MAX, 0) == 1 and libc.mallopt(_M_TRIM_THRESHOLD, -1) == 1
    _state["fresh"] = False
    return _state["on"]


def map_fresh_pages():
    """For measuring the memory a call needs (pyvf.bench.common.peak_memory): every block of 128 KiB
    or more mapped fresh and unmapped on free, and the heap's free pages returned now, so that a
    call cannot reuse what an earlier one freed and look as if it needed nothing. glibc's defaults
    back, the mmap threshold fixed at 128 KiB (glibc grows it as blocks are freed), for the rest of
    the process (reuse_freed_memory undone). A no-op where the C library is not glibc."""
    libc = _glibc()
    if libc is None:
        return
    if not _state["fresh"]:
        for param, value in ((_M_MMAP_MAX, _DEFAULT_MMAP_MAX), (_M_MMAP_THRESHOLD, _DEFAULT_THRESHOLD),
                             (_M_TRIM_THRESHOLD, _DEFAULT_THRESHOLD)):
            libc.mallopt(param, value)
        _state["fresh"], _state["on"] = True, False
    libc.malloc_trim(0)
