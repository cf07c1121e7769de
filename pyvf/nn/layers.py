"""The transformer's small layers as forward/backward pairs (docs/math.md §3).

Every layer is two functions: `x_forward(x, *params) -> (out, cache)` and
`x_backward(dout, cache) -> (dx, *dparams)`, gradients in the order of the forward's
arguments. `cache` holds only what the backward needs; each says what it saves. Arrays keep
their dtype (float32 or float64) throughout; nothing is cast.

Shapes: `...` is any leading shape (e.g. (R, B, N, L)); d the model width.

Arguments are checked as everywhere in pyvf (_checks): float32/float64 ndarrays of one dtype
(TypeError otherwise: nothing is cast), the documented shapes and finite values (ValueError
naming the argument); a result that overflows the dtype raises ValueError instead of handing
inf or NaN to the next layer. Views of any layout are accepted (strided, negative strides,
read-only); inputs are never modified.
"""

import math

import numpy as np

from .. import _checks, _core


def _grad(name, dy, like, shape):
    """dy: the upstream gradient, a finite array of the forward output's dtype and shape."""
    _checks.float_array(name, dy, like, "the forward's input")
    if dy.shape != tuple(shape):
        raise ValueError(f"{name} must have the forward output's shape {tuple(shape)}, got {dy.shape}")
    return _checks.finite(name, dy)


def _check_linear(x, w, b, names=("x", "w", "b")):
    """x (..., din), w (din, dout), b (1, dout): finite, one float dtype."""
    nx, nw, nb = names
    _checks.finite_float(nx, x)
    _checks.finite_float(nw, w, x, nx)
    _checks.finite_float(nb, b, x, nx)
    if w.ndim != 2:
        raise ValueError(f"{nw} must be 2-D (din, dout), got shape {w.shape}")
    din, dout = w.shape
    if x.ndim < 1 or x.shape[-1] != din:
        raise ValueError(f"{nx} must have last dimension din = {din} ({nw}.shape[0]), got shape {x.shape}")
    if b.shape != (1, dout):
        raise ValueError(f"{nb} must have shape (1, {dout}) (dout = {nw}.shape[1]), got {b.shape}")

# ---------------------------------------------------------------------------------------
# matmul (pyvf's GEMM) and add (NumPy's), in the forms the models call


def matmul(a, b, ta=False, tb=False, bias=None):
    """c = op(a) @ op(b) [+ bias], op = transpose when ta / tb, for 2-D operands or per entry of
    3-D ones (a leading batch axis): a (M, K), or (K, M) when ta; b (K, N), or (N, K) when tb; c
    (M, N); bias (N,) added to every row after its sum (as NumPy's a @ b + bias rounds); one
    float dtype (TypeError otherwise; the callers check the values).

    pyvf's GEMM (csrc/conv.cpp matmul_batched), not NumPy's BLAS: each element of c is one sum in
    increasing k, so the result is bitwise the same for any thread count (OpenBLAS's is not for
    some shapes), and the threads are pyvf's, which sleep between calls, where the BLAS's spin for
    milliseconds after each call on the cores pyvf's kernels need (a 2-thread kernel right after a
    2-thread BLAS product ran at the speed of one thread; measured again with the tiny transformer
    on 2 busy cores: np.matmul's 2 BLAS threads made its training step 14x slower, 1143 ms against
    79 ms). Its reference is the expression itself, np.matmul(op(a), op(b)) + bias: the tests
    (tests/test_conv.py, section 7) hold the kernel to it in float64."""
    _checks.float_array("a", a)
    _checks.float_array("b", b, a, "a")
    if bias is not None:
        _checks.float_array("bias", bias, a, "a")
    if a.ndim not in (2, 3):
        raise ValueError(f"a must be 2-D (M, K) or 3-D (batch, M, K), got shape {a.shape}")
    if b.ndim != a.ndim:
        raise ValueError(f"b must have a's {a.ndim} dimensions, got shape {b.shape} for a of shape {a.shape}")
    a, b = _checks.c_order(a), _checks.c_order(b)
    one = a.ndim == 2  # 2-D: one entry of the batched kernel
    a3, b3 = (a[None], b[None]) if one else (a, b)
    M, N = a3.shape[2 if ta else 1], b3.shape[1 if tb else 2]
    c = np.empty((a3.shape[0], M, N), dtype=a.dtype)  # (batch, M, N)
    _core.matmul(c, a3, b3, ta, tb, None if bias is None else _checks.c_order(bias))
    return c[0] if one else c


