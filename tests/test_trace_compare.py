"""Traces of the transformer and pyvf.compare: named activations and their gradients against torch
autograd in float64 (the torch port of pyvf/verify/torch_ports.py, its activations recorded by
module hooks, never rewriting it), and compare naming the first wrong quantity of a port's traces."""

import re

import numpy as np
import pytest
import torch

import pyvf
from conftest import assert_bitwise_equal, assert_close
from pyvf.models.transformer import trace_names
from pyvf.verify.torch_ports import TransformerPort, official_name, transformer_forward, transformer_losses, tree_mask
from test_transformer import TINY, random_batch, random_model

NO_GRAD = {"ce_loss", "pose_loss", "loss"}  # traced, but the seed of backward, not differentiated


def no_grad_names(n_layer):
    return NO_GRAD | {f"blocks.{j}.attn.lse" for j in range(n_layer)}


# ---------------------------------------------------------------------------------------
# the torch oracle, traced: the port of pyvf/verify/torch_ports.py (written from docs/math.md) with
# module hooks, as a port author traces theirs (tests/test_teacher.py), its losses transformer_losses


def trace_name(module):
    """A TransformerPort module's name -> the trace name of its output ('h.1.attn.c_attn' ->
    'blocks.1.attn.c_attn'); names pyvf does not trace pass through (dropped at the end)."""
    n = re.sub(r"^h\.(\d+)", r"blocks.\1", module).removeprefix("embed.")
    n = {"embed": "embed.out", "wte": "embed.tokens", "wpe": "embed.positions", "pose_head": "pose",
         "ln_f": "ln_f.generation"}.get(n, n)
    return n + ".out" if re.fullmatch(r"blocks\.\d+", n) else n


INPUT_NAMES = {"pose_embedding": "pose_embedding.input", ".ln_2": ".resid_1", ".attn.c_proj": ".attn.out"}


