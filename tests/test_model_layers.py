"""The transformer's remaining layers one by one against torch in float64, random upstream
gradients: the attention layer (fused v/q/k projection, heads, branching kernel, output
projection), the cross-entropy with label smoothing, the pose loss."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from conftest import assert_close
from pyvf.nn.attention import attention_layer_backward, attention_layer_forward
from pyvf.nn.losses import cross_entropy_backward, cross_entropy_forward, pose_loss_backward, pose_loss_forward
from pyvf.verify.torch_ports import tree_mask

# float64, O(10) roundings per value: measured <= 3e-15; 1e-12 leaves room
RTOL = 1e-12


@pytest.mark.parametrize("scale", [1.0, 0.125])
def test_attention_layer_matches_torch(scale, rng):
    R, B, N, L, d, H = 3, 2, 4, 5, 12, 3
    x = rng.standard_normal((R, B, N, L, d))
    w_attn, b_attn = rng.standard_normal((d, 3 * d)) * 0.5, rng.standard_normal((1, 3 * d))
    w_proj, b_proj = rng.standard_normal((d, d)) * 0.5, rng.standard_normal((1, d))
    dy = rng.standard_normal((R, B, N, L, d))
    y, cache = attention_layer_forward(x, w_attn, b_attn, w_proj, b_proj, H, scale)
    grads = attention_layer_backward(dy, cache)

    t = [torch.tensor(a, requires_grad=True) for a in (x, w_attn, b_attn, w_proj, b_proj)]
    tx = t[0].permute(1, 0, 2, 3, 4).reshape(B, R * N * L, d)  # flat [row][view][token]
    h = tx @ t[1] + t[2][0]
    v, q, k = h[..., :d], h[..., d:2 * d], h[..., 2 * d:]  # docs/math.md §3: values, queries, keys
    q, k, v = (a.reshape(B, -1, H, d // H).transpose(1, 2) for a in (q, k, v))
    o = F.scaled_dot_product_attention(q, k, v, attn_mask=tree_mask(N, L), scale=scale)
    ty = o.transpose(1, 2).reshape(B, R * N * L, d) @ t[3] + t[4][0]
    ty = ty.reshape(B, R, N, L, d).permute(1, 0, 2, 3, 4)
    (ty * torch.tensor(dy)).sum().backward()

    assert_close("y", y, ty.detach().numpy(), rtol=RTOL)
    for name, g, tt in zip(["dx", "dw_attn", "db_attn", "dw_proj", "db_proj"], grads, t):
        assert_close(name, g, tt.grad.numpy(), rtol=RTOL)


@pytest.mark.parametrize("eps", [0.0, 0.1])
def test_cross_entropy_matches_torch(eps, rng):
    M, V = 37, 23
    logits = rng.standard_normal((M, V)) * 5
    logits[0] += 1e4  # a huge row: the log-sum-exp must stay finite and exact
    targets = rng.integers(0, V, M)
    dloss = rng.standard_normal(M)
    loss, cache = cross_entropy_forward(logits, targets, eps)
    (dlogits,) = cross_entropy_backward(dloss, cache)
    tl = torch.tensor(logits, requires_grad=True)
    tloss = F.cross_entropy(tl, torch.tensor(targets), reduction="none", label_smoothing=eps)
    (tloss * torch.tensor(dloss)).sum().backward()
    assert_close("ce", loss, tloss.detach().numpy(), rtol=RTOL)
    assert_close("dlogits", dlogits, tl.grad.numpy(), rtol=RTOL)


U32 = float(np.finfo(np.float32).eps) / 2


@pytest.mark.parametrize("eps", [0.0, 0.1])
def test_cross_entropy_float32_against_torch_float64(eps, rng):
    """float32 logits (V = 1000) against torch in float64 on the
    same rounded values, a random dloss. The kernel's loss is the float64 log-sum-exp of float32
    exponentials (each ~1 ulp), rounded once: within 4 u of the largest loss. dlogits: each p_i is
    the exp of an argument rounded to float32, |z_i - ls| u off, |z_i - ls| < 40 here: within 64 u
    of the largest |dlogits|."""
    M, V = 64, 1000
    logits = (4 * rng.standard_normal((M, V))).astype(np.float32)
    targets, dloss = rng.integers(0, V, M), rng.standard_normal(M).astype(np.float32)
    loss, cache = cross_entropy_forward(logits, targets, eps)
    (dlogits,) = cross_entropy_backward(dloss, cache)
    assert loss.dtype == dlogits.dtype == np.float32
    tl = torch.tensor(logits.astype(np.float64), requires_grad=True)
    tloss = F.cross_entropy(tl, torch.tensor(targets), reduction="none", label_smoothing=eps)
    (tloss * torch.tensor(dloss.astype(np.float64))).sum().backward()
    assert_close("ce float32", loss, tloss.detach().numpy(), rtol=4 * U32)
    assert_close("dlogits float32", dlogits, tl.grad.numpy(), rtol=64 * U32)
    # the bound has teeth: a loss computed from logits read one row off is far outside it
    wrong, _ = cross_entropy_forward(np.roll(logits, 1, axis=0), targets, eps)
    assert np.abs(wrong - tloss.detach().numpy()).max() > 1e4 * 4 * U32 * np.abs(loss).max()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_cross_entropy_hard_cases(dtype):
    """Closed forms: logits spanning the dtype, ties, one class, no rows, probabilities below the
    smallest normal number (kept as NumPy's exp keeps them, not flushed to 0)."""
    big = np.finfo(dtype).max
    one = np.ones(2, dtype)
    # a row from -max to +max: the target at the max has p = 1, loss 0, dlogits 0 (z = -inf elsewhere)
    loss, cache = cross_entropy_forward(np.array([[big, -big]], dtype), np.array([0]))
    assert loss.tolist() == [0.0] and cross_entropy_backward(one[:1], cache)[0].tolist() == [[0.0, 0.0]]
    # the other target: -log p = 2 max overflows the dtype: inf, never a NaN or a finite lie
    assert cross_entropy_forward(np.array([[big, -big]], dtype), np.array([1]))[0].tolist() == [np.inf]
    # ties: p = 1/V, loss = log V (rounded once); dlogits = 1/V - [i = t]
    V = 7
    loss, cache = cross_entropy_forward(np.full((2, V), 3.5, dtype), np.array([0, 6]))
    assert_close("ties' loss", loss, np.full(2, np.log(V)), rtol=float(np.finfo(dtype).eps))
    (d,) = cross_entropy_backward(one, cache)
    want = np.full((2, V), 1 / V) - np.eye(V)[[0, 6]]
    assert_close("ties", d, want, rtol=4 * float(np.finfo(dtype).eps))
    # one class: loss 0, dlogits 0, exactly; with smoothing too (q = 1)
    for eps in (0.0, 0.3):
        loss, cache = cross_entropy_forward(np.array([[5.0], [-2.0]], dtype), np.array([0, 0]), eps)
        assert loss.tolist() == [0.0, 0.0] and cross_entropy_backward(one, cache)[0].tolist() == [[0.0], [0.0]]
    # no rows
    loss, cache = cross_entropy_forward(np.zeros((0, 5), dtype), np.zeros(0, np.int64))
    assert loss.shape == (0,) and cross_entropy_backward(np.zeros(0, dtype), cache)[0].shape == (0, 5)
    # a probability in the subnormals (float32: e^-100 = 3.7e-44): the gradient keeps it
    gap = dtype(-100.0) if dtype == np.float32 else dtype(-740.0)
    loss, cache = cross_entropy_forward(np.array([[0.0, gap]], dtype), np.array([0]))
    (d,) = cross_entropy_backward(one[:1], cache)
    assert d[0, 1] == np.exp(gap) and d[0, 1] > 0, d


@pytest.mark.parametrize("sign_invariant", [False, True])
def test_pose_loss_matches_torch_and_uses_the_raw_quaternion(rng, sign_invariant):
    raw = rng.standard_normal((2, 3, 5, 7)) * 2  # a quaternion of norm ~4: not normalised
    target = rng.standard_normal((2, 3, 1, 7))  # broadcast over the tokens; q . q_raw of both signs
    dloss = rng.standard_normal((2, 3, 5))
    m = 0.2
    loss, cache = pose_loss_forward(raw, target, m, sign_invariant)
    (draw,) = pose_loss_backward(dloss, cache)
    tr = torch.tensor(raw, requires_grad=True)
    tt = torch.tensor(target)
    tq = ((tt[..., 3:] - tr[..., 3:]) ** 2).mean(-1)
    if sign_invariant:  # the oracle: the smaller loss of q and -q, autograd through the smaller
        tq = torch.minimum(tq, ((-tt[..., 3:] - tr[..., 3:]) ** 2).mean(-1))
    tloss = ((m * tt[..., :3] - tr[..., :3]) ** 2).mean(-1) + tq
    (tloss * torch.tensor(dloss)).sum().backward()
    assert_close("pose loss", loss, tloss.detach().numpy(), rtol=RTOL)
    assert_close("draw", draw, tr.grad.numpy(), rtol=RTOL)
    flipped = np.concatenate([target[..., :3], -target[..., 3:]], axis=-1)  # the same rotations
    same = pose_loss_forward(raw, flipped, m, sign_invariant)[0] == loss
    assert same.all() if sign_invariant else not same.any()
