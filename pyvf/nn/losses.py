"""The transformer's losses as forward/backward pairs (docs/math.md §3).

Both return a loss per row (per token); the model takes the means over views, tokens and the
batch itself, so that what is averaged over is visible where it happens.

Arguments are checked as in pyvf.nn.layers: float32/float64 arrays of one dtype, integer targets,
the documented shapes, finite values (TypeError/ValueError naming the argument); a loss or
gradient that overflows the dtype raises ValueError. Inputs are never modified.
"""

import numpy as np

from .. import _checks


def cross_entropy_forward(logits, targets, label_smoothing=0.0):
    """Per-row cross-entropy from the log-sum-exp.

    logits (M, V) float, targets (M,) integers in [0, V) -> loss (M,).
    Target distribution q = (1 - eps) * onehot(target) + eps / V, loss = -sum_v q_v log p_v,
    log p = z - logsumexp(z), z = logits - max: logits of any size give a finite loss.
    label_smoothing in [0, 1]. In float64, the loss rounded to the logits' dtype once.
    cache: the logits (not copied: do not modify them before the backward), each row's max and
    log-sum (float64), the targets, eps.
    """
    _checks.finite_float("logits", logits)
    if logits.ndim != 2 or logits.shape[1] == 0:
        raise ValueError(f"logits must be 2-D (M, V) with V >= 1 classes, got shape {logits.shape}")
    M, V = logits.shape
    _checks.int_array("targets", targets)
    if targets.shape != (M,):
        raise ValueError(f"targets must have shape (M,) = ({M},) (one class per row of logits), got {targets.shape}")
    if M and (targets.min() < 0 or targets.max() >= V):  # numpy would wrap -1 around
        raise ValueError(f"targets must be in [0, {V}) (V = logits.shape[1]), got values in "
                         f"[{targets.min()}, {targets.max()}]")
    eps = _checks.real("label_smoothing", label_smoothing, 0.0, 1.0)
    rowmax = logits.max(axis=1, keepdims=True).astype(np.float64)  # (M, 1)
    with np.errstate(over="ignore"):  # logits spanning beyond float64 give z = -inf: checked below
        z = logits - rowmax  # (M, V) float64, <= 0
        logsum = np.log(np.exp(z).sum(axis=1, keepdims=True))  # (M, 1): log sum_v exp(z_v), in [0, log V]
        # -sum_v q_v log p_v with log p_v = z_v - logsum: (1 - eps) (logsum - z_t) + eps (logsum - mean_v z_v)
        z_t = np.take_along_axis(z, targets.reshape(M, 1), axis=1)  # (M, 1)
        loss = np.zeros((M, 1))  # (M, 1); a term whose weight is 0 is left out (0 * inf is NaN)
        if eps < 1:
            loss += (1 - eps) * (logsum - z_t)
        if eps > 0:
            loss += eps * (logsum - z.mean(axis=1, keepdims=True))
        loss = loss[:, 0].astype(logits.dtype)  # (M,)
    _checks.finite_result("cross_entropy_forward", loss, "the loss")  # logits spanning beyond the dtype
    return loss, (logits, rowmax, logsum, targets, eps)


def cross_entropy_backward(dloss, cache):
    """dloss (M,) -> dlogits (M, V) = dloss * (softmax(logits) - q)."""
    logits, rowmax, logsum, targets, eps = cache
    M, V = logits.shape
    _checks.finite_float("dloss", dloss, logits, "the logits")
    if dloss.shape != (M,):
        raise ValueError(f"dloss must have shape (M,) = ({M},), got {dloss.shape}")
    # forward was loss = -sum_v q_v (z_v - logsum), so dloss/dz_v = p_v - q_v, p = exp(z - logsum)
    with np.errstate(over="ignore"):  # z = -inf: p = 0
        dz = np.exp(logits - rowmax - logsum)  # (M, V): p
    dz -= eps / V  # q's smoothing share
    dz[np.arange(M), targets] -= 1 - eps  # and its target share
    dlogits = (dz * dloss[:, None]).astype(logits.dtype)  # (M, V)
    return (_checks.finite_result("cross_entropy_backward", dlogits, "dlogits"),)


def pose_loss_forward(raw, target, pose_multiplier=1.0):
    """The pose loss on the head's raw output (docs/math.md §3: the raw quaternion, not the normalised one).

    raw (..., 7) = [xyz_raw, q_raw]; target (..., 7) = [xyz, q] in input units, broadcast to raw.
    loss (...) = mean over xyz of (pose_multiplier * xyz - xyz_raw)^2 + mean over wxyz of (q - q_raw)^2.
    The loss has raw's shape without the last axis: target may broadcast to raw, never beyond.
    cache: the two residuals.
    """
    _checks.finite_float("raw", raw, like_name="raw")
    _checks.finite_float("target", target, raw, "raw")
    for name, a in (("raw", raw), ("target", target)):
        if a.ndim < 1 or a.shape[-1] != 7:
            raise ValueError(f"{name} must have last dimension 7 (xyz, then the quaternion wxyz), got shape {a.shape}")
    try:
        shape = np.broadcast_shapes(raw.shape, target.shape)
    except ValueError:
        shape = None
    if shape != raw.shape:
        raise ValueError(f"target of shape {target.shape} does not broadcast to raw's shape {raw.shape}")
    pose_multiplier = _checks.real("pose_multiplier", pose_multiplier)
    big = float(np.finfo(raw.dtype).max)
    if abs(pose_multiplier) > big:  # it would become inf in the dtype, and inf * 0 NaN
        raise ValueError(f"pose_multiplier {pose_multiplier!r} is beyond {raw.dtype}'s range (largest {big:.4g}): "
                         f"the positions are multiplied by it in {raw.dtype}")
    with np.errstate(over="ignore", invalid="ignore"):  # checked: overflow raises
        rxyz = raw[..., :3] - raw.dtype.type(pose_multiplier) * target[..., :3]  # (..., 3)
        rq = raw[..., 3:] - target[..., 3:]  # (..., 4)
        loss = (rxyz * rxyz).mean(axis=-1) + (rq * rq).mean(axis=-1)  # (...)
    _checks.finite_result("pose_loss_forward", loss, "the loss")
    return loss, (rxyz, rq)


def pose_loss_backward(dloss, cache):
    """dloss (...) -> draw (..., 7)."""
    rxyz, rq = cache
    _checks.finite_float("dloss", dloss, rxyz, "raw")
    if dloss.shape != rxyz.shape[:-1]:
        raise ValueError(f"dloss must have the loss's shape {rxyz.shape[:-1]}, got {dloss.shape}")
    # forward was loss = mean_3(rxyz^2) + mean_4(rq^2), rxyz = xyz_raw - m * xyz, rq = q_raw - q
    with np.errstate(over="ignore", invalid="ignore"):  # checked
        draw = np.concatenate([rxyz * (2 / 3), rq * (2 / 4)], axis=-1)  # (..., 7)
        draw *= dloss[..., None]
    return (_checks.finite_result("pose_loss_backward", draw, "draw"),)
