"""pyvf.evaluate and pyvf.models: the metrics against closed forms, the baselines on a hand-made
scene, the scene cache against the whole tree, a smoke run of evaluate() and its files, and the
`pyvf demo` / `pyvf evaluate` commands.

The models are tiny and random (16x16 images, 8x8 tokens of 32 codes): what is tested is the
protocol and the bookkeeping, not the quality of a trained model. About ten seconds on 2 cores.
"""

import importlib.util
import json
import os

import numpy as np
import pytest
from PIL import Image

import pyvf
import pyvf.evaluate.run
import pyvf.models
from pyvf.cli import main
from conftest import assert_close
from pyvf.scenes import generate_scenes
from pyvf.evaluate.metrics import (closest_image_pose, image_metrics, mean_image, mean_pose, nearest_view,
                                  pose_metrics, psnr_cap, to_model_images, to_uint8)
from pyvf.evaluate.run import METHODS, TOKEN_SCORES, evaluate

CODEBOOK = pyvf.CodebookConfig(ch=32, ch_mult=(1, 2), num_res_blocks=1, attn_resolutions=(), z_channels=32,
                               embed_dim=16, n_embed=32, image_size=16)
TRANSFORMER = dict(n_embeddings=32, n_head=2, d_model=32, n_layer=2, token_image_size=8, sequence_size=4,
                   n_loss_skip=1, pose_multiplier=0.2)


def random_transformer(dtype="float64", seed=0, spread=0.3):
    """Parameters random everywhere (gamma != 1, biases != 0), so that a wrong role of any of
    them shows in the outputs."""
    model = pyvf.Transformer(pyvf.TransformerConfig(**TRANSFORMER, dtype=dtype), seed=seed)
    rng = np.random.default_rng(seed + 100)
    for name, p in model.params.items():
        model.params[name] = (p + rng.normal(0, spread, p.shape)).astype(p.dtype)
    return model


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    """(codebook, transformer, codebook path, transformer path), float32, saved once."""
    folder = tmp_path_factory.mktemp("models")
    cb = pyvf.Codebook(CODEBOOK, seed=0)
    tf = random_transformer("float32", spread=0.05)
    cb.save(folder / "cb.npz")
    tf.save(folder / "tf.npz")
    return cb, tf, str(folder / "cb.npz"), str(folder / "tf.npz")


def quat_about(axis, degrees):
    """The unit quaternion (w, x, y, z) of a rotation by `degrees` about the unit `axis`."""
    h = np.radians(degrees) / 2
    return np.concatenate([[np.cos(h)], np.sin(h) * np.asarray(axis, float)])


# ---------------------------------------------------------------------------------------
# (b) the metrics against closed forms


