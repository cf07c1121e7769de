"""pyvf's command line: `python -m pyvf <command>`, or the console script `pyvf <command>`.

    python -m pyvf demo                     # branching attention: error, time, memory; ~1 minute
    python -m pyvf demo --sizes small       # seconds
    python -m pyvf demo --threads 1

Each command is a function `cmd_<name>(args) -> exit status` with an argparse subparser made
in build_parser(); a new command (render, localize, a bigger demo) is one more of each.
NumPy only: nothing here imports torch.
"""

import argparse
import sys
import time

import numpy as np

import pyvf
from pyvf.measure import format_bytes, median_time, memory_method, peak_memory, rel_err

# ---------------------------------------------------------------------------------------
# demo: branching attention (SPEC.md §2), the C++ kernel beside the dense NumPy reference

# Error bounds, as in tests/test_attention.py (RTOL64, RTOL32), relative to max|reference|.
# float64: the kernel and the reference sum the same O(1) terms in another order (measured
# ~4e-15). float32 on unit-normal inputs, scale 1 (logits up to ~40): one logit's rounding,
# sqrt(dh) * 2^-24 * |logit| ~ 2e-5 at worst, moves each probability by that relative amount;
# measured ~3e-6. A real bug (wrong mask, missed rescale) is an O(1) error.
BOUND64 = 1e-12
BOUND32 = 1e-5

# Sizes, small to the paper's (SPEC.md §1). The dense reference costs O(T^2) time and memory
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
REPEAT = 5  # timed calls of pyvf per median


def _errors(o, grads, o_ref, grads_ref, heads):
    """Normwise relative errors of o and (dq, dk, dv) against the reference, on `heads` only."""
    pick = (lambda x: x) if heads is None else (lambda x: x[:, :, heads])
    out = {"o": rel_err(pick(o), o_ref)}
    for name, g, w in zip(("dq", "dk", "dv"), grads, grads_ref):
        out[name] = rel_err(pick(g), w)
    return out


def _measured(fn, repeat=1):
    """repeat timed calls of fn, the first under peak_memory: (its result, its extra peak bytes,
    the seconds of every call)."""
    box = {}

    def call():
        t0 = time.perf_counter()
        out = fn()
        box["seconds"] = time.perf_counter() - t0
        return out

    result, extra = peak_memory(call)
    times = [box["seconds"]]
    if repeat > 1:
        times += median_time(fn, repeat - 1, warmup=0)[1]
    return result, extra, times


def _times(ratio):
    return f"{ratio:.0f}x" if ratio >= 10 else f"{ratio:.1f}x"


def _row(cells, widths):
    return "  ".join(str(c).rjust(w) if i else str(c).ljust(w) for i, (c, w) in enumerate(zip(cells, widths)))


def demo_size(name, shape, ref_repeat, all_heads, seed=0):
    """Run one size; print its three tables; return True when pyvf is within its bounds.

    ref_repeat: timed calls of the dense reference; all_heads: check every head against the
    float64 reference, else only the first and the last."""
    R, B, H, N, L, dh = (shape[x] for x in ("R", "B", "H", "N", "L", "dh"))
    T = R * N * L
    heads = None if all_heads else sorted({0, H - 1})  # None: every head
    print(f"\n== {name}: R={R} B={B} H={H} N={N} L={L} dh={dh}  (T = R*N*L = {T} tokens) ==", flush=True)

    rng = np.random.default_rng(seed)
    q, k, v, do = (rng.standard_normal((R, B, H, N, L, dh), dtype=np.float32) for _ in range(4))
    q64, k64, v64, do64 = (x.astype(np.float64) for x in (q, k, v, do))  # the same values, in float64

    # the oracle: the dense reference in float64 (on the checked heads)
    sub = [x if heads is None else np.ascontiguousarray(x[:, :, heads]) for x in (q64, k64, v64, do64)]
    o_ref = pyvf.branching_attention_reference(*sub[:3])
    g_ref = pyvf.branching_attention_reference_vjp(*sub)

    # pyvf in float64: the same math as the reference, another summation order
    err64 = _errors(pyvf.branching_attention(q64, k64, v64), pyvf.branching_attention_vjp(q64, k64, v64, do64),
                    o_ref, g_ref, heads)

    # pyvf in float32: one warm-up call (threads), then one measured call of each, then the medians
    def fwd():
        return pyvf.branching_attention_forward(q, k, v)

    def fwd_bwd():
        o, lse = pyvf.branching_attention_forward(q, k, v)
        return o, pyvf.branching_attention_backward(do, q, k, v, o, lse)

    fwd_bwd()
    (o32, _), mem_fwd, _ = _measured(fwd)
    (_, g32), mem_fb, _ = _measured(fwd_bwd)
    err32 = _errors(o32, g32, o_ref, g_ref, heads)
    ok = max(err64.values()) <= BOUND64 and max(err32.values()) <= BOUND32
    t_fwd, _ = median_time(fwd, repeat=REPEAT, warmup=0)
    t_fb, _ = median_time(fwd_bwd, repeat=REPEAT, warmup=0)

    # the dense reference in float32, no warm-up (a call can take seconds): the memory-measured
    # call is its first timing sample
    o_np, mem_np_fwd, ts_np_fwd = _measured(lambda: pyvf.branching_attention_reference(q, k, v), ref_repeat)
    g_np, mem_np_vjp, ts_np_vjp = _measured(lambda: pyvf.branching_attention_reference_vjp(q, k, v, do), ref_repeat)
    err_np = _errors(o_np, g_np, o_ref, g_ref, heads)
    del o_np, g_np

    where = "all heads" if heads is None else f"heads {' and '.join(map(str, heads))} of {H}"
    print(f"max relative error vs the dense NumPy reference in float64 ({where}; max|x - ref| / max|ref|)")
    w = (24, 9, 9, 9, 9, 7, 8)
    print(_row(["", "o", "dq", "dk", "dv", "bound", ""], w))
    for label, e, bound in (("pyvf float64", err64, BOUND64), ("pyvf float32", err32, BOUND32),
                            ("NumPy reference float32", err_np, None)):
        verdict = "" if bound is None else ("ok" if max(e.values()) <= bound else "EXCEEDED")
        print(_row([label] + [f"{e[c]:.1e}" for c in ("o", "dq", "dk", "dv")]
                   + ["" if bound is None else f"{bound:g}", verdict], w))

    n_np = len(ts_np_fwd)
    print(f"time, float32 (median of {REPEAT} calls for pyvf, {n_np} for the reference)")
    w = (24, 12, 18, 10)
    print(_row(["", "forward", "forward+backward", ""], w))
    print(_row(["pyvf (C++ kernel)", f"{t_fwd * 1e3:.1f} ms", f"{t_fb * 1e3:.1f} ms", ""], w))
    np_fwd, np_vjp = float(np.median(ts_np_fwd)), float(np.median(ts_np_vjp))
    print(_row(["NumPy dense reference", f"{np_fwd * 1e3:.1f} ms", f"{np_vjp * 1e3:.1f} ms", "(its vjp)"], w))
    print(_row(["reference / pyvf", _times(np_fwd / t_fwd), _times(np_vjp / t_fb), ""], w))

    logits = B * H * T * T * 4
    print("extra peak memory of one call, float32 (measured; outputs included)")
    print(_row(["", "forward", "forward+backward", ""], w))
    print(_row(["pyvf (C++ kernel)", format_bytes(mem_fwd), format_bytes(mem_fb), "O(T*dh)"], w))
    print(_row(["NumPy dense reference", format_bytes(mem_np_fwd), format_bytes(mem_np_vjp), "O(T^2)"], w))
    print(_row(["dense logits (computed)", format_bytes(logits), "", "B*H*T^2*4"], w))
    print(_row(["one array like q", format_bytes(q.nbytes), "", "B*H*T*dh*4"], w))
    return ok


