"""The training loops called from Python with hard inputs (pyvf/train/loops.py): a bad pose or
held-out set raises naming the argument before any step runs (not many steps in, with an
internal name); every error names the public argument; numpy integers are accepted where the
checks accept them; a held-out set that is not evaluated on is not part of the run.

Tiny models and a handful of steps, as tests/test_train_loops.py."""

import dataclasses
import json
import os

import numpy as np
import pytest

import pyvf.train.loops as loops
from pyvf.models.codebook import Codebook
from pyvf.train import codebook_batch, tokenize, train_codebook, train_transformer, transformer_batch
from pyvf.train.tasks import compare_runs
from test_train_loops import CB, QUIET, TF, _checkpoint, _images, _log, _poses, _tokens

# 4x4 images -> 2x2 tokens of 16 codes: the held-out set TF reads (as test_train_loops' evaluation)
CB4 = dataclasses.replace(CB, image_size=4, ch_mult=(1, 1), n_embed=16)


def _eval_set(rng, scenes=2, views=7):
    cb = Codebook(CB4, seed=0)
    images, poses = _images(rng, scenes=scenes, views=views, size=4), _poses(rng, scenes=scenes, views=views)
    tokens = tokenize(cb, images).reshape(scenes, views, -1).astype(np.int64)  # (n, V, L)
    return {"codebook": cb, "images": images, "poses": poses, "tokens": tokens}


def _count_steps(monkeypatch):
    """The number of transformer updates the loop runs from here on."""
    calls, real = [], loops.transformer_step

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(loops, "transformer_step", counted)
    return calls


def test_a_non_unit_quaternion_in_poses_raises_before_any_step(tmp_path, rng, monkeypatch):
    """poses' quaternions are checked when the call starts, the error naming poses at its own
    (scene, view): not at the first batch that happens to draw the bad view, many steps (and the
    work since the last checkpoint) later, at an index into that batch."""
    tokens, poses = _tokens(rng, scenes=8), _poses(rng, scenes=8)
    poses[7, 4, 3:] *= 1.01
    steps, out = _count_steps(monkeypatch), str(tmp_path / "run")
    with pytest.raises(ValueError, match=r"quaternions of poses must hold unit quaternions .* at index \(7, 4\)"):
        train_transformer(tokens, poses, TF, out, steps=50, batch_size=1, checkpoint_every=100, **QUIET)
    assert steps == [] and not os.path.exists(out)
    # float16 poses cannot hold a unit quaternion to float32's tolerance: refused as a dtype
    with pytest.raises(TypeError, match="^poses must be float32 or float64, got float16"):
        train_transformer(tokens, _poses(rng, scenes=8).astype(np.float16), TF, out, steps=1, **QUIET)


def test_a_bad_eval_set_raises_naming_it_before_any_step(tmp_path, rng, monkeypatch):
    """Each entry of eval_set is checked when the call starts and named (not as the evaluation's
    internals: context_tokens, target and pred, an AttributeError), before the run folder is
    touched; a resumed run, which does not evaluate at step 0, does not train eval_every steps
    first and then lose them."""
    good = _eval_set(rng)
    tokens, poses = _tokens(rng), _poses(rng)
    other_codes = Codebook(dataclasses.replace(CB4, n_embed=32), seed=0)
    cases = [
        ("codebook", TypeError, {"codebook": "cb.npz"}),
        ("codebook", ValueError, {"codebook": other_codes}),
        ("images", TypeError, {"images": good["images"].astype(np.float32)}),
        ("images", ValueError, {"images": good["images"][:, :, :2]}),
        ("poses", TypeError, {"poses": good["poses"].astype(np.float32)}),
        ("poses", ValueError, {"poses": good["poses"][:1]}),
        ("poses", ValueError, {"poses": good["poses"] * 2}),
        ("tokens", ValueError, {"tokens": good["tokens"].reshape(2, 7, 2, 2)}),
        ("tokens", ValueError, {"tokens": good["tokens"] + 16}),
        ("tokens", TypeError, {"tokens": good["tokens"] * 1.0}),
    ]
    out = str(tmp_path / "fresh")
    for name, exc, change in cases:
        with pytest.raises(exc, match=rf"^eval_set\['{name}'\]"):
            train_transformer(tokens, poses, TF, out, steps=2, batch_size=2, eval_set={**good, **change},
                              eval_every=1, **QUIET)
        assert not os.path.exists(out), name

    resumed = str(tmp_path / "resumed")
    train_transformer(tokens, poses, TF, resumed, steps=2, batch_size=2, total_steps=6, checkpoint_every=10, **QUIET)
    steps = _count_steps(monkeypatch)
    with pytest.raises(TypeError, match=r"^eval_set\['poses'\]"):
        train_transformer(tokens, poses, TF, resumed, steps=6, batch_size=2, total_steps=6, checkpoint_every=10,
                          eval_set={**good, "poses": good["poses"].astype(np.float32)}, eval_every=3, **QUIET)
    assert steps == [] and _checkpoint(resumed)[0]["step"] == 2


