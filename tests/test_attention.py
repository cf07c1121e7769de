"""Tests of branching attention (docs/math.md §2): the C++ kernel and its NumPy reference against
torch float64 autograd, the defining property of the tree, the plain loops, hard numerical cases,
argument checks, reproducibility, the mask, the kernel's vectorised exp (its memory: test_memory.py).

Shapes: q, k, v, do, o (R, B, H, N, L, dh); lse (R, B, H, N, L); flat sequences (B, H, T, dh)
with T = R*N*L in the order [row][view][token]. Query block (r, i) attends trunk blocks (0, j),
j < i, and its own block (r, i), every token of each fully.

Relative errors are normwise: max|got - want| / max|want| (conftest.assert_close). Every
tolerance carries the reason for its size; the numbers quoted as "measured" are the largest
seen on the development machine (AVX-512, FMA, 2 threads).
"""


import numpy as np
import pytest
import torch

import pyvf
from pyvf import _core

from conftest import assert_bitwise_equal, assert_close, forced_threads

# every test here runs once per kernel path this machine executes (conftest.kernel_path)
pytestmark = pytest.mark.usefixtures("kernel_path")

U32 = 2.0 ** -24  # float32 unit roundoff
U64 = 2.0 ** -53  # float64 unit roundoff

# float64 kernel vs float64 reference: both are O(dh + N*L) term sums of O(1) numbers in a
# different order; measured <= 9.2e-15 (dh = 64, L = 64, scale 1). 1e-12 leaves room for larger sums
# while any real bug (a wrong mask, a swapped operand, a missed rescale) is an O(1) error.
RTOL64 = 1e-12

# pyvf float32 vs a float64 computation on the same float32 inputs, unit-normal q, k, v, do,
# dh <= 64, scale 1 (logits up to ~40): a logit carries a float32 rounding error of about
# sqrt(dh) * u * |logit| ~ 2e-5 at worst, which moves each probability by that relative amount;
# the exp adds <= 2 ulp and the sums over <= 192 keys a few ulp. Measured <= 2.4e-6 (forward
# and every gradient); 1e-5 = 4x margin, and still 5 orders of magnitude below a real bug.
RTOL32 = 1e-5


# ---------------------------------------------------------------------------------------
# independent helpers (not taken from pyvf)


def rule_mask(R, N, L):
    """(T, T) bool: mask[t, u] says query token t attends key token u, written from the rule in
    docs/math.md §2 by a loop over block pairs (independent of pyvf.branching_mask)."""
    T = R * N * L
    mask = np.zeros((T, T), dtype=bool)
    for r in range(R):
        for i in range(N):
            for kr in range(R):
                for j in range(N):
                    if (kr == 0 and j < i) or (kr == r and j == i):
                        t0, u0 = (r * N + i) * L, (kr * N + j) * L
                        mask[t0:t0 + L, u0:u0 + L] = True
    return mask


def flat(x):
    """(R, B, H, N, L, dh) -> (B, H, T, dh), T in the order [row][view][token]."""
    R, B, H, N, L, dh = x.shape
    return np.ascontiguousarray(np.moveaxis(x, 0, 2).reshape(B, H, R * N * L, dh))


def unflat(x, shape):
    """(B, H, T, ...) -> (R, B, H, N, L, ...)."""
    R, B, H, N, L = shape[:5]
    return np.moveaxis(x.reshape((B, H, R, N, L) + x.shape[3:]), 2, 0)


def dense_lse(q, k, scale, mask):
    """float64 log-sum-exp of every row's attended logits, from flat (B, H, T, dh) q, k: (B, H, T)."""
    s = np.where(mask, scale * np.einsum("bhtd,bhud->bhtu", q, k), -np.inf)  # (B, H, T, T)
    m = s.max(axis=-1, keepdims=True)
    return (m + np.log(np.exp(s - m).sum(axis=-1, keepdims=True)))[..., 0]


def attended_mean(v):
    """The output when every attended key has the same logit: the mean of the attended values.
    (R, B, H, N, L, dh) -> same shape, by the rule written out per block."""
    R, N = v.shape[0], v.shape[3]
    o = np.empty_like(v)
    for r in range(R):
        for i in range(N):
            if r == 0:
                keys = v[0, :, :, :i + 1]  # (B, H, i+1, L, dh)
            else:
                keys = np.concatenate([v[0, :, :, :i], v[r, :, :, i:i + 1]], axis=2)
            o[r, :, :, i] = keys.mean(axis=(2, 3))[:, :, None, :]
    return o


def torch_flat(x):
    """(R, B, H, N, L, dh) tensor -> (B, H, T, dh)."""
    R, B, H, N, L, dh = x.shape
    return x.permute(1, 2, 0, 3, 4, 5).reshape(B, H, R * N * L, dh)


def torch_unflat(x, shape):
    R, B, H, N, L, dh = shape
    return x.reshape(B, H, R, N, L, dh).permute(2, 0, 1, 3, 4, 5)


def torch_branching_mask(R, N, L):
    """(T, T) bool built in torch from each token's row and view."""
    t = torch.arange(R * N * L)
    row, view = t // (N * L), (t // L) % N
    rq, iq, rk, ik = row[:, None], view[:, None], row[None, :], view[None, :]
    return ((rk == 0) & (ik < iq)) | ((rk == rq) & (ik == iq))


