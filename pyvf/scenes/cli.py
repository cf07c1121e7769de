"""The `pyvf scenes` command and the preview grid.

    pyvf scenes --out data/sm7 --scenes 2000 --seed 0 [--views 15] [--size 64] [--shard-size 500]
                [--preview sm7.png] [--overwrite] [--quiet]

cli_register(subparsers) adds the subcommand to pyvf's parser; its handler cmd_scenes(args)
only parses and calls write_dataset (dataset.py), then optionally save_preview.
"""

import sys
import time

import numpy as np

from .dataset import write_dataset
from .render import generate_scenes

__all__ = ["cli_register", "cmd_scenes", "preview_grid", "save_preview"]

PREVIEW_SCENES = 8  # rows of the preview: the dataset's first scenes, every view as a column
_GAP = 2  # pixels of white between the tiles


def preview_grid(images, gap=_GAP):
    """Tile views into one picture: images (S, V, H, W, 3) uint8 -> (S*(H+gap)-gap, V*(W+gap)-gap, 3)
    uint8, scene s in row s, view v in column v, white gaps."""
    images = np.asarray(images)
    if images.ndim != 5 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise ValueError(f"images must be uint8 (S, V, H, W, 3), got {images.dtype}{images.shape}")
    S, V, H, W, _ = images.shape
    grid = np.full((S * (H + gap) - gap, V * (W + gap) - gap, 3), 255, dtype=np.uint8)
    for s in range(S):
        for v in range(V):
            grid[s * (H + gap):s * (H + gap) + H, v * (W + gap):v * (W + gap) + W] = images[s, v]
    return grid


def save_preview(path, images, scale=2):
    """Write preview_grid(images), enlarged `scale` times (nearest neighbour), as a PNG."""
    from PIL import Image  # a dependency of pyvf; imported here so that `import pyvf` stays light

    grid = preview_grid(images)
    if scale > 1:
        grid = np.repeat(np.repeat(grid, scale, axis=0), scale, axis=1)
    Image.fromarray(grid).save(path, format="PNG")


def cmd_scenes(args):
    """Render a Shepard-Metzler-7 dataset (docs/math.md §7) into .npz shards and a manifest."""
    t0 = time.perf_counter()
    try:
        manifest = write_dataset(args.out, args.scenes, args.seed, views=args.views, size=args.size,
                                 shard_size=args.shard_size, progress=not args.quiet,
                                 overwrite=args.overwrite)
    except (ValueError, TypeError, FileExistsError) as e:
        print(f"pyvf scenes: {e}", file=sys.stderr)
        return 2
    total = sum(s["bytes"] for s in manifest["shards"])
    print(f"pyvf scenes: {manifest['n_scenes']} scenes x {manifest['views']} views of "
          f"{manifest['height']}x{manifest['width']} (seed {manifest['seed']}) in "
          f"{len(manifest['shards'])} shards, {total / 2**20:.1f} MiB, {time.perf_counter() - t0:.1f} s -> {args.out}")
    if args.preview:
        # the dataset's first scenes again: generation is deterministic, so these are the same bytes
        images, _ = generate_scenes(args.seed, min(args.scenes, PREVIEW_SCENES), views=args.views, size=args.size)
        save_preview(args.preview, images)
        print(f"pyvf scenes: preview of the first {len(images)} scenes -> {args.preview}")
    return 0


def cli_register(subparsers):
    """Add the `scenes` subcommand to an argparse subparsers object; returns its parser."""
    p = subparsers.add_parser("scenes", help="render a Shepard-Metzler-7 dataset (.npz shards + manifest)",
                              description=cmd_scenes.__doc__)
    p.add_argument("--out", required=True, metavar="DIR", help="folder to write the shards and manifest.json into")
    p.add_argument("--scenes", type=int, required=True, metavar="N", help="number of scenes")
    p.add_argument("--seed", type=int, required=True, metavar="S",
                   help="dataset seed: scene i draws from numpy.random.default_rng([S, i])")
    p.add_argument("--views", type=int, default=15, help="views per scene (default 15, as SM7)")
    p.add_argument("--size", type=int, default=64, help="image side in pixels (default 64, as SM7)")
    p.add_argument("--shard-size", type=int, default=500, metavar="N", help="scenes per shard (default 500)")
    p.add_argument("--preview", default=None, metavar="PNG",
                   help=f"also write a PNG grid of the first {PREVIEW_SCENES} scenes' views")
    p.add_argument("--overwrite", action="store_true", help="replace a dataset already in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_scenes)
    return p