def add(a, b, out=None):
    """a + b (np.add; out as np.add's, a or b itself included). Kept as the models' name for the
    residual adds."""
    return np.add(a, b, out=out)


# ---------------------------------------------------------------------------------------
# linear, published layout: weight (din, dout), bias (1, dout)


def _linear(x, w, b):
    din, dout = w.shape
    M = int(np.prod(x.shape[:-1]))  # rows; explicit rather than -1, so that din = 0 works
    # (an overflow gives inf, which the callers check)
    return matmul(x.reshape(M, din), w, bias=b.reshape(dout)).reshape(*x.shape[:-1], dout)  # (..., dout)


def _linear_backward(dy, x, w):
    din, dout = w.shape
    M = int(np.prod(x.shape[:-1]))
    dy2 = dy.reshape(M, dout)  # (M, dout)
    with np.errstate(over="ignore", invalid="ignore"):  # the callers check the results
        # forward was y = x @ w + b
        dx = matmul(dy2, w, tb=True).reshape(x.shape)  # dx = dy @ w^T
        dw = matmul(x.reshape(M, din), dy2, ta=True)  # dw = x^T @ dy
        db = dy2.sum(axis=0, keepdims=True)  # db = sum over rows of dy
    return dx, dw, db


def linear_forward(x, w, b):
    """y = x @ w + b.   x (..., din), w (din, dout), b (1, dout) -> y (..., dout).
    cache: x and w (no copies)."""
    _check_linear(x, w, b)
    y = _checks.finite_result("linear_forward", _linear(x, w, b))
    return y, (x, w)


def linear_backward(dy, cache):
    """-> dx (..., din), dw (din, dout), db (1, dout)."""
    x, w = cache
    _grad("dy", dy, x, x.shape[:-1] + (w.shape[1],))
    grads = _linear_backward(dy, x, w)
    for name, g in zip(("dx", "dw", "db"), grads):
        _checks.finite_result("linear_backward", g, name)
    return grads


# ---------------------------------------------------------------------------------------
# LayerNorm over the last axis, eps inside the square root (TF LayerNormalization, eps 1e-5)


def layernorm_forward(x, gamma, beta, eps=1e-5):
    """y = (x - mean) / sqrt(var + eps) * gamma + beta.   x (..., d), gamma, beta (d,).

    Two-pass (csrc/layernorm.cpp, rows on pyvf's threads): the mean is accumulated in float64
    and rounded, the row centred twice (the second time by the centred row's own residual mean),
    then the variance is the mean square of it, accumulated in float64, so a row of mean 1e4 and
    spread 0.1 keeps its digits and a constant row gives y = beta exactly. Rows whose squares
    overflow (|x - mean| beyond 1e154 in float64) are scaled by a power of two first, so they
    normalise too. Bitwise the same for any thread count. cache: xhat (..., d), rstd (..., 1),
    gamma. layernorm_forward_numpy below is the same math in NumPy (float64 throughout), the
    reference the kernel is tested against; the kernel stays because NumPy's ten passes and their
    temporaries took the tiny transformer's training step below 1.3x torch's speed
    (pyvf bench transformer --quick)."""
    _checks.finite_float("x", x)
    if x.ndim < 1 or x.shape[-1] == 0:
        raise ValueError(f"x must have a last dimension d >= 1 to normalise over, got shape {x.shape}")
    d = x.shape[-1]
    _checks.finite_float("gamma", gamma, x)
    _checks.finite_float("beta", beta, x)
    for name, a in (("gamma", gamma), ("beta", beta)):
        if a.shape != (d,):
            raise ValueError(f"{name} must have shape ({d},) for x of shape {x.shape}, got {a.shape}")
    eps = _checks.real("eps", eps, lo=0.0, lo_open=True)
    x, gamma, beta = _checks.c_order(x), _checks.c_order(gamma), _checks.c_order(beta)
    y, xhat = np.empty_like(x), np.empty_like(x)  # (..., d)
    rstd = np.empty(x.shape[:-1] + (1,), x.dtype)  # (..., 1)
    if _core.layernorm_forward(y, xhat, rstd, x, gamma, beta, eps):
        raise ValueError(f"layernorm_forward: mean(x) or x - mean(x) overflows {x.dtype}: rescale x")
    _checks.finite_result("layernorm_forward", y)
    return y, (xhat, rstd, gamma)


