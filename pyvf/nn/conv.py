"""The codebook's image layers as forward/backward pairs (docs/math.md §4): conv2d, GroupNorm,
swish, nearest-neighbour x2 upsampling, and the 2D attention block built from them.

Every layer is two functions: `x_forward(x, *params) -> (out, cache)` and
`x_backward(dout, cache) -> (dx, *dparams)`, gradients in the order of the forward's
arguments. `cache` holds only what the backward needs; each says what it saves and what it
recomputes. Arrays keep their dtype (float32 or float64) throughout; nothing is cast, and a
parameter of another dtype than x is refused rather than converted.

Shapes: images are NCHW, (B, C, Hi, Wi); conv weights are torch's (Co, C, kh, kw), biases
(Co,), so an official `state_dict` loads as is. Co, Ho, Wo are a conv's output channels and
size; P = Hi * Wi pixels; K = C * kh * kw the length of one im2col column.
"""

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from .. import _checks, _core
from .layers import matmul



# ---------------------------------------------------------------------------------------
# argument checks (shared): name the argument, never cast


def _check_float(name, a, like=None, like_name="x", finite=True):
    """A float32/float64 ndarray (of like's dtype), finite: NaN or inf raise naming `name`.
    finite=False: the finiteness is left to _after_kernel (conv2d and GroupNorm)."""
    _checks.float_array(name, a, like, like_name)
    if finite:
        _checks.finite(name, a)


def _after_kernel(what, run, outputs, inputs, every_input_read=True):
    """run() (a C++ kernel call), then the outputs ((name, array), ...) checked finite; the inputs
    ((name, array), ...) are scanned only when the kernel raised or an output is not finite.

    conv2d's and GroupNorm's outputs are not finite whenever an input they read holds NaN or inf
    (every input element is a term of some output's sum, and NaN/inf propagate through sums;
    GroupNorm's group statistics read all of x), so scanning the inputs only then names the same
    argument as scanning them first, without a pass over every input on every call (in a paper
    codebook's training step those passes read 2.2 GB: 3% of the step). An input element no output
    reads would not be found: every_input_read=False (a stride larger than the kernel skips pixels; an
    empty output reads nothing) scans the inputs first. An output not finite from finite inputs
    overflowed: _checks.finite_result's message."""
    if not every_input_read:
        for name, a in inputs:
            _checks.finite(name, a)
    try:
        run()
    except ValueError:  # the kernel's own check of y / dx: an input's NaN or inf, else an overflow
        for name, a in inputs:
            _checks.finite(name, a)
        raise
    for name, g in outputs:
        if not _checks.all_finite(g):
            for iname, a in inputs:
                _checks.finite(iname, a)
            _checks.finite_result(what, g, name)


def _check_image(name, x, finite=True):
    _check_float(name, x, finite=finite)
    if x.ndim != 4:
        raise ValueError(f"{name} must be 4-D (B, C, Hi, Wi), got shape {x.shape}")


def _check_vector(name, a, n, x, finite=True):
    _check_float(name, a, like=x, finite=finite)
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {a.shape}")


def _check_grad(name, dy, shape):
    if not isinstance(dy, np.ndarray):  # a TypeError, as _checks.float_array's
        raise TypeError(f"{name} must be a numpy.ndarray of the forward output's shape {shape}, "
                        f"got {type(dy).__name__}")
    if dy.shape != shape:
        raise ValueError(f"{name} must be an array of the forward output's shape {shape}, got {dy.shape}")


INT_MAX = 2**31 - 1  # the kernels' sides, strides and paddings are C ints (csrc/conv_bind.cpp)


def _padding4(padding):
    """int p -> (p, p, p, p); (top, bottom, left, right) -> itself. Non-negative ints only."""
    if isinstance(padding, (int, np.integer)) and not isinstance(padding, bool):
        pad = (int(padding),) * 4
    else:
        try:
            pad = tuple(padding)
        except TypeError:
            raise TypeError(f"padding must be an int or (top, bottom, left, right), got {padding!r}") from None
        if len(pad) != 4 or not all(isinstance(p, (int, np.integer)) and not isinstance(p, bool) for p in pad):
            raise ValueError(f"padding must be an int or 4 ints (top, bottom, left, right), got {padding!r}")
        pad = tuple(int(p) for p in pad)
    if min(pad) < 0:
        raise ValueError(f"padding must be non-negative, got {padding!r}")
    if max(pad) > INT_MAX:
        raise ValueError(f"padding must be at most 2^31 - 1 (the kernels' int sides), got {padding!r}")
    return pad


# ---------------------------------------------------------------------------------------
# conv2d: cross-correlation as torch.nn.functional.conv2d, any kernel, stride, padding


