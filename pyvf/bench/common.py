"""What the benchmarks share: the validator, the memory measurement, the machine, worker processes,
tables, JSON and plots; the timer is pyvf/_machine.py's median_time (re-exported)."""

import gc
import json
import os
import sys

import numpy as np

from .._io import atomic_write_text
from .._machine import cpu_name, median_time  # noqa: F401  (re-exported: the benchmarks import them from here)
from .._memory import map_fresh_pages

TORCH_MISSING = "torch is not installed (the torch extra: pip install 'pyvf[torch]')"
MEMORY_METHOD = "resident memory (Linux VmHWM): every allocation counts, NumPy, C++ workspace and torch; outputs included"


def torch_or_none():
    """torch, or None where it is not installed."""
    try:
        import torch
    except ImportError:
        return None
    return torch


def machine(threads):
    """Sets pyvf's threads (numpy's BLAS too) and torch's: the machine a report runs on, as a dict."""
    import platform

    import pyvf
    torch = torch_or_none()
    pyvf.set_num_threads(threads)
    if torch is not None:
        torch.set_num_threads(threads)
    return dict(platform=platform.platform(), processor=cpu_name(), cpu_count=os.cpu_count(),
                python=platform.python_version(), numpy=np.__version__, torch=torch and torch.__version__,
                pyvf=pyvf.__version__, kernel_path=pyvf.kernel_path(), kernel_paths=pyvf.kernel_paths(), threads=threads)


def validate(outs, refs, names, bound):
    """Each output against its float64 reference: ({name: max|x - ref| / max|ref|}, worst <= bound).
    An output holding a NaN or an inf, of another shape, or missing is an error of inf."""
    errs = {}
    for name, ref, x in zip(names, refs, list(outs) + [None] * len(names)):
        x = None if x is None else np.asarray(x, dtype=np.float64)
        ok = x is not None and x.shape == ref.shape and np.isfinite(x).all()
        errs[name] = float(np.abs(x - ref).max(initial=0) / (np.abs(ref).max(initial=0) or 1.0)) if ok else float("inf")
    return errs, max(errs.values()) <= bound


def _status_bytes(field):
    """A memory field of /proc/self/status ("VmRSS", "VmHWM"), in bytes."""
    with open("/proc/self/status") as f:
        return int(next(line for line in f if line.startswith(field + ":")).split()[1]) * 1024


def peak_memory(fn):
    """Run fn() once: (result, peak resident memory while it ran minus the resident memory just
    before), Linux only, page granularity. Make the inputs and call fn once before (thread pools).
    Frees go back to the system from here on (map_fresh_pages): a call cannot reuse what an
    earlier one freed and look as if it needed nothing."""
    gc.collect()
    map_fresh_pages()
    before = _status_bytes("VmRSS")
    with open("/proc/self/clear_refs", "w") as f:  # VmHWM reset to VmRSS (Linux >= 4.0)
        f.write("5")
    result = fn()
    return result, max(_status_bytes("VmHWM") - before, 0)


def format_bytes(n):
    """1536 -> '1.5 KiB'; powers of 1024, three significant figures."""
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(n) < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.3g} {unit}"
        n /= 1024


def ms(seconds):
    """0.0123 -> '12.3 ms'; None -> '-'."""
    return "-" if seconds is None else f"{seconds * 1e3:.3g} ms" if seconds < 1 else f"{seconds * 1e3:.0f} ms"


def run_worker(work, spec):
    """work(spec) in a fresh process, `python -m work's module JSON(spec)` (worker_main): its JSON
    answer. It starts in the folder above this pyvf package, so that it imports this pyvf."""
    import subprocess

    import pyvf
    cmd = [sys.executable, "-m", work.__module__, json.dumps(spec)]
    proc = subprocess.run(cmd, capture_output=True, text=True, stdin=subprocess.DEVNULL,
                          cwd=os.path.dirname(os.path.dirname(os.path.abspath(pyvf.__file__))))
    if proc.returncode:
        raise RuntimeError(f"worker {' '.join(cmd[1:])} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def worker_main(work):
    """A benchmark module's `if __name__ == "__main__":`: print json.dumps(work(spec))."""
    print(json.dumps(work(json.loads(sys.argv[1]))))


def table(header, rows):
    """A markdown table of str()-able cells, each column as wide as its widest cell."""
    widths = [max(len(str(c)) for c in col) for col in zip(header, *rows)]
    line = lambda cells: "| " + " | ".join(str(c).ljust(w) for c, w in zip(cells, widths)) + " |"  # noqa: E731
    return "\n".join([line(header), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + [line(r) for r in rows])


def write_json(path, report):
    """A report as JSON, written whole or not at all."""
    atomic_write_text(path, json.dumps(report, indent=1))


def save_plot(folder, name, lines, title, xlabel, ylabel, logx=True, xticks=None):
    """folder/name, a PNG: log y (and log x unless not logx) against x, a line per label of lines
    {label: (x, y, matplotlib format)}, the legend outside on the right; a y of 0 drawn at a tenth
    of the smallest y > 0, a NaN or an inf at ten times the largest. The path, or None where
    matplotlib (the `plots` extra) is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    ys = [np.asarray(y, dtype=np.float64) for _, y, _ in lines.values()]
    positive = np.concatenate([y[np.isfinite(y) & (y > 0)] for y in ys])
    floor, top = positive.min() / 10, positive.max() * 10
    fig, ax = plt.subplots(figsize=(9.6, 4.8), layout="constrained")
    for (label, (x, _, fmt)), y in zip(lines.items(), ys):
        ax.plot(x, np.where(np.isfinite(y), np.maximum(y, floor), top), fmt, label=label)
    if any((~(y > 0) | (y == np.inf)).any() for y in ys):
        ylabel += f"\n(0 drawn at {floor:.0e}, NaN and inf at {top:.0e})"
    ax.set(xscale="log" if logx else "linear", yscale="log", title=title, xlabel=xlabel, ylabel=ylabel)
    if xticks:
        ax.set_xticks(xticks, [str(t) for t in xticks])
    ax.xaxis.set_minor_formatter("")  # no minor tick labels
    ax.grid(True, which="both", alpha=0.3)
    fig.legend(loc="outside right upper", fontsize=7)
    os.makedirs(folder, exist_ok=True)
    fig.savefig(os.path.join(folder, name), dpi=100)
    plt.close(fig)
    return os.path.join(folder, name)
