"""What every benchmark shares: the one timer and the one validator, memory measured, the
machine's name, worker processes, tables, JSON and plots. NumPy and the standard library only
(matplotlib where a plot is asked for, torch where a benchmark compares with it).

    seconds, times = median_time(fn, repeat=5, warmup=1)   # the one timer (pyvf/_machine.py)
    errs, ok = validate(outs, refs, names, bound)        # the one validator: normwise errors vs float64
    result, extra = peak_memory(fn)   # bytes of resident memory fn() needed above what was resident before
    print(table(header, rows)); write_json(path, report)
    compare_steps(module, ...)        # pyvf's and torch's training steps, each in a worker, checked, timed

peak_memory measures the process's resident memory (Linux VmHWM), so it covers every
allocation the call makes: NumPy arrays, C++ workspace, torch tensors. It counts the call's
outputs (alive when fn returns), and nothing allocated before the call: allocate the inputs
first, then measure.
"""

import gc
import json
import os
import sys
import tracemalloc
import zlib

import numpy as np

from .._io import atomic_write_text
from .._machine import cpu_name, median_time  # noqa: F401  (re-exported: the benchmarks import them from here)
from .._memory import map_fresh_pages
from .._threads import set_num_threads

# numpy's BLAS takes its thread count from these variables once, when numpy loads; `pyvf bench`
# sets them to the benchmark's --threads (pyvf/cli/bench.py), so that numpy's GEMM and pyvf's
# layers use the threads that pyvf's kernels and torch are given
BLAS_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")
TORCH_MISSING = "torch is not installed (the torch extra: pip install 'pyvf[torch]')"


def torch_or_none():
    """torch, or None where it is not installed (its column then says TORCH_MISSING)."""
    try:
        import torch
    except ImportError:
        return None
    return torch


def machine(threads):
    """The machine a report ran on: CPU, versions, pyvf's kernel path, the threads."""
    import platform

    import pyvf
    torch = torch_or_none()
    return dict(platform=platform.platform(), processor=cpu_name(), cpu_count=os.cpu_count(),
                python=platform.python_version(), numpy=np.__version__, torch=torch and torch.__version__,
                pyvf=pyvf.__version__, kernel_path=pyvf.kernel_path(), kernel_paths=pyvf.kernel_paths(),
                threads=threads, blas_thread_env={v: os.environ.get(v) for v in BLAS_THREAD_VARS})


# ---------------------------------------------------------------------------------------
# the validator


def validate(outs, refs, names, bound):
    """Each output against its float64 reference: ({name: max|x - ref| / max|ref|}, worst <= bound).
    An output holding a NaN or an inf, of another shape, or missing is an error of inf: a NaN
    compares False with every bound, so it would otherwise pass unseen."""
    outs = list(outs)
    errs = {}
    for i, (name, ref) in enumerate(zip(names, refs)):
        x = np.asarray(outs[i], dtype=np.float64) if len(outs) == len(names) else None
        if x is None or x.shape != ref.shape or not np.isfinite(x).all():
            errs[name] = float("inf")
        else:
            errs[name] = float(np.abs(x - ref).max(initial=0) / (np.abs(ref).max(initial=0) or 1.0))
    return errs, max(errs.values()) <= bound


# ---------------------------------------------------------------------------------------
# memory


def _status_bytes(field):
    """A memory field of /proc/self/status ("VmRSS", "VmHWM"), in bytes."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    raise OSError(field)


def _reset_hwm():
    """Reset the kernel's peak-resident counter VmHWM to the current VmRSS (Linux >= 4.0)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


try:
    _reset_hwm()
    _HWM = _status_bytes("VmHWM") > 0
except OSError:
    _HWM = False


def memory_method():
    """One line saying how peak_memory measures on this machine."""
    if _HWM:
        return "resident memory (Linux VmHWM): every allocation counts, NumPy, C++ workspace and torch; outputs included"
    return "tracemalloc (no /proc/self/clear_refs here): NumPy allocations only, C++ and torch NOT counted"


