"""Speed against error (issue 11, item 2): each op of pyvf, each variant, its error against a
float64 reference and its time.

    pyvf bench accuracy                       # the sizes below; ~2 minutes on 2 cores
    pyvf bench accuracy --quick               # small sizes, ~20 s
    pyvf bench accuracy --json F --plots DIR  # every number; a time-vs-error Pareto plot per op

Ops (the time is of what the op's outputs need: `layernorm` is forward + backward, `attention
backward` the backward alone, given the forward's o and lse):

    attention_forward   pyvf.branching_attention_forward            o
    attention_backward  pyvf.branching_attention_backward           dq, dk, dv
    vq_nearest          pyvf.vq_nearest                             squared distance (+ wrong codes)
    layernorm           pyvf.nn.layers.layernorm_forward/_backward     y, dx, dgamma, dbeta
    groupnorm           pyvf.nn.conv.groupnorm_forward/_backward       y, dx, dgamma, dbeta
    cross_entropy       pyvf.nn.losses.cross_entropy_forward/_backward loss, dlogits
    gelu                pyvf.nn.layers.gelu_forward/_backward          y, dx (elementwise: ulps too)
    conv2d              pyvf.nn.conv.conv2d_forward/_backward          y, dx, dw, db

Variants: pyvf float32 on each instruction-set path this CPU runs (pyvf.kernel_paths(); switched
in this process with pyvf.use_kernel_path, which reaches every path PYVF_ISA could force at
import), pyvf float64, pyvf's plain C++ loops (attention), torch float32 (when torch imports),
and the NumPy reference float32 (the textbook NumPy formula: the dense masked softmax, the
expanded |x|^2 - 2 x.e + |e|^2 distance, np.var, softmax then log, 0.5 (1 + erf), im2col).

Every variant gets the same inputs, drawn in float64 and rounded to float32 (so float32 and float64
variants see identical numbers), and is compared with a float64 reference on them: NumPy float64
formulas written here (and pyvf's dense float64 attention reference, the float64 im2col conv),
mpmath for GELU, whose float64 erf form loses every digit in the tail. Errors: the normwise
relative error max|x - ref| / max|ref| (pyvf.rel_err; the largest over the op's outputs), and
for GELU the max error in ulps of the true value.

Each variant is validated before it is timed: pyvf against the bound the tests state for it
(tests/test_attention.py, test_layers.py, test_conv.py; BOUNDS below), torch and NumPy against
SANITY (they compute the same function: a wrong mask or layout is an O(1) error). A variant
outside its bound is not timed; the table says FAIL and the command exits with status 1.
Time: the median of --repeat calls after a warm-up, on --threads threads (pyvf and torch); an op's
variants are timed in interleaved rounds (time_variants).
"""

import math
import os
import statistics
import time

import numpy as np

import pyvf
from pyvf.nn import conv, layers, losses
from pyvf.bench.attention import flat, unflat
from pyvf.bench.common import legend_outside, log_ticks, machine, median_time, pyplot, save_figure, table, torch_or_none
from pyvf.bench.vq import brute_force
from pyvf.verify.compare import rel_err

U32, U64 = 2.0 ** -24, 2.0 ** -53  # unit roundoff

# Sizes of each op's problem. quick: seconds; smoke: the pytest-benchmark suite's (tests/test_benchmarks.py).
SIZES = {
    "full": dict(attention=(3, 1, 4, 8, 64, 64), vq=(8192, 1024, 64), layernorm=(4096, 256),
                 groupnorm=(4, 128, 32, 32), cross_entropy=(2048, 1024), gelu=8192, conv2d=(4, 64, 64, 32, 32)),
    "quick": dict(attention=(3, 1, 2, 4, 32, 32), vq=(2048, 256, 32), layernorm=(512, 128),
                  groupnorm=(2, 64, 16, 16), cross_entropy=(256, 512), gelu=2048, conv2d=(2, 16, 16, 16, 16)),
    "smoke": dict(attention=(3, 1, 2, 2, 16, 16), vq=(256, 64, 16), layernorm=(64, 64),
                  groupnorm=(1, 64, 8, 8), cross_entropy=(64, 128), gelu=256, conv2d=(1, 8, 8, 8, 8)),
}