def torch_attention(q, k, v, scale, mask):
    """Explicit masked softmax attention on (B, H, T, dh) tensors; masked logits are -inf."""
    s = scale * (q @ k.transpose(-1, -2))  # (B, H, T, T)
    s = s.masked_fill(~mask, float("-inf"))
    return torch.softmax(s, dim=-1) @ v


def scale_of(kind, dh):
    return {"one": 1.0, "inv_sqrt_dh": 1.0 / np.sqrt(dh), "negative": -0.7}[kind]


# ---------------------------------------------------------------------------------------
# 1. kernel and the NumPy reference vs torch float64 autograd, under a random upstream gradient

# R in {1..4}, N in {1, 2, 5}, L in {1, odd, a multiple of the SIMD width, > 2 SIMD widths},
# dh in {5, 17, 64}; B, H > 1 in most. Each shape with one scale (1, 1/sqrt(dh) or negative).
SHAPES = [
    ((1, 2, 3, 1, 1, 5), "one"),  # one key per query
    ((1, 2, 2, 5, 3, 17), "negative"),  # trunk only: block-causal
    ((2, 2, 3, 2, 1, 64), "inv_sqrt_dh"),  # L = 1
    ((3, 2, 2, 5, 7, 17), "one"),  # the paper's R = 3, odd L
    ((4, 3, 2, 5, 4, 5), "negative"),
    ((3, 2, 2, 2, 16, 64), "inv_sqrt_dh"),  # L a whole number of vectors
    ((2, 1, 2, 3, 64, 64), "inv_sqrt_dh"),  # the paper's L = 64, dh = 64
    ((2, 2, 1, 2, 33, 17), "negative"),  # L past two float32 vectors plus a tail
]


def torch_value_and_grads(q, k, v, do, scale):
    """o and (dq, dk, dv) of sum(o * do) by torch autograd in float64, as (R, B, H, N, L, dh)."""
    R, N, L = q.shape[0], q.shape[3], q.shape[4]
    leaves = [torch.tensor(x, dtype=torch.float64, requires_grad=True) for x in (q, k, v)]
    o = torch_attention(*(torch_flat(x) for x in leaves), scale, torch_branching_mask(R, N, L))
    (o * torch_flat(torch.tensor(do, dtype=torch.float64))).sum().backward()
    return torch_unflat(o, q.shape).detach().numpy(), tuple(x.grad.numpy() for x in leaves)


@pytest.mark.parametrize("shape, scale_kind", SHAPES, ids=lambda s: "x".join(map(str, s)) if isinstance(s, tuple) else s)
def test_matches_torch(shape, scale_kind, make_qkv):
    scale = scale_of(scale_kind, shape[-1])
    q, k, v, do = make_qkv(shape)
    o_t, grads_t = torch_value_and_grads(q, k, v, do, scale)
    # float64 against float64: the same sums in another order (see RTOL64); the kernel and the
    # NumPy reference alike (a wrong oracle would hide a wrong kernel)
    o, lse = pyvf.branching_attention_forward(q, k, v, scale)
    assert o.dtype == np.float64 and lse.dtype == np.float64 and lse.shape == shape[:5]
    assert_close("o f64", o, o_t, RTOL64)
    assert_close("reference o", pyvf.branching_attention_reference(q, k, v, scale), o_t, RTOL64)
    # lse against the log-sum-exp of the masked logits, computed here from the rule
    R, N, L = shape[0], shape[3], shape[4]
    lse_indep = dense_lse(flat(q), flat(k), scale, rule_mask(R, N, L))
    assert_close("lse", lse, unflat(lse_indep, shape), RTOL64)
    for name, g, w in zip(("dq", "dk", "dv"), pyvf.branching_attention_vjp(q, k, v, do, scale), grads_t):
        assert g.dtype == np.float64 and g.shape == shape
        assert_close(f"{name} f64", g, w, RTOL64)
    for name, g, w in zip(("dq", "dk", "dv"), pyvf.branching_attention_reference_vjp(q, k, v, do, scale), grads_t):
        assert_close(f"reference {name}", g, w, RTOL64)

    # pyvf float32 against torch float64 run on the same (float32-rounded) inputs, so the
    # difference is pyvf's float32 arithmetic only (see RTOL32)
    q32, k32, v32, do32 = (x.astype(np.float32) for x in (q, k, v, do))
    o_t, grads_t = torch_value_and_grads(*(x.astype(np.float64) for x in (q32, k32, v32, do32)), scale)
    o32 = pyvf.branching_attention(q32, k32, v32, scale)
    assert o32.dtype == np.float32
    assert_close("o f32", o32, o_t, RTOL32)
    for name, g, w in zip(("dq", "dk", "dv"), pyvf.branching_attention_vjp(q32, k32, v32, do32, scale), grads_t):
        assert g.dtype == np.float32
        assert_close(f"{name} f32", g, w, RTOL32)


# ---------------------------------------------------------------------------------------
# 2. the defining property: branch r at view i is block-causal attention on
#    [trunk views 0..i-1, branch r view i]


def torch_block_causal(q, k, v, L, scale):
    """Block-causal attention on (B, H, n*L, dh) tensors: token of view i sees views 0..i."""
    view = torch.arange(q.shape[-2]) // L
    return torch_attention(q, k, v, scale, view[None, :] <= view[:, None])


