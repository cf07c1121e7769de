"""The training commands of `pyvf`: argument parsing only; the work is in loops.py.

    pyvf train-codebook    --data DIR --out runs/cb --steps 20000 [--batch 16] [--config tiny|FILE]
    pyvf tokenize          --codebook runs/cb/codebook.npz --data DIR --out runs/tokens.npz
    pyvf train-transformer --tokens runs/tokens.npz --out runs/tf --steps 50000 [--batch 16] [--codebook F]
    pyvf runs runs/cb runs/cb2 [--plot]   # compare runs: their last held-out evaluation
    pyvf train --out runs/quick [--preset quick|full|smoke]   # every stage, resumable

Run again with the same arguments to resume from the run folder's checkpoint (--no-resume
starts over). --config takes "tiny" (TINY_CODEBOOK / TINY_TRANSFORMER) or a JSON file: the
configuration's fields, or a run's config.json (its "config" is used).
Each handler returns an exit status: 0, or 1 after printing the error.
"""

import dataclasses
import json
import os
import sys
import zipfile

from ..models.codebook import Codebook, CodebookConfig
from ..models.transformer import TransformerConfig
from .curves import plot_eval, runs_table
from .loops import (
    CODEBOOK_RECIPES,
    TINY_CODEBOOK,
    _Threads,
    held_out_set,
    TINY_TRANSFORMER,
    load_tokens,
    save_tokens,
    tokenize,
    train_codebook,
    train_transformer,
)


def _config(value, cls, tiny):
    """--config: "tiny" or a JSON file -> a cls instance (ValueError naming the file)."""
    if value == "tiny":
        return tiny
    try:
        with open(value, encoding="utf-8") as f:
            d = json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"--config {value}: cannot read a JSON configuration ({e})") from e
    if isinstance(d, dict) and isinstance(d.get("config"), dict):  # a run's config.json
        d = d["config"]
    if not isinstance(d, dict):
        raise ValueError(f"--config {value}: expected a JSON object of {cls.__name__} fields")
    try:
        return cls(**d)
    except TypeError as e:  # unknown or missing fields
        raise ValueError(f"--config {value}: not a {cls.__name__} ({e}); its fields are "
                         f"{[f.name for f in dataclasses.fields(cls)]}") from e


def _load_dataset(path):
    """pyvf.scenes.load_dataset(path): .images uint8 (scenes, views, Hi, Wi, 3), .poses (scenes, views, 7)."""
    try:
        from ..scenes import load_dataset  # imported here: the scenes home is optional for the other commands
    except ImportError as e:
        raise ValueError(f"cannot read the dataset {path}: pyvf.scenes is not available ({e})") from e
    return load_dataset(path)


def _record(args):
    """The command line, for config.json."""
    return {"argv": list(sys.argv), "args": {k: v for k, v in vars(args).items() if k != "func"}}


def _guarded(name, work):
    """Run work(); a ValueError, TypeError or OSError (bad arguments or files) is printed, status 1."""
    try:
        work()
    except (ValueError, TypeError, OSError) as e:
        print(f"pyvf {name}: error: {e}", file=sys.stderr)
        return 1
    return 0


EVAL_VIEWS = 4  # views per held-out scene in a training run's evaluation


def _held_out_views(args, data, size):
    """The held-out views a run evaluates on every --eval-every steps: the first EVAL_VIEWS views
    of --eval-scenes scenes of --eval-seed, (scenes * EVAL_VIEWS, size, size, 3) uint8; None
    when --eval-every is 0. The seed must differ from the training data's."""
    if not args.eval_every:
        return None
    if args.eval_scenes < 1:
        raise ValueError(f"--eval-scenes must be a positive integer, got {args.eval_scenes}")
    if getattr(data, "seed", None) == args.eval_seed:
        raise ValueError(f"--eval-seed {args.eval_seed} is the training data's seed: held-out scenes need "
                         "another seed")
    from ..scenes import generate_scenes
    images, _ = generate_scenes(args.eval_seed, args.eval_scenes, views=EVAL_VIEWS, size=size)
    return images.reshape(-1, size, size, images.shape[-1])


