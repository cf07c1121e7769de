"""evaluate(): a codebook and a transformer on held-out SM7 scenes, against four baselines.

    metrics = evaluate(codebook, transformer, scenes=200, context=(1, 3, 5), seed=1000, out="eval")

The protocol (the metrics: metrics.py, docs/math.md §6): scenes generate_scenes(seed, scenes) (the
training data uses seed 0, so seed 1000 gives scenes the models never saw). For each scene and
context size C the context is views 0..C-1, the queries the last QUERIES views, the same for every
C. The transformer encodes the context once per (batch, C) (the scene cache of docs/math.md §3),
renders and localizes every query. Methods: `pyvf`, `codebook` (the ground truth encoded and
decoded: the best a rendering through this codebook can be), the baselines `nearest_view`,
`mean_image`, `closest_image_pose`, `mean_pose`. Image metrics and token scores are means over the
queries, pose metrics medians. The result, also out/metrics.json:

    {"context": {"C": {method: {metric: value}}},      # C as a string: "1", "3", "5"
     "timing":  {"render_cached_one_s_per_view": seconds, ...},   # _timing: cached vs re-encoding render
     "meta":    {"seed": 1000, "scenes": 200, ...}}
"""

import dataclasses
import json
import os
import time

import numpy as np

from .._io import atomic_write_text
from .. import _checks, _core
from .._machine import median_time
from .._threads import num_threads
from .._version import __version__
from ..models import check_pair
from ..nn.layers import matmul
from ..scenes import generate_scenes
from .metrics import (QUERIES, closest_image_pose, empty_entropy, empty_patches, encode_images, image_metrics,
                      mean_image, mean_pose, nearest_view, pose_metrics, psnr_cap, to_uint8)

__all__ = ["IMAGE_METRICS", "POSE_METRICS", "METHODS", "PAPER_SM7", "DECODES", "DEFAULT_DECODE",
           "evaluate", "metrics_markdown", "paper_line", "render_images", "verdict_lines",
           "write_metrics"]

IMAGE_METRICS = ("mae", "rmse", "psnr")
POSE_METRICS = ("position_error_median", "orientation_error_median_deg")
# pyvf's token figures: over all query tokens, and split into the tokens of empty patches (every
# pixel background: metrics.empty_patches) and of object patches
TOKEN_SCORES = ("ce", "token_accuracy", "ce_empty", "ce_object", "token_accuracy_empty", "token_accuracy_object")
# method -> the metrics it has, in the tables' order
METHODS = {"pyvf": IMAGE_METRICS + POSE_METRICS, "codebook": IMAGE_METRICS, "nearest_view": IMAGE_METRICS,
           "mean_image": IMAGE_METRICS, "closest_image_pose": POSE_METRICS, "mean_pose": POSE_METRICS}
SM7_VIEWS = 15
PICTURE_SCENES = 4  # scenes drawn in views.png and poses.png
# how render_images turns a view's logits (L, K) into the codebook's input (docs/math.md §6)
DECODES = {"argmax": "each token's most likely code",  # the published generation
           "expected": "each token's mean code vector under the softmax of its logits"}  # least squared error
# The default: a small model is unsure of most tokens of a novel view, and argmax commits each
# token to its own guess, while the mean code vector scores lower MAE and RMSE (docs/models.md
# evaluates the shipped pair both ways). "argmax" compares with the paper or another port.
DEFAULT_DECODE = "expected"


