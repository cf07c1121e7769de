"""Branching attention (docs/math.md §2): the C++ kernel's Python face, and a dense NumPy reference.

Shapes: q, k, v, o of shape (R, B, H, N, L, dh): tree row, batch, head, view, token, head width.
Row 0 is the trunk, rows 1..R-1 the branches. Query block (r, i) (the L tokens of view i in
row r) attends every key of

    trunk blocks (0, j), j < i     and     its own block (r, i).

For the trunk that is block-causal attention over views 0..i; a branch at view i sees the
strictly earlier trunk views and itself, never another branch and never a later view. Masked
keys are excluded before the softmax, exactly. The logit is scale * (q . k) with scale = 1 by
default, as in the published model (docs/math.md §2: logits are not divided by sqrt(dh)).

    o = branching_attention(q, k, v)                      # forward
    dq, dk, dv = branching_attention_vjp(q, k, v, do)     # gradient of sum(o * do)
    o, lse = branching_attention_forward(q, k, v)         # forward that keeps what backward needs
    dq, dk, dv = branching_attention_backward(do, q, k, v, o, lse)
    o, lse = context_attention_forward(q, k, v, k_ctx, v_ctx)  # query rows against a cached trunk

The reference (branching_attention_reference and its _vjp) materialises the (T, T) logits of
the flat sequence, T = R*N*L in the order [row][view][token], with branching_mask: it is the
oracle tests and benchmarks compare the kernel against, and costs O(T^2) memory on purpose.
"""

import numpy as np

from .. import _checks, _core
from .layers import linear_backward, linear_forward, matmul

__all__ = [
    "branching_attention",
    "branching_attention_vjp",
    "branching_attention_forward",
    "branching_attention_backward",
    "branching_mask",
    "branching_attention_reference",
    "branching_attention_reference_vjp",
    "context_attention_forward",
    "attention_layer_forward",
    "attention_layer_backward",
]

# ---------------------------------------------------------------------------------------
# argument checks of the public faces: every error names the argument


def _check_qkv(q, k, v, scale, **more):
    """q: finite, C-contiguous, float, 6 non-zero dimensions; k, v, `more` like it -> float(scale)."""
    _checks.float_array("q", q)
    if q.ndim != 6 or 0 in q.shape:
        raise ValueError(f"q must have 6 non-zero dimensions (R, B, H, N, L, dh), got shape {q.shape}")
    for name, a in (("q", q), ("k", k), ("v", v), *more.items()):
        _checks.float_array(name, a, q, "q")
        if a.shape != q.shape:
            raise ValueError(f"{name} has shape {a.shape} but q has shape {q.shape}")
        _checks.contiguous(name, a)
        _checks.finite(name, a)
    return _checks.real("scale", scale)


def _check_finite_result(name, *arrays):
    for a in arrays:
        if not _checks.all_finite(a):
            raise ValueError(f"{name}: the result is not finite: it overflowed {a.dtype} "
                             "(inputs too large for the dtype; use float64 or rescale them)")


# ---------------------------------------------------------------------------------------
# the kernel


def branching_attention_forward(q, k, v, scale=1.0, *, plain=False):
    """q, k, v: (R, B, H, N, L, dh), float32 or float64, C-contiguous, one dtype -> o of q's shape
    and dtype, lse (R, B, H, N, L) float64 (also for float32: csrc says why), the log-sum-exp of
    each query's attended logits. plain=True: the plain C++ loops (the oracle)."""
    scale = _check_qkv(q, k, v, scale)
    o = np.empty_like(q)
    lse = np.empty(q.shape[:5], dtype=np.float64)
    (_core.attn_forward_plain if plain else _core.attn_forward)(o, lse, q, k, v, scale)
    _check_finite_result("branching_attention", o)
    return o, lse


