"""Hard cases of the EMA quantizer (docs/math.md §4) found by an audit, each against an
independent oracle (a plain NumPy EMA step written here, closed-form values, set logic): dead-code
restarts onto distinct vectors, an eps the dtype cannot hold, a commitment loss whose float32 sum
overflowed although its mean is representable, impossible states refused on load (negative
cluster sizes, a counter int64 cannot hold), arguments named (rng, train), and the codebook's EMA
rollback when the perceptual term fails."""

import numpy as np
import pytest

from pyvf.models.codebook import Codebook, CodebookConfig
from pyvf.nn.quantizer import EMAQuantizer

SMALL = dict(ch=32, ch_mult=(1, 2), num_res_blocks=1, attn_resolutions=(8,), z_channels=32, embed_dim=8,
             n_embed=16, image_size=16)


def _state_equal(a, b):
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def numpy_ema_step(flat, emb, hcs, hdw, counter, decay, eps):
    """docs/math.md §4 in float64 with a brute-force nearest column (ties: smallest index)."""
    d = ((flat[:, :, None] - emb[None]) ** 2).sum(1)  # (M, K)
    idx = d.argmin(1)
    K = emb.shape[1]
    N = np.bincount(idx, minlength=K).astype(np.float64)
    S = np.zeros_like(emb)
    for m, k in enumerate(idx):
        S[:, k] += flat[m]
    hcs = hcs + (1 - decay) * (N - hcs)
    hdw = hdw + (1 - decay) * (S - hdw)
    counter += 1
    cs, dw = hcs / (1 - decay ** counter), hdw / (1 - decay ** counter)
    n = cs.sum()
    cs = (cs + eps) / (n + K * eps) * n
    return idx, dw / cs, hcs, hdw, counter


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


def test_reset_dead_codes_names_a_bad_rng(rng):
    q = EMAQuantizer(4, 8, dtype="float64")
    before = q.state_dict()
    z = rng.standard_normal((1, 4, 2, 2))
    with pytest.raises(TypeError, match="^rng must be None, a non-negative integer seed or a numpy Generator"):
        q.reset_dead_codes(z, rng="abc")
    with pytest.raises(ValueError, match="^rng must be None, a non-negative integer seed or a numpy Generator"):
        q.reset_dead_codes(z, rng=-1)
    assert _state_equal(q.state_dict(), before)
    assert q.reset_dead_codes(z, rng=np.random.default_rng(0)) == 8  # a Generator is taken as it is


@pytest.mark.parametrize("eps", [1e-50, 1e39])
def test_eps_that_the_dtype_cannot_hold_is_refused(eps, rng):
    """float32: eps=1e-50 rounds to 0, so an unused code's smoothed size is 0 and its code 0/0;
    eps=1e39 is inf. Both were accepted and every training step then blamed z ("the EMA update
    overflows ... z is too large"). Refused at construction, naming eps."""
    with pytest.raises(ValueError, match=r"^eps must be in \[1.175e-38, .*for dtype float32 .*got "):
        EMAQuantizer(3, 5, eps=eps, dtype="float32")
    with pytest.raises(ValueError, match=r"^eps must be in"):
        Codebook(CodebookConfig(**SMALL, eps=eps))


def test_tiny_eps_in_float64_matches_the_numpy_step(rng):
    """eps=1e-50 is a normal float64: accepted, and the step is the formula's (unused codes 0)."""
    D, K = 3, 5
    q = EMAQuantizer(D, K, eps=1e-50, dtype="float64", seed=2)
    emb, hcs, hdw = q.embeddings.copy(), np.zeros(K), np.zeros((D, K))
    z = rng.standard_normal((2, D, 2, 2))
    out, _ = q.forward(z, train=True)
    idx, emb, hcs, hdw, _ = numpy_ema_step(z.transpose(0, 2, 3, 1).reshape(-1, D), emb, hcs, hdw, 0, 0.99, 1e-50)
    np.testing.assert_array_equal(out.codes.ravel(), idx)
    np.testing.assert_allclose(q.embeddings, emb, rtol=1e-13, atol=0)


