"""Optimisers, the learning-rate schedule and gradient clipping (docs/math.md §4, §5).

    opt = AdamW(params, lr=WarmupCosine(1e-4, 2000, 120_000), weight_decay=0.01)
    norm = clip_grad_norm(grads, 1.0, mode="per_tensor")   # in place
    opt.step(grads)                                          # params updated in place

params and grads are dicts name -> float32/float64 array, the moments in the parameters' dtype.
The published transformer's optimiser: AdamW(eps_convention="keras", eps=1e-8,
decay=published_weight_decay), WarmupCosine, clip_grad_norm(mode="per_tensor"); the published
codebook's: Adam(params, 1.584e-3, betas=(0.5, 0.9)).
"""

import math
import re

import numpy as np

from .. import _checks


_PUBLISHED_NO_DECAY = re.compile("LayerNorm|layer_norm|bias")


def published_weight_decay(name):
    """True where the published transformer optimiser decays the parameter `name`: HuggingFace's
    `AdamWeightDecay` excludes names matching "LayerNorm", "layer_norm" and "bias" (re.search), which
    with the published names excludes only the biases: `h.{j}/ln_1/gamma` matches none, so the
    LayerNorms are decayed (as are wte, wpe). Pass as AdamW(decay=...)."""
    return _PUBLISHED_NO_DECAY.search(name) is None


def adam_update(p, m, v, g, lr, t, b1, b2, eps, wd, keras, sqrt=np.sqrt):
    """Update t (1, 2, ...) of p by gradient g with moments m, v -> the new (p, m, v), nothing
    modified (AdamW's docstring has the math). p, m, v, g: arrays of one shape and dtype (numpy's,
    or torch tensors with sqrt=torch.sqrt: the torch engine's); the rest Python floats (wd 0: no
    decay). Every operation rounds once in p's dtype, left to right as written."""
    bc1, bc2 = 1 - b1 ** t, 1 - b2 ** t  # bias corrections
    m = m * b1 + (1 - b1) * g
    v = v * b2 + (1 - b2) * g * g
    if keras:  # eps on the raw sqrt(v), the bias corrections folded into the step size
        u = (m * (lr * math.sqrt(bc2) / bc1)) / (sqrt(v) + eps)
    else:  # torch: eps on the bias-corrected sqrt(v / bc2)
        u = (lr / bc1) * (m / (sqrt(v) / math.sqrt(bc2) + eps))
    p = (p * (1 - lr * wd) if wd else p) - u  # decoupled weight decay, with the scheduled lr
    return p, m, v