def test_branch_block_equals_block_causal_sequence(make_qkv):
    shape, scale = (3, 2, 2, 4, 3, 5), 1.0
    R, B, H, N, L, dh = shape
    q, k, v, _ = make_qkv(shape)
    o = pyvf.branching_attention(q, k, v, scale)
    for r in range(R):
        for i in range(N):
            # the plain sequence [trunk views 0..i-1, row r view i] as a one-row tree
            seq = [np.concatenate([x[0, :, :, :i], x[r, :, :, i:i + 1]], axis=2)[None] for x in (q, k, v)]
            tq, tk, tv = (torch.tensor(x[0].reshape(B, H, (i + 1) * L, dh)) for x in seq)
            o_torch = torch_block_causal(tq, tk, tv, L, scale)[:, :, i * L:].reshape(B, H, L, dh)
            assert_close(f"branch {r} view {i} vs torch block-causal", o[r, :, :, i], o_torch.numpy(), RTOL64)


# ---------------------------------------------------------------------------------------
# 3. the plain C++ loops vs the fast kernel


@pytest.mark.parametrize("shape", [(3, 2, 2, 5, 7, 17), (1, 2, 1, 2, 1, 5)],
                         ids=lambda s: "x".join(map(str, s)))
def test_plain_loops_match_fast_kernel(shape, make_qkv):
    q, k, v, do = make_qkv(shape)
    scale = 1.0
    # float64: both are float64 sums of the same terms in a different order; measured <= 2e-15
    # (the plain loops accumulate in double too). 1e-13: tight, still well above rounding.
    o_p, lse_p = pyvf.branching_attention_forward(q, k, v, scale, plain=True)
    o_f, lse_f = pyvf.branching_attention_forward(q, k, v, scale)
    assert_close("o plain vs fast", o_f, o_p, 1e-13)
    assert_close("lse plain vs fast", lse_f, lse_p, 1e-13)
    g_p = pyvf.branching_attention_backward(do, q, k, v, o_p, lse_p, scale, plain=True)
    g_f = pyvf.branching_attention_backward(do, q, k, v, o_f, lse_f, scale)
    for name, a, b in zip(("dq", "dk", "dv"), g_f, g_p):
        assert_close(f"{name} plain vs fast", a, b, 1e-13)

    # float32: the plain loops accumulate in double and round once at the end (error <= u
    # relative per element, so 2 * u normwise); the fast kernel within RTOL32 of float64.
    q32, k32, v32, do32 = (x.astype(np.float32) for x in (q, k, v, do))
    as64 = [x.astype(np.float64) for x in (q32, k32, v32, do32)]
    o_ref = pyvf.branching_attention_reference(*as64[:3], scale)
    g_ref = pyvf.branching_attention_reference_vjp(*as64, scale)
    o_p, lse_p = pyvf.branching_attention_forward(q32, k32, v32, scale, plain=True)
    o_f, lse_f = pyvf.branching_attention_forward(q32, k32, v32, scale)
    assert_close("o f32 plain vs f64 reference", o_p, o_ref, 2 * U32)
    assert_close("o f32 fast vs f64 reference", o_f, o_ref, RTOL32)
    # lse: float64 for float32 inputs; plain computes it in double from exact products
    assert_close("lse f32 plain vs f64", lse_p, pyvf.branching_attention_forward(*as64[:3], scale)[1], 1e-13)
    assert_close("lse f32 fast vs f64", lse_f, lse_p, RTOL32)
    g_p = pyvf.branching_attention_backward(do32, q32, k32, v32, o_p, lse_p, scale, plain=True)
    g_f = pyvf.branching_attention_backward(do32, q32, k32, v32, o_f, lse_f, scale)
    for name, a, b, w in zip(("dq", "dk", "dv"), g_f, g_p, g_ref):
        # plain backward takes o rounded to float32, so D = rowsum(do * o) carries u relative
        # error and ds = p (dp - D) cancels: a few u normwise (measured 1.2e-7 = 2 u)
        assert_close(f"{name} f32 plain vs f64 reference", b, w, 8 * U32)
        assert_close(f"{name} f32 fast vs f64 reference", a, w, RTOL32)


# ---------------------------------------------------------------------------------------
# 4. hard cases


def dyadic_large_logits(rng, shape, magnitude):
    """q, k whose logits are magnitude + (a multiple of 1/16 of size <= dh), exactly
    representable in float32 and float64 and computed exactly by any summation order:
    q[..., 0] * k[..., 0] = magnitude exactly, the other entries are multiples of 1/4 in [-1, 1],
    and every partial sum is a multiple of 1/16 below 2^20 in size (24 bits). So the kernel
    and the reference start from the same logits, and only the softmax is being tested."""
    a, b = {1e4: (100.0, 100.0), 2e4: (100.0, 200.0), 1e6: (1000.0, 1000.0)}[abs(magnitude)]
    q = rng.integers(-4, 5, shape) / 4.0
    k = rng.integers(-4, 5, shape) / 4.0
    q[..., 0], k[..., 0] = np.sign(magnitude) * a, b
    assert abs(magnitude) + shape[-1] < 2 ** 20
    return q, k


