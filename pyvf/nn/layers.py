"""The transformer's small layers as forward/backward pairs (docs/math.md §3):
`x_forward(x, *params) -> (out, cache)`, `x_backward(dout, cache) -> (dx, *dparams)`. Arrays keep
their dtype throughout. `...` is any leading shape (e.g. (R, B, N, L)); d the model width.
"""

import math

import numpy as np

from .. import _core


# ---------------------------------------------------------------------------------------
# matmul, in the forms the layers call


def matmul(a, b, ta=False, tb=False, bias=None):
    """c = op(a) @ op(b) [+ bias], op = transpose when ta / tb, for 2-D operands or per entry of
    3-D ones: a (M, K), or (K, M) when ta; b (K, N), or (N, K) when tb; c (M, N); bias (N,) added
    after the sum. pyvf's GEMM (csrc/matmul.cpp; reference matmul_numpy): each element one sum in
    increasing k, the same for any thread count, no BLAS threads spinning on the kernels' cores."""
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    one = a.ndim == 2  # 2-D: one entry of the batched kernel
    a3, b3 = (a[None], b[None]) if one else (a, b)
    M, N = a3.shape[2 if ta else 1], b3.shape[1 if tb else 2]
    c = np.empty((a3.shape[0], M, N), dtype=a.dtype)  # (batch, M, N)
    _core.matmul(c, a3, b3, ta, tb, None if bias is None else np.ascontiguousarray(bias))
    return c[0] if one else c


def matmul_numpy(a, b, ta=False, tb=False, bias=None):
    """matmul in NumPy: np.matmul(op(a), op(b)) + bias."""
    c = np.matmul(a.swapaxes(-1, -2) if ta else a, b.swapaxes(-1, -2) if tb else b)
    return c if bias is None else c + bias


# ---------------------------------------------------------------------------------------
# linear, published layout: weight (din, dout), bias (1, dout)


def linear_forward(x, w, b):
    """y = x @ w + b.   x (..., din), w (din, dout), b (1, dout) -> y (..., dout), one matmul
    over all rows. cache: x and w (no copies)."""
    din, dout = w.shape
    M = math.prod(x.shape[:-1])  # rows; explicit rather than -1, so that din = 0 works
    y = matmul(x.reshape(M, din), w, bias=b[0])  # (M, dout)
    return y.reshape(*x.shape[:-1], dout), (x, w)


def linear_backward(dy, cache):
    """-> dx (..., din), dw (din, dout), db (1, dout)."""
    x, w = cache
    din, dout = w.shape
    M = math.prod(x.shape[:-1])  # rows
    dy2 = dy.reshape(M, dout)  # (M, dout)
    # forward was y = x @ w + b
    dx = matmul(dy2, w, tb=True).reshape(x.shape)  # (..., din): dx = dy @ w^T
    dw = matmul(x.reshape(M, din), dy2, ta=True)  # (din, dout): dw = x^T @ dy
    db = dy2.sum(axis=0, keepdims=True)  # (1, dout): db = sum over rows of dy
    return dx, dw, db


# ---------------------------------------------------------------------------------------
# LayerNorm over the last axis, eps inside the square root (TF LayerNormalization, eps 1e-5)


def layernorm_forward(x, gamma, beta, eps=1e-5):
    """y = (x - mean) / sqrt(var + eps) * gamma + beta.   x (..., d), gamma, beta (d,).
    Two-pass: the row centred by its float64 mean rounded, then by the residual mean, the variance
    the mean square of that: a row of mean 1e4 and spread 0.1 keeps its digits and a constant row
    gives y = beta exactly. cache: xhat (..., d), rstd (..., 1), gamma."""
    xc = x - x.mean(axis=-1, keepdims=True, dtype=np.float64).astype(x.dtype)  # (..., d)
    xc -= xc.mean(axis=-1, keepdims=True, dtype=np.float64).astype(x.dtype)  # the rounded mean's residual
    var = np.einsum("...i,...i->...", xc, xc)[..., None] / x.shape[-1]  # (..., 1): mean of xc^2
    rstd = 1 / np.sqrt(var + x.dtype.type(eps))  # (..., 1)
    xhat = xc * rstd  # (..., d)
    return xhat * gamma + beta, (xhat, rstd, gamma)


def layernorm_backward(dy, cache):
    """-> dx (..., d), dgamma (d,), dbeta (d,)."""
    xhat, rstd, gamma = cache
    d = xhat.shape[-1]
    M = math.prod(xhat.shape[:-1])  # rows
    # forward was y = xhat * gamma + beta, so dxhat = dy * gamma, dgamma = sum over rows of dy * xhat
    dxhat = dy * gamma  # (..., d)
    dgamma = np.einsum("mi,mi->i", dy.reshape(M, d), xhat.reshape(M, d))  # (d,)
    dbeta = dy.reshape(M, d).sum(axis=0)  # (d,)
    # forward was xhat = (x - mean(x)) * rstd, rstd = (mean((x - mean)^2) + eps)^(-1/2), so
    # dx = rstd * (dxhat - mean(dxhat) - xhat * mean(dxhat * xhat))
    proj = np.einsum("...i,...i->...", dxhat, xhat)[..., None] / d  # (..., 1): mean(dxhat * xhat)
    dx = rstd * (dxhat - dxhat.mean(axis=-1, keepdims=True) - xhat * proj)  # (..., d)
    return dx, dgamma, dbeta


