"""The EMA quantizer against an independent torch implementation of docs/math.md §4 (three training
steps: codes, outputs, losses, every buffer), its gradients, and the hard cases: unused codes,
every vector on one code, state round trip, bad input."""

import numpy as np
import pytest
import torch

from conftest import assert_close
from pyvf.nn.quantizer import EMAQuantizer


def torch_ema_step(z, emb, hidden_cs, hidden_dw, counter, decay, eps):
    """One published-style step in torch float64: nearest column by exact distances, output from
    the old codes, then the EMA update. Returns quantized, codes, commitment, new buffers."""
    B, D, h, w = z.shape
    flat = z.permute(0, 2, 3, 1).reshape(-1, D)  # (M, D)
    d = ((flat[:, :, None] - emb[None]) ** 2).sum(1)  # (M, K) exact distances
    idx = d.argmin(1)
    e = emb.T[idx]  # old codes
    onehot = torch.nn.functional.one_hot(idx, emb.shape[1]).to(z.dtype)  # (M, K)
    hidden_cs = hidden_cs + (1 - decay) * (onehot.sum(0) - hidden_cs)
    hidden_dw = hidden_dw + (1 - decay) * (flat.detach().T @ onehot - hidden_dw)
    counter = counter + 1
    cs = hidden_cs / (1 - decay ** counter)
    dw = hidden_dw / (1 - decay ** counter)
    n = cs.sum()
    cs = (cs + eps) / (n + emb.shape[1] * eps) * n
    new_emb = dw / cs
    quantized = (flat + (e - flat).detach()).reshape(B, h, w, D).permute(0, 3, 1, 2)
    commitment = ((e.detach() - flat) ** 2).mean()
    return quantized, idx.reshape(B, h, w), commitment, new_emb, hidden_cs, hidden_dw, counter


def test_three_training_steps_match_torch(rng):
    D, K = 8, 16
    q = EMAQuantizer(D, K, dtype="float64", seed=3)
    emb = torch.tensor(q.embeddings)
    hcs, hdw, counter = torch.zeros(K, dtype=torch.float64), torch.zeros(D, K, dtype=torch.float64), 0
    for step in range(3):
        z = rng.standard_normal((2, D, 4, 4)) * 1.5
        out, cache = q.forward(z, train=True)
        tz = torch.tensor(z, requires_grad=True)
        tq, tcodes, tcom, emb, hcs, hdw, counter = torch_ema_step(tz, emb, hcs, hdw, counter, 0.99, 1e-5)
        np.testing.assert_array_equal(out.codes, tcodes.numpy())
        assert_close(f"quantized {step}", out.quantized, tq.detach().numpy(), rtol=1e-15)
        assert abs(out.commitment_loss - tcom.item()) <= 1e-14 * tcom.item()
        # buffers after the step: float64, a handful of roundings each
        assert_close(f"embeddings {step}", q.embeddings, emb.numpy(), rtol=1e-13)
        assert_close(f"cluster size {step}", q.ema_cluster_size_hidden, hcs.numpy(), rtol=1e-13)
        assert_close(f"dw {step}", q.ema_dw_hidden, hdw.numpy(), rtol=1e-13)
        assert q.counter == counter
        # gradients: random upstream for the output, weight 0.25 on the commitment loss
        dq = rng.standard_normal(z.shape)
        (dz,) = q.backward(dq, 0.25, cache)
        ((tq * torch.tensor(dq)).sum() + 0.25 * tcom).backward()
        assert_close(f"dz {step}", dz, tz.grad.numpy(), rtol=1e-14)


def test_eval_does_not_update(rng):
    q = EMAQuantizer(4, 8, dtype="float64")
    before = q.state_dict()
    q.forward(rng.standard_normal((1, 4, 2, 2)), train=False)
    for name, value in q.state_dict().items():
        np.testing.assert_array_equal(value, before[name])


