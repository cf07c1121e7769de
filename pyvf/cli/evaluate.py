"""`pyvf demo` and `pyvf evaluate`: load the shipped pretrained pair (pyvf.models.load_pretrained)
unless files are given, run evaluate() on held-out scenes, print the tables and timings. The demo's
defaults finish in about two minutes on 2 cores; --quick is a few seconds' smoke run."""

import numbers
import os
import sys
import time

from .. import _core
from .._threads import set_num_threads
from ..evaluate.run import DECODES, DEFAULT_DECODE, evaluate, metrics_markdown
from ..models import load_pretrained
from .options import add_threads, context_sizes, fail, folder_to_make, positive_int

DEMO_SCENES = 20  # held-out scenes of the demo
DEMO_CONTEXT = (1, 3, 5)
QUICK_SCENES, QUICK_CONTEXT = 2, (1, 3)


def report(name, *, out, scenes, context, seed, codebook=None, transformer=None, threads=None, progress=True,
           decode=DEFAULT_DECODE, repeat=5):
    """Load the pair, evaluate, print the tables and timings, write `out`. Returns the exit status:
    0, or 1 (printed to stderr) when a model file is missing or does not fit."""
    print(f"pyvf kernels: path {_core.current_path()} (this CPU runs {', '.join(_core.available_paths())}; "
          "PYVF_ISA=<path> forces one; `pyvf config` for details)", flush=True)
    if threads is not None:
        set_num_threads(threads)
    try:
        cb, tf = load_pretrained(codebook, transformer)
    except (ValueError, TypeError, KeyError, OSError) as e:  # missing, no model, or a pair that does not fit
        print(f"pyvf {name}: cannot load the models: {e}", file=sys.stderr)
        return 1
    c, t = cb.config, tf.config
    print(f"codebook: {codebook or 'pretrained (pyvf/models/sm7-codebook.npz)'}: {c.image_size}x{c.image_size} "
          f"images -> {c.token_size}x{c.token_size} tokens of {c.n_embed} codes")
    print(f"transformer: {transformer or 'pretrained (pyvf/models/sm7-transformer.npz)'}: d={t.d_model}, "
          f"{t.n_layer} layers, {t.n_head} heads, trained on up to {t.sequence_size - 1} context views")
    sizes = (context,) if isinstance(context, numbers.Integral) else context
    print(f"evaluating {scenes} held-out scenes (seed {seed}), context {', '.join(map(str, sizes))} ...",
          flush=True)
    t0 = time.perf_counter()
    try:
        metrics = evaluate(cb, tf, scenes=scenes, context=context, seed=seed, out=out, progress=progress,
                           sources={"codebook": codebook or "pretrained", "transformer": transformer or "pretrained"},
                           decode=decode, repeat=repeat)
    except ValueError as e:
        print(f"pyvf {name}: {e}", file=sys.stderr)
        return 1
    print()
    print(metrics_markdown(metrics))
    files = ", ".join(os.path.join(out, f) for f in ("metrics.json", "metrics.md", "views.png", "poses.png"))
    print(f"wrote {files} ({time.perf_counter() - t0:.0f} s)")
    return 0


def demo(out="pyvf-demo", *, scenes=None, context=None, seed=1000, quick=False, codebook=None, transformer=None,
         threads=None, progress=True, decode=DEFAULT_DECODE):
    """`pyvf demo`: report() on DEMO_SCENES held-out scenes at DEMO_CONTEXT (quick: QUICK_SCENES,
    QUICK_CONTEXT, each step timed once), then where to read more. Returns the exit status."""
    scenes = scenes if scenes is not None else (QUICK_SCENES if quick else DEMO_SCENES)
    context = context if context is not None else (QUICK_CONTEXT if quick else DEMO_CONTEXT)
    status = report("demo", out=out, scenes=scenes, context=context, seed=seed, codebook=codebook,
                    transformer=transformer, threads=threads, progress=progress, decode=decode,
                    repeat=1 if quick else 5)
    if status == 0:
        print("\nHow these models were trained, their learning curves and their metrics on 200 held-out "
              "scenes: docs/models.md in the pyvf repository.")
        print("How it works, from pixels to a rendered view, every step run and checked: docs/walkthrough.md "
              "(the same repository).")
    return status


def cmd_demo(args):
    """Render novel views and find camera poses of held-out Shepard-Metzler scenes with the
    pretrained models; compare with simple baselines; write the tables and pictures."""
    return _into_folder("demo", args.out, lambda: demo(
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
    return _into_folder("evaluate", args.out, lambda: report(
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
                   help=f"held-out scenes (default {DEMO_SCENES}; --quick: {QUICK_SCENES})")
    p.add_argument("--context", type=context_sizes, default=None, metavar="C[,C...]",
                   help=f"context sizes (default {','.join(map(str, DEMO_CONTEXT))}; "
                        f"--quick: {','.join(map(str, QUICK_CONTEXT))})")
    p.add_argument("--quick", action="store_true", help="a smoke run: few scenes, one context size")
    _common(p)
    p.set_defaults(func=cmd_demo)

    p = subparsers.add_parser("evaluate", help="evaluate a model pair on held-out scenes: metrics.json, "
                                               "metrics.md and pictures", description=cmd_evaluate.__doc__)
    p.add_argument("--scenes", type=positive_int, default=200, metavar="N", help="held-out scenes (default 200)")
    p.add_argument("--context", type=context_sizes, default=DEMO_CONTEXT, metavar="C[,C...]",
                   help="context sizes (default 1,3,5)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for metrics.json, metrics.md and the PNGs")
    _common(p)
    p.set_defaults(func=cmd_evaluate)
    return subparsers
