"""The torch engines' refusals and records that tests/test_torch_engine.py does not cover: a GPU that is not
there or a malformed one named before anything runs, bf16 autocast asked of a float64 configuration (and the
codebook's engine under torchrun) refused before the run folder is touched, and parity.csv holding the rows of
the run it continues only."""

import csv
import dataclasses
import os

import numpy as np
import pytest
import torch

from pyvf.train.loops import train_codebook, train_transformer
from pyvf.train.torch_engine import check_engine

from test_torch_engine import CB, CFG, _data, _images, _train


@pytest.fixture
def one_gpu(monkeypatch):
    """torch as on a machine with one CUDA device (cuda:0): what check_engine asks torch."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)


def test_a_gpu_that_is_not_there_is_named(one_gpu, tmp_path):
    """cuda:1 on a machine with one GPU: torch.device accepts it and the first .to() fails with "CUDA error:
    invalid device ordinal", after the run folder was made; refused first, naming the device."""
    check_engine("torch", "cuda:0", "fp32")
    check_engine("torch", "cuda", "bf16")
    with pytest.raises(ValueError, match=r"device='cuda:1', but torch sees 1 CUDA device \(cuda:0\)"):
        check_engine("torch", "cuda:1", "fp32")
    with pytest.raises(ValueError, match=r"device='cuda:1', but torch sees 1 CUDA device"):
        train_transformer(*_data(), CFG, tmp_path / "t", steps=3, batch_size=4, progress=False, engine="torch",
                          device="cuda:1")
    assert not (tmp_path / "t").exists()  # refused before the run folder is made


@pytest.mark.parametrize("device", ["cuda:", "cuda:x", "cuda:-1", "cuda:00", "cuda:1 ", "cuda:0,1"])
@pytest.mark.parametrize("engine", ["pyvf", "torch"])
def test_a_malformed_gpu_is_refused_as_such(one_gpu, device, engine):
    """torch.device raises RuntimeError ("Invalid device string") for each, after the run folder was made;
    without CUDA the old check said "torch sees no CUDA device", as if the string were right."""
    with pytest.raises(ValueError, match=r"device must be 'cpu', 'cuda' or 'cuda:N'"):
        check_engine(engine, device, "fp32")
    with pytest.raises(RuntimeError):  # what torch does with it
        torch.device(device)


def test_bf16_of_a_float64_configuration_is_refused(tmp_path):
    """Autocast casts float32 tensors only: a float64 model under precision='bf16' ran in float64 (no bf16
    anywhere) with its logits rounded to float32, recorded as a bf16 run. The transformer and the codebook
    refuse it, naming the precision and the dtype; fp32 trains in float64 as asked."""
    cfg64 = dataclasses.replace(CFG, dtype="float64")
    tokens, poses = _data()
    poses = poses.astype(np.float64)
    poses[..., 3:] /= np.linalg.norm(poses[..., 3:], axis=-1, keepdims=True)  # unit in float64
    with pytest.raises(ValueError, match=r"precision='bf16' .* dtype is float64"):
        train_transformer(tokens, poses, cfg64, tmp_path / "t", steps=3, batch_size=4, progress=False,
                          engine="torch", precision="bf16")
    with pytest.raises(ValueError, match=r"precision='bf16' .* dtype is float64"):
        train_codebook(_images(), dataclasses.replace(CB, dtype="float64"), tmp_path / "c", steps=1, batch_size=2,
                       progress=False, engine="torch", precision="bf16")
    m = train_transformer(tokens, poses, cfg64, tmp_path / "t64", steps=3, batch_size=4, progress=False,
                          engine="torch")
    assert all(p.dtype == np.float64 for p in m.params.values())


def _parity_steps(run):
    return [r["step"] for r in csv.DictReader(open(run / "parity.csv"))]


def test_parity_log_holds_the_run_it_continues(tmp_path):
    """As log.csv: a fresh start in the folder drops an older run's rows (they were appended to), a resume
    keeps the rows up to its checkpoint."""
    _train(tmp_path, "p", "torch", steps=6, checkpoint_every=2)
    assert _parity_steps(tmp_path / "p") == ["2", "4", "6"]
    _train(tmp_path, "p", "torch", steps=6, checkpoint_every=3, resume=False)  # start over
    assert _parity_steps(tmp_path / "p") == ["3", "6"]
    assert [r["step"] for r in csv.DictReader(open(tmp_path / "p" / "log.csv"))][-1] == "6"
    # a resume from step 3 (a run stopped there): the rows to 3 kept, 5 and 6 appended
    _train(tmp_path, "r", "torch", steps=3, total_steps=6, checkpoint_every=3)
    _train(tmp_path, "r", "torch", steps=6, checkpoint_every=5)
    assert _parity_steps(tmp_path / "r") == ["3", "5", "6"]


def _folder(path):
    """Every file under path with its bytes."""
    return {os.path.relpath(os.path.join(d, f), path): open(os.path.join(d, f), "rb").read()
            for d, _, files in os.walk(path) for f in files}


def test_refusals_leave_the_run_folder_as_it_was(tmp_path, monkeypatch):
    """bf16 of a float64 configuration, and the codebook's torch engine under torchrun (WORLD_SIZE 2), were
    refused after Run had written config.json and, with resume=False, removed the folder's checkpoint: a
    mistaken command cost the run. Now both are refused first; the folder is byte for byte as it was."""
    cb64 = dataclasses.replace(CB, dtype="float64")
    train_codebook(_images(), cb64, tmp_path / "c", steps=2, batch_size=2, progress=False)
    before = _folder(tmp_path / "c")
    assert "checkpoint.npz" in before
    with pytest.raises(ValueError, match=r"precision='bf16' .* dtype is float64"):
        train_codebook(_images(), cb64, tmp_path / "c", steps=4, batch_size=2, progress=False, engine="torch",
                       precision="bf16", resume=False)
    assert _folder(tmp_path / "c") == before
    monkeypatch.setenv("WORLD_SIZE", "2")
    with pytest.raises(ValueError, match=r"runs in one process, got 2"):
        train_codebook(_images(), cb64, tmp_path / "c", steps=4, batch_size=2, progress=False, engine="torch",
                       resume=False)
    assert _folder(tmp_path / "c") == before


def test_grad_norm_is_logged_without_clipping_by_both_engines(tmp_path):
    """max_grad_norm=None: the torch engine logged the global gradient norm, pyvf's engine nan, though
    train_transformer says the logged grad_norm is the global norm. Both now log it; from the same start
    the first steps' norms agree to the float32 parity bound (the torch engine is the oracle)."""
    for engine in ("pyvf", "torch"):
        _train(tmp_path, engine, engine, steps=3, max_grad_norm=None, log_every=1)
    logs = {e: [float(r["grad_norm"]) for r in csv.DictReader(open(tmp_path / e / "log.csv"))]
            for e in ("pyvf", "torch")}
    assert len(logs["pyvf"]) == 3 and all(np.isfinite(logs["pyvf"]))
    np.testing.assert_allclose(logs["pyvf"], logs["torch"], rtol=1e-3)
