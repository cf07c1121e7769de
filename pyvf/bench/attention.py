"""Benchmark branching attention (docs/math.md §2): pyvf's C++ kernel against torch's
scaled_dot_product_attention with the dense (T, T) mask and against the dense NumPy reference.

    pyvf bench attention                   # paper size R=3, B=1, H=12, N=20, L=64, dh=64
    pyvf bench attention --quick           # smaller sizes
    pyvf bench attention --json out.json   # every number, machine-readable

What it does, in order:
1. validates: pyvf float32, torch SDPA float32 and the NumPy reference in float32 against the
   NumPy reference in float64 on float64 copies of the same inputs (output and every gradient,
   normwise relative error max|x - ref| / max|ref|), plus torch float64 as a check of the flat
   layout and mask given to torch; exits with status 1, nothing timed, if pyvf is outside its
   bound or another is outside BOUND_OTHERS (it would be the time of another computation);
2. measures the extra peak memory of one call of each (pyvf.bench.common.peak_memory: resident
   memory, outputs included) beside the memory expected for it;
3. times forward and forward+backward of each (median of --repeat calls), with the useful
   GFLOP/s (attended block pairs only) and the machine's float32 GEMM rate for scale;
4. times pyvf on every kernel path this CPU runs, each validated first, as % of the GEMM rate.

How the memory grows with N, against stacked prefixes and dense masks: `pyvf bench scaling`.
Inputs are unit-normal, scale = 1 (the published model's unscaled logits, docs/math.md §2).
Layouts: pyvf takes (R, B, H, N, L, dh); torch and the reference's flat sequence are
(B, H, T, dh) with T = R*N*L in the order [row][view][token].

run() is the benchmark (its report: every number, for --json); demo() is `pyvf bench
demo-attention` (and `pyvf demo` while no pretrained models are installed): the same check without
torch, at three sizes, pyvf against the dense NumPy reference only (error, time, memory). torch is
imported inside the functions that use it.
"""

import time

import numpy as np

import pyvf
from pyvf.bench.common import (TORCH_MISSING, format_bytes, machine, measured, median_time, memory_method, table,
                               torch_or_none)
from pyvf.verify.compare import rel_err

# The bounds pyvf must meet before anything is timed: the same as tests/test_attention.py
# (RTOL64, RTOL32), where their reasons are written out. float64: the kernel and the reference
# sum the same O(1) terms in another order (measured ~4e-15). float32 on unit-normal inputs with
# scale 1 (logits up to ~40): a logit's float32 rounding, sqrt(dh) * 2^-24 * |logit| ~ 2e-5 at
# worst, moves each probability by that relative amount; measured ~2.5e-6; a bug is O(1).
BOUND64 = 1e-12
BOUND32 = 1e-5
# The other implementations (torch SDPA, the NumPy reference in float32) round
# the logits (up to ~40 here: unit-normal inputs, scale 1) in float32 in their own order, torch's
# flash kernel with its own exp (measured: ~3.3e-6 at the paper size, ~1.5e-6 at the small one);
# what is checked is that each computes the same function, where a wrong mask or layout is an
# O(1) error. A contender outside it is not timed.
BOUND_OTHERS = 1e-4

PAPER = dict(R=3, B=1, H=12, N=20, L=64, dh=64)
QUICK = dict(R=3, B=1, H=4, N=8, L=64, dh=64)


def error(x, ref):
    """rel_err, inf where x holds a NaN: a NaN error compares False with every bound (and max()
    over several skips it), so it would pass any check."""
    e = rel_err(x, ref)
    return e if e == e else float("inf")


# ---------------------------------------------------------------------------------------
# problem: inputs in both layouts


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


def useful_flops(R, B, H, N, L, dh):
    """(forward, forward+backward) flops of the attended blocks only. Per block pair the forward
    is two (L, L, dh) matmuls, q k^T and p v: 4 L^2 dh; the backward five more (recomputed
    q k^T, dv, dp, dq, dk), so forward+backward is 7 matmuls = 3.5x the forward."""
    fwd = 4 * L * L * dh * attended_pairs(R, N) * B * H
    return fwd, 3.5 * fwd


