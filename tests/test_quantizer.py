"""The EMA quantizer against an independent torch implementation of docs/math.md §4 (three training
steps: codes, outputs, losses, every buffer), its gradients, and the hard cases: unused codes,
every vector on one code, state round trip, bad input."""

import numpy as np
import torch

from conftest import assert_close
from pyvf.models.codebook import Codebook, CodebookConfig
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


def torch_buffers(D, K):
    """The EMA state of a fresh quantizer for torch_ema_step: cluster sizes, dw, counter."""
    return torch.zeros(K, dtype=torch.float64), torch.zeros(D, K, dtype=torch.float64), 0


def test_three_training_steps_match_torch(rng):
    D, K = 8, 16
    q = EMAQuantizer(D, K, dtype="float64", seed=3)
    emb = torch.tensor(q.embeddings)
    hcs, hdw, counter = torch_buffers(D, K)
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
    # reset is off by default (the unused codes collapsed above); asked for, it counts those below threshold
    assert q2.reset_dead_codes(z, threshold=1e-3, rng=0) == K - 1


def test_usage_and_perplexity_closed_form():
    q = EMAQuantizer(2, 4, dtype="float64")
    q.embeddings = np.array([[0.0, 10.0, 20.0, 30.0], [0.0, 0.0, 0.0, 0.0]])
    z = np.array([0.0, 0.1, 10.0, 9.9]).reshape(1, 1, 2, 2)  # two vectors on code 0, two on code 1
    z = np.concatenate([z, np.zeros_like(z)], axis=1)  # (1, 2, 2, 2)
    out, _ = q.forward(z)
    np.testing.assert_array_equal(out.codes.ravel(), [0, 0, 1, 1])
    assert out.usage == 0.5 and abs(out.perplexity - 2.0) < 1e-12


def test_state_round_trip(rng):
    q = EMAQuantizer(4, 8, dtype="float32")
    q.forward(rng.standard_normal((1, 4, 2, 2)).astype(np.float32), train=True)
    q2 = EMAQuantizer(4, 8, dtype="float32", seed=9)
    q2.load_state_dict(q.state_dict())
    z = rng.standard_normal((1, 4, 2, 2)).astype(np.float32)
    np.testing.assert_array_equal(q2.forward(z)[0].codes, q.forward(z)[0].codes)


# ---------------------------------------------------------------------------------------
# hard cases, each against an independent oracle (the torch EMA step, closed forms, set logic)


def test_reset_dead_codes_moves_each_code_to_a_different_vector(rng):
    """8 dead codes, 16 distinct vectors: the draw was with replacement, so two codes often landed
    on one vector; the larger index of such a pair is never chosen (ties go to the smallest) and
    stays dead. Each restarted code must be a different vector of z."""
    z = rng.standard_normal((1, 2, 4, 4))
    vectors = {tuple(v) for v in z.transpose(0, 2, 3, 1).reshape(-1, 2)}
    for seed in range(10):
        q = EMAQuantizer(2, 8, dtype="float64")  # counter 0: every code is dead
        assert q.reset_dead_codes(z, rng=seed) == 8
        cols = [tuple(c) for c in q.embeddings.T]
        assert set(cols) <= vectors
        assert len(set(cols)) == 8, f"seed {seed}: {8 - len(set(cols))} codes share a vector"
    # fewer vectors than dead codes: every vector is used, every code is one of them
    z3 = rng.standard_normal((1, 2, 1, 3))
    three = {tuple(v) for v in z3.transpose(0, 2, 3, 1).reshape(-1, 2)}
    for seed in range(10):
        q = EMAQuantizer(2, 8, dtype="float64")
        assert q.reset_dead_codes(z3, rng=seed) == 8
        assert {tuple(c) for c in q.embeddings.T} == three