def layernorm_backward(dy, cache):
    """-> dx (..., d), dgamma (d,), dbeta (d,)."""
    xhat, rstd, gamma = cache
    _grad("dy", dy, xhat, xhat.shape)
    d = xhat.shape[-1]
    dx = np.empty_like(xhat)  # (..., d)
    dgamma, dbeta = np.empty(d, xhat.dtype), np.empty(d, xhat.dtype)  # (d,)
    # forward was y = xhat * gamma + beta, xhat = (x - mean(x)) * rstd, rstd = (mean((x - mean)^2)
    # + eps)^(-1/2), so dx = rstd * (dxhat - mean(dxhat) - xhat * mean(dxhat * xhat)), dxhat = dy * gamma;
    # dgamma = sum over rows of dy * xhat, dbeta = sum over rows of dy (csrc/layernorm.cpp)
    _core.layernorm_backward(dx, dgamma, dbeta, _checks.c_order(dy), xhat, rstd, gamma)
    for name, g in (("dx", dx), ("dgamma", dgamma), ("dbeta", dbeta)):
        _checks.finite_result("layernorm_backward", g, name)
    return dx, dgamma, dbeta


def layernorm_forward_numpy(x, gamma, beta, eps=1e-5):
    """layernorm_forward's math in NumPy, the reference the C++ kernel is tested against (and the
    same cache). In float64 whatever x's dtype, rounded to it once at the end. Two-pass: the mean, then the
    variance as the mean square of the centred row, centred a second time by its own residual
    mean, so that a row of mean 1e4 and spread 0.1 keeps its digits and a constant row gives
    y = beta exactly. Each row is first divided by a power of two s <= max|x| (exact), so that
    rows near float64's largest value sum and square without overflow; eps enters as eps / s^2.
    cache: xhat (..., d) and rstd (..., 1), rounded to x's dtype, and gamma."""
    d = x.shape[-1]
    x64 = x.astype(np.float64)  # (..., d)
    amax = np.abs(x64).max(axis=-1, keepdims=True)  # (..., 1)
    s = np.ldexp(1.0, np.frexp(np.where(amax > 0, amax, 1.0))[1] - 1)  # (..., 1): s <= max|x| < 2 s
    xs = x64 / s  # (..., d), |xs| < 2
    xc = xs - xs.mean(axis=-1, keepdims=True)  # (..., d)
    xc -= xc.mean(axis=-1, keepdims=True)  # the residual of the rounded mean (0 for a constant row)
    with np.errstate(over="ignore"):  # eps / s^2 beyond float64 (rows below 1e-150): rstd 0, xhat 0
        rstd_s = 1 / np.sqrt((xc * xc).mean(axis=-1, keepdims=True) + eps / (s * s))  # (..., 1)
    xhat = xc * rstd_s  # (..., d)
    y = (xhat * gamma.astype(np.float64) + beta).astype(x.dtype)  # (..., d)
    return y, (xhat.astype(x.dtype), (rstd_s / s).astype(x.dtype), gamma)  # rstd (..., 1) in x's units


