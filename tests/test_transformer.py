"""The whole transformer: against a torch model written independently (tests/torch_transformer.py),
finite differences, the tree's defining property, cached inference, training, weights and bad input."""

import dataclasses
import json
import os

import numpy as np
import pytest
import torch

import pyvf
from conftest import assert_bitwise_equal, assert_close
from pyvf.models.transformer import pose_prediction
from pyvf.nn import attention, layers, losses
from pyvf.verify import convert_tf, torch_transformer

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


def torch_run(model, tokens, poses):
    P = {k: torch.tensor(v, requires_grad=True) for k, v in model.params.items()}
    logits, raw, ce, pl, loss = torch_transformer.forward(P, torch.tensor(tokens), torch.tensor(poses), model.config)
    loss.backward()
    return logits.detach().numpy(), raw.detach().numpy(), ce.detach().numpy(), pl.detach().numpy(), \
        loss.item(), {k: t.grad.numpy() for k, t in P.items()}


# ---------------------------------------------------------------------------------------
# 1. against torch, float64


CONFIGS = {
    "tiny": {},
    "weights": dict(pose_multiplier=0.2, localization_weight=5.0, image_generation_weight=0.7, label_smoothing=0.1),
    "scaled": dict(attention_scale=1 / 4, n_loss_skip=2, n_layer=3, n_head=4),
    "no_skip": dict(n_loss_skip=0, n_head=1, d_model=24),
}


@pytest.mark.parametrize("variant", CONFIGS)
def test_model_matches_torch_float64(variant, rng):
    cfg = pyvf.TransformerConfig(**{**TINY, **CONFIGS[variant]}, dtype="float64")
    model = random_model(cfg, rng)
    tokens, poses = random_batch(rng, 2, 5, 16, cfg.n_embeddings)
    out = model.forward(tokens, poses)
    grads = model.backward()
    logits, raw, ce, pl, loss, tgrads = torch_run(model, tokens, poses)
    # float64 through ~40 roundings per path: measured <= 2e-14 relative; 1e-12 leaves room
    assert_close("logits", out.logits, logits, rtol=1e-12)
    assert_close("ce", out.ce_loss, ce, rtol=1e-12)
    assert_close("pose loss", out.pose_loss, pl, rtol=1e-12)
    assert abs(out.loss - loss) <= 1e-12 * abs(loss)
    # the prediction from torch's raw head output, written out here (not pyvf's pose_prediction):
    # xyz / pose_multiplier, the quaternion over its norm, its sign flipped where w < 0
    raw = np.asarray(raw, dtype=np.float64)
    q = raw[..., 3:] / np.linalg.norm(raw[..., 3:], axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0, -q, q)
    pred = np.concatenate([raw[..., :3] / cfg.pose_multiplier, q], axis=-1)
    assert_close("pose prediction", out.pose_prediction, pred, rtol=1e-12)
    assert set(grads) == set(tgrads) == set(model.params)
    for name in grads:
        assert_close(f"d{name}", grads[name], tgrads[name], rtol=1e-11)


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
    got = pyvf.models.transformer.pose_prediction(raw, pose_multiplier=0.2)
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
# 2. finite differences of the loss


def test_finite_differences_of_the_loss(rng):
    cfg = pyvf.TransformerConfig(n_embeddings=16, n_head=2, d_model=8, n_layer=2, token_image_size=2,
                                 sequence_size=3, n_loss_skip=1, pose_multiplier=0.5, label_smoothing=0.1,
                                 dtype="float64")
    model = random_model(cfg, rng, spread=0.5)
    tokens, poses = random_batch(rng, 2, 3, 4, cfg.n_embeddings)
    model.forward(tokens, poses)
    grads = model.backward()
    base = {k: v.copy() for k, v in model.params.items()}
    h = 1e-5  # central differences: truncation ~h^2 |f'''| ~ 1e-10, rounding ~eps/h ~ 1e-11
    for name in base:
        u = rng.standard_normal(base[name].shape)  # a random direction per parameter
        vals = []
        for sign in (1, -1):
            model.params[name] = base[name] + sign * h * u
            vals.append(model.forward(tokens, poses).loss)
        model.params[name] = base[name]
        numeric = (vals[0] - vals[1]) / (2 * h)
        analytic = float((grads[name] * u).sum())
        assert abs(numeric - analytic) <= 1e-7 * max(1.0, abs(analytic)), (name, numeric, analytic)


