"""pyvf.bench.profile: every kernel call is timed under its (kernel, shapes), the time outside the
kernels is what is left, the wrappers leave no trace, a result that depends on the thread count
is caught, and the table's speed-ups and shares are the recorded times'. (Its quick run from a
temporary folder is in test_cli.py.)"""

import time

import numpy as np
import pytest

import pyvf
from pyvf import _core
from pyvf.bench import profile


def test_kernel_timer_counts_each_call_under_its_shapes_and_leaves_no_trace(rng):
    a, b = rng.standard_normal((3, 5)).astype(np.float32), rng.standard_normal((3, 5)).astype(np.float32)
    c = rng.standard_normal((7,)).astype(np.float32)
    with profile.kernel_timer() as totals:
        assert "add" in vars(_core)  # the wrapper is the module attribute, found before __getattr__
        got = [pyvf.nn.layers.add(a, b) for _ in range(3)]
        pyvf.nn.layers.add(c, c)
    assert "add" not in vars(_core) and not any(k in vars(_core) for k in _core.kernels())
    assert totals["add 3x5"][0] == 3 and totals["add 7"][0] == 1
    assert set(totals) == {"add 3x5", "add 7"}
    assert all(np.array_equal(g, a + b) for g in got)  # the wrapped kernel's result, unchanged


def test_kernel_timer_removes_its_wrappers_when_the_block_raises():
    with pytest.raises(RuntimeError, match="planted"):
        with profile.kernel_timer():
            raise RuntimeError("planted")
    assert not any(k in vars(_core) for k in _core.kernels())


def test_profile_call_splits_kernel_time_from_the_rest_and_checks_the_bits(rng):
    x = rng.standard_normal((256, 256)).astype(np.float32)
    sleep = 0.02  # outside any kernel

    def prepare():
        def step():
            time.sleep(sleep)
            last["y"] = pyvf.nn.layers.add(x, x)
        last = {}
        return step, lambda: last["y"].ravel()
    prof = profile.profile_call(prepare, [1, 2], steps=2)
    for n in (1, 2):
        parts = prof["parts"][n]
        assert set(parts) == {"add 256x256", profile.OUTSIDE}
        assert parts[profile.OUTSIDE] >= sleep
        assert sum(parts.values()) == pytest.approx(prof["step"][n], rel=1e-9)  # the parts add up to the step
    assert prof["calls"] == {"add 256x256": 1.0} and prof["bitwise"]

    def moving():  # a result that depends on the thread count
        return (lambda: None), (lambda: np.array([pyvf.num_threads()], np.float64))
    assert not profile.profile_call(moving, [1, 2], steps=1)["bitwise"]


def test_profile_table_on_made_up_times():
    prof = {"parts": {1: {"k a": 0.8, "k b": 0.1, "k c": 0.05, profile.OUTSIDE: 0.05},
                      4: {"k a": 0.2, "k b": 0.1, "k c": 0.01, profile.OUTSIDE: 0.05}},
            "calls": {"k a": 2.0, "k b": 10.0, "k c": 1.0}, "step": {1: 1.0, 4: 0.36}, "bitwise": True}
    header, rows = profile.profile_table(prof, top=1)
    assert header == ["part", "calls", "1 thr: ms (speed-up)", "4 thr: ms (speed-up)", "share on 4 thr"]
    assert rows[0] == ["k a", "2", "800.0 (1.0x)", "200.0 (4.0x)", "56%"]
    assert rows[1] == ["2 other kernel shapes", "11", "150.0 (1.0x)", "110.0 (1.4x)", "31%"]
    assert rows[2] == [profile.OUTSIDE, "", "50.0 (1.0x)", "50.0 (1.0x)", "14%"]
    assert rows[3] == ["the whole step", "", "1000.0 (1.0x)", "360.0 (2.8x)", "100%"]
