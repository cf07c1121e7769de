"""The whole transformer: float32 against float64, the tree's defining property,
weights and bad input (against torch float64: tests/test_trace_compare.py)."""

import dataclasses
import json
import os

import numpy as np
import pytest

import pyvf
from conftest import assert_bitwise_equal, assert_close
from pyvf.models.transformer import pose_prediction
from pyvf.verify import convert_tf

TINY = dict(n_embeddings=64, n_head=2, d_model=32, n_layer=2, token_image_size=4, sequence_size=5, n_loss_skip=1)
SPEC = os.path.join(os.path.dirname(__file__), "data", "official-transformer-tiny.json")


def random_model(cfg, rng, spread=0.3):
    """A model whose parameters are random everywhere (gamma != 1, biases != 0): a bug in any
    parameter's role shows in the outputs."""
    model = pyvf.Transformer(cfg, seed=1)
    for name, p in model.params.items():
        model.params[name] = (p + rng.normal(0, spread, p.shape)).astype(p.dtype)
    return model


def random_batch(rng, B, N, L, V, dtype=np.float64):
    tokens = rng.integers(0, V, (B, N, L))
    poses = rng.normal(size=(B, N, 7))
    poses[..., 3:] /= np.linalg.norm(poses[..., 3:], axis=-1, keepdims=True)
    return tokens, poses.astype(dtype)


# ---------------------------------------------------------------------------------------
# 1. the model against torch float64: every activation and gradient, tests/test_trace_compare.py


def test_pose_prediction_closed_form():
    """The head's raw (xyz, w, x, y, z) -> (xyz / pose_multiplier, unit quaternion with w >= 0),
    on rows whose answers are written by hand: a 3-4-5 quaternion with w < 0 (flipped), one with
    w > 0 (kept), one with w == 0 (kept, as the published code does), a negative unit one."""
    raw = np.array([[1.0, -2.0, 0.5, -3.0, 0.0, 4.0, 0.0],
                    [0.0, 0.4, -0.6, 1.0, 2.0, 2.0, 4.0],
                    [0.0, 0.0, 0.0, 0.0, -2.0, 0.0, 0.0],
                    [0.2, 0.2, 0.2, -0.5, -0.5, -0.5, -0.5]])[None, None]  # (B=1, N=1, L=4, 7)
    want = np.array([[5.0, -10.0, 2.5, 0.6, 0.0, -0.8, 0.0],
                     [0.0, 2.0, -3.0, 0.2, 0.4, 0.4, 0.8],
                     [0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0],
                     [1.0, 1.0, 1.0, 0.5, 0.5, 0.5, 0.5]])[None, None]
    got = pose_prediction(raw, pose_multiplier=0.2)
    # a few roundings of values <= 10 (0.6 / 0.2 is not exactly 3 in binary): 1e-15 relative
    assert_close("pose prediction", got, want, rtol=1e-15)


def test_float32_model_tracks_float64(rng):
    cfg64 = pyvf.TransformerConfig(**TINY, dtype="float64")
    m64 = random_model(cfg64, rng)
    m32 = pyvf.Transformer(dataclasses.replace(cfg64, dtype="float32"))
    m32.load_official(m64.params)  # the same values, rounded to float32
    tokens, poses = random_batch(rng, 2, 5, 16, cfg64.n_embeddings)
    o64, g64 = m64.forward(tokens, poses), m64.backward()
    o32, g32 = m32.forward(tokens, poses.astype(np.float32)), m32.backward()
    assert o32.logits.dtype == np.float32 and all(g.dtype == np.float32 for g in g32.values())
    # float32 (u = 6e-8) through two blocks, parameters rounded too: measured 1.6e-6 for the
    # logits and <= 1.7e-5 for the gradients (the pose MLP's first layer, whose gradient sums
    # many cancelling terms); bounds 1e-5 and 1e-4
    assert_close("logits f32", o32.logits, o64.logits, rtol=1e-5)
    assert abs(o32.loss - o64.loss) <= 1e-5 * o64.loss
    for name in g64:
        assert_close(f"d{name} f32", g32[name], g64[name], rtol=1e-4)


# ---------------------------------------------------------------------------------------
# 2. the tree's defining property, at the whole-model level


