"""`pyvf bench NAME [options]`: each benchmark's arguments; the work is the run() of its module
in pyvf.bench (and pyvf.bench.attention.demo for demo-attention).

    pyvf bench attention|vq|transformer|codebook|scaling [--quick] [...]   # `pyvf bench NAME --help`
    pyvf bench accuracy|hardcases [--quick] [--json F] [--plots DIR]      # speed vs error; hard cases
    pyvf bench report [--quick] [--out DIR]     # docs/performance.md and docs/accuracy.md, regenerated
    pyvf bench demo-attention [--sizes small]   # branching attention: error, time, memory

Each benchmark is a parser function `_<name>_parser() -> (parser, check(args) or None)` and a
handler `_<name>(args) -> exit status` in BENCHMARKS; the modules are imported when their
benchmark runs. Every option is checked when it is parsed (options.py's argparse types, then
check): a bad size, limit or output path is the parser's one-line error before anything is
measured.
"""

import argparse
import importlib
import os
import subprocess
import sys

from ..bench.common import BLAS_THREAD_VARS, TORCH_MISSING, torch_or_none, write_outputs
from .options import (add_threads, context_sizes, names, non_negative_float, output_dir, output_file, positive_float,
                      positive_int)

DEMO_ATTENTION = "demo-attention"  # `pyvf bench demo-attention`: pyvf.bench.attention.demo()
COMPARE_THREADS = "threads for pyvf and torch (default 2)"
# benchmarks that cannot run without torch (the others time pyvf alone where it is missing)
NEEDS_TORCH = {"transformer": "the oracle its first step is checked against before both are timed",
               "codebook": "the oracle its first step is checked against before both are timed"}


def _module(name):
    return importlib.import_module(f"pyvf.bench.{name}")


def _parser(name, quick, epilog=False, repeat=None, json=True, plots=None):
    """A benchmark's parser with the options most take: --quick (its help), --threads (default 2),
    --repeat (repeat: its help), --json, --plots (plots: what is drawn); the module docstring's first
    paragraph as description (all of it as epilog when asked), the raw layout kept."""
    doc = _module(name).__doc__
    p = argparse.ArgumentParser(prog=f"pyvf bench {name}", description=doc.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=doc if epilog else None)
    p.add_argument("--quick", action="store_true", help=quick)
    add_threads(p, 2, COMPARE_THREADS)
    if repeat:
        p.add_argument("--repeat", type=positive_int, default=None, help=f"timed calls per median ({repeat})")
    if json:
        p.add_argument("--json", metavar="PATH", type=output_file, help="write every number to PATH")
    if plots:
        p.add_argument("--plots", metavar="DIR", type=output_dir, help=plots + " (PNG) to DIR (needs matplotlib)")
    return p


def _repeat(p, args, default, least):
    """--repeat filled in with its default and checked: at least `least` calls per median."""
    args.repeat = args.repeat or default
    if args.repeat < least:
        p.error(f"--repeat must be at least {least} (a median of fewer calls is not worth printing)")


def _sizes(args, base, quick):
    """The size options named by base's keys (--R, ...), each defaulting to base's (quick's with --quick)."""
    return [getattr(args, n) or (quick if args.quick else base)[n] for n in base]


# ---------------------------------------------------------------------------------------
# attention, scaling, vq, transformer, codebook


def _attention_parser():
    attention = _module("attention")
    p = _parser("attention", "smaller sizes (H=4, N=8)", repeat="default 5, at least 5")
    for name, val in attention.PAPER.items():
        p.add_argument(f"--{name}", type=positive_int, default=None,
                       help=f"default {val} ({attention.QUICK[name]} with --quick)")
    return p, lambda args: _repeat(p, args, 5, 5)


def _attention(args):
    attention = _module("attention")
    report = attention.run(*_sizes(args, attention.PAPER, attention.QUICK), threads=args.threads, repeat=args.repeat)
    write_outputs(report, args.json)
    if "aborted" in report:
        print(f"\nFAIL: {report['aborted']}; nothing is timed.", file=sys.stderr)
        return 1
    return 0


def _head_sizes(text):
    """argparse type of --sizes: comma-separated HxDH pairs of positive integers, e.g. 12x64,4x32."""
    try:
        sizes = tuple(tuple(int(y) for y in x.lower().split("x")) for x in text.split(","))
    except ValueError:
        sizes = ()
    if not sizes or any(len(s) != 2 or min(s) < 1 for s in sizes):
        raise argparse.ArgumentTypeError(f"expected HxDH pairs of positive integers, e.g. 12x64,4x32; got {text!r}")
    return sizes


