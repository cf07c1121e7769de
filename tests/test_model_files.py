"""Audit of the weight mechanism (pyvf/models/io.py, table.py): every layout round-trips bit for
bit against transposes written out here, a layout or shape that does not fit a parameter raises
naming it (never a silent transpose or reshape), a layer table's role must be one the model's
layouts know, and a model file whose configuration lacks a field is refused, not given defaults."""

import dataclasses
import json

import numpy as np
import pytest

import pyvf
from conftest import assert_bitwise_equal
from pyvf._io import CheckpointError
from pyvf.models import check_pair, transformer
from test_model_table import replace_row

TINY = dict(n_embeddings=64, n_head=2, d_model=32, n_layer=1, token_image_size=4, sequence_size=5, n_loss_skip=1)
CB = dict(ch=32, ch_mult=(1, 2), num_res_blocks=1, attn_resolutions=(8,), z_channels=32, embed_dim=8, n_embed=16,
          image_size=16)


def special(rng, shape, dtype):
    """Random values with -0.0, a subnormal and the dtype's largest value planted: their bits must survive."""
    a = rng.normal(size=shape).astype(dtype).reshape(-1)
    fi = np.finfo(dtype)
    a[: min(3, a.size)] = np.array([-0.0, fi.smallest_subnormal, -fi.max], dtype)[: min(3, a.size)]
    return a.reshape(shape)


def by_hand(model, name, p, layout):
    """The parameter in `layout`, written out: nn.Linear's (out, in) kernel and (out,) bias for a
    Transformer's "torch", channels-last (kh, kw, in, out) conv kernels for a Codebook's "tf"."""
    if isinstance(model, pyvf.Transformer) and layout == "torch":
        if transformer.is_dense_kernel(name):
            return np.array([[p[i, o] for i in range(p.shape[0])] for o in range(p.shape[1])], p.dtype)
        if name.endswith("/bias"):
            return p[0].copy()
    if isinstance(model, pyvf.Codebook) and layout == "tf" and p.ndim == 4:
        o, i, kh, kw = p.shape
        out = np.empty((kh, kw, i, o), p.dtype)
        for a in range(kh):
            for b in range(kw):
                out[a, b] = p[:, :, a, b].T
        return out
    return p.copy()


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_every_layout_round_trips_bitwise(rng, tmp_path, dtype):
    for model in (pyvf.Transformer(pyvf.TransformerConfig(**TINY, dtype=dtype)),
                  pyvf.Codebook(pyvf.CodebookConfig(**CB, dtype=dtype))):
        state = {k: (v if k.startswith("quantize.") else special(rng, v.shape, dtype))
                 for k, v in model.state_dict().items()}
        model.load_official(state)
        for layout in model.LAYOUTS:
            sd = model.state_dict(layout=layout)
            for name, p in model.params.items():
                want = by_hand(model, name, p, layout)
                got = model.to_layout(name, p, layout)
                assert_bitwise_equal(f"{name} to {layout}", got, want)
                assert_bitwise_equal(f"{name} state_dict {layout}", sd[name], want)
                assert got.flags.c_contiguous and not np.shares_memory(got, p)
                assert_bitwise_equal(f"{name} from {layout}", model.from_layout(name, want, layout), p)
            again = type(model)(model.config, seed=7)
            again.load_official(sd, layout=layout)
            for name, v in model.state_dict().items():
                assert_bitwise_equal(f"{name} load {layout}", np.asarray(again.state_dict()[name]), np.asarray(v))
        back = type(model).load(model.save(tmp_path / type(model).__name__))
        assert back.config == model.config
        for name, v in model.state_dict().items():
            assert_bitwise_equal(f"{name} save/load", np.asarray(back.state_dict()[name]), np.asarray(v))


def test_a_bad_layout_raises_for_every_parameter():
    """Also for a parameter every layout holds as published (an embedding, a LayerNorm gain):
    a misspelt layout is never taken for the published one."""
    model = pyvf.Transformer(pyvf.TransformerConfig(**TINY))
    cb = pyvf.Codebook(pyvf.CodebookConfig(**CB))
    for m, name in ((model, "wte/weight"), (model, "ln_f/gamma"), (cb, "encoder.conv_in.bias")):
        p = m.params[name]
        for bad in ("TF", "jax", None):
            with pytest.raises(ValueError, match="layout must be one of"):
                m.layout_shapes(name, bad)
            with pytest.raises(ValueError, match="layout must be one of"):
                m.from_layout(name, p, bad)
            with pytest.raises(ValueError, match="layout must be one of"):
                m.to_layout(name, p, bad)