def branching_attention_backward(do, q, k, v, o, lse, scale=1.0, *, plain=False):
    """Gradient of sum(o * do) with respect to q, k, v, given the forward's o and lse (as
    branching_attention_forward returned them) -> new arrays dq, dk, dv of q's shape and dtype."""
    scale = _check_qkv(q, k, v, scale, do=do, o=o)
    if not isinstance(lse, np.ndarray) or lse.dtype != np.float64 or lse.shape != q.shape[:5]:
        raise TypeError(f"lse must be the float64 array of shape {q.shape[:5]} that branching_attention_forward "
                        "returned")
    _checks.contiguous("lse", lse)
    _checks.finite("lse", lse)
    dq, dk, dv = np.empty_like(q), np.empty_like(q), np.empty_like(q)
    (_core.attn_backward_plain if plain else _core.attn_backward)(dq, dk, dv, lse, q, k, v, o, do, scale)
    _check_finite_result("branching_attention_backward", dq, dk, dv)
    return dq, dk, dv


def branching_attention(q, k, v, scale=1.0):
    """o = softmax over attended keys of scale * q k^T, times v. Shapes (R, B, H, N, L, dh)."""
    return branching_attention_forward(q, k, v, scale)[0]


def branching_attention_vjp(q, k, v, do, scale=1.0):
    """(dq, dk, dv): the gradient of sum(branching_attention(q, k, v) * do)."""
    o, lse = branching_attention_forward(q, k, v, scale)
    return branching_attention_backward(do, q, k, v, o, lse, scale)


def context_attention_forward(q, k, v, k_ctx, v_ctx, scale=1.0):
    """Branch blocks against a cached trunk: the scene cache's attention (docs/math.md §3).

    q, k, v (R, B, H, 1, L, dh): R query rows of one view each; k_ctx, v_ctx (B, H, Nc, L, dh):
    the trunk's keys and values of Nc context views. Query block (r, b, h) attends every context
    block (b, h, 0..Nc-1) and its own block, nothing else: what branch block (r, Nc) attends in
    the tree over [context, query]. -> o (R, B, H, 1, L, dh), lse (R, B, H, 1, L) float64, as
    branching_attention_forward; Nc + 1 block pairs per query, not the tree's (Nc+1)(Nc+2)/2, and
    o equal to the kernel's up to rounding (tests/test_scene_cache.py bounds it).
    """
    R, B, H, _, L, dh = q.shape
    C, G, n = k_ctx.shape[2] * L, B * H, R * B * H  # context keys, heads, query blocks
    qh = np.ascontiguousarray(q.reshape(R, G, L, dh).transpose(1, 0, 2, 3)).reshape(G, R * L, dh)  # per head
    kc, vc = k_ctx.reshape(G, C, dh), v_ctx.reshape(G, C, dh)  # (G, C, dh)
    # logits s_ij = scale * q_i . k_j, against the context's keys (the R queries of a head in one
    # product) and against the own block's
    sc = scale * matmul(qh, kc, tb=True).reshape(G, R, L, C).transpose(1, 0, 2, 3)  # (R, G, L, C)
    so = scale * matmul(q.reshape(n, L, dh), k.reshape(n, L, dh), tb=True).reshape(R, G, L, L)  # (R, G, L, L)
    # the softmax over all T = C + L keys of each query, kept in the two parts: p = exp(s - m), m the
    # query's largest logit, denom = the sum of its p (in float64); every key the query attends
    # (nothing is masked: exact exclusion)
    m = np.maximum(sc.max(axis=-1, keepdims=True), so.max(axis=-1, keepdims=True))  # (R, G, L, 1)
    pc, po = np.exp(sc - m), np.exp(so - m)  # (R, G, L, C), (R, G, L, L)
    denom = pc.sum(axis=-1, keepdims=True, dtype=np.float64) + po.sum(axis=-1, keepdims=True, dtype=np.float64)
    # o = sum_j p_j v_j / denom over the context's values and the own block's
    oc = matmul(np.ascontiguousarray(pc.transpose(1, 0, 2, 3)).reshape(G, R * L, C), vc)  # (G, R L, dh)
    oo = matmul(po.reshape(n, L, L), v.reshape(n, L, dh)).reshape(R, G, L, dh)  # (R, G, L, dh)
    o = ((oo + oc.reshape(G, R, L, dh).transpose(1, 0, 2, 3)) / denom).astype(q.dtype)  # (R, G, L, dh)
    lse = (m.astype(np.float64) + np.log(denom))[..., 0]  # (R, G, L)
    return o.reshape(R, B, H, 1, L, dh), lse.reshape(R, B, H, 1, L)