def _im2col(x, kh, kw, stride, pad):
    """x (B, C, Hi, Wi) -> cols (B, K, Ho*Wo), K = C*kh*kw in w's (c, i, j) order:
    cols[b, (c, i, j), (u, v)] = xpad[b, c, stride*u + i, stride*v + j]. One copy (the columns);
    the windows themselves are a strided view."""
    pt, pb, pl, pr = pad
    # zero padding on each side separately: np.pad's order is (before, after) per axis, here
    # (top, bottom) for the rows and (left, right) for the columns. The Downsample's (0, 1, 0, 1)
    # pads only after (bottom, right): the padding trap of docs/math.md §4, see conv2d_forward
    xp = np.pad(x, ((0, 0), (0, 0), (pt, pb), (pl, pr))) if any(pad) else x  # (B, C, Hp, Wp)
    win = sliding_window_view(xp, (kh, kw), axis=(2, 3))[:, :, ::stride, ::stride]  # (B, C, Ho, Wo, kh, kw), a view
    B, C, Ho, Wo = win.shape[:4]
    return win.transpose(0, 1, 4, 5, 2, 3).reshape(B, C * kh * kw, Ho * Wo)  # (B, K, Ho*Wo)


def _conv_args(x, w, b, stride, padding):
    """Check conv2d's arguments (naming the wrong one, never casting) -> (stride, pad, Ho, Wo)."""
    _check_image("x", x, finite=False)  # finiteness: _after_kernel
    _check_float("w", w, like=x, finite=False)
    if w.ndim != 4:
        raise ValueError(f"w must be 4-D (Co, C, kh, kw), got shape {w.shape}")
    B, C, Hi, Wi = x.shape
    Co, Cw, kh, kw = w.shape
    if Cw != C:
        raise ValueError(f"w has {Cw} input channels (w.shape[1]) but x has {C} (x.shape[1])")
    _check_vector("b", b, Co, x, finite=False)
    if not isinstance(stride, (int, np.integer)) or isinstance(stride, bool) or not 1 <= stride <= INT_MAX:
        raise ValueError(f"stride must be a positive int of at most 2^31 - 1, got {stride!r}")
    stride = int(stride)
    pad = _padding4(padding)
    pt, pb, pl, pr = pad
    Ho, Wo = (Hi + pt + pb - kh) // stride + 1, (Wi + pl + pr - kw) // stride + 1
    if Ho < 1 or Wo < 1:
        raise ValueError(f"kernel {kh}x{kw} does not fit the padded image {Hi + pt + pb}x{Wi + pl + pr} "
                         f"(x {Hi}x{Wi}, padding {padding!r})")
    return stride, pad, Ho, Wo


def _reads_every_x(x, w, stride, pad):
    """Whether conv2d's windows read every element of x: along each axis the windows leave no gap
    (kernel >= stride) and the last one reaches the last row / column; and y is not empty."""
    B, _, Hi, Wi = x.shape
    Co, _, kh, kw = w.shape
    pt, pb, pl, pr = pad
    Ho, Wo = (Hi + pt + pb - kh) // stride + 1, (Wi + pl + pr - kw) // stride + 1
    return (B > 0 and Co > 0 and kh >= stride and kw >= stride and (Ho - 1) * stride - pt + kh >= Hi
            and (Wo - 1) * stride - pl + kw >= Wi)


def _conv_grad_args(dy, cache):
    x, w, stride, pad = cache
    B, C, Hi, Wi = x.shape
    Co, _, kh, kw = w.shape
    pt, pb, pl, pr = pad
    Ho, Wo = (Hi + pt + pb - kh) // stride + 1, (Wi + pl + pr - kw) // stride + 1
    _check_grad("dy", dy, (B, Co, Ho, Wo))
    _check_float("dy", dy, like=x, like_name="the forward's x", finite=False)  # finiteness: _after_kernel
    return x, w, stride, pad


