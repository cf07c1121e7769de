"""`pyvf demo` and `pyvf evaluate`: their arguments; the work is pyvf.evaluate.demo's."""

import os

from ..evaluate import demo as work
from ..evaluate.run import DECODES, DEFAULT_DECODE
from .options import add_threads, context_sizes, fail, folder_to_make, positive_int


def cmd_demo(args):
    """Render novel views and find camera poses of held-out Shepard-Metzler scenes with the
    pretrained models; compare with simple baselines; write the tables and pictures."""
    return _into_folder("demo", args.out, lambda: work.demo(
        args.out, scenes=args.scenes, context=args.context, seed=args.seed, quick=args.quick,
        codebook=args.codebook, transformer=args.transformer, threads=args.threads,
        progress=not args.no_progress, decode=args.decode))


def _into_folder(command, out, run):
    """run() (-> exit status) writing into the folder `out`, created first; a folder made here and
    left empty by a run that failed (a model file missing) is removed again."""
    made = not os.path.lexists(out)
    try:
        if problem := folder_to_make(out):
            return fail(command, f"argument --out: {problem}")
        os.makedirs(out, exist_ok=True)
    except OSError as e:  # a read-only or virtual file system (/proc), no permission
        return fail(command, f"argument --out: cannot create the folder {out!r}: {e.strerror}")
    status = run()
    if status and made and os.path.isdir(out) and not os.listdir(out):
        os.rmdir(out)
    return status


def cmd_evaluate(args):
    """Evaluate a codebook and transformer pair on held-out scenes: metrics.json, metrics.md, pictures."""
    return _into_folder("evaluate", args.out, lambda: work.report(
        "evaluate", out=args.out, scenes=args.scenes, context=args.context, seed=args.seed,
        codebook=args.codebook, transformer=args.transformer, threads=args.threads,
        progress=not args.no_progress, decode=args.decode))


def _common(p):
    p.add_argument("--seed", type=int, default=1000,
                   help="scene seed (default 1000; the training data uses 0, so these scenes are held out)")
    p.add_argument("--codebook", default=None, metavar="FILE",
                   help="a codebook .npz (Codebook.save, e.g. runs/cb/codebook.npz); default: the pretrained one")
    p.add_argument("--transformer", default=None, metavar="FILE",
                   help="a transformer .npz (Transformer.save); default: the pretrained one")
    p.add_argument("--decode", choices=sorted(DECODES), default=DEFAULT_DECODE,
                   help="a rendered token's latent: expected (its mean code vector; default) or argmax (its most "
                        "likely code, as published)")
    add_threads(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def register(subparsers):
    """Add `demo` and `evaluate` to an argparse subparsers object."""
    p = subparsers.add_parser("demo", help="render views and find poses of held-out scenes with the pretrained "
                                           "models, against baselines",
                              description=cmd_demo.__doc__)
    p.add_argument("--out", default="pyvf-demo", metavar="DIR",
                   help="folder for metrics.json, metrics.md, views.png, poses.png (default ./pyvf-demo)")
    p.add_argument("--scenes", type=positive_int, default=None, metavar="N",
                   help=f"held-out scenes (default {work.DEMO_SCENES}; --quick: {work.QUICK_SCENES})")
    p.add_argument("--context", type=context_sizes, default=None, metavar="C[,C...]",
                   help=f"context sizes (default {','.join(map(str, work.DEMO_CONTEXT))}; "
                        f"--quick: {','.join(map(str, work.QUICK_CONTEXT))})")
    p.add_argument("--quick", action="store_true", help="a smoke run: few scenes, one context size")
    _common(p)
    p.set_defaults(func=cmd_demo)

    p = subparsers.add_parser("evaluate", help="evaluate a model pair on held-out scenes: metrics.json, "
                                               "metrics.md and pictures", description=cmd_evaluate.__doc__)
    p.add_argument("--scenes", type=positive_int, default=200, metavar="N", help="held-out scenes (default 200)")
    p.add_argument("--context", type=context_sizes, default=work.DEMO_CONTEXT, metavar="C[,C...]",
                   help="context sizes (default 1,3,5)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for metrics.json, metrics.md and the PNGs")
    _common(p)
    p.set_defaults(func=cmd_evaluate)
    return subparsers
