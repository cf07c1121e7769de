"""Numerical stability on hard inputs: sweeps that push one quantity across orders of magnitude,
showing where the textbook formula breaks and that pyvf stays within its stated bound throughout.

    pyvf bench hardcases           # ~1 minute on 2 cores
    pyvf bench hardcases --quick   # fewer points, smaller problems

Each sweep has a line per variant (its error against a reference at every point, computed on the
very numbers the variants see: float64, long double for the norm, mpmath for GELU and the
cross-entropy) and pyvf's bound as a function of the swept quantity. A pyvf line that leaves its
bound anywhere (a NaN or an inf counts as an error of inf) is a failure. The nearest code's
cancellation far from the origin is `pyvf bench vq`'s table of offsets.

    attention-spread  logits of size s = 1..1e6 (random q, k): float32 softmax without the max
                      subtracted overflows at s ~ 88; pyvf, torch and the max-subtracted reference
                      are limited by the logits' own float32 rounding, delta ~ dh u s
    attention-mask    attended logits near -s, s = 1..1e6: the published mask, logits * mask - 1e4 *
                      (1 - mask), puts the weight on the masked keys once s > 1e4; pyvf excludes them
    layernorm         rows of mean s times their spread, s = 1..1e6: the one-pass variance
                      E[x^2] - E[x]^2 cancels; pyvf's two passes do not
    gelu              x in [-40, 0], error in ulps of the true value: 0.5 (1 + erf(x/sqrt 2)) (torch's
                      exact GELU) cancels from x ~ -6 and is 0 past -8.4 (float64)
    cross-entropy     target logit s = 1..1e4 below the row's maximum: -log(softmax) gives inf once
                      the probability underflows; the log-sum-exp form does not
"""

import functools
import math

import numpy as np

import pyvf
from pyvf.bench.accuracy import U32, U64, gelu_mp, gelu_naive
from pyvf.bench.attention import flat
from pyvf.bench.common import machine, save_plot, torch_or_none
from pyvf.nn import layers, losses


def _err(got, ref, scale):
    """max|got - ref| / scale, inf where got holds a NaN or an inf."""
    got = np.asarray(got, dtype=np.float64)
    return float(np.abs(got - ref).max() / scale) if np.isfinite(got).all() else float("inf")


def _dense(q, k, v, mask, sentinel=False, subtract_max=True):
    """Dense attention on flat (B, H, T, dh) arrays in their dtype: exact exclusion (-inf), or the
    published sentinel logits * mask - 1e4 * (1 - mask); subtract_max=False: exp of the raw logits."""
    s = q @ k.swapaxes(-1, -2)  # (B, H, T, T)
    with np.errstate(over="ignore", invalid="ignore"):
        m = mask.astype(s.dtype)
        s = s * m - s.dtype.type(1e4) * (1 - m) if sentinel else np.where(mask, s, -np.inf)
        p = np.exp(s - s.max(-1, keepdims=True) if subtract_max else s)
        return p / p.sum(-1, keepdims=True) @ v


