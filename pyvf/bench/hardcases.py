"""Numerical stability on hard cases (issue 11, item 3): sweeps that push one quantity across
orders of magnitude, showing where the naive formula breaks and whether pyvf stays within its
stated bound over the whole range.

    pyvf bench hardcases                       # every sweep; ~1 minute on 2 cores
    pyvf bench hardcases --quick               # fewer points, smaller problems: ~15 s
    pyvf bench hardcases --json F --plots DIR  # every number; one plot per sweep (hardcase-*.png)

Each sweep has a line per variant (its error against a reference at every point of the sweep)
and pyvf's bound as a function of the swept quantity, drawn on the plot. The reference is computed
on the very float32 (or float64) numbers the variants see: float64 where that is exact enough, long
double (x87, 64-bit significand) for the norms, mpmath for GELU, the cross-entropy and the angles.
A pyvf line that leaves its bound at any point fails the sweep: the report prints FAIL and the
command exits with status 1. A non-finite result (NaN, inf) counts as an error of inf. The
nearest-code search's cancellation (the expanded |x|^2 - 2 x.e + |e|^2 picks wrong codes far
from the origin; pyvf's re-ranked search stays exact) is `pyvf bench vq`'s table of offsets.

Sweeps (BOUND says what pyvf promises; the tests named hold the same claims at single points):
  attention-spread    logits of size s = 1..1e6 (random q, k): float32 softmax without the max
                      subtracted overflows at s ~ 88; pyvf, torch and the max-subtracted reference
                      are limited by the logits' own float32 rounding, delta ~ dh u s
  attention-mask      attended logits near -s, s = 1..1e6: the published mask, logits * mask - 1e4 *
                      (1 - mask), puts the weight on the masked keys once s > 1e4; pyvf excludes them
  layernorm/groupnorm rows (groups) of mean s times their spread, s = 1..1e6: one-pass variance
                      E[x^2] - E[x]^2 cancels; pyvf's two passes do not
  gelu                x in [-40, 0], error in ulps of the true value (mpmath): 0.5 (1 + erf(x/sqrt 2))
                      (torch's exact GELU) cancels from x ~ -6 and is 0 past -8.4 (float64)
  cross-entropy       target logit s = 1..1e4 below the row's maximum: -log(softmax) gives inf once
                      the probability underflows; the log-sum-exp form does not
  quat-normalize      |q| = 1..1e-30 (float32): q / sqrt(sum q^2) divides by an underflowed 0
  orientation         rotations 180 - s degrees, s = 10..1e-6: the published 2 asin(|vec r|) loses
                      half its digits near 180 (asin is flat at 1); pyvf's 2 atan2(|vec r|, |w|) does not
"""

import math
import os
import time

import numpy as np

import pyvf
from pyvf.nn import conv, layers, losses
from pyvf.bench.common import legend_outside, machine, pyplot, save_figure, torch_or_none
from pyvf.bench.accuracy import U32, U64, gelu_mp, gelu_naive
from pyvf.bench.attention import flat
from pyvf.geometry import _conj, _mul  # the Hamilton product, for the published asin form

LD = np.longdouble


def _torch():
    import torch
    import torch.nn.functional as F

    return torch, F


def _err_or_inf(e):
    return float(e) if np.isfinite(e) else float("inf")


# ---------------------------------------------------------------------------------------
# attention


ATT_SHAPE = {"full": (3, 1, 2, 4, 16, 32), "quick": (3, 1, 2, 3, 8, 16)}  # (R, B, H, N, L, dh)
RTOL32_ATT, RTOL64_ATT = 1e-5, 1e-12  # tests/test_attention.py RTOL32, RTOL64


def _dense(q, k, v, mask, sentinel=False, subtract_max=True):
    """Dense attention on flat (B, H, T, dh) arrays in their dtype: exact exclusion (-inf), or the
    published sentinel logits * mask - 1e4 * (1 - mask); subtract_max=False: exp of the raw logits."""
    s = q @ k.swapaxes(-1, -2)  # (B, H, T, T)
    with np.errstate(over="ignore", invalid="ignore"):
        if sentinel:
            m = mask.astype(s.dtype)
            s = s * m - s.dtype.type(1e4) * (1 - m)
        else:
            s = np.where(mask, s, -np.inf)
        if subtract_max:
            s = s - s.max(-1, keepdims=True)
        p = np.exp(s)
        p /= p.sum(-1, keepdims=True)
        return p @ v