def conv2d_forward(x, w, b, stride=1, padding=0):
    """y = conv2d(x, w) + b, torch's cross-correlation (no kernel flip).

    x (B, C, Hi, Wi), w (Co, C, kh, kw), b (Co,) -> y (B, Co, Ho, Wo),
    Ho = (Hi + top + bottom - kh) // stride + 1, Wo likewise.
    padding: an int (the same zeros on all four sides, torch's `padding=p`) or
    (top, bottom, left, right).

    Padding trap (docs/math.md §4): the Downsample pads only the right and the bottom, by one pixel,
    then convolves 3x3 stride 2 with padding 0: padding=(0, 1, 0, 1) here, F.pad(x, (0, 1, 0, 1))
    in torch (whose order is (left, right, top, bottom); with these numbers both orders agree).
    padding=1 gives the same output size on even images but shifts every window by one pixel;
    (1, 0, 1, 0) pads the wrong corner. Neither raises: only the values tell.

    The C++ kernel (csrc/conv.cpp): implicit GEMM, y_b = w2 @ cols_b + b with w2 = w as (Co, K),
    K = C*kh*kw, the im2col columns cols_b (K, Ho*Wo) built a cache-sized tile at a time and never
    stored whole; every y element one dot product of K terms in T. conv2d_forward_numpy is the same
    layer in NumPy (one BLAS matmul on the whole cols), kept as a second reference.
    cache: x and w (no copies unless they were not C-contiguous), stride, padding; the columns
    are recomputed in the backward (they are kh*kw times the size of x)."""
    stride, pad, Ho, Wo = _conv_args(x, w, b, stride, padding)
    x, w, b = (_checks.c_order(a) for a in (x, w, b))  # the kernel takes C order; views are copied once
    y = np.empty((x.shape[0], w.shape[0], Ho, Wo), dtype=x.dtype)  # (B, Co, Ho, Wo)
    # the kernel raises if y is not finite (each task checks its part); then x, w, b are scanned
    _after_kernel("conv2d_forward", lambda: _core.conv2d_forward(y, x, w, b, stride, *pad), (),
                  (("x", x), ("w", w), ("b", b)), _reads_every_x(x, w, stride, pad))
    return y, (x, w, stride, pad)


def conv2d_backward(dy, cache):
    """-> dx (B, C, Hi, Wi), dw (Co, C, kh, kw), db (Co,).

    forward was y_b = w2 @ cols_b + b, so dw = sum_b dy_b @ cols_b^T, dcols_b = w2^T @ dy_b
    (scattered back onto x by col2im), db = sum of dy over b, u, v. The C++ kernel computes dx of a
    stride-1 conv as the conv of dy with the flipped, transposed kernel (a gather, no scatter);
    csrc/conv.cpp says how dw and db are split into tasks so that the result is the same for any
    thread count."""
    x, w, stride, pad = _conv_grad_args(dy, cache)
    dy = _checks.c_order(dy)
    dx, dw = np.empty_like(x), np.empty_like(w)  # (B, C, Hi, Wi), (Co, C, kh, kw)
    db = np.empty(w.shape[0], dtype=x.dtype)  # (Co,)
    # the kernel raises if dx, dw or db is not finite (each task checks what it wrote), then dy is
    # scanned. db is the sum of every dy element, so a NaN or inf anywhere in dy makes it not finite.
    _after_kernel("conv2d_backward", lambda: _core.conv2d_backward(dx, dw, db, x, w, dy, stride, *pad),
                  (), (("dy", dy),))
    return dx, dw, db


def conv2d_forward_numpy(x, w, b, stride=1, padding=0):
    """conv2d_forward in NumPy: one BLAS matmul on the whole im2col columns. Same arguments,
    output and cache; a second reference for the tests (and conv2d_backward_numpy takes the
    cache of either).

    One matmul: y_b = w2 @ cols_b, w2 = w as (Co, K), cols the im2col columns (B, K, Ho*Wo).
    A 1x1 conv with stride 1 and no padding is a plain matmul on x itself (no columns)."""
    stride, pad, Ho, Wo = _conv_args(x, w, b, stride, padding)
    B, C, Hi, Wi = x.shape
    Co, _, kh, kw = w.shape
    w2 = w.reshape(Co, C * kh * kw)  # (Co, K), columns in (c, i, j) order
    if kh == kw == 1 and stride == 1 and not any(pad):
        y = w2 @ x.reshape(B, C, Hi * Wi)  # (B, Co, P): y[b,o,p] = sum_c w[o,c] x[b,c,p]
    else:
        y = w2 @ _im2col(x, kh, kw, stride, pad)  # (B, Co, Ho*Wo): y[b,o,p] = sum_k w2[o,k] cols[b,k,p]
    y = y.reshape(B, Co, Ho, Wo)
    y += b[:, None, None]  # (B, Co, Ho, Wo)
    return y, (x, w, stride, pad)


