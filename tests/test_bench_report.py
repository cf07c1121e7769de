"""`pyvf bench report`'s conclusions and plots (pyvf/bench/report.py; the plot functions of
accuracy.py, hardcases.py, scaling.py), on made-up measurements whose answers are known in closed
form: every number of a conclusion line must be the one the measurements give (a planted wrong
slope, time or ratio must be caught), a measurement that is missing must be said to be missing,
and every plot must be readable: no two tick labels overlapping, every legend outside the axes
(so it covers no data), the floors drawn. The quick report itself runs in test_bench_accuracy.py.
"""

import re

import numpy as np
import pytest

from pyvf.bench import accuracy, common, hardcases, report, scaling

SIZE = (4, 32)  # (H, dh) of the made-up scaling report
VIEWS = (2, 4, 8, 16, 32)
# method -> (memory ~ c N^p: c, p; time: c, p; the largest N measured)
LAWS = {"pyvf": (2 ** 20, 1.0, 1e-3, 2.0, 32),
        "naive_pyvf": (3 * 2 ** 20, 2.0, 2e-3, 3.0, 16),
        "dense_sdpa": (5 * 2 ** 20, 1.5, 4e-3, 2.5, 32)}


def scaling_report(laws=LAWS, not_run=("dense_numpy",)):
    """A scaling report (as scaling.run writes it) whose memory and time follow `laws` exactly;
    each method skipped above its largest N; the slopes fitted by the scaling study's own fits()."""
    points = []
    for N in VIEWS:
        for m, (cm, pm, ct, pt, top) in laws.items():
            p = dict(method=m, H=SIZE[0], dh=SIZE[1], N=N, theory=dict(expected_fwd=N, expected_fwd_bwd=N))
            if N > top:
                p["skipped"] = "predicted 99 s > --max-point-seconds 30"
            else:
                p.update(fwd_bytes=cm * N ** pm / 2, fwd_seconds=ct * N ** pt / 2, fwd_bwd_bytes=cm * N ** pm,
                         fwd_bwd_seconds=ct * N ** pt)
            points.append(p)
    methods = list(laws)
    return dict(config=dict(sizes=[list(SIZE)], methods=methods, R=3, B=1, L=64, threads=2,
                            not_run={m: "not in --quick" for m in not_run}),
                points=points, slopes=scaling.fits(points, [SIZE], methods))


def expected_scaling_numbers(kind, laws=LAWS):
    """The closed-form answer: (pyvf's exponent, the N all methods share, [(exponent, ratio to
    pyvf) per other method])."""
    c, p = (0, 1) if kind == "bytes" else (2, 3)
    n = min(law[4] for law in laws.values())
    others = [(law[p], law[c] * n ** law[p] / (laws["pyvf"][c] * n ** laws["pyvf"][p])) for m, law in laws.items()
              if m != "pyvf"]
    return laws["pyvf"][p], n, others


def assert_scaling_line(line, kind, laws=LAWS):
    """Every number of the line against the closed form: exponents to the 2 decimals printed,
    ratios to the 3 significant digits printed."""
    p_pyvf, n, others = expected_scaling_numbers(kind, laws)
    assert re.search(r"grows as \*\*N\^([\d.]+)\*\*", line).group(1) == f"{p_pyvf:.2f}", line
    assert f"at N={n}, the largest N every method measured" in line, line
    got = re.findall(r"N\^([\d.]+), ([\d.]+)x pyvf's", line)
    assert got == [(f"{p:.2f}", f"{r:.3g}") for p, r in others], line


@pytest.mark.parametrize("kind", ["bytes", "seconds"])
def test_scaling_line_states_the_measured_slopes_and_ratios(kind):
    rep = scaling_report()
    line = report.scaling_line(rep, kind)
    assert line.startswith("* **Memory**" if kind == "bytes" else "* **Time**")
    assert_scaling_line(line, kind)
    # the methods not run are named, with the reason, never given a number
    assert "Not measured: dense masked (NumPy): not in --quick" in line


