"""The inputs a demanding user tries on pyvf.nn.layers and pyvf.nn.losses: outputs that overlap an
input, ids out of range in the public helpers, operands of the wrong dtype or rank, and memory
layouts (Fortran order, negative strides, read-only views) that must not change a result.

Oracles are independent: NumPy float64 formulas written here, or torch in float64; never the
code under test.
"""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

import pyvf
from pyvf.nn import layers, losses

from conftest import assert_close, forced_threads

RTOL64 = 1e-13  # float64 against torch float64: sums in another order (see test_layers.RTOL64)


# ---------------------------------------------------------------------------------------
# layers.add: an `out` that overlaps a or b without being the same array


@pytest.mark.parametrize("shift", [1, -1, 3])
def test_add_out_partially_overlapping_an_input(shift):
    """out = buf[s:], a = buf[:-s] (or the reverse): the same memory, shifted. NumPy's a + b reads
    every input before its slot is overwritten; pyvf's threaded kernel wrote elements that later
    reads used (1 + 1 + ... cascading), a silently wrong sum."""
    n = 3 * 65536 + 7  # past the parallel threshold
    k = abs(shift)
    for n_thr in (1, 2):
        with forced_threads(n_thr):
            buf = np.zeros(n + k)
            a, out = (buf[:-k], buf[k:]) if shift > 0 else (buf[k:], buf[:-k])
            b = np.ones(n)
            want = a.copy() + b.copy()  # NumPy float64, inputs copied first
            got = layers.add(a, b, out=out)
            assert got is out
            np.testing.assert_array_equal(got, want, err_msg=f"shift {shift} on {n_thr} threads")
            buf = np.zeros(n + k)
            b, out = (buf[:-k], buf[k:]) if shift > 0 else (buf[k:], buf[:-k])
            a = np.ones(n)
            got = layers.add(a, b, out=out)
            np.testing.assert_array_equal(got, np.ones(n), err_msg=f"b overlapped, shift {shift}")


def test_add_out_is_an_input_still_in_place():
    """out is a (or b) itself: the documented in-place residual add, element by element."""
    rng = np.random.default_rng(0)
    for dtype in (np.float32, np.float64):
        a = rng.standard_normal(70001).astype(dtype)
        b = rng.standard_normal(70001).astype(dtype)
        want = a.astype(np.float64) + b.astype(np.float64)
        a2 = a.copy()
        assert layers.add(a2, b, out=a2) is a2
        np.testing.assert_array_equal(a2, want.astype(dtype))
        b2 = b.copy()
        assert layers.add(a, b2, out=b2) is b2
        np.testing.assert_array_equal(b2, want.astype(dtype))


# ---------------------------------------------------------------------------------------
# layers.sum_rows_by_id: ids outside [0, n)


@pytest.mark.parametrize("bad", [-1, -3, 3, 7])
def test_sum_rows_by_id_rejects_ids_out_of_range(bad):
    """A negative id wrapped around (NumPy indexing) into a silently wrong row; one >= n was an
    IndexError that named no argument."""
    ids = np.array([0, bad, 2])
    rows = np.ones((3, 4))
    with pytest.raises(ValueError, match=r"ids must be in \[0, 3\)"):
        layers.sum_rows_by_id(ids, rows, 3)


def test_sum_rows_by_id_against_a_loop():
    rng = np.random.default_rng(1)
    ids = rng.integers(0, 5, 40)
    rows = rng.standard_normal((40, 3))
    want = np.zeros((6, 3))
    for i, k in enumerate(ids):
        want[k] += rows[i]
    assert_close("sum_rows_by_id", layers.sum_rows_by_id(ids, rows, 6), want, 1e-15)


# ---------------------------------------------------------------------------------------
# layers.matmul: operands of the wrong dtype or rank


@pytest.mark.parametrize("a_dt, b_dt, bias_dt, name", [
    (np.float32, np.float64, None, "b"),
    (np.float64, np.float32, None, "b"),
    (np.int64, np.int64, None, "a"),
    (np.float16, np.float16, None, "a"),
    (np.float64, np.float64, np.float32, "bias"),
])
def test_matmul_wrong_dtype_names_the_argument(a_dt, b_dt, bias_dt, name):
    a, b = np.ones((3, 4), a_dt), np.ones((4, 2), b_dt)
    bias = None if bias_dt is None else np.ones(2, bias_dt)
    with pytest.raises(TypeError, match=rf"^{name} "):
        layers.matmul(a, b, bias=bias)