def logit_rounding_bound(q, k, mask):
    """delta = gamma_dh * max over attended (t, u) of sum_e |q_te k_ue|: the largest rounding error a
    float32 dot product of length dh can put on a logit (tests/test_attention.py; flat arrays)."""
    dh = q.shape[-1]
    terms = np.abs(q) @ np.abs(k).swapaxes(-1, -2)
    return dh * U32 / (1 - dh * U32) * np.where(mask, terms, 0).max()


def _attention_sweep(name, title, xlabel, values, make_qk, mode, rng):
    """Shared by both attention sweeps. make_qk(s, q, k) scales/offsets unit-normal q, k for point s.
    Error: max|o - o_ref| / max|v| (o is a weighted mean of v). pyvf float32's bound:
    (e^(2 delta) - 1) + RTOL32 with delta the logit rounding bound (tests/test_attention.py,
    test_large_logits_offset_random_inputs); float64's 4 s u64 + RTOL64, s the largest |logit|."""
    shape = ATT_SHAPE[mode]
    R, B, H, N, L, dh = shape
    mask = pyvf.branching_mask(R, N, L)
    with_torch = torch_or_none() is not None
    lines = {k: [] for k in ("pyvf float32", "pyvf float64", "torch SDPA float32", "numpy exact float32",
                             "naive exp (no max) float32", "published -1e4 mask float32",
                             "published -1e4 mask float64")}
    if not with_torch:
        del lines["torch SDPA float32"]
    bounds = {"pyvf float32": [], "pyvf float64": []}
    for s in values:
        q, k, v = (rng.standard_normal(shape) for _ in range(3))
        q, k = make_qk(s, q, k)
        q32, k32, v32 = (a.astype(np.float32) for a in (q, k, v))
        q64, k64, v64 = (a.astype(np.float64) for a in (q32, k32, v32))
        ref = flat(pyvf.branching_attention_reference(q64, k64, v64))
        vmax = np.abs(v64).max()
        err = lambda o: _err_or_inf(np.abs(np.asarray(o, np.float64) - ref).max() / vmax)  # noqa: E731
        fq32, fk32, fv32, fq64, fk64, fv64 = (flat(a) for a in (q32, k32, v32, q64, k64, v64))
        lines["pyvf float32"].append(err(flat(pyvf.branching_attention(q32, k32, v32))))
        lines["pyvf float64"].append(err(flat(pyvf.branching_attention(q64, k64, v64))))
        if with_torch:
            torch, F = _torch()
            o = F.scaled_dot_product_attention(*(torch.from_numpy(a) for a in (fq32, fk32, fv32)),
                                               attn_mask=torch.from_numpy(mask), scale=1.0)
            lines["torch SDPA float32"].append(err(o.numpy()))
        lines["numpy exact float32"].append(err(_dense(fq32, fk32, fv32, mask)))
        lines["naive exp (no max) float32"].append(err(_dense(fq32, fk32, fv32, mask, subtract_max=False)))
        lines["published -1e4 mask float32"].append(err(_dense(fq32, fk32, fv32, mask, sentinel=True)))
        lines["published -1e4 mask float64"].append(err(_dense(fq64, fk64, fv64, mask, sentinel=True)))
        delta = logit_rounding_bound(fq64, fk64, mask)
        smax = np.abs(np.where(mask, fq64 @ fk64.swapaxes(-1, -2), 0)).max()
        bounds["pyvf float32"].append(float(np.expm1(2 * delta) + RTOL32_ATT))
        bounds["pyvf float64"].append(float(4 * smax * U64 + RTOL64_ATT))
    return dict(name=name, title=title, xlabel=xlabel, ylabel="max |o - o_ref| / max |v|", x=list(values),
                lines=lines, bounds=bounds,
                bound_text="float32: e^(2 delta) - 1 + 1e-5, delta = dh u max sum|q k| (the logits' float32 "
                           "rounding; vacuous, > 1, past s ~ 1e5); float64: 4 s u64 + 1e-12",
                shape=shape)