def cmd_demo(args):
    """Branching attention at a few sizes: error against the dense reference, time, memory."""
    if args.threads is not None:
        pyvf.set_num_threads(args.threads)
    names = [s.strip() for s in args.sizes.split(",") if s.strip()]
    unknown = [s for s in names if s not in DEMO_SIZES]
    if unknown or not names:
        print(f"pyvf demo: unknown size {unknown or args.sizes!r}; choose from {', '.join(DEMO_SIZES)}",
              file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    print(f"pyvf kernels: path {pyvf.kernel_path()} (this CPU runs {', '.join(pyvf.kernel_paths())}; "
          "PYVF_ISA=<path> forces one; `pyvf config` for details)")
    print("pyvf demo: branching attention (SPEC.md §2), the C++ kernel against the dense NumPy reference")
    print(f"pyvf {pyvf.__version__}, numpy {np.__version__}, {pyvf.num_threads()} kernel threads; "
          "inputs unit normal, scale 1 (unscaled logits, as the published model)")
    print(f"memory: {memory_method()}")
    ok = True
    for name in names:
        ok &= demo_size(name, **DEMO_SIZES[name])
    print(f"\n{'all errors within their bounds' if ok else 'ERROR BOUND EXCEEDED'}; "
          f"total {time.perf_counter() - t0:.0f} s")
    return 0 if ok else 1


def cmd_config(args):
    """Print pyvf.show_config(): the kernels' instruction-set path, the paths this CPU runs, threads."""
    pyvf.show_config()
    return 0


# ---------------------------------------------------------------------------------------
# the parser


def build_parser():
    parser = argparse.ArgumentParser(
        prog="pyvf", description="pyvf: a reference implementation of ViewFormer (ECCV 2022).")
    parser.add_argument("--version", action="version", version=f"pyvf {pyvf.__version__}")
    commands = parser.add_subparsers(dest="command", metavar="command")

    p = commands.add_parser("demo", help="branching attention: error, time and memory against the dense reference",
                            description=cmd_demo.__doc__)
    p.add_argument("--threads", type=int, default=None,
                   help="threads for pyvf's C++ kernels (default: OpenMP's, OMP_NUM_THREADS or all cores)")
    p.add_argument("--sizes", default=",".join(DEMO_SIZES),
                   help=f"comma-separated sizes to run, from {', '.join(DEMO_SIZES)} (default: all)")
    p.set_defaults(func=cmd_demo)

    p = commands.add_parser("config", help="which instruction-set path the kernels use, and the threads",
                            description=cmd_config.__doc__)
    p.set_defaults(func=cmd_config)
    return parser


def main(argv=None):
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    if getattr(args, "threads", None) is not None and args.threads < 1:
        parser.error("--threads must be a positive integer")
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