def test_image_metrics_closed_forms():
    rng = np.random.default_rng(0)
    target = rng.integers(20, 200, (3, 4, 5, 3)).astype(np.uint8)  # 3 images of 4x5 pixels
    m = image_metrics(target + np.uint8(7), target)  # every value 7 levels too bright
    np.testing.assert_allclose(m["mae"], 7.0, rtol=1e-15)
    np.testing.assert_allclose(m["rmse"], 7.0, rtol=1e-15)
    np.testing.assert_allclose(m["psnr"], 10 * np.log10(255.0 ** 2 / 49.0), rtol=1e-15)

    pred = target.astype(np.int64)
    pred[..., :2, :, :] += 3  # half of every image's pixels +3, the other half -5
    pred[..., 2:, :, :] -= 5
    m = image_metrics(pred.astype(np.uint8), target)
    np.testing.assert_allclose(m["mae"], 4.0, rtol=1e-15)
    np.testing.assert_allclose(m["rmse"], np.sqrt(17.0), rtol=1e-15)  # per image: sqrt((9 + 25) / 2)
    np.testing.assert_allclose(m["psnr"], 10 * np.log10(255.0 ** 2 / 17.0), rtol=1e-15)

    # a perfect image: given the PSNR of one value off by half a level (mse = 0.25 / 60)
    m = image_metrics(target, target)
    assert (m["mae"] == 0).all() and (m["rmse"] == 0).all()
    cap = 10 * np.log10(255.0 ** 2 / (0.25 / (4 * 5 * 3)))
    assert psnr_cap((4, 5, 3)) == pytest.approx(cap, rel=1e-15)
    np.testing.assert_allclose(m["psnr"], cap, rtol=1e-15)
    # the smallest non-zero error, one value off by one level (mse = 1 / 60), scores 20 log10(2)
    # = 6.02 dB less: strictly below the perfect image, as the module docstring says
    one_off = target.copy()
    one_off[:, 0, 0, 0] += 1
    best_imperfect = image_metrics(one_off, target)["psnr"]
    np.testing.assert_allclose(best_imperfect, 10 * np.log10(255.0 ** 2 * 60), rtol=1e-15)
    assert (best_imperfect < m["psnr"]).all()
    np.testing.assert_allclose(m["psnr"] - best_imperfect, 20 * np.log10(2.0), rtol=1e-12)

    # RMSE is per image, then the mean: two images off by 3 and by 4 give 3.5, not sqrt(12.5)
    pair = np.stack([target[0] + np.uint8(3), target[0] + np.uint8(4)])
    assert image_metrics(pair, np.stack([target[0]] * 2))["rmse"].mean() == pytest.approx(3.5, rel=1e-15)


def test_image_conversions():
    levels = np.arange(256, dtype=np.uint8)
    images = np.stack([np.broadcast_to(levels.reshape(16, 16, 1), (16, 16, 3))]).copy()  # (1, 16, 16, 3)
    for dtype in (np.float32, np.float64):
        x = to_model_images(images, dtype)
        assert x.dtype == dtype and x.shape == (1, 3, 16, 16)
        assert x.min() == -1 and x.max() == 1
        np.testing.assert_array_equal(to_uint8(x), images)  # every level comes back exactly
    x = np.array([-3.0, -1.0, -0.999, 0.0, 0.999, 1.0, 1.5], np.float32).reshape(1, 1, 1, 7)
    np.testing.assert_array_equal(to_uint8(x)[0, 0, :, 0], [0, 0, 0, 128, 255, 255, 255])  # 127.5 rounds to even
    x = np.array([-np.inf, 0.0, np.inf], np.float32).reshape(1, 1, 1, 3)  # infinities clip
    np.testing.assert_array_equal(to_uint8(x)[0, 0, :, 0], [0, 128, 255])


