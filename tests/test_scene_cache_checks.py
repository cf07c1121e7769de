"""The inference entry points (encode_scene, render_scene, localize_scene, render, localize) refuse
what would give a silently wrong answer, and name the argument at fault.

* A scene is the trunk of one model's weights: used with another model (other weights, other
  layers, another dtype) or after the model's parameters were replaced (load_official), the
  query blocks would attend keys and values of other weights and return a wrong answer
  silently (or an IndexError deep inside). Such a scene is refused; a model holding the very
  same parameter arrays and configuration is the same function and may use it.
* Errors of the context and the queries name context_tokens, context_poses, query_poses.

The oracle of the results is the whole tree's forward over [context views, query]
(docs/math.md §3), never the cached path itself.
"""

import dataclasses

import numpy as np
import pytest

import pyvf
from conftest import assert_close

TINY = dict(n_embeddings=64, n_head=2, d_model=32, n_layer=2, token_image_size=4, sequence_size=5,
            n_loss_skip=1, pose_multiplier=0.5)


def model(seed, dtype="float64", **overrides):
    """A model with random parameters everywhere (gamma != 1, biases != 0)."""
    m = pyvf.Transformer(pyvf.TransformerConfig(**{**TINY, **overrides}, dtype=dtype), seed=seed)
    rng = np.random.default_rng(seed)
    for name, p in m.params.items():
        m.params[name] = (p + rng.normal(0, 0.3, p.shape)).astype(m.dtype)
    return m


def views(seed, B, N, dtype="float64"):
    rng = np.random.default_rng(seed)
    poses = rng.normal(size=(B, N, 7))
    poses[..., 3:] /= np.linalg.norm(poses[..., 3:], axis=-1, keepdims=True)
    return rng.integers(0, TINY["n_embeddings"], (B, N, 16)), poses.astype(dtype)


def whole_tree(m, tokens, poses, C):
    """The uncached oracle: forward on [context, query m] for each query, (B, M, L, V), (B, M, 7)."""
    logits, located = [], []
    for q in range(C, tokens.shape[1]):
        rel, ref = pyvf.make_relative(poses[:, [*range(C), q]])
        out = m.forward(tokens[:, [*range(C), q]], rel)
        logits.append(out.logits[:, C])
        located.append(pyvf.absolute_poses(pyvf.average_pose(out.pose_prediction[:, C], axis=1), ref))
    return np.stack(logits, axis=1), np.stack(located, axis=1)


# ---------------------------------------------------------------------------------------
# a scene belongs to the model (and the weights) that encoded it


@pytest.mark.parametrize("other", [dict(seed=5), dict(seed=0, n_layer=1), dict(seed=0, n_layer=3),
                                   dict(seed=0, n_embeddings=32), dict(seed=0, dtype="float32")])
def test_scene_of_another_model_is_refused(other):
    m = model(0)
    tokens, poses = views(1, 2, 5)
    scene = m.encode_scene(tokens[:, :3], poses[:, :3])
    o = model(**other)
    q_poses = poses[:, 3:].astype(o.dtype)
    with pytest.raises(ValueError, match="scene was encoded by another model"):
        o.render_scene(scene, q_poses)
    with pytest.raises(ValueError, match="scene was encoded by another model"):
        o.localize_scene(scene, tokens[:, 3:])


def test_scene_after_load_official_is_refused_and_a_new_one_is_right():
    m, other = model(0), model(7)
    tokens, poses = views(2, 2, 5)
    scene = m.encode_scene(tokens[:, :3], poses[:, :3])
    m.load_official(other.state_dict())  # m now computes other's function; scene holds the old trunk
    with pytest.raises(ValueError, match="scene was encoded by another model"):
        m.render_scene(scene, poses[:, 3:])
    with pytest.raises(ValueError, match="scene was encoded by another model"):
        m.localize_scene(scene, tokens[:, 3:])
    fresh = m.encode_scene(tokens[:, :3], poses[:, :3])
    want_logits, want_poses = whole_tree(m, tokens, poses, 3)
    assert_close("render after reload", m.render_scene(fresh, poses[:, 3:]), want_logits, rtol=1e-12)
    assert_close("localize after reload", m.localize_scene(fresh, tokens[:, 3:]), want_poses, rtol=1e-12)


def test_scene_is_usable_by_a_model_sharing_its_parameters():
    """The same arrays and configuration are the same function: nothing to refuse."""
    m = model(3)
    twin = pyvf.Transformer(m.config)
    twin.params = m.params
    tokens, poses = views(4, 1, 4)
    scene = m.encode_scene(tokens[:, :2], poses[:, :2])
    want_logits, want_poses = whole_tree(m, tokens, poses, 2)
    assert_close("render", twin.render_scene(scene, poses[:, 2:]), want_logits, rtol=1e-12)
    assert_close("localize", twin.localize_scene(scene, tokens[:, 2:]), want_poses, rtol=1e-12)
    # and a scene copied field by field (dataclasses.replace) keeps its model
    assert_close("render, replaced", m.render_scene(dataclasses.replace(scene), poses[:, 2:]), want_logits,
                 rtol=1e-12)


@pytest.mark.parametrize("scene", [None, np.zeros((1, 3, 16), np.int64), "scene"])
def test_scene_must_be_a_scene(scene):
    m = model(0)
    tokens, poses = views(1, 1, 4)
    with pytest.raises(TypeError, match="scene must be a Scene"):
        m.render_scene(scene, poses[:, 3:])
    with pytest.raises(TypeError, match="scene must be a Scene"):
        m.localize_scene(scene, tokens[:, 3:])


