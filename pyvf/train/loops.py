"""Training loops: the codebook on images, tokenization, the transformer on tokens (docs/math.md §4, §5).

    cb = train_codebook(images, TINY_CODEBOOK, "runs/cb", steps=20_000)  # images (scenes, views, Hi, Wi, 3) uint8
    tokens = tokenize(cb, images)                                         # (scenes, views, k, k) int16
    tf = train_transformer(tokens, poses, TINY_TRANSFORMER, "runs/tf", steps=50_000)

Each loop checkpoints its run folder atomically (see _run.py for the layout) every
`checkpoint_every` steps, at the end, and at Ctrl-C (SIGINT, in the main thread: the step under
way finishes and is saved, then KeyboardInterrupt; a second Ctrl-C raises at once), and a call
with resume=True continues from the checkpoint to exactly the parameters, optimiser moments and
EMA buffers an uninterrupted run reaches, bit for bit, on the same kernel path (pyvf.show_config:
baseline, avx2 and avx512 may round differently; 1 and 2 threads were measured to give the same
bits). That needs every batch to be a pure function of (seed, step):
`codebook_batch` and `transformer_batch` draw from np.random.default_rng([seed, step]), so
no generator state is saved.
"""

import dataclasses
import os
import sys

import numpy as np

from .. import _checks
from .._io import atomic_savez, load_npz
from .._threads import threads as kernel_threads
from ..models.codebook import Codebook, CodebookConfig
from ..evaluate.health import (
    CODEBOOK_HEALTH,
    codebook_health,
    health_contexts,
    transformer_health,
    transformer_health_columns,
)
from ..evaluate.metrics import encode_images
from ..geometry import _check_unit
from .optim import Adam, AdamW, WarmupCosine, published_weight_decay
from ..models.transformer import Transformer, TransformerConfig
from ._run import CHECKPOINT, Run, _diff, file_sha256, fingerprint, integer, jsonable, positive_int, real, resume_point
from .batches import codebook_batch, transformer_batch
from .curves import plot_eval
from .step import check_clipping, codebook_train_step, transformer_step
from .torch_codebook_engine import check_codebook_engine, parity_images
from .torch_engine import Follower, TorchTransformer, check_engine, data_parallel, log_parity, parity_batch

# 64x64 images -> 8x8 tokens (3 downsamplings, where the paper's 128x128 needs 4); the paper's
# configuration (docs/math.md §4) at a quarter of the channels, one ResnetBlock per level and no
# attention, so that a step of batch 16 takes about 2 s on 2 cores. 256 codes: SM7 scenes have
# few colours and one object (the paper's 1024 serve real photographs).
TINY_CODEBOOK = CodebookConfig(ch=32, ch_mult=(1, 1, 2, 2), num_res_blocks=1, attn_resolutions=(),
                               z_channels=64, embed_dim=64, n_embed=256, image_size=64)

TINY_TRANSFORMER = TransformerConfig(
    n_embeddings=256,  # = TINY_CODEBOOK.n_embed
    n_head=4,  # dh = 128 / 4 = 32: half the paper's 64, four heads to keep several attention patterns
    d_model=128,  # the low end of 128..192: a B=16 step took 2.8 s on 2 cores, d=192 3.9 s
    n_layer=4,
    token_image_size=8,  # = TINY_CODEBOOK.token_size: L = 64 tokens per view
    sequence_size=6,  # SM7 in the paper: context 5, so n = 6 views per sequence
    n_loss_skip=1,  # view 0 is pure context; every other view is a target with context 1..5
    pose_multiplier=0.2,  # SM7: positions scaled by 0.2 (docs/math.md §5)
)

# Codebook training recipes: Adam's settings, dead-code restarts and the loss weight of object
# pixels. "published" is the published code's (docs/math.md §4), kept for exactness work: it pairs
# lr 1.584e-3 and betas (0.5, 0.9) with a batch of 352. With the batches of 16 a CPU affords
# the same settings collapse the latent (measured on SM7: 9 to 31 codes in use in the first 300
# steps, the decoded colours on one line); "small-batch", the default, is chosen by the
# ablations in docs/models-remarks.md: at 1000 steps on SM7 its Adam settings kept 252 codes
# and a latent of effective rank 27 where the published ones kept 11 and 5, and weighting the
# objects' pixels 4 times the background's (a tenth of an SM7 image is object) raised the
# objects' colour_r2 from 0.45 to 0.79 and lowered the whole image's MAE from 5.5 to 4.9.
# restart, reseat and kmeans (issue 48): where dead codes restart ("batch": vectors drawn uniformly,
# "worst": the worst represented), how many low-utility codes each reset moves as well, and the
# Lloyd iterations of a k-means initialisation of the codes from data (0: the uniform one); see
# EMAQuantizer.reset_dead_codes and init_kmeans.
_CODES = {"restart": "batch", "reseat": 0, "kmeans": 0}
CODEBOOK_RECIPES = {
    "published": {"lr": 1.584e-3, "betas": (0.5, 0.9), "reset_dead_codes": 0, "object_weight": 1.0, **_CODES},
    "small-batch": {"lr": 3e-4, "betas": (0.9, 0.99), "reset_dead_codes": 20, "object_weight": 4.0, **_CODES},
}
KMEANS_BATCHES = 4  # the k-means initialisation clusters the encoder's outputs of this many batches