def test_baselines_hand_made():
    """Three context views of constant grey levels 10, 50, 90 at known cameras; two queries:
    query 0 stands near camera 0 and looks like view 2, query 1 near camera 2 and looks like view 0."""
    levels = np.array([10, 50, 90], np.uint8)
    ctx_img = np.broadcast_to(levels[None, :, None, None, None], (1, 3, 4, 4, 3)).copy()  # (B=1, C=3, 4, 4, 3)
    q1 = quat_about([0, 1, 0], 90)
    ctx_pose = np.array([[[10, 0, 0, 1, 0, 0, 0], [0, 0, 10, *q1], [-10, 0, 0, 1, 0, 0, 0]]], float)  # (1, 3, 7)
    q_pose = np.array([[[9, 0, 1, 1, 0, 0, 0], [-9, 1, 0, 1, 0, 0, 0]]], float)  # (1, M=2, 7)
    q_img = np.broadcast_to(np.array([85, 12], np.uint8)[None, :, None, None, None], (1, 2, 4, 4, 3)).copy()

    nv = nearest_view(ctx_img, ctx_pose, q_pose)  # (1, 2, 4, 4, 3)
    np.testing.assert_array_equal(nv[0, 0], ctx_img[0, 0])  # camera 0 is nearest query 0
    np.testing.assert_array_equal(nv[0, 1], ctx_img[0, 2])
    np.testing.assert_array_equal(mean_image(ctx_img), np.full((1, 4, 4, 3), 50, np.uint8))

    cp = closest_image_pose(ctx_img, ctx_pose, q_img)  # (1, 2, 7)
    np.testing.assert_array_equal(cp[0, 0], ctx_pose[0, 2])  # 85 is closest to 90
    np.testing.assert_array_equal(cp[0, 1], ctx_pose[0, 0])  # 12 is closest to 10

    mp = mean_pose(ctx_pose)  # (1, 7)
    np.testing.assert_allclose(mp[0, :3], [0, 0, 10 / 3], atol=1e-15)
    q = np.array([1 + q1[0] + 1, 0, q1[2], 0]) / 3  # the canonical quaternions' mean, then normalised
    np.testing.assert_allclose(mp[0, 3:], q / np.linalg.norm(q), rtol=1e-15, atol=1e-15)

    # the metrics of the nearest view by hand: |85 - 10| = 75 and |12 - 90| = 78 everywhere
    m = image_metrics(nv, q_img)
    np.testing.assert_allclose(m["mae"], [[75, 78]], rtol=1e-15)
    np.testing.assert_allclose(m["rmse"], [[75, 78]], rtol=1e-15)
    np.testing.assert_allclose(m["psnr"], 10 * np.log10(255.0 ** 2 / np.array([[75.0, 78.0]]) ** 2), rtol=1e-15)
    p = pose_metrics(cp, q_pose)
    np.testing.assert_allclose(p["position_error"], [[np.hypot(19, 1), np.hypot(19, 1)]], rtol=1e-15)
    np.testing.assert_allclose(p["orientation_error_deg"], [[0, 0]], atol=1e-12)


def image_row(pred, target):
    """uint8 images (..., Hi, Wi, 3) -> the mean over images of MAE, RMSE and PSNR, written out
    from docs/math.md §6: per image on the 0..255 scale, PSNR = 10 log10(255^2 / mse), a perfect
    image given the PSNR of one value half a level off."""
    d = pred.astype(np.float64) - target.astype(np.float64)  # (..., Hi, Wi, 3)
    d = d.reshape(-1, int(np.prod(d.shape[-3:])))  # (images, values)
    mse = (d * d).mean(axis=1)
    with np.errstate(divide="ignore"):
        psnr = np.minimum(10 * np.log10(255.0 ** 2 / mse), 10 * np.log10(255.0 ** 2 / (0.25 / d.shape[1])))
    return {"mae": np.abs(d).mean(axis=1).mean(), "rmse": np.sqrt(mse).mean(), "psnr": psnr.mean()}


def pose_row(pred, target):
    """poses (..., 7) -> the medians of the position error (Euclidean) and of the orientation error
    in degrees, the angle between unit quaternions: 2 arccos |q1 . q2|."""
    position = np.sqrt(((pred[..., :3] - target[..., :3]) ** 2).sum(axis=-1))
    q1, q2 = (p[..., 3:] / np.linalg.norm(p[..., 3:], axis=-1, keepdims=True) for p in (pred, target))
    angle = np.degrees(2 * np.arccos(np.minimum(np.abs((q1 * q2).sum(axis=-1)), 1.0)))
    return {"position_error_median": np.median(position), "orientation_error_median_deg": np.median(angle)}