def _scaling_parser():
    scaling = _module("scaling")
    p = _parser("scaling", "N = 2, 4, 8, H=4 dh=32", epilog=True, repeat="default 5, at least 5",
                plots="write memory and time plots")
    p.add_argument("--views", type=context_sizes, help="comma-separated N (default 2,4,...,64; 2,4,8 with --quick)")
    p.add_argument("--sizes", type=_head_sizes, help="comma-separated HxDH (default 12x64,4x32; 4x32 with --quick)")
    p.add_argument("--methods", help=f"comma-separated, from {', '.join(scaling.METHODS)} (default all)")
    p.add_argument("--mem-limit-mib", type=positive_float, default=None,
                   help="plan against this many MiB instead of /proc/meminfo MemAvailable")
    p.add_argument("--max-point-seconds", type=non_negative_float, default=scaling.MAX_POINT_SECONDS,
                   help="skip a point whose run time, predicted from the previous N by the FLOPs it computes, "
                        f"exceeds this (default {scaling.MAX_POINT_SECONDS}; 0: never)")

    def check(args):
        _repeat(p, args, 5, 5)
        args.views = args.views or (scaling.QUICK_VIEWS if args.quick else scaling.VIEWS)
        args.sizes = args.sizes or (scaling.QUICK_SIZES if args.quick else scaling.SIZES)
        args.methods = names(p, args.methods, scaling.METHODS, "method")
    return p, check


def _scaling(args):
    scaling = _module("scaling")
    report = scaling.run(args.sizes, args.views, args.methods, args.threads, args.repeat, args.mem_limit_mib,
                         args.max_point_seconds, plots=args.plots)
    write_outputs(report, args.json)
    return 1 if scaling.validation_failed(report) else 0


def _vq_parser():
    vq = _module("vq")
    p = _parser("vq", f"smaller sizes, answers checked on {vq.QUICK['checked_rows']} rows", json=False,
                repeat=f"default {vq.PAPER['repeat']}, {vq.QUICK['repeat']} with --quick; at least 3")
    for name in ("M", "K", "D"):
        p.add_argument(f"--{name}", type=positive_int, default=None,
                       help=f"default {vq.PAPER[name]} ({vq.QUICK[name]} with --quick)")
    return p, lambda args: _repeat(p, args, (vq.QUICK if args.quick else vq.PAPER)["repeat"], 3)


def _vq(args):
    vq = _module("vq")
    base = vq.QUICK if args.quick else vq.PAPER
    sizes = _sizes(args, {n: vq.PAPER[n] for n in "MKD"}, vq.QUICK)
    report = vq.run(*sizes, args.repeat, base["checked_rows"], args.threads)
    return 1 if report["failures"] else 0


def _steps_parser(name):
    """transformer and codebook: pyvf's training step against torch's, per configuration."""
    module = _module(name)
    p = _parser(name, "the tiny configuration only, 10 steps", json=False)
    p.add_argument("--configs", nargs="+", default=None, choices=list(module.CONFIGS),
                   help="default: tiny paper (tiny with --quick)")
    p.add_argument("--steps", type=int, default=None, help="timed steps (default: 20 tiny for the transformer, 10 "
                                                           "for the codebook; 3 paper; 10 with --quick)")

    def check(args):
        args.configs = args.configs or (["tiny"] if args.quick else ["tiny", "paper"])
        args.steps = args.steps or (10 if args.quick else None)
        if args.steps is not None and args.steps < 3:
            p.error("--steps must be at least 3 (a median of fewer steps is not worth printing)")
    return p, check


def _steps(name):
    return lambda args: 1 if _module(name).run(args.configs, args.steps, args.threads)["failures"] else 0


# ---------------------------------------------------------------------------------------
# the checking benchmarks (accuracy, hardcases), the report, the demo


def _verdict(report, args, make_plots, what):
    """The end of a checking benchmark: the plots and the JSON asked for, a FAIL line per entry of
    report["failures"] and the verdict. Returns the exit status: 1 if anything failed."""
    write_outputs(report, args.json, args.plots, make_plots)
    for f in report["failures"]:
        print(f"FAIL {f}")
    print(f"\n{'FAIL' if report['failures'] else 'PASS'}: {len(report['failures'])} {what} outside their bound; "
          f"total {report['total_seconds']:.0f} s")
    return 1 if report["failures"] else 0


def _accuracy_parser():
    accuracy = _module("accuracy")
    p = _parser("accuracy", "small sizes, median of 3", epilog=True, repeat="default 5; 3 with --quick; at least 3",
                plots="write a time-vs-error plot per op")
    p.add_argument("--ops", help=f"comma-separated, from {', '.join(accuracy.OPS)} (default all)")

    def check(args):
        args.ops = names(p, args.ops, accuracy.OPS, "op")
        _repeat(p, args, 3 if args.quick else 5, 3)
    return p, check


def _accuracy(args):
    accuracy = _module("accuracy")
    print(f"# speed against error: {len(args.ops)} ops, {'quick' if args.quick else 'full'} sizes, "
          f"{args.threads} threads, median of {args.repeat}")
    report = accuracy.run(args.ops, "quick" if args.quick else "full", args.repeat, args.threads)
    accuracy.print_report(report)
    return _verdict(report, args, lambda d: accuracy.plot(report["results"], d), "variant(s)")


