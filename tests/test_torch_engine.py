"""train_transformer's torch engine against pyvf's: the same run in both, resume across engines,
the parity check at checkpoints, the options' errors; two data-parallel processes against one;
train_codebook's torch engine against pyvf's."""

import csv
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
from pyvf.train.loops import TINY_TRANSFORMER, save_tokens, train_codebook, train_transformer
from pyvf.train.torch_codebook_engine import TorchCodebook, parity_images
from pyvf.train.torch_engine import (PARITY_RTOL, DataParallel, TorchTransformer, check_engine, data_parallel,
                                     log_parity, parity_batch)
from pyvf.train.optim import Adam, AdamW, published_weight_decay
from pyvf.models.transformer import Transformer
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


def _train(tmp_path, name, engine, steps=20, **kw):
    tokens, poses = _data()
    return train_transformer(tokens, poses, CFG, tmp_path / name, steps=steps, batch_size=4, lr=1e-3, warmup=2,
                             progress=False, engine=engine, **kw)


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


@pytest.mark.parametrize("clip", [dict(), dict(max_grad_norm=0.02), dict(max_grad_norm=0.1, clip_mode="global")])
def test_torch_engine_equals_pyvf_after_20_steps(tmp_path, clip):
    """clip: the default per-tensor norm 1 (no tensor reaches it: at step 1 their norms are
    0.002 to 0.66), 0.02 (clips most of them) and a global norm of 0.1 (step 1's is 1.35)."""
    a = _train(tmp_path, "pyvf", "pyvf", **clip).state_dict()
    b = _train(tmp_path, "torch", "torch", **clip).state_dict()
    _check_same_run(a, b, Transformer(CFG, seed=0).state_dict())
    # and the logs: the same losses to float32 rounding, the same learning rates exactly
    logs = [list(csv.DictReader(open(tmp_path / n / "log.csv"))) for n in ("pyvf", "torch")]
    for ra, rb in zip(*logs):
        assert ra["lr"] == rb["lr"]
        assert abs(float(ra["loss"]) - float(rb["loss"])) < 1e-5 * abs(float(ra["loss"]))


def test_a_wrong_optimizer_is_caught(tmp_path):
    """The comparison above would catch an engine that skips the decay (a real difference, not rounding)."""
    a = _train(tmp_path, "pyvf", "pyvf").state_dict()
    tokens, poses = _data()
    b = train_transformer(tokens, poses, CFG, tmp_path / "wd0", steps=20, batch_size=4, lr=1e-3, warmup=2,
                          progress=False, engine="torch", weight_decay=0.0).state_dict()
    with pytest.raises(AssertionError):
        _check_same_run(a, b, Transformer(CFG, seed=0).state_dict())


def test_resume_exact_and_across_engines(tmp_path):
    straight = _train(tmp_path, "straight", "torch").state_dict()
    _train(tmp_path, "split", "torch", steps=10, total_steps=20)
    resumed = _train(tmp_path, "split", "torch", steps=20).state_dict()
    for k in straight:  # the same engine on the same machine: bit for bit
        np.testing.assert_array_equal(straight[k], resumed[k], err_msg=k)
    # pyvf's checkpoint continued by torch: the pyvf run to float32 rounding
    _train(tmp_path, "cross", "pyvf", steps=10, total_steps=20)
    cross = _train(tmp_path, "cross", "torch", steps=20).state_dict()
    _check_same_run(_train(tmp_path, "pyvf", "pyvf").state_dict(), cross, Transformer(CFG, seed=0).state_dict())


def test_parity_logged_at_checkpoints(tmp_path):
    _train(tmp_path, "p", "torch", checkpoint_every=10)
    rows = list(csv.DictReader(open(tmp_path / "p" / "parity.csv")))
    assert [r["step"] for r in rows] == ["10", "20"]
    assert all(0 < float(r["rel_err"]) < 1e-5 for r in rows), rows  # measured ~4e-7
    assert all(float(r["bound"]) == PARITY_RTOL for r in rows)