def _held_out_scenes(args):
    """train-transformer's held-out scenes: --eval-scenes whole scenes of --eval-seed (all 15
    views), tokenized by --codebook -> train_transformer's eval_set."""
    if args.eval_scenes < 1:
        raise ValueError(f"--eval-scenes must be a positive integer, got {args.eval_scenes}")
    codebook = _read_codebook(args.codebook)
    from ..scenes import generate_scenes
    images, poses = generate_scenes(args.eval_seed, args.eval_scenes, size=codebook.config.image_size)
    with _Threads(args.threads):
        return held_out_set(codebook, images, poses)


def _read_codebook(path):
    """Codebook.load(path), its errors as ValueError naming the file."""
    try:
        return Codebook.load(path)
    except FileNotFoundError as e:
        raise ValueError(f"codebook {path} does not exist") from e
    except (zipfile.BadZipFile, EOFError, KeyError, ValueError) as e:
        raise ValueError(f"codebook {path} is not a readable codebook file: {type(e).__name__}: {e}") from e


def cmd_train_codebook(args):
    """Train the codebook (VQ-VAE) on a dataset's images; resumable."""
    def work():
        config = _config(args.config, CodebookConfig, TINY_CODEBOOK)
        data = _load_dataset(args.data)
        held_out = _held_out_views(args, data, config.image_size)
        train_codebook(data.images, config, args.out, steps=args.steps, batch_size=args.batch, recipe=args.recipe,
                       lr=args.lr, betas=args.betas, reset_dead_codes=args.reset_dead_codes,
                       object_weight=args.object_weight, seed=args.seed, checkpoint_every=args.checkpoint_every,
                       log_every=args.log_every, eval_images=held_out, eval_every=args.eval_every,
                       resume=not args.no_resume, progress=not args.no_progress, threads=args.threads,
                       command=_record(args))
        print(f"codebook: {os.path.join(args.out, 'codebook.npz')}")
    return _guarded("train-codebook", work)


def cmd_tokenize(args):
    """Encode a dataset's images into token images with a trained codebook."""
    def work():
        codebook = _read_codebook(args.codebook)
        data = _load_dataset(args.data)
        with _Threads(args.threads):
            tokens = tokenize(codebook, data.images, batch_size=args.batch, progress=not args.no_progress)
        folder = os.path.dirname(os.path.abspath(args.out))
        os.makedirs(folder, exist_ok=True)
        save_tokens(args.out, tokens, data.poses, codebook.config.n_embed)
        print(f"tokens {tokens.shape} {tokens.dtype}: {args.out}")
    return _guarded("tokenize", work)


def cmd_train_transformer(args):
    """Train the transformer on a tokenized dataset; resumable."""
    def work():
        config = _config(args.config, TransformerConfig, TINY_TRANSFORMER)
        tokens, poses, n_embed = load_tokens(args.tokens)
        if config.n_embeddings != n_embed:
            raise ValueError(f"the configuration has n_embeddings={config.n_embeddings} but {args.tokens} "
                             f"was made by a codebook of {n_embed} codes")
        eval_set = _held_out_scenes(args) if args.eval_every and args.codebook else None
        if args.eval_every and not args.codebook:
            print("pyvf train-transformer: no --codebook, so no held-out evaluation (it renders through the "
                  "codebook)", file=sys.stderr)
        train_transformer(tokens, poses, config, args.out, steps=args.steps, batch_size=args.batch,
                          eval_set=eval_set, eval_every=args.eval_every,
                          context=args.context, lr=args.lr, warmup=args.warmup, total_steps=args.total_steps,
                          weight_decay=args.weight_decay,
                          max_grad_norm=None if args.max_grad_norm <= 0 else args.max_grad_norm,
                          seed=args.seed, checkpoint_every=args.checkpoint_every, log_every=args.log_every,
                          resume=not args.no_resume, progress=not args.no_progress, threads=args.threads,
                          command=_record(args), engine=args.engine, device=args.device, precision=args.precision)
        print(f"transformer: {os.path.join(args.out, 'transformer.npz')}")
    return _guarded("train-transformer", work)


