"""Training loops: the codebook on images, tokenization, the transformer on tokens (docs/math.md §4, §5).

    cb = train_codebook(images, TINY_CODEBOOK, "runs/cb", RunOptions(steps=20_000))  # images (scenes, views, Hi, Wi, 3) uint8
    tokens = tokenize(cb, images)                                                     # (scenes, views, k, k) int16
    tf = train_transformer(tokens, poses, TINY_TRANSFORMER, "runs/tf", RunOptions(steps=50_000))

RunOptions says how a call runs, the configuration and the recipe what it learns. A call resumes
from the run folder's checkpoint (_run.py) to exactly the state an uninterrupted run reaches, bit
for bit on the same kernel path: every batch is a pure function of (seed, step).
"""

import dataclasses
import os

import numpy as np

from .. import _checks
from .._io import atomic_savez, load_npz
from .._threads import threads as kernel_threads
from ..evaluate.health import (
    CODEBOOK_HEALTH,
    codebook_health,
    health_contexts,
    transformer_health,
    transformer_health_columns,
)
from ..evaluate.metrics import encode_images, object_mask, to_model_images
from ..geometry import _check_unit, make_relative
from ..models.codebook import Codebook, CodebookConfig
from ..models.transformer import Transformer, TransformerConfig
from ._run import CHECKPOINT, Run, file_sha256, fingerprint
from .optim import Adam, AdamW, WarmupCosine, clip_grad_norm, global_norm, published_weight_decay
from .torch_engine import Follower, TorchCodebook, TorchTransformer, check_engine, data_parallel

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

# Codebook training recipes. "published" is the published code's (docs/math.md §4), whose lr and
# betas serve a batch of 352: at batches of 16 they collapse the latent on SM7. "small-batch", the
# default, is chosen by the ablations of docs/models-remarks.md. restart, reseat, kmeans:
# EMAQuantizer.reset_dead_codes' and init_kmeans' (0: a uniform initialisation); schedule: the lr
# "constant", or "cosine" from lr at the first step to 0 at the last (WarmupCosine without warmup).
# Options newer than the first runs: a run's config.json records them only away from these defaults.
_LATER_OPTIONS = {"restart": "batch", "reseat": 0, "kmeans": 0, "schedule": "constant"}
CODEBOOK_RECIPES = {
    "published": {"lr": 1.584e-3, "betas": (0.5, 0.9), "reset_dead_codes": 0, "object_weight": 1.0, **_LATER_OPTIONS},
    "small-batch": {"lr": 3e-4, "betas": (0.9, 0.99), "reset_dead_codes": 20, "object_weight": 4.0, **_LATER_OPTIONS},
}
KMEANS_BATCHES = 4  # the k-means initialisation clusters the encoder's outputs of this many batches

CODEBOOK_LOG = ["loss", "rec_loss", "commitment", "perplexity", "usage", "lr"]
TRANSFORMER_LOG = ["loss", "ce_loss", "pose_loss", "grad_norm", "lr"]


@dataclasses.dataclass(frozen=True)
class RunOptions:
    """How a training call runs. Checked when made; an error names the field."""

    steps: int  # the total number of updates; a resumed run continues to it from its checkpoint
    batch_size: int = 16
    seed: int = 0  # the initialisation and every batch (np.random.default_rng([seed, step]))
    checkpoint_every: int = 200  # steps between checkpoints (and one at the end): where a stopped run resumes
    eval_every: int = 0  # steps between held-out evaluations (0: none)
    resume: bool = True  # continue from out_dir/checkpoint.npz when there is one; False starts over
    progress: bool = True  # a progress bar on stderr
    threads: int | None = None  # the kernels' and BLAS' threads during the call (None: as they are)
    command: dict | None = None  # the command line, recorded in config.json
    engine: str = "pyvf"  # "pyvf" (its own kernels, on the CPU) or "torch" (torch_engine.py)
    device: str = "cpu"  # the torch engine's: "cpu", "cuda" or "cuda:N"
    precision: str = "fp32"  # the torch engine's: "fp32" or "bf16" autocast
    init: str | None = None  # a Codebook.save / Transformer.save file a fresh run starts from

    def __post_init__(self):
        for name, lo in (("steps", 1), ("batch_size", 1), ("seed", 0), ("checkpoint_every", 1), ("eval_every", 0),
                         ("threads", 1)):
            if name != "threads" or self.threads is not None:
                object.__setattr__(self, name, _checks.integer(name, getattr(self, name), lo))
        check_engine(self.engine, self.device, self.precision)


