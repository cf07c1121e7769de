"""The whole codebook against the torch oracle written from docs/math.md §4 (pyvf/verify/torch_ports.py):
codes, reconstructions, losses, every parameter gradient, the EMA buffers over three training
steps; official names; encode/decode; bad input."""

import dataclasses
import json
import os

import numpy as np
import pytest
import torch

from conftest import assert_close
from pyvf.models.codebook import Codebook, CodebookConfig, parameter_shapes
from pyvf.verify import convert_torch
from pyvf.verify.torch_ports import CodebookPort, codebook_forward
from test_codebook_trace import SMALL, random_codebook

SPEC = os.path.join(os.path.dirname(__file__), "data", "official-codebook-tiny.json")


def tiny_config(**kw):
    with open(SPEC) as f:
        c = json.load(f)["config"]
    fields = {k: c[k] for k in ("ch", "ch_mult", "num_res_blocks", "attn_resolutions", "z_channels", "embed_dim",
                                "n_embed", "image_size")}
    return CodebookConfig(**{**fields, **kw})


def torch_state(cb):
    P = {k: torch.tensor(v, requires_grad=True) for k, v in cb.params.items()}
    q = cb.quantizer
    buffers = {"quantize.embeddings": torch.tensor(q.embeddings),
               "quantize.ema_cluster_size_hidden": torch.tensor(q.ema_cluster_size_hidden),
               "quantize.ema_dw_hidden": torch.tensor(q.ema_dw_hidden), "quantize.counter": q.counter}
    return P, buffers


def test_parameter_names_and_shapes_are_the_official_ones():
    with open(SPEC) as f:
        want = {k: tuple(v) for k, v in json.load(f)["state_dict"].items() if not k.startswith("quantize.")}
    cfg = tiny_config()
    assert parameter_shapes(cfg) == want
    assert {n: tuple(p.shape) for n, p in CodebookPort(cfg).named_parameters()} == want


def with_empty_patches(images, p):
    """Every other p x p patch of each image made empty: all its pixels the top-left pixel's colour."""
    images[:, :, :p, :p] = images[:, :, :1, :1]
    images[:, :, -p:, :p] = images[:, :, :1, :1]
    return images


CONFIGS = {  # the official tiny one at 32 x 32 (its levels and attention at the last level, 4x faster)
    "small": dict(SMALL), "official tiny": dict(image_size=32, attn_resolutions=(4,)),
    "empty code": dict(SMALL, empty_code=True),  # pyvf's own (docs/math.md §4): the torch port has it
}