def _run_options(p, batch, checkpoint_every):
    p.add_argument("--out", required=True, help="run folder: checkpoint.npz, log.csv, config.json, the final model")
    p.add_argument("--steps", type=int, required=True, help="total updates (a resumed run continues to it)")
    p.add_argument("--batch", type=int, default=batch, help=f"batch size (default {batch})")
    p.add_argument("--seed", type=int, default=0, help="initialisation and batches (default 0)")
    p.add_argument("--config", default="tiny", help='"tiny" (default) or a JSON file of the configuration')
    p.add_argument("--checkpoint-every", type=int, default=checkpoint_every,
                   help=f"steps between checkpoints (default {checkpoint_every}; one at the end always)")
    p.add_argument("--log-every", type=int, default=10, help="steps between log.csv rows (default 10)")
    p.add_argument("--no-resume", action="store_true", help="start over even if the run folder has a checkpoint")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--threads", type=int, default=None, help="threads for pyvf's C++ kernels")


def _eval_options(p, every, scenes):
    p.add_argument("--eval-every", type=int, default=every,
                   help=f"steps between evaluations on held-out scenes, logged to eval.csv (default {every}; 0: none)")
    p.add_argument("--eval-scenes", type=int, default=scenes, help=f"held-out scenes evaluated (default {scenes})")
    p.add_argument("--eval-seed", type=int, default=1,
                   help="their pyvf.scenes seed, not the training data's (default 1; pyvf evaluate uses 1000)")


def cmd_train(args):
    """The whole pipeline, resumable stage by stage: training scenes, codebook, tokens,
    transformer (both runs evaluated on held-out scenes as they train), then pyvf evaluate."""
    from .pipeline import train_pipeline

    def work():
        train_pipeline(args.out, args.preset, threads=args.threads, progress=not args.no_progress,
                       command=_record(args))
        print(f"pyvf train: done; the runs' curves: {os.path.join(args.out, 'codebook', 'eval.png')}, "
              f"{os.path.join(args.out, 'transformer', 'eval.png')}; the pictures: {os.path.join(args.out, 'eval')}")
    return _guarded("train", work)


def cmd_runs(args):
    """Compare training runs: each run folder's steps, wall time, changed hyperparameters and last
    held-out evaluation, as a markdown table; with --plot, each folder's eval.png redrawn."""
    def work():
        for d in args.run_dirs:
            if not os.path.exists(os.path.join(d, "config.json")):
                raise ValueError(f"{d} is not a run folder (no config.json)")
        print(runs_table(args.run_dirs), end="")
        if args.plot:
            for d in args.run_dirs:
                if os.path.exists(os.path.join(d, "eval.csv")):
                    print(f"wrote {plot_eval(d)}")
    return _guarded("runs", work)