@pytest.mark.parametrize("bug", ["qkv_order", "wrong_branch", "ln_eps"])
def test_parity_catches_a_planted_bug(tmp_path, bug):
    model = Transformer(CFG, seed=3)
    eng = TorchTransformer(model, AdamW(model.params, 1e-3, decay=published_weight_decay))
    bad = TransformerPort(CFG, bug=bug)
    bad.load_state_dict(eng.port.state_dict())
    eng.port = bad  # the same weights (pyvf reads them from the engine's own): only the math differs
    tokens, poses = _data()
    comparison = eng.parity(*parity_batch(tokens, poses, 4, 0, "float32"))
    assert not comparison.ok
    with pytest.raises(RuntimeError, match=r"parity check at step 7: the torch model and pyvf differ first in"):
        log_parity(tmp_path, 7, comparison)
    assert (tmp_path / "parity.csv").exists()


def test_engine_options_are_checked():
    with pytest.raises(ValueError, match="engine must be 'pyvf' or 'torch'"):
        check_engine("jax", "cpu", "fp32")
    with pytest.raises(ValueError, match="need engine='torch'"):
        check_engine("pyvf", "cuda", "fp32")
    with pytest.raises(ValueError, match="precision must be"):
        check_engine("torch", "cpu", "fp16")
    with pytest.raises(ValueError, match="device must be"):
        check_engine("torch", "gpu", "fp32")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="torch sees no CUDA device"):
            check_engine("torch", "cuda", "fp32")


def test_bf16_trains_and_stays_near_fp32(tmp_path):
    """bf16 autocast on the CPU: the loss falls as in fp32, the weights stay float32."""
    a = _train(tmp_path, "fp32", "torch", steps=30)
    b = _train(tmp_path, "bf16", "torch", steps=30, precision="bf16")
    la = [float(r["loss"]) for r in csv.DictReader(open(tmp_path / "fp32" / "log.csv"))]
    lb = [float(r["loss"]) for r in csv.DictReader(open(tmp_path / "bf16" / "log.csv"))]
    assert lb[-1] < lb[0] and abs(lb[-1] - la[-1]) < 0.05 * la[-1], (la, lb)  # bf16's u = 3.9e-3
    assert all(p.dtype == np.float32 for p in b.params.values())
    assert any(not np.array_equal(a.params[k], b.params[k]) for k in a.params)  # autocast did change the math


# ---------------------------------------------------------------------------------------
# data-parallel: two gloo processes (torchrun) against one


def _torchrun(tmp_path, out, *args):
    """`torchrun --nproc-per-node 2 pyvf train-transformer --engine torch` on _data() (the tokens file and
    CFG written once), as a user runs it; returns the run folder."""
    files = tmp_path / "tokens.npz", tmp_path / "config.json"
    if not files[0].exists():
        save_tokens(files[0], *_data(), CFG.n_embeddings)
        files[1].write_text(json.dumps(dataclasses.asdict(CFG)))
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2", "-m", "pyvf",
           "train-transformer", "--engine", "torch", "--tokens", str(files[0]), "--config", str(files[1]),
           "--out", str(tmp_path / out), "--lr", "1e-3", "--warmup", "2", "--eval-every", "0", "--no-progress",
           "--log-every", "1", *args]
    # from tmp_path, as every command test: the installed pyvf, never a checkout on sys.path
    done = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    return tmp_path / out


def test_two_processes_equal_one_and_resume(tmp_path):
    """Batch 5 on 2 gloo processes (shards of 3 and 2 rows), 3 steps, then resumed by both to 6,
    against one process running the whole batch 6 steps. The bound is _check_same_run's, 1e-4 of
    how far training moved each tensor: the processes sum their weighted shard gradients in
    another order than one process sums the batch (float32 rounding, ~1e-7 per step, amplified
    where Adam divides a small gradient by its sqrt(v)); measured 9e-6 (ln_f/gamma), 5e-7 elsewhere."""
    _torchrun(tmp_path, "two", "--steps", "3", "--total-steps", "6", "--batch", "5", "--checkpoint-every", "3")
    two = _torchrun(tmp_path, "two", "--steps", "6", "--batch", "5", "--checkpoint-every", "3")
    tokens, poses = _data()
    one = train_transformer(tokens, poses, CFG, tmp_path / "one", steps=6, batch_size=5, lr=1e-3, warmup=2,
                            log_every=1, progress=False, engine="torch").state_dict()
    _check_same_run(one, Transformer.load(two / "transformer.npz").state_dict(), Transformer(CFG, seed=0).state_dict())
    # rank 0 alone wrote the folder: one row per step, the parity checks at both checkpoints
    logs = [list(csv.DictReader(open(d / "log.csv"))) for d in (tmp_path / "one", two)]
    assert [r["step"] for r in logs[1]] == [str(t) for t in range(1, 7)]
    for ra, rb in zip(*logs):
        assert ra["lr"] == rb["lr"] and abs(float(ra["loss"]) - float(rb["loss"])) < 1e-5 * float(ra["loss"])
    assert [r["step"] for r in csv.DictReader(open(two / "parity.csv"))] == ["3", "6"]
    calls = json.loads((two / "config.json").read_text())["calls"]
    assert [c["processes"] for c in calls] == [2, 2] and calls[1]["resumed_from_step"] == 3


