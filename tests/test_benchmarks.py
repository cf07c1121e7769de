"""The pytest-benchmark suite: every op of `pyvf bench accuracy` (pyvf/bench/accuracy.py), every
variant (pyvf float32 on each kernel path this CPU runs, pyvf float64, the plain loops, torch
float32, the NumPy reference), grouped by op, each result validated against the float64
reference before it is timed, with backend, dtype, path, the error and the peak memory of one
call in `extra_info`.

In the normal `pytest` run this is a smoke run (the "smoke" sizes, 3 rounds: a few seconds);
PYVF_BENCH_SIZE=quick or full times the sizes of `pyvf bench accuracy [--quick]`:

    PYVF_BENCH_SIZE=full pytest tests/test_benchmarks.py --benchmark-only --benchmark-json=bench.json
"""

import functools
import os

import numpy as np
import pytest
import pytest_benchmark  # noqa: F401  (a test requirement: missing, this fails, never skips)

import pyvf
from pyvf.bench import accuracy
from pyvf.bench.common import peak_memory, torch_or_none

SIZE = os.environ.get("PYVF_BENCH_SIZE", "smoke")
ROUNDS = 3 if SIZE == "smoke" else 5
WITH_TORCH = torch_or_none() is not None


@functools.lru_cache(maxsize=None)
def problem(name):
    """(op, inputs, float64 reference, exact vq indices or None) for one op, built once."""
    op = accuracy.make_op(name, SIZE)
    x = op.inputs(np.random.default_rng(0))
    exact = op.exact_indices(x) if name == "vq_nearest" else None
    return op, x, op.reference(x), exact


def cases():
    out = []
    for name in accuracy.OPS:
        op = accuracy.make_op(name, "smoke")
        for v in accuracy.variants(op, with_torch=WITH_TORCH):
            out.append(pytest.param(name, v, id=f"{name}-{v['name'].replace(' ', '_')}"))
    return out


@pytest.mark.parametrize("name, variant", cases())
def test_bench(benchmark, name, variant):
    op, x, ref, exact = problem(name)
    fn = accuracy.variant_fn(op, x, variant)
    with pyvf.use_kernel_path(variant["path"] or pyvf.kernel_path()):
        # validate before timing: the same errors and bounds as `pyvf bench accuracy`
        err = accuracy.errors(op, fn(), ref, variant["dtype"])
        worst = max(e["rel"] for e in err.values())
        assert worst <= variant["bound"], f"{name} {variant['name']}: error {worst:.2e} > bound {variant['bound']:.1e}"
        if exact is not None and variant["backend"] == "pyvf":
            assert (fn.indices == exact).all(), f"{name} {variant['name']}: a wrong code"
        if op.elementwise and variant["backend"] == "pyvf":
            assert err["y"]["ulps"] <= accuracy.GELU_ULPS + 1, err
        _, peak = peak_memory(fn)
        benchmark.group = name
        benchmark.extra_info.update(backend=variant["backend"], dtype=variant["dtype"], path=variant["path"],
                                    plain=variant["plain"], size=str(op.size), peak_bytes=int(peak),
                                    rel_error=worst, bound=variant["bound"])
        benchmark.pedantic(fn, rounds=ROUNDS, iterations=1, warmup_rounds=1)