def peak_memory(fn):
    """Run fn() once: (result, the peak resident memory while it ran minus the resident memory just
    before). Page granularity; the kernel's per-CPU counters lag by a few dozen pages, so below
    ~1 MiB it is approximate. Call fn once before to keep one-time costs (thread pools) out.
    Frees go back to the system from here on (pyvf._memory.map_fresh_pages), so that a call cannot
    reuse what an earlier one freed and look as if it needed nothing."""
    gc.collect()
    map_fresh_pages()
    if _HWM:
        before = _status_bytes("VmRSS")
        _reset_hwm()
        result = fn()
        return result, max(_status_bytes("VmHWM") - before, 0)
    tracemalloc.start()
    try:
        result = fn()
        return result, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def format_bytes(n):
    """1536 -> '1.5 KiB'; powers of 1024, three significant figures; None -> '-'."""
    if n is None:
        return "-"
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(n) < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.3g} {unit}"
        n /= 1024


def ms(seconds):
    return "-" if seconds is None else f"{seconds * 1e3:.3g} ms"


# ---------------------------------------------------------------------------------------
# worker processes


def run_worker(module, spec):
    """Run `python -m module SPEC` (SPEC the JSON of the dict spec) in a fresh process and return
    the JSON object printed on its last line (worker_main): each framework's thread pool, or each
    point's memory, in a process of its own. It starts in the folder that holds this pyvf package,
    so that it imports the same pyvf, not a source tree in the working folder."""
    import subprocess

    import pyvf
    cmd = [sys.executable, "-m", module, json.dumps(spec)]
    proc = subprocess.run(cmd, capture_output=True, text=True, stdin=subprocess.DEVNULL,
                          cwd=os.path.dirname(os.path.dirname(os.path.abspath(pyvf.__file__))))
    if proc.returncode:
        raise RuntimeError(f"worker {' '.join(cmd[1:])} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def worker_main(work):
    """A benchmark module's `if __name__ == "__main__":`: print json.dumps(work(spec))."""
    print(json.dumps(work(json.loads(sys.argv[1]))))


# ---------------------------------------------------------------------------------------
# training steps, pyvf against torch (transformer.py, codebook.py)

# pyvf's and torch's first step, compared before any time is printed: the loss and the loss after
# the first update to LOSS_RTOL (float32 both, the same weights and batch); each gradient's
# checksums to CHECK_RTOL of its norm (measured: 3e-5 at most, the paper codebook). A gradient
# below CHECK_FLOOR of the largest one's norm is compared at that level: the biases that feed a
# normalisation have a gradient of exactly 0, computed as rounding noise.
LOSS_RTOL, CHECK_RTOL, CHECK_FLOOR = 1e-4, 1e-3, 1e-3


def checksums(arrays):
    """{name: [2-norm, projection]} of each array, the projection its dot product with unit-normal
    numbers seeded by its name (the same in every process): what a worker sends of a gradient. An
    array zeroed, transposed or missing a term moves the projection by about its norm."""
    out = {}
    for name, a in arrays.items():
        a = np.asarray(a, dtype=np.float64).ravel()
        r = np.random.default_rng(zlib.crc32(name.encode())).standard_normal(a.size)
        out[name] = [float(np.sqrt(a @ a)), float(a @ r)]
    return out


def first_step_differs(p, t):
    """How pyvf's first step differs from torch's, or None. p, t: {loss, gradients (checksums),
    loss_after_update}. NaN differs from everything."""
    if not abs(p["loss"] - t["loss"]) <= LOSS_RTOL * abs(t["loss"]):
        return f"the loss: pyvf {p['loss']}, torch {t['loss']}"
    pg, tg = p["gradients"], t["gradients"]
    if set(pg) != set(tg):
        return f"the gradients named: pyvf only {sorted(set(pg) - set(tg))}, torch only {sorted(set(tg) - set(pg))}"
    floor = CHECK_FLOOR * max(norm for norm, _ in tg.values())
    wrong = [n for n in tg if not all(abs(a - b) <= CHECK_RTOL * max(tg[n][0], floor) for a, b in zip(pg[n], tg[n]))]
    if wrong:
        return f"the gradients of {', '.join(wrong[:3])}: (norm, projection) pyvf {pg[wrong[0]]}, torch {tg[wrong[0]]}"
    if not abs(p["loss_after_update"] - t["loss_after_update"]) <= LOSS_RTOL * abs(t["loss_after_update"]):
        return f"the loss after update: pyvf {p['loss_after_update']}, torch {t['loss_after_update']}"
    return None


def step_figures(step, steps):
    """A training step's figures (step() -> the loss before its update): a warm-up call (it makes
    the optimizer's moments, resident from then on as the weights are), the next one under
    peak_memory (its loss, after one update, checks the optimizer), then the median of `steps`."""
    step()
    after, memory = peak_memory(step)
    return dict(loss_after_update=after, memory=memory, time=median_time(step, steps, warmup=0)[0])


def step_worker(worker_pyvf, worker_torch):
    """A worker of {framework, config, steps, threads}: one framework's step_figures."""
    def worker(spec):
        set_num_threads(spec["threads"])
        return (worker_pyvf if spec["framework"] == "pyvf" else worker_torch)(spec["config"], spec["steps"])
    return worker


def compare_steps(module, configs, steps, threads, describe):
    """pyvf's and torch's training step on each configuration named, each framework in a worker
    process (`python -m module SPEC`); their first steps compared (first_step_differs) before any
    time is printed. -> {config, results {name: {"pyvf", "torch"}}, failures}: a configuration
    whose steps differ is a failure, and nothing after it runs."""
    report = dict(config=dict(configs=list(configs), threads=threads), results={}, failures=[])
    for name in configs:
        p, t = (run_worker(module, dict(framework=f, config=name, steps=steps(name), threads=threads))
                for f in ("pyvf", "torch"))
        differs = first_step_differs(p, t)
        if differs:
            print(f"{name}: pyvf and torch differ in {differs}", file=sys.stderr)
            report["failures"].append(f"{name}: the first steps of pyvf and torch differ")
            break
        print(f"\n## {name}: {describe(name)}, float32, {threads} threads, median of {steps(name)} steps, each "
              "framework in its own process")
        print(f"first-step loss: pyvf {p['loss']:.6f}, torch {t['loss']:.6f} (and the gradients, and the loss after "
              "an update, agree)\n")
        print(table(["", "step time", "peak memory of a step"],
                    [["pyvf", ms(p["time"]), format_bytes(p["memory"])],
                     ["torch", ms(t["time"]), format_bytes(t["memory"])],
                     ["torch / pyvf", f"{t['time'] / p['time']:.2f}", f"{t['memory'] / p['memory']:.2f}"]]))
        report["results"][name] = {"pyvf": p, "torch": t}
    return report


# ---------------------------------------------------------------------------------------
# tables, files, plots


def table(header, rows):
    """A markdown table of str()-able cells, each column as wide as its widest cell."""
    widths = [max(len(str(c)) for c in col) for col in zip(header, *rows)]
    line = lambda cells: "| " + " | ".join(str(c).ljust(w) for c, w in zip(cells, widths)) + " |"  # noqa: E731
    return "\n".join([line(header), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + [line(r) for r in rows])


def write_json(path, report):
    """A benchmark's report as JSON, written whole or not at all."""
    atomic_write_text(path, json.dumps(report, indent=1))


def pyplot():
    """matplotlib.pyplot on the file-only Agg backend, or None where matplotlib (the `plots`
    extra, `pip install pyvf[plots]`) is not installed."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def save_figure(fig, path, where="right upper", ncol=1):
    """One legend for every axes of fig, outside them (fig made with layout="constrained"), then
    fig written to path and closed."""
    seen = {}
    for ax in fig.axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(label, handle)
    fig.legend(list(seen.values()), list(seen), loc=f"outside {where}", fontsize=7, ncol=ncol)
    fig.savefig(path, dpi=100)
    pyplot().close(fig)