class _World:
    """torch.distributed's rank and world size, for DataParallel.shard."""

    def __init__(self, rank, world):
        self.get_rank, self.get_world_size = (lambda: rank), (lambda: world)


@pytest.mark.parametrize("batch,world,sizes", [(4, 2, [2, 2]), (5, 2, [3, 2]), (7, 3, [3, 2, 2]), (3, 3, [1, 1, 1])])
def test_shards_cover_the_batch_once(batch, world, sizes):
    shards = [DataParallel(_World(r, world), "cpu", False).shard(batch) for r in range(world)]
    assert [hi - lo for lo, hi in shards] == sizes
    assert [lo for lo, _ in shards] == [0, *np.cumsum(sizes)[:-1]] and shards[-1][1] == batch


def test_data_parallel_refusals(tmp_path, monkeypatch):
    """Under torchrun (WORLD_SIZE 2): a batch smaller than the world, and one GPU named for two processes."""
    monkeypatch.setenv("WORLD_SIZE", "2")
    with pytest.raises(ValueError, match=r"batch_size=1 \(--batch\) is smaller than the 2 processes"):
        train_transformer(*_data(), CFG, tmp_path / "b1", steps=2, batch_size=1, progress=False, engine="torch")
    with pytest.raises(ValueError, match=r"device='cuda:1' names one GPU for 2 processes"):
        data_parallel("cuda:1", 4)
    assert not os.path.exists(tmp_path / "b1")  # refused before the run folder is made


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


def _train_cb(tmp_path, name, engine, cfg=CB64, steps=20, **kw):
    """The default recipe (small-batch: Adam (0.9, 0.99), objects weighted 4) with a dead-code restart
    every 10 steps."""
    return train_codebook(_images(), cfg, tmp_path / name, steps=steps, batch_size=4, reset_dead_codes=10,
                          progress=False, engine=engine, **kw)


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


def test_torch_codebook_equals_pyvf_after_20_steps(tmp_path):
    """In float64, 20 steps with object weighting and two dead-code restarts: every weight and EMA
    buffer within 1e-9 of its movement (measured 1.3e-12: float64's u = 1.1e-16 amplified by 20 steps
    of training, ~1e4). In float32 the same amplification of u = 6e-8, and the nearest-code choices
    it flips (near-ties, from step 11 on this data), leave 2% after 20 steps: the float32 check
    below stops at 6 steps, before any flip."""
    a = _train_cb(tmp_path, "pyvf", "pyvf").state_dict()
    b = _train_cb(tmp_path, "torch", "torch").state_dict()
    _check_same_codebook(a, b, Codebook(CB64, seed=0).state_dict(), 1e-9)
    logs = [list(csv.DictReader(open(tmp_path / n / "log.csv"))) for n in ("pyvf", "torch")]
    for ra, rb in zip(*logs):
        assert ra["lr"] == rb["lr"] and ra["usage"] == rb["usage"], (ra, rb)
        assert abs(float(ra["loss"]) - float(rb["loss"])) < 1e-12 * float(ra["loss"])
    with pytest.raises(AssertionError):  # the comparison sees an engine that skips the object weighting
        c = _train_cb(tmp_path, "w1", "torch", object_weight=1.0).state_dict()
        _check_same_codebook(a, c, Codebook(CB64, seed=0).state_dict(), 1e-9)


