"""Branching attention (docs/math.md §2), forward and forward+backward, at one size: pyvf's C++
kernel against torch's scaled_dot_product_attention with the dense (T, T) mask and the dense
NumPy reference; also the measurement of one point of `pyvf bench scaling` (worker()).

    pyvf bench attention           # paper size R=3, B=1, H=12, N=20, L=64, dh=64
    pyvf bench attention --quick   # H=2, N=4, dh=32

Each method in a process of its own: validated against the float64 reference (else not timed),
then one call's extra peak memory beside the memory expected, and the median time of 5 calls.
Inputs unit-normal, scale 1 (the published model's unscaled logits).
"""

import numpy as np

import pyvf
from pyvf.bench.common import (MEMORY_METHOD, TORCH_MISSING, format_bytes, machine, median_time, ms, peak_memory,
                               run_worker, table, torch_or_none, validate, worker_main)

R, B, L = 3, 1, 64  # tree rows, batch, tokens per view (docs/math.md §1)
# pyvf's bounds, tests/test_attention.py's RTOL64 and RTOL32 (their reasons written out there); torch
# SDPA and the reference in float32 round the logits in their own order (measured ~3.3e-6): a wrong
# mask or layout is an O(1) error
BOUND64, BOUND32, BOUND_OTHERS = 1e-12, 1e-5, 1e-4
NAMES = ("o", "dq", "dk", "dv")
METHODS = {
    "pyvf": "pyvf branching kernel",
    "naive_pyvf": "naive stacked, pyvf kernel at R=1",
    "dense_sdpa": "dense (T,T) mask, torch SDPA",
    "dense_numpy": "dense (T,T) mask, NumPy reference",
}
REPEAT = 5  # timed calls of each pass


def flat(x):
    """(R, B, H, N, L, dh) -> (B, H, T, dh), T in the order [row][view][token]."""
    R, B, H, N, L, dh = x.shape
    return np.ascontiguousarray(x.transpose(1, 2, 0, 3, 4, 5).reshape(B, H, R * N * L, dh))


def attended_pairs(R, N):
    """Block pairs one (b, h) attends: trunk N(N+1)/2, each branch N(N-1)/2 + N (docs/math.md §2)."""
    return N * (N + 1) // 2 + (R - 1) * (N * (N - 1) // 2 + N)