def test_unused_codes_and_a_single_used_code_give_no_nan(rng):
    """Every vector on one code: the other codes' cluster sizes are 0; Laplace smoothing keeps
    cs' > 0, so the update is finite and the unused codes decay to 0 (their dw does)."""
    D, K = 4, 6
    q = EMAQuantizer(D, K, dtype="float64")
    q.embeddings[:] = 100.0
    q.embeddings[:, 2] = 0.0  # only code 2 is near the data
    z = rng.standard_normal((2, D, 3, 3)) * 0.1
    out, _ = q.forward(z, train=True)
    assert (out.codes == 2).all()
    assert out.usage == 1 / K and abs(out.perplexity - 1.0) < 1e-12
    unused = [k for k in range(K) if k != 2]
    assert (q.embeddings[:, unused] == 0).all()  # dw of an unused code is exactly 0 from the start
    # the published collapse: the zeroed codes are now nearer the data than code 2 may be;
    # whatever is chosen, nothing becomes NaN
    for _ in range(2):
        out, _ = q.forward(rng.standard_normal((2, D, 3, 3)) * 0.1, train=True)
        assert np.isfinite(q.embeddings).all() and np.isfinite(out.quantized).all()
    # the used code tracks the mean of its vectors: after one step with one batch it is that mean
    q2 = EMAQuantizer(D, K, dtype="float64")
    q2.embeddings[:] = 100.0
    q2.embeddings[:, 2] = 0.0
    z = rng.standard_normal((1, D, 2, 2))
    q2.forward(z, train=True)
    mean = z.transpose(0, 2, 3, 1).reshape(-1, D).mean(0)
    n = 4.0  # the smoothing factor at step 1: cs' = (4 + eps) / (4 + K eps) * 4
    cs = (n + 1e-5) / (n + K * 1e-5) * n
    np.testing.assert_allclose(q2.embeddings[:, 2], mean * n / cs, rtol=1e-14)


def test_usage_and_perplexity_closed_form():
    q = EMAQuantizer(2, 4, dtype="float64")
    q.embeddings = np.array([[0.0, 10.0, 20.0, 30.0], [0.0, 0.0, 0.0, 0.0]])
    z = np.array([0.0, 0.1, 10.0, 9.9]).reshape(1, 1, 2, 2)  # two vectors on code 0, two on code 1
    z = np.concatenate([z, np.zeros_like(z)], axis=1)  # (1, 2, 2, 2)
    out, _ = q.forward(z)
    np.testing.assert_array_equal(out.codes.ravel(), [0, 0, 1, 1])
    assert out.usage == 0.5 and abs(out.perplexity - 2.0) < 1e-12


def test_dead_code_reset_is_off_by_default_and_restarts_codes(rng):
    q = EMAQuantizer(4, 6, dtype="float64")
    q.embeddings[:] = 100.0
    q.embeddings[:, 0] = 0.0
    z = rng.standard_normal((1, 4, 3, 3))
    q.forward(z, train=True)
    assert (q.embeddings[:, 1:] == 0).all()  # dead codes collapse to 0 without a reset
    n = q.reset_dead_codes(z, threshold=1e-3, rng=0)
    assert n == 5
    flat = z.transpose(0, 2, 3, 1).reshape(-1, 4)
    for k in range(1, 6):  # each restarted code is one of the batch's vectors, and stays there
        assert any(np.array_equal(q.embeddings[:, k], v) for v in flat)
    q.forward(np.zeros((1, 4, 1, 1)) + 1e3, train=True)  # a batch far away: codes 1.. unused
    assert np.isfinite(q.embeddings).all()


def test_state_round_trip_and_bad_input(rng):
    q = EMAQuantizer(4, 8, dtype="float32")
    q.forward(rng.standard_normal((1, 4, 2, 2)).astype(np.float32), train=True)
    q2 = EMAQuantizer(4, 8, dtype="float32", seed=9)
    q2.load_state_dict(q.state_dict())
    z = rng.standard_normal((1, 4, 2, 2)).astype(np.float32)
    np.testing.assert_array_equal(q2.forward(z)[0].codes, q.forward(z)[0].codes)
    with pytest.raises(TypeError, match="z must be a float32"):
        q.forward(z.astype(np.float64))
    with pytest.raises(ValueError, match=r"z must have shape \(B, 4, h, w\)"):
        q.forward(z[:, :3].copy())
    with pytest.raises(ValueError, match="z contains NaN|x contains NaN"):
        q.forward(np.full_like(z, np.nan))
    with pytest.raises(ValueError, match="shape"):
        q2.load_state_dict({**q.state_dict(), "embeddings": np.zeros((8, 4))})
    with pytest.raises(ValueError, match="n_embed must be a positive integer"):
        EMAQuantizer(4, 0)


