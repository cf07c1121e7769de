"""The whole ViewFormer pipeline in one call: scenes, codebook, tokens, transformer, evaluation.

    metrics = train_pipeline("runs/quick", preset="quick")   # `pyvf train --out runs/quick --preset quick`

The folder holds one stage each, every stage resumable (call again with the same arguments):

    scenes/        pyvf.scenes.write_dataset (kept once its manifest is written)
    codebook/      train_codebook's run folder (checkpoint, log.csv, eval.csv, eval.png, codebook.npz)
    tokens.npz     tokenize's output, with tokens.json naming the codebook file it came from (sha256)
    transformer/   train_transformer's run folder, evaluated on held-out scenes through the codebook
    eval/          pyvf evaluate's metrics.json, metrics.md, views.png, poses.png

A preset (PRESETS) fixes every size: the data, both models, their steps and the evaluation.
Training scenes use seed 0, the runs' health checks seed 1, the final evaluation seed 1000.
"""

import dataclasses
import json
import os

from .._io import atomic_write_text
from ..models.codebook import Codebook, CodebookConfig
from ..models.transformer import TransformerConfig
from ._run import file_sha256
from .loops import (TINY_CODEBOOK, TINY_TRANSFORMER, RunOptions, TransformerRecipe, held_out_set, load_tokens,
                    save_tokens, tokenize, train_codebook, train_transformer)

TRAIN_SEED, HEALTH_SEED, EVAL_SEED = 0, 1, 1000
# every preset's codebook: the background's patches take one code (empty_code), the codes start at k-means
# of the first batches' encodings and dead ones restart at the worst represented (docs/models.md's ablation)
CODEBOOK_RECIPE = {"restart": "worst", "kmeans": 10}
TINY_EMPTY = dataclasses.replace(TINY_CODEBOOK, empty_code=True)


@dataclasses.dataclass(frozen=True)
class Preset:
    scenes: int  # training scenes of 15 views
    codebook: CodebookConfig
    codebook_steps: int
    transformer: TransformerConfig
    transformer_steps: int
    transformer_batch: int
    transformer_lr: float
    eval_scenes: int  # pyvf evaluate's scenes at the end
    health_scenes: int  # held-out scenes of the runs' evaluations
    eval_every: int  # steps between the runs' evaluations
    size: int = 64  # image side
    codebook_batch: int = 16


PRESETS = {
    # a pair trained from scratch in about 15 minutes on 2 cores where a codebook step of 16 images takes
    # 0.5-0.6 s and a transformer step of 8 scenes ~0.9 s (another 2-core AVX2 machine: 1.3 s a codebook
    # step, 25 min in all, docs/models.md); too short to beat the baselines: it shows the pipeline at work
    "quick": Preset(scenes=400, codebook=TINY_EMPTY, codebook_steps=800, transformer=TINY_TRANSFORMER,
                    transformer_steps=300, transformer_batch=8, transformer_lr=5e-4, eval_scenes=30,
                    health_scenes=8, eval_every=250),
    # the shipped models' sizes: many hours of a 2-core machine (run in the background; resumable)
    "full": Preset(scenes=4000, codebook=TINY_EMPTY, codebook_steps=20000, transformer=TINY_TRANSFORMER,
                   transformer_steps=20000, transformer_batch=16, transformer_lr=5e-4, eval_scenes=200,
                   health_scenes=16, eval_every=500),
    # seconds: every stage runs, for the tests and a first look at the files
    "smoke": Preset(scenes=3, codebook=dataclasses.replace(TINY_EMPTY, ch=32, ch_mult=(1, 1), image_size=16,
                                                           z_channels=8, embed_dim=8, n_embed=16),
                    codebook_steps=2, transformer=dataclasses.replace(TINY_TRANSFORMER, n_embeddings=16, d_model=32,
                                                                      n_head=2, n_layer=1),
                    transformer_steps=2, transformer_batch=2, transformer_lr=1e-3, eval_scenes=1, health_scenes=1,
                    eval_every=1, size=16, codebook_batch=2),
}