CODEBOOK_LOG = ["loss", "rec_loss", "commitment", "perplexity", "usage", "lr"]
TRANSFORMER_LOG = ["loss", "ce_loss", "pose_loss", "grad_norm", "lr"]


# ---------------------------------------------------------------------------------------
# data checks and batches


def _check_images(images, config, name="images"):
    """images: uint8 (scenes, views, Hi, Wi, C) or (M, Hi, Wi, C) -> a (M, Hi, Wi, C) view.
    name: the argument's, for the errors (eval_images of train_codebook, say)."""
    if not isinstance(images, np.ndarray) or images.dtype != np.uint8:
        raise TypeError(f"{name} must be a uint8 numpy array, got {getattr(images, 'dtype', type(images).__name__)}")
    S, C = config.image_size, config.in_channels
    if images.ndim not in (4, 5) or images.shape[-3:] != (S, S, C) or images.size == 0:
        raise ValueError(f"{name} must have shape (scenes, views, {S}, {S}, {C}) or (M, {S}, {S}, {C}) "
                         f"for this codebook, got {images.shape}")
    return images.reshape(-1, S, S, C)


def _check_tokens_poses(tokens, poses, config):
    if not isinstance(tokens, np.ndarray) or tokens.dtype.kind not in "iu":
        raise TypeError("tokens must be an integer numpy array, got "
                        f"{getattr(tokens, 'dtype', type(tokens).__name__)}")
    k = config.token_image_size
    if tokens.ndim != 4 or tokens.shape[2:] != (k, k) or tokens.size == 0:
        raise ValueError(f"tokens must have shape (scenes, views, {k}, {k}), got {tokens.shape}")
    lo, hi = int(tokens.min()), int(tokens.max())
    if lo < 0 or hi >= config.n_embeddings:
        raise ValueError(f"tokens must be in [0, {config.n_embeddings}) (config.n_embeddings), got [{lo}, {hi}]")
    _checks.float_array("poses", poses)
    if poses.shape != tokens.shape[:2] + (7,):
        raise ValueError(f"poses must have shape (scenes, views, 7) = {tokens.shape[:2] + (7,)}, got {poses.shape}")
    if not np.isfinite(poses).all():
        raise ValueError("poses contain NaN or inf")
    # as the batches hold them (in the model's dtype), here rather than at the first step that
    # draws a bad view, which may come thousands of steps in and name an index into its batch
    _check_unit("the quaternions of poses", poses[..., 3:].astype(config.dtype))  # at (scene, view)


class _Threads:
    """`--threads` for a block: pyvf.threads(n) (the kernels and numpy's BLAS), n checked first
    so that a bad value raises naming the argument before anything runs."""

    def __init__(self, n):
        # an int (a numpy integer passes the check, and config.json records it: JSON takes ints)
        self.n, self._block = None if n is None else positive_int("threads", n), None

    def __enter__(self):
        self._block = kernel_threads(self.n)
        return self._block.__enter__()

    def __exit__(self, *exc):
        return self._block.__exit__(*exc)


def _warm_start(init, cls, config, hyper, out_dir, resume):
    """train_codebook's and train_transformer's `init`: None, or the path of a model file written
    by cls.save (cls: Codebook or Transformer) whose configuration is the run's `config`.
    Returns (hyper with the file's record, "init": {"path": its name, "sha256": its bytes'}, the
    file's state_dict()), or (hyper, None) without one (no "init" entry: runs from before the
    option resume as they were). The file counts at step 0 only: when the run resumes from
    out_dir's checkpoint it is not read (it may have changed or gone since), the checkpoint holds
    the run's state and Run keeps its record; a file other than the one the run started from is
    named in a note on stderr. Errors name init and come before the run folder is touched."""
    if init is None:
        return hyper, None
    try:
        path = os.fspath(init)
    except TypeError:
        raise TypeError(f"init must be a path to a {cls.FILE_KIND} model file, got {type(init).__name__}") from None
    meta = resume_point(out_dir, resume)
    if meta is not None and meta.get("kind") == cls.FILE_KIND:  # (another kind's: Run refuses the folder)
        _note_init_not_read(path, meta, os.path.join(os.fspath(out_dir), CHECKPOINT))
        return hyper, None
    try:
        model = cls.load(path)
    except FileNotFoundError as e:
        raise FileNotFoundError(f"init {path}: no such file") from e
    except ValueError as e:  # CheckpointError: corrupt, or another kind of model
        raise ValueError(f"init {path} is not a {cls.FILE_KIND} model file ({cls.__name__}.save's): {e}") from e
    saved, now = jsonable(dataclasses.asdict(model.config)), jsonable(dataclasses.asdict(config))
    differ = _diff(saved, now)
    if differ:
        said = "; ".join(f"{k}: {saved.get(k)!r} in the file, {now.get(k)!r} in the run" for k in differ)
        raise ValueError(f"init {path} holds a {cls.__name__} of another configuration (differs in {differ}: "
                         f"{said}): start from a model of the run's configuration, or run with the file's")
    record = {"path": os.path.basename(path), "sha256": file_sha256(path)}
    return {**hyper, "init": record}, model.state_dict()


