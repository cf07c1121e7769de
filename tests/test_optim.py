"""Tests of pyvf.train.optim (docs/math.md §4, §5): AdamW and Adam against torch.optim in float64 over many
steps of random gradients, the Keras epsilon convention against a hand computation, the warmup +
cosine schedule at its key steps and driven through torch's LambdaLR, gradient clipping against
torch.nn.utils.clip_grad_norm_ and by hand (hard case: float32 values near its maximum), zero and non-finite gradients, checkpoint round trips
(save, load, continue = the uninterrupted run, bit for bit) and argument checks.

params and grads are dicts name -> array. Relative errors are normwise (conftest.assert_close).
"""

import math
import pickle
import warnings

import numpy as np
import pytest
import torch

from pyvf.train import optim

from conftest import assert_bitwise_equal, assert_close

# pyvf vs torch, float64, 20 steps: the same operations in the same order on the same numbers,
# except that torch updates m by lerp and v by addcmul, which round differently from
# b1*m + (1-b1)*g by an ulp; each step's update is O(lr) and the errors do not grow through
# Adam's normalisation. Measured <= 1.9e-16 (some configurations bitwise equal); 1e-13 leaves
# room for another CPU while a real bug (a wrong bias correction, eps in the wrong place, decay
# after the step) is >= 1e-6.
RTOL_TORCH64 = 1e-13
# float32, the same with float32 roundings: measured 7.7e-8 (~1 ulp of the parameters); 1e-6
RTOL_TORCH32 = 1e-6
# by-hand results of one multiply by a rounded coefficient (g * (max_norm / |g|)): 1 ulp
ULP64 = 2.0 ** -52

SHAPES = {"h.0/attn/c_attn/weight": (6, 18), "h.0/attn/c_attn/bias": (1, 18),
          "h.0/ln_1/gamma": (6,), "wte/weight": (10, 6)}


def make_params(rng, dtype=np.float64, shapes=SHAPES):
    return {k: rng.standard_normal(s).astype(dtype) for k, s in shapes.items()}


def make_grads(rng, dtype=np.float64, shapes=SHAPES, scale=1.0):
    # the gradients' scales differ per tensor, as in a model (and so that eps matters somewhere)
    return {k: (scale * 10.0 ** rng.uniform(-4, 1) * rng.standard_normal(s)).astype(dtype)
            for k, s in shapes.items()}


def torch_run(params, grad_seq, opt_cls, groups=None, lr_lambda=None, **kw):
    """Run torch opt_cls over grad_seq from copies of params; returns the final params (numpy)
    and the torch optimiser."""
    t = {k: torch.tensor(v.copy(), requires_grad=True) for k, v in params.items()}
    if groups is None:
        opt = opt_cls(list(t.values()), **kw)
    else:
        opt = opt_cls([{"params": [t[k] for k in names], **g} for names, g in groups], **kw)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_lambda) if lr_lambda else None
    for grads in grad_seq:
        for k, p in t.items():
            p.grad = torch.tensor(grads[k])
        opt.step()
        if sched:
            sched.step()
    return {k: p.detach().numpy() for k, p in t.items()}, opt


def pyvf_run(params, grad_seq, opt_cls, **kw):
    p = {k: v.copy() for k, v in params.items()}
    opt = opt_cls(p, **kw)
    lrs = [opt.step(g) for g in grad_seq]
    return p, opt, lrs


def assert_params_close(got, want, rtol):
    assert got.keys() == want.keys()
    for k in got:
        assert got[k].dtype == want[k].dtype, k
        assert_close(k, got[k], want[k], rtol=rtol)


# ---------------------------------------------------------------------------------------
# AdamW and Adam against torch


