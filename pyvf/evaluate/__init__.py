"""Evaluation: a codebook and transformer pair on held-out SM7 scenes against baselines, the
pictures, and the work of the `pyvf demo` / `pyvf evaluate` commands.

    from pyvf.evaluate import evaluate
    metrics = evaluate(codebook, transformer, scenes=200, context=(1, 3, 5), out="eval")

    metrics.py   docs/math.md §6 metrics, the baselines, uint8 <-> model image conversions
    run.py       evaluate(): the protocol, the timings of the scene cache, metrics.json / metrics.md
    pictures.py  views.png (context | truth | codebook | pyvf) and poses.png (cameras from above), Pillow
    demo.py      what `pyvf demo` and `pyvf evaluate` do (their arguments: pyvf/cli/evaluate.py)

Note: the function `evaluate` lives in the package `pyvf.evaluate`; re-exporting it from pyvf
under the same name would hide the package attribute, so pyvf exports it as `pyvf.evaluate`
the package (call `pyvf.evaluate.evaluate(...)`).
"""

from .metrics import (
    closest_image_pose,
    image_metrics,
    mean_image,
    mean_pose,
    nearest_view,
    pose_metrics,
    psnr_cap,
    to_model_images,
    to_uint8,
)
from .run import (
    DECODES,
    DEFAULT_DECODE,
    IMAGE_METRICS,
    META_KEYS,
    METHODS,
    POSE_METRICS,
    TIMING_KEYS,
    evaluate,
    metrics_markdown,
    render_images,
    write_metrics,
)

__all__ = [
    "DECODES",
    "DEFAULT_DECODE",
    "IMAGE_METRICS",
    "META_KEYS",
    "METHODS",
    "POSE_METRICS",
    "TIMING_KEYS",
    "closest_image_pose",
    "evaluate",
    "image_metrics",
    "mean_image",
    "mean_pose",
    "metrics_markdown",
    "nearest_view",
    "pose_metrics",
    "psnr_cap",
    "render_images",
    "to_model_images",
    "to_uint8",
    "write_metrics",
]
