"""Optimisers, the learning-rate schedule and gradient clipping (docs/math.md §4, §5).

    opt = AdamW(params, lr=WarmupCosine(1e-4, 2000, 120_000), weight_decay=0.01)
    norm = clip_grad_norm(grads, 1.0, mode="per_tensor")   # in place
    opt.step(grads)                                          # params updated in place
    ckpt = opt.state_dict(); opt2.load_state_dict(ckpt)      # checkpointing

params and grads are dicts name -> numpy array (float32 or float64; a gradient has its
parameter's shape and dtype). Parameters are updated in place and keep their dtype; the
moments live in the optimiser, in the parameters' dtype. Nothing is cast.

The published training (docs/math.md §5) maps to these pieces as follows. Transformer: the
HuggingFace `AdamWeightDecay` over Keras Adam, i.e. AdamW(eps_convention="keras",
eps=1e-8, decay=published_weight_decay) (Keras Adam without decay when weight_decay is 0),
2000 warmup steps then cosine decay to 0 (WarmupCosine), and `tf.clip_by_norm` per tensor
when clipping (clip_grad_norm(mode="per_tensor")). Codebook: torch Adam with betas
(0.5, 0.9): Adam(params, 1.584e-3, betas=(0.5, 0.9)).
"""

import math
import re
import numpy as np

from .. import _checks

__all__ = [
    "AdamW",
    "Adam",
    "WarmupCosine",
    "warmup_cosine_lr",
    "clip_grad_norm",
    "global_norm",
    "published_weight_decay",
]



def _nonfinite_names(d):
    return [k for k, a in d.items() if not _checks.all_finite(a)]


def _check_grads(grads, like=None, writable=False):
    """grads: dict name -> float32/float64 array (with like's names, dtypes and shapes; writable:
    clipped in place), errors naming grads[name]: the optimisers' and clip_grad_norm's boundary."""
    if like is not None and set(grads) != set(like):
        raise ValueError(f"grads must have exactly the parameters' names, got {sorted(set(grads) ^ set(like))} "
                         "extra or missing")
    for k, g in grads.items():
        _checks.float_array(f"grads[{k!r}]", g, None if like is None else like[k], "its parameter")
        if like is not None and g.shape != like[k].shape:
            raise ValueError(f"grads[{k!r}] has shape {g.shape} but its parameter {like[k].shape}")
        if writable and not g.flags.writeable:
            raise ValueError(f"grads[{k!r}] is read-only: it is clipped in place")


# ---------------------------------------------------------------------------------------
# which parameters get weight decay


_PUBLISHED_NO_DECAY = re.compile("LayerNorm|layer_norm|bias")


def published_weight_decay(name):
    """True where the published transformer optimiser decays the parameter `name`.

    The HuggingFace `AdamWeightDecay` used by ViewFormer excludes names matching the regexes
    "LayerNorm", "layer_norm" and "bias" (re.search). With the published names that excludes
    only the biases: the LayerNorm parameters are `h.{j}/ln_1/gamma` etc., which match none
    of the patterns, so they are decayed (as are wte, wpe). Pass as AdamW(decay=...)."""
    return _PUBLISHED_NO_DECAY.search(name) is None


# ---------------------------------------------------------------------------------------
# the Adam update (docs/math.md §4), one parameter


