"""Attention memory and time as the number of views N grows: pyvf's branching kernel against the
approaches it replaces (issue 11, item 1; docs/math.md §2).

    pyvf bench scaling                             # N = 2, 4, ..., 64; H=12 dh=64 and H=4 dh=32; long
    pyvf bench scaling --quick                     # N = 2, 4, 8; H=4 dh=32
    pyvf bench scaling --json out.json --plots plots/

Methods (float32, R=3 tree rows, B=1, L=64 tokens per view, scale 1):
  pyvf         pyvf's branching kernel, (R, B, H, N, L, dh): O(T*dh) memory, T = R*N*L
  naive_pyvf   the naive approach the paper avoids: one sequence per query view (the trunk, and
               for each branch r and view i the trunk views 0..i-1 followed by the branch's view
               i), padded with zero views to N*L tokens and stacked along the batch: S = 1 +
               (R-1)*N sequences. Run with pyvf's kernel at R=1, which is plain block-causal
               attention over views (pyvf has no separate causal kernel: R=1 is that kernel).
               Padding comes after every real token, so no real query sees it; the stacked output
               gives back exactly the branching output
  dense_sdpa   torch SDPA on the flat (B, H, T, dh) sequence with the (T, T) branching mask
  dense_numpy  pyvf.branching_attention_reference: the NumPy dense reference, (T, T) logits

Every point (method, size, N) runs in a process of its own (this module, worker()): it
validates its output (and gradients) against the float64 dense reference at the first N of each
size, then measures one call's extra peak memory (pyvf.bench.common.peak_memory: resident memory,
inputs excluded, outputs included) forward and forward+backward, then times each (median of
--repeat calls after a warm-up). Beside the measurement: the tokens held, the block pairs
computed and the memory expected. A point whose
inputs plus expected memory would not fit in MEM_FRACTION of /proc/meminfo MemAvailable (read
before each point; --mem-limit-mib overrides it) is skipped with the reason written down, as is a
point whose predicted run time exceeds --max-point-seconds.

The fitted slope of log(memory) and log(time) against log(N) per method is in the table and on
the plots (--plots DIR, matplotlib: `pip install pyvf[plots]`). Theory: pyvf's memory ~N^1; the
dense mask ~N^2; the naive stacked approach ~N^2 in tokens and activations, time ~N^3 (S
sequences of N*L tokens each). At small N the per-thread, N-independent buffers hold pyvf's
slope below 1.
"""

import os
import time

import numpy as np

import pyvf
from pyvf.bench.attention import (BOUND32, BOUND_OTHERS, attended_pairs, error, expected_memory, make_inputs, ms,
                                  pyvf_fns, reference_fns, torch_backend, torch_fns)
from pyvf.bench.common import (MEMORY_NOISE_BYTES, cpu_name, format_bytes, legend_outside, machine, measured,
                               median_time, memory_method, pyplot, run_worker, save_figure, table, worker_main,
                               write_outputs)

WORKER = "pyvf.bench.scaling"  # this module, run as `python -m WORKER SPEC` (worker_main)
R, B, L = 3, 1, 64  # tree rows, batch, tokens per view (docs/math.md §1)
SIZES = ((12, 64), (4, 32))  # (H, dh): the paper's, and a small one
QUICK_SIZES = ((4, 32),)
VIEWS = (2, 4, 8, 16, 32, 64)
QUICK_VIEWS = (2, 4, 8)
METHODS = {
    "pyvf": "pyvf branching kernel",
    "naive_pyvf": "naive stacked, pyvf kernel at R=1",
    "dense_sdpa": "dense (T,T) mask, torch SDPA",
    "dense_numpy": "dense (T,T) mask, NumPy reference",
}
TORCH_METHODS = ("dense_sdpa",)
# The other implementations are held to BOUND_OTHERS (pyvf/bench/attention.py: they compute the
# same function, where a wrong mask or layout is an O(1) error); pyvf (and pyvf's kernel on the
# stacked sequences) to BOUND32, tests/test_attention.py's bound.
# the naive approach's time grows as N^3: at N=64, H=12 one forward+backward is minutes on 2 cores
MAX_POINT_SECONDS = 120
MEM_FRACTION = 0.8  # of MemAvailable a point may plan to use: the rest is margin (others share the machine)
# resident memory of a worker before its inputs (python + numpy + pyvf; + torch): measured ~60 MiB
# and ~350 MiB here, rounded up
BASELINE = dict(numpy=128 * 2 ** 20, torch=512 * 2 ** 20)


