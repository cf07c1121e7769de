"""Nearest-code lookup at the paper's size: pyvf.vq_nearest against torch (cdist + argmin, and the
expanded |x|^2 - 2 x.e + |e|^2 matmul the published quantizer uses) and numpy, side by side.

    pyvf bench vq            # M = 352*64, K = 1024, D = 256, float32, 2 threads
    pyvf bench vq --quick    # M = 4096, K = 256, D = 64, median of 3: seconds

Each method's answers are compared with float64 brute force (exact distances, first minimum)
before timing: on unit-normal data (pyvf must be exact, the others nearly: SANITY_WRONG), and on
the cancellation cases (data offset by 1e2..1e4 from the origin) where the expanded formula
picks wrong codes. The offset cases also time pyvf, which re-ranks exactly every code its error
bound cannot exclude. torch is imported inside the functions that use it.
"""

import sys

import numpy as np

import pyvf
from pyvf.bench.common import TORCH_MISSING, median_time, torch_or_none
from pyvf.nn.quantizer import vq_nearest

PAPER = dict(M=352 * 64, K=1024, D=256, repeat=5, checked_rows=4096)
QUICK = dict(M=4096, K=256, D=64, repeat=3, checked_rows=1024)
# The share of wrong codes allowed at offset 0 (unit-normal data, where the time is measured) to
# the other methods: their float32 distances are right there but for near ties (measured: none
# wrong at either size); a wrong axis or layout picks wrong codes nearly everywhere. Over it a
# method is not timed.
SANITY_WRONG = 0.01


def brute_force(x, codes, chunk=512):
    """argmin of float64 direct-difference distances, in chunks of rows (memory)."""
    c = codes.astype(np.float64)
    out = np.empty(len(x), dtype=np.int64)
    for i in range(0, len(x), chunk):
        xs = x[i:i + chunk].astype(np.float64)
        d = ((xs[:, None, :] - c[None]) ** 2).sum(axis=-1)
        out[i:i + chunk] = d.argmin(axis=1)
    return out


def methods():
    """name -> fn(x, codes) -> indices; the torch rows only where torch is installed."""
    def numpy_expanded(x, codes):
        d = (x ** 2).sum(1, keepdims=True) - 2 * x @ codes.T + (codes ** 2).sum(1)
        return d.argmin(axis=1)

    pyvf_numpy = {"pyvf.vq_nearest": lambda x, c: vq_nearest(x, c)[0], "numpy expanded matmul": numpy_expanded}
    torch = torch_or_none()
    if torch is None:
        return pyvf_numpy

    def torch_cdist(x, codes):
        return torch.cdist(torch.from_numpy(x), torch.from_numpy(codes)).argmin(dim=1).numpy()

    def torch_expanded(x, codes):
        tx, tc = torch.from_numpy(x), torch.from_numpy(codes)
        d = (tx ** 2).sum(1, keepdim=True) - 2 * tx @ tc.T + (tc ** 2).sum(1)
        return d.argmin(dim=1).numpy()

    return {**pyvf_numpy, "torch cdist + argmin": torch_cdist, "torch expanded matmul": torch_expanded}


def run(M, K, D, repeat=5, checked_rows=4096, threads=2):
    """The table (module docstring) for M points, K codes of width D: each method's median time
    of `repeat` calls and its share of wrong codes at each offset (on the first checked_rows
    points), then pyvf's time at the offsets. Returns the report; report["failures"] is not
    empty when pyvf disagrees with brute force (then nothing more is timed) or another method
    picks more than SANITY_WRONG wrong codes at offset 0 (that one is not timed)."""
    torch = torch_or_none()
    if torch is not None:
        torch.set_num_threads(threads)
    pyvf.set_num_threads(threads)
    rng = np.random.default_rng(0)
    checked_rows = min(checked_rows, M)
    report = dict(config=dict(M=M, K=K, D=D, repeat=repeat, checked_rows=checked_rows, threads=threads),
                  offsets=[0.0, 1e2, 1e3, 1e4], methods={}, pyvf_offset_seconds={}, failures=[])
    print(f"# nearest code: M={M} K={K} D={D}, float32, {threads} threads, median of {repeat}\n")
    print("| method | time (unit normal data) | wrong, offset 0 | wrong, 1e2 | wrong, 1e3 | wrong, 1e4 |")
    print("|---|---|---|---|---|---|")
    base_x = rng.standard_normal((M, D)).astype(np.float32)
    base_c = rng.standard_normal((K, D)).astype(np.float32)
    truth = {}
    for off in report["offsets"]:  # a subset of rows is enough for the disagreement rates
        xs, cs = base_x[:checked_rows] + np.float32(off), base_c + np.float32(off)
        truth[off] = (xs, cs, brute_force(xs, cs))
    results = report["methods"]
    for name, fn in methods().items():
        wrong = [float((fn(xs, cs) != want).mean()) for xs, cs, want in truth.values()]
        if name.startswith("pyvf") and any(wrong):
            print(f"pyvf disagrees with brute force: {wrong}", file=sys.stderr)
            report["failures"].append(f"pyvf disagrees with brute force: {wrong}")
            return report
        if not wrong[0] <= SANITY_WRONG:  # not the nearest-code lookup: its time would mean nothing
            print(f"| {name} | not timed | " + " | ".join(f"{w:.2%}" for w in wrong) + " |")
            report["failures"].append(f"{name}: {wrong[0]:.2%} wrong codes at offset 0 > {SANITY_WRONG:.0%}")
            continue
        t, _ = median_time(lambda: fn(base_x, base_c), repeat=repeat)
        results[name] = dict(seconds=t, wrong=wrong)
        print(f"| {name} | {t * 1e3:.1f} ms | " + " | ".join(f"{w:.2%}" for w in wrong) + " |")
    t0 = results["pyvf.vq_nearest"]["seconds"]
    print("\n" + ("; ".join(f"{name} / pyvf time: {results[name]['seconds'] / t0:.2f}x"
                            for name in ("torch cdist + argmin", "torch expanded matmul") if name in results)
                  if torch is not None else f"torch: {TORCH_MISSING}"))
    print("\npyvf at the cancellation offsets (exact re-rank of the codes the bound cannot exclude):")
    for off in (1e2, 1e3, 1e4):
        xs, cs = base_x + np.float32(off), base_c + np.float32(off)
        t, _ = median_time(lambda: vq_nearest(xs, cs), repeat=1)
        report["pyvf_offset_seconds"][f"{off:g}"] = t
        print(f"  offset {off:g}: {t * 1e3:.0f} ms")
    return report