# ---------------------------------------------------------------------------------------
# the batches: each a pure function of (seed, step); the parity checks' from seed + PARITY_SEED


PARITY_SEED = 1_000_003


def codebook_batch(images, batch_size, seed, step, dtype="float32", object_weight=None):
    """batch_size views drawn uniformly (with replacement) from the (M, Hi, Wi, C) uint8 images ->
    (B, C, Hi, Wi) in [-1, 1]; with object_weight also the pixel weights (B, 1, Hi, Wi):
    object_weight on the pixels health.object_mask marks, 1 on the background."""
    rng = np.random.default_rng([seed, step])
    idx = rng.integers(0, images.shape[0], size=batch_size)  # (B,)
    x = to_model_images(images[idx], np.dtype(dtype))
    if object_weight is None:
        return x
    w = np.where(object_mask(images[idx]), object_weight, 1.0).astype(dtype)[:, None]  # (B, 1, Hi, Wi)
    return x, w


def transformer_batch(tokens, poses, n_views, batch_size, seed, step, dtype="float32"):
    """Per sample a scene drawn uniformly, then n_views distinct views of it in random order.
    tokens (scenes, views, k, k), poses (scenes, views, 7) -> tokens (B, N, L) int64, poses (B, N, 7)."""
    rng = np.random.default_rng([seed, step])
    n_scenes, n_avail = tokens.shape[:2]
    scenes = rng.integers(0, n_scenes, size=batch_size)  # (B,)
    order = rng.permuted(np.tile(np.arange(n_avail), (batch_size, 1)), axis=1)  # (B, views): a permutation per row
    views = order[:, :n_views]  # (B, N)
    tok = tokens[scenes[:, None], views].reshape(batch_size, n_views, -1).astype(np.int64)  # (B, N, L)
    pos = poses[scenes[:, None], views].astype(dtype)  # (B, N, 7)
    return tok, pos


def train_step(model, optimizer, tokens, poses, *, max_grad_norm=None, clip_mode="global"):
    """One transformer step: forward, backward, optional clipping (clip_grad_norm's; "per_tensor" is
    the published choice), optimiser step (docs/math.md §5). tokens (B, N, L) ints, poses (B, N, 7),
    made relative to each sequence's first view (geometry.make_relative), as the published input
    pipeline does. -> (the TransformerOutput before the update, clip_grad_norm's norm(s))."""
    if optimizer.params is not model.params:
        raise ValueError("optimizer must be built on model.params (AdamW(model.params, ...))")
    out = model.forward(tokens, make_relative(poses)[0])
    grads = model.backward()
    if max_grad_norm is not None:
        norm = clip_grad_norm(grads, max_grad_norm, mode=clip_mode)
    else:  # no clipping: the global norm all the same (nan or inf where a gradient is not finite)
        norm = global_norm(grads)
    optimizer.step(grads)
    return out, norm


def codebook_train_step(codebook, optimizer, images, pixel_weights=None):
    """One codebook step: forward with the EMA update (train=True), backward, optimiser step (the
    codes are not parameters: the EMA moves them). pixel_weights: Codebook.forward's. -> the step's
    CodebookOutput."""
    if optimizer.params is not codebook.params:
        raise ValueError("optimizer must be built on codebook.params (Adam(codebook.params, ...))")
    out = codebook.forward(images, train=True, pixel_weights=pixel_weights)
    optimizer.step(codebook.backward())
    return out


def _check_images(images, config, name="images"):
    """images: uint8 (scenes, views, Hi, Wi, C) or (M, Hi, Wi, C) -> a (M, Hi, Wi, C) view."""
    if not isinstance(images, np.ndarray) or images.dtype != np.uint8:
        raise TypeError(f"{name} must be a uint8 numpy array, got {getattr(images, 'dtype', type(images).__name__)}")
    S, C = config.image_size, config.in_channels
    if images.ndim not in (4, 5) or images.shape[-3:] != (S, S, C) or images.size == 0:
        raise ValueError(f"{name} must have shape (scenes, views, {S}, {S}, {C}) or (M, {S}, {S}, {C}), "
                         f"got {images.shape}")
    return images.reshape(-1, S, S, C)


