"""The whole codebook against the torch oracle written from docs/math.md §4 (tests/torch_codebook.py):
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
from pyvf.verify import convert_torch, torch_codebook

SPEC = os.path.join(os.path.dirname(__file__), "data", "official-codebook-tiny.json")


def tiny_config(**kw):
    with open(SPEC) as f:
        c = json.load(f)["config"]
    fields = {k: c[k] for k in ("ch", "ch_mult", "num_res_blocks", "attn_resolutions", "z_channels", "embed_dim",
                                "n_embed", "image_size")}
    return CodebookConfig(**{**fields, **kw})


SMALL = dict(ch=32, ch_mult=(1, 2), num_res_blocks=1, attn_resolutions=(8,), z_channels=32, embed_dim=8,
             n_embed=16, image_size=16)


def random_codebook(cfg, rng):
    """Every parameter random (GroupNorm gammas != 1, biases != 0): a role mix-up shows."""
    cb = Codebook(cfg, seed=1)
    for name, p in cb.params.items():
        if p.ndim == 1:
            cb.params[name] = (rng.normal(1.0 if name.endswith(".weight") else 0.0, 0.2, p.shape)).astype(p.dtype)
    return cb


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
    assert torch_codebook.parameter_shapes(dataclasses.replace(cfg)) == want


@pytest.mark.parametrize("config", ["small", "official tiny"])
def test_codebook_matches_torch_over_three_training_steps(config, rng):
    cfg = CodebookConfig(**SMALL, dtype="float64") if config == "small" else tiny_config(dtype="float64")
    cb = random_codebook(cfg, rng)
    P, buffers = torch_state(cb)
    steps = 3 if config == "small" else 1
    for step in range(steps):
        images = rng.uniform(-1, 1, (2, cfg.in_channels, cfg.image_size, cfg.image_size))
        out = cb.forward(images, train=True)
        grads = cb.backward()
        for p in P.values():
            p.grad = None
        ref = torch_codebook.forward(P, buffers, torch.tensor(images), cfg, cfg.codebook_weight, train=True)
        ref["loss"].backward()
        np.testing.assert_array_equal(out.codes, ref["codes"].numpy())
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


def test_state_dict_save_load_and_bad_weights(rng, tmp_path):
    cb = random_codebook(CodebookConfig(**SMALL), rng)
    cb.forward(rng.uniform(-1, 1, (1, 3, 16, 16)).astype(np.float32), train=True)
    path = tmp_path / "codebook.npz"
    cb.save(path)
    loaded = Codebook.load(path)
    for name, value in cb.state_dict().items():
        np.testing.assert_array_equal(loaded.state_dict()[name], value)
    state = cb.state_dict()
    bad = dict(state)
    bad.pop("encoder.conv_in.bias")
    with pytest.raises(ValueError, match="missing"):
        cb.load_official(bad)
    with pytest.raises(ValueError, match="unexpected"):
        cb.load_official({**state, "encoder.extra.weight": np.zeros(3, np.float32)})
    bad = dict(state)
    bad["encoder.conv_in.weight"] = np.zeros((3, 32, 3, 3), np.float32)  # in/out swapped
    with pytest.raises(ValueError, match=r"'encoder.conv_in.weight' has shape \(3, 32, 3, 3\), expected \(32, 3, 3, 3\)"):
        cb.load_official(bad)


def test_bad_input_raises(rng):
    cb = Codebook(CodebookConfig(**SMALL))
    x = rng.uniform(-1, 1, (1, 3, 16, 16)).astype(np.float32)
    with pytest.raises(TypeError, match="images must be a float32"):
        cb.forward(x.astype(np.float64))
    with pytest.raises(ValueError, match=r"images must have shape \(B, 3, 16, 16\)"):
        cb.forward(x[:, :, :8].copy())
    with pytest.raises(ValueError, match="images contains NaN"):
        cb.forward(np.full_like(x, np.nan))
    # pixels on 0..255 passed as they are: refused by every model call, saying how to convert
    pixels = np.round((x + 1) * 127.5).astype(np.float32)
    for call in (cb.forward, cb.encode, lambda a: cb.forward(a, train=True)):
        with pytest.raises(ValueError, match=r"images must be in \[-1, 1\], got values in \[\d.*to_model_images"):
            call(pixels)
        # the picture as it comes (uint8, channels last), and channels last converted to float only
        picture = pixels.astype(np.uint8).transpose(0, 2, 3, 1).copy()  # (B, S, S, 3)
        with pytest.raises(TypeError, match=r"got uint8: convert uint8 pictures .*to_model_images"):
            call(picture)
        with pytest.raises(TypeError, match=r"got uint8: convert uint8 pictures .*to_model_images"):
            call(picture.transpose(0, 3, 1, 2).copy())
        with pytest.raises(ValueError, match=r"got \(1, 16, 16, 3\): convert uint8 pictures .*to_model_images"):
            call(x.transpose(0, 2, 3, 1).copy())
    with pytest.raises(TypeError, match=r"images must be a float32 numpy array in \[-1, 1\], got float64$"):
        cb.encode(x.astype(np.float64))  # a float of another dtype: no word about pictures
    edge = np.clip(x * np.float32(1.0005), -1.0005, 1.0005).astype(np.float32)  # within the slack of 1e-3
    cb.encode(edge)
    with pytest.raises(ValueError, match="must be in"):
        cb.encode(x * np.float32(1.01) + np.float32(0.02))
    with pytest.raises(ValueError, match=r"codes must be in \[0, 16\)"):
        cb.decode_code(np.full((1, 8, 8), 16))
    with pytest.raises(TypeError, match="codes must be an integer"):
        cb.decode_code(np.zeros((1, 8, 8), np.float32))
    with pytest.raises(RuntimeError, match="needs a forward"):
        Codebook(CodebookConfig(**SMALL)).backward()
    with pytest.raises(ValueError, match="divisible by the 32 GroupNorm groups"):
        CodebookConfig(**{**SMALL, "ch": 16})
    with pytest.raises(ValueError, match="not divisible by"):
        CodebookConfig(**{**SMALL, "image_size": 15})


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
    # equal weights, however large, are the plain mean: the unweighted loss (which numpy sums in
    # float32, pairwise: rel 1e-6) and gradients (1 / numel rounded once to float32 either way)
    plain = cb.forward(x)
    g_plain = cb.backward()
    for value in (1e36, 3e38):
        o = cb.forward(x, pixel_weights=np.full((2, 1, 16, 16), value, np.float32))
        g_w = cb.backward()
        assert o.rec_loss == pytest.approx(plain.rec_loss, rel=1e-6), value
        for name in g_plain:
            assert_close(f"{name} (w={value:g})", g_w[name], g_plain[name], rtol=1e-6)


def test_load_official_refuses_float64_values_beyond_float32(rng):
    """A float64 state dict into a float32 codebook: a value past float32's largest would become
    inf (numpy only warns), in a parameter or in a quantizer buffer. Refused, each named, and
    nothing loaded (parameters and buffers as before); a float64 codebook takes the same values."""
    cb = random_codebook(CodebookConfig(**SMALL), rng)
    cb.forward(rng.uniform(-1, 1, (1, 3, 16, 16)).astype(np.float32), train=True)
    before = cb.state_dict()
    state = {k: v.astype(np.float64) if v.dtype.kind == "f" else v for k, v in before.items()}
    state["encoder.conv_in.bias"][1] = 1e39
    state["quantize.embeddings"][0, 2] = -1e39
    with pytest.raises(ValueError, match=r"load_official: 2 problems: 'encoder.conv_in.bias' holds a value of "
                                         r"magnitude 1e\+39, beyond float32's range.*'quantize.embeddings' "):
        cb.load_official(state)
    for name, value in cb.state_dict().items():
        np.testing.assert_array_equal(value, before[name], err_msg=name)
    cb64 = Codebook(CodebookConfig(**SMALL, dtype="float64"))
    cb64.load_official(state)
    assert cb64.params["encoder.conv_in.bias"][1] == 1e39 and cb64.quantizer.embeddings[0, 2] == -1e39


@pytest.mark.parametrize("field, value, exc, match", [
    # every float field finite (a NaN or inf weight made forward().loss NaN or inf), decay and eps
    # in the quantizer's ranges
    ("codebook_weight", float("nan"), ValueError, r"^CodebookConfig.codebook_weight must be finite"),
    ("codebook_weight", float("inf"), ValueError, r"^CodebookConfig.codebook_weight must be finite"),
    ("perceptual_weight", float("-inf"), ValueError, r"^CodebookConfig.perceptual_weight must be finite"),
    ("decay", float("nan"), ValueError, r"^CodebookConfig.decay must be finite and in \(0.0, 1.0\)"),
    ("decay", 1.0, ValueError, r"^CodebookConfig.decay must be finite and in \(0.0, 1.0\)"),
    ("eps", 0.0, ValueError, r"^CodebookConfig.eps must be finite and in \(0.0"),
    ("codebook_weight", "1", TypeError, r"^CodebookConfig.codebook_weight must be a real number, got str"),
    ("eps", None, TypeError, r"^CodebookConfig.eps must be a real number, got NoneType"),
    # sequences of positive integers, named (not "'int' object is not iterable")
    ("ch_mult", 1, TypeError, r"^CodebookConfig.ch_mult must be a tuple of positive integers, got int 1"),
    ("ch_mult", (1, 0), ValueError, r"^CodebookConfig.ch_mult\[1\] must be a positive integer, got 0"),
    ("ch_mult", (1, 2.0), TypeError, r"^CodebookConfig.ch_mult\[1\] must be an integer, got float"),
    ("ch_mult", (), ValueError, r"^CodebookConfig.ch_mult must name at least one level"),
    ("attn_resolutions", None, TypeError, r"^CodebookConfig.attn_resolutions must be a tuple of positive integers"),
    ("attn_resolutions", "8", TypeError, r"^CodebookConfig.attn_resolutions must be a tuple of positive integers"),
    ("ch", True, TypeError, r"^CodebookConfig.ch must be an integer, got bool"),
    ("n_embed", np.int64(0), ValueError, r"^CodebookConfig.n_embed must be a positive integer, got 0"),
])
def test_bad_config_field_is_named(field, value, exc, match):
    with pytest.raises(exc, match=match):
        CodebookConfig(**{**SMALL, field: value})


def test_config_takes_numpy_integers_as_ints(tmp_path):
    """NumPy integers (not bool) are integers, as everywhere in pyvf (_checks.integer): the
    configuration equals the one of Python ints and holds ints, so a codebook saves (its
    configuration is JSON) and loads back. An empty attn_resolutions (no attention) stays valid."""
    fields = {**{k: np.int64(v) for k, v in SMALL.items() if isinstance(v, int)},
              "ch_mult": np.array([1, 2]), "attn_resolutions": [np.int32(8)], "decay": np.float32(0.5)}
    cfg = CodebookConfig(**fields)
    assert cfg == CodebookConfig(**SMALL, decay=0.5)
    assert all(type(getattr(cfg, k)) is int for k, v in SMALL.items() if isinstance(v, int))
    assert all(type(m) is int for m in cfg.ch_mult + cfg.attn_resolutions) and type(cfg.decay) is float
    path = Codebook(cfg).save(tmp_path / "cb.npz")
    assert Codebook.load(path).config == cfg
    assert CodebookConfig(**{**SMALL, "attn_resolutions": ()}).attn_resolutions == ()


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
    loaded = Codebook.load(out)
    for name, value in cb.state_dict().items():
        np.testing.assert_array_equal(loaded.state_dict()[name], value)


def test_training_step_fits_a_fixed_batch(rng):
    """The published optimiser (Adam, lr 1.584e-3, betas (0.5, 0.9)) with the EMA quantizer: the
    loss on one fixed batch falls (measured: 1.15 to ~0.15 in 30 steps; asserted: below 30%)."""
    import pyvf
    cb = Codebook(CodebookConfig(**SMALL), seed=0)
    x = np.tanh(np.random.default_rng(0).standard_normal((4, 3, 16, 16))).astype(np.float32)
    opt = pyvf.Adam(cb.params, 1.584e-3, betas=(0.5, 0.9))
    losses = [pyvf.codebook_train_step(cb, opt, x).loss for _ in range(30)]
    assert np.isfinite(losses).all() and np.isfinite(cb.quantizer.embeddings).all()
    assert losses[-1] < 0.3 * losses[0], losses
    assert cb.quantizer.counter == 30


class FeatureDistance:
    """A stand-in perceptual loss: per image, the mean squared difference of fixed random 1x1
    features of x and x_hat (LPIPS has the same interface, with VGG features)."""

    def __init__(self, rng, c=3, f=5):
        self.w = rng.standard_normal((f, c))

    def forward(self, x, x_hat):
        d = np.einsum("fc,bchw->bfhw", self.w, x_hat - x)  # (B, f, h, w)
        return (d * d).mean(axis=(1, 2, 3)), d

    def backward(self, dloss, d):
        n = d[0].size
        return np.einsum("fc,bfhw->bchw", self.w, 2 * d * dloss[:, None, None, None] / n)


def test_perceptual_term_is_pluggable_and_differentiated(rng):
    cfg = CodebookConfig(**SMALL, perceptual_weight=0.7, dtype="float64")
    with pytest.raises(ValueError, match="needs a perceptual module"):
        Codebook(cfg)
    with pytest.raises(ValueError, match="needs perceptual_weight > 0"):
        Codebook(CodebookConfig(**SMALL, dtype="float64"), perceptual=FeatureDistance(rng))
    cb = Codebook(cfg, perceptual=FeatureDistance(rng))
    x = rng.uniform(-1, 1, (2, 3, 16, 16))
    out = cb.forward(x)
    assert out.perceptual_loss > 0
    assert abs(out.loss - (out.rec_loss + 0.7 * out.perceptual_loss + out.commitment_loss)) < 1e-12
    g = cb.backward()
    # central differences of the loss along a random direction of two decoder parameters
    for name in ("decoder.conv_out.bias", "decoder.conv_out.weight"):
        u = rng.standard_normal(cb.params[name].shape)
        base = cb.params[name].copy()
        vals = []
        for sgn in (1, -1):
            cb.params[name] = base + sgn * 1e-6 * u
            vals.append(cb.forward(x).loss)
        cb.params[name] = base
        numeric = (vals[0] - vals[1]) / 2e-6
        # |x - x_hat| is not smooth where a pixel's error crosses 0; a 1e-6 step crosses none
        # here (checked by the tight agreement): truncation ~1e-12, rounding ~1e-10
        assert abs(numeric - (g[name] * u).sum()) <= 1e-6 * max(1.0, abs(numeric)), (name, numeric)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_inference_and_trace_paths_give_the_same_bits(dtype, rng):
    """encode/decode_code keep nothing (residual sums in place, no GroupNorm cache) and forward
    without a trace adds the residuals in place; forward with a trace keeps every activation. All
    are the same operations on the same numbers: bitwise equal results."""
    cb = random_codebook(CodebookConfig(**SMALL, dtype=dtype), rng)
    images = rng.uniform(-1, 1, (2, 3, 16, 16)).astype(dtype)
    plain = cb.forward(images)
    traced = cb.forward(images, trace=True)
    np.testing.assert_array_equal(plain.reconstruction, traced.reconstruction)
    np.testing.assert_array_equal(cb.encode(images), traced.codes)
    # decode_code feeds the embeddings themselves (forward feeds z + (e - z)): equal up to that rounding
    assert_close("decode_code", cb.decode_code(traced.codes), traced.reconstruction,
                 rtol=1e-5 if dtype == "float32" else 1e-12)
    # the traced activations were not modified in place afterwards: conv2's output is not its block's sum
    tr = traced.trace
    name = "encoder.down.0.block.0"
    assert not np.array_equal(tr[name + ".conv2"], tr[name])


def test_residual_backward_adds_in_place_only_into_a_fresh_gradient(rng):
    """_resblock_backward adds the shortcut's gradient into the body's dx in place. Where the body
    is empty its dx is dy itself (and the identity shortcut's is too): the sum must then go to a
    new array, dy left as it was (the caller's gradient), and the result be dy + dy."""
    cb = random_codebook(CodebookConfig(**SMALL), rng)
    dy = rng.standard_normal((2, 32, 8, 8)).astype(np.float32)
    before = dy.copy()
    out = cb._resblock_backward(dy, ([], []), {})
    np.testing.assert_array_equal(dy, before)
    assert not np.may_share_memory(out, dy)
    np.testing.assert_array_equal(out, before + before)