def _note_init_not_read(path, meta, ckpt_path):
    """A resume with init: a note on stderr when the file is not the one the run started from
    (other bytes, or gone), saying that it is not read: the checkpoint holds the run's state."""
    started = meta["hyper"].get("init")
    if started is not None and os.path.isfile(path) and file_sha256(path) == started.get("sha256"):
        return  # the run's own file (any name, any folder): nothing to say
    origin = (f"{started.get('path')} of sha256 {started.get('sha256')}" if started is not None
              else "the seed's initialisation")
    print(f"pyvf: note: init {os.path.abspath(path)} is not read: {ckpt_path} resumes the run from step "
          f"{meta['step']}, and a model file counts at step 0 only (this run started from {origin}); start over "
          "from it with resume=False (--no-resume) or another output folder", file=sys.stderr)


# ---------------------------------------------------------------------------------------
# the codebook


def _checkpoint(run, step, state, opt, check):
    """The loops' checkpoint after `step`, when due or when Ctrl-C asked the run to stop (then
    KeyboardInterrupt after the save): the engine's check(out_dir, step) first (the torch engine's
    parity: a divergent model is not checkpointed), then run.save."""
    stop = run.stop_requested()  # read once: a Ctrl-C from here on stops after the next step
    if stop or run.checkpoint_due(step):
        if check is not None:
            check(run.out_dir, step)
        run.save(step, state(), opt)
    if stop:
        raise KeyboardInterrupt


def _recipe(recipe, lr, betas, reset_dead_codes, object_weight, restart, reseat, kmeans):
    """train_codebook's lr, betas, reset_dead_codes, object_weight, restart, reseat and kmeans:
    the recipe's (a name of CODEBOOK_RECIPES) where None, each checked."""
    if recipe not in CODEBOOK_RECIPES:
        raise ValueError(f"recipe must be one of {sorted(CODEBOOK_RECIPES)}, got {recipe!r}")
    r = CODEBOOK_RECIPES[recipe]
    lr = real("lr", r["lr"] if lr is None else lr)
    betas = r["betas"] if betas is None else betas
    if (not isinstance(betas, (tuple, list)) or len(betas) != 2
            or not all(0 <= real("betas", b) < 1 for b in betas)):
        raise ValueError(f"betas must be two numbers in [0, 1), got {betas!r}")
    betas = (float(betas[0]), float(betas[1]))
    reset_dead_codes = integer("reset_dead_codes", r["reset_dead_codes"] if reset_dead_codes is None
                               else reset_dead_codes, 0)
    object_weight = real("object_weight", r["object_weight"] if object_weight is None else object_weight)
    if object_weight == 0:
        raise ValueError("object_weight must be positive")
    restart = r["restart"] if restart is None else restart
    if restart not in ("batch", "worst"):
        raise ValueError(f"restart must be 'batch' or 'worst', got {restart!r}")
    reseat = integer("reseat", r["reseat"] if reseat is None else reseat, 0)
    kmeans = integer("kmeans", r["kmeans"] if kmeans is None else kmeans, 0)
    codes = {"restart": restart, "reseat": reseat, "kmeans": kmeans}
    # what the run records beyond the base hyperparameters: absent at their defaults (object_weight
    # 1.0, _CODES), so that runs from before these options resume as they were
    recorded = {"object_weight": object_weight} if object_weight != 1.0 else {}
    recorded.update({k: v for k, v in codes.items() if v != _CODES[k]})
    return lr, betas, reset_dead_codes, object_weight, codes, recorded


def _codebook_eval(eval_images, eval_every, config):
    """train_codebook's held-out evaluation: (eval_every, the images checked or None, their
    fingerprint, None when nothing is evaluated). A set not evaluated on (eval_every 0) is not
    the run's: not recorded, so a later call may evaluate on any set, and a resume that evaluates
    nothing passes whatever set it names."""
    eval_every = integer("eval_every", eval_every, 0)
    if eval_images is not None:
        eval_images = _check_images(eval_images, config, "eval_images")
    evaluating = eval_images is not None and eval_every > 0
    return eval_every, eval_images, fingerprint(eval_images) if evaluating else None


def _kmeans_start(model, flat, iters, batch_size, seed):
    """A fresh run's codes by k-means (EMAQuantizer.init_kmeans, `iters` Lloyd iterations; 0 keeps
    the uniform initialisation) on the encoder's outputs of KMEANS_BATCHES batches drawn as step 0's."""
    if iters:
        x = codebook_batch(flat, KMEANS_BATCHES * batch_size, seed, 0, model.config.dtype)  # (B, C, Hi, Wi)
        z = model._encoder(None, x)
        model.quantizer.init_kmeans(z, iters, batch_size, rng=np.random.default_rng([seed, 0, 2]),
                                    empty=model.empty_patches(x))


def _codebook_and_optimiser(run, config, seed, lr, betas, init_state=None):
    """A new Codebook and its Adam; both as the run's checkpoint left them when it resumes. A fresh
    run with init_state (_warm_start's) starts from its parameters and EMA buffers, its Adam fresh
    (zero moments, step 0); a resumed run ignores init_state: the checkpoint holds the run's state."""
    model = Codebook(config, seed=seed)
    if run.resumed:
        run.restore("model", model.load_official, run.model_state)  # replaces model.params
    elif init_state is not None:
        # Codebook.save writes the quantizer's four buffers and Codebook.load requires them, so
        # the EMA state is the file's too: the hidden cluster sizes and sums with the counter
        # whose bias correction 1 - decay^counter they were accumulated under (docs/math.md §4).
        # The codes then move from the file's by EMA steps, as in the run that wrote it. Zeroed
        # averages and counter would not: at counter 1 the correction undoes the (1 - decay)
        # weight, so the first update would set every code to that batch's mean of the vectors
        # that chose it, and every code the batch left unused to 0.
        model.load_official(init_state)  # replaces model.params and the quantizer's buffers
    opt = Adam(model.params, lr, betas=betas)  # after the restore: on the params it put in place
    if run.resumed:
        run.restore("optimizer", opt.load_state_dict, run.optimizer_state)
    return model, opt


