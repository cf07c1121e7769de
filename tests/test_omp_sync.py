"""How many times a kernel call wakes its threads (tools/omp_sync_count.c, an LD_PRELOAD shim over
libgomp): under OMP_WAIT_POLICY=PASSIVE each parallel region and each barrier inside one is a
futex wake of sleeping threads (35-50 us on a VM, csrc/threads.h), so the kernels keep them few,
and these counts pin that down: a conv2d backward is one region with one barrier (the flipped
weights and the channels-last dy ready before any task), a forward one region and no barrier,
GroupNorm's forward and backward one region each (the backward sums dgamma and dbeta over the
images after its region), the GEMM one region (a barrier only where its sum is split into parts),
the attention's backward one region (a barrier only where its key blocks fall into several
groups). A barrier added back, or a kernel split into two regions again, fails here. Every call
on 2 forced threads (tests/conftest.py). And each region asks for pyvf's thread count whichever
Python thread calls the kernel."""

import os
import shutil
import subprocess
import sys
import textwrap

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# the kernels themselves (pyvf._core: the Python wrappers add their own finiteness scans), each run
# once in the child after a warm-up: name -> (code, regions, barriers per thread)
CASES = {
    "conv2d forward": ("K.conv2d_forward(y, x, w, b, 1, 1, 1, 1, 1)", 1, 0),
    "conv2d backward (dw on channels-last dy)": ("K.conv2d_backward(dx, dw, db, x, w, dy, 1, 1, 1, 1, 1)", 1, 1),
    "conv2d backward (dw lane sums, 3 channels)": ("K.conv2d_backward(dx, dw3, db3, x, w3, dy3, 1, 1, 1, 1, 1)", 1, 1),
    "conv2d backward, stride 2": ("K.conv2d_backward(dx, dw, db, x, w, dy2, 2, 0, 1, 0, 1)", 1, 1),
    "groupnorm + swish forward": ("K.groupnorm_forward(gy, gst, gx, gg, gb, 4, 1e-6, True)", 1, 0),
    "groupnorm + swish backward": ("K.groupnorm_backward(gdx, gdg, gdb, gx, gst, gg, gb, gdy, 4, True)", 1, 0),
    "matmul": ("K.matmul(c, a, bm, False, False, None)", 1, 0),
    "matmul, sum split in parts": ("K.matmul(c_long, a_long, b_long, False, False, None)", 1, 1),
    "attention forward": ("K.attn_forward(o, lse, q, k, v, 1.0)", 1, 0),
    "attention backward, 6 key groups": ("K.attn_backward(dq, dk, dv, lse, q, k, v, o, do, 1.0)", 1, 1),
    "attention backward, 1 key group":
        ("K.attn_backward(dq16, dk16, dv16, lse16, q16, k16, v16, o16, do16, 1.0)", 1, 0),
}

CHILD = textwrap.dedent("""
    import ctypes, json, sys
    import numpy as np
    import pyvf
    from pyvf import _core as K
    lib = ctypes.CDLL(sys.argv[1])
    lib.omp_sync_regions.restype = lib.omp_sync_barriers.restype = ctypes.c_long
    rng = np.random.default_rng(0)
    f = lambda *s: rng.standard_normal(s).astype(np.float32)
    e = lambda *s: np.empty(s, np.float32)
    x, w, b, w3 = f(2, 9, 10, 12), f(35, 9, 3, 3), f(35), f(3, 9, 3, 3)
    y, dy, dy3, dy2 = e(2, 35, 10, 12), f(2, 35, 10, 12), f(2, 3, 10, 12), f(2, 35, 5, 6)
    dx, dw, db, dw3, db3 = e(2, 9, 10, 12), e(35, 9, 3, 3), e(35), e(3, 9, 3, 3), e(3)
    gx, gg, gb, gdy = f(2, 8, 6, 6), f(8), f(8), f(2, 8, 6, 6)
    gy, gst, gdx, gdg, gdb = e(2, 8, 6, 6), e(2, 4, 3), e(2, 8, 6, 6), e(8), e(8)
    a, bm, c = f(1, 40, 50), f(1, 50, 60), e(1, 40, 60)
    a_long, b_long, c_long = f(1, 8, 4096), f(1, 4096, 16), e(1, 8, 16)
    q, k, v, do = (f(2, 1, 2, 3, 16, 8) for _ in range(4))  # 2 heads: the key blocks in 6 groups
    o, dq, dk, dv, lse = e(*q.shape), e(*q.shape), e(*q.shape), e(*q.shape), np.empty(q.shape[:5])
    q16, k16, v16, do16 = (f(2, 2, 8, 3, 16, 8) for _ in range(4))  # 16 heads: one group
    o16, dq16, dk16, dv16, lse16 = e(*q16.shape), e(*q16.shape), e(*q16.shape), e(*q16.shape), np.empty(q16.shape[:5])
    K.attn_forward(o, lse, q, k, v, 1.0)
    K.attn_forward(o16, lse16, q16, k16, v16, 1.0)
    pyvf.set_num_threads(2)
    K.set_force_parallel(True)
    out = {}
    for name, code in json.loads(sys.argv[2]).items():
        eval(code)  # warm-up
        r, bar = lib.omp_sync_regions(), lib.omp_sync_barriers()
        eval(code)
        out[name] = [lib.omp_sync_regions() - r, (lib.omp_sync_barriers() - bar) / 2]
    # the threads a region asks for, a kernel called from another Python thread than the one
    # that set the count (OpenMP's own setting is per thread; pyvf's holds for the process)
    import threading
    lib.omp_sync_last_threads.restype = ctypes.c_long
    asked = []
    for n in (3, 1, 2):
        pyvf.set_num_threads(n)
        t = threading.Thread(target=lambda: (K.matmul(c, a, bm, False, False, None),
                                             asked.append(lib.omp_sync_last_threads())))
        t.start()
        t.join()
    out["threads asked from another thread"] = asked
    print(json.dumps(out))
""")


