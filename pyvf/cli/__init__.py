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
    pyvf scenes | train-codebook | tokenize | train-transformer | train | runs | export   # data, training

This package is the only place that parses arguments (argparse is imported nowhere else): each
command is a function `cmd_<name>(args) -> exit status` that calls one library function of the
homes below (pyvf.evaluate, pyvf.bench, pyvf.scenes, pyvf.train, pyvf.verify), so a test calls
the same function a user's command does. The commands of each home are in a module of their own
(evaluate.py, bench.py, scenes.py, train.py), each with a register(subparsers); options that more
than one command takes (--threads) are defined and checked once, in options.py. Nothing here
imports torch: the benchmarks and the torch-codebook converter import it inside the functions
that need it.
"""

import argparse
import sys

import pyvf
from pyvf.verify import convert_tf, convert_torch

from . import bench, evaluate, scenes, train

# name -> (the converter's module, what its checkpoint argument is, what its config is)
CONVERTERS = {
    "tf-transformer": (convert_tf, "checkpoint prefix, e.g. path/model (beside model.index)", "TransformerConfig"),
    "torch-codebook": (convert_torch, "the checkpoint file, e.g. path/model.ckpt", "CodebookConfig"),
}


def cmd_config(args):
    """Print pyvf.show_config(): the kernels' instruction-set path, the paths this CPU runs, threads."""
    pyvf.show_config()
    return 0


def cmd_convert(args):
    """Convert a published checkpoint into the .npz that pyvf loads."""
    try:
        n, skipped = CONVERTERS[args.format][0].convert_checkpoint(args.checkpoint, args.config, args.output)
    except ModuleNotFoundError as e:  # the converter's framework (tensorflow, torch) is not installed
        print(f"pyvf convert: {e}", file=sys.stderr)
        return 1
    print(f"wrote {args.output}: {n} arrays; skipped {len(skipped)} other keys")
    return 0


def _convert(commands):
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


def build_parser():
    parser = argparse.ArgumentParser(
        prog="pyvf", description="pyvf: a reference implementation of ViewFormer (ECCV 2022).")
    parser.add_argument("--version", action="version", version=f"pyvf {pyvf.__version__}")
    commands = parser.add_subparsers(dest="command", metavar="command")
    evaluate.register(commands)  # demo and evaluate, first in the help
    p = commands.add_parser("config", help="which instruction-set path the kernels use, and the threads",
                            description=cmd_config.__doc__)
    p.set_defaults(func=cmd_config)
    bench.register(commands)
    _convert(commands)
    scenes.register(commands)
    train.register(commands)
    return parser


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    pyvf.reuse_freed_memory()  # a command is a process of its own: its steps reuse the memory freed
    return args.func(args)
