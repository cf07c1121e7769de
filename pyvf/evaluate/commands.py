"""The `pyvf demo` and `pyvf evaluate` commands: argument parsing, then report() does the work.

    pyvf demo [--out DIR] [--scenes N] [--context C[,C...]] [--seed S] [--quick]
              [--codebook FILE --transformer FILE] [--threads T]
    pyvf evaluate --scenes N --context C[,C...] --seed S --out DIR [--codebook FILE --transformer FILE]

Both load the shipped pretrained pair (pyvf.models.load_pretrained) unless files are given,
run evaluate() on held-out scenes and print the tables and timings. The demo's defaults are
sized to finish in about two minutes on 2 cores; --quick is a few seconds' smoke run.
A model file given on the command line that is missing prints what is missing and exits with
status 1. While the package ships no pretrained pair, `pyvf demo` without files says so, prints
how to train one, and runs the branching attention demo instead (exit 0).
"""

import argparse
import os
import sys
import time

from ..models import PRETRAINED, TRAIN_HINT, load_pretrained, pretrained_path
from .run import evaluate, metrics_markdown

__all__ = ["DEMO_SCENES", "QUICK_SCENES", "MODEL_CARD", "WALKTHROUGH", "cli_register", "cmd_demo", "cmd_evaluate",
           "kernel_line", "report"]

DEMO_SCENES = 20  # held-out scenes of the demo (measured wall time in README/the report)
DEMO_CONTEXT = (1, 3, 5)
QUICK_SCENES, QUICK_CONTEXT = 2, (1, 3)
MODEL_CARD = "docs/models.md"  # the shipped models: training, curves, held-out metrics
WALKTHROUGH = "docs/walkthrough.md"  # every step from pixels to a rendered view, explained and checked


def kernel_line():
    """The line every pyvf demo starts with: which instruction-set path the C++ kernels run."""
    import pyvf  # at call time: pyvf imports this package

    return (f"pyvf kernels: path {pyvf.kernel_path()} (this CPU runs {', '.join(pyvf.kernel_paths())}; "
            "PYVF_ISA=<path> forces one; `pyvf config` for details)")


def report(name, *, out, scenes, context, seed, codebook=None, transformer=None, threads=None, progress=True):
    """Load the pair, evaluate, print the tables and timings, write `out`. Returns the exit status:
    0, or 1 (printed to stderr) when a model file is missing or does not fit."""
    import pyvf

    print(kernel_line(), flush=True)
    if threads is not None:
        pyvf.set_num_threads(threads)
    try:
        cb, tf = load_pretrained(codebook, transformer)
    except FileNotFoundError as e:
        print(f"pyvf {name}: {e}", file=sys.stderr)
        return 1
    except (ValueError, TypeError, KeyError, OSError) as e:  # a file that is no model, or a pair that does not fit
        print(f"pyvf {name}: cannot load the models: {e}", file=sys.stderr)
        return 1
    c, t = cb.config, tf.config
    print(f"codebook: {codebook or 'pretrained (pyvf/models/sm7-codebook.npz)'}: {c.image_size}x{c.image_size} "
          f"images -> {c.token_size}x{c.token_size} tokens of {c.n_embed} codes")
    print(f"transformer: {transformer or 'pretrained (pyvf/models/sm7-transformer.npz)'}: d={t.d_model}, "
          f"{t.n_layer} layers, {t.n_head} heads, trained on up to {t.sequence_size - 1} context views")
    print(f"evaluating {scenes} held-out scenes (seed {seed}), context {', '.join(map(str, context))} ...",
          flush=True)
    t0 = time.perf_counter()
    try:
        metrics = evaluate(cb, tf, scenes=scenes, context=context, seed=seed, out=out, progress=progress,
                           sources={"codebook": codebook or "pretrained", "transformer": transformer or "pretrained"})
    except ValueError as e:
        print(f"pyvf {name}: {e}", file=sys.stderr)
        return 1
    print()
    print(metrics_markdown(metrics))
    files = ", ".join(os.path.join(out, f) for f in ("metrics.json", "metrics.md", "views.png", "poses.png"))
    print(f"wrote {files} ({time.perf_counter() - t0:.0f} s)")
    return 0


