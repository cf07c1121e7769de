"""Learning curves from a run folder's log.csv and eval.csv, drawn with Pillow, and a table that
compares runs.

    rows = read_log("runs/codebook")                        # {column: np.ndarray}
    plot_curves("runs/codebook", "curves.png", ["rec_loss", "commitment"])
    plot_eval("runs/codebook")                              # runs/codebook/eval.png: held-out health
    print(runs_table(["runs/a", "runs/b"]))                 # markdown: each run's last evaluation
"""

import csv
import json
import os

import numpy as np

from .._io import atomic_write_png


BASELINE_COLOURS = [(214, 39, 40), (44, 160, 44), (148, 103, 189)]


def read_log(run_dir, name="log.csv"):
    """run_dir/log.csv (or another of its CSV files) -> {column: float64 array}. A torn last line (a
    process killed mid-write) is left out, as a resuming trainer drops it."""
    with open(os.path.join(run_dir, name), newline="", encoding="utf-8") as f:
        header, *rows = csv.reader(f)
    if rows and len(rows[-1]) != len(header):
        rows.pop()  # torn
    table = np.array(rows, dtype=np.float64).reshape(len(rows), len(header))
    return {k: table[:, j] for j, k in enumerate(header)}


def plot_curves(run_dir, png, columns, title=None, log_y=(), size=(360, 220), name="log.csv", baselines=None):
    """Write a PNG of `columns` of run_dir/<name> against the step, one panel each, side by side (log
    axis for the columns of log_y, min and max labelled, the last value in the title). baselines:
    {column: [baseline columns]}, each a dashed line at its mean: a model's curve must cross below."""
    from PIL import Image, ImageDraw

    log = read_log(run_dir, name)
    baselines = baselines or {}
    w, h = size
    top = 24 if title else 0
    img = Image.new("RGB", (w * len(columns), h + top), "white")
    draw = ImageDraw.Draw(img)
    if title:
        draw.text((6, 6), title, fill="black")
    step = log["step"]
    smin, smax = float(step.min()), float(step.max())
    smax = smax if smax > smin else smin + 1.0
    for i, col in enumerate(columns):
        y = log[col]
        lines = np.array([np.nanmean(log[b]) for b in baselines.get(col, ())])  # horizontal baselines
        use_log = col in log_y and (y > 0).all() and (lines > 0).all()
        yv, lv = (np.log10(y), np.log10(lines)) if use_log else (y, lines)
        x0, y0, x1, y1 = i * w + 46, top + 22, (i + 1) * w - 10, top + h - 22  # plot area
        draw.rectangle([x0, y0, x1, y1], outline="gray")
        both = np.concatenate([yv, lv])
        finite = both[np.isfinite(both)]
        lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        hi = hi if hi > lo else lo + 1.0
        lo, hi = lo - 0.04 * (hi - lo), hi + 0.04 * (hi - lo)  # a margin: no line on the frame
        px = x0 + (step - smin) / (smax - smin) * (x1 - x0)
        py = y1 - (yv - lo) / (hi - lo) * (y1 - y0)
        for k, (b, v) in enumerate(zip(baselines.get(col, ()), lv)):
            if not np.isfinite(v):
                continue
            yb = y1 - (v - lo) / (hi - lo) * (y1 - y0)
            colour = BASELINE_COLOURS[k % len(BASELINE_COLOURS)]
            for xa in np.arange(x0, x1, 8.0):  # dashed
                draw.line([(xa, yb), (min(xa + 4, x1), yb)], fill=colour, width=1)
            draw.text((x0 + 4, top + 16 + 11 * (k + 1)), f"-- {b}", fill=colour)
        ok = np.isfinite(py)
        if ok.sum() > 1:
            draw.line(list(zip(px[ok].tolist(), py[ok].tolist())), fill=(31, 119, 180), width=2)
        fmt = (lambda v: f"{10 ** v:.3g}") if use_log else (lambda v: f"{v:.3g}")
        draw.text((i * w + 2, y0 - 4), fmt(hi), fill="black")
        draw.text((i * w + 2, y1 - 8), fmt(lo), fill="black")
        draw.text((x0, y1 + 4), f"{smin:.0f}", fill="black")
        draw.text((x1 - 30, y1 + 4), f"{smax:.0f}", fill="black")
        draw.text((x0 + 4, top + 4), f"{col}{' (log)' if use_log else ''}: last {y[-1]:.4g}", fill="black")
    atomic_write_png(png, img)
    return png