# ---------------------------------------------------------------------------------------
# GELU, exact erf form: the C++ kernel (NumPy has no erfc, see csrc/gelu.cpp) beside its NumPy
# reference


def gelu_forward(x):
    """y = x * Phi(x).   x (...) -> y (...). cache: x (C-contiguous; a copy if x was not)."""
    x = np.asarray(x, order="C")  # not ascontiguousarray, which makes a 0-d array 1-d
    y = np.empty_like(x)
    _core.gelu(y, x)
    return y, x


def gelu_backward(dy, cache):
    """-> dx = dy * (Phi(x) + x * phi(x))."""
    x = cache
    dx = np.empty_like(x)
    _core.gelu_backward(dx, np.asarray(dy, order="C"), x)
    return (dx,)


_erfc = np.frompyfunc(math.erfc, 1, 1)  # C99's erfc, one element at a time (NumPy has none)


def gelu_forward_numpy(x):
    """gelu_forward in NumPy, the C++ kernel's reference: in float64, Phi(x) = erfc(-x / sqrt(2)) / 2
    (not (1 + erf(x / sqrt(2))) / 2, which loses every digit for x <= -6), y = x * Phi(x) rounded once."""
    x64 = x.astype(np.float64)  # (...)
    Phi = 0.5 * _erfc(-x64 / math.sqrt(2)).astype(np.float64)  # (...)
    return (x64 * Phi).astype(x.dtype), x


def gelu_backward_numpy(dy, cache):
    """-> dx: forward was y = x * Phi(x), so dx = dy * (Phi(x) + x * phi(x)), phi the normal pdf."""
    x64 = cache.astype(np.float64)  # (...)
    Phi = 0.5 * _erfc(-x64 / math.sqrt(2)).astype(np.float64)  # (...)
    phi = np.exp(-0.5 * x64 * x64) / math.sqrt(2 * math.pi)  # (...)
    return ((dy * (Phi + x64 * phi)).astype(cache.dtype),)


# ---------------------------------------------------------------------------------------
# embedding lookup


def embedding_forward(ids, table):
    """y = table[ids].   ids (...) integers in [0, len(table)), table (n, d) -> y (..., d).
    cache: ids and the table's shape."""
    return table[ids], (ids, table.shape)


def sum_rows_by_id(ids, rows, n):
    """out[k] = the sum of rows[i] over every i with ids[i] == k, in the order of i.
    ids (m,) integers in [0, n), rows (m, d) -> out (n, d), rows' dtype. The ids sorted (stably)
    into runs, each run summed by np.add.reduceat (np.add.at: 2-4x slower)."""
    out = np.zeros((n, rows.shape[1]), dtype=rows.dtype)
    if ids.size:
        order = np.argsort(ids, kind="stable")
        run = ids[order]
        starts = np.flatnonzero(np.concatenate(([True], run[1:] != run[:-1])))
        out[run[starts]] = np.add.reduceat(rows[order], starts, axis=0)
    return out


def embedding_backward(dy, cache):
    """-> dtable (n, d): the rows of dy scatter-added at their ids (a row used twice gets both)."""
    ids, (n, d) = cache
    # forward was y = table[ids]
    return (sum_rows_by_id(ids.reshape(-1), dy.reshape(ids.size, d), n),)


# ---------------------------------------------------------------------------------------
# MLP: linear, GELU, linear (the transformer's mlp, the pose embedding and the pose head)


def mlp_forward(x, w_fc, b_fc, w_proj, b_proj):
    """y = gelu(x @ w_fc + b_fc) @ w_proj + b_proj.   x (..., din) -> y (..., dout).
    w_fc (din, dh), b_fc (1, dh), w_proj (dh, dout), b_proj (1, dout).
    cache: ((x, w_fc), h, (a, w_proj)), h the hidden layer before the GELU, a after it."""
    h, c_fc = linear_forward(x, w_fc, b_fc)  # (..., dh)
    a, h = gelu_forward(h)  # (..., dh)
    y, c_proj = linear_forward(a, w_proj, b_proj)  # (..., dout)
    return y, (c_fc, h, c_proj)


def mlp_backward(dy, cache, trace=None, name=""):
    """-> dx, dw_fc, db_fc, dw_proj, db_proj. trace: None, or a dict that also receives the
    gradients of the GELU's output and input, as trace[name + ".gelu"] and trace[name + ".c_fc"]."""
    c_fc, h, c_proj = cache
    da, dw_proj, db_proj = linear_backward(dy, c_proj)  # forward was y = a @ w_proj + b_proj
    (dh,) = gelu_backward(da, h)  # forward was a = gelu(h)
    if trace is not None:
        trace[name + ".gelu"], trace[name + ".c_fc"] = da, dh
    dx, dw_fc, db_fc = linear_backward(dh, c_fc)  # forward was h = x @ w_fc + b_fc
    return dx, dw_fc, db_fc, dw_proj, db_proj