def sweep_attention_spread(mode, rng):
    values = np.logspace(0, 6, 13 if mode == "full" else 7)

    def make_qk(s, q, k):  # |logit| up to s: scale q and k by sqrt(s / max|q.k|)
        m = np.abs(flat(q) @ flat(k).swapaxes(-1, -2)).max()
        return q * math.sqrt(s / m), k * math.sqrt(s / m)

    return _attention_sweep("attention-spread", "attention: logits of size s (random q, k)", "s = max |logit|",
                            values, make_qk, mode, rng)


def sweep_attention_mask(mode, rng):
    values = np.logspace(0, 6, 13 if mode == "full" else 7)

    def make_qk(s, q, k):  # every logit -s + O(sqrt(dh)) (tests/test_attention.py's offset inputs)
        q[..., 0], k[..., 0] = -math.sqrt(s), math.sqrt(s)
        return q, k

    return _attention_sweep("attention-mask", "attention: attended logits near -s, exact exclusion vs the "
                            "published -1e4 mask", "s (logits = -s + O(1))", values, make_qk, mode, rng)


# ---------------------------------------------------------------------------------------
# LayerNorm and GroupNorm


def _norm_ref(xg, eps):
    """xhat of rows xg (..., n) in long double, two passes: the reference."""
    x = xg.astype(LD)
    xc = x - x.mean(-1, keepdims=True)
    xc -= xc.mean(-1, keepdims=True)
    return xc / np.sqrt((xc * xc).mean(-1, keepdims=True) + LD(eps))


def _one_pass(xg, eps):
    """The one-pass variance, E[x^2] - E[x]^2, in xg's dtype."""
    m = xg.mean(-1, keepdims=True)
    var = np.maximum((xg * xg).mean(-1, keepdims=True) - m * m, 0)
    return (xg - m) / np.sqrt(var + xg.dtype.type(eps))


