"""Memory: pyvf.reuse_freed_memory (pyvf/_memory.py), after which a large array freed and allocated
again comes back from memory already mapped, without page faults; the kernels' extra memory
(branching attention, vq_nearest) bounded; an allocation failure inside a kernel a MemoryError.
Each in a process of its own (the settings are process-wide)."""

import json
import platform
import subprocess
import sys

import pytest

CHILD = r"""
import json, resource
import numpy as np
import pyvf


def rounds():
    faults = []
    for _ in range(3):
        r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        a = np.ones(16 * 2 ** 20, np.float32)  # 64 MiB: above glibc's largest mmap threshold (32 MiB)
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0)
        del a
    return faults


off = rounds()
on = pyvf.reuse_freed_memory()
print(json.dumps({"off": off, "on": on, "again": pyvf.reuse_freed_memory(), "faults": rounds()}))
"""


def test_reuse_freed_memory_removes_the_page_faults_of_a_second_allocation(tmp_path):
    """64 MiB written three times: without the setting every round faults its pages in again (at
    least 32 faults, 2-MiB huge pages or not); with it, rounds two and three reuse the first
    round's pages (at most 1% of its faults, or 8, for Python's own small allocations). Where the
    C library is not glibc it changes nothing and says so (False). From tmp_path: `python -c`
    from the source tree would import the unbuilt package."""
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, check=True, cwd=tmp_path)
    on = json.loads(out.stdout.strip().splitlines()[-1])
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        assert on["on"] is False, on
        return
    assert on["on"] is True and on["again"] is True
    assert min(on["off"][1:]) >= 32, on  # fresh pages each round
    assert on["faults"][0] >= 32, on
    # a few faults of Python's own small allocations may fall inside a round: at most 8 (or 1%)
    assert max(on["faults"][1:]) <= max(on["faults"][0] // 100, 8), on


OOM_WORKER = """
import resource, sys, numpy as np, pyvf
H, N, L, dh, headroom = (int(a) for a in sys.argv[1:])
q = np.random.default_rng(0).standard_normal((1, 1, H, N, L, dh)).astype(np.float32)
o, lse = pyvf.branching_attention_forward(q, q, q)  # threads started, first-call memory taken
grads = [np.empty_like(q) for _ in range(3)]  # the outputs exist: only the kernel's own buffers are asked for
vm = int([l for l in open("/proc/self/status") if l.startswith("VmSize")][0].split()[1]) * 1024
resource.setrlimit(resource.RLIMIT_AS, (vm + headroom, resource.RLIM_INFINITY))
try:
    pyvf._core.attn_backward(*grads, lse, q, q, q, o, q, 1.0)
    print("no error")
except MemoryError as e:
    print("MemoryError:", e)
resource.setrlimit(resource.RLIMIT_AS, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
small = np.ascontiguousarray(q[:, :, :1, :2, :16, :8])
print("still running:", pyvf.branching_attention(small, small, small).shape)
"""


@pytest.mark.parametrize("H, N, L, dh, headroom", [
    (1, 8, 1024, 256, 24 << 20),  # B*H = 1: the backward's per-group dq buffers (7 x 8 MiB) cannot be had
    (16, 8, 256, 64, 256 << 10),  # B*H = 16: one group; each thread's (1 MiB) buffers fail inside the OpenMP region
])
def test_attention_allocation_failure_is_a_memory_error_not_an_abort(H, N, L, dh, headroom, tmp_path):
    """An allocation that fails inside the kernel, also inside an OpenMP region, raises
    MemoryError and the interpreter goes on (an exception escaping an OpenMP region would
    abort the process). The address space is limited in a subprocess so that it fails (the
    allocations are the same code on every kernel path: one path tested)."""
    args = [str(a) for a in (H, N, L, dh, headroom)]
    proc = subprocess.run([sys.executable, "-c", OOM_WORKER, *args], cwd=tmp_path, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "MemoryError: branching_attention: not enough memory" in proc.stdout, proc.stdout
    assert "still running: (1, 1, 1, 2, 16, 8)" in proc.stdout


ATTENTION_WORKER = """
import sys, numpy as np, pyvf
from pyvf.bench.common import peak_memory
L = int(sys.argv[1])
pyvf.set_num_threads(4)  # the same count on every machine: each thread holds its own buffers
q = np.random.default_rng(0).standard_normal((1, 1, 1, 2, L, 1)).astype(np.float32)
small = np.ascontiguousarray(q[..., :8, :])
pyvf.branching_attention_backward(small, small, small, small, *pyvf.branching_attention_forward(small, small, small))
(o, lse), fwd = peak_memory(lambda: pyvf.branching_attention_forward(q, q, q))
_, bwd = peak_memory(lambda: pyvf.branching_attention_backward(q, q, q, q, o, lse))
print(fwd, bwd, pyvf.num_threads())
"""


def test_attention_memory_is_bounded_for_long_views(tmp_path):
    """q of shape (1, 1, 1, 2, L, 1): a per-thread (L, L) logit buffer would be L^2 * 4 bytes
    (64 MiB at L = 4096, 64 GiB at L = 131072); the kernel works in tiles of 256 x 256, so the
    extra memory is the outputs plus O(threads x (256^2 + R*N*L*dh)). Measured at L = 4096:
    0.5 MiB forward, 1.8 MiB backward. The buffers are the same on every kernel path: one tested."""
    L = 4096
    proc = subprocess.run([sys.executable, "-c", ATTENTION_WORKER, str(L)], cwd=tmp_path, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    fwd, bwd, threads = (int(x) for x in proc.stdout.split())
    outputs = 2 * L * 4 + 2 * L * 8  # o, lse
    per_thread = 4 * (8 * 256 * 256 + 6 * 2 * L)  # tiles and per-view buffers, generously
    # every thread holds its own buffers (the backward measured 0.9 MiB a thread at 16 threads)
    bound = 3 * outputs + max(4, threads) * per_thread + (4 << 20)
    assert fwd <= bound and bwd <= bound + 3 * 2 * L * 4, (fwd, bwd, bound)
    assert bwd < L * L * 4 // 8  # far below one (L, L) buffer


VQ_WORKER = """
import numpy as np
from pyvf.bench.common import peak_memory
from pyvf.nn.quantizer import vq_nearest
for K, D in ((1 << 20, 1), (16384, 256)):
    codes = np.random.default_rng(0).standard_normal((K, D)).astype(np.float32)
    x = np.random.default_rng(1).standard_normal((64, D)).astype(np.float32)
    vq_nearest(x[:1], codes[:2])  # thread pools and first-call allocations outside the measurement
    _, extra = peak_memory(lambda: vq_nearest(x, codes))
    print(K, D, extra)
"""


def test_vq_extra_memory_is_bounded_by_the_codes(tmp_path):
    """Peak extra memory of one call, measured in a fresh process: the packed codes (as large as
    the codes), one double per code, and per thread (64, D + 2048) float32 buffers. The buffers
    are the same on every kernel path: one tested."""
    proc = subprocess.run([sys.executable, "-c", VQ_WORKER], cwd=tmp_path, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for line in proc.stdout.strip().splitlines():
        K, D, extra = (int(a) for a in line.split())
        bound = 2 * K * D * 4 + 8 * K + 16 * 2 ** 20
        assert extra <= bound, f"K={K}, D={D}: extra {extra / 2**20:.1f} MiB > bound {bound / 2**20:.1f} MiB"