# The bounds pyvf is held to (normwise relative, every output), the tests' own where they have one:
BOUNDS = {
    # tests/test_attention.py RTOL32 / RTOL64 (unit-normal inputs, scale 1: logits up to ~40)
    "attention_forward": (1e-5, 1e-12),
    "attention_backward": (1e-5, 1e-12),
    # float32: the distance is summed in float64 from the chosen code and rounded once: u. float64:
    # a D-term float64 sum, as the reference's, in another order: D u = 7e-15 at D = 64. And the
    # index must be exact (WRONG_CODES_ALLOWED)
    "vq_nearest": (2 * U32, 1e-14),
    # tests/test_layers.py RTOL32["layernorm"] is 1e-6 for 120 rows; here dgamma and dbeta are
    # float32 sums of 4096 rows of random-signed terms (NumPy's pairwise sum): up to log2(n) u
    # sum|t| / |sum t| ~ 12 u sqrt(n) = 4.6e-5, measured 2.1e-6 (NumPy's own float32 sum, the
    # same; torch 1.2e-6). 1e-5 = 5x the measured; y and dx measure 2e-7. RTOL64
    "layernorm": (1e-5, 1e-13),
    # tests/test_conv.py RTOL32["groupnorm"] (4e-7 for groups of 45 numbers; here up to 4096 per
    # group and dgamma over 4096 pixels, the float64 sums keep it measured <= 1.5e-7: 1e-6), RTOL64
    "groupnorm": (1e-6, 1e-13),
    # the log-sum-exp of V terms and one exp per dlogit: a few u on losses of size ~log V and on
    # O(1) gradients (the V-term sum's worst case, V u, is far from typical). Measured 2.3e-7: 1e-6
    "cross_entropy": (1e-6, 1e-13),
    # tests/test_layers.py RTOL32["gelu"], RTOL64; plus GELU_ULPS below
    "gelu": (4e-7, 1e-13),
    # tests/test_conv.py RTOL32["conv2d"] is for K = 45 terms; here K = 576 and dw sums 4096
    # pixels: sqrt(K) u = 1.4e-6 at worst, measured 5e-7: 2e-6; RTOL64
    "conv2d": (2e-6, 1e-13),
}
# tests/test_layers.py test_gelu_tail_few_ulp: y within a few ulp of the true value everywhere (plus the
# subnormal results' rounding step). Not gelu'(x) = Phi(x) + x phi(x): near its zero, x = -0.7518,
# the two terms cancel and its ulps measure the conditioning (measured 56 ulp in float64 there)
GELU_ULPS = 4
WRONG_CODES_ALLOWED = 0  # vq_nearest is exact (pyvf/nn/quantizer.py)
# torch and the NumPy reference compute the same function in float32 in their own order: a
# wiring error (mask, layout, eps 1e-5 for GroupNorm's 1e-6) is O(1e-2..1); their rounding is 1e-4 at most
SANITY = 1e-3


# ---------------------------------------------------------------------------------------
# ops: inputs, the float64 reference, and each variant as a zero-argument callable


def _round32(*arrays):
    """float64 arrays holding float32 values (every variant then sees the same numbers)."""
    return [a.astype(np.float32).astype(np.float64) for a in arrays]


def _cast(inputs, dtype):
    return {k: (v.astype(dtype) if isinstance(v, np.ndarray) and v.dtype.kind == "f" else v)
            for k, v in inputs.items()}


class Op:
    """One op's problem. Subclasses define inputs(size, rng) -> dict of float64 arrays (float32
    values) and ints, reference(x) -> list of float64 outputs, and pyvf(x, plain), torch(x),
    numpy(x): each returns fn() -> list of output arrays (x already cast to the variant's dtype);
    None where the variant does not exist."""

    name = title = ""
    outputs = ()
    elementwise = False

    def __init__(self, size):
        self.size = size

    def pyvf(self, x, plain=False):  # noqa: D401
        raise NotImplementedError

    def torch(self, x):
        return None

    def numpy(self, x):
        return None

    has_plain = False


class AttentionForward(Op):
    name, title, outputs = "attention_forward", "branching attention, forward", ("o",)
    has_plain = True

    def inputs(self, rng):
        q, k, v, do = _round32(*(rng.standard_normal(self.size) for _ in range(4)))
        return dict(q=q, k=k, v=v, do=do)

    def reference(self, x):
        return [pyvf.branching_attention_reference(x["q"], x["k"], x["v"])]

    def pyvf(self, x, plain=False):
        return lambda: [pyvf.branching_attention_forward(x["q"], x["k"], x["v"], plain=plain)[0]]

    def torch(self, x):
        import torch
        import torch.nn.functional as F

        R, B, H, N, L, dh = self.size
        q, k, v = (torch.from_numpy(flat(x[n])) for n in "qkv")
        mask = torch.from_numpy(pyvf.branching_mask(R, N, L))

        def fn():
            with torch.no_grad():
                return [unflat(F.scaled_dot_product_attention(q, k, v, attn_mask=mask, scale=1.0).numpy(), self.size)]
        return fn

    def numpy(self, x):
        return lambda: [pyvf.branching_attention_reference(x["q"], x["k"], x["v"])]