def test_from_and_to_layout_refuse_arrays_of_another_shape(rng):
    """from_layout and to_layout are public: an array not of the parameter's shape in the layout
    stated raises naming the parameter, instead of being transposed or reshaped silently."""
    model = pyvf.Transformer(pyvf.TransformerConfig(**TINY))
    k = "h.0/mlp/c_fc/weight"  # (32, 128) published, (128, 32) in torch's layout
    tf_kernel = rng.normal(size=(32, 128))
    # a published (tf) kernel said to be in torch's layout: transposed to (128, 32) before
    with pytest.raises(ValueError, match=r"'h.0/mlp/c_fc/weight' has shape \(32, 128\), expected \(128, 32\).*'torch'"):
        model.from_layout(k, tf_kernel, "torch")
    # a torch kernel given as the published one: transposed back to (32, 128) before
    with pytest.raises(ValueError, match=r"'h.0/mlp/c_fc/weight' has shape \(128, 32\), expected \(32, 128\)"):
        model.to_layout(k, tf_kernel.T, "torch")
    # a (2, 16) array is no bias of 32 in any layout: reshaped to (1, 32) before
    with pytest.raises(ValueError, match=r"'h.0/attn/c_proj/bias' has shape \(2, 16\)"):
        model.from_layout("h.0/attn/c_proj/bias", np.zeros((2, 16)), "torch")
    with pytest.raises(ValueError, match=r"'ln_f/gamma' has shape \(31,\)"):
        model.from_layout("ln_f/gamma", np.zeros(31), "tf")
    cb = pyvf.Codebook(pyvf.CodebookConfig(**CB))
    with pytest.raises(ValueError, match=r"'encoder.conv_in.weight' has shape \(3, 3\)"):  # numpy's "axes don't match"
        cb.to_layout("encoder.conv_in.weight", np.zeros((3, 3)), "tf")
    # the shapes each layout allows still convert, as written out by hand
    assert_bitwise_equal("torch kernel", model.from_layout(k, tf_kernel.T, "torch"), tf_kernel)
    b = rng.normal(size=(1, 32))
    assert_bitwise_equal("torch (out,) bias", model.from_layout("h.0/attn/c_proj/bias", b[0], "torch"), b)
    assert_bitwise_equal("torch (1, out) bias", model.from_layout("h.0/attn/c_proj/bias", b, "torch"), b)


def test_a_table_role_no_layout_knows_is_refused():
    """A row whose parameter carries a misspelt role was held as published in every layout: its
    kernel was silently left untransposed by state_dict(layout="torch") and load_official."""
    cfg = pyvf.TransformerConfig(**TINY)
    rows = transformer.layer_table(cfg)
    row = next(r for r in rows if r.name == "blocks.0.attn")
    params = tuple((s, shape, "dense_kernal" if role == "dense_kernel" else role) for s, shape, role in row.params)
    with pytest.raises(ValueError, match=r"'h.0/attn/c_attn/weight'.*role 'dense_kernal'"):
        pyvf.Transformer(cfg, layers=replace_row(rows, "blocks.0.attn", params=params))
    # a role of the other model's layouts (a conv kernel's "tf") is no layout of the Transformer
    params = tuple((s, shape, "conv_kernel" if role == "dense_kernel" else role) for s, shape, role in row.params)
    with pytest.raises(ValueError, match=r"'h.0/attn/c_attn/weight'.*role 'conv_kernel'"):
        pyvf.Transformer(cfg, layers=replace_row(rows, "blocks.0.attn", params=params))