def rows_by_hand(cb, tf, images, poses, C):
    """evaluate()'s rows for 2 scenes (images (2, 15, 16, 16, 3), poses (2, 15, 7)) at context C:
    context views 0..C-1, queries 10..14; pyvf renders each query (argmax tokens, decoded) and
    localizes it from its tokens through Transformer.render / localize, one scene per call."""
    q, k, f = np.arange(10, 15), cb.config.token_size, tf.dtype
    truth, truth_pose = images[:, q], poses[:, q]  # (2, 5, 16, 16, 3), (2, 5, 7)
    ctx, ctx_pose = images[:, :C], poses[:, :C]  # (2, C, 16, 16, 3), (2, C, 7)
    tok = np.stack([cb.encode(to_model_images(v, cb.dtype)).reshape(15, -1) for v in images])  # (2, 15, L)

    def decoded(codes):  # (2, 5, L) -> uint8 (2, 5, 16, 16, 3)
        return to_uint8(cb.decode_code(codes.reshape(10, k, k))).reshape(2, 5, 16, 16, 3)

    # one scene per call, as evaluate(batch=1): the same shapes, so the same float32 roundings
    # (GEMMs blocked for another batch size round otherwise; a near-tie of an argmax would show it)
    s = [slice(i, i + 1) for i in range(2)]
    logits = np.concatenate([tf.render(tok[i, :C], ctx_pose[i].astype(f), truth_pose[i].astype(f)) for i in s])
    est = np.concatenate([tf.localize(tok[i, :C], ctx_pose[i].astype(f), tok[i][:, q]) for i in s])
    b = np.arange(2)[:, None]
    near = np.linalg.norm(truth_pose[:, :, None, :3] - ctx_pose[:, None, :, :3], axis=-1).argmin(axis=2)  # (2, 5)
    closest = ((truth[:, :, None].astype(float) - ctx[:, None]) ** 2).mean(axis=(-3, -2, -1)).argmin(axis=2)
    mean_img = np.rint(ctx.mean(axis=1)).astype(np.uint8)[:, None].repeat(5, axis=1)  # (2, 5, 16, 16, 3)
    quats = ctx_pose[..., 3:] / np.linalg.norm(ctx_pose[..., 3:], axis=-1, keepdims=True)  # (2, C, 4)
    quats = np.where(quats[..., :1] < 0, -quats, quats).mean(axis=1)  # canonical (w >= 0), then the mean
    mean_p = np.concatenate([ctx_pose[..., :3].mean(axis=1), quats], axis=-1)[:, None].repeat(5, axis=1)
    return {"pyvf": {**image_row(decoded(logits.argmax(-1)), truth), **pose_row(est.astype(np.float64), truth_pose)},
            "codebook": image_row(decoded(tok[:, q]), truth),
            "nearest_view": image_row(ctx[b, near], truth),
            "mean_image": image_row(mean_img, truth),
            "closest_image_pose": pose_row(ctx_pose[b, closest], truth_pose),
            "mean_pose": pose_row(mean_p, truth_pose)}


SMOKE = dict(scenes=2, context=(3, 1), seed=5, progress=False, repeat=1, timing_scenes=1, batch=1)


@pytest.fixture(scope="module")
def smoke(models, tmp_path_factory):
    """evaluate() by argmax (as rows_by_hand renders) on 2 scenes at contexts 1 and 3: (metrics, out)."""
    out = tmp_path_factory.mktemp("eval")
    return evaluate(models[0], models[1], out=str(out), decode="argmax", **SMOKE), out