# ---------------------------------------------------------------------------------------
# errors name the argument at fault


@pytest.mark.parametrize("q", [(2.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), (0.6, 0.6, 0.0, 0.0)])
def test_query_poses_non_unit_quaternion_is_named(q):
    """A zero or unnormalised quaternion raises naming query_poses, not `poses` (an argument the
    user never passed)."""
    m = model(0)
    tokens, poses = views(1, 2, 5)
    scene = m.encode_scene(tokens[:, :3], poses[:, :3])
    bad = poses[:, 3:].copy()
    bad[1, 0, 3:] = q
    for call in (lambda: m.render_scene(scene, bad), lambda: m.render(tokens[:, :3], poses[:, :3], bad)):
        with pytest.raises(ValueError, match=r"quaternions of query_poses must hold unit quaternions.* \(1, 0\)"):
            call()


def test_context_errors_name_the_context_arguments():
    m = model(0)
    tokens, poses = views(1, 2, 5)
    bad = poses[:, :3].copy()
    bad[0, 2, 3:] = (0.0, 0.0, 0.0, 0.0)
    nan = poses[:, :3].copy()
    nan[1, 1, 0] = np.nan
    cases = [
        ((tokens[:, :0], poses[:, :0]), ValueError, "context_tokens has a zero-size dimension"),
        ((tokens[:, :3].astype(np.float64), poses[:, :3]), TypeError, "context_tokens must be an integer"),
        ((tokens[:, :3] + 64, poses[:, :3]), ValueError, r"context_tokens must be in \[0, 64\)"),
        ((tokens[:, :3], poses[:, :3].astype(np.float32)), TypeError, "context_poses must be a float64"),
        ((tokens[:, :3], poses[:, :2]), ValueError, r"context_poses must have shape \(B, N, 7\)"),
        ((tokens[:, :3], nan), ValueError, "context_poses contains NaN"),
        ((tokens[:, :3], bad), ValueError, r"quaternions of context_poses must hold unit quaternions.* \(0, 2\)"),
    ]
    for args, exc, match in cases:
        with pytest.raises(exc, match=match):
            m.encode_scene(*args)
        with pytest.raises(exc, match=match):
            m.localize(*args, tokens[:, 3:])


def test_zero_queries_say_so():
    m = model(0)
    tokens, poses = views(1, 2, 5)
    scene = m.encode_scene(tokens[:, :3], poses[:, :3])
    with pytest.raises(ValueError, match=r"query_poses must have shape \(B=2, M >= 1, 7\)"):
        m.render_scene(scene, poses[:, 3:3])
    with pytest.raises(ValueError, match=r"query_tokens must have shape \(B=2, M >= 1, L=16\)"):
        m.localize_scene(scene, tokens[:, 3:3])


def test_forward_keeps_its_argument_names():
    """The training forward's messages are unchanged (tests/test_transformer.py relies on them)."""
    m = model(0)
    tokens, poses = views(1, 2, 5)
    with pytest.raises(TypeError, match="^tokens must be an integer"):
        m.forward(tokens.astype(np.float64), poses)
    with pytest.raises(TypeError, match="^poses must be a float64"):
        m.forward(tokens, poses.astype(np.float32))


# ---------------------------------------------------------------------------------------
# pyvf.evaluate.demo


def test_report_takes_one_context_size_as_evaluate_does(monkeypatch, tmp_path, capsys):
    """evaluate(context=3) means (3,); report (and demo) printed `', '.join(map(str, 3))` first: a
    TypeError "'int' object is not iterable" naming nothing. The evaluation itself is stubbed:
    it records its context and stops (report's status 1 path)."""
    from pyvf.evaluate import demo

    seen = []

    def stub(codebook, transformer, *, context, **kwargs):
        seen.append(context)
        raise ValueError("stub: stopped after the arguments")

    monkeypatch.setattr(demo, "evaluate", stub)
    assert demo.report("demo", out=str(tmp_path / "out"), scenes=1, context=3, seed=0, progress=False) == 1
    assert seen == [3]
    assert "context 3 ..." in capsys.readouterr().out


def test_localize_says_when_the_model_predicts_no_rotation():
    """A pose head whose quaternion outputs are zero (the whole tree's forward predicts the zero
    quaternion: the oracle) leaves no rotation to return. localize_scene said so as "the
    quaternions of rel must hold unit quaternions ... normalise it first", naming an argument
    the user never passed and a remedy that does not apply."""
    m = model(0)
    head = "quaternion_pose_representation/pose_classifier/"
    m.params[head + "c_proj/weight"][:, 3:] = 0
    m.params[head + "c_proj/bias"][:, 3:] = 0
    tokens, poses = views(1, 2, 5)
    rel, _ = pyvf.make_relative(poses[:, :4])
    assert not m.forward(tokens[:, :4], rel).pose_prediction[:, 3, :, 3:].any()  # the oracle: zero quaternions
    scene = m.encode_scene(tokens[:, :3], poses[:, :3])
    with pytest.raises(ValueError, match=r"localize_scene: query 0 of scene 0: the model's pose predictions "
                                         r"average to no rotation"):
        m.localize_scene(scene, tokens[:, 3:])
