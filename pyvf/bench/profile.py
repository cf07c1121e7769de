"""Where a call's time goes, kernel by kernel, at each thread count.

    pyvf bench threads --profile --calls codebook-paper --counts 1 16

For each chosen scaling call (`pyvf bench threads`' SCALING_CALLS) and thread count: a fresh model,
its first step (its result must be bitwise the first count's, as in the scaling), a second step
untimed (the warm-up), then `steps` steps with every compiled kernel timed per (kernel, shapes of
its array arguments). What is left of the step's time is Python and NumPy outside the kernels: on
one thread wherever pyvf's threads are, so it is what limits the speed-up on many cores
(Amdahl's law: a part that takes a fraction s of the 1-thread time bounds the speed-up by 1/s).

The timer wraps each kernel of `pyvf._core` in the process (kernel_timer); the wrappers are
removed on leaving, also when the step raises. A wrapper adds about a microsecond a call.
"""

import collections
import contextlib
import time

import numpy as np

import pyvf
from pyvf import _core
from pyvf.bench import threads
from pyvf.bench.common import table

OUTSIDE = "outside the kernels (Python, NumPy)"


def _key(name, args):
    """"kernel shapes": the distinct shapes of its array arguments, in order of first appearance."""
    shapes = dict.fromkeys("x".join(map(str, a.shape)) for a in args if isinstance(a, np.ndarray))
    return " ".join([name, *shapes])


@contextlib.contextmanager
def kernel_timer():
    """Within the block every compiled kernel called through `pyvf._core` is timed; yields
    {"kernel shapes": [calls, seconds]}, filled as the calls run. The kernels are those of the
    kernel path current on entry (a `pyvf.use_kernel_path` inside the block does not reach them)."""
    totals = collections.defaultdict(lambda: [0, 0.0])
    names = _core.kernels()

    def wrap(name, fn):
        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                entry = totals[_key(name, args)]
                entry[0] += 1
                entry[1] += time.perf_counter() - t0
        return timed
    # a module attribute is found before the module's __getattr__, so every `_core.<kernel>` call
    # reaches the wrapper; deleting it restores the forwarding to the current path
    for name in names:
        setattr(_core, name, wrap(name, getattr(_core, name)))
    try:
        yield totals
    finally:
        for name in names:
            _core.__dict__.pop(name, None)


def profile_call(prepare, counts, steps=2):
    """prepare(): a scaling call's (-> (step, result)). -> {"parts": {count: {part: seconds per
    step}}, the parts each (kernel, shapes) and OUTSIDE (the step's time in no kernel), "calls":
    {part: kernel calls per step}, "step": {count: seconds per step}, "bitwise": whether the first
    step's result is bitwise the same at every count}."""
    parts, calls, total, want, same = {}, {}, {}, None, True
    for n in counts:
        with pyvf.threads(n):
            step, got = threads.prepared(prepare)
            with kernel_timer() as totals:
                t0 = time.perf_counter()
                for _ in range(steps):
                    step()
                elapsed = time.perf_counter() - t0
        want = got if want is None else want
        same = same and bool(np.array_equal(got, want))
        parts[n] = {k: s / steps for k, (_, s) in totals.items()}
        parts[n][OUTSIDE] = max(elapsed / steps - sum(parts[n].values()), 0.0)
        calls.update({k: c / steps for k, (c, _) in totals.items()})
        total[n] = elapsed / steps
    return {"parts": parts, "calls": calls, "step": total, "bitwise": same}


def profile_table(prof, top=15):
    """(header, rows) of a profile_call result: the `top` kernel parts by their time on the first
    count, each one's calls per step, ms per step and speed-up at every count, and its share of the
    step on the last count; the other kernels folded into one row, then OUTSIDE and the step."""
    parts, total = prof["parts"], prof["step"]
    counts = list(parts)
    first = parts[counts[0]]
    kernels = sorted((k for k in first if k != OUTSIDE), key=first.get, reverse=True)
    shown, rest = kernels[:top], kernels[top:]

    def row(name, get, calls):
        t1 = get(counts[0])
        return [name, calls, *(f"{get(n) * 1e3:.1f}" + (f" ({t1 / get(n):.1f}x)" if get(n) > 0 else "")
                              for n in counts), f"{100 * get(counts[-1]) / total[counts[-1]]:.0f}%"]
    rows = [row(k, lambda n, k=k: parts[n].get(k, 0.0), f"{prof['calls'][k]:g}") for k in shown]
    if rest:
        rows.append(row(f"{len(rest)} other kernel shapes", lambda n: sum(parts[n].get(k, 0.0) for k in rest),
                        f"{sum(prof['calls'][k] for k in rest):g}"))
    rows.append(row(OUTSIDE, lambda n: parts[n][OUTSIDE], ""))
    rows.append(row("the whole step", lambda n: total[n], ""))
    return ["part", "calls", *(f"{n} thr: ms (speed-up)" for n in counts), f"share on {counts[-1]} thr"], rows


def run(calls, counts, quick=False, steps=2, log=print):
    """Profile each of `calls` (threads.SCALING_CALLS names; quick: their quick sizes) at `counts`;
    -> {"counts", "calls": {name: profile_call's result}, "failures", "kernel_path"} (seconds)."""
    report = {"counts": list(counts), "calls": {}, "failures": [], "kernel_path": pyvf.kernel_path()}
    for name in calls:
        prof = profile_call(threads.SCALING_CALLS[name][0](quick), counts, steps)
        log(f"# {name}: {steps} timed steps per count")
        log(table(*profile_table(prof)))
        if not prof["bitwise"]:
            report["failures"].append(f"profile: {name} is not bitwise the same at every thread count")
        report["calls"][name] = dict(prof, parts={str(n): p for n, p in prof["parts"].items()},
                                     step={str(n): t for n, t in prof["step"].items()})
    return report
