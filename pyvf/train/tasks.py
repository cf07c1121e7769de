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


def codebook_run(data, out, opts, *, config="tiny", eval_scenes=32, eval_seed=1, **recipe):
    """train_codebook on the dataset folder `data` into the run folder `out`, evaluated every
    opts.eval_every steps on the first EVAL_VIEWS views of eval_scenes scenes of eval_seed (not the
    data's); recipe: train_codebook's recipe and overrides."""
    config = read_config(config, CodebookConfig, TINY_CODEBOOK)
    from ..scenes import generate_scenes, load_dataset  # at the call: tests stand a fake module in
    data, held_out, S = load_dataset(data), None, config.image_size
    if opts.eval_every:
        if getattr(data, "seed", None) == eval_seed:
            raise ValueError(f"eval_seed {eval_seed} is the training data's seed: held-out scenes need another seed")
        held_out = generate_scenes(eval_seed, eval_scenes, views=EVAL_VIEWS, size=S)[0].reshape(-1, S, S, 3)
    return train_codebook(data.images, config, out, opts, eval_images=held_out, **recipe)


def tokenize_dataset(codebook, data, out, *, progress=True, threads=None):
    """The dataset folder `data` encoded by the codebook file into the tokens file `out` -> the tokens."""
    codebook = Codebook.load(codebook)
    from ..scenes import load_dataset  # at the call: tests stand a fake dataset reader in
    data = load_dataset(data)
    with kernel_threads(threads):
        tokens = tokenize(codebook, data.images, progress=progress)
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    save_tokens(out, tokens, data.poses, codebook.config.n_embed, codebook.fingerprint())
    return tokens


def transformer_run(tokens, out, opts, recipe=TransformerRecipe(), *, config="tiny", codebook=None, eval_scenes=16,
                    eval_seed=1):
    """train_transformer on the tokens file into the run folder `out`; with codebook (the file the
    tokens came from), evaluated every opts.eval_every steps on eval_scenes scenes of eval_seed,
    refused when their poses are the training data's."""
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
        from ..scenes import generate_scenes
        cb = Codebook.load(codebook)
        images, held_poses = generate_scenes(eval_seed, eval_scenes, size=cb.config.image_size)
        n, views = min(len(held_poses), len(poses)), min(held_poses.shape[1], poses.shape[1])
        if n and np.allclose(held_poses[:n, :views], poses[:n, :views], rtol=0, atol=1e-6):
            raise ValueError(f"eval_seed {eval_seed} is the training data's seed: held-out scenes need another seed")
        with kernel_threads(opts.threads):
            eval_set = held_out_set(cb, images, held_poses)
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
