"""The codebook's image layers as forward/backward pairs (docs/math.md §4): conv2d, GroupNorm,
swish, nearest-neighbour x2 upsampling, and the 2D attention block built from them.
`x_forward(x, *params) -> (out, cache)`, `x_backward(dout, cache) -> (dx, *dparams)`; arrays keep
their dtype throughout.

Shapes: images are NCHW, (B, C, Hi, Wi); conv weights are torch's (Co, C, kh, kw), biases
(Co,). Co, Ho, Wo are a conv's output channels and size; P = Hi * Wi pixels; K = C * kh * kw
the length of one im2col column.
"""

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from .. import _core
from .layers import matmul


def _padding4(padding):
    """int p -> (p, p, p, p); (top, bottom, left, right) -> itself."""
    return (int(padding),) * 4 if np.ndim(padding) == 0 else tuple(int(p) for p in padding)


# ---------------------------------------------------------------------------------------
# conv2d: cross-correlation as torch.nn.functional.conv2d, any kernel, stride, padding


def _im2col(x, kh, kw, stride, pad):
    """x (B, C, Hi, Wi) -> cols (K, B, Ho, Wo), K = C*kh*kw in w's (c, i, j) order:
    cols[(c, i, j), b, u, v] = xpad[b, c, stride*u + i, stride*v + j]. One copy (the columns);
    the windows themselves are a strided view."""
    pt, pb, pl, pr = pad
    # zero padding on each side separately: np.pad's order is (before, after) per axis, here
    # (top, bottom) for the rows and (left, right) for the columns. The Downsample's (0, 1, 0, 1)
    # pads only after (bottom, right): the padding trap of docs/math.md §4, see conv2d_forward
    xp = np.pad(x, ((0, 0), (0, 0), (pt, pb), (pl, pr))) if any(pad) else x  # (B, C, Hp, Wp)
    win = sliding_window_view(xp, (kh, kw), axis=(2, 3))[:, :, ::stride, ::stride]  # (B, C, Ho, Wo, kh, kw), a view
    B, C, Ho, Wo = win.shape[:4]
    return win.transpose(1, 4, 5, 0, 2, 3).reshape(C * kh * kw, B, Ho, Wo)  # (K, B, Ho, Wo)