# ---------------------------------------------------------------------------------------
# 3. the tree's defining property, at the whole-model level


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


def test_outputs_at_view_i_ignore_later_views(rng):
    cfg = pyvf.TransformerConfig(**TINY, dtype="float64")
    model = random_model(cfg, rng)
    tokens, poses = random_batch(rng, 2, 5, 16, cfg.n_embeddings)
    out = model.forward(tokens, poses)
    for i in range(4):
        t2, p2 = tokens.copy(), poses.copy()
        t2[:, i + 1:] = rng.integers(0, cfg.n_embeddings, t2[:, i + 1:].shape)
        p2[:, i + 1:] += 1.0
        out2 = model.forward(t2, p2)
        assert_bitwise_equal(f"logits at views <= {i}", out2.logits[:, :i + 1], out.logits[:, :i + 1])
        assert_bitwise_equal(f"poses at views <= {i}", out2.pose_prediction[:, :i + 1],
                             out.pose_prediction[:, :i + 1])
        assert not np.array_equal(out2.logits[:, i + 1:], out.logits[:, i + 1:])  # the change did reach


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
# 4. cached inference (against the whole tree: tests/test_scene_cache.py)


def test_render_and_localize_are_the_scene_paths(rng):
    """render / localize (one call) are encode_scene then render_scene / localize_scene, bitwise."""
    cfg = pyvf.TransformerConfig(**{**TINY, "pose_multiplier": 0.5}, dtype="float64")
    model = random_model(cfg, rng)
    ctx_tokens, ctx_poses = random_batch(rng, 2, 4, 16, cfg.n_embeddings)
    q_tokens, q_poses = random_batch(rng, 2, 3, 16, cfg.n_embeddings)
    scene = model.encode_scene(ctx_tokens, ctx_poses)
    assert_bitwise_equal("render", model.render(ctx_tokens, ctx_poses, q_poses), model.render_scene(scene, q_poses))
    assert_bitwise_equal("localize", model.localize(ctx_tokens, ctx_poses, q_tokens),
                         model.localize_scene(scene, q_tokens))


# ---------------------------------------------------------------------------------------
# 5. training


def test_tiny_model_overfits_a_fixed_batch(rng):
    cfg = pyvf.TransformerConfig(**TINY)
    model = pyvf.Transformer(cfg, seed=0)
    tokens, poses = random_batch(rng, 4, 5, 16, cfg.n_embeddings, dtype=np.float32)
    opt = pyvf.AdamW(model.params, lr=1e-2, weight_decay=0.0)
    losses = [pyvf.train_step(model, opt, tokens, poses, max_grad_norm=1.0)[0] for _ in range(100)]
    assert np.isfinite(losses).all()
    assert losses[-1] <= 0.1 * losses[0], f"loss fell from {losses[0]} to {losses[-1]} only"


def test_train_step_per_tensor_clipping_and_schedule(rng):
    cfg = pyvf.TransformerConfig(**TINY)
    model = pyvf.Transformer(cfg, seed=0)
    tokens, poses = random_batch(rng, 2, 5, 16, cfg.n_embeddings, dtype=np.float32)
    opt = pyvf.AdamW(model.params, lr=pyvf.WarmupCosine(1e-3, 2, 10), decay=pyvf.published_weight_decay)
    before = {k: v.copy() for k, v in model.params.items()}
    loss, norms = pyvf.train_step(model, opt, tokens, poses, max_grad_norm=0.1, clip_mode="per_tensor")
    assert np.isfinite(loss) and isinstance(norms, dict) and set(norms) == set(model.params)
    assert all(np.array_equal(before[k], model.params[k]) for k in before)  # warmup: lr(0) = 0
    pyvf.train_step(model, opt, tokens, poses)
    assert not np.array_equal(before["wte/weight"], model.params["wte/weight"])
    with pytest.raises(ValueError, match="optimizer must be built on model.params"):
        pyvf.train_step(model, pyvf.AdamW({k: v.copy() for k, v in model.params.items()}), tokens, poses)