@pytest.mark.parametrize("plant", ["slope", "point", "law"])
def test_scaling_line_check_catches_a_wrong_number(plant):
    """The check above must fail when the line does not match the measurements: a planted fitted
    slope, a planted measurement at the common N, and a line made from other measurements."""
    rep = scaling_report()
    if plant == "slope":
        rep["slopes"]["4x32"]["naive_pyvf"]["fwd_bwd_bytes"] += 0.1
    elif plant == "point":
        p = next(p for p in rep["points"] if (p["method"], p["N"]) == ("dense_sdpa", 16))
        p["fwd_bwd_bytes"] *= 1.01
    else:
        rep = scaling_report(dict(LAWS, pyvf=(2 ** 20, 1.1, 1e-3, 2.0, 32)))
    with pytest.raises(AssertionError):
        assert_scaling_line(report.scaling_line(rep, "bytes"), "bytes")


def test_scaling_line_without_pyvf_says_so():
    rep = scaling_report(dict(LAWS, pyvf=(2 ** 20, 1.0, 1e-3, 2.0, 0)))
    line = report.scaling_line(rep, "bytes")
    assert "was not measured (predicted 99 s" in line and "N^" not in line, line


def variant(name, backend, seconds, rel):
    return dict(name=name, backend=backend, seconds=seconds, rel=rel)


def accuracy_report():
    """Two ops: on `fast` pyvf's default is the fastest (on the front), 0.25x torch's time; on
    `slow` its baseline path is faster at the same error, so it is off the front (torch is faster
    still, but less accurate), 2x torch's time."""
    fast = [variant("pyvf float32 avx2 (default)", "pyvf", 1e-3, 1e-7), variant("pyvf float64", "pyvf", 3e-3, 1e-16),
            variant("torch float32", "torch", 4e-3, 2e-7), variant("numpy float32", "numpy", 9e-3, 3e-7)]
    slow = [variant("pyvf float32 avx2 (default)", "pyvf", 2e-3, 1e-7),
            variant("pyvf float32 baseline", "pyvf", 1.5e-3, 1e-7), variant("torch float32", "torch", 1e-3, 2e-7)]
    return dict(machine=dict(kernel_path="avx2"),
                results=[dict(op="fast", variants=fast), dict(op="slow", variants=slow)])


def assert_speed_line(line, on_front, ratios, beaten):
    assert f"for **{on_front} of {len(ratios)} ops**" in line, line
    assert "its time over torch float32's: " + ", ".join(f"{op} {r:.2g}" for op, r in ratios) in line, line
    assert ("Not on the front: " + "; ".join(f"{op} ({b})" for op, b in beaten)) in line


def test_speed_error_line_states_the_front_and_the_time_ratios():
    line = report.speed_error_line(accuracy_report())
    beaten = [("slow", "pyvf float32 baseline faster and as accurate")]
    assert_speed_line(line, 1, [("fast", 0.25), ("slow", 2.0)], beaten)
    # planted: the default made slower on `fast`; the line changes and the old numbers no longer hold
    acc = accuracy_report()
    acc["results"][0]["variants"][0]["seconds"] = 5e-3
    with pytest.raises(AssertionError):
        assert_speed_line(report.speed_error_line(acc), 1, [("fast", 0.25), ("slow", 2.0)], beaten)


