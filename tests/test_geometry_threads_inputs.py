"""Hard and bad inputs for pyvf.geometry's rotations, pyvf's thread setting (pyvf/_threads.py), the
atomic writes and reads of pyvf/_io.py and the timer of pyvf/_machine.py: each test pins a defect
that was found and fixed (the docstring says what went wrong before).

Oracles are independent of pyvf: rotation matrices built in float64 from the quaternion (exact
for float32 inputs near the float32 limit, which float64 holds with room to spare), the
documented thread counts, and the files on disk.
"""

import math
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import pyvf
from pyvf import _io, _machine, _threads
from pyvf import geometry as geo

from conftest import assert_close


# ---------------------------------------------------------------------------------------
# geometry: rotating vectors near the top of the dtype's range


def rotation_matrix(q):
    """(..., 3, 3) float64 rotation matrix of unit quaternions q (..., 4), the textbook formula."""
    w, x, y, z = (np.asarray(q, np.float64)[..., i] for i in range(4))
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def rotated(q, v):
    """R(q) v in float64 (float32 inputs of 3e38 are far from float64's limit)."""
    return np.einsum("...ij,...j->...i", rotation_matrix(q), np.asarray(v, np.float64))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_rotating_a_vector_near_the_dtype_limit_does_not_overflow_in_between(dtype):
    """A rotation keeps the length, so rotating a finite vector whose components and rotated
    components are all representable must give a finite result. Before, the expanded formula's
    intermediate t = 2 u x v reached 2 |v| and overflowed: quat_rotate(90 deg about z,
    float32 (3e38, 3e38, 0)) raised "quat_rotate: the result is not finite: it overflowed
    float32", where the answer is (-3e38, 3e38, 0); float64 (1.7e308, 0, 0) likewise, and
    relative_poses, absolute_poses and make_relative with such positions.

    Tolerance: 16 ulp of the dtype, normwise: the float64 matrix product of the same (rounded)
    inputs is exact to 1e-16, and pyvf's formula is a few multiply-adds per component."""
    big = float(np.finfo(dtype).max)
    rtol = 16 * float(np.finfo(dtype).eps)
    s = math.sqrt(0.5)
    qz = np.array([s, 0, 0, s], dtype)  # 90 degrees about z: (x, y, z) -> (-y, x, z)
    rng = np.random.default_rng(0)
    q = rng.standard_normal((50, 4))
    q = (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(dtype)
    # random directions whose components and rotated components all stay below max / 2
    v = rng.standard_normal((50, 3))
    v = (0.28 * big * (v / np.linalg.norm(v, axis=-1, keepdims=True))).astype(dtype)
    cases = [("90 deg, (0.88 max, 0.88 max, 0)", qz, np.array([0.88 * big, 0.88 * big, 0], dtype)),
             ("90 deg, (0.99 max, 0, 0)", qz, np.array([0.99 * big, 0, 0], dtype)),
             ("random", q, v)]
    for what, qq, vv in cases:
        want = rotated(qq, vv)
        assert np.all(np.abs(want) < big), what  # the answer is representable
        assert_close(f"quat_rotate {what}", geo.quat_rotate(qq, vv), want, rtol=rtol)
    # the pose functions rotate positions the same way: ref at the origin turned 90 degrees about z
    xyz = np.concatenate([v, [cases[0][2], cases[1][2]]])  # (52, 3)
    ref = np.concatenate([np.zeros(3, dtype), qz])
    poses = np.concatenate([xyz, np.tile(qz, (len(xyz), 1))], -1)
    back = qz * np.array([1, -1, -1, -1], dtype)  # conj(qz)
    assert_close("relative_poses", geo.relative_poses(poses, ref)[:, :3], rotated(back, xyz), rtol=rtol)
    assert_close("absolute_poses", geo.absolute_poses(poses, ref)[:, :3], rotated(qz, xyz), rtol=rtol)
    rel, _ = geo.make_relative(np.concatenate([ref[None], poses])[None])
    assert_close("make_relative", rel[0, 1:, :3], rotated(back, xyz), rtol=rtol)
    # a rotated vector that does not fit the dtype still raises: 45 degrees about z turns
    # (0.88 max, 0.88 max, 0) into (0, 1.24 max, 0)
    c, sn = math.cos(math.pi / 8), math.sin(math.pi / 8)
    with pytest.raises(ValueError, match=f"^quat_rotate: the result is not finite: it overflowed {np.dtype(dtype)}"):
        geo.quat_rotate(np.array([c, 0, 0, sn], dtype), np.array([0.88 * big, 0.88 * big, 0], dtype))


# ---------------------------------------------------------------------------------------
# threads


@pytest.fixture
def restore_threads():
    """Put the kernels' and numpy's BLAS counts back after a test that sets them."""
    from threadpoolctl import threadpool_limits
    kernels, blas = pyvf.num_threads(), _threads.blas_num_threads()
    yield
    pyvf.set_num_threads(kernels)
    threadpool_limits(limits=blas, user_api="blas")


def test_set_num_threads_takes_numpy_integers(restore_threads):
    """A count from numpy (np.arange, an array of core counts) is an integer like any other, as
    pyvf's own argument checks take it (_checks.integer). Before, pyvf.set_num_threads(np.int64(1))
    raised "ValueError: n must be a positive integer below 2^31, got np.int64(1)", and
    pyvf.threads(np.int32(1)) too. Bools (np.bool_ included) are still refused."""
    pyvf.set_num_threads(np.int64(1))
    assert pyvf.num_threads() == 1 and _threads.blas_num_threads() == 1
    assert type(pyvf.num_threads()) is int
    pyvf.set_num_threads(2)
    with pyvf.threads(np.int32(1)):
        assert pyvf.num_threads() == 1 and _threads.blas_num_threads() == 1
    assert pyvf.num_threads() == 2
    for bad in (True, np.bool_(True), np.int64(0), np.uint64(2 ** 31)):
        with pytest.raises(ValueError, match="^n must be a positive integer"):
            pyvf.set_num_threads(bad)
        with pytest.raises(ValueError, match="^n must be a positive integer"):
            pyvf.threads(bad)


@pytest.mark.parametrize("value", ["³", "²", "¹⁰"])
def test_malformed_thread_variable_is_named(value):
    """Superscript digits are digits to str.isdigit but not to int(). Before,
    PYVF_NUM_THREADS='³' raised "ValueError: invalid literal for int() with base 10: '³'" at
    import, naming neither the variable nor what it must be (the documented ImportError)."""
    with pytest.raises(ImportError, match=f"^PYVF_NUM_THREADS='{value}' is not a positive integer"):
        _threads.set_from_environment({"PYVF_NUM_THREADS": value})


def test_default_under_a_narrower_affinity_limits_numpy_blas_too(tmp_path):
    """The default is one thread per CPU of the affinity for the kernels and numpy's BLAS alike
    (docs/api.md, Threads). A process that imported numpy (its BLAS pool sized to every CPU) and
    was then pinned to one CPU (a launcher pinning its workers) before importing pyvf: OpenMP
    reads the new affinity, so the kernels got 1 thread, but set_from_environment compared cores()
    with OpenMP's count only and left numpy's BLAS at 2 (printed before: "1 2"). Then
    set_num_threads moves both. (On a machine of one CPU, or without sched_setaffinity, the pin
    changes nothing and the same lines are expected: the test runs everywhere, it can fail only
    where there are CPUs to take away.) From tmp_path: the checkout's root would shadow the
    installed package in CI."""
    code = textwrap.dedent("""
        import os
        import numpy
        if hasattr(os, "sched_setaffinity"):
            os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        import pyvf
        from pyvf import _threads
        print(pyvf.num_threads(), _threads.blas_num_threads())
        pyvf.set_num_threads(2)
        print(pyvf.num_threads(), _threads.blas_num_threads())
    """)
    env = {k: v for k, v in os.environ.items() if k not in ("PYVF_NUM_THREADS", "OMP_NUM_THREADS",
                                                            "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120,
                         cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:2] == ["1 1", "2 2"], out.stdout


# ---------------------------------------------------------------------------------------
# files


def test_an_atomic_write_into_a_missing_folder_names_the_destination(tmp_path):
    """Before, the error named only the temporary file the user never asked for:
    "FileNotFoundError: [Errno 2] No such file or directory: '.../missing/.x.json.1234.ab12cd34.tmp'"
    (and "Not a directory: '.../file/.x.json...tmp'" under a file). Now it names the destination;
    the exception class is kept (FileNotFoundError, NotADirectoryError), and nothing is left."""
    (tmp_path / "file").write_text("a file, not a folder")
    for parent, kind in (("missing", FileNotFoundError), ("file", NotADirectoryError)):
        dest = str(tmp_path / parent / "x.json")
        for write in (lambda: _io.atomic_write_text(dest, "{}"), lambda: _io.atomic_savez(dest, a=np.zeros(2)),
                      lambda: _io.atomic_write_bytes(dest, b"{}")):
            with pytest.raises(kind) as e:
                write()
            assert f"cannot write {dest}" in str(e.value), str(e.value)
    assert sorted(os.listdir(tmp_path)) == ["file"]


def test_atomic_write_bytes_refuses_what_is_not_bytes(tmp_path):
    """bytes(5) is five zero bytes: before, atomic_write_bytes(path, 5) silently wrote
    b'\\x00\\x00\\x00\\x00\\x00'. A bytes-like object (bytes, bytearray, memoryview, a numpy
    buffer) is written as it is; anything else raises TypeError naming data, and nothing is
    written."""
    path = str(tmp_path / "b.bin")
    for bad in (5, "text", [1, 2], None):
        with pytest.raises(TypeError, match="^data must be a bytes-like object"):
            _io.atomic_write_bytes(path, bad)
    assert os.listdir(tmp_path) == []
    for good, want in ((b"ab", b"ab"), (bytearray(b"cd"), b"cd"), (memoryview(b"ef"), b"ef"),
                       (np.array([1, 2], np.uint8), b"\x01\x02")):
        _io.atomic_write_bytes(path, good)
        assert open(path, "rb").read() == want


def test_atomic_savez_entry_names_that_are_savez_arguments(tmp_path):
    """atomic_savez(path, **arrays) passed the entries to np.savez(file, *args, allow_pickle=True,
    **kwds) as keywords. Before, an entry named allow_pickle was taken as that flag and silently
    not written (the file loaded as {}), one named file raised "savez() got multiple values for
    argument 'file'" and one named path "atomic_savez() got multiple values for argument 'path'".
    Now path is positional-only (an entry may be called path) and the two names np.savez cannot
    store raise ValueError naming the entry, before anything is written."""
    path = str(tmp_path / "x.npz")
    _io.atomic_savez(path, path=np.arange(2), a=np.ones(1))
    got = _io.load_npz(path)
    assert sorted(got) == ["a", "path"] and np.array_equal(got["path"], np.arange(2))
    for name in ("allow_pickle", "file"):
        with pytest.raises(ValueError, match=f"^atomic_savez: the entry name {name!r}"):
            _io.atomic_savez(str(tmp_path / "y.npz"), **{name: np.ones(3)})
    assert sorted(os.listdir(tmp_path)) == ["x.npz"]


def test_remove_stale_temps_removes_only_the_temps_of_its_path(tmp_path):
    """remove_stale_temps(path) matched `.{name}.*.tmp`, so clearing "model" also removed a
    temporary file of "model.npz", and clearing "checkpoint.npz" one of "checkpoint.npz.bak":
    an atomic write of that other file under way in another process then failed at its rename.
    Only `.{name}.{pid}.{hex}.tmp`, what _io names a temporary file of `name`, is removed now."""
    ours = [".checkpoint.npz.123.abcd.tmp", ".checkpoint.npz.98765.0f1e2d3c.tmp"]
    others = [".checkpoint.npz.bak.123.0f1e2d3c.tmp", ".checkpoint.npz.notes.tmp", ".checkpoint.npzz.1.ab.tmp",
              "checkpoint.npz", ".model.npz.55.ab12cd34.tmp"]
    for name in ours + others:
        (tmp_path / name).write_bytes(b"x")
    # the name a real atomic write uses is one of ours
    assert _io._temp_name(str(tmp_path / "checkpoint.npz")).startswith(str(tmp_path / ".checkpoint.npz."))
    assert sorted(_io.remove_stale_temps(str(tmp_path / "checkpoint.npz"))) == sorted(ours)
    assert _io.remove_stale_temps(str(tmp_path / "model")) == []
    assert sorted(os.listdir(tmp_path)) == sorted(others)
    real = os.path.basename(_io._temp_name(str(tmp_path / "model.npz")))  # what a write of model.npz leaves
    (tmp_path / real).write_bytes(b"x")
    assert sorted(_io.remove_stale_temps(str(tmp_path / "model.npz"))) == sorted([".model.npz.55.ab12cd34.tmp", real])


def test_load_npz_of_a_folder_says_it_is_a_folder(tmp_path):
    """Before, load_npz of a folder raised CheckpointError "checkpoint ... is truncated or corrupt:
    IsADirectoryError", sending the user to look for damage in a file that does not exist. A folder
    is an IsADirectoryError naming it (an OSError, like the missing file's FileNotFoundError)."""
    with pytest.raises(IsADirectoryError, match=f"^checkpoint {tmp_path} is a folder, not a file"):
        _io.load_npz(str(tmp_path), "checkpoint")


# ---------------------------------------------------------------------------------------
# the timer's arguments (nothing is timed: every call below raises before calling fn)


def test_median_time_argument_checks():
    """Before, repeat=2.5 raised "TypeError: 'float' object cannot be interpreted as an integer"
    and repeat=True ran once as if it were 1; warmup likewise. fn must not be called."""
    def fn():
        raise AssertionError("fn called")

    for kw, name in (({"repeat": 2.5}, "repeat"), ({"repeat": True}, "repeat"), ({"warmup": 1.0}, "warmup"),
                     ({"warmup": None}, "warmup")):
        with pytest.raises(TypeError, match=f"^{name} must be an integer"):
            _machine.median_time(fn, **kw)
    with pytest.raises(ValueError, match="^repeat must be a positive integer"):
        _machine.median_time(fn, repeat=0)
    with pytest.raises(ValueError, match="^warmup must be >= 0"):
        _machine.median_time(fn, warmup=-1)


def test_quat_normalize_eps_too_large_for_a_float():
    """eps = 10**400, a Python int beyond float64: before, "TypeError: ufunc 'isfinite' not
    supported for the input types ..." naming neither eps nor the reason; now the ValueError of
    every other non-finite eps."""
    with pytest.raises(ValueError, match="^eps must be finite and > 0"):
        geo.quat_normalize(np.array([1.0, 0, 0, 0]), eps=10 ** 400)