def test_commitment_loss_with_a_float32_sum_past_float32_max():
    """Every (e - z)^2 = (1.5e19)^2 = 2.25e38 < float32 max: the mean is representable, but its
    float32 sum over 16 elements is not; forward raised "the commitment loss overflows"."""
    q = EMAQuantizer(1, 1, dtype="float32")
    q.embeddings[:] = 0
    z = np.full((1, 1, 4, 4), 1.5e19, np.float32)
    out, _ = q.forward(z)
    want = float(np.float32(1.5e19)) ** 2
    assert abs(out.commitment_loss - want) <= 1e-7 * want
    # past float32's range the loss itself overflows: still refused
    with pytest.raises(ValueError, match="the commitment loss overflows float32"):
        q.forward(np.full((1, 1, 1, 1), 2e19, np.float32))


def test_negative_cluster_sizes_are_refused_on_load(rng):
    """A state whose cluster size is negative (impossible for an EMA of counts) loaded silently
    and gave codes that are not the formula's (a smoothed size of ~0 or < 0 divides dw)."""
    q = EMAQuantizer(3, 4, dtype="float64")
    q.forward(rng.standard_normal((1, 3, 2, 2)), train=True)
    before = q.state_dict()
    state = q.state_dict()
    state["ema_cluster_size_hidden"][0] = -1.0
    with pytest.raises(ValueError, match="'ema_cluster_size_hidden' holds a negative cluster size -1"):
        q.load_state_dict(state)
    assert _state_equal(q.state_dict(), before)
    state["ema_cluster_size_hidden"][0] = -0.0  # a signed zero is a zero
    q.load_state_dict(state)
    cb = Codebook(CodebookConfig(**SMALL))
    sd = cb.state_dict()
    sd["quantize.ema_cluster_size_hidden"] = -np.ones(16, np.float32)
    with pytest.raises(ValueError, match="'quantize.ema_cluster_size_hidden' holds a negative cluster size"):
        cb.load_official(sd)


def test_counter_int64_cannot_hold_is_refused(rng):
    """A counter of 2^63 loaded, then state_dict() raised OverflowError (it stores int64)."""
    q = EMAQuantizer(2, 3, dtype="float64")
    state = q.state_dict()
    for big in (np.uint64(2 ** 63), 2 ** 63, np.array(2.0 ** 63)):
        state["counter"] = big
        with pytest.raises(ValueError, match="'counter' must be a non-negative integer"):
            q.load_state_dict(state)
        assert q.counter == 0
    state["counter"] = np.uint64(2 ** 63 - 1)
    q.load_state_dict(state)
    assert q.state_dict()["counter"] == 2 ** 63 - 1
    state["counter"] = np.array(1e18)  # a float counter of an integral value, as torch may store it
    q.load_state_dict(state)
    q.forward(rng.standard_normal((1, 2, 1, 1)), train=True)  # decay ** counter = 0: no debias
    assert np.isfinite(q.embeddings).all() and q.state_dict()["counter"] == 10 ** 18 + 1


def test_train_must_be_a_bool(rng):
    """A non-bool train was taken by truthiness: "False" trained, an array (pixel_weights passed by
    position to Codebook.forward) raised numpy's "truth value of an array is ambiguous"."""
    q = EMAQuantizer(4, 8, dtype="float64")
    before = q.state_dict()
    z = rng.standard_normal((1, 4, 2, 2))
    for bad in ("False", np.ones(3), 1):
        with pytest.raises(TypeError, match="^train must be True or False"):
            q.forward(z, train=bad)
    assert _state_equal(q.state_dict(), before)
    q.forward(z, train=np.bool_(True))
    assert q.counter == 1
    cb = Codebook(CodebookConfig(**SMALL), seed=0)
    images = np.tanh(rng.standard_normal((2, 3, 16, 16))).astype(np.float32)
    w = np.ones((2, 1, 16, 16), np.float32)
    for bad in (w, np.ones(1, np.float32), "no"):
        with pytest.raises(TypeError, match="^train must be True or False"):
            cb.forward(images, bad)
    assert cb.quantizer.counter == 0