# ---------------------------------------------------------------------------------------
# 6. weights


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
        got = state[pyvf.models.transformer.official_name(name)]
        assert got.dtype == np.float64 and np.array_equal(got, arr.astype(np.float64))
    model2 = pyvf.Transformer(cfg)
    model2.load_official(state)  # plain names load too
    tokens, poses = random_batch(rng, 1, 5, 16, cfg.n_embeddings)
    assert_bitwise_equal("same weights, same logits", model2.forward(tokens, poses).logits,
                         model.forward(tokens, poses).logits)


def test_load_official_refuses_float64_values_beyond_float32(rng):
    """A float64 checkpoint into a float32 model: a value past float32's largest (3.4028e38)
    would become inf (numpy only warns). Refused with every such parameter named, and nothing
    loaded; the largest float32 value itself loads exactly, and a float64 model takes 1e39."""
    cfg = pyvf.TransformerConfig(**TINY)
    model = random_model(cfg, rng)
    before = model.state_dict()
    weights = {k: v.astype(np.float64) for k, v in before.items()}
    weights["wte/weight"][0, 0] = 1e39
    weights["h.1/mlp/c_proj/bias"][0, 3] = -2e300
    with pytest.raises(ValueError, match=r"load_official: 2 problems: 'wte/weight' holds a value of magnitude "
                                         r"1e\+39, beyond float32's range.*'h.1/mlp/c_proj/bias' .* 2e\+300"):
        model.load_official(weights)
    for name, p in before.items():  # nothing assigned
        assert_bitwise_equal(name, model.params[name], p)
    edge = float(np.finfo(np.float32).max)
    weights["wte/weight"][0, 0], weights["h.1/mlp/c_proj/bias"][0, 3] = edge, -edge
    model.load_official(weights)
    assert model.params["wte/weight"][0, 0] == np.float32(edge)
    assert model.params["h.1/mlp/c_proj/bias"][0, 3] == -np.float32(edge)
    weights["wte/weight"][0, 0] = 1e39
    model64 = pyvf.Transformer(dataclasses.replace(cfg, dtype="float64"))
    model64.load_official(weights)
    assert model64.params["wte/weight"][0, 0] == 1e39


def test_save_and_load_round_trip(tmp_path, rng):
    cfg = pyvf.TransformerConfig(**{**TINY, "label_smoothing": 0.1}, dtype="float64")
    model = random_model(cfg, rng)
    path = tmp_path / "model.npz"
    model.save(path)
    loaded = pyvf.Transformer.load(path)
    assert loaded.config == cfg
    for name, p in model.params.items():
        assert_bitwise_equal(name, loaded.params[name], p)


# ---------------------------------------------------------------------------------------
# 7. refusals: one table per entry point, the exception type and the argument's name


def _forward_args(rng):
    cfg = pyvf.TransformerConfig(**TINY)
    return pyvf.Transformer(cfg), *random_batch(rng, 2, 5, 16, cfg.n_embeddings, dtype=np.float32)


@pytest.mark.parametrize("edit, error, name", [
    (lambda t, p: (np.where(t == t.max(), 64, t), p), ValueError, "tokens"),
    (lambda t, p: (t - 1, p), ValueError, "tokens"),
    (lambda t, p: (t.astype(np.float32), p), TypeError, "tokens"),
    (lambda t, p: (t[0], p), ValueError, "tokens"),
    (lambda t, p: (t.tolist(), p), TypeError, "tokens"),
    (lambda t, p: (t[:, :1], p[:, :1]), ValueError, "tokens"),  # one view: no view is a loss target
    (lambda t, p: (np.zeros((1, 2, 257), np.int64), p[:1, :2]), ValueError, "tokens"),  # past wpe's rows
    (lambda t, p: (t, p[..., :6]), ValueError, "poses"),
    (lambda t, p: (t, p.astype(np.float64)), TypeError, "poses"),
    (lambda t, p: (t, np.where(np.arange(7) == 2, np.inf, p).astype(np.float32)), ValueError, "poses"),
    (lambda t, p: (t, np.full_like(p, np.nan)), ValueError, "poses"),
])
def test_forward_refusals(rng, edit, error, name):
    model, tokens, poses = _forward_args(rng)
    with pytest.raises(error, match=rf"\b{name}\b"):
        model.forward(*edit(tokens, poses))


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
])
def test_load_official_refusals_name_the_weight(rng, edit, error, name):
    weights, spec_cfg = official_weights(rng)
    model = pyvf.Transformer(pyvf.TransformerConfig(**spec_cfg))
    with pytest.raises(error, match=name):
        model.load_official(edit(weights))


