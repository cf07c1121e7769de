"""Attention memory and time as the number of views N grows: pyvf's branching kernel against the
approaches it replaces (docs/math.md §2), float32, R=3 tree rows, B=1, L=64 tokens per view, scale 1.

    pyvf bench scaling            # N = 2, 4, ..., 64; H=12 dh=64 and H=4 dh=32; long
    pyvf bench scaling --quick    # N = 2, 4, 8; H=4 dh=32

The methods (attention.METHODS): pyvf's kernel; the naive approach the paper avoids, one sequence
per query view (attention.stack_naive); the (T, T) mask in torch SDPA and in the NumPy reference.
Each point is `pyvf bench attention`'s worker, validated at the first N, skipped (and its larger N)
when predicted to take more than --max-point-seconds. Fitted: the slopes of log(memory) and
log(time) against log(N); in theory pyvf's memory ~N, the others' ~N^2, the naive time ~N^3.
"""

import numpy as np

from pyvf.bench.attention import B, L, METHODS, R, run_points
from pyvf.bench.common import MEMORY_METHOD, machine, save_plot, table

SIZES, QUICK_SIZES = ((12, 64), (4, 32)), ((4, 32),)  # (H, dh): the paper's, and a small one
VIEWS, QUICK_VIEWS = (2, 4, 8, 16, 32, 64), (2, 4, 8)
KEYS = ("fwd_bytes", "fb_bytes", "fwd_seconds", "fb_seconds")  # what is measured, and fitted
MAX_POINT_SECONDS = 120  # the naive approach's time grows as N^3: at N=64, H=12, minutes per call


def fit_slope(Ns, values):
    """The least-squares slope p of log(value) = p log(N) + c over the values > 0 (None: < 2 of them)."""
    pts = [(n, v) for n, v in zip(Ns, values) if v is not None and v > 0]
    if len(pts) < 2:
        return None
    x, y = np.log(np.array(pts, dtype=np.float64)).T
    return float(np.polyfit(x, y, 1)[0])


def fits(points, sizes, methods):
    """{"HxDH": {method: {N: [measured N], fwd_bytes, fb_bytes, fwd_seconds, fb_seconds: slope}}}."""
    out = {}
    for H, dh in sizes:
        out[f"{H}x{dh}"] = per = {}
        for method in methods:
            pts = [p for p in points if (p["method"], p["H"], p["dh"]) == (method, H, dh) and "fb_seconds" in p]
            per[method] = {key: fit_slope([p["N"] for p in pts], [p[key] for p in pts]) for key in KEYS}
            per[method]["N"] = [p["N"] for p in pts]
    return out


def _s(x):
    return "-" if x is None else f"{x:.2f}"


def tables(fit, sizes, methods):
    """Per size, markdown: the fitted slopes."""
    out = []
    for H, dh in sizes:
        f = fit[f"{H}x{dh}"]
        rows = [[m, *(_s(f[m][k]) for k in KEYS), ",".join(map(str, f[m]["N"]))] for m in methods]
        out.append(f"### H={H} dh={dh} (R={R} B={B} L={L}, float32): slopes of log(memory) and log(time) against "
                   "log(N)\n\n" + table(["method", "memory fwd", "memory fwd+bwd", "time fwd", "time fwd+bwd",
                                          "N measured"], rows))
    return out


def plot(points, fit, sizes, methods, folder):
    """scaling-{memory,time}-H<h>-dh<d>.png in folder: a line per method and pass (forward dashed)."""
    files = []
    for H, dh in sizes:
        for what, unit, scale in (("memory", "extra peak memory (MiB)", 2 ** 20), ("time", "median time (ms)", 1e-3)):
            lines = {}
            for key in [k for k in KEYS if k.endswith("bytes" if what == "memory" else "seconds")]:
                for i, m in enumerate(methods):
                    pts = [p for p in points if (p["method"], p["H"], p["dh"]) == (m, H, dh) and p.get(key)]
                    fb = key.startswith("fb")
                    lines[f"{METHODS[m]}, {'fwd+bwd' if fb else 'fwd'} (slope {_s(fit[f'{H}x{dh}'][m][key])})"] = (
                        [p["N"] for p in pts], [p[key] / scale for p in pts], f"C{i}o{'-' if fb else '--'}")
            files.append(save_plot(folder, f"scaling-{what}-H{H}-dh{dh}.png", lines, f"{what}: H={H} dh={dh} R={R} "
                                   f"L={L}", "N (views)", unit, xticks=sorted({p["N"] for p in points})))
    return None if None in files else files


def run(quick=False, threads=2, sizes=None, views=None, methods=tuple(METHODS), max_point_seconds=MAX_POINT_SECONDS,
        plots=None, log=print):
    """The study (module docstring) -> its report; failures: the points whose validation failed."""
    sizes, views = sizes or (QUICK_SIZES if quick else SIZES), views or (QUICK_VIEWS if quick else VIEWS)
    log(f"# Attention memory and time against the number of views N: R={R} B={B} L={L}, float32, scale 1, "
        f"{threads} threads\nmemory: {MEMORY_METHOD}\n")
    points = run_points(sizes, views, methods, threads, max_point_seconds, log=log)
    fit = fits(points, sizes, methods)
    log("\n" + "\n\n".join(tables(fit, sizes, methods)))
    report = dict(config=dict(views=list(views), sizes=[list(s) for s in sizes], threads=threads, methods=list(methods),
                              max_point_seconds=max_point_seconds), machine=machine(threads), points=points, slopes=fit,
                  failures=[f"H={p['H']} dh={p['dh']} N={p['N']} {p['method']}: {p['error']}" for p in points
                            if p.get("error", "").startswith("validation failed")])
    if plots:
        report["plots"] = plot(points, fit, sizes, methods, plots)
        log("plots need matplotlib: pip install pyvf[plots]" if report["plots"] is None
            else "wrote " + ", ".join(report["plots"]))
    return report