def test_evaluate_smoke(models, smoke):
    cb, tf, _, _ = models
    metrics, out = smoke
    with open(out / "metrics.json") as f:
        on_disk = json.load(f)
    assert on_disk == metrics
    assert set(metrics) == {"context", "timing", "meta"}
    assert list(metrics["context"]) == ["1", "3"]  # sorted
    for C, table in metrics["context"].items():
        assert set(table) == set(METHODS), C
        extra = {"pyvf": TOKEN_SCORES, "codebook": ("empty_entropy",)}  # issue 48's token figures
        for method, row in table.items():
            assert list(row) == list(METHODS[method]) + list(extra.get(method, ())), (C, method)
            # None: the queries have no empty (or no object) patch
            assert all(v is None and k in TOKEN_SCORES[2:] + ("empty_entropy",) or isinstance(v, float)
                       and np.isfinite(v) for k, v in row.items()), (C, method, row)
    assert list(metrics["timing"]) == ["context", "scenes", "repeat", "encode_scene_s_per_scene",
                                       "render_cached_one_s_per_view", "render_reencode_s_per_view",
                                       "speedup_vs_reencode", "total_s"]
    assert all(v is not None and v > 0 for v in metrics["timing"].values()), metrics["timing"]
    meta = metrics["meta"]
    assert meta["query_views"] == [10, 11, 12, 13, 14] and meta["n_queries"] == 10
    assert meta["context_sizes"] == [1, 3] and meta["image_size"] == 16 and meta["seed"] == 5

    # what follows from the definitions: the codebook's row is the same for every C, and with one
    # context view the nearest view and the mean image are that view, the two pose baselines its pose
    c1, c3 = metrics["context"]["1"], metrics["context"]["3"]
    assert c1["codebook"] == c3["codebook"]
    assert c1["nearest_view"] == c1["mean_image"]
    assert c1["closest_image_pose"] == c1["mean_pose"]

    # every row recomputed outside evaluate(), its metrics and baselines written out in NumPy here.
    # The same uint8 images and float64 poses, summed in another order, the angle by another
    # formula (arccos, ~1e-14 rad off here): 1e-9 relative; one pixel one level off moves MAE by ~1e-5
    images, poses = generate_scenes(5, 2, size=16)  # (2, 15, 16, 16, 3), (2, 15, 7)
    for C in (1, 3):
        want = rows_by_hand(cb, tf, images, poses, C)
        assert list(want) == list(metrics["context"][str(C)])
        for method, row in want.items():
            got = metrics["context"][str(C)][method]
            assert list(row) == list(got)[:len(row)], (C, method)  # the token figures: test_tokens.py
            for name, value in row.items():
                assert got[name] == pytest.approx(value, rel=1e-9, abs=1e-9), (C, method, name, got[name], value)

    md = (out / "metrics.md").read_text()
    assert "## Context 1 view" in md and "## Context 3 views" in md and "| pyvf |" in md
    for name in ("views.png", "poses.png"):
        with Image.open(out / name) as im:
            im.load()
            assert im.format == "PNG" and im.size[0] > 100 and im.size[1] > 100, (name, im.size)


# ---------------------------------------------------------------------------------------
# pyvf.models


def test_load_pretrained_given_files_and_mismatch(models, tmp_path, monkeypatch):
    cb, tf, cb_path, tf_path = models
    cb2, tf2 = pyvf.models.load_pretrained(cb_path, tf_path)
    assert cb2.config == cb.config and tf2.config == tf.config
    for field, value, named in (("n_embeddings", 64, "n_embeddings"), ("token_image_size", 4, "token images")):
        pyvf.Transformer(pyvf.TransformerConfig(**{**TRANSFORMER, field: value})).save(tmp_path / "other.npz")
        with pytest.raises(ValueError, match=named):
            pyvf.models.load_pretrained(cb_path, tmp_path / "other.npz")
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        pyvf.models.load_pretrained(tmp_path / "missing.npz", tf_path)
    monkeypatch.setitem(pyvf.models.PRETRAINED, "codebook", "never-shipped.npz")  # the shipped file's absence
    with pytest.raises(FileNotFoundError, match="never-shipped.npz"):
        pyvf.models.load_pretrained()


# ---------------------------------------------------------------------------------------
# (e) the commands, as a user runs them