@pytest.mark.parametrize("field, value, error", [
    ("d_model", 33, ValueError),  # not divisible by n_head
    ("token_image_size", 17, ValueError),  # 289 tokens per view, wpe has 256
    ("n_loss_skip", -1, ValueError),
    ("dtype", "float16", ValueError),
    ("label_smoothing", 1.0, ValueError),
    ("label_smoothing", float("nan"), ValueError),
    ("label_smoothing", None, TypeError),
    ("n_head", 0, ValueError),
    ("n_head", np.int64(0), ValueError),
    ("n_head", True, TypeError),
    ("n_head", 2.0, TypeError),
    ("n_loss_skip", "1", TypeError),
    # positions are multiplied by pose_multiplier and predictions divided by it (docs/math.md §3):
    # 0, or a magnitude that is 0 or subnormal in the dtype (its reciprocal overflows), gave inf poses
    ("pose_multiplier", 0.0, ValueError),
    ("pose_multiplier", -0.0, ValueError),
    ("pose_multiplier", 1e-40, ValueError),
    ("pose_multiplier", 1e39, ValueError),
    ("pose_multiplier", float("nan"), ValueError),
    ("pose_multiplier", "a", TypeError),
    ("attention_scale", [1.0], TypeError),
    ("localization_weight", True, TypeError),
])
def test_config_refusals(field, value, error):
    with pytest.raises(error, match=rf"\b{field}\b"):
        pyvf.TransformerConfig(**{**TINY, field: value})


def test_config_takes_numpy_scalars_as_python_numbers(tmp_path):
    """NumPy integers (not bool) are integers, as everywhere in pyvf (_checks.integer): the
    configuration equals the one of Python numbers and holds Python numbers, so a model saves
    (its configuration is JSON) and loads back."""
    fields = {k: np.int64(v) if k != "n_head" else np.int32(v) for k, v in TINY.items()}
    cfg = pyvf.TransformerConfig(**fields, pose_multiplier=np.float32(0.5), label_smoothing=np.float64(0.1))
    assert cfg == pyvf.TransformerConfig(**TINY, pose_multiplier=0.5, label_smoothing=0.1)
    assert all(type(getattr(cfg, k)) is int for k in TINY)
    assert type(cfg.pose_multiplier) is float and type(cfg.label_smoothing) is float
    path = pyvf.Transformer(cfg).save(tmp_path / "m.npz")
    assert pyvf.Transformer.load(path).config == cfg
    # the subnormal bound is the dtype's: 1e-40 is a normal float64
    assert pyvf.TransformerConfig(**TINY, pose_multiplier=1e-40, dtype="float64").pose_multiplier == 1e-40


def test_negative_pose_multiplier_mirrors_positions_consistently(rng):
    """A negative pose_multiplier is allowed: it mirrors the positions the model sees and
    predicts alike. The model with -m, its pose MLP's xyz input rows and its pose head's xyz
    output columns negated, computes the same loss and the same pose predictions (xyz_raw / m)
    as the model with +m: every negation is exact, so bitwise."""
    cfg = pyvf.TransformerConfig(**TINY, pose_multiplier=0.2, dtype="float64")
    model = random_model(cfg, rng)
    mirror = pyvf.Transformer(dataclasses.replace(cfg, pose_multiplier=-0.2))
    mirror.params = {k: v.copy() for k, v in model.params.items()}
    mirror.params["pose_embedding/c_fc/weight"][:3] *= -1  # rows of xyz * pose_multiplier
    head = "quaternion_pose_representation/pose_classifier/c_proj/"
    mirror.params[head + "weight"][:, :3] *= -1  # columns of xyz_raw
    mirror.params[head + "bias"][:, :3] *= -1
    tokens, poses = random_batch(rng, 2, 5, 16, cfg.n_embeddings)
    want, got = model.forward(tokens, poses), mirror.forward(tokens, poses)
    assert got.loss == want.loss
    assert_bitwise_equal("pose_prediction", got.pose_prediction, want.pose_prediction)
    assert_bitwise_equal("pose_raw xyz mirrored", got.pose_raw[..., :3], -want.pose_raw[..., :3])


