"""`pyvf bench accuracy`, `pyvf bench hardcases` and `pyvf bench report` (pyvf/bench/accuracy.py,
hardcases.py, report.py): the quick report through the installed console script from a folder
outside the source tree (its scaling, accuracy and hard-case runs: their JSON's fields, the plots,
the documents), and that the checks can fail: a planted bug is flagged and fails the command, a
sweep whose pyvf line leaves its bound fails, and the naive formulas break where the sweeps say
they do.
"""

import json

import numpy as np
import pytest

import pyvf
from pyvf.bench import BLAS_THREAD_VARS, accuracy, hardcases, report
from pyvf.cli import main
from pyvf.nn import layers
from test_bench_scaling import check_scaling
from test_cli import assert_ran, run


def test_accuracy_variant_outside_its_bound_is_not_timed_and_fails_the_command(monkeypatch, capsys):
    """pyvf's LayerNorm made 1e-3 off (relative): each pyvf variant of it must be reported as FAIL,
    left untimed, and make the command exit with status 1; torch and NumPy, untouched, are timed."""
    forward = layers.layernorm_forward

    def planted(*args, **kwargs):
        y, cache = forward(*args, **kwargs)
        return y * y.dtype.type(1 + 1e-3), cache
    monkeypatch.setattr(layers, "layernorm_forward", planted)
    for var in BLAS_THREAD_VARS:  # the benchmark's --threads 2: in this process, where the bug is
        monkeypatch.setenv(var, "2")
    assert main(["bench", "accuracy", "--quick", "--ops", "layernorm", "--repeat", "3"]) == 1
    out = capsys.readouterr().out
    assert "FAIL layernorm / pyvf float32 " in out and "FAIL layernorm / pyvf float64" in out, out[-2000:]
    assert "FAIL layernorm / torch" not in out and "FAIL layernorm / numpy" not in out, out[-2000:]


def test_pareto_front():
    pts = [(1.0, 1e-3), (2.0, 1e-6), (3.0, 1e-6), (0.5, 1e-2), (2.0, 1e-2)]
    assert accuracy.pareto(pts) == [0, 1, 3]
    # timings within the tolerance are not told apart: one code on two paths, 5% apart, same
    # error, are both on the front; 20% apart, the slower is not
    assert accuracy.pareto([(1.00, 1e-7), (1.05, 1e-7)]) == [0, 1]
    assert accuracy.pareto([(1.00, 1e-7), (1.20, 1e-7)]) == [0]
    assert accuracy.pareto([(1.00, 1e-7), (1.05, 1e-7)], tol=0.0) == [0]


def test_beats_within_the_time_tolerance_only_by_a_smaller_error():
    tol = accuracy.TIME_TOL
    assert accuracy.beats((1.0, 1e-7), (1.0 + 2 * tol, 1e-7)) == "faster and as accurate"
    assert accuracy.beats((1.0, 1e-7), (1.0 + tol / 2, 1e-7)) is None  # noise, not faster
    assert accuracy.beats((1.0 + tol / 2, 1e-16), (1.0, 1e-7)) == "as fast and more accurate"
    assert accuracy.beats((1.0 + 2 * tol, 1e-16), (1.0, 1e-7)) is None  # slower: a trade-off
    assert accuracy.beats((0.5, 2e-7), (1.0, 1e-7)) is None  # faster but less accurate
    assert accuracy.beats((1.0, 1e-7), (1.0, 1e-7)) is None  # a point does not beat its equal
    # never both ways, and a front whatever the points (random clouds, ties and near-ties)
    rng = np.random.default_rng(7)
    for _ in range(200):
        pts = [(float(t), float(e)) for t, e in zip(rng.choice([1.0, 1.04, 1.09, 1.2, 2.0], 6),
                                                      rng.choice([0.0, 1e-16, 1e-7, 2e-7], 6))]
        assert not any(accuracy.beats(p, q) and accuracy.beats(q, p) for p in pts for q in pts)
        assert accuracy.pareto(pts)


