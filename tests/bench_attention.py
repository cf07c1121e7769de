"""pytest-benchmark suite: branching attention at the paper size (docs/math.md §1-2), pyvf's C++
kernel against torch's scaled_dot_product_attention with the dense (T, T) boolean mask.

    python -m pytest tests/bench_attention.py                      # run the benchmarks
    python -m pytest tests/bench_attention.py --benchmark-json b.json
    PYVF_BENCH_THREADS=1 python -m pytest tests/bench_attention.py

Not part of the test run: pytest collects test_*.py only (pyproject.toml), this file only when
named. Every benchmark validates its own result before it times anything: against pyvf in
float64 on the same inputs, which is itself checked here against the dense NumPy reference in
float64 on head 0 (the reference costs O(T^2): 50 s for all 12 heads; heads are independent)
and against the reference on every head in tests/test_attention.py.
For side-by-side numbers with memory and the NumPy reference: pyvf bench attention.

Shapes: q, k, v, do (R, B, H, N, L, dh) for pyvf; (B, H, T, dh) for torch, T = R*N*L in the
order [row][view][token]. Inputs unit normal, scale 1 (the published model's unscaled logits).
"""

import os

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import pyvf
from conftest import assert_close

R, B, H, N, L, dh = 3, 1, 12, 20, 64, 64  # the paper's size
SHAPE = (R, B, H, N, L, dh)
THREADS = int(os.environ.get("PYVF_BENCH_THREADS", len(os.sched_getaffinity(0))))

# Tolerances, relative to max|want|, as in tests/test_attention.py. float64 vs float64: the same
# O(1) terms summed in another order, measured ~4e-15. float32 (pyvf or torch) vs float64 on
# the same float32 inputs, logits up to ~40: a logit's float32 rounding, sqrt(dh) * 2^-24 *
# |logit| ~ 2e-5 at worst, moves each probability by that relative amount; measured ~3e-6.
RTOL64 = 1e-12
RTOL32 = 1e-5

# Useful flops, attended block pairs only (trunk N(N+1)/2, each branch N(N-1)/2 + N, per head):
# forward 2 matmuls (q k^T, p v) of 2 L^2 dh flops per pair; forward+backward 7 matmuls.
PAIRS = N * (N + 1) // 2 + (R - 1) * (N * (N - 1) // 2 + N)
FLOPS_FWD = 4 * L * L * dh * PAIRS * B * H
FLOPS_FWD_BWD = 3.5 * FLOPS_FWD


def flat(x):
    """(R, B, H, N, L, dh) -> (B, H, T, dh) torch tensor."""
    return torch.from_numpy(np.ascontiguousarray(x.transpose(1, 2, 0, 3, 4, 5).reshape(B, H, R * N * L, dh)))


def unflat(t):
    """(B, H, T, dh) torch tensor -> (R, B, H, N, L, dh) numpy array."""
    return t.detach().numpy().reshape(B, H, R, N, L, dh).transpose(2, 0, 1, 3, 4, 5)


@pytest.fixture(scope="module", autouse=True)
def threads():
    pyvf.set_num_threads(THREADS)
    torch.set_num_threads(THREADS)
    return THREADS


@pytest.fixture(scope="module")
def inputs():
    """q, k, v, do: unit-normal float32 (R, B, H, N, L, dh)."""
    rng = np.random.default_rng(0)
    return tuple(rng.standard_normal(SHAPE, dtype=np.float32) for _ in range(4))


@pytest.fixture(scope="module")
def oracle(inputs):
    """(o, (dq, dk, dv)) of pyvf in float64 on the float32 inputs' values, checked first against
    the dense NumPy reference in float64 on head 0."""
    q, k, v, do = (x.astype(np.float64) for x in inputs)
    o = pyvf.branching_attention(q, k, v)
    grads = pyvf.branching_attention_vjp(q, k, v, do)
    head0 = [np.ascontiguousarray(x[:, :, :1]) for x in (q, k, v, do)]
    assert_close("pyvf f64 o vs reference (head 0)", o[:, :, :1], pyvf.branching_attention_reference(*head0[:3]),
                 RTOL64)
    for name, g, w in zip(("dq", "dk", "dv"), grads, pyvf.branching_attention_reference_vjp(*head0)):
        assert_close(f"pyvf f64 {name} vs reference (head 0)", g[:, :, :1], w, RTOL64)
    return o, grads


@pytest.fixture(scope="module")
def torch_inputs(inputs):
    """Flat q, k, v, do, leaves of q, k, v that require grad, and the (T, T) bool mask."""
    q, k, v, do = (flat(x) for x in inputs)
    leaves = tuple(x.clone().requires_grad_(True) for x in (q, k, v))
    mask = torch.from_numpy(pyvf.branching_mask(R, N, L))
    return q, k, v, do, leaves, mask


def record(benchmark, flops):
    benchmark.extra_info["threads"] = THREADS
    benchmark.extra_info["useful_gflop"] = flops / 1e9
    benchmark.extra_info["useful_gflops_per_s_median"] = flops / benchmark.stats.stats.median / 1e9


# ---------------------------------------------------------------------------------------
# forward


@pytest.mark.benchmark(group="forward")
def test_pyvf_forward(benchmark, inputs, oracle):
    q, k, v, _ = inputs

    def fwd():
        return pyvf.branching_attention_forward(q, k, v)

    o, _ = fwd()
    assert_close("pyvf f32 o", o, oracle[0], RTOL32)
    benchmark(fwd)
    record(benchmark, FLOPS_FWD)


@pytest.mark.benchmark(group="forward")
def test_torch_sdpa_dense_mask_forward(benchmark, torch_inputs, oracle):
    q, k, v, _, _, mask = torch_inputs

    def fwd():
        with torch.no_grad():
            return F.scaled_dot_product_attention(q, k, v, attn_mask=mask, scale=1.0)

    assert_close("torch f32 o", unflat(fwd()), oracle[0], RTOL32)
    benchmark(fwd)
    record(benchmark, FLOPS_FWD)


# ---------------------------------------------------------------------------------------
# forward + backward (random upstream gradient do)


@pytest.mark.benchmark(group="forward+backward")
def test_pyvf_forward_backward(benchmark, inputs, oracle):
    q, k, v, do = inputs

    def fwd_bwd():
        o, lse = pyvf.branching_attention_forward(q, k, v)
        return o, pyvf.branching_attention_backward(do, q, k, v, o, lse)

    o, grads = fwd_bwd()
    assert_close("pyvf f32 o", o, oracle[0], RTOL32)
    for name, g, w in zip(("dq", "dk", "dv"), grads, oracle[1]):
        assert_close(f"pyvf f32 {name}", g, w, RTOL32)
    benchmark(fwd_bwd)
    record(benchmark, FLOPS_FWD_BWD)


@pytest.mark.benchmark(group="forward+backward")
def test_torch_sdpa_dense_mask_forward_backward(benchmark, torch_inputs, oracle):
    _, _, _, do, leaves, mask = torch_inputs

    def fwd_bwd():  # autograd.grad: no .grad accumulated across rounds
        o = F.scaled_dot_product_attention(*leaves, attn_mask=mask, scale=1.0)
        return o, torch.autograd.grad(o, leaves, do)

    o, grads = fwd_bwd()
    assert_close("torch f32 o", unflat(o), oracle[0], RTOL32)
    for name, g, w in zip(("dq", "dk", "dv"), grads, oracle[1]):
        assert_close(f"torch f32 {name}", unflat(g), w, RTOL32)
    benchmark(fwd_bwd)
    record(benchmark, FLOPS_FWD_BWD)