class AttentionBackward(AttentionForward):
    name, title, outputs = "attention_backward", "branching attention, backward", ("dq", "dk", "dv")

    def reference(self, x):
        return list(pyvf.branching_attention_reference_vjp(x["q"], x["k"], x["v"], x["do"]))

    def pyvf(self, x, plain=False):
        q, k, v, do = x["q"], x["k"], x["v"], x["do"]
        o, lse = pyvf.branching_attention_forward(q, k, v, plain=plain)  # the forward is not timed
        return lambda: list(pyvf.branching_attention_backward(do, q, k, v, o, lse, plain=plain))

    def torch(self, x):
        import torch
        import torch.nn.functional as F

        R, B, H, N, L, dh = self.size
        leaves = [torch.from_numpy(flat(x[n])).requires_grad_(True) for n in "qkv"]
        do = torch.from_numpy(flat(x["do"]))
        o = F.scaled_dot_product_attention(*leaves, attn_mask=torch.from_numpy(pyvf.branching_mask(R, N, L)),
                                           scale=1.0)  # the forward is not timed; its graph is kept
        return lambda: [unflat(g.numpy(), self.size) for g in torch.autograd.grad(o, leaves, do, retain_graph=True)]

    def numpy(self, x):  # the reference's vjp recomputes the probabilities: it is forward + backward
        return lambda: list(pyvf.branching_attention_reference_vjp(x["q"], x["k"], x["v"], x["do"]))


class VQNearest(Op):
    name, title, outputs = "vq_nearest", "vq_nearest (nearest code)", ("sq_dist",)

    def inputs(self, rng):
        M, K, D = self.size
        codes = rng.standard_normal((K, D))
        x = codes[rng.integers(0, K, M)] + 0.7 * rng.standard_normal((M, D))  # near a code, not on it
        x, codes = _round32(x, codes)
        return dict(x=x, codes=codes)

    def exact_indices(self, x):
        return brute_force(x["x"], x["codes"], chunk=64)

    def reference(self, x):
        idx = self.exact_indices(x)
        return [((x["x"] - x["codes"][idx]) ** 2).sum(axis=1)]

    def pyvf(self, x, plain=False):
        def fn():
            idx, sq = pyvf.vq_nearest(x["x"], x["codes"])
            fn.indices = idx
            return [sq]
        return fn

    def torch(self, x):
        import torch

        xt, ct = torch.from_numpy(x["x"]), torch.from_numpy(x["codes"])

        def fn():
            d, idx = torch.cdist(xt, ct).min(dim=1)
            fn.indices = idx.numpy()
            return [(d * d).numpy()]
        return fn

    def numpy(self, x):
        xs, cs = x["x"], x["codes"]

        def fn():  # the published quantizer's expanded formula
            d = (xs ** 2).sum(1, keepdims=True) - 2 * xs @ cs.T + (cs ** 2).sum(1)  # (M, K)
            fn.indices = d.argmin(axis=1)
            return [d[np.arange(len(xs)), fn.indices]]
        return fn


def _torch_norm(x, norm):
    """fn() -> [y, dx, dgamma, dbeta] of y = norm(F, x, gamma, beta) by torch autograd with dy."""
    import torch
    import torch.nn.functional as F

    xt, g, b = (torch.from_numpy(x[n]).requires_grad_(True) for n in ("x", "gamma", "beta"))
    dy = torch.from_numpy(x["dy"])

    def fn():
        y = norm(F, xt, g, b)
        return [y.detach().numpy()] + [t.numpy() for t in torch.autograd.grad(y, (xt, g, b), dy)]
    return fn


