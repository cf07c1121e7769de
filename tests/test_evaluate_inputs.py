"""Audit of pyvf.evaluate: hard cases of the metrics and the baselines against closed forms and
plain NumPy written here, and the arguments that used to give a silent wrong answer, an error
naming another (internal) argument, or a crash after the work was done."""

import io
import os

import numpy as np
import pytest
from PIL import Image

import pyvf
import pyvf.evaluate.run as run
from pyvf.evaluate import (
    closest_image_pose,
    evaluate,
    image_metrics,
    mean_pose,
    nearest_view,
    pose_metrics,
    to_model_images,
    to_uint8,
)
from pyvf.evaluate.health import codebook_health, colour_r2, effective_rank, object_mask, transformer_health
from pyvf.evaluate.pictures import save_poses, save_views
import test_evaluate
from test_evaluate import CODEBOOK

TRANSFORMER = pyvf.TransformerConfig(**test_evaluate.TRANSFORMER, dtype="float32")


@pytest.fixture(scope="module")
def models():
    return pyvf.Codebook(CODEBOOK, seed=0), pyvf.Transformer(TRANSFORMER, seed=0)


def pose(xyz, axis, degrees):
    h = np.radians(degrees) / 2
    return np.concatenate([xyz, [np.cos(h)], np.sin(h) * np.asarray(axis, float)])


# ---------------------------------------------------------------------------------------
# image metrics and conversions


def test_image_metrics_one_pixel_odd_sizes_and_a_single_image():
    """1x1x1 and 3x5x3 images, batch of one and no batch: the closed forms of math.md §6."""
    a, b = np.array([[[10]]], np.uint8), np.array([[[13]]], np.uint8)
    m = image_metrics(a, b)
    assert m["mae"] == 3 and m["rmse"] == 3 and m["psnr"] == pytest.approx(10 * np.log10(255.0 ** 2 / 9), rel=1e-15)
    assert image_metrics(a, a)["psnr"] == pytest.approx(10 * np.log10(4 * 255.0 ** 2), rel=1e-15)  # the cap
    rng = np.random.default_rng(1)
    p, t = rng.integers(0, 256, (2, 1, 3, 5, 3)).astype(np.uint8)  # one image of 3x5x3
    d = p.astype(float) - t.astype(float)
    m = image_metrics(p, t)
    assert m["mae"].shape == (1,)
    np.testing.assert_allclose(m["rmse"], [np.sqrt((d ** 2).mean())], rtol=1e-14)
    np.testing.assert_allclose(m["psnr"], [10 * np.log10(1 / ((d / 255) ** 2).mean())], rtol=1e-12)


def test_to_uint8_refuses_nan_and_clips_infinities():
    """A NaN in a decoder's output has no picture: it used to become 0 (black) silently."""
    x = np.array([-np.inf, 0.0, np.inf], np.float32).reshape(1, 1, 1, 3)
    np.testing.assert_array_equal(to_uint8(x)[0, 0, :, 0], [0, 128, 255])
    x = np.zeros((1, 3, 2, 2))
    x[0, 1, 1, 0] = np.nan
    with pytest.raises(ValueError, match="^x contains NaN"):
        to_uint8(x)


def test_to_model_images_names_images_of_the_wrong_rank():
    with pytest.raises(ValueError, match=r"^images must be .*\(B, Hi, Wi, C\).*\(1, 2, 3, 3, 3\)"):
        to_model_images(np.zeros((1, 2, 3, 3, 3), np.uint8), np.float32)


# ---------------------------------------------------------------------------------------
# pose metrics


