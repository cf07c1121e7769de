"""What every benchmark shares: the time and memory of a call, measured; the BLAS threads; the
machine's name; a worker process; a table, a JSON file and the plots. NumPy and the standard
library only (matplotlib where a plot is asked for).

    seconds, times = median_time(fn, repeat=5, warmup=1)   # the one timing helper (pyvf/_machine.py)
    result, extra = peak_memory(fn)   # bytes of resident memory fn() needed above what was resident before
    result, extra, times = measured(fn, warmup=1, repeat=1)  # one call under peak_memory, timed, then more
    memory_method()                   # how peak_memory measures, for printing beside its numbers
    print(table(header, rows))        # a markdown table
    write_json(path, report)          # a benchmark's report, as every benchmark writes it
    legend_outside(fig); log_ticks(ax.xaxis); save_figure(fig, path)  # the plots' shared settings
    first_step_differs(p, t)          # pyvf's and torch's first step (loss, checksums) compared
    compare_steps(module, ...)        # pyvf's and torch's training steps, each in a worker, checked, timed

peak_memory measures the process's resident memory (Linux VmHWM), so it covers every
allocation the call makes: NumPy arrays, C++ std::vector workspace, torch tensors. It counts
the call's outputs too (they are still alive when fn returns), and nothing allocated before
the call: allocate the inputs first, then measure.
"""

import gc
import json
import os
import time
import tracemalloc
import zlib

import numpy as np

from .._threads import set_num_threads
from .._machine import cpu_name, median_time  # (re-exported: every benchmark imports them from here)
from .._io import atomic_write_text
from .._memory import map_fresh_pages


# numpy's BLAS takes its thread count from these variables once, when numpy loads; `pyvf bench`
# sets them to the benchmark's --threads (pyvf/cli/bench.py), so that numpy's GEMM and pyvf's
# layers use the threads that pyvf's kernels and torch are given
BLAS_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def machine(threads):
    """The machine a report ran on, for its JSON and the documents: the CPU, the versions (torch
    None where it is not installed), pyvf's kernel path and the ones this CPU runs, the threads
    asked for and pyvf's in effect, and BLAS_THREAD_VARS as numpy's BLAS pool was started with."""
    import platform

    import pyvf
    torch = torch_or_none()
    return dict(platform=platform.platform(), processor=cpu_name(), cpu_count=os.cpu_count(),
                python=platform.python_version(), numpy=np.__version__, torch=torch and torch.__version__,
                pyvf=pyvf.__version__, kernel_path=pyvf.kernel_path(), kernel_paths=pyvf.kernel_paths(),
                threads=threads, pyvf_threads=pyvf.num_threads(),
                blas_thread_env={v: os.environ.get(v) for v in BLAS_THREAD_VARS})


_STATUS = "/proc/self/status"
_CLEAR_REFS = "/proc/self/clear_refs"


# ---------------------------------------------------------------------------------------
# peak memory


def _status_bytes(field):
    """A memory field of /proc/self/status ("VmRSS", "VmHWM"), in bytes."""
    with open(_STATUS) as f:
        for line in f:
            if line.startswith(field + ":"):
                value, unit = line.split()[1:3]
                assert unit == "kB", line
                return int(value) * 1024
    raise OSError(f"{field} not in {_STATUS}")


def _reset_hwm():
    """Reset the kernel's peak-resident counter VmHWM to the current VmRSS (Linux >= 4.0)."""
    with open(_CLEAR_REFS, "w") as f:
        f.write("5")


def _hwm_available():
    try:
        _reset_hwm()
        return _status_bytes("VmHWM") > 0 and _status_bytes("VmRSS") > 0
    except OSError:
        return False


_HWM = _hwm_available()
# below this, a peak_memory reading is approximate: the kernel's per-CPU RSS counters lag by up to
# a few dozen pages per CPU (peak_memory's docstring); the memory plots draw it
MEMORY_NOISE_BYTES = 2 ** 20