def _codebook_engine(engine, model, opt, parity, device, precision):
    """train_codebook's engine: (step(x, w) -> the log's values but lr, reset(x, rng): the
    dead-code restart after the step, state() -> the state dict, current() -> the model, the
    optimiser the loop reads, check(out_dir, step) before each checkpoint or None). The torch
    engine's check is the parity of the torch model and pyvf's on the images `parity`."""
    if engine != "torch":
        def step(x, w):
            out = codebook_train_step(model, opt, x, pixel_weights=w)
            return {"loss": out.loss, "rec_loss": out.rec_loss, "commitment": out.commitment_loss,
                    "perplexity": out.perplexity, "usage": out.usage}

        def reset(x, rng, **codes):
            z = model._encoder([], x)  # (B, D, k, k) with the updated weights
            return model.quantizer.reset_dead_codes(z, rng=rng, empty=model.empty_patches(x), **codes)

        return step, reset, model.state_dict, lambda: model, opt, None
    from .torch_codebook_engine import TorchCodebook
    eng = TorchCodebook(model, opt, device=device, precision=precision)

    def check(out_dir, step):  # before the save: a divergent model is not checkpointed
        log_parity(out_dir, step, eng.parity(parity))

    return eng.step, eng.reset_dead_codes, eng.state_dict, eng.to_pyvf, eng.opt, check


def train_codebook(images, config, out_dir, *, steps, batch_size=16, recipe="small-batch", lr=None, betas=None,
                   reset_dead_codes=None, object_weight=None, restart=None, reseat=None, kmeans=None, seed=0,
                   checkpoint_every=200, log_every=10, eval_images=None, eval_every=0, resume=True, progress=True,
                   threads=None, command=None, engine="pyvf", device="cpu", precision="fp32", init=None):
    """Train a Codebook with Adam and the EMA quantizer (docs/math.md §4).

    images: uint8 (scenes, views, Hi, Wi, C) or (M, Hi, Wi, C), Hi = Wi = config.image_size.
    out_dir: the run folder (created): checkpoint.npz, log.csv, config.json, and at the end
        codebook.npz (Codebook.load reads it).
    steps: the total number of updates; a resumed run continues to it from its checkpoint.
    recipe: a name of CODEBOOK_RECIPES, the defaults of lr, betas (Adam's), reset_dead_codes
        and object_weight; each of those given overrides the recipe's.
    object_weight: the loss weight of object pixels (health.object_mask) against 1 for the
        background (1.0: the plain mean, as published).
    eval_images: None, or held-out uint8 views (M, Hi, Wi, C): every eval_every steps (0:
        never; then the set is not the run's), at the last step and before the first of a fresh
        run, health.codebook_health on them is appended to out_dir/eval.csv (reads the model only).
    resume: continue from out_dir/checkpoint.npz when there is one (its configuration and
        hyperparameters must be these); False starts over, overwriting the folder's files.
    threads: the C++ kernels' thread count during the call (None: as it is).
    command: JSON-able record of the command line, written to config.json.
    reset_dead_codes: every this many steps (0: never, the published behaviour), codes whose
        EMA cluster size fell below 1e-3 are moved to random encoder outputs of that step's
        batch (EMAQuantizer.reset_dead_codes, random from (seed, step): resumes stay exact).
        Without it a small codebook trained from the uniform initialisation can collapse onto a
        few codes (measured on SM7: 9 of 256 codes in use at step 80).
    restart, reseat: where dead codes restart ("batch" or "worst") and how many low-utility codes
        each reset moves too (EMAQuantizer.reset_dead_codes); kmeans: 0, or the Lloyd iterations
        of a fresh run's k-means initialisation of the codes on the encoder's outputs of
        KMEANS_BATCHES batches (EMAQuantizer.init_kmeans). Each defaults to the recipe's.
    engine, device, precision: as train_transformer's (torch_codebook_engine.TorchCodebook: the
        same run with the model in torch, parity.csv at every checkpoint; one process).
    init: None, or a Codebook.save file of this configuration: a fresh run starts from its weights
        and EMA buffers instead of the seed's, Adam fresh. A resume does not read it (the
        checkpoint holds the run's state; a file other than the run's own is named in a note).
    Returns the trained Codebook."""
    if not isinstance(config, CodebookConfig):
        raise TypeError(f"config must be a CodebookConfig, got {type(config).__name__}")
    flat = _check_images(images, config)  # (M, Hi, Wi, C)
    batch_size = positive_int("batch_size", batch_size)
    seed = integer("seed", seed, 0)
    lr, betas, reset_dead_codes, object_weight, codes, recorded = _recipe(recipe, lr, betas, reset_dead_codes,
                                                                          object_weight, restart, reseat, kmeans)
    eval_every, eval_images, eval_fp = _codebook_eval(eval_images, eval_every, config)
    evaluating = eval_fp is not None
    hyper = {"batch_size": batch_size, "lr": lr, "betas": betas, "seed": seed, "reset_dead_codes": reset_dead_codes,
             "data": {"shape": images.shape, "fingerprint": fingerprint(images)}, **recorded}
    check_codebook_engine(engine, device, precision, config.dtype)
    threads_set = _Threads(threads)  # checked before the run folder is touched
    hyper, init_state = _warm_start(init, Codebook, config, hyper, out_dir, resume)
    call = {"command": command, "threads": threads_set.n, "recipe": recipe, "engine": engine, "device": device,
            "precision": precision, "eval": None if eval_fp is None else {"every": eval_every, "fingerprint": eval_fp}}
    with threads_set:  # before the Run: config.json records the threads the run uses
        run = Run(out_dir, "codebook", dataclasses.asdict(config), hyper, CODEBOOK_LOG, final="codebook.npz",
                  steps=steps, resume=resume, progress=progress, checkpoint_every=checkpoint_every, log_every=log_every,
                  call=call, eval_columns=None if eval_fp is None else CODEBOOK_HEALTH, eval_fingerprint=eval_fp)
        model, opt = _codebook_and_optimiser(run, config, seed, lr, betas, init_state)
        if not run.resumed and init_state is None:
            _kmeans_start(model, flat, codes["kmeans"], batch_size, seed)
        step, reset, state, current, opt, check = _codebook_engine(
            engine, model, opt, parity_images(flat, seed, config.dtype), device, precision)
        with run:
            if evaluating and not run.resumed:
                run.log_eval(0, codebook_health(current(), eval_images))
                plot_eval(run.out_dir)
            for t in run.steps():
                weighted = object_weight != 1.0
                x = codebook_batch(flat, batch_size, seed, t, config.dtype, object_weight if weighted else None)
                x, w = x if weighted else (x, None)  # (B, C, Hi, Wi), (B, 1, Hi, Wi)
                lr_t = opt.lr_at(opt.step_count)
                values = step(x, w)
                if reset_dead_codes and t % reset_dead_codes == 0:
                    reset(x, np.random.default_rng([seed, t, 1]), restart=codes["restart"], reseat=codes["reseat"])
                run.log(t, {**values, "lr": lr_t})
                if evaluating and run.eval_due(t, eval_every):
                    run.log_eval(t, codebook_health(current(), eval_images))
                    plot_eval(run.out_dir)  # eval.png: the curves so far
                _checkpoint(run, t, state, opt, check)
        run.save_final(state())
        return current()


