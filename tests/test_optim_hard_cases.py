"""Hard cases of pyvf.train.optim found by an audit, each a defect that was fixed: a global norm
that overflows float64 (gradients silently zeroed), parameters that share memory (updated
twice), a parameter made non-finite after the optimiser was built (reported as an overflow),
and a parameter replaced in the dict by an array of another shape, dtype or flags (silently
wrong moments, or a half-applied step). Oracles: torch in float64 and closed forms.
"""

import math

import numpy as np
import pytest
import torch

from pyvf.train import optim

from conftest import assert_bitwise_equal, assert_close


def _copy(d):
    return {k: v.copy() for k, v in d.items()}


def _torch_adamw(params, grad_seq, **kw):
    t = {k: torch.tensor(np.array(v, dtype=np.float64), requires_grad=True) for k, v in params.items()}
    opt = torch.optim.AdamW(list(t.values()), **kw)
    for g in grad_seq:
        for k, p in t.items():
            p.grad = torch.tensor(np.array(g[k], dtype=np.float64))
        opt.step()
    return {k: p.detach().numpy() for k, p in t.items()}


# ---------------------------------------------------------------------------------------
# clip_grad_norm: a total norm beyond float64


def test_clip_global_total_overflowing_float64_raises_and_changes_nothing():
    """Two finite tensors of norm 1.5e308: each norm is finite, their total (2.1e308) is not.
    torch (error_if_nonfinite=True) refuses; pyvf returned inf and multiplied every gradient by
    max_norm / inf = 0, zeroing them. Now ValueError, as per_tensor mode does for a tensor's
    own overflowing norm, and nothing is modified. Just below the limit (total sqrt(2) 1e308)
    the gradients are clipped to the closed form 1/sqrt(2)."""
    grads = {"a": np.array([1.5e308]), "b": np.array([-1.5e308])}
    ps = [torch.zeros(1, dtype=torch.float64) for _ in grads]
    for p, g in zip(ps, grads.values()):
        p.grad = torch.tensor(g)
    with pytest.raises(RuntimeError, match="non-finite"):
        torch.nn.utils.clip_grad_norm_(ps, 1.0, error_if_nonfinite=True)
    for flag in (True, False):
        g = _copy(grads)
        with pytest.raises(ValueError, match="overflows float64: nothing was clipped"):
            optim.clip_grad_norm(g, 1.0, error_if_nonfinite=flag)
        for k in grads:
            assert_bitwise_equal(k, g[k], grads[k])
    g = {"a": np.array([1e308]), "b": np.array([-1e308], np.float64)}
    total = optim.clip_grad_norm(g, 1.0)
    assert_close("total", total, math.sqrt(2) * 1e308, rtol=2 ** -52)
    assert_close("a", g["a"], [1 / math.sqrt(2)], rtol=2 ** -51)
    assert_close("b", g["b"], [-1 / math.sqrt(2)], rtol=2 ** -51)


# ---------------------------------------------------------------------------------------
# AdamW: parameters sharing memory


def test_parameters_sharing_memory_are_refused():
    """One array under two names (a tied weight listed twice) was updated twice per step, with two
    sets of moments (torch warns of duplicate parameters); a view overlapping another parameter
    likewise. Now ValueError naming both. Disjoint views of one flat buffer, also interleaved
    ones, are separate parameters and follow torch."""
    rng = np.random.default_rng(0)
    x = rng.standard_normal((3, 4))
    for params, pair in [({"w": x, "w_tied": x}, "'w', 'w_tied'"),
                         ({"row": x[1], "b": np.zeros(2), "w": x}, "'row', 'w'|'w', 'row'")]:
        before = x.copy()
        with pytest.raises(ValueError, match=f"share memory.*({pair})"):
            optim.AdamW(params, lr=0.1)
        assert_bitwise_equal("x", x, before)
    buf = rng.standard_normal(20)
    params = {"a": buf[:6].reshape(2, 3), "b": buf[6:10], "even": buf[10:][::2], "odd": buf[10:][1::2]}
    start = _copy(params)
    grad_seq = [{k: rng.standard_normal(p.shape) for k, p in params.items()} for _ in range(4)]
    opt = optim.AdamW(params, lr=0.05, weight_decay=0.1)
    for g in grad_seq:
        opt.step(g)
    want = _torch_adamw(start, grad_seq, lr=0.05, weight_decay=0.1)
    for k in params:
        assert_close(k, params[k], want[k], rtol=1e-13)


# ---------------------------------------------------------------------------------------
# AdamW: parameters changed after the optimiser was built