def conv2d_backward_numpy(dy, cache):
    """conv2d_backward in NumPy -> dx (B, C, Hi, Wi), dw (Co, C, kh, kw), db (Co,)."""
    x, w, stride, pad = _conv_grad_args(dy, cache)
    B, C, Hi, Wi = x.shape
    Co, _, kh, kw = w.shape
    pt, pb, pl, pr = pad
    Ho, Wo = dy.shape[2:]
    dy2 = dy.reshape(B, Co, Ho * Wo)  # (B, Co, Ho*Wo)
    w2 = w.reshape(Co, C * kh * kw)  # (Co, K)
    # forward was y = ... + b[o], so db[o] = sum over b, u, v of dy
    db = dy.sum(axis=(0, 2, 3))  # (Co,)

    if kh == kw == 1 and stride == 1 and not any(pad):
        x2 = x.reshape(B, C, Hi * Wi)  # (B, C, P)
        # forward was y_b = w2 @ x_b, so dx_b = w2^T @ dy_b and dw = sum_b dy_b @ x_b^T
        dx = (w2.T @ dy2).reshape(x.shape)  # (B, C, Hi, Wi)
        dw = (dy2 @ x2.transpose(0, 2, 1)).sum(axis=0).reshape(w.shape)  # (Co, C, 1, 1)
        return dx, dw, db

    cols = _im2col(x, kh, kw, stride, pad)  # (B, K, Ho*Wo), recomputed
    # forward was y_b = w2 @ cols_b, so dw = sum_b dy_b @ cols_b^T, dcols_b = w2^T @ dy_b
    dw = (dy2 @ cols.transpose(0, 2, 1)).sum(axis=0).reshape(w.shape)  # (Co, C, kh, kw)
    dcols = (w2.T @ dy2).reshape(B, C, kh, kw, Ho, Wo)  # (B, C, kh, kw, Ho, Wo)
    # col2im: forward read cols[b, (c,i,j), (u,v)] = xpad[b, c, stride*u + i, stride*v + j], so each
    # kernel offset (i, j) scatter-adds its (Ho, Wo) slab onto a strided slice of the padded image
    dxp = np.zeros((B, C, Hi + pt + pb, Wi + pl + pr), dtype=x.dtype)  # (B, C, Hp, Wp)
    for i in range(kh):
        for j in range(kw):
            dxp[:, :, i:i + stride * (Ho - 1) + 1:stride, j:j + stride * (Wo - 1) + 1:stride] += dcols[:, :, i, j]
    # the padding was constant zeros: its gradient is dropped; crop (top, left) to where x sits
    dx = np.ascontiguousarray(dxp[:, :, pt:pt + Hi, pl:pl + Wi])  # (B, C, Hi, Wi)
    return dx, dw, db


# ---------------------------------------------------------------------------------------
# GroupNorm (Normalize in the codebook): 32 groups of contiguous channels, eps 1e-6, affine


def _groupnorm_args(x, gamma, beta, groups, eps):
    _check_image("x", x, finite=False)  # finiteness: _after_kernel
    B, C, Hi, Wi = x.shape
    _check_vector("gamma", gamma, C, x, finite=False)
    _check_vector("beta", beta, C, x, finite=False)
    if not isinstance(groups, (int, np.integer)) or isinstance(groups, bool) or groups < 1:
        raise ValueError(f"groups must be a positive int, got {groups!r}")
    if C % groups:
        raise ValueError(f"groups={groups} does not divide the {C} channels of x")
    _checks.real("eps", eps, lo=0, lo_open=True)  # finite and > 0: eps = inf would give y = beta
    if eps > float(np.finfo(x.dtype).max):
        raise ValueError(f"eps = {eps!r} overflows x's dtype {x.dtype} (the kernel adds it in that dtype)")
    if x.dtype.type(eps) == 0:  # else a constant group (variance 0) divides by 0, blamed on x as an overflow
        raise ValueError(f"eps = {eps!r} rounds to 0 in x's dtype {x.dtype} (the kernel adds it in that dtype)")
    return int(groups)


def _groupnorm_kernel(x, gamma, beta, G, eps, swish):
    """The C++ forward (csrc/groupnorm.cpp) -> y (B, C, Hi, Wi), x as C-ordered, stats (B, G, 3):
    per group (mean, r, rstd), from which the backward recomputes xhat = ((x - mean) - r) * rstd
    bitwise as the forward computed it (xhat is never stored)."""
    x, gamma, beta = (_checks.c_order(a) for a in (x, gamma, beta))
    y = np.empty_like(x)  # (B, C, Hi, Wi)
    stats = np.empty((x.shape[0], G, 3), dtype=x.dtype)  # (B, G, 3)
    inputs = (("x", x), ("gamma", gamma), ("beta", beta))

    def run():
        _core.groupnorm_forward(y, stats, x, gamma, beta, G, float(eps), swish)
        if not (stats[..., 2] > 0).all():  # NaN: an input's (named by _after_kernel's scan of x)
            raise ValueError("groupnorm: the statistics of a group of x are not finite")
    _after_kernel("groupnorm_forward", run, (), inputs, every_input_read=y.size > 0)  # y: the kernel checks it
    return y, x, stats


