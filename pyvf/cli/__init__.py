"""pyvf's command line, `pyvf <command>` or `python -m pyvf <command>`; each home's commands in a
module of their own. Each command is a function `cmd_<name>(args) -> exit status` that calls one
library function. A mistake in the arguments is one line, `pyvf COMMAND: error: ...`, exit status
2, before the work starts.
"""

import argparse
import glob
import json
import os
import sys

import pyvf
from pyvf import CodebookConfig, TransformerConfig
from pyvf.verify import convert_tf, convert_torch

from . import bench, evaluate, scenes, train
from .options import fail, file_to_read, file_to_write

# name -> (the converter's module, what its checkpoint argument is, the class of its --config)
CONVERTERS = {
    "tf-transformer": (convert_tf, "checkpoint prefix, e.g. path/model (beside model.index)", TransformerConfig),
    "torch-codebook": (convert_torch, "the checkpoint file, e.g. path/model.ckpt", CodebookConfig),
}


def cmd_config(args):
    """Print pyvf.show_config(): the kernels' instruction-set path, the paths this CPU runs, threads."""
    pyvf.show_config()
    return 0


def cmd_convert(args):
    """Convert a published checkpoint into the .npz that pyvf loads."""
    command = f"convert {args.format}"
    module, _, config_class = CONVERTERS[args.format]
    output = args.output if args.output.endswith(".npz") else args.output + ".npz"  # the name Model.save writes
    # every argument checked before the framework is imported and the checkpoint read
    found = os.path.exists(args.checkpoint) or glob.glob(glob.escape(args.checkpoint) + ".*")  # a file or TF prefix
    for option, problem in (("checkpoint", None if found else f"no checkpoint at {args.checkpoint!r}"),
                            ("--config", _config_problem(args.config, config_class)),
                            ("-o/--output", file_to_write(output))):
        if problem:
            return fail(command, f"argument {option}: {problem}")
    try:
        n, skipped = module.convert_checkpoint(args.checkpoint, args.config, output)
    except ModuleNotFoundError as e:  # the converter's framework (tensorflow, torch) is not installed
        print(f"pyvf convert: {e}", file=sys.stderr)
        return 1
    except Exception as e:  # noqa: BLE001 -- damaged, another model's, or the framework's own read errors
        return fail(command, f"argument checkpoint: cannot convert {args.checkpoint!r} ({type(e).__name__}: {e})")
    print(f"wrote {output}: {n} arrays; skipped {len(skipped)} other keys")
    return 0


def _config_problem(path, config_class):
    """None, or why the JSON file `path` is not the fields of a config_class."""
    if problem := file_to_read(path):
        return problem
    try:
        with open(path, "rb") as f:
            config_class(**json.loads(f.read().decode("utf-8")))
    except (ValueError, TypeError) as e:  # not UTF-8 JSON of an object, a field unknown, missing or out of range
        return f"{path!r} is not a JSON object of {config_class.__name__} fields ({e})"
    return None


def _convert(commands):
    p = commands.add_parser("convert", help="a published checkpoint -> the .npz pyvf loads",
                            description=cmd_convert.__doc__)
    formats = p.add_subparsers(dest="format", metavar="format", required=True)
    for name, (module, checkpoint_help, config_class) in CONVERTERS.items():
        c = formats.add_parser(name, help=module.__doc__.split("\n\n")[0].replace("\n", " "),
                               description=module.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
        c.add_argument("checkpoint", help=checkpoint_help)
        c.add_argument("--config", required=True, help=f"JSON file of {config_class.__name__} fields")
        c.add_argument("-o", "--output", required=True, help="the .npz to write (.npz appended when missing)")
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