class LayerNorm(Op):
    name, title, outputs = "layernorm", "LayerNorm forward + backward", ("y", "dx", "dgamma", "dbeta")
    eps = 1e-5

    def inputs(self, rng):
        M, d = self.size
        x = rng.standard_normal((M, d)) * rng.uniform(0.1, 3, (M, 1)) + rng.uniform(-3, 3, (M, 1))
        return dict(zip(("x", "gamma", "beta", "dy"),
                        _round32(x, 1 + 0.1 * rng.standard_normal(d), 0.1 * rng.standard_normal(d),
                                 rng.standard_normal((M, d)))))

    @staticmethod
    def _norm(xg, gamma, beta, dy, eps, two_pass=True):
        """The textbook LayerNorm over the last axis of xg (rows, n) with gamma/beta broadcast
        per element: (y, dx, xhat). two_pass=False: var = E[x^2] - E[x]^2 (one pass)."""
        mean = xg.mean(axis=-1, keepdims=True)
        xc = xg - mean
        var = (xc * xc).mean(axis=-1, keepdims=True) if two_pass else (xg * xg).mean(-1, keepdims=True) - mean ** 2
        rstd = 1 / np.sqrt(np.maximum(var, 0) + eps)
        xhat = xc * rstd
        dxhat = dy * gamma
        dx = rstd * (dxhat - dxhat.mean(-1, keepdims=True) - xhat * (dxhat * xhat).mean(-1, keepdims=True))
        return xhat * gamma + beta, dx, xhat

    def reference(self, x):
        y, dx, xhat = self._norm(x["x"], x["gamma"], x["beta"], x["dy"], self.eps)
        return [y, dx, (x["dy"] * xhat).sum(0), x["dy"].sum(0)]

    def pyvf(self, x, plain=False):
        def fn():
            y, cache = layers.layernorm_forward(x["x"], x["gamma"], x["beta"], self.eps)
            return [y, *layers.layernorm_backward(x["dy"], cache)]
        return fn

    def torch(self, x):
        return _torch_norm(x, lambda F, xt, g, b: F.layer_norm(xt, (xt.shape[-1],), g, b, self.eps))

    def numpy(self, x):
        def fn():
            y, dx, xhat = self._norm(x["x"], x["gamma"], x["beta"], x["dy"], np.float32(self.eps))
            return [y, dx, (x["dy"] * xhat).sum(0), x["dy"].sum(0)]
        return fn


class GroupNorm(Op):
    name, title, outputs = "groupnorm", "GroupNorm forward + backward", ("y", "dx", "dgamma", "dbeta")
    groups, eps = 32, 1e-6  # the codebook's Normalize (docs/math.md §4: eps 1e-6, not torch's 1e-5)

    def inputs(self, rng):
        B, C, Hi, Wi = self.size
        x = rng.standard_normal((B, C, Hi, Wi)) * rng.uniform(0.1, 3, (B, C, 1, 1)) + rng.uniform(-3, 3, (B, C, 1, 1))
        return dict(zip(("x", "gamma", "beta", "dy"),
                        _round32(x, 1 + 0.1 * rng.standard_normal(C), 0.1 * rng.standard_normal(C),
                                 rng.standard_normal(x.shape))))

    def _numpy(self, x, eps):
        B, C, Hi, Wi = x["x"].shape
        G = self.groups
        per_c = lambda a: np.broadcast_to(a[None, :, None, None], x["x"].shape).reshape(B, G, -1)  # noqa: E731
        y, dx, xhat = LayerNorm._norm(x["x"].reshape(B, G, -1), per_c(x["gamma"]), per_c(x["beta"]),
                                      x["dy"].reshape(B, G, -1), eps)
        dyx = (x["dy"] * xhat.reshape(x["x"].shape)).sum((0, 2, 3))
        return [y.reshape(x["x"].shape), dx.reshape(x["x"].shape), dyx, x["dy"].sum((0, 2, 3))]

    def reference(self, x):
        return self._numpy(x, self.eps)

    def pyvf(self, x, plain=False):
        def fn():
            y, cache = conv.groupnorm_forward(x["x"], x["gamma"], x["beta"], self.groups, self.eps)
            return [y, *conv.groupnorm_backward(x["dy"], cache)]
        return fn

    def torch(self, x):
        return _torch_norm(x, lambda F, xt, g, b: F.group_norm(xt, self.groups, g, b, self.eps))

    def numpy(self, x):
        return lambda: self._numpy(x, np.float32(self.eps))


