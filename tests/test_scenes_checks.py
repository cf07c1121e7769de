"""Audit of pyvf.scenes: the inputs that gave silently wrong answers, misleading errors, or work
started (and a folder left blocked) for a request that can never finish.

Oracles are independent of the code under test: rotation matrices written out here from the
axis-angle form, the folder's listing before and after, and whether any scene was rendered.
"""

import math
import os

import numpy as np
import pytest

from pyvf import scenes as sc
from pyvf.scenes import dataset as dataset_module

from conftest import assert_close

CUBE = np.zeros((1, 3), dtype=np.int64)
COLOUR = np.array([[0.9, 0.35, 0.6]])
FRONT = np.array([0.0, 0.0, -10.0, 1.0, 0.0, 0.0, 0.0])  # at z = -10 looking along +z (identity rotation)


def rotation_about(axis, angle):
    """Rodrigues' rotation matrix, written here: I + sin(t) K + (1 - cos(t)) K^2."""
    x, y, z = axis
    K = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]], dtype=np.float64)
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


# ---------------------------------------------------------------------------------------
# poses given to the renderer and to pose_matrix


def test_pose_matrix_closed_form_and_checks():
    axis = np.array([2.0, -1.0, 2.0]) / 3
    t = 0.7
    q = np.concatenate([[math.cos(t / 2)], math.sin(t / 2) * axis])  # (w, x, y, z)
    assert_close("pose_matrix", sc.pose_matrix(q), rotation_about(axis, t), rtol=1e-12)
    with pytest.raises(ValueError, match=r"q.*unit"):  # (1, 1, 0, 0) is no rotation: |q|^2 = 2
        sc.pose_matrix(np.array([1.0, 1.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match=r"\bq\b.*4"):
        sc.pose_matrix(np.array([1.0, 0.0, 0.0]))
    with pytest.raises(TypeError, match=r"\bq\b"):
        sc.pose_matrix([1.0, 0.0, 0.0, 0.0])


@pytest.mark.parametrize("pose, match", [
    (np.array([0.0, 0.0, -10.0, 1.0, 1.0, 0.0, 0.0]), r"poses.*unit"),   # not a rotation
    (np.array([0.0, 0.0, -10.0, 2.0, 0.0, 0.0, 0.0]), r"poses.*unit"),   # a scaled identity
    (np.array([0.0, 0.0, np.nan, 1.0, 0.0, 0.0, 0.0]), r"poses.*NaN"),   # rendered all background before
    (np.array([0.2, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0]), r"poses.*inside"),   # a camera inside the cube
    (np.array([0.5, 0.5, -0.5, 1.0, 0.0, 0.0, 0.0]), r"poses.*inside"),  # on its corner: the closed box
])
def test_render_views_refuses_poses_it_cannot_render(pose, match):
    """Each of these rendered an image without complaint: of no rotation, or from inside a cube."""
    with pytest.raises(ValueError, match=match):
        sc.render_views(CUBE, COLOUR, pose[None], 8)


def test_render_views_takes_float32_poses():
    """float32 unit quaternions (unit to float32's precision) are still rendered, as before."""
    p32 = sc.look_at_poses(np.array([[3.0, -1.0, 9.0]], dtype=np.float32))
    assert abs(float((p32[0, 3:].astype(np.float64) ** 2).sum()) - 1) > 1e-12  # not unit in float64
    img = sc.render_views(CUBE, COLOUR, p32, 16)
    assert img.shape == (1, 16, 16, 3) and (img != img[0, 0, 0]).any()


# ---------------------------------------------------------------------------------------
# the random generator and the camera count


@pytest.mark.parametrize("call, error, match", [
    (lambda: sc.sample_camera_positions(np.random.default_rng(0), -1), ValueError, r"\bn\b"),
    (lambda: sc.sample_camera_positions(np.random.default_rng(0), 2.0), TypeError, r"\bn\b"),
    (lambda: sc.sample_camera_positions(np.random.default_rng(0), 2, radius=0.0), ValueError, "radius"),
    (lambda: sc.sample_camera_positions(np.random.default_rng(0), 2, radius=np.inf), ValueError, "radius"),
    (lambda: sc.sample_camera_positions(0, 2), TypeError, r"rng.*Generator"),
    (lambda: sc.make_object(0), TypeError, r"rng.*Generator"),
])
def test_sampler_arguments_are_named(call, error, match):
    with pytest.raises(error, match=match):
        call()


# ---------------------------------------------------------------------------------------
# huge counts: refused before the folder is touched (no progress record left to block a rerun)


def forbid_rendering(monkeypatch):
    def scene(*args):
        raise AssertionError("a scene was rendered")
    monkeypatch.setattr(dataset_module, "generate_scene", scene)


@pytest.mark.parametrize("kwargs, match", [
    (dict(n_scenes=1, views=10**10, size=8), "views"),                  # 1.75 TiB of images in one shard
    (dict(n_scenes=2, views=3, size=10**6, shard_size=1), "size"),      # a scene's rendering: PiB
    (dict(n_scenes=10**15, views=15, size=64, shard_size=1), "n_scenes"),  # 10^15 shards in the manifest
])
def test_write_dataset_refuses_work_beyond_memory(tmp_path, monkeypatch, kwargs, match):
    """Before: a MemoryError after progress.jsonl was written (the same call with corrected
    arguments then refused the folder as an unfinished write of another dataset), or a table of
    every shard built first (10^15 entries: the machine's memory exhausted)."""
    forbid_rendering(monkeypatch)
    monkeypatch.setattr(dataset_module, "_physical_memory", lambda: 64 * 2**30)
    out = tmp_path / "ds"
    with pytest.raises(ValueError, match=f"{match}.*GiB of memory"):
        sc.write_dataset(out, seed=0, progress=False, **kwargs)
    assert not out.exists()
    monkeypatch.undo()
    sc.write_dataset(out, 1, seed=0, views=2, size=8, progress=False)  # the folder is not blocked
    assert sorted(os.listdir(out)) == ["manifest.json", "shard-00000.npz"]


def test_write_dataset_refuses_work_beyond_the_disk(tmp_path, monkeypatch):
    """Deflate compresses at most 1032:1, so shards of raw size B need at least B / 1032 bytes."""
    forbid_rendering(monkeypatch)
    monkeypatch.setattr(dataset_module, "_physical_memory", lambda: 2**60)
    n = 10**12  # raw: 10^12 * 15 * 64 * 64 * 3 bytes = 1.8e17, at least 1.8e14 on disk
    with pytest.raises(ValueError, match=r"n_scenes.*GiB of disk"):
        sc.write_dataset(tmp_path / "ds", n, seed=0, shard_size=10**7, progress=False)
    assert not (tmp_path / "ds").exists()


# ---------------------------------------------------------------------------------------
# load_dataset of a file, the preview


def test_load_dataset_of_a_file_says_so(tmp_path):
    """A shard (or any file) given as the dataset folder: it exists, it is not a folder."""
    sc.write_dataset(tmp_path / "ds", 1, seed=0, views=2, size=8, progress=False)
    shard = tmp_path / "ds" / "shard-00000.npz"
    with pytest.raises(NotADirectoryError, match=r"shard-00000\.npz.*not a folder"):
        sc.load_dataset(shard)


def test_preview_grid_of_no_scene_is_named():
    with pytest.raises(ValueError, match=r"images.*at least one"):
        sc.preview_grid(np.zeros((0, 2, 8, 8, 3), dtype=np.uint8))
    with pytest.raises(ValueError, match=r"images.*at least one"):
        sc.preview_grid(np.zeros((2, 0, 8, 8, 3), dtype=np.uint8))


def test_save_preview_is_atomic(tmp_path, monkeypatch):
    """A save interrupted half way (Ctrl-C in the PNG encoder) leaves the earlier preview whole."""
    from PIL import Image, PngImagePlugin  # noqa: F401  (the plugin registers the PNG writer)

    path = tmp_path / "p.png"
    images = np.full((1, 2, 8, 8, 3), 7, dtype=np.uint8)
    sc.save_preview(path, images)
    before = path.read_bytes()

    def torn(im, fp, filename, *args, **kwargs):
        fp.write(b"\x89PNG half")
        raise KeyboardInterrupt

    monkeypatch.setitem(Image.SAVE, "PNG", torn)
    with pytest.raises(KeyboardInterrupt):
        sc.save_preview(path, images + 1)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["p.png"]  # no temporary file left
