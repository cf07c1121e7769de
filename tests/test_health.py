"""Training-health figures (pyvf/evaluate/health.py) on hand-made cases with known answers,
and the codebook's weighted reconstruction loss against an independent oracle."""

import dataclasses

import numpy as np
import pytest

from pyvf.models.codebook import Codebook, CodebookConfig
from pyvf.evaluate.health import chroma, codebook_health, colour_r2, effective_rank, object_mask
from pyvf.evaluate.metrics import image_metrics, to_model_images, to_uint8

CB = CodebookConfig(ch=32, ch_mult=(1, 1), num_res_blocks=1, attn_resolutions=(), z_channels=8, embed_dim=8,
                    n_embed=16, image_size=16)


def test_effective_rank_known_values(rng):
    # rank 1: every row a multiple of one vector (plus a constant row, which centring removes)
    u, v = rng.standard_normal(200), rng.standard_normal(16)
    assert effective_rank(np.outer(u, v) + rng.standard_normal(16)) == pytest.approx(1.0, abs=1e-6)
    # D equal singular values: orthogonal centred columns of equal norm -> rank D exactly
    q, _ = np.linalg.qr(rng.standard_normal((200, 8)))
    q -= q.mean(axis=0)
    q, _ = np.linalg.qr(q)  # still orthonormal; centred columns stay centred up to rounding
    assert effective_rank(q[:, :8] - q[:, :8].mean(axis=0)) == pytest.approx(8.0, rel=1e-6)
    # two directions of singular values 3:1 -> exp(H(3/4, 1/4))
    z = np.zeros((4, 2))
    z[:, 0], z[:, 1] = [3, -3, 3, -3], [1, 1, -1, -1]
    p = np.array([0.75, 0.25])
    assert effective_rank(z) == pytest.approx(np.exp(-(p * np.log(p)).sum()), rel=1e-12)
    assert effective_rank(np.ones((5, 3))) == 0.0  # no variance at all
    # a constant latent whose mean is not exact (three 0.1 do not average to 0.1): centred rows of
    # 1e-17 gave rank 1.0, not 0
    for z in (np.full((3, 4), 0.1), np.full((7, 5), 1 / 3), np.full((4, 2), 0.1, np.float32)):
        assert effective_rank(z) == 0.0


def _objects(rng, n=6, size=16):
    """Images of a flat background (38, 38, 38) with coloured squares of random saturated colours."""
    im = np.full((n, size, size, 3), 38, np.uint8)
    for i in range(n):
        y, x = rng.integers(2, size - 7, 2)
        im[i, y:y + 5, x:x + 5] = rng.choice([0, 128, 255], 3) if i % 2 else rng.integers(0, 256, 3)
    return im


def test_object_mask_and_colour_r2_hand_made(rng):
    im = _objects(rng)
    mask = object_mask(im)
    assert mask.shape == im.shape[:-1] and (mask.sum(axis=(1, 2)) == 25).all()
    assert colour_r2(im, im, mask) == 1.0  # a perfect reconstruction
    # every object drawn grey (its brightness kept): the chroma is 0 everywhere -> r2 <= 0
    grey = im.copy()
    grey[mask] = im[mask].mean(axis=-1, keepdims=True).astype(np.uint8)
    ct = chroma(im[mask])
    assert colour_r2(grey, im, mask) == pytest.approx(
        1 - (ct ** 2).sum() / ((ct - ct.mean(0)) ** 2).sum(), abs=0.02)  # grey: |chroma| <= 1.5 after rounding
    # red and cyan swapped (each channel inverted on the objects): the colours point the other way
    swapped = im.copy()
    swapped[mask] = 255 - im[mask]
    assert colour_r2(swapped, im, mask) < -1.0
    # brightness alone does not count: a darker copy of a grey object is still perfect
    flat = np.full((1, 8, 8, 3), 38, np.uint8)
    flat[0, 2:5, 2:5] = [200, 100, 50]
    flat[0, 5:7, 5:7] = [50, 200, 100]
    m = object_mask(flat)
    assert colour_r2(flat, flat, m) == 1.0
    assert np.isnan(colour_r2(flat, flat, np.zeros_like(m)))  # no object pixels


def test_codebook_health_against_its_definition(rng):
    cb = Codebook(CB, seed=3)
    im = _objects(rng, n=5)
    before = {k: v.copy() for k, v in cb.quantizer.state_dict().items()}
    h = codebook_health(cb, im, batch=2)  # batches of 2, 2, 1
    for k, v in cb.quantizer.state_dict().items():  # inference only: the EMA buffers are untouched
        assert np.array_equal(v, before[k]), k
    x = to_model_images(im, np.float32)
    codes = cb.encode(x)
    rec = to_uint8(cb.decode_code(codes))
    m = image_metrics(rec, im)
    assert (h["mae"], h["rmse"], h["psnr"]) == (m["mae"].mean(), m["rmse"].mean(), m["psnr"].mean())
    assert h["codes_in_use"] == len(np.unique(codes))
    counts = np.unique(codes, return_counts=True)[1] / codes.size
    assert h["perplexity"] == pytest.approx(np.exp(-(counts * np.log(counts)).sum()), rel=1e-12)
    z, codes2 = cb.encode(x, return_latent=True)
    assert np.array_equal(codes2, codes) and z.shape == (5, CB.embed_dim, 8, 8)
    assert h["latent_rank"] == pytest.approx(effective_rank(z.transpose(0, 2, 3, 1).reshape(-1, 8)), rel=1e-9)
    assert h["colour_r2"] == colour_r2(rec, im, object_mask(im))


