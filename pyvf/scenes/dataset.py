"""A Shepard-Metzler dataset on disk: .npz shards and a manifest, written atomically, verified on load.

    manifest = write_dataset("data/sm7", n_scenes=2000, seed=0)   # shards, then manifest.json
    ds = load_dataset("data/sm7")     # every shard checked: ds.images (S, V, H, W, 3) uint8, ds.poses (S, V, 7)
    make_dataset("data/sm7", 2000, seed=0, preview="sm7.png")      # `pyvf scenes`: the same, said, and a preview

The format (FORMAT = "pyvf-sm7-scenes", FORMAT_VERSION = 1), in one folder:

* `shard-00000.npz`, `shard-00001.npz`, ...: shard k holds scenes k*shard_size onwards (the
  last one fewer), as three arrays: `images` (n, V, H, W, 3) uint8 RGB, `poses` (n, V, 7)
  float64 (xyz + unit quaternion (w, x, y, z), camera to world; conventions in cameras.py),
  `scene_index` (n,) int64, the scenes' global indices (scene i is generate_scene(seed, i)).
  A zip (deflate) of .npy files with a fixed timestamp, so the same arguments give the same bytes.
* `manifest.json`, written last: format and version, seed, counts and sizes, the camera and
  render constants, and for each shard its file name, scene range, size in bytes and sha256.
  A folder without a manifest is an unfinished write.
* `progress.jsonl`, only while a write is unfinished: the manifest without `shards`. A write
  interrupted (Ctrl-C, a crash) is resumed by the same arguments: the shards on disk are kept
  (each written atomically by pyvf._io, so whole), the others rendered, and the folder ends
  with the same bytes as an uninterrupted write.
"""

import dataclasses
import hashlib
import io
import json
import math
import os
import time
import zipfile

import numpy as np

from .._io import atomic_write_bytes, atomic_write_png, fsync_dir
from . import cameras, render
from .. import _checks
from .render import generate_scene, generate_scenes

__all__ = ["FORMAT", "FORMAT_VERSION", "DatasetExistsError", "SceneDataset", "write_dataset", "load_dataset",
           "PREVIEW_SCENES", "make_dataset", "preview_grid", "save_preview"]

FORMAT = "pyvf-sm7-scenes"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
PROGRESS = "progress.jsonl"  # the record of an unfinished write (module docstring)
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)  # the earliest zip timestamp: the shard's bytes do not depend on the clock


class DatasetExistsError(FileExistsError):
    """out_dir holds another dataset (finished, or a write these arguments cannot resume)."""

    def __init__(self, folder, holds):
        super().__init__(f"out_dir {folder} {holds}; overwrite=True replaces it")


@dataclasses.dataclass(eq=False)
class SceneDataset:
    """A loaded dataset: images (S, V, H, W, 3) uint8, poses (S, V, 7) float64, the seed that
    generated it and its manifest (the parsed manifest.json)."""

    images: np.ndarray
    poses: np.ndarray
    seed: int
    manifest: dict


