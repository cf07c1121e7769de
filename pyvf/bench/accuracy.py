"""Speed against error: each op of pyvf, its error against a float64 reference beside its time,
and the same for torch and the textbook NumPy formula.

    pyvf bench accuracy            # ~1 minute on 2 cores
    pyvf bench accuracy --quick    # small sizes, seconds

The ops, forward and backward, every output compared: attention (pyvf.branching_attention_forward
and _backward), vq_nearest (pyvf.vq_nearest: the squared distance to the code chosen), layernorm
and gelu (pyvf.nn.layers), cross_entropy (pyvf.nn.losses), conv2d (pyvf.nn.conv). Variants: pyvf
float32 and float64, torch float32 and the textbook NumPy formula in float32 (the dense masked
softmax, the expanded |x|^2 - 2 x.e + |e|^2 distance, two-pass moments, softmax then log,
0.5 (1 + erf), shifted-window conv), all on the same numbers (drawn in float64, rounded to
float32). Error: max|x - ref| / max|ref|, the largest over the op's outputs, against a float64
reference (mpmath for GELU, whose float64 erf form loses every digit in the tail). Each variant is
validated before it is timed: pyvf against its tests' bound (BOUNDS), torch and NumPy against
SANITY (a wrong mask or layout is an O(1) error); one outside its bound is not timed, a failure.
Time: the median of 5 calls (3 with --quick) after a warm-up.
"""

import math

import numpy as np

import pyvf
from pyvf.bench import attention
from pyvf.bench.common import machine, median_time, ms, save_plot, table, torch_or_none, validate
from pyvf.bench.vq import brute_force
from pyvf.nn import conv, layers, losses

U32, U64 = 2.0 ** -24, 2.0 ** -53  # unit roundoff
SIZES = {  # by --quick
    False: dict(attention=(3, 1, 4, 8, 64, 64), vq_nearest=(8192, 1024, 64), layernorm=(4096, 256),
                cross_entropy=(2048, 1024), gelu=8192, conv2d=(4, 64, 64, 32, 32)),
    True: dict(attention=(3, 1, 2, 4, 32, 32), vq_nearest=(2048, 256, 32), layernorm=(512, 128),
               cross_entropy=(256, 512), gelu=2048, conv2d=(2, 16, 16, 16, 16)),
}
# pyvf's bounds (normwise relative, every output; float32, float64), the tests' where they have one:
BOUNDS = {
    "attention": (attention.BOUND32, attention.BOUND64),
    # the distance is summed in float64 from the chosen code and rounded once; in float64 a D-term
    # sum in another order than the reference's: D u = 7e-15 at D = 64
    "vq_nearest": (2 * U32, 1e-14),
    # dgamma and dbeta are float32 sums of 4096 rows of random-signed terms: ~12 u sqrt(n) = 4.6e-5
    # at worst, measured 2.1e-6 (NumPy's own float32 sum too): 1e-5
    "layernorm": (1e-5, 1e-13),
    # the log-sum-exp of V terms and one exp per dlogit: a few u on O(1) outputs; measured 2.3e-7
    "cross_entropy": (1e-6, 1e-13),
    "gelu": (4e-7, 1e-13),  # tests/test_layers.py RTOL32["gelu"], RTOL64
    # K = 576 terms per output and dw over 4096 pixels: sqrt(K) u = 1.4e-6 at worst, measured 5e-7
    "conv2d": (2e-6, 1e-13),
}
# torch and NumPy compute the same function in float32 in their own order: a wiring error (mask,
# layout, eps) is O(1e-2..1); their rounding 1e-4 at most
SANITY = 1e-3


# ops: each a function (size, rng) -> dict(outputs, inputs (float64 arrays of float32 values),
# reference (a list of float64 outputs), and pyvf, numpy, torch: x (the inputs in the variant's
# dtype) -> fn() -> the outputs)


def _round32(*arrays):
    return [a.astype(np.float32).astype(np.float64) for a in arrays]


def _pair(forward, backward, dy, *args):
    """fn() -> [y, *gradients] of a layer pair: y, cache = forward(*args); backward(dy, cache)."""
    def fn():
        y, cache = forward(*args)
        return [y, *backward(dy, cache)]
    return fn