def test_eval_images_errors_name_eval_images(tmp_path, rng):
    """train_codebook's held-out images are eval_images in its errors, not images (the training
    data, which is right)."""
    images, out = _images(rng), str(tmp_path / "run")
    for exc, bad in ((TypeError, images.astype(np.float32)), (ValueError, images[..., :2])):
        with pytest.raises(exc, match="^eval_images must"):
            train_codebook(images, CB, out, steps=1, batch_size=2, eval_images=bad, eval_every=1, **QUIET)
    assert not os.path.exists(out)


def test_warmup_past_the_schedule_names_warmup(tmp_path, rng):
    """warmup >= total_steps is train_transformer's warmup, not WarmupCosine's warmup_steps; the
    message says that total_steps is steps when not given."""
    tokens, poses = _tokens(rng), _poses(rng)
    with pytest.raises(ValueError, match=r"^warmup=5 must be less than total_steps=5") as e:
        train_transformer(tokens, poses, TF, str(tmp_path / "run"), steps=5, warmup=5, **QUIET)
    assert "warmup_steps" not in str(e.value) and "steps when not given" in str(e.value)
    with pytest.raises(ValueError, match=r"^warmup=9 must be less than total_steps=8"):
        train_transformer(tokens, poses, TF, str(tmp_path / "run"), steps=5, total_steps=8, warmup=9, **QUIET)


def test_numpy_integer_threads_are_accepted(tmp_path, rng):
    """threads=np.int64(1) passes the check (any integer does) and config.json records it:
    it used to pass the check and then crash writing config.json (int64 is not JSON)."""
    cb, tf = str(tmp_path / "cb"), str(tmp_path / "tf")
    train_codebook(_images(rng), CB, cb, steps=1, batch_size=2, threads=np.int64(1), **QUIET)
    train_transformer(_tokens(rng), _poses(rng), TF, tf, steps=1, batch_size=2, threads=np.int32(1), **QUIET)
    for run in (cb, tf):
        with open(os.path.join(run, "config.json"), encoding="utf-8") as f:
            assert json.load(f)["calls"][-1]["threads"] == 1