class CrossEntropy(Op):
    name, title, outputs = "cross_entropy", "softmax cross-entropy forward + backward", ("loss", "dlogits")

    def inputs(self, rng):
        M, V = self.size
        logits, dloss = _round32(3 * rng.standard_normal((M, V)), rng.standard_normal(M))
        return dict(logits=logits, targets=rng.integers(0, V, M), dloss=dloss)

    def reference(self, x):
        z = x["logits"] - x["logits"].max(1, keepdims=True)
        logp = z - np.log(np.exp(z).sum(1, keepdims=True))
        M = len(z)
        d = np.exp(logp)
        d[np.arange(M), x["targets"]] -= 1
        return [-logp[np.arange(M), x["targets"]], d * x["dloss"][:, None]]

    def pyvf(self, x, plain=False):
        def fn():
            loss, cache = losses.cross_entropy_forward(x["logits"], x["targets"])
            return [loss, *losses.cross_entropy_backward(x["dloss"], cache)]
        return fn

    def torch(self, x):
        import torch
        import torch.nn.functional as F

        lt = torch.from_numpy(x["logits"]).requires_grad_(True)
        t, dl = torch.from_numpy(x["targets"]), torch.from_numpy(x["dloss"])

        def fn():
            loss = F.cross_entropy(lt, t, reduction="none")
            return [loss.detach().numpy(), torch.autograd.grad(loss, lt, dl)[0].numpy()]
        return fn

    def numpy(self, x):
        def fn():  # the textbook form: softmax, then the log of the target's probability
            e = np.exp(x["logits"] - x["logits"].max(1, keepdims=True))
            p = e / e.sum(1, keepdims=True)
            M = len(p)
            loss = -np.log(p[np.arange(M), x["targets"]])
            p[np.arange(M), x["targets"]] -= 1
            return [loss, p * x["dloss"][:, None]]
        return fn


def gelu_mp(x):
    """(gelu(x), gelu'(x)) as mpmath numbers, at mpmath's working precision."""
    import mpmath

    xm = mpmath.mpf(float(x))
    Phi = mpmath.ncdf(xm)
    return xm * Phi, Phi + xm * mpmath.npdf(xm)


def gelu_naive(x):
    """x * 0.5 * (1 + erf(x / sqrt 2)) with erf in float64 (math.erf; NumPy has none), in x's
    dtype, and its derivative 0.5 (1 + erf) + x phi(x): the textbook form, which cancels in the tail."""
    erf = np.vectorize(math.erf, otypes=[np.float64])(x.astype(np.float64) / math.sqrt(2)).astype(x.dtype)
    Phi = x.dtype.type(0.5) * (1 + erf)
    return x * Phi, Phi + x * np.exp(-x * x / 2) * x.dtype.type(1 / math.sqrt(2 * math.pi))


