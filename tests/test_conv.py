"""Tests of the codebook's image layers (docs/math.md §4): conv2d, GroupNorm, swish, nearest x2
upsampling, GroupNorm + swish and the 2D attention block (pyvf/nn/conv.py).

Each layer is a pair `x_forward(...) -> (out, cache)`, `x_backward(dout, cache) -> (dx, *dparams)`.
The tests: every layer against PyTorch in float64 under a random upstream gradient (output and
every gradient); float32 against float64 on the same inputs; the parity traps shown to matter
(the Downsample's (0,1,0,1) padding, GroupNorm eps 1e-6, the grouping of channels, a transposed
kernel, upsample's summing backward); hard numerical cases (constant groups, groups of mean 1e4
and spread 0.1 against mpmath, swish at +-1000 with every floating-point error raised); dtypes.
Then the C++ kernel (section 3, once per instruction-set path) against its NumPy reference and
torch on every code path and a 1x1 image, 1 vs 2 vs 5 threads bitwise. The GEMM: tests/test_layers.py.

Shapes: images (B, C, Hi, Wi), NCHW; conv weights torch's (Co, C, kh, kw). Channels 5 -> 7 for the
convs (not multiples of 8, in != out), batch 3, odd and even image sides; 32 groups on 64 and 96
channels for GroupNorm.

Relative errors are normwise: max|got - want| / max|want| (conftest.assert_close). "Measured"
numbers are the largest seen on the development machine (x86-64, numpy 2.4 with OpenBLAS,
torch 2.13 CPU, 2 cores).
"""

import mpmath
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pyvf.nn import conv

from conftest import assert_bitwise_equal, assert_close, float_arrays, forced_threads

EPS = 1e-6  # the codebook's GroupNorm eps (docs/math.md §4); torch's default is 1e-5
G = 32  # groups of Normalize

# float64 pyvf vs float64 torch: the same sums (<= 7 * 3 * 3 * 5 = 315 terms for dw, 96 * 15 for
# GroupNorm) in another order. Measured <= 1.5e-15 over every layer, output and gradient (conv2d
# 7.8e-16, groupnorm 3.6e-16, attnblock 1.5e-15, swish 3.6e-16, upsample 1.6e-16). 1e-13 leaves
# room for other BLAS orders while every bug this file targets is far larger (each gap is asserted
# below): padding on the wrong side, a transposed kernel or channels grouped wrongly are O(1)
# errors; eps 1e-5 moves GroupNorm's y by 0.37 here; an averaging upsample backward is off by 3/4.
RTOL64 = 1e-13

# pyvf float32 vs torch float64 on the same float32 inputs: pyvf's float32 arithmetic only.
RTOL32 = {
    # y and dx are dot products of K = C*kh*kw <= 171 terms accumulated in float32 (FMA where the
    # path has it); dw sums B*Ho*Wo <= 2680 products, in chunks of 256; db sums in double. About sqrt(n) u
    # normwise (u = 6e-8); measured <= 4.7e-7 (dx of the 3x3 case on 9x67, baseline path; y 3.9e-7,
    # dw 2.7e-7, db 4.3e-8); 2e-6 leaves 4x.
    "conv2d": 2e-6,
    # group mean and variance over <= 3 * 15 = 45 numbers, a reciprocal square root, the backward's
    # two group means, dgamma/dbeta summed over B*Hi*Wi. Groups of variance ~ eps are no worse
    # conditioned (eps bounds rstd by 1000). Measured <= 1.1e-7 (y); 4e-7 = 3.6x margin.
    "groupnorm": 4e-7,
    # elementwise: exp, one division, a few products. Measured <= 5.6e-8 (dx); 2e-7 = 3.6x margin.
    "swish": 2e-7,
    # GroupNorm, then swish's few ulp elementwise. Measured <= 1.7e-7.
    "groupnorm_swish": 4e-7,
    # copies forward; the backward adds 4 numbers. Measured <= 6.1e-8 (dx); 2e-7 = 3.3x margin.
    "upsample": 2e-7,
    # GroupNorm, three 1x1 convs, a softmax over P = 15 positions, two batched products, a 1x1
    # conv, composed; the backward through all of them. Measured <= 4.1e-7 (dwk); 2e-6 = 5x margin.
    "attnblock": 2e-6,
}

