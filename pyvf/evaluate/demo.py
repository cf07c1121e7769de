"""The work of the `pyvf demo` and `pyvf evaluate` commands (their arguments: pyvf/cli/evaluate.py):

    demo(out="pyvf-demo", quick=True)                                           # pyvf demo --quick
    report("evaluate", out="eval", scenes=200, context=(1, 3, 5), seed=1000)   # pyvf evaluate --out eval

Both load the shipped pretrained pair (pyvf.models.load_pretrained) unless files are given, run
evaluate() on held-out scenes and print the tables and timings. The demo's defaults finish in
about two minutes on 2 cores; --quick is a few seconds' smoke run.
"""

import numbers
import os
import sys
import time

from .._machine import kernel_line
from .._threads import set_num_threads
from ..models import load_pretrained
from .run import DEFAULT_DECODE, evaluate, metrics_markdown

__all__ = ["DEMO_SCENES", "DEMO_CONTEXT", "QUICK_SCENES", "QUICK_CONTEXT", "demo", "report"]

DEMO_SCENES = 20  # held-out scenes of the demo
DEMO_CONTEXT = (1, 3, 5)
QUICK_SCENES, QUICK_CONTEXT = 2, (1, 3)


def report(name, *, out, scenes, context, seed, codebook=None, transformer=None, threads=None, progress=True,
           decode=DEFAULT_DECODE, repeat=5):
    """Load the pair, evaluate, print the tables and timings, write `out`. Returns the exit status:
    0, or 1 (printed to stderr) when a model file is missing or does not fit."""
    print(kernel_line(), flush=True)
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