def test_branch_equals_block_causal_run_of_its_prefix(rng):
    """Branch r at view i after every block equals the last block of a plain block-causal run
    (the trunk alone, R = 1) on [trunk inputs of views 0..i-1, branch r's input of view i]."""
    cfg = pyvf.TransformerConfig(**{**TINY, "n_layer": 3}, dtype="float64")
    model = random_model(cfg, rng)
    tokens, poses = random_batch(rng, 2, 5, 16, cfg.n_embeddings)
    x0, _ = model._embed_forward(tokens, poses)  # (3, B, N, L, d)
    x = x0
    for j in range(cfg.n_layer):
        x, _ = model._block_forward(x, j)
    for r in (1, 2):
        for i in range(5):
            seq = np.concatenate([x0[0, :, :i], x0[r, :, i:i + 1]], axis=1)[None]  # (1, B, i+1, L, d)
            for j in range(cfg.n_layer):
                seq, _ = model._block_forward(seq, j)
            assert_close(f"branch {r} view {i}", x[r, :, i], seq[0, :, i], rtol=1e-13)


def test_generation_branch_does_not_see_its_own_image(rng):
    """The generation row hides the image of its view: its logits at view i do not depend on the
    tokens of view i (only on earlier views), while the localization row does."""
    cfg = pyvf.TransformerConfig(**TINY, dtype="float64")
    model = random_model(cfg, rng)
    tokens, poses = random_batch(rng, 2, 5, 16, cfg.n_embeddings)
    out = model.forward(tokens, poses)
    t2 = tokens.copy()
    t2[:, 4] = (t2[:, 4] + 1) % cfg.n_embeddings  # only the last view's image changes
    out2 = model.forward(t2, poses)
    assert_bitwise_equal("generation logits of view 4", out2.logits[:, 4], out.logits[:, 4])
    assert not np.array_equal(out2.pose_prediction[:, 4], out.pose_prediction[:, 4])


# ---------------------------------------------------------------------------------------
# 3. weights


def official_weights(rng, dtype=np.float32):
    with open(SPEC) as f:
        spec = json.load(f)
    return {name: rng.normal(size=shape).astype(dtype) for name, shape in spec["variables"].items()}, spec["config"]


def test_load_official_names_and_shapes(rng):
    weights, spec_cfg = official_weights(rng)
    cfg = pyvf.TransformerConfig(**spec_cfg, dtype="float64")
    model = pyvf.Transformer(cfg)
    model.load_official(weights)  # "migt/...:0" names, float32 into a float64 model
    state = model.state_dict()
    assert set(state) == {n[len("migt/"):-2] for n in weights}
    for name, arr in weights.items():
        got = state[model.official_name(name)]
        assert got.dtype == np.float64 and np.array_equal(got, arr.astype(np.float64))
    model2 = pyvf.Transformer(cfg)
    model2.load_official(state)  # plain names load too
    tokens, poses = random_batch(rng, 1, 5, 16, cfg.n_embeddings)
    assert_bitwise_equal("same weights, same logits", model2.forward(tokens, poses).logits,
                         model.forward(tokens, poses).logits)


# ---------------------------------------------------------------------------------------
# 4. refusals: one table per entry point, the exception type and the argument's name


def _call(rng, what, edit):
    """Call the entry point `what` on a valid batch changed by edit(dict of its arguments)."""
    model = pyvf.Transformer(pyvf.TransformerConfig(**TINY))
    tokens, poses = random_batch(rng, 2, 5, 16, 64, dtype=np.float32)
    if what == "forward":
        return model.forward(**edit(dict(tokens=tokens, poses=poses)))
    if what == "backward":
        model.forward(tokens, poses)
        return model.backward(**edit({}))
    if what == "encode_scene":
        return model.encode_scene(**edit(dict(context_tokens=tokens, context_poses=poses)))
    scene = model.encode_scene(tokens, poses)
    if what == "render_scene":
        return model.render_scene(scene, **edit(dict(query_poses=poses[:, :2])))
    if what == "localize_scene":
        return model.localize_scene(scene, **edit(dict(query_tokens=tokens[:, :2])))
    other = pyvf.Transformer(pyvf.TransformerConfig(**TINY), seed=1)
    return other.render_scene(scene, poses[:, :2])  # "scene": another model's


def _set(name, f):
    return lambda kw: {**kw, name: f(kw.get(name))}