def _state_equal(a, b):
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def test_reset_dead_codes_checks_its_arguments_and_changes_nothing_on_error(rng):
    """z as forward takes it (the quantizer's dtype, (B, D, h, w), non-empty, finite) and a finite
    threshold >= 0, each wrong one named; nothing is written before the checks pass (an all-NaN z
    wrote NaN into the dead codes, a float64 z was cast silently into a float32 quantizer)."""
    q = EMAQuantizer(4, 8, dtype="float32")  # counter 0: every code is dead, every call would reset
    before = q.state_dict()
    z = rng.standard_normal((1, 4, 2, 2)).astype(np.float32)
    cases = [(np.full_like(z, np.nan), ValueError, "^z contains NaN or inf"),
             (z.astype(np.float64), TypeError, "^z must be a float32 numpy array, got float64"),
             (z[:, :3].copy(), ValueError, r"^z must have shape \(B, 4, h, w\), got \(1, 3, 2, 2\)"),
             (z[0], ValueError, r"^z must have shape \(B, 4, h, w\), got \(4, 2, 2\)"),
             (z.tolist(), TypeError, "^z must be a float32 numpy array, got list"),
             (z[:0], ValueError, r"^z is empty: shape \(0, 4, 2, 2\)")]
    for bad, exc, match in cases:
        with pytest.raises(exc, match=match):
            q.reset_dead_codes(bad, rng=0)
    for threshold, exc, match in [(float("nan"), ValueError, "^threshold must be finite"),
                                  (float("inf"), ValueError, "^threshold must be finite"),
                                  (-1.0, ValueError, r"^threshold must be finite and in \[0.0"),
                                  ("0.1", TypeError, "^threshold must be a real number, got str")]:
        with pytest.raises(exc, match=match):
            q.reset_dead_codes(z, threshold=threshold, rng=0)
    assert _state_equal(q.state_dict(), before)
    # the same quantizer with good arguments does reset: the checks above were the only reason it did not
    assert q.reset_dead_codes(z, rng=0) == 8 and not _state_equal(q.state_dict(), before)
    assert np.isfinite(q.embeddings).all()


def test_numpy_integer_sizes_are_ints():
    """embed_dim and n_embed: Python or NumPy integers (not bool), held as int."""
    q = EMAQuantizer(np.int64(4), np.int32(8))
    assert type(q.embed_dim) is int and type(q.n_embed) is int
    assert q.embeddings.shape == (4, 8) and q.state_dict().keys() == EMAQuantizer(4, 8).state_dict().keys()
    with pytest.raises(TypeError, match="^embed_dim must be an integer, got bool"):
        EMAQuantizer(True, 8)
    with pytest.raises(TypeError, match="^n_embed must be an integer, got float"):
        EMAQuantizer(4, 8.0)
    with pytest.raises(ValueError, match="^n_embed must be a positive integer, got 0"):
        EMAQuantizer(4, np.int64(0))


def test_load_state_dict_refuses_float64_values_beyond_float32(rng):
    """A float64 buffer into a float32 quantizer: a value past float32's largest would become inf.
    Refused, named, nothing loaded; the largest float32 value loads exactly."""
    q = EMAQuantizer(4, 8, dtype="float32")
    q.forward(rng.standard_normal((1, 4, 2, 2)).astype(np.float32), train=True)
    before = q.state_dict()
    state = {k: v.astype(np.float64) if k != "counter" else v for k, v in before.items()}
    state["ema_dw_hidden"][3, 5] = 1e39
    with pytest.raises(ValueError, match=r"'ema_dw_hidden' holds a value of magnitude 1e\+39, beyond float32's"):
        q.load_state_dict(state)
    assert _state_equal(q.state_dict(), before)
    state["ema_dw_hidden"][3, 5] = float(np.finfo(np.float32).max)
    q.load_state_dict(state)
    assert q.ema_dw_hidden[3, 5] == np.finfo(np.float32).max
