"""pyvf's benchmarks, each a module with `main(argv=None) -> exit status` and a `--quick` mode:

    pyvf bench attention   branching attention: pyvf's kernel, torch SDPA, the dense NumPy reference
    pyvf bench vq          nearest-code lookup: pyvf.vq_nearest, torch, numpy, float64 brute force
    pyvf bench transformer one training step, pyvf against the torch oracle model
    pyvf bench codebook    encode/decode and a training step, pyvf against the torch oracle model
    pyvf bench scaling     attention memory and time against the number of views: pyvf, naive stacked, dense
    pyvf bench accuracy    speed against error: every op and variant against a float64 reference
    pyvf bench hardcases   sweeps into the hard cases, pyvf's stated bound checked along each
    pyvf bench report      docs/performance.md and docs/accuracy.md from the three above

`pyvf bench <name> [args]` (or `python -m pyvf.bench.<name> [args]`) runs one; `--help` lists its
options. Every benchmark validates its results before it times them. torch is imported only
inside the functions that use it: importing a module here does not import torch.
"""

import argparse
import json
import os

# numpy's BLAS takes its thread count from these variables once, when numpy loads; `pyvf bench`
# sets them to the benchmark's --threads (pyvf.cli.cmd_bench), so that numpy's GEMM and pyvf's
# layers use the threads that pyvf's kernels and torch are given
BLAS_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def blas_thread_env():
    """{variable: value or None} of BLAS_THREAD_VARS in this process, for a benchmark's report."""
    return {v: os.environ.get(v) for v in BLAS_THREAD_VARS}


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


def write_json(path, report):
    with open(path, "w") as f:
        json.dump(report, f, indent=1)


def finish(report, json_path, plots_dir, make_plots, what):
    """The end of a checking benchmark's main (accuracy, hardcases): the plots (make_plots(dir) ->
    the files, or None without matplotlib), the JSON, a FAIL line per entry of report["failures"]
    and the verdict. Returns the exit status: 1 if anything failed."""
    if plots_dir:
        files = make_plots(plots_dir)
        print("\nplots need matplotlib: pip install pyvf[plots]" if files is None else "\nwrote " + ", ".join(files))
        report["plots"] = files
    if json_path:
        write_json(json_path, report)
        print(f"wrote {json_path}")
    for f in report["failures"]:
        print(f"FAIL {f}")
    print(f"\n{'FAIL' if report['failures'] else 'PASS'}: {len(report['failures'])} {what} outside their bound; "
          f"total {report['total_seconds']:.0f} s")
    return 1 if report["failures"] else 0


def pick(parser, value, choices, what):
    """The comma-separated names of an option (all of choices when it was not given), each one
    checked against choices: an unknown name is the parser's error, naming the choices."""
    names = tuple(n.strip() for n in value.split(",")) if value else tuple(choices)
    unknown = [n for n in names if n not in choices]
    if unknown:
        parser.error(f"unknown {what} {', '.join(unknown)}; choose from {', '.join(choices)}")
    return names


def checking_parser(prog, doc, quick, plots):
    """The options every checking benchmark (accuracy, hardcases) takes: --quick, --threads, --json
    and --plots; the module docstring as description and epilog. quick, plots: their help texts."""
    p = argparse.ArgumentParser(prog=prog, description=doc.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=doc)
    p.add_argument("--quick", action="store_true", help=quick)
    p.add_argument("--threads", type=int, default=2, help="threads for pyvf and torch (default 2)")
    p.add_argument("--json", metavar="PATH", help="write every number to PATH")
    p.add_argument("--plots", metavar="DIR", help=plots + " (PNG) to DIR (needs matplotlib)")
    return p