B, CI, CO = 3, 5, 7  # conv batch, in and out channels: not multiples of 8, in != out


# ---------------------------------------------------------------------------------------
# the torch twins (float64 autograd), written independently of pyvf's padding convention


def torch_conv2d(x, w, b, stride=1, padding=0):
    if isinstance(padding, int):
        return F.conv2d(x, w, b, stride=stride, padding=padding)  # torch's own symmetric padding
    top, bottom, left, right = padding
    return F.conv2d(F.pad(x, (left, right, top, bottom)), w, b, stride=stride)  # F.pad: last axis first


def torch_groupnorm(x, gamma, beta, groups=G, eps=EPS):
    return F.group_norm(x, groups, gamma, beta, eps=eps)


def torch_swish(x):
    return F.silu(x)


def torch_upsample(x):
    return F.interpolate(x, scale_factor=2, mode="nearest")


def torch_attnblock(x, ng, nb, wq, bq, wk, bk, wv, bv, wo, bo, groups=G, eps=EPS):
    """taming-transformers' AttnBlock.forward, line for line."""
    h_ = F.group_norm(x, groups, ng, nb, eps=eps)
    q, k, v = F.conv2d(h_, wq, bq), F.conv2d(h_, wk, bk), F.conv2d(h_, wv, bv)
    b, c, h, w = q.shape
    q = q.reshape(b, c, h * w).permute(0, 2, 1)  # b, hw, c
    k = k.reshape(b, c, h * w)  # b, c, hw
    w_ = torch.bmm(q, k) * (int(c) ** (-0.5))  # b, hw, hw
    w_ = torch.softmax(w_, dim=2)
    v = v.reshape(b, c, h * w)
    h_ = torch.bmm(v, w_.permute(0, 2, 1))  # b, c, hw
    h_ = F.conv2d(h_.reshape(b, c, h, w), wo, bo)
    return x + h_


LAYERS = {  # name -> (forward, backward, torch twin, gradient names in forward-argument order)
    "conv2d": (conv.conv2d_forward, conv.conv2d_backward, torch_conv2d, ("dx", "dw", "db")),
    "groupnorm": (conv.groupnorm_forward, conv.groupnorm_backward, torch_groupnorm, ("dx", "dgamma", "dbeta")),
    "swish": (conv.swish_forward, conv.swish_backward, torch_swish, ("dx",)),
    "upsample": (conv.upsample_nearest2x_forward, conv.upsample_nearest2x_backward, torch_upsample, ("dx",)),
    "groupnorm_swish": (conv.groupnorm_swish_forward, conv.groupnorm_swish_backward,
                        lambda x, g, b: F.silu(torch_groupnorm(x, g, b)), ("dx", "dgamma", "dbeta")),
    "attnblock": (conv.attnblock_forward, conv.attnblock_backward, torch_attnblock,
                  ("dx", "dnorm_gamma", "dnorm_beta", "dwq", "dbq", "dwk", "dbk", "dwv", "dbv", "dwo", "dbo")),
}