def _groupnorm_grad_kernel(dy, x, stats, gamma, beta, G, swish):
    name = "dz" if swish else "dy"  # the caller's argument: groupnorm_swish_backward's is dz
    _check_grad(name, dy, x.shape)
    _check_float(name, dy, like=x, like_name="the forward's x", finite=False)  # finiteness: _after_kernel
    dy = _checks.c_order(dy)
    dx = np.empty_like(x)  # (B, C, Hi, Wi)
    dgamma, dbeta = np.empty_like(gamma), np.empty_like(gamma)  # (C,)
    _after_kernel("groupnorm_backward",
                  lambda: _core.groupnorm_backward(dx, dgamma, dbeta, x, stats, gamma, beta, dy, G, swish),
                  (("dgamma", dgamma), ("dbeta", dbeta)), ((name, dy),))  # dx: the kernel checks it
    return dx, dgamma, dbeta


def groupnorm_forward(x, gamma, beta, groups=32, eps=1e-6):
    """y = (x - mean_g) / sqrt(var_g + eps) * gamma[c] + beta[c], statistics over each group g of
    C/groups consecutive channels and all their pixels (torch's grouping).

    x (B, C, Hi, Wi), gamma, beta (C,) -> y (B, C, Hi, Wi).

    Parity trap (docs/math.md §4): the codebook's Normalize uses eps = 1e-6, not torch's
    nn.GroupNorm / F.group_norm default 1e-5. On groups of variance ~1e-5 the two differ by
    tens of percent.

    Two-pass, as layernorm_forward: the mean is accumulated in float64 and rounded, the group
    centred twice (the second time by the centred group's own residual mean r), then the variance
    is the mean square of it. So a group of mean 1e4 and spread 0.1 keeps its digits, and a
    constant group gives y = beta exactly (xhat = 0 even when the rounded mean is an ulp off).
    The C++ kernel (csrc/groupnorm.cpp) does exactly this, every sum in float64;
    groupnorm_forward_numpy is the same in NumPy, kept as a second reference.
    cache: x (B, C, Hi, Wi) (itself: do not modify it before the backward), stats (B, groups, 3) =
    (mean, r, rstd) per group, gamma, groups; the backward recomputes xhat from them, bitwise."""
    G = _groupnorm_args(x, gamma, beta, groups, eps)
    y, xc, stats = _groupnorm_kernel(x, gamma, beta, G, eps, swish=False)
    return y, (xc, stats, _checks.c_order(gamma), G)


def groupnorm_backward(dy, cache):
    """-> dx (B, C, Hi, Wi), dgamma (C,), dbeta (C,).

    forward was y = xhat * gamma[c] + beta[c], xhat = (x - mean_g(x)) * rstd, so dgamma = sum of
    dy * xhat, dbeta = sum of dy, and per group dx = rstd * (dxhat - mean_g(dxhat) - xhat *
    mean_g(dxhat * xhat)), dxhat = dy * gamma[c] (the C++ kernel; the sums in float64)."""
    x, stats, gamma, G = cache
    return _groupnorm_grad_kernel(dy, x, stats, gamma, gamma, G, swish=False)  # beta unused without swish


def groupnorm_swish_forward(x, gamma, beta, groups=32, eps=1e-6):
    """z = swish(groupnorm(x)): the Normalize + swish pair of the codebook (ResnetBlock's norm1 and
    norm2, and norm_out before conv_out, docs/math.md §4), in one pass of the C++ kernel.

    x (B, C, Hi, Wi), gamma, beta (C,) -> z (B, C, Hi, Wi). The same numbers as
    swish_forward(groupnorm_forward(x, gamma, beta, groups, eps)[0])[0] (bitwise: the same
    operations), without the intermediate y. eps 1e-6: the parity trap of groupnorm_forward.
    cache: x (B, C, Hi, Wi) (itself: do not modify it before the backward), stats (B, groups, 3),
    gamma, beta, groups; xhat and y = xhat * gamma + beta are recomputed in the backward."""
    G = _groupnorm_args(x, gamma, beta, groups, eps)
    z, xc, stats = _groupnorm_kernel(x, gamma, beta, G, eps, swish=True)
    return z, (xc, stats, _checks.c_order(gamma), _checks.c_order(beta), G)


def groupnorm_swish_backward(dz, cache):
    """-> dx (B, C, Hi, Wi), dgamma (C,), dbeta (C,).

    forward was z = swish(y), y = xhat * gamma[c] + beta[c], so dy = dz * swish'(y) (y recomputed),
    then groupnorm_backward's formulas."""
    x, stats, gamma, beta, G = cache
    return _groupnorm_grad_kernel(dz, x, stats, gamma, beta, G, swish=True)


