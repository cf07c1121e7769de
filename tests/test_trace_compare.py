"""Traces of the transformer and pyvf.compare: named activations and their gradients against torch
autograd in float64 (the oracle pyvf/verify/torch_transformer.py, its activations recorded by
wrapping its layer functions, never rewriting them), and compare naming the first wrong quantity
of a port's traces."""

import contextlib

import numpy as np
import pytest
import torch
from torch.overrides import TorchFunctionMode

import pyvf
from conftest import assert_bitwise_equal, assert_close
from pyvf.models.transformer import trace_names
from pyvf.verify import torch_transformer as tt
from test_transformer import TINY, random_batch, random_model

NO_GRAD = {"ce_loss", "pose_loss", "loss"}  # traced, but the seed of backward, not differentiated


def no_grad_names(n_layer):
    return NO_GRAD | {f"blocks.{j}.attn.lse" for j in range(n_layer)}


# ---------------------------------------------------------------------------------------
# the torch oracle, traced: its activations under pyvf's names, in pyvf's tree layout


def module_to_trace(name):
    """Official module name -> trace prefix: 'h.1/attn/c_attn' -> 'blocks.1.attn.c_attn'."""
    name = name.replace("quaternion_pose_representation/pose_classifier", "pose_head")
    if name.startswith("h."):
        j, rest = name[2:].split("/", 1)
        name = f"blocks.{j}/{rest}"
    return name.replace("/", ".")


@contextlib.contextmanager
def traced_oracle(P, tokens, cfg, rec):
    """While active, torch_transformer.forward records into rec (name -> torch tensor, in the
    oracle's flat layout (B, T, ...), T in [row][view][token])."""
    linear0, layer_norm0 = tt.linear, tt.layer_norm

    def linear(x, P_, name):
        y = linear0(x, P_, name)
        key = module_to_trace(name)
        if name.endswith("attn/c_attn"):  # the oracle splits what this returns as [v | q | k]
            rec[key] = y
            rec[key.replace("c_attn", "vqk")] = y  # not a trace name: q, k, v are cut from it
            return y
        if name == "pose_embedding/c_fc":
            rec["pose_embedding.input"] = x
        if name.endswith("attn/c_proj"):
            rec[key.replace("c_proj", "out")] = x  # the heads merged: (B, T, d)
        elif name.endswith("c_proj"):
            rec[key.replace("c_proj", "gelu")] = x
        rec["pose" if key == "pose_head.c_proj" else key] = y
        return y

    def layer_norm(x, P_, name):
        y = layer_norm0(x, P_, name)
        if name == "ln_f":  # called on the generation row, then the localization row
            rec["ln_f.localization" if "ln_f.generation" in rec else "ln_f.generation"] = y
            return y
        key = module_to_trace(name)  # blocks.j.ln_1 or blocks.j.ln_2
        j = int(key.split(".")[1])
        if key.endswith("ln_1"):
            rec["embed.out" if j == 0 else f"blocks.{j - 1}.out"] = x
        else:
            rec[f"blocks.{j}.resid_1"] = x
        rec[key] = y
        return y

    class Lookups(TorchFunctionMode):
        """The lookups the oracle writes inline: wte[tokens], wpe[:L], and the last block's output
        (the only reshape to (B, R, N, L, d))."""

        def __torch_function__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            if func is torch.Tensor.__getitem__ and args[0] is P["wte/weight"] and args[1] is tokens:
                rec["embed.tokens"] = out
            elif func is torch.Tensor.__getitem__ and args[0] is P["wpe/embeddings"]:
                rec["embed.positions"] = out
            elif func is torch.Tensor.reshape and len(args) == 6:
                rec[f"blocks.{cfg.n_layer - 1}.out"] = args[0]
            elif func in (torch.Tensor.matmul, torch.Tensor.__matmul__) and args[0] is rec.get("ln_f.generation"):
                rec["logits"] = out
            return out

    tt.linear, tt.layer_norm = linear, layer_norm
    try:
        with Lookups():
            yield
    finally:
        tt.linear, tt.layer_norm = linear0, layer_norm0


