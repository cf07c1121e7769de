"""`pyvf bench report` (pyvf/bench/report.py) on made-up measurements whose answers are known in
closed form: every number of a conclusion line must be the one the measurements give (a planted
wrong slope or point must be caught), a method not measured is said to be missing, and the report
writes both documents, their plots and the JSON. The runs themselves are tested in
test_bench_validation.py.
"""

import json
import re

import numpy as np
import pytest

from pyvf.bench import accuracy, hardcases, report, scaling

VIEWS = (2, 4, 8, 16, 32)
# method -> (memory ~ c N^p: c, p; time: c, p; the largest N measured)
LAWS = {"pyvf": (2 ** 20, 1.0, 1e-3, 2.0, 32), "naive_pyvf": (3 * 2 ** 20, 2.0, 2e-3, 3.0, 16),
        "dense_sdpa": (5 * 2 ** 20, 1.5, 4e-3, 2.5, 32), "dense_numpy": (0, 0, 0, 0, 0)}


def scaling_report(laws=LAWS):
    """A scaling report (as scaling.run returns it, H=4 dh=32) following `laws` exactly; a method
    skipped above its largest N; the slopes fitted by scaling.fits."""
    points = []
    for N in VIEWS:
        for m, (cm, pm, ct, pt, top) in laws.items():
            p = dict(method=m, H=4, dh=32, N=N)
            if N > top:
                p["skipped"] = "predicted 99 s > --max-point-seconds 30"
            else:
                p.update(fwd_bytes=cm * N ** pm / 2, fwd_seconds=ct * N ** pt / 2, fb_bytes=cm * N ** pm,
                         fb_seconds=ct * N ** pt)
            points.append(p)
    return dict(config=dict(sizes=[[4, 32]], methods=list(laws)), points=points, memory_method="VmHWM",
                slopes=scaling.fits(points, [(4, 32)], list(laws)))


@pytest.mark.parametrize("kind", ["bytes", "seconds"])
def test_scaling_line_states_the_measured_slopes_and_ratios(kind):
    c, p = (0, 1) if kind == "bytes" else (2, 3)
    line = report.scaling_line(scaling_report(), kind)
    assert re.search(r"grows as \*\*N\^([\d.]+)\*\*", line).group(1) == f"{LAWS['pyvf'][p]:.2f}", line
    assert "at N=16, the largest N every method measured" in line, line
    want = [(f"{law[p]:.2f}", f"{law[c] * 16 ** law[p] / (LAWS['pyvf'][c] * 16 ** LAWS['pyvf'][p]):.3g}")
            for m, law in LAWS.items() if m in ("naive_pyvf", "dense_sdpa")]
    assert re.findall(r"N\^([\d.]+), ([\d.]+)x pyvf's", line) == want, line
    assert "Not measured: dense (T,T) mask, NumPy reference: predicted 99 s" in line, line
    # planted: a slope or a measurement that is not the law's changes the line
    rep = scaling_report()
    rep["slopes"]["4x32"]["naive_pyvf"][f"fb_{kind}"] += 0.1
    assert report.scaling_line(rep, kind) != line
    rep = scaling_report()
    next(q for q in rep["points"] if (q["method"], q["N"]) == ("dense_sdpa", 16))[f"fb_{kind}"] *= 1.01
    assert re.findall(r"N\^([\d.]+), ([\d.]+)x pyvf's", report.scaling_line(rep, kind)) != want


def test_scaling_line_without_pyvf_says_so():
    line = report.scaling_line(scaling_report(dict(LAWS, pyvf=(1, 1, 1, 1, 0))), "bytes")
    assert "was not measured (predicted 99 s" in line and "N^" not in line, line


def accuracy_report():
    """Two ops: on `fast` pyvf is 4x faster than torch at half its error; on `slow` 2x slower at
    the same error."""
    def variants(times, rels):
        return [dict(name=n, backend=n.split()[0], bound=1e-3, seconds=t, rel=e)
                for n, t, e in zip(("pyvf float32", "pyvf float64", "torch float32", "numpy float32"), times, rels)]
    machine = dict(platform="Linux", processor="CPU", cpu_count=2, python="3", numpy="2", torch=None, pyvf="0",
                   kernel_path="avx2", kernel_paths=["avx2"], threads=2, generated="today")
    return dict(machine=machine, config=dict(repeat=3), failures=[],
                results=[dict(op="fast", size=[8], variants=variants((1, 2, 4, 9), (1e-7, 0, 2e-7, 3e-7))),
                         dict(op="slow", size=[8], variants=variants((2, 3, 1, 1), (1e-7, 0, 1e-7, 1e-7)))])


def test_speed_error_line_states_the_time_and_error_ratios():
    line = report.speed_error_line(accuracy_report())
    assert "against torch float32, time ratio / error ratio: fast 0.25 / 0.5, slow 2 / 1; faster on 1 of 2 ops, " \
           "at most its error on 2" in line, line
    acc = accuracy_report()
    del acc["results"][1]["variants"][0]["seconds"]  # failed validation: not timed, not compared
    assert "fast 0.25 / 0.5; faster on 1 of 2 ops" in report.speed_error_line(acc)


def test_report_writes_both_documents_plots_and_json(tmp_path, monkeypatch):
    """The runs replaced by made-up reports: the documents say what those measured, every image
    they show exists, every JSON is written."""
    def fake_scaling(quick, threads, plots, **kw):
        rep = dict(scaling_report(), failures=[])
        rep["plots"] = scaling.plot(rep["points"], rep["slopes"], [(4, 32)], rep["config"]["methods"], plots)
        return rep

    sweep = dict(name="layernorm", title="LayerNorm", xlabel="s", ylabel="error", x=[1.0, 10.0], bound_text="1e-6",
                 lines={"pyvf float32": [1e-7, 0.0], "one-pass float32": [1e-7, np.inf]},
                 bounds={"pyvf float32": [1e-6, 1e-6]})
    sweep["check"] = hardcases.check(sweep)
    acc = accuracy_report()
    monkeypatch.setattr(scaling, "run", fake_scaling)
    monkeypatch.setattr(accuracy, "run", lambda quick, threads, plots, **k: dict(acc, results=[
        dict(res, plot=accuracy.plot_op(res, plots)) for res in acc["results"]]))
    monkeypatch.setattr(hardcases, "run", lambda quick, threads, plots, **k: dict(
        sweeps=[dict(sweep, plot=hardcases.plot_sweep(sweep, plots))], failures=[]))
    out = tmp_path / "docs"
    rep = report.run(True, out=str(out), log=lambda *a, **k: None)
    assert rep["failures"] == [] and rep["files"] == [str(out / "performance.md"), str(out / "accuracy.md")]
    perf, acc = (out / "performance.md").read_text(), (out / "accuracy.md").read_text()
    for doc in (perf, acc):
        assert doc.startswith("<!-- generated by `pyvf bench report --quick`")
        for link in re.findall(r"!\[[^]]*\]\(([^)]+)\)", doc):
            assert (out / link).stat().st_size > 1000, link
    assert report.scaling_line(scaling_report(), "bytes") in perf and report.speed_error_line(accuracy_report()) in perf
    assert "scaling-memory-H4-dh32.png" in perf and "accuracy-fast.png" in acc and "hardcase-layernorm.png" in acc
    assert "**PASS**" in acc and "* one-pass float32: leaves pyvf's bound at x = 10" in acc
    for name in ("scaling-H4-dh32-quick", "accuracy-quick", "hardcases-quick"):
        assert json.loads((out / "measurements" / f"{name}.json").read_text())
