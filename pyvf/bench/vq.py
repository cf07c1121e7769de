"""Nearest-code lookup: pyvf.vq_nearest against torch (cdist + argmin, and the expanded
|x|^2 - 2 x.e + |e|^2 matmul the published quantizer uses) and NumPy's expanded matmul.

    pyvf bench vq            # M = 352*64, K = 1024, D = 256, float32
    pyvf bench vq --quick    # M = 4096, K = 256, D = 64

Each method's codes are compared with float64 brute force on unit-normal data (where it is timed)
and offset by 1e2..1e4, where the expanded formula cancels: pyvf must be exact at every offset,
the others miss at most SANITY_WRONG of the codes at offset 0 (near ties), else they are not timed.
"""

import numpy as np

from pyvf.bench.common import TORCH_MISSING, machine, median_time, ms, table, torch_or_none
from pyvf.nn.quantizer import vq_nearest

PAPER = dict(M=352 * 64, K=1024, D=256)
QUICK = dict(M=4096, K=256, D=64)
OFFSETS = (0.0, 1e2, 1e3, 1e4)
SANITY_WRONG = 0.01  # measured: none wrong at offset 0; a wrong axis or layout is wrong nearly everywhere


def brute_force(x, codes, chunk=512):
    """argmin of float64 direct-difference distances, in chunks of rows (memory)."""
    c = codes.astype(np.float64)
    out = np.empty(len(x), dtype=np.int64)
    for i in range(0, len(x), chunk):
        out[i:i + chunk] = ((x[i:i + chunk, None, :].astype(np.float64) - c[None]) ** 2).sum(-1).argmin(1)
    return out


def methods():
    """name -> fn(x, codes) -> indices (torch's where torch is installed)."""
    def numpy_expanded(x, codes):
        return ((x ** 2).sum(1, keepdims=True) - 2 * x @ codes.T + (codes ** 2).sum(1)).argmin(axis=1)

    out = {"pyvf.vq_nearest": lambda x, c: vq_nearest(x, c)[0], "numpy expanded matmul": numpy_expanded}
    torch = torch_or_none()
    if torch is not None:
        def torch_expanded(x, codes):
            tx, tc = torch.from_numpy(x), torch.from_numpy(codes)
            return ((tx ** 2).sum(1, keepdim=True) - 2 * tx @ tc.T + (tc ** 2).sum(1)).argmin(dim=1).numpy()

        out["torch cdist + argmin"] = lambda x, c: torch.cdist(torch.from_numpy(x), torch.from_numpy(c)).argmin(1).numpy()
        out["torch expanded matmul"] = torch_expanded
    return out


def run(quick=False, threads=2, size=None, checked_rows=4096):
    """The table (module docstring) at size dict(M, K, D), wrong codes counted on the first checked_rows."""
    M, K, D = (size or (QUICK if quick else PAPER)).values()
    repeat, checked_rows = 3 if quick else 5, min(checked_rows, M)
    rng = np.random.default_rng(0)
    report = dict(config=dict(M=M, K=K, D=D, threads=threads), machine=machine(threads), methods={}, failures=[])
    print(f"# nearest code: M={M} K={K} D={D}, float32, {threads} threads, median of {repeat}\n")
    x, codes = rng.standard_normal((M, D)).astype(np.float32), rng.standard_normal((K, D)).astype(np.float32)
    cases = [(x[:checked_rows] + np.float32(o), codes + np.float32(o)) for o in OFFSETS]
    truth = [brute_force(*case) for case in cases]
    for name, fn in methods().items():
        wrong = [float((fn(*case) != want).mean()) for case, want in zip(cases, truth)]
        if name.startswith("pyvf") and any(wrong):
            report["failures"].append(f"pyvf disagrees with brute force: {wrong}")
            return report
        ok = wrong[0] <= SANITY_WRONG  # else not the nearest-code lookup: its time would mean nothing
        if not ok:
            report["failures"].append(f"{name}: {wrong[0]:.2%} wrong codes at offset 0 > {SANITY_WRONG:.0%}")
        t = median_time(lambda: fn(x, codes), repeat)[0] if ok else None
        report["methods"][name] = dict(seconds=t, wrong=wrong)
    t0 = report["methods"]["pyvf.vq_nearest"]["seconds"]
    print(table(["method", "time", "time / pyvf's", *(f"wrong codes at offset {o:g}" for o in OFFSETS)], [
        [n, ms(r["seconds"]) if r["seconds"] else "not timed", f"{r['seconds'] / t0:.2f}" if r["seconds"] else "-",
         *(f"{w:.2%}" for w in r["wrong"])] for n, r in report["methods"].items()]))
    if torch_or_none() is None:
        print(f"\ntorch: {TORCH_MISSING}")
    return report