def attention_sweep(name, quick, rng):
    """attention-spread or attention-mask; the error relative to max|v| (o is a weighted mean of v)."""
    shape = (3, 1, 2, 3, 8, 16) if quick else (3, 1, 2, 4, 16, 32)  # (R, B, H, N, L, dh)
    R, B, H, N, L, dh = shape
    mask = pyvf.branching_mask(R, N, L)
    torch = torch_or_none()
    lines, bounds = {}, {"pyvf float32": [], "pyvf float64": []}
    values = np.logspace(0, 6, 7 if quick else 13)
    for s in values:
        q, k, v = (rng.standard_normal(shape) for _ in range(3))
        if name == "attention-spread":  # |logit| up to s
            scale = math.sqrt(s / np.abs(flat(q) @ flat(k).swapaxes(-1, -2)).max())
            q, k = q * scale, k * scale
        else:  # every logit -s + O(sqrt(dh))
            q[..., 0], k[..., 0] = -math.sqrt(s), math.sqrt(s)
        x32 = [a.astype(np.float32) for a in (q, k, v)]
        x64 = [a.astype(np.float64) for a in x32]
        ref = flat(pyvf.branching_attention_reference(*x64))
        f32, f64 = [flat(a) for a in x32], [flat(a) for a in x64]
        outs = {"pyvf float32": flat(pyvf.branching_attention(*x32)),
                "pyvf float64": flat(pyvf.branching_attention(*x64)), "numpy exact float32": _dense(*f32, mask),
                "naive exp (no max) float32": _dense(*f32, mask, subtract_max=False),
                "published -1e4 mask float32": _dense(*f32, mask, sentinel=True),
                "published -1e4 mask float64": _dense(*f64, mask, sentinel=True)}
        if torch:
            outs["torch SDPA float32"] = torch.nn.functional.scaled_dot_product_attention(
                *map(torch.from_numpy, f32), attn_mask=torch.from_numpy(mask), scale=1.0).numpy()
        for line, o in outs.items():
            lines.setdefault(line, []).append(_err(o, ref, np.abs(x64[2]).max()))
        logits = np.where(mask, np.abs(f64[0]) @ np.abs(f64[1]).swapaxes(-1, -2), 0)
        bounds["pyvf float32"].append(float(np.expm1(2 * dh * U32 / (1 - dh * U32) * logits.max()) + 1e-5))
        bounds["pyvf float64"].append(float(4 * np.abs(np.where(mask, f64[0] @ f64[1].swapaxes(-1, -2), 0)).max()
                                            * U64 + 1e-12))
    title = ("attention: logits of size s (random q, k)" if name == "attention-spread" else
             "attention: attended logits near -s, exact exclusion vs the published -1e4 mask")
    return dict(name=name, title=title, xlabel="s", ylabel="max |o - o_ref| / max |v|", x=list(values), lines=lines,
                bounds=bounds, bound_text="float32: e^(2 delta) - 1 + 1e-5, delta = dh u max sum|q k| (the logits' "
                                          "float32 rounding); float64: 4 s u64 + 1e-12")


def layernorm_sweep(quick, rng):
    """Rows of mean +-s and spread 1, gamma = 1, beta = 0 (y = xhat); the reference in long double."""
    shape, eps = ((64, 64) if quick else (256, 256)), 1e-5
    torch, lines = torch_or_none(), {}
    values = np.logspace(0, 6, 7 if quick else 13)
    for s in values:
        x = s * rng.choice([-1.0, 1.0], (shape[0], 1)) + rng.standard_normal(shape)
        for dtype, tag in ((np.float32, "float32"), (np.float64, "float64")):
            xd = x.astype(dtype)
            xl = xd.astype(np.longdouble)
            xc = xl - xl.mean(-1, keepdims=True)
            xc -= xc.mean(-1, keepdims=True)
            ref = (xc / np.sqrt((xc * xc).mean(-1, keepdims=True) + np.longdouble(eps))).astype(np.float64)
            ys = {f"pyvf {tag}": layers.layernorm_forward(xd, np.ones(shape[1], dtype), np.zeros(shape[1], dtype), eps)[0]}
            m, eps_d = xd.mean(-1, keepdims=True), dtype(eps)
            with np.errstate(all="ignore"):
                ys[f"one-pass {tag}"] = (xd - m) / np.sqrt(np.maximum((xd * xd).mean(-1, keepdims=True) - m * m, 0) + eps_d)
            if tag == "float32":
                ys["numpy two-pass float32"] = (xd - m) / np.sqrt(xd.var(-1, keepdims=True) + eps_d)
                if torch:
                    ys["torch float32"] = torch.nn.functional.layer_norm(torch.from_numpy(xd), (shape[1],), eps=eps).numpy()
            for name, y in ys.items():
                lines.setdefault(name, []).append(_err(y, ref, np.abs(ref).max()))
    return dict(name="layernorm", title=f"LayerNorm: rows of mean +-s, spread 1 ({shape[0]} rows of d={shape[1]})",
                xlabel="s = |mean| / spread", ylabel="max |y - y_ref| / max |y_ref|", x=list(values), lines=lines,
                bounds={"pyvf float32": [1e-6] * len(values), "pyvf float64": [1e-13] * len(values)},
                bound_text="float32 1e-6, float64 1e-13 (the tests' bounds for ordinary rows), at every s")