def _warm_start(cls, config, hyper, out_dir, opts):
    """opts.init, a cls.save file with the run's shapes (empty_code may differ) -> (hyper with the
    file's {"path", "sha256"}, its state_dict()); None or a resume -> (hyper, None)."""
    path = opts.init
    if path is None or opts.resume and os.path.exists(os.path.join(out_dir, CHECKPOINT)):
        return hyper, None
    try:
        model = cls.load(path)
        cls(config).load_official(model.state_dict())  # the run's shapes, or an error naming the first weight
    except (OSError, ValueError) as e:
        raise type(e)(f"init {path}: {e}") from e
    return {**hyper, "init": {"path": os.path.basename(path), "sha256": file_sha256(path)}}, model.state_dict()


def _restore(run, model, make_optimiser, init_state):
    """The model as the run's checkpoint (or init_state) left it, then make_optimiser(model.params),
    its state the checkpoint's. A codebook's init_state holds the EMA buffers and counter too: zeroed
    averages at counter 1 would set each code to one batch's mean (docs/math.md §4)."""
    if run.resumed or init_state is not None:
        model.load_official(run.model_state if run.resumed else init_state)  # replaces model.params
    opt = make_optimiser(model.params)  # after the restore: on the params it put in place
    if run.resumed:
        opt.load_state_dict(run.optimizer_state)
    return opt


def _loop(run, opt, step, current, check, health, eval_every):
    """The loop both trainings run: step(t) -> the log's values but lr; current() -> the model (and
    opt, the pyvf optimiser) as the engine has them; health() -> the held-out figures (None: no
    evaluation), at step 0 of a fresh run, every eval_every steps and at the last; check(run, t)
    before each checkpoint (None: none); the final model."""
    state = lambda: current().state_dict()  # noqa: E731
    if health is not None and not run.resumed:
        run.log_eval(0, health())
    for t in run.steps():
        lr_t = opt.lr_at(opt.step_count)
        run.log(t, {**step(t), "lr": lr_t})
        if health is not None and eval_every and (t % eval_every == 0 or t == run.steps_total):
            run.log_eval(t, health())
        run.checkpoint(t, state, opt, check)
    run.save_final(state())


# ---------------------------------------------------------------------------------------
# the codebook


def _recipe(recipe, overrides):
    """The recipe with the overrides not None, checked -> (the settings, the hyperparameters a run
    records beyond the base ones: those of object_weight and _LATER_OPTIONS not at their defaults)."""
    if recipe not in CODEBOOK_RECIPES:
        raise ValueError(f"recipe must be one of {sorted(CODEBOOK_RECIPES)}, got {recipe!r}")
    unknown = sorted(set(overrides) - set(CODEBOOK_RECIPES[recipe]))
    if unknown:
        raise TypeError(f"train_codebook got unexpected keyword arguments {unknown}")
    r = {**CODEBOOK_RECIPES[recipe], **{k: v for k, v in overrides.items() if v is not None}}
    r["lr"] = _checks.real("lr", r["lr"], lo=0.0)
    r["betas"] = tuple(_checks.real("betas", b, 0.0, 1.0, hi_open=True) for b in r["betas"])
    for name in ("reset_dead_codes", "reseat", "kmeans"):
        r[name] = _checks.integer(name, r[name], 0)
    r["object_weight"] = _checks.real("object_weight", r["object_weight"], lo=0.0, lo_open=True)
    if r["restart"] not in ("batch", "worst"):
        raise ValueError(f"restart must be 'batch' or 'worst', got {r['restart']!r}")
    if r["schedule"] not in ("constant", "cosine"):
        raise ValueError(f"schedule must be 'constant' or 'cosine', got {r['schedule']!r}")
    recorded = {"object_weight": r["object_weight"]} if r["object_weight"] != 1.0 else {}
    recorded.update({k: r[k] for k in _LATER_OPTIONS if r[k] != _LATER_OPTIONS[k]})
    return r, recorded


