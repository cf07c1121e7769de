"""pyvf's command line: the console script `pyvf <command>`, or `python -m pyvf <command>`.

    pyvf demo                                   # the pretrained models on held-out scenes; ~2 minutes
    pyvf demo --quick                           # seconds
    pyvf evaluate --scenes 200 --context 1,3,5 --out eval [--codebook F --transformer F]
    pyvf config                                 # the kernels' instruction-set path, threads
    pyvf bench attention|vq|transformer|codebook|scaling [--quick] [...]   # `pyvf bench NAME --help`
    pyvf bench accuracy|hardcases [--quick] [--json F] [--plots DIR]      # speed vs error; hard cases
    pyvf bench report [--quick] [--out DIR]     # docs/performance.md and docs/accuracy.md, regenerated
    pyvf bench demo-attention [--sizes small]   # branching attention: error, time, memory; ~1 minute
    pyvf convert tf-transformer path/model --config config.json -o model.npz
    pyvf convert torch-codebook model.ckpt --config config.json -o codebook.npz

This file only parses arguments and calls the functions that do the work (pyvf.bench,
pyvf.verify), so a test calls the same function a user's command does. Each command is a
function `cmd_<name>(args) -> exit status` with an argparse subparser made in build_parser();
a new command is one more of each. Nothing here imports torch: the benchmarks and the
torch-codebook converter import it inside the functions that need it.
"""

import argparse
import importlib
import os
import subprocess
import sys

import pyvf
from pyvf.bench import BLAS_THREAD_VARS
from pyvf.bench import attention as bench_attention
from pyvf.evaluate.commands import cli_register as evaluate_commands
from pyvf.scenes.cli import cli_register as scenes_commands
from pyvf.train.commands import cli_register as train_commands
from pyvf.verify import convert_tf, convert_torch

BENCHMARKS = ("attention", "vq", "transformer", "codebook", "scaling", "accuracy", "hardcases", "report")  # pyvf.bench
DEMO_ATTENTION = "demo-attention"  # `pyvf bench demo-attention`: pyvf.bench.attention.demo()
# name -> (the converter's module, what its checkpoint argument is, what its config is)
CONVERTERS = {
    "tf-transformer": (convert_tf, "checkpoint prefix, e.g. path/model (beside model.index)", "TransformerConfig"),
    "torch-codebook": (convert_torch, "the checkpoint file, e.g. path/model.ckpt", "CodebookConfig"),
}


def cmd_demo_attention(argv):
    """Branching attention at a few sizes: error against the dense reference, time, memory."""
    p = argparse.ArgumentParser(prog=f"pyvf bench {DEMO_ATTENTION}", description=cmd_demo_attention.__doc__)
    p.add_argument("--threads", type=int, default=None,
                   help="threads for pyvf's C++ kernels (default: OpenMP's, OMP_NUM_THREADS or all cores)")
    sizes = ", ".join(bench_attention.DEMO_SIZES)
    p.add_argument("--sizes", default=",".join(bench_attention.DEMO_SIZES),
                   help=f"comma-separated sizes to run, from {sizes} (default: all)")
    args = p.parse_args(argv)
    if args.threads is not None and args.threads < 1:
        p.error("--threads must be a positive integer")
    names = [s.strip() for s in args.sizes.split(",") if s.strip()]
    unknown = [s for s in names if s not in bench_attention.DEMO_SIZES]
    if unknown or not names:
        print(f"pyvf bench {DEMO_ATTENTION}: unknown size {unknown or args.sizes!r}; "
              f"choose from {', '.join(bench_attention.DEMO_SIZES)}", file=sys.stderr)
        return 2
    return bench_attention.demo(names, threads=args.threads)


def cmd_config(args):
    """Print pyvf.show_config(): the kernels' instruction-set path, the paths this CPU runs, threads."""
    pyvf.show_config()
    return 0