def tokenize(codebook, images, batch_size=64, progress=False):
    """images uint8 (scenes, views, Hi, Wi, C) or (M, Hi, Wi, C) -> codebook.encode's codes,
    (scenes, views, k, k) or (M, k, k), as int16 (int32 when n_embed > 32768)."""
    if not isinstance(codebook, Codebook):
        raise TypeError(f"codebook must be a Codebook, got {type(codebook).__name__}")
    flat = _check_images(images, codebook.config)  # (M, Hi, Wi, C)
    batch_size = positive_int("batch_size", batch_size)
    dtype = np.int16 if codebook.config.n_embed <= np.iinfo(np.int16).max + 1 else np.int32
    out = encode_images(codebook, flat, batch_size, dtype, progress="tokenize" if progress else None)  # (M, k, k)
    return out.reshape(images.shape[:-3] + out.shape[1:])


def held_out_set(codebook, images, poses):
    """train_transformer's eval_set: held-out scenes images uint8 (n, V, S, S, 3) and poses
    (n, V, 7) with their tokens (n, V, L) int64 by this codebook."""
    n, V = images.shape[:2]
    tokens = tokenize(codebook, images).reshape(n, V, -1).astype(np.int64)
    return {"codebook": codebook, "images": images, "poses": poses, "tokens": tokens}


def save_tokens(path, tokens, poses, n_embed, codebook_fingerprint=None):
    """Write a tokenized dataset atomically: tokens (scenes, views, k, k) ints in [0, n_embed),
    poses (scenes, views, 7) floats, n_embed (the codebook size the tokens index) and the
    codebook's fingerprint (Codebook.fingerprint; None: not recorded)."""
    n_embed = positive_int("n_embed", n_embed)
    if not isinstance(tokens, np.ndarray) or tokens.dtype.kind not in "iu" or tokens.ndim != 4:
        raise TypeError("tokens must be an integer numpy array (scenes, views, k, k)")
    if not isinstance(poses, np.ndarray) or poses.dtype.kind != "f" or poses.shape != tokens.shape[:2] + (7,):
        raise ValueError(f"poses must be a float array of shape {tokens.shape[:2] + (7,)}, got "
                         f"{getattr(poses, 'dtype', None)} {getattr(poses, 'shape', None)}")
    if tokens.size and (tokens.min() < 0 or tokens.max() >= n_embed):
        raise ValueError(f"tokens must be in [0, n_embed={n_embed})")
    extra = {} if codebook_fingerprint is None else {"codebook_fingerprint": str(codebook_fingerprint)}
    atomic_savez(path, tokens=tokens, poses=poses, n_embed=np.int64(n_embed), **extra)


