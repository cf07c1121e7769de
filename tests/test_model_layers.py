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
from pyvf.verify.torch_transformer import tree_mask

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
    o = F.scaled_dot_product_attention(q, k, v, attn_mask=tree_mask(R, N, L), scale=scale)
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


def test_pose_loss_matches_torch_and_uses_the_raw_quaternion(rng):
    raw = rng.standard_normal((2, 3, 5, 7)) * 2  # a quaternion of norm ~4: not normalised
    target = rng.standard_normal((2, 3, 1, 7))  # broadcast over the tokens
    dloss = rng.standard_normal((2, 3, 5))
    m = 0.2
    loss, cache = pose_loss_forward(raw, target, m)
    (draw,) = pose_loss_backward(dloss, cache)
    tr = torch.tensor(raw, requires_grad=True)
    tt = torch.tensor(target)
    tloss = ((m * tt[..., :3] - tr[..., :3]) ** 2).mean(-1) + ((tt[..., 3:] - tr[..., 3:]) ** 2).mean(-1)
    (tloss * torch.tensor(dloss)).sum().backward()
    assert_close("pose loss", loss, tloss.detach().numpy(), rtol=RTOL)
    assert_close("draw", draw, tr.grad.numpy(), rtol=RTOL)
