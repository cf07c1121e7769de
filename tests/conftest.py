"""Shared test helpers: the comparison helper, its bitwise twin, seeded random generators, and
forced_threads (the kernels' parallel loops on the tests' small shapes).

Every tolerance comparison in the tests goes through assert_close, so that a failure always
says the same things: the largest absolute and relative error, where it is, and the first
mismatches. assert_bitwise_equal is for the claims that are exact (reproducibility, what a
block cannot see).
"""

import contextlib

import numpy as np
import pytest

import pyvf
from pyvf import _core


def assert_close(name, got, want, rtol, atol=0.0, n_show=5):
    """Assert |got - want| <= rtol * max|want| + atol elementwise (a normwise relative bound).

    The relative error is taken against the largest |want| of the whole array, not element by
    element: attention outputs and gradients have entries near zero whose own relative error
    means nothing. On failure prints the largest absolute error and where it is, the relative
    error, and the first n_show indices that break the bound.
    """
    got_a, want_a = np.asarray(got), np.asarray(want)
    assert got_a.shape == want_a.shape, f"{name}: shape {got_a.shape} != expected {want_a.shape}"
    g, w = got_a.astype(np.float64), want_a.astype(np.float64)
    assert np.isfinite(w).all(), f"{name}: the expected value itself is not finite"
    bad_fin = ~np.isfinite(g)
    if bad_fin.any():
        idx = np.argwhere(bad_fin)[:n_show]
        pytest.fail(f"{name}: {int(bad_fin.sum())} non-finite values, first at {[tuple(map(int, i)) for i in idx]}")
    err = np.abs(g - w)
    scale = np.abs(w).max()
    bound = rtol * scale + atol
    if (err <= bound).all():
        return
    worst = np.unravel_index(np.argmax(err), err.shape)
    bad = np.argwhere(err > bound)
    lines = [
        f"{name}: {len(bad)} of {err.size} elements exceed rtol={rtol:g} * max|want|={scale:.3g} + atol={atol:g}",
        f"  largest abs error {err[worst]:.3e} at {tuple(map(int, worst))}: got {g[worst]!r}, want {w[worst]!r}",
        f"  relative error max|got-want|/max|want| = {err[worst] / scale if scale else np.inf:.3e}",
        "  first mismatches:",
    ]
    for i in bad[:n_show]:
        i = tuple(map(int, i))
        lines.append(f"    {i}: got {g[i]!r}, want {w[i]!r}, |diff| {err[i]:.3e}")
    pytest.fail("\n".join(lines))


def assert_bitwise_equal(name, got, want, n_show=5):
    """Assert identical bits (same dtype, shape and every value; -0.0 and 0.0 differ)."""
    got, want = np.ascontiguousarray(got), np.ascontiguousarray(want)
    assert got.dtype == want.dtype and got.shape == want.shape, \
        f"{name}: {got.dtype}{got.shape} vs {want.dtype}{want.shape}"
    diff = got.view(np.uint8).reshape(got.shape + (-1,)) != want.view(np.uint8).reshape(want.shape + (-1,))
    diff = diff.any(axis=-1)
    if diff.any():
        bad = np.argwhere(diff)[:n_show]
        shown = ", ".join(f"{tuple(map(int, i))}: {got[tuple(i)]!r} vs {want[tuple(i)]!r}" for i in bad)
        pytest.fail(f"{name}: {int(diff.sum())} of {diff.size} elements differ in their bits; first {shown}")


@contextlib.contextmanager
def forced_threads(n):
    """n kernel threads, and every kernel call with any work on them: the size thresholds below
    which a call stays on one thread are skipped (they would keep most test shapes serial, and a
    test of the parallel loops would then test nothing). On the kernel path in use when entered."""
    before = _core.force_parallel()
    with pyvf.threads(n):
        _core.set_force_parallel(True)
        try:
            yield
        finally:
            _core.set_force_parallel(before)


SEED = 20220724  # fixed: every run of the suite draws the same numbers


@pytest.fixture
def rng():
    """A fresh, fixed-seed numpy Generator for each test."""
    return np.random.default_rng(SEED)


@pytest.fixture
def make_qkv(rng):
    """make_qkv(shape, dtype=float64, n=4) -> n standard normal arrays of that shape and dtype
    (q, k, v, do by default), drawn from the test's seeded generator."""

    def make(shape, dtype=np.float64, n=4):
        return tuple(rng.standard_normal(shape).astype(dtype) for _ in range(n))

    return make


@pytest.fixture(params=pyvf.kernel_paths(), ids=lambda p: f"path-{p}")
def kernel_path(request):
    """Run the test once per instruction-set path this machine can execute (baseline, avx2,
    avx512 on x86-64), every kernel switched to it. Kernel test modules use it for all their
    tests: `pytestmark = pytest.mark.usefixtures("kernel_path")`. CI checks (.ci/run) that
    every path the machine runs was exercised."""
    with pyvf.use_kernel_path(request.param):
        yield request.param


def float_arrays(obj):
    """The float arrays in obj, an array or nested tuples/lists of them (a layer's cache)."""
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind == "f":
            yield obj
    elif isinstance(obj, (tuple, list)):
        for o in obj:
            yield from float_arrays(o)