def test_pose_metrics_hard_cases_closed_forms():
    """Identical poses, q against -q, 180 degrees, a 1e-9 rad rotation, zero translation."""
    a = pose([1, 2, 3], [0, 0, 1], 0)
    pred = np.stack([a, a * np.r_[1, 1, 1, -1, -1, -1, -1], pose([1, 2, 3], [1, 0, 0], 180),
                     pose([1, 2, 3], [0, 1, 0], np.degrees(1e-9)), pose([4, 6, 3], [0, 0, 1], 0)])
    m = pose_metrics(pred, np.broadcast_to(a, pred.shape).copy())
    np.testing.assert_array_equal(m["position_error"][:4], 0)
    assert m["position_error"][4] == pytest.approx(5.0, rel=1e-15)
    np.testing.assert_array_equal(m["orientation_error_deg"][[0, 1, 4]], 0)
    assert m["orientation_error_deg"][2] == pytest.approx(180.0, rel=1e-15)
    assert m["orientation_error_deg"][3] == pytest.approx(np.degrees(1e-9), rel=1e-12)


def test_pose_metrics_refuse_a_broadcast_and_name_pred_and_target():
    """pred (2, 1, 7) against target (1, 3, 7) used to give a (2, 3) grid of errors (whose median
    is no query's); errors named geometry's p1/p2/q1 instead of pred/target."""
    a = pose([0, 0, 0], [0, 0, 1], 10)
    with pytest.raises(ValueError, match="^pred and target must have one shape"):
        pose_metrics(np.tile(a, (2, 1, 1)), np.tile(a, (1, 3, 1)))
    with pytest.raises(ValueError, match=r"^pred must be poses \(\.\.\., 7\)"):
        pose_metrics(a[None, :3], a[None, :3])
    with pytest.raises(TypeError, match="^target"):
        pose_metrics(a[None], a[None].astype(np.int64))
    bad = a[None].copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="^pred contains NaN"):
        pose_metrics(bad, a[None])


def test_baselines_name_bad_context_poses():
    """closest_image_pose returned integer or NaN context poses as its estimate; nearest_view's
    errors named geometry's p2; mean_pose of a (C, 7) array spoke of an axis."""
    img, q_img = np.zeros((1, 2, 2, 2, 3), np.uint8), np.zeros((1, 1, 2, 2, 3), np.uint8)
    good = np.tile(pose([0, 0, 0], [0, 0, 1], 0), (1, 2, 1))  # (1, 2, 7)
    nan = good.copy()
    nan[0, 1, 0] = np.nan
    for fn, third in ((closest_image_pose, q_img), (nearest_view, good[:, :1])):
        with pytest.raises(TypeError, match="^context_poses"):
            fn(img, good.astype(np.int64), third)
        with pytest.raises(ValueError, match="^context_poses contains NaN"):
            fn(img, nan, third)
    with pytest.raises(ValueError, match="^query_poses contains NaN"):
        nearest_view(img, good, nan[:, 1:])
    with pytest.raises(TypeError, match="^query_poses"):
        nearest_view(img, good, good[:, :1].astype(np.float32))
    with pytest.raises(ValueError, match="^context_poses contains NaN"):
        mean_pose(nan)
    with pytest.raises(ValueError, match=r"^context_poses must have shape \(B, C, 7\)"):
        mean_pose(good[0])


# ---------------------------------------------------------------------------------------
# evaluate's arguments


def test_evaluate_refuses_non_integer_context_sizes(models):
    """context=(1, 2.7) was evaluated as (1, 2), (True,) as (1,)."""
    cb, tf = models
    for context in ((1, 2.7), (True,), "13"):
        with pytest.raises(ValueError, match="context sizes must be positive integers"):
            evaluate(cb, tf, scenes=1, context=context, progress=False)


def test_evaluate_checks_timing_arguments_before_the_work(models, monkeypatch):
    """timing_scenes=0 crashed after every scene was scored (an error naming context_tokens), and
    repeat=0 too: both are refused before any scene is generated."""
    cb, tf = models

    def no_work(*args, **kwargs):
        raise AssertionError("the work started")

    monkeypatch.setattr(run, "generate_scenes", no_work)
    with pytest.raises(ValueError, match="^timing_scenes must be a positive integer"):
        evaluate(cb, tf, scenes=1, context=1, progress=False, timing_scenes=0)
    with pytest.raises(ValueError, match="^repeat must be a positive integer"):
        evaluate(cb, tf, scenes=1, context=1, progress=False, repeat=0)