def test_parameter_made_nonfinite_later_is_named_as_such():
    """A parameter set to NaN or inf after construction (params are checked only there): the
    error said "the update overflows (gradients or learning rate too large)", which sends the
    user after the wrong cause. Now it names the parameter as non-finite; nothing is updated."""
    for bad in (np.nan, np.inf):
        params = {"a": np.ones(3), "b": np.ones(2)}
        opt = optim.AdamW(params, lr=0.1)
        params["b"][0] = bad
        with pytest.raises(ValueError, match=r"params contain NaN or inf in \['b'\]"):
            opt.step({"a": np.ones(3), "b": np.ones(2)})
        assert opt.step_count == 0 and (params["a"] == 1).all()
        assert not any(m.any() for m in (*opt.exp_avg.values(), *opt.exp_avg_sq.values()))


def test_parameter_replaced_in_the_dict_is_checked():
    """The optimiser holds the caller's dict. A parameter replaced there by an array of the same
    size in another shape was updated with the old shape's moments (silently wrong); in another
    dtype or size the kernel's binding error named no parameter; a name added gave KeyError; a
    non-contiguous parameter made read-only was found only after the other parameters and every
    moment had been updated (a half-applied step). Each now raises naming the parameter, with
    nothing changed. A replacement of the same shape and dtype is followed (torch's result)."""
    rng = np.random.default_rng(1)
    start = {"a": rng.standard_normal((3, 4)), "f": np.asfortranarray(rng.standard_normal((2, 3)))}
    grads = {"a": rng.standard_normal((3, 4)), "f": rng.standard_normal((2, 3))}
    cases = [("a", rng.standard_normal((4, 3)), ValueError, r"params\['a'\] is now float64\(4, 3\)"),
             ("a", rng.standard_normal(12), ValueError, r"params\['a'\] is now float64\(12,\)"),
             ("a", rng.standard_normal((3, 4)).astype(np.float32), ValueError, r"params\['a'\] is now float32"),
             ("a", np.zeros((3, 5)), ValueError, r"params\['a'\] is now float64\(3, 5\)"),
             ("c", np.zeros(2), ValueError, r"params gained or lost names.*\['c'\]"),
             ("f", None, ValueError, r"params\['f'\] is read-only")]
    for name, new, exc, match in cases:
        params = _copy(start)
        params["f"] = np.asfortranarray(params["f"])
        opt = optim.AdamW(params, lr=0.1)
        opt.step(grads)
        saved, state = _copy(params), opt.state_dict()
        if new is None:
            params[name].flags.writeable = False
        else:
            params[name] = new
        g = {**grads, name: np.ones_like(params[name])}
        with pytest.raises(exc, match=match):
            opt.step(g)
        assert opt.step_count == 1
        for k in start:
            if params[k] is not new:
                assert_bitwise_equal(k, params[k], saved[k])
            assert_bitwise_equal(f"m {k}", opt.exp_avg[k], state["exp_avg"][k])
            assert_bitwise_equal(f"v {k}", opt.exp_avg_sq[k], state["exp_avg_sq"][k])
    params = _copy(start)
    opt = optim.AdamW(params, lr=0.1)
    opt.step(grads)
    params["a"] = params["a"].copy()  # the same values in a new array: the optimiser follows it
    opt.step(grads)
    want = _torch_adamw(start, [grads, grads], lr=0.1)
    for k in start:
        assert_close(k, params[k], want[k], rtol=1e-13)


def test_global_norm_is_the_float64_norm_and_says_nan_or_inf():
    """global_norm (transformer_step's norm without clipping) against NumPy in float64: float32
    tensors whose squares overflow float32, an empty tensor, all zeros; NaN and inf named as nan
    and inf; the gradients are not modified."""
    from pyvf.train.optim import global_norm
    rng = np.random.default_rng(5)
    g = {"a": (rng.standard_normal((7, 5)) * 1e25).astype(np.float32), "b": np.zeros(0, np.float32),
         "c": rng.standard_normal(11)}
    before = {k: v.copy() for k, v in g.items()}
    want = np.sqrt(sum(np.sum(v.astype(np.float64) ** 2) for v in g.values()))
    assert global_norm(g) == pytest.approx(want, rel=1e-14)
    assert all(np.array_equal(before[k], g[k]) for k in g)
    assert global_norm({"z": np.zeros(3)}) == 0.0
    assert np.isnan(global_norm({"a": np.array([np.inf]), "b": np.array([np.nan])}))
    assert global_norm({"a": np.array([np.inf, 1.0]), "b": np.ones(2)}) == np.inf