@pytest.mark.parametrize("config", list(CONFIGS))
def test_codebook_matches_torch_over_three_training_steps(config, rng):
    cfg = (tiny_config if config == "official tiny" else CodebookConfig)(**CONFIGS[config], dtype="float64")
    cb = random_codebook(cfg, rng)
    P, buffers = torch_state(cb)
    steps = 1 if config == "official tiny" else 3
    for step in range(steps):
        images = rng.uniform(-1, 1, (2, cfg.in_channels, cfg.image_size, cfg.image_size))
        if cfg.empty_code:  # an empty patch takes code 0 whatever is nearest; no other patch does
            images = with_empty_patches(images, cfg.image_size // cfg.token_size)
            assert (cb.empty_patches(images).sum(), cb.empty_patches(images)[:, 0, 0].all()) == (4, True)
        out = cb.forward(images, train=True)
        grads = cb.backward()
        for p in P.values():
            p.grad = None
        ref = codebook_forward(P, buffers, torch.tensor(images), cfg)
        ref["loss"].backward()
        np.testing.assert_array_equal(out.codes, ref["codes"].numpy())
        if cfg.empty_code:
            np.testing.assert_array_equal(out.codes == 0, cb.empty_patches(images))
        # float64 through ~30 layers: measured <= 1e-13; 1e-11 leaves room
        assert_close(f"reconstruction {step}", out.reconstruction, ref["reconstruction"].detach().numpy(), rtol=1e-11)
        assert abs(out.rec_loss - ref["rec_loss"].item()) <= 1e-12 * ref["rec_loss"].item()
        assert abs(out.commitment_loss - ref["commitment_loss"].item()) <= 1e-11 * ref["commitment_loss"].item()
        # a bias feeding a GroupNorm with one channel per group (32 channels, 32 groups) has an
        # exactly zero gradient (the norm subtracts it); both sides give rounding noise there, so
        # the bound has a floor relative to the model's largest gradient
        scale = max(np.abs(P[n].grad.numpy()).max() for n in grads)
        for name, g in grads.items():
            assert_close(f"d{name} step {step}", g, P[name].grad.numpy(), rtol=1e-10, atol=1e-12 * scale)
        buffers = ref["buffers"]
        q = cb.quantizer
        assert q.counter == buffers["quantize.counter"]
        for name, mine in (("embeddings", q.embeddings), ("ema_cluster_size_hidden", q.ema_cluster_size_hidden),
                           ("ema_dw_hidden", q.ema_dw_hidden)):
            assert_close(f"{name} step {step}", mine, buffers["quantize." + name].numpy(), rtol=1e-12)


def test_float32_tracks_float64(rng):
    cb64 = random_codebook(CodebookConfig(**SMALL, dtype="float64"), rng)
    cb32 = Codebook(CodebookConfig(**SMALL))
    cb32.load_official(cb64.state_dict())
    images = rng.uniform(-1, 1, (2, 3, 16, 16))
    o64, g64 = cb64.forward(images), cb64.backward()
    o32, g32 = cb32.forward(images.astype(np.float32)), cb32.backward()
    assert o32.reconstruction.dtype == np.float32
    np.testing.assert_array_equal(o32.codes, o64.codes)  # no near-tie in this draw
    # float32 through ~20 layers: measured ~1e-6; 2e-5 and gradients 2e-4 (sums of many terms)
    assert_close("reconstruction f32", o32.reconstruction, o64.reconstruction, rtol=2e-5)
    scale = max(np.abs(g).max() for g in g64.values())  # zero-gradient biases: see above
    for name in g64:
        assert_close(f"d{name} f32", g32[name], g64[name], rtol=2e-4, atol=1e-6 * scale)


def test_encode_decode_and_eval_leaves_buffers(rng):
    cb = random_codebook(CodebookConfig(**SMALL, dtype="float64"), rng)
    images = rng.uniform(-1, 1, (3, 3, 16, 16))
    before = cb.state_dict()
    codes = cb.encode(images)
    assert codes.shape == (3, 8, 8) and codes.dtype == np.int64
    out = cb.forward(images, train=False)
    np.testing.assert_array_equal(codes, out.codes)
    # decode_code of the codes is the forward's reconstruction (straight-through value e, up to
    # the one rounding of z + (e - z))
    assert_close("decode_code", cb.decode_code(codes), out.reconstruction, rtol=1e-12)
    for name, value in cb.state_dict().items():
        np.testing.assert_array_equal(value, before[name])


def test_pixel_weights_near_float32_max_give_the_gradient_of_small_ones(rng):
    """rec_loss = sum w |rec - x| / (C sum w) does not change when every weight is scaled by one
    factor. Weights near float32's largest (C sum w overflows float32) must give the loss and
    every gradient of the same weights scaled down: with a power of two, exactly (the float64
    normalisation divides out the scale exactly), where an overflow gave w / inf = 0, an all-zero
    gradient with a correct-looking loss. The loss itself against a float64 sum of the weighted
    errors of the reconstruction."""
    cb = random_codebook(CodebookConfig(**SMALL), rng)
    x = rng.uniform(-1, 1, (2, 3, 16, 16)).astype(np.float32)
    w = rng.uniform(0.25, 1.0, (2, 1, 16, 16)).astype(np.float32)
    out = cb.forward(x, pixel_weights=w)
    g = cb.backward()
    err = np.abs(out.reconstruction.astype(np.float64) - x)  # (B, C, S, S)
    want = (w * err).sum() / (3 * w.astype(np.float64).sum())
    # the model forms rec - x in float32 (one rounding, <= 2^-24 relative, per element): rel 1e-7
    assert out.rec_loss == pytest.approx(want, rel=1e-7)
    big = w * np.float32(2.0 ** 127)  # exact; up to 1.7e38, C sum w ~ 4e41 is past float32's 3.4e38
    out_big = cb.forward(x, pixel_weights=big)
    g_big = cb.backward()
    assert out_big.rec_loss == out.rec_loss and out_big.loss == out.loss
    assert np.abs(g["decoder.conv_out.weight"]).max() > 0
    for name in g:
        np.testing.assert_array_equal(g_big[name], g[name], err_msg=name)


def test_torch_checkpoint_converter(rng, tmp_path):
    """A model.ckpt as the published training writes it (torch.save of a dict with state_dict,
    extra loss-network keys beside the model's) converts to an .npz that loads to the same model."""
    cfg = CodebookConfig(**SMALL)
    cb = random_codebook(cfg, rng)
    sd = {k: torch.tensor(v) for k, v in cb.state_dict().items()}
    sd["loss.perceptual_loss.net.lin0.weight"] = torch.zeros(3)  # not the model's: skipped
    ckpt = tmp_path / "model.ckpt"
    torch.save({"state_dict": sd, "epoch": 3}, ckpt)
    config = tmp_path / "config.json"
    config.write_text(json.dumps(dataclasses.asdict(cfg)))
    out = tmp_path / "codebook.npz"
    convert_torch.convert_checkpoint(ckpt, config, out)
    loaded = Codebook.load(out).state_dict()
    for name, value in cb.state_dict().items():
        np.testing.assert_array_equal(loaded[name], value)


# ---------------------------------------------------------------------------------------
# refusals: one table per entry point, the exception type and the argument's name


X = np.random.default_rng(0).uniform(-1, 1, (2, 3, 16, 16)).astype(np.float32)  # (B, 3, S, S) in [-1, 1]


def _run(call, arg):
    cb = Codebook(CodebookConfig(**SMALL), seed=3)
    if call in ("forward", "train", "encode"):
        return {"forward": cb.forward, "train": lambda a: cb.forward(a, train=True), "encode": cb.encode}[call](arg)
    if call == "pixel_weights":
        return cb.forward(X, pixel_weights=arg)
    if call in ("decode_code", "decode_latent", "load_official"):
        return getattr(cb, call)(arg if call != "load_official" else arg(cb.state_dict()))
    cb.forward(X)
    return cb.backward(**arg)


def _without(state, name):
    return {k: v for k, v in state.items() if k != name}


@pytest.mark.parametrize("call, arg, error, name", [
    ("forward", X.astype(np.float64), TypeError, "images"),
    ("forward", X[:, :, :8].copy(), ValueError, "images"),
    ("train", np.full_like(X, np.nan), ValueError, "images"),
    ("train", X * np.float32(1.01) + np.float32(0.02), ValueError, "images"),  # out of [-1, 1]
    ("encode", X.transpose(0, 2, 3, 1).copy(), ValueError, "images"),  # channels last
    ("pixel_weights", np.ones((2, 1, 16, 16)), TypeError, "pixel_weights"),  # float64 for float32 images
    ("pixel_weights", np.ones((2, 3, 16, 16), np.float32), ValueError, "pixel_weights"),
    ("pixel_weights", -np.ones((2, 1, 16, 16), np.float32), ValueError, "pixel_weights"),
    ("decode_code", np.full((1, 8, 8), 16), ValueError, "codes"),
    ("decode_code", np.zeros((1, 8, 8), np.float32), TypeError, "codes"),
    ("decode_code", np.zeros((1, 4, 4), np.int64), ValueError, "codes"),
    ("decode_latent", np.zeros((1, 8, 8, 8)), TypeError, "z"),
    ("decode_latent", np.full((1, 8, 8, 8), np.nan, np.float32), ValueError, "z"),
    ("backward", dict(drec=np.ones((2, 3, 16, 16))), TypeError, "drec"),
    ("backward", dict(drec=np.ones((2, 3, 16, 8), np.float32)), ValueError, "drec"),
    ("backward", dict(drec=np.full((2, 3, 16, 16), np.nan, np.float32)), ValueError, "drec"),
    ("backward", dict(dloss=float("nan")), ValueError, "dloss"),
    ("load_official", lambda s: _without(s, "encoder.conv_in.bias"), ValueError, "encoder.conv_in.bias"),
    ("load_official", lambda s: {**s, "encoder.extra.weight": np.zeros(3, np.float32)}, ValueError,
     "encoder.extra.weight"),
    ("load_official", lambda s: {**s, "encoder.conv_in.weight": np.zeros((3, 32, 3, 3), np.float32)}, ValueError,
     "encoder.conv_in.weight"),
    ("load_official", lambda s: {**s, "quantize.counter": np.array(-1)}, ValueError, "quantize.counter"),
    ("load_official", lambda s: {**s, "quantize.counter": 2 ** 63}, ValueError, "quantize.counter"),  # int64's
    ("load_official", lambda s: {**s, "quantize.embeddings": np.zeros((16, 8), np.float32)}, ValueError,
     "quantize.embeddings"),  # transposed
    # float64 past float32's largest into a float32 model: inf (numpy only warns)
    ("load_official", lambda s: {**s, "encoder.conv_in.bias": np.full(32, 1e39)}, ValueError, "encoder.conv_in.bias"),
])
def test_entry_point_refusals(call, arg, error, name):
    with pytest.raises(error, match=rf"\b{name}\b"):
        _run(call, arg)


@pytest.mark.parametrize("field, value, error", [
    ("ch", 16, ValueError),  # not divisible by the 32 GroupNorm groups
    ("image_size", 15, ValueError),
    ("codebook_weight", float("nan"), ValueError),
    ("perceptual_weight", 0.5, ValueError),  # LPIPS is not implemented
    ("decay", 1.0, ValueError),
    ("eps", 0.0, ValueError),
    ("codebook_weight", "1", TypeError),
    ("ch_mult", (1, 0), ValueError),
    ("ch_mult", (1, 2.0), TypeError),
    ("dtype", "float16", ValueError),
])
def test_config_refusals(field, value, error):
    with pytest.raises(error, match=rf"\b{field}\b"):
        CodebookConfig(**{**SMALL, field: value})