GRAD = (2, 5, 16, 64)
REFUSALS = [
    ("forward", _set("tokens", lambda t: np.where(t == t.max(), 64, t)), ValueError, "tokens"),
    ("forward", _set("tokens", lambda t: t.astype(np.float32)), TypeError, "tokens"),
    ("forward", _set("tokens", lambda t: t[0]), ValueError, "tokens"),
    ("forward", lambda kw: dict(tokens=kw["tokens"][:, :1], poses=kw["poses"][:, :1]), ValueError, "tokens"),  # no target
    ("forward", _set("poses", lambda p: p[..., :6]), ValueError, "poses"),
    ("forward", _set("poses", lambda p: p.astype(np.float64)), TypeError, "poses"),
    ("forward", _set("poses", lambda p: np.full_like(p, np.nan)), ValueError, "poses"),
    ("backward", lambda kw: dict(dlogits=np.ones(GRAD)), TypeError, "dlogits"),  # float64 for a float32 model
    ("backward", lambda kw: dict(dlogits=np.ones(GRAD[:3] + (63,), np.float32)), ValueError, "dlogits"),
    ("backward", lambda kw: dict(dlogits=np.full(GRAD, np.nan, np.float32)), ValueError, "dlogits"),
    ("backward", lambda kw: dict(dpose=np.ones(GRAD[:3] + (6,), np.float32)), ValueError, "dpose"),
    ("backward", lambda kw: dict(dloss=float("inf")), ValueError, "dloss"),
    ("backward", lambda kw: dict(dloss="1"), TypeError, "dloss"),
    ("encode_scene", _set("context_tokens", lambda t: t + 64), ValueError, "context_tokens"),
    ("encode_scene", _set("context_poses", lambda p: 2 * p), ValueError, "context_poses"),  # not unit quaternions
    ("render_scene", _set("query_poses", lambda p: p[:1]), ValueError, "query_poses"),  # another B
    ("render_scene", _set("query_poses", lambda p: np.full_like(p, np.inf)), ValueError, "query_poses"),
    ("localize_scene", _set("query_tokens", lambda t: t[..., :4]), ValueError, "query_tokens"),  # another L
    ("localize_scene", _set("query_tokens", lambda t: t.astype(float)), TypeError, "query_tokens"),
    ("other model", None, ValueError, "scene"),
]


@pytest.mark.parametrize("what, edit, error, name", REFUSALS)
def test_entry_point_refusals(rng, what, edit, error, name):
    with pytest.raises(error, match=rf"\b{name}\b"):
        _call(rng, what, edit)


def test_backward_needs_a_forward():
    with pytest.raises(RuntimeError, match=r"forward"):
        pyvf.Transformer(pyvf.TransformerConfig(**TINY)).backward()


def _without(weights, name):
    weights = dict(weights)
    weights.pop(name)
    return weights


@pytest.mark.parametrize("edit, error, name", [
    (lambda w: _without(w, "migt/h.1/mlp/c_fc/bias:0"), ValueError, "h.1/mlp/c_fc/bias"),  # missing
    (lambda w: {**w, "migt/h.2/ln_1/gamma:0": np.ones(32, np.float32)}, ValueError, "h.2/ln_1/gamma"),  # unexpected
    (lambda w: {**w, "migt/h.0/attn/c_attn/weight:0": np.zeros((96, 32), np.float32)}, ValueError,
     "h.0/attn/c_attn/weight"),  # transposed
    (lambda w: {**w, "migt/ln_f/gamma:0": np.ones(32, np.int32)}, TypeError, "ln_f/gamma"),
    (lambda w: {**w, "migt/ln_f/gamma:0": np.full(32, np.nan, np.float32)}, ValueError, "ln_f/gamma"),
    (lambda w: {**w, "ln_f/gamma": np.ones(32, np.float32)}, ValueError, "ln_f/gamma"),  # given twice
    (lambda w: {**w, "migt/ln_f/gamma:0": np.full(32, 1e39)}, ValueError, "ln_f/gamma"),  # inf in float32
    (lambda w: dict(weights=w, layout="Torch"), ValueError, "layout"),
])
def test_load_official_refusals_name_the_weight(rng, edit, error, name):
    weights, spec_cfg = official_weights(rng)
    model = pyvf.Transformer(pyvf.TransformerConfig(**spec_cfg))
    args = edit(weights)
    with pytest.raises(error, match=name):
        model.load_official(**args) if "layout" in args else model.load_official(args)


