"""Health figures of a model in training: what a loss curve does not show.

    h = codebook_health(codebook, images)   # images uint8 (M, Hi, Wi, 3): held-out views
    h = transformer_health(codebook, transformer, images, poses, tokens, contexts=(1, 3, 5))

Why these: a codebook whose latent collapses can keep a falling reconstruction loss, a healthy
perplexity and most of its codes in use while it loses the objects' colours (measured on SM7:
every object drawn red or cyan); the latent's effective rank and the colour figure show it early.

* effective rank (Roy and Vetterli, 2007): the singular values s_i of the centred latent
  vectors, p_i = s_i / sum(s), rank = exp(-sum p_i log p_i). 1 for a rank-1 latent, D for D
  equal singular values; in between it counts the directions the latent really uses.
* colour_r2: the chroma of a pixel is its two opponent-colour coordinates on 0..255,
  (R - G, (R + G) / 2 - B). Over the object pixels of the targets (object_mask),
  colour_r2 = 1 - sum |c_pred - c_true|^2 / sum |c_true - mean c_true|^2: 1 when every object
  pixel keeps its colour, about 0 for a prediction that draws every object grey or one colour,
  negative for colours moved elsewhere (red drawn as cyan, say). Brightness does not enter it.
"""

import numpy as np

from ..nn.quantizer import code_statistics
from .metrics import QUERIES, empty_entropy, empty_patches, image_metrics, object_mask, to_model_images, to_uint8

__all__ = ["effective_rank", "chroma", "colour_r2", "codebook_health", "CODEBOOK_HEALTH", "health_contexts",
           "transformer_health", "transformer_health_columns"]  # object_mask and empty_*: metrics', imported here

CODEBOOK_HEALTH = ["mae", "rmse", "psnr", "codes_in_use", "perplexity", "latent_rank", "colour_r2", "empty_entropy"]


def effective_rank(z):
    """z (N, D) float -> float in [1, min(N - 1, D)]: exp of the entropy of the normalised singular
    values of z minus its mean row. A constant z (no variance) has rank 0 by convention."""
    if (z == z[:1]).all():  # constant: exactly rank 0 (the mean of equal rows can round off them)
        return 0.0
    zc = z.astype(np.float64) - z.astype(np.float64).mean(axis=0)  # (N, D)
    s = np.linalg.svd(zc, compute_uv=False)  # (min(N, D),)
    p = s[s > 0] / s.sum()
    return float(np.exp(-(p * np.log(p)).sum()))


def chroma(images):
    """uint8 or float (..., 3) RGB on 0..255 -> float64 (..., 2): (R - G, (R + G) / 2 - B)."""
    x = np.asarray(images, dtype=np.float64)
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    return np.stack([r - g, 0.5 * (r + g) - b], axis=-1)


def colour_r2(pred, target, mask):
    """pred, target uint8 (..., Hi, Wi, 3) of one shape, mask bool (..., Hi, Wi) -> float: the
    share of the chroma variance of target's masked pixels that pred keeps (module docstring);
    nan when the mask is empty or those pixels all have one chroma."""
    ct, cp = chroma(target[mask]), chroma(pred[mask])  # (n, 2)
    if ct.shape[0] == 0:
        return float("nan")
    spread = ((ct - ct.mean(axis=0)) ** 2).sum()
    if not spread > 0:
        return float("nan")
    return float(1.0 - ((cp - ct) ** 2).sum() / spread)


def codebook_health(codebook, images, batch=64):
    """A codebook's health on held-out views: uint8 images (M, Hi, Wi, 3) -> {CODEBOOK_HEALTH key:
    float}: reconstruction mae, rmse, psnr through the codes (metrics.py), codes_in_use,
    perplexity (exp of the entropy of the codes' frequencies), latent_rank (effective_rank of the
    encoder's unquantized vectors), colour_r2 (of object pixels), empty_entropy. Inference only."""
    rec = np.empty_like(images)  # (M, Hi, Wi, 3)
    zs, codes = [], []
    for i in range(0, images.shape[0], batch):
        x = to_model_images(images[i:i + batch], codebook.dtype)  # (b, C, Hi, Wi)
        z, c = codebook.encode(x, return_latent=True)  # (b, D, k, k), (b, k, k)
        rec[i:i + batch] = to_uint8(codebook.decode_code(c))
        zs.append(z.transpose(0, 2, 3, 1).reshape(-1, z.shape[1]))  # (b k k, D)
        codes.append(c)
    m = image_metrics(rec, images)
    codes = np.concatenate(codes)  # (M, k, k)
    empty = empty_entropy(codes, empty_patches(images, codes.shape[-1]))
    codes = codes.ravel()
    counts = np.bincount(codes, minlength=codebook.config.n_embed)  # (K,)
    _, perplexity = code_statistics(counts)
    return {"mae": float(m["mae"].mean()), "rmse": float(m["rmse"].mean()), "psnr": float(m["psnr"].mean()),
            "codes_in_use": float(np.count_nonzero(counts)), "perplexity": perplexity,
            "latent_rank": effective_rank(np.concatenate(zs)),
            "colour_r2": colour_r2(rec, images, object_mask(images)), "empty_entropy": empty}


# the transformer
_TF_METRICS = tuple(  # (method, metric, column stem) for each context size, in eval.csv's order
    [("pyvf", m, m) for m in ("ce", "token_accuracy", "ce_empty", "ce_object", "token_accuracy_empty",
                              "token_accuracy_object", "mae", "rmse")]  # tokens of all, empty, object patches
    + [(base, m, f"{base}_{m}") for m in ("mae", "rmse") for base in ("nearest_view", "mean_image")]
    + [(method, metric, prefix + stem)
       for method, prefix in (("pyvf", ""), ("closest_image_pose", "closest_image_"), ("mean_pose", "mean_pose_"))
       for metric, stem in (("position_error_median", "position"), ("orientation_error_median_deg", "orientation"))])


def health_contexts(transformer_config, views):
    """The context sizes a training run is evaluated at: of 1, 3 and 5 views, those the transformer
    was trained on (sequence_size - 1) and the scenes leave QUERIES queries for."""
    top = min(transformer_config.sequence_size - 1, views - QUERIES)
    return tuple(c for c in (1, 3, 5) if c <= top) or ((top,) if top >= 1 else ())


def transformer_health_columns(contexts):
    """eval.csv's columns for these context sizes: stem_cC for each of _TF_METRICS' stems."""
    return [f"{stem}_c{C}" for C in contexts for _, _, stem in _TF_METRICS]


def transformer_health(codebook, transformer, images, poses, tokens, contexts, batch=8):
    """A transformer's health on held-out scenes, with the baselines beside it: pyvf evaluate's
    figures (run.score_scenes) for each C in contexts, the queries the last QUERIES views.

    images uint8 (n, V, S, S, 3), poses (n, V, 7), tokens (n, V, L) int64 (the codebook's tokens
    of the images) -> {column: float} (transformer_health_columns). The rendering decodes by
    argmax, as every run's eval.csv always has, so that runs compare across versions."""
    from .run import score_scenes  # evaluate.run imports the scenes home; only this needs it
    views = images.shape[1]
    qidx = np.arange(views - QUERIES, views)
    results, _ = score_scenes(codebook, transformer, images, poses, tokens, sorted(contexts), qidx, batch,
                              decode="argmax")
    return {f"{stem}_c{C}": results[str(C)][method][metric]
            for C in contexts for method, metric, stem in _TF_METRICS}