def bench_threads(argv):
    """The --threads a benchmark's arguments ask for (its default, 2, when none), or None for
    a value its own parser should reject."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--threads", default="2")
    value = p.parse_known_args(argv)[0].threads
    return int(value) if value.isdigit() and int(value) >= 1 else None


def cmd_bench(args):
    """Run one benchmark of pyvf.bench; the arguments after its name go to its main().

    A benchmark runs with numpy's BLAS on its --threads: where the BLAS_THREAD_VARS of this
    process say otherwise (numpy is loaded by then, its BLAS thread count fixed), it runs in a
    child process `pyvf bench ...` with them set, and returns the child's status. The child runs
    in this working folder (relative paths in the arguments keep their meaning) but drops it from
    sys.path before importing pyvf: run from a source checkout, `python -m pyvf` would import the
    unbuilt source tree instead of the installed package."""
    n = bench_threads(args.args) if args.name != DEMO_ATTENTION else None
    if n is not None and any(os.environ.get(v) != str(n) for v in BLAS_THREAD_VARS):
        env = dict(os.environ, **{v: str(n) for v in BLAS_THREAD_VARS})
        boot = "import sys; del sys.path[0]; from pyvf.cli import main; sys.exit(main())"
        return subprocess.run([sys.executable, "-c", boot, "bench", args.name, *args.args], env=env).returncode
    if args.name == DEMO_ATTENTION:
        return cmd_demo_attention(args.args)
    module = importlib.import_module(f"pyvf.bench.{args.name}")
    return module.main(args.args)


def cmd_convert(args):
    """Convert a published checkpoint into the .npz that pyvf loads."""
    try:
        n, skipped = CONVERTERS[args.format][0].convert_checkpoint(args.checkpoint, args.config, args.output)
    except ModuleNotFoundError as e:  # the converter's framework (tensorflow, torch) is not installed
        print(f"pyvf convert: {e}", file=sys.stderr)
        return 1
    print(f"wrote {args.output}: {n} arrays; skipped {len(skipped)} other keys")
    return 0


# ---------------------------------------------------------------------------------------
# the parser


def build_parser():
    parser = argparse.ArgumentParser(
        prog="pyvf", description="pyvf: a reference implementation of ViewFormer (ECCV 2022).")
    parser.add_argument("--version", action="version", version=f"pyvf {pyvf.__version__}")
    commands = parser.add_subparsers(dest="command", metavar="command")
    evaluate_commands(commands)  # demo and evaluate (pyvf/evaluate/commands.py), first in the help

    p = commands.add_parser("config", help="which instruction-set path the kernels use, and the threads",
                            description=cmd_config.__doc__)
    p.set_defaults(func=cmd_config)

    p = commands.add_parser("bench", help="a benchmark: " + ", ".join(BENCHMARKS) + " (--quick: at most a couple of minutes)"
                            f"; {DEMO_ATTENTION}: the attention kernel's error, time and memory at a few sizes",
                            description=cmd_bench.__doc__ + " `pyvf bench NAME --help` lists its options.")
    p.add_argument("name", choices=BENCHMARKS + (DEMO_ATTENTION,), help="which benchmark")
    p.add_argument("args", nargs=argparse.REMAINDER, help="the benchmark's own options, e.g. --quick")
    p.set_defaults(func=cmd_bench)

    p = commands.add_parser("convert", help="a published checkpoint -> the .npz pyvf loads",
                            description=cmd_convert.__doc__)
    formats = p.add_subparsers(dest="format", metavar="format", required=True)
    for name, (module, checkpoint_help, config_class) in CONVERTERS.items():
        c = formats.add_parser(name, help=module.__doc__.split("\n\n")[0].replace("\n", " "),
                               description=module.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
        c.add_argument("checkpoint", help=checkpoint_help)
        c.add_argument("--config", required=True, help=f"JSON file of {config_class} fields")
        c.add_argument("-o", "--output", required=True, help="the .npz to write")
        c.set_defaults(func=cmd_convert)

    # the SM7 scenes and the training commands: their parsers live beside their work
    # (pyvf/scenes/cli.py, pyvf/train/commands.py)
    scenes_commands(commands)
    train_commands(commands)
    return parser


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    if getattr(args, "threads", None) is not None and args.threads < 1:
        parser.error("--threads must be a positive integer")
    return args.func(args)
