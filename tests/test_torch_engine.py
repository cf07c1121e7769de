"""train_transformer's torch engine against pyvf's: the same run in both, resume across engines,
the checkpointed optimiser state, the parity check at checkpoints (and a divergent forward that
stops a run); two data-parallel processes against one; train_codebook's torch engine against
pyvf's; the engines' refusals, one table, before the run folder is touched."""

import csv
import functools
import dataclasses
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from pyvf.cli import main
from pyvf.models.codebook import Codebook, CodebookConfig
from pyvf.train import torch_engine
from pyvf.train._run import read_checkpoint
from pyvf.train.loops import (TINY_TRANSFORMER, RunOptions, TransformerRecipe, save_tokens,
                              train_codebook, train_transformer)
from pyvf.train.loops import codebook_batch, transformer_batch
from pyvf.train.torch_engine import PARITY_RTOL, TorchCodebook, TorchTransformer, check_engine, data_parallel
from pyvf.train.optim import Adam, AdamW, published_weight_decay
from pyvf.models.transformer import Transformer
from pyvf.verify import torch_ports
from pyvf.verify.torch_ports import CodebookPort, TransformerPort

CFG = dataclasses.replace(TINY_TRANSFORMER, d_model=32, n_head=2, n_layer=2, token_image_size=4, sequence_size=4,
                          n_embeddings=16)
D = CFG.d_model