@pytest.mark.parametrize("a_shape, b_shape, name", [
    ((3,), (3, 2), "a"),
    ((2, 3, 4), (4, 2), "b"),
    ((3, 4), (2, 4, 2), "b"),
    ((1, 1, 3, 4), (1, 1, 4, 2), "a"),
])
def test_matmul_wrong_rank_names_the_argument(a_shape, b_shape, name):
    with pytest.raises(ValueError, match=rf"^{name} "):
        layers.matmul(np.ones(a_shape), np.ones(b_shape))


def test_matmul_against_numpy_float64():
    rng = np.random.default_rng(2)
    a, b, bias = rng.standard_normal((5, 7)), rng.standard_normal((6, 7)), rng.standard_normal(6)
    assert_close("matmul", layers.matmul(a, b, tb=True, bias=bias), a @ b.T + bias, RTOL64)
    a3, b3 = rng.standard_normal((2, 7, 5)), rng.standard_normal((2, 7, 3))
    assert_close("matmul batched", layers.matmul(a3, b3, ta=True), np.einsum("bkm,bkn->bmn", a3, b3), RTOL64)


# ---------------------------------------------------------------------------------------
# every layer and loss: layouts give torch float64's answer, inputs are not modified


def _layouts(a):
    """a in C order, Fortran order, reversed along the last axis twice (a negatively strided view
    of a reversed copy) and read-only."""
    yield "C", a.copy()
    yield "F", np.asfortranarray(a)
    yield "neg", np.ascontiguousarray(a[..., ::-1])[..., ::-1]
    ro = a.copy()
    ro.setflags(write=False)
    yield "readonly", ro


def _t(a):
    return torch.tensor(np.ascontiguousarray(a), dtype=torch.float64, requires_grad=True)


def _torch_grads(out, dy, leaves):
    out.backward(torch.tensor(dy, dtype=torch.float64))
    return [x.grad.numpy() for x in leaves]


def _cases(rng):
    x, w, b = rng.standard_normal((3, 4, 6)), rng.standard_normal((6, 5)), rng.standard_normal((1, 5))
    g, be = rng.standard_normal(6), rng.standard_normal(6)
    w2, b2 = rng.standard_normal((5, 3)), rng.standard_normal((1, 3))
    ids, table = rng.integers(0, 4, (3, 5)), rng.standard_normal((4, 6))
    logits, tgt = rng.standard_normal((7, 6)) * 3, rng.integers(0, 6, 7)
    raw, target = rng.standard_normal((4, 3, 7)), rng.standard_normal((3, 7))

    def t_linear(x, w, b):
        return F.linear(x, w.T, b[0])

    def t_mlp(x, w, b, w2, b2):
        return F.linear(F.gelu(F.linear(x, w.T, b[0])), w2.T, b2[0])

    def t_ce(lg):
        return F.cross_entropy(lg, torch.tensor(tgt), reduction="none", label_smoothing=0.1)

    def t_pose(r):
        tg = torch.tensor(target, dtype=torch.float64)
        return ((r[..., :3] - 2.5 * tg[..., :3]) ** 2).mean(-1) + ((r[..., 3:] - tg[..., 3:]) ** 2).mean(-1)

    def t_emb(tb):
        return tb[torch.tensor(ids)]

    return [
        ("linear", layers.linear_forward, layers.linear_backward, (x, w, b), (0, 1, 2), t_linear),
        ("layernorm", layers.layernorm_forward, layers.layernorm_backward, (x, g, be), (0, 1, 2),
         lambda x, g, be: F.layer_norm(x, (6,), g, be, eps=1e-5)),
        ("gelu", layers.gelu_forward, layers.gelu_backward, (x,), (0,), F.gelu),
        ("mlp", layers.mlp_forward, layers.mlp_backward, (x, w, b, w2, b2), (0, 1, 2, 3, 4), t_mlp),
        ("embedding", layers.embedding_forward, layers.embedding_backward, (ids, table), (1,), t_emb),
        ("cross_entropy", lambda lg, t: losses.cross_entropy_forward(lg, t, 0.1), losses.cross_entropy_backward,
         (logits, tgt), (0,), t_ce),
        ("pose_loss", lambda r, t: losses.pose_loss_forward(r, t, 2.5), losses.pose_loss_backward,
         (raw, target), (0,), t_pose),
    ]