def train_codebook(images, config, out_dir, opts, *, eval_images=None, recipe="small-batch", **overrides):
    """Train a Codebook with Adam and the EMA quantizer (docs/math.md §4) into the run folder out_dir
    (_run.py; at the end codebook.npz) -> the trained Codebook.

    images: uint8 (scenes, views, Hi, Wi, C) or (M, Hi, Wi, C), Hi = Wi = config.image_size.
    eval_images: None, or held-out uint8 views (M, Hi, Wi, C) whose codebook_health goes to eval.csv.
    recipe: a name of CODEBOOK_RECIPES; overrides (each not None replaces the recipe's): lr, betas,
        reset_dead_codes (every this many steps dead codes move to encoder outputs; 0: never),
        object_weight (the loss weight of object pixels, 1 for the background), restart, reseat, kmeans,
        schedule (the cosine's end is opts.steps, recorded: a resume must ask for the same steps)."""
    flat = _check_images(images, config)  # (M, Hi, Wi, C)
    r, recorded = _recipe(recipe, overrides)
    if eval_images is not None:
        eval_images = _check_images(eval_images, config, "eval_images")
    eval_fp = fingerprint(eval_images) if eval_images is not None and opts.eval_every else None
    B, seed = opts.batch_size, opts.seed
    hyper = {"batch_size": B, "lr": r["lr"], "betas": r["betas"], "seed": seed,
             "reset_dead_codes": r["reset_dead_codes"],
             "data": {"shape": images.shape, "fingerprint": fingerprint(images)}, **recorded}
    lr = r["lr"]
    if r["schedule"] == "cosine":  # its end recorded: a resume must ask for the same steps
        hyper["total_steps"], lr = opts.steps, WarmupCosine(r["lr"], 0, opts.steps)
    check_engine(opts.engine, opts.device, opts.precision, config.dtype, one_process=True)
    hyper, init_state = _warm_start(Codebook, config, hyper, out_dir, opts)
    call = {"recipe": recipe, "eval": None if eval_fp is None else {"every": opts.eval_every, "fingerprint": eval_fp}}
    with kernel_threads(opts.threads):  # before the Run: config.json records the threads the run uses
        run = Run(out_dir, "codebook", dataclasses.asdict(config), hyper, CODEBOOK_LOG, opts, call=call,
                  evaluation=None if eval_fp is None else (CODEBOOK_HEALTH, eval_fp))
        model = Codebook(config, seed=seed)
        opt = _restore(run, model, lambda params: Adam(params, lr, betas=r["betas"]), init_state)
        if not run.resumed and init_state is None and r["kmeans"]:  # the codes by k-means on step 0's batches
            x = codebook_batch(flat, KMEANS_BATCHES * B, seed, 0, config.dtype)  # (B', C, Hi, Wi)
            model.quantizer.init_kmeans(model._encoder(None, x), r["kmeans"], B,
                                        rng=np.random.default_rng([seed, 0, 2]), empty=model.empty_patches(x))
        weight = r["object_weight"] if r["object_weight"] != 1.0 else None

        if opts.engine == "torch":  # step, the dead-code reset, the model as the engine has it, the parity check
            eng = TorchCodebook(model, opt, device=opts.device, precision=opts.precision,
                                parity_batch=(codebook_batch(flat, 4, seed + PARITY_SEED, 0, config.dtype),))
            step, reset, current, check = eng.step, eng.reset_dead_codes, eng.to_pyvf, eng.check
        else:
            def step(x, w):  # the update -> the log's values but lr
                out = codebook_train_step(model, opt, x, pixel_weights=w)
                return {"loss": out.loss, "rec_loss": out.rec_loss, "commitment": out.commitment_loss,
                        "perplexity": out.perplexity, "usage": out.usage}

            def reset(x, rng, **codes):
                z = model._encoder([], x)  # (B, D, k, k) with the updated weights
                return model.quantizer.reset_dead_codes(z, rng=rng, empty=model.empty_patches(x), **codes)

            current, check = (lambda: model), None

        def step_t(t):
            x = codebook_batch(flat, B, seed, t, config.dtype, weight)
            x, w = x if weight else (x, None)  # (B, C, Hi, Wi), (B, 1, Hi, Wi) or None
            values = step(x, w)
            if r["reset_dead_codes"] and t % r["reset_dead_codes"] == 0:
                reset(x, np.random.default_rng([seed, t, 1]), restart=r["restart"], reseat=r["reseat"])
            return values

        health = None if eval_fp is None else lambda: codebook_health(current(), eval_images)
        _loop(run, opt, step_t, current, check, health, opts.eval_every)
        return current()


