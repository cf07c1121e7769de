"""`pyvf train` (pyvf/train/pipeline.py): every stage at the smoke preset, from a temporary folder;
a second call resumes every stage instead of redoing it; a changed codebook re-tokenizes."""

import json
import os

import pytest

from pyvf.cli import main
from pyvf.models.codebook import Codebook
from pyvf.models.transformer import Transformer
from pyvf.train.pipeline import PRESETS, train_pipeline


def test_pipeline_runs_every_stage_and_resumes(tmp_path, monkeypatch, capsys):
    """Ctrl-C during the transformer stage: one line, status 130; the same command resumes and
    finishes every stage, and a third call retrains nothing."""
    import pyvf.train.loops as loops

    monkeypatch.chdir(tmp_path)
    real = loops.transformer_batch

    def interrupted(*args):
        if args[5] == 2:  # the step
            raise KeyboardInterrupt
        return real(*args)

    monkeypatch.setattr(loops, "transformer_batch", interrupted)
    command = ["train", "--out", "run", "--preset", "smoke", "--no-progress"]
    try:
        assert main(command) == 130
    except KeyboardInterrupt:
        pytest.fail("KeyboardInterrupt escaped the command: the user sees a traceback")
    *held_out, last = capsys.readouterr().err.splitlines()  # the runs' held-out lines, then one line
    assert all(" held-out at step " in line for line in held_out), held_out
    assert last == "pyvf train: interrupted; rerun the same command (a training run resumes from its last checkpoint)"
    monkeypatch.setattr(loops, "transformer_batch", real)
    assert main(command) == 0
    calls = json.loads((tmp_path / "run" / "transformer" / "config.json").read_text())["calls"]
    assert [c["resumed_from_step"] for c in calls] == [None, 1]
    out = capsys.readouterr().out
    assert [line[:5] for line in out.splitlines() if line.startswith("[")] == ["[1/5]", "[2/5]", "[3/5]", "[4/5]",
                                                                             "[5/5]"]
    assert "Does pyvf beat the baselines? (context 5" in out
    run = tmp_path / "run"
    for f in ("scenes/manifest.json", "codebook/codebook.npz", "codebook/eval.png", "tokens.npz", "tokens.json",
              "transformer/transformer.npz", "transformer/eval.csv", "eval/metrics.json", "eval/views.png"):
        assert (run / f).is_file(), f
    first = json.loads((run / "eval" / "metrics.json").read_text())
    # the transformer records the codebook its tokens came from (file, run folder, export), which
    # evaluate checks its pairing by (models.check_pair, tests/test_model_files.py)
    fingerprint = Codebook.load(str(run / "codebook" / "codebook.npz")).fingerprint()
    assert Transformer.load(str(run / "transformer" / "transformer.npz")).codebook_fingerprint == fingerprint
    assert json.loads((run / "transformer" / "config.json").read_text())["hyperparameters"][
        "codebook_fingerprint"] == fingerprint
    assert main(["export", "run/transformer", "-o", "now.npz"]) == 0
    assert Transformer.load("now.npz").codebook_fingerprint == fingerprint
    stamps = {f: os.path.getmtime(run / f) for f in ("codebook/codebook.npz", "tokens.npz", "scenes/manifest.json")}

    # again: the runs are complete, so nothing is retrained or re-tokenized, and the metrics agree
    lines = []
    again = train_pipeline(str(run), "smoke", progress=False, log=lines.append)
    assert again["context"] == first["context"]
    assert os.path.getmtime(run / "tokens.npz") == stamps["tokens.npz"]
    assert os.path.getmtime(run / "scenes/manifest.json") == stamps["scenes/manifest.json"]
    cb_config = json.loads((run / "codebook" / "config.json").read_text())
    assert [c["resumed_from_step"] for c in cb_config["calls"]][-1] == PRESETS["smoke"].codebook_steps
    # every preset's codebook recipe (docs/models.md's ablation): the empty code, k-means, worst restarts
    assert cb_config["config"]["empty_code"] and {"restart": "worst", "kmeans": 10}.items() <= cb_config[
        "hyperparameters"].items()

    # a codebook file that changed makes the tokens stale: they are made again from it
    stamp = json.loads((run / "tokens.json").read_text())
    (run / "tokens.json").write_text(json.dumps({**stamp, "codebook_sha256": "0" * 64}))
    train_pipeline(str(run), "smoke", progress=False, log=lines.append)
    assert os.path.getmtime(run / "tokens.npz") > stamps["tokens.npz"]
    assert json.loads((run / "tokens.json").read_text()) == stamp