@pytest.mark.parametrize("field", ["pose_multiplier", "dtype", "n_loss_skip"])
def test_a_model_file_lacking_a_config_field_is_refused(tmp_path, field):
    """A configuration missing a field (here SM7's pose_multiplier 0.2) loaded the model with the
    field's default (1.0) silently: another model than the file's."""
    model = pyvf.Transformer(pyvf.TransformerConfig(**{**TINY, "n_loss_skip": 2}, pose_multiplier=0.2))
    cfg = dataclasses.asdict(model.config)
    del cfg[field]
    path = str(tmp_path / "partial.npz")
    np.savez(path, __config__=json.dumps(cfg), **model.state_dict())
    with pytest.raises(CheckpointError, match=rf"partial.npz: entry '__config__' lacks the fields \['{field}'\]"):
        pyvf.Transformer.load(path)
    cb = pyvf.Codebook(pyvf.CodebookConfig(**CB))
    cfg = dataclasses.asdict(cb.config)
    del cfg["decay"]
    np.savez(path, __config__=json.dumps(cfg), **cb.state_dict())
    with pytest.raises(CheckpointError, match=r"lacks the fields \['decay'\]"):
        pyvf.Codebook.load(path)


def test_a_model_file_is_refused_whole_for_any_bad_entry(tmp_path):
    """Regression checks of what is promised (docs/verify.md, Weights in and out): an entry of
    another model, a float64 value beyond float32's range, a pickled object, each named."""
    model = pyvf.Transformer(pyvf.TransformerConfig(**TINY))
    cfg = json.dumps(dataclasses.asdict(model.config))
    sd = model.state_dict()
    path = str(tmp_path / "bad.npz")
    np.savez(path, __config__=cfg, **{**sd, "ln_f/gamma": np.full(32, 1e39)})
    with pytest.raises(CheckpointError, match=r"'ln_f/gamma' holds a value of magnitude 1e\+39, beyond float32"):
        pyvf.Transformer.load(path)
    np.savez(path, __config__=cfg, **sd, **{"h.1/ln_1/gamma": np.ones(32)})
    with pytest.raises(CheckpointError, match="unexpected parameter 'h.1/ln_1/gamma'"):
        pyvf.Transformer.load(path)
    np.savez(path, __config__=cfg, **{**sd, "ln_f/gamma": np.array([None] * 32, dtype=object)})
    with pytest.raises(CheckpointError, match=r"entry 'ln_f/gamma'.*allow_pickle=False"):
        pyvf.Transformer.load(path)


def test_a_transformer_records_its_codebook_and_a_pairing_checks_it(tmp_path):
    """The codebook's fingerprint: the same after a round trip, another for one ulp in one parameter
    or a code, blind to the EMA statistics (they make no token). A transformer's file keeps the
    fingerprint; check_pair refuses another codebook naming both files, and warns for a file that
    records none (one saved before pyvf recorded it)."""
    cb = pyvf.Codebook(pyvf.CodebookConfig(**CB), seed=0)
    cb.save(tmp_path / "cb.npz")
    loaded = pyvf.Codebook.load(tmp_path / "cb.npz")
    assert loaded.fingerprint() == cb.fingerprint()
    loaded.quantizer.ema_dw_hidden += 1
    assert loaded.fingerprint() == cb.fingerprint()
    name = sorted(cb.params)[3]
    loaded.params[name].flat[5] = np.nextafter(loaded.params[name].flat[5], np.float32(np.inf))
    assert loaded.fingerprint() != cb.fingerprint()
    other = pyvf.Codebook.load(tmp_path / "cb.npz")
    other.quantizer.embeddings[0, 0] = np.nextafter(other.quantizer.embeddings[0, 0], np.float32(np.inf))
    assert other.fingerprint() != cb.fingerprint()
    other.save(tmp_path / "other.npz")

    tf = pyvf.Transformer(pyvf.TransformerConfig(**{**TINY, "n_embeddings": 16, "token_image_size": cb.config.token_size}))
    tf.save(tmp_path / "old.npz")  # records no codebook
    tf.codebook_fingerprint = cb.fingerprint()
    tf.save(tmp_path / "tf.npz")
    check_pair(pyvf.Codebook.load(tmp_path / "cb.npz"), pyvf.Transformer.load(tmp_path / "tf.npz"))
    with pytest.raises(ValueError) as e:
        check_pair(pyvf.Codebook.load(tmp_path / "other.npz"), pyvf.Transformer.load(tmp_path / "tf.npz"))
    assert str(tmp_path / "other.npz") in str(e.value) and str(tmp_path / "tf.npz") in str(e.value)
    with pytest.warns(UserWarning, match="old.npz"):
        check_pair(cb, pyvf.Transformer.load(tmp_path / "old.npz"))