def _torch_vjp(f, dy, *args):
    """fn() -> [y, *the gradients of args' float arrays] of y = f(F, *args) by torch autograd, upstream dy."""
    import torch
    from torch.nn import functional as F

    ts = [torch.from_numpy(a).requires_grad_(a.dtype.kind == "f") for a in args]

    def fn():
        y = f(F, *ts)
        return [y.detach().numpy()] + [g.numpy() for g in torch.autograd.grad(
            y, [t for t in ts if t.requires_grad], torch.from_numpy(dy))]
    return fn


def attention_op(size, rng):
    """Branching attention forward + backward (pyvf bench attention's contenders): o, dq, dk, dv."""
    x = _round32(*(rng.standard_normal(size) for _ in range(4)))  # q, k, v, do
    outs = lambda contender: lambda x: contender(*x.values())["outs"]  # noqa: E731
    return dict(outputs=attention.NAMES, inputs=dict(zip("qkvd", x)), pyvf=outs(attention.pyvf_contender),
                reference=attention.reference_contender(*x)["outs"](),  # in float64: the oracle
                numpy=outs(attention.reference_contender), torch=outs(attention.torch_contender))


def vq_op(size, rng):
    M, K, D = size
    codes = rng.standard_normal((K, D))
    x, codes = _round32(codes[rng.integers(0, K, M)] + 0.7 * rng.standard_normal((M, D)), codes)  # near a code
    best = brute_force(x, codes)  # float64 direct differences, the first minimum

    def numpy_fn(x):  # the published quantizer's expanded formula
        d = (x["x"] ** 2).sum(1, keepdims=True) - 2 * x["x"] @ x["codes"].T + (x["codes"] ** 2).sum(1)  # (M, K)
        return [d[np.arange(M), d.argmin(1)]]

    def torch_fn(x):
        import torch
        xt, ct = torch.from_numpy(x["x"]), torch.from_numpy(x["codes"])
        return lambda: [(torch.cdist(xt, ct).min(dim=1)[0] ** 2).numpy()]

    return dict(outputs=("sq_dist",), inputs=dict(x=x, codes=codes), reference=[((x - codes[best]) ** 2).sum(1)],
                pyvf=lambda x: lambda: [pyvf.vq_nearest(x["x"], x["codes"])[1]], numpy=lambda x: lambda: numpy_fn(x),
                torch=torch_fn)


def layernorm_op(size, rng):
    """LayerNorm over the rows of (M, d), forward + backward: y, dx, dgamma, dbeta."""
    M, d = size
    x = rng.standard_normal(size) * rng.uniform(0.1, 3, (M, 1)) + rng.uniform(-3, 3, (M, 1))  # rows' own scale, offset
    x = dict(zip(("x", "gamma", "beta", "dy"), _round32(x, 1 + 0.1 * rng.standard_normal(d),
                                                         0.1 * rng.standard_normal(d), rng.standard_normal(size))))

    def numpy_fn(x):  # the textbook two-pass moments
        xc = x["x"] - x["x"].mean(-1, keepdims=True)
        rstd = 1 / np.sqrt((xc * xc).mean(-1, keepdims=True) + x["x"].dtype.type(1e-5))
        xhat, dxhat = xc * rstd, x["dy"] * x["gamma"]
        dx = rstd * (dxhat - dxhat.mean(-1, keepdims=True) - xhat * (dxhat * xhat).mean(-1, keepdims=True))
        return [xhat * x["gamma"] + x["beta"], dx, (x["dy"] * xhat).sum(0), x["dy"].sum(0)]

    return dict(outputs=("y", "dx", "dgamma", "dbeta"), inputs=x, reference=numpy_fn(x),
                numpy=lambda x: lambda: numpy_fn(x),
                torch=lambda x: _torch_vjp(lambda F, *a: F.layer_norm(a[0], (d,), *a[1:], 1e-5), x["dy"], x["x"],
                                           x["gamma"], x["beta"]),
                pyvf=lambda x: _pair(layers.layernorm_forward, layers.layernorm_backward, x["dy"], x["x"], x["gamma"],
                                     x["beta"], 1e-5))