def render_images(codebook, logits, decode="argmax", batch=32):
    """A transformer's rendered logits (..., L, K) (L = token_size**2 tokens over K = n_embed codes,
    e.g. render_scene's (B, M, L, K)) -> uint8 images (..., S, S, 3) through the codebook, `batch`
    views per decoder call. decode (DECODES): "argmax" decodes each token's most likely code;
    "expected" each token's mean code vector sum_j softmax(logits)_j e_j (softmax in float64)."""
    if decode not in DECODES:
        raise ValueError(f"decode must be one of {sorted(DECODES)}, got {decode!r}")
    k, K = codebook.config.token_size, codebook.config.n_embed
    _checks.float_array("logits", logits)
    if logits.shape[-2:] != (k * k, K):
        raise ValueError(f"logits must have shape (..., {k * k}, {K}) for this codebook, got {logits.shape}")
    _checks.finite("logits", logits)  # argmax would pick a NaN's index silently
    flat = logits.reshape(-1, k * k, K)  # (n, L, K)
    out = _decode(codebook, flat.argmax(axis=-1) if decode == "argmax" else flat, batch)  # (n, S, S, 3)
    return out.reshape(*logits.shape[:-2], *out.shape[1:])  # (..., S, S, 3); no -1: the lead may hold a 0


def _decode(codebook, inputs, batch):
    """codes (n, L) ints, or logits (n, L, K) decoded by their expected code vectors -> uint8
    images (n, S, S, 3), `batch` per decoder call."""
    k, S = codebook.config.token_size, codebook.config.image_size
    E = codebook.quantizer.embeddings.astype(np.float64)  # (D, K): the codes are columns
    out = np.empty((inputs.shape[0], S, S, codebook.config.out_ch), np.uint8)
    for i in range(0, inputs.shape[0], batch):
        x = inputs[i:i + batch]
        if x.ndim == 2:
            images = codebook.decode_code(x.reshape(-1, k, k).astype(np.int64))
        else:
            p = x.astype(np.float64)
            p = np.exp(p - p.max(axis=-1, keepdims=True))
            p /= p.sum(axis=-1, keepdims=True)  # (b, L, K) softmax
            z = matmul(p.reshape(-1, E.shape[1]), E, tb=True)  # (b*L, D) = p @ E^T
            z = z.reshape(-1, k, k, E.shape[0]).transpose(0, 3, 1, 2)  # (b, D, k, k)
            images = codebook.decode_latent(np.ascontiguousarray(z, dtype=codebook.dtype))
        out[i:i + batch] = to_uint8(images)
    return out