def test_evaluate_command_and_the_demo_without_models(models, tmp_path, monkeypatch, capsys):
    """`pyvf evaluate` on given model files (in-process; the demo on the shipped models is
    test_cli.py's): its options reach evaluate(). The demo without models names the missing file."""
    _, _, cb_path, tf_path = models
    monkeypatch.chdir(tmp_path)
    assert main(["evaluate", "--scenes", "1", "--context", "2,1", "--seed", "3", "--out", "ev", "--codebook",
                 cb_path, "--transformer", tf_path, "--no-progress", "--decode", "argmax"]) == 0
    with open(tmp_path / "ev" / "metrics.json") as f:
        metrics = json.load(f)
    assert list(metrics["context"]) == ["1", "2"] and metrics["meta"]["scenes"] == 1
    assert metrics["meta"]["decode"] == "argmax"  # not the default: the option reaches evaluate()
    assert metrics["meta"]["sources"] == {"codebook": cb_path, "transformer": tf_path}
    assert (tmp_path / "ev" / "metrics.md").is_file() and (tmp_path / "ev" / "views.png").is_file()

    capsys.readouterr()
    assert main(["demo", "--codebook", "missing-cb.npz", "--transformer", "missing-tf.npz", "--out", "d2"]) == 1
    assert "missing-cb.npz" in capsys.readouterr().err and not (tmp_path / "d2").exists()
    with pytest.raises(SystemExit) as e:
        main(["evaluate", "--context", "0,1", "--out", "x"])
    assert e.value.code == 2 and "--context" in capsys.readouterr().err


def test_verdicts_at_each_context_and_the_goal_at_contexts_3_and_5():
    """Hand-made metrics, every baseline's figures distinct: at context 3 pyvf beats every baseline
    on every figure; at context 5 it loses mean_image's MAE (2.0 vs 1.5) and closest_image_pose's
    orientation (10 vs 8). verdict_lines(context=C) reads that context, not the largest; goal_line
    names exactly the figures that hold and fail (an inverted comparison or a swapped baseline
    would move them); the model card's section (tools/model_card.py, goal_line's home) has every
    context, then them."""
    from pyvf.evaluate.run import verdict_lines
    spec = importlib.util.spec_from_file_location(
        "model_card", os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tools",
                                   "model_card.py"))
    card = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(card)
    goal_line = card.goal_line

    def row(mae=None, rmse=None, pos=None, ori=None):
        return {k: v for k, v in (("mae", mae), ("rmse", rmse), ("position_error_median", pos),
                                  ("orientation_error_median_deg", ori)) if v is not None}

    c3 = {"pyvf": row(2.0, 9.0, 1.0, 10.0), "nearest_view": row(3.0, 10.0), "mean_image": row(4.0, 11.0),
          "closest_image_pose": row(pos=2.0, ori=12.0), "mean_pose": row(pos=3.0, ori=14.0)}
    c5 = {"pyvf": row(2.0, 9.0, 1.0, 10.0), "nearest_view": row(3.0, 10.0), "mean_image": row(1.5, 11.0),
          "closest_image_pose": row(pos=2.0, ori=8.0), "mean_pose": row(pos=3.0, ori=14.0)}
    metrics = {"context": {"3": c3, "5": c5, "10": c3}, "meta": {"scenes": 7}}
    lines = verdict_lines(metrics, context=5)
    assert lines == ["Does pyvf beat the baselines? (context 5, 7 held-out scenes; lower is better)",
                     "- nearest_view: yes (MAE 2.00 vs 3.00, RMSE 9.00 vs 10.00)",
                     "- mean_image: partly (MAE 2.00 vs 1.50, RMSE 9.00 vs 11.00)",
                     "- closest_image_pose: partly (position 1.00 vs 2.00, orientation (deg) 10.00 vs 8.00)",
                     "- mean_pose: yes (position 1.00 vs 3.00, orientation (deg) 10.00 vs 14.00)"]
    assert all(" yes (" in x for x in verdict_lines(metrics, context="3")[1:])
    every = ("nearest_view (MAE, RMSE), mean_image (MAE, RMSE), closest_image_pose (position, orientation), "
             "mean_pose (position, orientation)")
    assert goal_line(metrics) == (
        f"- the goal, at contexts 3 and 5: pyvf beats {every}: not met. Context 3: beats {every} (all). "
        "Context 5: beats nearest_view (MAE, RMSE), mean_image (RMSE), closest_image_pose "
        "(position), mean_pose (position, orientation); does not beat mean_image (MAE), closest_image_pose "
        "(orientation).")
    assert ": met. " in goal_line(metrics, contexts=(3, 10))
    assert ": not shown (a context is missing). Context 3: " in goal_line({"context": {"3": c3}})
    assert goal_line({"context": {"3": c3}}).endswith("Context 5: not evaluated.")

    section = card._baselines(metrics)
    assert section[0] == "## Against the baselines"
    heads = [x for x in section if x.startswith("Does pyvf beat")]
    assert [h.split(",")[0] for h in heads] == ["Does pyvf beat the baselines? (context 3",
                                                "Does pyvf beat the baselines? (context 5",
                                                "Does pyvf beat the baselines? (context 10"]
    assert section.index(lines[2]) > section.index(heads[1]) and goal_line(metrics) in section
    assert sum("the paper's SM7 models" in x for x in section) == 1