def _hardcases_parser():
    hardcases = _module("hardcases")
    p = _parser("hardcases", "fewer points, smaller problems", epilog=True, plots="write one plot per sweep")
    p.add_argument("--sweeps", help=f"comma-separated, from {', '.join(hardcases.SWEEPS)} (default all)")
    return p, lambda args: setattr(args, "sweeps", names(p, args.sweeps, hardcases.SWEEPS, "sweep"))


def _hardcases(args):
    hardcases = _module("hardcases")
    print(f"# hard cases: {len(args.sweeps)} sweeps, {'quick' if args.quick else 'full'}, {args.threads} threads")
    report = hardcases.run(args.sweeps, "quick" if args.quick else "full", args.threads)
    hardcases.print_report(report)
    return _verdict(report, args, lambda d: hardcases.plot_all(report["sweeps"], d), "pyvf line(s)")


def _report_parser():
    p = _parser("report", "every run in its --quick mode", epilog=True, json=False)
    p.add_argument("--out", default="docs", type=output_dir, help="the folder for performance.md, accuracy.md, "
                                                                  "img/ and measurements/ (default docs)")
    return p, None


def _report(args):
    rep = _module("report").run(args.quick, args.out, args.threads)
    print("wrote " + ", ".join(rep["files"]))
    for f in rep["failures"]:
        print(f"FAIL {f}")
    print(f"{'FAIL' if rep['failures'] else 'PASS'}; total {rep['total_seconds'] / 60:.1f} minutes")
    return 1 if rep["failures"] else 0


def _demo_attention_parser():
    attention = _module("attention")
    p = argparse.ArgumentParser(prog=f"pyvf bench {DEMO_ATTENTION}", description="Branching attention at a few "
                                "sizes: error against the dense reference, time, memory.")
    add_threads(p, None, "threads for pyvf's C++ kernels (default: OpenMP's, OMP_NUM_THREADS or all cores)")
    p.add_argument("--sizes", help=f"comma-separated sizes, from {', '.join(attention.DEMO_SIZES)} (default all)")
    return p, lambda args: setattr(args, "sizes", names(p, args.sizes, attention.DEMO_SIZES, "size"))


def _demo_attention(args):
    return _module("attention").demo(args.sizes, threads=args.threads)


# name -> (its parser function -> (parser, check(args) or None), its handler)
BENCHMARKS = {
    "attention": (_attention_parser, _attention),
    "vq": (_vq_parser, _vq),
    "transformer": (lambda: _steps_parser("transformer"), _steps("transformer")),
    "codebook": (lambda: _steps_parser("codebook"), _steps("codebook")),
    "scaling": (_scaling_parser, _scaling),
    "accuracy": (_accuracy_parser, _accuracy),
    "hardcases": (_hardcases_parser, _hardcases),
    "report": (_report_parser, _report),
    DEMO_ATTENTION: (_demo_attention_parser, _demo_attention),
}


def cmd_bench(args):
    """Run one benchmark of pyvf.bench; the arguments after its name go to its main().

    A benchmark runs with numpy's BLAS on its --threads: where the BLAS_THREAD_VARS of this
    process say otherwise (numpy is loaded by then, its BLAS thread count fixed), it runs in a
    child process `pyvf bench ...` with them set, and returns the child's status. The child runs
    in this working folder (relative paths in the arguments keep their meaning) but drops it from
    sys.path before importing pyvf: run from a source checkout, `python -m pyvf` would import the
    unbuilt source tree instead of the installed package."""
    make_parser, handler = BENCHMARKS[args.name]
    parser, check = make_parser()
    bench_args = parser.parse_args(args.args)
    if check is not None:
        check(bench_args)
    if args.name in NEEDS_TORCH and torch_or_none() is None:
        print(f"pyvf bench {args.name}: needs torch, {NEEDS_TORCH[args.name]}: {TORCH_MISSING}", file=sys.stderr)
        return 1
    n = bench_args.threads if args.name != DEMO_ATTENTION else None  # (demo-attention's default: OpenMP's)
    if n is not None and any(os.environ.get(v) != str(n) for v in BLAS_THREAD_VARS):
        env = dict(os.environ, **{v: str(n) for v in BLAS_THREAD_VARS})
        boot = "import sys; del sys.path[0]; from pyvf.cli import main; sys.exit(main())"
        return subprocess.run([sys.executable, "-c", boot, "bench", args.name, *args.args], env=env).returncode
    return handler(bench_args)


def register(subparsers):
    """Add `bench` to an argparse subparsers object."""
    listed = ", ".join(n for n in BENCHMARKS if n != DEMO_ATTENTION)
    p = subparsers.add_parser("bench", help=f"a benchmark: {listed} (--quick: at most a couple of minutes)"
                              f"; {DEMO_ATTENTION}: the attention kernel's error, time and memory at a few sizes",
                              description=cmd_bench.__doc__ + " `pyvf bench NAME --help` lists its options.")
    p.add_argument("name", choices=tuple(BENCHMARKS), help="which benchmark")
    p.add_argument("args", nargs=argparse.REMAINDER, help="the benchmark's own options, e.g. --quick")
    p.set_defaults(func=cmd_bench)
    return p
