"""Every benchmark (pyvf/bench/) runs on its smallest sizes and validates what it times before
timing it: a bug planted in a timed computation (a NaN gradient, a transposed mask or weight, an
output off by 1e-3, a wrong code) must stop it or record a failure instead of printing a time.
"""

import numpy as np
import pytest
import torch

import pyvf
from pyvf.bench import accuracy, attention, common, hardcases, scaling, steps, vq
from pyvf.nn import layers

QUIET = dict(log=lambda *a, **k: None)
SMOKE = dict(attention=(3, 1, 2, 2, 16, 16), vq_nearest=(256, 64, 16), layernorm=(64, 64), cross_entropy=(64, 128),
             gelu=256, conv2d=(1, 8, 8, 8, 8))


@pytest.fixture(autouse=True)
def _keep_threads():
    """The benchmarks set pyvf's and torch's threads: put them back for the other tests."""
    n, nt = pyvf.num_threads(), torch.get_num_threads()
    yield
    pyvf.set_num_threads(n)
    torch.set_num_threads(nt)


def test_validate_rejects_nan_shape_missing_and_error_above_the_bound():
    ref = [np.ones((2, 3)), np.full(4, 2.0)]
    errs, ok = common.validate([np.ones((2, 3)), np.full(4, 2.0 + 1e-9)], ref, ("a", "b"), 1e-8)
    assert ok and errs["a"] == 0 and errs["b"] == pytest.approx(5e-10)
    assert not common.validate([ref[0], np.full(4, 2.0 + 1e-7)], ref, ("a", "b"), 1e-8)[1]
    for wrong in ([ref[0], np.full(4, np.nan)], [ref[0], np.full(5, 2.0)], [ref[0]], [ref[0], np.full(4, np.inf)]):
        errs, ok = common.validate(wrong, ref, ("a", "b"), 1.0)
        assert not ok and errs["b"] == np.inf, wrong


def test_attention_validates_then_times_every_method(monkeypatch):
    """The workers in this process (worker processes: test_scaling_run_in_workers)."""
    monkeypatch.setattr(attention, "run_worker", lambda work, spec: work(spec))
    report = attention.run(size=(1, 8, 2))
    assert report["failures"] == [] and [p["method"] for p in report["points"]] == ["pyvf", "dense_sdpa", "dense_numpy"]
    assert max(report["points"][0]["errors"].values()) <= attention.BOUND32
    assert all(p["fb_seconds"] > 0 and p["fb_bytes"] >= 0 for p in report["points"])


@pytest.mark.parametrize("who", ["pyvf", "torch SDPA"])
def test_attention_does_not_time_a_wrong_method(who, monkeypatch):
    """A NaN in pyvf's dq; torch given the transposed mask (the workers run in this process)."""
    if who == "pyvf":
        backward = pyvf.branching_attention_backward

        def planted(*args):
            dq, dk, dv = backward(*args)
            return np.where(dq == dq.flat[0], np.nan, dq), dk, dv
        monkeypatch.setattr(pyvf, "branching_attention_backward", planted)
    else:
        mask = pyvf.branching_mask
        monkeypatch.setattr(pyvf, "branching_mask", lambda R, N, L: mask(R, N, L).T.copy())
    monkeypatch.setattr(attention, "run_worker", lambda work, spec: work(spec))
    report = attention.run(size=(1, 8, 2))
    assert len(report["failures"]) == 1 and who in report["failures"][0] and "gemm_gflops" not in report
    assert not any("fb_seconds" in p for p in report["points"] if "error" in p)


def test_naive_stacked_prefixes_give_the_branching_output_and_gradients():
    """In process, at the smallest size: the naive sequences, unstacked, give back the branching
    output and gradients (the stacking is right)."""
    out = attention.worker(dict(method="naive_pyvf", H=1, dh=8, N=2, threads=2, validate=True))
    assert "error" not in out and max(out["errors"].values()) <= attention.BOUND32, out
    assert out["fb_bytes"] > 0 and out["fb_seconds"] > 0