class AdamW:
    """Adam with decoupled weight decay (Loshchilov & Hutter), PyTorch semantics by default.

    params: dict name -> float32/float64 array, updated in place by step().
    lr: a float, or a schedule: a callable step -> float called with the number of updates
        already applied (0 for the first update), as Keras and torch's LambdaLR do.
    betas, eps, weight_decay: as torch.optim.AdamW (defaults 0.9, 0.999; 1e-8; 0.01).
    decay: which parameters get weight decay: None (all), a collection of names, or a
        predicate name -> bool (e.g. published_weight_decay).
    eps_convention: "torch" (default) or "keras", where eps enters the update:

    Update t (t = 1, 2, ...), every parameter p with gradient g, lr = lr(t - 1):

        p *= 1 - lr * weight_decay                    (decayed parameters only)
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g^2
        torch:  p -= lr / (1 - b1^t) * m / (sqrt(v) / sqrt(1 - b2^t) + eps)
        keras:  p -= lr * sqrt(1 - b2^t) / (1 - b1^t) * m / (sqrt(v) + eps)

    Keras/TF (`ResourceApplyAdam`, the published transformer's) therefore equals torch with eps
    replaced by eps / sqrt(1 - b2^t): a larger epsilon early on (31.6x at t = 1 with b2 = 0.999,
    3.2x at t = 100) that tends to the same one as t grows. Weight decay is decoupled in both (the
    published `AdamWeightDecay` subtracts lr * wd * p before the Adam step), with the scheduled lr.
    """

    def __init__(self, params, lr=1e-3, betas=(0.9, 0.999), eps=1e-8, weight_decay=1e-2, *,
                 decay=None, eps_convention="torch"):
        self.lr = lr if callable(lr) else _checks.real("lr", lr, lo=0.0)
        self.betas = tuple(_checks.real("betas", b, 0.0, 1.0, hi_open=True) for b in betas)
        # eps > 0: with eps = 0 a parameter whose gradients have all been 0 gets 0 / 0
        self.eps = _checks.real("eps", eps, lo=0.0, lo_open=True)
        self.weight_decay = _checks.real("weight_decay", weight_decay, lo=0.0)
        if eps_convention not in ("torch", "keras"):
            raise ValueError(f"eps_convention must be 'torch' or 'keras', got {eps_convention!r}")
        self.eps_convention = eps_convention
        self.decayed = frozenset(params if decay is None else filter(decay, params) if callable(decay) else decay)
        self.params = params
        self.step_count = 0
        self.exp_avg = {k: np.zeros(p.shape, p.dtype) for k, p in params.items()}
        self.exp_avg_sq = {k: np.zeros(p.shape, p.dtype) for k, p in params.items()}

    def lr_at(self, step):
        """The learning rate of the update that follows `step` applied updates."""
        return self.lr(step) if callable(self.lr) else self.lr

    def step(self, grads):
        """Apply one update. grads: dict name -> array of its parameter's shape and dtype, not
        modified. An update that is not finite (a NaN or inf gradient, or one that overflows
        the dtype) raises ValueError naming the tensors, nothing updated. Returns the lr used."""
        lr, t = self.lr_at(self.step_count), self.step_count + 1
        with np.errstate(over="ignore", invalid="ignore"):  # checked below, before anything is written
            new = {k: adam_update(p, self.exp_avg[k], self.exp_avg_sq[k], grads[k], lr, t, *self.betas, self.eps,
                                  self.weight_decay if k in self.decayed else 0.0, self.eps_convention == "keras")
                   for k, p in self.params.items()}
        bad = [k for k, (p1, _, v1) in new.items() if not (_checks.all_finite(p1) and _checks.all_finite(v1))]
        if bad:  # (an inf v gives a finite p: both are checked)
            raise ValueError(f"the update of {sorted(bad)} is not finite (NaN or inf in grads, or an "
                             "overflow of the dtype): no update applied")
        for k, (p1, m1, v1) in new.items():
            np.copyto(self.params[k], p1)  # in place: the caller's arrays are the model's
            self.exp_avg[k], self.exp_avg_sq[k] = np.asarray(m1), np.asarray(v1)  # a 0-d one's are NumPy scalars
        self.step_count = t
        return lr

    def _hyper(self):
        return {"betas": tuple(self.betas), "eps": self.eps, "weight_decay": self.weight_decay,
                "eps_convention": self.eps_convention, "decayed": sorted(self.decayed)}

    def state_dict(self):
        """{'step': int, 'exp_avg': {name: array}, 'exp_avg_sq': {name: array},
        'hyperparameters': {...}}: copies. The learning rate is not saved: the schedule is a function of 'step'."""
        return {"step": self.step_count,
                "exp_avg": {k: a.copy() for k, a in self.exp_avg.items()},
                "exp_avg_sq": {k: a.copy() for k, a in self.exp_avg_sq.items()},
                "hyperparameters": self._hyper()}

    def load_state_dict(self, state):
        """Restore a state_dict() (copied in); its hyperparameters must be this optimiser's, else
        ValueError: the moments mean nothing under others."""
        hyper = dict(state["hyperparameters"])
        # a JSON round trip gives lists: betas and decayed are compared as a tuple and a sorted list
        hyper["betas"], hyper["decayed"] = tuple(hyper["betas"]), sorted(hyper["decayed"])
        if hyper != self._hyper():
            raise ValueError(f"state was saved with other hyperparameters {hyper}: construct the optimiser with them")
        self.step_count = int(state["step"])
        self.exp_avg = {k: np.array(state["exp_avg"][k]) for k in self.params}
        self.exp_avg_sq = {k: np.array(state["exp_avg_sq"][k]) for k in self.params}


class Adam(AdamW):
    """Adam without weight decay (nor torch Adam's L2 term): AdamW with weight_decay = 0. The
    codebook's (docs/math.md §4): Adam(params, 1.584e-3, betas=(0.5, 0.9))."""

    def __init__(self, params, lr=1e-3, betas=(0.9, 0.999), eps=1e-8):
        super().__init__(params, lr, betas, eps, 0.0)