def test_speed_error_line_does_not_count_timing_noise_as_faster():
    """A variant within the timing tolerance (accuracy.TIME_TOL) and as accurate does not take the
    default off the front (it did: the same NumPy code on two kernel paths, 5% apart); one as fast
    and more accurate does, and is named as such."""
    acc = accuracy_report()
    fast = acc["results"][0]["variants"]
    fast.append(variant("pyvf float32 baseline", "pyvf", 0.96e-3, 1e-7))
    assert_speed_line(report.speed_error_line(acc), 1, [("fast", 0.25), ("slow", 2.0)],
                      [("slow", "pyvf float32 baseline faster and as accurate")])
    fast[1]["seconds"] = 1.05e-3  # pyvf float64: as fast, more accurate
    assert_speed_line(report.speed_error_line(acc), 0, [("fast", 0.25), ("slow", 2.0)],
                      [("fast", "pyvf float64 as fast and more accurate"),
                       ("slow", "pyvf float32 baseline faster and as accurate")])


def test_speed_error_line_names_a_variant_that_failed_validation():
    acc = accuracy_report()
    del acc["results"][1]["variants"][0]["seconds"]  # failed validation: not timed
    line = report.speed_error_line(acc)
    assert "for **1 of 2 ops**" in line and "failed validation: slow" in line and "Not on the front" not in line, line


# ---------------------------------------------------------------------------------------
# the plots


def plot_problems(fig):
    """What makes fig hard to read: two tick labels of one axis overlapping, a legend over an
    axes. [] when none."""
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    problems = []
    for i, ax in enumerate(fig.axes):
        box = ax.get_window_extent(r)
        for name, axis, lo, hi in (("x", ax.xaxis, box.x0, box.x1), ("y", ax.yaxis, box.y0, box.y1)):
            labels = []
            for t in axis.get_ticklabels(which="both"):
                b = t.get_window_extent(r)
                centre = (b.x0 + b.x1) / 2 if name == "x" else (b.y0 + b.y1) / 2
                if t.get_visible() and t.get_text() and lo - 1 <= centre <= hi + 1:  # drawn: within the axes
                    labels.append((t.get_text(), b))
            for j, (ta, a) in enumerate(labels):
                for tb, b in labels[j + 1:]:
                    if _overlap(a, b) > 1:
                        problems.append(f"axes {i} {name}: tick labels {ta!r} and {tb!r} overlap")
        for leg in [ax.get_legend(), *fig.legends]:
            if leg is not None and _overlap(leg.get_window_extent(r), box) > 1:
                problems.append(f"axes {i}: a legend covers the axes")
    return problems


def _overlap(a, b):
    """The area (pixels) two boxes share."""
    return max(0.0, min(a.x1, b.x1) - max(a.x0, b.x0)) * max(0.0, min(a.y1, b.y1) - max(a.y0, b.y0))


def test_plot_problems_finds_overlapping_ticks_and_a_legend_over_the_data():
    """The check above can fail: matplotlib's default log axis over 1.3..25 ms labels 2x10^0,
    3x10^0, 4x10^0 into each other (the old LayerNorm plot), and a legend inside the axes covers them."""
    plt = common.pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    ax.loglog([1.3, 25], [1e-6, 1e-16], "o", label="a")
    ax.legend(loc="lower left")
    problems = plot_problems(fig)
    plt.close(fig)
    assert any("tick labels" in p and "x" in p for p in problems), problems
    assert any("legend covers" in p for p in problems), problems


@pytest.fixture
def figures(monkeypatch):
    """Every figure the plot functions save, checked (plot_problems) before it is written: [{path,
    problems, texts (the legend's), hlines (log10 of the dotted horizontal lines' y), ylabels}]."""
    seen = []

    def checked(fig, path, dpi=110):
        texts = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
        hlines = {round(float(np.log10(ln.get_ydata()[0])), 3) for ax in fig.axes for ln in ax.get_lines()
                  if len(set(ln.get_ydata())) == 1 and ln.get_ydata()[0] > 0 and ln.get_linestyle() == ":"}
        seen.append(dict(path=path, problems=plot_problems(fig), texts=texts, hlines=hlines,
                         ylabels=[ax.get_ylabel() for ax in fig.axes]))
        common.save_figure(fig, path, dpi)

    for module in (accuracy, hardcases, scaling):
        monkeypatch.setattr(module, "save_figure", checked)
    return seen