def test_scaling_run_in_workers():
    """(The plots: test_bench_report.py.)"""
    rep = scaling.run(sizes=((1, 8),), views=(2, 4), methods=("pyvf",), **QUIET)
    assert rep["failures"] == [] and [p.get("error") for p in rep["points"]] == [None] * 2
    assert rep["slopes"]["1x8"]["pyvf"]["N"] == [2, 4]


@pytest.mark.parametrize("p", [0.5, 1.0, 3.0, -1.0])
def test_fit_slope_recovers_exact_power_laws(p):
    Ns = [2, 4, 8, 16]
    assert scaling.fit_slope(Ns, [3.7 * n ** p for n in Ns]) == pytest.approx(p, abs=1e-12)
    assert scaling.fit_slope(Ns, [None, 0.0] + [5.0 * n ** p for n in Ns[2:]]) == pytest.approx(p, abs=1e-12)
    assert scaling.fit_slope(Ns[:2], [1.0, None]) is None


@pytest.mark.parametrize("op", list(accuracy.OPS))
def test_accuracy_op_validates_and_times_every_variant(op, monkeypatch):
    monkeypatch.setitem(accuracy.SIZES, True, SMOKE)
    res = accuracy.run_op(op, True, repeat=1, **QUIET)
    assert [r["name"] for r in res["variants"]] == ["pyvf float32", "pyvf float64", "torch float32", "numpy float32"]
    for r in res["variants"]:
        assert "fail" not in r and r["rel"] <= r["bound"] and r["seconds"] > 0, r
    assert res["variants"][1]["rel"] < 1e-12  # float64 really ran in float64


def test_accuracy_variant_outside_its_bound_is_not_timed(monkeypatch):
    """pyvf's LayerNorm made 1e-3 off: both pyvf variants fail, untimed; torch and NumPy pass."""
    forward = layers.layernorm_forward
    monkeypatch.setattr(layers, "layernorm_forward", lambda *a, **k: (lambda y, c: (y * (1 + 1e-3), c))(*forward(*a, **k)))
    monkeypatch.setitem(accuracy.SIZES, True, SMOKE)
    report = accuracy.run(True, ops=("layernorm",), **QUIET)
    assert [f.split(":")[0] for f in report["failures"]] == ["layernorm / pyvf float32", "layernorm / pyvf float64"]
    assert ["seconds" in r for r in report["results"][0]["variants"]] == [False, False, True, True]


def test_hardcases_hold_and_the_naive_formulas_break_where_the_sweeps_say():
    """(The plots: test_bench_report.py.)"""
    report = hardcases.run(True, **QUIET)
    assert report["failures"] == []
    brk = {sw["name"]: {n: c["first_x_out"] for n, c in sw["check"].items()} for sw in report["sweeps"]}
    assert 1e2 <= brk["attention-spread"]["naive exp (no max) float32"] <= 1e3
    assert brk["attention-mask"]["published -1e4 mask float64"] == pytest.approx(1e4)
    assert brk["attention-mask"]["numpy exact float32"] is None
    assert brk["layernorm"]["one-pass float32"] <= 1e2 and brk["layernorm"]["one-pass float64"] <= 1e4
    assert -8 <= brk["gelu"]["naive 0.5 (1 + erf) float64"] < 0 and -8 <= brk["gelu"]["torch float64"] < 0
    assert brk["cross-entropy"]["naive -log(softmax) float32"] <= 1e2


