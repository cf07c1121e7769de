"""The transformer's small layers as forward/backward pairs (SPEC.md §3).

Every layer is two functions: `x_forward(x, *params) -> (out, cache)` and
`x_backward(dout, cache) -> (dx, *dparams)`, gradients in the order of the forward's
arguments. `cache` holds only what the backward needs; each says what it saves. Arrays keep
their dtype (float32 or float64) throughout; nothing is cast.

Shapes: `...` is any leading shape (e.g. (R, B, N, L)); d the model width.
"""

import numpy as np

from . import _core

# ---------------------------------------------------------------------------------------
# linear, published layout: weight (din, dout), bias (1, dout)


def linear_forward(x, w, b):
    """y = x @ w + b.   x (..., din), w (din, dout), b (1, dout) -> y (..., dout).
    cache: x and w (no copies)."""
    din, dout = w.shape
    y = (x.reshape(-1, din) @ w + b).reshape(*x.shape[:-1], dout)  # (..., dout)
    return y, (x, w)


def linear_backward(dy, cache):
    """-> dx (..., din), dw (din, dout), db (1, dout)."""
    x, w = cache
    din, dout = w.shape
    dy2 = dy.reshape(-1, dout)  # (M, dout)
    # forward was y = x @ w + b
    dx = (dy2 @ w.T).reshape(x.shape)  # dx = dy @ w^T
    dw = x.reshape(-1, din).T @ dy2  # dw = x^T @ dy
    db = dy2.sum(axis=0, keepdims=True)  # db = sum over rows of dy
    return dx, dw, db


# ---------------------------------------------------------------------------------------
# LayerNorm over the last axis, eps inside the square root (TF LayerNormalization, eps 1e-5)


def layernorm_forward(x, gamma, beta, eps=1e-5):
    """y = (x - mean) / sqrt(var + eps) * gamma + beta.   x (..., d), gamma, beta (d,).

    Two-pass: the mean is accumulated in float64 and rounded, the row centred twice (the second
    time by the centred row's own residual mean), then the variance is the mean square of it, so a row of mean 1e4 and spread 0.1 keeps its digits and a
    constant row gives y = beta exactly. cache: xhat (..., d), rstd (..., 1), gamma."""
    mean = x.mean(axis=-1, keepdims=True, dtype=np.float64).astype(x.dtype)  # (..., 1)
    xc = x - mean  # (..., d)
    # second pass: the rounded mean can be an ulp off, which 1/sqrt(eps) = 316 would amplify on
    # a constant row; the residual mean of xc is tiny and exact to subtract
    xc -= xc.mean(axis=-1, keepdims=True, dtype=np.float64).astype(x.dtype)
    var = np.mean(xc * xc, axis=-1, keepdims=True)  # (..., 1)
    rstd = 1.0 / np.sqrt(var + x.dtype.type(eps))  # (..., 1)
    xhat = xc * rstd  # (..., d)
    y = xhat * gamma + beta  # (..., d)
    return y, (xhat, rstd, gamma)


def layernorm_backward(dy, cache):
    """-> dx (..., d), dgamma (d,), dbeta (d,)."""
    xhat, rstd, gamma = cache
    d = xhat.shape[-1]
    # forward was y = xhat * gamma + beta
    dgamma = (dy * xhat).reshape(-1, d).sum(axis=0)  # (d,)
    dbeta = dy.reshape(-1, d).sum(axis=0)  # (d,)
    dxhat = dy * gamma  # (..., d)
    # forward was xhat = (x - mean(x)) * rstd, rstd = (mean((x - mean)^2) + eps)^(-1/2), so
    # dx = rstd * (dxhat - mean(dxhat) - xhat * mean(dxhat * xhat))
    dx = rstd * (dxhat - dxhat.mean(axis=-1, keepdims=True) - xhat * (dxhat * xhat).mean(axis=-1, keepdims=True))
    return dx, dgamma, dbeta


# ---------------------------------------------------------------------------------------
# GELU, exact erf form (the C++ kernel: accurate in the far negative tail, see csrc/elementwise.cpp)


def _contig(x):
    # the kernels take C-contiguous arrays; layer outputs already are, so this copies nothing there
    return np.ascontiguousarray(x)


def gelu_forward(x):
    """y = x * Phi(x).   x (...) -> y (...). cache: x."""
    x = _contig(x)
    y = np.empty_like(x)
    _core.gelu(y, x)
    return y, x


def gelu_backward(dy, cache):
    """-> dx = dy * (Phi(x) + x * phi(x))."""
    x = cache
    dx = np.empty_like(x)
    _core.gelu_backward(dx, _contig(dy), x)
    return (dx,)


# ---------------------------------------------------------------------------------------
# embedding lookup


def embedding_forward(ids, table):
    """y = table[ids].   ids (...) integers in [0, len(table)), table (n, d) -> y (..., d).
    cache: ids and the table's shape."""
    if ids.dtype.kind not in "iu":
        raise TypeError(f"ids must be integers, got {ids.dtype}")
    if ids.size and (ids.min() < 0 or ids.max() >= table.shape[0]):  # numpy would wrap -1 around
        raise ValueError(f"ids must be in [0, {table.shape[0]}), got values in [{ids.min()}, {ids.max()}]")
    return table[ids], (ids, table.shape)


def embedding_backward(dy, cache):
    """-> dtable (n, d): the rows of dy scatter-added at their ids (a row used twice gets both)."""
    ids, shape = cache
    dtable = np.zeros(shape, dtype=dy.dtype)
    np.add.at(dtable, ids.reshape(-1), dy.reshape(-1, shape[1]))  # forward was y = table[ids]
    return (dtable,)


# ---------------------------------------------------------------------------------------
# MLP: linear, GELU, linear (the transformer's mlp, the pose embedding and the pose head)


def mlp_forward(x, w_fc, b_fc, w_proj, b_proj):
    """y = gelu(x @ w_fc + b_fc) @ w_proj + b_proj.   x (..., din) -> y (..., dout)."""
    h, c_fc = linear_forward(x, w_fc, b_fc)  # (..., dh)
    a, c_act = gelu_forward(h)  # (..., dh)
    y, c_proj = linear_forward(a, w_proj, b_proj)  # (..., dout)
    return y, (c_fc, c_act, c_proj)


def mlp_backward(dy, cache):
    """-> dx, dw_fc, db_fc, dw_proj, db_proj."""
    c_fc, c_act, c_proj = cache
    da, dw_proj, db_proj = linear_backward(dy, c_proj)
    (dh,) = gelu_backward(da, c_act)
    dx, dw_fc, db_fc = linear_backward(dh, c_fc)
    return dx, dw_fc, db_fc, dw_proj, db_proj