def eval_panels(columns):
    """eval.csv's columns -> (panels, baselines) for plot_curves: the codebook's health, or the
    transformer's figures at its largest evaluated context with their baselines."""
    if "colour_r2" in columns:  # a codebook run (empty_entropy: runs since it was measured)
        return [c for c in ("mae", "psnr", "codes_in_use", "latent_rank", "colour_r2", "empty_entropy")
                if c in columns], {}
    C = max(int(c.rsplit("_c", 1)[1]) for c in columns if c.startswith("mae_c"))
    panels = [f"ce_c{C}", f"token_accuracy_c{C}", f"mae_c{C}", f"position_c{C}", f"orientation_c{C}"]
    baselines = {f"mae_c{C}": [f"nearest_view_mae_c{C}", f"mean_image_mae_c{C}"],
                 f"position_c{C}": [f"closest_image_position_c{C}", f"mean_pose_position_c{C}"],
                 f"orientation_c{C}": [f"closest_image_orientation_c{C}", f"mean_pose_orientation_c{C}"]}
    return panels, baselines


def eval_line(values):
    """One held-out evaluation (column -> value) as a console line: each panel's value, its baselines
    in brackets."""
    panels, baselines = eval_panels(list(values))
    return ", ".join(f"{c} {values[c]:.4g}" + (" [" + ", ".join(f"{b} {values[b]:.4g}" for b in baselines[c]) + "]"
                                               if c in baselines else "") for c in panels)


def plot_eval(run_dir, png=None):
    """Plot run_dir/eval.csv (eval_panels) to png (default run_dir/eval.png); returns its path."""
    log = read_log(run_dir, "eval.csv")
    panels, baselines = eval_panels(list(log))
    png = png or os.path.join(run_dir, "eval.png")
    dashed = " (dashed: baselines)" if baselines else ""  # the codebook's panels have none
    return plot_curves(run_dir, png, panels, title=f"{os.path.basename(os.path.normpath(run_dir))}: held-out "
                       f"evaluation against the step{dashed}", name="eval.csv", baselines=baselines,
                       log_y=[c for c in panels if c == "mae" or c.startswith(("ce_c", "mae_c"))])


def _last_at(steps, step):
    """The index of the last of the ascending steps at or before step (None: the last), or None."""
    k = len(steps) - 1 if step is None else int(np.searchsorted(steps, step, side="right")) - 1
    return k if k >= 0 else None


def runs_table(run_dirs, step=None):
    """Markdown: one row per run folder: its name, steps, wall seconds, what its hyperparameters
    change against the first run's of its kind, and its last held-out evaluation (eval_panels'
    columns of eval.csv); with step, all at or before that step."""
    rows, firsts = [], {}
    for d in run_dirs:
        with open(os.path.join(d, "config.json"), encoding="utf-8") as f:
            cfg = json.load(f)
        flat = {**{f"config.{k}": v for k, v in cfg["config"].items()},
                **{k: v for k, v in cfg["hyperparameters"].items() if k != "data"}}
        first = firsts.setdefault(cfg["kind"], flat)
        changed = ", ".join(f"{k.removeprefix('config.')}={flat.get(k)}" for k in sorted(set(flat) | set(first))
                            if flat.get(k) != first.get(k)) or f"(the first {cfg['kind']} run)"
        log = read_log(d)  # a header alone: a run before its first logged step
        ev = read_log(d, "eval.csv") if os.path.exists(os.path.join(d, "eval.csv")) else {}
        i, j = _last_at(log["step"], step), _last_at(ev["step"], step) if ev else None
        last = {c: f"{ev[c][j]:.4g} ({int(ev['step'][j])})" for c in ev if j is not None}
        panels = eval_panels(list(ev))[0] if ev else []
        rows.append((os.path.basename(os.path.normpath(d)), int(log["step"][i]) if i is not None else 0,
                     float(log["seconds"][i]) if i is not None else 0.0, changed, last, panels))
    cols = list(dict.fromkeys(c for r in rows for c in r[5]))  # the first run's order first
    head = ["run", "steps", "wall (s)", "changes"] + [f"{c} (step)" for c in cols]
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, steps, secs, changed, last, _ in rows:
        vals = [last.get(c, "-") for c in cols]
        out.append("| " + " | ".join([name, str(steps), f"{secs:.0f}", changed] + vals) + " |")
    return "\n".join(out) + "\n"