@pytest.mark.parametrize("lr,wd,betas,eps,dtype", [
    (1e-3, 0.01, (0.9, 0.999), 1e-8, np.float64),
    (5e-4, 0.3, (0.8, 0.999), 1e-3, np.float64),  # eps large enough to matter for the small-gradient tensors
    (1e-2, 0.1, (0.9, 0.999), 1e-8, np.float32),  # the parameters and moments stay float32
    (1.584e-3, None, (0.5, 0.9), 1e-8, np.float64),  # Adam (no decay) with the codebook's lr and betas
])
def test_adamw_matches_torch(rng, lr, wd, betas, eps, dtype):
    """20 steps, fresh random gradients each step: parameters, both moments and the step count
    equal torch.optim.AdamW's, or Adam's for wd None (float64: 1e-13; float32: 1e-6)."""
    rtol = RTOL_TORCH64 if dtype == np.float64 else RTOL_TORCH32
    params = make_params(rng, dtype)
    grad_seq = [make_grads(rng, dtype) for _ in range(20)]
    kw = dict(lr=lr, betas=betas, eps=eps, **({} if wd is None else {"weight_decay": wd}))
    got, opt, _ = pyvf_run(params, grad_seq, optim.Adam if wd is None else optim.AdamW, **kw)
    want, topt = torch_run(params, grad_seq, torch.optim.Adam if wd is None else torch.optim.AdamW, **kw)
    assert_params_close(got, want, rtol)
    tp = dict(zip(params, topt.param_groups[0]["params"]))
    for k in params:
        st = topt.state[tp[k]]
        assert opt.exp_avg[k].dtype == opt.exp_avg_sq[k].dtype == dtype
        assert_close(f"m {k}", opt.exp_avg[k], st["exp_avg"].numpy(), rtol=rtol)
        assert_close(f"v {k}", opt.exp_avg_sq[k], st["exp_avg_sq"].numpy(), rtol=rtol)
        assert int(st["step"]) == opt.step_count == 20


def test_adamw_decay_subset_matches_torch_param_groups(rng):
    """Weight decay only on some parameters (published_weight_decay: all but the biases; the set of
    their names gives the same optimiser) = torch with two param groups, weight_decay 0 on the other."""
    params = make_params(rng)
    grad_seq = [make_grads(rng) for _ in range(10)]
    decayed = [k for k in params if optim.published_weight_decay(k)]
    assert decayed == ["h.0/attn/c_attn/weight", "h.0/ln_1/gamma", "wte/weight"]  # LayerNorm is decayed
    rest = [k for k in params if k not in decayed]
    assert optim.AdamW(_copy(params), decay=set(decayed)).decayed == frozenset(decayed)
    got, opt, _ = pyvf_run(params, grad_seq, optim.AdamW, lr=1e-2, weight_decay=0.2, decay=optim.published_weight_decay)
    assert opt.decayed == frozenset(decayed)
    want, _ = torch_run(params, grad_seq, torch.optim.AdamW, lr=1e-2,
                        groups=[(decayed, {"weight_decay": 0.2}), (rest, {"weight_decay": 0.0})])
    assert_params_close(got, want, RTOL_TORCH64)


def test_schedule_as_lr_matches_torch_lambda_lr(rng):
    """lr = WarmupCosine(...) is called with the number of updates already applied, as torch's
    LambdaLR (lambda(0) for the first step): 30 steps through warmup (5), cosine and the end at 0
    (total 25), against torch AdamW + LambdaLR(schedule / peak)."""
    sched = optim.WarmupCosine(peak_lr=0.05, warmup_steps=5, total_steps=25)
    params = make_params(rng)
    grad_seq = [make_grads(rng) for _ in range(30)]
    got, _, lrs = pyvf_run(params, grad_seq, optim.AdamW, lr=sched, weight_decay=0.1)
    assert lrs == [sched(s) for s in range(30)] and lrs[0] == 0.0 and lrs[5] == 0.05
    want, _ = torch_run(params, grad_seq, torch.optim.AdamW, lr=0.05, weight_decay=0.1,
                        lr_lambda=lambda s: sched(s) / 0.05)
    # torch multiplies the base lr by the lambda, so its lr differs from ours by an ulp: 1e-13
    assert_params_close(got, want, RTOL_TORCH64)


# ---------------------------------------------------------------------------------------
# the Keras epsilon convention


def test_keras_convention_first_step_closed_form():
    """After one step m = (1-b1) g, v = (1-b2) g^2, so the two conventions are, in closed form,
        torch: p1 = p0 (1 - lr wd) - lr g / (|g| + eps)
        keras: p1 = p0 (1 - lr wd) - lr g / (|g| + eps / sqrt(1 - b2)).
    With |g| = 1e-7 ~ eps / sqrt(1 - b2) = 3.2e-7 the Keras step is about 2.6x smaller."""
    lr, wd, b1, b2, eps = 0.1, 0.01, 0.9, 0.999, 1e-8
    p0, g = np.array([0.5, -2.0, 3.0]), np.array([1e-7, -1.0, 0.0])
    for conv, eps_eff in (("torch", eps), ("keras", eps / math.sqrt(1 - b2))):
        p = {"w": p0.copy()}
        optim.AdamW(p, lr=lr, betas=(b1, b2), eps=eps, weight_decay=wd, eps_convention=conv).step({"w": g})
        want = p0 * (1 - lr * wd) - lr * g / (np.abs(g) + eps_eff)
        assert_close(f"{conv} step 1", p["w"], want, rtol=1e-15)


