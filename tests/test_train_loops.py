"""The training loops (pyvf/train/loops.py) and commands (pyvf/cli/train.py): a resumed run equals
an uninterrupted one bit for bit (parameters, optimiser moments, EMA buffers, log), with or without
held-out evaluation (which only reads); a killed save leaves the previous checkpoint; a corrupt one
raises naming the file; training lowers the loss; tokenize equals Codebook.encode; the commands
run end to end; bad arguments raise naming the argument; an interrupted run resumes from its
last checkpoint.

Tiny models and a handful of steps: the whole file runs in seconds."""

import argparse
import csv
import dataclasses
import hashlib
import json
import os
import shutil
import sys
import types

import numpy as np
import pytest

import pyvf
import pyvf._io
import pyvf.train.loops as loops
from conftest import assert_bitwise_equal
from pyvf._io import CheckpointError, atomic_savez, load_npz
from pyvf.evaluate.health import CODEBOOK_HEALTH, codebook_health, transformer_health, transformer_health_columns
from pyvf.models.codebook import Codebook, CodebookConfig
from pyvf.models.transformer import Transformer, TransformerConfig
from pyvf.train import codebook_batch, load_tokens, tokenize, train_codebook, train_transformer, transformer_batch
from pyvf.train.loops import CODEBOOK_LOG, RunOptions, TransformerRecipe
from pyvf.cli.train import export_run, register as cli_register
from pyvf.train.curves import runs_table

# 16x16 images -> 8x8 tokens (one downsampling), 16 codes
CB = CodebookConfig(ch=32, ch_mult=(1, 1), num_res_blocks=1, attn_resolutions=(), z_channels=8, embed_dim=8,
                    n_embed=16, image_size=16)
# 2x2 tokens per view, 3 views per sample, one block
TF = TransformerConfig(n_embeddings=16, n_head=2, d_model=32, n_layer=1, token_image_size=2, sequence_size=3,
                       n_loss_skip=1)
# 4x4 images -> 2x2 tokens of 16 codes: the held-out set TF reads
CB4 = dataclasses.replace(CB, image_size=4)


@pytest.fixture(autouse=True)
def _log_every_step(monkeypatch):
    """A log row every step: the logs then compare step by step."""
    monkeypatch.setattr(pyvf.train._run, "LOG_EVERY", 1)


def opts(steps, **kw):
    """RunOptions of these tests: no progress bar, batches of 2."""
    return RunOptions(**{"steps": steps, "batch_size": 2, "progress": False, **kw})


def _images(rng, scenes=3, views=4, size=16):
    return rng.integers(0, 256, (scenes, views, size, size, 3), dtype=np.uint8)