def load_tokens(path):
    """Read save_tokens' file -> (tokens (scenes, views, k, k), poses (scenes, views, 7), n_embed,
    the codebook's fingerprint or None when the file does not record it)."""
    f = load_npz(path, "tokens file", required=("tokens", "poses", "n_embed"))
    fingerprint = str(f["codebook_fingerprint"]) if "codebook_fingerprint" in f else None
    return f["tokens"], f["poses"], int(f["n_embed"]), fingerprint


# ---------------------------------------------------------------------------------------
# the transformer


def _transformer_hyper(tokens, poses, config, steps, batch_size, context, lr, warmup, total_steps, weight_decay,
                       max_grad_norm, clip_mode, seed, codebook_fingerprint):
    """train_transformer's arguments checked: (the run's hyperparameters, the WarmupCosine schedule,
    steps); the hyperparameters hold batch_size, views (N), lr, warmup, total_steps, weight_decay,
    clipping, seed, the data's fingerprint and the codebook's (when known)."""
    batch_size = positive_int("batch_size", batch_size)
    steps = positive_int("steps", steps)
    seed = integer("seed", seed, 0)
    lr, weight_decay = real("lr", lr), real("weight_decay", weight_decay)
    n_views = 1 + (config.sequence_size - 1 if context is None else integer("context", context, 0))  # N
    if n_views <= config.n_loss_skip:
        raise ValueError(f"context={n_views - 1} leaves no loss target: a sample needs more than "
                         f"n_loss_skip={config.n_loss_skip} views")
    if n_views > tokens.shape[1]:
        raise ValueError(f"context={n_views - 1} needs {n_views} distinct views per scene, "
                         f"tokens has {tokens.shape[1]}")
    total_steps = steps if total_steps is None else positive_int("total_steps", total_steps)
    if total_steps < steps:
        raise ValueError(f"steps={steps} runs past total_steps={total_steps}, the schedule's end: its last "
                         f"{steps - total_steps} steps would run at learning rate 0. Ask for at most total_steps "
                         "steps, or a longer schedule (total_steps >= steps) in a run of its own")
    warmup = min(2000, total_steps // 10) if warmup is None else integer("warmup", warmup, 0)
    if warmup >= total_steps:  # here: WarmupCosine would name its own warmup_steps
        raise ValueError(f"warmup={warmup} must be less than total_steps={total_steps} (total_steps is steps when "
                         "not given): the schedule warms up, then decays over the steps left")
    schedule = WarmupCosine(lr, warmup, total_steps)
    max_grad_norm = check_clipping(max_grad_norm, clip_mode)
    hyper = {"batch_size": batch_size, "views": n_views, "lr": lr, "warmup": int(warmup),
             "total_steps": total_steps, "weight_decay": weight_decay, "eps": 1e-8, "eps_convention": "keras",
             "max_grad_norm": None if max_grad_norm is None else float(max_grad_norm), "clip_mode": clip_mode,
             "seed": seed, "data": {"shape": tokens.shape, "fingerprint": fingerprint(tokens, poses)}}
    if codebook_fingerprint is not None:
        hyper["codebook_fingerprint"] = str(codebook_fingerprint)
    return hyper, schedule, steps


def _check_eval_set(eval_set, config):
    """train_transformer's eval_set, each entry checked and named: a Codebook whose tokens the
    transformer of `config` reads, uint8 images (n, V, S, S, C) of its size, float64 poses
    (n, V, 7) of unit quaternions, integer tokens (n, V, L) in [0, n_embeddings). Checked when
    the call starts: the evaluation would fail at its first row, after the run folder was
    touched (in a resumed run, after eval_every steps of training), naming its own internals."""
    if not isinstance(eval_set, dict) or set(eval_set) != {"codebook", "images", "poses", "tokens"}:
        raise ValueError("eval_set must be a dict of codebook, images, poses and tokens (held_out_set's)")
    cb, images, poses, tokens = (eval_set[k] for k in ("codebook", "images", "poses", "tokens"))
    if not isinstance(cb, Codebook):
        raise TypeError(f"eval_set['codebook'] must be a Codebook, got {type(cb).__name__}")
    c, k = cb.config, config.token_image_size
    if (c.n_embed, c.token_size) != (config.n_embeddings, k):
        raise ValueError(f"eval_set['codebook'] makes {c.token_size}x{c.token_size} token images of {c.n_embed} "
                         f"codes; the transformer reads {k}x{k} of {config.n_embeddings} (config.token_image_size, "
                         "config.n_embeddings): evaluate through the codebook its tokens came from")
    _check_images(images, c, "eval_set['images']")
    if images.ndim != 5:
        raise ValueError(f"eval_set['images'] must have shape (scenes, views, {c.image_size}, {c.image_size}, "
                         f"{c.in_channels}), got {images.shape}")
    n, V = images.shape[:2]
    if not isinstance(poses, np.ndarray) or poses.dtype != np.float64:  # the evaluation's scores are float64
        raise TypeError("eval_set['poses'] must be a float64 numpy array (as pyvf.scenes.generate_scenes makes "
                        f"them), got {getattr(poses, 'dtype', type(poses).__name__)}")
    if poses.shape != (n, V, 7):
        raise ValueError(f"eval_set['poses'] must have shape (scenes, views, 7) = {(n, V, 7)}, got {poses.shape}")
    _checks.finite("eval_set['poses']", poses)
    _check_unit("eval_set['poses'][..., 3:]", poses[..., 3:].astype(config.dtype))  # as the model reads them
    _checks.int_array("eval_set['tokens']", tokens)
    if tokens.shape != (n, V, k * k):
        raise ValueError(f"eval_set['tokens'] must have shape (scenes, views, L) = {(n, V, k * k)} "
                         f"(held_out_set's), got {tokens.shape}")
    if tokens.size and (tokens.min() < 0 or tokens.max() >= config.n_embeddings):
        raise ValueError(f"eval_set['tokens'] must be in [0, {config.n_embeddings}) (config.n_embeddings), got "
                         f"[{int(tokens.min())}, {int(tokens.max())}]")


def _transformer_eval(eval_set, eval_every, config):
    """train_transformer's held-out evaluation, eval_set and eval_every checked: (eval_every, its
    record for config.json, the columns of eval.csv, health(model) -> the row of transformer_health
    at health_contexts); all but eval_every None without eval_set or with eval_every 0 (a set not
    evaluated on is not the run's: not recorded, as train_codebook's eval_images)."""
    eval_every = integer("eval_every", eval_every, 0)
    if eval_set is None:
        return eval_every, None, None, None
    _check_eval_set(eval_set, config)
    if eval_every == 0:
        return eval_every, None, None, None
    e = eval_set
    contexts = health_contexts(config, e["images"].shape[1])
    if not contexts:
        raise ValueError(f"eval_set's scenes have {e['images'].shape[1]} views: too few for a context "
                         "and the held-out queries")

    def health(model):
        return transformer_health(e["codebook"], model, e["images"], e["poses"], e["tokens"], contexts)

    record = {"every": eval_every, "contexts": contexts, "fingerprint": fingerprint(e["tokens"])}
    return eval_every, record, transformer_health_columns(contexts), health


def _transformer_and_optimiser(run, config, hyper, schedule, init_state=None):
    """A new Transformer (of hyper's seed, recording hyper's codebook fingerprint) and its
    optimiser, the published one (optim.py: HF AdamWeightDecay over Keras Adam, hyper's weight
    decay); both as the run's checkpoint left them when it resumes. A fresh run with init_state
    (_warm_start's) starts from its parameters, the optimiser fresh (zero moments, step 0, the
    schedule from its start)."""
    model = Transformer(config, seed=hyper["seed"])
    model.codebook_fingerprint = hyper.get("codebook_fingerprint")  # both engines return this model
    if run.resumed:
        run.restore("model", model.load_official, run.model_state)  # replaces model.params
    elif init_state is not None:
        model.load_official(init_state)  # replaces model.params
    opt = AdamW(model.params, lr=schedule, eps=1e-8, weight_decay=hyper["weight_decay"], decay=published_weight_decay,
                eps_convention="keras")  # after the restore: on the params it put in place
    if run.resumed:
        run.restore("optimizer", opt.load_state_dict, run.optimizer_state)
    return model, opt


def _pyvf_engine(model, opt, max_grad_norm, clip_mode):
    """train_transformer's engine "pyvf": (step(tok, pos) -> (loss, mean ce, mean pose loss, the
    global gradient norm), the state dict's function, the current model's)."""
    def step(tok, pos):
        out, norm = transformer_step(model, opt, tok, pos, max_grad_norm=max_grad_norm, clip_mode=clip_mode,
                                     relative=True)
        if isinstance(norm, dict):  # per_tensor: {name: |g|} -> the global norm
            norm = float(np.sqrt(sum(n * n for n in norm.values())))
        return out.loss, float(np.mean(out.ce_loss)), float(np.mean(out.pose_loss)), norm

    return step, model.state_dict, lambda: model


def _transformer_engine(engine, model, opt, dp, parity, clipping, device, precision):
    """train_transformer's engine: (step(tok, pos) -> (loss, mean ce, mean pose loss, grad norm),
    state() -> the state dict, current() -> the model, the optimiser whose lr_at and step count
    the loop reads, check(out_dir, step) before each checkpoint or None). The torch engine's
    check is the parity of the torch model and pyvf's on the batch `parity` (tokens, poses)."""
    if engine != "torch":
        return (*_pyvf_engine(model, opt, *clipping), opt, None)
    eng = TorchTransformer(model, opt, device=device, precision=precision, max_grad_norm=clipping[0],
                           clip_mode=clipping[1], dp=dp)

    def check(out_dir, step):  # before the save: a divergent model is not checkpointed
        log_parity(out_dir, step, eng.parity(*parity))

    return eng.step, eng.state_dict, eng.to_pyvf, eng.opt, check


def _run_folder(dp, make_run, steps, out_dir):
    """make_run(): the Run, in a single process and on rank 0 of a data-parallel run (dp); on the
    other processes a Follower from rank 0's start step (torch_engine.Follower)."""
    if dp is None:
        return make_run()
    run = make_run() if dp.rank == 0 else None
    start = dp.broadcast_int(run.start if run is not None else 0)
    return run if run is not None else Follower(start, steps, out_dir)


def train_transformer(tokens, poses, config, out_dir, *, steps, batch_size=16, context=None, lr=1e-4, warmup=None,
                      total_steps=None, weight_decay=0.01, max_grad_norm=1.0, clip_mode="per_tensor", seed=0,
                      checkpoint_every=200, log_every=10, eval_set=None, eval_every=0, resume=True, progress=True,
                      threads=None, command=None, engine="pyvf", device="cpu", precision="fp32", init=None,
                      codebook_fingerprint=None):
    """Train a Transformer on token images and poses, every context size and both tasks at once
    (the branching tree, docs/math.md §2-3), with the published optimiser (docs/math.md §5).

    tokens: ints (scenes, views, k, k) in [0, config.n_embeddings); poses: float32 or float64
        (scenes, views, 7), xyz and a unit quaternion wxyz (in config.dtype, checked at the
        start), in any frame (each sample is made relative to its first view).
    context: the most context views a sample has: a sample is N = context + 1 distinct views
        of one scene (default config.sequence_size - 1); the tree trains the contexts
        n_loss_skip..N-1 in the same step.
    lr, warmup, total_steps: WarmupCosine(lr, warmup, total_steps): linear warmup from 0,
        then cosine decay to 0 at total_steps (default steps; default warmup
        min(2000, total_steps // 10): the paper's 2000 steps, shortened for short runs). The
        schedule is part of the run: to extend a run, pass its total_steps; steps past
        total_steps (learning rate 0) raise.
    weight_decay: AdamW's decoupled decay on the parameters published_weight_decay selects
        (all but the biases), Keras' epsilon convention as the published optimiser.
    max_grad_norm, clip_mode: gradient clipping (None: off); "per_tensor" is the published
        tf.clip_by_norm, "global" torch's clip_grad_norm_. The logged grad_norm is the global norm.
    eval_set: None, or held-out scenes {"codebook": the Codebook the tokens came from, "images":
        uint8 (n, V, S, S, 3), "poses": float64 (n, V, 7), "tokens": (n, V, L) their codes}
        (held_out_set's; checked at the start): every eval_every steps (0: never; then the set
        is not the run's), at the last step and before the first of a fresh run,
        health.transformer_health at health.health_contexts is appended to out_dir/eval.csv.
    out_dir, resume, seed, init, threads, command: as train_codebook (init a Transformer.save
        file); the final model is out_dir/transformer.npz (Transformer.load reads it).
    codebook_fingerprint: the fingerprint of the codebook the tokens came from (load_tokens'):
        recorded in config.json and the model, whose pairings then check it (models.check_pair).
    engine, device, precision: "pyvf" (its own kernels, on the CPU) or "torch" on `device` "cpu" |
        "cuda" | "cuda:N" at `precision` "fp32" | "bf16": the same run with the model in torch,
        checked against pyvf's at every checkpoint, data-parallel under torchrun (torch_engine's
        docstring; docs/howto-torch-engine.md). A checkpoint of either engine resumes in the other.
    Returns the trained Transformer."""
    if not isinstance(config, TransformerConfig):
        raise TypeError(f"config must be a TransformerConfig, got {type(config).__name__}")
    _check_tokens_poses(tokens, poses, config)
    hyper, schedule, steps = _transformer_hyper(tokens, poses, config, steps, batch_size, context, lr, warmup,
                                                total_steps, weight_decay, max_grad_norm, clip_mode, seed,
                                                codebook_fingerprint)
    batch_size, n_views, seed = (hyper[k] for k in ("batch_size", "views", "seed"))
    check_engine(engine, device, precision, config.dtype)
    eval_every, eval_record, eval_columns, health = _transformer_eval(eval_set, eval_every, config)
    threads_set = _Threads(threads)
    hyper, init_state = _warm_start(init, Transformer, config, hyper, out_dir, resume)
    dp, device = data_parallel(device, batch_size) if engine == "torch" else (None, device)
    call = {"command": command, "threads": threads_set.n, "engine": engine, "device": device, "precision": precision,
            "processes": 1 if dp is None else dp.world, "eval": eval_record}
    with threads_set:  # before the Run: config.json records the threads the run uses
        run = _run_folder(dp, lambda: Run(
            out_dir, "transformer", dataclasses.asdict(config), hyper, TRANSFORMER_LOG, final="transformer.npz",
            steps=steps, resume=resume, progress=progress, checkpoint_every=checkpoint_every, log_every=log_every,
            call=call, eval_columns=eval_columns, eval_fingerprint=(eval_record or {}).get("fingerprint"),
            stop_at_step_end=dp is None), steps, out_dir)
        evaluating = health is not None and eval_every > 0 and not isinstance(run, Follower)
        model, opt = _transformer_and_optimiser(run, config, hyper, schedule, init_state)
        step, state, current, opt, check = _transformer_engine(
            engine, model, opt, dp, parity_batch(tokens, poses, n_views, seed, config.dtype),
            (max_grad_norm, clip_mode), device, precision)
        with run:
            if evaluating and not run.resumed:
                run.log_eval(0, health(current()))
                plot_eval(run.out_dir)
            for t in run.steps():
                tok, pos = transformer_batch(tokens, poses, n_views, batch_size, seed, t,
                                             config.dtype)  # (B, N, L), (B, N, 7)
                lr_t = opt.lr_at(opt.step_count)
                loss, ce, pl, norm = step(tok, pos)
                run.log(t, {"loss": loss, "ce_loss": ce, "pose_loss": pl, "grad_norm": norm, "lr": lr_t})
                if evaluating and run.eval_due(t, eval_every):
                    run.log_eval(t, health(current()))
                    plot_eval(run.out_dir)  # eval.png: the curves so far, the baselines dashed
                _checkpoint(run, t, state, opt, check)
        run.save_final(state())
    if dp is not None:
        dp.close()
    return current()
