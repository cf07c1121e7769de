"""glibc malloc's policy for the memory a process frees: kept for its next allocations
(reuse_freed_memory, for speed), or mapped fresh for each (map_fresh_pages, for measuring memory).

Keeping the memory a process frees for its next allocations (glibc's malloc) means that a loop
whose arrays have the same sizes step after step reuses pages already mapped instead of asking
the kernel for fresh ones. Re-exported by pyvf (`pyvf.reuse_freed_memory`); called by every pyvf
command (pyvf/cli), left to the user in the library.

Why: glibc serves each allocation above 32 MiB (and, once the heap's free top passes its trim
threshold, smaller ones too) with a fresh mmap and unmaps it on free, so every training step
page-faults its large activations in again; with transparent huge pages each fault zeroes 2 MiB.
On a 2-core VM a paper-size transformer step spent 2.9 s of its 17 s in the kernel that way
(its system time, resource.getrusage), 0.3 s with this on. The faults are also a serial part of a
parallel step: a page table is locked while the kernel fills it.
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
    try:
        libc = ctypes.CDLL(None)
        libc.mallopt.argtypes, libc.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
        return libc
    except (OSError, AttributeError):  # pragma: no cover - a glibc without mallopt
        return None


def reuse_freed_memory():
    """Make this process keep the memory it frees for its next allocations: glibc's malloc then
    serves large blocks from its heap, not from fresh mmaps, and never returns the heap's free top
    to the system (mallopt M_MMAP_MAX = 0, M_TRIM_THRESHOLD = -1). The process's resident memory
    stays at its peak until it exits. For a process that runs one kind of loop, as every pyvf
    command does (pyvf.bench's memory measurements put fresh pages back: map_fresh_pages).
    Returns True when in effect (also when already on), False
    where the C library is not glibc (nothing changed)."""
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
    call cannot reuse what an earlier one freed and look as if it needed nothing (measured: the
    second OpenMP thread's backward workspace vanished from the second call on). glibc grows its
    mmap threshold as blocks are freed (up to 32 MiB), so the threshold is fixed at its initial
    128 KiB, mmap allowed again and trimming at its default, for the rest of the process
    (reuse_freed_memory undone); the price is page faults on every call (~3-5% of the attention
    kernel's time). A no-op where the C library is not glibc."""
    libc = _glibc()
    if libc is None:
        return
    if not _state["fresh"]:
        for param, value in ((_M_MMAP_MAX, _DEFAULT_MMAP_MAX), (_M_MMAP_THRESHOLD, _DEFAULT_THRESHOLD),
                             (_M_TRIM_THRESHOLD, _DEFAULT_THRESHOLD)):
            libc.mallopt(param, value)
        _state["fresh"], _state["on"] = True, False
    libc.malloc_trim(0)