def tokenize(codebook, images, batch_size=64, progress=False):
    """images uint8 (scenes, views, Hi, Wi, C) or (M, Hi, Wi, C) -> codebook.encode's codes,
    (scenes, views, k, k) or (M, k, k), as int16 (int32 when n_embed > 32768)."""
    flat = _check_images(images, codebook.config)  # (M, Hi, Wi, C)
    batch_size = _checks.integer("batch_size", batch_size, 1)
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
    """Write a tokenized dataset atomically: tokens (scenes, views, k, k) ints in [0, n_embed), poses
    (scenes, views, 7) floats, n_embed and the codebook's fingerprint (None: not recorded)."""
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


@dataclasses.dataclass(frozen=True)
class TransformerRecipe:
    """train_transformer's published optimiser (docs/math.md §5); AdamW's weight decay is the published
    0.01. Checked when made; an error names the field."""

    lr: float = 1e-4  # WarmupCosine's peak: linear warmup from 0, then cosine decay to 0 at total_steps
    warmup: int | None = None  # None: min(2000, total_steps // 10), the paper's 2000 shortened for short runs
    total_steps: int | None = None  # None: the run's steps; part of the run: keep it to extend a run
    max_grad_norm: float | None = 1.0  # tf.clip_by_norm per tensor (None: off); the logged grad_norm is the global norm

    def __post_init__(self):
        for name, lo in (("warmup", 0), ("total_steps", 1)):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _checks.integer(name, getattr(self, name), lo))
        object.__setattr__(self, "lr", _checks.real("lr", self.lr, lo=0.0))
        if self.max_grad_norm is not None:
            object.__setattr__(self, "max_grad_norm", _checks.real("max_grad_norm", self.max_grad_norm, lo=0.0,
                                                                   lo_open=True))