def gelu_sweep(quick, rng):
    """x on [-40, 0]; the error in ulps (np.spacing) of the true value; pyvf's bound: tests/test_layers.py's."""
    x64 = np.linspace(0, -40, 21 if quick else 161)
    want = np.array([[float(a), float(b)] for a, b in map(gelu_mp, x64)])  # (n, 2): gelu, gelu'
    torch = torch_or_none()
    lines, bounds = {}, {}
    for dtype, tag in ((np.float32, "float32"), (np.float64, "float64")):
        x, ft = x64.astype(dtype), np.finfo(dtype)
        sp = lambda w: np.spacing(np.abs(w).astype(dtype)).astype(np.float64)  # noqa: E731  (an ulp of w in dtype)

        def ulps(got, w):
            return list(np.where(np.isfinite(got), np.abs(np.asarray(got, np.float64) - w) / sp(w), np.inf))

        y, cache = layers.gelu_forward(x)
        (dx,) = layers.gelu_backward(np.ones_like(x), cache)
        Phi = np.abs(want[:, 0] / np.where(x64 == 0, 1, x64))
        slack = np.where(Phi < ft.smallest_normal, np.abs(x64) * float(ft.smallest_subnormal), 0)
        lines[f"pyvf {tag}"], bounds[f"pyvf {tag}"] = ulps(y, want[:, 0]), list(4 + slack / sp(want[:, 0]))
        # gelu' = Phi + x phi cancels near its zero, x = -0.7518: a few ulps of |Phi| + |x phi| there
        cond = (Phi + np.abs(want[:, 1] - Phi)) / np.where(want[:, 1] == 0, 1, np.abs(want[:, 1]))
        lines[f"pyvf {tag} gelu'"], bounds[f"pyvf {tag} gelu'"] = ulps(dx, want[:, 1]), list(4 * cond + slack / sp(want[:, 1]))
        lines[f"naive 0.5 (1 + erf) {tag}"] = ulps(gelu_naive(x)[0], want[:, 0])
        if torch:
            lines[f"torch {tag}"] = ulps(torch.nn.functional.gelu(torch.from_numpy(x)).numpy(), want[:, 0])
    return dict(name="gelu", title="GELU on [-40, 0] against mpmath (in ulps of the true value)", xlabel="x",
                ylabel="|error| in ulps of the true value", x=list(x64), lines=lines, bounds=bounds, logx=False,
                bound_text="4 ulp (plus |x| * smallest subnormal where Phi(x) is subnormal), float32 and float64; "
                           "gelu': 4 ulp of |Phi| + |x phi| (its two terms cancel near x = -0.75)")


def cross_entropy_sweep(quick, rng):
    """Rows of V logits N(0, 1), the target's s below the row's maximum; the reference: mpmath's log-sum-exp."""
    import mpmath

    M, V = (4, 256) if quick else (16, 1024)
    values = np.logspace(0, 4, 5 if quick else 9)
    torch, lines = torch_or_none(), {}
    targets = rng.integers(0, V, M)
    for s in values:
        base = rng.standard_normal((M, V))
        base[np.arange(M), targets] = base.max(1) - s
        for dtype, tag in ((np.float32, "float32"), (np.float64, "float64")):
            logits = base.astype(dtype)
            ref = np.array([float(mpmath.log(mpmath.fsum(mpmath.exp(mpmath.mpf(float(v))) for v in row))
                                  - mpmath.mpf(float(row[t]))) for row, t in zip(logits, targets)])
            ys = {f"pyvf {tag}": losses.cross_entropy_forward(logits, targets)[0]}
            with np.errstate(all="ignore"):
                e = np.exp(logits - logits.max(1, keepdims=True))
                ys[f"naive -log(softmax) {tag}"] = -np.log((e / e.sum(1, keepdims=True))[np.arange(M), targets])
            if torch and tag == "float32":
                ys["torch float32"] = torch.nn.functional.cross_entropy(torch.from_numpy(logits), torch.from_numpy(targets),
                                                                        reduction="none").numpy()
            for name, loss in ys.items():
                lines.setdefault(name, []).append(_err(np.asarray(loss, np.float64) / ref, 1.0, 1.0))
    return dict(name="cross-entropy", title=f"cross-entropy: target logit s below the row's maximum (V={V})",
                xlabel="s = max logit - target logit", ylabel="max |loss - loss_ref| / loss_ref", x=list(values),
                lines=lines, bounds={"pyvf float32": [(V + 4) * U32] * len(values), "pyvf float64": [(V + 4) * U64] * len(values)},
                bound_text=f"(V + 4) u relative, V = {V}: the V-term sum of exponentials, the log, and the one "
                           "rounding of the target logit's difference")