def cross_entropy_op(size, rng):
    M, V = size
    logits, dloss = _round32(3 * rng.standard_normal((M, V)), rng.standard_normal(M))
    t = rng.integers(0, V, M)

    def numpy_fn(x, log_softmax=False):  # the textbook form: softmax, then the log (the reference: log-sum-exp)
        z = x["logits"] - x["logits"].max(1, keepdims=True)
        logp = z - np.log(np.exp(z).sum(1, keepdims=True)) if log_softmax else np.log(
            np.exp(z) / np.exp(z).sum(1, keepdims=True))
        d = np.exp(logp)
        d[np.arange(M), t] -= 1
        return [-logp[np.arange(M), t], d * x["dloss"][:, None]]

    x = dict(logits=logits, dloss=dloss)
    return dict(outputs=("loss", "dlogits"), inputs=x, reference=numpy_fn(x, log_softmax=True),
                numpy=lambda x: lambda: numpy_fn(x),
                pyvf=lambda x: _pair(losses.cross_entropy_forward, losses.cross_entropy_backward, x["dloss"], x["logits"], t),
                torch=lambda x: _torch_vjp(lambda F, z, t: F.cross_entropy(z, t, reduction="none"), x["dloss"],
                                           x["logits"], t))


def gelu_mp(x):
    """(gelu(x), gelu'(x)) as mpmath numbers, at mpmath's working precision."""
    import mpmath

    xm = mpmath.mpf(float(x))
    return xm * mpmath.ncdf(xm), mpmath.ncdf(xm) + xm * mpmath.npdf(xm)


def gelu_naive(x):
    """x 0.5 (1 + erf(x / sqrt 2)) (erf in float64, NumPy has none; the result in x's dtype) and its
    derivative 0.5 (1 + erf) + x phi(x): the textbook form, which cancels in the tail."""
    erf = np.vectorize(math.erf, otypes=[np.float64])(x.astype(np.float64) / math.sqrt(2)).astype(x.dtype)
    Phi = x.dtype.type(0.5) * (1 + erf)
    return x * Phi, Phi + x * np.exp(-x * x / 2) * x.dtype.type(1 / math.sqrt(2 * math.pi))