def memory_method():
    """One line saying how peak_memory measures on this machine."""
    if _HWM:
        return ("resident memory, Linux VmHWM reset through /proc/self/clear_refs: every "
                "allocation counts (NumPy, C++ workspace, torch); outputs included; blocks >= 128 KiB "
                "mapped fresh on every call (glibc mmap threshold fixed)")
    return ("tracemalloc (no /proc/self/clear_refs here): NumPy and Python allocations only, "
            "C++ workspace and torch are NOT counted; outputs included")


def peak_memory(fn):
    """Run fn() once; return (result, extra_peak_bytes).

    extra_peak_bytes is the peak resident memory of the process while fn ran minus the resident
    memory just before it: the memory the call needed, its outputs included (they are alive when
    fn returns). Inputs allocated before the call do not count. On Linux this reads VmHWM after
    resetting it (every allocation counts, at page granularity, 4 KiB; the kernel's per-CPU
    RSS counters lag by up to a few dozen pages per CPU, so below ~1 MiB it is approximate); elsewhere it falls
    back to tracemalloc, which sees NumPy's allocations only (memory_method() says which).
    Call fn once before measuring to keep one-time costs (thread pools, lazy imports) out.
    On glibc the first call changes malloc's policy for the rest of the process: see
    pyvf._memory.map_fresh_pages.
    """
    gc.collect()
    map_fresh_pages()
    if _HWM:
        before = _status_bytes("VmRSS")
        _reset_hwm()
        result = fn()
        peak = _status_bytes("VmHWM")
        return result, max(peak - before, 0)
    started = not tracemalloc.is_tracing()
    if started:
        tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        before = tracemalloc.get_traced_memory()[0]
        result = fn()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        if started:
            tracemalloc.stop()
    return result, max(peak - before, 0)


def measured(fn, warmup=0, repeat=1):
    """`warmup` plain calls of fn, then `repeat` timed calls, the first under peak_memory: (the
    measured call's result, its extra peak bytes, the seconds of every timed call)."""
    for _ in range(warmup):
        fn()
    box = {}

    def call():
        t0 = time.perf_counter()
        out = fn()
        box["seconds"] = time.perf_counter() - t0
        return out

    result, extra = peak_memory(call)
    times = [box["seconds"]]
    if repeat > 1:
        times += median_time(fn, repeat - 1, warmup=0)[1]
    return result, extra, times


# ---------------------------------------------------------------------------------------
# printing and writing


def format_bytes(n):
    """1536 -> '1.5 KiB'; powers of 1024, three significant figures."""
    n = float(n)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(n) < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.3g} {unit}"
        n /= 1024
    raise AssertionError("unreachable")


