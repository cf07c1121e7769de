"""The training batches: each a pure function of (seed, step), so that a resumed run draws the
same batches and both engines (pyvf's and torch's) train on the same ones.

    x, w = codebook_batch(images, 16, seed, step, object_weight=4.0)   # (B, C, Hi, Wi), (B, 1, Hi, Wi)
    tok, pos = transformer_batch(tokens, poses, 6, 8, seed, step)       # (B, N, L), (B, N, 7)
"""

import numpy as np

from ..evaluate.metrics import object_mask, to_model_images

__all__ = ["codebook_batch", "transformer_batch"]


def codebook_batch(images, batch_size, seed, step, dtype="float32", object_weight=None):
    """Batch of step `step`: batch_size views drawn uniformly (with replacement) from the
    (M, Hi, Wi, C) uint8 images -> (B, C, Hi, Wi) in [-1, 1]. A pure function of (seed, step).
    With object_weight (a float), also the pixel weights (B, 1, Hi, Wi): object_weight on the
    pixels health.object_mask marks, 1 on the background."""
    rng = np.random.default_rng([seed, step])
    idx = rng.integers(0, images.shape[0], size=batch_size)  # (B,)
    x = to_model_images(images[idx], np.dtype(dtype))
    if object_weight is None:
        return x
    w = np.where(object_mask(images[idx]), object_weight, 1.0).astype(dtype)[:, None]  # (B, 1, Hi, Wi)
    return x, w


def transformer_batch(tokens, poses, n_views, batch_size, seed, step, dtype="float32"):
    """Batch of step `step`: per sample a scene drawn uniformly, then n_views distinct views
    of it in random order. tokens (scenes, views, k, k), poses (scenes, views, 7) ->
    tokens (B, N, L) int64, poses (B, N, 7) of dtype. A pure function of (seed, step)."""
    rng = np.random.default_rng([seed, step])
    n_scenes, n_avail = tokens.shape[:2]
    scenes = rng.integers(0, n_scenes, size=batch_size)  # (B,)
    order = rng.permuted(np.tile(np.arange(n_avail), (batch_size, 1)), axis=1)  # (B, views): a permutation per row
    views = order[:, :n_views]  # (B, N)
    tok = tokens[scenes[:, None], views].reshape(batch_size, n_views, -1).astype(np.int64)  # (B, N, L)
    pos = poses[scenes[:, None], views].astype(dtype)  # (B, N, 7)
    return tok, pos