# ---------------------------------------------------------------------------------------
# the schedule


def test_warmup_cosine_key_steps():
    """W = 2000, T = 120000 (the SM7 run), peak 1e-4: 0 at step 0, linear (peak/2 at W/2), peak
    exactly at W, half the peak at (W + T)/2, 0 exactly at T and after. W = 0 starts at the peak."""
    f = optim.warmup_cosine_lr
    kw = dict(peak_lr=1e-4, warmup_steps=2000, total_steps=120_000)
    assert f(0, **kw) == 0.0
    assert f(1000, **kw) == 5e-5
    assert f(2000, **kw) == 1e-4
    assert abs(f(61_000, **kw) - 0.5e-4) <= 1e-16 * 1e-4
    q = 2000 + 118_000 // 4  # a quarter into the decay: cos(pi/4)
    assert abs(f(q, **kw) - 1e-4 * (1 + math.sqrt(0.5)) / 2) <= 1e-15 * 1e-4
    assert f(120_000, **kw) == 0.0 and f(10 ** 9, **kw) == 0.0
    assert f(0, 1e-3, 0, 100) == 1e-3 and f(100, 1e-3, 0, 100) == 0.0
    sched = optim.WarmupCosine(1e-4, 2000, 120_000)
    assert [sched(s) for s in (0, 2000, 61_000, 120_000)] == [f(s, **kw) for s in (0, 2000, 61_000, 120_000)]
    lrs = np.array([f(s, **kw) for s in range(2000, 120_001, 500)])
    assert (np.diff(lrs) <= 0).all()  # monotone decay


# ---------------------------------------------------------------------------------------
# gradient clipping


def _copy(d):
    return {k: v.copy() for k, v in d.items()}


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("max_norm", [0.5, 1e3])  # clipping, and not
def test_clip_global_matches_torch(rng, dtype, max_norm):
    """The returned total norm and the clipped gradients equal torch.nn.utils.clip_grad_norm_'s
    (float64: 1e-15, a sum of squares in another order, measured 2.6e-16; float32: the norm
    here is accumulated in float64, torch's in float32, measured 1.4e-7, 1e-6)."""
    grads = make_grads(rng, dtype, scale=1.0)
    mine = _copy(grads)
    total = optim.clip_grad_norm(mine, max_norm)
    ps = [torch.zeros(g.shape, dtype=torch.float64 if dtype == np.float64 else torch.float32)
          for g in grads.values()]
    for p, g in zip(ps, grads.values()):
        p.grad = torch.tensor(g)
    ttotal = torch.nn.utils.clip_grad_norm_(ps, max_norm)
    rtol = 1e-15 if dtype == np.float64 else 1e-6
    assert isinstance(total, float)
    assert_close("total norm", total, float(ttotal), rtol=rtol)
    exact = math.sqrt(math.fsum(float(np.sum(g.astype(np.float64) ** 2)) for g in grads.values()))
    assert_close("total norm vs fsum", total, exact, rtol=1e-15)
    for (k, g), p in zip(mine.items(), ps):
        assert g.dtype == dtype
        assert_close(k, g, p.grad.numpy(), rtol=rtol)
    if max_norm > total:
        for k in grads:
            assert_bitwise_equal(f"untouched {k}", mine[k], grads[k])


def test_clip_per_tensor_by_hand():
    """tf.clip_by_norm per tensor, max_norm 1: (3, 4) (norm 5) -> (0.6, 0.8); a tensor of norm
    0.5 and an all-zero tensor are left untouched bit for bit; returns each tensor's norm."""
    grads = {"a": np.array([3.0, 4.0]), "b": np.array([[0.3], [-0.4]]), "z": np.zeros(3),
             "f": np.array([[0.0, -6.0], [8.0, 0.0]], np.float32)}
    orig = _copy(grads)
    norms = optim.clip_grad_norm(grads, 1.0, mode="per_tensor")
    assert norms == {"a": 5.0, "b": 0.5, "z": 0.0, "f": 10.0}
    assert_close("a", grads["a"], [0.6, 0.8], rtol=ULP64)
    assert_close("f", grads["f"], np.array([[0, -0.6], [0.8, 0]]), rtol=1e-7)
    assert grads["f"].dtype == np.float32
    assert_bitwise_equal("b", grads["b"], orig["b"])
    assert_bitwise_equal("z", grads["z"], orig["z"])


