"""The training commands (train-codebook, tokenize, train-transformer, train, runs, export): their
arguments, and their work on files: a dataset folder or a tokens file in, a run folder out. config:
"tiny" or a JSON file of the configuration's fields (or a run's config.json)."""

import json
import os
import sys

import numpy as np

from .._threads import threads as kernel_threads
from ..models.codebook import Codebook, CodebookConfig
from ..models.transformer import Transformer, TransformerConfig
from ..train._run import CHECKPOINT, read_checkpoint
from ..train.curves import runs_table
from ..train.loops import (CODEBOOK_RECIPES, TINY_CODEBOOK, TINY_TRANSFORMER, RunOptions, TransformerRecipe,
                           held_out_set, load_tokens, save_tokens, tokenize, train_codebook, train_transformer)
from ..train.pipeline import PRESETS, train_pipeline
from .options import INTERRUPTED, add_threads, non_negative_int, positive_int


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
    opts.eval_every steps on the first 4 views of eval_scenes scenes of eval_seed (not the data's);
    recipe: train_codebook's recipe and overrides."""
    config = read_config(config, CodebookConfig, TINY_CODEBOOK)
    from ..scenes import generate_scenes, load_dataset  # at the call: tests stand a fake module in
    data, held_out, S = load_dataset(data), None, config.image_size
    if opts.eval_every:
        if getattr(data, "seed", None) == eval_seed:
            raise ValueError(f"eval_seed {eval_seed} is the training data's seed: held-out scenes need another seed")
        held_out = generate_scenes(eval_seed, eval_scenes, views=4, size=S)[0].reshape(-1, S, S, 3)
    return train_codebook(data.images, config, out, opts, eval_images=held_out, **recipe)


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
    cb = Codebook.load(codebook) if codebook else None
    if cb is not None and fingerprint is not None and (given := cb.fingerprint()) != fingerprint:
        raise ValueError(f"--codebook {codebook} is not the codebook that made {tokens_path} (fingerprints {given} "
                         f"and {fingerprint})")
    eval_set = None
    if opts.eval_every and cb is not None:
        from ..scenes import generate_scenes
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


def _record(args):
    """The command line, for config.json."""
    return {"argv": list(sys.argv), "args": {k: v for k, v in vars(args).items() if k != "func"}}


def _command(subparsers, name, cmd, help):
    """The parser of `pyvf name`, whose handler runs cmd(args): a ValueError, TypeError or OSError is
    printed, status 1; Ctrl-C prints one line, status 130."""
    def handler(args):
        try:
            cmd(args)
        except (ValueError, TypeError, OSError) as e:
            print(f"pyvf {name}: error: {e}", file=sys.stderr)
            return 1
        except KeyboardInterrupt:
            print(f"pyvf {name}: interrupted; rerun the same command (a training run resumes from its last "
                  "checkpoint)", file=sys.stderr)
            return INTERRUPTED
        return 0

    p = subparsers.add_parser(name, help=help, description=cmd.__doc__)
    p.set_defaults(func=handler)
    return p


def _run(args):
    """The options every training run takes: (RunOptions, the held-out scenes' keywords)."""
    opts = RunOptions(steps=args.steps, batch_size=args.batch, seed=args.seed, checkpoint_every=args.checkpoint_every,
                      eval_every=args.eval_every, resume=not args.no_resume, progress=not args.no_progress,
                      threads=args.threads, command=_record(args), engine=args.engine, device=args.device,
                      precision=args.precision, init=args.init)
    return opts, dict(config=args.config, eval_scenes=args.eval_scenes)


def cmd_train_codebook(args):
    """Train the codebook (VQ-VAE) on a dataset's images; rerun to resume from the last checkpoint."""
    opts, held_out = _run(args)
    codebook_run(args.data, args.out, opts, recipe=args.recipe, lr=args.lr, object_weight=args.object_weight,
                 restart=args.restart, reseat=args.reseat, kmeans=args.kmeans, schedule=args.schedule, **held_out)
    print(f"codebook: {os.path.join(args.out, 'codebook.npz')}")


def cmd_tokenize(args):
    """Encode a dataset's images into token images with a trained codebook."""
    codebook = Codebook.load(args.codebook)
    from ..scenes import load_dataset  # at the call: tests stand a fake dataset reader in
    data = load_dataset(args.data)
    with kernel_threads(args.threads):
        tokens = tokenize(codebook, data.images, progress=not args.no_progress)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    save_tokens(args.out, tokens, data.poses, codebook.config.n_embed, codebook.fingerprint())
    print(f"tokens {tokens.shape} {tokens.dtype}: {args.out}")


def cmd_train_transformer(args):
    """Train the transformer on a tokenized dataset; rerun to resume from the last checkpoint."""
    opts, held_out = _run(args)
    recipe = TransformerRecipe(lr=args.lr, warmup=args.warmup, total_steps=args.total_steps)
    transformer_run(args.tokens, args.out, opts, recipe, codebook=args.codebook, **held_out)
    print(f"transformer: {os.path.join(args.out, 'transformer.npz')}")


def cmd_train(args):
    """The whole pipeline, resumable stage by stage: training scenes, codebook, tokens,
    transformer (both runs evaluated on held-out scenes as they train), then pyvf evaluate."""
    train_pipeline(args.out, args.preset, threads=args.threads, progress=not args.no_progress,
                   command=_record(args), engine=args.engine, device=args.device, precision=args.precision)
    print(f"pyvf train: done; the runs' curves: {os.path.join(args.out, 'codebook', 'eval.png')}, "
          f"{os.path.join(args.out, 'transformer', 'eval.png')}; the pictures: {os.path.join(args.out, 'eval')}")


def cmd_runs(args):
    """Compare training runs: each run's steps, wall time, changed hyperparameters and last held-out
    evaluation, as a markdown table."""
    print(runs_table(args.run_dirs, step=args.step), end="")


def cmd_export(args):
    """Write the model of a training run's last checkpoint, as the run writes its final model at the
    end: evaluate or ship a run while it trains."""
    kind, step, path = export_run(args.run, args.output)
    print(f"{kind} at step {step}: {path}")


def _run_options(p, every, scenes):
    p.add_argument("--out", required=True, help="run folder: checkpoint.npz, log.csv, config.json, the final model")
    p.add_argument("--steps", type=int, required=True, help="total updates (a resumed run continues to it)")
    p.add_argument("--batch", type=int, default=16, help="batch size (default 16)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="initialisation and batches (default 0)")
    p.add_argument("--config", default="tiny", help='"tiny" (default) or a JSON file of the configuration')
    p.add_argument("--init", default=None, metavar="FILE", help="a fresh run starts from this model file's weights")
    p.add_argument("--checkpoint-every", type=int, default=200,
                   help="steps between checkpoints, where an interrupted run resumes (default 200)")
    p.add_argument("--no-resume", action="store_true", help="start over even if the run folder has a checkpoint")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_threads(p)
    p.add_argument("--eval-every", type=int, default=every,
                   help=f"steps between evaluations on held-out scenes (eval.csv; default {every}; 0: none)")
    p.add_argument("--eval-scenes", type=positive_int, default=scenes, help=f"held-out scenes (default {scenes})")
    _engine_options(p)


def _engine_options(p):
    p.add_argument("--engine", default="pyvf", choices=["pyvf", "torch"],
                   help="pyvf's kernels (default) or torch, checked against pyvf at every checkpoint")
    p.add_argument("--device", default="cpu", help="the torch engine's device: cpu (default), cuda or cuda:N")
    p.add_argument("--precision", default="fp32", choices=["fp32", "bf16"],
                   help="the torch engine's arithmetic: fp32 (default) or bf16 autocast")


def register(subparsers):
    """Add train-codebook, tokenize, train-transformer, train, runs and export to argparse subparsers."""
    p = _command(subparsers, "train-codebook", cmd_train_codebook, "train the codebook (VQ-VAE) on a dataset")
    p.add_argument("--data", required=True, help="dataset folder (pyvf scenes)")
    _run_options(p, every=100, scenes=32)
    p.add_argument("--recipe", default="small-batch", choices=sorted(CODEBOOK_RECIPES),
                   help="the defaults of the options below (default small-batch; published: the published code's)")
    p.add_argument("--lr", type=float, default=None, help="Adam learning rate")
    p.add_argument("--object-weight", type=float, default=None, help="loss weight of object pixels (background: 1)")
    p.add_argument("--restart", default=None, choices=["batch", "worst"],
                   help="dead codes restart at random encoder outputs (batch) or the worst represented ones")
    p.add_argument("--reseat", type=int, default=None, metavar="N",
                   help="each reset also moves up to N codes of least utility")
    p.add_argument("--kmeans", type=int, default=None, metavar="ITERS",
                   help="initialise the codes by ITERS k-means iterations on encoder outputs (0: uniform)")
    p.add_argument("--schedule", default=None, choices=["constant", "cosine"],
                   help="the learning rate: constant, or a cosine from --lr to 0 at the last step")

    p = _command(subparsers, "tokenize", cmd_tokenize, "encode a dataset into token images with a codebook")
    p.add_argument("--codebook", required=True, help="codebook .npz (train-codebook's codebook.npz)")
    p.add_argument("--data", required=True, help="dataset folder (pyvf scenes)")
    p.add_argument("--out", required=True, help="tokens .npz to write")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_threads(p)

    p = _command(subparsers, "train-transformer", cmd_train_transformer, "train the transformer on a tokens file")
    p.add_argument("--tokens", required=True, help="tokens .npz (from pyvf tokenize)")
    p.add_argument("--codebook", default=None, help="the tokens' codebook .npz: the held-out evaluation needs it")
    _run_options(p, every=200, scenes=16)
    p.add_argument("--lr", type=float, default=1e-4, help="peak learning rate (default 1e-4)")
    p.add_argument("--warmup", type=int, default=None, help="warmup steps (default min(2000, total/10))")
    p.add_argument("--total-steps", type=int, default=None, help="length of the cosine schedule (default --steps)")

    p = _command(subparsers, "train", cmd_train, "train a ViewFormer pair from scratch, every stage resumable")
    p.add_argument("--out", required=True, help="folder of the stages; run again to resume")
    p.add_argument("--preset", default="quick", choices=sorted(PRESETS),
                   help="sizes and steps of every stage: quick (default, ~15 min on 2 cores), full, smoke (seconds)")
    add_threads(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    _engine_options(p)

    p = _command(subparsers, "runs", cmd_runs, "compare training runs' last held-out evaluations")
    p.add_argument("run_dirs", nargs="+", metavar="RUN", help="run folders")
    p.add_argument("--step", type=int, default=None, help="each run's last evaluation at or before STEP")

    p = _command(subparsers, "export", cmd_export, "the model of a training run's last checkpoint, as a model file")
    p.add_argument("run", metavar="RUN", help="a run folder or its checkpoint.npz")
    p.add_argument("-o", "--output", required=True, help="the model .npz to write")
    return subparsers