def evaluate(codebook, transformer, *, scenes=200, context=(1, 3, 5), seed=1000, batch=8, out=None,
             timing_scenes=4, repeat=5, progress=True, sources=None, decode=DEFAULT_DECODE):
    """Score the pair on `scenes` held-out scenes for every context size; return the metrics dict
    (module docstring). batch: scenes per transformer call. out: a folder for metrics.json,
    metrics.md, views.png and poses.png (the first PICTURE_SCENES scenes at the largest C).
    sources: JSON-able, where the models came from, kept as meta["sources"]. decode: a key of
    DECODES (render_images)."""
    t_start = time.perf_counter()
    check_pair(codebook, transformer)
    for name, v in (("scenes", scenes), ("batch", batch), ("timing_scenes", timing_scenes), ("repeat", repeat)):
        _checks.positive_integer(name, v)
    context = (context,) if np.ndim(context) == 0 else context
    context = tuple(sorted({_checks.positive_integer("context", c) for c in context}))  # 2.7 is not 2
    if not context or context[-1] + QUERIES > SM7_VIEWS:
        raise ValueError(f"context must name sizes of at most {SM7_VIEWS - QUERIES} ({QUERIES} queries of "
                         f"{SM7_VIEWS} views per scene), got {context}")
    if decode not in DECODES:
        raise ValueError(f"decode must be one of {sorted(DECODES)}, got {decode!r}")
    cb_cfg, tf_cfg = codebook.config, transformer.config
    n, S, Cmax = scenes, cb_cfg.image_size, context[-1]
    qidx = np.arange(SM7_VIEWS - QUERIES, SM7_VIEWS)  # (M,) the query views
    used = np.concatenate([np.arange(Cmax), qidx])  # the views any method looks at
    images, poses = generate_scenes(seed, n, size=S)  # (n, V, S, S, 3), (n, V, 7)

    tokens = np.zeros((n, SM7_VIEWS, tf_cfg.token_image_size ** 2), np.int64)  # (n, V, L); unused views stay 0
    flat = np.ascontiguousarray(images[:, used]).reshape(-1, S, S, 3)
    tokens[:, used] = encode_images(codebook, flat, 4 * batch).reshape(n, len(used), -1)
    results, picture = score_scenes(codebook, transformer, images, poses, tokens, context, qidx, batch,
                                    progress=progress, decode=decode)
    for table in results.values():  # None, not NaN, where the queries have no patch of that kind
        for row, keys in ((table["pyvf"], TOKEN_SCORES[2:]), (table["codebook"], ("empty_entropy",))):
            row.update({k: None for k in keys if np.isnan(row[k])})

    timing = _timing(transformer, tokens[:timing_scenes], poses[:timing_scenes], Cmax, qidx, repeat)
    timing["total_s"] = time.perf_counter() - t_start  # the whole evaluate() call
    meta = {
        "pyvf_version": __version__, "seed": int(seed), "scenes": int(n), "views": SM7_VIEWS,
        "image_size": int(S), "context_sizes": list(context), "query_views": [int(i) for i in qidx],
        "n_queries": int(n * QUERIES),  # the images (and poses) each number is taken over
        "trained_context": tf_cfg.sequence_size - 1,  # larger C were never trained on
        "psnr_cap_db": psnr_cap((S, S, 3)), "decode": decode, "kernel_path": _core.current_path(),
        "kernel_threads": num_threads(), "codebook": dataclasses.asdict(cb_cfg),
        "transformer": dataclasses.asdict(tf_cfg),
        "sources": sources,  # where the models came from, as the caller said
    }
    # through JSON once: the dict returned is the file's content (tuples become lists), and a
    # NaN or inf anywhere raises here instead of writing a file that strict readers reject
    metrics = json.loads(json.dumps({"context": results, "timing": timing, "meta": meta}, allow_nan=False))
    if out is not None:
        write_metrics(metrics, out)
        from .pictures import save_poses, save_views  # Pillow, only when pictures are written
        save_views(os.path.join(out, "views.png"), picture)
        save_poses(os.path.join(out, "poses.png"), picture)
    return metrics