def gradient_bound(q, k, v, do, scale):
    """Componentwise size of the terms of (dq, dk, dv), from the float64 probabilities P, in
    units of which their rounding errors are measured: ds = P * (dp - D) is a difference of
    dot products, each with an error ~ u |do|.|v|, and dq = scale * ds @ k is a sum whose terms
    may cancel (they do when k[..., 0] is the same for every key: dq[..., 0] = scale k0 sum_u ds_u
    and sum_u ds_u = 0). Returns (|scale| W @ |k|, |scale| W^T @ |q|, P^T @ |do|) with
    W = P * (|do| @ |v|^T + |do| . |o|), each (R, B, H, N, L, dh)."""
    R, N, L = q.shape[0], q.shape[3], q.shape[4]
    qf, kf, vf, dof = (flat(x) for x in (q, k, v, do))
    s = scale * np.einsum("bhtd,bhud->bhtu", qf, kf)
    s = np.where(rule_mask(R, N, L), s, -np.inf)
    p = np.exp(s - s.max(axis=-1, keepdims=True))
    p /= p.sum(axis=-1, keepdims=True)  # (B, H, T, T)
    o = p @ vf
    w = p * (np.abs(dof) @ np.abs(vf).swapaxes(-1, -2) + (np.abs(dof) * np.abs(o)).sum(-1, keepdims=True))
    out = (abs(scale) * w @ np.abs(kf), abs(scale) * w.swapaxes(-1, -2) @ np.abs(qf),
           p.swapaxes(-1, -2) @ np.abs(dof))
    return tuple(unflat(x, q.shape) for x in out)


def assert_within_rounding(name, got, want, size, u, c):
    """|got - want| <= c * u * size elementwise: an error bound in units of the rounding error
    the computation can make on terms of that size (for sums that cancel, where a normwise
    relative bound means nothing)."""
    diff = np.abs(np.asarray(got, np.float64) - want)
    with np.errstate(divide="ignore", invalid="ignore"):  # terms of size 0: only an exact 0 passes
        ratio = np.where(diff == 0, 0.0, diff / (u * size))
    worst = np.unravel_index(np.argmax(ratio), ratio.shape)
    assert ratio.max() <= c, (f"{name}: error reaches {ratio.max():.3g} > {c:g} times u * (size of its terms) "
                              f"at {tuple(map(int, worst))}: got {got[worst]!r}, want {want[worst]!r}")


# -2e4: every attended logit near -2e4, where the published -1e4 sentinel would give the masked
# keys the weight (pyvf excludes them exactly; the hard-case report shows the sentinel's error)
@pytest.mark.parametrize("magnitude", [1e4, -2e4, 1e6, -1e6])
def test_large_logits_exact_inputs(magnitude, rng):
    shape = (3, 1, 2, 4, 5, 9)
    q, k = dyadic_large_logits(rng, shape, magnitude)
    v, do = rng.standard_normal(shape), rng.standard_normal(shape)

    # float64. Forward: identical logits, so only softmax rounding remains (measured 4e-16).
    assert_close("o f64", pyvf.branching_attention(q, k, v), pyvf.branching_attention_reference(q, k, v), RTOL64)
    # Backward recomputes p = exp(s - lse) from the saved lse, a float64 near |magnitude| whose
    # own rounding (|magnitude| * 2^-53, 1.1e-10 at 1e6) becomes a relative error of p. That is
    # the float64 input's own resolution at that size (a 1-ulp change of q moves the logit
    # as much), not a kernel bug. Measured <= 0.6 |magnitude| 2^-53; bound 2 |magnitude| 2^-53
    # + RTOL64.
    rtol_bwd = 2 * abs(magnitude) * U64 + RTOL64
    grads = pyvf.branching_attention_vjp(q, k, v, do)
    for name, g, w in zip(("dq", "dk", "dv"), grads, pyvf.branching_attention_reference_vjp(q, k, v, do)):
        assert_close(f"{name} f64", g, w, rtol_bwd)

    # float32: the inputs are exactly float32 and so are the logits (24 bits), so the float32
    # result must be as good as float32 allows: exp <= 2 ulp, sums of <= 20 terms. Measured
    # 1.3e-7 forward, 2e-7 dk and dv; 1e-6. A float32 lse (one ulp = 0.06 at 1e6, a 6% error
    # in every probability) or an unstable softmax would be off by orders of magnitude.
    q32, k32, v32, do32 = (x.astype(np.float32) for x in (q, k, v, do))
    assert_close("o f32", pyvf.branching_attention(q32, k32, v32), pyvf.branching_attention_reference(q, k, v), 1e-6)
    dq32, dk32, dv32 = pyvf.branching_attention_vjp(q32, k32, v32, do32)
    dq, dk, dv = pyvf.branching_attention_reference_vjp(q, k, v, do)
    assert_close("dk f32", dk32, dk, 1e-6)
    assert_close("dv f32", dv32, dv, 1e-6)
    # dq cancels (see gradient_bound): compare it componentwise against the size of its terms,
    # |dq32 - dq| <= c u (W @ |k|), c = dh: the dot-product error constant gamma_dh ~ dh u.
    # Measured c <= 1.5.
    assert_within_rounding("dq f32", dq32, dq, gradient_bound(q, k, v, do, 1.0)[0], U32, shape[-1])


def logit_rounding_bound(q, k, mask):
    """delta = gamma_dh * max over attended (t, u) of sum_e |q_te k_ue|: the largest rounding
    error a float32 dot product of length dh can put on a logit (gamma_n = n u / (1 - n u))."""
    dh = q.shape[-1]
    gamma = dh * U32 / (1 - dh * U32)
    terms = np.abs(flat(q)) @ np.abs(flat(k)).swapaxes(-1, -2)  # (B, H, T, T)
    return gamma * np.where(mask, terms, 0).max()