def layernorm_backward_numpy(dy, cache):
    """-> dx (..., d), dgamma (d,), dbeta (d,), in float64, rounded to dy's dtype."""
    xhat, rstd, gamma = cache
    d = xhat.shape[-1]
    dy64 = dy.astype(np.float64)  # (..., d)
    # forward was y = xhat * gamma + beta, so dxhat = dy * gamma
    dxhat = dy64 * gamma  # (..., d)
    # forward was xhat = (x - mean(x)) * rstd, rstd = (mean((x - mean)^2) + eps)^(-1/2), so
    # dx = rstd * (dxhat - mean(dxhat) - xhat * mean(dxhat * xhat))
    xhat, rstd = xhat.astype(np.float64), rstd.astype(np.float64)  # (..., d), (..., 1)
    dx = rstd * (dxhat - dxhat.mean(axis=-1, keepdims=True) - xhat * (dxhat * xhat).mean(axis=-1, keepdims=True))
    dgamma = (dy64 * xhat).reshape(-1, d).sum(axis=0)  # (d,): sum over rows of dy * xhat
    dbeta = dy64.reshape(-1, d).sum(axis=0)  # (d,): sum over rows of dy
    return tuple(g.astype(dy.dtype) for g in (dx, dgamma, dbeta))


# ---------------------------------------------------------------------------------------
# GELU, exact erf form: the C++ kernel (accurate in the far negative tail, see csrc/elementwise.cpp)
# beside its NumPy reference


def _gelu(x):
    y = np.empty_like(x)
    _core.gelu(y, x)
    return y


def gelu_forward(x):
    """y = x * Phi(x).   x (...) -> y (...). cache: x (C-contiguous; a copy if x was not).
    Finite for every finite x (|gelu(x)| <= |x|)."""
    _checks.finite_float("x", x)
    x = _checks.c_order(x)
    return _gelu(x), x


def _gelu_backward(dy, x):
    dx = np.empty_like(x)
    _core.gelu_backward(dx, _checks.c_order(dy), x)
    return dx


def gelu_backward(dy, cache):
    """-> dx = dy * (Phi(x) + x * phi(x))."""
    x = cache
    _grad("dy", dy, x, x.shape)
    return (_checks.finite_result("gelu_backward", _gelu_backward(dy, x), "dx"),)


_erfc = np.frompyfunc(math.erfc, 1, 1)  # C99's erfc, one element at a time (NumPy has none)


def gelu_forward_numpy(x):
    """gelu_forward's math in NumPy, the reference the C++ kernel is tested against: in float64,
    Phi(x) = erfc(-x / sqrt(2)) / 2 (erfc, not 1 + erf(x / sqrt(2)), which loses every digit of
    Phi for x <= -6), y = x * Phi(x), rounded once. Slow (Python's erfc per element)."""
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
    _checks.int_array("ids", ids)
    _checks.finite_float("table", table)
    if table.ndim != 2:
        raise ValueError(f"table must be 2-D (n, d), got shape {table.shape}")
    if ids.size and (ids.min() < 0 or ids.max() >= table.shape[0]):  # numpy would wrap -1 around
        raise ValueError(f"ids must be in [0, {table.shape[0]}), got values in [{ids.min()}, {ids.max()}]")
    return table[ids], (ids, table.shape, table.dtype)


def sum_rows_by_id(ids, rows, n):
    """out[k] = the sum of rows[i] over every i with ids[i] == k, in the order of i.
    ids (m,) integers in [0, n), rows (m, d) -> out (n, d), rows' dtype; rows no id names are 0.
    The ids sorted (stably) into runs, each run summed by np.add.reduceat: np.add.at does the same
    one element at a time, 2-4x slower."""
    _checks.int_array("ids", ids)
    if ids.ndim != 1:
        raise ValueError(f"ids must be 1-D (m,), got shape {ids.shape}")
    _checks.float_array("rows", rows)
    if rows.ndim != 2:
        raise ValueError(f"rows must be 2-D (m, d), got shape {rows.shape}")
    if rows.shape[0] != ids.shape[0]:  # rows past the ids were left out of the sum, silently
        raise ValueError(f"rows has {rows.shape[0]} rows but ids has {ids.shape[0]} ids: one id per row")
    n = _checks.integer("n", n, lo=0)
    out = np.zeros((n, rows.shape[1]), dtype=rows.dtype)
    if ids.size:
        order = np.argsort(ids, kind="stable")
        run = ids[order]
        if run[0] < 0 or run[-1] >= n:  # numpy would wrap -1 around
            raise ValueError(f"ids must be in [0, {n}), got values in [{run[0]}, {run[-1]}]")
        starts = np.flatnonzero(np.concatenate(([True], run[1:] != run[:-1])))
        out[run[starts]] = np.add.reduceat(rows[order], starts, axis=0)
    return out