def test_tiny_eps_in_float64_matches_the_torch_step(rng):
    """eps=1e-50 is a normal float64: accepted, and the step is the formula's (unused codes 0)."""
    D, K = 3, 5
    q = EMAQuantizer(D, K, eps=1e-50, dtype="float64", seed=2)
    emb = torch.tensor(q.embeddings)
    z = rng.standard_normal((2, D, 2, 2))
    out, _ = q.forward(z, train=True)
    _, idx, _, emb, *_ = torch_ema_step(torch.tensor(z), emb, *torch_buffers(D, K), 0.99, 1e-50)
    np.testing.assert_array_equal(out.codes, idx.numpy())
    np.testing.assert_allclose(q.embeddings, emb.numpy(), rtol=1e-13, atol=0)


def test_commitment_loss_with_a_float32_sum_past_float32_max():
    """Every (e - z)^2 = (1.5e19)^2 = 2.25e38 < float32 max: the mean is representable, but its
    float32 sum over 16 elements is not: the loss is summed in float64."""
    q = EMAQuantizer(1, 1, dtype="float32")
    q.embeddings[:] = 0
    z = np.full((1, 1, 4, 4), 1.5e19, np.float32)
    out, _ = q.forward(z)
    want = float(np.float32(1.5e19)) ** 2
    assert abs(out.commitment_loss - want) <= 1e-7 * want


def test_batch_of_one_vector_and_a_code_unused_for_many_steps(rng):
    """One vector per step, float32, 200 steps, the data always on code 0 of 3: against the float64
    torch step (codes, every buffer). The unused codes collapse to 0 (their dw does), away from
    the data around (10, 10), and stay finite."""
    D, K = 2, 3
    q = EMAQuantizer(D, K, dtype="float32", seed=0)
    q.embeddings[:] = np.array([[10.0, 50.0, -50.0], [10.0, 50.0, 50.0]], np.float32)
    emb, (hcs, hdw, counter) = torch.tensor(q.embeddings, dtype=torch.float64), torch_buffers(D, K)
    for step in range(200):
        z = (10 + rng.standard_normal((1, D, 1, 1)) * 0.5).astype(np.float32)
        out, _ = q.forward(z, train=True)
        _, idx, _, emb, hcs, hdw, counter = torch_ema_step(torch.tensor(z, dtype=torch.float64), emb, hcs, hdw,
                                                           counter, 0.99, 1e-5)
        assert out.codes.shape == (1, 1, 1) and out.codes[0, 0, 0] == idx[0, 0, 0] == 0
        assert out.usage == 1 / K and out.perplexity == 1.0
    emb, hcs, hdw = emb.numpy(), hcs.numpy(), hdw.numpy()
    np.testing.assert_allclose(q.embeddings, emb, rtol=0, atol=1e-5 * np.abs(emb).max())
    np.testing.assert_allclose(q.ema_cluster_size_hidden, hcs, rtol=1e-5, atol=0)
    np.testing.assert_allclose(q.ema_dw_hidden, hdw, rtol=0, atol=1e-5 * np.abs(hdw).max())
    assert (q.embeddings[:, 1:] == 0).all() and q.counter == 200


def test_a_float_counter_of_an_integral_value_loads_and_steps():
    """A torch checkpoint may hold the counter as a float: 1e18 loads (decay ** counter = 0: no
    debias), and a float64 buffer holding float32's largest value loads exactly."""
    cb = Codebook(CodebookConfig(ch=32, ch_mult=(1, 2), num_res_blocks=1, attn_resolutions=(8,), z_channels=32,
                                 embed_dim=4, n_embed=8, image_size=16))
    state = cb.state_dict()
    state["quantize.counter"] = np.array(1e18)
    state["quantize.ema_dw_hidden"] = state["quantize.ema_dw_hidden"].astype(np.float64)
    state["quantize.ema_dw_hidden"][3, 5] = float(np.finfo(np.float32).max)
    cb.load_official(state)
    q = cb.quantizer
    assert q.ema_dw_hidden.dtype == np.float32 and q.ema_dw_hidden[3, 5] == np.finfo(np.float32).max
    q.ema_dw_hidden[3, 5] = 0
    q.forward(np.random.default_rng(0).standard_normal((1, 4, 2, 2)).astype(np.float32), train=True)
    assert np.isfinite(q.embeddings).all() and q.state_dict()["counter"] == 10 ** 18 + 1