def groupnorm_forward_numpy(x, gamma, beta, groups=32, eps=1e-6):
    """groupnorm_forward in NumPy (float64 means, the variance in x's dtype): same arguments, output
    and cache; a second reference for the tests."""
    G = _groupnorm_args(x, gamma, beta, groups, eps)
    B = x.shape[0]
    xg = x.reshape(B, G, -1)  # (B, G, C/G * Hi * Wi): a group's channels are consecutive
    mean = xg.mean(axis=-1, keepdims=True, dtype=np.float64).astype(x.dtype)  # (B, G, 1)
    xc = xg - mean  # (B, G, M)
    # second pass: the rounded mean can be an ulp off, which 1/sqrt(eps) = 1000 would amplify on a
    # constant group; the residual mean of xc is tiny and exact to subtract
    xc -= xc.mean(axis=-1, keepdims=True, dtype=np.float64).astype(x.dtype)
    var = np.mean(xc * xc, axis=-1, keepdims=True)  # (B, G, 1)
    rstd = 1.0 / np.sqrt(var + x.dtype.type(eps))  # (B, G, 1)
    xhat = (xc * rstd).reshape(x.shape)  # (B, C, Hi, Wi)
    y = xhat * gamma[:, None, None] + beta[:, None, None]  # (B, C, Hi, Wi)
    return y, (xhat, rstd, gamma, G)


def groupnorm_backward_numpy(dy, cache):
    """groupnorm_backward in NumPy -> dx (B, C, Hi, Wi), dgamma (C,), dbeta (C,)."""
    xhat, rstd, gamma, G = cache
    _check_grad("dy", dy, xhat.shape)
    B = xhat.shape[0]
    # forward was y = xhat * gamma[c] + beta[c]
    dgamma = (dy * xhat).sum(axis=(0, 2, 3))  # (C,)
    dbeta = dy.sum(axis=(0, 2, 3))  # (C,)
    dxhat = (dy * gamma[:, None, None]).reshape(B, G, -1)  # (B, G, M)
    xh = xhat.reshape(B, G, -1)  # (B, G, M)
    # forward was xhat = (x - mean_g(x)) * rstd, rstd = (mean_g((x - mean)^2) + eps)^(-1/2), so per group
    # dx = rstd * (dxhat - mean_g(dxhat) - xhat * mean_g(dxhat * xhat))
    dx = rstd * (dxhat - dxhat.mean(axis=-1, keepdims=True) - xh * (dxhat * xh).mean(axis=-1, keepdims=True))
    return dx.reshape(xhat.shape), dgamma, dbeta


# ---------------------------------------------------------------------------------------
# swish(x) = x * sigmoid(x) (torch's SiLU)


def swish_forward(x):
    """y = x * sigmoid(x).   x (...) -> y (...). Finite and warning-free for any finite x
    (x = -1000 gives -0.0, x = +1000 gives 1000).

    The C++ kernel (csrc/groupnorm.cpp) computes what _sigmoids does: z = exp(-|x|) in (0, 1],
    sigmoid(|x|) = 1 / (1 + z), sigmoid(-|x|) = z / (1 + z), assigned by the sign of x; exp is a
    vectorised one of about 1 ulp, std::exp where e^-|x| is subnormal. swish_forward_numpy is the
    same in NumPy. cache: x (no copy unless x was not C-contiguous); the sigmoids are recomputed."""
    _check_float("x", x)
    x = _checks.c_order(x)
    y = np.empty_like(x)
    _core.swish_forward(y, x)
    _checks.finite_result("swish_forward", y, "y")
    return y, x


def swish_backward(dy, cache):
    """-> dx (...). forward was y = x * s, s' = s * (1 - s), so
    dy/dx = s + x * s * (1 - s) = s * (1 + x * sigmoid(-x))."""
    x = cache
    _check_grad("dy", dy, x.shape)
    _check_float("dy", dy, like=x, like_name="the forward's x")
    dy = _checks.c_order(dy)
    dx = np.empty_like(x)
    _core.swish_backward(dx, dy, x)
    _checks.finite_result("swish_backward", dx, "dx")
    return (dx,)


def _sigmoids(x):
    """(sigmoid(x), sigmoid(-x)) without overflow or cancellation. z = exp(-|x|) is in (0, 1], so
    exp never overflows; sigmoid(|x|) = 1 / (1 + z) and sigmoid(-|x|) = z / (1 + z), each assigned
    by the sign of x. sigmoid(-x) is computed, not taken as 1 - sigmoid(x), which would cancel to
    0 for x >~ 17 (float64) and lose the gradient's tail.
    Call inside errstate(under='ignore'): e^-|x| underflowing to 0 or a subnormal for large |x| is
    the correctly rounded value, not an error."""
    z = np.exp(-np.abs(x))  # (...), in (0, 1]
    one_z = 1 + z
    s_pos, s_neg = 1 / one_z, z / one_z  # sigmoid(|x|), sigmoid(-|x|)
    pos = x >= 0
    return np.where(pos, s_pos, s_neg), np.where(pos, s_neg, s_pos)


def swish_forward_numpy(x):
    """swish_forward in NumPy, a second reference for the tests."""
    _check_float("x", x)
    with np.errstate(under="ignore"):  # only underflow, the correct result for large |x|; overflow still raises
        s, _ = _sigmoids(x)
        y = x * s
    return y, x