def test_pixel_weights_equal_repeated_images(rng):
    """Integer weights are repeated images: weights (2 on image a, 1 on image b) give the loss and
    every parameter gradient of the unweighted batch [a, a, b] (commitment weight 0, so that only
    the reconstruction term counts; GroupNorm normalises each image alone). Float64: the two
    computations differ only in summation order (bound: 1e-12 relative, far above the ~1e-15
    rounding and far below any error in the weights' normalisation)."""
    cfg = dataclasses.replace(CB, dtype="float64", codebook_weight=0.0)
    cb = Codebook(cfg, seed=1)
    x = rng.uniform(-1, 1, (2, 3, 16, 16))
    w = np.ones((2, 1, 16, 16))
    w[0] = 2.0
    out = cb.forward(x, pixel_weights=w)
    g = cb.backward()
    ref = cb.forward(x[[0, 0, 1]])
    g_ref = cb.backward()
    assert out.rec_loss == pytest.approx(ref.rec_loss, rel=1e-13)
    # absolute bound on the scale of all gradients: a bias before a GroupNorm has a gradient that
    # is zero in exact arithmetic, rounding noise of ~1e-18 here, relative to nothing
    scale = max(np.abs(v).max() for v in g_ref.values())
    for k in g_ref:
        np.testing.assert_allclose(g[k], g_ref[k], rtol=1e-12, atol=1e-13 * scale, err_msg=k)
    # equal weights are the plain mean
    out1 = cb.forward(x, pixel_weights=np.full((2, 1, 16, 16), 0.5))
    assert out1.rec_loss == pytest.approx(cb.forward(x).rec_loss, rel=1e-14)
    for bad, error in ((w.astype(np.float32), TypeError), (w[:, :, :8], ValueError), (-w, ValueError),
                       (0 * w, ValueError)):
        with pytest.raises(error, match=r"\bpixel_weights\b"):
            cb.forward(x, pixel_weights=bad)


def test_token_scores_against_torch(rng):
    """Held-out cross-entropy and token accuracy against torch's cross_entropy (float64)."""
    import torch  # the oracle: installed with the tests, never skipped

    from pyvf.evaluate.run import _token_scores

    logits = (rng.standard_normal((2, 3, 5, 7)) * 30).astype(np.float32)  # large: log-sum-exp must be stable
    tokens = rng.integers(0, 7, (2, 3, 5))
    empty = rng.random((2, 3, 5)) < 0.5
    got = _token_scores(logits, tokens, empty)
    t = torch.from_numpy(logits.astype(np.float64)).reshape(-1, 7)
    ce = torch.nn.functional.cross_entropy(t, torch.from_numpy(tokens).reshape(-1), reduction="none")
    np.testing.assert_allclose(got["ce"].ravel(), ce.reshape(6, 5).mean(1).numpy(), rtol=1e-12)
    acc = (t.argmax(1).reshape(6, 5) == torch.from_numpy(tokens).reshape(6, 5)).double().mean(1).numpy()
    np.testing.assert_array_equal(got["token_accuracy"].ravel(), acc)
    e = torch.from_numpy(empty.ravel())
    np.testing.assert_allclose(got["ce_empty"], ce[e].numpy(), rtol=1e-12)  # per token, in order
    np.testing.assert_allclose(got["ce_object"], ce[~e].numpy(), rtol=1e-12)


def test_transformer_health_is_evaluate_on_the_same_scenes():
    """transformer_health's columns are pyvf evaluate's numbers for the same scenes, method by
    method (the shipped models; a column wired to the wrong method or context fails)."""
    from pyvf.evaluate.health import transformer_health
    from pyvf.evaluate.run import evaluate
    from pyvf.models import load_pretrained
    from pyvf.scenes import generate_scenes

    cb, tf = load_pretrained()
    images, poses = generate_scenes(7, 1, size=cb.config.image_size)
    tokens = np.stack([cb.encode(to_model_images(v, np.float32)).reshape(15, -1) for v in images])
    h = transformer_health(cb, tf, images, poses, tokens, (1, 5), batch=2)
    m = evaluate(cb, tf, scenes=1, context=(1, 5), seed=7, batch=2, progress=False, timing_scenes=1, repeat=1,
                 decode="argmax")  # the health's decode (its docstring says why)
    names = {"mae": ("pyvf", "mae"), "nearest_view_mae": ("nearest_view", "mae"),
             "mean_image_rmse": ("mean_image", "rmse"), "position": ("pyvf", "position_error_median"),
             "orientation": ("pyvf", "orientation_error_median_deg"),
             "closest_image_orientation": ("closest_image_pose", "orientation_error_median_deg"),
             "mean_pose_position": ("mean_pose", "position_error_median")}
    for C in (1, 5):
        for stem, (method, metric) in names.items():
            assert h[f"{stem}_c{C}"] == m["context"][str(C)][method][metric], (stem, C)
        assert 0 <= h[f"token_accuracy_c{C}"] <= 1 and h[f"ce_c{C}"] > 0
