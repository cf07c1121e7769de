"""The work of the `pyvf scenes` command (its arguments: pyvf/cli/scenes.py): a dataset on disk,
a line saying what was written, and a preview picture.

    make_dataset("data/sm7", 2000, seed=0, preview="sm7.png")
"""

import time

from .dataset import write_dataset
from .preview import save_preview
from .render import generate_scenes

__all__ = ["PREVIEW_SCENES", "make_dataset"]

PREVIEW_SCENES = 8  # rows of the preview: the dataset's first scenes, every view as a column


def make_dataset(out, n_scenes, seed, *, views=15, size=64, shard_size=500, preview=None, progress=True,
                 overwrite=False):
    """write_dataset (dataset.py) into the folder `out`, then print what was written; with preview
    (a PNG path), save_preview (preview.py) of the first PREVIEW_SCENES scenes. Returns the
    manifest; a bad argument raises write_dataset's ValueError, TypeError or FileExistsError."""
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
