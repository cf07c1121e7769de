"""`pyvf bench NAME [options]`: each benchmark's arguments; the work is the run() of its module in
pyvf.bench.

    pyvf bench attention|vq|transformer|codebook [--quick] [--threads N]
    pyvf bench scaling [--quick] [--sizes 12x64,4x32] [--max-point-seconds S] [--json F] [--plots DIR]
    pyvf bench accuracy|hardcases [--quick] [--json F] [--plots DIR]
    pyvf bench report [--quick] [--out DIR]     # docs/performance.md and docs/accuracy.md, regenerated

Every option is checked when it is parsed (options.py's argparse types): a bad size or output path
is the parser's one-line error before anything is measured.
"""

import argparse
import importlib
import sys

from ..bench.common import TORCH_MISSING, torch_or_none, write_json
from .options import add_threads, non_negative_float, output_dir, output_file

NEEDS_TORCH = ("transformer", "codebook")  # the oracle their first step is checked against before timing


def _module(name):
    return importlib.import_module(f"pyvf.bench.{name}")


def _parser(name, quick, json=False, plots=False):
    """A benchmark's parser: --quick (its help), --threads (default 2), --json, --plots; the module
    docstring's first paragraph as description, all of it as epilog."""
    doc = _module("steps" if name in NEEDS_TORCH else name).__doc__
    p = argparse.ArgumentParser(prog=f"pyvf bench {name}", description=doc.split("\n\n")[0], epilog=doc,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help=quick)
    add_threads(p, 2, "threads for pyvf and torch (default 2)")
    if json:
        p.add_argument("--json", metavar="PATH", type=output_file, help="write every number to PATH")
    if plots:
        p.add_argument("--plots", metavar="DIR", type=output_dir, help="write the plots (PNG) to DIR (needs matplotlib)")
    return p


def _head_sizes(text):
    """argparse type of --sizes: comma-separated HxDH pairs of positive integers, e.g. 12x64,4x32."""
    try:
        sizes = tuple(tuple(int(y) for y in x.lower().split("x")) for x in text.split(","))
    except ValueError:
        sizes = ()
    if not sizes or any(len(s) != 2 or min(s) < 1 for s in sizes):
        raise argparse.ArgumentTypeError(f"expected HxDH pairs of positive integers, e.g. 12x64,4x32; got {text!r}")
    return sizes


def _attention(args):
    attention = _module("attention")
    report = attention.run(**(attention.QUICK if args.quick else attention.PAPER), threads=args.threads)
    if args.json:
        write_json(args.json, report)
    return 1 if "aborted" in report else 0


def _scaling(args):
    scaling = _module("scaling")
    report = scaling.run(args.sizes or (scaling.QUICK_SIZES if args.quick else scaling.SIZES),
                         scaling.QUICK_VIEWS if args.quick else scaling.VIEWS, threads=args.threads,
                         max_point_seconds=args.max_point_seconds, plots=args.plots, json_path=args.json)
    return 1 if scaling.validation_failed(report) else 0


def _vq(args):
    vq = _module("vq")
    return 1 if vq.run(**(vq.QUICK if args.quick else vq.PAPER), threads=args.threads)["failures"] else 0


def _steps(name):
    def handler(args):
        steps = _module("steps")
        configs = ["quick" if name == "codebook" else "tiny"] if args.quick else steps.FULL
        return 1 if steps.run(name, configs, 5 if args.quick else None, args.threads)["failures"] else 0
    return handler


def _checking(name, what):
    """accuracy and hardcases: the report, the plots and the JSON asked for, a FAIL line per failure."""
    def handler(args):
        module = _module(name)
        report = module.run(mode="quick" if args.quick else "full", threads=args.threads)
        module.print_report(report)
        if args.plots:
            files = module.plot_all(report, args.plots)
            print("\nplots need matplotlib: pip install pyvf[plots]" if files is None else "\nwrote " + ", ".join(files))
        if args.json:
            write_json(args.json, report)
        for f in report["failures"]:
            print(f"FAIL {f}")
        print(f"\n{'FAIL' if report['failures'] else 'PASS'}: {len(report['failures'])} {what} outside their bound; "
              f"total {report['total_seconds']:.0f} s")
        return 1 if report["failures"] else 0
    return handler


def _report(args):
    rep = _module("report").run(args.quick, args.out, args.threads)
    print("wrote " + ", ".join(rep["files"]))
    for f in rep["failures"]:
        print(f"FAIL {f}")
    print(f"{'FAIL' if rep['failures'] else 'PASS'}; total {rep['total_seconds'] / 60:.1f} minutes")
    return 1 if rep["failures"] else 0


def _scaling_parser():
    scaling = _module("scaling")
    p = _parser("scaling", "N = 2, 4, 8, H=4 dh=32", json=True, plots=True)
    p.add_argument("--sizes", type=_head_sizes, help="comma-separated HxDH (default 12x64,4x32; 4x32 with --quick)")
    p.add_argument("--max-point-seconds", type=non_negative_float, default=scaling.MAX_POINT_SECONDS,
                   help="skip a point whose run time, predicted from the previous N by the FLOPs it computes, "
                        f"exceeds this (default {scaling.MAX_POINT_SECONDS}; 0: never)")
    return p


def _report_parser():
    p = _parser("report", "every run in its --quick mode")
    p.add_argument("--out", default="docs", type=output_dir, help="the folder for performance.md, accuracy.md, "
                                                                  "img/ and measurements/ (default docs)")
    return p


# name -> (its parser function, its handler)
BENCHMARKS = {
    "attention": (lambda: _parser("attention", "a small size (H=2, N=4, dh=32)", json=True), _attention),
    "vq": (lambda: _parser("vq", "smaller sizes (M=4096, K=256, D=64)"), _vq),
    "transformer": (lambda: _parser("transformer", "the tiny configuration only"), _steps("transformer")),
    "codebook": (lambda: _parser("codebook", "the tiny configuration on a batch of two 32x32 images"),
                 _steps("codebook")),
    "scaling": (_scaling_parser, _scaling),
    "accuracy": (lambda: _parser("accuracy", "small sizes", json=True, plots=True), _checking("accuracy", "variant(s)")),
    "hardcases": (lambda: _parser("hardcases", "fewer points, smaller problems", json=True, plots=True),
                  _checking("hardcases", "pyvf line(s)")),
    "report": (_report_parser, _report),
}


def cmd_bench(args):
    """Run one benchmark of pyvf.bench; the arguments after its name go to its parser. It runs on
    its --threads: pyvf's kernels and numpy's BLAS pool (pyvf.set_num_threads) and torch's."""
    make_parser, handler = BENCHMARKS[args.name]
    bench_args = make_parser().parse_args(args.args)
    if args.name in NEEDS_TORCH and torch_or_none() is None:
        print(f"pyvf bench {args.name}: needs torch, the oracle its first step is checked against before both are "
              f"timed: {TORCH_MISSING}", file=sys.stderr)
        return 1
    return handler(bench_args)


def register(subparsers):
    """Add `bench` to an argparse subparsers object."""
    p = subparsers.add_parser("bench", help=f"a benchmark: {', '.join(BENCHMARKS)} (--quick: at most a couple of "
                              "minutes)",
                              description=cmd_bench.__doc__ + " `pyvf bench NAME --help` lists its options.")
    p.add_argument("name", choices=tuple(BENCHMARKS), help="which benchmark")
    p.add_argument("args", nargs=argparse.REMAINDER, help="the benchmark's own options, e.g. --quick")
    p.set_defaults(func=cmd_bench)
    return p
