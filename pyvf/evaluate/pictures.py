"""The evaluation's two pictures, drawn with Pillow (no plotting library).

    save_views("views.png", picture)   # a row per scene: context | ground truth | codebook | pyvf
    save_poses("poses.png", picture)   # a panel per scene: the cameras seen from above

`picture` is what evaluate() keeps of its first P scenes at the largest context C: context
(P, C, S, S, 3) uint8, context_poses (P, C, 7), truth, codebook, pyvf (P, S, S, 3) uint8 (the
first query view), query_poses and estimated_poses (P, M, 7), and C.
"""

import numpy as np

from .._io import atomic_write_png

__all__ = ["save_views", "save_poses"]

_WHITE, _BLACK, _GREY = (255, 255, 255), (0, 0, 0), (190, 190, 190)
_CONTEXT, _TRUTH, _ESTIMATE = (40, 90, 220), (20, 150, 40), (220, 30, 30)
_GAP, _GROUP_GAP, _LABEL_W, _HEAD_H = 4, 14, 64, 18


def save_views(path, picture):
    """The views sheet, a row per scene: context | ground truth | codebook | pyvf, as a PNG."""
    from PIL import Image, ImageDraw, ImageFont  # a dependency of pyvf; imported when a picture is drawn

    font = ImageFont.load_default()
    ctx = picture["context"]  # (P, C, S, S, 3)
    P, C, S = ctx.shape[0], ctx.shape[1], ctx.shape[2]
    scale = max(2, 128 // S)
    T = S * scale  # tile side in pixels
    columns = [(f"context {i + 1}", ctx[:, i]) for i in range(C)]
    columns += [("ground truth", picture["truth"]), ("codebook", picture["codebook"]), ("pyvf", picture["pyvf"])]
    # a wider gap between the context's columns and the query's
    xs = [_LABEL_W + j * (T + _GAP) + (_GROUP_GAP if j >= C else 0) for j in range(len(columns))]
    caption = ("codebook: the ground truth encoded and decoded (the best a rendering can be).",
               f"pyvf: rendered from the {C} context views and the query's pose.")
    sheet = Image.new("RGB", (max(xs[-1] + T + _GAP, 500), _HEAD_H + P * (T + _GAP) + 32), _WHITE)
    draw = ImageDraw.Draw(sheet)
    for (label, tiles), x in zip(columns, xs):
        draw.text((x + (T - draw.textlength(label, font=font)) / 2, 3), label, fill=_BLACK, font=font)  # centred
        for r in range(P):
            tile = np.repeat(np.repeat(tiles[r], scale, axis=0), scale, axis=1)  # (T, T, 3), nearest
            sheet.paste(Image.fromarray(np.ascontiguousarray(tile)), (x, _HEAD_H + r * (T + _GAP)))
    for r in range(P):
        draw.text((6, _HEAD_H + r * (T + _GAP) + T // 2 - 6), f"scene {r}", fill=_BLACK, font=font)
    for i, line in enumerate(caption):
        draw.text((6, _HEAD_H + P * (T + _GAP) + 2 + 14 * i), line, fill=_BLACK, font=font)
    atomic_write_png(path, sheet)


def save_poses(path, picture, panel=280):
    """The camera panels, one per scene, seen from above, as a PNG."""
    from PIL import Image, ImageDraw, ImageFont

    font = ImageFont.load_default()
    ctx, truth, est = picture["context_poses"], picture["query_poses"], picture["estimated_poses"]
    P = ctx.shape[0]
    legend = (("context cameras", _CONTEXT), ("true query cameras", _TRUTH),
              ("estimated query cameras (line: from the truth)", _ESTIMATE), ("seen from above: x right, z up", None))
    head, foot = 30, 8 + 14 * len(legend)
    sheet = Image.new("RGB", (max(P * (panel + _GAP) + _GAP, 300), head + panel + foot), _WHITE)
    draw = ImageDraw.Draw(sheet)
    for s in range(P):
        x0 = _GAP + s * (panel + _GAP)
        pts = np.concatenate([ctx[s], truth[s], est[s]])[:, [0, 2]]  # (K, 2) x and z
        R = max(float(np.abs(pts).max()) * 1.1, 1e-9)
        half = panel / 2

        def px(p, x0=x0, R=R, half=half):  # world (x, y, z, ...) -> panel pixel: x right, z up
            return (x0 + half + p[0] / R * (half - 8), head + half - p[2] / R * (half - 8))

        draw.rectangle([x0, head, x0 + panel - 1, head + panel - 1], outline=_GREY)
        cx, cy = px((0.0, 0.0, 0.0))
        draw.line([cx - 4, cy, cx + 4, cy], fill=_BLACK)  # the object at the origin
        draw.line([cx, cy - 4, cx, cy + 4], fill=_BLACK)
        for p in ctx[s]:
            x, y = px(p)
            draw.ellipse([x - 4, y - 4, x + 4, y + 4], fill=_CONTEXT)
        for p, q in zip(truth[s], est[s]):
            (x, y), (u, v) = px(p), px(q)
            draw.line([x, y, u, v], fill=_ESTIMATE)
            draw.ellipse([x - 4, y - 4, x + 4, y + 4], fill=_TRUTH)
            draw.line([u - 4, v - 4, u + 4, v + 4], fill=_ESTIMATE, width=2)
            draw.line([u - 4, v + 4, u + 4, v - 4], fill=_ESTIMATE, width=2)
        err = np.median(np.linalg.norm(est[s][:, :3] - truth[s][:, :3], axis=-1))
        draw.text((x0 + 2, 2), f"scene {s}, context {picture['C']}", fill=_BLACK, font=font)
        draw.text((x0 + 2, 15), f"median position error {err:.2f}", fill=_BLACK, font=font)
    for i, (label, colour) in enumerate(legend):
        y = head + panel + 5 + 14 * i
        if colour is not None:
            draw.ellipse([_GAP, y + 2, _GAP + 8, y + 10], fill=colour)
        draw.text((_GAP + 14, y), label, fill=_BLACK, font=font)
    atomic_write_png(path, sheet)
