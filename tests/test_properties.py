"""Property-based tests (hypothesis) of every public function of pyvf: what it refuses, what it
computes, and what it leaves alone.

For each public function (branching attention and its references, vq_nearest, EMAQuantizer, the
geometry functions, AdamW/Adam/clip_grad_norm/warmup_cosine_lr) random arguments are drawn (shapes with zero-size dimensions, float32 and
float64, magnitudes from 1e-300 to 1e300) and the call must either

* return the NumPy reference's result within the bound written beside it (references are
  computed in long double from the very same inputs, so they neither overflow nor round where
  the function does), or
* raise a clear TypeError, ValueError or MemoryError (never another kind, never a crash) whose
  message names the argument at fault.

Ordinary magnitudes must give a result; extreme ones may instead raise ValueError (overflow),
and must raise where the true result is not representable. Every other dtype (float16,
longdouble, integers, bool, object, complex, a list) in a float argument, NaN/inf in any
argument and a mismatched shape must raise; non-contiguous, negatively strided, Fortran-ordered
and read-only views give the same result or a ValueError naming the argument. Inputs are never
modified (compared bitwise), and a call that raises leaves an optimiser's state and the EMA
buffers bit for bit unchanged. (The models' refusals, saves and loads: tests/test_transformer.py,
test_codebook.py, test_model_files.py.)

The tests of functions that call the C++ kernels directly (test_kernel_*) run in a child
pytest process (test_kernel_properties_in_a_subprocess), so that a crash fails one test
instead of killing the run; so do the allocation-failure and oversized-dimension cases.

The internal layers (pyvf.nn.layers, losses, conv and the attention layer) trust their callers
and are tested against torch in float64 and mpmath where they are hard (tests/test_layers.py,
test_conv.py, test_attention.py).

Budget: the default settings profile "ci" runs a fixed number of examples per test,
derandomized (the same cases on every run), without deadlines: the file runs in well under a
minute on 2 cores. A longer, randomized search is one command:

    HYPOTHESIS_PROFILE=long pytest -p no:cacheprovider tests/test_properties.py

(PYVF_PROPERTIES_CHILD=1 runs the test_kernel_* tests in this process instead of a child.)
"""

import math
import os
import re
import subprocess
import sys
import tempfile
import textwrap

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from hypothesis.configuration import set_hypothesis_home_dir

import pyvf
from pyvf import geometry
from pyvf.train import optim


# hypothesis keeps its files (cached constants, patches with failing examples) out of the source
# tree, in the temp folder, unless HYPOTHESIS_STORAGE_DIRECTORY says where
if not os.environ.get("HYPOTHESIS_STORAGE_DIRECTORY"):
    set_hypothesis_home_dir(os.path.join(tempfile.gettempdir(), "pyvf-hypothesis"))
# filter_too_much is not suppressed: a property whose assume() rejects most examples would run few
# valid ones unseen; hypothesis fails it instead, and run_property asserts that every example ran
_HEALTH = [HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.differing_executors]
settings.register_profile("ci", max_examples=20, derandomize=True, deadline=None, database=None,
                          suppress_health_check=_HEALTH, print_blob=True)