# ---------------------------------------------------------------------------------------
# the dense reference


def branching_mask(R, N, L):
    """Boolean (T, T) mask, T = R*N*L, flat order [row][view][token]: mask[t, u] is True where
    query token t attends key token u."""
    R, N, L = (_checks.positive_integer(name, n) for name, n in (("R", R), ("N", N), ("L", L)))
    r = np.repeat(np.arange(R), N)  # (R*N,) row of each block
    i = np.tile(np.arange(N), R)  # (R*N,) view of each block
    rq, iq, rk, ik = r[:, None], i[:, None], r[None, :], i[None, :]
    blocks = ((rk == 0) & (ik < iq)) | ((rk == rq) & (ik == iq))  # (R*N, R*N)
    return np.kron(blocks, np.ones((L, L), dtype=bool))  # (T, T)


def _flat(x):
    """(R, B, H, N, L, dh) -> (B, H, T, dh), T in the order [row][view][token]."""
    R, B, H, N, L, dh = x.shape
    return x.transpose(1, 2, 0, 3, 4, 5).reshape(B, H, R * N * L, dh)


def _unflat(x, shape):
    R, B, H, N, L, dh = shape
    return x.reshape(B, H, R, N, L, dh).transpose(2, 0, 1, 3, 4, 5)


def _reference_probs(q, k, scale, mask):
    s = scale * (q @ k.swapaxes(-1, -2))  # (B, H, T, T) logits
    s = np.where(mask, s, -np.inf)  # exact exclusion: exp(-inf) = 0
    s -= s.max(axis=-1, keepdims=True)  # every row attends its own block, so the max is finite
    p = np.exp(s, out=s)
    p /= p.sum(axis=-1, keepdims=True)
    return p  # (B, H, T, T)


def branching_attention_reference(q, k, v, scale=1.0):
    """Dense NumPy reference of branching_attention: materialised (T, T) logits, masked to -inf."""
    scale = _check_qkv(q, k, v, scale)
    R, B, H, N, L, dh = q.shape
    p = _reference_probs(_flat(q), _flat(k), scale, branching_mask(R, N, L))
    return _unflat(p @ _flat(v), q.shape).copy()


def branching_attention_reference_vjp(q, k, v, do, scale=1.0):
    """Dense NumPy reference of branching_attention_vjp."""
    scale = _check_qkv(q, k, v, scale, do=do)
    R, B, H, N, L, dh = q.shape
    qf, kf, vf, dof = _flat(q), _flat(k), _flat(v), _flat(do)
    p = _reference_probs(qf, kf, scale, branching_mask(R, N, L))  # (B, H, T, T)
    # forward: o = p v
    dv = p.swapaxes(-1, -2) @ dof  # dv = p^T do
    dp = dof @ vf.swapaxes(-1, -2)  # dp = do v^T
    # forward: p = softmax(s) per row, so ds = p * (dp - rowsum(p * dp))
    ds = p * (dp - (p * dp).sum(axis=-1, keepdims=True))
    # forward: s = scale * q k^T
    dq = scale * (ds @ kf)
    dk = scale * (ds.swapaxes(-1, -2) @ qf)
    return tuple(_unflat(g, q.shape).copy() for g in (dq, dk, dv))


# ---------------------------------------------------------------------------------------
# the attention layer: fused projection, heads, the kernel, output projection