@pytest.mark.parametrize("field, value, error", [
    ("d_model", 33, ValueError),  # not divisible by n_head
    ("token_image_size", 17, ValueError),  # 289 tokens per view, wpe has 256
    ("n_loss_skip", -1, ValueError),
    ("dtype", "float16", ValueError),
    ("label_smoothing", 1.0, ValueError),
    ("label_smoothing", float("nan"), ValueError),
    ("n_head", 0, ValueError),
    ("n_head", 2.0, TypeError),
    ("pose_multiplier", 0.0, ValueError),  # predictions are divided by it
    ("attention_scale", [1.0], TypeError),
    ("sign_invariant_pose", 1, TypeError),  # a bool, as JSON writes it
])
def test_config_refusals(field, value, error):
    with pytest.raises(error, match=rf"\b{field}\b"):
        pyvf.TransformerConfig(**{**TINY, field: value})


# ---------------------------------------------------------------------------------------
# 5. the TensorFlow checkpoint converter (pyvf convert tf-transformer), with a stand-in for tf.train.load_checkpoint


class FakeReader:
    def __init__(self, tensors):
        self.tensors = tensors

    def get_variable_to_shape_map(self):
        return {k: list(v.shape) for k, v in self.tensors.items()}

    def get_tensor(self, key):
        return self.tensors[key]


@pytest.mark.parametrize("style", ["name", "object"])
def test_tf_converter_maps_checkpoint_keys(style, rng, tmp_path):
    weights, spec_cfg = official_weights(rng)
    suffix = "/.ATTRIBUTES/VARIABLE_VALUE" if style == "object" else ""
    tensors = {n[:-2] + suffix: w for n, w in weights.items()}  # "migt/...:0" -> checkpoint keys
    tensors["save_counter" + suffix] = np.array(1)
    tensors["migt/h.0/ln_1/gamma/.OPTIMIZER_SLOT/optimizer/m" + suffix] = np.ones(32, np.float32)
    cfg = pyvf.TransformerConfig(**spec_cfg)
    got, skipped = convert_tf.convert(FakeReader(tensors), cfg)
    assert len(skipped) == 2 and set(got) == set(pyvf.models.transformer.parameter_shapes(cfg))
    for name, w in weights.items():
        assert np.array_equal(got[name[len("migt/"):-2]], w)
    del tensors["migt/wte/weight" + suffix]
    with pytest.raises(ValueError, match="1 weights not found"):
        convert_tf.convert(FakeReader(tensors), cfg)


# ---------------------------------------------------------------------------------------
# 6. buffers changed between forward() and backward(); a loss past the dtype's range


SMALL = dict(n_embeddings=16, n_head=2, d_model=8, n_layer=1, token_image_size=2, sequence_size=3, n_loss_skip=1)


def small_model(dtype="float64", **cfg):
    return pyvf.Transformer(pyvf.TransformerConfig(**{**SMALL, **cfg}, dtype=dtype), seed=0)


def assert_same_grads(got, want):
    assert got.keys() == want.keys()
    for name in want:
        assert_bitwise_equal(name, got[name], want[name])


@pytest.mark.parametrize("B, skip", [(1, 1), (2, 0)])
def test_backward_ignores_arrays_changed_after_forward(rng, B, skip):
    """The caller's tokens and poses (a data loader refilling its buffers) and the outputs
    (out.logits, a view of the loss's logits when B = 1 or n_loss_skip = 0) changed in place
    between forward() and backward() change nothing: the oracle is the same forward and backward
    on arrays nobody touched, bitwise."""
    m = small_model(n_loss_skip=skip)
    tokens, poses = random_batch(rng, B, 3, 4, 16)
    m.forward(tokens.copy(), poses.copy())
    want = m.backward()
    out = m.forward(tokens, poses)
    tokens[...] = (tokens + 1) % SMALL["n_embeddings"]
    poses[...] = poses[::-1]
    for a in (out.logits, out.pose_raw, out.pose_prediction, out.ce_loss, out.pose_loss):
        a *= 2
    assert_same_grads(m.backward(), want)