# ---------------------------------------------------------------------------------------
# 8. the TensorFlow checkpoint converter (pyvf convert tf-transformer), with a stand-in for tf.train.load_checkpoint


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
        assert np.array_equal(got[pyvf.models.transformer.official_name(name)], w)
    del tensors["migt/wte/weight" + suffix]
    with pytest.raises(ValueError, match="1 weights not found"):
        convert_tf.convert(FakeReader(tensors), cfg)


# ---------------------------------------------------------------------------------------
# 8. what a demanding user tries: buffers changed between forward() and backward(), losses, seeds
# and pose multipliers past the dtype's range


SMALL = dict(n_embeddings=16, n_head=2, d_model=8, n_layer=1, token_image_size=2, sequence_size=3, n_loss_skip=1)


def small_batch(rng, B, N, dtype, L=4, V=16):
    return random_batch(rng, B, N, L, V, dtype)


def small_model(dtype="float64", **cfg):
    return pyvf.Transformer(pyvf.TransformerConfig(**{**SMALL, **cfg}, dtype=dtype), seed=0)


def assert_same_grads(got, want):
    assert got.keys() == want.keys()
    for name in want:
        assert_bitwise_equal(name, got[name], want[name])


@pytest.mark.parametrize("B", [1, 2])
def test_backward_ignores_inputs_changed_after_forward(rng, B):
    """The forward kept the caller's tokens array itself (the embedding's scatter ids, and the
    cross-entropy's targets when they were a view): a data loader refilling its buffer before
    backward() moved the wte gradient to the new batch's rows, silently (max |diff| 1.2 on a
    tiny model). The oracle: the same forward and backward on arrays nobody touched, bitwise."""
    m = small_model()
    tokens, poses = small_batch(rng, B, 3, np.float64)
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
    m = small_model(n_loss_skip=skip)
    tokens, poses = small_batch(rng, B, 3, np.float64)
    m.forward(tokens, poses)
    want = m.backward()
    out = m.forward(tokens, poses)
    for a in (out.logits, out.pose_raw, out.pose_prediction, out.ce_loss, out.pose_loss):
        a *= 2
    assert_same_grads(m.backward(), want)


def test_loss_that_overflows_raises_and_keeps_the_last_forward(rng):
    """A float32 loss weight that makes each batch element's weighted loss 0.75 of float32's
    largest value: the batch mean fits, the sum NumPy's mean takes first does not, and out.loss
    came back inf, silently (a RuntimeWarning at most), while backward() gave finite gradients
    of that inf. Now a ValueError naming the loss; the failed forward leaves what backward()
    differentiates unchanged (bitwise)."""
    tokens, poses = small_batch(rng, 1, 3, np.float32)
    pl = float(small_model("float32").forward(tokens, poses).pose_loss[0])
    m = small_model("float32", localization_weight=0.75 * float(np.finfo(np.float32).max) / pl)  # same seed, same weights
    m.forward(tokens, poses)  # one element: its weighted loss fits float32
    want = m.backward()
    with pytest.raises(ValueError, match=r"\bloss\b"):
        m.forward(np.concatenate([tokens, tokens]), np.concatenate([poses, poses]))  # the sum of two does not
    assert_same_grads(m.backward(), want)


