"""Codebook traces (issue 13, item 1): forward(..., trace=True) names every activation after the
published torch modules, in execution order; backward(drec=) returns every traced activation's
gradient by the same names. Checked bitwise against the untraced model here; every traced
activation and gradient against the torch port in float64, and a port's planted bugs located,
in tests/test_teacher.py."""

import numpy as np
import pytest

from pyvf.models.codebook import Codebook, CodebookConfig, trace_names

SMALL = dict(ch=32, ch_mult=(1, 2), num_res_blocks=1, attn_resolutions=(8,), z_channels=32, embed_dim=8,
             n_embed=16, image_size=16)
LOSSES = ("rec_loss", "commitment_loss", "loss")


def random_codebook(cfg, rng):
    """Every parameter random (GroupNorm gammas != 1, biases != 0)."""
    cb = Codebook(cfg, seed=1)
    for name, p in cb.params.items():
        if p.ndim == 1:
            cb.params[name] = rng.normal(1.0 if name.endswith(".weight") else 0.0, 0.2, p.shape).astype(p.dtype)
    return cb


def images_for(cfg, rng, B=2):
    return rng.uniform(-1, 1, (B, cfg.in_channels, cfg.image_size, cfg.image_size)).astype(cfg.dtype)


@pytest.mark.parametrize("dtype, seed_kind", [("float32", "both"), ("float64", "drec")])
def test_traced_equals_untraced_bitwise(dtype, seed_kind, rng):
    cfg = CodebookConfig(**SMALL, dtype=dtype)
    cb = random_codebook(cfg, rng)
    x = images_for(cfg, rng)
    drec = rng.normal(size=x.shape).astype(dtype)
    kw = {"drec": {"drec": drec}, "both": {"drec": drec, "dloss": 0.5}}[seed_kind]
    state = cb.state_dict()
    plain = cb.forward(x, train=True)
    g_plain = cb.backward(**kw)
    after_plain = cb.state_dict()
    cb.load_official(state)
    traced = cb.forward(x, train=True, trace=True)
    g_traced = cb.backward(**kw)
    assert plain.trace is None
    np.testing.assert_array_equal(traced.reconstruction, plain.reconstruction)
    np.testing.assert_array_equal(traced.codes, plain.codes)
    assert (traced.loss, traced.rec_loss, traced.commitment_loss) == (plain.loss, plain.rec_loss,
                                                                      plain.commitment_loss)
    for k, v in cb.state_dict().items():  # the same EMA step
        np.testing.assert_array_equal(v, after_plain[k], err_msg=k)
    assert set(g_plain) == set(cb.params)
    for name in cb.params:
        np.testing.assert_array_equal(g_traced[name], g_plain[name], err_msg=name)
    # the trace is what the output is made of: no copies
    tr = traced.trace
    np.testing.assert_array_equal(tr["decoder.conv_out"], traced.reconstruction)
    assert np.shares_memory(tr["decoder.conv_out"], traced.reconstruction)
    for name, a in tr.items():
        if isinstance(a, np.ndarray):
            assert a.dtype == cfg.dtype, name
    assert tr["loss"] == traced.loss


def test_trace_names_in_execution_order(rng):
    cfg = CodebookConfig(**dict(SMALL, ch_mult=(1, 1, 2), num_res_blocks=2, attn_resolutions=(16, 4)), dtype="float64")
    cb = random_codebook(cfg, rng)
    out = cb.forward(images_for(cfg, rng), trace=True)
    names = list(out.trace)
    assert names == trace_names(cfg)
    for must in ("encoder.conv_in", "encoder.down.0.block.0", "encoder.down.0.block.0.norm1",
                 "encoder.down.0.downsample.conv", "encoder.mid.block_1", "encoder.mid.attn_1", "encoder.norm_out",
                 "encoder.conv_out", "quant_conv", "quantize", "post_quant_conv", "decoder.conv_in",
                 "decoder.up.1.upsample.interp", "decoder.up.1.upsample.conv", "decoder.norm_out", "decoder.conv_out"):
        assert must in names, must
    pos = {n: i for i, n in enumerate(names)}
    assert pos["encoder.down.0.block.0.conv2"] < pos["encoder.down.0.block.0"] < pos["encoder.down.0.downsample.conv"]
    assert (pos["encoder.conv_out"] < pos["quant_conv"] < pos["quantize"] < pos["post_quant_conv"]
            < pos["decoder.conv_in"])
    assert pos["decoder.up.1.upsample.interp"] < pos["decoder.up.1.upsample.conv"] < pos["decoder.up.0.block.0"]
    assert names[-4:] == ["decoder.conv_out", *LOSSES]
    # every parameter's module is traced (nested ones: a ResnetBlock's children)
    modules = {p.rsplit(".", 1)[0] for p in cb.params}
    attn_children = {m for m in modules if m.rsplit(".", 1)[-1] in ("norm", "q", "k", "v", "proj_out")}
    assert modules - attn_children <= set(names)
    # backward: every activation but the losses, exactly in the reverse order, then the parameters
    g = cb.backward(drec=np.ones_like(out.reconstruction))
    acts = [n for n in g if n not in cb.params]
    assert acts == [n for n in reversed(names) if n not in LOSSES]
    assert list(g)[len(acts):] == list(cb.params)
    for n in acts:
        assert g[n].shape == out.trace[n].shape, n
