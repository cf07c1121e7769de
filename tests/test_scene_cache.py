"""The scene cache (docs/math.md §3): encode_scene, then render_scene / localize_scene, run the
training blocks with the trunk's keys and values cached, and compute what the whole tree's
forward computes for the query's branch row.

Why not bitwise. The two paths evaluate the same function in a different order of rounding:
the cached attention takes its softmax in one pass where the tree's kernel takes it block by
block. (The linear layers' rows do not differ: pyvf's GEMM sums each element in one order
whatever the number of rows in the product.) So the test bounds the difference by the rounding error of the training
forward itself, measured:

    E32 = max |forward_float32 - forward_float64|   (the same float32 weights, widened)

is the float32 forward's own error. Either path's error is of that size, so
|cached - forward| <= |cached - exact| + |forward - exact|, and the bound allows each twice
E32: 4 * E32 in float32. Rounding errors scale with the unit roundoff u, so in float64 the
bound is 4 * E32 * u64 / u32. E32 measured on a handful of numbers (one localized pose is 7)
can fall below the error's typical size, so the bound is at least 16 ulps of the largest value
(16 u max|want|): the pose's last steps (average_pose, absolute_poses) alone round a few times.
Measured on the cases below: the float32 cached path is 0.8 to 1.7 times E32 from float64
(2.9 on the single pose of B = C = M = 1), |cached - forward| 0.1 to 0.4 of the bound, the
float64 difference 0.07 to 0.2 of its bound. A planted bug (a query that does not see itself,
the wrong layer's cache, queries that see each other) is off by 1e4 to 3e5 times the bound.
"""

import dataclasses

import numpy as np
import pytest

import pyvf
from conftest import assert_close
from pyvf.nn import attention

U32, U64 = np.finfo(np.float32).eps / 2, np.finfo(np.float64).eps / 2  # unit roundoffs
TINY = dict(n_embeddings=64, n_head=2, d_model=32, n_layer=2, token_image_size=4, sequence_size=5,
            n_loss_skip=1, pose_multiplier=0.5)


def model_pair(seed, **overrides):
    """A float32 model with random parameters everywhere (gamma != 1, biases != 0), and its
    float64 copy holding the same (widened) numbers."""
    cfg = pyvf.TransformerConfig(**{**TINY, **overrides}, dtype="float32")
    m32 = pyvf.Transformer(cfg, seed=seed)
    rng = np.random.default_rng(seed)
    for name, p in m32.params.items():
        m32.params[name] = (p + rng.normal(0, 0.3, p.shape)).astype(np.float32)
    m64 = pyvf.Transformer(dataclasses.replace(cfg, dtype="float64"))
    m64.params = {name: p.astype(np.float64) for name, p in m32.params.items()}
    return m32, m64


def random_views(rng, B, N, L, V):
    """tokens (B, N, L) and poses (B, N, 7) float64 (unit quaternions)."""
    poses = rng.normal(size=(B, N, 7))
    poses[..., 3:] /= np.linalg.norm(poses[..., 3:], axis=-1, keepdims=True)
    return rng.integers(0, V, (B, N, L)), poses


def whole_tree(model, tokens, poses, C):
    """For each query m: Transformer.forward on [context views, query m] (the training forward),
    the generation row's logits and the localization row's pose at view C, as the cache returns
    them: logits (B, M, L, V), poses (B, M, 7) in the frame of the given poses."""
    logits, located = [], []
    for m in range(tokens.shape[1] - C):
        views = [*range(C), C + m]
        rel, ref = pyvf.make_relative(poses[:, views])  # the first context view's frame
        out = model.forward(tokens[:, views], rel)
        logits.append(out.logits[:, C])
        located.append(pyvf.absolute_poses(pyvf.average_pose(out.pose_prediction[:, C], axis=1), ref))
    return np.stack(logits, axis=1), np.stack(located, axis=1)


def cached(model, tokens, poses, C):
    scene = model.encode_scene(tokens[:, :C], poses[:, :C])
    return model.render_scene(scene, poses[:, C:]), model.localize_scene(scene, tokens[:, C:])


def check_cache_equals_whole_tree(B, C, M, seed=0, **overrides):
    """The cached render and localize of M queries equal the whole tree's, within the bound of
    the module docstring, in float32 and in float64."""
    m32, m64 = model_pair(seed, **overrides)
    tokens, poses = random_views(np.random.default_rng(seed + 1), B, C + M, m32.config.L, m32.config.n_embeddings)
    p32 = poses.astype(np.float32)  # their rounding is part of the float32 forward's error E32
    tree32, tree64 = whole_tree(m32, tokens, p32, C), whole_tree(m64, tokens, poses, C)
    cache32, cache64 = cached(m32, tokens, p32, C), cached(m64, tokens, poses, C)
    for i, what in enumerate(("render_scene logits", "localize_scene poses")):
        e32 = np.abs(tree32[i].astype(np.float64) - tree64[i]).max()  # the float32 forward's own error
        assert e32 > 0, f"{what}: float32 and float64 forwards agree exactly; E32 measures nothing"
        assert cache32[i].dtype == np.float32 and cache64[i].dtype == np.float64
        # rtol: the floor of 16 ulps of the largest value (module docstring)
        assert_close(f"{what}, float32", cache32[i], tree32[i], rtol=16 * U32, atol=4 * e32)
        assert_close(f"{what}, float64", cache64[i], tree64[i], rtol=16 * U64, atol=4 * e32 * U64 / U32)