SWEEPS = {"attention-spread": functools.partial(attention_sweep, "attention-spread"),
          "attention-mask": functools.partial(attention_sweep, "attention-mask"),
          "layernorm": layernorm_sweep, "gelu": gelu_sweep, "cross-entropy": cross_entropy_sweep}


def check(sw):
    """{line: {first_x_out: the first x where it leaves its bound, or None; worst_ratio: error / bound}}:
    a pyvf line against its own bound, another against the first pyvf bound of its precision."""
    x, bounds = np.asarray(sw["x"]), {n: np.array(b) for n, b in sw["bounds"].items()}
    b32 = next(b for n, b in bounds.items() if "float32" in n)
    b64 = next((b for n, b in bounds.items() if "float64" in n), b32)
    out = {}
    for name, vals in sw["lines"].items():
        vals, b = np.array(vals, dtype=np.float64), bounds.get(name, b64 if "float64" in name else b32)
        outside = ~(vals <= b)  # NaN and inf are outside
        out[name] = dict(first_x_out=float(x[outside][0]) if outside.any() else None, worst_ratio=float(np.max(vals / b)))
    return out


def plot_sweep(sw, folder):
    """hardcase-<name>.png in folder: a line per variant, pyvf's bounds dashed."""
    lines = {name: (sw["x"], v, "o-" if name.startswith("pyvf") else ".-") for name, v in sw["lines"].items()}
    lines.update({f"bound of {name}": (sw["x"], b, "k--") for name, b in sw["bounds"].items()})
    return save_plot(folder, f"hardcase-{sw['name']}.png", lines, sw["title"], sw["xlabel"], sw["ylabel"],
                     sw.get("logx", True))


def sweep_summary(sw):
    """Markdown lines: pyvf's bound, PASS/FAIL per pyvf line, where each other line leaves it."""
    out = [f"bound: {sw['bound_text']}", ""]
    for name, c in sorted(sw["check"].items(), key=lambda item: item[0] not in sw["bounds"]):  # pyvf's first
        x = c["first_x_out"]
        if name in sw["bounds"]:
            out.append(f"* {'PASS' if x is None else 'FAIL'} {name}: worst error / bound {c['worst_ratio']:.2g}"
                       + ("" if x is None else f", first out at x = {x:.3g}"))
        else:
            out.append(f"* {name}: " + ("within pyvf's bound over the range" if x is None else
                                        f"leaves pyvf's bound at x = {x:.3g}"))
    return "\n".join(out)


def run(quick=False, threads=2, names=tuple(SWEEPS), plots=None, log=print):
    """Every sweep named, checked, printed and plotted into the folder plots: {config, machine, sweeps, failures}."""
    report = dict(config=dict(quick=quick, sweeps=list(names)), machine=machine(threads), sweeps=[])
    for name in names:
        sw = SWEEPS[name](quick, np.random.default_rng(0))
        sw["check"] = check(sw)
        log(f"\n## {sw['title']}\n\n{sweep_summary(sw)}", flush=True)
        if plots:
            sw["plot"] = plot_sweep(sw, plots)
        report["sweeps"].append(sw)
    report["failures"] = [f"{sw['name']} / {n}: first out at x = {c['first_x_out']:.3g} (worst error / bound "
                          f"{c['worst_ratio']:.2g})" for sw in report["sweeps"] for n, c in sw["check"].items()
                          if n in sw["bounds"] and c["first_x_out"] is not None]
    return report
