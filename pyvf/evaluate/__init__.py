"""Evaluation: a codebook and transformer pair on held-out SM7 scenes against baselines, the
pictures, and the work of the `pyvf demo` / `pyvf evaluate` commands.

    metrics.py   docs/math.md §6 metrics, the baselines, uint8 <-> model image conversions
    run.py       evaluate(): the protocol, the timings of the scene cache, metrics.json / metrics.md
    health.py    the training runs' held-out figures
    pictures.py  views.png (context | truth | codebook | pyvf) and poses.png (cameras from above)
    demo.py      what `pyvf demo` and `pyvf evaluate` do

pyvf exports this package as `pyvf.evaluate`: call `pyvf.evaluate.evaluate(codebook, transformer,
scenes=200, context=(1, 3, 5), out="eval")`.
"""

from .run import DECODES, DEFAULT_DECODE, evaluate, render_images

__all__ = ["DECODES", "DEFAULT_DECODE", "evaluate", "render_images"]
