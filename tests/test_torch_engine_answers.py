"""Second audit of the torch engines' answers: the optimiser state a torch run checkpoints against
pyvf's run, and what parity.csv's check stops (a divergent forward in a whole run) and does not
(a wrong update: the check is a forward comparison from the torch model's own weights)."""

import functools

import numpy as np
import pytest

from pyvf.train import torch_engine
from pyvf.train._run import read_checkpoint
from pyvf.verify import torch_ports

from test_torch_engine import _train


def test_checkpointed_moments_and_step_equal_pyvf(tmp_path):
    """The existing same-run tests compare weights and losses only; a resume continues from the
    checkpoint's moments and step count, so those must be pyvf's too. 8 steps with global clipping:
    each moment tensor normwise within 1e-4 of pyvf's (measured <= 1.4e-6: float32 rounding in
    another order, ~1e-6 per step as the weights'), the step count and hyperparameters equal."""
    for engine in ("pyvf", "torch"):
        _train(tmp_path, engine, engine, steps=8, max_grad_norm=0.1, clip_mode="global")
    meta_a, _, opt_a = read_checkpoint(tmp_path / "pyvf" / "checkpoint.npz", "transformer")
    meta_b, _, opt_b = read_checkpoint(tmp_path / "torch" / "checkpoint.npz", "transformer")
    assert meta_a["optimizer"] == meta_b["optimizer"] and opt_a["step"] == opt_b["step"] == 8
    for key in ("exp_avg", "exp_avg_sq"):
        assert set(opt_a[key]) == set(opt_b[key])
        for k, a in opt_a[key].items():
            b = opt_b[key][k]
            assert b.dtype == a.dtype == np.float32 and b.shape == a.shape, (key, k)
            err = np.linalg.norm(a - b) / np.linalg.norm(a)
            assert err < 1e-4, (key, k, err)


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