@pytest.mark.parametrize("dloss", [1e40, -1e300])
def test_backward_seed_beyond_the_dtype_is_named(rng, dloss):
    """backward(dloss=1e40) on a float32 model said "dloss contains NaN or inf" (and NumPy
    warned of an overflowing cast): dloss is finite; it is the per-token seed dloss / (B N L)
    that float32 cannot hold. The error now says so, and the model is left as it was."""
    m = small_model("float32")
    tokens, poses = small_batch(rng, 2, 3, np.float32)
    m.forward(tokens, poses)
    want = m.backward()
    with pytest.raises(ValueError, match=r"\bdloss\b") as e:
        m.backward(dloss=dloss)
    assert "NaN" not in str(e.value)
    assert_same_grads(m.backward(), want)


@pytest.mark.parametrize("raw, pm, exc, name", [
    (np.ones((2, 7), np.int64), 1.0, TypeError, "raw"),
    (np.full((2, 7), np.nan, np.float32), 1.0, ValueError, "raw"),
    ([[1.0] * 7], 1.0, TypeError, "raw"),
    (np.ones((2, 6)), 1.0, ValueError, "raw"),
    (np.ones((2, 7), np.float32), 0.0, ValueError, "pose_multiplier"),
    (np.ones((2, 7), np.float32), 1e-40, ValueError, "pose_multiplier"),  # 0 in float32
    (np.ones((2, 7), np.float32), "0.2", TypeError, "pose_multiplier"),
    (np.full((2, 7), 1e30, np.float32), 1e-10, ValueError, "pose_prediction"),  # the quotient overflows
])
def test_pose_prediction_bad_input_is_named(raw, pm, exc, name):
    """pose_prediction blamed `q`, the quaternion helper's argument, for a raw of the wrong dtype
    or with NaN; pose_multiplier = 0 (or one float32 holds as 0) and a quotient past float32's
    range returned inf poses, silently."""
    with np.errstate(all="raise"):  # no division by zero or overflow reaches NumPy any more
        with pytest.raises(exc, match=rf"\b{name}\b"):
            pose_prediction(raw, pm)


def test_pose_loss_multiplier_beyond_the_dtype_is_named():
    """pose_multiplier = 1e39 is finite but not a float32: it became inf, and inf * 0 NaN, so a
    zero target (whose loss is mean(raw^2), finite) raised "the loss is not finite: it
    overflowed float32", blaming the loss for the argument."""
    raw, target = np.ones((2, 7), np.float32), np.zeros((2, 7), np.float32)
    with pytest.raises(ValueError, match=r"\bpose_multiplier\b"):
        losses.pose_loss_forward(raw, target, 1e39)
    # the bound is the dtype's: the same multiplier is a float64
    loss, _ = losses.pose_loss_forward(raw.astype(np.float64), target.astype(np.float64), 1e39)
    np.testing.assert_array_equal(loss, np.full(2, 2.0))  # 3/3 + 4/4: exact


@pytest.mark.parametrize("ids, rows, exc, name", [
    (np.array([0, 1]), np.ones((3, 2)), ValueError, "rows"),
    (np.array([0, 1, 1]), np.ones((2, 2)), ValueError, "rows"),
])
def test_sum_rows_by_id_refuses_ids_and_rows_of_other_lengths(ids, rows, exc, name):
    """ids shorter than rows dropped the rows past them from the sum, silently ([[1, 1], [1, 1]]
    for three rows of ones on ids [0, 1])."""
    with pytest.raises(exc, match=rf"\b{name}\b"):
        layers.sum_rows_by_id(ids, rows, 2)


@pytest.mark.parametrize("n_head", [2.0, "2", True])
def test_attention_n_head_of_the_wrong_type_is_a_type_error(rng, n_head):
    """n_head = 2.0 raised ValueError "must be a positive integer": a wrong type is a TypeError
    throughout pyvf (_checks.positive_integer; TransformerConfig.n_head says so)."""
    x = rng.normal(size=(2, 1, 2, 3, 4))
    w_attn, b_attn = rng.normal(size=(4, 12)), np.zeros((1, 12))
    w_proj, b_proj = rng.normal(size=(4, 4)), np.zeros((1, 4))
    with pytest.raises(TypeError, match=r"\bn_head\b"):
        attention.attention_layer_forward(x, w_attn, b_attn, w_proj, b_proj, n_head)