# ---------------------------------------------------------------------------------------
# 1. the cache computes the whole tree's branch row


@pytest.mark.parametrize("B, C, M", [(1, 1, 1), (2, 3, 4), (1, 5, 2), (3, 2, 1)])
def test_cache_equals_whole_tree(B, C, M):
    check_cache_equals_whole_tree(B, C, M, seed=B * 100 + C * 10 + M)


def test_cache_equals_whole_tree_scaled_logits_more_layers():
    """attention_scale != 1 and more heads and layers: every layer's cache and the scale are used."""
    check_cache_equals_whole_tree(2, 3, 2, seed=7, attention_scale=0.25, n_layer=3, n_head=4)


def test_queries_are_independent():
    """A query's result does not depend on the other queries rendered with it."""
    m32, _ = model_pair(3)
    tokens, poses = random_views(np.random.default_rng(4), 2, 6, m32.config.L, m32.config.n_embeddings)
    poses = poses.astype(np.float32)
    scene = m32.encode_scene(tokens[:, :3], poses[:, :3])
    every = m32.render_scene(scene, poses[:, 3:]), m32.localize_scene(scene, tokens[:, 3:])
    one = m32.render_scene(scene, poses[:, 4:5]), m32.localize_scene(scene, tokens[:, 4:5])
    # the rows of one query pass through products of other sizes: rounding only (float32, E32 ~ 1e-6)
    assert_close("render, query 1 alone", one[0][:, 0], every[0][:, 1], rtol=1e-5)
    assert_close("localize, query 1 alone", one[1][:, 0], every[1][:, 1], rtol=1e-5)


# ---------------------------------------------------------------------------------------
# 2. planted bugs fail the check


def test_planted_bug_query_does_not_attend_itself(monkeypatch):
    real = attention.context_attention_forward

    def blind(q, k, v, k_ctx, v_ctx, scale=1.0):  # the own block replaced by the last context block
        last = lambda c: np.broadcast_to(c[None, :, :, -1:], q.shape).copy()  # noqa: E731
        return real(q, last(k_ctx), last(v_ctx), k_ctx, v_ctx, scale)

    monkeypatch.setattr(attention, "context_attention_forward", blind)
    with pytest.raises(pytest.fail.Exception):
        check_cache_equals_whole_tree(2, 3, 2)


def test_planted_bug_wrong_layers_cache(monkeypatch):
    encode = pyvf.Transformer.encode_scene

    def shifted(self, *args):  # layer j gets layer j+1's keys and values
        s = encode(self, *args)
        return dataclasses.replace(s, keys=s.keys[1:] + s.keys[:1], values=s.values[1:] + s.values[:1])

    monkeypatch.setattr(pyvf.Transformer, "encode_scene", shifted)
    with pytest.raises(pytest.fail.Exception):
        check_cache_equals_whole_tree(2, 3, 2)


def test_planted_bug_queries_see_each_other(monkeypatch):
    real = attention.context_attention_forward

    def mixed(q, k, v, k_ctx, v_ctx, scale=1.0):  # query r's own block taken from query r+1
        return real(q, np.roll(k, 1, axis=0), np.roll(v, 1, axis=0), k_ctx, v_ctx, scale)

    monkeypatch.setattr(attention, "context_attention_forward", mixed)
    with pytest.raises(pytest.fail.Exception):
        check_cache_equals_whole_tree(1, 2, 3)


# ---------------------------------------------------------------------------------------
# 3. the attention of query rows against a cached trunk


def branch_tree(q, k, v, k_ctx, v_ctx):
    """The tree over [context, query r] for every query row r at once: (1 + R, B, H, Nc + 1, L, dh),
    the trunk holding the context (view Nc unused, zeros), branch row 1 + r query r at view Nc."""
    R, B, H, _, L, dh = q.shape
    Nc = k_ctx.shape[2]
    trees = []
    for x, ctx in ((q, np.zeros_like(k_ctx)), (k, k_ctx), (v, v_ctx)):
        t = np.zeros((1 + R, B, H, Nc + 1, L, dh), dtype=q.dtype)
        t[0, :, :, :Nc] = ctx
        t[1:, :, :, Nc:] = x
        trees.append(t)
    return trees