def swish_backward_numpy(dy, cache):
    """swish_backward in NumPy -> dx (...)."""
    x = cache
    _check_grad("dy", dy, x.shape)
    with np.errstate(under="ignore"):
        s, sn = _sigmoids(x)  # sigmoid(x), sigmoid(-x) = 1 - sigmoid(x)
        # forward was y = x * s, s' = s * (1 - s), so dy/dx = s + x * s * (1 - s) = s * (1 + x * sigmoid(-x))
        dx = dy * (s * (1 + x * sn))
    return (dx,)


# ---------------------------------------------------------------------------------------
# nearest-neighbour x2 upsampling (the Upsample's interpolation, F.interpolate(scale_factor=2))


def upsample_nearest2x_forward(x):
    """y[b, c, 2u + i, 2v + j] = x[b, c, u, v] for i, j in {0, 1}.
    x (B, C, Hi, Wi) -> y (B, C, 2Hi, 2Wi) (a copy on pyvf's threads). cache: x's shape and dtype."""
    _check_image("x", x)
    x = _checks.c_order(x)
    y = np.empty(x.shape[:2] + (2 * x.shape[2], 2 * x.shape[3]), x.dtype)  # (B, C, 2Hi, 2Wi)
    _core.upsample2x(y, x)
    return y, (x.shape, x.dtype)


def upsample_nearest2x_backward(dy, cache):
    """-> dx (B, C, Hi, Wi): forward copied each pixel to a 2x2 block, so dx sums the block:
    (dy[2u, 2v] + dy[2u, 2v+1]) + (dy[2u+1, 2v] + dy[2u+1, 2v+1]), in that order (the kernel on
    pyvf's threads; upsample_nearest2x_backward_numpy is the same sum in NumPy, bitwise)."""
    (B, C, Hi, Wi), dtype = cache
    _check_grad("dy", dy, (B, C, 2 * Hi, 2 * Wi))
    _check_float("dy", dy)
    if dy.dtype != dtype:
        raise TypeError(f"dy is {dy.dtype} but the forward's x is {dtype}: both must share one dtype "
                        "(pyvf never casts silently)")
    dx = np.empty((B, C, Hi, Wi), dtype)
    _core.upsample2x_backward(dx, _checks.c_order(dy))
    return (_checks.finite_result("upsample_nearest2x_backward", dx, "dx"),)


def upsample_nearest2x_backward_numpy(dy, cache):
    """upsample_nearest2x_backward in NumPy (the tests' reference) -> dx (B, C, Hi, Wi)."""
    (B, C, Hi, Wi), _ = cache
    d = dy.reshape(B, C, Hi, 2, Wi, 2)  # d[b, c, u, i, v, j] = dy[b, c, 2u + i, 2v + j]
    dx = (d[:, :, :, 0, :, 0] + d[:, :, :, 0, :, 1]) + (d[:, :, :, 1, :, 0] + d[:, :, :, 1, :, 1])  # (B, C, Hi, Wi)
    return (dx,)


# ---------------------------------------------------------------------------------------
# AttnBlock(c): single-head attention over the Hi*Wi positions, residual (docs/math.md §4)


def attnblock_forward(x, norm_gamma, norm_beta, wq, bq, wk, bk, wv, bv, wo, bo, groups=32, eps=1e-6):
    """y = x + proj_out(attention(q, k, v)), q, k, v = 1x1 convs of GroupNorm(x).

    x (B, C, Hi, Wi); norm_gamma, norm_beta (C,) (`norm.weight`, `norm.bias`); wq, wk, wv, wo
    (C, C, 1, 1) and bq, bk, bv, bo (C,) (`q`, `k`, `v`, `proj_out`) -> y (B, C, Hi, Wi).
    Attention: logits s[b, i, j] = C**-0.5 * sum_c q[b, c, i] k[b, c, j] over the P = Hi*Wi
    positions (query i, key j), softmax over j, a[b, c, i] = sum_j p[b, i, j] v[b, c, j].
    Unlike the transformer (docs/math.md §2), these logits ARE scaled, by C**-0.5 with C the channels.
    cache: the children's caches, q, k, v as (B, C, P) and p (B, P, P)."""
    _check_image("x", x)
    C = x.shape[1]
    # checked here, not by the children, which name their own arguments (gamma, w, b) and not these
    params = (("norm_gamma", norm_gamma), ("norm_beta", norm_beta), ("wq", wq), ("bq", bq), ("wk", wk), ("bk", bk),
              ("wv", wv), ("bv", bv), ("wo", wo), ("bo", bo))
    for name, a in params:
        _check_float(name, a, like=x, finite=False)  # finiteness: below, once a child has raised
        want = (C, C, 1, 1) if name[0] == "w" else (C,)
        if a.shape != want:
            raise ValueError(f"{name} must have shape {want} for x of {C} channels, got {a.shape}")
    try:
        return _attnblock_forward(x, *(a for _, a in params), groups, eps)
    except ValueError:
        # a child raises when a parameter holds NaN or inf (each is read whole, or scanned where
        # the output is empty: see _after_kernel): only then are they scanned, to name it
        for name, a in params:
            _checks.finite(name, a)
        raise


