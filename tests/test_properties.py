"""Property-based tests (hypothesis) of every public function of pyvf: what it refuses, what it
computes, and what it leaves alone.

For each function (branching attention and its references, vq_nearest, EMAQuantizer, the
geometry functions, AdamW/Adam/clip_grad_norm/warmup_cosine_lr, every forward/backward pair of
pyvf.nn.layers, pyvf.nn.losses and the attention layer) random arguments are drawn (shapes with zero-size dimensions, float32 and
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

The internal layers (pyvf.nn.layers, losses, conv and the attention layer) trust their callers:
for them only the value properties run (prop_valid, prop_layout), on ordinary magnitudes.

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
import pyvf.nn.conv
from pyvf import geometry
from pyvf.nn import layers, losses
from pyvf.train import optim
from pyvf.nn.attention import attention_layer_backward, attention_layer_forward

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
# the layers (pyvf.nn.layers, pyvf.nn.losses): each case runs the forward, then the backward


def case_linear(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    lead = draw_shape(data, 2, 3)
    din, dout = data.draw(st.integers(0, 4), label="din"), data.draw(st.integers(0, 4), label="dout")
    e = [draw_exp(data, dt, extreme) for _ in range(4)]
    args = {"x": normal(rng, lead + (din,), dt, e[0]), "w": normal(rng, (din, dout), dt, e[1]),
            "b": normal(rng, (1, dout), dt, e[2]), "dy": normal(rng, lead + (dout,), dt, e[3])}

    def run(x, w, b, dy):
        y, cache = layers.linear_forward(x, w, b)
        return (y,) + tuple(layers.linear_backward(dy, cache))

    def check(out, a):
        X, W, B, DY = (L(a[k]) for k in ("x", "w", "b", "dy"))
        M = int(np.prod(lead))
        X2, DY2 = X.reshape(M, din), DY.reshape(M, dout)
        y = (X2 @ W + B).reshape(lead + (dout,))
        by = (np.abs(X2) @ np.abs(W) + np.abs(B)).reshape(lead + (dout,))  # |x||w| + |b|: the terms summed
        dx, bdx = (DY2 @ W.T).reshape(lead + (din,)), (np.abs(DY2) @ np.abs(W.T)).reshape(lead + (din,))
        dw, bdw = X2.T @ DY2, np.abs(X2.T) @ np.abs(DY2)
        db, bdb = DY2.sum(0, keepdims=True), np.abs(DY2).sum(0, keepdims=True)
        # a dot product of n terms is within (n + 1) u of the sum of its terms' magnitudes
        for name, got, ref, terms, n in (("y", out[0], y, by, din + 1), ("dx", out[1], dx, bdx, dout),
                                         ("dw", out[2], dw, bdw, M), ("db", out[3], db, bdb, M)):
            check_close(name, got, ref, 2 * (n + 1) * u(dt) * terms + (n + 1) * tiny(dt), dt)

    return Case(args, run, check, floats=("x", "w", "b", "dy"), ordinary=not extreme, dtype=dt)


def case_layernorm(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    lead = draw_shape(data, 2, 3)
    d = data.draw(st.integers(1, 6), label="d")
    e = [draw_exp(data, dt, extreme) for _ in range(4)]
    x = normal(rng, lead + (d,), dt, e[0])
    if x.size and data.draw(st.booleans(), label="offset rows"):  # rows of mean >> spread
        x = (x + normal(rng, lead + (1,), dt, 0) * np.asarray(4 * np.abs(x).max() + 1, dt)).astype(dt)
    args = {"x": x, "gamma": normal(rng, (d,), dt, e[1]), "beta": normal(rng, (d,), dt, e[2]),
            "dy": normal(rng, lead + (d,), dt, e[3])}

    def run(x, gamma, beta, dy):
        y, cache = layers.layernorm_forward(x, gamma, beta)
        return (y,) + tuple(layers.layernorm_backward(dy, cache))

    def check(out, a):
        X, G, Bt, DY = (L(a[k]) for k in ("x", "gamma", "beta", "dy"))
        mean = X.mean(-1, keepdims=True)
        xc = X - mean
        var = (xc * xc).mean(-1, keepdims=True)
        rstd = 1 / np.sqrt(var + LD(np.asarray(1e-5, dt)))
        xhat = xc * rstd
        # the inputs themselves are resolved to ulp(max|x|) of the row: relative to the row's
        # spread sqrt(var + eps) that is p = u max|x| rstd, the conditioning of the centring (the
        # large-mean-small-spread case); plus a few u per pass over d elements
        p = (8 * d + 16) * u(dt) * (np.abs(X).max(-1, keepdims=True) * rstd + 1)  # (..., 1)
        xerr = p * (np.abs(xhat) + 1)
        DYs = DY.reshape(-1, d)
        dxhat = DY * G
        m1, m2 = dxhat.mean(-1, keepdims=True), (dxhat * xhat).mean(-1, keepdims=True)
        dx = rstd * (dxhat - m1 - xhat * m2)
        bdx = rstd * p * (np.abs(dxhat) + np.abs(dxhat).mean(-1, keepdims=True) * (1 + 2 * (np.abs(xhat) + 1) ** 2))
        check_close("y", out[0], xhat * G + Bt, xerr * np.abs(G) + 4 * u(dt) * np.abs(Bt) + tiny(dt), dt)
        check_close("dx", out[1], dx, bdx + 4 * tiny(dt), dt)
        n = DYs.shape[0] + 1
        check_close("dgamma", out[2], (DYs * xhat.reshape(-1, d)).sum(0),
                    n * (np.abs(DYs) * xerr.reshape(-1, d)).sum(0) + n * u(dt) * np.abs(DYs * xhat.reshape(-1, d)).sum(0)
                    + n * tiny(dt), dt)
        check_close("dbeta", out[3], DYs.sum(0), 2 * n * u(dt) * np.abs(DYs).sum(0) + n * tiny(dt), dt)

    return Case(args, run, check, floats=("x", "gamma", "beta", "dy"), ordinary=not extreme, dtype=dt)


def _gelu_ref(x):
    """gelu(x) and gelu'(x) in float64 from math.erfc (accurate over the whole range)."""
    x64 = np.asarray(x, np.float64)
    Phi = np.vectorize(lambda t: 0.5 * math.erfc(-t / math.sqrt(2)))(x64) if x64.size else x64.copy()
    with np.errstate(under="ignore", over="ignore"):
        phi = np.exp(-0.5 * np.minimum(x64 * x64, 1e300)) / math.sqrt(2 * math.pi)
    return L(x64) * L(Phi), L(Phi) + L(x64) * L(phi), L(Phi) + np.abs(L(x64)) * L(phi)