# ---------------------------------------------------------------------------------------
# the naive approach: one sequence per query view, stacked along the batch


def n_sequences(R, N):
    """S: the trunk, and one sequence per (branch, view)."""
    return 1 + (R - 1) * N


def stack_naive(x, queries_only=False):
    """(R, B, H, N, L, dh) -> (S, B, H, N, L, dh): sequence 0 is the trunk; sequence 1 + (r-1)*N + i
    holds the trunk views 0..i-1, then branch r's view i, then zero views up to N.

    queries_only (for the upstream gradient do): zeros in place of the trunk copies of the branch
    sequences, whose outputs the naive approach throws away (only their view i is its query)."""
    R, B, H, N, L, dh = x.shape
    out = np.zeros((n_sequences(R, N),) + x.shape[1:], dtype=x.dtype)  # (S, B, H, N, L, dh)
    out[0] = x[0]
    for r in range(1, R):
        for i in range(N):
            s = 1 + (r - 1) * N + i
            if not queries_only:
                out[s, :, :, :i] = x[0, :, :, :i]
            out[s, :, :, i] = x[r, :, :, i]
    return out


def unstack_naive(st, R, keys=False):
    """The inverse of stack_naive for an output or a gradient (S, B, H, N, L, dh) -> (R, B, H, N, L, dh).

    A query token appears in one sequence only (o, dq: keys=False); a trunk key in the trunk and in
    every later branch sequence, so its gradient (dk, dv: keys=True) is the sum over them."""
    S, B, H, N, L, dh = st.shape
    out = np.zeros((R, B, H, N, L, dh), dtype=st.dtype)
    out[0] = st[0]
    for r in range(1, R):
        for i in range(N):
            s = 1 + (r - 1) * N + i
            out[r, :, :, i] = st[s, :, :, i]
            if keys:
                out[0, :, :, :i] += st[s, :, :, :i]
    return out


def naive_pyvf_fns(qs, ks, vs, dos):
    """pyvf's kernel at R=1 (block-causal over views) on the stacked (S, B, H, N, L, dh) inputs,
    seen as one row of S*B batch entries (a free reshape)."""
    S, B = qs.shape[:2]
    return pyvf_fns(*(x.reshape((1, S * B) + x.shape[2:]) for x in (qs, ks, vs, dos)))


# ---------------------------------------------------------------------------------------
# theory: what each method holds and computes, and the memory expected


def theory(method, R, B, H, N, L, dh, threads, backend="FLASH_ATTENTION"):
    """The counts of one point, float32: tokens held (per batch entry and head), (L, L) block pairs
    computed per (b, h), the inputs' bytes and the extra memory expected forward and
    forward+backward (attention.expected_memory; backend: torch SDPA's)."""
    S = R * B * H * N * L * dh * 4  # one array like q
    T = R * N * L
    if method == "naive_pyvf":  # pyvf's kernel at R=1 on the stacked (S, B, H, N, L, dh) sequences
        nseq = n_sequences(R, N)
        tokens, pairs, inputs = nseq * N * L, nseq * N * (N + 1) // 2, 4 * nseq * S // R
        fwd, fb = expected_memory("pyvf", 1, nseq * B, H, N, L, dh, threads)
    else:
        tokens, pairs = T, (attended_pairs(R, N) if method == "pyvf" else (R * N) ** 2)
        inputs = 7 * S + T * T if method == "dense_sdpa" else 4 * S  # SDPA: q, k, v, do, 3 leaves, the mask
        fwd, fb = expected_memory({"dense_sdpa": "sdpa", "dense_numpy": "numpy"}.get(method, method),
                                  R, B, H, N, L, dh, threads, backend)
    return dict(tokens=tokens, block_pairs=pairs, computed_flops_fwd=4 * L * L * dh * pairs * B * H,
                inputs_bytes=inputs, expected_fwd=fwd, expected_fwd_bwd=fb)