def _atomic_png(save, picture, tmp_path, monkeypatch):
    path = tmp_path / "sheet.png"
    path.write_bytes(b"the previous picture")

    def broken_save(self, fp, format=None, **kwargs):
        if isinstance(fp, (str, os.PathLike)):
            fp = open(fp, "wb")
        fp.write(b"\x89PNG half")
        raise OSError("disk full")

    monkeypatch.setattr(Image.Image, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        save(str(path), picture)
    assert path.read_bytes() == b"the previous picture"
    monkeypatch.undo()
    save(str(path), picture)
    with Image.open(path) as im:
        assert im.format == "PNG"


def test_pictures_are_written_atomically(tmp_path, monkeypatch):
    """An error while encoding used to leave a half-written views.png / poses.png over the old one."""
    rng = np.random.default_rng(0)
    q = pose([0, 0, 10], [0, 1, 0], 0)
    picture = {"context": rng.integers(0, 256, (1, 2, 4, 4, 3)).astype(np.uint8),
               "truth": np.zeros((1, 4, 4, 3), np.uint8), "codebook": np.zeros((1, 4, 4, 3), np.uint8),
               "pyvf": np.zeros((1, 4, 4, 3), np.uint8), "context_poses": np.tile(q, (1, 2, 1)),
               "query_poses": np.tile(q, (1, 1, 1)), "estimated_poses": np.tile(q, (1, 1, 1)), "C": 2}
    for save in (save_views, save_poses):
        _atomic_png(save, picture, tmp_path, monkeypatch)


# ---------------------------------------------------------------------------------------
# health


def test_effective_rank_of_a_constant_latent_is_zero_and_nan_is_named():
    """np.full((3, 4), 0.1): the mean of three 0.1 is not 0.1 in float64, the centred rows were
    1e-17 instead of 0 and the rank came out 1.0 instead of the documented 0."""
    for z in (np.full((3, 4), 0.1), np.full((7, 5), 1 / 3), np.full((4, 2), 0.1, np.float32)):
        assert effective_rank(z) == 0.0
    s = np.array([3.0, 1.0])  # a latent of two directions: exp(entropy of s / sum s)
    z = np.array([[3.0, 0], [-3, 0], [0, 1], [0, -1]]) / np.sqrt(2) + 0.1
    p = s / s.sum()
    assert effective_rank(z) == pytest.approx(np.exp(-(p * np.log(p)).sum()), rel=1e-12)
    with pytest.raises(ValueError, match="^z contains NaN"):
        effective_rank(np.array([[np.nan, 1.0], [2.0, 3.0]]))


def test_colour_r2_refuses_a_mask_that_is_not_boolean():
    """A 0/1 integer mask indexed the images by position: nan (or garbage) instead of the score."""
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (2, 4, 4, 3)).astype(np.uint8)
    mask = object_mask(img)
    assert colour_r2(img, img, mask) == 1.0
    with pytest.raises(TypeError, match="^mask must be a bool"):
        colour_r2(img, img, mask.astype(np.uint8))


def test_codebook_health_names_a_bad_batch(models):
    cb, _ = models
    images = np.zeros((2, 16, 16, 3), np.uint8)
    with pytest.raises(ValueError, match="^batch must be >= 1"):
        codebook_health(cb, images, batch=0)


def test_transformer_health_refuses_contexts_the_queries_overlap(models):
    """8 views with context 5: the 5 queries (views 3..7) used to include context views 3 and 4,
    so the model and the baselines were scored on views they were shown; no context crashed."""
    cb, tf = models
    images = np.zeros((1, 8, 16, 16, 3), np.uint8)
    poses = np.tile(pose([0, 0, 10], [0, 1, 0], 0), (1, 8, 1))
    tokens = np.zeros((1, 8, 64), np.int64)
    with pytest.raises(ValueError, match="needs 10 views"):
        transformer_health(cb, tf, images, poses, tokens, (5,))
    with pytest.raises(ValueError, match="context sizes"):
        transformer_health(cb, tf, images, poses, tokens, ())