@pytest.mark.parametrize("mode", ["global", "per_tensor"])
def test_clip_zero_gradients(mode):
    """All-zero gradients: norm 0, nothing changed, no warning, no NaN."""
    grads = {"a": np.zeros((3, 2)), "b": np.zeros(4, np.float32)}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with np.errstate(all="raise"):
            out = optim.clip_grad_norm(grads, 1.0, mode=mode)
    assert out == (0.0 if mode == "global" else {"a": 0.0, "b": 0.0})
    assert all((g == 0).all() and not np.signbit(g).any() for g in grads.values())


@pytest.mark.parametrize("mode", ["global", "per_tensor"])
def test_clip_nonfinite(mode):
    """NaN/inf gradients raise ValueError naming grads, and so does a float64 norm that overflows
    (entries of 1e200): nothing is modified (max_norm / inf would zero the gradients)."""
    for bad in (np.nan, np.inf, 1e200):
        grads = {"ok": np.array([30.0, 40.0]), "bad": np.array([1.0, bad])}
        orig = _copy(grads)
        with pytest.raises(ValueError, match=r"\bgrads\b"):
            optim.clip_grad_norm(grads, 1.0, mode=mode)
        for k in grads:
            assert_bitwise_equal(k, grads[k], orig[k])


# ---------------------------------------------------------------------------------------
# zero and non-finite gradients in the optimiser


def test_adamw_zero_gradients(rng):
    """Zero gradients: m = v = 0, the Adam step is exactly 0 (0 / eps), so without decay the
    parameters are unchanged bit for bit and with decay they only shrink by 1 - lr wd. No NaN."""
    params = make_params(rng)
    zeros = {k: np.zeros_like(v) for k, v in params.items()}
    p = _copy(params)
    opt = optim.AdamW(p, lr=0.1, weight_decay=0.0)
    with np.errstate(all="raise"):
        for _ in range(3):
            opt.step(zeros)
    for k in params:
        assert_bitwise_equal(k, p[k], params[k])
    p = _copy(params)
    opt = optim.AdamW(p, lr=0.1, weight_decay=0.5)
    opt.step(zeros)
    for k in params:
        assert_bitwise_equal(k, p[k], params[k] * (1 - 0.1 * 0.5))


@pytest.mark.parametrize("bad, dtype", [(np.nan, np.float64), (-np.inf, np.float64), (1e22, np.float32)])
def test_adamw_nonfinite_update_raises_and_changes_nothing(rng, bad, dtype):
    """A NaN or inf gradient, or a float32 one of 1e22 ((1 - b2) g g overflows: v = inf), in the last
    tensor of several: ValueError naming it; parameters, moments and the step count untouched (the
    tensors checked before it too), so skipping the step is the same as never seeing it."""
    p = make_params(rng, dtype)
    opt = optim.AdamW(p, lr=0.1)
    opt.step(make_grads(rng, dtype))
    before_p, before = _copy(p), opt.state_dict()
    g = make_grads(rng, dtype)
    g["wte/weight"][3, 2] = bad
    with pytest.raises(ValueError, match="wte/weight"):
        opt.step(g)
    assert opt.step_count == 1
    for k in before_p:
        assert_bitwise_equal(k, p[k], before_p[k])
        assert_bitwise_equal(f"m {k}", opt.exp_avg[k], before["exp_avg"][k])
        assert_bitwise_equal(f"v {k}", opt.exp_avg_sq[k], before["exp_avg_sq"][k])


# ---------------------------------------------------------------------------------------
# checkpointing