def score_scenes(codebook, transformer, images, poses, tokens, context, qidx, batch, *, progress=False,
                 decode=DEFAULT_DECODE):
    """Score the pair and the baselines: for each C in context (ascending), the context is views
    0..C-1 and the queries the views qidx. images uint8 (n, V, S, S, 3), poses (n, V, 7) float64,
    tokens (n, V, L) int64 (the codebook's, of at least the views used) -> (results, picture):
    results[str(C)][method][metric] as evaluate()'s, pyvf's row with TOKEN_SCORES, the codebook's
    with empty_entropy (of the queries' codes); picture for pictures.py."""
    n, M, S = images.shape[0], len(qidx), images.shape[2]
    dt, Cmax, P = transformer.dtype, context[-1], PICTURE_SCENES
    gt, gt_pose = images[:, qidx], poses[:, qidx]  # (n, M, S, S, 3), (n, M, 7) float64
    side = transformer.config.token_image_size
    empty = empty_patches(gt, side).reshape(n, M, side * side)  # (n, M, L)
    per = {str(C): {m: {} for m in METHODS} for C in context}  # C -> method -> metric -> per-query list

    def add(C, method, values):
        for key, v in values.items():
            per[C][method].setdefault(key, []).append(np.asarray(v).reshape(-1))

    # the codebook's reconstruction of the ground truth: independent of C
    recon = _decode(codebook, tokens[:, qidx].reshape(n * M, -1), 4 * batch).reshape(n, M, S, S, 3)
    rec_scores = image_metrics(recon, gt)
    picture = {"context": images[:P, :Cmax], "context_poses": poses[:P, :Cmax], "truth": gt[:P, 0],
               "codebook": recon[:P, 0], "query_poses": gt_pose[:P], "C": Cmax, "pyvf": [], "estimated_poses": []}
    starts = range(0, n, batch)
    if progress:
        from tqdm.auto import tqdm
        starts = tqdm(starts, desc="evaluate", unit="batch")
    for b0 in starts:
        sl = slice(b0, min(b0 + batch, n))
        q_tok = tokens[sl][:, qidx]  # (B, M, L)
        q_pose = poses[sl][:, qidx].astype(dt)  # (B, M, 7)
        truth, truth_pose = gt[sl], gt_pose[sl]
        for C in context:
            key = str(C)
            ctx_img, ctx_pose = images[sl, :C], poses[sl, :C]  # (B, C, S, S, 3), (B, C, 7)
            scene = transformer.encode_scene(tokens[sl, :C], ctx_pose.astype(dt))
            logits = transformer.render_scene(scene, q_pose)  # (B, M, L, V)
            add(key, "pyvf", _token_scores(logits, q_tok, empty[sl]))
            rendered = render_images(codebook, logits, decode, 4 * batch)  # (B, M, S, S, 3)
            est = transformer.localize_scene(scene, q_tok).astype(np.float64)  # (B, M, 7)
            add(key, "pyvf", image_metrics(rendered, truth))
            add(key, "pyvf", pose_metrics(est, truth_pose))
            add(key, "codebook", {m: rec_scores[m][sl] for m in IMAGE_METRICS})
            add(key, "nearest_view", image_metrics(nearest_view(ctx_img, ctx_pose, truth_pose), truth))
            add(key, "mean_image", image_metrics(np.repeat(mean_image(ctx_img)[:, None], M, axis=1), truth))
            add(key, "closest_image_pose", pose_metrics(closest_image_pose(ctx_img, ctx_pose, truth), truth_pose))
            add(key, "mean_pose", pose_metrics(np.repeat(mean_pose(ctx_pose)[:, None], M, axis=1), truth_pose))
            if C == Cmax and sl.start < P:
                picture["pyvf"].append(rendered[:P - sl.start, 0])
                picture["estimated_poses"].append(est[:P - sl.start])

    picture["pyvf"], picture["estimated_poses"] = (np.concatenate(picture[k]) for k in ("pyvf", "estimated_poses"))
    results = _summaries(per)
    for C in map(str, context):
        results[C]["codebook"]["empty_entropy"] = empty_entropy(tokens[:, qidx].reshape(n * M, side, side),
                                                                empty.reshape(n * M, side, side))
    return results, picture


def _summaries(per):
    """score_scenes' per-query values (C -> method -> metric -> list of arrays) -> C -> method ->
    metric: the mean of the image metrics and token scores (nan where no token was of that kind),
    the median of the pose errors."""
    results = {}
    for C in per:
        results[C] = {}
        for method, names in METHODS.items():
            vals = {k: np.concatenate(v) for k, v in per[C][method].items()}  # per query (n*M,)
            row = {}
            for name in names + (TOKEN_SCORES if method == "pyvf" else ()):
                if name in POSE_METRICS:
                    row[name] = float(np.median(vals[name.replace("_median", "")]))
                else:
                    row[name] = float(np.mean(vals[name])) if vals[name].size else float("nan")
            results[C][method] = row
    return results


def _token_scores(logits, tokens, empty):
    """logits (B, M, L, V), true tokens (B, M, L), empty (B, M, L) bool -> per view: the mean
    cross-entropy of the true tokens (log-softmax in float64) and the share of tokens whose argmax
    is right, each (B, M); and per token of empty (of object) patches the same, each (n_empty,)."""
    z = logits.astype(np.float64)
    z -= z.max(axis=-1, keepdims=True)
    logp = z - np.log(np.exp(z).sum(axis=-1, keepdims=True))  # (B, M, L, V)
    nll = -np.take_along_axis(logp, tokens[..., None], axis=-1)[..., 0]  # (B, M, L)
    right = logits.argmax(axis=-1) == tokens  # (B, M, L)
    return {"ce": nll.mean(axis=-1), "token_accuracy": right.mean(axis=-1), "ce_empty": nll[empty],
            "ce_object": nll[~empty], "token_accuracy_empty": right[empty], "token_accuracy_object": right[~empty]}


