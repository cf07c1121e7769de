"""Evaluation: a codebook and transformer pair on held-out SM7 scenes against baselines, the
pictures, and the work of the `pyvf demo` / `pyvf evaluate` commands.

    from pyvf.evaluate import evaluate
    metrics = evaluate(codebook, transformer, scenes=200, context=(1, 3, 5), out="eval")

    metrics.py   docs/math.md §6 metrics, the baselines, uint8 <-> model image conversions
    run.py       evaluate(): the protocol, the timings of the scene cache, metrics.json / metrics.md
    health.py    the training runs' held-out figures
    pictures.py  views.png (context | truth | codebook | pyvf) and poses.png (cameras from above)
    demo.py      what `pyvf demo` and `pyvf evaluate` do

pyvf exports this package as `pyvf.evaluate` (call `pyvf.evaluate.evaluate(...)`): a function of
the same name there would hide the package.
"""

from .metrics import closest_image_pose, image_metrics, mean_image, mean_pose, nearest_view, pose_metrics
from .run import DECODES, DEFAULT_DECODE, METHODS, evaluate, metrics_markdown, render_images, write_metrics

__all__ = ["DECODES", "DEFAULT_DECODE", "METHODS", "closest_image_pose", "evaluate", "image_metrics", "mean_image",
           "mean_pose", "metrics_markdown", "nearest_view", "pose_metrics", "render_images", "write_metrics"]