@pytest.mark.parametrize("conv, dtype", [("torch", np.float64), ("keras", np.float32)])
def test_state_round_trip_continues_bitwise(rng, conv, dtype):
    """Run 12 steps with a schedule; separately run 5, save (state_dict, through pickle, as a
    checkpoint file would), build a new optimiser on the saved parameters, load, run the last 7:
    the parameters and moments are bitwise those of the uninterrupted run."""
    params = make_params(rng, dtype)
    grad_seq = [make_grads(rng, dtype) for _ in range(12)]
    kw = dict(lr=optim.WarmupCosine(0.05, 3, 10), weight_decay=0.1, eps_convention=conv,
              decay=optim.published_weight_decay)
    full, opt_full, _ = pyvf_run(params, grad_seq, optim.AdamW, **kw)
    half, opt_half, _ = pyvf_run(params, grad_seq[:5], optim.AdamW, **kw)
    blob = pickle.dumps((half, opt_half.state_dict()))
    for g in grad_seq[5:7]:  # the first run goes on; the checkpoint must not change
        opt_half.step(g)
    saved_params, saved_state = pickle.loads(blob)
    opt = optim.AdamW(saved_params, **kw)
    opt.load_state_dict(saved_state)
    assert opt.step_count == 5
    for g in grad_seq[5:]:
        opt.step(g)
    assert opt.step_count == 12
    for k in params:
        assert_bitwise_equal(k, saved_params[k], full[k])
        assert_bitwise_equal(f"m {k}", opt.exp_avg[k], opt_full.exp_avg[k])
        assert_bitwise_equal(f"v {k}", opt.exp_avg_sq[k], opt_full.exp_avg_sq[k])


def test_state_dict_is_a_copy_and_load_checks(rng):
    """state_dict() is independent of later steps, and load_state_dict copies in; loading into an
    optimiser with other hyperparameters raises ValueError; the lists a JSON round trip gives are
    the saved tuple and names, and load."""
    params = make_params(rng)
    opt = optim.AdamW(_copy(params), lr=0.1)
    opt.step(make_grads(rng))
    sd = opt.state_dict()
    m0 = sd["exp_avg"]["wte/weight"].copy()
    opt.step(make_grads(rng))
    assert_bitwise_equal("saved m unchanged", sd["exp_avg"]["wte/weight"], m0)
    opt2 = optim.AdamW(_copy(params), lr=0.1)
    hyper = sd["hyperparameters"]
    opt2.load_state_dict({**sd, "hyperparameters": {**hyper, "betas": list(hyper["betas"]),
                                                    "decayed": list(reversed(hyper["decayed"]))}})
    sd["exp_avg"]["wte/weight"][:] = 7
    assert not (opt2.exp_avg["wte/weight"] == 7).any() and opt2.step_count == 1
    for kw, what in [(dict(betas=(0.9, 0.99)), "betas"), (dict(decay={"wte/weight"}), "decayed")]:
        with pytest.raises(ValueError, match=f"other hyperparameters.*{what}"):
            optim.AdamW(_copy(params), lr=0.1, **kw).load_state_dict(opt.state_dict())


@pytest.mark.parametrize("call, error, name", [
    (lambda p: optim.AdamW(p, lr=-1.0), ValueError, "lr"),
    (lambda p: optim.AdamW(p, betas=(0.9, 1.0)), ValueError, "betas"),
    (lambda p: optim.AdamW(p, eps=0.0), ValueError, "eps"),
    (lambda p: optim.AdamW(p, weight_decay=-0.1), ValueError, "weight_decay"),
    (lambda p: optim.AdamW(p, eps_convention="tf"), ValueError, "eps_convention"),
    (lambda p: optim.WarmupCosine(1e-3, 100, 100), ValueError, "total_steps"),
    (lambda p: optim.WarmupCosine(float("nan"), 10, 100), ValueError, "peak_lr"),
    (lambda p: optim.clip_grad_norm(p, 0.0), ValueError, "max_norm"),
    (lambda p: optim.clip_grad_norm(p, 1.0, mode="tensor"), ValueError, "mode"),
])
def test_refusals_name_the_argument(rng, call, error, name):
    with pytest.raises(error, match=rf"\b{name}\b"):
        call(make_params(rng))


# ---------------------------------------------------------------------------------------
# the norm train_step logs


def test_global_norm_is_the_float64_norm_and_says_nan_or_inf():
    """global_norm (train_step's norm without clipping) against NumPy in float64: float32
    tensors whose squares overflow float32, an empty tensor, all zeros; NaN and inf named as nan
    and inf; the gradients are not modified. Per tensor, float32 values near the float32 maximum."""
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
    big = {"c": np.array([3e38, 4e38 / 2], np.float32)}
    big_orig = big["c"].astype(np.float64)
    norms = optim.clip_grad_norm(big, 1.0, mode="per_tensor")
    assert_close("float32 max", norms["c"], math.hypot(float(np.float32(3e38)), float(np.float32(2e38))), rtol=1e-15)
    # the coefficient 1 / 3.6e38 is subnormal in float32 (21 significant bits): 1e-6, not float32's 1e-7
    assert_close("clipped", big["c"], big_orig / norms["c"], rtol=1e-6)
