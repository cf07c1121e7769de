"""The weight mechanism and model files (pyvf/models/io.py, pyvf/_io.py): every layout round-trips
bit for bit against transposes written out here, a layout or shape that does not fit a parameter
raises naming it (never a silent transpose or reshape), a model file is written atomically and
refused whole, naming the file and entry, for any bad entry or a configuration lacking a field."""

import json
import os
import re

import numpy as np
import pytest

import pyvf
from conftest import assert_bitwise_equal
from pyvf import _io
from pyvf._io import CheckpointError
from pyvf.models import check_pair, transformer

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
            return np.einsum("io->oi", p)
        if name.endswith("/bias"):
            return p[0]
    if isinstance(model, pyvf.Codebook) and layout == "tf" and p.ndim == 4:
        return np.einsum("oihw->hwio", p)
    return p


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
            got = again.state_dict()
            for name, v in model.state_dict().items():
                assert_bitwise_equal(f"{name} load {layout}", np.asarray(got[name]), np.asarray(v))
        back = type(model).load(model.save(tmp_path / type(model).__name__))
        assert back.config == model.config
        got = back.state_dict()
        for name, v in model.state_dict().items():
            assert_bitwise_equal(f"{name} save/load", np.asarray(got[name]), np.asarray(v))


def test_a_bad_layout_or_shape_raises_naming_it(rng):
    """A misspelt layout is never taken for the published one, also for a parameter every layout
    holds as published; an array not of the parameter's shape in the layout stated raises naming
    the parameter instead of being transposed or reshaped silently."""
    model = pyvf.Transformer(pyvf.TransformerConfig(**TINY))
    cb = pyvf.Codebook(pyvf.CodebookConfig(**CB))
    for call in (lambda: model.from_layout("wte/weight", model.params["wte/weight"], "TF"),
                 lambda: model.to_layout("ln_f/gamma", model.params["ln_f/gamma"], None),
                 lambda: cb.state_dict(layout="jax"), lambda: cb.load_official(cb.state_dict(), layout="Torch")):
        with pytest.raises(ValueError, match=r"\blayout\b"):
            call()
    # (the tf kernel untransposed in "torch": test_layout_convert's params_from_layout)
    for name, a, layout in (("h.0/attn/c_proj/bias", np.zeros((2, 16)), "torch"), ("ln_f/gamma", np.zeros(31), "tf")):
        with pytest.raises(ValueError, match=re.escape(repr(name))):
            model.from_layout(name, a, layout)


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


# ---------------------------------------------------------------------------------------
# saving and loading: atomic, and never half-done


def _models(dtype):
    return [pyvf.Transformer(pyvf.TransformerConfig(**TINY, dtype=dtype), seed=3),
            pyvf.Codebook(pyvf.CodebookConfig(**CB, dtype=dtype), seed=3)]


def test_save_is_atomic_and_appends_npz(tmp_path, monkeypatch):
    """save() writes path + '.npz' when the name lacks it (np.savez's rule, kept) and returns the
    path; a save killed while writing leaves the previous file intact and no temporary file behind
    (killed before the rename: test_train_loops' checkpoint, the same atomic_savez)."""
    for m in _models("float32"):
        assert m.save(tmp_path / "model") == str(tmp_path / "model.npz")
        path = tmp_path / "m.npz"
        first = path.read_bytes() if m.save(path) == str(path) else None
        real = np.savez

        def dying(f, **arrays):
            real(f, **{k: arrays[k] for k in list(arrays)[:2]})
            raise KeyboardInterrupt("killed while writing")
        monkeypatch.setattr(np, "savez", dying)
        with pytest.raises(KeyboardInterrupt):
            m.save(path)
        monkeypatch.undo()
        assert path.read_bytes() == first, "the previous file was changed"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["m.npz", "model.npz"], "a temporary file was left"


