"""The inputs a demanding user tries on the Transformer and the layers it is built of: arrays the
caller changes between forward() and backward(), losses and seeds past the dtype's range,
pose multipliers the dtype cannot hold, and public helpers given mismatched shapes.

Each test is a defect found that way: its docstring says what happened before. Oracles are
independent of the code path under test: the same computation on untouched inputs (bitwise), or
the error contract of pyvf._checks (every error names the argument and says why).
"""

import numpy as np
import pytest

import pyvf
from pyvf.models.transformer import pose_prediction
from pyvf.nn import attention, layers, losses

from conftest import assert_bitwise_equal

SMALL = dict(n_embeddings=16, n_head=2, d_model=8, n_layer=1, token_image_size=2, sequence_size=3, n_loss_skip=1)


def batch(rng, B, N, dtype, L=4, V=16):
    tokens = rng.integers(0, V, (B, N, L))
    poses = rng.normal(size=(B, N, 7))
    poses[..., 3:] /= np.linalg.norm(poses[..., 3:], axis=-1, keepdims=True)
    return tokens, poses.astype(dtype)


def model(dtype="float64", **cfg):
    return pyvf.Transformer(pyvf.TransformerConfig(**{**SMALL, **cfg}, dtype=dtype), seed=0)


def assert_same_grads(got, want):
    assert got.keys() == want.keys()
    for name in want:
        assert_bitwise_equal(name, got[name], want[name])


# ---------------------------------------------------------------------------------------
# backward() differentiates the last forward, whatever the caller does to its arrays since


@pytest.mark.parametrize("B", [1, 2])
def test_backward_ignores_inputs_changed_after_forward(rng, B):
    """The forward kept the caller's tokens array itself (the embedding's scatter ids, and the
    cross-entropy's targets when they were a view): a data loader refilling its buffer before
    backward() moved the wte gradient to the new batch's rows, silently (max |diff| 1.2 on a
    tiny model). The oracle: the same forward and backward on arrays nobody touched, bitwise."""
    m = model()
    tokens, poses = batch(rng, B, 3, np.float64)
    m.forward(tokens.copy(), poses.copy())
    want = m.backward()
    m.forward(tokens, poses)
    tokens[...] = (tokens + 1) % SMALL["n_embeddings"]  # the caller reuses its buffers
    poses[...] = poses[::-1]
    assert_same_grads(m.backward(), want)


@pytest.mark.parametrize("B, skip", [(1, 1), (2, 0), (2, 1)])
def test_backward_ignores_outputs_changed_after_forward(rng, B, skip):
    """out.logits is the caller's array, yet with B = 1 or n_loss_skip = 0 the cross-entropy's
    cache was a view of it (the logits of the loss views, reshaped without a copy): a softmax
    written in place into out.logits changed the next backward() silently."""
    m = model(n_loss_skip=skip)
    tokens, poses = batch(rng, B, 3, np.float64)
    m.forward(tokens, poses)
    want = m.backward()
    out = m.forward(tokens, poses)
    for a in (out.logits, out.pose_raw, out.pose_prediction, out.ce_loss, out.pose_loss):
        a *= 2
    assert_same_grads(m.backward(), want)


# ---------------------------------------------------------------------------------------
# the loss and its seed past the dtype's range


def test_loss_that_overflows_raises_and_keeps_the_last_forward(rng):
    """A float32 loss weight that makes each batch element's weighted loss 0.75 of float32's
    largest value: the batch mean fits, the sum NumPy's mean takes first does not, and out.loss
    came back inf, silently (a RuntimeWarning at most), while backward() gave finite gradients
    of that inf. Now a ValueError naming the loss; the failed forward leaves what backward()
    differentiates unchanged (bitwise)."""
    tokens, poses = batch(rng, 1, 3, np.float32)
    pl = float(model("float32").forward(tokens, poses).pose_loss[0])
    m = model("float32", localization_weight=0.75 * float(np.finfo(np.float32).max) / pl)  # same seed, same weights
    m.forward(tokens, poses)  # one element: its weighted loss fits float32
    want = m.backward()
    with pytest.raises(ValueError, match=r"loss is not finite: it overflowed float32"):
        m.forward(np.concatenate([tokens, tokens]), np.concatenate([poses, poses]))  # the sum of two does not
    assert_same_grads(m.backward(), want)


@pytest.mark.parametrize("dloss", [1e40, -1e300])
def test_backward_seed_beyond_the_dtype_is_named(rng, dloss):
    """backward(dloss=1e40) on a float32 model said "dloss contains NaN or inf" (and NumPy
    warned of an overflowing cast): dloss is finite; it is the per-token seed dloss / (B N L)
    that float32 cannot hold. The error now says so, and the model is left as it was."""
    m = model("float32")
    tokens, poses = batch(rng, 2, 3, np.float32)
    m.forward(tokens, poses)
    want = m.backward()
    with pytest.raises(ValueError, match=r"^dloss=.* float32") as e:
        m.backward(dloss=dloss)
    assert "NaN" not in str(e.value)
    assert_same_grads(m.backward(), want)