def test_a_held_out_set_not_evaluated_on_is_not_part_of_the_run(tmp_path, rng):
    """With eval_every=0 nothing is evaluated, so the held-out set passed is not recorded: a
    resume with eval_every=0 passes whatever set it names (the advice of the refusal of another
    set), and a run that evaluated nothing may evaluate on any set later, as the commands do
    (they pass no set with --eval-every 0)."""
    images = _images(rng)
    first, other = (_images(rng, scenes=1, views=2).reshape(-1, 16, 16, 3) for _ in range(2))
    kw = dict(batch_size=2, **QUIET)
    evaluated = str(tmp_path / "evaluated")
    train_codebook(images, CB, evaluated, steps=2, eval_images=first, eval_every=1, **kw)
    rows = _log(evaluated, "eval.csv")
    train_codebook(images, CB, evaluated, steps=3, eval_images=other, eval_every=0, **kw)
    assert _checkpoint(evaluated)[0]["step"] == 3 and _log(evaluated, "eval.csv") == rows
    with pytest.raises(ValueError, match="another held-out set"):  # the run's record kept
        train_codebook(images, CB, evaluated, steps=4, eval_images=other, eval_every=1, **kw)

    plain = str(tmp_path / "plain")
    train_codebook(images, CB, plain, steps=2, eval_images=first, eval_every=0, **kw)
    assert not os.path.exists(os.path.join(plain, "eval.csv"))
    train_codebook(images, CB, plain, steps=3, eval_images=other, eval_every=1, **kw)
    assert [r[0] for r in _log(plain, "eval.csv")[1:]] == ["3"]

    tokens, poses = _tokens(rng), _poses(rng)
    tf, kw = str(tmp_path / "tf"), dict(batch_size=2, total_steps=3, **QUIET)
    train_transformer(tokens, poses, TF, tf, steps=2, eval_set=_eval_set(rng), eval_every=0, **kw)
    assert not os.path.exists(os.path.join(tf, "eval.csv"))
    train_transformer(tokens, poses, TF, tf, steps=3, eval_set=_eval_set(rng), eval_every=1, **kw)
    assert [r[0] for r in _log(tf, "eval.csv")[1:]] == ["3"]


def test_the_batch_functions_name_their_arguments(rng):
    """codebook_batch and transformer_batch are public: a bad batch_size, seed, step or n_views is
    named, not reported as numpy's reshape error, as "images" (an empty batch) or as "seed" (a
    fractional step, from np.random.default_rng)."""
    images, tokens, poses = _images(rng).reshape(-1, 16, 16, 3), _tokens(rng), _poses(rng)  # 5 views a scene
    cases = [
        (ValueError, "batch_size", lambda: codebook_batch(images, 0, 0, 1)),
        (ValueError, "seed", lambda: codebook_batch(images, 2, -1, 1)),
        (TypeError, "step", lambda: codebook_batch(images, 2, 0, 1.5)),
        (ValueError, "n_views", lambda: transformer_batch(tokens, poses, 6, 2, 0, 1)),
        (ValueError, "n_views", lambda: transformer_batch(tokens, poses, 0, 2, 0, 1)),
        (ValueError, "batch_size", lambda: transformer_batch(tokens, poses, 3, 0, 0, 1)),
        (TypeError, "step", lambda: transformer_batch(tokens, poses, 3, 2, 0, 1.5)),
        (ValueError, "step", lambda: transformer_batch(tokens, poses, 3, 2, 0, -1)),
    ]
    for exc, name, call in cases:
        with pytest.raises(exc, match=f"^{name} must"):
            call()


def test_compare_runs_takes_a_numpy_integer_step(tmp_path, rng):
    """compare_runs' step: a numpy integer (a step read from a log's array, say) is an integer, as
    everywhere else in pyvf; a negative one or a float is still refused naming step."""
    out = str(tmp_path / "run")
    train_codebook(_images(rng), CB, out, steps=2, batch_size=2, **QUIET)
    assert compare_runs([out], step=np.int64(1))[0] == compare_runs([out], step=1)[0]
    for bad in (np.int64(-1), 1.0, True):
        with pytest.raises(ValueError, match="^step must be a non-negative integer"):
            compare_runs([out], step=bad)


def test_an_out_dir_that_is_a_file_and_a_command_json_cannot_hold_are_named(tmp_path):
    """out_dir naming a file gave makedirs' "[Errno 17] File exists"; a command json cannot hold
    gave "Object of type object is not JSON serializable" after the folder was made. Both name
    their argument now, before anything is written."""
    images = np.zeros((4, CB.image_size, CB.image_size, 3), np.uint8)
    afile = tmp_path / "f"
    afile.write_text("x")
    with pytest.raises(NotADirectoryError, match=f"^out_dir {afile} is a file, not a folder"):
        train_codebook(images, CB, str(afile), steps=1, batch_size=2, progress=False)
    with pytest.raises(TypeError, match="^command must be JSON-able"):
        train_codebook(images, CB, str(tmp_path / "run"), steps=1, batch_size=2, progress=False, command=object())
    assert not (tmp_path / "run").exists() and afile.read_text() == "x"