def conv2d_forward(x, w, b, stride=1, padding=0):
    """y = conv2d(x, w) + b, torch's cross-correlation (no kernel flip).

    x (B, C, Hi, Wi), w (Co, C, kh, kw), b (Co,) -> y (B, Co, Ho, Wo),
    Ho = (Hi + top + bottom - kh) // stride + 1, Wo likewise. padding: an int (all four sides) or
    (top, bottom, left, right).

    Padding trap (docs/math.md §4): the Downsample pads only the right and the bottom, by one pixel,
    then convolves 3x3 stride 2 with padding 0: padding=(0, 1, 0, 1) here, F.pad(x, (0, 1, 0, 1))
    in torch. padding=1 gives the same output size on even images but shifts every window by one
    pixel; (1, 0, 1, 0) pads the wrong corner. Neither raises: only the values tell.

    The C++ kernel (csrc/conv.cpp, implicit GEMM); conv2d_forward_numpy is its reference.
    cache: x and w (C-ordered), stride, padding."""
    pad = _padding4(padding)
    pt, pb, pl, pr = pad
    x, w, b = np.ascontiguousarray(x), np.ascontiguousarray(w), np.ascontiguousarray(b)
    (B, _, Hi, Wi), (Co, _, kh, kw) = x.shape, w.shape
    y = np.empty((B, Co, (Hi + pt + pb - kh) // stride + 1, (Wi + pl + pr - kw) // stride + 1), x.dtype)
    _core.conv2d_forward(y, x, w, b, stride, *pad)  # (B, Co, Ho, Wo)
    return y, (x, w, stride, pad)


def conv2d_backward(dy, cache):
    """-> dx (B, C, Hi, Wi), dw (Co, C, kh, kw), db (Co,): conv2d_backward_numpy's formulas, in
    the C++ kernel (dx of a stride-1 conv as the conv of dy with the flipped, transposed kernel)."""
    x, w, stride, pad = cache
    dx, dw, db = np.empty_like(x), np.empty_like(w), np.empty(w.shape[0], x.dtype)
    _core.conv2d_backward(dx, dw, db, x, w, np.ascontiguousarray(dy), stride, *pad)
    return dx, dw, db


def conv2d_forward_numpy(x, w, b, stride=1, padding=0):
    """conv2d_forward in NumPy, its reference: same arguments, output and cache. One matmul:
    y[o, (b, u, v)] = sum_k w2[o, k] cols[k, (b, u, v)], w2 = w as (Co, K), cols the im2col columns
    (K, B*Ho*Wo), recomputed in the backward (kh*kw times the size of x)."""
    pad = _padding4(padding)
    B, C = x.shape[:2]
    Co, _, kh, kw = w.shape
    w2 = w.reshape(Co, C * kh * kw)  # (Co, K), columns in (c, i, j) order
    cols = _im2col(x, kh, kw, stride, pad)  # (K, B, Ho, Wo)
    Ho, Wo = cols.shape[2:]
    y = (w2 @ cols.reshape(C * kh * kw, B * Ho * Wo)).reshape(Co, B, Ho, Wo).transpose(1, 0, 2, 3)  # (B, Co, Ho, Wo)
    y = y + b[:, None, None]  # (B, Co, Ho, Wo), C-ordered
    return y, (x, w, stride, pad)


def conv2d_backward_numpy(dy, cache):
    """-> dx (B, C, Hi, Wi), dw (Co, C, kh, kw), db (Co,) (the math in the comments below)."""
    x, w, stride, pad = cache
    B, C, Hi, Wi = x.shape
    Co, _, kh, kw = w.shape
    pt, pb, pl, pr = pad
    Ho, Wo = dy.shape[2:]
    w2 = w.reshape(Co, C * kh * kw)  # (Co, K)
    db = dy.sum(axis=(0, 2, 3))  # (Co,): forward was y = ... + b[o]
    dyT = dy.transpose(1, 0, 2, 3).reshape(Co, B * Ho * Wo)  # (Co, B*Ho*Wo), a copy
    cols = _im2col(x, kh, kw, stride, pad).reshape(C * kh * kw, B * Ho * Wo)  # (K, B*Ho*Wo), recomputed
    # forward was y = w2 @ cols, so dw = dy @ cols^T, dcols = w2^T @ dy
    dw = (dyT @ cols.T).reshape(w.shape)  # (Co, C, kh, kw)
    dcols = (w2.T @ dyT).reshape(C, kh, kw, B, Ho, Wo)  # (C, kh, kw, B, Ho, Wo)
    # col2im: forward read cols[(c,i,j), b, u, v] = xpad[b, c, stride*u + i, stride*v + j], so each
    # kernel offset (i, j) adds its (Ho, Wo) slab onto a strided slice of the padded image
    dxp = np.zeros((C, B, Hi + pt + pb, Wi + pl + pr), dtype=x.dtype)  # (C, B, Hp, Wp)
    for i in range(kh):
        for j in range(kw):
            dxp[:, :, i:i + stride * (Ho - 1) + 1:stride, j:j + stride * (Wo - 1) + 1:stride] += dcols[:, i, j]
    # the padding was constant zeros: its gradient is dropped; crop (top, left) to where x sits
    dx = np.ascontiguousarray(dxp[:, :, pt:pt + Hi, pl:pl + Wi].transpose(1, 0, 2, 3))  # (B, C, Hi, Wi)
    return dx, dw, db


# ---------------------------------------------------------------------------------------
# GroupNorm (Normalize in the codebook): 32 groups of contiguous channels, eps 1e-6, affine


def groupnorm_forward(x, gamma, beta, groups=32, eps=1e-6):
    """y = (x - mean_g) / sqrt(var_g + eps) * gamma[c] + beta[c], statistics over each group g of
    C/groups consecutive channels and all their pixels (torch's grouping).

    x (B, C, Hi, Wi), gamma, beta (C,) -> y (B, C, Hi, Wi).

    Parity trap (docs/math.md §4): the codebook's Normalize uses eps = 1e-6, not torch's default
    1e-5; on groups of variance ~1e-5 the two differ by tens of percent.

    Two-pass, as layernorm_forward: the group centred by its float64 mean rounded, then by the
    residual mean, the variance the mean square of that; so a group of mean 1e4 and spread 0.1
    keeps its digits and a constant group gives y = beta exactly (xhat = 0 even when the rounded
    mean is an ulp off, which 1/sqrt(eps) = 1000 would amplify).
    cache: xhat (B, C, Hi, Wi), rstd (B, G, 1), gamma, groups."""
    B, C, Hi, Wi = x.shape
    xg = x.reshape(B, groups, C // groups * Hi * Wi)  # (B, G, M): a group's channels are consecutive
    xc = xg - xg.mean(axis=-1, keepdims=True, dtype=np.float64).astype(x.dtype)  # (B, G, M)
    xc -= xc.mean(axis=-1, keepdims=True, dtype=np.float64).astype(x.dtype)  # the rounded mean's residual
    var = np.einsum("bgm,bgm->bg", xc, xc)[..., None] / xc.shape[-1]  # (B, G, 1): mean of xc^2
    rstd = 1 / np.sqrt(var + x.dtype.type(eps))  # (B, G, 1)
    xhat = (xc * rstd).reshape(x.shape)  # (B, C, Hi, Wi)
    y = xhat * gamma[:, None, None] + beta[:, None, None]  # (B, C, Hi, Wi)
    return y, (xhat, rstd, gamma, groups)


def groupnorm_backward(dy, cache):
    """-> dx (B, C, Hi, Wi), dgamma (C,), dbeta (C,)."""
    xhat, rstd, gamma, G = cache
    B, C, Hi, Wi = xhat.shape
    M = C // G * Hi * Wi  # elements per group
    # forward was y = xhat * gamma[c] + beta[c]
    dgamma = np.einsum("bchw,bchw->c", dy, xhat)  # (C,)
    dbeta = dy.sum(axis=(0, 2, 3))  # (C,)
    dxhat = (dy * gamma[:, None, None]).reshape(B, G, M)  # (B, G, M)
    xh = xhat.reshape(B, G, M)  # (B, G, M)
    # forward was xhat = (x - mean_g(x)) * rstd, rstd = (mean_g((x - mean)^2) + eps)^(-1/2), so per group
    # dx = rstd * (dxhat - mean_g(dxhat) - xhat * mean_g(dxhat * xhat))
    proj = np.einsum("bgm,bgm->bg", dxhat, xh)[..., None] / M  # (B, G, 1): mean_g(dxhat * xhat)
    dx = rstd * (dxhat - dxhat.mean(axis=-1, keepdims=True) - xh * proj)  # (B, G, M)
    return dx.reshape(xhat.shape), dgamma, dbeta


def groupnorm_swish_forward(x, gamma, beta, groups=32, eps=1e-6):
    """z = swish(groupnorm(x)): the codebook's Normalize + swish (norm1, norm2, norm_out).
    x (B, C, Hi, Wi), gamma, beta (C,) -> z (B, C, Hi, Wi). cache: the two children's caches."""
    y, c_norm = groupnorm_forward(x, gamma, beta, groups, eps)
    z, c_swish = swish_forward(y)
    return z, (c_norm, c_swish)


def groupnorm_swish_backward(dz, cache):
    """-> dx (B, C, Hi, Wi), dgamma (C,), dbeta (C,): forward was z = swish(y), y = groupnorm(x)."""
    c_norm, c_swish = cache
    (dy,) = swish_backward(dz, c_swish)
    return groupnorm_backward(dy, c_norm)


# ---------------------------------------------------------------------------------------
# swish(x) = x * sigmoid(x) (torch's SiLU)


def _sigmoids(x):
    """(sigmoid(|x|), sigmoid(-|x|), x >= 0), without overflow or cancellation: z = exp(-|x|) is
    in (0, 1]; sigmoid(|x|) = 1 / (1 + z) and sigmoid(-|x|) = z / (1 + z) (not 1 - sigmoid(|x|),
    which cancels to 0 for x >~ 17 and loses the gradient's tail). In place: most of swish's time."""
    z = np.abs(x)
    np.negative(z, out=z)
    with np.errstate(under="ignore"):  # e^-|x| underflowing for large |x| is the correctly rounded value
        np.exp(z, out=z)  # (...), in (0, 1]
        s_pos = z + 1
        np.reciprocal(s_pos, out=s_pos)  # sigmoid(|x|)
        np.multiply(z, s_pos, out=z)  # sigmoid(-|x|)
    return s_pos, z, x >= 0


def swish_forward(x):
    """y = x * sigmoid(x).   x (...) -> y (...). Finite and warning-free for any finite x
    (x = -1000 gives -0.0, x = +1000 gives 1000). cache: x, sigmoid(x), sigmoid(-x) (kept: recomputing
    them in backward cost a third of the codebook's training step)."""
    s_pos, s_neg, pos = _sigmoids(x)
    s, sn = np.where(pos, s_pos, s_neg), np.where(pos, s_neg, s_pos)  # sigmoid(x), sigmoid(-x)
    with np.errstate(under="ignore"):
        return x * s, (x, s, sn)


def swish_backward(dy, cache):
    """-> dx (...). forward was y = x * s, s' = s * (1 - s), so
    dy/dx = s + x * s * (1 - s) = s * (1 + x * sigmoid(-x))."""
    x, s, sn = cache
    with np.errstate(under="ignore"):
        dx = sn * x
        dx += 1
        dx *= s
        dx *= dy
        return (dx,)


# ---------------------------------------------------------------------------------------
# nearest-neighbour x2 upsampling (the Upsample's interpolation, F.interpolate(scale_factor=2))


def upsample_nearest2x_forward(x):
    """y[b, c, 2u + i, 2v + j] = x[b, c, u, v] for i, j in {0, 1}.
    x (B, C, Hi, Wi) -> y (B, C, 2Hi, 2Wi). cache: x's shape."""
    B, C, Hi, Wi = x.shape
    y = np.broadcast_to(x[:, :, :, None, :, None], (B, C, Hi, 2, Wi, 2))  # (B, C, Hi, 2, Wi, 2), a view
    return y.reshape(B, C, 2 * Hi, 2 * Wi), x.shape  # (B, C, 2Hi, 2Wi), a copy


def upsample_nearest2x_backward(dy, cache):
    """-> dx (B, C, Hi, Wi): forward copied each pixel to a 2x2 block, so dx sums the block."""
    B, C, Hi, Wi = cache
    d = dy.reshape(B, C, Hi, 2, Wi, 2)  # d[b, c, u, i, v, j] = dy[b, c, 2u + i, 2v + j]
    return (d.sum(axis=(3, 5)),)


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
    s -= s.max(axis=-1, keepdims=True)
    with np.errstate(under="ignore"):  # exp of very negative logits underflowing to 0 is correct
        p = np.exp(s)  # (B, P, P)
    p /= p.sum(axis=-1, keepdims=True)  # softmax over the keys j
    a = matmul(v2, p, tb=True)  # (B, C, P): a[b,c,i] = sum_j v[b,c,j] p[b,i,j]
    o, c_o = conv2d_forward(a.reshape(B, C, Hi, Wi), wo, bo)  # (B, C, Hi, Wi)
    o += x  # y = x + o, in o's fresh buffer
    return o, (c_norm, c_q, c_k, c_v, c_o, q2, k2, v2, p, scale)


def attnblock_backward(dy, cache):
    """-> dx, dnorm_gamma, dnorm_beta, dwq, dbq, dwk, dbk, dwv, dbv, dwo, dbo."""
    c_norm, c_q, c_k, c_v, c_o, q2, k2, v2, p, scale = cache
    B, C, P = q2.shape
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
    shape = dy.shape  # (B, C, Hi, Wi)
    dhq, dwq, dbq = conv2d_backward(dq2.reshape(shape), c_q)
    dhk, dwk, dbk = conv2d_backward(dk2.reshape(shape), c_k)
    dhv, dwv, dbv = conv2d_backward(dv2.reshape(shape), c_v)
    # forward was q, k, v = conv(h, .): h feeds all three
    dxn, dgamma, dbeta = groupnorm_backward(dhq + dhk + dhv, c_norm)
    dx = dy + dxn  # the residual
    return dx, dgamma, dbeta, dwq, dbq, dwk, dbk, dwv, dbv, dwo, dbo