def case_gelu(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    shape = draw_shape(data, 3, 4)
    args = {"x": np.array(normal(rng, shape, dt, draw_exp(data, dt, extreme)) * dt.type(4), dtype=dt),
            "dy": normal(rng, shape, dt, draw_exp(data, dt, extreme))}

    def run(x, dy):
        y, cache = layers.gelu_forward(x)
        return (y,) + tuple(layers.gelu_backward(dy, cache))

    def check(out, a):
        g, dg, dterms = _gelu_ref(a["x"])  # dterms: Phi + |x| phi, what gelu' = Phi + x phi cancels
        X = np.abs(L(a["x"]))
        # the tail's conditioning: erfc's relative condition number there is x^2 (tests/test_layers.py),
        # and the float64 reference carries the same; plus the subnormal steps of tiny results
        rel = (16 + 4 * X * X) * max(u(dt), u(np.float64))
        check_close("y", out[0], g, rel * np.abs(g) + (X + 1) * tiny(dt), dt)
        DY = L(a["dy"])
        check_close("dx", out[1], DY * dg, rel * np.abs(DY) * dterms + 4 * np.abs(DY) * tiny(dt) + tiny(dt), dt)

    return Case(args, run, check, floats=("x", "dy"), ordinary=not extreme, dtype=dt)


def case_embedding(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    n, d = data.draw(st.integers(1, 5), label="n"), data.draw(st.integers(0, 4), label="d")
    shape = draw_shape(data, 2, 4)
    idt = data.draw(st.sampled_from(["int64", "int32", "uint8", "int8"]), label="ids dtype")
    args = {"ids": rng.integers(0, n, shape).astype(idt), "table": normal(rng, (n, d), dt, draw_exp(data, dt, extreme)),
            "dy": normal(rng, shape + (d,), dt, draw_exp(data, dt, extreme))}

    def run(ids, table, dy):
        y, cache = layers.embedding_forward(ids, table)
        return (y,) + tuple(layers.embedding_backward(dy, cache))

    def check(out, a):
        ids, table, DY = a["ids"], a["table"], L(a["dy"])
        assert same_bits(np.ascontiguousarray(out[0]), np.ascontiguousarray(table[ids.astype(np.int64)]))
        ref, terms = np.zeros((n, d), LD), np.zeros((n, d), LD)
        np.add.at(ref, ids.reshape(-1).astype(np.int64), DY.reshape(ids.size, d))
        np.add.at(terms, ids.reshape(-1).astype(np.int64), np.abs(DY).reshape(ids.size, d))
        k = ids.size + 1
        check_close("dtable", out[1], ref, k * u(dt) * terms + k * tiny(dt), dt)

    return Case(args, run, check, floats=("table", "dy"), ints=("ids",), shaped=("table", "dy"),
                ordinary=not extreme, dtype=dt)


def case_mlp(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    lead = draw_shape(data, 2, 3)
    din, dh, dout = (data.draw(st.integers(1, 4), label=n) for n in ("din", "dh", "dout"))
    e = [draw_exp(data, dt, extreme) for _ in range(6)]
    args = {"x": normal(rng, lead + (din,), dt, e[0]), "w_fc": normal(rng, (din, dh), dt, e[1]),
            "b_fc": normal(rng, (1, dh), dt, e[2]), "w_proj": normal(rng, (dh, dout), dt, e[3]),
            "b_proj": normal(rng, (1, dout), dt, e[4]), "dy": normal(rng, lead + (dout,), dt, e[5])}

    def run(x, w_fc, b_fc, w_proj, b_proj, dy):
        y, cache = layers.mlp_forward(x, w_fc, b_fc, w_proj, b_proj)
        return (y,) + tuple(layers.mlp_backward(dy, cache))

    def check(out, a):
        # the reference in long double from the definition, gelu from math.erfc (_gelu_ref), not
        # pyvf's layers. The bound follows each rounding through the layers: a dot product of n
        # terms within 2 (n + 2) u of their magnitudes; |gelu'| <= 1.13 and |gelu''| <= 0.8 carry
        # the hidden layer's error eh into gelu and gelu'; tiny(dt) per step for the subnormal range
        X, DY = L(a["x"]).reshape(-1, din), L(a["dy"]).reshape(-1, dout)  # (M, din), (M, dout)
        Wf, Bf, Wp, Bp = (L(a[k]) for k in ("w_fc", "b_fc", "w_proj", "b_proj"))
        M, ud, tn = X.shape[0], u(dt), tiny(dt)
        H = X @ Wf + Bf  # (M, dh)
        eh = 2 * (din + 2) * ud * (np.abs(X) @ np.abs(Wf) + np.abs(Bf)) + (din + 2) * tn
        g, gp, gterms = _gelu_ref(H)
        rel = (16 + 4 * np.minimum(H * H, 1600)) * max(ud, u(np.float64))  # erfc's tail (case_gelu)
        eg = 1.13 * eh + rel * np.abs(g) + (np.abs(H) + 1) * tn
        egp = 0.8 * eh + rel * gterms + 4 * tn
        DG = DY @ Wp.T  # (M, dh)
        edg = 2 * (dout + 2) * ud * (np.abs(DY) @ np.abs(Wp.T)) + (dout + 2) * tn
        DH = DG * gp
        edh = edg * (np.abs(gp) + egp) + np.abs(DG) * egp + 4 * ud * np.abs(DH) + 4 * (np.abs(DG) + edg + 1) * tn
        G_, DH_ = np.abs(g) + eg, np.abs(DH) + edh  # what pyvf's g and dh can be, in magnitude
        dot = lambda n, terms, carried: 2 * (n + 2) * ud * terms + carried + (n + 2) * tn
        want = {"y": (g @ Wp + Bp, dot(dh, G_ @ np.abs(Wp) + np.abs(Bp), eg @ np.abs(Wp))),
                "dx": (DH @ Wf.T, dot(dh, DH_ @ np.abs(Wf.T), edh @ np.abs(Wf.T))),
                "dw_fc": (X.T @ DH, dot(M, np.abs(X.T) @ DH_, np.abs(X.T) @ edh)),
                "db_fc": (DH.sum(0, keepdims=True), dot(M, DH_.sum(0, keepdims=True), edh.sum(0, keepdims=True))),
                "dw_proj": (g.T @ DY, dot(M, G_.T @ np.abs(DY), eg.T @ np.abs(DY))),
                "db_proj": (DY.sum(0, keepdims=True), dot(M, np.abs(DY).sum(0, keepdims=True), 0))}
        shapes = {"y": lead + (dout,), "dx": lead + (din,)}
        for (name, (ref, bound)), got in zip(want.items(), out):
            shape = shapes.get(name, ref.shape)
            check_close(name, got, ref.reshape(shape), bound.reshape(shape), dt)

    return Case(args, run, check, floats=tuple(args), ordinary=not extreme, dtype=dt)


def case_cross_entropy(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    M, V = data.draw(st.integers(0, 5), label="M"), data.draw(st.integers(1, 5), label="V")
    eps = data.draw(st.sampled_from([0.0, 0.1, 1.0]), label="label_smoothing")
    tdt = data.draw(st.sampled_from(["int64", "int32", "uint16"]), label="targets dtype")
    args = {"logits": normal(rng, (M, V), dt, draw_exp(data, dt, extreme)),
            "targets": rng.integers(0, V, M).astype(tdt),
            "dloss": normal(rng, (M,), dt, draw_exp(data, dt, extreme))}

    def run(logits, targets, dloss):
        loss, cache = losses.cross_entropy_forward(logits, targets, eps)
        return (loss,) + tuple(losses.cross_entropy_backward(dloss, cache))

    def check(out, a):
        Z, t, DL = L(a["logits"]), a["targets"].astype(np.int64), L(a["dloss"])
        z = Z - Z.max(-1, keepdims=True)
        logp = z - np.log(np.exp(z).sum(-1, keepdims=True))
        T = np.full((M, V), LD(np.asarray(eps, dt)) / V)
        T[np.arange(M), t] += 1 - LD(np.asarray(eps, dt))
        loss = -(T * logp).sum(-1)
        # log p is within (V + 4) u (|z| + log V) of the truth (the shift, the sum, the log)
        lerr = (V + 8) * u(dt) * (np.abs(z) + np.log(LD(V)) + 1)
        check_close("loss", out[0], loss, (T * lerr).sum(-1) + tiny(dt), dt)
        p = np.exp(logp)
        check_close("dlogits", out[1], DL[:, None] * (p - T),
                    np.abs(DL[:, None]) * (p * lerr + 4 * u(dt)) + 4 * tiny(dt), dt)

    # a wider logits is valid (more classes): only targets and dloss have a constrained last dimension
    return Case(args, run, check, floats=("logits", "dloss"), ints=("targets",), shaped=("targets", "dloss"),
                ordinary=not extreme, dtype=dt)


def case_pose_loss(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    lead = draw_shape(data, 2, 3)
    tlead = tuple(1 if data.draw(st.booleans(), label="broadcast") else n for n in lead)  # broadcast to raw
    m = data.draw(st.sampled_from([1.0, 0.2, 3.0]), label="pose_multiplier")
    args = {"raw": normal(rng, lead + (7,), dt, draw_exp(data, dt, extreme)),
            "target": normal(rng, tlead + (7,), dt, draw_exp(data, dt, extreme)),
            "dloss": normal(rng, lead, dt, draw_exp(data, dt, extreme))}

    def run(raw, target, dloss):
        loss, cache = losses.pose_loss_forward(raw, target, m)
        return (loss,) + tuple(losses.pose_loss_backward(dloss, cache))

    def check(out, a):
        R, T, DL = L(a["raw"]), np.broadcast_to(L(a["target"]), lead + (7,)), L(a["dloss"])
        mm = np.concatenate([np.full(3, LD(np.asarray(m, dt))), np.ones(4, LD)])
        r = R - mm * T  # (..., 7) residuals
        terms = np.abs(R) + np.abs(mm * T)  # their rounding: u * terms each
        w = np.concatenate([np.full(3, LD(1) / 3), np.full(4, LD(1) / 4)])
        loss = (w * r * r).sum(-1)
        check_close("loss", out[0], loss, (w * (4 * u(dt) * 2 * np.abs(r) * terms + 8 * u(dt) * r * r)).sum(-1)
                    + 8 * tiny(dt), dt)
        draw = 2 * w * r * DL[..., None]
        check_close("draw", out[1], draw, np.abs(2 * w * DL[..., None]) * 4 * u(dt) * (terms + np.abs(r))
                    + 4 * tiny(dt), dt)

    # target's leading shape may broadcast, so only its last dimension is constrained: with_bad_shape
    # changes exactly that
    return Case(args, run, check, floats=("raw", "target", "dloss"), ordinary=not extreme, dtype=dt)


LAYER_CASES = [case_linear, case_layernorm, case_gelu, case_embedding, case_mlp, case_cross_entropy, case_pose_loss]


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


def case_attention_layer(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    R, B, N, Ln = (data.draw(st.integers(1, 2), label=n) for n in ("R", "B", "N", "L"))
    H = data.draw(st.integers(1, 2), label="H")
    d = H * data.draw(st.integers(1, 3), label="dh")
    args = {"x": normal(rng, (R, B, N, Ln, d), dt), "w_attn": normal(rng, (d, 3 * d), dt, -1),
            "b_attn": normal(rng, (1, 3 * d), dt, -1), "w_proj": normal(rng, (d, d), dt, -1),
            "b_proj": normal(rng, (1, d), dt, -1), "dy": normal(rng, (R, B, N, Ln, d), dt)}

    def run(x, w_attn, b_attn, w_proj, b_proj, dy):
        y, cache = attention_layer_forward(x, w_attn, b_attn, w_proj, b_proj, H)
        return (y,) + tuple(attention_layer_backward(dy, cache))

    def check(out, a):
        for g, k in zip(out[1:], ("x", "w_attn", "b_attn", "w_proj", "b_proj")):
            assert g.shape == a[k].shape and g.dtype == dt, k
        # y and every gradient against torch autograd in float64 (the fused projection's v/q/k
        # column order, unscaled logits), with the tree's mask written out here (tree_mask, not pyvf's)
        import torch

        T = R * N * Ln
        mask = torch.from_numpy(tree_mask(R, N, Ln))
        leaves = [torch.tensor(np.array(a[k], np.float64, order="C"), requires_grad=True)  # any layout a test made
                  for k in ("x", "w_attn", "b_attn", "w_proj", "b_proj")]
        tx, tW, tB, tWp, tBp = leaves
        th = (tx @ tW + tB).reshape(R, B, T // R, 3 * d).permute(1, 0, 2, 3).reshape(B, T, 3 * d)
        heads = lambda t: t.reshape(B, T, H, d // H).transpose(1, 2)  # (B, H, T, dh)
        tv, tq, tk = heads(th[..., :d]), heads(th[..., d:2 * d]), heads(th[..., 2 * d:])
        att = (tq @ tk.transpose(-1, -2)).masked_fill(~mask, float("-inf")).softmax(-1) @ tv  # scale 1
        to = att.transpose(1, 2).reshape(B, R, T // R, d).permute(1, 0, 2, 3).reshape(R, B, N, Ln, d)
        ty = to @ tWp + tBp
        ty.backward(torch.from_numpy(np.array(a["dy"], np.float64, order="C")))
        tol = 1e-4 if dt == np.float32 else 1e-11  # normwise, relative to the largest value (and 1: O(1) inputs)
        for name, g, ref in zip(("y", "dx", "dw_attn", "db_attn", "dw_proj", "db_proj"), out,
                                [ty.detach().numpy()] + [leaf.grad.numpy() for leaf in leaves]):
            check_close(name, g, L(ref), tol * (np.abs(ref).max() + 1), dt)

    return Case(args, run, check, floats=tuple(args), shaped=tuple(args), dtype=dt)


KERNEL_CASES = [case_attention, case_attention_reference, case_vq, case_quantizer, case_attention_layer]


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


# ---------------------------------------------------------------------------------------
# the codebook's image layers (pyvf.nn.conv)


def _ld_conv(X, W, stride, pad):
    """conv2d in long double by its definition: -> (y, the padded x, Ho, Wo)."""
    pt, pb, pl, pr = pad
    Xp = np.pad(X, ((0, 0), (0, 0), (pt, pb), (pl, pr)))
    Co, C, kh, kw = W.shape
    Ho, Wo = (Xp.shape[2] - kh) // stride + 1, (Xp.shape[3] - kw) // stride + 1
    y = np.zeros((X.shape[0], Co, Ho, Wo), LD)
    for i in range(kh):
        for j in range(kw):
            patch = Xp[:, :, i:i + stride * (Ho - 1) + 1:stride, j:j + stride * (Wo - 1) + 1:stride]
            y += np.einsum("bchw,oc->bohw", patch, W[:, :, i, j])
    return y, Xp, Ho, Wo


def case_conv2d(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    B, C, Co = data.draw(st.integers(0, 2), label="B"), data.draw(st.integers(1, 3), label="C"), \
        data.draw(st.integers(1, 3), label="Co")
    Hi, Wi = data.draw(st.integers(1, 4), label="Hi"), data.draw(st.integers(1, 4), label="Wi")
    stride = data.draw(st.integers(1, 2), label="stride")
    pad = data.draw(st.one_of(st.integers(0, 1).map(lambda p: (p,) * 4),
                              st.tuples(*[st.integers(0, 1)] * 4)), label="padding")
    # kernels no larger than the padded image, drawn so (nothing filtered): Ho, Wo >= 1
    kh = data.draw(st.integers(1, min(3, Hi + pad[0] + pad[1])), label="kh")
    kw = data.draw(st.integers(1, min(3, Wi + pad[2] + pad[3])), label="kw")
    Ho, Wo = (Hi + pad[0] + pad[1] - kh) // stride + 1, (Wi + pad[2] + pad[3] - kw) // stride + 1
    e = [draw_exp(data, dt, extreme) for _ in range(4)]
    args = {"x": normal(rng, (B, C, Hi, Wi), dt, e[0]), "w": normal(rng, (Co, C, kh, kw), dt, e[1]),
            "b": normal(rng, (Co,), dt, e[2]), "dy": normal(rng, (B, Co, Ho, Wo), dt, e[3])}

    def run(x, w, b, dy):
        y, cache = pyvf.nn.conv.conv2d_forward(x, w, b, stride, pad)
        return (y,) + tuple(pyvf.nn.conv.conv2d_backward(dy, cache))

    def check(out, a):
        X, W, Bb, DY = (L(a[k]) for k in ("x", "w", "b", "dy"))
        y, Xp, _, _ = _ld_conv(X, W, stride, pad)
        ty, _, _, _ = _ld_conv(np.abs(X), np.abs(W), stride, pad)
        K = C * kh * kw
        check_close("y", out[0], y + Bb[:, None, None], (2 * K + 4) * u(dt) * (ty + np.abs(Bb)[:, None, None])
                    + (K + 1) * tiny(dt), dt)
        dxp, tdx = np.zeros(Xp.shape, LD), np.zeros(Xp.shape, LD)
        dw, tdw = np.zeros(W.shape, LD), np.zeros(W.shape, LD)
        for i in range(kh):
            for j in range(kw):
                sl = (slice(None), slice(None), slice(i, i + stride * (Ho - 1) + 1, stride),
                      slice(j, j + stride * (Wo - 1) + 1, stride))
                dxp[sl] += np.einsum("bohw,oc->bchw", DY, W[:, :, i, j])
                tdx[sl] += np.einsum("bohw,oc->bchw", np.abs(DY), np.abs(W[:, :, i, j]))
                dw[:, :, i, j] = np.einsum("bohw,bchw->oc", DY, Xp[sl])
                tdw[:, :, i, j] = np.einsum("bohw,bchw->oc", np.abs(DY), np.abs(Xp[sl]))
        crop = (slice(None), slice(None), slice(pad[0], pad[0] + Hi), slice(pad[2], pad[2] + Wi))
        n = B * Ho * Wo + Co * kh * kw + 4
        check_close("dx", out[1], dxp[crop], 2 * n * u(dt) * tdx[crop] + n * tiny(dt), dt)
        check_close("dw", out[2], dw, 2 * n * u(dt) * tdw + n * tiny(dt), dt)
        check_close("db", out[3], DY.sum((0, 2, 3)), 2 * n * u(dt) * np.abs(DY).sum((0, 2, 3)) + n * tiny(dt), dt)

    # x and w may change size without changing the output's (stride 2 floors): only b and dy are pinned
    return Case(args, run, check, floats=("x", "w", "b", "dy"), shaped=("b", "dy"), ordinary=not extreme, dtype=dt)


def case_groupnorm(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    G, k = data.draw(st.sampled_from([1, 2, 4]), label="groups"), data.draw(st.integers(1, 2), label="C/G")
    B, Hi, Wi = (data.draw(st.integers(1, 2), label=n) for n in ("B", "Hi", "Wi"))
    C = G * k
    e = [draw_exp(data, dt, extreme) for _ in range(4)]
    args = {"x": normal(rng, (B, C, Hi, Wi), dt, e[0]), "gamma": normal(rng, (C,), dt, e[1]),
            "beta": normal(rng, (C,), dt, e[2]), "dy": normal(rng, (B, C, Hi, Wi), dt, e[3])}

    def run(x, gamma, beta, dy):
        y, cache = pyvf.nn.conv.groupnorm_forward(x, gamma, beta, groups=G)
        return (y,) + tuple(pyvf.nn.conv.groupnorm_backward(dy, cache))

    def check(out, a):
        X, Gm, Bt, DY = (L(a[k_]) for k_ in ("x", "gamma", "beta", "dy"))
        Xg = X.reshape(B, G, -1)
        xc = Xg - Xg.mean(-1, keepdims=True)
        rstd = 1 / np.sqrt((xc * xc).mean(-1, keepdims=True) + LD(np.asarray(1e-6, dt)))
        xhat = (xc * rstd).reshape(X.shape)
        n = Xg.shape[-1]
        p = ((8 * n + 16) * u(dt) * (np.abs(Xg).max(-1, keepdims=True) * rstd + 1))  # as for layernorm
        xerr = (p * (np.abs(xc * rstd) + 1)).reshape(X.shape)
        g4, b4 = Gm[:, None, None], Bt[:, None, None]
        check_close("y", out[0], xhat * g4 + b4, xerr * np.abs(g4) + 4 * u(dt) * np.abs(b4) + tiny(dt), dt)
        for name, got in zip(("dx", "dgamma", "dbeta"), out[1:]):
            assert np.isfinite(got).all(), name
        if extreme:
            return  # huge and tiny magnitudes: the forward's bound above and finiteness are what is stated
        # the gradients against the closed form, in long double, per group of n values:
        # dx = rstd (dxhat - mean(dxhat) - xhat mean(dxhat xhat)), dxhat = dy gamma;
        # dgamma = sum_{b,h,w} dy xhat, dbeta = sum_{b,h,w} dy. Ordinary magnitudes: the bound is a
        # few hundred roundings of the largest term (n <= 8 values a group, rstd <= 1e3 for eps 1e-6)
        dxh = (DY * g4).reshape(B, G, -1)
        xh = xhat.reshape(B, G, -1)
        dx = (rstd * (dxh - dxh.mean(-1, keepdims=True) - xh * (dxh * xh).mean(-1, keepdims=True))).reshape(X.shape)
        refs = {"dx": dx, "dgamma": (DY * xhat).sum((0, 2, 3)), "dbeta": DY.sum((0, 2, 3))}
        scale = {"dx": rstd.max() * np.abs(dxh).max() * (1 + np.abs(xh).max() ** 2),
                 "dgamma": np.abs(DY * xhat).sum((0, 2, 3)).max(), "dbeta": np.abs(DY).sum((0, 2, 3)).max()}
        for name, got in zip(("dx", "dgamma", "dbeta"), out[1:]):
            check_close(name, got, refs[name], 512 * u(dt) * (scale[name] + 1) * (1 + rstd.max() * p.max()), dt)

    return Case(args, run, check, floats=("x", "gamma", "beta", "dy"), ordinary=not extreme, dtype=dt)


def case_swish(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    shape = draw_shape(data, 3, 3)
    args = {"x": np.array(normal(rng, shape, dt, draw_exp(data, dt, extreme)) * dt.type(8), dtype=dt),
            "dy": normal(rng, shape, dt, draw_exp(data, dt, extreme))}

    def run(x, dy):
        y, cache = pyvf.nn.conv.swish_forward(x)
        return (y,) + tuple(pyvf.nn.conv.swish_backward(dy, cache))

    def check(out, a):
        X, DY = L(a["x"]), L(a["dy"])
        with np.errstate(over="ignore"):
            s = 1 / (1 + np.exp(-X))
        # sigmoid(x) itself is rounded to the dtype's subnormal steps for x < -87 (float32): y and
        # dx carry that absolute error times |x| and |dy| (1 + |x|)
        check_close("y", out[0], X * s, 8 * u(dt) * np.abs(X * s) + (np.abs(X) + 1) * tiny(dt), dt)
        d = s * (1 + X * (1 - s))
        dterms = s * (1 + np.abs(X) * (1 - s))
        check_close("dx", out[1], DY * d, 16 * u(dt) * np.abs(DY) * dterms + 4 * (np.abs(DY) + 1) * (np.abs(X) + 1)
                    * tiny(dt), dt)

    return Case(args, run, check, floats=("x", "dy"), ordinary=not extreme, dtype=dt)


def case_upsample(data, extreme_ok=True):
    rng, dt = rng_of(data), draw_dtype(data)
    extreme = extreme_ok and data.draw(st.booleans(), label="extreme")
    B, C, Hi, Wi = (data.draw(st.integers(0 if n == "B" else 1, 2), label=n) for n in ("B", "C", "Hi", "Wi"))
    args = {"x": normal(rng, (B, C, Hi, Wi), dt, draw_exp(data, dt, extreme)),
            "dy": normal(rng, (B, C, 2 * Hi, 2 * Wi), dt, draw_exp(data, dt, extreme))}

    def run(x, dy):
        y, cache = pyvf.nn.conv.upsample_nearest2x_forward(x)
        return (y,) + tuple(pyvf.nn.conv.upsample_nearest2x_backward(dy, cache))

    def check(out, a):
        x, DY = a["x"], L(a["dy"])
        assert same_bits(np.ascontiguousarray(out[0]), x.repeat(2, 2).repeat(2, 3)), "upsampled"
        ref = DY.reshape(B, C, Hi, 2, Wi, 2).sum((3, 5))
        check_close("dx", out[1], ref, 4 * u(dt) * np.abs(DY).reshape(B, C, Hi, 2, Wi, 2).sum((3, 5))
                    + 4 * tiny(dt), dt)

    return Case(args, run, check, floats=("x", "dy"), ordinary=not extreme, dtype=dt)


CONV_CASES = [case_conv2d, case_groupnorm, case_swish, case_upsample]
CASES = LAYER_CASES + GEOMETRY_CASES + OPTIM_CASES


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


def _ordinary(make):
    """An internal layer's case: ordinary magnitudes only. The layers trust their callers (the
    models check once, at their boundary), so their properties are the values and the layouts;
    the refusals are the public entry points'."""
    def ordinary(data, extreme_ok=True):
        return make(data, extreme_ok=False)
    ordinary.__name__ = make.__name__
    return ordinary


INTERNAL = [_ordinary(f) for f in LAYER_CASES + CONV_CASES + [case_attention_layer]]
VALUE_PROPERTIES = [prop_valid, prop_layout]


def _pairs(cases, internal):
    return [(m, p) for m in cases for p in PROPERTIES] + [(m, p) for m in internal for p in VALUE_PROPERTIES]


def _pair_id(pair):
    return f"{_id(pair[0])}-{pair[1].__name__[5:]}"


@pytest.mark.parametrize("pair", _pairs(GEOMETRY_CASES + OPTIM_CASES, INTERNAL[:-1]), ids=_pair_id)
def test_property(pair):
    run_property(*pair)


if CHILD:  # collected only in the child process (never skipped in the parent: CI counts skips)
    @pytest.mark.parametrize("pair", _pairs(KERNEL_CASES[:-1], INTERNAL[-1:]), ids=_pair_id)
    def test_kernel_property(pair):
        run_property(*pair)


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