def mem_available():
    """/proc/meminfo MemAvailable in bytes (None where there is no /proc/meminfo)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def skip_reason(method, th, available):
    """Why a point must not run (a string), or None when its inputs, the expected memory of its
    largest pass and the worker's baseline fit in MEM_FRACTION of `available` bytes."""
    if available is None:
        return None
    base = BASELINE["torch" if method in TORCH_METHODS else "numpy"]
    peak = max(th["expected_fwd"], th["expected_fwd_bwd"])
    need = th["inputs_bytes"] + peak + base
    if need > MEM_FRACTION * available:
        return (f"needs ~{format_bytes(need)} (inputs {format_bytes(th['inputs_bytes'])} + expected peak "
                f"{format_bytes(peak)} + process {format_bytes(base)}) > {MEM_FRACTION:.0%} of the "
                f"{format_bytes(available)} available")
    return None


def fit_slope(Ns, values):
    """The least-squares slope of log(value) against log(N): the exponent p of value ~ c N^p.
    Points with a value of None or <= 0 are left out; None when fewer than two remain."""
    pts = [(n, v) for n, v in zip(Ns, values) if v is not None and v > 0]
    if len(pts) < 2:
        return None
    x, y = np.log(np.array(pts, dtype=np.float64)).T
    return float(np.polyfit(x, y, 1)[0])


# ---------------------------------------------------------------------------------------
# the worker: one point in a process of its own


def worker(spec):
    """Run one point: {method, H, dh, N, threads, repeat, validate} -> the dict printed as JSON.
    1. validate (spec["validate"]: the first N of a size) against the float64 dense reference;
    2. the extra peak memory of one call of each pass, after a warm-up call; 3. the median times."""
    method, H, dh, N = spec["method"], spec["H"], spec["dh"], spec["N"]
    pyvf.set_num_threads(spec["threads"])
    if method in TORCH_METHODS:
        import torch

        torch.set_num_threads(spec["threads"])
    q, k, v, do = make_inputs(R, B, H, N, L, dh, seed=N)  # (R, B, H, N, L, dh) each
    out = dict(method=method)
    c = contender(method, (q, k, v, do), out)
    if spec["validate"]:
        x64 = [x.astype(np.float64) for x in (q, k, v, do)]
        ref = (pyvf.branching_attention_reference(*x64[:3]), pyvf.branching_attention_reference_vjp(*x64))
        ok = validate_point(out, c, ref)
        del x64, ref  # freed before the memory is measured
        if not ok:
            return out
    passes = (("fwd", c["fwd"]), ("fwd_bwd", c["fb"]))
    for name, fn in passes:
        _, out[f"{name}_bytes"], _ = measured(fn, warmup=1)
    for name, fn in passes:
        out[f"{name}_seconds"], out[f"{name}_times"] = median_time(fn, spec["repeat"], warmup=0)
    return out


def contender(method, inputs, out):
    """One method's closures on the (R, B, H, N, L, dh) inputs: {fwd, fb (-> (o or None,
    gradients)), o_map, g_map (its output and gradients mapped back to (R, B, H, N, L, dh)), bound}.
    out gets the SDPA backend chosen."""
    q, k, v, do = inputs
    if method == "naive_pyvf":
        qs, ks, vs = (stack_naive(x) for x in (q, k, v))  # (S, B, H, N, L, dh)
        st = qs.shape
        fwd, fb = naive_pyvf_fns(qs, ks, vs, stack_naive(do, queries_only=True))
        return dict(fwd=fwd, fb=fb, bound=BOUND32, o_map=lambda o: unstack_naive(o.reshape(st), R),
                    g_map=lambda g: [unstack_naive(g[0].reshape(st), R)]
                    + [unstack_naive(x.reshape(st), R, keys=True) for x in g[1:]])
    to_np = np.asarray
    if method == "pyvf":
        fwd, fb = pyvf_fns(q, k, v, do)
    elif method == "dense_numpy":
        fwd, vjp = reference_fns(q, k, v, do)
        fb = lambda: (None, vjp())  # noqa: E731  (the reference's vjp returns the gradients only)
    else:  # dense_sdpa
        mask = pyvf.branching_mask(R, q.shape[3], L)  # (T, T) bool
        fwd, fb, to_np = torch_fns(q, k, v, do, mask)  # to_np: a flat tensor -> (R, B, H, N, L, dh)
        out["backend"] = torch_backend(q, mask)
    return dict(fwd=fwd, fb=fb, bound=BOUND32 if method == "pyvf" else BOUND_OTHERS, o_map=to_np,
                g_map=lambda g: [to_np(x) for x in g])


