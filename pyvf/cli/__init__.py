"""pyvf's command line: the console script `pyvf <command>`, or `python -m pyvf <command>`.

    pyvf demo                                   # the pretrained models on held-out scenes
    pyvf demo --quick                           # a smoke run
    pyvf evaluate --scenes 200 --context 1,3,5 --out eval [--codebook F --transformer F]
    pyvf config                                 # the kernels' instruction-set path, threads
    pyvf bench attention|vq|transformer|codebook|scaling [--quick] [...]   # `pyvf bench NAME --help`
    pyvf bench accuracy|hardcases [--quick] [--json F] [--plots DIR]      # speed vs error; hard cases
    pyvf bench report [--quick] [--out DIR]     # docs/performance.md and docs/accuracy.md, regenerated
    pyvf convert tf-transformer path/model --config config.json -o model.npz
    pyvf convert torch-codebook model.ckpt --config config.json -o codebook.npz
    pyvf scenes | train-codebook | tokenize | train-transformer | train | runs | export   # data, training

This package is the only place that parses arguments (argparse is imported nowhere else): each
command is a function `cmd_<name>(args) -> exit status` that calls one library function of the
homes below (pyvf.evaluate, pyvf.bench, pyvf.scenes, pyvf.train, pyvf.verify), so a test calls
the same function a user's command does. The commands of each home are in a module of their own
(evaluate.py, bench.py, scenes.py, train.py), each with a register(subparsers); options that more
than one command takes (--threads) are defined and checked once, in options.py, beside the
checks of the paths a command reads and writes (made before its work starts; a mistake is one
line, `pyvf COMMAND: error: ...`, and exit status 2). Nothing here imports torch: the
benchmarks and the torch-codebook converter import it inside the functions that need it.
"""

import argparse
import glob
import json
import os
import pickle
import sys
import zipfile

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
# the first bytes of a torch checkpoint in the legacy (before torch 1.6) format: the pickled magic number
_TORCH_LEGACY_MAGIC = b"\x80\x02\x8a\x0al\xfc\x9cF\xf9 j\xa8P\x19"


def cmd_config(args):
    """Print pyvf.show_config(): the kernels' instruction-set path, the paths this CPU runs, threads."""
    pyvf.show_config()
    return 0


def cmd_convert(args):
    """Convert a published checkpoint into the .npz that pyvf loads."""
    command = f"convert {args.format}"
    module, _, config_class = CONVERTERS[args.format]
    # the name Model.save writes (it appends .npz), passed on ending in .npz
    output = args.output if args.output.endswith(".npz") else args.output + ".npz"
    # every argument checked before the framework is imported and the checkpoint read
    for option, problem in (("checkpoint", _checkpoint_problem(args.format, args.checkpoint)),
                            ("--config", _config_problem(args.config, config_class)),
                            ("-o/--output", file_to_write(output))):
        if problem:
            return fail(command, f"argument {option}: {problem}")
    try:
        n, skipped = module.convert_checkpoint(args.checkpoint, args.config, output)
    except ModuleNotFoundError as e:  # the converter's framework (tensorflow, torch) is not installed
        print(f"pyvf convert: {e}", file=sys.stderr)
        return 1
    except (EOFError, pickle.UnpicklingError) as e:  # torch.load: a pickle cut short or damaged
        return fail(command, f"argument checkpoint: {args.checkpoint!r} is damaged or truncated "
                             f"({type(e).__name__}: {e})")
    except ValueError as e:  # convert or load_official: a weight of --config's model missing or misshapen
        return fail(command, f"argument checkpoint: {args.checkpoint!r} does not hold the model that "
                             f"--config {args.config!r} describes: {e}")
    except OSError as e:  # reading a damaged archive, or writing the output (a full disk)
        return fail(command, f"cannot convert {args.checkpoint!r} into {output!r}: {e}")
    except Exception as e:  # tensorflow's own errors (tf.errors.DataLossError, ...) name what it could not read
        if type(e).__module__.split(".")[0] != "tensorflow":
            raise
        return fail(command, f"argument checkpoint: tensorflow cannot read {args.checkpoint!r}: {e}")
    print(f"wrote {output}: {n} arrays; skipped {len(skipped)} other keys")
    return 0


def _checkpoint_problem(fmt, path):
    """None, or why `path` is no checkpoint of the format: a missing file (or TF prefix), or for
    torch a file of another kind (its first bytes: a torch zip archive holds */data.pkl, the
    legacy format opens with a pickled magic number), which torch.load would meet with a
    RuntimeError that says nothing of the file."""
    if fmt == "tf-transformer":  # a prefix (model, beside model.index and model.data-*) or a folder
        if os.path.isdir(path) or glob.glob(glob.escape(path) + ".*"):
            return None
        return f"no checkpoint at {path!r}: neither a folder nor the prefix of files such as {path}.index"
    if problem := file_to_read(path):
        return problem
    if zipfile.is_zipfile(path):
        with zipfile.ZipFile(path) as z:
            if any(name.endswith("/data.pkl") for name in z.namelist()):
                return None
        return f"{path!r} is a zip archive but not a torch checkpoint (no data.pkl in it; an .npz?)"
    with open(path, "rb") as f:
        if f.read(len(_TORCH_LEGACY_MAGIC)) == _TORCH_LEGACY_MAGIC:
            return None
    return f"{path!r} is not a torch checkpoint, or is truncated (neither a torch zip archive nor its legacy format)"


def _config_problem(path, config_class):
    """None, or why the JSON file `path` is not the fields of a config_class (read as the converters
    read it, then checked by the class itself)."""
    if problem := file_to_read(path):
        return problem
    try:
        with open(path, "rb") as f:
            fields = json.loads(f.read().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        return f"{path!r} is not JSON ({e})"
    if not isinstance(fields, dict):
        return f"{path!r} holds a JSON {type(fields).__name__}, not an object of {config_class.__name__} fields"
    try:
        config_class(**fields)
    except (TypeError, ValueError) as e:  # a field missing or unknown; a value out of range
        return f"{path!r} is not a valid {config_class.__name__}: {e}"
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