def _norm_sweep(kind, mode, rng):
    """Rows (LayerNorm, d values) or groups (GroupNorm) of mean +-s and spread 1; gamma = 1,
    beta = 0, so y = xhat. Error: max|y - y_ref| / max|y_ref| (normwise). pyvf's bound: its tests'
    RTOL32 / RTOL64 for ordinary rows, whatever s: the second centring pass makes the large mean
    cost nothing (tests/test_layers.py, tests/test_conv.py: large mean, small spread)."""
    values = np.logspace(0, 6, 13 if mode == "full" else 7)
    with_torch = torch_or_none() is not None
    if kind == "layernorm":
        shape, eps, b32 = ((256, 256) if mode == "full" else (64, 64)), 1e-5, 1e-6
    else:
        shape, eps, b32 = ((2, 64, 8, 8) if mode == "full" else (1, 64, 4, 4)), 1e-6, 4e-7
    G = 32
    names = ["pyvf float32", "pyvf float64", "one-pass float32", "one-pass float64", "numpy two-pass float32"]
    names += ["torch float32"] if with_torch else []
    lines = {n: [] for n in names}
    for s in values:
        if kind == "layernorm":
            x = s * rng.choice([-1.0, 1.0], (shape[0], 1)) + rng.standard_normal(shape)
            rows = lambda a: a  # noqa: E731  (rows, d)
        else:
            B, C = shape[:2]
            x = (s * rng.choice([-1.0, 1.0], (B, G, 1, 1, 1)) + rng.standard_normal((B, G, C // G) + shape[2:])
                 ).reshape(shape)
            rows = lambda a: a.reshape(a.shape[0], G, -1)  # noqa: E731  (B, G, C/G * Hi * Wi)
        for dtype, tag in ((np.float32, "float32"), (np.float64, "float64")):
            xd = x.astype(dtype)
            ref = _norm_ref(rows(xd), eps).astype(np.float64).reshape(shape)
            err = lambda y: _err_or_inf(np.abs(np.asarray(y, np.float64) - ref).max() / np.abs(ref).max())  # noqa: E731
            one, zero = np.ones(shape[-1] if kind == "layernorm" else shape[1], dtype), None
            zero = np.zeros_like(one)
            if kind == "layernorm":
                lines[f"pyvf {tag}"].append(err(layers.layernorm_forward(xd, one, zero, eps)[0]))
            else:
                lines[f"pyvf {tag}"].append(err(conv.groupnorm_forward(xd, one, zero, G, eps)[0]))
            with np.errstate(all="ignore"):
                lines[f"one-pass {tag}"].append(err(_one_pass(rows(xd), eps).reshape(shape)))
            if dtype == np.float32:
                xr = rows(xd)
                xc = xr - xr.mean(-1, keepdims=True)
                lines["numpy two-pass float32"].append(
                    err((xc / np.sqrt(xr.var(-1, keepdims=True) + np.float32(eps))).reshape(shape)))
                if with_torch:
                    torch, F = _torch()
                    xt = torch.from_numpy(xd)
                    y = F.layer_norm(xt, (shape[-1],), eps=eps) if kind == "layernorm" else F.group_norm(xt, G, eps=eps)
                    lines["torch float32"].append(err(y.numpy()))
    title = {"layernorm": f"LayerNorm: rows of mean +-s, spread 1 ({shape[0]} rows of d={shape[1]})",
             "groupnorm": f"GroupNorm: groups of mean +-s, spread 1 (x {shape}, 32 groups, eps 1e-6)"}[kind]
    n = len(values)
    return dict(name=kind, title=title, xlabel="s = |mean| / spread", ylabel="max |y - y_ref| / max |y_ref|",
                x=list(values), lines=lines, bounds={"pyvf float32": [b32] * n, "pyvf float64": [1e-13] * n},
                bound_text=f"float32 {b32:g}, float64 1e-13 (the tests' bounds for ordinary rows), at every s")


def sweep_layernorm(mode, rng):
    return _norm_sweep("layernorm", mode, rng)


def sweep_groupnorm(mode, rng):
    return _norm_sweep("groupnorm", mode, rng)


# ---------------------------------------------------------------------------------------
# GELU


def sweep_gelu(mode, rng):
    """x on [-40, 0]; error in ulps of the true value in the result's dtype (np.spacing of the
    rounded true value, so the subnormal step below the normal range). pyvf's bound
    (tests/test_layers.py test_gelu_tail_few_ulp): 4 ulp plus, where Phi(x) is subnormal, the
    |x| * (smallest subnormal) its rounding can cost the product, in ulps."""
    x64 = np.linspace(0, -40, 161 if mode == "full" else 41)  # easy to hard, as every sweep
    lines, bounds = {}, {}
    with_torch = torch_or_none() is not None
    want = {}
    for xi in x64:
        want[xi] = gelu_mp(xi)
    for dtype, tag in ((np.float32, "float32"), (np.float64, "float64")):
        x = x64.astype(dtype)
        ft = np.finfo(dtype)
        wy = np.array([float(want[xi][0]) for xi in x64])
        wd = np.array([float(want[xi][1]) for xi in x64])
        Phi = np.abs(wy / np.where(x64 == 0, 1, x64))
        sp = lambda w: np.spacing(np.abs(w).astype(dtype)).astype(np.float64)  # noqa: E731
        ulp_err = lambda got, w: np.where(np.isfinite(got), np.abs(np.asarray(got, np.float64) - w) / sp(w), np.inf)  # noqa: E731
        y, cache = layers.gelu_forward(x)
        (dx,) = layers.gelu_backward(np.ones_like(x), cache)
        slack = np.where(Phi < ft.smallest_normal, np.abs(x64) * float(ft.smallest_subnormal), 0)
        lines[f"pyvf {tag}"] = list(ulp_err(y, wy))
        bounds[f"pyvf {tag}"] = list(4 + slack / sp(wy))
        lines[f"pyvf {tag} gelu'"] = list(ulp_err(dx, wd))
        # gelu' = Phi + x phi cancels near its zero, x = -0.7518: a few ulps of the terms' size
        # there, |Phi| + |x phi| = Phi + |gelu' - Phi|, which is many ulps of gelu' itself
        cond = (Phi + np.abs(wd - Phi)) / np.where(wd == 0, 1, np.abs(wd))
        bounds[f"pyvf {tag} gelu'"] = list(4 * cond + slack / sp(wd))
        lines[f"naive 0.5 (1 + erf) {tag}"] = list(ulp_err(gelu_naive(x)[0], wy))
        if with_torch:
            torch, F = _torch()
            lines[f"torch {tag}"] = list(ulp_err(F.gelu(torch.from_numpy(x)).numpy(), wy))
    return dict(name="gelu", title="GELU on [-40, 0] against mpmath (in ulps of the true value)", xlabel="x",
                ylabel="|error| in ulps of the true value", x=list(x64), lines=lines, bounds=bounds, logx=False, floor=1e-2,
                bound_text="4 ulp (plus the subnormal rounding step |x| * smallest subnormal where Phi(x) "
                           "is subnormal), float32 and float64; gelu': 4 ulp of |Phi| + |x phi| (its two terms "
                           "cancel near x = -0.75)")


# ---------------------------------------------------------------------------------------
# cross-entropy


def sweep_cross_entropy(mode, rng):
    """Rows of V logits N(0, 1) with the maximum at 0... and the target's logit s below the row's
    maximum. Error: max over rows of |loss - loss_ref| / loss_ref (mpmath log-sum-exp on the same
    numbers). pyvf's bound: (V + 4) u relative: the V-term sum of exponentials, the log, and the
    one rounding of z_t = logit_t - max (the loss is >= s)."""
    import mpmath

    M, V = (16, 1024) if mode == "full" else (8, 256)
    values = np.logspace(0, 4, 9 if mode == "full" else 5)
    with_torch = torch_or_none() is not None
    names = ["pyvf float32", "pyvf float64", "naive -log(softmax) float32", "naive -log(softmax) float64"]
    names += ["torch float32"] if with_torch else []
    lines = {n: [] for n in names}
    targets = rng.integers(0, V, M)
    for s in values:
        base = rng.standard_normal((M, V))
        base[np.arange(M), targets] = base.max(1) - s
        for dtype, tag in ((np.float32, "float32"), (np.float64, "float64")):
            logits = base.astype(dtype)
            ref = np.array([float(mpmath.log(mpmath.fsum(mpmath.exp(mpmath.mpf(float(v))) for v in row))
                                  - mpmath.mpf(float(row[t]))) for row, t in zip(logits, targets)])
            err = lambda loss: _err_or_inf((np.abs(np.asarray(loss, np.float64) - ref) / ref).max())  # noqa: E731
            lines[f"pyvf {tag}"].append(err(losses.cross_entropy_forward(logits, targets)[0]))
            with np.errstate(all="ignore"):
                e = np.exp(logits - logits.max(1, keepdims=True))
                lines[f"naive -log(softmax) {tag}"].append(err(-np.log((e / e.sum(1, keepdims=True))[np.arange(M), targets])))
            if with_torch and dtype == np.float32:
                torch, F = _torch()
                lines["torch float32"].append(
                    err(F.cross_entropy(torch.from_numpy(logits), torch.from_numpy(targets), reduction="none").numpy()))
    n = len(values)
    return dict(name="cross-entropy", title=f"cross-entropy: target logit s below the row's maximum (V={V})",
                xlabel="s = max logit - target logit", ylabel="max |loss - loss_ref| / loss_ref", x=list(values),
                lines=lines, bounds={"pyvf float32": [(V + 4) * U32] * n, "pyvf float64": [(V + 4) * U64] * n},
                bound_text=f"(V + 4) u relative, V = {V}: {(V + 4) * U32:.1e} (float32), {(V + 4) * U64:.1e} (float64)")


# ---------------------------------------------------------------------------------------
# quaternions


def sweep_quat_normalize(mode, rng):
    """Random unit quaternions times s, s = 1..1e-30, normalised with eps = 1e-70 (so sqrt(eps) =
    1e-35 is below every |q| here and the exact answer is q / |q|). Error: max over quaternions of
    max|q_n - ref|, ref in float64. pyvf's bound: 4 u (two nested hypots, ~1 ulp each, one division)."""
    n = 256 if mode == "full" else 64
    values = np.logspace(0, -30, 31 if mode == "full" else 11)
    eps = 1e-70
    with_torch = torch_or_none() is not None
    lines = {n_: [] for n_ in ["pyvf float32", "naive q / sqrt(max(sum q^2, eps)) float32"]
             + (["torch F.normalize float32"] if with_torch else [])}
    u = rng.standard_normal((n, 4))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    for s in values:
        q = (u * s).astype(np.float32)
        q64 = q.astype(np.float64)
        ref = q64 / np.sqrt((q64 * q64).sum(1, keepdims=True))  # float64: no underflow down to 1e-150
        err = lambda got: _err_or_inf(np.abs(np.asarray(got, np.float64) - ref).max())  # noqa: E731
        lines["pyvf float32"].append(err(pyvf.quat_normalize(q, eps=eps)))
        with np.errstate(all="ignore"):
            lines["naive q / sqrt(max(sum q^2, eps)) float32"].append(
                err(q / np.sqrt(np.maximum((q * q).sum(1, keepdims=True), np.float32(eps)))))
        if with_torch:
            torch, F = _torch()
            lines["torch F.normalize float32"].append(err(F.normalize(torch.from_numpy(q), dim=1, eps=1e-35).numpy()))
    return dict(name="quat-normalize", title="quaternion normalisation near zero (float32, eps 1e-70)",
                xlabel="|q|", ylabel="max |q_n - q/|q||", x=list(values), lines=lines,
                bounds={"pyvf float32": [4 * U32] * len(values)}, bound_text=f"4 u = {4 * U32:.1e} at every |q|",
                invert_x=True)


def angle_mp(a, b):
    """The angle in degrees between quaternions a and b (4,), exactly from their values: mpmath."""
    import mpmath

    a = [mpmath.mpf(float(v)) for v in a]
    b = [mpmath.mpf(float(v)) for v in b]
    aw, ax, ay, az = a
    bw, bx, by, bz = b[0], -b[1], -b[2], -b[3]
    w = aw * bw - ax * bx - ay * by - az * bz
    x = aw * bx + ax * bw + ay * bz - az * by
    y = aw * by + ay * bw + az * bx - ax * bz
    z = aw * bz + az * bw + ax * by - ay * bx
    return mpmath.degrees(2 * mpmath.atan2(mpmath.sqrt(x * x + y * y + z * z), abs(w)))


def sweep_orientation(mode, rng):
    """Pairs of quaternions 180 - s degrees apart, s = 10..1e-6 degrees, about random axes.
    Error: max over pairs of |angle - angle_ref| in degrees, ref by mpmath on the same numbers.
    pyvf's bound: the product r = q1 * conj(q2) costs each component <= 4 u |q1||q2| (<= 2 after
    the power-of-two scaling), which moves the angle by <= 2 * 4 u * 2 / |r| rad; with |r| >= 1/4:
    64 u rad, plus atan2's own ~2 u relative: 64 u + 2 u * angle, in degrees."""
    n = 64 if mode == "full" else 16
    values = np.logspace(1, -6, 15 if mode == "full" else 8)
    lines = {k: [] for k in ("pyvf float32", "pyvf float64", "published 2 asin(|vec r|) float32",
                             "published 2 asin(|vec r|) float64", "2 acos(|w r|) float32")}
    bounds = {"pyvf float32": [], "pyvf float64": []}
    for s in values:
        theta = math.radians(180 - s)
        q1 = rng.standard_normal((n, 4))
        q1 /= np.linalg.norm(q1, axis=1, keepdims=True)
        axis = rng.standard_normal((n, 3))
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        rot = np.concatenate([np.full((n, 1), math.cos(theta / 2)), math.sin(theta / 2) * axis], 1)
        q2 = _mul(rot, q1)  # q1 * conj(q2) = conj(rot) ... a rotation by theta
        for dtype, tag in ((np.float32, "float32"), (np.float64, "float64")):
            a, b = q1.astype(dtype), q2.astype(dtype)
            ref = np.array([float(angle_mp(x, y)) for x, y in zip(a, b)])
            err = lambda ang: _err_or_inf(np.abs(np.asarray(ang, np.float64) - ref).max())  # noqa: E731
            lines[f"pyvf {tag}"].append(err(pyvf.orientation_error(a, b)))
            r = _mul(a, _conj(b))
            with np.errstate(invalid="ignore"):
                vec = np.sqrt((r[:, 1:] ** 2).sum(1))
                lines[f"published 2 asin(|vec r|) {tag}"].append(err(np.degrees(2 * np.arcsin(vec))))
                if dtype == np.float32:
                    lines["2 acos(|w r|) float32"].append(err(np.degrees(2 * np.arccos(np.abs(r[:, 0])))))
            u = U32 if dtype == np.float32 else U64
            bounds[f"pyvf {tag}"].append(math.degrees(64 * u + 2 * u * math.radians(ref.max())))
    return dict(name="orientation", title="orientation error near 180 degrees", xlabel="180 degrees - angle",
                ylabel="max |angle - angle_ref| (degrees)", x=list(values), lines=lines, bounds=bounds,
                bound_text="(64 u + 2 u angle) rad, in degrees: 6.7e-5 deg (float32), 1.2e-13 deg (float64)",
                invert_x=True)


SWEEPS = {
    "attention-spread": sweep_attention_spread,
    "attention-mask": sweep_attention_mask,
    "layernorm": sweep_layernorm,
    "groupnorm": sweep_groupnorm,
    "gelu": sweep_gelu,
    "cross-entropy": sweep_cross_entropy,
    "quat-normalize": sweep_quat_normalize,
    "orientation": sweep_orientation,
}


# ---------------------------------------------------------------------------------------
# checking, breaking points, plots


def check(sw):
    """Each bounded (pyvf) line against its bound: {line: {"ok", "worst_ratio", "first_x_out"}}."""
    out = {}
    for name, bound in sw["bounds"].items():
        vals = np.array(sw["lines"][name], dtype=np.float64)
        b = np.array(bound, dtype=np.float64)
        outside = ~(vals <= b)  # NaN and inf are outside
        ratio = np.where(b > 0, vals / np.where(b > 0, b, 1), np.where(vals > 0, np.inf, 0.0))
        out[name] = dict(ok=bool(not outside.any()), worst_ratio=float(np.nanmax(ratio)) if len(ratio) else 0.0,
                         first_x_out=float(np.asarray(sw["x"])[outside][0]) if outside.any() else None)
    return out


def breaks(sw):
    """For each unbounded (comparison) line, the first x where it leaves the loosest pyvf bound of
    the same precision: {line: x or None}. 'Loosest' so that a break is never an artefact of a
    tight bound; lines of the other precision are compared with the float32 bound."""
    out = {}
    b32 = next((np.array(b) for n, b in sw["bounds"].items() if "float32" in n), None)
    b64 = next((np.array(b) for n, b in sw["bounds"].items() if "float64" in n), b32)
    for name, vals in sw["lines"].items():
        if name in sw["bounds"]:
            continue
        b = b64 if "float64" in name else b32
        if b is None:
            continue
        outside = ~(np.array(vals, dtype=np.float64) <= b)
        out[name] = float(np.asarray(sw["x"])[outside][0]) if outside.any() else None
    return out


# the sweeps whose error is relative to the output's size: their plots draw the unit roundoffs,
# the floor an output's own rounding sets
RELATIVE = ("attention-spread", "attention-mask", "layernorm", "groupnorm", "cross-entropy", "quat-normalize")


def plot_sweep(sw, folder):
    """hardcase-<name>.png: a line per variant, pyvf's bounds dashed; non-finite errors drawn as x
    at the top of the axes; errors below the floor (0 among them) drawn at it, and the ylabel says
    so; the unit roundoffs dotted on the RELATIVE sweeps; the legend beside the axes. Returns the
    path, or None without matplotlib."""
    plt = pyplot()
    if plt is None:
        return None
    os.makedirs(folder, exist_ok=True)
    fig, ax = plt.subplots(figsize=(9.6, 4.8), layout="constrained")
    x = np.asarray(sw["x"], dtype=np.float64)
    finite = [v for vals in sw["lines"].values() for v in vals if np.isfinite(v) and v > 0]
    floor = sw.get("floor") or (min(finite) / 10 if finite else 1e-20)
    top = max(finite) * 10 if finite else 1.0
    for name, vals in sw["lines"].items():
        v = np.array(vals, dtype=np.float64)
        bad = ~np.isfinite(v)
        shown = np.where(bad, np.nan, np.maximum(v, floor))
        style = "o-" if name.startswith("pyvf") else ".-"
        lw = 2.0 if name.startswith("pyvf") else 1.0
        (ln,) = ax.plot(x, shown, style, lw=lw, ms=4, label=name)
        if bad.any():
            ax.plot(x[bad], np.full(bad.sum(), top), "x", color=ln.get_color(), ms=7)
    for name, b in sw["bounds"].items():
        ax.plot(x, np.maximum(np.array(b, dtype=np.float64), floor), "--", lw=1.2, color="k", alpha=0.7,
                label="pyvf's bound(s)")
    if sw["name"] in RELATIVE:
        for u in (U32, U64):
            ax.axhline(u, color="0.4", ls=":", lw=1.0, label=f"unit roundoff, float32 {U32:.1e} / float64 {U64:.1e}")
    ax.plot([], [], "x", color="gray", label="NaN / inf (drawn at the top)")
    ax.set_yscale("log")
    if sw.get("logx", True):
        ax.set_xscale("log")
    if sw.get("invert_x"):
        ax.invert_xaxis()
    ax.set_ylim(min(floor, U64 if sw["name"] in RELATIVE else floor) / 2, top * 3)
    below = any(v < floor for vals in sw["lines"].values() for v in vals)  # NaN compares False
    ax.set_xlabel(sw["xlabel"])
    ax.set_ylabel(sw["ylabel"] + (f"\n(below {floor:.0e}, 0 included, drawn at {floor:.0e})" if below else ""))
    ax.set_title(sw["title"], fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    legend_outside(fig)
    path = os.path.join(folder, f"hardcase-{sw['name']}.png")
    save_figure(fig, path, dpi=100)
    return path


def plot_all(sweeps, folder):
    """plot_sweep for each sweep (its path in sw["plot"]): the files, or None without matplotlib."""
    for sw in sweeps:
        sw["plot"] = plot_sweep(sw, folder)
    return None if any(sw["plot"] is None for sw in sweeps) else [sw["plot"] for sw in sweeps]


def _x(v):
    return "-" if v is None else f"{v:.3g}"


def sweep_summary(sw):
    """Markdown lines: pyvf's bound, PASS/FAIL per pyvf line, where each other line leaves it."""
    out = [f"bound: {sw['bound_text']}", ""]
    for name, c in sw["check"].items():
        out.append(f"* {'PASS' if c['ok'] else 'FAIL'} {name}: worst error / bound {c['worst_ratio']:.2g}"
                   + ("" if c["ok"] else f", first out at x = {_x(c['first_x_out'])}"))
    for name, x in sw["breaks"].items():
        out.append(f"* {name}: " + ("within pyvf's bound over the range" if x is None
                                    else f"leaves pyvf's bound at x = {_x(x)}"))
    return "\n".join(out)


def run(names=tuple(SWEEPS), mode="full", threads=2, seed=0, log=print):
    t0 = time.perf_counter()
    pyvf.set_num_threads(threads)
    torch = torch_or_none()
    if torch is not None:
        torch.set_num_threads(threads)
    sweeps = []
    for name in names:
        t1 = time.perf_counter()
        sw = SWEEPS[name](mode, np.random.default_rng(seed))
        sw["check"], sw["breaks"] = check(sw), breaks(sw)
        sw["seconds"] = time.perf_counter() - t1
        sw["passed"] = all(c["ok"] for c in sw["check"].values())
        log(f"  {name:<16} {'PASS' if sw['passed'] else 'FAIL'}  {sw['seconds']:.1f} s", flush=True)
        sweeps.append(sw)
    failures = [f"{sw['name']} / {n}: first out at x = {_x(c['first_x_out'])} (worst error / bound "
                f"{c['worst_ratio']:.2g})" for sw in sweeps for n, c in sw["check"].items() if not c["ok"]]
    return dict(config=dict(mode=mode, seed=seed, sweeps=list(names)), machine=machine(threads), sweeps=sweeps,
                failures=failures, total_seconds=time.perf_counter() - t0)


def print_report(report):
    """Each sweep's summary (sweep_summary) under its title."""
    for sw in report["sweeps"]:
        print(f"\n## {sw['title']}\n\n{sweep_summary(sw)}")
