"""Tests of the codebook's image layers (docs/math.md §4): conv2d, GroupNorm, swish, nearest x2
upsampling and the 2D attention block (pyvf/nn/conv.py).

Each layer is a pair `x_forward(...) -> (out, cache)`, `x_backward(dout, cache) -> (dx, *dparams)`.
The tests: every layer against PyTorch in float64 under a random upstream gradient (output and
every gradient); float32 against float64 on the same inputs; the parity traps shown to matter
(the Downsample's (0,1,0,1) padding, GroupNorm eps 1e-6, the grouping of channels, a transposed
kernel, upsample's summing backward); hard numerical cases (constant groups, groups of mean 1e4
and spread 0.1 against mpmath, swish at +-1000 with every floating-point error raised, a 1x1
image); float64 central finite differences; dtypes; strided inputs; bad arguments. Then the C++
kernels themselves (section 6): the fast conv2d against its plain-loop twin, NumPy and torch on
every shape family and code path, 1 vs 2 vs 5 threads bitwise (forced_threads: every
shape on the threads), float32 against float64, sizes refused;
the fused GroupNorm + swish.

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

import pyvf
from pyvf.nn.layers import matmul
from pyvf import _core
from pyvf.nn import conv

from conftest import assert_bitwise_equal, assert_close, forced_threads

# every test here runs once per kernel path this machine executes (conftest.kernel_path): conv2d,
# GroupNorm and swish are C++ kernels (csrc/conv.cpp, csrc/groupnorm.cpp)
pytestmark = pytest.mark.usefixtures("kernel_path")

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
    # dot products of K = C*kh*kw <= 45 terms (forward, dx), dw summed over B*Ho*Wo <= 189
    # products, db over as many: about sqrt(n) u normwise (u = 6e-8). Measured <= 2.2e-7 (y of
    # the odd Downsample case); 1e-6 = 4.5x margin.
    "conv2d": 1e-6,
    # group mean and variance over <= 3 * 15 = 45 numbers, a reciprocal square root, the backward's
    # two group means, dgamma/dbeta summed over B*Hi*Wi. Groups of variance ~ eps are no worse
    # conditioned (eps bounds rstd by 1000). Measured <= 1.1e-7 (y); 4e-7 = 3.6x margin.
    "groupnorm": 4e-7,
    # elementwise: exp, one division, a few products. Measured <= 5.6e-8 (dx); 2e-7 = 3.6x margin.
    "swish": 2e-7,
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
    if name == "conv2d":
        (kh, kw), stride, padding, (Hi, Wi) = dims
        inputs = [f(B, CI, Hi, Wi), f(CO, CI, kh, kw) / np.sqrt(CI * kh * kw), f(CO)]
        kwargs = {"stride": stride, "padding": padding}
    elif name == "groupnorm":
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
    # conv2d: (kh, kw), stride, padding, (Hi, Wi)
    ("conv2d", (1, 1), 1, 0, (7, 6)),  # the 1x1 fast path (nin_shortcut, quant_conv, q/k/v)
    ("conv2d", (1, 1), 2, 0, (7, 6)),  # 1x1 through the im2col path: stride
    ("conv2d", (1, 1), 1, 1, (5, 4)),  # ... and padding: the border is bias only
    ("conv2d", (3, 3), 1, 1, (7, 6)),  # ResnetBlock conv1/conv2, conv_in/conv_out, Upsample's conv
    ("conv2d", (3, 3), 1, 1, (8, 8)),
    ("conv2d", (3, 3), 1, 0, (6, 9)),
    ("conv2d", (3, 3), 2, 1, (9, 8)),
    ("conv2d", (3, 3), 2, DOWN, (8, 8)),  # the Downsample, even sides (the real case)
    ("conv2d", (3, 3), 2, DOWN, (7, 10)),  # ... odd and even
    ("conv2d", (3, 3), 1, (2, 0, 1, 3), (6, 5)),  # every side different: the order of the 4-tuple
    ("conv2d", (4, 2), 1, 0, (7, 6)),  # non-square kernel: a transposed kernel cannot even run
    ("conv2d", (4, 2), 2, 1, (9, 7)),
    ("conv2d", (4, 2), 2, DOWN, (8, 5)),
    ("groupnorm", 64, 5, 3),  # 2 channels per group
    ("groupnorm", 96, 4, 4),  # 3 channels per group
    ("swish",),
    ("upsample", 5, 4),
    ("upsample", 1, 3),
    ("attnblock", 64, 5, 3),  # P = 15 positions, C**-0.5 = 1/8
]


def case_id(c):
    return "-".join("x".join(map(str, p)) if isinstance(p, tuple) else str(p) for p in c)


# ---------------------------------------------------------------------------------------
# 1. every layer vs torch, float64, random upstream gradient


@pytest.mark.parametrize("case", CASES, ids=case_id)
def test_matches_torch_float64(case, rng):
    name, inputs, kwargs, dy = build(case, rng, np.float64)
    y, grads, _ = pyvf_run(name, inputs, kwargs, dy)
    y_t, grads_t = torch_run(name, inputs, kwargs, dy)
    compare(name, y, grads, y_t, grads_t, RTOL64, f"{case_id(case)} f64")


def gap(got, want):
    return np.abs(got - want).max() / np.abs(want).max()


def test_conv2d_traps_have_teeth(rng):
    """The Downsample case (docs/math.md §4), against the mistakes that still run: symmetric padding 1
    (same output size on even images), the pad on the top-left corner instead, a transposed 3x3
    kernel. Each is an O(1) change of y, far outside RTOL64 (measured gaps 1.06, 1.06, 0.73)."""
    _, (x, w, b), kwargs, _ = build(("conv2d", (3, 3), 2, DOWN, (8, 8)), rng, np.float64)
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


def test_upsample_backward_sums_the_block():
    """dy = 1 everywhere gives dx = 4 exactly (an averaging backward would give 1); a dy that is
    1 on one pixel of each block picks that pixel out."""
    x = np.arange(2 * 3 * 4 * 5, dtype=np.float64).reshape(2, 3, 4, 5)
    y, cache = conv.upsample_nearest2x_forward(x)
    assert_bitwise_equal("y[2u+i, 2v+j] = x[u, v]", y[:, :, 1::2, ::2], x)
    (dx,) = conv.upsample_nearest2x_backward(np.ones_like(y), cache)
    assert_bitwise_equal("dx of dy = 1", dx, np.full_like(x, 4))
    dy = np.zeros_like(y)
    dy[:, :, 1::2, ::2] = y[:, :, 1::2, ::2]
    assert_bitwise_equal("dx of a one-pixel-per-block dy", conv.upsample_nearest2x_backward(dy, cache)[0], x)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_upsample_kernel_is_bitwise_numpy_on_any_threads(rng, dtype):
    """The kernels on 1 and 3 threads (rows past the parallel threshold, an odd width): y is
    every pixel copied into its block (NumPy's repeat), dx the NumPy sum in its order,
    (d00 + d01) + (d10 + d11); dy spread over 1e-20..1e20 so that another order of the four terms
    rounds differently (checked: the order d00 + d10 + d01 + d11 gives other bits); a
    non-contiguous x and dy are accepted."""
    x = rng.standard_normal((2, 33, 40, 31)).astype(dtype)
    dy = (rng.standard_normal((2, 33, 80, 62)) * 10.0 ** rng.uniform(-20, 20, (2, 33, 80, 62))).astype(dtype)
    want_y = x.repeat(2, axis=3).repeat(2, axis=2)
    (want_dx,) = conv.upsample_nearest2x_backward_numpy(dy, (x.shape, x.dtype))
    d = dy.reshape(2, 33, 40, 2, 31, 2)
    other = (d[:, :, :, 0, :, 0] + d[:, :, :, 1, :, 0]) + (d[:, :, :, 0, :, 1] + d[:, :, :, 1, :, 1])
    assert not np.array_equal(other, want_dx)
    for n in (1, 3):
        with pyvf.threads(n):
            y, cache = conv.upsample_nearest2x_forward(x)
            assert_bitwise_equal(f"y, {n} threads", y, want_y)
            assert_bitwise_equal(f"dx, {n} threads", conv.upsample_nearest2x_backward(dy, cache)[0], want_dx)
            xt = np.asfortranarray(x)
            assert_bitwise_equal(f"y of a Fortran-order x, {n} threads", conv.upsample_nearest2x_forward(xt)[0],
                                 want_y)
            assert_bitwise_equal(f"dx of a Fortran-order dy, {n} threads",
                                 conv.upsample_nearest2x_backward(np.asfortranarray(dy), cache)[0], want_dx)


# ---------------------------------------------------------------------------------------
# 2. float32 vs float64 on the same inputs; dtypes kept


@pytest.mark.parametrize("case", CASES, ids=case_id)
def test_float32_matches_float64(case, rng):
    name, inputs, kwargs, dy = build(case, rng, np.float32)
    y, grads, cache = pyvf_run(name, inputs, kwargs, dy)
    assert y.dtype == np.float32 and all(g.dtype == np.float32 for g in grads), \
        f"{name}: y {y.dtype}, grads {[g.dtype for g in grads]}"
    for g, a in zip(grads, inputs):
        assert g.shape == a.shape
    for a in float_arrays(cache):
        assert a.dtype == np.float32, f"{name} caches a {a.dtype} array {a.shape}: a silent upcast"
    y_t, grads_t = torch_run(name, inputs, kwargs, dy)  # float64 on the float32 values
    compare(name, y, grads, y_t, grads_t, RTOL32[name], f"{case_id(case)} f32")


def float_arrays(obj):
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind == "f":
            yield obj
    elif isinstance(obj, (tuple, list)):
        for o in obj:
            yield from float_arrays(o)


def strided(a):
    """The same values as a view with stride 2 on the last axis."""
    big = np.zeros(a.shape[:-1] + (2 * a.shape[-1],), dtype=a.dtype)
    big[..., ::2] = a
    return big[..., ::2]


@pytest.mark.parametrize("case", [c for c in CASES if c[0] != "conv2d" or c[3] in (0, DOWN)], ids=case_id)
def test_strided_inputs(case, rng):
    """Non-contiguous inputs and upstream gradients give the same results (reductions may reorder)."""
    name, inputs, kwargs, dy = build(case, rng, np.float64)
    y, grads, _ = pyvf_run(name, inputs, kwargs, dy)
    y_s, grads_s, _ = pyvf_run(name, [strided(a) for a in inputs], kwargs, strided(dy))
    compare(name, y_s, grads_s, y, grads, RTOL64, f"{case_id(case)} strided")


# ---------------------------------------------------------------------------------------
# 3. hard cases: GroupNorm

CONSTANTS = [0.0, 0.1, -7.77, 1e4 + 0.3, 123456.789]  # 0.1, 1e4+0.3, ... are not dyadic


def constant_group_images(rng, dtype):
    """(2, 64, 3, 4) images, groups of 2 channels; in batch 0 groups 0..4 are constant (both
    channels, every pixel) at the CONSTANTS, the rest ordinary."""
    x = group_images(rng, (2, 64, 3, 4))
    for g, c in enumerate(CONSTANTS):
        x[0, 2 * g:2 * g + 2] = c
    return x.astype(dtype)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_groupnorm_constant_groups(dtype, rng):
    """A constant group has var = 0: xhat = 0, so y == beta exactly (bitwise), and it adds exactly
    nothing to dgamma. Its gradient is NOT zero: d var / dx = 0 there, so
    dx = rstd * (dxhat - mean_g(dxhat)), dxhat = dy * gamma, rstd = 1/sqrt(eps) = 1000: finite.
    Checked against that closed form, and in float64 against torch."""
    x = constant_group_images(rng, dtype)
    C = x.shape[1]
    gamma, beta = (rng.standard_normal(C).astype(dtype) for _ in range(2))
    dy = rng.standard_normal(x.shape).astype(dtype)
    y, cache = conv.groupnorm_forward(x, gamma, beta)
    dx, dgamma, dbeta = conv.groupnorm_backward(dy, cache)
    assert np.isfinite(y).all() and np.isfinite(dx).all()
    k = 2 * len(CONSTANTS)  # the constant channels of batch 0
    want_y = np.ascontiguousarray(np.broadcast_to(beta[:k, None, None], (k,) + x.shape[2:]))
    assert_bitwise_equal(f"y of constant groups ({dtype.__name__})", y[0, :k], want_y)
    x_c, stats, _, G = cache  # xhat = ((x - mean) - r) * rstd per group: the kernel's operations
    g = x_c.reshape(x_c.shape[0], G, -1)
    xhat = (((g - stats[..., 0:1]) - stats[..., 1:2]) * stats[..., 2:3]).reshape(x_c.shape)
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


def groupnorm_within_10u_of_mpmath(x, groups, label, rng):
    """GroupNorm of x (random gamma, beta, dy) forward and backward: y, dx and dgamma within 10 u
    (u the dtype's unit roundoff, normwise) of mpmath on the same rounded inputs. -> (gamma, beta,
    mpmath's (y, dx, dgamma), the bound)."""
    dtype = x.dtype.type
    gamma, beta = (rng.standard_normal(x.shape[1]).astype(dtype) for _ in range(2))
    dy = rng.standard_normal(x.shape).astype(dtype)
    y, cache = conv.groupnorm_forward(x, gamma, beta)
    dx, dgamma, _ = conv.groupnorm_backward(dy, cache)
    want = groupnorm_mp(x, gamma, beta, dy, groups)
    rtol = 10 * float(np.finfo(dtype).eps) / 2
    for what, got, w in zip(("y", "dx", "dgamma"), (y, dx, dgamma), want):
        assert got.dtype == dtype
        assert_close(f"{what} ({label}, {dtype.__name__})", got, w, rtol)
    return gamma, beta, want, rtol


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
    gamma, beta, want, rtol = groupnorm_within_10u_of_mpmath(x, groups, "mean 1e4, spread 0.1", rng)

    # the bound has teeth: the one-pass variance in the same precision is far outside it
    xg = x.reshape(2, groups, -1)
    m = xg.mean(axis=-1, keepdims=True, dtype=np.float64).astype(dtype)
    var1 = np.maximum((xg * xg).mean(axis=-1, keepdims=True) - m * m, 0)
    y1 = ((xg - m) / np.sqrt(var1 + dtype(EPS))).reshape(x.shape) * gamma[:, None, None] + beta[:, None, None]
    assert gap(y1, want[0]) > 100 * rtol, f"one-pass variance error {gap(y1, want[0]):.1e} is inside {rtol:.1e}"


@pytest.mark.parametrize("dtype, spread", [(np.float32, 1e20), (np.float32, 1e36),
                                           (np.float64, 1e160), (np.float64, 1e300)])
def test_groupnorm_spread_beyond_the_dtypes_variance(dtype, spread, rng):
    """Groups whose variance overflows the dtype (float32: spread beyond ~1.8e19) or whose sum of
    squares overflows double too (float64 beyond ~1e154), though every y, dx and dgamma is of
    ordinary size: the kernel computes rstd in double, rescaled by a power of two where needed
    (it refused the group before, naming a float64 overflow even for float32). Against mpmath on
    the same rounded inputs, the bound of test_groupnorm_large_mean_small_spread (10 u)."""
    x = (spread * rng.standard_normal((2, 64, 3, 3))).astype(dtype)
    groupnorm_within_10u_of_mpmath(x, G, f"spread {spread:g}", rng)


@pytest.mark.parametrize("shape", [(2, 64, 0, 3), (2, 0, 4, 4)])
def test_groupnorm_of_empty_groups(shape, rng):
    """Groups with no elements (no pixels; no channels, 32 groups of 0): an empty y and dx, dgamma
    and dbeta 0 (sums of nothing). They were refused as a float64 overflow of the variance."""
    x = np.zeros(shape, np.float32)
    gamma, beta = (rng.standard_normal(shape[1]).astype(np.float32) for _ in range(2))
    y, cache = conv.groupnorm_forward(x, gamma, beta)
    assert y.shape == shape
    dx, dgamma, dbeta = conv.groupnorm_backward(np.zeros(shape, np.float32), cache)
    assert dx.shape == shape and not dgamma.any() and not dbeta.any()


def test_groupnorm_eps_beyond_the_dtype_is_refused():
    with pytest.raises(ValueError, match="eps = 1e\\+300 overflows x's dtype float32"):
        conv.groupnorm_forward(np.ones((1, 32, 2, 2), np.float32), np.ones(32, np.float32),
                               np.zeros(32, np.float32), eps=1e300)


# ---------------------------------------------------------------------------------------
# 3. hard cases: swish's ends, every floating-point error raised

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
# 3. hard cases: conv on a 1x1 image


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_conv2d_one_pixel_image(dtype, rng):
    """A 1x1 image: 3x3 pad 1 sees only the centre tap (y = w[:, :, 1, 1] @ x + b); 1x1 pad 1 gives
    a 3x3 output that is b on the border; the Downsample's 3x3 stride 2 on the padded 2x2 image
    does not fit and raises. Against torch, and the centre tap by hand."""
    x = rng.standard_normal((2, CI, 1, 1)).astype(dtype)
    rtol = RTOL32["conv2d"] if dtype == np.float32 else RTOL64
    for (kh, kw), padding in (((3, 3), 1), ((1, 1), 1), ((4, 2), (2, 1, 0, 1))):
        w = rng.standard_normal((CO, CI, kh, kw)).astype(dtype)
        b = rng.standard_normal(CO).astype(dtype)
        y, cache = conv.conv2d_forward(x, w, b, padding=padding)
        dy = rng.standard_normal(y.shape).astype(dtype)
        grads = conv.conv2d_backward(dy, cache)
        y_t, grads_t = torch_run("conv2d", [x, w, b], {"padding": padding}, dy)
        compare("conv2d", y, grads, y_t, grads_t, rtol, f"1x1 image, kernel {kh}x{kw}, padding {padding}")
        if (kh, kw) == (3, 3):
            assert_close("centre tap", y[:, :, 0, 0], x[:, :, 0, 0] @ w[:, :, 1, 1].T + b, rtol)
        if (kh, kw) == (1, 1):
            border = np.ones((3, 3), bool)
            border[1, 1] = False
            assert_bitwise_equal("border = b", y[:, :, border], np.broadcast_to(b[:, None], (2, CO, 8)).copy())
    w = rng.standard_normal((CO, CI, 3, 3)).astype(dtype)
    with pytest.raises(ValueError, match="does not fit"):
        conv.conv2d_forward(x, w, rng.standard_normal(CO).astype(dtype), stride=2, padding=DOWN)


# ---------------------------------------------------------------------------------------
# 4. float64 central finite differences of f = sum(y * dy), one direction per element

# conv2d is linear in each input, so the central difference has no truncation error, only
# rounding ~ u |f| / h; GroupNorm adds h^2/6 |f'''| for groups of O(1) spread. Both ~1e-11..1e-10
# at h = 1e-5. Measured <= 1.3e-10 relative to the largest gradient entry (conv2d 4.8e-11,
# groupnorm 1.3e-10); 1e-8 is 75x that and still 8 orders below an O(1) gradient bug.
FD_STEP = 1e-5
FD_RTOL = 1e-8


def fd_check(name, inputs, kwargs, dy):
    fwd, bwd, _, grad_names = LAYERS[name]
    f = lambda args: float((fwd(*args, **kwargs)[0] * dy).sum())
    grads = bwd(dy, fwd(*inputs, **kwargs)[1])
    for k, (gname, g) in enumerate(zip(grad_names, grads)):
        fd = np.empty_like(inputs[k])
        for i in range(fd.size):
            plus, minus = [a.copy() for a in inputs], [a.copy() for a in inputs]
            plus[k].reshape(-1)[i] += FD_STEP
            minus[k].reshape(-1)[i] -= FD_STEP
            fd.reshape(-1)[i] = (f(plus) - f(minus)) / (2 * FD_STEP)
        assert_close(f"{name} {gname} (finite differences)", g, fd, FD_RTOL)


def test_finite_differences_conv2d_downsample(rng):
    f = rng.standard_normal
    x, w, b = f((2, 2, 5, 4)), f((3, 2, 3, 3)), f(3)
    y, _ = conv.conv2d_forward(x, w, b, stride=2, padding=DOWN)
    fd_check("conv2d", [x, w, b], {"stride": 2, "padding": DOWN}, f(y.shape))


def test_finite_differences_groupnorm(rng):
    f = rng.standard_normal
    x = rng.uniform(-3, 3, (2, 4, 1, 1)) + rng.uniform(0.5, 2, (2, 4, 1, 1)) * f((2, 4, 3, 2))
    fd_check("groupnorm", [x, f(4), f(4)], {"groups": 2}, f(x.shape))


# ---------------------------------------------------------------------------------------
# 5. bad arguments: TypeError for a dtype, ValueError for a shape or a value, naming the argument

f64 = lambda *s: np.zeros(s)
BAD = [
    ("x 3-D", lambda: conv.conv2d_forward(f64(5, 4, 4), f64(7, 5, 3, 3), f64(7)), ValueError, "x must be 4-D"),
    ("w 3-D", lambda: conv.conv2d_forward(f64(1, 5, 4, 4), f64(7, 5, 3), f64(7)), ValueError, "w must be 4-D"),
    ("channels", lambda: conv.conv2d_forward(f64(1, 5, 4, 4), f64(7, 4, 3, 3), f64(7)), ValueError,
     r"w has 4 input channels \(w.shape\[1\]\) but x has 5"),
    ("b shape", lambda: conv.conv2d_forward(f64(1, 5, 4, 4), f64(7, 5, 3, 3), f64(5)), ValueError,
     r"b must have shape \(7,\)"),
    ("x int", lambda: conv.conv2d_forward(np.zeros((1, 5, 4, 4), int), f64(7, 5, 3, 3), f64(7)), TypeError,
     "x must be float32 or float64"),
    ("w float32", lambda: conv.conv2d_forward(f64(1, 5, 4, 4), f64(7, 5, 3, 3).astype(np.float32), f64(7)), TypeError,
     "w is float32 but x is float64"),
    ("padding 3", lambda: conv.conv2d_forward(f64(1, 5, 4, 4), f64(7, 5, 3, 3), f64(7), padding=(0, 1, 0)), ValueError,
     "padding must be"),
    ("padding < 0", lambda: conv.conv2d_forward(f64(1, 5, 4, 4), f64(7, 5, 3, 3), f64(7), padding=-1), ValueError,
     "padding must be non-negative"),
    ("stride 0", lambda: conv.conv2d_forward(f64(1, 5, 4, 4), f64(7, 5, 3, 3), f64(7), stride=0), ValueError, "stride"),
    # beyond int64, pybind11 refused the call with its C++ signatures instead of naming the argument
    ("stride 2^63", lambda: conv.conv2d_forward(f64(1, 5, 4, 4), f64(7, 5, 3, 3), f64(7), stride=2**63), ValueError,
     "stride must be a positive int of at most 2"),
    ("padding 2^63", lambda: conv.conv2d_forward(f64(1, 5, 4, 4), f64(7, 5, 3, 3), f64(7), padding=(0, 2**63, 0, 0)),
     ValueError, "padding must be at most 2"),
    ("no fit", lambda: conv.conv2d_forward(f64(1, 5, 2, 4), f64(7, 5, 3, 3), f64(7)), ValueError, "does not fit"),
    ("dy shape", lambda: conv.conv2d_backward(f64(1, 7, 3, 3),
                                              conv.conv2d_forward(f64(1, 5, 4, 4), f64(7, 5, 3, 3), f64(7))[1]),
     ValueError, "dy must be"),
    ("gn groups", lambda: conv.groupnorm_forward(f64(1, 48, 2, 2), f64(48), f64(48)), ValueError,
     "groups=32 does not divide the 48 channels of x"),
    ("gn x 2-D", lambda: conv.groupnorm_forward(f64(2, 64), f64(64), f64(64)), ValueError, "x must be 4-D"),
    ("gn gamma", lambda: conv.groupnorm_forward(f64(1, 64, 2, 2), f64(32), f64(64)), ValueError,
     "gamma must have shape"),
    ("gn int", lambda: conv.groupnorm_forward(np.zeros((1, 64, 2, 2), np.int32), f64(64), f64(64)), TypeError,
     "x must be float32 or float64"),
    ("gn beta f32", lambda: conv.groupnorm_forward(f64(1, 64, 2, 2), f64(64), f64(64).astype(np.float32)), TypeError,
     "beta is float32"),
    ("attn wk shape", lambda: conv.attnblock_forward(f64(1, 64, 2, 2), f64(64), f64(64), f64(64, 64, 1, 1), f64(64),
                                                     f64(32, 64, 1, 1), f64(32), f64(64, 64, 1, 1), f64(64),
                                                     f64(64, 64, 1, 1), f64(64)), ValueError,
     r"wk must have shape \(64, 64, 1, 1\)"),
    ("gn eps inf", lambda: conv.groupnorm_forward(f64(1, 64, 2, 2), f64(64), f64(64), eps=float("inf")), ValueError,
     "eps must be finite"),
    ("swish int", lambda: conv.swish_forward(np.arange(3)), TypeError, "x must be float32 or float64"),
    ("swish dy f32", lambda: conv.swish_backward(f64(3).astype(np.float32), conv.swish_forward(f64(3))[1]), TypeError,
     "dy is float32"),
    ("upsample dy f32", lambda: conv.upsample_nearest2x_backward(
        f64(1, 2, 2, 2).astype(np.float32), conv.upsample_nearest2x_forward(f64(1, 2, 1, 1))[1]), TypeError,
     "dy is float32"),
    ("conv dy f32", lambda: conv.conv2d_backward(f64(1, 7, 2, 2).astype(np.float32),
                                                 conv.conv2d_forward(f64(1, 5, 4, 4), f64(7, 5, 3, 3), f64(7))[1]),
     TypeError, "dy is float32"),
    ("upsample 3-D", lambda: conv.upsample_nearest2x_forward(f64(3, 4, 4)), ValueError, "x must be 4-D"),
    ("upsample f16", lambda: conv.upsample_nearest2x_forward(f64(1, 3, 4, 4).astype(np.float16)), TypeError,
     "x must be float32 or float64"),
]


def test_swish_keeps_a_0d_array_0d():
    """The C++ swish takes C-contiguous arrays; a 0-d one is passed as is (np.ascontiguousarray
    would make it 1-d)."""
    y, cache = conv.swish_forward(np.array(0.5))
    (dx,) = conv.swish_backward(np.array(1.0), cache)
    assert y.shape == dx.shape == ()
    assert_close("swish(0.5)", y, np.array(0.5 / (1 + np.exp(-0.5))), RTOL64)


@pytest.mark.parametrize("call, exc, match", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_arguments(call, exc, match):
    with pytest.raises(exc, match=match):
        call()


# ---------------------------------------------------------------------------------------
# 6. the C++ kernels: fast conv2d vs the plain loops (double sums) vs torch, every code path

# (B, C, Co, (Hi, Wi), (kh, kw), stride, padding): each family of the codebook and each code path of
# csrc/conv.cpp on every kernel path (vector widths W = 4..16). C and Co are not multiples of any
# vector width, and C > 8 makes several channel blocks (kCB = 8) in the dw and the stride-2 dx.
KERNEL_CASES = [
    (3, 19, 13, (9, 67), (3, 3), 1, 1),  # 3x3 pad 1, rows of >= 4 vectors: per-row products, dw on padded rows
    (2, 11, 13, (16, 16), (3, 3), 1, 1),  # 16x16: per-row forward (W <= 8), im2col dw
    (2, 19, 5, (8, 8), (3, 3), 1, 1),  # 8x8: one wide product per tile, columns past each row dropped
    (1, 5, 7, (5, 4), (3, 3), 1, 1),  # B = 1, rows shorter than a vector
    (2, 7, 3, (1, 9), (3, 3), 1, 1),  # one row: every tap row but the centre is padding
    (3, 19, 13, (8, 8), (3, 3), 2, DOWN),  # the Downsample: im2col, col2im for dx
    (2, 5, 7, (9, 35), (3, 3), 2, DOWN),  # ... odd height, a width past 2 vectors
    (3, 19, 13, (7, 37), (1, 1), 1, 0),  # 1x1: x read in place (no columns)
    (2, 5, 7, (7, 6), (1, 1), 2, 0),  # 1x1 strided
    (2, 5, 7, (5, 20), (1, 1), 1, 1),  # 1x1 padded: its stride-1 dx crops (negative padding)
    (2, 9, 6, (7, 40), (2, 3), 1, (2, 0, 1, 3)),  # every side different, stride-1 dx padded (-1, 1, 1, -1)
    (1, 6, 5, (9, 7), (4, 2), 2, (2, 1, 0, 1)),  # non-square kernel, stride 2, odd sizes
    # Co >= W on every path (W <= 16): the dw as products on channels-last dy (dw_gemm), Co = 37 =
    # 2 vectors + a scalar tail on AVX-512, two channel blocks (kCB = 8) of which one partial
    (2, 11, 37, (8, 8), (3, 3), 1, 1),  # padded-row tiles taken as rows of Wp pixels (zero columns of dy)
    (2, 9, 35, (20, 67), (3, 3), 1, 1),  # several row tiles, chunks of kDwChunk = 256 pixels
    (2, 9, 35, (9, 35), (3, 3), 2, DOWN),  # the Downsample: im2col tiles
    (2, 9, 35, (7, 37), (1, 1), 1, 0),  # 1x1 below 32x32 pixels: x read in place
    (1, 5, 35, (32, 33), (1, 1), 1, 0),  # 1x1 from 32x32 pixels on: the lane sums again
    # AVX-512's 12-row tiles of the stride-1 products: Co = 28 = 12 + 8 + 8 (M % 12 == 4 as two
    # 8-row tiles), and the dx's 16 rows = 8 + 8
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


def plain_run(inputs, kwargs, dy):
    """The plain loops of csrc/conv.cpp (one double sum per output element, rounded once)."""
    x, w, b = inputs
    pad = conv._padding4(kwargs["padding"])
    y = np.empty(dy.shape, dy.dtype)
    _core.conv2d_forward_plain(y, x, w, b, kwargs["stride"], *pad)
    grads = [np.empty_like(a) for a in inputs]
    _core.conv2d_backward_plain(*grads, x, w, dy, kwargs["stride"], *pad)
    return y, grads


def numpy_run(inputs, kwargs, dy):
    y, cache = conv.conv2d_forward_numpy(*inputs, **kwargs)
    return y, conv.conv2d_backward_numpy(dy, cache)


@pytest.mark.parametrize("case", KERNEL_CASES, ids=kernel_case_id)
def test_conv2d_kernel_float64(case, rng):
    """float64: fast kernel, plain loops, the NumPy path and torch agree to RTOL64 (the same sums
    in other orders; measured <= 2.5e-15 on the baseline and avx2 paths)."""
    inputs, kwargs, dy = kernel_inputs(case, rng, np.float64)
    y, grads, _ = pyvf_run("conv2d", inputs, kwargs, dy)
    runs = {"plain": plain_run(inputs, kwargs, dy), "numpy": numpy_run(inputs, kwargs, dy),
            "torch": torch_run("conv2d", inputs, kwargs, dy)}
    for name, (y_r, grads_r) in runs.items():
        compare("conv2d", y, grads, y_r, grads_r, RTOL64, f"{kernel_case_id(case)} fast vs {name}")
    compare("conv2d", *runs["plain"], *runs["torch"], RTOL64, f"{kernel_case_id(case)} plain vs torch")


# float32 fast kernel vs the float64 plain loops on the same (float32) inputs: the kernel's float32
# arithmetic only. y and dx are dot products of K = C*kh*kw <= 171 terms accumulated in float32
# (FMA where the path has it); dw sums B*Ho*Wo <= 1809 products in W lanes; db sums in double.
# About sqrt(n) u normwise; measured <= 4.7e-7 (dx of the 3x3 case on 9x67, baseline path; y 3.9e-7,
# dw 2.7e-7, db 4.3e-8); 2e-6 leaves 4x. The plain loops in float32 measured <= 4.8e-8.
RTOL32_KERNEL = 2e-6


@pytest.mark.parametrize("case", KERNEL_CASES, ids=kernel_case_id)
def test_conv2d_kernel_float32(case, rng):
    inputs, kwargs, dy = kernel_inputs(case, rng, np.float32)
    y, grads, _ = pyvf_run("conv2d", inputs, kwargs, dy)
    assert y.dtype == np.float32 and all(g.dtype == np.float32 for g in grads)
    y64, grads64 = plain_run([a.astype(np.float64) for a in inputs], kwargs, dy.astype(np.float64))
    compare("conv2d", y, grads, y64, grads64, RTOL32_KERNEL, f"{kernel_case_id(case)} f32 vs f64")
    # the plain loops in float32 round one double sum per element: within an ulp or two of float64
    y_p, grads_p = plain_run(inputs, kwargs, dy)
    compare("conv2d", y_p, grads_p, y64, grads64, 2 * float(np.finfo(np.float32).eps),
            f"{kernel_case_id(case)} f32 plain vs f64")


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("case", KERNEL_CASES, ids=kernel_case_id)
def test_conv2d_kernel_threads_bitwise(case, dtype, rng):
    """The tasks depend on the shapes only, each output element is summed by one task in one
    order: 1, 2 and 5 threads give the same bits (y, dx, dw, db). 5 threads: the blocks that
    follow the thread count (the dw's and the forward's output channels) change, and the
    backward's dw and dx tasks share one loop in another interleaving."""
    inputs, kwargs, dy = kernel_inputs(case, rng, dtype)
    out = {}
    for n in (1, 2, 5):
        with forced_threads(n):  # these shapes are below the size at which a call takes threads
            y, grads, _ = pyvf_run("conv2d", inputs, kwargs, dy)
        out[n] = [y, *grads]
    for n in (2, 5):
        for name, a, b in zip(("y", "dx", "dw", "db"), out[1], out[n]):
            assert_bitwise_equal(f"{kernel_case_id(case)} {name}, 1 vs {n} threads", a, b)


def test_conv2d_kernel_padding_trap(rng):
    """The kernel itself on the Downsample (docs/math.md §4): padding=(0, 1, 0, 1) against 1 (same
    output size on even images) and (1, 0, 1, 0) (the wrong corner): O(1) apart, while each
    matches torch's own version of it."""
    inputs, kwargs, dy = kernel_inputs((2, 5, 7, (8, 8), (3, 3), 2, DOWN), rng, np.float64)
    y, _ = conv.conv2d_forward(*inputs, stride=2, padding=DOWN)
    for wrong in (1, (1, 0, 1, 0)):
        y_w, _ = conv.conv2d_forward(*inputs, stride=2, padding=wrong)
        assert y_w.shape == y.shape
        assert gap(y, y_w) > 0.1, f"padding {wrong} is only {gap(y, y_w):.1e} from (0, 1, 0, 1)"
        y_t, _ = torch_run("conv2d", inputs, {"stride": 2, "padding": wrong}, dy)
        assert_close(f"padding {wrong} vs torch", y_w, y_t, RTOL64)


def test_conv2d_empty_batch():
    """B = 0: an empty y, and zero dw, db (a sum of nothing)."""
    x, w, b = np.zeros((0, 5, 6, 7)), np.ones((4, 5, 3, 3)), np.ones(4)
    y, cache = conv.conv2d_forward(x, w, b, padding=1)
    assert y.shape == (0, 4, 6, 7)
    dx, dw, db = conv.conv2d_backward(y, cache)
    assert dx.shape == x.shape
    assert_bitwise_equal("dw of no images", dw, np.zeros_like(w))
    assert_bitwise_equal("db of no images", db, np.zeros_like(b))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("xshape, wshape, padding", [
    ((1, 0, 4, 4), (2, 0, 3, 3), 1),        # no input channels: the backward divided by C (SIGFPE)
    ((1, 1, 0, 4), (3, 1, 3, 3), 2),        # no rows, the padding alone fits the kernel (SIGFPE)
    ((2, 3, 5, 0), (17, 3, 3, 3), (0, 0, 2, 1)),  # no columns, 17 output channels (whole vectors and a tail)
])
def test_conv2d_of_an_empty_image_is_its_bias(dtype, xshape, wshape, padding, rng):
    """x with no elements but an output the padding makes: y = b everywhere, and the backward
    gives an empty dx, dw = 0 (every window read only padding) and db = the sums of dy, in the
    double sum of db's kernel. Closed forms, on a random dy and b."""
    x, w = np.zeros(xshape, dtype), rng.standard_normal(wshape).astype(dtype)
    b = rng.standard_normal(wshape[0]).astype(dtype)
    y, cache = conv.conv2d_forward(x, w, b, padding=padding)
    assert y.size > 0
    assert_bitwise_equal("y of an empty image", y, np.broadcast_to(b[:, None, None], y.shape))
    dy = rng.standard_normal(y.shape).astype(dtype)
    dx, dw, db = conv.conv2d_backward(dy, cache)
    assert dx.shape == x.shape and dw.shape == w.shape
    assert not dw.view(np.uint8).any(), "dw of an empty image: not +0 everywhere"  # (also when w is empty)
    want = dy.astype(np.float64).sum(axis=(0, 2, 3))  # at most 2 * 8 * 5 terms: exact enough
    assert_close("db of an empty image", db, want, 2 * np.finfo(dtype).eps)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_conv2d_backward_reads_nothing_stale(dtype, rng):
    """The backward's work buffers (dy channels-last with zero padding pixels for the dw tasks, the
    flipped weights for dx) are not zeroed when allocated: the kernel writes every element its
    tasks read. A backward of an all-NaN dy (which raises) leaves NaN in the buffers it frees, and
    the next call of the same shape mostly gets them back from the allocator: its gradients must
    be bitwise those of the first call, which match the plain loops. (With the padding pixels'
    zeros left out of the preparation, that next call raised: dw not finite.)"""
    for B, C, Co, H, Wd in [(2, 8, 16, 9, 9), (1, 3, 32, 5, 12), (2, 16, 24, 17, 7)]:
        x, dy = rng.standard_normal((B, C, H, Wd)).astype(dtype), rng.standard_normal((B, Co, H, Wd)).astype(dtype)
        w = rng.standard_normal((Co, C, 3, 3)).astype(dtype)
        want = [np.empty_like(a) for a in (x, w, w[:, 0, 0, 0])]  # dx, dw, db
        _core.conv2d_backward_plain(*want, x, w, dy, 1, 1, 1, 1, 1)
        first = [np.empty_like(a) for a in want]
        _core.conv2d_backward(*first, x, w, dy, 1, 1, 1, 1, 1)
        for name, g, r in zip(("dx", "dw", "db"), first, want):
            assert_close(f"{name} {(B, C, Co, H, Wd)} vs plain", g, r, RTOL64 if dtype == np.float64 else RTOL32_KERNEL)
        nan, got = np.full_like(dy, np.nan), [np.empty_like(a) for a in want]
        for _ in range(3):
            with pytest.raises(ValueError, match="not finite"):
                _core.conv2d_backward(*got, x, w, nan, 1, 1, 1, 1, 1)
            _core.conv2d_backward(*got, x, w, dy, 1, 1, 1, 1, 1)
            for name, g, f in zip(("dx", "dw", "db"), got, first):
                assert_bitwise_equal(f"{name} {(B, C, Co, H, Wd)} after a NaN call", g, f)


def test_conv2d_backward_wide_channel_blocks(rng):
    """From 128 input channels on, the dw tasks take blocks of 16 channels instead of 8 (130: eight
    full blocks and one of 2), with the tiles of 8 channels: a dw element's sums do not depend on
    the block it falls in. So dw[:, :120] of a 130-channel layer is bitwise the dw of its first
    120 channels alone (blocks of 8); the image is wide and tall enough (125 x 40) that tiles of
    16 channels would cut its rows elsewhere. Also: the plain loops in float64, and 1, 2, 5
    threads bitwise."""
    B, C, Co, H, Wd = 1, 130, 16, 40, 125
    x = rng.standard_normal((B, C, H, Wd)).astype(np.float32)
    w = rng.standard_normal((Co, C, 3, 3)).astype(np.float32)
    dy = rng.standard_normal((B, Co, H, Wd)).astype(np.float32)

    def backward(x, w, dy, n=1):
        out = [np.empty_like(a) for a in (x, w, w[:, 0, 0, 0])]
        with forced_threads(n):
            _core.conv2d_backward(*out, x, w, dy, 1, 1, 1, 1, 1)
        return out

    dx, dw, db = backward(x, w, dy)
    _, dw120, _ = backward(np.ascontiguousarray(x[:, :120]), np.ascontiguousarray(w[:, :120]), dy)
    assert_bitwise_equal("dw of the first 120 channels, in a 130-channel layer vs alone", dw[:, :120], dw120)
    for n in (2, 5):
        for name, a, b in zip(("dx", "dw", "db"), (dx, dw, db), backward(x, w, dy, n)):
            assert_bitwise_equal(f"{name}, 1 vs {n} threads", a, b)
    x64, w64, dy64 = (a.astype(np.float64) for a in (x, w, dy))
    want = [np.empty_like(a) for a in (x64, w64, w64[:, 0, 0, 0])]
    _core.conv2d_backward_plain(*want, x64, w64, dy64, 1, 1, 1, 1, 1)
    for name, g, r in zip(("dx", "dw", "db"), backward(x64, w64, dy64, 2), want):
        assert_close(f"{name} float64 vs plain", g, r, RTOL64)


BIG = [  # sizes past the kernels' int indexing, on arrays with no elements (B = 0 or Co = 0)
    ("x", dict(x=(0, 1, 50_000, 50_000), w=(1, 1, 1, 1), padding=0), r"x: Hi\*Wi = 2500000000"),
    ("w", dict(x=(0, 2 ** 28, 1, 1), w=(0, 2 ** 28, 3, 3), padding=1), r"w: C\*kh\*kw = 2415919104"),
    ("padding", dict(x=(0, 1, 1, 1), w=(1, 1, 1, 1), padding=2 ** 16), r"padding: Ho\*Wo"),
]


@pytest.mark.parametrize("what, sizes, match", BIG, ids=[b[0] for b in BIG])
def test_conv2d_refuses_int_overflow(what, sizes, match):
    x, w = np.zeros(sizes["x"], np.float32), np.zeros(sizes["w"], np.float32)
    with pytest.raises(ValueError, match=match):
        conv.conv2d_forward(x, w, np.zeros(w.shape[0], np.float32), padding=sizes["padding"])


def test_conv2d_bindings_refuse_bad_arrays(rng):
    """The bindings (pyvf._core) check again: a wrong output shape is a ValueError, a wrong dtype
    or a non-C-contiguous array a TypeError (never a silent copy or cast)."""
    x, w, b = rng.standard_normal((2, 3, 5, 5)), rng.standard_normal((4, 3, 3, 3)), rng.standard_normal(4)
    with pytest.raises(ValueError, match="y must have shape"):
        _core.conv2d_forward(np.empty((2, 4, 5, 4)), x, w, b, 1, 1, 1, 1, 1)
    with pytest.raises(TypeError):
        _core.conv2d_forward(np.empty((2, 4, 5, 5)), x[:, :, :, ::-1], w, b, 1, 1, 1, 1, 1)
    with pytest.raises(TypeError):
        _core.conv2d_forward(np.empty((2, 4, 5, 5)), x.astype(np.float32), w, b, 1, 1, 1, 1, 1)
    with pytest.raises(ValueError, match="dw must have shape"):
        _core.conv2d_backward(np.empty_like(x), np.empty((4, 3, 3, 2)), np.empty(4), x, w,
                              np.empty((2, 4, 5, 5)), 1, 1, 1, 1, 1)


# ---------------------------------------------------------------------------------------
# 7. GroupNorm + swish, fused (ResnetBlock's norm1/norm2 + swish, norm_out + swish)


def torch_groupnorm_swish(x, gamma, beta, groups=G, eps=EPS):
    return F.silu(F.group_norm(x, groups, gamma, beta, eps=eps))


LAYERS["groupnorm_swish"] = (conv.groupnorm_swish_forward, conv.groupnorm_swish_backward, torch_groupnorm_swish,
                             ("dx", "dgamma", "dbeta"))
RTOL32["groupnorm_swish"] = RTOL32["groupnorm"]  # swish adds a few ulp elementwise; measured <= 1.7e-7
GN_CASES = [(64, 5, 3), (96, 4, 4), (32, 9, 37)]  # 2, 3, 1 channels per group; pixels not a vector multiple


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("C, Hi, Wi", GN_CASES)
def test_groupnorm_swish_fused(C, Hi, Wi, dtype, rng):
    """The fused pair against torch (F.silu(F.group_norm)) in float64 on the same inputs, and
    bitwise against the unfused pyvf pair (the same operations), forward and backward."""
    _, inputs, _, dy = build(("groupnorm", C, Hi, Wi), rng, dtype)
    z, grads, cache = pyvf_run("groupnorm_swish", inputs, {}, dy)
    assert z.dtype == dtype and len(cache) == 5
    z_t, grads_t = torch_run("groupnorm_swish", inputs, {}, dy)
    rtol = RTOL64 if dtype == np.float64 else RTOL32["groupnorm_swish"]
    compare("groupnorm_swish", z, grads, z_t, grads_t, rtol, f"groupnorm+swish {C}x{Hi}x{Wi} vs torch")
    y, c_gn = conv.groupnorm_forward(*inputs)
    z2, c_sw = conv.swish_forward(y)
    (dy2,) = conv.swish_backward(dy, c_sw)
    grads2 = conv.groupnorm_backward(dy2, c_gn)
    assert_bitwise_equal("fused z vs swish(groupnorm)", z, z2)
    for name, a, b in zip(("dx", "dgamma", "dbeta"), grads, grads2):
        assert_bitwise_equal(f"fused {name} vs the unfused pair", a, b)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_groupnorm_swish_constant_groups(dtype, rng):
    """A constant group normalises to exactly beta, so the fused output there is exactly
    swish(beta), whatever the constant (1e4 + 0.3, 123456.789: not dyadic)."""
    x = constant_group_images(rng, dtype)
    C = x.shape[1]
    gamma, beta = (rng.standard_normal(C).astype(dtype) for _ in range(2))
    z, _ = conv.groupnorm_swish_forward(x, gamma, beta)
    k = 2 * len(CONSTANTS)
    want = conv.swish_forward(np.ascontiguousarray(np.broadcast_to(beta[:k, None, None], (k,) + x.shape[2:])))[0]
    assert_bitwise_equal(f"z of constant groups ({dtype.__name__})", z[0, :k], want)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_groupnorm_swish_kernels_vs_numpy(dtype, rng):
    """The C++ GroupNorm and swish against the NumPy versions kept in pyvf/nn/conv.py (the same
    formulas; C++ sums in float64 where NumPy sums pairwise in the dtype): within the float32
    tolerances of section 2, RTOL64 in float64."""
    _, inputs, _, dy = build(("groupnorm", 96, 4, 4), rng, dtype)
    rtol = RTOL64 if dtype == np.float64 else RTOL32["groupnorm"]
    y, c = conv.groupnorm_forward(*inputs)
    y_n, c_n = conv.groupnorm_forward_numpy(*inputs)
    assert_close("groupnorm y vs numpy", y, y_n, rtol)
    for name, a, b in zip(("dx", "dgamma", "dbeta"), conv.groupnorm_backward(dy, c), conv.groupnorm_backward_numpy(dy, c_n)):
        assert_close(f"groupnorm {name} vs numpy", a, b, rtol)
    x, ds = ((6 * rng.standard_normal((2, 4, 5, 3))).astype(dtype) for _ in range(2))
    rtol = RTOL64 if dtype == np.float64 else RTOL32["swish"]
    s, c = conv.swish_forward(x)
    assert_close("swish vs numpy", s, conv.swish_forward_numpy(x)[0], rtol)
    assert_close("swish' vs numpy", conv.swish_backward(ds, c)[0], conv.swish_backward_numpy(ds, c)[0], rtol)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_groupnorm_swish_threads_bitwise(dtype, rng):
    """GroupNorm (+ swish) and swish: 1 and 2 threads give the same bits (tasks per (image, group),
    dgamma/dbeta summed per image, then over images in order)."""
    _, inputs, _, dy = build(("groupnorm", 64, 24, 24), rng, dtype)  # 73728 elements: threads start
    before = pyvf.num_threads()
    try:
        out = {}
        for n in (1, 2):
            pyvf.set_num_threads(n)
            z, grads, _ = pyvf_run("groupnorm_swish", inputs, {}, dy)
            y, c = conv.groupnorm_forward(*inputs)
            s, c_s = conv.swish_forward(y)
            out[n] = [z, *grads, y, *conv.groupnorm_backward(dy, c), s, *conv.swish_backward(dy, c_s)]
    finally:
        pyvf.set_num_threads(before)
    for i, (a, b) in enumerate(zip(out[1], out[2])):
        assert_bitwise_equal(f"output {i}, 1 vs 2 threads", a, b)


# ---------------------------------------------------------------------------------------
# 7. pyvf's GEMM (csrc/conv.cpp matmul_batched: the AttnBlock's products, the transformer's linear
# layers and tied logits) against NumPy in float64

# (batch, M, N, K): odd sides past every register tile (8, 6, 4 rows; vectors of 2..16, the packed
# tile's 6), several row blocks of 96 and column blocks of 192, k chunks of 256 with a short last
# one, the attention's own square case; K = 0 gives zeros, zero rows or columns an empty result;
# few blocks of c and a long K (a weight gradient's shape) split along k into parts
# (kMatMinTasks): 2 parts with a short last one, and 9 parts of 1024 (the tiny transformer's X^T dY)
MATMUL_CASES = [(2, 37, 21, 13), (1, 97, 35, 50), (3, 5, 3, 7), (2, 64, 64, 32), (1, 4, 4, 0), (0, 3, 5, 2),
                (1, 203, 401, 531), (2, 96, 192, 256), (1, 0, 5, 3), (1, 9, 0, 3), (1, 37, 21, 2500),
                (1, 101, 67, 9216)]


def _mm(a, b, ta, tb):
    """c (nb, M, N) = op(a) @ op(b) per entry by the kernel."""
    nb, M, N = a.shape[0], a.shape[2 if ta else 1], b.shape[1 if tb else 2]
    c = np.full((nb, M, N), np.nan, dtype=a.dtype)  # NaN: an element the kernel skips shows
    _core.matmul(c, a, b, ta, tb)
    return c


def _operands(rng, case, ta, tb, dtype, draw=None):
    nb, M, N, K = case
    draw = draw or (lambda shape: rng.standard_normal(shape))
    a = draw((nb, K, M) if ta else (nb, M, K)).astype(dtype)
    b = draw((nb, N, K) if tb else (nb, K, N)).astype(dtype)
    a64, b64 = a.astype(np.float64), b.astype(np.float64)
    want = (a64.transpose(0, 2, 1) if ta else a64) @ (b64.transpose(0, 2, 1) if tb else b64)
    return a, b, want


@pytest.mark.parametrize("tb", [False, True])
@pytest.mark.parametrize("ta", [False, True])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("case", MATMUL_CASES, ids=lambda c: "x".join(map(str, c)))
def test_matmul_kernel(case, dtype, ta, tb, rng):
    """c = op(a) @ op(b) per entry against NumPy in float64 on the same inputs. Each element is
    one sum of K products in increasing k (or, split along k, its parts' sums added in order: no
    larger a bound), so its error is at most K u sum_k |a_ik b_kj| (Higham 3.5) and in practice
    ~sqrt(K) u of the normwise scale: float64 within 1e-13, float32 within
    2e-6 * max(1, sqrt(K / 50)) (measured <= 3e-7 at K = 50); bitwise the same on 1, 2 and 5
    threads (each element's sum does not depend on which task or thread computes it), every case
    on the threads whatever its size (forced_threads)."""
    nb, M, N, K = case
    a, b, want = _operands(rng, case, ta, tb, dtype)
    out = {}
    for n in (1, 2, 5):
        with forced_threads(n):
            out[n] = _mm(a, b, ta, tb)
    c = out[1]
    assert c.dtype == dtype and c.shape == (nb, M, N)
    if c.size:  # (the helpers need at least one element)
        rtol = 1e-13 if dtype == np.float64 else 2e-6 * max(1.0, np.sqrt(K / 50))
        assert_close("matmul", c, want, rtol=rtol)
        for n in (2, 5):
            assert_bitwise_equal(f"matmul, 1 vs {n} threads", out[n], c)
    if K == 0:
        assert not c.any(), "a sum of no products must be 0"


@pytest.mark.parametrize("ta, tb", [(False, False), (True, False), (False, True), (True, True)])
def test_matmul_kernel_exact_on_integers(ta, tb, rng):
    """Small integers make every partial sum exact in float32 (|sum| <= 3 * 3 * 800 < 2^24), so
    the kernel must equal the float64 product exactly: a k chunk dropped or counted twice, an
    edge row or column (past the packed tiles) or an entry computed from the wrong block all
    show, however small the other errors."""
    for case in [(2, 2 * 96 + 13, 192 + 96 + 21, 3 * 256 + 31),
                 (1, 96 + 13, 21, 3 * 1024 + 31)]:  # split along k into 3 parts, the last one short
        a, b, want = _operands(rng, case, ta, tb, np.float32, draw=lambda s: rng.integers(-3, 4, s))
        np.testing.assert_array_equal(_mm(a, b, ta, tb), want.astype(np.float32), err_msg=str(case))


@pytest.mark.parametrize("tb", [False, True])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_matmul_kernel_bias_rounds_as_numpy(dtype, tb, rng):
    """c = op(a) @ op(b) + bias: the bias is added to each element after its whole sum, one
    rounding, so the result is bitwise the kernel's product + bias in NumPy (across block, chunk
    and tile edges, 1 and 2 threads); K = 0 gives the bias itself; a bias of another length is
    refused."""
    for case in [(2, 101, 203, 300), (1, 37, 45, 2100)]:  # the second split along k: the bias after the parts
        a, b, _ = _operands(rng, case, False, tb, dtype)
        bias = rng.standard_normal(case[2]).astype(dtype)
        want = _mm(a, b, False, tb) + bias
        for n in (1, 2):
            with forced_threads(n):
                c = np.full(want.shape, np.nan, dtype=dtype)
                _core.matmul(c, a, b, False, tb, bias)
            assert_bitwise_equal(f"matmul + bias {case}, {n} threads", c, want)
    c = np.full((1, 3, 4), np.nan, dtype=dtype)
    _core.matmul(c, np.zeros((1, 3, 0), dtype), np.zeros((1, 0, 4), dtype), False, False, bias[:4])
    np.testing.assert_array_equal(c, np.broadcast_to(bias[:4], (1, 3, 4)))
    with pytest.raises(ValueError, match="bias must have shape"):
        _core.matmul(c, np.zeros((1, 3, 2), dtype), np.zeros((1, 2, 4), dtype), False, False, bias[:5])


def test_matmul_layers_helper(rng):
    """pyvf.nn.layers.matmul, the entry the linear layers, the logits and the AttnBlock use: each
    transpose flag against NumPy in float64 on 2-D and batched operands, and a non-contiguous
    operand read as its values."""
    a3, b3 = rng.standard_normal((2, 3, 30, 40))
    assert_close("batched a @ b^T", matmul(a3, b3, tb=True), a3 @ b3.transpose(0, 2, 1), rtol=1e-13)
    a, b = rng.standard_normal((2, 30, 40))
    assert_close("a @ b^T", matmul(a, b, tb=True), a @ b.T, rtol=1e-13)
    assert_close("a^T @ b", matmul(a[:, :30].T, b[:, :30], ta=True), a[:, :30] @ b[:, :30], rtol=1e-13)
    assert_close("a @ b", matmul(a[:, :30], b.T[:30]), a[:, :30] @ b.T[:30], rtol=1e-13)


def test_matmul_kernel_would_catch_a_transpose(rng):
    """The oracle tells a transposed operand apart (square sizes, where shapes cannot)."""
    a, b = rng.standard_normal((2, 2, 9, 9))
    good = matmul(a, b)
    assert gap(matmul(a, b, ta=True), good) > 0.1
    assert gap(_mm(a, b, False, True), good) > 0.1
    assert_close("matmul square", good, a @ b, rtol=1e-13)


def test_matmul_kernel_refuses_bad_arguments():
    a, b = np.zeros((2, 3, 4)), np.zeros((2, 4, 5))
    with pytest.raises(TypeError):  # one dtype, never cast
        _core.matmul(np.zeros((2, 3, 5)), a.astype(np.float32), b, False)
    with pytest.raises(ValueError, match="b must have shape"):
        _core.matmul(np.zeros((2, 3, 5)), a, np.zeros((2, 3, 5)), False)
    with pytest.raises(ValueError, match=r"b must have shape \(batch, N, K\) with a's batch 2 and K = 4, got \(2, 4, 5\)"):
        _core.matmul(np.zeros((2, 3, 5)), a, b, False, True)
    with pytest.raises(ValueError, match=r"c must have shape \(batch, M, N\) = \(2, 3, 5\), got \(2, 3, 4\)"):
        _core.matmul(np.zeros((2, 3, 4)), a, b, False)
    with pytest.raises(ValueError, match=r"bias must have shape \(N,\) = \(5,\), got \(4,\)"):
        _core.matmul(np.zeros((2, 3, 5)), a, b, False, False, np.zeros(4))
    with pytest.raises(ValueError, match="c must have shape"):
        _core.matmul(np.zeros((2, 3, 4)), a, b, False)
    with pytest.raises(ValueError, match="3-D"):
        _core.matmul(np.zeros((3, 5)), a, b, False)


# ---------------------------------------------------------------------------------------
# 8. overflow: finite inputs whose result exceeds the dtype raise, naming the layer and output


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_outputs_that_overflow_raise(dtype, rng):
    """Every layer checks what it returns: a conv whose sums pass the dtype's largest number, a
    GroupNorm whose gamma scales xhat past it, and a backward whose dy does, raise ValueError
    naming the function and the output, instead of returning inf. Just below, the same layers
    return finite numbers (so the check is not simply refusing large inputs)."""
    big = np.finfo(dtype).max
    x = rng.uniform(0.5, 1.0, (1, 4, 6, 6)).astype(dtype)
    w = np.full((3, 4, 3, 3), dtype(big / 20), dtype)  # up to 36 positive terms of x * w: > max
    b = np.zeros(3, dtype)
    with pytest.raises(ValueError, match="conv2d_forward: y is not finite"):
        conv.conv2d_forward(x, w, b, padding=1)
    y, cache = conv.conv2d_forward(x, w / dtype(64), b, padding=1)  # <= 36/64 of max: finite
    assert np.isfinite(y).all()
    with pytest.raises(ValueError, match="conv2d_backward: dx is not finite"):
        conv.conv2d_backward(np.full(y.shape, dtype(64), dtype), cache)  # dx sums 27 terms of 64 * w/64 * ...

    # dw and db, each the only output that overflows (the kernels check them as they write them,
    # dx before dw before db); the reference kernel (_plain) checks the same outputs
    small = np.full((3, 4, 3, 3), dtype(1e-3), dtype)
    cases = {"dw": (x * dtype(big / 8), small, dtype(1)),          # dw sums 36 terms of ~big/8
             "db": (x * dtype(1e-3), small, dtype(big / 8))}       # db sums 36 terms of big/8
    for name, (xo, wo, g) in cases.items():
        y, cache = conv.conv2d_forward(xo, wo, b, padding=1)
        dy = np.full(y.shape, g, dtype)
        with pytest.raises(ValueError, match=f"conv2d_backward: {name} is not finite: it overflowed"):
            conv.conv2d_backward(dy, cache)
        for kernel in (_core.conv2d_backward, _core.conv2d_backward_plain):
            outs = np.empty_like(xo), np.empty_like(wo), np.empty_like(b)
            with pytest.raises(ValueError, match=f"conv2d_backward: {name} is not finite"):
                kernel(*outs, xo, wo, dy, 1, 1, 1, 1, 1)
        finite = conv.conv2d_backward(dy / dtype(64), cache)  # 36/64 of the largest: finite
        assert all(np.isfinite(a).all() for a in finite)

    xg = rng.standard_normal((2, 64, 5, 5)).astype(dtype)
    gamma, beta = np.full(64, big, dtype), np.zeros(64, dtype)  # mean xhat^2 ~ 1: some |xhat| > 1
    with pytest.raises(ValueError, match="groupnorm_forward: y is not finite"):
        conv.groupnorm_forward(xg, gamma, beta)
    with pytest.raises(ValueError, match="groupnorm_forward: y is not finite"):
        conv.groupnorm_swish_forward(xg, gamma, beta)
    yg, cg = conv.groupnorm_forward(xg, gamma / dtype(1e6), beta)
    assert np.isfinite(yg).all()


# ---------------------------------------------------------------------------------------
# 9. NaN or inf in an input: conv2d and GroupNorm scan their inputs only when an output is not
# finite (pyvf/nn/conv.py's _after_kernel); the error names the input all the same


CONV_SHAPES = [  # (x shape, w shape, stride, padding): the codebook's three kinds
    ((2, 5, 7, 6), (4, 5, 3, 3), 1, 1),
    ((2, 5, 8, 8), (4, 5, 3, 3), 2, (0, 1, 0, 1)),
    ((2, 5, 4, 3), (4, 5, 1, 1), 1, 0),
]


def _spoil(a, rng, bad):
    """a copy of a with `bad` at a random element, or at its first or last one"""
    a = a.copy()
    where = rng.integers(3)
    flat = a.reshape(-1)
    flat[[0, flat.size - 1, rng.integers(flat.size)][where]] = bad
    return a


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("shape", CONV_SHAPES, ids=["3x3", "3x3 stride 2", "1x1"])
def test_conv_names_the_input_that_holds_nan_or_inf(shape, dtype, bad, rng):
    """Any element of x, w, b (forward) or dy (backward) that is NaN or inf raises ValueError
    '<name> contains NaN or inf', although the inputs are scanned only after an output came out
    not finite: every element of each is read by some output of these shapes."""
    xs, ws, stride, padding = shape
    x, w, b = (rng.standard_normal(s).astype(dtype) for s in (xs, ws, (ws[0],)))
    args = dict(x=x, w=w, b=b)
    for _ in range(4):  # random positions, the first and the last elements among them
        for name in args:
            spoilt = dict(args, **{name: _spoil(args[name], rng, bad)})
            with pytest.raises(ValueError, match=f"^{name} contains NaN or inf"):
                conv.conv2d_forward(spoilt["x"], spoilt["w"], spoilt["b"], stride, padding)
        y, cache = conv.conv2d_forward(x, w, b, stride, padding)
        dy = rng.standard_normal(y.shape).astype(dtype)
        with pytest.raises(ValueError, match="^dy contains NaN or inf"):
            conv.conv2d_backward(_spoil(dy, rng, bad), cache)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("swish", [False, True])
def test_groupnorm_names_the_input_that_holds_nan_or_inf(swish, dtype, bad, rng):
    fwd = conv.groupnorm_swish_forward if swish else conv.groupnorm_forward
    bwd = conv.groupnorm_swish_backward if swish else conv.groupnorm_backward
    x = rng.standard_normal((2, 64, 3, 5)).astype(dtype)
    gamma, beta = (rng.standard_normal(64).astype(dtype) for _ in range(2))
    args = dict(x=x, gamma=gamma, beta=beta)
    for _ in range(4):
        for name in args:
            spoilt = dict(args, **{name: _spoil(args[name], rng, bad)})
            with pytest.raises(ValueError, match=f"^{name} contains NaN or inf"):
                fwd(spoilt["x"], spoilt["gamma"], spoilt["beta"])
        y, cache = fwd(x, gamma, beta)
        with pytest.raises(ValueError, match=f"^{'dz' if swish else 'dy'} contains NaN or inf"):  # bwd's own argument
            bwd(_spoil(rng.standard_normal(y.shape).astype(dtype), rng, bad), cache)


@pytest.mark.parametrize("xs, ws, stride, padding, where", [
    ((1, 2, 4, 4), (3, 2, 1, 1), 2, 0, (0, 1, 1, 1)),  # a stride past the kernel skips odd pixels
    ((1, 2, 6, 6), (3, 2, 3, 3), 2, 0, (0, 0, 5, 2)),  # the last window ends before the last row
    ((0, 2, 4, 4), (3, 2, 3, 3), 1, 1, None),          # an empty batch reads no w
    ((1, 2, 4, 4), (0, 2, 3, 3), 1, 1, (0, 1, 2, 3)),  # no output channels read no x
])
def test_conv_scans_inputs_first_where_some_are_not_read(xs, ws, stride, padding, where, rng):
    """Where no output reads an element of x (or any of w, b), its NaN could not show in y: those
    calls scan the inputs first, so the NaN still raises naming x (or w)."""
    x, w, b = rng.standard_normal(xs), rng.standard_normal(ws), rng.standard_normal(ws[0])
    name = "x" if where else "w"
    if where:
        x[where] = np.nan
    else:
        w[0, 0, 0, 0] = np.nan
    with pytest.raises(ValueError, match=f"^{name} contains NaN or inf"):
        conv.conv2d_forward(x, w, b, stride, padding)
    if where and ws[0] > 0:  # the kernel alone would not have seen it (y unchanged by it)
        x[where] = 0.0
        y_clean = conv.conv2d_forward(x, w, b, stride, padding)[0]
        x[where] = 1e30
        assert_bitwise_equal("y with the unread element changed", conv.conv2d_forward(x, w, b, stride, padding)[0], y_clean)


def test_attnblock_logits_that_overflow_are_named_as_such(rng):
    """q.k / sqrt(C) beyond float32 (finite x, weights wq = wk = 1e19 I): the softmax's s - max s
    gave inf - inf = NaN, and the error came from the next conv as "x contains NaN or inf",
    blaming an input the user never passed. Now the logits are named; with wq = wk = I the
    same block runs (the boundary)."""
    C = 32
    x = rng.standard_normal((1, C, 4, 4)).astype(np.float32)
    eye = np.eye(C, dtype=np.float32)[:, :, None, None]
    zeros, ones = np.zeros(C, np.float32), np.ones(C, np.float32)
    w = (rng.standard_normal((C, C, 1, 1)) / np.sqrt(C)).astype(np.float32)
    args = lambda big: (x, ones, zeros, big * eye, zeros, big * eye, zeros, w, zeros, w, zeros)
    y, _ = conv.attnblock_forward(*args(np.float32(1)))
    assert np.isfinite(y).all()
    with pytest.raises(ValueError, match="attention logits .* overflow float32"):
        conv.attnblock_forward(*args(np.float32(1e19)))