settings.register_profile("long", max_examples=400, deadline=None, database=None,
                          suppress_health_check=_HEALTH, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


def _examples(ci):
    """max_examples for a heavier test: `ci` in the ci profile, a quarter of the long profile's."""
    return ci if settings().max_examples <= 20 else max(ci, settings().max_examples // 4)


CHILD = os.environ.get("PYVF_PROPERTIES_CHILD") == "1"
ALLOWED = (TypeError, ValueError, MemoryError)
FLOATS = (np.float32, np.float64)
LD = np.longdouble
# long double with a wide exponent (x86-64: 80-bit): references of 1e300 * 1e300 do not overflow
WIDE_LD = np.finfo(LD).max > 1e4000


# ---------------------------------------------------------------------------------------
# helpers: calling, snapshots, messages, comparisons


def attempt(fn, *args, **kw):
    """(True, result) or (False, exception); an exception of another kind than
    TypeError/ValueError/MemoryError fails the test with its traceback."""
    try:
        return True, fn(*args, **kw)
    except ALLOWED as e:
        assert str(e), f"{type(e).__name__} without a message"
        return False, e
    except Exception as e:  # noqa: BLE001 - the property is about the kind
        raise AssertionError(f"raised {type(e).__name__} (only TypeError, ValueError, MemoryError are "
                             f"allowed): {e}") from e


def snapshot(obj):
    """A deep copy of every array in obj (nested dicts, lists, tuples), for a bitwise comparison."""
    if isinstance(obj, np.ndarray):
        return ("array", obj.dtype, obj.shape, obj.strides, obj.copy())
    if isinstance(obj, dict):
        return {k: snapshot(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(snapshot(v) for v in obj)
    return obj


def same_bits(a, b):
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    if a.dtype.hasobject:
        return all(x is y or x == y for x, y in zip(a.ravel().tolist(), b.ravel().tolist()))
    return np.ascontiguousarray(a).tobytes() == np.ascontiguousarray(b).tobytes()


def assert_unchanged(before, obj, what="input"):
    """obj still has the bits, dtype, shape and strides it had when snapshot() took `before`."""
    if isinstance(obj, np.ndarray):
        kind, dtype, shape, strides, copy = before
        assert (obj.dtype, obj.shape, obj.strides) == (dtype, shape, strides), f"{what}: metadata changed"
        assert same_bits(obj, copy), f"{what} was modified"
    elif isinstance(obj, dict):
        assert set(obj) == set(before), f"{what}: keys changed"
        for k in obj:
            assert_unchanged(before[k], obj[k], f"{what}[{k!r}]")
    elif isinstance(obj, (list, tuple)):
        for i, (b, o) in enumerate(zip(before, obj)):
            assert_unchanged(b, o, f"{what}[{i}]")


def names(exc, *args):
    """True when the message of exc names one of args (as a word: 'x' in 'x must', not in 'max');
    a dict entry "grads['a']" is also named by "grads ... ['a']"."""
    msg = str(exc)
    for a in args:
        if re.search(rf"(?<![\w.]){re.escape(a)}(?!\w)", msg):
            return True
        m = re.fullmatch(r"(\w+)\[(.+)\]", a)
        if m and m.group(1) in msg and m.group(2) in msg:
            return True
    return False


def assert_names(exc, name, others=()):
    assert names(exc, name, *others), f"the {type(exc).__name__} does not name {name!r}: {exc}"


def u(dtype):
    """Unit roundoff of dtype."""
    return float(np.finfo(dtype).eps) / 2


def tiny(dtype):
    """Absolute slack per operation for results near the underflow (flush-to-zero tolerated)."""
    return float(np.finfo(dtype).smallest_normal)


def L(a):
    return np.asarray(a, dtype=LD)


def check_close(what, got, ref, bound, dtype):
    """|got - ref| <= bound elementwise, got finite; where the reference lies beyond the dtype's
    range by more than the bound, the call should have raised instead of returning."""
    got = np.asarray(got)
    ref = L(ref)
    bound = np.broadcast_to(L(bound), ref.shape)
    assert got.shape == ref.shape, f"{what}: shape {got.shape}, reference {ref.shape}"
    big = float(np.finfo(dtype).max)
    over = np.abs(ref) - bound > big
    assert not over.any(), f"{what}: the true result overflows {np.dtype(dtype)} but no error was raised"
    assert np.isfinite(got).all(), f"{what}: non-finite values returned"
    err = np.abs(L(got) - ref)
    bad = ~(err <= bound)
    if bad.any():
        i = tuple(np.argwhere(bad)[0])
        pytest.fail(f"{what}: {int(bad.sum())} of {bad.size} elements beyond the bound; first at {i}: "
                    f"got {got[i]!r}, reference {ref[i]!r}, |err| {err[i]!r} > bound {bound[i]!r}")


# ---------------------------------------------------------------------------------------
# drawing arguments


def rng_of(data):
    return np.random.default_rng(data.draw(st.integers(0, 2 ** 32 - 1), label="seed"))


def draw_dtype(data):
    return np.dtype(data.draw(st.sampled_from(FLOATS), label="dtype"))


def draw_exp(data, dtype, extreme):
    """A decimal exponent for an argument's magnitude: 0 for ordinary cases, else anywhere in the
    dtype's range (1e-300 .. 1e300 for float64)."""
    if not extreme:
        return 0
    # (a long double as narrow as float64 would overflow in the references beyond ~1e100 each)
    top = (300 if WIDE_LD else 100) if np.dtype(dtype) == np.float64 else 37
    return data.draw(st.integers(-top, top), label="exponent")


def normal(rng, shape, dtype, exp=0):
    """standard normal values times 10^exp, rounded to dtype (finite)."""
    a = rng.standard_normal(shape) * 10.0 ** exp
    big = float(np.finfo(dtype).max)
    return np.array(np.clip(a, -big, big), dtype=dtype)  # an array even for shape ()


def draw_shape(data, ndim_max=2, size_max=3, min_size=0, label="shape"):
    nd = data.draw(st.integers(0, ndim_max), label=label + " ndim")
    return tuple(data.draw(st.lists(st.integers(min_size, size_max), min_size=nd, max_size=nd), label=label))


def unit_quat(rng, shape, dtype):
    q = rng.standard_normal(shape + (4,))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return q.astype(dtype)


def poses(rng, shape, dtype, exp=0):
    xyz = normal(rng, shape + (3,), dtype, exp)
    return np.concatenate([xyz, unit_quat(rng, shape, dtype)], axis=-1)


# the ways an argument can be wrong, and the views a correct one can come as

BAD_FLOAT_DTYPES = ["float16", "longdouble", "int32", "int64", "uint8", "bool", "object", "complex128", "list",
                    "other float"]
BAD_INT_DTYPES = ["float64", "float32", "bool", "object", "complex128", "list"]
LAYOUTS = ["strided", "negative strides", "fortran", "read-only"]


def with_dtype(a, kind):
    """a converted to the wrong kind of argument `kind`."""
    if kind == "list":
        return a.tolist()
    if kind == "other float":
        return a.astype(np.float32 if a.dtype == np.float64 else np.float64)
    with np.errstate(all="ignore"):
        return a.astype(np.dtype(kind))


def with_layout(a, kind):
    """A view of a copy of a with the same values and another memory layout."""
    if kind == "read-only":
        c = a.copy()
        c.setflags(write=False)
        return c
    if kind == "fortran":
        return np.asfortranarray(a)
    if kind == "negative strides":
        return np.flip(np.flip(a, axis=0).copy(), axis=0)
    big = np.zeros(a.shape[:-1] + (2 * a.shape[-1],), a.dtype)  # strided: every other element
    big[..., ::2] = a
    return big[..., ::2]


def with_bad_shape(a):
    """a with its last dimension one longer (a 0-d array becomes (1,))."""
    if a.ndim == 0:
        return a.reshape(1)
    return np.concatenate([a, np.zeros(a.shape[:-1] + (1,), a.dtype)], axis=-1)


# ---------------------------------------------------------------------------------------
# a case: the arguments of one call, how to run it, its reference and what it may refuse


class Case:
    """args: name -> value (the names the error messages must use); run(**args) -> result;
    check(result, args) asserts the result against the reference; floats/ints: the arguments that
    must be float/integer arrays; finite: those where NaN/inf must raise; shaped: those whose
    shape is constrained (a changed one must raise); contiguous: those that may refuse a
    non-contiguous view (ValueError naming them) instead of computing; ordinary: the magnitudes
    are ordinary, so the call must succeed; state(): what a failed call must leave unchanged;
    same_dtype: float arguments must share one dtype."""

    def __init__(self, args, run, check, floats=(), ints=(), finite=None, shaped=None, contiguous=(),
                 ordinary=True, state=None, same_dtype=True, dtype=None, mutated=()):
        self.args, self.run, self.check = args, run, check
        self.floats, self.ints = tuple(floats), tuple(ints)
        self.finite = tuple(self.floats if finite is None else finite)
        self.shaped = tuple(self.floats + self.ints if shaped is None else shaped)
        self.contiguous, self.ordinary = tuple(contiguous), ordinary
        self.state = state or (lambda: None)
        self.same_dtype, self.dtype, self.mutated = same_dtype, dtype, tuple(mutated)

    def call(self, args):
        return attempt(self.run, **args)


def run_and_check_unchanged(case, args):
    """Call with args; inputs unchanged afterwards (except documented in-place ones on success),
    the state unchanged when it raised. -> (ok, result)."""
    before, state = snapshot(args), snapshot(case.state())
    ok, out = case.call(args)
    for k in args:
        if not (ok and k in case.mutated):
            assert_unchanged(before[k], args[k], f"argument {k}")
    if not ok:
        assert_unchanged(state, case.state(), "the state after a failed call")
    return ok, out


# ---------------------------------------------------------------------------------------
# geometry


def _ld_mul(a, b):
    aw, ax, ay, az = (a[..., i] for i in range(4))
    bw, bx, by, bz = (b[..., i] for i in range(4))
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by + ay * bw + az * bx - ax * bz, aw * bz + az * bw + ax * by - ay * bx], -1)


def _ld_conj(q):
    return q * np.array([1, -1, -1, -1], LD)


def _ld_rotate(q, v):
    qv = np.concatenate([np.zeros(v.shape[:-1] + (1,), LD), v], -1)
    return _ld_mul(_ld_mul(q, qv), _ld_conj(q))[..., 1:]


def _bshapes(data, n=2):
    """n leading shapes that broadcast against each other (some dimensions 1, some 0)."""
    base = draw_shape(data, 2, 3, label="leading")
    out = []
    for i in range(n):
        s = tuple(1 if data.draw(st.booleans(), label=f"bcast{i}") else k for k in base)
        drop = data.draw(st.integers(0, len(s)), label=f"drop{i}")
        out.append(s[drop:])
    return out


def case_quat_mul(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    sa, sb = _bshapes(data)
    args = {"a": normal(rng, sa + (4,), dt, draw_exp(data, dt, extreme)),
            "b": normal(rng, sb + (4,), dt, draw_exp(data, dt, extreme))}

    def check(out, a):
        A, B = L(a["a"]), L(a["b"])
        bound = 8 * u(dt) * np.abs(A).sum(-1, keepdims=True) * np.abs(B).sum(-1, keepdims=True) + 8 * tiny(dt)
        check_close("a * b", out, _ld_mul(A, B), bound, dt)

    return Case(args, lambda a, b: geometry.quat_mul(a, b), check, floats=("a", "b"), ordinary=not extreme, dtype=dt)


def case_quat_conj_canonical_normalize(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    shape = draw_shape(data, 2, 3)
    q = normal(rng, shape + (4,), dt, draw_exp(data, dt, extreme))
    if q.size and data.draw(st.booleans(), label="zeros"):
        q[..., 0] = 0  # w == 0: the canonical form's tie
    args = {"q": q}

    def run(q):
        return geometry.quat_conj(q), geometry.quat_canonical(q), geometry.quat_canonical(q, tie_break=True), \
            geometry.quat_normalize(q)

    def check(out, a):
        q = a["q"]
        conj, can, tie, nrm = out
        assert same_bits(conj, q * np.array([1, -1, -1, -1], dt)), "conj"
        assert same_bits(can, np.where(q[..., :1] < 0, -q, q)), "canonical"
        first = np.argmax(q != 0, axis=-1)[..., None]
        lead = np.take_along_axis(q, first, -1)
        assert same_bits(tie, np.where(lead < 0, -q, q)), "canonical tie_break"
        Q = L(q)
        n = np.sqrt((Q * Q).sum(-1, keepdims=True))
        ref = Q / np.maximum(n, LD(np.asarray(np.sqrt(1e-12), dt)))
        check_close("normalize", nrm, ref, 8 * u(dt) * np.abs(ref) + 2 * tiny(dt), dt)

    return Case(args, run, check, floats=("q",), ordinary=not extreme, dtype=dt)


def case_quat_rotate(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    sq, sv = _bshapes(data)
    args = {"q": unit_quat(rng, sq, dt), "v": normal(rng, sv + (3,), dt, draw_exp(data, dt, extreme))}

    def check(out, a):
        V = L(a["v"])
        ref = _ld_rotate(L(a["q"]), V)
        check_close("rotate", out, ref, 32 * u(dt) * np.sqrt((V * V).sum(-1, keepdims=True)) + 16 * tiny(dt), dt)

    return Case(args, lambda q, v: geometry.quat_rotate(q, v), check, floats=("q", "v"), ordinary=not extreme,
                dtype=dt)


def case_relative_absolute(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    sp, sr = _bshapes(data)
    ep, er = draw_exp(data, dt, extreme), draw_exp(data, dt, extreme)
    args = {"poses": poses(rng, sp, dt, ep), "ref": poses(rng, sr, dt, er)}

    def run(poses, ref):
        rel = geometry.relative_poses(poses, ref)
        return rel, geometry.absolute_poses(rel, ref)

    def check(out, a):
        P, R = L(a["poses"]), L(a["ref"])
        q0i = _ld_conj(R[..., 3:])
        xyz = _ld_rotate(q0i, P[..., :3] - R[..., :3])
        q = _ld_mul(q0i, P[..., 3:])
        size = np.sqrt((P[..., :3] ** 2).sum(-1, keepdims=True)) + np.sqrt((R[..., :3] ** 2).sum(-1, keepdims=True))
        bound = np.concatenate([np.broadcast_to(32 * u(dt) * size, xyz.shape), np.full(q.shape, 16 * u(dt))], -1)
        check_close("relative", out[0], np.concatenate([xyz, q], -1), bound + 16 * tiny(dt), dt)
        back = np.broadcast_to(P, out[1].shape)
        check_close("absolute(relative)", out[1], back, 2 * bound + 64 * u(dt) * np.concatenate(
            [np.broadcast_to(size, xyz.shape), np.zeros(q.shape, LD)], -1) + 32 * tiny(dt), dt)

    return Case(args, run, check, floats=("poses", "ref"), ordinary=not extreme, dtype=dt)


def case_make_relative(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    lead = draw_shape(data, 1, 3)
    N = data.draw(st.integers(1, 4), label="N")
    args = {"poses": poses(rng, lead + (N,), dt, draw_exp(data, dt, extreme))}

    def check(out, a):
        rel, ref = out
        assert same_bits(ref, a["poses"][..., 0, :]), "ref is the first view"
        # the reference in long double, from the quaternion algebra written out above (not pyvf's
        # geometry): xyz = conj(q0) (p - p0) q0, q = conj(q0) q, normalised, w >= 0
        P = L(a["poses"])
        q0i = _ld_conj(P[..., :1, 3:])
        xyz = _ld_rotate(q0i, P[..., :3] - P[..., :1, :3])
        q = _ld_mul(q0i, P[..., 3:])
        q = q / np.sqrt((q * q).sum(-1, keepdims=True))
        # where w is within rounding of 0 either sign is right: there the reference takes the one returned
        toward = (q * L(rel[..., 3:])).sum(-1, keepdims=True) < 0
        q = np.where(np.where(np.abs(q[..., :1]) <= 32 * u(dt), toward, q[..., :1] < 0), -q, q)
        norm3 = lambda t: np.sqrt((t[..., :3] ** 2).sum(-1, keepdims=True))
        size = norm3(P) + norm3(P[..., :1, :])  # |p| + |p0|
        bound = np.concatenate([np.broadcast_to(32 * u(dt) * size, xyz.shape), np.full(q.shape, 32 * u(dt))], -1)
        check_close("rel", rel, np.concatenate([xyz, q], -1), bound + 16 * tiny(dt), dt)

    return Case(args, lambda poses: geometry.make_relative(poses), check, floats=("poses",), ordinary=not extreme,
                dtype=dt)


def case_position_error(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    s1, s2 = _bshapes(data)
    width = data.draw(st.sampled_from([3, 7]), label="width")  # positions or poses
    args = {"p1": normal(rng, s1 + (width,), dt, draw_exp(data, dt, extreme)),
            "p2": normal(rng, s2 + (width,), dt, draw_exp(data, dt, extreme))}

    def check(out, a):
        P1, P2 = L(a["p1"])[..., :3], L(a["p2"])[..., :3]
        d = P1 - P2
        size = np.sqrt((P1 ** 2).sum(-1)) + np.sqrt((P2 ** 2).sum(-1))
        check_close("position_error", out, np.sqrt((d * d).sum(-1)), 8 * u(dt) * size + 4 * tiny(dt), dt)

    return Case(args, lambda p1, p2: geometry.position_error(p1, p2), check, floats=("p1", "p2"),
                ordinary=not extreme, dtype=dt)


def case_orientation_error(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    s1, s2 = _bshapes(data)
    width = data.draw(st.sampled_from([4, 7]), label="width")  # quaternions or poses
    args = {"q1": normal(rng, s1 + (width,), dt, draw_exp(data, dt, extreme)),
            "q2": normal(rng, s2 + (width,), dt, draw_exp(data, dt, extreme))}

    def check(out, a):
        q1, q2 = L(a["q1"])[..., -4:], L(a["q2"])[..., -4:]
        q1 = q1 / np.sqrt((q1 * q1).sum(-1, keepdims=True))
        q2 = q2 / np.sqrt((q2 * q2).sum(-1, keepdims=True))
        r = _ld_mul(q1, _ld_conj(q2))
        ang = np.degrees(2 * np.arctan2(np.sqrt((r[..., 1:] ** 2).sum(-1)), np.abs(r[..., 0])))
        # scale-invariant, and atan2 keeps full accuracy: within a few u radians at every size
        check_close("orientation_error", out, ang, LD(64 * 180 / math.pi) * u(dt) + 0 * ang, dt)

    return Case(args, lambda q1, q2: geometry.orientation_error(q1, q2), check, floats=("q1", "q2"),
                ordinary=not extreme, dtype=dt)


def case_average_pose(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    lead = draw_shape(data, 1, 3)
    n = data.draw(st.integers(1, 4), label="n")
    base = poses(rng, lead + (1,), dt, draw_exp(data, dt, extreme))
    # predictions that agree (what average_pose is for): one pose plus small noise
    noise = normal(rng, lead + (n, 7), dt, -3)
    args = {"poses": (base + noise * np.concatenate([np.abs(base[..., :3]) + 1, np.ones(base.shape[:-1] + (4,), dt)],
                                                    -1)).astype(dt)}

    def check(out, a):
        P = L(a["poses"])
        xyz = P[..., :3].mean(-2)
        q = P[..., 3:] / np.sqrt((P[..., 3:] ** 2).sum(-1, keepdims=True))
        q = np.where(q[..., :1] < 0, -q, q).mean(-2)
        q = q / np.sqrt((q * q).sum(-1, keepdims=True))
        q = np.where(q[..., :1] < 0, -q, q)
        bound = np.concatenate([8 * u(dt) * np.abs(P[..., :3]).max(-2) + tiny(dt),
                                np.full(q.shape, 32 * u(dt))], -1)
        check_close("average_pose", out, np.concatenate([xyz, q], -1), bound, dt)

    return Case(args, lambda poses: geometry.average_pose(poses), check, floats=("poses",), ordinary=not extreme,
                dtype=dt)


GEOMETRY_CASES = [case_quat_mul, case_quat_conj_canonical_normalize, case_quat_rotate, case_relative_absolute,
                  case_make_relative, case_position_error, case_orientation_error, case_average_pose]


# ---------------------------------------------------------------------------------------
# the kernels: branching attention, vq_nearest, the quantizer, the attention layer


def tree_mask(R, N, Ln):
    """The tree's attention mask written out here (not pyvf's branching_mask), (T, T) bool over
    tokens ordered [row][view][token]: query block (r, i) sees trunk blocks (0, j < i) and its own (r, i)."""
    row, view = np.divmod(np.arange(R * N * Ln) // Ln, N)  # each flattened token's tree row and view
    return ((row[None, :] == 0) & (view[None, :] < view[:, None])) | \
        ((row[None, :] == row[:, None]) & (view[None, :] == view[:, None]))


def ld_attention(a, scale, dt):
    """Branching attention's o, dq, dk, dv for a["q"], a["k"], a["v"], a["do"] (R, B, H, N, L, dh),
    dense in long double with tree_mask, and the bound each result of dtype dt must meet: a
    softmax's outputs are within ~(T + dh) u of its max |v|, relative to the logits' size
    (u * max|s| is the softmax's own conditioning)."""
    Q, K, Vv, DO = (L(a[n]) for n in "q k v do".split())
    R, B, H, N, Ln, dh = Q.shape
    fl = lambda t: t.transpose(1, 2, 0, 3, 4, 5).reshape(B, H, R * N * Ln, dh)
    qf, kf, vf, dof = fl(Q), fl(K), fl(Vv), fl(DO)
    s = LD(scale) * (qf @ kf.swapaxes(-1, -2))
    s = np.where(tree_mask(R, N, Ln), s, -np.inf)
    s = s - s.max(-1, keepdims=True)
    p = np.exp(s)
    p /= p.sum(-1, keepdims=True)
    uf = lambda t: t.reshape(B, H, R, N, Ln, -1).transpose(2, 0, 1, 3, 4, 5)
    dp = dof @ vf.swapaxes(-1, -2)
    ds = p * (dp - (p * dp).sum(-1, keepdims=True))
    refs = (uf(p @ vf), uf(LD(scale) * (ds @ kf)), uf(LD(scale) * (ds.swapaxes(-1, -2) @ qf)),
            uf(p.swapaxes(-1, -2) @ dof))  # o, dq, dk, dv
    T = R * N * Ln
    smax = LD(scale) * np.abs(qf).max() * np.abs(kf).max() * dh  # bound on |logits|
    c = (T + dh + 8) * u(dt) * (1 + smax)
    big = lambda t: np.abs(t).max() if t.size else LD(0)
    sc = LD(scale) * 2 * dh
    sizes = (big(Vv), sc * big(DO) * big(Vv) * big(K), sc * big(DO) * big(Vv) * big(Q), big(DO))
    return [(ref, 4 * c * size + 2 * u(dt) * np.abs(ref) + 8 * T * tiny(dt)) for ref, size in zip(refs, sizes)]


def case_attention(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    shape = tuple(data.draw(st.integers(1, n), label=k) for k, n in zip("RBHNLd", (3, 2, 2, 3, 3, 4)))
    e = [draw_exp(data, dt, extreme) for _ in range(4)]
    scale = data.draw(st.sampled_from([1.0, 0.5]), label="scale")
    args = {"q": normal(rng, shape, dt, e[0]), "k": normal(rng, shape, dt, e[1]), "v": normal(rng, shape, dt, e[2]),
            "do": normal(rng, shape, dt, e[3])}

    def run(q, k, v, do):
        o, lse = pyvf.branching_attention_forward(q, k, v, scale)
        grads = pyvf.branching_attention_backward(do, q, k, v, o, lse, scale)
        return (o,) + tuple(grads) + (pyvf.branching_attention(q, k, v, scale),) + \
            tuple(pyvf.branching_attention_vjp(q, k, v, do, scale))

    def check(out, a):
        for name, got, (ref, bound) in zip(("o", "dq", "dk", "dv"), out, ld_attention(a, scale, dt)):
            check_close(name, got, ref, bound, dt)
        assert same_bits(out[4], out[0]), "branching_attention == forward's o"
        for i in range(3):
            assert same_bits(out[5 + i], out[1 + i]), "vjp == forward + backward"

    return Case(args, run, check, floats=("q", "k", "v", "do"), contiguous=("q", "k", "v", "do"),
                ordinary=not extreme, dtype=dt)


def case_attention_reference(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    shape = tuple(data.draw(st.integers(1, n), label=k) for k, n in zip("RBHNLd", (2, 2, 2, 3, 2, 3)))
    args = {n: normal(rng, shape, dt) for n in ("q", "k", "v", "do")}

    def run(q, k, v, do):
        return (pyvf.branching_attention_reference(q, k, v),) + tuple(pyvf.branching_attention_reference_vjp(q, k, v, do))

    def check(out, a):  # the long double dense reference with the mask written out, not pyvf's kernel
        for name, got, (ref, bound) in zip(("o", "dq", "dk", "dv"), out, ld_attention(a, 1.0, dt)):
            check_close(name, got, ref, bound, dt)

    return Case(args, run, check, floats=("q", "k", "v", "do"), contiguous=("q", "k", "v", "do"), dtype=dt)


def case_vq(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    M, K, D = data.draw(st.integers(0, 6), label="M"), data.draw(st.integers(1, 6), label="K"), \
        data.draw(st.integers(1, 4), label="D")
    e = draw_exp(data, dt, extreme)
    codes = normal(rng, (K, D), dt, e)
    x = normal(rng, (M, D), dt, e + data.draw(st.integers(-2, 2), label="x exponent offset"))
    if M and data.draw(st.booleans(), label="ties"):
        x[0] = codes[rng.integers(K)]  # an exact hit
        codes = np.concatenate([codes, codes[:1]])  # a duplicate code: ties go to the smaller index
    args = {"x": x, "codes": codes}

    def check(out, a):
        idx, sq = out
        X, C = L(a["x"]), L(a["codes"])
        assert idx.dtype == np.int64 and idx.shape == (M,) and sq.dtype == dt and sq.shape == (M,)
        dist = ((X[:, None, :] - C[None, :, :]) ** 2).sum(-1)  # (M, K) in long double: exact enough
        if not M:
            return
        assert ((0 <= idx) & (idx < len(C))).all(), "an index out of range"
        best = dist.min(1)
        chosen = dist[np.arange(M), idx]
        # the chosen code is the nearest up to the rounding of the distances themselves
        slack = 4 * (D + 2) * u(np.float64) * best + D * LD(tiny(np.float64)) * 4
        assert (chosen <= best + slack).all(), f"not the nearest code: {chosen} vs {best}"
        exact = dist == best[:, None]
        first = np.argmax(exact, 1)
        assert ((idx == first) | (chosen > best)).all() or (chosen <= best + slack).all()
        big = float(np.finfo(dt).max)
        fin = chosen < big * (1 - 4 * D * u(dt))
        assert np.isfinite(sq[fin]).all(), "an infinite distance where the true one is finite"
        check_close("sq_distances", sq[fin], chosen[fin], 4 * (D + 2) * u(dt) * chosen[fin] + D * tiny(dt) * 4, dt)

    return Case(args, lambda x, codes: pyvf.vq_nearest(x, codes), check, floats=("x", "codes"),
                contiguous=("x", "codes"), ordinary=not extreme, dtype=dt)


def case_quantizer(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    D, K = data.draw(st.integers(1, 3), label="D"), data.draw(st.integers(1, 4), label="K")
    B, h, w = (data.draw(st.integers(1, 2), label=n) for n in ("B", "h", "w"))
    train = data.draw(st.booleans(), label="train")
    q = pyvf.EMAQuantizer(D, K, dtype=dt.name, seed=data.draw(st.integers(0, 3), label="qseed"))
    if data.draw(st.booleans(), label="warm"):
        q.forward(normal(rng, (2, D, 1, 1), dt), train=True)
    state0 = q.state_dict()
    e = draw_exp(data, dt, extreme)
    args = {"z": normal(rng, (B, D, h, w), dt, e), "dquantized": normal(rng, (B, D, h, w), dt, draw_exp(data, dt, extreme)),
            "dcommitment": float(rng.uniform(0.1, 2))}

    def run(z, dquantized, dcommitment):
        before = snapshot(q.state_dict())
        try:
            out, cache = q.forward(z, train=train)
        except ALLOWED:
            assert_unchanged(before, q.state_dict(), "the EMA buffers after a failed forward")
            raise
        return out, q.backward(dquantized, dcommitment, cache)[0]

    def check(res, a):
        out, dz = res
        Z = L(a["z"]).transpose(0, 2, 3, 1).reshape(-1, D)
        E = L(state0["embeddings"]).T  # codes before the update
        dist = ((Z[:, None] - E[None]) ** 2).sum(-1)
        idx = out.codes.reshape(-1)
        chosen, best = dist[np.arange(len(idx)), idx], dist.min(1)
        assert (chosen <= best * (1 + 8 * D * u(np.float64)) + D * tiny(np.float64)).all(), "not the nearest code"
        e_ = E[idx]
        qz = out.quantized.transpose(0, 2, 3, 1).reshape(-1, D)
        check_close("quantized", qz, e_, 4 * u(dt) * (np.abs(e_) + np.abs(Z)) + tiny(dt), dt)
        com = ((e_ - Z) ** 2).mean()
        assert abs(LD(out.commitment_loss) - com) <= 8 * (Z.size + 2) * u(dt) * (
            (np.abs(e_) + np.abs(Z)) ** 2).mean() + tiny(dt), "commitment loss"
        dflat = -2 * LD(a["dcommitment"]) / Z.size * (e_ - Z)
        ref = L(a["dquantized"]) + dflat.reshape(B, h, w, D).transpose(0, 3, 1, 2)
        check_close("dz", dz, ref, 8 * u(dt) * (np.abs(ref) + np.abs(dflat).max() + np.abs(L(a["dquantized"])))
                    + 4 * tiny(dt), dt)
        if train:
            assert q.counter == state0["counter"] + 1
            a_ = 1 - LD(np.asarray(q.decay, dt))
            counts = np.bincount(idx, minlength=K).astype(LD)
            S = np.zeros((D, K), LD)
            np.add.at(S.T, idx, Z)
            hcs = L(state0["ema_cluster_size_hidden"]) * (1 - a_) + a_ * counts
            hdw = L(state0["ema_dw_hidden"]) * (1 - a_) + a_ * S
            tol = 16 * (len(idx) + 4) * u(dt)
            check_close("ema_cluster_size_hidden", q.ema_cluster_size_hidden, hcs, tol * (np.abs(hcs) + counts + 1), dt)
            check_close("ema_dw_hidden", q.ema_dw_hidden, hdw,
                        tol * (np.abs(L(state0["ema_dw_hidden"])) + (np.abs(Z).sum(0)[:, None] if len(Z) else 0))
                        + 8 * tiny(dt), dt)
            assert np.isfinite(q.embeddings).all()
        else:
            for k, v in state0.items():
                assert same_bits(np.asarray(q.state_dict()[k]), np.asarray(v)), f"{k} changed without train"

    return Case(args, run, check, floats=("z", "dquantized"), finite=("z", "dquantized"),
                shaped=("z", "dquantized"), ordinary=not extreme, dtype=dt)


KERNEL_CASES = [case_attention, case_attention_reference, case_vq, case_quantizer]


# ---------------------------------------------------------------------------------------
# the optimisers


def case_adamw(data, extreme_ok=True):
    rng = rng_of(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    conv = data.draw(st.sampled_from(["torch", "keras"]), label="eps_convention")
    wd = data.draw(st.sampled_from([0.0, 0.01, 0.3]), label="weight_decay")
    lr = data.draw(st.sampled_from([1e-3, 0.5]), label="lr")
    names = ["a", "b"]
    dts = {n: draw_dtype(data) for n in names}  # parameters may differ in dtype; a gradient has its parameter's
    shapes = {n: draw_shape(data, 2, 3, label=n) for n in names}
    params = {n: normal(rng, shapes[n], dts[n], draw_exp(data, dts[n], extreme)) for n in names}
    opt = pyvf.AdamW(params, lr=lr, weight_decay=wd, eps_convention=conv, decay=["a"])
    for _ in range(data.draw(st.integers(0, 2), label="warm steps")):
        opt.step({n: normal(rng, shapes[n], dts[n]) for n in names})
    p0 = {n: p.copy() for n, p in params.items()}
    s0 = opt.state_dict()
    args = {f"grads[{n!r}]": normal(rng, shapes[n], dts[n], draw_exp(data, dts[n], extreme)) for n in names}

    def run(**grads):
        return opt.step({n: grads[f"grads[{n!r}]"] for n in names})

    def check(out, a):
        assert out == lr
        t = s0["step"] + 1
        b1, b2 = (LD(b) for b in opt.betas)
        for n in names:
            dt = dts[n]
            g, p = L(a[f"grads[{n!r}]"]), L(p0[n])
            m = LD(b1) * L(s0["exp_avg"][n]) + (1 - b1) * g
            v = LD(b2) * L(s0["exp_avg_sq"][n]) + (1 - b2) * g * g
            bc1, bc2 = 1 - b1 ** t, 1 - b2 ** t
            if conv == "torch":
                step = LD(lr) / bc1 * m / (np.sqrt(v) / np.sqrt(bc2) + LD(opt.eps))
            else:
                step = LD(lr) * np.sqrt(bc2) / bc1 * m / (np.sqrt(v) + LD(opt.eps))
            decay = 1 - LD(lr) * LD(wd) if n == "a" else LD(1)
            ref = p * decay - step
            # the bias corrections 1 - b^t are computed in float64 (as torch and Keras do): b^t
            # rounded, then cancelled, a relative error of u b^t / (1 - b^t)
            cond = b1 ** t / bc1 + b2 ** t / bc2 / 2
            check_close(f"exp_avg[{n}]", opt.exp_avg[n], m, 4 * u(dt) * (np.abs(m) + np.abs(g)) + tiny(dt), dt)
            check_close(f"exp_avg_sq[{n}]", opt.exp_avg_sq[n], v, 4 * u(dt) * v + tiny(dt), dt)
            check_close(f"params[{n}]", params[n], ref, 16 * u(dt) * (np.abs(p) + np.abs(step))
                        + 4 * u(np.float64) * cond * np.abs(step) + 4 * tiny(dt), dt)

    def state():
        return {"params": params, "opt": opt.state_dict()}

    return Case(args, run, check, floats=tuple(args), state=state, same_dtype=False, ordinary=not extreme)


def case_clip(data, extreme_ok=True):
    rng = rng_of(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    mode = data.draw(st.sampled_from(["global", "per_tensor"]), label="mode")
    max_norm = data.draw(st.sampled_from([1e-3, 1.0, 1e3]), label="max_norm")
    names = ["a", "b"]
    dts = {n: draw_dtype(data) for n in names}
    args = {f"grads[{n!r}]": normal(rng, draw_shape(data, 2, 3, label=n), dts[n], draw_exp(data, dts[n], extreme))
            for n in names}
    g0 = {k: v.copy() for k, v in args.items()}

    def run(**grads):
        out = optim.clip_grad_norm({n: grads[f"grads[{n!r}]"] for n in names}, max_norm, mode=mode)
        return {f"grads[{n!r}]": v for n, v in out.items()} if mode == "per_tensor" else out

    def check(out, a):
        norms = {k: np.sqrt((L(v) ** 2).sum()) for k, v in g0.items()}
        if mode == "per_tensor":
            assert set(out) == set(args)
            for k, v in g0.items():
                n = norms[k]
                assert abs(LD(out[k]) - n) <= 4 * (v.size + 2) * u(np.float64) * n, f"norm of {k}"
                coef = LD(max_norm) / n if n > max_norm else LD(1)
                check_close(k, a[k], L(v) * coef, 4 * u(v.dtype) * np.abs(L(v) * coef) + tiny(v.dtype), v.dtype)
        else:
            total = np.sqrt(sum(n * n for n in norms.values()))
            size = sum(v.size for v in g0.values())
            assert abs(LD(out) - total) <= 4 * (size + 2) * u(np.float64) * total, "global norm"
            coef = LD(max_norm) / (total + LD(1e-6)) if total + LD(1e-6) > max_norm else LD(1)
            for k, v in g0.items():
                check_close(k, a[k], L(v) * coef, 8 * u(v.dtype) * np.abs(L(v) * coef) + tiny(v.dtype), v.dtype)

    # clipping works on any shape: no shape is constrained
    return Case(args, run, check, floats=tuple(args), shaped=(), same_dtype=False, ordinary=not extreme,
                mutated=tuple(args))


OPTIM_CASES = [case_adamw, case_clip]


CASES = GEOMETRY_CASES + OPTIM_CASES


def _id(f):
    return f.__name__[len("case_"):]


# ---------------------------------------------------------------------------------------
# the generic properties, for every case


def prop_valid(make, data):
    """Valid arguments: the reference's result within its bound, or (extreme magnitudes only) a
    ValueError/MemoryError; inputs unchanged; a failed call changes no state."""
    case = make(data)
    ok, out = run_and_check_unchanged(case, case.args)
    if ok:
        case.check(out, case.args)
    else:
        assert isinstance(out, (ValueError, MemoryError)), f"valid arguments refused with {type(out).__name__}: {out}"
        assert not case.ordinary, f"ordinary arguments refused: {out}"


def prop_bad_dtype(make, data):
    """Any dtype but float32/float64 in a float argument, any non-integer one in an integer
    argument, a list instead of an array: TypeError/ValueError naming it, nothing modified."""
    case = make(data, extreme_ok=False)  # ordinary magnitudes: the only fault is the one made here
    choices = list(case.floats + case.ints)
    assume(choices)
    name = data.draw(st.sampled_from(choices), label="argument")
    kinds = BAD_FLOAT_DTYPES if name in case.floats else BAD_INT_DTYPES
    if name in case.floats and not (case.same_dtype and len(case.floats) > 1):
        kinds = [k for k in kinds if k != "other float"]
    kind = data.draw(st.sampled_from(kinds), label="bad dtype")
    args = dict(case.args)
    args[name] = with_dtype(args[name], kind)
    ok, out = run_and_check_unchanged(case, args)
    assert not ok, f"{name} as {kind} was accepted (a silent cast)"
    assert isinstance(out, (TypeError, ValueError)), f"{type(out).__name__}: {out}"
    assert_names(out, name, () if kind != "other float" else case.floats)


def prop_nonfinite(make, data):
    """NaN or +-inf anywhere in any float argument: ValueError naming it, nothing modified."""
    case = make(data, extreme_ok=False)  # ordinary magnitudes: the only fault is the one made here
    choices = [n for n in case.finite if np.size(case.args[n])]
    assume(choices)
    name = data.draw(st.sampled_from(choices), label="argument")
    a = case.args[name].copy()
    a.flat[data.draw(st.integers(0, a.size - 1), label="index")] = data.draw(
        st.sampled_from([np.nan, np.inf, -np.inf]), label="value")
    args = {**case.args, name: a}
    ok, out = run_and_check_unchanged(case, args)
    assert not ok, f"a non-finite {name} was accepted"
    assert isinstance(out, ValueError), f"{type(out).__name__}: {out}"
    assert_names(out, name)


def prop_layout(make, data):
    """Strided, negatively strided, Fortran-ordered and read-only views: the same result, or a
    ValueError naming the argument (only where the function needs C-contiguous arrays)."""
    case = make(data, extreme_ok=False)  # ordinary magnitudes: the only fault is the one made here
    choices = [n for n in case.floats + case.ints if np.ndim(case.args[n]) >= 1]
    assume(choices)
    name = data.draw(st.sampled_from(choices), label="argument")
    layout = data.draw(st.sampled_from(LAYOUTS), label="layout")
    view = with_layout(case.args[name], layout)
    args = {**case.args, name: view}
    ok, out = run_and_check_unchanged(case, args)
    if ok:
        case.check(out, args)
        return
    if not case.ordinary and isinstance(out, ValueError) and "overflow" in str(out):
        return
    if name in case.mutated and layout == "read-only":
        assert isinstance(out, ValueError) and "read-only" in str(out), out
        assert_names(out, name)
        return
    assert name in case.contiguous and layout != "read-only" and not view.flags.c_contiguous, \
        f"{name} as a {layout} view refused: {out}"
    assert isinstance(out, ValueError), f"{type(out).__name__}: {out}"
    assert_names(out, name)


def prop_bad_shape(make, data):
    """A constrained dimension one too long: TypeError/ValueError naming an argument."""
    case = make(data, extreme_ok=False)  # ordinary magnitudes: the only fault is the one made here
    choices = list(case.shaped)
    if not choices:  # nothing constrained (clip_grad_norm takes any shape)
        return
    name = data.draw(st.sampled_from(choices), label="argument")
    args = {**case.args, name: with_bad_shape(case.args[name])}
    ok, out = run_and_check_unchanged(case, args)
    assert not ok, f"{name} of shape {args[name].shape} was accepted"
    assert isinstance(out, (TypeError, ValueError)), f"{type(out).__name__}: {out}"
    assert_names(out, name, tuple(case.args))


PROPERTIES = [prop_valid, prop_bad_dtype, prop_nonfinite, prop_layout, prop_bad_shape]


def run_property(make, prop):
    """Run prop on make's cases through hypothesis and assert that every example the profile asks
    for ran to the end: the assume()s of the properties (no argument of the kind a property needs,
    e.g. only empty arrays for prop_nonfinite) and hypothesis' own discards must not thin out the
    examples unseen (hypothesis stops after ten times max_examples discards and passes with fewer)."""
    ran = []

    @given(data=st.data())
    def examples(data):
        prop(make, data)
        ran.append(1)

    examples()
    want = settings().max_examples
    assert len(ran) >= want, f"only {len(ran)} of {want} examples were valid: draw valid arguments directly"


@pytest.mark.parametrize("prop", PROPERTIES, ids=lambda p: p.__name__[5:])
@pytest.mark.parametrize("make", CASES, ids=_id)
def test_property(make, prop):
    run_property(make, prop)


if CHILD:  # collected only in the child process (never skipped in the parent: CI counts skips)
    @pytest.mark.parametrize("prop", PROPERTIES, ids=lambda p: p.__name__[5:])
    @pytest.mark.parametrize("make", KERNEL_CASES, ids=_id)
    def test_kernel_property(make, prop):
        run_property(make, prop)


def _child(args, timeout=300, **env_extra):
    env = {**os.environ, "PYVF_PROPERTIES_CHILD": "1", **env_extra}
    with tempfile.TemporaryDirectory() as cwd:  # never the source tree: its pyvf/ is not built
        return subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True,
                              timeout=timeout)


def test_kernel_properties_in_a_subprocess():
    """The test_kernel_* properties in a child pytest: a crash there fails this test with the
    child's output instead of killing the run."""
    r = _child(["-m", "pytest", "-q", "-p", "no:cacheprovider", os.path.abspath(__file__), "-k", "test_kernel_property"])
    tail = (r.stdout + r.stderr)[-6000:]
    assert r.returncode >= 0, f"the child crashed (signal {-r.returncode}):\n{tail}"
    assert r.returncode == 0, f"kernel properties failed:\n{tail}"


# ---------------------------------------------------------------------------------------
# scalars: the schedule and the optimisers' hyperparameters

ODD_SCALARS = [None, "1", [1], np.array([1.0]), True, np.bool_(False), float("nan"), float("inf"), -1, -1.5, 1e308,
               2 ** 70, np.float16(1), np.complex128(1), object()]


@given(step=st.one_of(st.integers(-5, 10 ** 12), st.sampled_from(ODD_SCALARS)),
       peak=st.one_of(st.floats(0, 1e300), st.sampled_from(ODD_SCALARS)),
       warm=st.one_of(st.integers(0, 10 ** 6), st.sampled_from(ODD_SCALARS)),
       total=st.one_of(st.integers(1, 10 ** 7), st.sampled_from(ODD_SCALARS)),
       ratio=st.one_of(st.floats(0, 1), st.sampled_from(ODD_SCALARS)))
@settings(max_examples=_examples(60))
def test_warmup_cosine_lr(step, peak, warm, total, ratio):
    """Either a TypeError/ValueError naming the argument, or lr in [final, peak]: linear up to the
    warmup, exactly final from total_steps on, the cosine in between."""
    ok, out = attempt(optim.warmup_cosine_lr, step, peak, warm, total, ratio)
    if not ok:
        assert names(out, "step", "peak_lr", "warmup_steps", "total_steps", "min_lr_ratio"), out
        return
    assert isinstance(out, float) and math.isfinite(out)
    final = peak * ratio
    assert final * (1 - 1e-15) <= out <= peak * (1 + 1e-15)
    if step <= warm and warm > 0:
        assert out == peak * (step / warm)
    elif step >= total:
        assert out == final
    else:
        frac = (step - warm) / (total - warm)
        ref = final + (peak - final) * (1 + math.cos(math.pi * frac)) / 2
        assert abs(out - ref) <= 8e-16 * peak


@given(R=st.one_of(st.integers(-2, 4), st.sampled_from(ODD_SCALARS)), N=st.integers(-1, 4),
       L=st.one_of(st.integers(0, 3), st.sampled_from(ODD_SCALARS)))
@settings(max_examples=_examples(40))
def test_branching_mask(R, N, L):
    """A TypeError/ValueError naming R, N or L, or the mask of docs/math.md §2 by brute force."""
    ok, m = attempt(pyvf.branching_mask, R, N, L)
    if not ok:
        assert names(m, "R", "N", "L"), m
        return
    T = R * N * L
    want = np.zeros((T, T), bool)
    for t in range(T):
        for s_ in range(T):
            (rq, iq), (rk, ik) = divmod(t // L, N), divmod(s_ // L, N)
            want[t, s_] = (rk == 0 and ik < iq) or (rk == rq and ik == iq)
    assert m.dtype == bool and same_bits(m, want)


def test_branching_mask_of_narrow_integers():
    """numpy uint8 counts whose products wrap in uint8 (20 * 20 = 144): the mask of Python ints."""
    m = pyvf.branching_mask(np.uint8(20), np.uint8(20), 1)
    assert m.shape == (400, 400) and same_bits(m, pyvf.branching_mask(20, 20, 1))


@given(v=st.one_of(st.integers(-3, 2 ** 40), st.sampled_from(ODD_SCALARS)))
@settings(max_examples=_examples(30))
def test_scalar_settings(v):
    """set_num_threads, use_kernel_path and published_weight_decay: a TypeError/ValueError naming
    the argument, or the setting applied (and restored)."""
    n0 = pyvf.num_threads()
    try:
        ok, out = attempt(pyvf.set_num_threads, v)
        if ok:
            assert pyvf.num_threads() == v
        else:
            assert names(out, "n"), out
    finally:
        pyvf.set_num_threads(n0)
    ok, out = attempt(pyvf.use_kernel_path, v)
    assert not ok and names(out, "path"), out
    ok, out = attempt(pyvf.published_weight_decay, v)
    assert ok if isinstance(v, str) else (not ok and names(out, "name")), out


@given(data=st.data())
@settings(max_examples=_examples(30))
def test_optimiser_hyperparameters(data):
    """Odd hyperparameters (types, NaN, ranges, an eps that rounds to 0 in float32): a
    TypeError/ValueError naming it, or an optimiser whose first step is finite."""
    cls = data.draw(st.sampled_from([pyvf.AdamW, pyvf.Adam]))
    hyper = ["lr", "betas", "eps", "eps_convention"] + (["weight_decay", "decay"] if cls is pyvf.AdamW else [])
    name = data.draw(st.sampled_from(hyper))
    value = data.draw(st.one_of(st.sampled_from(ODD_SCALARS), st.floats(allow_nan=True, allow_infinity=True),
                                st.tuples(st.floats(-1, 2), st.floats(-1, 2)), st.just(1e-50)))
    p = {"w": np.ones(3, np.float32)}
    ok, opt = attempt(cls, p, **{name: value})
    if not ok:
        assert names(opt, name, f"{name}[0]", f"{name}[1]"), opt
        return
    before = snapshot(p)
    ok, out = attempt(opt.step, {"w": np.zeros(3, np.float32)})
    if ok:
        assert np.isfinite(p["w"]).all(), f"{name}={value!r}: the step made the parameters non-finite"
    else:
        assert_unchanged(before, p)


# ---------------------------------------------------------------------------------------
# crash-prone cases, each in a child process

_CRASH_SCRIPT = textwrap.dedent("""
    import resource, sys
    import numpy as np
    import pyvf

    def expect(what, fn, kinds):
        try:
            fn()
        except kinds as e:
            print("ok", what, type(e).__name__, flush=True)
            return
        except Exception as e:
            print("WRONG KIND", what, type(e).__name__, e, flush=True)
            sys.exit(3)
        print("NO ERROR", what, flush=True)
        sys.exit(4)

    # a dimension beyond the kernel's limit (L > 2^20): refused, not overrun
    big = np.zeros((1, 1, 1, 1, (1 << 20) + 1, 1))
    expect("attention L > 2^20", lambda: pyvf.branching_attention(big, big, big), (ValueError,))
    # zero-size and one-element corners, every kernel
    one = np.ones((1, 1, 1, 1, 1, 1))
    assert pyvf.branching_attention(one, one, one).shape == one.shape
    expect("attention zero-size", lambda: pyvf.branching_attention(one[:0], one[:0], one[:0]), (ValueError,))
    idx, sq = pyvf.vq_nearest(np.zeros((0, 3)), np.zeros((1, 3)))
    assert idx.shape == (0,)
    expect("vq no codes", lambda: pyvf.vq_nearest(np.zeros((1, 3)), np.zeros((0, 3))), (ValueError,))
    from pyvf.nn import layers
    assert layers.gelu_forward(np.zeros(0))[0].shape == (0,)
    # allocation failures: with the address space capped just above what the outputs need, the
    # kernels' work buffers cannot all be had: each call succeeds or raises MemoryError, never
    # aborts; at least one cap must reach a kernel's own MemoryError
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    rng = np.random.default_rng(0)
    q = rng.standard_normal((1, 1, 1, 2, 4096, 64))
    x = rng.standard_normal((64, 64)); codes = rng.standard_normal((1 << 16, 64))
    # start OpenMP's threads first: libgomp cannot report a failed thread creation, it exits the
    # process ("libgomp: Thread creation failed"), whatever the kernel does
    w = np.ascontiguousarray(q[..., :512, :])
    pyvf.branching_attention(w, w, w)
    pyvf.vq_nearest(x, codes[:4096])
    import gc; gc.collect()

    def capped(what, fn, extras):
        hits = []
        for extra in extras:
            usage = int(open("/proc/self/statm").read().split()[0]) * resource.getpagesize()
            resource.setrlimit(resource.RLIMIT_AS, (usage + int(extra), hard))
            try:
                fn()
                hits.append("ok")
            except MemoryError as e:
                hits.append("kernel" if what in str(e) else "numpy")
            except Exception as e:
                print("WRONG KIND", what, type(e).__name__, e, flush=True)
                sys.exit(3)
            finally:
                resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
        print(what, hits, flush=True)
        if "kernel" not in hits:
            print("NO KERNEL MemoryError", what, flush=True)
            sys.exit(4)

    capped("branching_attention", lambda: pyvf.branching_attention(q, q, q),
           [q.nbytes * f for f in (1.0, 1.02, 1.04, 1.06, 1.1, 1.2, 1.5)])
    capped("vq_nearest", lambda: pyvf.vq_nearest(x, codes), [codes.nbytes * f for f in (0.1, 0.5, 1.0, 1.5)])
    print("done", flush=True)
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="uses /proc and RLIMIT_AS")
def test_crash_prone_cases_in_a_subprocess():
    """Oversized dimensions, zero-size corners and allocation failures in the kernels: a clear
    exception in a child process, which must exit normally (an abort or a segfault fails)."""
    # glibc malloc: one arena and a fixed mmap threshold, so that every large block is mapped
    # when allocated (per-thread arenas and a grown threshold would serve the kernels' buffers
    # from memory already reserved, out of the cap's reach)
    r = _child(["-c", _CRASH_SCRIPT], timeout=120, MALLOC_ARENA_MAX="1", MALLOC_MMAP_THRESHOLD_="65536",
               MALLOC_TRIM_THRESHOLD_="0", MALLOC_TOP_PAD_="0")
    out = r.stdout + r.stderr
    assert r.returncode >= 0, f"the child crashed (signal {-r.returncode}):\n{out[-4000:]}"
    assert r.returncode == 0 and "done" in r.stdout, out[-4000:]