def validate_point(out, c, ref):
    """The first call of each pass against ref = (o, (dq, dk, dv)), the float64 dense reference:
    the errors and the bound go into out. False (out["error"] says so) when the worst error is
    above the bound."""
    err = {"o": error(c["o_map"](c["fwd"]()), ref[0])}
    o, grads = c["fb"]()
    err.update((n, error(g, w)) for n, g, w in zip(("dq", "dk", "dv"), c["g_map"](grads), ref[1]))
    if o is not None:
        err["o of fwd+bwd"] = error(c["o_map"](o), ref[0])
    out.update(errors=err, bound=c["bound"])
    worst = max(err.values())  # (error(): a NaN is inf)
    if not worst <= c["bound"]:
        out["error"] = f"validation failed: max rel. error {worst:.2e} > {c['bound']:g} against the float64 reference"
        return False
    return True


# ---------------------------------------------------------------------------------------
# the driver


def sdpa_backend():
    """The backend torch SDPA picks here for float32 with a bool mask (whether the logits are
    materialised, for the memory expected); None without torch."""
    try:
        import torch
        from torch.nn.attention import SDPBackend
    except ImportError:
        return None
    t = torch.zeros(1, 1, 2 * L, 32)
    m = torch.ones(2 * L, 2 * L, dtype=torch.bool)
    try:
        return SDPBackend(torch._fused_sdp_choice(t, t, t, attn_mask=m, scale=1.0)).name
    except Exception:  # noqa: BLE001 -- a private function: assume the worst (logits materialised)
        return "MATH"


def predicted_seconds(prev, th, repeat):
    """The run time of a point predicted from the previous N's point of the same method and size
    (time scaled by the computed FLOPs): (repeat + 3) calls of each pass. None without one."""
    if prev is None or "fwd_seconds" not in prev:
        return None
    per_call = prev["fwd_seconds"] + prev["fwd_bwd_seconds"]
    return (repeat + 3) * per_call * th["computed_flops_fwd"] / prev["theory"]["computed_flops_fwd"]


def run_points(sizes, views, methods, threads, repeat, mem_limit=None, max_point_seconds=None, log=print):
    """Every point, each in a worker process (or skipped, with the reason): a list of dicts."""
    backend = sdpa_backend()
    points = []
    for H, dh in sizes:
        prev = {}
        for idx, N in enumerate(views):
            for method in methods:
                th = theory(method, R, B, H, N, L, dh, threads, backend or "FLASH_ATTENTION")
                p = dict(method=method, H=H, dh=dh, N=N, T=R * N * L, theory=th)
                est = predicted_seconds(prev.get(method), th, repeat)
                if method in TORCH_METHODS and backend is None:
                    p["skipped"] = "torch is not installed"
                elif prev.get(method, {}).get("skipped"):
                    p["skipped"] = "a smaller N of this method was skipped"
                elif max_point_seconds and est is not None and est > max_point_seconds:
                    p["skipped"] = f"predicted {est:.0f} s > --max-point-seconds {max_point_seconds:g}"
                else:
                    reason = skip_reason(method, th, mem_limit if mem_limit is not None else mem_available())
                    if reason:
                        p["skipped"] = reason
                if "skipped" in p:
                    log(f"  H={H} dh={dh} N={N:>2} {method:<12} skipped: {p['skipped']}")
                else:
                    spec = dict(method=method, H=H, dh=dh, N=N, threads=threads, repeat=repeat, validate=idx == 0)
                    t0 = time.perf_counter()
                    try:
                        p.update(run_worker(WORKER, spec))
                    except (RuntimeError, ValueError) as e:  # a crashed worker: record it, carry on
                        p["error"] = str(e)[-2000:]
                    p["worker_seconds"] = time.perf_counter() - t0
                    what = p.get("error") or (f"fwd {format_bytes(p['fwd_bytes'])} {ms(p['fwd_seconds'])}, fwd+bwd "
                                              f"{format_bytes(p['fwd_bwd_bytes'])} {ms(p['fwd_bwd_seconds'])}")
                    log(f"  H={H} dh={dh} N={N:>2} {method:<12} {p['worker_seconds']:.1f} s: {what}", flush=True)
                prev[method] = p
                points.append(p)
    return points


