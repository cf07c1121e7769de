"""The transformer's losses as forward/backward pairs (SPEC.md §3).

Both return a loss per row (per token); the model takes the means over views, tokens and the
batch itself, so that what is averaged over is visible where it happens.
"""

import numpy as np


def cross_entropy_forward(logits, targets, label_smoothing=0.0):
    """Per-row cross-entropy from the log-sum-exp.

    logits (M, V) float, targets (M,) integers in [0, V) -> loss (M,).
    Target distribution t = (1 - eps) * onehot(target) + eps / V, loss = -sum_v t_v log p_v,
    log p = logits - logsumexp(logits) computed with the row max subtracted, so logits of any
    size give a finite loss. cache: log p (M, V), targets, eps.
    """
    M, V = logits.shape
    z = logits - logits.max(axis=-1, keepdims=True)  # (M, V), max 0
    logp = z - np.log(np.exp(z).sum(axis=-1, keepdims=True))  # (M, V)
    eps = logits.dtype.type(label_smoothing)
    loss = -(1 - eps) * logp[np.arange(M), targets]  # (M,)
    if label_smoothing:
        loss = loss - eps / V * logp.sum(axis=-1)
    return loss, (logp, targets, eps)


def cross_entropy_backward(dloss, cache):
    """dloss (M,) -> dlogits (M, V) = dloss * (softmax(logits) - t)."""
    logp, targets, eps = cache
    M, V = logp.shape
    dlogits = np.exp(logp)  # (M, V) softmax
    dlogits[np.arange(M), targets] -= 1 - eps
    if eps:
        dlogits -= eps / V
    dlogits *= dloss[:, None]
    return (dlogits,)


def pose_loss_forward(raw, target, pose_multiplier=1.0):
    """The pose loss on the head's raw output (SPEC.md §3: the raw quaternion, not the normalised one).

    raw (..., 7) = [xyz_raw, q_raw]; target (..., 7) = [xyz, q] in input units, broadcast to raw.
    loss (...) = mean over xyz of (pose_multiplier * xyz - xyz_raw)^2 + mean over wxyz of (q - q_raw)^2.
    cache: the two residuals.
    """
    rxyz = raw[..., :3] - raw.dtype.type(pose_multiplier) * target[..., :3]  # (..., 3)
    rq = raw[..., 3:] - target[..., 3:]  # (..., 4)
    loss = (rxyz * rxyz).mean(axis=-1) + (rq * rq).mean(axis=-1)  # (...)
    return loss, (rxyz, rq)


def pose_loss_backward(dloss, cache):
    """dloss (...) -> draw (..., 7)."""
    rxyz, rq = cache
    # forward was loss = mean_3(rxyz^2) + mean_4(rq^2), rxyz = xyz_raw - m * xyz, rq = q_raw - q
    draw = np.concatenate([rxyz * (2 / 3), rq * (2 / 4)], axis=-1)  # (..., 7)
    draw *= dloss[..., None]
    return (draw,)