@pytest.mark.parametrize("magnitude", [1e4, 1e5, 1e6, -1e6])
def test_large_logits_offset_random_inputs(magnitude, rng):
    """Logits = magnitude + O(3) from random (inexact) q, k: the rows are not one-hot, and the
    logits' own rounding, ~|magnitude| * u, is what limits any implementation."""
    shape = (3, 2, 2, 4, 5, 8)
    R, B, H, N, L, dh = shape
    q, k, v, do = (rng.standard_normal(shape) for _ in range(4))
    q[..., 0], k[..., 0] = np.sign(magnitude) * np.sqrt(abs(magnitude)), np.sqrt(abs(magnitude))

    # float64: kernel and reference round the logits differently, by a few |magnitude| 2^-53,
    # which is the relative error of every probability; measured <= 1.2 |magnitude| 2^-53
    # (forward and gradients), bound 4 |magnitude| 2^-53 + RTOL64.
    rtol = 4 * abs(magnitude) * U64 + RTOL64
    assert_close("o f64", pyvf.branching_attention(q, k, v), pyvf.branching_attention_reference(q, k, v), rtol)
    for name, g, w in zip(("dq", "dk", "dv"), pyvf.branching_attention_vjp(q, k, v, do),
                          pyvf.branching_attention_reference_vjp(q, k, v, do)):
        assert_close(f"{name} f64", g, w, rtol)

    # float32 against float64 on the same float32 inputs. Conditioning: each logit carries a
    # rounding error up to delta (logit_rounding_bound); a softmax weight p_u = e^(s_u) / Z then
    # moves by at most a factor e^(+-2 delta), so |o32 - o| <= (e^(2 delta) - 1) max|v|, and
    # dv = P^T do likewise by (e^(2 delta) - 1) P^T |do| (plus RTOL32 for the rest of the
    # arithmetic). delta ~ dh u |magnitude|: 5e-3 at 1e4, 0.5 at 1e6 (where the bound is
    # nearly vacuous). Measured error / bound <= 0.07 for o, <= 0.02 for dv.
    q32, k32, v32, do32 = (x.astype(np.float32) for x in (q, k, v, do))
    as64 = [x.astype(np.float64) for x in (q32, k32, v32, do32)]
    delta = logit_rounding_bound(as64[0], as64[1], rule_mask(R, N, L))
    assert delta < 0.6, delta  # the inputs are what the comment says they are
    o32 = pyvf.branching_attention(q32, k32, v32)
    assert_close("o f32 (conditioning bound)", o32, pyvf.branching_attention_reference(*as64[:3]), 0.0,
                 atol=(np.expm1(2 * delta) + RTOL32) * np.abs(as64[2]).max())
    grads32 = pyvf.branching_attention_vjp(q32, k32, v32, do32)
    assert all(np.isfinite(g).all() for g in grads32)
    dv = pyvf.branching_attention_reference_vjp(*as64)[2]
    pt_abs_do = gradient_bound(*as64, 1.0)[2]  # P^T |do|
    assert_close("dv f32 (conditioning bound)", grads32[2], dv, RTOL32, atol=np.expm1(2 * delta) * pt_abs_do.max())


@pytest.mark.parametrize("magnitude", [1e4, 1e6])
def test_large_logits_one_hot_random_inputs(magnitude, rng):
    """Random q, k with logits of size ~magnitude: gaps between logits are ~magnitude too, so
    a row puts all its weight on its largest logit and o is that key's value."""
    shape = (3, 2, 2, 4, 5, 8)
    R, B, H, N, L, dh = shape
    a = np.sqrt(magnitude / np.sqrt(dh))  # q . k ~ a^2 sqrt(dh) = magnitude
    q, k = a * rng.standard_normal(shape), a * rng.standard_normal(shape)
    v, do = rng.standard_normal(shape), rng.standard_normal(shape)

    # rows with a clear winner: best attended logit ahead of the second by >= 30 (the second
    # has weight <= e^-30 ~ 1e-13), so o must be the winner's value to the dtype's precision
    s = np.where(rule_mask(R, N, L), np.einsum("bhtd,bhud->bhtu", flat(q), flat(k)), -np.inf)
    top2 = -np.sort(-s, axis=-1)[..., :2]
    clear = top2[..., 0] - top2[..., 1] >= 30  # (B, H, T); a single attended key: gap inf
    assert clear.mean() > 0.8, "the test needs rows with a clear winner"
    winner_v = np.take_along_axis(flat(v), s.argmax(-1)[..., None], axis=2)  # (B, H, T, dh)

    o = pyvf.branching_attention(q, k, v)
    assert_close("o f64 == value of the winning key", flat(o)[clear], winner_v[clear], RTOL64)
    # float64 vs reference, the logit rounding bound of the offset test; measured <= 2e-13
    rtol = 4 * magnitude * U64 + RTOL64
    assert_close("o f64", o, pyvf.branching_attention_reference(q, k, v), rtol)
    dq, dk, dv = pyvf.branching_attention_vjp(q, k, v, do)
    dq_ref, dk_ref, dv_ref = pyvf.branching_attention_reference_vjp(q, k, v, do)
    assert_close("dv f64", dv, dv_ref, rtol)
    # dq and dk are sums of ds = p * (dp - D) terms, and on a one-hot row dp_winner - D is a
    # difference of two float64 dot products of the same vectors (o == v_winner): exactly 0 in
    # exact arithmetic, and 0 in floating point only if both are rounded in the same order.
    # Which order a vector path uses (FMA or not, vector width) is not part of the contract,
    # so the bound is the dot-product error gamma_dh ~ dh u on terms of size W @ |k| and
    # W^T @ |q| (gradient_bound), on every path: 2 dh for the two dot products, plus the
    # relative error of each p = exp(s - lse) from the logits' own rounding, 4 |magnitude| u
    # as in the offset test (it shows on the rows' runners-up, p ~ 1e-169, on the SSE2 path).
    # Measured <= 2.1 (AVX2) and 1.2e4 = 0.3 x 4 |magnitude| (baseline, at 1e4).
    sizes = gradient_bound(q, k, v, do, 1.0)
    c = 2 * dh + 4 * magnitude
    assert_within_rounding("dq f64", dq, dq_ref, sizes[0], U64, c)
    assert_within_rounding("dk f64", dk, dk_ref, sizes[1], U64, c)

    # float32: finite, and the same winners (a float32 logit error of ~dh u |q||k| is far
    # below a gap of 30 at these sizes: ~0.5 at 1e6). o = (v_w + e^-30 ...) / (1 + e^-30 ...)
    # rounds to v_w within an ulp or two (measured 3.5e-8 normwise); 4 u.
    q32, k32, v32, do32 = (x.astype(np.float32) for x in (q, k, v, do))
    o32 = pyvf.branching_attention(q32, k32, v32)
    assert_close("o f32 == value of the winning key", flat(o32)[clear], winner_v[clear], 4 * U32)
    assert all(np.isfinite(g).all() for g in pyvf.branching_attention_vjp(q32, k32, v32, do32))