def run_worker(module, spec):
    """Run `python -m module SPEC` in a fresh process, SPEC the JSON of the dict spec, and return
    the JSON object printed on its last line (the module's worker_main): for benchmarks that keep
    each framework's thread pools in a process of its own, or each point's memory apart. The
    process starts in the folder that holds
    this process's pyvf package, so that it imports the same pyvf (`python -m` puts the working
    folder first on sys.path: started from a source checkout, it would import the unbuilt source
    tree). Its standard input is empty."""
    import subprocess
    import sys

    import pyvf
    cmd = [sys.executable, "-m", module, json.dumps(spec)]
    proc = subprocess.run(cmd, capture_output=True, text=True,
                          cwd=os.path.dirname(os.path.dirname(os.path.abspath(pyvf.__file__))),
                          stdin=subprocess.DEVNULL)
    if proc.returncode:
        raise RuntimeError(f"worker {' '.join(cmd[1:])} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def step_worker(worker_pyvf, worker_torch):
    """The transformer's and the codebook's worker: {framework: "pyvf" | "torch", config, steps,
    threads} -> worker_pyvf(config, steps) or worker_torch(config, steps), on `threads` threads."""
    def worker(spec):
        set_num_threads(spec["threads"])
        return (worker_pyvf if spec["framework"] == "pyvf" else worker_torch)(spec["config"], spec["steps"])
    return worker


def worker_main(work):
    """A benchmark module's `if __name__ == "__main__":` (run_worker's other end): print
    json.dumps(work(spec)), spec the JSON object of the command line's one argument."""
    import sys

    print(json.dumps(work(json.loads(sys.argv[1]))))


# pyvf's and torch's first step, compared before any time is printed (first_step_differs): the
# loss (and, where an optimizer is timed, the loss after its first update) to LOSS_RTOL (float32
# both, the same weights and batch); each output's and gradient's checksums to CHECK_RTOL of its
# norm (measured: 3e-5 at most, the paper codebook; 4e-6, the paper transformer). A gradient below
# CHECK_FLOOR of the largest one's norm is compared at that level: the biases that feed a
# normalisation have a gradient of exactly 0, computed as rounding noise.
LOSS_RTOL, CHECK_RTOL, CHECK_FLOOR = 1e-4, 1e-3, 1e-3


def checksums(arrays):
    """{name: [2-norm, projection]} of each array (name -> gradient or output), in float64: the
    projection is its dot product with unit-normal numbers seeded by its name, the same in every
    process. What a worker sends of arrays too large to send: an array zeroed, transposed or
    missing a term moves the projection by about its norm."""
    out = {}
    for name, a in arrays.items():
        a = np.asarray(a, dtype=np.float64).ravel()
        r = np.random.default_rng(zlib.crc32(name.encode())).standard_normal(a.size)
        out[name] = [float(np.sqrt(a @ a)), float(a @ r)]
    return out


def _checksums_differ(pc, tc):
    """What differs between two checksums() dicts of one kind (outputs, gradients), or None."""
    if set(pc) != set(tc):
        return f"the arrays compared: pyvf only {sorted(set(pc) - set(tc))}, torch only {sorted(set(tc) - set(pc))}"
    floor = CHECK_FLOOR * max((norm for norm, _ in tc.values()), default=0.0)
    wrong = [name for name in tc if not all(abs(a - b) <= CHECK_RTOL * max(tc[name][0], floor)
                                            for a, b in zip(pc[name], tc[name]))]
    if wrong:
        return (f"{len(wrong)} array(s): {', '.join(wrong[:3])}{', ...' if len(wrong) > 3 else ''}; "
                f"{wrong[0]} (norm, projection): pyvf {pc[wrong[0]]}, torch {tc[wrong[0]]}")
    return None


def first_step_differs(p, t):
    """How pyvf's first step differs from torch's, or None. p, t: {loss, gradients (checksums of
    the first step's), and where they are timed outputs (checksums) and loss_after_update}. In
    order (the first step's differences first: they name what differs): the loss beyond LOSS_RTOL,
    an output's or a gradient's checksums beyond CHECK_RTOL of its norm, an array on one side
    only, the loss after the update. NaN differs from everything."""
    def loss_differs(key):
        if (key in p or key in t) and not abs(p[key] - t[key]) <= LOSS_RTOL * abs(t[key]):
            return f"the {key.replace('_', ' ')}: pyvf {p[key]}, torch {t[key]}"
        return None

    return (loss_differs("loss")
            or next((f"the {kind}: {why}" for kind in ("outputs", "gradients") if kind in p or kind in t
                     for why in [_checksums_differ(p.get(kind, {}), t.get(kind, {}))] if why), None)
            or loss_differs("loss_after_update"))


def step_figures(step, steps):
    """A training step's figures (step() -> the loss before its update): a first call, the warm-up
    (its update makes the optimizer's moments, resident from then on as the weights are: no step's
    memory), the next one under peak_memory (its loss, after one update, checks the optimizer),
    then the median of `steps` more. -> {loss_after_update, memory (bytes), time (seconds)}."""
    step()
    after, memory = peak_memory(step)
    return dict(loss_after_update=after, memory=memory, time=median_time(step, steps, warmup=0)[0])


def compare_steps(module, configs, steps, threads, describe):
    """pyvf's and torch's training step on each configuration named, each framework in a worker
    process (`python -m module SPEC`, SPEC {framework, config, steps (steps(name)), threads}, the
    worker returning {loss, gradients (checksums), step_figures' fields}): their first steps are
    compared (first_step_differs) before any time is printed; describe(name): the configuration in
    words. -> {config, results {name: {"pyvf", "torch"}}, failures}: a configuration whose steps
    differ is a failure, and nothing after it runs."""
    import sys

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
                    [["pyvf", f"{p['time'] * 1e3:.1f} ms", format_bytes(p["memory"])],
                     ["torch", f"{t['time'] * 1e3:.1f} ms", format_bytes(t["memory"])],
                     ["torch / pyvf", f"{t['time'] / p['time']:.2f}", f"{t['memory'] / p['memory']:.2f}"]]))
        report["results"][name] = {"pyvf": p, "torch": t}
    return report