def test_ulps_in_the_true_values_spacing():
    want = np.array([1.0, 2.0 ** -140, 0.0])  # normal, float32-subnormal, zero
    got = want + np.array([2.0 ** -23, 2.0 ** -149, 0.0])
    assert accuracy.ulps(got[:1], want[:1], np.float32) == pytest.approx(1.0)
    assert accuracy.ulps(got[1:], want[1:], np.float32) == pytest.approx(1.0)  # the subnormal step
    assert accuracy.ulps(got, want, np.float64) > 1e9


def test_hardcase_sweep_fails_when_pyvf_leaves_its_bound(monkeypatch):
    """pyvf.quat_normalize replaced by the naive q / sqrt(sum q^2): the sweep must fail, at the |q|
    where the squares underflow, and the run must list it as a failure."""
    def naive(q, eps=1e-12):
        with np.errstate(all="ignore"):
            return q / np.sqrt(np.maximum((q * q).sum(-1, keepdims=True), q.dtype.type(eps)))

    monkeypatch.setattr(pyvf, "quat_normalize", naive)
    rep = hardcases.run(["quat-normalize"], mode="quick", log=lambda *a, **k: None)
    c = rep["sweeps"][0]["check"]["pyvf float32"]
    assert not c["ok"] and 1e-25 <= c["first_x_out"] <= 1e-18, c
    assert rep["failures"] and "quat-normalize / pyvf float32" in rep["failures"][0]


def test_check_treats_nan_as_outside():
    sw = dict(x=[1, 2, 3], lines={"pyvf float32": [0.0, float("nan"), 1.0], "other": [1.0, 5.0, 5.0]},
              bounds={"pyvf float32": [1.0, 1.0, 1.0]})
    c = hardcases.check(sw)["pyvf float32"]
    assert not c["ok"] and c["first_x_out"] == 2
    assert hardcases.breaks(sw) == {"other": 2.0}


def check_accuracy(report, plots):
    """`pyvf bench accuracy --quick`'s JSON (as the quick report writes it) and its plots."""
    assert report["failures"] == []
    assert report["machine"]["kernel_path"] == pyvf.kernel_path() and report["machine"]["threads"] == 2
    assert [r["op"] for r in report["results"]] == list(accuracy.OPS)
    for res in report["results"]:
        names = [r["name"] for r in res["variants"]]
        # every kernel path this CPU runs, float64, torch and the NumPy reference
        for p in pyvf.kernel_paths():
            assert any(n.startswith(f"pyvf float32 {p}") for n in names), (res["op"], names)
        assert {"pyvf float64", "torch float32", "numpy float32"} <= set(names), names
        for r in res["variants"]:
            # validated (an error against the reference for every output), then timed
            assert set(r["errors"]) == set(res["outputs"]) and "fail" not in r, (res["op"], r)
            assert r["rel"] <= r["bound"] and len(r["times"]) == 3 and r["seconds"] > 0, r
        pyvf32 = res["variants"][0]
        assert pyvf32["path"] == pyvf.kernel_path() and pyvf32["rel"] <= accuracy.BOUNDS[res["op"]][0]
        f64 = next(r for r in res["variants"] if r["name"] == "pyvf float64")
        assert f64["rel"] < 1e-12, f64  # float64 really ran in float64
        assert (plots / f"accuracy-{res['op'].replace('_', '-')}.png").stat().st_size > 1000
    gelu = next(res for res in report["results"] if res["op"] == "gelu")
    assert gelu["variants"][0]["ulps"]["y"] <= accuracy.GELU_ULPS + 1
    # the textbook 0.5 (1 + erf) form (torch's too) is 0 in the float32 tail: a relative error of 1 = 2^24 ulp
    assert next(r for r in gelu["variants"] if r["name"] == "torch float32")["ulps"]["y"] > 1e6
    vq = next(res for res in report["results"] if res["op"] == "vq_nearest")
    assert all(r["wrong_codes"] == 0 for r in vq["variants"] if r["backend"] == "pyvf")


