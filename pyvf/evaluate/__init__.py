"""Evaluation: a codebook and transformer pair on held-out SM7 scenes against baselines
(metrics.py, run.py), the training runs' health figures (health.py) and the pictures.
`pyvf.evaluate.evaluate(codebook, transformer, scenes=200)`.
"""

from .run import DECODES, DEFAULT_DECODE, evaluate, render_images

__all__ = ["DECODES", "DEFAULT_DECODE", "evaluate", "render_images"]