def torch_trace(model, tokens, poses, dlogits=None, dpose=None, dloss=None):
    """The port in float64 on the model's weights -> (trace, activations' gradients, parameters'
    gradients), pyvf's names and layouts, for dloss * loss + sum(logits * dlogits) + sum(raw * dpose).
    q, k, v are the column blocks of c_attn ([v | q | k]), lse is computed from them."""
    cfg, (B, N, L) = model.config, tokens.shape
    d, H = cfg.d_model, cfg.n_head
    port = TransformerPort(cfg).double()
    sd = model.state_dict(layout="torch")
    port.load_state_dict({n: torch.tensor(sd[official_name(n)]) for n in port.state_dict()})
    rec = {}

    def hook(module, args, out):
        name = trace_name(names[module])
        for end, what in INPUT_NAMES.items():  # inputs pyvf traces: a layer's input, not an output
            if name.endswith(end):
                rec[name[:-len(end)] + what] = args[0]
        rec["ln_f.localization" if name in rec else name] = out  # ln_f: generation row, then localization

    names = {m: n for n, m in port.named_modules() if n}
    handles = [m.register_forward_hook(hook) for m in names]
    t_tokens, t_poses = torch.tensor(tokens), torch.tensor(poses, requires_grad=True)
    rec["logits"], raw = port(t_tokens, t_poses)
    [h.remove() for h in handles]
    ce, pl, loss = transformer_losses(rec["logits"], raw, t_tokens, t_poses, cfg)
    [t.retain_grad() for t in rec.values()]
    total = sum(t for t in (None if dloss is None else dloss * loss,
                            None if dlogits is None else (rec["logits"] * torch.tensor(dlogits)).sum(),
                            None if dpose is None else (raw * torch.tensor(dpose)).sum()) if t is not None)
    total.backward()
    heads = lambda t: t.reshape(B, 3 * N * L, H, d // H).transpose(1, 2)  # noqa: E731  (B, H, T, dh)
    trace, grads = dict(rec), {n: torch.zeros_like(t) if t.grad is None else t.grad for n, t in rec.items()}
    mask = tree_mask(N, L)
    for j in range(cfg.n_layer):
        b = f"blocks.{j}.attn."
        for which, a in ((trace, rec[b + "c_attn"].detach()), (grads, rec[b + "c_attn"].grad)):
            which[b + "v"], which[b + "q"], which[b + "k"] = (heads(t) for t in a.split(d, dim=-1))
            which[b + "out"] = heads(which[b + "out"])
        s = cfg.attention_scale * trace[b + "q"] @ trace[b + "k"].transpose(-1, -2)
        trace[b + "lse"] = torch.logsumexp(s.masked_fill(~mask, float("-inf")), -1)  # (B, H, T)
    trace.update(ce_loss=ce, pose_loss=pl, loss=loss.detach().numpy())
    keep = set(trace_names(cfg.n_layer))
    param_grads = pyvf.params_from_layout(model, {official_name(n): torch.zeros_like(p) if p.grad is None else p.grad
                                                  for n, p in port.named_parameters()}, "torch")
    return (pyvf.trace_from_flat({n: t for n, t in trace.items() if n in keep}, N, L),
            pyvf.trace_from_flat({n: t for n, t in grads.items() if n in keep}, N, L), param_grads)


def setup(rng, dtype="float64", **overrides):
    cfg = pyvf.TransformerConfig(**{**TINY, **overrides}, dtype=dtype)
    model = random_model(cfg, rng)
    tokens, poses = random_batch(rng, 2, 4, 16, cfg.n_embeddings, dtype=np.dtype(dtype))
    return model, tokens, poses


def upstream(rng, model, tokens):
    B, N, L = tokens.shape
    return rng.normal(size=(B, N, L, model.config.n_embeddings)), rng.normal(size=(B, N, L, 7))


# ---------------------------------------------------------------------------------------
# 1. tracing changes nothing and costs nothing when off


def test_traced_forward_and_backward_equal_untraced_bitwise(rng):
    model, tokens, poses = setup(rng, "float32")
    dl, dp = (a.astype(np.float32) for a in upstream(rng, model, tokens))
    plain = model.forward(tokens, poses)
    assert plain.trace is None
    g_loss, g_vjp = model.backward(), model.backward(dlogits=dl, dpose=dp)
    assert set(g_loss) == set(model.params)  # untraced: the parameters only, as always
    out = model.forward(tokens, poses, trace=True)
    t_loss, t_vjp = model.backward(), model.backward(dlogits=dl, dpose=dp)
    for field in ("logits", "pose_prediction", "pose_raw", "ce_loss", "pose_loss"):
        assert_bitwise_equal(field, getattr(out, field), getattr(plain, field))
    assert out.loss == plain.loss
    for name in model.params:
        assert_bitwise_equal(f"d{name} (loss)", t_loss[name], g_loss[name])
        assert_bitwise_equal(f"d{name} (vjp)", t_vjp[name], g_vjp[name])
    # the trace: every name, in execution order; the model's outputs are the traced ones
    assert list(out.trace) == trace_names(model.config.n_layer)
    assert_bitwise_equal("trace logits", out.trace["logits"], out.logits)
    assert_bitwise_equal("trace pose", out.trace["pose"], out.pose_raw)
    # gradients: every traced activation but lse and the losses, in backward order, then the parameters
    acts = [n for n in trace_names(model.config.n_layer) if n not in no_grad_names(model.config.n_layer)]
    names = list(t_vjp)
    assert names[:len(acts)] == acts[::-1] and names[len(acts):] == list(model.params)
    assert_bitwise_equal("dlogits seed", t_vjp["logits"], dl)
    assert_bitwise_equal("dpose seed", t_vjp["pose"], dp)


# ---------------------------------------------------------------------------------------
# 2. every traced activation and its gradient against torch autograd, float64


SAME = dict(attention_scale=0.5, pose_multiplier=0.2, label_smoothing=0.1)
CASES = {  # configuration, backward's seeds
    "dlogits_only": (SAME, dict(dlogits=True)),
    "loss_and_vjp": (SAME, dict(dlogits=True, dpose=True, dloss=0.7)),
    "weights": (dict(pose_multiplier=0.2, localization_weight=5.0, image_generation_weight=0.7, label_smoothing=0.1,
                     sign_invariant_pose=True), dict(dloss=1.0)),
    "scaled": (dict(attention_scale=1 / 4, n_loss_skip=2, n_layer=3, n_head=4), dict(dloss=1.0)),
    "no_skip": (dict(n_loss_skip=0, n_head=1, d_model=24), dict(dloss=1.0)),
}


@pytest.mark.parametrize("case", CASES)
def test_trace_and_every_gradient_match_torch_float64(case, rng):
    config, seeds = CASES[case]
    model, tokens, poses = setup(rng, "float64", **config)
    dl, dp = upstream(rng, model, tokens)
    kw = dict(dlogits=dl if "dlogits" in seeds else None, dpose=dp if "dpose" in seeds else None,
              dloss=seeds.get("dloss"))
    out = model.forward(tokens, poses, trace=True)
    grads = model.backward(**kw)
    t_trace, t_grads, t_pgrads = torch_trace(model, tokens, poses, **kw)
    names = trace_names(model.config.n_layer)
    assert set(t_trace) == set(names)  # the oracle, traced, covers every name
    # float64 through ~40 roundings per path: measured <= 2e-14 relative (test_transformer.py); 1e-11 leaves room
    for name in names:
        assert_close(name, out.trace[name], t_trace[name], rtol=1e-11)
    acts = [n for n in names if n not in no_grad_names(model.config.n_layer)]
    assert set(t_grads) == set(acts)  # torch's autograd reaches every traced activation but lse and the losses
    for name in acts:
        assert_close(f"d {name}", grads[name], t_grads[name], rtol=1e-11)
    for name in model.params:
        assert_close(f"d {name}", grads[name], t_pgrads[name], rtol=1e-11)
    # and through compare, its default float64 tolerance
    report = pyvf.compare(t_trace, out.trace)
    assert report.ok, str(report)
    report = pyvf.compare({**t_grads, **t_pgrads}, grads)  # walked in backward's order
    assert report.ok, str(report)
    # the functional form (pyvf bench's torch side): the same port on the published layout
    P = {k: torch.tensor(v) for k, v in model.params.items()}
    logits, raw, ce, pl, loss = transformer_forward(P, torch.tensor(tokens), torch.tensor(poses), model.config)
    assert_close("transformer_forward logits", logits.detach().numpy(), out.logits, rtol=1e-11)
    assert abs(loss.item() - out.loss) <= 1e-12 * abs(out.loss)


# ---------------------------------------------------------------------------------------
# 3. compare's inputs and tolerances (its report on a port with a planted bug: tests/test_teacher.py)


def test_compare_inputs_and_tolerances():
    rng = np.random.default_rng(0)
    ref = {"a": rng.normal(size=(4, 5)), "b": rng.normal(size=(3,)), "ids": np.arange(6)}
    # torch tensors that require grad are read through .detach(); float64 tolerance 1e-10
    mine = {"a": torch.tensor(ref["a"] * (1 + 1e-12), requires_grad=True) * 1.0,
            "b": torch.tensor(ref["b"]), "ids": torch.arange(6)}
    report = pyvf.compare(mine, ref)
    assert report.ok and [r.rtol for r in report.rows] == [1e-10, 1e-10, 0.0]
    # the less precise side sets the tolerance: float32 -> 1e-3
    r32 = pyvf.compare({"a": (ref["a"] * (1 + 1e-4)).astype(np.float32)}, {"a": ref["a"]})
    assert r32.first is None and r32.rows[0].dtype == "float32" and r32.rows[0].rtol == 1e-3
    assert pyvf.compare({"a": ref["a"] * (1 + 1e-4)}, {"a": ref["a"]}).first == "a"  # float64: over
    assert pyvf.compare({"a": ref["a"] * (1 + 1e-4)}, {"a": ref["a"]}, dtype="float32").first is None
    assert pyvf.compare({"a": ref["a"] * (1 + 1e-4)}, {"a": ref["a"]}, rtol=1e-5).first == "a"
    bf = pyvf.compare({"a": torch.tensor(ref["a"]).to(torch.bfloat16)}, {"a": ref["a"]})
    assert bf.first is None and bf.rows[0].dtype == "bfloat16" and bf.rows[0].rtol == 5e-2
    # the error measure is pyvf.rel_err, public
    x = ref["a"] + 0.01 * rng.normal(size=ref["a"].shape)
    assert pyvf.compare({"a": x}, ref).rows[0].rel == pyvf.rel_err(x, ref["a"])
    # a wrong shape, a NaN, a wrong id: each diverges, the first in ref's order is named
    bad = pyvf.compare({"a": ref["a"].T, "b": np.full(3, np.nan), "ids": np.arange(1, 7)}, ref)
    assert bad.first == "a" and [r.ok for r in bad.rows] == [False, False, False]
    assert "shape (5, 4) vs ref (4, 5)" in str(bad)
    assert pyvf.compare({"b": np.full(3, np.nan)}, ref).first == "b"


def test_compare_atol_accepts_exact_zeros_only_up_to_it():
    """A quantity that is zero in exact arithmetic is rounding on both sides: relative error noise
    over noise. atol accepts an absolute error up to it (and nothing else changes)."""
    ref = {"w": np.array([1.0, -2.0]), "b": np.array([3e-17, -1e-17])}  # b: an exact zero, rounded
    mine = {"w": ref["w"] * (1 + 1e-13), "b": np.array([-2e-17, 4e-17])}
    assert pyvf.compare(mine, ref).first == "b"  # relative error ~2: over 1e-10
    ok = pyvf.compare(mine, ref, atol=1e-10 * 2.0)  # 1e-10 of the largest neighbouring quantity
    assert ok.ok and "within atol" in ok.table() and ok.rows[1].rel > 1
    assert pyvf.compare({**mine, "w": ref["w"] * 1.001}, ref, atol=2e-10).first == "w"  # not a blanket pass
    assert pyvf.compare({"b": np.array([np.nan, 0.0])}, ref, atol=1.0).first == "b"  # never a NaN
    assert pyvf.compare({"b": np.zeros(3)}, ref, atol=1.0).first == "b"  # nor a wrong shape


def test_rel_err_at_the_ends_of_float64():
    """max |x - ref| / max |ref| where x - ref overflows float64 (it returned inf), of
    subnormals, and of nothing; a NaN in x is still reported, not scaled away."""
    assert pyvf.rel_err([1e308], [-1e308]) == 2.0
    assert pyvf.rel_err([1.5e308, 0.0], [1e308, 1e308]) == 1.0  # |0 - 1e308| / 1e308
    assert pyvf.rel_err([3e-320], [1e-320]) == pytest.approx(2.0, rel=1e-3)  # subnormals: 3 digits
    assert pyvf.rel_err(np.zeros((0, 3)), np.zeros((0, 3))) == 0.0
    assert np.isnan(pyvf.rel_err([np.nan, 1.0], [1.0, 1.0]))
    assert pyvf.rel_err([1e6, 0.0], [0.0, 0.0]) == 1e6  # an all-zero ref: the absolute error
    # an ordinary case: the power of two cancels exactly
    x, ref = np.array([1.0, 2.5, -3.0]), np.array([1.1, 2.0, -3.0])
    assert pyvf.rel_err(x, ref) == np.abs(x - ref).max() / 3.0


def test_integer_ref_must_match_exactly_whatever_the_float_tolerance():
    """Integer arrays (codes, token ids) match exactly: one wrong code of 1024 is a normwise error
    1/1023, below float32's 1e-3, against int or float port values; an explicit rtol rules."""
    codes = np.arange(1024).reshape(4, 256)
    wrong = codes.copy()
    wrong[0, 5] += 1
    assert pyvf.compare({"codes": wrong}, {"codes": codes}, dtype="float32").first == "codes"
    assert pyvf.compare({"codes": wrong.astype(np.float32)}, {"codes": codes}).first == "codes"
    assert pyvf.compare({"codes": codes.astype(np.float32)}, {"codes": codes}).ok
    assert pyvf.compare({"codes": wrong}, {"codes": codes}, rtol=1e-2).first is None


# ---------------------------------------------------------------------------------------
# refusals: one table, the exception type and the argument's name


REF = {"a": np.ones((4, 5)), "b": np.ones(3)}


@pytest.mark.parametrize("kw, error", [
    (dict(rtol=-1.0), ValueError), (dict(atol=np.inf), ValueError), (dict(atol="0"), TypeError),
    (dict(dtype="int8"), ValueError),
])
def test_compare_refusals_name_the_argument(kw, error):
    with pytest.raises(error, match=rf"\b{list(kw)[0]}\b"):
        pyvf.compare(REF, REF, **kw)