def check_hardcases(report, plots):
    """`pyvf bench hardcases --quick`'s JSON and plots: every bound holds, and the naive formulas
    break where the sweeps say they do."""
    sweeps = {sw["name"]: sw for sw in report["sweeps"]}
    assert list(sweeps) == list(hardcases.SWEEPS) and report["failures"] == []
    for sw in sweeps.values():
        assert sw["passed"] and sw["bounds"] and all(len(v) == len(sw["x"]) for v in sw["lines"].values()), sw["name"]
        assert all(name.startswith("pyvf") for name in sw["bounds"])
        assert (plots / f"hardcase-{sw['name']}.png").stat().st_size > 1000
    # where the naive formulas leave pyvf's bound (x of the first point outside; None = never)
    brk = {name: sw["breaks"] for name, sw in sweeps.items()}
    assert 1e2 <= brk["attention-spread"]["naive exp (no max) float32"] <= 1e3
    assert brk["attention-mask"]["published -1e4 mask float64"] == pytest.approx(1e4)
    assert brk["attention-mask"]["numpy exact float32"] is None
    for kind in ("layernorm", "groupnorm"):
        assert brk[kind]["one-pass float32"] <= 1e2 and brk[kind]["one-pass float64"] <= 1e4
    # 1 + erf(x / sqrt 2) cancels long before it reaches 0 (at x = -8.4 in float64)
    assert -8 <= brk["gelu"]["naive 0.5 (1 + erf) float64"] < 0 and -8 <= brk["gelu"]["torch float64"] < 0
    assert brk["cross-entropy"]["naive -log(softmax) float32"] <= 1e2
    assert brk["quat-normalize"]["naive q / sqrt(max(sum q^2, eps)) float32"] >= 1e-23
    assert brk["orientation"]["published 2 asin(|vec r|) float32"] >= 1e-2


def test_report_quick_writes_both_documents_with_their_plots(tmp_path):
    proc = run(["bench", "report", "--quick", "--out", "out"], tmp_path)
    assert_ran(proc, "wrote out/performance.md, out/accuracy.md", "PASS")
    out = tmp_path / "out"
    perf, acc = (out / "performance.md").read_text(), (out / "accuracy.md").read_text()
    for doc in (perf, acc):
        assert doc.startswith("<!-- generated by `pyvf bench report --quick`")
        assert f"kernel path **{pyvf.kernel_path()}**" in doc and "**2 threads**" in doc and "machine:" in doc
        # every image the documents show exists
        for link in [p.split("](", 1)[1].split(")")[0] for p in doc.split("![")[1:]]:
            assert (out / link).stat().st_size > 1000, link
    assert "fitted slopes" in perf and "scaling-memory-H4-dh32.png" in perf and "accuracy-gelu.png" in acc
    assert "**PASS**" in acc and "hardcase-orientation.png" in acc and "| pyvf float64 " in acc
    meas = {name: json.loads((out / "measurements" / f"{name}-quick.json").read_text())
            for name in ("accuracy", "hardcases", "scaling-H4-dh32")}
    # the conclusions come first, before any table, each the line the measurements written beside it give
    # (tests/test_bench_report.py checks those lines' numbers against known answers)
    glance = perf.split("## At a glance", 1)[1].split("\n## ", 1)[0]
    assert "\n| " not in perf.split("## The machine", 1)[0] and "## Attention memory" in perf
    slopes = meas["scaling-H4-dh32"]["slopes"]["4x32"]["pyvf"]
    memory, time, speed = (next(line for line in glance.splitlines() if line.startswith(f"* **{q}"))
                           for q in ("Memory", "Time", "Speed against error"))
    assert f"grows as **N^{slopes['fwd_bwd_bytes']:.2f}**" in memory
    assert f"grows as **N^{slopes['fwd_bwd_seconds']:.2f}**" in time
    assert speed == report.speed_error_line(meas["accuracy"])
    check_accuracy(meas["accuracy"], out / "img")
    check_hardcases(meas["hardcases"], out / "img")
    check_scaling(meas["scaling-H4-dh32"], out / "img")
    # every table under the machine and date it was measured on
    for section in perf.split("\n## ")[3:]:
        assert "\n| " not in section or "Measured on " in section.split("\n| ", 1)[0], section[:300]
