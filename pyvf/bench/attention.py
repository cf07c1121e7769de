"""Branching attention (docs/math.md §2), forward and forward+backward: pyvf's C++ kernel against
torch's scaled_dot_product_attention with the dense (T, T) mask and the dense NumPy reference.

    pyvf bench attention           # paper size R=3, B=1, H=12, N=20, L=64, dh=64
    pyvf bench attention --quick   # H=2, N=4, dh=32

Each contender's output and gradients (float32; pyvf float64 too) are first compared with the
NumPy reference in float64, normwise (max|x - ref| / max|ref|); if one is outside its bound nothing
is timed. Then each one's extra peak memory (beside the memory expected) and median time, with the
useful GFLOP/s (attended block pairs only) and its share of the machine's float32 GEMM rate.
Inputs unit-normal, scale 1 (the published model's unscaled logits); torch and the reference
take the flat (B, H, T, dh) sequence, T = R*N*L in the order [row][view][token].
"""

import numpy as np

import pyvf
from pyvf.bench.common import (MEMORY_METHOD, TORCH_MISSING, format_bytes, machine, median_time, ms, peak_memory,
                               table, torch_or_none, validate)

# pyvf's bounds, tests/test_attention.py's RTOL64 and RTOL32 (their reasons written out there); torch
# SDPA and the reference in float32 round the logits in their own order (measured ~3.3e-6): a wrong
# mask or layout is an O(1) error
BOUND64, BOUND32, BOUND_OTHERS = 1e-12, 1e-5, 1e-4
NAMES = ("o", "dq", "dk", "dv")
PAPER = dict(R=3, B=1, H=12, N=20, L=64, dh=64)
QUICK = dict(R=3, B=1, H=2, N=4, L=64, dh=32)


def flat(x):
    """(R, B, H, N, L, dh) -> (B, H, T, dh), T in the order [row][view][token]."""
    R, B, H, N, L, dh = x.shape
    return np.ascontiguousarray(x.transpose(1, 2, 0, 3, 4, 5).reshape(B, H, R * N * L, dh))


def unflat(x, shape):
    """(B, H, T, dh) -> (R, B, H, N, L, dh)."""
    R, B, H, N, L, dh = shape
    return x.reshape(B, H, R, N, L, dh).transpose(2, 0, 1, 3, 4, 5)


def make_inputs(R, B, H, N, L, dh, seed=0):
    """q, k, v, do: unit-normal float32 arrays of shape (R, B, H, N, L, dh)."""
    rng = np.random.default_rng(seed)
    return [rng.standard_normal((R, B, H, N, L, dh), dtype=np.float32) for _ in range(4)]


def attended_pairs(R, N):
    """Block pairs one (b, h) attends: trunk N(N+1)/2, each branch N(N-1)/2 + N (docs/math.md §2)."""
    return N * (N + 1) // 2 + (R - 1) * (N * (N - 1) // 2 + N)