def _timing(transformer, tokens, poses, C, qidx, repeat):
    """Seconds per view, the fastest of `repeat` calls after a warm-up (other processes only ever
    add time), of the cached and the re-encoding render, one query per scene per call on both (as
    a server answers queries that arrive apart). tokens (B, V, L), poses (B, V, 7) float64."""
    dt, B = transformer.dtype, tokens.shape[0]
    ctx_tok, ctx_pose = tokens[:, :C], poses[:, :C].astype(dt)  # (B, C, L), (B, C, 7)
    q_pose = poses[:, qidx[:1]].astype(dt)  # (B, 1, 7): the first query

    def timed(fn):
        return min(median_time(fn, repeat=repeat, warmup=1)[1])

    t_scene = timed(lambda: transformer.encode_scene(ctx_tok, ctx_pose))
    scene = transformer.encode_scene(ctx_tok, ctx_pose)
    t_render = timed(lambda: transformer.render_scene(scene, q_pose)) / B
    t_reencode = timed(lambda: transformer.render(ctx_tok, ctx_pose, q_pose)) / B
    return {"context": int(C), "scenes": int(B), "repeat": int(repeat),  # what was timed
            "encode_scene_s_per_scene": t_scene / B,  # the trunk over the context, once per scene
            "render_cached_one_s_per_view": t_render, "render_reencode_s_per_view": t_reencode,
            "speedup_vs_reencode": t_reencode / t_render}


# the report
_HEAD = {"mae": "MAE", "rmse": "RMSE", "psnr": "PSNR (dB)", "position_error_median": "position error (median)",
         "orientation_error_median_deg": "orientation error (median, deg)"}
_ALL = IMAGE_METRICS + POSE_METRICS


def _fmt(v, digits=2):
    return "—" if v is None else f"{v:.{digits}f}"


# The paper's SM7 figures (its Table on SM7; 64x64 images, context 3, 1000 scenes), from models
# trained for hundreds of GPU-hours: where the direction past the baselines leads.
PAPER_SM7 = {"mae": 1.61, "rmse": 7.02, "position_error_median": 0.21, "orientation_error_median_deg": 3.48}
# each baseline and the metrics it is judged on (lower is better for all of them)
VERDICTS = {"nearest_view": ("mae", "rmse"), "mean_image": ("mae", "rmse"),
            "closest_image_pose": ("position_error_median", "orientation_error_median_deg"),
            "mean_pose": ("position_error_median", "orientation_error_median_deg")}
_SHORT = {"mae": "MAE", "rmse": "RMSE", "position_error_median": "position",
          "orientation_error_median_deg": "orientation (deg)"}


def _against(me, other, names):
    """pyvf's row against a baseline's on the metrics it is judged on (lower is better; a tie is
    no win) -> (the figures beaten, the figures not beaten, "MAE 2.00 vs 3.00, ...")."""
    won = [m for m in names if me[m] < other[m]]
    pairs = ", ".join(f"{_SHORT[m]} {_fmt(me[m])} vs {_fmt(other[m])}" for m in names)
    return won, [m for m in names if m not in won], pairs


def verdict_lines(metrics, context=None):
    """One line per baseline at one context (None: the largest evaluated): pyvf's figures beside the
    baseline's, and whether pyvf beats it on all of them. -> list of str."""
    C = max(metrics["context"], key=int) if context is None else str(context)
    table = metrics["context"][C]
    lines = [f"Does pyvf beat the baselines? (context {C}, {metrics['meta']['scenes']} held-out scenes; "
             "lower is better)"]
    for base, names in VERDICTS.items():
        won, lost, pairs = _against(table["pyvf"], table[base], names)
        word = "no" if not won else ("partly" if lost else "yes")
        lines.append(f"- {base}: {word} ({pairs})")
    return lines


