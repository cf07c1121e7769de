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


@pytest.mark.parametrize("B, C, M, config", [(1, 1, 1, {}), (2, 3, 4, {}),
                                             # every layer's cache and the scale are used
                                             (2, 3, 2, dict(attention_scale=0.25, n_layer=3, n_head=4))])
def test_cache_equals_whole_tree(B, C, M, config):
    check_cache_equals_whole_tree(B, C, M, seed=B * 100 + C * 10 + M, **config)


# ---------------------------------------------------------------------------------------
# 2. planted bugs fail the check


def blind(real):  # the own block replaced by the last context block
    def f(q, k, v, k_ctx, v_ctx, scale=1.0):
        last = lambda c: np.broadcast_to(c[None, :, :, -1:], q.shape).copy()  # noqa: E731
        return real(q, last(k_ctx), last(v_ctx), k_ctx, v_ctx, scale)
    return f


def mixed(real):  # query r's own block taken from query r+1
    return lambda q, k, v, k_ctx, v_ctx, scale=1.0: real(q, np.roll(k, 1, axis=0), np.roll(v, 1, axis=0),
                                                         k_ctx, v_ctx, scale)


def shifted(encode):  # layer j gets layer j+1's keys and values
    def f(self, *args):
        s = encode(self, *args)
        return dataclasses.replace(s, keys=s.keys[1:] + s.keys[:1], values=s.values[1:] + s.values[:1])
    return f


@pytest.mark.parametrize("plant, where, B, C, M", [(blind, attention, 2, 3, 2), (mixed, attention, 1, 2, 3),
                                                   (shifted, pyvf.Transformer, 2, 3, 2)], ids=["blind", "mixed", "shifted"])
def test_planted_bug_fails_the_check(monkeypatch, plant, where, B, C, M):
    name = "encode_scene" if where is pyvf.Transformer else "context_attention_forward"
    monkeypatch.setattr(where, name, plant(getattr(where, name)))
    with pytest.raises(pytest.fail.Exception):
        check_cache_equals_whole_tree(B, C, M)


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


# ---------------------------------------------------------------------------------------
# a scene belongs to the model (and the weights) that encoded it: with other weights, layers or
# dtype the query blocks would attend another model's keys and values and answer wrongly


def reloaded():
    """The model that encoded the scene, with another model's weights loaded since."""
    m = model_pair(0)[1]
    m.load_official(model_pair(7)[1].state_dict())
    return m


@pytest.mark.parametrize("other", [lambda m: model_pair(5)[1], lambda m: model_pair(0, n_layer=3)[1],
                                   lambda m: model_pair(0)[0], lambda m: reloaded()],
                         ids=["seed", "more layers", "dtype", "load_official"])
def test_scene_of_another_model_is_refused(other):
    m = model_pair(0)[1]
    tokens, poses = random_views(np.random.default_rng(1), 2, 5, m.config.L, 32)
    scene = m.encode_scene(tokens[:, :3], poses[:, :3])
    o = other(m)
    with pytest.raises(ValueError, match=r"\bscene\b"):
        o.render_scene(scene, poses[:, 3:].astype(o.dtype))
    with pytest.raises(ValueError, match=r"\bscene\b"):
        o.localize_scene(scene, tokens[:, 3:])


def test_a_scene_encoded_after_load_official_is_the_new_weights_scene():
    m = reloaded()
    tokens, poses = random_views(np.random.default_rng(2), 2, 5, m.config.L, m.config.n_embeddings)
    fresh = m.encode_scene(tokens[:, :3], poses[:, :3])
    want_logits, want_poses = whole_tree(m, tokens, poses, 3)
    assert_close("render after reload", m.render_scene(fresh, poses[:, 3:]), want_logits, rtol=1e-12)
    assert_close("localize after reload", m.localize_scene(fresh, tokens[:, 3:]), want_poses, rtol=1e-12)


# ---------------------------------------------------------------------------------------
# refusals: one table, the exception type and the argument's name


@pytest.fixture(scope="module")
def inference():
    """A float64 model, context tokens and poses (B=2, 5 views), the scene of the first 3."""
    m = model_pair(0)[1]
    tokens, poses = random_views(np.random.default_rng(1), 2, 5, m.config.L, m.config.n_embeddings)
    return m, m.encode_scene(tokens[:, :3], poses[:, :3]), tokens, poses


def edited(a, index, value):
    a = a.copy()
    a[index] = value
    return a


CONTEXT = [  # (context tokens, context poses) from (tokens, poses), the exception, the argument
    (lambda t, p: (t[:, :0], p[:, :0]), ValueError, "context_tokens"),
    (lambda t, p: (t[:, :3].astype(np.float64), p[:, :3]), TypeError, "context_tokens"),
    (lambda t, p: (t[:, :3] + 64, p[:, :3]), ValueError, "context_tokens"),
    (lambda t, p: (t[:, :3], p[:, :3].astype(np.float32)), TypeError, "context_poses"),
    (lambda t, p: (t[:, :3], p[:, :2]), ValueError, "context_poses"),
    (lambda t, p: (t[:, :3], edited(p[:, :3], (1, 1, 0), np.nan)), ValueError, "context_poses"),
    (lambda t, p: (t[:, :3], edited(p[:, :3], (0, 2, slice(3, None)), 0.0)), ValueError, "context_poses"),
]


@pytest.mark.parametrize("call, error, name", [
    *[(lambda m, s, t, p, x=x: m.render_scene(x, p[:, 3:]), TypeError, "scene") for x in (None, np.zeros((1, 3, 16)))],
    (lambda m, s, t, p: m.localize_scene("scene", t[:, 3:]), TypeError, "scene"),
    # a zero or unnormalised quaternion is named query_poses, not poses (an argument never passed)
    *[(lambda m, s, t, p, q=q: m.render_scene(s, edited(p[:, 3:], (1, 0, slice(3, None)), q)), ValueError, "query_poses")
      for q in ((2.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), (0.6, 0.6, 0.0, 0.0))],
    (lambda m, s, t, p: m.render(t[:, :3], p[:, :3], edited(p[:, 3:], (1, 0, 3), 2.0)), ValueError, "query_poses"),
    (lambda m, s, t, p: m.render_scene(s, p[:, 3:3]), ValueError, "query_poses"),  # no query
    (lambda m, s, t, p: m.localize_scene(s, t[:, 3:3]), ValueError, "query_tokens"),
    *[(lambda m, s, t, p, c=c: m.encode_scene(*c(t, p)), e, n) for c, e, n in CONTEXT],
])
def test_refusals_name_the_argument(inference, call, error, name):
    with pytest.raises(error, match=rf"\b{name}\b"):
        call(*inference)