@pytest.mark.parametrize("R, B, H, Nc, L, dh, scale", [(1, 1, 1, 1, 4, 2, 1.0), (3, 2, 2, 4, 8, 4, 1.0),
                                                        (2, 1, 3, 2, 16, 8, 0.3),
                                                        # the softmax kernel on the threads, L = 37: whole
                                                        # vectors and a scalar tail on every path
                                                        (2, 2, 4, 3, 37, 8, 1.0)])
def test_context_attention_equals_branching_attention(R, B, H, Nc, L, dh, scale, kernel_path):
    """o and lse of each query row equal those of branch row 1 + r at view Nc of the tree: float64
    against the dense reference (sums of at most (Nc + 1) L = 80 terms: 1e-13 is about 1000 u64);
    float32 as accurate as the kernel on the tree (both against float64)."""
    rng = np.random.default_rng(R * 1000 + Nc)
    q, k, v = (rng.normal(0, 1, (R, B, H, 1, L, dh)) for _ in range(3))
    k_ctx, v_ctx = (rng.normal(0, 1, (B, H, Nc, L, dh)) for _ in range(2))
    o, lse = attention.context_attention_forward(q, k, v, k_ctx, v_ctx, scale)
    assert o.shape == q.shape and lse.shape == q.shape[:5] and lse.dtype == np.float64
    tree = branch_tree(q, k, v, k_ctx, v_ctx)
    want = pyvf.branching_attention_reference(*tree, scale)[1:, :, :, Nc:]  # (R, B, H, 1, L, dh)
    assert_close("o, float64", o, want, rtol=1e-13)
    _, want_lse = pyvf.branching_attention_forward(*tree, scale)
    assert_close("lse, float64", lse, want_lse[1:, :, :, Nc:], rtol=1e-13)

    o32, lse32 = attention.context_attention_forward(*(a.astype(np.float32) for a in (q, k, v, k_ctx, v_ctx)), scale)
    kern32, kern_lse32 = pyvf.branching_attention_forward(*(t.astype(np.float32) for t in tree), scale)
    assert o32.dtype == np.float32
    # twice the kernel's error, and at least 8 float32 ulps of the largest value (a sample of a
    # few numbers, as the first case's 4, can leave the kernel's error below its typical size)
    for what, got, kern, ref in (("o", o32, kern32, want), ("lse", lse32, kern_lse32, want_lse[1:, :, :, Nc:])):
        e32 = np.abs(kern[1:, :, :, Nc:] - ref).max()
        assert_close(f"{what}, float32", got, ref, rtol=8 * U32, atol=2 * e32)


def test_context_attention_rejects_bad_arguments():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(2, 1, 2, 1, 4, 3))
    ctx = rng.normal(size=(1, 2, 3, 4, 3))
    f = attention.context_attention_forward
    with pytest.raises(ValueError, match="q must hold query rows of one view"):
        f(rng.normal(size=(2, 1, 2, 2, 4, 3)), q, q, ctx, ctx)
    with pytest.raises(ValueError, match="k has shape"):
        f(q, q[:1], q, ctx, ctx)
    with pytest.raises(ValueError, match="k_ctx must be the context's"):
        f(q, q, q, ctx[:, :, :, :2], ctx)
    with pytest.raises(ValueError, match="v_ctx has shape"):
        f(q, q, q, ctx, ctx[:, :, :2])
    with pytest.raises(TypeError, match="v_ctx is float32 but q is float64"):
        f(q, q, q, ctx, ctx.astype(np.float32))
    bad = ctx.copy()
    bad[0, 0, 0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="k_ctx contains NaN"):
        f(q, q, q, bad, ctx)
    with pytest.raises(ValueError, match="not finite"):  # logits overflow float32
        f(*(a.astype(np.float32) * 1e20 for a in (q, q, q, ctx, ctx)))
    # values near float32's largest: the sums of p v overflow before the division (o returned inf)
    v, v_ctx = np.full(q.shape, 2e38, np.float32), np.full(ctx.shape, 2e38, np.float32)
    with pytest.raises(ValueError, match="context_attention_forward: the result is not finite"):
        f(np.zeros(q.shape, np.float32), np.zeros(q.shape, np.float32), v, np.zeros(ctx.shape, np.float32), v_ctx)


def test_attention_layer_with_context_has_no_backward():
    rng = np.random.default_rng(0)
    d, H = 8, 2
    x = rng.normal(size=(2, 1, 1, 4, d))
    w = [rng.normal(size=s) for s in ((d, 3 * d), (1, 3 * d), (d, d), (1, d))]
    ctx = tuple(rng.normal(size=(1, H, 3, 4, d // H)) for _ in range(2))
    y, cache = attention.attention_layer_forward(x, *w, H, context=ctx)
    assert y.shape == x.shape
    with pytest.raises(ValueError, match="has no backward"):
        attention.attention_layer_backward(rng.normal(size=y.shape), cache)
    with pytest.raises(TypeError, match="context must be None or a pair"):
        attention.attention_layer_forward(x, *w, H, context=ctx[0])
