"""pyvf's command line, `pyvf <command>` or `python -m pyvf <command>`; the commands of evaluate,
train and bench in modules of their own, config, convert and scenes here. Each command is a function `cmd_<name>(args) -> exit status` that calls one
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
from pyvf.scenes.dataset import PREVIEW_SCENES, DatasetExistsError, make_dataset
from pyvf.verify import convert_tf, convert_torch

from . import bench, evaluate, train
from .options import INTERRUPTED, fail, file_to_read, file_to_write, folder_to_make

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


def cmd_scenes(args):
    """Render a Shepard-Metzler-7 dataset (docs/math.md §7) into .npz shards and a manifest.
    An interrupted run is resumed by the same command: the shards it finished are kept."""
    for option, problem in (("--out", folder_to_make(args.out)),
                            ("--preview", args.preview is not None and file_to_write(args.preview))):
        if problem:  # before the rendering, which can take minutes
            return fail("scenes", f"argument {option}: {problem}")
    try:
        make_dataset(args.out, args.scenes, args.seed, views=args.views, size=args.size, shard_size=args.shard_size,
                     preview=args.preview, progress=not args.quiet, overwrite=args.overwrite)
    except DatasetExistsError as e:
        return fail("scenes", f"argument --out: {str(e).replace('overwrite=True', '--overwrite')}")
    except (ValueError, TypeError) as e:
        return fail("scenes", str(e))
    except OSError as e:  # a folder that cannot be written (a read-only or virtual file system, a full disk)
        return fail("scenes", f"cannot write {e.filename if e.filename is not None else args.out!r}: "
                              f"{e.strerror or e}")
    except KeyboardInterrupt:
        print(f"\npyvf scenes: interrupted; the same command resumes it, keeping the shards in {args.out} that "
              "are finished", file=sys.stderr)
        return INTERRUPTED
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


def _scenes(commands):
    p = commands.add_parser("scenes", help="render a Shepard-Metzler-7 dataset (.npz shards + manifest)",
                              description=cmd_scenes.__doc__)
    p.add_argument("--out", required=True, metavar="DIR", help="folder to write the shards and manifest.json into")
    p.add_argument("--scenes", type=int, required=True, metavar="N", help="number of scenes")
    p.add_argument("--seed", type=int, required=True, metavar="S",
                   help="dataset seed: scene i draws from numpy.random.default_rng([S, i])")
    p.add_argument("--views", type=int, default=15, help="views per scene (default 15, as SM7)")
    p.add_argument("--size", type=int, default=64, help="image side in pixels (default 64, as SM7)")
    p.add_argument("--shard-size", type=int, default=500, metavar="N", help="scenes per shard (default 500)")
    p.add_argument("--preview", default=None, metavar="PNG",
                   help=f"also write a PNG grid of the first {PREVIEW_SCENES} scenes' views")
    p.add_argument("--overwrite", action="store_true", help="replace a dataset already in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_scenes)


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
    _scenes(commands)
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
