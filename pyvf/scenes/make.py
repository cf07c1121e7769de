"""The work of the `pyvf scenes` command (its arguments: pyvf/cli/scenes.py): a dataset on disk,
a line saying what was written, and a preview picture.

    make_dataset("data/sm7", 2000, seed=0, preview="sm7.png")
"""

import time

import numpy as np

from .._io import atomic_write_png
from .dataset import write_dataset
from .render import generate_scenes

__all__ = ["PREVIEW_SCENES", "make_dataset", "preview_grid", "save_preview"]

PREVIEW_SCENES = 8  # rows of the preview: the dataset's first scenes, every view as a column


def make_dataset(out, n_scenes, seed, *, views=15, size=64, shard_size=500, preview=None, progress=True,
                 overwrite=False):
    """write_dataset into `out`, print what was written; save_preview of the first scenes to `preview`."""
    t0 = time.perf_counter()
    manifest = write_dataset(out, n_scenes, seed, views=views, size=size, shard_size=shard_size, progress=progress,
                             overwrite=overwrite)
    total = sum(s["bytes"] for s in manifest["shards"])
    print(f"pyvf scenes: {manifest['n_scenes']} scenes x {manifest['views']} views of "
          f"{manifest['height']}x{manifest['width']} (seed {manifest['seed']}) in "
          f"{len(manifest['shards'])} shards, {total / 2**20:.1f} MiB, {time.perf_counter() - t0:.1f} s -> {out}")
    if preview:
        # the dataset's first scenes again: generation is deterministic, so these are the same bytes
        images, _ = generate_scenes(seed, min(n_scenes, PREVIEW_SCENES), views=views, size=size)
        save_preview(preview, images)
        print(f"pyvf scenes: preview of the first {len(images)} scenes -> {preview}")
    return manifest


def preview_grid(images, gap=2):
    """Tile views into one picture: images (S, V, H, W, 3) uint8 -> (S*(H+gap)-gap, V*(W+gap)-gap, 3)
    uint8, scene s in row s, view v in column v, white gaps."""
    S, V, H, W, _ = images.shape
    padded = np.pad(images, ((0, 0), (0, 0), (0, gap), (0, gap), (0, 0)), constant_values=255)  # white gaps
    grid = padded.transpose(0, 2, 1, 3, 4).reshape(S * (H + gap), V * (W + gap), 3)  # scene s in row s
    return grid[:grid.shape[0] - gap, :grid.shape[1] - gap]  # no gap after the last row and column


def save_preview(path, images, scale=2):
    """Write preview_grid(images), enlarged `scale` times (nearest neighbour), as a PNG."""
    from PIL import Image  # a dependency of pyvf; imported here so that `import pyvf` stays light

    grid = np.repeat(np.repeat(preview_grid(images), scale, axis=0), scale, axis=1)
    atomic_write_png(path, Image.fromarray(grid))