def _split_heads(t, n_head, col=0, width=None):
    """Columns col:col + width of t (R, B, N, L, w) -> (R, B, H, N, L, dh), C-contiguous (head h =
    columns col + h*dh:col + (h+1)*dh); width defaults to w."""
    R, B, N, L, w = t.shape
    width = w if width is None else width
    heads = t[..., col:col + width].reshape(R, B, N, L, n_head, width // n_head)  # (R, B, N, L, H, dh)
    return np.ascontiguousarray(heads.transpose(0, 1, 4, 2, 3, 5))  # (R, B, H, N, L, dh)


def _merge_heads(t, out=None, col=0):
    """(R, B, H, N, L, dh) -> (R, B, N, L, H*dh); or into columns col:col + H*dh of out
    (R, B, N, L, w), returned."""
    R, B, H, N, L, dh = t.shape
    if out is None:
        out = np.empty((R, B, N, L, H * dh), t.dtype)
    out[..., col:col + H * dh] = t.transpose(0, 1, 3, 4, 2, 5).reshape(R, B, N, L, H * dh)
    return out


def _fused_heads(v, q, k):
    """The fused projection's columns [v | q | k] (R, B, N, L, 3 H dh) from the heads, (R, B, H, N, L,
    dh) each: the layout of attention_layer_forward's h (docs/math.md §3)."""
    R, B, H, N, L, dh = v.shape
    out = np.empty((R, B, N, L, 3 * H * dh), v.dtype)
    for i, t in enumerate((v, q, k)):
        _merge_heads(t, out, i * H * dh)
    return out


def attention_layer_forward(x, w_attn, b_attn, w_proj, b_proj, n_head, scale=1.0, *, context=None):
    """Branching self-attention over the rows of the tree.

    x (R, B, N, L, d); w_attn (d, 3d), b_attn (1, 3d); w_proj (d, d), b_proj (1, d) -> y (R, B, N, L, d).
    cache: both linear caches, q, k, v, o (R, B, H, N, L, dh), lse (the kernel's backward
    recomputes the probabilities from it), scale, context.

    context: None (x is the whole tree), or a scene's cached trunk (k_ctx, v_ctx) of this layer,
    each (B, H, Nc, L, dh): then x (R, B, 1, L, d) holds R query rows of one view each
    (context_attention_forward), for inference only.
    """
    d = x.shape[-1]
    h, c_attn = linear_forward(x, w_attn, b_attn)  # (R, B, N, L, 3d)
    # docs/math.md §3: the fused columns are [values | queries | keys], not GPT-2's q, k, v order
    v = _split_heads(h, n_head, 0, d)  # (R, B, H, N, L, dh)
    q = _split_heads(h, n_head, d, d)
    k = _split_heads(h, n_head, 2 * d, d)
    # docs/math.md §2: the published model does not divide the logits by sqrt(dh): scale = 1
    if context is None:
        o, lse = branching_attention_forward(q, k, v, scale)  # (R, B, H, N, L, dh), (R, B, H, N, L)
    else:
        k_ctx, v_ctx = context  # (B, H, Nc, L, dh) each
        o, lse = context_attention_forward(q, k, v, k_ctx, v_ctx, scale)  # (R, B, H, 1, L, dh), (R, B, H, 1, L)
    y, c_proj = linear_forward(_merge_heads(o), w_proj, b_proj)  # (R, B, N, L, d)
    return y, (c_attn, c_proj, q, k, v, o, lse, scale, context)


def attention_layer_backward(dy, cache, trace=None, name=""):
    """dy (R, B, N, L, d) -> dx, dw_attn, db_attn, dw_proj, db_proj. trace: None, or a dict that
    also receives the gradients of name + ".out", ".v", ".k", ".q", ".c_attn"."""
    c_attn, c_proj, q, k, v, o, lse, scale, context = cache
    n_head = q.shape[2]
    do, dw_proj, db_proj = linear_backward(dy, c_proj)  # (R, B, N, L, d)
    do = _split_heads(do, n_head)  # (R, B, H, N, L, dh)
    dq, dk, dv = branching_attention_backward(do, q, k, v, o, lse, scale)
    dh = _fused_heads(dv, dq, dk)  # (R, B, N, L, 3d): [v | q | k]
    if trace is not None:
        for part, g in (("out", do), ("v", dv), ("k", dk), ("q", dq), ("c_attn", dh)):  # the trace's order, reversed
            trace[f"{name}.{part}"] = g
    dx, dw_attn, db_attn = linear_backward(dh, c_attn)
    return dx, dw_attn, db_attn, dw_proj, db_proj