@pytest.mark.parametrize("dtype, noise", [(np.float64, 0.0), (np.float32, 0.0), (np.float64, 1e-12)],
                         ids=["equal-float64", "equal-float32", "near-ties-float64"])
def test_equal_or_near_tied_keys_give_the_mean_of_attended_values(dtype, noise, rng, make_qkv):
    """Every key of a head equal (noise 0) or equal up to 1e-12 (near ties): the attended logits of
    a query tie (to ~1e-12), the weights are uniform, o is the mean of the attended values (closed
    form), and dq = scale * sum_u ds_u k_u = scale * k * sum_u ds_u + (noise) = 0 + (noise), since
    the softmax backward's ds sums to 0 over a row."""
    shape = (3, 2, 2, 4, 3, 17)
    q, v, do = make_qkv(shape, dtype, n=3)
    base = rng.standard_normal(shape[1:3] + (1, 1, shape[-1]))  # (B, H, 1, 1, dh): one key per head
    k = (base + noise * rng.standard_normal(shape)).astype(dtype)
    as64 = [x.astype(np.float64) for x in (q, k, v, do)]
    o = pyvf.branching_attention(q, k, v, 0.5)
    # equal keys, float64: mean of <= N L = 12 values, measured 1.4e-16. float32: the same (the
    # logits of one query have identical bits for every key, so the weights are exactly uniform),
    # and the mean rounds within a few u: measured 6e-8, bound 4 u. Near ties: the weights differ
    # from uniform by ~1e-12 |q| |noise| relative: 1e-10 is generous.
    tol = 1e-10 if noise else (1e-14 if dtype == np.float64 else 4 * U32)
    assert_close("o vs mean of attended values", o, attended_mean(as64[2]), tol)
    rtol = RTOL64 if dtype == np.float64 else RTOL32
    assert_close("o", o, pyvf.branching_attention_reference(*as64[:3], 0.5), rtol)
    dq, dk, dv = pyvf.branching_attention_vjp(q, k, v, do, 0.5)
    want = pyvf.branching_attention_reference_vjp(*as64, 0.5)
    assert_close("dv", dv, want[2], rtol)
    assert_close("dk", dk, want[1], rtol)
    # dq is 0 (or ~1e-12 of its terms), below the rounding of the sum, in the kernel and the
    # reference alike: compare it componentwise against the size of its terms (gradient_bound),
    # c = dh as for any dot product of length dh (float32: D = rowsum(do * o) is rounded from
    # double while dp = do . v is float32, see test_single_key). Measured c <= 1.3.
    u = U64 if dtype == np.float64 else U32
    assert_within_rounding("dq", dq, want[0], gradient_bound(*as64, 0.5)[0], u, shape[-1])