def test_accuracy_plot_is_readable_and_draws_the_unit_roundoffs(figures, tmp_path):
    for times in ((0.26, 0.4, 0.61, 0.64, 0.9), (1.3, 2.1, 6.0, 13.0, 25.0), (0.01, 0.1, 2.0, 40.0, 900.0)):
        res = dict(op="layernorm", title="LayerNorm", size=(512, 128), variants=[
            variant(name, backend, t * 1e-3, rel) for (name, backend, rel), t in zip(
                [("pyvf float32 avx2 (default)", "pyvf", 6e-7), ("pyvf float32 baseline", "pyvf", 6e-7),
                 ("pyvf float64", "pyvf", 0.0), ("torch float32", "torch", 6.3e-7), ("numpy float32", "numpy", 6e-7)],
                times)])
        assert accuracy.plot([res], str(tmp_path)) == [str(tmp_path / "accuracy-layernorm.png")]
    for fig in figures:
        assert fig["problems"] == [], fig
        assert any(t.startswith("unit roundoff") for t in fig["texts"]) and "Pareto front" in fig["texts"], fig
        assert fig["hlines"] == {round(np.log10(accuracy.U32), 3), round(np.log10(accuracy.U64), 3)}, fig
        assert fig["ylabels"][0].endswith(f"(an error of 0 drawn at {accuracy.FLOOR:.0e})"), fig
    assert len(figures) == 3 and (tmp_path / "accuracy-layernorm.png").stat().st_size > 1000


def test_hardcase_plot_is_readable_and_says_where_zero_is_drawn(figures, tmp_path):
    sw = dict(name="layernorm", title="LayerNorm", xlabel="s", ylabel="error", x=[1.0, 10.0, 100.0, 1e3],
              lines={"pyvf float32": [1e-7, 1e-7, 0.0, 1e-7], "one-pass float32": [1e-7, 1e-4, 1e-1, float("inf")],
                     "pyvf float64": [1e-16] * 4},
              bounds={"pyvf float32": [1e-6] * 4, "pyvf float64": [1e-13] * 4})
    path = hardcases.plot_sweep(sw, str(tmp_path))
    fig, = figures
    assert fig["problems"] == [] and path.endswith("hardcase-layernorm.png"), fig
    assert "pyvf's bound(s)" in fig["texts"] and any(t.startswith("unit roundoff") for t in fig["texts"]), fig
    assert len(fig["hlines"]) == 2  # the two unit roundoffs
    assert fig["ylabels"][0] == "error\n(below 1e-17, 0 included, drawn at 1e-17)", fig  # min nonzero 1e-16 / 10


def test_scaling_plots_are_readable_with_the_memory_floor(figures, tmp_path):
    rep = scaling_report()
    files = scaling.plot(rep["points"], rep["slopes"], [SIZE], rep["config"]["methods"], str(tmp_path))
    assert [f.rsplit("/", 1)[1] for f in files] == ["memory_H4_dh32.png", "time_H4_dh32.png"]
    mem, tim = figures
    assert mem["problems"] == [] and tim["problems"] == [], (mem, tim)
    # one legend entry per method, with both fitted slopes where both passes were measured
    f = rep["slopes"]["4x32"]
    assert f"{scaling.METHODS['pyvf']} (slope fwd {f['pyvf']['fwd_bytes']:.2f}, fwd+bwd " \
           f"{f['pyvf']['fwd_bwd_bytes']:.2f})" in mem["texts"], mem
    # the memory plot draws the floor below which a reading is approximate (its points go down to 0.5 MiB)
    assert mem["hlines"] == {round(np.log10(common.MEMORY_NOISE_BYTES / 2 ** 20), 3)}, mem
    assert any("below it a reading is approximate" in t for t in mem["texts"]) and not tim["hlines"], (mem, tim)