def test_pipeline_refuses_another_dataset_and_unknown_presets(tmp_path):
    from pyvf.scenes import write_dataset

    write_dataset(str(tmp_path / "run" / "scenes"), 2, 5, size=16, progress=False)
    with pytest.raises(ValueError, match="holds another dataset"):
        train_pipeline(str(tmp_path / "run"), "smoke", progress=False, log=lambda s: None)
    with pytest.raises(ValueError, match="preset must be one of"):
        train_pipeline(str(tmp_path / "x"), "huge", log=lambda s: None)
    assert main(["train", "--out", str(tmp_path / "run"), "--preset", "smoke", "--no-progress"]) == 1


def test_pipeline_checks_the_engine_options_before_any_stage(tmp_path, capsys):
    """--device (or --precision) without --engine torch is refused before the scenes are rendered:
    nothing written."""
    assert main(["train", "--out", str(tmp_path / "run"), "--preset", "smoke", "--engine", "pyvf",
                 "--device", "cuda", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("pyvf train: error: device=") and len(err.splitlines()) == 1, err
    with pytest.raises(ValueError, match=r"\bprecision\b"):
        train_pipeline(str(tmp_path / "lib"), "smoke", precision="bf16", log=lambda s: None)
    assert not os.path.exists(tmp_path / "run") and not os.path.exists(tmp_path / "lib")


def test_the_scenes_stage_resumes_an_interrupted_write(tmp_path, monkeypatch):
    """Ctrl-C in the training scenes' third scene (shards of 2 scenes): the stage run again keeps
    the finished shard and renders only the rest (it started over: every scene again), and the
    folder has the bytes of an uninterrupted write. A write of another size there is replaced."""
    import functools
    import pyvf.scenes as scenes_pkg
    from pyvf.scenes import dataset as dataset_module
    from pyvf.train import pipeline

    monkeypatch.setattr(scenes_pkg, "write_dataset", functools.partial(scenes_pkg.write_dataset, shard_size=2))
    real, count = dataset_module.generate_scene, [0]

    def scene(*args):
        count[0] += 1
        if count[0] == 3:
            raise KeyboardInterrupt
        return real(*args)

    monkeypatch.setattr(dataset_module, "generate_scene", scene)
    with pytest.raises(KeyboardInterrupt):
        pipeline._scenes(str(tmp_path / "scenes"), 5, 16, False)
    count[0] = 10  # no more interruptions; count the scenes rendered from here
    data = pipeline._scenes(str(tmp_path / "scenes"), 5, 16, False)
    assert count[0] - 10 == 3 and data.images.shape[0] == 5  # scenes 2, 3, 4; shard 0 kept
    pipeline._scenes(str(tmp_path / "want"), 5, 16, False)
    for name in os.listdir(tmp_path / "want"):
        assert (tmp_path / "scenes" / name).read_bytes() == (tmp_path / "want" / name).read_bytes(), name
    # an unfinished write of other arguments (another size) is replaced, not refused
    count[0] = 2  # the next scene is interrupted
    with pytest.raises(KeyboardInterrupt):
        pipeline._scenes(str(tmp_path / "other"), 5, 16, False)
    count[0] = 10
    assert pipeline._scenes(str(tmp_path / "other"), 5, 24, False).images.shape[2] == 24