@pytest.mark.parametrize("how, names", [  # the entries' values: the load_official tables
    ("truncate", []), ("flip", []), ("shape", ["first"]), ("missing", ["first"]),
    ("config", ["__config__"]), ("not json", ["__config__"]),
    ("lacks a field", ["__config__", "dtype"]),  # never the field's default silently: another model
    ("pickled", ["first"]),
])
@pytest.mark.parametrize("which", [0, 1], ids=["transformer", "codebook"])
def test_load_refuses_a_broken_file_naming_file_and_entry(tmp_path, how, names, which):
    """Truncated, bytes flipped in its zip headers, an entry of the wrong shape or pickled, a
    missing entry, a broken __config__ or one lacking a field: CheckpointError (a ValueError)
    naming the file and, where one entry is at fault, the entry; nothing written beside it."""
    m = _models("float32")[which]
    path, bad = tmp_path / "model.npz", str(tmp_path / "bad.npz")
    m.save(path)
    raw = path.read_bytes()
    first = sorted(m.state_dict())[0]
    if how in ("truncate", "flip"):
        data = {"truncate": raw[: len(raw) // 2],
                "flip": bytes(b ^ 0xFF if i < 40 else b for i, b in enumerate(raw))}[how]
        open(bad, "wb").write(data)
    else:
        with np.load(path) as f:
            d = {k: f[k] for k in f.files}
        if how == "shape":
            d[first] = np.concatenate([d[first], d[first][..., :1]], axis=-1)
        elif how == "missing":
            del d[first]
        elif how == "config":
            d["__config__"] = np.array('{"n_embeddings": -1}')
        elif how == "lacks a field":
            cfg = json.loads(str(d["__config__"]))
            del cfg["dtype"]
            d["__config__"] = np.array(json.dumps(cfg))
        elif how == "pickled":
            d[first] = np.array([None] * d[first].size, dtype=object)
        else:
            d["__config__"] = np.array("not json {")
        np.savez(bad, **d)
    with pytest.raises(CheckpointError, match=re.escape(bad)) as e:
        type(m).load(bad)
    for name in names:
        assert (first if name == "first" else name) in str(e.value), e.value
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.npz", "model.npz"]
    with pytest.raises(FileNotFoundError):
        type(m).load(tmp_path / "no-such-file.npz")


# ---------------------------------------------------------------------------------------
# the atomic writes and reads under every model file (pyvf/_io.py)


def test_remove_stale_temps_removes_only_the_temps_of_its_path(tmp_path):
    """remove_stale_temps(path) matched `.{name}.*.tmp`, so clearing "model" also removed a
    temporary file of "model.npz", and clearing "checkpoint.npz" one of "checkpoint.npz.bak":
    an atomic write of that other file under way in another process then failed at its rename.
    Only `.{name}.{pid}.{hex}.tmp`, what _io names a temporary file of `name`, is removed now."""
    ours = [".checkpoint.npz.123.abcd.tmp", ".checkpoint.npz.98765.0f1e2d3c.tmp"]
    others = [".checkpoint.npz.bak.123.0f1e2d3c.tmp", ".checkpoint.npz.notes.tmp", ".checkpoint.npzz.1.ab.tmp",
              "checkpoint.npz", ".model.npz.55.ab12cd34.tmp"]
    for name in ours + others:
        (tmp_path / name).write_bytes(b"x")
    # the name a real atomic write uses is one of ours
    assert _io._temp_name(str(tmp_path / "checkpoint.npz")).startswith(str(tmp_path / ".checkpoint.npz."))
    assert sorted(_io.remove_stale_temps(str(tmp_path / "checkpoint.npz"))) == sorted(ours)
    assert _io.remove_stale_temps(str(tmp_path / "model")) == []
    assert sorted(os.listdir(tmp_path)) == sorted(others)
    real = os.path.basename(_io._temp_name(str(tmp_path / "model.npz")))  # what a write of model.npz leaves
    (tmp_path / real).write_bytes(b"x")
    assert sorted(_io.remove_stale_temps(str(tmp_path / "model.npz"))) == sorted([".model.npz.55.ab12cd34.tmp", real])