def expected_memory(method, R, B, H, N, L, dh, threads):
    """Bytes a float32 call should need above its inputs, outputs included: (forward, forward+backward).

    "pyvf" (csrc/branching_attention.cpp): o like q, lse (R, B, H, N, L) float64, per thread q^T and
    the accumulator (L, dh), s^T (L, L) and five L-vectors; the backward dq, dk, dv like q, per
    thread q^T and do^T of one head (R*N*L, dh) and three (L, L) buffers, and G-1 more dq, G =
    min(ceil(16 / (B*H)), 8, R*N) key groups where B*H < 16. "sdpa" (bool mask): the float32
    additive mask (4 T^2), then o (and dq, dk, dv). "numpy": s, p and p / sum(p), three (B, H, T, T)
    arrays, beside its (T, T) bool mask."""
    S = R * B * H * N * L * dh * 4  # one array like q
    T = R * N * L
    if method == "pyvf":
        Lt = min(L, 256)  # the kernel's tile
        G = 1 if B * H >= 16 else min(-(-16 // (B * H)), 8, R * N)
        lse, fwd_thread = R * B * H * N * L * 8, threads * (2 * Lt * dh + Lt * Lt + 5 * Lt) * 4
        bwd_thread = threads * (2 * T * dh + 3 * T + 3 * Lt * Lt) * 4
        return S + lse + fwd_thread, S + lse + max(fwd_thread, (2 + G) * S + bwd_thread)
    if method == "sdpa":
        return 4 * T * T + S, 4 * T * T + 4 * S
    logits = B * H * T * T * 4
    return T * T + 3 * logits + S, T * T + 3 * logits + 3 * S


# the contenders: {fwd, fb (forward+backward), outs (-> [o, dq, dk, dv] in pyvf's layout)}


def pyvf_contender(q, k, v, do):
    def fb():
        o, lse = pyvf.branching_attention_forward(q, k, v)
        return [o, *pyvf.branching_attention_backward(do, q, k, v, o, lse)]
    return dict(fwd=lambda: pyvf.branching_attention_forward(q, k, v)[0], fb=fb, outs=fb)


def torch_contender(q, k, v, do):
    """SDPA on (B, H, T, dh) with the bool (T, T) mask (True = attend), scale 1; backward by autograd."""
    import torch
    import torch.nn.functional as F

    mask = torch.from_numpy(pyvf.branching_mask(q.shape[0], q.shape[3], q.shape[4]))
    leaves = [torch.from_numpy(flat(x)).requires_grad_(True) for x in (q, k, v)]
    dot = torch.from_numpy(flat(do))

    def fwd():
        with torch.no_grad():
            return F.scaled_dot_product_attention(*leaves, attn_mask=mask, scale=1.0)

    def fb():  # autograd.grad rather than .backward(): no .grad left behind between calls
        o = F.scaled_dot_product_attention(*leaves, attn_mask=mask, scale=1.0)
        return o.detach(), torch.autograd.grad(o, leaves, dot)

    def outs():
        o, grads = fb()
        return [unflat(x.numpy(), q.shape) for x in (o, *grads)]
    return dict(fwd=fwd, fb=fb, outs=outs)


def reference_contender(q, k, v, do):
    """The dense NumPy reference; its vjp recomputes the probabilities."""
    def fwd():
        return pyvf.branching_attention_reference(q, k, v)

    def fb():
        return pyvf.branching_attention_reference_vjp(q, k, v, do)
    return dict(fwd=fwd, fb=fb, outs=lambda: [fwd(), *fb()])


def reference64(q, k, v, do):
    """[o, dq, dk, dv] of the dense reference in float64 on the same numbers: the oracle."""
    x64 = [x.astype(np.float64) for x in (q, k, v, do)]
    return [pyvf.branching_attention_reference(*x64[:3]), *pyvf.branching_attention_reference_vjp(*x64)]


def figures(c, repeat, warmup=1):
    """A contender's extra peak memory of one call and median time, forward and forward+backward
    (a call before, its validation, took the one-time costs); also each point of scaling.py's."""
    out = {}
    for name in ("fwd", "fb"):
        _, out[f"{name}_bytes"] = peak_memory(c[name])
        out[f"{name}_seconds"] = median_time(c[name], repeat, warmup)[0]
    return out


def run(quick=False, threads=2, size=None, repeat=5):
    """The benchmark (module docstring) at `size` (a dict R, B, H, N, L, dh; default PAPER, QUICK
    with quick): prints its tables, returns the report; report["failures"] lists the contenders
    outside their bound, and then nothing is timed."""
    size = size or (QUICK if quick else PAPER)
    shape, (R, N, L, dh) = tuple(size.values()), (size["R"], size["N"], size["L"], size["dh"])
    torch = torch_or_none()
    pyvf.set_num_threads(threads)
    if torch is not None:
        torch.set_num_threads(threads)
    report = dict(config=dict(size, threads=threads, repeat=repeat), machine=machine(threads), errors={}, failures=[])
    print(f"# Branching attention: {size} (T={R * N * L}), float32, scale 1, {threads} threads\n"
          f"machine: {report['machine']['processor']}; memory: {MEMORY_METHOD}\n")
    q, k, v, do = make_inputs(*shape)
    contenders = {"pyvf (C++ kernel)": (pyvf_contender(q, k, v, do), BOUND32, "pyvf")}
    if torch is not None:
        contenders["torch SDPA, dense bool mask"] = (torch_contender(q, k, v, do), BOUND_OTHERS, "sdpa")
    contenders["NumPy dense reference"] = (reference_contender(q, k, v, do), BOUND_OTHERS, "numpy")
    ref = reference64(q, k, v, do)
    checks = [("pyvf float64", pyvf_contender(*(x.astype(np.float64) for x in (q, k, v, do))), BOUND64)]
    for name, c, bound in checks + [(n, c, b) for n, (c, b, _) in contenders.items()]:
        report["errors"][name], ok = validate(c["outs"](), ref, NAMES, bound)
        report["failures"] += [] if ok else [f"{name} above {bound:g}: not timed"]
    print(table(["max rel. error vs float64 reference"] + list(NAMES),
                [[n] + [f"{e[c]:.2e}" for c in NAMES] for n, e in report["errors"].items()]) + "\n")
    if report["failures"]:
        return report
    a, b = np.random.default_rng(1).standard_normal((2, 1024, 1024), dtype=np.float32)
    gemm = report["gemm_gflops"] = 2 * 1024 ** 3 / median_time(lambda: a @ b, repeat)[0] / 1e9
    f_fwd = 4 * L * L * dh * attended_pairs(R, N) * size["B"] * size["H"]  # q k^T and p v per block pair
    f_fb = 3.5 * f_fwd  # the backward: q k^T recomputed, dv, dp, dq, dk
    rows, res = [], report.setdefault("results", {})
    for name, (c, _, method) in contenders.items():
        r = res[name] = figures(c, repeat, 0 if method == "numpy" else 1)
        r["expected_fwd_bytes"], r["expected_fb_bytes"] = expected_memory(method, *shape, threads)
        r["fb_of_gemm"] = f_fb / r["fb_seconds"] / 1e9 / gemm
        rows.append([name, ms(r["fwd_seconds"]), f"{f_fwd / r['fwd_seconds'] / 1e9:.1f}", ms(r["fb_seconds"]),
                     f"{f_fb / r['fb_seconds'] / 1e9:.1f}", f"{r['fb_of_gemm']:.0%}",
                     f"{format_bytes(r['fwd_bytes'])} / {format_bytes(r['expected_fwd_bytes'])}",
                     f"{format_bytes(r['fb_bytes'])} / {format_bytes(r['expected_fb_bytes'])}"])
    print(table(["", "forward", "GFLOP/s", "forward+backward", "GFLOP/s", "% of GEMM",
                 "memory fwd (measured / expected)", "memory fwd+bwd"], rows))
    print(f"\nmedian of {repeat} calls; GFLOP/s: useful flops ({attended_pairs(R, N)} of {(R * N) ** 2} block pairs "
          f"per head) / time; GEMM: numpy float32 matmul 1024x1024, {gemm:.1f} GFLOP/s")
    pyvf_fb = res["pyvf (C++ kernel)"]["fb_seconds"]
    if torch is None:
        print(f"torch SDPA: {TORCH_MISSING}")
    print("forward+backward time over pyvf's: " + ", ".join(f"{n} {r['fb_seconds'] / pyvf_fb:.2f}x"
                                                            for n, r in res.items() if not n.startswith("pyvf")))
    return report