# ---------------------------------------------------------------------------------------
# the memory one expects (written from csrc/branching_attention.cpp's header comment)


def key_groups(R, B, H, N):
    """G, the groups the backward splits each head's key blocks into (csrc/branching_attention.cpp,
    key_groups): 1 when B*H >= 16, else ceil(16 / (B*H)), at most 8 and at most R*N."""
    return 1 if B * H >= 16 else min(-(-16 // (B * H)), 8, R * N)


def pyvf_expected_memory(R, B, H, N, L, dh, itemsize, threads):
    """Bytes pyvf should need above its inputs: (forward, forward+backward), outputs included.

    forward: o (like q) and lse (R, B, H, N, L) float64, plus workspace per thread: q^T and the
    accumulator (L, dh), s^T (L, L) and five L-vectors.
    backward: dq, dk, dv (like q), plus per thread q^T and do^T of one head (R*N*L, dh), D and the
    lse hi/lo split (R*N*L each), three (L, L) buffers.
    forward+backward peaks in the backward, with o and lse still alive. When B*H < 16 the
    backward splits each head's key blocks into G = min(ceil(16 / (B*H)), 8, R*N) groups, and
    groups 1..G-1 keep a dq of their own: (G-1) more arrays like q.
    """
    S = R * B * H * N * L * dh * itemsize  # one array like q
    lse = R * B * H * N * L * 8
    Lt = min(L, 256)  # the kernel's tile
    G = key_groups(R, B, H, N)
    fwd_thread = (2 * Lt * dh + Lt * Lt + 5 * Lt) * itemsize
    bwd_thread = (2 * R * N * L * dh + 3 * R * N * L + 3 * Lt * Lt) * itemsize
    fwd = S + lse + threads * fwd_thread
    fwd_bwd = S + lse + max(threads * fwd_thread, (3 + G - 1) * S + threads * bwd_thread)
    return fwd, fwd_bwd


def dense_logits_bytes(R, B, H, N, L, itemsize):
    """The (B, H, T, T) logits a dense attention materialises."""
    T = R * N * L
    return B * H * T * T * itemsize


def expected_memory(method, R, B, H, N, L, dh, threads, backend="FLASH_ATTENTION"):
    """Bytes a float32 call should need above its inputs: (forward, forward+backward), outputs
    included. "pyvf": pyvf_expected_memory, O(T*dh). "sdpa", torch SDPA with the (T, T) bool mask:
    torch converts the mask to a float32 additive one (4 T^2), then o (and dq, dk, dv); its flash
    kernel (backend FLASH_ATTENTION) holds no logits, the math path the logits and, for the
    backward, the probabilities. "numpy", the dense reference: s, p = exp(s) and p / sum(p) alive
    at once, its vjp p, dp and one (dp - rowsum) temporary (3 dense (B, H, T, T) arrays each),
    beside its (T, T) bool mask."""
    if method == "pyvf":
        return pyvf_expected_memory(R, B, H, N, L, dh, 4, threads)
    S = R * B * H * N * L * dh * 4  # one array like q
    T2, logits = (R * N * L) ** 2, dense_logits_bytes(R, B, H, N, L, 4)
    if method == "sdpa":
        math = backend != "FLASH_ATTENTION"
        return 4 * T2 + S + math * logits, 4 * T2 + 4 * S + 2 * math * logits
    return T2 + 3 * logits + S, T2 + 3 * logits + 3 * S


# ---------------------------------------------------------------------------------------
# the contenders: each a forward and a forward+backward closure over prepared inputs


def pyvf_fns(q, k, v, do):
    def fwd():
        return pyvf.branching_attention_forward(q, k, v)[0]

    def fwd_bwd():
        o, lse = pyvf.branching_attention_forward(q, k, v)
        return o, pyvf.branching_attention_backward(do, q, k, v, o, lse)

    return fwd, fwd_bwd


def torch_fns(q, k, v, do, mask):
    """SDPA on the flat (B, H, T, dh) layout with the boolean (T, T) mask (True = attend),
    scale=1.0; backward through autograd with the upstream gradient do."""
    import torch
    import torch.nn.functional as F

    shape = q.shape
    qt, kt, vt, dot = (torch.from_numpy(flat(x)) for x in (q, k, v, do))
    leaves = [x.clone().requires_grad_(True) for x in (qt, kt, vt)]
    maskt = torch.from_numpy(mask)

    def fwd():
        with torch.no_grad():
            return F.scaled_dot_product_attention(qt, kt, vt, attn_mask=maskt, scale=1.0)

    def fwd_bwd():  # autograd.grad rather than .backward(): no .grad left behind between calls
        o = F.scaled_dot_product_attention(*leaves, attn_mask=maskt, scale=1.0)
        return o.detach(), torch.autograd.grad(o, leaves, dot)

    def to_pyvf(o):  # a flat torch tensor -> numpy (R, B, H, N, L, dh)
        return unflat(o.numpy(), shape)

    return fwd, fwd_bwd, to_pyvf


def reference_fns(q, k, v, do):
    """The dense NumPy reference. Its "forward+backward" is branching_attention_reference_vjp,
    which recomputes the forward's probabilities (not o) and returns the gradients."""
    def fwd():
        return pyvf.branching_attention_reference(q, k, v)

    def vjp():
        return pyvf.branching_attention_reference_vjp(q, k, v, do)

    return fwd, vjp


def torch_backend(q, mask):
    """The SDPA backend torch picks for these inputs (a private torch function: "unknown" if gone)."""
    import torch

    try:
        from torch.nn.attention import SDPBackend

        qt = torch.from_numpy(flat(q))
        choice = torch._fused_sdp_choice(qt, qt, qt, attn_mask=torch.from_numpy(mask), scale=1.0)
        return SDPBackend(choice).name
    except Exception:  # noqa: BLE001
        return "unknown"


# ---------------------------------------------------------------------------------------
# steps


def gemm_fn():
    """A float32 1024 x 1024 numpy matmul: the machine's GEMM rate for scale, 2 * 1024^3 flops
    per call, on the threads numpy's BLAS was loaded with (`pyvf bench` loads it with
    --threads, pyvf.cli.BLAS_THREAD_VARS)."""
    a, b = np.random.default_rng(1).standard_normal((2, 1024, 1024), dtype=np.float32)
    return lambda: a @ b


GEMM_FLOPS = 2 * 1024 ** 3


# ---------------------------------------------------------------------------------------
# the benchmark's steps


def path_times(q, k, v, do, repeat, f_fwd, f_fb, gemm):
    """Forward and forward+backward times of pyvf on every kernel path this process can use,
    each validated first (its output and gradients) against the current path's result (the same
    math, other rounding)."""
    out = {}
    o_ref = pyvf.branching_attention(q, k, v)
    g_ref = pyvf.branching_attention_vjp(q, k, v, do)
    for path in pyvf.kernel_paths():
        with pyvf.use_kernel_path(path):
            fwd, fwd_bwd = pyvf_fns(q, k, v, do)
            o, grads = fwd_bwd()
            err = _errors(o, grads, o_ref, g_ref, None)
            if not max(err.values()) <= BOUND32:
                raise RuntimeError(f"path {path}: differs from the default path by more than {BOUND32}: "
                                   + ", ".join(f"{n} {e:.2e}" for n, e in err.items()))
            t_f = median_time(fwd, repeat)[0]
            t_fb = median_time(fwd_bwd, repeat)[0]
        out[path] = dict(fwd=t_f, fwd_bwd=t_fb, fwd_gflops=f_fwd / t_f / 1e9, fwd_bwd_gflops=f_fb / t_fb / 1e9,
                         fwd_of_gemm=f_fwd / t_f / 1e9 / gemm, fwd_bwd_of_gemm=f_fb / t_fb / 1e9 / gemm)
    return out


def error_table(err):
    rows = [[name] + [f"{e[c]:.2e}" for c in ("o", "dq", "dk", "dv")] for name, e in err.items()]
    return table(["max rel. error vs float64 ref", "o", "dq", "dk", "dv"], rows)


def ms(sec):
    return "-" if sec is None else f"{sec * 1e3:.1f} ms"


def run(R, B, H, N, L, dh, threads=2, repeat=5):
    """The benchmark at one size (the module docstring's steps): prints each section as it goes
    and returns the report, every number. When pyvf is outside its bound, or torch SDPA or the
    NumPy reference outside BOUND_OTHERS, nothing is timed and report["aborted"] says so. Without
    torch, pyvf and the NumPy reference alone (report["torch"] says why)."""
    torch = torch_or_none()
    t_start = time.perf_counter()
    shape = (R, B, H, N, L, dh)
    pyvf.set_num_threads(threads)
    report = _start(shape, threads, repeat)
    q, k, v, do = make_inputs(*shape)
    mask = pyvf.branching_mask(R, N, L)  # (T, T) bool, for torch
    fns = dict(zip(("pyvf_fwd", "pyvf_fwd_bwd"), pyvf_fns(q, k, v, do)))
    to_np = None
    if torch is not None:
        torch.set_num_threads(threads)
        t_fwd, t_fb, to_np = torch_fns(q, k, v, do, mask)
        fns.update(torch_fwd=t_fwd, torch_fwd_bwd=t_fb)
    fns.update(zip(("numpy_fwd", "numpy_vjp"), reference_fns(q, k, v, do)))
    mem, first = _validate(report, (q, k, v, do), mask, fns, to_np)
    if "aborted" in report:
        return report
    _memory(report, shape, q, mask, mem, threads)
    f_fwd, f_fb = useful_flops(*shape)
    gemm = _time(report, shape, repeat, fns, first, (f_fwd, f_fb))
    print(f"\n## 4. pyvf on each kernel path this CPU runs (same inputs, medians of {repeat})\n")
    report["paths"] = paths = path_times(q, k, v, do, repeat, f_fwd, f_fb, gemm)
    print(table(["path", "forward", "GFLOP/s", "% of GEMM", "forward+backward", "GFLOP/s", "% of GEMM"],
                [[p, ms(r["fwd"]), f"{r['fwd_gflops']:.1f}", f"{r['fwd_of_gemm']:.0%}", ms(r["fwd_bwd"]),
                  f"{r['fwd_bwd_gflops']:.1f}", f"{r['fwd_bwd_of_gemm']:.0%}"] for p, r in paths.items()]))
    print(f"(GEMM: numpy float32 matmul 1024x1024, {gemm:.1f} GFLOP/s, the same for every row; "
          "PYVF_ISA=<path> runs the whole benchmark on one path)")
    report["total_seconds"] = total = time.perf_counter() - t_start
    print(f"\ntotal {total:.0f} s")
    return report


def _start(shape, threads, repeat):
    """The report's first fields (the problem, the machine, the bounds), printed as the header."""
    R, B, H, N, L, dh = shape
    T = R * N * L
    report = dict(config=dict(R=R, B=B, H=H, N=N, L=L, dh=dh, T=T, dtype="float32", scale=1.0, threads=threads,
                              repeat=repeat, inputs="unit normal, seed 0"),
                  machine=machine(threads), memory_method=memory_method(),
                  bounds=dict(pyvf_float32=BOUND32, pyvf_float64=BOUND64))
    m = report["machine"]
    print(f"# Branching attention benchmark: R={R} B={B} H={H} N={N} L={L} dh={dh} (T={T}), float32, "
          f"scale 1, {threads} threads")
    print(f"machine: {m['processor']}, {m['cpu_count']} CPUs; numpy {m['numpy']}, "
          f"torch {m['torch'] or 'not installed'}, pyvf {m['pyvf']}")
    print(f"memory: {memory_method()}\n")
    return report


def _validate(report, inputs, mask, fns, to_np):
    """Section 1: every contender against the float64 reference, the first calls' memory and time
    measured on the way. Returns ({call: extra peak bytes}, {call: seconds})."""
    q, k, v, do = inputs
    q64, k64, v64, do64 = (x.astype(np.float64) for x in inputs)
    print("## 1. Validation against the NumPy reference in float64 (float64 copies of the inputs)\n")
    t0 = time.perf_counter()
    o64 = pyvf.branching_attention_reference(q64, k64, v64)
    g64 = pyvf.branching_attention_reference_vjp(q64, k64, v64, do64)
    print(f"(float64 reference forward + vjp: {time.perf_counter() - t0:.1f} s)\n")
    mem, first, err = {}, {}, {}

    def measure(name, warmup):  # one measured call: its result; its memory and time kept
        out, mem[name], times = measured(fns[name], warmup)
        first[name] = times[0]
        return out

    # pyvf: one warm-up call (thread pool), then one measured call of each
    o, (_, grads) = measure("pyvf_fwd", 1), measure("pyvf_fwd_bwd", 1)
    err["pyvf float32"] = _errors(o, grads, o64, g64, None)
    o, grads = pyvf.branching_attention(q64, k64, v64), pyvf.branching_attention_vjp(q64, k64, v64, do64)
    err["pyvf float64"] = _errors(o, grads, o64, g64, None)
    worst32, worst64 = max(err["pyvf float32"].values()), max(err["pyvf float64"].values())
    bounds = f"pyvf bounds: float32 {BOUND32:g} (worst {worst32:.2e}), float64 {BOUND64:g} (worst {worst64:.2e})"
    report["errors"] = err
    if not (worst32 <= BOUND32 and worst64 <= BOUND64):  # stop before spending minutes on the others
        print(error_table(err))
        print(f"\n{bounds}")
        report["aborted"] = "pyvf error above its bound"
        return mem, first
    if "torch_fwd" in fns:
        o, (_, grads) = measure("torch_fwd", 1), measure("torch_fwd_bwd", 1)
        err["torch SDPA float32"] = _errors(to_np(o), [to_np(g) for g in grads], o64, g64, None)
        o, grads = torch_fns(q64, k64, v64, do64, mask)[1]()
        err["torch SDPA float64 (layout check)"] = _errors(to_np(o), [to_np(g) for g in grads], o64, g64, None)
    # the NumPy reference in float32: no warm-up (a call takes seconds); these calls are its
    # first timing sample too
    o, grads = measure("numpy_fwd", 0), measure("numpy_vjp", 0)
    err["numpy reference float32"] = _errors(o, grads, o64, g64, None)
    del o, grads
    print(error_table(err))
    print("\nrelative error = max|x - ref| / max|ref| over the whole array (normwise)")
    # the others compute the same function: a wrong mask or layout would make their times (and
    # the ratios to pyvf's) those of another computation
    wrong = [name for name, e in err.items() if not name.startswith("pyvf") and not max(e.values()) <= BOUND_OTHERS]
    if wrong:
        print(f"\n{bounds}: OK; {', '.join(wrong)} above {BOUND_OTHERS:g} (the same function)")
        report["aborted"] = f"{', '.join(wrong)} error above {BOUND_OTHERS:g}"
        return mem, first
    print(f"{bounds}; the others within {BOUND_OTHERS:g}: OK")
    return mem, first


def _memory(report, shape, q, mask, mem, threads):
    """Section 2: each call's extra peak memory beside the memory expected for it (expected_memory)."""
    print("\n## 2. Extra peak memory of one call (inputs excluded, outputs included)\n")
    backend = torch_backend(q, mask) if "torch_fwd" in mem else TORCH_MISSING
    expected = {}
    for method, (fwd, fb) in (("pyvf", ("pyvf_fwd", "pyvf_fwd_bwd")), ("sdpa", ("torch_fwd", "torch_fwd_bwd")),
                              ("numpy", ("numpy_fwd", "numpy_vjp"))):
        expected[fwd], expected[fb] = expected_memory(method, *shape, threads, backend)
    rows = [[name, format_bytes(mem[name]), format_bytes(expected[name]), f"{mem[name] / expected[name]:.2f}"]
            for name in mem]
    print(table(["call", "measured", "expected", "measured/expected"], rows))
    logits = dense_logits_bytes(*shape[:5], 4)
    print(f"\nexpected: pyvf O(T*dh); torch SDPA the (T, T) mask as float32 and, on its math path, the logits "
          f"(expected_memory); the NumPy reference 3 dense (B, H, T, T) arrays. Dense logits (B, H, T, T) float32 = "
          f"{format_bytes(logits)}; one array like q = {format_bytes(q.nbytes)}; torch SDPA backend chosen: {backend}")
    report["memory"] = {n: dict(measured_bytes=mem[n], expected_bytes=expected[n]) for n in mem}
    report["memory"]["dense_logits_bytes"] = logits
    report["torch_sdpa_backend"] = backend


def _time(report, shape, repeat, fns, first, flops):
    """Section 3: each contender's median time and GFLOP/s; the machine's GEMM rate (returned) for
    scale. Each is timed in `repeat` consecutive calls, not interleaved with the others: pyvf and
    torch have separate OpenMP runtimes (pyvf the system libgomp, torch its own copy), whose idle
    threads spin for a few ms after each parallel region; alternating them made both up to 2x
    slower and noisier here."""
    R, B, H, N, L, dh = shape
    f_fwd, f_fb = flops
    print(f"\n## 3. Time (median of {repeat} consecutive calls after one warm-up call)\n")
    order = ["pyvf_fwd", "torch_fwd", "pyvf_fwd_bwd", "torch_fwd_bwd"]
    times = {"gemm": median_time(gemm_fn(), repeat, 1)}
    times.update((name, median_time(fns[name], repeat, 1)) for name in order if fns.get(name) is not None)
    gemm = GEMM_FLOPS / times.pop("gemm")[0] / 1e9
    for name in ("numpy_fwd", "numpy_vjp"):  # first sample: the validation call
        all_t = [first[name]] + median_time(fns[name], repeat - 1, warmup=0)[1]
        times[name] = (float(np.median(all_t)), all_t)
    rows = []
    for fwd_name, fb_name, label in (("pyvf_fwd", "pyvf_fwd_bwd", "pyvf (C++ kernel)"),
                                     ("torch_fwd", "torch_fwd_bwd", "torch SDPA, dense bool mask"),
                                     ("numpy_fwd", "numpy_vjp", "NumPy dense reference")):
        if fwd_name not in times:
            continue
        row = [label]
        for name, f in ((fwd_name, f_fwd), (fb_name, f_fb)):
            row += [ms(times[name][0]), ms(min(times[name][1])), f"{f / times[name][0] / 1e9:.1f}"]
        rows.append(row)
    print(table(["", "forward", "(min)", "GFLOP/s", "forward+backward", "(min)", "GFLOP/s"], rows))
    print("GFLOP/s: useful flops (the same count for every row) / median time")
    ratio = {}
    if "torch_fwd" in times:
        ratio = {"fwd": times["torch_fwd"][0] / times["pyvf_fwd"][0],
                 "fwd_bwd": times["torch_fwd_bwd"][0] / times["pyvf_fwd_bwd"][0]}
        print(f"\ntorch SDPA / pyvf time: forward {ratio['fwd']:.2f}x, forward+backward {ratio['fwd_bwd']:.2f}x")
    else:
        print(f"\ntorch SDPA: {TORCH_MISSING}")
    print(f"NumPy reference / pyvf time: forward {times['numpy_fwd'][0] / times['pyvf_fwd'][0]:.0f}x, "
          f"forward+backward {times['numpy_vjp'][0] / times['pyvf_fwd_bwd'][0]:.0f}x")
    print(f"useful flops (attended block pairs only, {attended_pairs(R, N)} of {(R * N) ** 2} per head): "
          f"forward {f_fwd / 1e9:.2f} GFLOP, forward+backward {f_fb / 1e9:.2f} GFLOP (3.5x)")
    print(f"float32 GEMM rate, numpy matmul 1024x1024 (median, timed just before pyvf): {gemm:.1f} GFLOP/s")
    print("NumPy reference: no warm-up call (a call takes seconds), its first sample is the validation "
          "call; its forward+backward is branching_attention_reference_vjp (recomputes the "
          "probabilities, not o)")
    report["time"] = {n: dict(median_seconds=m, seconds=t) for n, (m, t) in times.items()}
    report["useful_flops"] = dict(fwd=f_fwd, fwd_bwd=f_fb, attended_pairs_per_head=attended_pairs(R, N))
    report["gflops"] = {n: (f_fwd if n.endswith("_fwd") else f_fb) / m / 1e9 for n, (m, _) in times.items()}
    report["gemm_float32_gflops"] = gemm
    report["ratio_torch_over_pyvf"] = ratio
    return gemm


# ---------------------------------------------------------------------------------------
# pyvf demo: the same check without torch, at three sizes, pyvf against the dense NumPy
# reference only; BOUND64 and BOUND32 as above

# Sizes, small to the paper's (docs/math.md §1). The dense reference costs O(T^2) time and memory
# (seconds per call in float64 at the paper size, 2 GiB), so the largest size is checked in
# float64 on two heads only, the first and the last (heads are computed independently, so the
# reference of those heads' inputs is exactly the reference's output for those heads), and
# the reference is timed in one call where a call takes a second or more (the whole demo then
# takes ~15 s on 2 cores, most of it the reference at the paper size).
DEMO_SIZES = {
    "small": dict(shape=dict(R=3, B=2, H=2, N=4, L=16, dh=16), ref_repeat=5, all_heads=True),
    "medium": dict(shape=dict(R=3, B=1, H=4, N=8, L=64, dh=64), ref_repeat=1, all_heads=True),
    "paper": dict(shape=dict(R=3, B=1, H=12, N=20, L=64, dh=64), ref_repeat=1, all_heads=False),
}
DEMO_REPEAT = 5  # timed calls of pyvf per median


def _errors(o, grads, o_ref, grads_ref, heads):
    """Normwise relative errors of o and (dq, dk, dv) against the reference, on `heads` only."""
    pick = (lambda x: x) if heads is None else (lambda x: x[:, :, heads])
    out = {"o": error(pick(o), o_ref)}
    for name, g, w in zip(("dq", "dk", "dv"), grads, grads_ref):
        out[name] = error(pick(g), w)
    return out


def demo_size(name, shape, ref_repeat, all_heads, seed=0):
    """Run one size; print its three tables; return True when pyvf is within its bounds.

    ref_repeat: timed calls of the dense reference; all_heads: check every head against the
    float64 reference, else only the first and the last."""
    R, B, H, N, L, dh = (shape[x] for x in ("R", "B", "H", "N", "L", "dh"))
    T = R * N * L
    heads = None if all_heads else sorted({0, H - 1})  # None: every head
    print(f"\n== {name}: R={R} B={B} H={H} N={N} L={L} dh={dh}  (T = R*N*L = {T} tokens) ==", flush=True)

    q, k, v, do = make_inputs(R, B, H, N, L, dh, seed)
    q64, k64, v64, do64 = (x.astype(np.float64) for x in (q, k, v, do))  # the same values, in float64

    # the oracle: the dense reference in float64 (on the checked heads)
    sub = [x if heads is None else np.ascontiguousarray(x[:, :, heads]) for x in (q64, k64, v64, do64)]
    o_ref = pyvf.branching_attention_reference(*sub[:3])
    g_ref = pyvf.branching_attention_reference_vjp(*sub)

    # pyvf in float64: the same math as the reference, another summation order
    err64 = _errors(pyvf.branching_attention(q64, k64, v64), pyvf.branching_attention_vjp(q64, k64, v64, do64),
                    o_ref, g_ref, heads)

    # pyvf in float32: one warm-up call (threads), then one measured call of each, then the medians
    fwd, fwd_bwd = pyvf_fns(q, k, v, do)
    fwd_bwd()
    o32, mem_fwd, _ = measured(fwd)
    (_, g32), mem_fb, _ = measured(fwd_bwd)
    err32 = _errors(o32, g32, o_ref, g_ref, heads)
    ok = max(err64.values()) <= BOUND64 and max(err32.values()) <= BOUND32
    t_fwd, _ = median_time(fwd, repeat=DEMO_REPEAT, warmup=0)
    t_fb, _ = median_time(fwd_bwd, repeat=DEMO_REPEAT, warmup=0)

    # the dense reference in float32, no warm-up (a call can take seconds): the memory-measured
    # call is its first timing sample
    r_fwd, r_vjp = reference_fns(q, k, v, do)
    o_np, mem_np_fwd, ts_np_fwd = measured(r_fwd, repeat=ref_repeat)
    g_np, mem_np_vjp, ts_np_vjp = measured(r_vjp, repeat=ref_repeat)
    err_np = _errors(o_np, g_np, o_ref, g_ref, heads)
    del o_np, g_np

    where = "all heads" if heads is None else f"heads {' and '.join(map(str, heads))} of {H}"
    print(f"max relative error vs the dense NumPy reference in float64 ({where}; max|x - ref| / max|ref|)")
    rows = []
    for label, e, bound in (("pyvf float64", err64, BOUND64), ("pyvf float32", err32, BOUND32),
                            ("NumPy reference float32", err_np, None)):
        verdict = "" if bound is None else ("ok" if max(e.values()) <= bound else "EXCEEDED")
        rows.append([label] + [f"{e[c]:.1e}" for c in ("o", "dq", "dk", "dv")]
                    + ["" if bound is None else f"{bound:g}", verdict])
    print(table(["", "o", "dq", "dk", "dv", "bound", ""], rows))

    print(f"\ntime, float32 (median of {DEMO_REPEAT} calls for pyvf, {len(ts_np_fwd)} for the reference), and the "
          "extra peak memory of one call (measured, outputs included)")
    np_fwd, np_vjp = float(np.median(ts_np_fwd)), float(np.median(ts_np_vjp))
    print(table(["", "forward", "forward+backward", "memory, forward", "memory, forward+backward"], [
        ["pyvf (C++ kernel)", ms(t_fwd), ms(t_fb), format_bytes(mem_fwd), format_bytes(mem_fb)],
        ["NumPy dense reference (its vjp)", ms(np_fwd), ms(np_vjp), format_bytes(mem_np_fwd), format_bytes(mem_np_vjp)],
        ["reference / pyvf", f"{np_fwd / t_fwd:.3g}x", f"{np_vjp / t_fb:.3g}x", "", ""]]))
    print(f"dense logits (B, H, T, T) float32 = {format_bytes(dense_logits_bytes(R, B, H, N, L, 4))}: O(T^2); one "
          f"array like q = {format_bytes(q.nbytes)}: O(T*dh)")
    return ok


def demo(sizes=tuple(DEMO_SIZES), threads=None, kernel_line=True):
    """`pyvf bench demo-attention`: branching attention at the given DEMO_SIZES names, pyvf against the dense
    NumPy reference: error, time, memory. Prints the tables; returns the exit status, 0 when
    every error is within its bound. NumPy only (no torch)."""
    if threads is not None:
        pyvf.set_num_threads(threads)
    t0 = time.perf_counter()
    if kernel_line:  # (the caller printed it already otherwise)
        from pyvf._machine import kernel_line as line
        print(line())
    print("pyvf demo: branching attention (docs/math.md §2), the C++ kernel against the dense NumPy reference")
    print(f"pyvf {pyvf.__version__}, numpy {np.__version__}, {pyvf.num_threads()} kernel threads; "
          "inputs unit normal, scale 1 (unscaled logits, as the published model)")
    print(f"memory: {memory_method()}")
    ok = True
    for name in sizes:
        ok &= demo_size(name, **DEMO_SIZES[name])
    print(f"\n{'all errors within their bounds' if ok else 'ERROR BOUND EXCEEDED'}; "
          f"total {time.perf_counter() - t0:.0f} s")
    return 0 if ok else 1