def _scenes(folder, n, size, progress):
    """The training scenes: loaded when the folder's manifest matches, else written (an interrupted
    write resumes, another dataset's is replaced)."""
    from ..scenes import load_dataset, write_dataset
    from ..scenes.dataset import DatasetExistsError

    if os.path.exists(os.path.join(folder, "manifest.json")):
        data = load_dataset(folder)
        if (data.images.shape[0], data.seed, data.images.shape[2]) == (n, TRAIN_SEED, size):
            return data
        raise ValueError(f"{folder} holds another dataset ({data.images.shape[0]} scenes of seed {data.seed}, "
                         f"{data.images.shape[2]} px): use another --out")
    try:
        write_dataset(folder, n, TRAIN_SEED, size=size, progress=progress)
    except DatasetExistsError:
        write_dataset(folder, n, TRAIN_SEED, size=size, progress=progress, overwrite=True)
    return load_dataset(folder)


def _tokens(path, codebook_path, images, poses, progress):
    """tokenize's output for this codebook file: reused when tokens.json names its sha256."""
    stamp = path[:-len(".npz")] + ".json"
    sha = file_sha256(codebook_path)
    if os.path.exists(path) and os.path.exists(stamp):
        with open(stamp, encoding="utf-8") as f:
            if json.load(f).get("codebook_sha256") == sha:
                return load_tokens(path)
    codebook = Codebook.load(codebook_path)
    tokens = tokenize(codebook, images, progress=progress)
    save_tokens(path, tokens, poses, codebook.config.n_embed, codebook.fingerprint())
    atomic_write_text(stamp, json.dumps({"codebook": os.path.basename(codebook_path), "codebook_sha256": sha}) + "\n")
    return load_tokens(path)


def train_pipeline(out, preset="quick", *, log=print, progress=True, **options):
    """Run (or resume) every stage of `preset` in the folder `out` -> the final evaluation's metrics
    dict. log: prints one line per stage; options: both runs' RunOptions fields."""
    from ..evaluate.run import evaluate, metrics_markdown
    from ..scenes import generate_scenes

    if preset not in PRESETS:
        raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {preset!r}")
    p = PRESETS[preset]
    run = RunOptions(steps=1, progress=progress, eval_every=p.eval_every, checkpoint_every=max(1, p.eval_every),
                     **options)
    os.makedirs(out, exist_ok=True)  # after the options' checks: a bad combination costs no rendering

    log(f"[1/5] scenes: {p.scenes} training scenes x 15 views of {p.size}x{p.size} (seed {TRAIN_SEED})")
    data = _scenes(os.path.join(out, "scenes"), p.scenes, p.size, progress)

    log(f"[2/5] codebook: {p.codebook_steps} steps of {p.codebook_batch} images, evaluated every {p.eval_every} "
        f"steps on {p.health_scenes} held-out scenes (seed {HEALTH_SEED})")
    held_images, held_poses = generate_scenes(HEALTH_SEED, p.health_scenes, size=p.size)  # (n, 15, S, S, 3)
    cb_dir = os.path.join(out, "codebook")
    codebook = train_codebook(data.images, p.codebook, cb_dir,
                              dataclasses.replace(run, steps=p.codebook_steps, batch_size=p.codebook_batch),
                              eval_images=held_images[:, :4].reshape(-1, p.size, p.size, 3), **CODEBOOK_RECIPE)

    log("[3/5] tokens: every training view through the codebook")
    tokens, poses, _, fingerprint = _tokens(os.path.join(out, "tokens.npz"), os.path.join(cb_dir, "codebook.npz"),
                                            data.images, data.poses, progress)

    log(f"[4/5] transformer: {p.transformer_steps} steps of {p.transformer_batch} scenes, evaluated every "
        f"{p.eval_every} steps on the held-out scenes against the baselines")
    eval_set = held_out_set(codebook, held_images, held_poses)
    transformer = train_transformer(tokens, poses, p.transformer, os.path.join(out, "transformer"),
                                    dataclasses.replace(run, steps=p.transformer_steps, batch_size=p.transformer_batch),
                                    TransformerRecipe(lr=p.transformer_lr), eval_set=eval_set,
                                    codebook_fingerprint=fingerprint)

    log(f"[5/5] evaluation: {p.eval_scenes} held-out scenes (seed {EVAL_SEED}), context 1, 3, 5")
    metrics = evaluate(codebook, transformer, scenes=p.eval_scenes, seed=EVAL_SEED, out=os.path.join(out, "eval"),
                       progress=progress, timing_scenes=1, repeat=1,
                       sources={"codebook": os.path.join(cb_dir, "codebook.npz"),
                                "transformer": os.path.join(out, "transformer", "transformer.npz")})
    log(metrics_markdown(metrics))  # the verdicts against each baseline first, then the tables
    return metrics