def _data(seed=0, scenes=10, views=6):
    rng = np.random.default_rng(seed)
    tokens = rng.integers(0, CFG.n_embeddings, size=(scenes, views, 4, 4)).astype(np.int16)
    q = rng.normal(size=(scenes, views, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    poses = np.concatenate([rng.normal(size=(scenes, views, 3)), q], -1).astype(np.float32)
    return tokens, poses


def _train(tmp_path, name, engine, steps=20, recipe=(), **kw):
    """recipe: TransformerRecipe's fields beside lr 1e-3 and warmup 2; kw: RunOptions'."""
    tokens, poses = _data()
    return train_transformer(tokens, poses, CFG, tmp_path / name, RunOptions(**{
        "steps": steps, "batch_size": 4, "progress": False, "engine": engine, **kw}),
        TransformerRecipe(**{"lr": 1e-3, "warmup": 2, **dict(recipe)}))


def _check_same_run(a, b, w0):
    """a, b: state dicts after the same steps from w0. Every tensor's difference is bounded by
    1e-4 of how far training moved it: both engines round each step's float32 arithmetic in
    another order (~1e-6 relative per step, measured 1e-6 over 20 steps), and Adam divides by
    sqrt(v), so a rounding difference in a small gradient moves its update by as much. Not the
    key bias (c_attn/bias's last third): softmax is invariant to it, its exact gradient is 0
    and what each engine computes is rounding noise (~1e-9) that Adam's eps (1e-8) keeps to
    steps of ~lr * 1e-1; its entries stay within 1e-5 of 0 in both."""
    for k in w0:
        da, db, moved = a[k], b[k], a[k] - w0[k]
        if k.endswith("attn/c_attn/bias"):
            key = slice(2 * D, 3 * D)
            assert np.abs(da[..., key]).max() < 1e-5 and np.abs(db[..., key]).max() < 1e-5, k
            da, db, moved = da[..., :2 * D], db[..., :2 * D], moved[..., :2 * D]
        err = np.linalg.norm(da - db) / np.linalg.norm(moved)
        assert err < 1e-4, (k, err)


@pytest.mark.parametrize("clip", [dict(max_grad_norm=None), dict(max_grad_norm=0.02)])
def test_torch_engine_equals_pyvf_after_20_steps(tmp_path, clip):
    """clip: none, or a per-tensor norm of 0.02 (clips most tensors: at step 1 their norms are 0.002
    to 0.66). The weights, the logged losses and gradient
    norms (logged without clipping too), and the checkpoint's moments, step count and
    hyperparameters: each moment tensor normwise within 1e-4 of pyvf's (measured <= 1.4e-6: float32
    rounding in another order, ~1e-6 per step as the weights')."""
    a = _train(tmp_path, "pyvf", "pyvf", recipe=clip).state_dict()
    b = _train(tmp_path, "torch", "torch", recipe=clip).state_dict()
    _check_same_run(a, b, Transformer(CFG, seed=0).state_dict())
    # and the logs: the same losses to float32 rounding, the same learning rates exactly
    logs = [list(csv.DictReader(open(tmp_path / n / "log.csv"))) for n in ("pyvf", "torch")]
    for ra, rb in zip(*logs):
        assert ra["lr"] == rb["lr"] and np.isfinite(float(ra["grad_norm"]))
        assert abs(float(ra["loss"]) - float(rb["loss"])) < 1e-5 * abs(float(ra["loss"]))
        assert abs(float(ra["grad_norm"]) - float(rb["grad_norm"])) < 1e-3 * float(ra["grad_norm"])
    meta_a, _, opt_a = read_checkpoint(tmp_path / "pyvf" / "checkpoint.npz", "transformer")
    meta_b, _, opt_b = read_checkpoint(tmp_path / "torch" / "checkpoint.npz", "transformer")
    assert meta_a["optimizer"] == meta_b["optimizer"] and opt_a["step"] == opt_b["step"] == 20
    for key in ("exp_avg", "exp_avg_sq"):
        assert set(opt_a[key]) == set(opt_b[key])
        for k, m in opt_a[key].items():
            assert opt_b[key][k].dtype == m.dtype == np.float32, (key, k)
            assert np.linalg.norm(m - opt_b[key][k]) / np.linalg.norm(m) < 1e-4, (key, k)


def test_resume_exact_and_across_engines(tmp_path):
    straight = _train(tmp_path, "straight", "torch").state_dict()
    _train(tmp_path, "split", "torch", steps=10, recipe=dict(total_steps=20))
    resumed = _train(tmp_path, "split", "torch", steps=20).state_dict()
    for k in straight:  # the same engine on the same machine: bit for bit
        np.testing.assert_array_equal(straight[k], resumed[k], err_msg=k)
    # pyvf's checkpoint continued by torch: torch's run to float32 rounding (each is pyvf's: the test above)
    _train(tmp_path, "cross", "pyvf", steps=10, recipe=dict(total_steps=20))
    cross = _train(tmp_path, "cross", "torch", steps=20).state_dict()
    _check_same_run(straight, cross, Transformer(CFG, seed=0).state_dict())


@pytest.mark.parametrize("bug", ["qkv_order", "wrong_branch"])  # ln_eps: the next test, in a whole run
def test_parity_catches_a_planted_bug(bug):
    model = Transformer(CFG, seed=3)
    eng = TorchTransformer(model, AdamW(model.params, 1e-3, decay=published_weight_decay))
    bad = TransformerPort(CFG, bug=bug)
    bad.load_state_dict(eng.port.state_dict())
    eng.port = bad  # the same weights (pyvf reads them from the engine's own): only the math differs
    tokens, poses = _data()
    comparison = eng.parity(*transformer_batch(tokens, poses, 4, 4, 0, 0))
    assert not comparison.ok, comparison


def test_a_divergent_forward_stops_a_whole_run_before_its_checkpoint(tmp_path, monkeypatch):
    """The planted-bug tests call parity() directly; here the torch model of a real run is wrong (the
    LayerNorm eps of the port's bug list), so training and the check both use it: the first checkpoint's
    parity must stop the run, log the failing row, and leave no checkpoint of the divergent model."""
    monkeypatch.setattr(torch_ports, "TransformerPort", functools.partial(torch_ports.TransformerPort, bug="ln_eps"))
    with pytest.raises(RuntimeError, match=r"parity check at step 3: the torch model and pyvf differ first in"):
        _train(tmp_path, "bad", "torch", steps=6, checkpoint_every=3)
    assert not (tmp_path / "bad" / "checkpoint.npz").exists()
    rows = (tmp_path / "bad" / "parity.csv").read_text().splitlines()
    assert len(rows) == 2 and rows[1].startswith("3,")
    assert float(rows[1].split(",")[2]) > torch_engine.PARITY_RTOL


def test_bf16_trains_and_stays_near_fp32(tmp_path):
    """bf16 autocast on the CPU: the loss falls as in fp32, the weights stay float32."""
    a = _train(tmp_path, "fp32", "torch", steps=15)
    b = _train(tmp_path, "bf16", "torch", steps=15, precision="bf16")
    la = [float(r["loss"]) for r in csv.DictReader(open(tmp_path / "fp32" / "log.csv"))]
    lb = [float(r["loss"]) for r in csv.DictReader(open(tmp_path / "bf16" / "log.csv"))]
    assert lb[-1] < lb[0] and abs(lb[-1] - la[-1]) < 0.05 * la[-1], (la, lb)  # bf16's u = 3.9e-3
    assert all(p.dtype == np.float32 for p in b.params.values())
    assert any(not np.array_equal(a.params[k], b.params[k]) for k in a.params)  # autocast did change the math


# One torchrun launch for the run and its resume: both processes call the command twice. The first
# call initialises the process group from torchrun's environment (the group is kept for the second,
# which finds it initialised: a process group cannot be made twice under one launch), the second
# resumes from rank 0's checkpoint.
_TWO_CALLS = """
import sys
import torch.distributed as dist
from pyvf.cli import main
destroy, dist.destroy_process_group = dist.destroy_process_group, lambda: None
argv = sys.argv[1:]
assert main([*argv, "--steps", "3", "--total-steps", "6"]) == 0
assert main([*argv, "--steps", "6"]) == 0
destroy()
"""


def test_two_processes_equal_one_and_resume(tmp_path):
    """`torchrun --nproc-per-node 2 pyvf train-transformer --engine torch`, batch 5 on 2 gloo processes
    (shards of 3 and 2 rows: unequal, so a shard weighted wrongly or a row run twice shows), 3 steps, then resumed by both to 6, against one process running the whole
    batch 6 steps. The bound is _check_same_run's, 1e-4 of how far training moved each tensor: the
    processes sum their weighted shard gradients in another order than one process sums the batch
    (float32 rounding, ~1e-7 per step, amplified where Adam divides a small gradient by its sqrt(v));
    measured 9e-6 (ln_f/gamma), 5e-7 elsewhere."""
    save_tokens(tmp_path / "tokens.npz", *_data(), CFG.n_embeddings)
    (tmp_path / "config.json").write_text(json.dumps(dataclasses.asdict(CFG)))
    (tmp_path / "two_calls.py").write_text(_TWO_CALLS)
    two = tmp_path / "two"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", "two_calls.py",
           "train-transformer", "--engine", "torch", "--tokens", "tokens.npz", "--config", "config.json",
           "--out", str(two), "--lr", "1e-3", "--warmup", "2", "--eval-every", "0", "--no-progress",
           "--batch", "5", "--checkpoint-every", "3"]
    # from tmp_path, as every command test: the installed pyvf, never a checkout on sys.path
    done = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    one = _train(tmp_path, "one", "torch", steps=6, batch_size=5).state_dict()
    _check_same_run(one, Transformer.load(two / "transformer.npz").state_dict(), Transformer(CFG, seed=0).state_dict())
    # rank 0 alone wrote the folder: a row at each call's last step, the parity checks at both checkpoints
    logs = [list(csv.DictReader(open(d / "log.csv"))) for d in (tmp_path / "one", two)]
    assert [r["step"] for r in logs[1]] == ["3", "6"]
    ra, rb = logs[0][-1], logs[1][-1]
    assert ra["lr"] == rb["lr"] and abs(float(ra["loss"]) - float(rb["loss"])) < 1e-5 * float(ra["loss"])
    assert [r["step"] for r in csv.DictReader(open(two / "parity.csv"))] == ["3", "6"]
    calls = json.loads((two / "config.json").read_text())["calls"]
    assert [c["processes"] for c in calls] == [2, 2] and calls[1]["resumed_from_step"] == 3


# ---------------------------------------------------------------------------------------
# the codebook's torch engine against pyvf's

# 64 channels: 2 per GroupNorm group (with 1 per group a conv bias before a GroupNorm has an exactly
# zero gradient, whose rounding noise Adam turns into lr-sized steps that differ between engines)
CB = CodebookConfig(ch=64, ch_mult=(1, 1), num_res_blocks=1, attn_resolutions=(8,), z_channels=32, embed_dim=8,
                    n_embed=16, image_size=16)
CB64 = dataclasses.replace(CB, dtype="float64")


def _images():
    from pyvf.scenes import generate_scenes
    return generate_scenes(0, 4, views=4, size=16)[0]  # (4, 4, 16, 16, 3) uint8


def _train_cb(tmp_path, name, engine, cfg=CB64, steps=4, object_weight=None, **kw):
    """The default recipe (small-batch: Adam (0.9, 0.99), objects weighted 4) with a dead-code restart
    every 3 steps."""
    return train_codebook(_images(), cfg, tmp_path / name, RunOptions(**{
        "steps": steps, "batch_size": 4, "progress": False, "engine": engine, **kw}), reset_dead_codes=3,
        object_weight=object_weight)


def _check_same_codebook(a, b, w0, rtol):
    """a, b: Codebook state dicts after the same steps from w0: every parameter and EMA buffer within
    rtol of how far training moved it. Not the attention's key biases (k.bias): softmax is invariant
    to them, their exact gradient is 0 and each engine's is rounding noise, below Adam's eps: both
    stay within 1e-4 of 0 (measured 3e-5 in float32 after 6 steps; one step of lr is 3e-4)."""
    assert a["quantize.counter"] == b["quantize.counter"]
    for k in w0:
        if k.endswith(".k.bias"):
            assert np.abs(a[k]).max() < 1e-4 and np.abs(b[k]).max() < 1e-4, k
        elif k != "quantize.counter":
            err = np.linalg.norm(a[k] - b[k]) / np.linalg.norm(a[k] - w0[k])
            assert err < rtol, (k, err)


@pytest.mark.parametrize("empty_code", [False, True])
def test_torch_codebook_equals_pyvf_and_resumes_across_engines(tmp_path, empty_code):
    """In float64 (with and without the empty code, whose patches a restart never draws from), 4 steps with object weighting and a dead-code restart: every weight and EMA
    buffer within 1e-9 of its movement (measured 1.3e-12 after 20 steps: float64's u = 1.1e-16
    amplified by training, ~1e4); the same for pyvf's checkpoint at step 3 continued by torch. (In
    float32 the same amplification of u = 6e-8 leaves ~1e-3: there parity checks the forward, below.)
    The comparison sees an engine that skips the object weighting. (A wrong epsilon convention or EMA
    decay moves the weights or the EMA buffers by far more than 1e-9; a wrong forward fails parity.)"""
    cfg = dataclasses.replace(CB64, empty_code=empty_code)
    w0 = Codebook(cfg, seed=0).state_dict()
    a = _train_cb(tmp_path, "pyvf", "pyvf", cfg).state_dict()
    b = _train_cb(tmp_path, "torch", "torch", cfg).state_dict()
    _check_same_codebook(a, b, w0, 1e-9)
    logs = [list(csv.DictReader(open(tmp_path / n / "log.csv"))) for n in ("pyvf", "torch")]
    for ra, rb in zip(*logs):
        assert ra["lr"] == rb["lr"] and ra["usage"] == rb["usage"], (ra, rb)
        assert abs(float(ra["loss"]) - float(rb["loss"])) < 1e-12 * float(ra["loss"])
    _train_cb(tmp_path, "cross", "pyvf", cfg, steps=3)
    _check_same_codebook(a, _train_cb(tmp_path, "cross", "torch", cfg).state_dict(), w0, 1e-9)
    with pytest.raises(AssertionError):
        _check_same_codebook(a, _train_cb(tmp_path, "w1", "torch", cfg, object_weight=1.0).state_dict(), w0, 1e-9)


def test_torch_codebook_resume_and_parity_log(tmp_path):
    """Resume bit for bit; parity.csv has a row per checkpoint within the bound (measured ~4e-7), and
    as log.csv a fresh start in the folder drops an older run's rows (a resume keeps them: the
    two-process test)."""
    straight = _train_cb(tmp_path, "straight", "torch", CB, steps=4, checkpoint_every=2).state_dict()
    _train_cb(tmp_path, "split", "torch", CB, steps=2)
    resumed = _train_cb(tmp_path, "split", "torch", CB, steps=4).state_dict()
    for k in straight:  # the same engine on the same machine: bit for bit
        np.testing.assert_array_equal(straight[k], resumed[k], err_msg=k)
    rows = list(csv.DictReader(open(tmp_path / "straight" / "parity.csv")))
    assert [r["step"] for r in rows] == ["2", "4"]
    assert all(0 < float(r["rel_err"]) < 1e-5 and float(r["bound"]) == PARITY_RTOL for r in rows), rows
    _train_cb(tmp_path, "split", "torch", CB, steps=1, resume=False)  # start over
    assert [r["step"] for r in csv.DictReader(open(tmp_path / "split" / "parity.csv"))] == ["1"]


def _transpose_mid_conv(port):
    """A conv that reads its (out, in) kernel as (in, out): a square kernel runs either way."""
    conv = port.encoder.mid.block_1.conv1
    conv.forward = lambda x: torch.nn.functional.conv2d(x, conv.weight.transpose(0, 1), conv.bias, padding=1)


def _group_norm_eps(port):
    """eps 1e-2 (published 1e-6) in the last GroupNorm: measured 1.4e-2 in the reconstruction (1e-3 gives
    1.4e-3, at the bound: an eps error shows from about 1e-3 on)."""
    port.decoder.norm_out.eps = 1e-2


@pytest.mark.parametrize("bug", ["padding", _transpose_mid_conv, _group_norm_eps])
def test_codebook_parity_catches_a_planted_bug(bug):
    model = Codebook(CB, seed=3)
    eng = TorchCodebook(model, Adam(model.params, 1e-3))
    bad = CodebookPort(CB, bug=bug if isinstance(bug, str) else None)
    bad.load_state_dict(eng.port.state_dict())
    if callable(bug):
        bug(bad)
    eng.port = bad  # the same weights (pyvf reads them from the engine's own): only the math differs
    comparison = eng.parity(codebook_batch(_images().reshape(-1, 16, 16, 3), 4, 0, 0))
    assert not comparison.ok, comparison


def test_pyvf_train_with_the_torch_engine(tmp_path):
    """`pyvf train --preset smoke --engine torch`: both stages train in torch, each checked by pyvf."""
    assert main(["train", "--out", str(tmp_path / "run"), "--preset", "smoke", "--engine", "torch",
                 "--no-progress"]) == 0
    for stage in ("codebook", "transformer"):
        calls = json.loads((tmp_path / "run" / stage / "config.json").read_text())["calls"]
        assert calls[-1]["engine"] == "torch"
        assert [r["step"] for r in csv.DictReader(open(tmp_path / "run" / stage / "parity.csv"))][-1] == "2"


# ---------------------------------------------------------------------------------------
# refusals: one table; each before the run folder is made or touched


@pytest.fixture
def one_gpu(monkeypatch):
    """torch as on a machine with one CUDA device (cuda:0): what check_engine asks torch."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)


@pytest.mark.parametrize("engine, device, precision, name", [
    ("jax", "cpu", "fp32", "engine"),
    ("pyvf", "cuda", "fp32", "engine"),  # a GPU needs the torch engine
    ("torch", "cpu", "fp16", "precision"),
    ("torch", "gpu", "fp32", "device"),
    ("torch", "cuda:1", "fp32", "device"),  # torch.device accepts it; the first .to() failed, after the folder
    ("torch", "cuda:x", "fp32", "device"),
])
def test_check_engine_refusals(one_gpu, engine, device, precision, name):
    """On a machine with one GPU; malformed device strings torch.device raises RuntimeError for."""
    check_engine("torch", "cuda:0", "fp32")
    check_engine("torch", "cuda", "bf16")
    with pytest.raises(ValueError, match=rf"\b{name}\b"):
        check_engine(engine, device, precision)


def _opts(steps, **kw):
    return RunOptions(**{"steps": steps, "batch_size": 2, "progress": False, "engine": "torch", **kw})


def _folder(path):
    """Every file under path with its bytes."""
    return {os.path.relpath(os.path.join(d, f), path): open(os.path.join(d, f), "rb").read()
            for d, _, files in os.walk(path) for f in files}


def _float64_data():
    tokens, poses = _data()
    poses = poses.astype(np.float64)
    poses[..., 3:] /= np.linalg.norm(poses[..., 3:], axis=-1, keepdims=True)  # unit in float64
    return tokens, poses


@pytest.mark.parametrize("call, world, name", [
    # autocast casts float32 tensors only: a float64 model under bf16 ran in float64, recorded as bf16
    (lambda out: train_transformer(*_float64_data(), dataclasses.replace(CFG, dtype="float64"), out,
                                   _opts(3, precision="bf16")), 1, "precision"),
    (lambda out: train_codebook(_images(), CB64, out, _opts(4, precision="bf16", resume=False)), 1, "precision"),
    (lambda out: train_codebook(_images(), CB64, out, _opts(4, resume=False)), 2, "engine"),  # one process
    (lambda out: train_transformer(*_data(), CFG, out, _opts(2, batch_size=1)), 2, "batch_size"),  # < 2 processes
    (lambda out: data_parallel("cuda:1", 4), 2, "device"),  # one GPU named for two processes
])
def test_training_refusals_leave_the_run_folder_as_it_was(tmp_path, monkeypatch, call, world, name):
    """Refused before Run writes config.json or (resume=False) removes the folder's checkpoint: a
    mistaken command must not cost the run. The folder is byte for byte as it was."""
    train_codebook(_images(), CB64, tmp_path / "run", RunOptions(steps=2, batch_size=2, progress=False))
    before = _folder(tmp_path / "run")
    monkeypatch.setenv("WORLD_SIZE", str(world))
    with pytest.raises(ValueError, match=rf"\b{name}\b"):
        call(tmp_path / "run")
    assert _folder(tmp_path / "run") == before