def table(header, rows):
    """A markdown table of str()-able cells, each column as wide as its widest cell."""
    widths = [max(len(str(c)) for c in col) for col in zip(header, *rows)]
    line = lambda cells: "| " + " | ".join(str(c).ljust(w) for c, w in zip(cells, widths)) + " |"  # noqa: E731
    out = [line(header), "|" + "|".join("-" * (w + 2) for w in widths) + "|"]
    return "\n".join(out + [line(r) for r in rows])


def write_json(path, report):
    """A benchmark's report as JSON (every benchmark's, and the ones `pyvf bench report` keeps),
    written whole or not at all (a run killed while writing leaves the last complete file)."""
    atomic_write_text(path, json.dumps(report, indent=1))


TORCH_MISSING = "torch is not installed (the torch extra: pip install 'pyvf[torch]')"


def torch_or_none():
    """torch, or None where it is not installed: benchmarks where torch is a comparison column
    measure pyvf without it (the column says TORCH_MISSING)."""
    try:
        import torch
    except ImportError:
        return None
    return torch


def pyplot():
    """matplotlib.pyplot on the file-only Agg backend, or None where matplotlib (the `plots`
    extra, `pip install pyvf[plots]`) is not installed: the plotting functions' one import."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def legend_outside(fig, where="right upper", ncol=1):
    """One legend for every axes of fig (each label once, in drawing order), outside the axes so
    that it covers no data. fig must be made with layout="constrained", which makes room for it.
    where: matplotlib's "outside" locations ("right upper", "lower center", ...)."""
    seen = {}
    for ax in fig.axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(label, handle)
    return fig.legend(list(seen.values()), list(seen), loc=f"outside {where}", fontsize=7, ncol=ncol)


def log_ticks(axis, most=6):
    """Label a log axis (ax.xaxis, after plotting) in plain numbers (0.3, 2, 40) at 1-2-5 steps
    (1..9 on an axis too short for three of those), or at powers of ten (every k-th) where they
    would be more than `most`; no minor labels.
    matplotlib's default labels every minor tick of an axis spanning under a decade (3x10^-1,
    4x10^-1, ...), and the labels run into each other."""
    import math

    from matplotlib import ticker

    lo, hi = sorted(axis.get_view_interval())
    decades = range(math.floor(math.log10(lo)), math.ceil(math.log10(hi)) + 1)

    def at(steps):  # the ticks m 10^k in [lo, hi], m in steps
        return [m * 10.0 ** k for k in decades for m in steps if lo <= m * 10.0 ** k <= hi]

    ticks = at((1, 2, 5))
    if len(ticks) < 3:  # under a decade
        ticks = at(range(1, 10))
    elif len(ticks) > most:  # over two decades: powers of ten
        ticks = at((1,))
    ticks = ticks[::max(1, math.ceil(len(ticks) / most))]
    axis.set_major_locator(ticker.FixedLocator(ticks))
    axis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))
    axis.set_minor_formatter(ticker.NullFormatter())


def save_figure(fig, path, dpi=110):
    """Write fig to path and close it: every benchmark plot is saved here (the tests wrap this to
    check each figure's tick labels and legend before it is written)."""
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)


def write_outputs(report, json_path=None, plots_dir=None, make_plots=None, log=print):
    """The files a benchmark was asked for: the plots (make_plots(dir) -> the files, or None
    without matplotlib; kept in report["plots"]), then the JSON of the report."""
    if plots_dir:
        files = make_plots(plots_dir)
        log("\nplots need matplotlib: pip install pyvf[plots]" if files is None else "\nwrote " + ", ".join(files))
        report["plots"] = files
    if json_path:
        write_json(json_path, report)
        log(f"wrote {json_path}")