def cli_register(subparsers):
    """Add train-codebook, tokenize and train-transformer to an argparse subparsers object."""
    p = subparsers.add_parser("train-codebook", help="train the codebook (VQ-VAE) on a dataset; resumable",
                              description=cmd_train_codebook.__doc__)
    p.add_argument("--data", required=True, help="dataset folder (pyvf.scenes.load_dataset)")
    _run_options(p, batch=16, checkpoint_every=200)
    p.add_argument("--recipe", default="small-batch", choices=sorted(CODEBOOK_RECIPES),
                   help="the defaults of --lr, --betas, --reset-dead-codes and --object-weight: "
                        + "; ".join(f"{k}: {v}" for k, v in CODEBOOK_RECIPES.items())
                        + " (default small-batch; published is the published code's, for exactness work)")
    p.add_argument("--lr", type=float, default=None, help="Adam learning rate (default: the recipe's)")
    p.add_argument("--betas", type=float, nargs=2, default=None, metavar=("B1", "B2"),
                   help="Adam's betas (default: the recipe's)")
    p.add_argument("--reset-dead-codes", type=int, default=None, metavar="EVERY",
                   help="every EVERY steps move unused codes to random encoder outputs (0: never, as "
                        "published; default: the recipe's)")
    p.add_argument("--object-weight", type=float, default=None,
                   help="loss weight of object pixels against 1 for the background (default: the recipe's)")
    _eval_options(p, every=100, scenes=32)
    p.set_defaults(func=cmd_train_codebook)

    p = subparsers.add_parser("tokenize", help="encode a dataset into token images with a codebook",
                              description=cmd_tokenize.__doc__)
    p.add_argument("--codebook", required=True, help="codebook .npz (train-codebook's codebook.npz)")
    p.add_argument("--data", required=True, help="dataset folder (pyvf.scenes.load_dataset)")
    p.add_argument("--out", required=True, help="tokens .npz to write: tokens, poses, n_embed")
    p.add_argument("--batch", type=int, default=64, help="images per encoder call (default 64)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--threads", type=int, default=None, help="threads for pyvf's C++ kernels")
    p.set_defaults(func=cmd_tokenize)

    p = subparsers.add_parser("train-transformer", help="train the transformer on a tokens file; resumable",
                              description=cmd_train_transformer.__doc__)
    p.add_argument("--tokens", required=True, help="tokens .npz (from pyvf tokenize)")
    _run_options(p, batch=16, checkpoint_every=200)
    p.add_argument("--context", type=int, default=None,
                   help="most context views per sample (default: the configuration's sequence_size - 1)")
    p.add_argument("--lr", type=float, default=1e-4, help="peak learning rate (default 1e-4, SM7)")
    p.add_argument("--warmup", type=int, default=None, help="warmup steps (default min(2000, total/10))")
    p.add_argument("--total-steps", type=int, default=None,
                   help="length of the cosine schedule (default --steps; keep it when extending a run)")
    p.add_argument("--weight-decay", type=float, default=0.01, help="AdamW decay (default 0.01)")
    p.add_argument("--max-grad-norm", type=float, default=1.0, help="per-tensor clipping norm; 0 turns it off")
    p.add_argument("--codebook", default=None,
                   help="the codebook .npz the tokens came from: the held-out evaluation renders through it "
                        "(without it, no evaluation)")
    _eval_options(p, every=200, scenes=16)
    p.add_argument("--engine", default="pyvf", choices=["pyvf", "torch"],
                   help="pyvf's kernels (default) or torch (pip install 'pyvf[torch]'): the same run, the model in "
                        "torch, checked against pyvf at every checkpoint (parity.csv)")
    p.add_argument("--device", default="cpu", help="the torch engine's device: cpu (default), cuda or cuda:N")
    p.add_argument("--precision", default="fp32", choices=["fp32", "bf16"],
                   help="the torch engine's arithmetic: fp32 (default) or bf16 autocast (weights stay float32)")
    p.set_defaults(func=cmd_train_transformer)

    from .pipeline import PRESETS
    p = subparsers.add_parser("train", help="train a ViewFormer pair from scratch, every stage resumable "
                              "(--preset quick: about 15 minutes on 2 cores)", description=cmd_train.__doc__)
    p.add_argument("--out", required=True, help="folder of the stages (scenes/, codebook/, tokens.npz, "
                                                "transformer/, eval/); run again to resume")
    p.add_argument("--preset", default="quick", choices=sorted(PRESETS),
                   help="sizes and steps of every stage: quick (default, ~15 min on 2 cores), full (the shipped "
                        "models' sizes, many hours), smoke (seconds)")
    p.add_argument("--threads", type=int, default=None, help="threads for pyvf's C++ kernels")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_train)

    p = subparsers.add_parser("runs", help="compare training runs: a markdown table of their last held-out "
                              "evaluations", description=cmd_runs.__doc__)
    p.add_argument("run_dirs", nargs="+", metavar="RUN", help="run folders (train-codebook's or train-transformer's --out)")
    p.add_argument("--plot", action="store_true", help="also redraw each run's eval.png")
    p.set_defaults(func=cmd_runs)
    return subparsers
