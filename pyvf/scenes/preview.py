"""The preview grid of a dataset: its scenes' views tiled into one picture."""


import numpy as np

from .._io import atomic_write_png

__all__ = ["preview_grid", "save_preview"]

_GAP = 2  # pixels of white between the tiles


def preview_grid(images, gap=_GAP):
    """Tile views into one picture: images (S, V, H, W, 3) uint8 -> (S*(H+gap)-gap, V*(W+gap)-gap, 3)
    uint8, scene s in row s, view v in column v, white gaps."""
    images = np.asarray(images)
    if images.ndim != 5 or images.shape[-1] != 3 or images.dtype != np.uint8 or 0 in images.shape:
        raise ValueError(f"images must be uint8 (S, V, H, W, 3) with at least one scene, view and pixel, "
                         f"got {images.dtype}{images.shape}")
    S, V, H, W, _ = images.shape
    grid = np.full((S * (H + gap) - gap, V * (W + gap) - gap, 3), 255, dtype=np.uint8)
    for s in range(S):
        for v in range(V):
            grid[s * (H + gap):s * (H + gap) + H, v * (W + gap):v * (W + gap) + W] = images[s, v]
    return grid


def save_preview(path, images, scale=2):
    """Write preview_grid(images), enlarged `scale` times (nearest neighbour), as a PNG (atomically:
    an interrupted save leaves the earlier file at `path` whole)."""
    from PIL import Image  # a dependency of pyvf; imported here so that `import pyvf` stays light

    grid = preview_grid(images)
    if scale > 1:
        grid = np.repeat(np.repeat(grid, scale, axis=0), scale, axis=1)
    atomic_write_png(path, Image.fromarray(grid))