def cmd_demo(args):
    """Render novel views and find camera poses of held-out Shepard-Metzler scenes with the
    pretrained models; compare with simple baselines; write the tables and pictures."""
    scenes = args.scenes if args.scenes is not None else (QUICK_SCENES if args.quick else DEMO_SCENES)
    context = args.context if args.context is not None else (QUICK_CONTEXT if args.quick else DEMO_CONTEXT)
    if args.codebook is None and args.transformer is None and not shipped():
        return _demo_without_models(args)
    status = report("demo", out=args.out, scenes=scenes, context=context, seed=args.seed, codebook=args.codebook,
                    transformer=args.transformer, threads=args.threads, progress=not args.no_progress)
    if status == 0:
        print(f"\nHow these models were trained, their learning curves and their metrics on 200 held-out "
              f"scenes: {MODEL_CARD} in the pyvf repository.")
        print(f"How it works, from pixels to a rendered view, every step run and checked: {WALKTHROUGH} "
              f"(the same repository).")
    return status


def shipped():
    """True when both pretrained files are in the package."""
    return all(os.path.exists(pretrained_path(kind)) for kind in PRETRAINED)


def _demo_without_models(args):
    """The package has no trained pair yet (they are being trained; docs/models.md): say so
    plainly, then run what pyvf can already show, branching attention against the dense
    reference, so that the main job still checks the kernels end to end."""
    from ..bench.attention import demo as attention_demo

    print(kernel_line(), flush=True)
    missing = [pretrained_path(kind) for kind in PRETRAINED if not os.path.exists(pretrained_path(kind))]
    print("pyvf demo: the pretrained SM7 models are not in this package yet (missing: "
          + ", ".join(os.path.basename(m) for m in missing) + "), so no views are rendered.\n"
          + TRAIN_HINT + "Meanwhile, the branching attention kernel against the dense float64 reference:", flush=True)
    return attention_demo(sizes=("small", "medium") if args.quick else ("small", "medium", "paper"),
                          threads=args.threads, kernel_line=False)


def cmd_evaluate(args):
    """Evaluate a codebook and transformer pair on held-out scenes: metrics.json, metrics.md, pictures."""
    return report("evaluate", out=args.out, scenes=args.scenes, context=args.context, seed=args.seed,
                  codebook=args.codebook, transformer=args.transformer, threads=args.threads,
                  progress=not args.no_progress)


def _context_sizes(text):
    try:
        sizes = tuple(int(s) for s in text.split(",") if s.strip())
    except ValueError:
        sizes = ()
    if not sizes or min(sizes) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers separated by commas, e.g. 1,3,5; got {text!r}")
    return sizes


def _positive(text):
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def _common(p):
    p.add_argument("--seed", type=int, default=1000,
                   help="scene seed (default 1000; the training data uses 0, so these scenes are held out)")
    p.add_argument("--codebook", default=None, metavar="FILE",
                   help="a codebook .npz (Codebook.save, e.g. runs/cb/codebook.npz); default: the pretrained one")
    p.add_argument("--transformer", default=None, metavar="FILE",
                   help="a transformer .npz (Transformer.save); default: the pretrained one")
    p.add_argument("--threads", type=_positive, default=None, help="threads for pyvf's C++ kernels")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def cli_register(subparsers):
    """Add `demo` and `evaluate` to an argparse subparsers object."""
    p = subparsers.add_parser("demo", help="render views and find poses of held-out scenes with the pretrained "
                                           "models, against baselines (~2 minutes; --quick: seconds)",
                              description=cmd_demo.__doc__)
    p.add_argument("--out", default="pyvf-demo", metavar="DIR",
                   help="folder for metrics.json, metrics.md, views.png, poses.png (default ./pyvf-demo)")
    p.add_argument("--scenes", type=_positive, default=None, metavar="N",
                   help=f"held-out scenes (default {DEMO_SCENES}; --quick: {QUICK_SCENES})")
    p.add_argument("--context", type=_context_sizes, default=None, metavar="C[,C...]",
                   help=f"context sizes (default {','.join(map(str, DEMO_CONTEXT))}; "
                        f"--quick: {','.join(map(str, QUICK_CONTEXT))})")
    p.add_argument("--quick", action="store_true", help="a smoke run of a few seconds")
    _common(p)
    p.set_defaults(func=cmd_demo)

    p = subparsers.add_parser("evaluate", help="evaluate a model pair on held-out scenes: metrics.json, "
                                               "metrics.md and pictures", description=cmd_evaluate.__doc__)
    p.add_argument("--scenes", type=_positive, default=200, metavar="N", help="held-out scenes (default 200)")
    p.add_argument("--context", type=_context_sizes, default=DEMO_CONTEXT, metavar="C[,C...]",
                   help="context sizes (default 1,3,5)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for metrics.json, metrics.md and the PNGs")
    _common(p)
    p.set_defaults(func=cmd_evaluate)
    return subparsers