@pytest.mark.parametrize("plain", [False, True], ids=["fast", "plain"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("R", [1, 3])
def test_single_key(R, dtype, plain, make_qkv):
    """N = L = 1: each query attends exactly one key (its own), p = 1 exactly, so o == v and
    dv == do bit for bit, and dq == dk == 0 exactly (ds = p (dp - D) with D = do . o = do . v)."""
    q, k, v, do = make_qkv((R, 2, 3, 1, 1, 17), dtype)
    o, lse = pyvf.branching_attention_forward(q, k, v, plain=plain)
    assert_bitwise_equal("o", o, v)
    # the lse of a single logit is the logit itself
    assert_close("lse", lse, np.einsum("...d,...d", q.astype(np.float64), k.astype(np.float64)),
                 1e-15 if dtype == np.float64 else 4 * 17 * U32)
    dq, dk, dv = pyvf.branching_attention_backward(do, q, k, v, o, lse, plain=plain)
    assert_bitwise_equal("dv", dv, do)
    for name, g in (("dq", dq), ("dk", dk)):  # ds = p (dp - D) with dp = do . v and D = do . o = do . v
        assert not np.any(g != 0), f"{name} must be exactly 0: {np.count_nonzero(g)} of {g.size} entries nonzero"


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_overflow_only_in_unattended_pairs_is_fine(dtype, make_qkv):
    """q of branch 1 and k of branch 2 are ~1e20: their product overflows float32, but branch 1
    never attends branch 2, so no attended logit overflows and nothing may raise."""
    shape = (3, 1, 2, 2, 3, 4)
    q, k, v, do = make_qkv(shape, dtype)
    q[1] *= 1e20
    k[2] *= 1e20
    o = pyvf.branching_attention(q, k, v)
    as64 = [x.astype(np.float64) for x in (q, k, v, do)]
    # attended logits reach ~1e20: rows are one-hot, o is exact to the dtype's rounding
    assert_close("o", o, pyvf.branching_attention_reference(*as64[:3]), 4 * U32 if dtype == np.float32 else RTOL64)
    assert all(np.isfinite(g).all() for g in pyvf.branching_attention_vjp(q, k, v, do))


# ---------------------------------------------------------------------------------------
# 5. bad input raises, naming the argument


def _qkvdo(shape=(2, 1, 2, 2, 3, 4), dtype=np.float64):
    rng = np.random.default_rng(7)
    return [rng.standard_normal(shape).astype(dtype) for _ in range(4)]


def _with(i, change):
    """q, k, v, do with argument i replaced by change(argument i)."""
    args = _qkvdo()
    args[i] = change(args[i])
    return args


def _fwd(args, **kw):
    return pyvf.branching_attention(*args[:3], **kw)


def _vjp(args, **kw):
    return pyvf.branching_attention_vjp(*args, **kw)


def _poison(x):
    x = x.copy()
    x[1, 0, 1, 1, 2, 3] = np.nan
    return x


def _bw(i, change):
    """branching_attention_backward with argument i of (do, q, k, v, o, lse) replaced by change(it)."""
    q, k, v, do = _qkvdo()
    args = [do, q, k, v, *pyvf.branching_attention_forward(q, k, v)]
    args[i] = change(args[i])
    return pyvf.branching_attention_backward(*args)


strided = lambda x: np.concatenate([x, x], -1)[..., ::2]
# the refusals of the kernel's public faces: (call, exception, the argument it names)
BAD_INPUTS = {
    "q int32": (lambda: _fwd(_with(0, lambda x: x.astype(np.int32))), TypeError, "q"),
    "k float32, q float64": (lambda: _fwd(_with(1, lambda x: x.astype(np.float32))), TypeError, "k"),
    "do float32": (lambda: _vjp(_with(3, lambda x: x.astype(np.float32))), TypeError, "do"),
    "v other shape": (lambda: _fwd(_with(2, lambda x: x[..., :3].copy())), ValueError, "v"),
    "do other shape": (lambda: _vjp(_with(3, lambda x: x[:1].copy())), ValueError, "do"),
    "5 dims": (lambda: _fwd([x[0] for x in _qkvdo()]), ValueError, "q"),
    "zero-size dim": (lambda: _fwd([x[:, :, :, :0] for x in _qkvdo()]), ValueError, "q"),
    "k strided": (lambda: _fwd(_with(1, strided)), ValueError, "k"),
    "scale nan": (lambda: _fwd(_qkvdo(), scale=float("nan")), ValueError, "scale"),
    "scale str": (lambda: _fwd(_qkvdo(), scale="1"), TypeError, "scale"),
    "q has NaN": (lambda: _vjp(_with(0, _poison)), ValueError, "q"),
    "v has NaN": (lambda: _fwd(_with(2, _poison)), ValueError, "v"),
    "do has NaN": (lambda: _vjp(_with(3, _poison)), ValueError, "do"),
    "backward o has NaN": (lambda: _bw(4, _poison), ValueError, "o"),
    "backward o float32": (lambda: _bw(4, lambda o: o.astype(np.float32)), TypeError, "o"),
    "backward lse float32": (lambda: _bw(5, lambda lse: lse.astype(np.float32)), TypeError, "lse"),
    "backward lse other shape": (lambda: _bw(5, lambda lse: lse[..., :2].copy()), TypeError, "lse"),
    # q, k ~ 1e20: q . k ~ 1e40 overflows float32 whatever the scale (float64 holds it): the kernel
    # says so instead of returning NaN or a made-up softmax
    "float32 logits overflow": (lambda: _fwd([x * np.float32(1e20) for x in _qkvdo(dtype=np.float32)]), ValueError, "overflowed"),
    "float64 logits overflow": (lambda: _fwd([x * 1e160 for x in _qkvdo()]), ValueError, "overflowed"),
    "mask R = 0": (lambda: pyvf.branching_mask(0, 2, 2), ValueError, "R"),
    "mask N float": (lambda: pyvf.branching_mask(2, 2.0, 2), TypeError, "N"),
}


@pytest.mark.parametrize("case", BAD_INPUTS, ids=str)
def test_bad_input_raises(case):
    call, exc, name = BAD_INPUTS[case]
    with pytest.raises(exc, match=rf"\b{name}\b"):
        call()


# ---------------------------------------------------------------------------------------
# 6. bitwise reproducibility


def test_bitwise_reproducible_across_runs_and_threads(make_qkv):
    """2, 1, 2 and 5 threads, every call on the threads (forced_threads: this shape is below the
    size at which a call takes them): the same bits. The backward's key blocks fall into 4 groups
    here (4 heads), whose dq are added in group order after a barrier."""
    shape = (3, 2, 2, 5, 16, 17)  # 60 query blocks, 4 heads: work to share between threads
    saved = pyvf.num_threads()
    results = {}
    for dtype in (np.float64, np.float32):
        q, k, v, do = make_qkv(shape, dtype)
        for threads in (2, 1, 2, 5):
            with forced_threads(threads):
                assert pyvf.num_threads() == threads or not _core.openmp
                o, lse = pyvf.branching_attention_forward(q, k, v)
                results.setdefault(dtype, []).append((o, lse) + pyvf.branching_attention_backward(do, q, k, v, o, lse))
    assert pyvf.num_threads() == saved
    names = ("o", "lse", "dq", "dk", "dv")
    for dtype, runs in results.items():
        for run, what in ((1, "1 thread vs 2 threads"), (2, "second run, 2 threads"), (3, "5 threads vs 2")):
            for name, a, b in zip(names, runs[run], runs[0]):
                assert_bitwise_equal(f"{np.dtype(dtype).name} {name}: {what}", a, b)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_backward_reads_nothing_stale(dtype, make_qkv):
    """The backward's dq buffers of key groups 1.. (dq_extra) are not zeroed when allocated: each
    task zeroes every block it adds into. A backward with a NaN do fills them with NaN, and the
    next call of the same shape mostly gets that memory back from the allocator: its gradients
    must be bitwise those of the first call (4 heads: 4 key groups; 1 and 2 threads)."""
    shape = (3, 1, 4, 5, 16, 8)
    q, k, v, do = make_qkv(shape, dtype)
    o, lse = pyvf.branching_attention_forward(q, k, v)
    nan = np.full_like(do, np.nan)
    for threads in (1, 2):
        with forced_threads(threads):
            first = [np.empty_like(q) for _ in range(3)]  # dq, dk, dv
            _core.attn_backward(*first, lse, q, k, v, o, do, 1.0)
            for _ in range(3):
                got = [np.empty_like(q) for _ in range(3)]
                _core.attn_backward(*got, lse, q, k, v, o, nan, 1.0)
                assert np.isnan(got[0]).all()
                _core.attn_backward(*got, lse, q, k, v, o, do, 1.0)
                for name, g, f in zip(("dq", "dk", "dv"), got, first):
                    assert_bitwise_equal(f"{name} on {threads} threads after a NaN call", g, f)


# ---------------------------------------------------------------------------------------
# 7. branching_mask


@pytest.mark.parametrize("R, N, L", [(1, 1, 1), (1, 4, 3), (3, 5, 4), (4, 2, 7), (3, 20, 2)])
def test_mask_shape_and_block_counts(R, N, L):
    m = pyvf.branching_mask(R, N, L)
    T = R * N * L
    assert m.shape == (T, T) and m.dtype == np.bool_
    np.testing.assert_array_equal(m, rule_mask(R, N, L))
    np.testing.assert_array_equal(m, torch_branching_mask(R, N, L).numpy())
    assert m.sum() == L * L * (R * N * (N + 1) // 2)
    assert np.all(np.diag(m))  # every token attends itself: no empty softmax row


# ---------------------------------------------------------------------------------------
# 8. the kernel's vectorised exp


# Cephes' expf (Cody-Waite reduction) about 1 ulp, measured 1.002 ulp: 2 ulp, against float64 (exact
# to 1e-16, far below a float32 ulp) on a dense grid over [ln(2^-126), 0]; Cephes' exp (Pade form)
# about 1 ulp (<= 2.2e-16 relative), measured 2.6e-16 (1.65 ulp just above a power of 2): 4e-16,
# against long double (64-bit mantissa on x86: exact to ~1e-19). A sloppier reduction or
# polynomial shows up as tens of ulp.
@pytest.mark.parametrize("dtype, lo, n, bound", [(np.float32, -87.3, 400_001, 2.0),
                                                 (np.float64, -708.0, 400_001, 4e-16)])
def test_exp_accuracy(dtype, lo, n, bound):
    x = np.concatenate([np.linspace(lo, 0, n, dtype=dtype), np.array([-1e-30, -0.0, 0.0], dtype)])
    y = np.empty_like(x)
    _core.exp(y, x)
    exact = np.exp(x.astype(np.longdouble))
    unit = np.spacing(exact.astype(dtype)).astype(np.longdouble) if dtype == np.float32 else exact  # ulps; relative
    err = (np.abs(y.astype(np.longdouble) - exact) / unit).astype(np.float64)
    worst = np.argmax(err)
    assert err.max() <= bound, f"exp {np.dtype(dtype).name}: error {err.max():.3g} at x = {x[worst]!r}"
    assert np.all(y[x == 0] == 1)  # exp(0) == exp(-0) == 1 exactly


@pytest.mark.parametrize("dtype, lo", [(np.float32, -87.33654), (np.float64, -708.3964185322641)])
def test_exp_underflow_and_minus_inf_give_zero(dtype, lo):
    """Below ln(smallest normal) the result is 0; -inf is 0; at the threshold it is >= the
    smallest normal."""
    lo = dtype(lo)
    tiny = np.finfo(dtype).tiny  # smallest normal
    below = np.array([np.nextafter(lo, dtype(-np.inf)), lo - 1, lo - 30, -1e4, -1e30, -np.finfo(dtype).max, -np.inf],
                     dtype=dtype)
    y = np.empty_like(below)
    _core.exp(y, below)
    assert np.all(y == 0), f"exp of {below[y != 0]} gave {y[y != 0]}"
    above = np.array([lo, np.nextafter(lo, dtype(0)), lo + dtype(1e-3)], dtype=dtype)
    y = np.empty_like(above)
    _core.exp(y, above)
    assert np.all(y >= tiny) and np.all(np.isfinite(y))
    assert_close("exp just above the threshold", y, np.exp(above.astype(np.float64)), 4 * np.finfo(dtype).eps)