def _adam_update(p, m, v, g, lr, t, b1, b2, eps, wd, keras):
    """Update t (1, 2, ...) of p by gradient g with moments m, v -> the new (p, m, v).
    p, m, v, g: arrays of one shape and dtype, not modified; the rest Python floats (wd 0: no
    decay). Every operation rounds once in p's dtype, the scalars rounded to it where they meet
    an array (NumPy's rule for a Python float), in the order of the formulas in the comments
    (sums and products of two terms commute exactly); in place where that saves a temporary
    (each one is a pass over memory, and the update runs over every parameter each step)."""
    bc1, bc2 = 1 - b1 ** t, 1 - b2 ** t  # bias corrections
    with np.errstate(over="ignore", invalid="ignore"):  # the caller checks the results
        m1 = m * b1  # m1 = b1 m + (1 - b1) g
        m1 += (1 - b1) * g
        v1 = (1 - b2) * g  # v1 = b2 v + ((1 - b2) g) g
        v1 *= g
        v1 += v * b2
        den = np.sqrt(v1)
        if keras:  # u = (m1 (lr sqrt(bc2) / bc1)) / (sqrt(v1) + eps): eps on the raw sqrt(v)
            den += eps
            u = m1 * (lr * math.sqrt(bc2) / bc1)
            u /= den
        else:  # u = (lr / bc1) (m1 / (sqrt(v1) / sqrt(bc2) + eps)): eps on the bias-corrected sqrt(v / bc2)
            den /= math.sqrt(bc2)
            den += eps
            u = m1 / den
            u *= lr / bc1
        p1 = p * (1 - lr * wd) if wd else p.copy()  # decoupled weight decay, with the scheduled lr
        p1 -= u  # p1 = p (1 - lr wd) - u
    return p1, np.asarray(m1), np.asarray(v1)  # a 0-d p's arithmetic gives NumPy scalars


# ---------------------------------------------------------------------------------------
# AdamW


