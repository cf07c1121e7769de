"""`pyvf bench scaling` (pyvf/bench/scaling.py): the pieces it rests on: the slope fit on exact
power laws, the skip of a point that would not fit in memory, the plots' optional dependency,
the naive stacked prefixes. Its quick run is checked on the quick report's measurements
(check_scaling, called by tests/test_bench_accuracy.py).
"""

import json
import os

import numpy as np
import pytest

from pyvf.bench import scaling
from test_cli import assert_ran, clean_env, run


def check_scaling(report, plots):
    """`pyvf bench scaling --quick`'s JSON (as the quick report writes it) and its plots."""
    points = report["points"]
    failed = [(p["method"], p["N"], p["error"][:300]) for p in points if "error" in p]
    assert not failed, failed
    assert not [p for p in points if "skipped" in p], "a quick-mode point was skipped"
    # every method validated against the float64 reference at the first N, before it was timed
    first = [p for p in points if p["N"] == min(report["config"]["views"])]
    assert {p["method"] for p in first} == set(scaling.METHODS)
    for p in first:
        assert max(p["errors"].values()) <= p["bound"], p
    for p in points:
        assert len(p["fwd_times"]) >= 5 and p["fwd_bytes"] > 0, p
    # the point of the study: pyvf's memory grows more slowly in N than the dense mask's
    s = report["slopes"]["4x32"]
    for key in ("fwd_bytes", "fwd_bwd_bytes"):
        assert s["pyvf"][key] < s["dense_numpy"][key] - 0.5, (key, s["pyvf"], s["dense_numpy"])
        assert s["pyvf"][key] < 1.3, s["pyvf"]
    assert s["pyvf"]["fwd_bytes"] < s["dense_sdpa"]["fwd_bytes"], (s["pyvf"], s["dense_sdpa"])
    # tests/requirements.txt installs matplotlib (the pyvf[plots] extra), so the plots must be there
    for name in ("scaling-memory-H4-dh32.png", "scaling-time-H4-dh32.png"):
        assert (plots / name).stat().st_size > 1000


@pytest.mark.parametrize("p", [0.5, 1.0, 2.0, 3.0, -1.0])
def test_fit_slope_recovers_exact_power_laws(p):
    Ns = [2, 4, 8, 16, 32, 64]
    assert scaling.fit_slope(Ns, [3.7 * n ** p for n in Ns]) == pytest.approx(p, abs=1e-12)
    # missing (None) and non-positive values are left out, not fitted as log(0)
    assert scaling.fit_slope(Ns, [None, 0.0] + [5.0 * n ** p for n in Ns[2:]]) == pytest.approx(p, abs=1e-12)


def test_fit_slope_needs_two_points():
    assert scaling.fit_slope([2, 4], [1.0, None]) is None
    assert scaling.fit_slope([], []) is None
    assert scaling.fit_slope([2, 4], [1.0, 4.0]) == pytest.approx(2.0)


def test_skip_reason_against_a_memory_limit():
    th = scaling.theory("dense_numpy", 3, 1, 4, 8, 64, 32, threads=2)
    assert scaling.skip_reason("dense_numpy", th, available=None) is None  # unknown: run it
    assert scaling.skip_reason("dense_numpy", th, available=2 ** 40) is None
    reason = scaling.skip_reason("dense_numpy", th, available=2 ** 20)
    assert reason and "1 MiB available" in reason
    # the estimate counts the inputs, the largest pass and the worker process itself
    need = th["inputs_bytes"] + max(th["expected_fwd"], th["expected_fwd_bwd"]) + scaling.BASELINE["numpy"]
    assert scaling.skip_reason("dense_numpy", th, available=int(need / scaling.MEM_FRACTION) + 1) is None
    assert scaling.skip_reason("dense_numpy", th, available=int(need / scaling.MEM_FRACTION) - 1)


def test_every_point_skipped_under_a_tiny_memory_limit_and_plots_need_matplotlib(tmp_path):
    """With --mem-limit-mib 1 nothing fits: every point is written down as skipped, no worker is
    started, and the run still succeeds. A matplotlib that fails to import (a stand-in package
    on PYTHONPATH) gives the install hint instead of plots, and the JSON is still written."""
    fake = tmp_path / "fake"
    (fake / "matplotlib").mkdir(parents=True)
    (fake / "matplotlib" / "__init__.py").write_text("raise ImportError('matplotlib is absent (test stand-in)')\n")
    proc = run(["bench", "scaling", "--quick", "--mem-limit-mib", "1", "--json", "out.json", "--plots", "plots"],
               tmp_path, env=clean_env(PYTHONPATH=str(fake)))
    assert_ran(proc, "skipped: needs", "pip install pyvf[plots]", "wrote out.json")
    report = json.loads((tmp_path / "out.json").read_text())
    assert report["plots"] is None and not os.path.exists(tmp_path / "plots")
    assert len(report["points"]) == len(scaling.QUICK_VIEWS) * len(scaling.METHODS)
    for p in report["points"]:
        assert "skipped" in p and "fwd_bytes" not in p, p


def test_naive_stacking_round_trip():
    """Each stacked sequence holds the trunk views before its query view, then the query view;
    unstacking gives the query views back, and sums a trunk key's gradient over its copies."""
    R, B, H, N, L, dh = 3, 1, 2, 4, 2, 3
    x = np.random.default_rng(0).standard_normal((R, B, H, N, L, dh))
    st = scaling.stack_naive(x)  # (S, B, H, N, L, dh)
    assert st.shape == (scaling.n_sequences(R, N), B, H, N, L, dh)
    np.testing.assert_array_equal(scaling.unstack_naive(st, R), x)
    keys = scaling.unstack_naive(st, R, keys=True)
    copies = 1 + (R - 1) * np.arange(N - 1, -1, -1)  # trunk view j is in the trunk and in views i > j of each branch
    np.testing.assert_allclose(keys[0], x[0] * copies[None, None, :, None, None])
    np.testing.assert_array_equal(keys[1:], x[1:])
    do = scaling.stack_naive(x, queries_only=True)
    for r in range(1, R):
        for i in range(N):
            s = 1 + (r - 1) * N + i
            assert not np.delete(do[s], i, axis=2).any()