def _poses(rng, scenes=3, views=5):
    q = rng.standard_normal((scenes, views, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)  # unit quaternions
    return np.concatenate([rng.standard_normal((scenes, views, 3)), q], axis=-1)  # (scenes, views, 7)


def _tokens(rng, scenes=3, views=5):
    return rng.integers(0, TF.n_embeddings, (scenes, views, 2, 2))


def _eval_set(rng, scenes=2, views=7):
    cb = Codebook(CB4, seed=0)
    images, poses = _images(rng, scenes=scenes, views=views, size=4), _poses(rng, scenes=scenes, views=views)
    return loops.held_out_set(cb, images, poses)


def _checkpoint(folder):
    """The checkpoint's meta (without the wall-clock seconds, nor the fingerprint of the held-out
    set eval.csv's rows came from: neither is part of the trajectory) and arrays."""
    arrays = load_npz(os.path.join(folder, "checkpoint.npz"), "checkpoint")
    meta = json.loads(str(arrays.pop("__meta__")))
    meta.pop("elapsed")
    meta.pop("eval", None)
    return meta, arrays


def _log(folder, name="log.csv"):
    """log.csv's (or eval.csv's) rows without the seconds column."""
    with open(os.path.join(folder, name), newline="") as f:
        return [row[:-1] for row in csv.reader(f)]


def _hyper(folder):
    return json.loads(open(os.path.join(folder, "config.json")).read())["hyperparameters"]


def _assert_same_arrays(got, want):
    """The same names, each array bit for bit."""
    assert sorted(got) == sorted(want)
    for k in want:
        assert_bitwise_equal(k, got[k], want[k])


def _assert_same_run(a, b, final):
    meta_a, arr_a = _checkpoint(a)
    meta_b, arr_b = _checkpoint(b)
    assert meta_a == meta_b
    assert any(k.startswith("optimizer/exp_avg_sq/") for k in arr_a)
    _assert_same_arrays(arr_b, arr_a)  # model, EMA buffers, both moments
    _assert_same_arrays(load_npz(os.path.join(b, final)), load_npz(os.path.join(a, final)))
    assert _log(a) == _log(b)
    assert [int(r[0]) for r in _log(a)[1:]] == list(range(1, meta_a["step"] + 1))


def _cli():
    """run(*argv): the training commands' handler on argv (parsed by their parser) -> exit status."""
    parser = argparse.ArgumentParser(prog="pyvf")
    cli_register(parser.add_subparsers(dest="command"))

    def run(*argv):
        args = parser.parse_args([str(a) for a in argv])
        return args.func(args)
    return run


def _smoke_files(tmp_path):
    """In tmp_path: d16/, 6 scenes of seed 0 at 16 px (pyvf scenes), the smoke preset's
    configurations as cb.json and tf.json, its untrained codebook cb.npz and tok.npz, d16 through
    `pyvf tokenize`: the files the commands start from. Returns the commands' runner and cb.npz."""
    from pyvf.scenes import write_dataset
    from pyvf.train.pipeline import PRESETS

    write_dataset(str(tmp_path / "d16"), 6, 0, size=16, progress=False)
    (tmp_path / "cb.json").write_text(json.dumps(dataclasses.asdict(PRESETS["smoke"].codebook)))
    (tmp_path / "tf.json").write_text(json.dumps(dataclasses.asdict(PRESETS["smoke"].transformer)))
    run, codebook = _cli(), Codebook(PRESETS["smoke"].codebook).save(str(tmp_path / "cb.npz"))
    assert run("tokenize", "--codebook", codebook, "--data", tmp_path / "d16", "--out", tmp_path / "tok.npz",
               "--no-progress") == 0
    return run, codebook


# ---------------------------------------------------------------------------------------
# (a) resume = uninterrupted, bit for bit; held-out evaluation only reads


def test_codebook_resume_is_exact_and_evaluation_only_reads(tmp_path, rng):
    """A codebook run with issue 48's options (k-means start, restarts to the worst represented
    vectors, reseats), object weights and held-out evaluation every 2 steps, stopped at step 3 and
    resumed, ends with the checkpoint, model and log of the same run uninterrupted without
    evaluation; eval.csv's last row is the final model's health."""
    images, held_out = _images(rng), _images(rng, scenes=2, views=3).reshape(-1, 16, 16, 3)
    a, b = str(tmp_path / "a"), str(tmp_path / "b")
    recipe = dict(reset_dead_codes=2, restart="worst", reseat=4, kmeans=3, object_weight=3.0)
    train_codebook(images, CB, a, opts(6, checkpoint_every=2, batch_size=3), **recipe)
    train_codebook(images, CB, b, opts(3, checkpoint_every=2, batch_size=3, eval_every=2), eval_images=held_out,
                   **recipe)
    train_codebook(images, CB, b, opts(6, checkpoint_every=2, batch_size=3, eval_every=2), eval_images=held_out,
                   **recipe)
    _assert_same_run(a, b, "codebook.npz")
    meta, arrays = _checkpoint(a)
    assert meta["step"] == 6 and int(arrays["model/quantize.counter"]) == 7  # the EMA buffers: 6 steps, k-means
    hyper = _hyper(a)
    assert (hyper["restart"], hyper["reseat"], hyper["kmeans"], hyper["object_weight"]) == ("worst", 4, 3, 3.0)
    rows = _log(b, "eval.csv")
    assert rows[0] == ["step", *CODEBOOK_HEALTH]
    assert [r[0] for r in rows[1:]] == ["0", "2", "3", "4", "6"]  # 3: the first call's last step
    want = codebook_health(Codebook.load(os.path.join(b, "codebook.npz")), held_out)
    np.testing.assert_array_equal([float(v) for v in rows[-1][1:]], [want[k] for k in CODEBOOK_HEALTH])  # nan == nan


def test_transformer_resume_is_exact_and_evaluation_only_reads(tmp_path, rng):
    tokens, poses, eval_set = _tokens(rng), _poses(rng), _eval_set(rng)
    a, b = str(tmp_path / "a"), str(tmp_path / "b")
    recipe = TransformerRecipe(lr=1e-3, warmup=2, total_steps=6)
    train_transformer(tokens, poses, TF, a, opts(6, batch_size=4, checkpoint_every=2), recipe)
    train_transformer(tokens, poses, TF, b, opts(3, batch_size=4, checkpoint_every=2, eval_every=3), recipe,
                      eval_set=eval_set)
    train_transformer(tokens, poses, TF, b, opts(6, batch_size=4, checkpoint_every=2, eval_every=3), recipe,
                      eval_set=eval_set)
    _assert_same_run(a, b, "transformer.npz")
    assert _checkpoint(a)[0]["optimizer"]["step"] == 6
    rows = _log(b, "eval.csv")
    assert rows[0] == ["step", *transformer_health_columns((1,))]  # TF trains context 2: only C = 1 of 1, 3, 5
    assert [r[0] for r in rows[1:]] == ["0", "3", "6"]
    e = eval_set
    want = transformer_health(e["codebook"], Transformer.load(os.path.join(b, "transformer.npz")), e["images"],
                              e["poses"], e["tokens"], (1,))
    np.testing.assert_array_equal([float(v) for v in rows[-1][1:]], list(want.values()))  # nan equals nan


def test_resume_refuses_another_run(tmp_path, rng):
    images, tokens, poses = _images(rng), _tokens(rng), _poses(rng)
    cb, tf = str(tmp_path / "cb"), str(tmp_path / "tf")
    train_codebook(images, CB, cb, opts(2))
    with pytest.raises(ValueError, match="lr"):
        train_codebook(images, CB, cb, opts(4), lr=1e-2)
    with pytest.raises(ValueError, match="data"):
        train_codebook(images[:2], CB, cb, opts(4))
    with pytest.raises(ValueError, match="past steps=1"):
        train_codebook(images, CB, cb, opts(1))
    train_codebook(images, CB, cb + "-cos", opts(6), schedule="cosine")  # the codebook's lr: a cosine to 0 at step 6
    lr = [float(r[CODEBOOK_LOG.index("lr") + 1]) for r in _log(cb + "-cos", "log.csv")[1:]]  # update t: lr(t - 1)
    np.testing.assert_allclose(lr, [3e-4 * (1 + np.cos(np.pi * t / 6)) / 2 for t in range(6)], rtol=1e-12)
    with pytest.raises(ValueError, match="total_steps"):  # more steps would end the cosine elsewhere
        train_codebook(images, CB, cb + "-cos", opts(8), schedule="cosine")
    with pytest.raises(ValueError, match="'codebook' run"):
        train_transformer(tokens, poses, TF, cb, opts(4))
    # the schedule's length is part of the run: extending one needs its total_steps
    train_transformer(tokens, poses, TF, tf, opts(2))
    with pytest.raises(ValueError, match="total_steps"):
        train_transformer(tokens, poses, TF, tf, opts(4))
    assert _checkpoint(tf)[0]["step"] == 2
    # resume=False starts over
    train_codebook(images, CB, cb, opts(1, resume=False), lr=1e-2)
    assert _checkpoint(cb)[0]["step"] == 1 and len(_log(cb)) == 2


def test_eval_csv_is_one_held_out_sets_curve(tmp_path, rng):
    """A resume evaluating on another held-out set raises, eval.csv and the checkpoint untouched; a
    resume without evaluation (eval_every 0) passes whatever set it names and keeps the record."""
    images = _images(rng)
    first, other = (_images(rng, scenes=1, views=2).reshape(-1, 16, 16, 3) for _ in range(2))
    out = str(tmp_path / "run")
    train_codebook(images, CB, out, opts(2, eval_every=1), eval_images=first)
    rows = _log(out, "eval.csv")
    with pytest.raises(ValueError, match=r"eval\.csv holds evaluations on another held-out set"):
        train_codebook(images, CB, out, opts(3, eval_every=1), eval_images=other)
    assert _log(out, "eval.csv") == rows and _checkpoint(out)[0]["step"] == 2
    train_codebook(images, CB, out, opts(3), eval_images=other)  # no evaluation this call
    with pytest.raises(ValueError, match="another held-out set"):
        train_codebook(images, CB, out, opts(4, eval_every=1), eval_images=other)
    train_codebook(images, CB, out, opts(4, eval_every=1), eval_images=first)
    assert [r[0] for r in _log(out, "eval.csv")[1:]] == ["0", "1", "2", "4"]


def test_batches(rng):
    """Shapes and range; another step, another batch; each transformer sample holds distinct views
    of one scene, their tokens and poses. (That a batch is a function of seed and step alone, the
    resume tests show.)"""
    images, tokens, poses = _images(rng).reshape(-1, 16, 16, 3), _tokens(rng, views=5), _poses(rng, views=5)
    x = codebook_batch(images, 4, 7, 3)
    assert x.shape == (4, 3, 16, 16) and x.dtype == np.float32 and x.flags.c_contiguous
    assert not np.array_equal(x, codebook_batch(images, 4, 7, 4))
    assert x.min() >= -1 and x.max() <= 1
    tok, pos = transformer_batch(tokens, poses, 3, 8, 7, 3)
    assert tok.shape == (8, 3, 4) and pos.shape == (8, 3, 7) and pos.dtype == np.float32
    # each sample: distinct views of one scene, the tokens and poses of the same views
    flat = tokens.reshape(3, 5, 4)
    for b in range(8):
        s = next(s for s in range(3) for v in range(5) if np.array_equal(poses[s, v].astype(np.float32), pos[b, 0]))
        views = [next(v for v in range(5) if np.array_equal(poses[s, v].astype(np.float32), pos[b, i]))
                 for i in range(3)]
        assert len(set(views)) == 3
        assert np.array_equal(tok[b], flat[s, views])


# ---------------------------------------------------------------------------------------
# (b) a killed save leaves the previous checkpoint; (c) a corrupt one names the file


def test_a_failed_save_leaves_the_previous_checkpoint(tmp_path, rng, monkeypatch):
    images = _images(rng)
    run = str(tmp_path / "run")
    ckpt = os.path.join(run, "checkpoint.npz")
    train_codebook(images, CB, run, opts(2, checkpoint_every=1))
    before = load_npz(ckpt)
    real = os.replace

    def killed(src, dst):  # the checkpoint's rename never happens
        if os.fspath(dst).endswith("checkpoint.npz"):
            raise OSError("killed before the rename")
        return real(src, dst)

    monkeypatch.setattr(pyvf._io.os, "replace", killed)
    with pytest.raises(OSError, match="killed"):
        train_codebook(images, CB, run, opts(4, checkpoint_every=1))
    monkeypatch.setattr(pyvf._io.os, "replace", real)
    _assert_same_arrays(load_npz(ckpt), before)
    assert sorted(os.listdir(run)) == ["checkpoint.npz", "codebook.npz", "config.json", "log.csv"]  # no temporary
    # a temporary file left by a SIGKILL'ed writer is removed by the next run in the folder
    stale = os.path.join(run, ".checkpoint.npz.123.abcd.tmp")
    open(stale, "wb").write(b"junk")
    train_codebook(images, CB, run, opts(2, checkpoint_every=1))
    assert not os.path.exists(stale)


def test_a_corrupt_checkpoint_raises_naming_the_file(tmp_path, rng):
    images = _images(rng)
    run = str(tmp_path / "run")
    ckpt = os.path.join(run, "checkpoint.npz")
    train_codebook(images, CB, run, opts(1))
    data = open(ckpt, "rb").read()
    for broken in (data[: len(data) // 2], b"", b"not a zip at all" * 10):
        with open(ckpt, "wb") as f:
            f.write(broken)
        with pytest.raises(CheckpointError, match="checkpoint .*checkpoint.npz"):
            train_codebook(images, CB, run, opts(2))
    atomic_savez(ckpt, __meta__=json.dumps({"format": "other"}))
    with pytest.raises(CheckpointError, match="checkpoint .*checkpoint.npz"):
        train_codebook(images, CB, run, opts(2))


# ---------------------------------------------------------------------------------------
# (d) training trains; tokenize


def test_training_lowers_the_loss(tmp_path, rng):
    # the codebook: four images of smooth colour gradients, 15 steps (measured rec_loss: 0.53 over
    # the first five, 0.29 over the last five)
    yy, xx = np.mgrid[0:16, 0:16] / 15.0
    planes = [np.stack([xx, yy, 1 - xx], -1), np.stack([yy, 1 - yy, xx], -1), np.stack([1 - xx, xx * yy, yy], -1),
              np.stack([xx * yy, 1 - xx, 1 - yy], -1)]
    images = np.round(255 * np.stack(planes)).astype(np.uint8)  # (4, 16, 16, 3)
    # (the published recipe: its lr 1.584e-3 moves fastest over 15 steps, which these numbers measured)
    train_codebook(images, CB, str(tmp_path / "cb"), opts(15, batch_size=4), recipe="published")
    rec = [float(r[2]) for r in _log(str(tmp_path / "cb"))[1:]]  # rec_loss
    assert np.mean(rec[-5:]) < 0.7 * np.mean(rec[:5]), rec

    # the transformer: two scenes to memorise, 30 steps
    tokens, poses = _tokens(rng, scenes=2, views=3), _poses(rng, scenes=2, views=3)
    train_transformer(tokens, poses, TF, str(tmp_path / "tf"), opts(30, batch_size=8), TransformerRecipe(lr=1e-2,
                                                                                                           warmup=0))
    rows = _log(str(tmp_path / "tf"))[1:]
    loss, ce, pose = ([float(r[i]) for r in rows] for i in (1, 2, 3))
    assert np.mean(loss[-5:]) < 0.7 * np.mean(loss[:5]), loss
    assert np.mean(ce[-5:]) < 0.7 * np.mean(ce[:5]), ce
    # the pose targets change with the view drawn first (they are relative to it), so the pose
    # loss falls slowly and noisily (measured: 2.17 -> 1.86 over these 30 steps): only "lower"
    assert np.mean(pose[-5:]) < np.mean(pose[:5]), pose


def test_tokenize_equals_encode(rng):
    images = _images(rng, scenes=2, views=3)
    cb = Codebook(CB, seed=3)
    tokens = tokenize(cb, images, batch_size=4)  # 6 images: batches of 4 and 2
    assert tokens.shape == (2, 3, 8, 8) and tokens.dtype == np.int16
    x = images.reshape(-1, 16, 16, 3).transpose(0, 3, 1, 2).astype(np.float32) / np.float32(127.5) - np.float32(1)
    assert np.array_equal(tokens.reshape(6, 8, 8), cb.encode(np.ascontiguousarray(x)))
    assert np.array_equal(tokenize(cb, images.reshape(6, 16, 16, 3)), tokens.reshape(6, 8, 8))


def _cb(d, out, o=None, **kw):
    return train_codebook(d["images"], kw.pop("config", CB), out, o or opts(1), **kw)


def _tf(d, out, o=None, recipe=TransformerRecipe(), **kw):
    return train_transformer(kw.pop("tokens", d["tokens"]), kw.pop("poses", d["poses"]), TF, out, o or opts(1),
                             recipe, **kw)


@pytest.mark.parametrize("call, error, name", [
    (lambda: opts(0), ValueError, "steps"),
    (lambda: opts(2.0), TypeError, "steps"),
    (lambda: opts(1, batch_size=0), ValueError, "batch_size"),
    (lambda: opts(1, eval_every=-1), ValueError, "eval_every"),
    (lambda: opts(1, device="cuda"), ValueError, "device"),  # needs engine="torch"
    (lambda: TransformerRecipe(lr=-1.0), ValueError, "lr"),
    (lambda: TransformerRecipe(max_grad_norm=0), ValueError, "max_grad_norm"),
])
def test_the_options_refusals_name_the_field(call, error, name):
    with pytest.raises(error, match=rf"\b{name}\b"):
        call()


@pytest.mark.parametrize("call, error, name", [
    (lambda d, out: _cb({"images": d["images"].astype(np.float32)}, out), TypeError, "images"),
    (lambda d, out: _cb({"images": d["images"][..., :2]}, out), ValueError, "images"),
    (lambda d, out: _cb(d, out, eval_images=d["images"][..., :2]), ValueError, "eval_images"),
    (lambda d, out: _cb(d, out, recipe="fast"), ValueError, "recipe"),
    (lambda d, out: _cb(d, out, betas=(0.9, 1.0)), ValueError, "betas"),
    (lambda d, out: _cb(d, out, object_weight=0), ValueError, "object_weight"),
    (lambda d, out: _cb(d, out, restart="best"), ValueError, "restart"),
    (lambda d, out: _cb(d, out, schedule="linear"), ValueError, "schedule"),
    (lambda d, out: _cb(d, out, opts(1, init=d["tf_file"])), ValueError, "init"),  # another kind of model
    (lambda d, out: _cb(d, out, opts(1, init=d["cb8_file"])), ValueError, "init"),  # another configuration
    (lambda d, out: _cb(d, out, opts(1, init=out + ".npz")), FileNotFoundError, "init"),
])
def test_train_codebook_refusals_name_the_argument(tmp_path, rng, call, error, name):
    d = {"images": _images(rng), "tf_file": Transformer(TF).save(str(tmp_path / "tf.npz")),
         "cb8_file": Codebook(dataclasses.replace(CB, n_embed=8)).save(str(tmp_path / "cb8.npz"))}
    out = str(tmp_path / "run")
    with pytest.raises(error, match=rf"\b{name}\b"):
        call(d, out)
    assert not os.path.exists(out)


@pytest.mark.parametrize("call, error, name", [
    (lambda d, out: _tf(d, out, tokens=d["tokens"] + 16), ValueError, "tokens"),
    (lambda d, out: _tf(d, out, tokens=d["tokens"] * 1.0), TypeError, "tokens"),
    (lambda d, out: _tf(d, out, poses=d["poses"][:, :4]), ValueError, "poses"),
    (lambda d, out: _tf(d, out, poses=d["poses"] * [1, 1, 1, 1.01, 1, 1, 1]), ValueError, "poses"),  # not unit
    (lambda d, out: _tf(d, out, poses=d["poses"] * np.nan), ValueError, "poses"),
    (lambda d, out: _tf(d, out, tokens=d["tokens"][:, :2], poses=d["poses"][:, :2]), ValueError, "tokens"),
    (lambda d, out: _tf(d, out, opts(5), TransformerRecipe(warmup=5)), ValueError, "warmup"),
    (lambda d, out: _tf(d, out, opts(8), TransformerRecipe(total_steps=4)), ValueError, "total_steps"),
    (lambda d, out: _tf(d, out, opts(1, init=d["cb_file"])), ValueError, "init"),
    (lambda d, out: tokenize(Codebook(CB), d["images"].astype(np.int64)), TypeError, "images"),
    (lambda d, out: tokenize(Codebook(CB), d["images"], batch_size=0), ValueError, "batch_size"),
])
def test_train_transformer_and_tokenize_refusals_name_the_argument(tmp_path, rng, call, error, name):
    d = {"images": _images(rng), "tokens": _tokens(rng), "poses": _poses(rng),
         "cb_file": Codebook(CB).save(str(tmp_path / "cb.npz"))}
    out = str(tmp_path / "run")
    with pytest.raises(error, match=rf"\b{name}\b"):
        call(d, out)
    assert not os.path.exists(out)


# ---------------------------------------------------------------------------------------
# (e) the commands


def test_commands_end_to_end(tmp_path, rng, monkeypatch, capsys):
    images, poses = _images(rng, scenes=3, views=5), _poses(rng, scenes=3, views=5)
    fake = types.ModuleType("pyvf.scenes")  # the dataset reader, whatever the state of pyvf.scenes
    fake.load_dataset = lambda path: types.SimpleNamespace(images=images, poses=poses, seed=0)
    held_out = []  # the held-out scenes the codebook run asked for: (seed, n, views, size)

    def generate_scenes(seed, n, views, size):
        held_out.append((seed, n, views, size))
        return _images(np.random.default_rng(seed), scenes=n, views=views), None

    fake.generate_scenes = generate_scenes
    monkeypatch.setitem(sys.modules, "pyvf.scenes", fake)
    cb_json, tf_json = tmp_path / "cb.json", tmp_path / "tf.json"
    cb_json.write_text(json.dumps(dataclasses.asdict(CB)))
    tf_json.write_text(json.dumps(dataclasses.asdict(dataclasses.replace(TF, token_image_size=8))))
    run, d = _cli(), tmp_path
    assert run("train-codebook", "--data", d / "data", "--out", d / "cb", "--steps", 3, "--batch", 2,
               "--config", cb_json, "--no-progress", "--restart", "worst", "--schedule", "cosine") == 0
    cb = Codebook.load(str(d / "cb" / "codebook.npz"))
    # evaluated on held-out scenes (seed 1, 4 views each) before the first step and after the last
    assert held_out == [(1, 32, 4, 16)]
    assert [r[0] for r in _log(str(d / "cb"), "eval.csv")[1:]] == ["0", "3"]
    recorded = json.loads((d / "cb" / "config.json").read_text())
    assert recorded["calls"][0]["command"]["args"]["steps"] == 3 and recorded["config"]["image_size"] == 16
    assert (recorded["hyperparameters"]["restart"], recorded["hyperparameters"]["schedule"]) == ("worst", "cosine")
    assert run("tokenize", "--codebook", d / "cb" / "codebook.npz", "--data", d / "data",
               "--out", d / "tok" / "tokens.npz", "--no-progress") == 0
    tokens, saved_poses, n_embed, fingerprint = load_tokens(str(d / "tok" / "tokens.npz"))
    assert np.array_equal(tokens, tokenize(cb, images)) and np.array_equal(saved_poses, poses) and n_embed == 16
    assert fingerprint == cb.fingerprint()
    tf = ["train-transformer", "--tokens", d / "tok" / "tokens.npz", "--out", d / "tf", "--total-steps", 3,
          "--batch", 2, "--no-progress", "--lr", 1e-3]
    assert run(*tf, "--steps", 2, "--config", tf_json) == 0
    Transformer.load(str(d / "tf" / "transformer.npz"))
    hyper = _hyper(d / "tf")
    assert (hyper["lr"], hyper["total_steps"], hyper["max_grad_norm"]) == (1e-3, 3, 1.0)
    # a run's config.json is a valid --config; a resume is one more call in config.json
    assert run(*tf, "--steps", 3, "--config", d / "tf" / "config.json") == 0
    calls = json.loads((d / "tf" / "config.json").read_text())["calls"]
    assert [c["resumed_from_step"] for c in calls] == [None, 2] and [c["steps"] for c in calls] == [2, 3]
    capsys.readouterr()

    # errors: printed, status 1, no run folder
    for argv, said in ((["train-transformer", "--tokens", d / "tok" / "tokens.npz", "--out", d / "x", "--steps", 2],
                        "n_embeddings=256"),  # tiny: 256 codes, but the tokens index 16
                       (["train-transformer", "--tokens", d / "tok" / "tokens.npz", "--out", d / "x", "--steps", 2,
                         "--config", tf_json, "--codebook", Codebook(CB, seed=9).save(str(d / "other.npz"))],
                        "other.npz"),  # the same sizes, not the codebook of these tokens
                       (["tokenize", "--codebook", d / "tf" / "log.csv", "--data", d / "data", "--out", d / "t.npz"],
                        "log.csv"),
                       (["train-codebook", "--data", d / "data", "--out", d / "x", "--steps", 1, "--config",
                         d / "missing.json"], "missing.json")):
        assert run(*argv, "--no-progress") == 1
        err = capsys.readouterr().err
        assert f"pyvf {argv[0]}: error: " in err and said in err, err
    assert not os.path.exists(d / "x")


def test_tasks_refuse_held_out_scenes_of_the_training_seed(tmp_path):
    """Held-out scenes of the training data's seed raise naming eval_seed, nothing written; seed 1 trains."""
    run, codebook = _smoke_files(tmp_path)
    o, out = opts(2, batch_size=2, eval_every=1), str(tmp_path / "tf")
    for call in (lambda seed: pyvf.cli.train.transformer_run(str(tmp_path / "tok.npz"), out, o, config=str(
                     tmp_path / "tf.json"), codebook=codebook, eval_scenes=1, eval_seed=seed),
                 lambda seed: pyvf.cli.train.codebook_run(str(tmp_path / "d16"), out, o, config=str(
                     tmp_path / "cb.json"), eval_scenes=1, eval_seed=seed)):
        with pytest.raises(ValueError, match=r"\beval_seed\b"):
            call(0)
    assert not os.path.exists(out)
    call(1)


def test_runs_table_and_eval_plot(tmp_path, rng, capsys):
    """`pyvf runs`: one row per run with its changed hyperparameters and last evaluation (read back
    from eval.csv), or the last at or before --step; a torn last line of a log is left out."""
    images, held_out = _images(rng), _images(rng, scenes=1, views=2).reshape(-1, 16, 16, 3)
    a, b = str(tmp_path / "a"), str(tmp_path / "b")
    train_codebook(images, CB, a, opts(2, eval_every=1), eval_images=held_out)
    train_codebook(images, CB, b, opts(3, eval_every=1), lr=1e-3, eval_images=held_out)
    assert os.path.getsize(os.path.join(b, "eval.png")) > 0
    table = runs_table([a, b]).splitlines()
    assert table[0].startswith("| run | steps | wall (s) | changes | mae (step) | psnr (step)")
    rows = _log(b, "eval.csv")
    assert table[3].startswith("| b | 3 |") and "lr=0.001 |" in table[3] and f"{float(rows[-1][1]):.4g} (3)" in table[3]
    assert "(the first codebook run)" in table[2]
    line = runs_table([a, b], step=2).splitlines()[3]
    assert line.startswith("| b | 2 |") and f"{float(rows[3][1]):.4g} (2)" in line and rows[3][1] != rows[-1][1]
    run = _cli()
    assert "codebook held-out at step 2: mae " in capsys.readouterr().err  # printed as the runs trained
    assert run("runs", a, b) == 0 and capsys.readouterr().out.splitlines() == table
    assert run("runs", str(tmp_path)) == 1 and "config.json" in capsys.readouterr().err  # not a run folder
    torn = tmp_path / "torn"
    shutil.copytree(a, torn)
    for name in ("eval.csv", "log.csv"):
        with open(torn / name, "a") as f:
            f.write("9,0.5")  # no newline: the write was cut
    assert run("runs", torn) == 0
    assert capsys.readouterr().out.splitlines()[2] == runs_table([a]).splitlines()[2].replace("| a |", "| torn |")
    train_codebook(images, CB, str(torn), opts(3, eval_every=1), eval_images=held_out)
    assert [r[0] for r in _log(str(torn), "eval.csv")[1:]] == ["0", "1", "2", "3"]  # the trainer agrees


def test_export_writes_the_checkpoints_model(tmp_path, rng, capsys):
    """`pyvf export RUN -o F`: the model of the run's last checkpoint, the same arrays and configuration
    as the final model file the run writes; a folder without a checkpoint, a file that is not a
    checkpoint each raise naming the file."""
    cb_run, tf_run = str(tmp_path / "cb"), str(tmp_path / "tf")
    train_codebook(_images(rng), CB, cb_run, opts(2))
    train_transformer(_tokens(rng), _poses(rng), TF, tf_run, opts(3))
    for run, name, cls in ((cb_run, "codebook.npz", Codebook), (tf_run, "transformer.npz", Transformer)):
        kind, step, path = export_run(run, tmp_path / f"exported-{name}")
        assert (kind, step) == (name[:-4], 2 if cls is Codebook else 3)
        want, got = load_npz(os.path.join(run, name), "model"), load_npz(path, "model")
        _assert_same_arrays(got, want)
        fresh = cls(cls.CONFIG(**json.loads(str(want["__config__"])))).state_dict()
        assert any(not np.array_equal(fresh[k], want[k]) for k in fresh)  # the test sees training
    run = _cli()
    assert run("export", os.path.join(tf_run, "checkpoint.npz"), "-o", tmp_path / "t") == 0
    assert capsys.readouterr().out.strip() == f"transformer at step 3: {tmp_path / 't.npz'}"
    assert run("export", tmp_path, "-o", tmp_path / "x") == 1
    assert "checkpoint.npz does not exist" in capsys.readouterr().err
    with pytest.raises(CheckpointError, match="log.csv"):
        export_run(os.path.join(tf_run, "log.csv"), tmp_path / "x")
    assert not os.path.exists(tmp_path / "x.npz")


def _engine_spy(monkeypatch):
    """Record what the loop starts from: the model's state dict (through the engine's current(), so
    the torch engine's own copy) and the optimiser's state (its moments synced by current())."""
    real, seen = loops._loop, {}

    def spy(run, opt, step, current, *args):
        seen["model"], seen["optimizer"] = current().state_dict(), opt.state_dict()
        return real(run, opt, step, current, *args)

    monkeypatch.setattr(loops, "_loop", spy)
    return seen


def _trained_model_files(tmp_path, rng):
    """A codebook and a transformer file, each trained 2 steps from seed 3 (the runs below use seed
    0): model files unlike both the seed's initialisation and each other's."""
    cb, tf = str(tmp_path / "init-cb"), str(tmp_path / "init-tf")
    train_codebook(_images(rng), CB, cb, opts(2, seed=3))
    train_transformer(_tokens(rng), _poses(rng), TF, tf, opts(2, seed=3), TransformerRecipe(lr=1e-3))
    return os.path.join(cb, "codebook.npz"), os.path.join(tf, "transformer.npz")


@pytest.mark.parametrize("engine", ["pyvf", "torch"])
def test_init_starts_from_the_files_weights(tmp_path, rng, monkeypatch, engine):
    """A fresh run with init starts, before its first update, from the file's parameters bit for bit
    (the codebook's EMA buffers too) with a fresh optimiser (step 0, zero moments): read from the
    engine, so the torch engine's model is checked, not only pyvf's. The run records init's name
    and sha256 among its hyperparameters."""
    cb_file, tf_file = _trained_model_files(tmp_path, rng)
    for kind, file in (("codebook", cb_file), ("transformer", tf_file)):
        seen = _engine_spy(monkeypatch)
        out = str(tmp_path / f"{engine}-{kind}")
        if kind == "codebook":
            train_codebook(_images(rng), CB, out, opts(1, init=file, engine=engine))
        else:
            train_transformer(_tokens(rng), _poses(rng), TF, out, opts(1, init=file, engine=engine))
        want = load_npz(file, "model")
        want.pop("__config__")
        _assert_same_arrays(seen["model"], want)
        fresh = (Codebook(CB) if kind == "codebook" else Transformer(TF)).state_dict()  # seed 0's
        assert any(not np.array_equal(fresh[k], want[k]) for k in fresh)  # the check sees init ignored
        opt = seen["optimizer"]
        assert opt["step"] == 0 and all(not a.any() for m in ("exp_avg", "exp_avg_sq") for a in opt[m].values())
        record = {"path": os.path.basename(file), "sha256": hashlib.sha256(open(file, "rb").read()).hexdigest()}
        assert _hyper(out)["init"] == record and _checkpoint(out)[0]["hyper"]["init"] == record
    assert int(load_npz(cb_file)["quantize.counter"]) == 2  # the EMA state compared above was a trained one


def test_init_may_differ_in_what_does_not_shape_the_weights(tmp_path, rng):
    """Fine-tuning onto the empty code: a codebook file without it starts a run with it, from the
    file's weights and under the run's configuration (a file of other shapes is refused above)."""
    file = Codebook(CB).save(str(tmp_path / "plain.npz"))
    out = str(tmp_path / "empty")
    train_codebook(_images(rng), dataclasses.replace(CB, empty_code=True), out, opts(1, init=file))
    assert _hyper(out)["init"]["path"] == "plain.npz"
    assert Codebook.load(os.path.join(out, "codebook.npz")).config.empty_code


def test_an_interrupted_run_resumes_from_its_last_checkpoint_bitwise(tmp_path, rng, monkeypatch):
    """KeyboardInterrupt (Ctrl-C, or any kill) during step 4 of a codebook run checkpointed every 2
    steps: the checkpoint is step 2's, and log.csv's row 3, past it, goes on resume; resuming gives
    the uninterrupted run bit for bit. (The transformer loop is the same Run: its resume is
    test_transformer_resume_..., its interrupted command the test below.)"""
    images, real = _images(rng), loops.codebook_batch
    a, b = str(tmp_path / "a"), str(tmp_path / "b")
    train_codebook(images, CB, a, opts(5, checkpoint_every=2))

    def interrupted(*args, **kwargs):
        if args[3] == 4:  # the step
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    with monkeypatch.context() as m:
        m.setattr(loops, "codebook_batch", interrupted)
        with pytest.raises(KeyboardInterrupt):
            train_codebook(images, CB, b, opts(5, checkpoint_every=2))
    assert _checkpoint(b)[0]["step"] == 2 and not os.path.exists(os.path.join(b, "codebook.npz"))
    assert [r[0] for r in _log(b)[1:]] == ["1", "2", "3"]
    train_codebook(images, CB, b, opts(5, checkpoint_every=2))
    _assert_same_run(a, b, "codebook.npz")


def test_ctrl_c_in_train_transformer_and_tokenize(tmp_path, monkeypatch, capsys):
    """KeyboardInterrupt inside train-transformer (during step 4 of a run checkpointed every 3 steps)
    and tokenize: one line each, status 130; the same command resumes from step 3."""
    run, cb = _smoke_files(tmp_path)
    real = loops.transformer_batch

    def interrupted(*args):
        if args[5] == 4:  # the step
            raise KeyboardInterrupt
        return real(*args)

    tf = ["train-transformer", "--tokens", tmp_path / "tok.npz", "--out", tmp_path / "tf", "--steps", 6, "--batch", 2,
          "--config", tmp_path / "tf.json", "--checkpoint-every", 3, "--eval-every", 0, "--no-progress"]
    capsys.readouterr()
    monkeypatch.setattr(loops, "transformer_batch", interrupted)
    assert run(*tf) == 130
    assert capsys.readouterr().err == ("pyvf train-transformer: interrupted; rerun the same command (a training run "
                                       "resumes from its last checkpoint)\n")
    monkeypatch.setattr(loops, "transformer_batch", real)
    assert run(*tf) == 0
    assert json.loads((tmp_path / "tf" / "config.json").read_text())["calls"][-1]["resumed_from_step"] == 3

    def tokenize(*args, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(pyvf.cli.train, "tokenize", tokenize)
    assert run("tokenize", "--codebook", cb, "--data", tmp_path / "d16", "--out", tmp_path / "t2.npz",
               "--no-progress") == 130
    assert capsys.readouterr().err.startswith("pyvf tokenize: interrupted; rerun the same command")
    assert not os.path.exists(tmp_path / "t2.npz")