class AdamW:
    """Adam with decoupled weight decay (Loshchilov & Hutter), PyTorch semantics by default.

    params: dict name -> float32/float64 array, updated in place by step(); no two may share
        memory (a tied parameter is listed once).
    lr: a float, or a schedule: a callable step -> float called with the number of updates
        already applied (0 for the first update), as Keras calls its schedules with
        `optimizer.iterations` and torch's LambdaLR starts at lambda(0).
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

    torch adds eps to the bias-corrected sqrt(v_hat); Keras/TF (`ResourceApplyAdam`, which
    the published transformer used) adds it to the raw sqrt(v) and folds the bias corrections
    into the step size. Keras therefore equals torch with eps replaced by
    eps / sqrt(1 - b2^t): a larger epsilon early on (31.6x at t = 1 with b2 = 0.999, 3.2x at
    t = 100) that tends to the same one as t grows. The two agree exactly when eps is
    negligible against sqrt(v_hat). Weight decay is decoupled in both (the published
    `AdamWeightDecay` subtracts lr * wd * p before the Adam step, as torch multiplies by
    1 - lr * wd); it uses the scheduled lr, not the bias-corrected step size.

    All arithmetic is in the parameters' dtype; the bias corrections and step sizes are
    Python floats (float64), rounded to that dtype where they meet the arrays (_adam_update: the
    torch convention's update is lr / (1 - b1^t) * (m / denom), that product last).
    state_dict()/load_state_dict() save and restore the step count and the moments, so that a
    run that is saved, loaded and continued matches an uninterrupted run bit for bit.
    """

    def __init__(self, params, lr=1e-3, betas=(0.9, 0.999), eps=1e-8, weight_decay=1e-2, *,
                 decay=None, eps_convention="torch"):
        self.lr = lr if callable(lr) else _checks.real("lr", lr, lo=0.0)
        if not isinstance(betas, (tuple, list)) or len(betas) != 2:
            raise TypeError(f"betas must be a pair (beta1, beta2), got {betas!r}")
        self.betas = (_checks.real("betas[0]", betas[0], 0.0, 1.0, hi_open=True),
                      _checks.real("betas[1]", betas[1], 0.0, 1.0, hi_open=True))
        # eps > 0: with eps = 0 a parameter whose gradients have all been 0 gets 0 / 0
        self.eps = _checks.real("eps", eps, lo=0.0, lo_open=True)
        self.weight_decay = _checks.real("weight_decay", weight_decay, lo=0.0)
        if eps_convention not in ("torch", "keras"):
            raise ValueError(f"eps_convention must be 'torch' or 'keras', got {eps_convention!r}")
        self.eps_convention = eps_convention
        # which parameters decay: all (None), a predicate name -> bool, or a collection of names
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
        the dtype) raises ValueError with nothing updated. Returns the learning rate used."""
        _check_grads(grads, self.params)
        lr = self.lr_at(self.step_count)
        t = self.step_count + 1
        b1, b2 = self.betas
        # every new value is computed and checked before any is written. Peak memory: the new
        # p, m, v of every parameter beside the old ones.
        new = {k: _adam_update(p, self.exp_avg[k], self.exp_avg_sq[k], grads[k], lr, t, b1, b2, self.eps,
                               self.weight_decay if k in self.decayed else 0.0, self.eps_convention == "keras")
               for k, p in self.params.items()}
        # p1 finite needs m1 finite (else u is not); v1 is checked itself (an inf v1 gives u = 0)
        bad = [k for k, (p1, _, v1) in new.items() if not (_checks.all_finite(p1) and _checks.all_finite(v1))]
        if bad:
            nonfinite = _nonfinite_names({k: grads[k] for k in bad})
            raise ValueError(f"grads contain NaN or inf in {nonfinite}: no update applied" if nonfinite else
                             f"the update of {bad} is not finite (gradients or learning rate too large for the "
                             "dtype, or NaN in the parameters): no update applied")
        for k, (p1, m1, v1) in new.items():
            np.copyto(self.params[k], p1)  # in place: the caller's arrays are the model's
            self.exp_avg[k], self.exp_avg_sq[k] = m1, v1
        self.step_count = t
        return lr

    # -----------------------------------------------------------------------------------
    # checkpointing

    def _hyper(self):
        return {"betas": tuple(self.betas), "eps": self.eps, "weight_decay": self.weight_decay,
                "eps_convention": self.eps_convention, "decayed": sorted(self.decayed)}

    def state_dict(self):
        """{'step': int, 'exp_avg': {name: array}, 'exp_avg_sq': {name: array},
        'hyperparameters': {...}}: copies, independent of later updates. The learning rate
        (possibly a callable) is not saved: the schedule is a function of 'step'."""
        return {
            "step": self.step_count,
            "exp_avg": {k: a.copy() for k, a in self.exp_avg.items()},
            "exp_avg_sq": {k: a.copy() for k, a in self.exp_avg_sq.items()},
            "hyperparameters": self._hyper(),
        }

    def load_state_dict(self, state):
        """Restore a state_dict() (copied in). The hyperparameters (betas, eps, weight decay and
        which parameters it applies to, the eps convention) and the moments' names, shapes and
        dtypes must be the saved ones, else ValueError: the moments mean nothing under other
        ones. The parameters themselves are checkpointed separately."""
        hyper = dict(state["hyperparameters"])
        # a JSON round trip gives lists: betas and decayed are compared as a tuple and a sorted list
        hyper["betas"], hyper["decayed"] = tuple(hyper["betas"]), sorted(hyper["decayed"])
        if hyper != self._hyper():
            diff = sorted(k for k in set(hyper) | set(self._hyper()) if hyper.get(k) != self._hyper().get(k))
            raise ValueError(f"state was saved with other hyperparameters ({diff}): construct the "
                             f"optimiser with the saved ones {hyper}")
        for key in ("exp_avg", "exp_avg_sq"):
            want = {k: (p.dtype, p.shape) for k, p in self.params.items()}
            if {k: (a.dtype, a.shape) for k, a in state[key].items()} != want:
                raise ValueError(f"state[{key!r}] does not hold the parameters' names, dtypes and shapes")
        self.step_count = _checks.integer("state['step']", state["step"], 0)
        self.exp_avg, self.exp_avg_sq = ({k: np.array(state[key][k]) for k in self.params}
                                         for key in ("exp_avg", "exp_avg_sq"))


class Adam(AdamW):
    """Adam without weight decay: AdamW with weight_decay = 0 (no L2 term either; torch's
    Adam(weight_decay=...) adds wd * p to the gradient, which this does not offer).
    The codebook (docs/math.md §4): Adam(params, 1.584e-3, betas=(0.5, 0.9))."""

    def __init__(self, params, lr=1e-3, betas=(0.9, 0.999), eps=1e-8, *, eps_convention="torch"):
        super().__init__(params, lr, betas, eps, 0.0, eps_convention=eps_convention)


# ---------------------------------------------------------------------------------------
# learning-rate schedule


def warmup_cosine_lr(step, peak_lr, warmup_steps, total_steps, min_lr_ratio=0.0):
    """Linear warmup then cosine decay (docs/math.md §5), as the published HuggingFace `WarmUp`
    over Keras `CosineDecay(peak_lr, total_steps - warmup_steps, alpha=min_lr_ratio)`.

    step: updates already applied (0 for the first update; see AdamW). With W = warmup_steps,
    T = total_steps, final = peak_lr * min_lr_ratio:

        step <= W:      peak_lr * step / W            (0 at step 0, peak_lr at step W exactly)
        W < step < T:   final + (peak_lr - final) * (1 + cos(pi * (step - W) / (T - W))) / 2
        step >= T:      final                         (exactly)

    With W = 0 the schedule starts at peak_lr. The published run used W = 2000 and
    min_lr_ratio = 0, so its first update has lr 0 (the moments still accumulate)."""
    step = _checks.integer("step", step, 0)
    peak_lr = _checks.real("peak_lr", peak_lr, lo=0.0)
    warmup_steps = _checks.integer("warmup_steps", warmup_steps, 0)
    total_steps = _checks.integer("total_steps", total_steps, 1)
    if total_steps <= warmup_steps:
        raise ValueError(f"total_steps ({total_steps}) must exceed warmup_steps ({warmup_steps})")
    min_lr_ratio = _checks.real("min_lr_ratio", min_lr_ratio, 0.0, 1.0)
    final = peak_lr * min_lr_ratio
    if step <= warmup_steps and warmup_steps > 0:
        return peak_lr * (step / warmup_steps)
    if step >= total_steps:
        return final
    frac = (step - warmup_steps) / (total_steps - warmup_steps)  # in [0, 1)
    # Keras CosineDecay: peak * ((1 - alpha) * c + alpha), c = (1 + cos(pi frac)) / 2
    return peak_lr * ((1 - min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * frac)) + min_lr_ratio)


class WarmupCosine:
    """warmup_cosine_lr as a callable step -> lr, for AdamW(lr=...). Arguments are checked
    when constructed."""

    def __init__(self, peak_lr, warmup_steps, total_steps, min_lr_ratio=0.0):
        warmup_cosine_lr(0, peak_lr, warmup_steps, total_steps, min_lr_ratio)  # validates
        self.peak_lr, self.warmup_steps = float(peak_lr), int(warmup_steps)
        self.total_steps, self.min_lr_ratio = int(total_steps), float(min_lr_ratio)

    def __call__(self, step):
        return warmup_cosine_lr(step, self.peak_lr, self.warmup_steps, self.total_steps, self.min_lr_ratio)

    def __repr__(self):
        return (f"WarmupCosine(peak_lr={self.peak_lr!r}, warmup_steps={self.warmup_steps}, "
                f"total_steps={self.total_steps}, min_lr_ratio={self.min_lr_ratio!r})")


# ---------------------------------------------------------------------------------------
# gradient clipping


_TINY, _HUGE = 1e-100, 1e100  # outside this range of max|g| the squares are rescaled first


def _norm64(g):
    """|g|_2 of a finite g, its squares summed in float64 (a Python float; NumPy's pairwise sum, the
    same for any thread count). A tensor whose largest entry is beyond 1e+-100 is divided by it
    first, so a gradient of 1e200 or 1e-200 (or of subnormals) gets its norm instead of inf or 0."""
    if g.size == 0:
        return 0.0
    x = g.astype(np.float64, copy=False).ravel()  # (n,)
    amax = float(np.abs(x).max())
    if amax == 0.0:
        return 0.0
    if amax > _HUGE or amax < _TINY:  # float64 only, and rare: x / amax (also for subnormals,
        y = x / amax                    # whose 1 / amax overflows where a power-of-two scale would)
        return amax * math.sqrt(float(np.square(y).sum()))
    return math.sqrt(float(np.square(x).sum()))


def _hypot_all(norms):
    """sqrt(sum n^2) of Python floats, rescaled like _norm64."""
    amax = max(norms, default=0.0)
    if amax == 0.0:
        return 0.0
    return amax * math.sqrt(math.fsum((n / amax) ** 2 for n in norms))


def global_norm(grads):
    """sqrt(sum over tensors of |g|^2) of grads (dict name -> float32/float64 array), accumulated
    in float64 as clip_grad_norm's global mode, nothing modified: nan where a gradient holds a
    NaN, inf where one holds an inf or the total overflows float64 (transformer_step's norm
    without clipping, so that a run logs the same quantity with clipping off)."""
    norms = [_norm64(g) if _checks.all_finite(g) else float(np.linalg.norm(g.astype(np.float64).ravel()))
             for g in grads.values()]
    if any(math.isnan(n) for n in norms):
        return math.nan
    return math.inf if any(math.isinf(n) for n in norms) else _hypot_all(norms)


def _scale(g, num, den):
    """g *= num / den in place (num / den <= 1). Where that coefficient is below the dtype's
    normal range (a tiny max_norm over a huge norm: 1e-3 / 1e37 is subnormal in float32) it
    would be rounded to a few bits or to 0, so g / den * num is computed in float64 instead."""
    coef = num / den
    if coef >= np.finfo(g.dtype).smallest_normal:
        g *= coef  # coef rounded to g's dtype
    else:
        with np.errstate(under="ignore"):  # results that small are correctly rounded subnormals
            np.copyto(g, g.astype(np.float64) / den * num, casting="same_kind")


def clip_grad_norm(grads, max_norm, *, mode="global", error_if_nonfinite=True, eps=1e-6):
    """Clip gradients in place; returns the norm(s) before clipping, accumulated in float64.

    grads: dict name -> float32/float64 array (writable).
    mode="global": torch.nn.utils.clip_grad_norm_. total = sqrt(sum over tensors of |g|^2);
        if total + eps > max_norm every gradient is multiplied by max_norm / (total + eps)
        (torch's eps = 1e-6; eps=0 gives tf.clip_by_global_norm). Returns total (a float).
    mode="per_tensor": tf.clip_by_norm on each tensor alone (Keras `clipnorm`, and what the
        published transformer does with `gradient_clip_val`): a tensor with |g| > max_norm
        becomes g * (max_norm / |g|); the others are left untouched (TF computes
        (g * max_norm) / max(|g|, max_norm) for every tensor, which can move the last bit,
        or overflow g * max_norm; this does neither).
        Returns {name: |g|}.
    All-zero gradients are left as they are (no 0/0). Non-finite gradients: with
    error_if_nonfinite=True (default) ValueError naming the tensors, before anything is
    modified; with False nothing is modified and the non-finite norm is returned (nan or
    inf; in per_tensor mode for those tensors, the finite ones are still clipped), so that
    the caller can skip the step. AdamW.step refuses non-finite gradients in any case."""
    _check_grads(grads, writable=True)
    max_norm = _checks.real("max_norm", max_norm, lo=0.0, lo_open=True)
    eps = _checks.real("eps", eps, lo=0.0)
    if mode not in ("global", "per_tensor"):
        raise ValueError(f"mode must be 'global' or 'per_tensor', got {mode!r}")
    bad = _nonfinite_names(grads)
    if bad and error_if_nonfinite:
        raise ValueError(f"grads contain NaN or inf in {bad}: cannot clip "
                         "(error_if_nonfinite=False returns the non-finite norm instead)")

    def norm_of(k, g):
        if k in bad:
            return float(np.linalg.norm(g.astype(np.float64, copy=False).ravel()))  # nan or inf
        n = _norm64(g)
        if not math.isfinite(n):
            raise ValueError(f"the norm of grads[{k!r}] overflows float64: nothing was clipped")
        return n

    norms = {k: norm_of(k, g) for k, g in grads.items()}
    if mode == "per_tensor":
        for k, g in grads.items():
            n = norms[k]
            if math.isfinite(n) and n > max_norm:
                _scale(g, max_norm, n)  # tf.clip_by_norm: g * max_norm / |g|
        return norms
    if bad:
        return math.nan if any(math.isnan(n) for n in norms.values()) else math.inf
    total = _hypot_all(list(norms.values()))
    if not math.isfinite(total):  # max_norm / inf would zero every gradient
        raise ValueError("the total norm of grads overflows float64: nothing was clipped")
    if total + eps > max_norm:
        for g in grads.values():
            _scale(g, max_norm, total + eps)  # coefficient max_norm / (total + eps) < 1
    return total