# writing
def _npz_bytes(arrays):
    """The bytes of an .npz (deflate) holding `arrays` (name -> ndarray), with fixed timestamps."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, a in arrays.items():
            info = zipfile.ZipInfo(name + ".npy", date_time=_ZIP_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.ascontiguousarray(a), allow_pickle=False)
    return buf.getvalue()


def _constants():
    """The camera and render constants, recorded in the manifest."""
    return {
        "n_cubes": render.N_CUBES, "camera_radius": cameras.CAMERA_RADIUS, "tan_half_fov": cameras.TAN_HALF_FOV,
        "fov_degrees": math.degrees(2 * math.atan(cameras.TAN_HALF_FOV)),
        "max_elevation_degrees": cameras.MAX_ELEVATION_DEG, "world_up": [0.0, -1.0, 0.0],
        "camera_frame": "OpenCV: x right, y down, z forward (optical axis)",
        "pose": "xyz + unit quaternion (w, x, y, z) of the camera-to-world rotation, w >= 0",
        "light_dir": list(render.LIGHT_DIR), "ambient": render.AMBIENT, "diffuse": render.DIFFUSE,
        "back": render.BACK, "shading": "colour * (ambient + diffuse * max(0, n.l) + back * max(0, -n.l))",
        "background": list(render.BACKGROUND), "saturation": render.SATURATION, "value": render.VALUE,
        "rng": "numpy.random.default_rng([seed, scene_index])",
    }


def _prepare_dir(out_dir, head, overwrite):
    """Make out_dir ready for the write whose manifest without shards is `head`: -> the shard
    files to keep (an unfinished write of the same arguments'); else DatasetExistsError, unless
    overwrite: then the old files are removed, the manifest first."""
    names = sorted(os.listdir(out_dir))
    shards = [n for n in names if n.startswith("shard-") and n.endswith(".npz")]
    if not overwrite and MANIFEST in names:
        raise DatasetExistsError(out_dir, "holds a finished dataset")
    if not overwrite and PROGRESS in names:
        try:
            with open(os.path.join(out_dir, PROGRESS), encoding="utf-8") as f:
                old = json.loads(f.readline())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            old = None
        if old != json.loads(json.dumps(head)):  # compared as JSON: tuples are lists there
            raise DatasetExistsError(out_dir, "holds an unfinished write that these arguments cannot resume")
        return set(shards)
    if not overwrite and shards:
        raise DatasetExistsError(out_dir, f"holds shards without {PROGRESS}, which cannot be resumed")
    for name in [n for n in (MANIFEST, PROGRESS) if n in names] + shards:
        os.remove(os.path.join(out_dir, name))
        fsync_dir(out_dir)
    return set()


def write_dataset(out_dir, n_scenes, seed, views=15, size=64, shard_size=500, progress=True, overwrite=False):
    """Render scenes 0..n_scenes-1 of `seed` into out_dir (created if needed) as .npz shards plus
    manifest.json; returns the manifest. An unfinished write of the same arguments there is
    resumed; another dataset raises DatasetExistsError unless overwrite=True."""
    n_scenes = _checks.integer("n_scenes", n_scenes, 1)
    seed = _checks.integer("seed", seed, 0)
    views = _checks.integer("views", views, 1)
    shard_size = _checks.integer("shard_size", shard_size, 1)
    H = W = size = _checks.integer("size", size, 8)  # square images, at least 8 pixels
    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)

    head = {
        "format": FORMAT, "version": FORMAT_VERSION, "seed": seed, "n_scenes": n_scenes, "views": views,
        "height": H, "width": W, "shard_size": shard_size,
        "arrays": {"images": "uint8 (scenes, views, height, width, 3) RGB", "poses": "float64 (scenes, views, 7)",
                   "scene_index": "int64 (scenes,)"},
        "scene": _constants(),
    }
    kept = _prepare_dir(out_dir, head, overwrite)
    # the record of this write, before any shard: a rerun resumes it, other arguments are refused
    record = os.path.join(out_dir, PROGRESS)
    atomic_write_bytes(record, (json.dumps(head) + "\n").encode())

    from tqdm.auto import tqdm  # a dependency of pyvf; imported here so that `import pyvf` stays light

    shards = []
    with tqdm(total=n_scenes, unit="scene", desc="pyvf scenes", disable=not progress) as bar:
        for k, first in enumerate(range(0, n_scenes, shard_size)):
            n, name = min(shard_size, n_scenes - first), f"shard-{k:05d}.npz"
            if name in kept:
                with open(os.path.join(out_dir, name), "rb") as f:
                    data = f.read()
            else:
                images = np.empty((n, views, H, W, 3), dtype=np.uint8)
                poses = np.empty((n, views, 7))
                for i in range(n):
                    images[i], poses[i] = generate_scene(seed, first + i, views, size)
                data = _npz_bytes({"images": images, "poses": poses,
                                   "scene_index": np.arange(first, first + n, dtype=np.int64)})
                atomic_write_bytes(os.path.join(out_dir, name), data)
            bar.update(n)
            shards.append({"file": name, "first_scene": first, "n_scenes": n,
                           "bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()})

    manifest = {**head, "shards": shards}
    atomic_write_bytes(os.path.join(out_dir, MANIFEST), (json.dumps(manifest, indent=1) + "\n").encode())
    os.remove(record)
    return manifest


# reading
def _read_shard(path, entry, shapes, mpath):
    """One shard's (images, poses), checked against its manifest entry: size and sha256 (what
    write_dataset wrote, bit for bit), then the arrays' shapes and scene indices."""
    where = f"{path} (an entry of {mpath})"
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{where} is missing")
    with open(path, "rb") as f:
        data = f.read()
    if len(data) != entry["bytes"] or hashlib.sha256(data).hexdigest() != entry["sha256"]:
        raise ValueError(f"{where} is corrupt: its size or sha256 is not the manifest's")
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        arrays = {name: z[name] for name in z.files}
    first = entry["first_scene"]
    if {k: getattr(arrays.get(k), "shape", None) for k in shapes} != shapes or not np.array_equal(
            arrays["scene_index"], np.arange(first, first + entry["n_scenes"])):
        raise ValueError(f"{where} does not hold the arrays of its manifest entry: {shapes}, scenes {first}..")
    return arrays["images"], arrays["poses"]


def load_dataset(path):
    """Load and verify the dataset write_dataset wrote into the folder `path` -> SceneDataset. A
    missing file raises FileNotFoundError, one that does not match its manifest ValueError."""
    mpath = os.path.join(path, MANIFEST)
    if not os.path.isfile(mpath):
        raise FileNotFoundError(f"{mpath} is missing: not a dataset folder, or its write did not finish")
    try:
        with open(mpath, encoding="utf-8") as f:
            manifest = json.load(f)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{mpath}: not a valid JSON manifest ({e})") from None
    if not isinstance(manifest, dict) or (manifest.get("format"), manifest.get("version")) != (FORMAT, FORMAT_VERSION):
        raise ValueError(f"{mpath}: not a {FORMAT} manifest of version {FORMAT_VERSION}")
    if sum(e["n_scenes"] for e in manifest["shards"]) != manifest["n_scenes"]:
        raise ValueError(f"{mpath}: its shards do not hold its n_scenes {manifest['n_scenes']!r}")
    S, V, H, W = (manifest[k] for k in ("n_scenes", "views", "height", "width"))
    images = np.empty((S, V, H, W, 3), dtype=np.uint8)
    poses = np.empty((S, V, 7))
    for e in manifest["shards"]:
        n, first = e["n_scenes"], e["first_scene"]
        shapes = {"images": (n, V, H, W, 3), "poses": (n, V, 7), "scene_index": (n,)}
        images[first:first + n], poses[first:first + n] = _read_shard(os.path.join(path, e["file"]), e, shapes, mpath)
    return SceneDataset(images=images, poses=poses, seed=manifest["seed"], manifest=manifest)


# the `pyvf scenes` command
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
