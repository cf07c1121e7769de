"""The transformer's losses as forward/backward pairs (docs/math.md §3). Both return a loss per
row (per token); the model takes the means itself, so that what is averaged is visible there.
"""

import numpy as np


def cross_entropy_forward(logits, targets, label_smoothing=0.0):
    """Per-row cross-entropy from the log-sum-exp: logits (M, V), targets (M,) in [0, V) -> loss (M,).

    Target q = (1 - eps) * onehot(target) + eps / V, eps = label_smoothing in [0, 1]; loss =
    -sum_v q_v log p_v, log p = z - logsumexp(z), z = logits - max: finite for logits of any size.
    In float64, rounded to the logits' dtype once. cache: the logits (not copied), each row's max
    and log-sum (float64), the targets, eps.
    """
    M, V = logits.shape
    eps = label_smoothing
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
    return loss, (logits, rowmax, logsum, targets, eps)


def cross_entropy_backward(dloss, cache):
    """dloss (M,) -> dlogits (M, V) = dloss * (softmax(logits) - q)."""
    logits, rowmax, logsum, targets, eps = cache
    M, V = logits.shape
    # forward was loss = -sum_v q_v (z_v - logsum), so dloss/dz_v = p_v - q_v, p = exp(z - logsum)
    with np.errstate(over="ignore"):  # z = -inf: p = 0
        dz = np.exp(logits - rowmax - logsum)  # (M, V): p
    dz -= eps / V  # q's smoothing share
    dz[np.arange(M), targets] -= 1 - eps  # and its target share
    dlogits = (dz * dloss[:, None]).astype(logits.dtype)  # (M, V)
    return (dlogits,)


def pose_loss_forward(raw, target, pose_multiplier=1.0, sign_invariant=False):
    """The pose loss on the head's raw output (docs/math.md §3: the raw quaternion, not the normalised one).

    raw (..., 7) = [xyz_raw, q_raw]; target (..., 7) = [xyz, q] in input units, broadcast to raw
    -> loss (...) = mean over xyz of (pose_multiplier * xyz - xyz_raw)^2 + mean over wxyz of
    (q - q_raw)^2. sign_invariant: q is replaced by -q where q . q_raw < 0 (the same rotation; the
    sign nearer the prediction), so a prediction never has to jump where the target's sign flips.
    cache: the two residuals (the gradient holds the chosen sign fixed).
    """
    rxyz = raw[..., :3] - raw.dtype.type(pose_multiplier) * target[..., :3]  # (..., 3)
    q = target[..., 3:]
    if sign_invariant:
        q = np.where((q * raw[..., 3:]).sum(axis=-1, keepdims=True) < 0, -q, q)  # (..., 4)
    rq = raw[..., 3:] - q  # (..., 4)
    loss = (rxyz * rxyz).mean(axis=-1) + (rq * rq).mean(axis=-1)  # (...)
    return loss, (rxyz, rq)


def pose_loss_backward(dloss, cache):
    """dloss (...) -> draw (..., 7)."""
    rxyz, rq = cache
    # forward was loss = mean_3(rxyz^2) + mean_4(rq^2), rxyz = xyz_raw - m * xyz, rq = q_raw - q
    draw = np.concatenate([rxyz * (2 / 3), rq * (2 / 4)], axis=-1)  # (..., 7)
    draw *= dloss[..., None]
    return (draw,)