# ---------------------------------------------------------------------------------------
# render_images: logits -> images, by the most likely code or by the expected code vector


def _spy_latents(cb, monkeypatch):
    """Record every z that reaches cb.decode_latent (then decode it as usual)."""
    seen, real = [], cb.decode_latent

    def spy(z):
        seen.append(z.copy())
        return real(z)

    monkeypatch.setattr(cb, "decode_latent", spy)
    return seen


def test_render_images_expected_is_the_softmax_mean_of_the_codes(models, monkeypatch):
    """decode="expected": each token's latent is sum_j p_j e_j, p the softmax of its logits. The
    oracle here loops over views and tokens and places token t at row t // k, column t % k, so a
    softmax over the wrong axis, E for E.T, or a transposed token grid fails it. The latents are
    float32 from a float64 sum: one float32 rounding, 6e-8 of max|z|; bound 1e-6 relative."""
    cb = models[0]
    k, K, E = cb.config.token_size, cb.config.n_embed, cb.quantizer.embeddings.astype(np.float64)
    logits = np.random.default_rng(2).normal(0, 3, (2, 3, k * k, K)).astype(np.float32)  # (B, M, L, K)
    seen = _spy_latents(cb, monkeypatch)
    images = pyvf.evaluate.render_images(cb, logits, "expected", batch=4)
    assert images.shape == (2, 3, 16, 16, 3) and images.dtype == np.uint8
    z = np.concatenate(seen)  # (6, D, k, k), decoded 4 then 2
    assert len(seen) == 2 and z.shape == (6, E.shape[0], k, k)
    want = np.empty(z.shape)
    for v, view in enumerate(logits.reshape(6, k * k, K).astype(np.float64)):
        for t, row in enumerate(view):
            p = np.exp(row - np.logaddexp.reduce(row))  # another form of the softmax
            want[v, :, t // k, t % k] = E @ p
    assert_close("expected latents", z, want, rtol=1e-6)
    np.testing.assert_array_equal(images.reshape(6, 16, 16, 3), to_uint8(cb.decode_latent(z)))


def test_render_images_argmax_and_a_certain_expected_agree(models):
    """A margin of 1e4 makes the softmax exactly one-hot in float64 (exp(-1e4) is 0), so the
    expected code vector is the code itself and both decodes give the same bytes (decode_latent of
    the codes' vectors is decode_code of the codes); argmax is decode_code of each token's largest logit."""
    cb = models[0]
    k, K = cb.config.token_size, cb.config.n_embed
    codes = np.random.default_rng(3).integers(0, K, (5, k * k))
    logits = np.zeros((5, k * k, K), np.float32)
    np.put_along_axis(logits, codes[..., None], 1e4, axis=-1)
    by_argmax = pyvf.evaluate.render_images(cb, logits, "argmax")
    np.testing.assert_array_equal(by_argmax, to_uint8(cb.decode_code(codes.reshape(5, k, k))))
    np.testing.assert_array_equal(pyvf.evaluate.render_images(cb, logits, "expected"), by_argmax)


def test_evaluate_expected_decode_is_recorded_and_renders_differently(models, smoke, tmp_path):
    """The same scenes through both decodes: the meta and the markdown say which; the poses and
    the baselines do not depend on it; the renderings do (random logits are far from one-hot)."""
    a = smoke[0]
    b = evaluate(models[0], models[1], out=str(tmp_path / "ev"), **SMOKE)  # the default: expected
    assert a["meta"]["decode"] == "argmax" and b["meta"]["decode"] == "expected" == pyvf.evaluate.DEFAULT_DECODE
    assert "(decode=expected)" in (tmp_path / "ev" / "metrics.md").read_text()
    ra, rb = a["context"]["3"], b["context"]["3"]
    for method in METHODS:
        if method != "pyvf":
            assert ra[method] == rb[method], method
    for name in ("position_error_median", "orientation_error_median_deg"):
        assert ra["pyvf"][name] == rb["pyvf"][name]
    assert ra["pyvf"]["mae"] != rb["pyvf"]["mae"]


# ---------------------------------------------------------------------------------------
# refusals: one table, the exception type and the argument's name


def _no_work(monkeypatch):
    """evaluate's arguments are refused before any scene is generated (timing_scenes=0 crashed
    after every scene was scored)."""
    def generate(*args, **kwargs):
        raise AssertionError("the work started")
    monkeypatch.setattr(pyvf.evaluate.run, "generate_scenes", generate)


NAN_X = np.zeros((1, 3, 2, 2))
NAN_X[0, 1, 1, 0] = np.nan  # a NaN in a decoder's output has no picture: it used to become black


def _logits(cb, bad=None, extra=0, dtype=np.float32):
    """Logits (2, 3, L, K + extra); one entry set to `bad`."""
    x = np.zeros((2, 3, cb.config.token_size ** 2, cb.config.n_embed + extra), dtype)
    if bad is not None:
        x[1, 2, 5, 7] = bad
    return x


@pytest.mark.parametrize("call, error, name", [
    (lambda cb, tf: to_uint8(NAN_X), ValueError, "x"),  # a NaN has no picture: it used to become black
    (lambda cb, tf: to_model_images(np.zeros((1, 2, 3, 3, 3), np.uint8), np.float32), ValueError, "images"),
    (lambda cb, tf: pyvf.evaluate.render_images(cb, _logits(cb), "mode"), ValueError, "decode"),
    (lambda cb, tf: pyvf.evaluate.render_images(cb, _logits(cb, extra=1)), ValueError, "logits"),
    (lambda cb, tf: pyvf.evaluate.render_images(cb, _logits(cb, dtype=np.int64)), TypeError, "logits"),
    (lambda cb, tf: cb.decode_latent(np.zeros((1, 16, 8, 8))), TypeError, "z"),
    (lambda cb, tf: cb.decode_latent(np.zeros((1, 16, 4, 8), np.float32)), ValueError, "z"),
    # argmax picked a NaN's index and returned an image
    *[(lambda cb, tf, bad=bad, d=d: pyvf.evaluate.render_images(cb, _logits(cb, bad), d), ValueError, "logits")
      for bad in (np.nan, np.inf) for d in ("argmax", "expected")],
    (lambda cb, tf: evaluate(cb, tf, scenes=1, context=(11,), progress=False), ValueError, "context"),  # 16 views
    # (1, 2.7) was evaluated as (1, 2), (True,) as (1,)
    *[(lambda cb, tf, c=c: evaluate(cb, tf, scenes=1, context=c, progress=False), TypeError, "context")
      for c in ((1, 2.7), (True,))],
    (lambda cb, tf: evaluate(cb, tf, scenes=0, context=1, progress=False), ValueError, "scenes"),
    (lambda cb, tf: evaluate(cb, tf, scenes=1, context=1, progress=False, timing_scenes=0), ValueError,
     "timing_scenes"),
    (lambda cb, tf: evaluate(cb, tf, scenes=1, context=(1,), decode="sample", progress=False), ValueError, "decode"),
])
def test_refusals_name_the_argument(models, monkeypatch, call, error, name):
    _no_work(monkeypatch)
    with pytest.raises(error, match=rf"\b{name}\b"):
        call(models[0], models[1])