def expected_memory(method, R, B, H, N, L, dh, threads):
    """Bytes a float32 call should need above its inputs, outputs included: (forward, forward+backward).
    "pyvf" (csrc/branching_attention.cpp): o like q, lse (R, B, H, N, L) float64, per thread q^T and
    the accumulator (L, dh), s^T (L, L) and five L-vectors; the backward dq, dk, dv like q, per
    thread q^T and do^T of one head (R*N*L, dh) and three (L, L), and G-1 more dq (G key groups).
    "dense_sdpa" (bool mask): the float32 additive mask (4 T^2), then o (and dq, dk, dv).
    "dense_numpy": s, p and p / sum(p), three (B, H, T, T) arrays, beside its (T, T) bool mask."""
    S = R * B * H * N * L * dh * 4  # one array like q
    T = R * N * L
    if method == "pyvf":
        Lt = min(L, 256)  # the kernel's tile
        G = 1 if B * H >= 16 else min(-(-16 // (B * H)), 8, R * N)  # key groups: ceil(16 / (B*H)), at most 8
        lse, fwd_thread = R * B * H * N * L * 8, threads * (2 * Lt * dh + Lt * Lt + 5 * Lt) * 4
        bwd_thread = threads * (2 * T * dh + 3 * T + 3 * Lt * Lt) * 4
        return S + lse + fwd_thread, S + lse + max(fwd_thread, (2 + G) * S + bwd_thread)
    if method == "dense_sdpa":
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

    torch.set_num_threads(pyvf.num_threads())
    mask = torch.from_numpy(pyvf.branching_mask(q.shape[0], q.shape[3], q.shape[4]))
    leaves = [torch.from_numpy(flat(x)).requires_grad_(True) for x in (q, k, v)]
    dot = torch.from_numpy(flat(do))

    def fwd():
        with torch.no_grad():
            return F.scaled_dot_product_attention(*leaves, attn_mask=mask, scale=1.0)

    def fb():  # autograd.grad rather than .backward(): no .grad left behind between calls
        o = F.scaled_dot_product_attention(*leaves, attn_mask=mask, scale=1.0)
        return o.detach(), torch.autograd.grad(o, leaves, dot)

    def outs():  # (B, H, T, dh) -> (B, H, R, N, L, dh) -> pyvf's (R, B, H, N, L, dh)
        o, grads = fb()
        return [x.numpy().reshape(q.shape[1:3] + q.shape[:1] + q.shape[3:]).transpose(2, 0, 1, 3, 4, 5)
                for x in (o, *grads)]
    return dict(fwd=fwd, fb=fb, outs=outs)


def reference_contender(q, k, v, do):
    """The dense NumPy reference; its vjp recomputes the probabilities."""
    fwd = lambda: pyvf.branching_attention_reference(q, k, v)  # noqa: E731
    fb = lambda: pyvf.branching_attention_reference_vjp(q, k, v, do)  # noqa: E731
    return dict(fwd=fwd, fb=fb, outs=lambda: [fwd(), *fb()])


def stack_naive(x, queries_only=False):
    """(R, B, H, N, L, dh) -> (S, B, H, N, L, dh), S = 1 + (R-1)*N: sequence 0 is the trunk;
    sequence 1 + (r-1)*N + i holds the trunk views 0..i-1, then branch r's view i, then zero views.
    queries_only (the upstream gradient): zeros in place of the trunk copies, whose outputs the
    naive approach throws away."""
    R, B, H, N, L, dh = x.shape
    out = np.zeros((1 + (R - 1) * N,) + x.shape[1:], dtype=x.dtype)
    out[0] = x[0]
    for r in range(1, R):
        for i in range(N):
            if not queries_only:
                out[1 + (r - 1) * N + i, :, :, :i] = x[0, :, :, :i]
            out[1 + (r - 1) * N + i, :, :, i] = x[r, :, :, i]
    return out


def unstack_naive(st, R, keys=False):
    """stack_naive's inverse for an output or a gradient: a query token is in one sequence only (o,
    dq); a trunk key in the trunk and in every later branch sequence, so its gradient (dk, dv:
    keys=True) is the sum over them."""
    N = st.shape[3]
    out = np.zeros((R,) + st.shape[1:], dtype=st.dtype)
    out[0] = st[0]
    for r in range(1, R):
        for i in range(N):
            out[r, :, :, i] = st[1 + (r - 1) * N + i, :, :, i]
            if keys:
                out[0, :, :, :i] += st[1 + (r - 1) * N + i, :, :, :i]
    return out


def naive_contender(q, k, v, do):
    """pyvf's kernel at R=1 on the stacked sequences, seen as one row of S*B batch entries."""
    st = [stack_naive(x) for x in (q, k, v)] + [stack_naive(do, queries_only=True)]
    S = st[0].shape[0]
    c = pyvf_contender(*(x.reshape((1, S * B) + x.shape[2:]) for x in st))
    outs, keys = c["outs"], (False, False, True, True)  # o, dq are queries' (one sequence each); dk, dv keys'
    c["outs"] = lambda: [unstack_naive(x.reshape(st[0].shape), R, key) for x, key in zip(outs(), keys)]
    return c


def theory(method, H, N, dh, threads):
    """{computed_flops (forward), expected_fwd, expected_fb (bytes)} of a point."""
    if method == "naive_pyvf":
        S = 1 + (R - 1) * N
        pairs = S * N * (N + 1) // 2
        fwd, fb = expected_memory("pyvf", 1, S * B, H, N, L, dh, threads)
    else:
        pairs = attended_pairs(R, N) if method == "pyvf" else (R * N) ** 2
        fwd, fb = expected_memory(method, R, B, H, N, L, dh, threads)
    return dict(computed_flops=4 * L * L * dh * pairs * B * H, expected_fwd=fwd, expected_fb=fb)


def worker(spec):
    """One point, {method, H, dh, N, threads, validate} -> its measurements (a dict)."""
    method, H, dh, N = spec["method"], spec["H"], spec["dh"], spec["N"]
    pyvf.set_num_threads(spec["threads"])
    q, k, v, do = np.random.default_rng(N).standard_normal((4, R, B, H, N, L, dh), dtype=np.float32)
    make = dict(pyvf=pyvf_contender, naive_pyvf=naive_contender, dense_sdpa=torch_contender,
                dense_numpy=reference_contender)[method]
    c, out = make(q, k, v, do), {}
    if spec["validate"]:
        bound = BOUND32 if "pyvf" in method else BOUND_OTHERS
        oracle = reference_contender(*(x.astype(np.float64) for x in (q, k, v, do)))["outs"]()  # float64, same numbers
        out["errors"], ok = validate(c["outs"](), oracle, NAMES, bound)
        if not ok:
            return dict(out, error=f"validation failed: max rel. error {max(out['errors'].values()):.2e} > {bound:g}")
    for name in ("fwd", "fb"):  # a warm-up call (thread pools), then one call's extra peak memory, then the time
        c[name]()
        _, out[f"{name}_bytes"] = peak_memory(c[name])
        out[f"{name}_seconds"] = median_time(c[name], REPEAT, warmup=0)[0]
    return out


def run_points(sizes, views, methods, threads, max_point_seconds, log=print):
    """Every point (method, (H, dh) of sizes, N of views), each in a worker process, validated at the
    first N, or skipped (with the reason) when predicted by its FLOPs from the method's previous N
    to take more than max_point_seconds (0: never): a list of dicts."""
    points, torch = [], torch_or_none()
    for H, dh in sizes:
        prev = {}
        for N in views:
            for method in methods:
                p, last = dict(method=method, H=H, dh=dh, N=N, theory=theory(method, H, N, dh, threads)), prev.get(method)
                est = None if last is None or "fb_seconds" not in last else (  # memory, warm-up, timed calls
                    (REPEAT + 3) * (last["fwd_seconds"] + last["fb_seconds"])
                    * p["theory"]["computed_flops"] / last["theory"]["computed_flops"])
                if method == "dense_sdpa" and torch is None:
                    p["skipped"] = TORCH_MISSING
                elif last is not None and "skipped" in last:
                    p["skipped"] = "a smaller N of this method was skipped"
                elif max_point_seconds and est is not None and est > max_point_seconds:
                    p["skipped"] = f"predicted {est:.0f} s > --max-point-seconds {max_point_seconds:g}"
                else:
                    try:
                        p.update(run_worker(worker, dict(method=method, H=H, dh=dh, N=N, threads=threads,
                                                         validate=N == views[0])))
                    except RuntimeError as e:  # a crashed worker: written down, the study carries on
                        p["error"] = str(e)[-2000:]
                t = p["theory"]
                log(f"  H={H} dh={dh} N={N:>2} {method:<12} " + (
                    f"skipped: {p['skipped']}" if "skipped" in p else f"FAILED: {p['error'].splitlines()[0][:100]}"
                    if "error" in p else f"memory (measured / expected) fwd {format_bytes(p['fwd_bytes'])} / "
                    f"{format_bytes(t['expected_fwd'])}, fwd+bwd {format_bytes(p['fb_bytes'])} / "
                    f"{format_bytes(t['expected_fb'])}; time fwd {ms(p['fwd_seconds'])}, fwd+bwd {ms(p['fb_seconds'])}"),
                    flush=True)
                points.append(p)
                prev[method] = p
    return points


def run(quick=False, threads=2, size=None):
    """The benchmark (module docstring) at size (H, dh, N): prints its tables, returns the report."""
    H, dh, N = size or ((2, 32, 4) if quick else (12, 64, 20))
    report = dict(config=dict(R=R, B=B, H=H, N=N, L=L, dh=dh, threads=threads), machine=machine(threads))
    print(f"# Branching attention: R={R} B={B} H={H} N={N} L={L} dh={dh} (T={R * N * L}), float32, scale 1, {threads} "
          f"threads, each method in its own process\nmachine: {report['machine']['processor']}; memory: {MEMORY_METHOD}\n")
    report["points"] = run_points([(H, dh)], [N], ("pyvf", "dense_sdpa", "dense_numpy"), threads, 0)
    points = [p for p in report["points"] if "skipped" not in p]  # torch SDPA without torch
    report["failures"] = [f"{METHODS[p['method']]}: {p['error']}: not timed" for p in points if "error" in p]
    if report["failures"]:
        return report
    a, b = np.random.default_rng(1).standard_normal((2, 1024, 1024), dtype=np.float32)
    gemm = report["gemm_gflops"] = 2 * 1024 ** 3 / median_time(lambda: a @ b, REPEAT)[0] / 1e9  # float32 GEMM rate
    f_fwd = 4 * L * L * dh * attended_pairs(R, N) * B * H  # useful flops: q k^T and p v per attended block pair
    f_fb = 3.5 * f_fwd  # the backward: q k^T recomputed, dv, dp, dq, dk
    print("\n" + table(["", "max rel. error", "forward", "GFLOP/s", "forward+backward", "GFLOP/s", "% of GEMM",
                        "fwd+bwd time / pyvf's"], [
        [METHODS[p["method"]], f"{max(p['errors'].values()):.2e}", ms(p["fwd_seconds"]),
         f"{f_fwd / p['fwd_seconds'] / 1e9:.1f}", ms(p["fb_seconds"]), f"{f_fb / p['fb_seconds'] / 1e9:.1f}",
         f"{f_fb / p['fb_seconds'] / 1e9 / gemm:.0%}", f"{p['fb_seconds'] / points[0]['fb_seconds']:.2f}"] for p in points]))
    print(f"\nmedian of {REPEAT} calls; error: the largest of {', '.join(NAMES)} against the float64 reference; "
          f"GFLOP/s: useful flops ({attended_pairs(R, N)} of {(R * N) ** 2} block pairs per head) / time; GEMM: "
          f"numpy float32 matmul 1024x1024, {gemm:.1f} GFLOP/s")
    return report


if __name__ == "__main__":  # a worker: `python -m pyvf.bench.attention SPEC`
    worker_main(worker)