def to_tree(name, t, cfg, N, L):
    """An oracle tensor (flat layout) -> pyvf's layout for that name, as float64 numpy."""
    t = t.detach()
    B, H, d = t.shape[0], cfg.n_head, cfg.d_model
    if name.startswith("blocks.") or name == "embed.out":
        if name.endswith(("attn.q", "attn.k", "attn.v", "attn.out")):  # (B, T, d) -> (R, B, H, N, L, dh)
            t = t.reshape(B, 3, N, L, H, d // H).permute(1, 0, 4, 2, 3, 5)
        elif name.endswith("attn.lse"):  # (B, H, T) -> (R, B, H, N, L)
            t = t.reshape(B, H, 3, N, L).permute(2, 0, 1, 3, 4)
        else:  # (B, T, w) -> (R, B, N, L, w)
            t = t.reshape(B, 3, N, L, -1).permute(1, 0, 2, 3, 4)
    return t.numpy().copy()


def torch_trace(model, tokens, poses, dlogits=None, dpose=None, dloss=None):
    """Run the oracle in float64 -> (trace, grads, param grads): name -> numpy in pyvf's layout.
    Backward of dloss * loss + sum(logits * dlogits) + sum(raw * dpose)."""
    cfg = model.config
    B, N, L = tokens.shape
    d, H = cfg.d_model, cfg.n_head
    P = {k: torch.tensor(v, requires_grad=True) for k, v in model.params.items()}
    t_tokens, rec = torch.tensor(tokens), {}
    with traced_oracle(P, t_tokens, cfg, rec):
        # poses require grad so that the pose MLP's input (xyz scaled) has a gradient to compare
        logits, raw, ce, pl, loss = tt.forward(P, t_tokens, torch.tensor(poses, requires_grad=True), cfg)
    for t in rec.values():
        t.retain_grad()
    vqk = {j: rec.pop(f"blocks.{j}.attn.vqk") for j in range(cfg.n_layer)}
    for j in range(cfg.n_layer):  # q, k, v are column blocks of what the oracle splits: [v | q | k]
        rec[f"blocks.{j}.attn.v"], rec[f"blocks.{j}.attn.q"], rec[f"blocks.{j}.attn.k"] = vqk[j].split(d, dim=-1)
    total = 0.0 * loss
    if dloss is not None:
        total = total + dloss * loss
    if dlogits is not None:
        total = total + (logits * torch.tensor(dlogits)).sum()
    if dpose is not None:
        total = total + (raw * torch.tensor(dpose)).sum()
    total.backward()
    grads = {}
    for name, t in rec.items():
        if name.endswith(("attn.q", "attn.k", "attn.v")):
            j = name.split(".")[1]
            dv, dq, dk = vqk[int(j)].grad.split(d, dim=-1)
            grads[name] = to_tree(name, {"q": dq, "k": dk, "v": dv}[name[-1]], cfg, N, L)
        else:
            grads[name] = to_tree(name, t.grad, cfg, N, L)
    trace = {name: to_tree(name, t, cfg, N, L) for name, t in rec.items()}
    mask = tt.tree_mask(3, N, L)
    with torch.no_grad():
        for j in range(cfg.n_layer):  # lse of the attended logits, from the oracle's own q and k
            q, k = (rec[f"blocks.{j}.attn.{c}"].reshape(B, 3 * N * L, H, d // H).transpose(1, 2) for c in "qk")
            s = (cfg.attention_scale * (q @ k.transpose(-1, -2))).masked_fill(~mask, float("-inf"))
            trace[f"blocks.{j}.attn.lse"] = to_tree(f"blocks.{j}.attn.lse", torch.logsumexp(s, -1), cfg, N, L)
    trace.update(ce_loss=ce.detach().numpy(), pose_loss=pl.detach().numpy(), loss=loss.item())
    return trace, grads, {k: t.grad.numpy() for k, t in P.items()}


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
    "weights": (dict(pose_multiplier=0.2, localization_weight=5.0, image_generation_weight=0.7, label_smoothing=0.1),
                dict(dloss=1.0)),
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