def paper_line():
    """The paper's SM7 figures (PAPER_SM7), for scale."""
    return ("- for scale, the paper's SM7 models (hundreds of GPU-hours; context 3; its own scenes, "
            "positions in its units): " + ", ".join(f"{_SHORT[m]} {_fmt(v)}" for m, v in PAPER_SM7.items()))


def _ms(s):
    return f"{s * 1e3:.1f} ms" if s < 1 else f"{s:.2f} s"


def metrics_markdown(metrics):
    """The metrics dict as markdown: the verdicts, a table per context size (methods x metrics),
    then the timings."""
    meta, t = metrics["meta"], metrics["timing"]
    q = meta["query_views"]
    lines = [f"# pyvf evaluation: {meta['scenes']} scenes (seed {meta['seed']}), {meta['image_size']}x"
             f"{meta['image_size']}, {meta['views']} views each",
             "",
             f"Context: the first C views of a scene. Queries: views {q[0]}..{q[-1]} of every scene "
             f"({meta['n_queries']} in all), the same for every C. Images: MAE and RMSE on 0..255 (per image, "
             f"then the mean), PSNR in dB on [0, 1] (per image, a perfect image capped at "
             f"{meta['psnr_cap_db']:.1f} dB, then the mean). Poses: medians over the queries, positions in cube "
             f"sides (cameras stand 10 from the object), orientations in degrees. `codebook` is the ground truth "
             f"encoded and decoded: the best any rendering through this codebook can be. pyvf's renderings "
             f"decode {DECODES[meta['decode']]} (decode={meta['decode']}).", ""]
    lines += verdict_lines(metrics) + [paper_line()]
    for C, table in metrics["context"].items():
        lines += ["", f"## Context {C} view{'s' if C != '1' else ''}"]
        if int(C) > meta["trained_context"]:
            lines += ["", f"(the transformer was trained with at most {meta['trained_context']} context views)"]
        lines += ["", "| method | " + " | ".join(_HEAD[m] for m in _ALL) + " |",
                  "|---|" + "---:|" * len(_ALL)]
        for method, row in table.items():
            lines.append(f"| {method} | " + " | ".join(_fmt(row.get(m)) for m in _ALL) + " |")
        p, cb = table["pyvf"], table["codebook"]
        lines += ["", f"Tokens of the queries: code entropy of empty patches {_fmt(cb['empty_entropy'])} nats "
                  f"(position by position); pyvf's cross-entropy {_fmt(p['ce_empty'])} nats on empty patches, "
                  f"{_fmt(p['ce_object'])} on object patches; accuracy {_fmt(p['token_accuracy_empty'])} and "
                  f"{_fmt(p['token_accuracy_object'])}."]
    lines += ["", f"## Timing ({meta['kernel_path']} kernels, {meta['kernel_threads']} thread"
              f"{'' if meta['kernel_threads'] == 1 else 's'})", "",
              f"{t['scenes']} scenes at context {t['context']}, one query per scene per call, the fastest of "
              f"{t['repeat']} calls.", "", "| step | time |", "|---|---:|",
              f"| encode_scene (the context trunk, once per scene) | {_ms(t['encode_scene_s_per_scene'])} |",
              f"| render a view from the cached scene | {_ms(t['render_cached_one_s_per_view'])} |",
              f"| render a view re-encoding the context (Transformer.render) | "
              f"{_ms(t['render_reencode_s_per_view'])} |", "",
              f"Speed-up of the scene cache: {_fmt(t['speedup_vs_reencode'], 1)}x against re-encoding the context "
              f"for every query. Whole evaluation: {t['total_s']:.1f} s."]
    return "\n".join(lines) + "\n"


def write_metrics(metrics, out):
    """Write out/metrics.json and out/metrics.md atomically (out is created)."""
    os.makedirs(out, exist_ok=True)
    atomic_write_text(os.path.join(out, "metrics.json"), json.dumps(metrics, indent=2, allow_nan=False) + "\n")
    atomic_write_text(os.path.join(out, "metrics.md"), metrics_markdown(metrics))
