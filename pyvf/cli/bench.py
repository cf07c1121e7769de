"""`pyvf bench NAME [--quick] [--threads N] [options]`: runs the benchmark pyvf.bench.NAME (`pyvf
bench NAME --help`); the exit status is 1 when its report lists a failure (a result not timed)."""

import argparse
import importlib
import sys

from ..bench.common import TORCH_MISSING, torch_or_none, write_json
from .options import add_threads, non_negative_float, output_dir, output_file

NAMES = ("attention", "vq", "transformer", "codebook", "scaling", "accuracy", "hardcases", "report")
NEEDS_TORCH = ("transformer", "codebook")  # the oracle their first step is checked against before timing


def _module(name):
    return importlib.import_module(f"pyvf.bench.{'steps' if name in NEEDS_TORCH else name}")


def _head_sizes(text):
    """argparse type of --sizes: comma-separated HxDH pairs of positive integers, e.g. 12x64,4x32."""
    sizes = [x.lower().split("x") for x in text.split(",")]
    if not all(len(s) == 2 and all(y.isdigit() and int(y) > 0 for y in s) for s in sizes):
        raise argparse.ArgumentTypeError(f"expected HxDH pairs of positive integers, e.g. 12x64,4x32; got {text!r}")
    return tuple(tuple(map(int, s)) for s in sizes)


def parser(name):
    """A benchmark's parser; its module docstring's first paragraph as description, the rest as epilog."""
    doc = _module(name).__doc__.strip().split("\n\n")
    p = argparse.ArgumentParser(prog=f"pyvf bench {name}", description=doc[0], epilog="\n\n".join(doc[1:]),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="smaller sizes, fewer steps (below): a few minutes at most")
    add_threads(p, 2, "threads for pyvf and torch (default 2)")
    if name == "report":
        p.add_argument("--out", default="docs", type=output_dir, help="the folder of the documents (default docs)")
        return p
    p.add_argument("--json", metavar="PATH", type=output_file, help="write every number to PATH")
    if name in ("scaling", "accuracy", "hardcases"):
        p.add_argument("--plots", metavar="DIR", type=output_dir, help="write the plots (PNG) to DIR (needs matplotlib)")
    if name == "scaling":
        p.add_argument("--sizes", type=_head_sizes, help="comma-separated HxDH (default 12x64,4x32; 4x32 with --quick)")
        p.add_argument("--max-point-seconds", type=non_negative_float, default=_module(name).MAX_POINT_SECONDS,
                       help="skip a point predicted to take longer (default %(default)s; 0: never)")
    return p


def cmd_bench(args):
    """Run one benchmark of pyvf.bench on --threads threads (pyvf's kernels, numpy's BLAS, torch's);
    the arguments after its name go to its parser. Its failures printed, its report written to --json."""
    name, args = args.name, parser(args.name).parse_args(args.args)
    if name in NEEDS_TORCH and torch_or_none() is None:
        print(f"pyvf bench {name}: needs torch, the oracle its first step is checked against before both are "
              f"timed: {TORCH_MISSING}", file=sys.stderr)
        return 1
    options = {k: v for k, v in vars(args).items() if k not in ("quick", "threads", "json") and v is not None}
    report = _module(name).run(*([name] if name in NEEDS_TORCH else []), args.quick, args.threads, **options)
    if getattr(args, "json", None):
        write_json(args.json, report)
    for f in report["failures"]:
        print(f"FAIL {f}")
    print(f"FAIL: {len(report['failures'])} failure(s)" if report["failures"] else "PASS")
    return 1 if report["failures"] else 0


def register(subparsers):
    """Add `bench` to an argparse subparsers object."""
    p = subparsers.add_parser("bench", help=f"a benchmark: {', '.join(NAMES)} (--quick: a few minutes at most)",
                              description=cmd_bench.__doc__ + " `pyvf bench NAME --help` lists its options.")
    p.add_argument("name", choices=NAMES, help="which benchmark")
    p.add_argument("args", nargs=argparse.REMAINDER, help="the benchmark's own options, e.g. --quick")
    p.set_defaults(func=cmd_bench)
    return p