def gelu_op(n, rng):
    x = _round32(np.concatenate([3 * rng.standard_normal(n - n // 8), rng.uniform(-12, 0, n // 8)]))[0]  # some tail
    dy = _round32(rng.standard_normal(n))[0]
    ys = [gelu_mp(v) for v in x]

    def numpy_fn(x):
        y, d = gelu_naive(x["x"])
        return [y, d * x["dy"]]

    return dict(outputs=("y", "dx"), inputs=dict(x=x, dy=dy), torch=lambda x: _torch_vjp(
        lambda F, a: F.gelu(a), x["dy"], x["x"]), numpy=lambda x: lambda: numpy_fn(x),
                pyvf=lambda x: _pair(layers.gelu_forward, layers.gelu_backward, x["dy"], x["x"]),
                reference=[np.array([float(a) for a, _ in ys]), np.array([float(b) for _, b in ys]) * dy])


def conv_windows(x, w, b, dy):
    """3x3 convolution, padding 1, by shifted windows (y, dx, dw, db): y[n,o,i,j] = b[o] + sum_{c,a,e}
    w[o,c,a,e] xp[n,c,i+a,j+e], xp x padded by 1; dx scatters dy back through the same windows."""
    Hi, Wi = x.shape[2:]
    xp = np.pad(x, ((0, 0), (0, 0), (1, 1), (1, 1)))
    win = np.lib.stride_tricks.sliding_window_view(xp, (3, 3), axis=(2, 3))  # (B, C, Hi, Wi, 3, 3)
    y = np.einsum("bchwae,ocae->bohw", win, w, optimize=True) + b[:, None, None]
    dxp = np.zeros_like(xp)
    for a in range(3):
        for e in range(3):
            dxp[:, :, a:a + Hi, e:e + Wi] += np.einsum("bohw,oc->bchw", dy, w[:, :, a, e])
    return [y, dxp[:, :, 1:-1, 1:-1], np.einsum("bchwae,bohw->ocae", win, dy, optimize=True), dy.sum((0, 2, 3))]


def conv2d_op(size, rng):
    B, C, Co, Hi, Wi = size
    x = dict(zip(("x", "w", "b", "dy"), _round32(rng.standard_normal((B, C, Hi, Wi)),
                                                 rng.standard_normal((Co, C, 3, 3)) / math.sqrt(9 * C),
                                                 rng.standard_normal(Co), rng.standard_normal((B, Co, Hi, Wi)))))

    return dict(outputs=("y", "dx", "dw", "db"), inputs=x, reference=conv_windows(*x.values()),
                pyvf=lambda x: _pair(conv.conv2d_forward, conv.conv2d_backward, x["dy"], x["x"], x["w"], x["b"], 1, 1),
                torch=lambda x: _torch_vjp(lambda F, *a: F.conv2d(*a, padding=1), x["dy"], x["x"], x["w"], x["b"]),
                numpy=lambda x: lambda: conv_windows(*x.values()))


OPS = {"attention": attention_op, "vq_nearest": vq_op, "layernorm": layernorm_op, "cross_entropy": cross_entropy_op,
       "gelu": gelu_op, "conv2d": conv2d_op}  # name -> its function (size, rng)


def run_op(name, quick=False, repeat=5, log=print):
    """One op's variants, each validated, then timed: {op, size, variants: [{name, backend, bound, rel, seconds or fail}]}."""
    size = SIZES[quick][name]
    op, (b32, b64) = OPS[name](size, np.random.default_rng(0)), BOUNDS[name]
    res = dict(op=name, size=size, variants=[])
    for vname, backend, dtype, bound in (("pyvf float32", "pyvf", np.float32, b32), ("pyvf float64", "pyvf", np.float64, b64),
                                         ("torch float32", "torch", np.float32, SANITY),
                                         ("numpy float32", "numpy", np.float32, SANITY)):
        if backend == "torch" and torch_or_none() is None:
            continue
        fn = op[backend]({k: v.astype(dtype) for k, v in op["inputs"].items()})
        errors, ok = validate(fn(), op["reference"], op["outputs"], bound)
        r = dict(name=vname, backend=backend, bound=bound, rel=max(errors.values()))
        if ok:
            r["seconds"] = median_time(fn, repeat)[0]
        else:
            r["fail"] = f"normwise error {r['rel']:.2e} > bound {bound:.0e}"
        log(f"  {name:<19} {vname:<14} err {r['rel']:.2e}  {r.get('fail') or ms(r['seconds'])}", flush=True)
        res["variants"].append(r)
    return res


def op_table(res):
    """The markdown table of one op's variants."""
    return table(["variant", "normwise rel. error", "time (median)", "bound", "validated"],
                 [[r["name"], f"{r['rel']:.2e}", ms(r.get("seconds")), f"{r['bound']:.0e}",
                   f"FAIL: {r['fail']}" if "fail" in r else "ok"] for r in res["variants"]])


def plot_op(res, folder):
    """accuracy-<op>.png in folder: a point (time, error) per variant timed, the unit roundoffs dotted."""
    done = [r for r in res["variants"] if "seconds" in r]
    t = [r["seconds"] * 1e3 for r in done] or [1.0]
    lines = {r["name"]: ([r["seconds"] * 1e3], [r["rel"]], dict(pyvf="o", torch="s", numpy="^")[r["backend"]])
             for r in done}
    lines.update({f"unit roundoff, {n} {u:.1e}": ([min(t), max(t)], [u, u], "k:") for n, u in (("float32", U32),
                                                                                            ("float64", U64))})
    return save_plot(folder, f"accuracy-{res['op'].replace('_', '-')}.png", lines, f"{res['op']}, size {res['size']}",
                     "median time (ms)", "normwise relative error vs float64 reference")


def run(quick=False, threads=2, ops=tuple(OPS), plots=None, log=print):
    """Every op named, printed and plotted into the folder plots: {config, machine, results (run_op's), failures}."""
    repeat = 3 if quick else 5
    report = dict(config=dict(quick=quick, repeat=repeat), machine=machine(threads))
    results = report["results"] = [run_op(name, quick, repeat, log=log) for name in ops]
    for res in results:
        log(f"\n## {res['op']}, size {res['size']}\n\n{op_table(res)}")
        if plots:
            res["plot"] = plot_op(res, plots)
    report["failures"] = [f"{res['op']} / {r['name']}: {r['fail']}" for res in results for r in res["variants"]
                          if "fail" in r]
    return report