def embedding_backward(dy, cache):
    """-> dtable (n, d): the rows of dy scatter-added at their ids (a row used twice gets both)."""
    ids, shape, dtype = cache
    _checks.float_array("dy", dy)
    if dy.dtype != dtype:
        raise TypeError(f"dy is {dy.dtype} but the table is {dtype}: both must share one dtype "
                        "(pyvf never casts silently)")
    _grad("dy", dy, None, ids.shape + (shape[1],))
    with np.errstate(over="ignore"):  # forward was y = table[ids]
        dtable = sum_rows_by_id(ids.reshape(-1), dy.reshape(ids.size, shape[1]), shape[0])
    return (_checks.finite_result("embedding_backward", dtable, "dtable"),)


# ---------------------------------------------------------------------------------------
# MLP: linear, GELU, linear (the transformer's mlp, the pose embedding and the pose head)


def mlp_forward(x, w_fc, b_fc, w_proj, b_proj):
    """y = gelu(x @ w_fc + b_fc) @ w_proj + b_proj.   x (..., din) -> y (..., dout).
    w_fc (din, dh), b_fc (1, dh), w_proj (dh, dout), b_proj (1, dout)."""
    _check_linear(x, w_fc, b_fc, ("x", "w_fc", "b_fc"))
    _checks.finite_float("w_proj", w_proj, x)
    if w_proj.ndim != 2 or w_proj.shape[0] != w_fc.shape[1]:
        raise ValueError(f"w_proj must be 2-D with {w_fc.shape[1]} rows (w_fc.shape[1]), got shape {w_proj.shape}")
    _checks.finite_float("b_proj", b_proj, x)
    if b_proj.shape != (1, w_proj.shape[1]):
        raise ValueError(f"b_proj must have shape (1, {w_proj.shape[1]}), got {b_proj.shape}")
    h = _checks.c_order(_checks.finite_result("mlp_forward", _linear(x, w_fc, b_fc), "the hidden layer"))  # (..., dh)
    a = _gelu(h)  # (..., dh)
    y = _checks.finite_result("mlp_forward", _linear(a, w_proj, b_proj))  # (..., dout)
    return y, ((x, w_fc), h, (a, w_proj))


def mlp_backward(dy, cache, trace=None, name=""):
    """-> dx, dw_fc, db_fc, dw_proj, db_proj. trace: a dict that also receives the gradients
    of the GELU's output and input, as trace[name + ".gelu"] and trace[name + ".c_fc"] (the
    models' backward after forward(trace=True))."""
    c_fc, c_act, c_proj = cache
    _grad("dy", dy, c_proj[0], c_proj[0].shape[:-1] + (c_proj[1].shape[1],))
    da, dw_proj, db_proj = _linear_backward(dy, *c_proj)  # forward was y = a @ w_proj + b_proj
    dh = _gelu_backward(da, c_act)  # forward was a = gelu(h)
    if trace is not None:
        trace[name + ".gelu"], trace[name + ".c_fc"] = da, dh
    dx, dw_fc, db_fc = _linear_backward(dh, *c_fc)  # forward was h = x @ w_fc + b_fc
    grads = (dx, dw_fc, db_fc, dw_proj, db_proj)
    for name, g in zip(("dx", "dw_fc", "db_fc", "dw_proj", "db_proj"), grads):
        _checks.finite_result("mlp_backward", g, name)
    return grads