def _transformer_hyper(tokens, poses, config, opts, recipe, codebook_fingerprint):
    """train_transformer's data and run checked (tokens ints (scenes, views, k, k) in [0, n_embeddings),
    poses (scenes, views, 7) finite with unit quaternions: here, not at the step that draws a bad
    view) -> (the run's hyperparameters, the WarmupCosine schedule)."""
    _checks.int_array("tokens", tokens)
    if tokens.ndim != 4 or tokens.shape[2:] != (config.token_image_size,) * 2:
        raise ValueError(f"tokens must have shape (scenes, views, k, k), k = {config.token_image_size}, "
                         f"got {tokens.shape}")
    if tokens.size == 0 or tokens.min() < 0 or tokens.max() >= config.n_embeddings:
        raise ValueError(f"tokens must be non-empty and in [0, {config.n_embeddings}) (config.n_embeddings)")
    _checks.float_array("poses", poses)
    if poses.shape != tokens.shape[:2] + (7,):
        raise ValueError(f"poses must have shape (scenes, views, 7) = {tokens.shape[:2] + (7,)}, got {poses.shape}")
    _checks.finite("poses", poses)
    _check_unit("the quaternions of poses", poses[..., 3:].astype(config.dtype))
    r, n_views = recipe, config.sequence_size  # N distinct views of a scene: the tree trains every context at once
    if not config.n_loss_skip < n_views <= tokens.shape[1]:
        raise ValueError(f"config.sequence_size={n_views} must leave a loss target (more than n_loss_skip="
                         f"{config.n_loss_skip} views) and fit the {tokens.shape[1]} views a scene has (tokens)")
    total_steps = opts.steps if r.total_steps is None else r.total_steps
    if total_steps < opts.steps:
        raise ValueError(f"steps={opts.steps} runs past total_steps={total_steps}, the schedule's end: ask for at "
                         "most total_steps steps, or a longer schedule")
    warmup = min(2000, total_steps // 10) if r.warmup is None else r.warmup
    if warmup >= total_steps:
        raise ValueError(f"warmup={warmup} must be less than total_steps={total_steps}")
    hyper = {"batch_size": opts.batch_size, "views": n_views, "lr": r.lr, "warmup": warmup,
             "total_steps": total_steps, "weight_decay": 0.01, "eps": 1e-8, "eps_convention": "keras",
             "max_grad_norm": r.max_grad_norm, "clip_mode": "per_tensor", "seed": opts.seed,
             "data": {"shape": tokens.shape, "fingerprint": fingerprint(tokens, poses)}}
    if codebook_fingerprint is not None:
        hyper["codebook_fingerprint"] = str(codebook_fingerprint)
    return hyper, WarmupCosine(r.lr, warmup, total_steps)


def train_transformer(tokens, poses, config, out_dir, opts, recipe=TransformerRecipe(), *, eval_set=None,
                      codebook_fingerprint=None):
    """Train a Transformer on token images and poses, every context size and both tasks at once
    (the branching tree, docs/math.md §2-3), with the published optimiser (docs/math.md §5), into the
    run folder out_dir (at the end transformer.npz) -> the trained Transformer.

    tokens: ints (scenes, views, k, k) in [0, config.n_embeddings); poses: float (scenes, views, 7),
        xyz and a unit quaternion wxyz, in any frame. Engine "torch": data-parallel under torchrun too.
    eval_set: None, or held_out_set's scenes whose transformer_health goes to eval.csv.
    codebook_fingerprint: the tokens' codebook's (load_tokens'), recorded in config.json and the model."""
    hyper, schedule = _transformer_hyper(tokens, poses, config, opts, recipe, codebook_fingerprint)
    B, n_views, seed = opts.batch_size, hyper["views"], opts.seed
    check_engine(opts.engine, opts.device, opts.precision, config.dtype)
    eval_record = evaluation = health = None  # config.json's record, Run's evaluation, health(model)
    if eval_set is not None and opts.eval_every:
        e = eval_set
        contexts = health_contexts(config, e["images"].shape[1])
        if not contexts:
            raise ValueError(f"eval_set's scenes have {e['images'].shape[1]} views: too few for a context and queries")
        eval_record = {"every": opts.eval_every, "contexts": contexts, "fingerprint": fingerprint(e["tokens"])}
        evaluation = (transformer_health_columns(contexts), eval_record["fingerprint"])
        health = lambda model: transformer_health(  # noqa: E731
            e["codebook"], model, e["images"], e["poses"], e["tokens"], contexts)
    hyper, init_state = _warm_start(Transformer, config, hyper, out_dir, opts)
    dp, device = data_parallel(opts.device, B) if opts.engine == "torch" else (None, opts.device)
    opts = dataclasses.replace(opts, device=device)
    call = {"processes": 1 if dp is None else dp.world, "eval": eval_record}
    with kernel_threads(opts.threads):  # before the Run: config.json records the threads the run uses
        if dp is None or dp.rank == 0:
            run = Run(out_dir, "transformer", dataclasses.asdict(config), hyper, TRANSFORMER_LOG, opts, call=call,
                      evaluation=evaluation)
        if dp is not None:  # the other processes follow rank 0's run from its start step
            start = dp.broadcast_int(run.start if dp.rank == 0 else 0)
            run = run if dp.rank == 0 else Follower(start, opts.steps)
        model = Transformer(config, seed=seed)
        model.codebook_fingerprint = hyper.get("codebook_fingerprint")  # both engines return this model
        opt = _restore(run, model, lambda params: AdamW(params, lr=schedule, eps=hyper["eps"], weight_decay=hyper[
            "weight_decay"], decay=published_weight_decay, eps_convention=hyper["eps_convention"]), init_state)
        if opts.engine == "torch":  # step, the model as the engine has it, the parity check
            parity = transformer_batch(tokens, poses, n_views, 4, seed + PARITY_SEED, 0, config.dtype)
            eng = TorchTransformer(model, opt, device=opts.device, precision=opts.precision, dp=dp,
                                   parity_batch=parity, max_grad_norm=recipe.max_grad_norm)
            step, current, check = eng.step, eng.to_pyvf, eng.check
        else:
            def step(tok, pos):  # the update -> the log's values but lr
                out, norm = train_step(model, opt, tok, pos, max_grad_norm=recipe.max_grad_norm,
                                       clip_mode=hyper["clip_mode"])
                if isinstance(norm, dict):  # clipped: {name: |g|} -> the global norm
                    norm = float(np.sqrt(sum(n * n for n in norm.values())))
                return {"loss": out.loss, "ce_loss": float(np.mean(out.ce_loss)),
                        "pose_loss": float(np.mean(out.pose_loss)), "grad_norm": norm}

            current, check = (lambda: model), None
        evaluate = None if health is None or isinstance(run, Follower) else lambda: health(current())
        _loop(run, opt, lambda t: step(*transformer_batch(tokens, poses, n_views, B, seed, t, config.dtype)), current,
              check, evaluate, opts.eval_every)  # batches (B, N, L), (B, N, 7)
    if dp is not None:
        dp.close()
    return current()
