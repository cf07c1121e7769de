"""Learning curves from a run folder's log.csv, drawn with Pillow (no plotting library needed).

    rows = read_log("runs/codebook")                        # {column: np.ndarray}
    plot_curves("runs/codebook", "curves.png", ["rec_loss", "commitment"])

One panel per column, x = step, y on a linear axis (log axis with log_y=True), min and max
labelled; the last value printed in the panel's title.
"""

import csv
import io
import os

import numpy as np

from .._io import atomic_write_bytes


def read_log(run_dir):
    """run_dir/log.csv -> {column: float64 array}, rows in file order."""
    path = os.path.join(run_dir, "log.csv")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{path} has no rows")
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}


def plot_curves(run_dir, png, columns, title=None, log_y=(), size=(360, 220)):
    """Write a PNG of `columns` of run_dir/log.csv against the step, one panel each, side by side."""
    from PIL import Image, ImageDraw

    log = read_log(run_dir)
    missing = [c for c in columns if c not in log]
    if missing:
        raise ValueError(f"columns {missing} are not in {os.path.join(run_dir, 'log.csv')} (it has {list(log)})")
    w, h = size
    top = 24 if title else 0
    img = Image.new("RGB", (w * len(columns), h + top), "white")
    draw = ImageDraw.Draw(img)
    if title:
        draw.text((6, 6), title, fill="black")
    step = log["step"]
    for i, col in enumerate(columns):
        y = log[col]
        use_log = col in log_y and (y > 0).all()
        yv = np.log10(y) if use_log else y
        x0, y0, x1, y1 = i * w + 46, top + 22, (i + 1) * w - 10, top + h - 22  # plot area
        draw.rectangle([x0, y0, x1, y1], outline="gray")
        lo, hi = float(yv.min()), float(yv.max())
        hi = hi if hi > lo else lo + 1.0
        smin, smax = float(step.min()), float(step.max())
        smax = smax if smax > smin else smin + 1.0
        px = x0 + (step - smin) / (smax - smin) * (x1 - x0)
        py = y1 - (yv - lo) / (hi - lo) * (y1 - y0)
        draw.line(list(zip(px.tolist(), py.tolist())), fill=(31, 119, 180), width=2)
        fmt = (lambda v: f"{10 ** v:.3g}") if use_log else (lambda v: f"{v:.3g}")
        draw.text((i * w + 2, y0 - 4), fmt(hi), fill="black")
        draw.text((i * w + 2, y1 - 8), fmt(lo), fill="black")
        draw.text((x0, y1 + 4), f"{smin:.0f}", fill="black")
        draw.text((x1 - 30, y1 + 4), f"{smax:.0f}", fill="black")
        draw.text((x0 + 4, top + 4), f"{col}{' (log)' if use_log else ''}: last {y[-1]:.4g}", fill="black")
    buf = io.BytesIO()
    img.save(buf, format="PNG")
    atomic_write_bytes(png, buf.getvalue())
    return png