# ---------------------------------------------------------------------------------------
# pose_multiplier: positions are multiplied by it in the loss, predictions divided by it


@pytest.mark.parametrize("raw, pm, exc, match", [
    (np.ones((2, 7), np.int64), 1.0, TypeError, "^raw must be float32 or float64"),
    (np.full((2, 7), np.nan, np.float32), 1.0, ValueError, "^raw contains NaN or inf"),
    ([[1.0] * 7], 1.0, TypeError, "^raw must be a numpy.ndarray"),
    (np.ones((2, 6)), 1.0, ValueError, "^raw must have last dimension 7"),
    (np.ones((2, 7), np.float32), 0.0, ValueError, "^pose_multiplier must be nonzero"),
    (np.ones((2, 7), np.float32), 1e-40, ValueError, "^pose_multiplier must be nonzero.*float32"),
    (np.ones((2, 7), np.float32), "0.2", TypeError, "^pose_multiplier must be a real number"),
    (np.full((2, 7), 1e30, np.float32), 1e-10, ValueError, "pose_prediction: the result is not finite"),
])
def test_pose_prediction_bad_input_is_named(raw, pm, exc, match):
    """pose_prediction blamed `q`, the quaternion helper's argument, for a raw of the wrong dtype
    or with NaN; a list failed inside NumPy indexing; pose_multiplier = 0 (or one float32 holds
    as 0 or a subnormal) and a quotient past float32's range returned inf poses, silently."""
    with np.errstate(all="raise"):  # no division by zero or overflow reaches NumPy any more
        with pytest.raises(exc, match=match):
            pose_prediction(raw, pm)


def test_pose_loss_multiplier_beyond_the_dtype_is_named():
    """pose_multiplier = 1e39 is finite but not a float32: it became inf, and inf * 0 NaN, so a
    zero target (whose loss is mean(raw^2), finite) raised "the loss is not finite: it
    overflowed float32", blaming the loss for the argument."""
    raw, target = np.ones((2, 7), np.float32), np.zeros((2, 7), np.float32)
    with pytest.raises(ValueError, match=r"^pose_multiplier .*float32"):
        losses.pose_loss_forward(raw, target, 1e39)
    # the bound is the dtype's: the same multiplier is a float64
    loss, _ = losses.pose_loss_forward(raw.astype(np.float64), target.astype(np.float64), 1e39)
    np.testing.assert_array_equal(loss, np.full(2, 2.0))  # 3/3 + 4/4: exact


# ---------------------------------------------------------------------------------------
# public helpers given mismatched shapes or types


@pytest.mark.parametrize("ids, rows, n, exc, match", [
    (np.array([0, 1]), np.ones((3, 2)), 2, ValueError, r"^rows has 3 rows but ids has 2 ids"),
    (np.array([0, 1, 1]), np.ones((2, 2)), 2, ValueError, r"^rows has 2 rows but ids has 3 ids"),
    (np.array([[0], [1]]), np.ones((2, 2)), 2, ValueError, r"^ids must be 1-D"),
    (np.array([0.0, 1.0]), np.ones((2, 2)), 2, TypeError, r"^ids must be an integer array"),
    (np.array([0, 1]), np.ones(2), 2, ValueError, r"^rows must be 2-D"),
    (np.array([0, 1]), np.ones((2, 2), np.int64), 2, TypeError, r"^rows must be float32 or float64"),
    (np.array([0, 1]), np.ones((2, 2)), 2.0, TypeError, r"^n must be an integer"),
    (np.array([], np.int64), np.ones((0, 2)), -1, ValueError, r"^n must be >= 0"),
])
def test_sum_rows_by_id_checks_its_arguments(ids, rows, n, exc, match):
    """ids shorter than rows dropped the rows past them from the sum, silently ([[1, 1], [1, 1]]
    for three rows of ones on ids [0, 1]); longer, or 2-D, or float ids failed inside NumPy
    with an error naming no argument."""
    with pytest.raises(exc, match=match):
        layers.sum_rows_by_id(ids, rows, n)


@pytest.mark.parametrize("n_head", [2.0, "2", True])
def test_attention_n_head_of_the_wrong_type_is_a_type_error(rng, n_head):
    """n_head = 2.0 raised ValueError "must be a positive integer": a wrong type is a TypeError
    throughout pyvf (_checks.positive_integer; TransformerConfig.n_head says so)."""
    x = rng.normal(size=(2, 1, 2, 3, 4))
    w_attn, b_attn = rng.normal(size=(4, 12)), np.zeros((1, 12))
    w_proj, b_proj = rng.normal(size=(4, 4)), np.zeros((1, 4))
    with pytest.raises(TypeError, match="^n_head must be an integer"):
        attention.attention_layer_forward(x, w_attn, b_attn, w_proj, b_proj, n_head)