def fits(points, sizes, methods):
    """{"HxDH": {method: {memory/time slope of each pass, and the local exponent between the last two N}}}."""
    out = {}
    for H, dh in sizes:
        per = {}
        for method in methods:
            pts = [p for p in points if p["method"] == method and (p["H"], p["dh"]) == (H, dh) and "fwd_seconds" in p]
            Ns = [p["N"] for p in pts]
            f = {}
            for key in ("fwd_bytes", "fwd_bwd_bytes", "fwd_seconds", "fwd_bwd_seconds"):
                vals = [p.get(key) for p in pts]
                f[key] = fit_slope(Ns, vals)
                f[key + "_last"] = fit_slope(Ns[-2:], vals[-2:])
            f["expected_fwd"] = fit_slope(Ns, [p["theory"]["expected_fwd"] for p in pts])
            f["expected_fwd_bwd"] = fit_slope(Ns, [p["theory"]["expected_fwd_bwd"] for p in pts])
            f["N"] = Ns
            per[method] = f
        out[f"{H}x{dh}"] = per
    return out


def _b(x):
    return "-" if x is None else format_bytes(x)


def _s(x):
    return "-" if x is None else f"{x:.2f}"


def tables(points, fit, sizes, methods):
    """The tables of every size and its fitted slopes, as text (markdown)."""
    out = []
    for H, dh in sizes:
        out.append(f"\n## H={H} dh={dh} (R={R} B={B} L={L}, float32)\n")
        rows = []
        for p in points:
            if (p["H"], p["dh"]) != (H, dh):
                continue
            th = p["theory"]
            if "skipped" in p:
                note = "skipped: " + p["skipped"]
            elif "error" in p:
                note = "FAILED: " + p["error"].splitlines()[0][:100]
            else:
                note = " ".join(x for x in (p.get("backend"), "validated" if "errors" in p else None) if x)
            rows.append([p["N"], p["method"], th["tokens"], th["block_pairs"], _b(th["expected_fwd"]),
                         _b(p.get("fwd_bytes")), _b(th["expected_fwd_bwd"]), _b(p.get("fwd_bwd_bytes")),
                         ms(p.get("fwd_seconds")), ms(p.get("fwd_bwd_seconds")), note])
        out.append(table(["N", "method", "tokens", "block pairs", "fwd expected", "fwd measured", "fwd+bwd expected",
                          "fwd+bwd measured", "fwd time", "fwd+bwd time", "note"], [[str(c) for c in r] for r in rows]))
        out.append(f"\nfitted slopes d log y / d log N over the measured N (last two N in brackets), H={H} dh={dh}\n")
        f = fit[f"{H}x{dh}"]
        rows = [[m, f"{_s(f[m]['fwd_bytes'])} ({_s(f[m]['fwd_bytes_last'])})",
                 f"{_s(f[m]['fwd_bwd_bytes'])} ({_s(f[m]['fwd_bwd_bytes_last'])})",
                 f"{_s(f[m]['expected_fwd'])} / {_s(f[m]['expected_fwd_bwd'])}",
                 f"{_s(f[m]['fwd_seconds'])} ({_s(f[m]['fwd_seconds_last'])})",
                 f"{_s(f[m]['fwd_bwd_seconds'])} ({_s(f[m]['fwd_bwd_seconds_last'])})",
                 ",".join(map(str, f[m]["N"]))] for m in methods]
        out.append(table(["method", "memory fwd", "memory fwd+bwd", "expected fwd / fwd+bwd", "time fwd",
                          "time fwd+bwd", "N measured"], rows))
    out.append("\nmemory: extra peak resident memory of one call (inputs excluded, outputs included); time: median; "
               "tokens: held per (batch entry, head), padding included; block pairs: (L, L) blocks computed per head")
    return "\n".join(out) + "\n"