def test_hardcase_sweep_fails_when_pyvf_leaves_its_bound(monkeypatch):
    """LayerNorm by the one-pass variance: the sweep fails where the mean's square cancels; a NaN
    counts as outside."""
    def one_pass(x, gamma, beta, eps=1e-5):
        m = x.mean(-1, keepdims=True)
        return (x - m) / np.sqrt((x * x).mean(-1, keepdims=True) - m * m + eps) * gamma + beta, None
    monkeypatch.setattr(layers, "layernorm_forward", one_pass)
    with np.errstate(invalid="ignore"):
        report = hardcases.run(True, names=("layernorm",), **QUIET)
    c = report["sweeps"][0]["check"]["pyvf float32"]
    assert c["first_x_out"] <= 1e2 and "layernorm / pyvf float32" in report["failures"][0]
    sw = dict(x=[1, 2], lines={"pyvf float32": [0.0, float("nan")]}, bounds={"pyvf float32": [1.0, 1.0]})
    assert hardcases.check(sw)["pyvf float32"]["first_x_out"] == 2


def test_vq_runs_and_refuses_to_time_a_wrong_method(monkeypatch):
    small = dict(quick=True, size=dict(M=512, K=64, D=16), checked_rows=256)
    assert vq.run(**small)["failures"] == []
    methods = vq.methods
    monkeypatch.setattr(vq, "methods", lambda: dict(methods(), **{"torch cdist + argmin": lambda x, c: np.zeros(
        len(x), dtype=np.int64)}))
    report = vq.run(**small)
    assert any("torch cdist" in f for f in report["failures"]) and report["methods"]["torch cdist + argmin"]["seconds"] is None
    monkeypatch.setattr(vq, "vq_nearest", lambda x, c: (np.zeros(len(x), dtype=np.int64), None))
    assert "pyvf disagrees" in vq.run(**small)["failures"][0]


def test_first_step_differs_on_nan_and_missing():
    good = dict(loss=1.5, gradients={"w": [2.0, 0.5]}, loss_after_update=1.4)
    assert steps.first_step_differs(good, good) is None
    for bad in (dict(good, loss=np.nan), dict(good, loss_after_update=np.nan), dict(good, gradients={}),
                dict(good, gradients={"w": [2.0, np.nan]})):
        assert steps.first_step_differs(bad, good), bad
    a = np.random.default_rng(0).standard_normal((8, 8))
    right, wrong = steps.checksums({"w": a})["w"], steps.checksums({"w": a.T})["w"]
    assert right[0] == pytest.approx(wrong[0]) and abs(right[1] - wrong[1]) > 0.1 * right[0]


def test_transformer_backward_and_optimizer_bugs_are_caught_before_timing(monkeypatch):
    t = steps.transformer_torch("transformer", 1)
    assert steps.first_step_differs(steps.transformer_pyvf("transformer", 1), t) is None
    with monkeypatch.context() as m:  # a square weight's gradient transposed
        backward = pyvf.Transformer.backward

        def transposed(self, *a, **k):
            g = backward(self, *a, **k)
            name = next(n for n, x in g.items() if x.ndim == 2 and x.shape[0] == x.shape[1])
            return dict(g, **{name: np.ascontiguousarray(g[name].T)})
        m.setattr(pyvf.Transformer, "backward", transposed)
        assert "gradients" in steps.first_step_differs(steps.transformer_pyvf("transformer", 1), t)
    step = pyvf.AdamW.step  # uphill
    monkeypatch.setattr(pyvf.AdamW, "step", lambda self, grads: step(self, {k: -g for k, g in grads.items()}))
    assert "after update" in steps.first_step_differs(steps.transformer_pyvf("transformer", 1), t)


def test_codebook_optimizer_bug_is_caught_before_timing(monkeypatch):
    t = steps.codebook_torch("codebook-quick", 1)
    assert steps.first_step_differs(steps.codebook_pyvf("codebook-quick", 1), t) is None
    step = pyvf.Adam.step
    monkeypatch.setattr(pyvf.Adam, "step", lambda self, grads: step(self, {k: -g for k, g in grads.items()}))
    assert "after update" in steps.first_step_differs(steps.codebook_pyvf("codebook-quick", 1), t)
