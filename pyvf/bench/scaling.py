"""Attention memory and time as the number of views N grows: pyvf's branching kernel against the
approaches it replaces (docs/math.md §2), float32, R=3 tree rows, B=1, L=64 tokens per view, scale 1.

    pyvf bench scaling            # N = 2, 4, ..., 64; H=12 dh=64 and H=4 dh=32; long
    pyvf bench scaling --quick    # N = 2, 4, 8; H=4 dh=32

    pyvf         pyvf's branching kernel, (R, B, H, N, L, dh): O(T*dh) memory, T = R*N*L
    naive_pyvf   one sequence per query view, the approach the paper avoids: the trunk, and for each
                 branch r and view i the trunk views 0..i-1, then the branch's view i, then zero
                 views (after every real token: no real query sees them); S = 1 + (R-1)*N
                 sequences of N*L tokens stacked along the batch, run by pyvf's kernel at R=1
    dense_sdpa   torch SDPA on the flat (B, H, T, dh) sequence with the (T, T) branching mask
    dense_numpy  pyvf.branching_attention_reference: the dense NumPy reference, (T, T) logits

Each point (method, size, N) is `pyvf bench attention`'s worker, validated at the first N. A
point predicted (from the method's previous N, by its FLOPs) to take more than --max-point-seconds
is skipped, and so are its larger N. The slopes of log(memory) and log(time) against log(N) are
fitted: in theory pyvf's memory ~N; the dense mask's ~N^2; the naive approach's ~N^2, time ~N^3.
"""

import numpy as np

from pyvf.bench.attention import B, L, METHODS, R, REPEAT, WORKER, theory
from pyvf.bench.common import (MEMORY_METHOD, format_bytes, machine, ms, pyplot, run_worker, save_figure, table,
                               torch_or_none)

SIZES, QUICK_SIZES = ((12, 64), (4, 32)), ((4, 32),)  # (H, dh): the paper's, and a small one
VIEWS, QUICK_VIEWS = (2, 4, 8, 16, 32, 64), (2, 4, 8)
KEYS = ("fwd_bytes", "fb_bytes", "fwd_seconds", "fb_seconds")  # what is measured, and fitted
MAX_POINT_SECONDS = 120  # the naive approach's time grows as N^3: at N=64, H=12, minutes per call


def run_points(sizes, views, methods, threads, max_point_seconds, log=print):
    """Every point, each in a worker process (or skipped, with the reason): a list of dicts."""
    points, torch = [], torch_or_none()
    for H, dh in sizes:
        prev = {}
        for N in views:
            for method in methods:
                p, last = dict(method=method, H=H, dh=dh, N=N, theory=theory(method, H, N, dh, threads)), prev.get(method)
                est = None if last is None or "fb_seconds" not in last else (  # memory, warm-up, timed calls
                    (REPEAT + 3) * (last["fwd_seconds"] + last["fb_seconds"])
                    * p["theory"]["computed_flops"] / last["theory"]["computed_flops"])
                if method == "dense_sdpa" and torch is None:
                    p["skipped"] = "torch is not installed"
                elif last is not None and "skipped" in last:
                    p["skipped"] = "a smaller N of this method was skipped"
                elif max_point_seconds and est is not None and est > max_point_seconds:
                    p["skipped"] = f"predicted {est:.0f} s > --max-point-seconds {max_point_seconds:g}"
                else:
                    try:
                        p.update(run_worker(WORKER, dict(method=method, H=H, dh=dh, N=N, threads=threads,
                                                         validate=N == views[0])))
                    except RuntimeError as e:  # a crashed worker: written down, the study carries on
                        p["error"] = str(e)[-2000:]
                t = p["theory"]
                log(f"  H={H} dh={dh} N={N:>2} {method:<12} " + (
                    f"skipped: {p['skipped']}" if "skipped" in p else f"FAILED: {p['error'].splitlines()[0][:100]}"
                    if "error" in p else f"memory (measured / expected) fwd {format_bytes(p['fwd_bytes'])} / "
                    f"{format_bytes(t['expected_fwd'])}, fwd+bwd {format_bytes(p['fb_bytes'])} / "
                    f"{format_bytes(t['expected_fb'])}; time fwd {ms(p['fwd_seconds'])}, fwd+bwd {ms(p['fb_seconds'])}"),
                    flush=True)
                points.append(p)
                prev[method] = p
    return points


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
    """scaling-{memory,time}-H<h>-dh<d>.png in folder: log-log against N, a panel per pass, a line
    per method, the fitted slopes in the legend. The files, or None without matplotlib."""
    plt = pyplot()
    if plt is None:
        return None
    from matplotlib.ticker import NullFormatter
    files, Ns = [], sorted({p["N"] for p in points})
    for H, dh in sizes:
        for what, unit, scale in (("memory", "MiB", 2 ** 20), ("time", "ms", 1e-3)):
            keys = ("fwd_bytes", "fb_bytes") if what == "memory" else ("fwd_seconds", "fb_seconds")
            fig, axes = plt.subplots(1, 2, figsize=(12, 5.4), sharey=True, layout="constrained")
            for ax, key, title in zip(axes, keys, ("forward", "forward+backward")):
                for i, m in enumerate(methods):
                    pts = [p for p in points if (p["method"], p["H"], p["dh"]) == (m, H, dh) and p.get(key)]
                    slopes = ", ".join(f"{t} {_s(fit[f'{H}x{dh}'][m][k])}" for t, k in zip(("fwd", "fwd+bwd"), keys))
                    if pts:
                        ax.loglog([p["N"] for p in pts], [p[key] / scale for p in pts], "o-", color=f"C{i}",
                                  label=f"{METHODS[m]} (slope {slopes})")
                ax.set_xticks(Ns, [str(n) for n in Ns])
                ax.xaxis.set_minor_formatter(NullFormatter())
                ax.set(title=f"{what}, {title}: H={H} dh={dh} R={R} L={L}", xlabel="N (views)")
            axes[0].set_ylabel(f"extra peak memory ({unit})" if what == "memory" else f"median time ({unit})")
            files.append(save_figure(fig, folder, f"scaling-{what}-H{H}-dh{dh}.png", "lower center", ncol=2))
    return files


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
