"""The training commands' arguments (train-codebook, tokenize, train-transformer, train, runs,
export); the work is pyvf.train.tasks' and train_pipeline's."""

import os
import sys

from ..train import tasks
from ..train.curves import runs_table
from ..train.loops import CODEBOOK_RECIPES, RunOptions, TransformerRecipe
from ..train.pipeline import PRESETS, train_pipeline
from .options import INTERRUPTED, add_threads, non_negative_int, positive_int


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
    """Train the codebook (VQ-VAE) on a dataset's images; resumable."""
    opts, held_out = _run(args)
    tasks.codebook_run(args.data, args.out, opts, recipe=args.recipe, lr=args.lr, object_weight=args.object_weight,
                       restart=args.restart, reseat=args.reseat, kmeans=args.kmeans, **held_out)
    print(f"codebook: {os.path.join(args.out, 'codebook.npz')}")


def cmd_tokenize(args):
    """Encode a dataset's images into token images with a trained codebook."""
    tokens = tasks.tokenize_dataset(args.codebook, args.data, args.out, progress=not args.no_progress,
                                    threads=args.threads)
    print(f"tokens {tokens.shape} {tokens.dtype}: {args.out}")


def cmd_train_transformer(args):
    """Train the transformer on a tokenized dataset; resumable."""
    opts, held_out = _run(args)
    recipe = TransformerRecipe(lr=args.lr, warmup=args.warmup, total_steps=args.total_steps)
    tasks.transformer_run(args.tokens, args.out, opts, recipe, codebook=args.codebook, **held_out)
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
    kind, step, path = tasks.export_run(args.run, args.output)
    print(f"{kind} at step {step}: {path}")


def _run_options(p, every, scenes):
    p.add_argument("--out", required=True, help="run folder: checkpoint.npz, log.csv, config.json, the final model")
    p.add_argument("--steps", type=int, required=True, help="total updates (a resumed run continues to it)")
    p.add_argument("--batch", type=int, default=16, help="batch size (default 16)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="initialisation and batches (default 0)")
    p.add_argument("--config", default="tiny", help='"tiny" (default) or a JSON file of the configuration')
    p.add_argument("--init", default=None, metavar="FILE", help="a fresh run starts from this model file's weights")
    p.add_argument("--checkpoint-every", type=int, default=200, help="steps between checkpoints (default 200)")
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
    p = _command(subparsers, "train-codebook", cmd_train_codebook, "train the codebook (VQ-VAE) on a dataset; "
                 "resumable")
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

    p = _command(subparsers, "tokenize", cmd_tokenize, "encode a dataset into token images with a codebook")
    p.add_argument("--codebook", required=True, help="codebook .npz (train-codebook's codebook.npz)")
    p.add_argument("--data", required=True, help="dataset folder (pyvf scenes)")
    p.add_argument("--out", required=True, help="tokens .npz to write")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_threads(p)

    p = _command(subparsers, "train-transformer", cmd_train_transformer, "train the transformer on a tokens file; "
                 "resumable")
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
