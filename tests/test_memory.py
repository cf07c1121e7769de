"""pyvf.reuse_freed_memory (pyvf/_memory.py): after it, a large array freed and allocated again
comes back from memory already mapped, without page faults; before it, glibc maps fresh pages.
Each case runs in a process of its own (the setting is process-wide and cannot be undone)."""

import json
import platform
import subprocess
import sys

CHILD = r"""
import json, resource, sys
import numpy as np
import pyvf
on = pyvf.reuse_freed_memory() if sys.argv[1] == "on" else None
faults = []
for _ in range(3):
    r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = np.ones(16 * 2 ** 20, np.float32)  # 64 MiB: above glibc's largest mmap threshold (32 MiB)
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0)
    del a
print(json.dumps({"on": on, "again": pyvf.reuse_freed_memory() if on else None, "faults": faults}))
"""


def child(mode, folder):
    # from a folder of its own: `python -c` puts the working folder first on sys.path, and from the
    # source tree it would import the unbuilt package
    out = subprocess.run([sys.executable, "-c", CHILD, mode], capture_output=True, text=True, check=True, cwd=folder)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_reuse_freed_memory_removes_the_page_faults_of_a_second_allocation(tmp_path):
    """64 MiB written three times: without the setting every round faults in its pages again (at
    least 16 Ki 4-KiB pages' worth... or, with huge pages, at least 32 faults of 2 MiB); with it,
    rounds two and three reuse the first round's pages (at most 1% of the first round's faults, or
    8, for Python's own small allocations).
    And the call reports that it is in effect, twice. Where the C library is not glibc it changes
    nothing and says so (False)."""
    off, on = child("off", tmp_path), child("on", tmp_path)
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        assert on["on"] is False, on
        return
    assert on["on"] is True and on["again"] is True
    assert min(off["faults"][1:]) >= 32, off  # fresh pages each round
    assert on["faults"][0] >= 32, on
    # a few faults of Python's own small allocations may fall inside a round: at most 8 (or 1%)
    assert max(on["faults"][1:]) <= max(on["faults"][0] // 100, 8), on
