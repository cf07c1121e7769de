"""The work of the training commands (their arguments: pyvf/cli/train.py), on files: a dataset
folder or a tokens file in, a run folder out. config: "tiny" or a JSON file of the configuration's
fields (or a run's config.json).
"""

import json
import os
import sys

import numpy as np

from .._threads import threads as kernel_threads
from ..models.codebook import Codebook, CodebookConfig
from ..models.transformer import Transformer, TransformerConfig
from ._run import CHECKPOINT, read_checkpoint
from .loops import (TINY_CODEBOOK, TINY_TRANSFORMER, TransformerRecipe, held_out_set, load_tokens, save_tokens,
                    tokenize, train_codebook, train_transformer)

EVAL_VIEWS = 4  # views per held-out scene in a codebook run's evaluation


def read_config(value, cls, tiny):
    """config: "tiny" or a JSON file -> a cls instance (ValueError naming the file)."""
    if value == "tiny":
        return tiny
    try:
        with open(value, encoding="utf-8") as f:
            d = json.load(f)
        d = d["config"] if isinstance(d, dict) and isinstance(d.get("config"), dict) else d  # a run's config.json
        return cls(**d)
    except (OSError, ValueError, TypeError) as e:  # unreadable, not JSON, unknown or missing fields
        raise ValueError(f"--config {value}: not a JSON file of {cls.__name__} fields ({e})") from e


def held_out_views(eval_every, eval_scenes, eval_seed, data, size):
    """A codebook run's held-out views, (eval_scenes * EVAL_VIEWS, size, size, 3) uint8, of eval_seed
    (not the training data's); None when eval_every is 0."""
    if not eval_every:
        return None
    if getattr(data, "seed", None) == eval_seed:
        raise ValueError(f"--eval-seed {eval_seed} is the training data's seed: held-out scenes need another seed")
    from ..scenes import generate_scenes
    images, _ = generate_scenes(eval_seed, eval_scenes, views=EVAL_VIEWS, size=size)
    return images.reshape(-1, size, size, images.shape[-1])


def held_out_scenes(codebook, eval_scenes, eval_seed, threads, train_poses):
    """A transformer run's held-out scenes of eval_seed, tokenized by the codebook file ->
    train_transformer's eval_set. Scenes whose poses are the training data's raise."""
    codebook = Codebook.load(codebook)
    from ..scenes import generate_scenes
    images, poses = generate_scenes(eval_seed, eval_scenes, size=codebook.config.image_size)
    n, views = min(len(poses), len(train_poses)), min(poses.shape[1], train_poses.shape[1])
    if n and np.allclose(poses[:n, :views], train_poses[:n, :views], rtol=0, atol=1e-6):
        raise ValueError(f"--eval-seed {eval_seed} is the training data's seed: held-out scenes need another seed")
    with kernel_threads(threads):
        return held_out_set(codebook, images, poses)


def codebook_run(data, out, opts, *, config="tiny", eval_scenes=32, eval_seed=1, **recipe):
    """train_codebook on the dataset folder `data` into the run folder `out`, evaluated every
    opts.eval_every steps on held_out_views; recipe: train_codebook's recipe and overrides."""
    config = read_config(config, CodebookConfig, TINY_CODEBOOK)
    from ..scenes import load_dataset  # at the call: tests stand a fake dataset reader in
    data = load_dataset(data)
    held_out = held_out_views(opts.eval_every, eval_scenes, eval_seed, data, config.image_size)
    return train_codebook(data.images, config, out, opts, eval_images=held_out, **recipe)


def tokenize_dataset(codebook, data, out, *, batch_size=64, progress=True, threads=None):
    """The dataset folder `data` encoded by the codebook file into the tokens file `out` -> the tokens."""
    codebook = Codebook.load(codebook)
    from ..scenes import load_dataset  # at the call: tests stand a fake dataset reader in
    data = load_dataset(data)
    with kernel_threads(threads):
        tokens = tokenize(codebook, data.images, batch_size=batch_size, progress=progress)
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    save_tokens(out, tokens, data.poses, codebook.config.n_embed, codebook.fingerprint())
    return tokens


def transformer_run(tokens, out, opts, recipe=TransformerRecipe(), *, config="tiny", codebook=None, eval_scenes=16,
                    eval_seed=1):
    """train_transformer on the tokens file into the run folder `out`; with codebook (the file the
    tokens came from), evaluated every opts.eval_every steps on held_out_scenes."""
    config = read_config(config, TransformerConfig, TINY_TRANSFORMER)
    tokens_path, (tokens, poses, n_embed, fingerprint) = tokens, load_tokens(tokens)
    if config.n_embeddings != n_embed:
        raise ValueError(f"the configuration has n_embeddings={config.n_embeddings} but {tokens_path} "
                         f"was made by a codebook of {n_embed} codes")
    if codebook and fingerprint is not None and (given := Codebook.load(codebook).fingerprint()) != fingerprint:
        raise ValueError(f"--codebook {codebook} is not the codebook that made {tokens_path} (fingerprints {given} "
                         f"and {fingerprint})")
    eval_set = None
    if opts.eval_every and codebook:
        eval_set = held_out_scenes(codebook, eval_scenes, eval_seed, opts.threads, poses)
    elif opts.eval_every:
        print("pyvf train-transformer: no --codebook, so no held-out evaluation", file=sys.stderr)
    return train_transformer(tokens, poses, config, out, opts, recipe, eval_set=eval_set,
                             codebook_fingerprint=fingerprint)


def export_run(run, out):
    """The model of a run's last checkpoint (run: its folder or checkpoint.npz) written to `out` ->
    (the run's kind, its step, the path written)."""
    path = os.path.join(run, CHECKPOINT) if os.path.isdir(run) else os.fspath(run)
    meta, state, _ = read_checkpoint(path, None)
    cls = {"codebook": Codebook, "transformer": Transformer}[meta["kind"]]
    model = cls(cls.CONFIG(**meta["config"]))
    model.load_official(state)
    model.codebook_fingerprint = meta["hyper"].get("codebook_fingerprint")  # a transformer's
    return meta["kind"], int(meta["step"]), model.save(out)