def plot(points, fit, sizes, methods, folder):
    """memory_HxDH.png and time_HxDH.png in folder: log-log against N, a panel per pass, a line per
    method (one colour in both panels), the fitted slopes in the legend below the panels; the
    memory plots draw MEMORY_NOISE_BYTES, below which a reading is approximate. Returns the files
    written, or None without matplotlib."""
    plt = pyplot()
    if plt is None:
        return None
    import matplotlib.ticker
    os.makedirs(folder, exist_ok=True)
    files = []
    views = sorted({p["N"] for p in points})
    for H, dh in sizes:
        f = fit[f"{H}x{dh}"]
        for what, keys, unit, scale in (("memory", ("fwd_bytes", "fwd_bwd_bytes"), "MiB", 2 ** 20),
                                        ("time", ("fwd_seconds", "fwd_bwd_seconds"), "ms", 1e-3)):
            fig, axes = plt.subplots(1, 2, figsize=(12, 5.4), sharey=True, layout="constrained")
            lowest = float("inf")
            for ax, key, title in zip(axes, keys, ("forward", "forward+backward")):
                for i, method in enumerate(methods):
                    pts = [p for p in points if p["method"] == method and (p["H"], p["dh"]) == (H, dh)
                           and p.get(key)]
                    slopes = ", ".join(f"{t} {_s(f[method][k])}" for t, k in zip(("fwd", "fwd+bwd"), keys)
                                       if f[method][k] is not None)
                    if pts:
                        ax.loglog([p["N"] for p in pts], [p[key] / scale for p in pts], "o-", color=f"C{i}",
                                  label=f"{METHODS[method]} (slope {slopes})")
                        lowest = min(lowest, min(p[key] for p in pts))
                ax.set_xticks(views, [str(n) for n in views])
                ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
                ax.set_title(f"{what}, {title}: H={H} dh={dh} R={R} L={L}", fontsize=10)
                ax.set_xlabel("N (views)")
                ax.grid(True, which="both", alpha=0.3)
                if what == "memory" and lowest < 4 * MEMORY_NOISE_BYTES:
                    ax.axhline(MEMORY_NOISE_BYTES / scale, color="0.4", ls=":", lw=1.0,
                               label=f"{format_bytes(MEMORY_NOISE_BYTES)}: below it a reading is approximate")
            axes[0].set_ylabel(f"extra peak memory ({unit})" if what == "memory" else f"median time ({unit})")
            legend_outside(fig, "lower center", ncol=2)
            path = os.path.join(folder, f"{what}_H{H}_dh{dh}.png")
            save_figure(fig, path)
            files.append(path)
    return files


def run(sizes=SIZES, views=VIEWS, methods=tuple(METHODS), threads=2, repeat=5, mem_limit_mib=None,
        max_point_seconds=MAX_POINT_SECONDS, plots=None, log=print):
    """The whole study (module docstring): every point in a worker process, the fitted slopes, the
    tables logged, the plots written to the folder `plots` (None: none). Returns the report, every
    number; a point whose validation failed has an "error" starting "validation failed"."""
    t_start = time.perf_counter()
    mem_limit = None if mem_limit_mib is None else int(mem_limit_mib * 2 ** 20)
    available = mem_available()
    log(f"# Attention memory and time against the number of views N: R={R} B={B} L={L}, float32, scale 1, "
        f"{threads} threads")
    log(f"machine: {cpu_name()}, {os.cpu_count()} CPUs; memory available "
        f"{_b(available)}{'' if mem_limit is None else f' (planning against --mem-limit-mib: {_b(mem_limit)})'}")
    log(f"memory: {memory_method()}")
    log("each point in its own process; validated against the float64 dense reference at the first N\n")
    points = run_points(sizes, views, methods, threads, repeat, mem_limit, max_point_seconds or None, log=log)
    fit = fits(points, sizes, methods)
    log(tables(points, fit, sizes, methods).rstrip("\n"))
    report = dict(
        config=dict(R=R, B=B, L=L, views=list(views), sizes=[list(s) for s in sizes], dtype="float32",
                    scale=1.0, threads=threads, repeat=repeat, methods=list(methods),
                    not_run={m: "not in --methods" for m in METHODS if m not in methods},
                    mem_fraction=MEM_FRACTION, mem_limit_bytes=mem_limit, max_point_seconds=max_point_seconds,
                    inputs="unit normal, seed N"),
        machine=dict(machine(threads), mem_available_bytes=available),
        memory_method=memory_method(), methods=METHODS, points=points, slopes=fit)
    write_outputs(report, plots_dir=plots, make_plots=lambda d: plot(points, fit, sizes, methods, d), log=log)
    errors = [p for p in points if "error" in p]
    if errors:
        log(f"\n{len(errors)} point(s) failed: " + "; ".join(f"{p['method']} N={p['N']}: "
                                                          f"{p['error'].splitlines()[0][:200]}" for p in errors))
    report["total_seconds"] = time.perf_counter() - t_start
    log(f"\ntotal {report['total_seconds']:.0f} s")
    return report


def validation_failed(report):
    """True when a point's validation failed (a crashed or skipped point is only written down)."""
    return any(p.get("error", "").startswith("validation failed") for p in report["points"])


if __name__ == "__main__":  # a worker: `python -m pyvf.bench.scaling SPEC` (run_points, run_worker)
    worker_main(worker)