@pytest.mark.parametrize("case", range(7))
def test_layouts_match_torch_and_inputs_unchanged(case):
    rng = np.random.default_rng(3)
    name, fwd, bwd, args, diff, tfn = _cases(rng)[case]
    leaves = [_t(args[i]) for i in diff]
    targs = list(args)
    for i, leaf in zip(diff, leaves):
        targs[i] = leaf
    want_y = tfn(*[targs[i] for i in diff]) if name in ("cross_entropy", "pose_loss", "embedding") else tfn(*targs)
    dy = rng.standard_normal(tuple(want_y.shape))
    want_g = _torch_grads(want_y, dy, leaves)
    want_y = want_y.detach().numpy()
    for i in range(len(args)):
        if args[i].ndim < 2 and args[i].dtype.kind != "f":
            continue
        for tag, v in _layouts(args[i]):
            call = list(args)
            call[i] = v
            before = [c.copy() for c in call]
            y, cache = fwd(*call)
            assert_close(f"{name} y, arg {i} {tag}", y, want_y, RTOL64)
            for dtag, dv in _layouts(dy):
                grads = bwd(dv, cache)
                for j, gw in zip(diff, want_g):
                    assert_close(f"{name} grad {j}, arg {i} {tag}, dy {dtag}", grads[diff.index(j)], gw, RTOL64)
                np.testing.assert_array_equal(dv, dy)
            for c, c0 in zip(call, before):
                np.testing.assert_array_equal(c, c0, err_msg=f"{name}: an input was modified")


# ---------------------------------------------------------------------------------------
# the upstream gradient: wrong dtype, wrong (broadcastable) shape, not an array, NaN


def _forwards():
    x = np.ones((2, 3))
    return {
        "linear": (layers.linear_backward, layers.linear_forward(x, np.ones((3, 4)), np.ones((1, 4)))[1], (2, 4), "dy"),
        "layernorm": (layers.layernorm_backward, layers.layernorm_forward(x, np.ones(3), np.zeros(3))[1], (2, 3), "dy"),
        "gelu": (layers.gelu_backward, layers.gelu_forward(x)[1], (2, 3), "dy"),
        "embedding": (layers.embedding_backward, layers.embedding_forward(np.array([0, 1]), x)[1], (2, 3), "dy"),
        "mlp": (layers.mlp_backward, layers.mlp_forward(x, np.ones((3, 4)), np.ones((1, 4)), np.ones((4, 2)),
                                                        np.ones((1, 2)))[1], (2, 2), "dy"),
        "cross_entropy": (losses.cross_entropy_backward, losses.cross_entropy_forward(x, np.array([0, 2]))[1], (2,),
                          "dloss"),
        "pose_loss": (losses.pose_loss_backward, losses.pose_loss_forward(np.ones((2, 7)), np.zeros(7))[1], (2,),
                      "dloss"),
    }


@pytest.mark.parametrize("layer", ["linear", "layernorm", "gelu", "embedding", "mlp", "cross_entropy", "pose_loss"])
def test_bad_upstream_gradient_raises_naming_it(layer):
    bwd, cache, shape, name = _forwards()[layer]
    for bad in (np.ones(shape, np.float32), np.ones(shape, np.float16), np.ones(shape, np.int64),
                np.ones(shape, bool), np.ones(shape, object), np.ones(shape).tolist()):
        with pytest.raises(TypeError, match=rf"^{name} "):
            bwd(bad, cache)
    for bad in (np.ones(shape[:-1] + (1,)), np.ones(()), np.ones(shape + (1,)), np.ones((0,) + shape[1:])):
        with pytest.raises(ValueError, match=rf"^{name} "):
            bwd(bad, cache)
    nan = np.ones(shape)
    nan.flat[-1] = np.nan
    with pytest.raises(ValueError, match=rf"^{name} contains NaN"):
        bwd(nan, cache)