class _FailingPerceptual:
    def forward(self, x, x_hat):
        raise RuntimeError("perceptual failed")

    def backward(self, dloss, cache):
        raise AssertionError("not reached")


def test_codebook_perceptual_failure_leaves_the_ema_buffers(rng):
    """The EMA update ran, then the perceptual term raised: the quantizer stayed updated (a retry
    of the step updated it twice), although a failed forward leaves the buffers as they were."""
    cb = Codebook(CodebookConfig(**SMALL, perceptual_weight=1.0), seed=0, perceptual=_FailingPerceptual())
    before = cb.quantizer.state_dict()
    images = np.tanh(rng.standard_normal((2, 3, 16, 16))).astype(np.float32)
    with pytest.raises(RuntimeError, match="perceptual failed"):
        cb.forward(images, train=True)
    assert _state_equal(cb.quantizer.state_dict(), before)


def test_batch_of_one_vector_and_a_code_unused_for_many_steps(rng):
    """One vector per step, float32, 400 steps, the data always on code 0 of 3: against the float64
    NumPy step (codes, every buffer). The unused codes collapse to 0 (their dw does), away from
    the data around (10, 10), and stay finite."""
    D, K = 2, 3
    q = EMAQuantizer(D, K, dtype="float32", seed=0)
    q.embeddings[:] = np.array([[10.0, 50.0, -50.0], [10.0, 50.0, 50.0]], np.float32)
    emb, hcs, hdw, counter = q.embeddings.astype(np.float64), np.zeros(K), np.zeros((D, K)), 0
    for step in range(400):
        z = (10 + rng.standard_normal((1, D, 1, 1)) * 0.5).astype(np.float32)
        out, _ = q.forward(z, train=True)
        idx, emb, hcs, hdw, counter = numpy_ema_step(z.reshape(1, D).astype(np.float64), emb, hcs, hdw, counter,
                                                     0.99, 1e-5)
        assert out.codes.shape == (1, 1, 1) and out.codes[0, 0, 0] == idx[0] == 0
        assert out.usage == 1 / K and out.perplexity == 1.0
    np.testing.assert_allclose(q.embeddings, emb, rtol=0, atol=1e-5 * np.abs(emb).max())
    np.testing.assert_allclose(q.ema_cluster_size_hidden, hcs, rtol=1e-5, atol=0)
    np.testing.assert_allclose(q.ema_dw_hidden, hdw, rtol=0, atol=1e-5 * np.abs(hdw).max())
    assert (q.embeddings[:, 1:] == 0).all() and q.counter == 400


def test_ties_and_duplicated_codes_go_to_the_smallest_index():
    """x exactly between two codes, and codes repeated: the smallest index (float32 values whose
    squared differences are exact in float64, so the tie is exact)."""
    q = EMAQuantizer(2, 5, dtype="float32")
    q.embeddings[:] = np.array([[3.0, 1.0, -1.0, 1.0, -1.0], [0.0, 0.0, 0.0, 0.0, 0.0]], np.float32)
    z = np.array([0.0, 1.0, -1.0, 2.0], np.float32).reshape(1, 1, 2, 2)
    z = np.concatenate([z, np.zeros_like(z)], axis=1)  # (1, 2, 2, 2)
    out, _ = q.forward(z, train=True)
    np.testing.assert_array_equal(out.codes.ravel(), [1, 1, 2, 0])  # 0 ties 1 and 2; 2 ties 0 and 1
    assert np.isfinite(q.embeddings).all()