class GELU(Op):
    name, title, outputs = "gelu", "GELU forward + backward (exact erf form)", ("y", "dx")
    elementwise = True

    def inputs(self, rng):
        n = self.size
        x = np.concatenate([3 * rng.standard_normal(n - n // 8), rng.uniform(-12, 0, n // 8)])  # some tail
        return dict(x=_round32(x)[0], dy=np.ones(n))  # dy = 1: dx is gelu'(x) itself, in ulps

    def reference(self, x):
        ys = [gelu_mp(v) for v in x["x"]]
        return [np.array([float(a) for a, _ in ys]), np.array([float(b) for _, b in ys])]

    def pyvf(self, x, plain=False):
        def fn():
            y, cache = layers.gelu_forward(x["x"])
            return [y, *layers.gelu_backward(x["dy"], cache)]
        return fn

    def torch(self, x):
        import torch
        import torch.nn.functional as F

        xt, dy = torch.from_numpy(x["x"]).requires_grad_(True), torch.from_numpy(x["dy"])

        def fn():
            y = F.gelu(xt)
            return [y.detach().numpy(), torch.autograd.grad(y, xt, dy)[0].numpy()]
        return fn

    def numpy(self, x):
        def fn():
            y, d = gelu_naive(x["x"])
            return [y, d * x["dy"]]
        return fn


class Conv2d(Op):
    name, title, outputs = "conv2d", "conv2d 3x3, padding 1, forward + backward", ("y", "dx", "dw", "db")

    def inputs(self, rng):
        B, C, Co, Hi, Wi = self.size
        x, w, b, dy = _round32(rng.standard_normal((B, C, Hi, Wi)),
                               rng.standard_normal((Co, C, 3, 3)) / math.sqrt(9 * C),  # unit-variance y
                               rng.standard_normal(Co), rng.standard_normal((B, Co, Hi, Wi)))
        return dict(x=x, w=w, b=b, dy=dy)

    def _run(self, x, forward, backward):
        y, cache = forward(x["x"], x["w"], x["b"], 1, 1)
        return [y, *backward(x["dy"], cache)]

    def reference(self, x):  # the float64 im2col + BLAS formulation
        return self._run(x, conv.conv2d_forward_numpy, conv.conv2d_backward_numpy)

    def pyvf(self, x, plain=False):
        return lambda: self._run(x, conv.conv2d_forward, conv.conv2d_backward)

    def torch(self, x):
        import torch
        import torch.nn.functional as F

        xt, w, b = (torch.from_numpy(x[n]).requires_grad_(True) for n in ("x", "w", "b"))
        dy = torch.from_numpy(x["dy"])

        def fn():
            y = F.conv2d(xt, w, b, padding=1)
            return [y.detach().numpy()] + [t.numpy() for t in torch.autograd.grad(y, (xt, w, b), dy)]
        return fn

    def numpy(self, x):
        return lambda: self._run(x, conv.conv2d_forward_numpy, conv.conv2d_backward_numpy)


OPS = {cls.name: cls for cls in (AttentionForward, AttentionBackward, VQNearest, LayerNorm, GroupNorm,
                                 CrossEntropy, GELU, Conv2d)}
SIZE_KEY = dict(attention_forward="attention", attention_backward="attention", vq_nearest="vq")


def make_op(name, size="full"):
    return OPS[name](SIZES[size][SIZE_KEY.get(name, name)])


# ---------------------------------------------------------------------------------------
# variants and errors


def variants(op, with_torch=True):
    """[{name, backend, dtype, path, plain, bound}] for op: pyvf float32 on every kernel path this
    process can use (the default path first), pyvf float64, the plain loops, torch, NumPy."""
    b32, b64 = BOUNDS[op.name]
    best = pyvf.kernel_path()
    paths = [best] + [p for p in reversed(pyvf.kernel_paths()) if p != best]
    out = [dict(name=f"pyvf float32 {p}" + (" (default)" if p == best else ""), backend="pyvf",
                dtype="float32", path=p, plain=False, bound=b32) for p in paths]
    out.append(dict(name="pyvf float64", backend="pyvf", dtype="float64", path=best, plain=False, bound=b64))
    if op.has_plain:
        out.append(dict(name="pyvf float32 plain loops", backend="pyvf", dtype="float32", path=best, plain=True,
                        bound=b32))
    if with_torch:
        out.append(dict(name="torch float32", backend="torch", dtype="float32", path=None, plain=False, bound=SANITY))
    out.append(dict(name="numpy float32", backend="numpy", dtype="float32", path=None, plain=False, bound=SANITY))
    return out


def variant_fn(op, x, v):
    """fn() -> list of outputs for variant v on the inputs x (cast to v's dtype here), or None."""
    xs = _cast(x, np.dtype(v["dtype"]))
    if v["backend"] == "pyvf":
        with pyvf.use_kernel_path(v["path"]):
            return op.pyvf(xs, plain=v["plain"])
    return op.torch(xs) if v["backend"] == "torch" else op.numpy(xs)


def ulps(got, want_mp, dtype):
    """max over elements of |got - want| in ulps of the true value in dtype (np.spacing of the
    rounded true value: the subnormal spacing below the normal range); want_mp float64 or mpmath."""
    got = np.asarray(got, dtype=np.float64)
    want = np.asarray(want_mp, dtype=np.float64)
    spacing = np.spacing(np.abs(want).astype(dtype)).astype(np.float64)
    return float((np.abs(got - want) / spacing).max()) if got.size else 0.0


def errors(op, outs, ref, dtype):
    """{output: {rel, abs[, ulps]}} of one variant's outputs against the reference; ValueError
    where an output is missing (or one too many) or of another shape."""
    if len(outs) != len(op.outputs) or len(ref) != len(op.outputs):
        raise ValueError(f"{op.name}: {len(outs)} outputs, reference {len(ref)}, expected {len(op.outputs)} "
                         f"({', '.join(op.outputs)})")
    out = {}
    for name, got, want in zip(op.outputs, outs, ref):
        got = np.asarray(got)
        if got.shape != want.shape:
            raise ValueError(f"{op.name} {name}: shape {got.shape}, reference {want.shape}")
        e = dict(rel=rel_err(got, want) if np.isfinite(got).all() else float("inf"))
        if op.elementwise:
            e["ulps"] = ulps(got, want, np.dtype(dtype))
        out[name] = e
    return out


def run_variant(op, x, ref, v, exact_indices=None):
    """Validate one variant: (the dict that goes into the report, its function, or None where it
    failed and is not timed)."""
    r = {k: v[k] for k in ("name", "backend", "dtype", "path", "bound")}
    fn = variant_fn(op, x, v)
    with pyvf.use_kernel_path(v["path"] or pyvf.kernel_path()):  # torch and NumPy: path None
        outs = fn()
        r["errors"] = errors(op, outs, ref, v["dtype"])
        r["rel"] = max(e["rel"] for e in r["errors"].values())
        if op.elementwise:
            r["ulps"] = {k: e["ulps"] for k, e in r["errors"].items()}
        problems = []
        if not r["rel"] <= v["bound"]:
            problems.append(f"normwise error {r['rel']:.2e} > bound {v['bound']:.1e}")
        if op.elementwise and v["backend"] == "pyvf" and not r["errors"]["y"]["ulps"] <= GELU_ULPS + 1:
            # +1: the subnormal results' rounding step (~1 ulp of the smallest subnormal)
            problems.append(f"y {r['errors']['y']['ulps']:.1f} ulps > {GELU_ULPS} + 1")
        if exact_indices is not None:
            r["wrong_codes"] = int((fn.indices != exact_indices).sum())
            if v["backend"] == "pyvf" and r["wrong_codes"] > WRONG_CODES_ALLOWED:
                problems.append(f"{r['wrong_codes']} rows with a wrong code")
        if problems:
            r["fail"] = "; ".join(problems)
            return r, None
    return r, fn


def time_variants(timed, repeat):
    """Time the validated variants [(report dict, fn, kernel path)]: pyvf's in interleaved rounds
    (round i calls each once, in order), so that a transient (NumPy's BLAS threads spinning on the
    cores after the float64 reference) falls on each alike: timed one after another, the first of
    an op's variants took it all (the avx512 conv2d measured slower than avx2, 7.1 vs 6.1 ms, though
    30% faster alone). torch's and NumPy's one after another, after pyvf's: interleaved with pyvf's
    calls, torch's OpenMP threads and pyvf's (another runtime) would spin on each other's cores.
    Sets each dict's seconds (median) and times."""
    ours = [t for t in timed if t[0]["backend"] == "pyvf"]
    times = [[] for _ in ours]
    for _ in range(1 + repeat):  # the first round is the warm-up
        for i, (r, fn, path) in enumerate(ours):
            with pyvf.use_kernel_path(path):
                t0 = time.perf_counter()
                fn()
                times[i].append(time.perf_counter() - t0)
    for (r, _, _), t in zip(ours, times):
        r["times"] = t[1:]
        r["seconds"] = statistics.median(r["times"])
    for r, fn, path in [t for t in timed if t[0]["backend"] != "pyvf"]:
        with pyvf.use_kernel_path(path):
            r["seconds"], r["times"] = median_time(fn, repeat, warmup=1)


def run_op(name, size="full", repeat=5, with_torch=True, seed=0, log=print):
    """Every variant of one op: {op, title, outputs, size, reference_seconds, variants: [...]}."""
    op = make_op(name, size)
    x = op.inputs(np.random.default_rng(seed))
    t0 = time.perf_counter()
    ref = op.reference(x)
    res = dict(op=name, title=op.title, outputs=list(op.outputs), size=op.size, elementwise=op.elementwise,
               reference_seconds=time.perf_counter() - t0, variants=[])
    exact = op.exact_indices(x) if isinstance(op, VQNearest) else None
    timed = []
    for v in variants(op, with_torch):
        r, fn = run_variant(op, x, ref, v, exact)
        res["variants"].append(r)
        if fn is not None:
            timed.append((r, fn, v["path"] or pyvf.kernel_path()))
    time_variants(timed, repeat)
    for r in res["variants"]:
        log(f"  {name:<19} {r['name']:<28} err {r['rel']:.2e}  "
            + (f"FAIL: {r['fail']}" if "fail" in r else f"{r['seconds'] * 1e3:.2f} ms"), flush=True)
    return res


# ---------------------------------------------------------------------------------------
# output


def _e(x):
    return "-" if x is None else ("inf" if x == float("inf") else f"{x:.2e}")


def op_table(res):
    """The markdown table of one op's variants."""
    rows = []
    ew = res["elementwise"]
    vq = res["op"] == "vq_nearest"
    for r in res["variants"]:
        row = [r["name"], _e(r["rel"])]
        if ew:
            row.append(" / ".join(f"{u:.3g}" for u in r["ulps"].values()))
        if vq:
            row.append(str(r.get("wrong_codes", "-")))
        row += [f"{r['seconds'] * 1e3:.3g} ms" if "seconds" in r else "-",
                f"{r['bound']:.0e}", f"FAIL: {r['fail']}" if "fail" in r else "ok"]
        rows.append(row)
    head = ["variant", "normwise rel. error"]
    head += [f"max ulps ({' / '.join(res['outputs'])})"] if ew else []
    head += (["wrong codes"] if vq else []) + ["time (median)", "bound", "validated"]
    return table(head, rows)


# Timings closer than this are not told apart: the medians of one call move by up to 10% between
# runs on a loaded 2-core VM, and one code on two kernel paths (cross_entropy is NumPy on every
# path) read up to 5% apart. Errors are compared exactly: they are deterministic.
TIME_TOL = 0.10
FRONT_RULE = f"more than {TIME_TOL:.0%} faster and as accurate, or as fast and more accurate"


def beats(a, b, tol=TIME_TOL):
    """How point a = (time, error) beats point b, or None: "faster and as accurate" (more than
    tol faster, an error at most b's) or "as fast and more accurate" (at most tol slower, a smaller
    error). Neither can hold both ways, and no chain of them returns to its start (along one the
    error never grows, and the time falls where it does not fall), so a front always exists."""
    (ta, ea), (tb, eb) = a, b
    if ta * (1 + tol) < tb and ea <= eb:
        return "faster and as accurate"
    if ta <= tb * (1 + tol) and ea < eb:
        return "as fast and more accurate"
    return None


def pareto(points, tol=TIME_TOL):
    """The indices of the points (time, error) that no other point beats (beats)."""
    return [i for i, p in enumerate(points) if not any(beats(q, p, tol) for q in points)]


FLOOR = 1e-17  # where an error of exactly 0 is drawn on a log axis


def plot(results, folder, prefix="accuracy-"):
    """A time-vs-error plot per op: {prefix}{op}.png in folder, each variant a point, the Pareto
    front joined, the unit roundoffs (the floor: an output's own rounding) dotted, the legend beside
    the axes. Returns the files, or None without matplotlib."""
    plt = pyplot()
    if plt is None:
        return None
    os.makedirs(folder, exist_ok=True)
    files = []
    for res in results:
        pts = [r for r in res["variants"] if "seconds" in r]
        if not pts:
            continue
        fig, ax = plt.subplots(figsize=(8.4, 4.4), layout="constrained")
        xy = [(r["seconds"] * 1e3, max(r["rel"], FLOOR)) for r in pts]
        for (t, e), r in zip(xy, pts):
            marker = {"pyvf": "o", "torch": "s", "numpy": "^"}[r["backend"]]
            ax.loglog(t, e, marker, ms=8, label=r["name"])
        front = sorted(xy[i] for i in pareto(xy))
        ax.plot(*zip(*front), "k--", lw=0.8, alpha=0.6, label="Pareto front")
        for u in (U32, U64):
            ax.axhline(u, color="0.4", ls=":", lw=1.0, label=f"unit roundoff, float32 {U32:.1e} / float64 {U64:.1e}")
        lo, hi = ax.get_ylim()
        ax.set_ylim(min(lo, U64 / 3), max(hi, U32 * 3))  # both roundoffs in view
        ax.set_xlabel("median time (ms)")
        zero = any(r["rel"] == 0 for r in pts)
        ax.set_ylabel("normwise relative error vs float64 reference" + (f"\n(an error of 0 drawn at {FLOOR:.0e})"
                                                                        if zero else ""))
        ax.set_title(f"{res['title']}\n{res['op']} size {res['size']}", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        log_ticks(ax.xaxis)
        legend_outside(fig)
        path = os.path.join(folder, f"{prefix}{res['op'].replace('_', '-')}.png")
        save_figure(fig, path, dpi=100)
        files.append(path)
    return files


def run(ops=tuple(OPS), size="full", repeat=5, threads=2, log=print):
    """The whole benchmark: the report dict (machine, results per op, failures)."""
    t0 = time.perf_counter()
    pyvf.set_num_threads(threads)
    torch = torch_or_none()
    if torch is not None:
        torch.set_num_threads(threads)
    with_torch = torch is not None
    results = [run_op(name, size, repeat, with_torch, log=log) for name in ops]
    failures = [f"{res['op']} / {r['name']}: {r['fail']}" for res in results for r in res["variants"] if "fail" in r]
    return dict(config=dict(size=size, sizes={n: make_op(n, size).size for n in ops}, repeat=repeat, bounds=BOUNDS,
                            gelu_ulps=GELU_ULPS, sanity=SANITY, torch=with_torch),
                machine=machine(threads), results=results, failures=failures,
                total_seconds=time.perf_counter() - t0)


def print_report(report):
    """The machine, then each op's table of variants (op_table)."""
    m = report["machine"]
    print(f"\nmachine: {m['processor']}, {m['cpu_count']} CPUs; kernel path {m['kernel_path']} "
          f"(this CPU runs {', '.join(m['kernel_paths'])}); {m['threads']} threads")
    for res in report["results"]:
        print(f"\n## {res['title']} ({res['op']}, size {res['size']})\n")
        print(op_table(res))