def _libgomp_kernels():
    """True when the kernels run on GCC's libgomp (the shim wraps its entry points)."""
    from pyvf import _core
    so = _core._module(_core.current_path()).__file__
    ldd = shutil.which("ldd")
    return bool(ldd) and "libgomp" in subprocess.run([ldd, so], capture_output=True, text=True).stdout


@pytest.fixture(scope="module")
def counts(tmp_path_factory):
    import json
    # the suite runs from a source checkout, whose kernels were built here: a C compiler is present,
    # and built with GCC the kernels link libgomp (CMakeLists.txt's OpenMP); either missing is a
    # failure, not a skip
    cc = shutil.which("gcc") or shutil.which("cc")
    assert cc, "tools/omp_sync_count.c needs a C compiler (gcc or cc) on PATH"
    assert _libgomp_kernels(), "the kernels do not link GCC's libgomp, whose entry points the shim wraps"
    shim = str(tmp_path_factory.mktemp("shim") / "omp_sync_count.so")
    subprocess.run([cc, "-O2", "-shared", "-fPIC", os.path.join(ROOT, "tools", "omp_sync_count.c"), "-o", shim, "-ldl"],
                   check=True)
    env = dict(os.environ, LD_PRELOAD=shim)
    run = subprocess.run([sys.executable, "-c", CHILD, shim, json.dumps({n: c for n, (c, _, _) in CASES.items()})],
                         env=env, capture_output=True, text=True, cwd=str(tmp_path_factory.mktemp("cwd")), timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads(run.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("name", list(CASES))
def test_wakes_per_call(name, counts):
    _, regions, barriers = CASES[name]
    got_regions, got_barriers = counts[name]
    assert [got_regions, got_barriers] == [regions, barriers], \
        f"{name}: {got_regions} regions and {got_barriers} barriers per thread, expected {regions} and {barriers}"


def test_the_thread_setting_holds_in_every_python_thread(counts):
    """pyvf.set_num_threads on the main thread sets the threads a kernel's region asks for when
    another Python thread calls it (a region without pyvf's num_threads clause asks for 0,
    OpenMP's default, there)."""
    assert counts["threads asked from another thread"] == [3, 1, 2]


def test_region_end_tool_builds_and_runs(tmp_path):
    """tools/omp_region_end.cpp (the measurement behind csrc/threads.h's RegionEnd) compiles and
    prints its line for both modes (its numbers are the machine's, not checked here)."""
    cxx = shutil.which("g++") or shutil.which("c++")
    assert cxx, "tools/omp_region_end.cpp needs a C++ compiler (g++ or c++) on PATH"
    exe = str(tmp_path / "region_end")
    subprocess.run([cxx, "-O2", "-fopenmp", os.path.join(ROOT, "tools", "omp_region_end.cpp"), "-o", exe], check=True)
    for mode in ("0", "1"):
        run = subprocess.run([exe, "20", mode, "5"], capture_output=True, text=True, timeout=60,
                             env=dict(os.environ, OMP_NUM_THREADS="2", OMP_WAIT_POLICY="PASSIVE"))
        assert run.returncode == 0, run.stderr
        assert f"threads 2, work 20 us per thread, mode {mode}, gap 5 us: median" in run.stdout, run.stdout
    assert subprocess.run([exe], capture_output=True).returncode == 2  # usage


def test_every_region_names_the_thread_count():
    """Every parallel region of the kernels asks for pyvf's count (csrc/threads.h): one written
    without the clause would run on OpenMP's default in a Python thread other than the one that
    set it (the behaviour test above checks one kernel; this one, every region's source line)."""
    regions = []
    for name in sorted(os.listdir(os.path.join(ROOT, "csrc"))):
        if name.endswith((".cpp", ".h")):
            with open(os.path.join(ROOT, "csrc", name)) as f:
                regions += [(name, i + 1, line.strip()) for i, line in enumerate(f)
                            if line.lstrip().startswith("#pragma omp parallel")]
    assert {r[0] for r in regions} >= {"branching_attention.cpp", "conv.cpp", "vq.cpp"}, regions  # the scan finds them
    missing = [r for r in regions if "num_threads(num_threads())" not in r[2]]
    assert not missing, missing