def group_images(rng, shape, groups=G):
    """(B, C, Hi, Wi) images whose groups differ in scale (log-uniform in [10^-3.5, 10^0.5], so
    some groups have var << eps = 1e-6, some ~ eps, most >> eps) and whose channels differ in
    offset and spread within a group, so that eps and which channels share a group both matter."""
    Bn, C = shape[:2]
    scale = np.repeat(10.0 ** rng.uniform(-3.5, 0.5, (Bn, groups)), C // groups, axis=1)[:, :, None, None]
    offset = rng.uniform(-2, 2, (Bn, C, 1, 1))
    spread = rng.uniform(0.3, 3, (Bn, C, 1, 1))
    return scale * (offset + spread * rng.standard_normal(shape))


def build(case, rng, dtype):
    """(name, inputs in forward-argument order, keyword arguments, random upstream gradient dy),
    the arrays of `dtype`."""
    name, *dims = case
    f = lambda *shape: rng.standard_normal(shape)
    kwargs = {}
    if name in ("groupnorm", "groupnorm_swish"):
        C, Hi, Wi = dims
        inputs = [group_images(rng, (2, C, Hi, Wi)), 1 + 0.5 * f(C), f(C)]
    elif name == "swish":
        inputs = [6 * f(2, 4, 5, 3)]  # reaches |x| ~ 25: both tails and the curved middle
    elif name == "upsample":
        Hi, Wi = dims
        inputs = [f(2, 3, Hi, Wi)]
    elif name == "attnblock":
        C, Hi, Wi = dims
        lin = lambda: [f(C, C, 1, 1) / np.sqrt(C), 0.1 * f(C)]
        inputs = [f(2, C, Hi, Wi) + f(2, C, 1, 1), 1 + 0.5 * f(C), 0.5 * f(C), *lin(), *lin(), *lin(), *lin()]
    inputs = [a.astype(dtype) for a in inputs]
    y, _ = LAYERS[name][0](*inputs, **kwargs)
    return name, inputs, kwargs, f(*y.shape).astype(dtype)


def pyvf_run(name, inputs, kwargs, dy):
    fwd, bwd, _, _ = LAYERS[name]
    y, cache = fwd(*inputs, **kwargs)
    return y, bwd(dy, cache), cache


def torch_run(name, inputs, kwargs, dy, twin=None):
    """y and the gradients of sum(y * dy) w.r.t. every input, by torch autograd in float64
    (float32 inputs are converted exactly)."""
    twin = twin or LAYERS[name][2]
    leaves = [torch.tensor(a, dtype=torch.float64, requires_grad=True) for a in inputs]
    y = twin(*leaves, **kwargs)
    (y * torch.tensor(dy, dtype=torch.float64)).sum().backward()
    return y.detach().numpy(), [t.grad.numpy() for t in leaves]


def compare(name, got_y, got_grads, want_y, want_grads, rtol, label):
    grad_names = LAYERS[name][3]
    assert len(got_grads) == len(want_grads) == len(grad_names), f"{name}: {len(got_grads)} gradients returned"
    assert_close(f"{label} y", got_y, want_y, rtol)
    for gname, g, w in zip(grad_names, got_grads, want_grads):
        if name == "attnblock" and gname == "dbk":
            # the key bias adds q_i . bk to every logit of query row i alike, which the softmax
            # ignores: dbk is exactly 0 and both sides hold rounding noise. Bounded absolutely, on the
            # scale of dwk (the other gradient that flows through k).
            assert_close(f"{label} dbk (zero)", g, np.zeros_like(w), 0.0, atol=rtol * np.abs(want_grads[5]).max())
            continue
        assert_close(f"{label} {gname}", g, w, rtol)


DOWN = (0, 1, 0, 1)  # the Downsample's padding (top, bottom, left, right): right and bottom only
CASES = [
    # conv2d: its shapes and code paths in section 3
    ("groupnorm", 64, 5, 3),  # 2 channels per group
    ("groupnorm", 96, 4, 4),  # 3 channels per group
    ("groupnorm_swish", 64, 5, 3),  # ResnetBlock's norm1/norm2 + swish, norm_out + swish
    ("groupnorm_swish", 32, 9, 37),
    ("swish",),
    ("upsample", 5, 4),
    ("upsample", 1, 3),
    ("attnblock", 64, 5, 3),  # P = 15 positions, C**-0.5 = 1/8
]


def case_id(c):
    return "-".join("x".join(map(str, p)) if isinstance(p, tuple) else str(p) for p in c)


# ---------------------------------------------------------------------------------------
# 1. every layer vs torch float64, random upstream gradient; float64 and float32


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("case", CASES, ids=case_id)
def test_matches_torch(case, dtype, rng):
    """float32 against torch float64 on the same float32 inputs (pyvf's float32 arithmetic only).
    Also: the dtype in is the dtype out, of every gradient and every cached array (no silent upcast)."""
    name, inputs, kwargs, dy = build(case, rng, dtype)
    y, grads, cache = pyvf_run(name, inputs, kwargs, dy)
    assert y.dtype == dtype and all(g.dtype == dtype for g in grads), \
        f"{name}: y {y.dtype}, grads {[g.dtype for g in grads]}"
    for g, a in zip(grads, inputs):
        assert g.shape == a.shape
    for a in float_arrays(cache):
        assert a.dtype == dtype, f"{name} caches a {a.dtype} array {a.shape}: a silent upcast"
    y_t, grads_t = torch_run(name, inputs, kwargs, dy)  # float64 (on the float32 values, for float32)
    rtol = RTOL64 if dtype == np.float64 else RTOL32[name]
    compare(name, y, grads, y_t, grads_t, rtol, f"{case_id(case)} {np.dtype(dtype).name}")


def gap(got, want):
    return np.abs(got - want).max() / np.abs(want).max()


def test_conv2d_traps_have_teeth(rng):
    """The Downsample case (docs/math.md §4), against the mistakes that still run: symmetric padding 1
    (same output size on even images), the pad on the top-left corner instead, a transposed 3x3
    kernel. Each is an O(1) change of y, far outside RTOL64 (measured gaps 1.06, 1.06, 0.73)."""
    (x, w, b), kwargs, _ = kernel_inputs((3, CI, CO, (8, 8), (3, 3), 2, DOWN), rng, np.float64)
    y, _ = conv.conv2d_forward(x, w, b, **kwargs)
    t = [torch.tensor(a) for a in (x, w, b)]
    wrong = {
        "padding=1": F.conv2d(t[0], t[1], t[2], stride=2, padding=1),
        "pad top-left": F.conv2d(F.pad(t[0], (1, 0, 1, 0)), t[1], t[2], stride=2),
        "transposed kernel": F.conv2d(F.pad(t[0], (0, 1, 0, 1)), t[1].transpose(2, 3), t[2], stride=2),
    }
    for what, yt in wrong.items():
        assert yt.shape == y.shape, what  # same shape: only the values can tell
        assert gap(y, yt.numpy()) > 0.1, f"{what} is only {gap(y, yt.numpy()):.1e} from pyvf's Downsample"


def test_groupnorm_traps_have_teeth(rng):
    """eps 1e-5 (torch's default) instead of 1e-6, and channels grouped by c % groups instead of in
    consecutive runs, both move y and dx far outside the float64 and float32 tolerances (measured:
    eps y 0.37, dx 1.5; interleaved y 0.80, dx 1.75)."""
    name, inputs, kwargs, dy = build(("groupnorm", 64, 5, 3), rng, np.float64)
    y, (dx, _, _), _ = pyvf_run(name, inputs, kwargs, dy)
    y5, g5 = torch_run(name, inputs, kwargs, dy, twin=lambda *a: torch_groupnorm(*a, eps=1e-5))
    C = inputs[0].shape[1]
    perm = np.arange(C).reshape(C // G, G).T.reshape(-1)  # group g gets channels g, g+G, ...
    inv = np.argsort(perm)
    interleaved = lambda x, g, b: torch_groupnorm(x[:, perm], g[perm], b[perm])[:, inv]
    yi, gi = torch_run(name, inputs, kwargs, dy, twin=interleaved)
    for what, yw, dxw in (("eps 1e-5", y5, g5[0]), ("interleaved groups", yi, gi[0])):
        for q, got, want in (("y", y, yw), ("dx", dx, dxw)):
            assert gap(got, want) > 1e3 * RTOL32["groupnorm"], f"{what}: {q} only {gap(got, want):.1e} away"


# ---------------------------------------------------------------------------------------
# 2. hard cases: GroupNorm

CONSTANTS = [0.0, 0.1, -7.77, 1e4 + 0.3, 123456.789]  # 0.1, 1e4+0.3, ... are not dyadic


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_groupnorm_constant_groups(dtype, rng):
    """A constant group has var = 0: xhat = 0, so y == beta exactly (bitwise), and it adds exactly
    nothing to dgamma. Its gradient is NOT zero: d var / dx = 0 there, so
    dx = rstd * (dxhat - mean_g(dxhat)), dxhat = dy * gamma, rstd = 1/sqrt(eps) = 1000: finite.
    Checked against that closed form, and in float64 against torch."""
    x = group_images(rng, (2, 64, 3, 4))  # groups of 2 channels
    for g, c in enumerate(CONSTANTS):  # batch 0, groups 0..4: constant (both channels, every pixel)
        x[0, 2 * g:2 * g + 2] = c
    x = x.astype(dtype)
    C = x.shape[1]
    gamma, beta = (rng.standard_normal(C).astype(dtype) for _ in range(2))
    dy = rng.standard_normal(x.shape).astype(dtype)
    y, cache = conv.groupnorm_forward(x, gamma, beta)
    dx, dgamma, dbeta = conv.groupnorm_backward(dy, cache)
    assert np.isfinite(y).all() and np.isfinite(dx).all()
    k = 2 * len(CONSTANTS)  # the constant channels of batch 0
    want_y = np.ascontiguousarray(np.broadcast_to(beta[:k, None, None], (k,) + x.shape[2:]))
    assert_bitwise_equal(f"y of constant groups ({dtype.__name__})", y[0, :k], want_y)
    xhat = cache[0]
    zero = np.zeros_like(xhat[0, :k])
    assert_bitwise_equal("xhat of constant groups (so dgamma gets nothing)", np.abs(xhat[0, :k]), zero)

    dxhat = (dy[0, :k] * gamma[:k, None, None]).astype(np.float64).reshape(len(CONSTANTS), -1)
    want_dx = (dxhat - dxhat.mean(axis=-1, keepdims=True)) / np.sqrt(float(dtype(EPS)))
    rtol = RTOL32["groupnorm"] if dtype == np.float32 else RTOL64
    assert_close("dx of constant groups (closed form)", dx[0, :k].reshape(len(CONSTANTS), -1), want_dx, rtol)
    assert np.abs(dx[0, :k]).max() > 100, "a constant group's dx is ~ 1000 |dy gamma|, not zero"
    if dtype == np.float64:
        # torch is not exact here: its mean of a constant group can miss by an ulp, which rstd = 1000
        # amplifies (measured: y off by 6.3e-9 on the group of 123456.789, dgamma by 3.3e-9
        # relative). So y only where no group is constant, and not dgamma; dx and dbeta everywhere.
        y_t, (dx_t, _, dbeta_t) = torch_run("groupnorm", [x, gamma, beta], {}, dy)
        assert_close("y vs torch, ordinary groups (batch 0)", y[0, k:], y_t[0, k:], RTOL64)
        assert_close("y vs torch, ordinary groups (batch 1)", y[1], y_t[1], RTOL64)
        assert_close("dx vs torch", dx, dx_t, RTOL64)
        assert_close("dbeta vs torch", dbeta, dbeta_t, RTOL64)


def groupnorm_mp(x, gamma, beta, dy, groups, eps=EPS, dps=40):
    """y, dx, dgamma of GroupNorm and of sum(y * dy), each the float64 rounding of a `dps`-digit
    mpmath evaluation on the exact binary values of the inputs (40 digits absorb the 5 lost to
    x - mean at mean 1e4, spread 0.1)."""
    Bn, C = x.shape[:2]
    X = x.astype(np.float64).reshape(Bn, groups, -1)
    DY = dy.astype(np.float64).reshape(Bn, groups, -1)
    per = X.shape[-1] // (C // groups)  # pixels per channel
    Y, DX = np.empty_like(X), np.empty_like(X)
    dg = [mpmath.mpf(0)] * C
    with mpmath.workdps(dps):
        e = mpmath.mpf(float(eps))
        for b in range(Bn):
            for g in range(groups):
                chan = [g * (C // groups) + m // per for m in range(X.shape[-1])]
                xs = [mpmath.mpf(float(v)) for v in X[b, g]]
                dys = [mpmath.mpf(float(v)) for v in DY[b, g]]
                n = len(xs)
                mean = mpmath.fsum(xs) / n
                xc = [v - mean for v in xs]
                rstd = 1 / mpmath.sqrt(mpmath.fsum(v * v for v in xc) / n + e)
                xhat = [v * rstd for v in xc]
                dxhat = [d * mpmath.mpf(float(gamma[c])) for d, c in zip(dys, chan)]
                m1 = mpmath.fsum(dxhat) / n
                m2 = mpmath.fsum(a * h for a, h in zip(dxhat, xhat)) / n
                for j in range(n):
                    c = chan[j]
                    Y[b, g, j] = float(xhat[j] * mpmath.mpf(float(gamma[c])) + mpmath.mpf(float(beta[c])))
                    DX[b, g, j] = float(rstd * (dxhat[j] - m1 - xhat[j] * m2))
                    dg[c] += dys[j] * xhat[j]
    return Y.reshape(x.shape), DX.reshape(x.shape), np.array([float(v) for v in dg])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_groupnorm_large_mean_small_spread(dtype, rng):
    """Groups of mean +-1e4 and spread 0.1, against mpmath on the same (rounded) inputs.

    x - mean(x) is exact here (Sterbenz: both within a factor 2), and the second centring pass
    removes the ulp by which the rounded mean misses, so what remains is ordinary rounding on the
    centred values: bound 10 u (u = 6e-8, 1.1e-16). Measured, in u: float32 y 1.7, dx 1.1,
    dgamma 2.1; float64 1.5, 1.7, 3.0. The one-pass variance E[x^2] - E[x]^2 in the same
    precision fails this by orders of magnitude (asserted below; measured 1.5e9 u and 2e10 u:
    y off by O(1) or more)."""
    C, groups = 64, G
    x = 1e4 * rng.choice([-1.0, 1.0], (2, groups, 1, 1, 1)) + 0.1 * rng.standard_normal((2, groups, 2, 3, 3))
    x = x.reshape(2, C, 3, 3).astype(dtype)
    gamma, beta = (rng.standard_normal(C).astype(dtype) for _ in range(2))
    dy = rng.standard_normal(x.shape).astype(dtype)
    y, cache = conv.groupnorm_forward(x, gamma, beta)
    dx, dgamma, _ = conv.groupnorm_backward(dy, cache)
    want = groupnorm_mp(x, gamma, beta, dy, groups)
    rtol = 10 * float(np.finfo(dtype).eps) / 2  # 10 u
    for what, got, w in zip(("y", "dx", "dgamma"), (y, dx, dgamma), want):
        assert got.dtype == dtype
        assert_close(f"{what} (mean 1e4, spread 0.1, {dtype.__name__})", got, w, rtol)

    # the bound has teeth: the one-pass variance in the same precision is far outside it
    xg = x.reshape(2, groups, -1)
    m = xg.mean(axis=-1, keepdims=True, dtype=np.float64).astype(dtype)
    var1 = np.maximum((xg * xg).mean(axis=-1, keepdims=True) - m * m, 0)
    y1 = ((xg - m) / np.sqrt(var1 + dtype(EPS))).reshape(x.shape) * gamma[:, None, None] + beta[:, None, None]
    assert gap(y1, want[0]) > 100 * rtol, f"one-pass variance error {gap(y1, want[0]):.1e} is inside {rtol:.1e}"


# ---------------------------------------------------------------------------------------
# 2. hard cases: swish's ends, every floating-point error raised

ENDS = [-1000.0, -750.0, -745.0, -104.0, -100.0, -89.0, -30.0, -17.0, -0.0, 0.0,
        17.0, 30.0, 89.0, 100.0, 104.0, 745.0, 750.0, 1000.0]


def swish_mp(x):
    """(swish(x), swish'(x)) at the exact binary value of x, 40 digits."""
    with mpmath.workdps(40):
        X = mpmath.mpf(float(x))
        s = 1 / (1 + mpmath.exp(-X))
        return X * s, s * (1 + X * (1 - s))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_swish_ends_raise_nothing(dtype, rng):
    """x up to +-1000 (exp(1000) overflows both dtypes; exp(-1000) underflows them): no overflow,
    invalid or division warning with np.errstate(all='raise') (underflow of e^-|x| is the right
    value and is allowed inside the layer only). Exact ends: swish(-1000) = 0, swish(1000) = 1000,
    swish'(-1000) = 0, swish'(1000) = 1; swish(0) = 0, swish'(0) = 1/2. Everything against mpmath,
    elementwise, within 4 ulp of the true value plus, where sigmoid(x) is subnormal, the absolute
    step |x| * smallest_subnormal (measured <= 2.3 ulp in float64, 1.7 in float32; in the subnormal
    range <= 0.49 of the step)."""
    x = np.array(ENDS, dtype=dtype)
    dy = rng.standard_normal(x.shape).astype(dtype)
    with np.errstate(all="raise"):
        y, cache = conv.swish_forward(x)
        (dx,) = conv.swish_backward(dy, cache)
        (d1,) = conv.swish_backward(np.ones_like(x), cache)
    assert y.dtype == dx.dtype == dtype and np.isfinite(y).all() and np.isfinite(dx).all()
    i = {v: ENDS.index(v) for v in (-1000.0, 1000.0, 0.0)}
    assert y[i[-1000.0]] == 0 and y[i[1000.0]] == 1000 and y[i[0.0]] == 0
    assert d1[i[-1000.0]] == 0 and d1[i[1000.0]] == 1 and d1[i[0.0]] == 0.5
    ft = np.finfo(dtype)
    for xi, yi, di in zip(x, y, d1):
        for what, got, want in (("swish", yi, swish_mp(xi)[0]), ("swish'", di, swish_mp(xi)[1])):
            ulp = float(np.spacing(dtype(abs(float(want)))))
            bound = 4 * ulp + abs(float(xi)) * float(ft.smallest_subnormal)
            err = float(abs(mpmath.mpf(float(got)) - want))
            assert err <= bound, f"{what}({float(xi)!r}) = {float(got)!r}, want {float(want)!r}: {err / ulp:.1f} ulp"
    assert_close("dx = dy * swish'", dx, dy.astype(np.float64) * d1, float(ft.eps))
    if dtype == np.float64:  # and torch agrees on the ends too
        _, (dx_t,) = torch_run("swish", [x], {}, dy)
        assert_close("dx vs torch at the ends", dx, dx_t, RTOL64)


# ---------------------------------------------------------------------------------------
# 3. the C++ conv2d vs its NumPy reference vs torch, every code path
# (each test once per instruction-set path: conftest.kernel_path)

# (B, C, Co, (Hi, Wi), (kh, kw), stride, padding): each family of the codebook and each code path of
# csrc/conv.cpp on every kernel path (vector widths W = 4..16). C and Co are not multiples of any
# vector width, and C > 8 makes several channel blocks (kCB = 8) in the dw and the stride-2 dx.
KERNEL_CASES = [
    (3, 19, 13, (9, 67), (3, 3), 1, 1),  # 3x3 pad 1: per-row products, dw on padded rows
    (2, 11, 13, (16, 16), (3, 3), 1, 1),  # 16x16: per-row forward (W <= 8)
    (2, 19, 5, (8, 8), (3, 3), 1, 1),  # 8x8: one product per tile, columns past each row dropped
    (1, 5, 7, (5, 4), (3, 3), 1, 1),  # B = 1, rows shorter than a vector
    (3, 5, 7, (6, 9), (3, 3), 1, 0),  # 3x3 unpadded
    (3, 5, 7, (9, 8), (3, 3), 2, 1),  # 3x3 stride 2, symmetric padding
    (2, 7, 3, (1, 9), (3, 3), 1, 1),  # one row: every tap row but the centre is padding
    (2, 5, 7, (1, 1), (3, 3), 1, 1),  # a 1x1 image: only the centre tap sees it
    (2, 5, 7, (1, 1), (1, 1), 1, 1),  # ... a 3x3 output that is b on the border
    (2, 5, 7, (1, 1), (4, 2), 1, (2, 1, 0, 1)),  # ... every side padded differently
    (3, 19, 13, (8, 8), (3, 3), 2, DOWN),  # the Downsample: im2col, col2im for dx
    (2, 5, 7, (9, 35), (3, 3), 2, DOWN),  # ... odd height, a width past 2 vectors
    (3, 19, 13, (7, 37), (1, 1), 1, 0),  # 1x1
    (2, 5, 7, (7, 6), (1, 1), 2, 0),  # 1x1 strided
    (2, 5, 7, (5, 20), (1, 1), 1, 1),  # 1x1 padded: its stride-1 dx crops (negative padding)
    (2, 9, 6, (7, 40), (2, 3), 1, (2, 0, 1, 3)),  # every side different, stride-1 dx padded (-1, 1, 1, -1)
    (1, 6, 5, (9, 7), (4, 2), 2, (2, 1, 0, 1)),  # non-square kernel, stride 2, odd sizes
    # Co >= W on every path (W <= 16): Co = 37 = 2 vectors + 5 columns on AVX-512, rounded up to
    # whole vectors in the dw; two channel blocks (kCB = 8), one partial
    (2, 11, 37, (8, 8), (3, 3), 1, 1),  # padded-row tiles taken as rows of Wp pixels (zero pixels of dy)
    (2, 9, 35, (20, 67), (3, 3), 1, 1),  # several row tiles, chunks of kDwChunk = 256 pixels
    (2, 9, 35, (9, 35), (3, 3), 2, DOWN),  # the Downsample: im2col tiles
    (2, 9, 35, (7, 37), (1, 1), 1, 0),  # 1x1
    # AVX-512's 12-row tiles of the stride-1 products: Co = 28 = 12 + 12 + 4, the dx's 16 rows = 12 + 4
    (2, 16, 28, (6, 35), (3, 3), 1, 1),
]


def kernel_case_id(c):
    B, C, Co, (Hi, Wi), (kh, kw), s, p = c
    return f"B{B}-{C}to{Co}-{Hi}x{Wi}-k{kh}x{kw}-s{s}-p{'x'.join(map(str, p)) if isinstance(p, tuple) else p}"


def kernel_inputs(case, rng, dtype):
    B, C, Co, (Hi, Wi), (kh, kw), stride, padding = case
    f = rng.standard_normal
    x, w, b = f((B, C, Hi, Wi)), f((Co, C, kh, kw)) / np.sqrt(C * kh * kw), f(Co)
    kwargs = {"stride": stride, "padding": padding}
    y, _ = conv.conv2d_forward_numpy(x, w, b, **kwargs)
    return [a.astype(dtype) for a in (x, w, b)], kwargs, f(y.shape).astype(dtype)


def kernel_run_on_1_2_5_threads(inputs, kwargs, dy):
    """y and the gradients on 1 thread, asserted bitwise the same on 2 and 5: the tasks depend on
    the shapes only, each output element is summed by one task in one order. 5 threads: the blocks
    that follow the thread count (the dw's and the forward's output channels) change, and the
    backward's dw and dx tasks share one loop in another interleaving."""
    out = {}
    for n in (1, 2, 5):
        with forced_threads(n):  # these shapes are below the size at which a call takes threads
            y, grads, _ = pyvf_run("conv2d", inputs, kwargs, dy)
        out[n] = [y, *grads]
    for n in (2, 5):
        for name, a, b in zip(("y", "dx", "dw", "db"), out[1], out[n]):
            assert_bitwise_equal(f"{name}, 1 vs {n} threads", a, b)
    return out[1][0], out[1][1:]


@pytest.mark.usefixtures("kernel_path")
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("case", KERNEL_CASES, ids=kernel_case_id)
def test_conv2d_kernel(case, dtype, rng):
    """float64: the kernel, its NumPy reference and torch agree to RTOL64 (the same sums in other
    orders; measured <= 2.5e-15 on the baseline and avx2 paths). float32: the kernel against torch
    float64 on the same float32 inputs, within RTOL32["conv2d"] (its float32 arithmetic only)."""
    inputs, kwargs, dy = kernel_inputs(case, rng, dtype)
    y, grads = kernel_run_on_1_2_5_threads(inputs, kwargs, dy)
    assert y.dtype == dtype and all(g.dtype == dtype for g in grads)
    runs = {"torch": torch_run("conv2d", inputs, kwargs, dy)}
    if dtype == np.float64:
        y_n, cache_n = conv.conv2d_forward_numpy(*inputs, **kwargs)
        runs["numpy"] = (y_n, conv.conv2d_backward_numpy(dy, cache_n))
    rtol = RTOL64 if dtype == np.float64 else RTOL32["conv2d"]
    for name, (y_r, grads_r) in runs.items():
        compare("conv2d", y, grads, y_r, grads_r, rtol, f"{kernel_case_id(case)} {np.dtype(dtype).name} vs {name}")