def _attnblock_forward(x, norm_gamma, norm_beta, wq, bq, wk, bk, wv, bv, wo, bo, groups, eps):
    """attnblock_forward's layers, its arguments checked."""
    B, C, Hi, Wi = x.shape
    P = Hi * Wi
    h, c_norm = groupnorm_forward(x, norm_gamma, norm_beta, groups, eps)  # (B, C, Hi, Wi)
    q, c_q = conv2d_forward(h, wq, bq)  # (B, C, Hi, Wi)
    k, c_k = conv2d_forward(h, wk, bk)  # (B, C, Hi, Wi)
    v, c_v = conv2d_forward(h, wv, bv)  # (B, C, Hi, Wi)
    q2, k2, v2 = q.reshape(B, C, P), k.reshape(B, C, P), v.reshape(B, C, P)  # (B, C, P)
    scale = x.dtype.type(C ** -0.5)
    s = matmul(q2, k2, ta=True)  # (B, P, P): s[b,i,j] = sum_c q[b,c,i] k[b,c,j]
    s *= scale
    if not _checks.all_finite(s):  # (else inf - inf = NaN, and the error would blame a later layer's input)
        raise ValueError(f"attnblock_forward: the attention logits q.k / sqrt(C) overflow {x.dtype} "
                         "(q and k too large: the weights wq, wk or the input diverged)")
    s -= s.max(axis=-1, keepdims=True)
    with np.errstate(under="ignore"):  # exp of very negative logits underflowing to 0 is correct
        p = np.exp(s)  # (B, P, P)
    p /= p.sum(axis=-1, keepdims=True)  # softmax over the keys j
    a = matmul(v2, p, tb=True)  # (B, C, P): a[b,c,i] = sum_j v[b,c,j] p[b,i,j]
    o, c_o = conv2d_forward(a.reshape(B, C, Hi, Wi), wo, bo)  # (B, C, Hi, Wi)
    o += x  # y = x + o, in o's fresh buffer (referenced nowhere else)
    y = o  # (B, C, Hi, Wi)
    return y, (c_norm, c_q, c_k, c_v, c_o, q2, k2, v2, p, scale)


def attnblock_backward(dy, cache):
    """-> dx, dnorm_gamma, dnorm_beta, dwq, dbq, dwk, dbk, dwv, dbv, dwo, dbo."""
    c_norm, c_q, c_k, c_v, c_o, q2, k2, v2, p, scale = cache
    B, C, P = q2.shape
    _check_grad("dy", dy, c_norm[0].shape)
    # forward was y = x + o
    da, dwo, dbo = conv2d_backward(dy, c_o)
    da2 = da.reshape(B, C, P)  # (B, C, P)
    # forward was a = v @ p^T, so dv = da @ p and dp = da^T @ v
    dv2 = matmul(da2, p)  # (B, C, P): dv[b,c,j] = sum_i da[b,c,i] p[b,i,j]
    dp = matmul(da2, v2, ta=True)  # (B, P, P): dp[b,i,j] = sum_c da[b,c,i] v[b,c,j]
    # forward was p = softmax_j(s), so ds = p * (dp - sum_j p * dp); s = scale * q^T k
    ds = p * (dp - (p * dp).sum(axis=-1, keepdims=True))  # (B, P, P)
    ds *= scale
    dq2 = matmul(k2, ds, tb=True)  # (B, C, P): dq[b,c,i] = sum_j k[b,c,j] ds[b,i,j]
    dk2 = matmul(q2, ds)  # (B, C, P): dk[b,c,j] = sum_i q[b,c,i] ds[b,i,j]
    shape = c_norm[0].shape  # (B, C, Hi, Wi)
    dhq, dwq, dbq = conv2d_backward(dq2.reshape(shape), c_q)
    dhk, dwk, dbk = conv2d_backward(dk2.reshape(shape), c_k)
    dhv, dwv, dbv = conv2d_backward(dv2.reshape(shape), c_v)
    # forward was q, k, v = conv(h, .): h feeds all three
    dxn, dgamma, dbeta = groupnorm_backward(dhq + dhk + dhv, c_norm)
    dx = dy + dxn  # the residual
    return dx, dgamma, dbeta, dwq, dbq, dwk, dbk, dwv, dbv, dwo, dbo