def warmup_cosine_lr(step, peak_lr, warmup_steps, total_steps):
    """Linear warmup then cosine decay to 0 (docs/math.md §5), as the published HuggingFace `WarmUp`
    over Keras `CosineDecay(peak_lr, total_steps - warmup_steps)`.

    step: updates already applied (0 for the first update; see AdamW). With W = warmup_steps,
    T = total_steps:

        step <= W:      peak_lr * step / W            (0 at step 0, peak_lr at step W exactly)
        W < step < T:   peak_lr * (1 + cos(pi * (step - W) / (T - W))) / 2
        step >= T:      0

    With W = 0 the schedule starts at peak_lr. The published run used W = 2000, so its first
    update has lr 0 (the moments still accumulate)."""
    if step <= warmup_steps and warmup_steps > 0:
        return peak_lr * (step / warmup_steps)
    if step >= total_steps:
        return 0.0
    frac = (step - warmup_steps) / (total_steps - warmup_steps)  # in [0, 1)
    return peak_lr * (0.5 * (1 + math.cos(math.pi * frac)))


class WarmupCosine:
    """warmup_cosine_lr as a callable step -> lr, for AdamW(lr=...); arguments checked here."""

    def __init__(self, peak_lr, warmup_steps, total_steps):
        self.peak_lr = _checks.real("peak_lr", peak_lr, lo=0.0)
        self.warmup_steps = _checks.integer("warmup_steps", warmup_steps, 0)
        self.total_steps = _checks.integer("total_steps", total_steps, self.warmup_steps + 1)

    def __call__(self, step):
        return warmup_cosine_lr(step, self.peak_lr, self.warmup_steps, self.total_steps)


def _norm64(g):
    """|g|_2, its squares summed in float64 (NumPy's pairwise sum: the same for any thread count)."""
    x = g.astype(np.float64, copy=False).ravel()  # (n,)
    with np.errstate(over="ignore"):  # inf beyond ~1e154: the callers say so
        return math.sqrt(float(np.square(x).sum()))


def global_norm(grads):
    """sqrt(sum over tensors of |g|^2) in float64, nothing modified; nan or inf where a gradient
    holds one (train_step's norm without clipping: a run logs the same quantity either way)."""
    return math.sqrt(math.fsum(_norm64(g) ** 2 for g in grads.values()))


def clip_grad_norm(grads, max_norm, *, mode="global"):
    """Clip gradients in place; returns the norm(s) before clipping, accumulated in float64.

    grads: dict name -> float32/float64 array, finite, its norm finite in float64 (else
        ValueError, nothing modified: max_norm / inf would zero the gradients).
    mode="global": torch.nn.utils.clip_grad_norm_. total = sqrt(sum over tensors of |g|^2);
        if total + eps > max_norm (torch's eps = 1e-6) every gradient is multiplied by
        max_norm / (total + eps). Returns total (a float).
    mode="per_tensor": tf.clip_by_norm on each tensor alone (Keras `clipnorm`, and what the
        published transformer does with `gradient_clip_val`): a tensor with |g| > max_norm
        becomes g * (max_norm / |g|); the others are left untouched. Returns {name: |g|}.
    All-zero gradients are left as they are (no 0/0)."""
    max_norm = _checks.real("max_norm", max_norm, lo=0.0, lo_open=True)
    if mode not in ("global", "per_tensor"):
        raise ValueError(f"mode must be 'global' or 'per_tensor', got {mode!r}")
    norms = {k: _norm64(g) for k, g in grads.items()}
    total = math.sqrt(math.fsum(n * n for n in norms.values()))
    if not math.isfinite(total):  # a NaN or inf, or float64 entries beyond ~1e154
        raise ValueError("grads hold a NaN or inf, or their norm overflows float64: nothing was clipped")
    if mode == "per_tensor":
        for k, g in grads.items():
            if norms[k] > max_norm:
                g *= max_norm / norms[k]  # tf.clip_by_norm: the coefficient rounded to g's dtype
        return norms
    if total + 1e-6 > max_norm:  # torch's eps
        for g in grads.values():
            g *= max_norm / (total + 1e-6)
    return total