def test_torch_codebook_float32(tmp_path):
    """6 float32 steps: within 1e-2 of the movement (measured 1.5e-3 at step 6, 4e-3 at step 1, in
    encoder.mid.block_2.conv1.weight). Adam's first steps are about lr * sign(g) for every entry
    above its eps: an entry whose gradient is within float32 rounding of 0 (the encoder's, reached
    through the commitment term only, are ~1e-8) may step the other way in the other engine."""
    a = _train_cb(tmp_path, "pyvf", "pyvf", CB, steps=6).state_dict()
    b = _train_cb(tmp_path, "torch", "torch", CB, steps=6).state_dict()
    _check_same_codebook(a, b, Codebook(CB, seed=0).state_dict(), 1e-2)


def test_torch_codebook_resume_and_parity_log(tmp_path):
    straight = _train_cb(tmp_path, "straight", "torch", CB, steps=12, checkpoint_every=6).state_dict()
    _train_cb(tmp_path, "split", "torch", CB, steps=6)
    resumed = _train_cb(tmp_path, "split", "torch", CB, steps=12)
    for k in straight:  # the same engine on the same machine: bit for bit
        np.testing.assert_array_equal(straight[k], resumed.state_dict()[k], err_msg=k)
    assert Codebook.load(tmp_path / "split" / "codebook.npz").state_dict()["quantize.counter"] == 12
    rows = list(csv.DictReader(open(tmp_path / "straight" / "parity.csv")))
    assert [r["step"] for r in rows] == ["6", "12"]
    assert all(0 < float(r["rel_err"]) < 1e-5 and float(r["bound"]) == PARITY_RTOL for r in rows), rows
    # pyvf's checkpoint continued by torch, in float64: the pyvf run to 1e-9 of the movement
    _train_cb(tmp_path, "cross", "pyvf", steps=10)
    cross = _train_cb(tmp_path, "cross", "torch", steps=20).state_dict()
    _check_same_codebook(_train_cb(tmp_path, "pyvf", "pyvf").state_dict(), cross, Codebook(CB64, seed=0).state_dict(),
                         1e-9)


def _transpose_mid_conv(port):
    """A conv that reads its (out, in) kernel as (in, out): a square kernel runs either way."""
    conv = port.encoder.mid.block_1.conv1
    conv.forward = lambda x: torch.nn.functional.conv2d(x, conv.weight.transpose(0, 1), conv.bias, padding=1)


def _group_norm_eps(port):
    """eps 1e-2 (published 1e-6) in the last GroupNorm: measured 1.4e-2 in the reconstruction (1e-3 gives
    1.4e-3, at the bound: an eps error shows from about 1e-3 on)."""
    port.decoder.norm_out.eps = 1e-2


@pytest.mark.parametrize("bug", ["padding", _transpose_mid_conv, _group_norm_eps])
def test_codebook_parity_catches_a_planted_bug(tmp_path, bug):
    model = Codebook(CB, seed=3)
    eng = TorchCodebook(model, Adam(model.params, 1e-3))
    bad = CodebookPort(CB, bug=bug if isinstance(bug, str) else None)
    bad.load_state_dict(eng.port.state_dict())
    if callable(bug):
        bug(bad)
    eng.port = bad  # the same weights (pyvf reads them from the engine's own): only the math differs
    comparison = eng.parity(parity_images(_images().reshape(-1, 16, 16, 3), 0, "float32"))
    assert not comparison.ok, comparison
    with pytest.raises(RuntimeError, match=r"parity check at step 7: the torch model and pyvf differ first in"):
        log_parity(tmp_path, 7, comparison)


def test_codebook_engine_refuses_several_processes(tmp_path, monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    with pytest.raises(ValueError, match="the codebook's torch engine runs in one process"):
        _train_cb(tmp_path, "w2", "torch", CB, steps=1)


def test_pyvf_train_with_the_torch_engine(tmp_path):
    """`pyvf train --preset smoke --engine torch`: both stages train in torch, each checked by pyvf."""
    assert main(["train", "--out", str(tmp_path / "run"), "--preset", "smoke", "--engine", "torch",
                 "--no-progress"]) == 0
    for stage in ("codebook", "transformer"):
        calls = json.loads((tmp_path / "run" / stage / "config.json").read_text())["calls"]
        assert calls[-1]["engine"] == "torch"
        assert [r["step"] for r in csv.DictReader(open(tmp_path / "run" / stage / "parity.csv"))][-1] == "2"
