"""Issue 13's done-when: a typical bug planted in a torch port (pyvf/verify/torch_ports.py, torch
nn.Modules as a port author writes them) is found by pyvf.compare on a traced forward+backward
(the FIRST wrong quantity) and by pyvf.teacher_force (the ONLY wrong layer or layers), with at
most 15 lines of user code beside the port (the functions below marked USER CODE; their lines
are counted by test_user_code_is_at_most_15_lines). The correct port is checked too: nothing may
be flagged, so a tool that flags everything fails here as much as one that flags nothing. The
references are independent: the port is written from docs/math.md, and pyvf's side of each layer is
pyvf's own layer pair (checked against torch autograd in float64 in test_trace_compare.py)."""

import re

import numpy as np
import pytest
import torch

import pyvf
import pyvf.verify.teacher
from pyvf.verify.torch_ports import (CODEBOOK_BUGS, TRANSFORMER_BUGS, CodebookPort, TransformerPort,
                                     official_name)
from test_codebook import with_empty_patches
from test_codebook_trace import SMALL, images_for, random_codebook
from test_transformer import TINY, random_batch, random_model


# ---------------------------------------------------------------------------------------
# USER CODE: what a port author writes beside the port (torch nn.Modules) to use the tools


def port_trace(port, tokens, poses, dlogits, dpose):  # USER CODE (transformer, compare)
    """Run the port, record its modules' outputs under pyvf's trace names in pyvf's tree
    layout, and their gradients for the upstream gradients dlogits, dpose."""
    rename = {"embed": "embed.out", "embed.wte": "embed.tokens", "embed.wpe": "embed.positions",
              "embed.pose_embedding": "pose_embedding", "pose_head": "pose", "ln_f": "ln_f.generation"}
    rec, names = {}, {m: re.sub(r"^h\.(\d+)", r"blocks.\1", rename.get(n, n.replace("embed.pose_", "pose_")))
                      for n, m in port.named_modules() if n}
    hook = lambda m, args, out: rec.update({"ln_f.localization" if names[m] in rec else names[m]: out})  # noqa: E731
    handles = [m.register_forward_hook(hook) for m in names]  # (ln_f runs twice: generation row, then localization)
    rec["logits"], pose = port(torch.tensor(tokens), torch.tensor(poses))
    [h.remove() for h in handles] + [t.retain_grad() for t in rec.values()]
    ((rec["logits"] * torch.tensor(dlogits)).sum() + (pose * torch.tensor(dpose)).sum()).backward()
    grads = pyvf.trace_from_flat({n: t.grad for n, t in rec.items()}, *tokens.shape[1:])
    return pyvf.trace_from_flat(rec, *tokens.shape[1:]), {**grads, **{official_name(n): p.grad for n, p
                                                                           in port.named_parameters()}}


def port_layers(port, N, L):  # USER CODE (transformer, teacher forcing)
    layers, mask = {"embed": port.embed, "ln_f": port.ln_f, "logits": port.logits, "pose_head": port.pose_head}, port.mask(N, L)
    for j, b in enumerate(port.h):
        layers |= {f"blocks.{j}.ln_1": b.ln_1, f"blocks.{j}.attn": lambda x, b=b: b.attn(x, mask),
                   f"blocks.{j}.ln_2": b.ln_2, f"blocks.{j}.mlp": b.mlp}
    return layers, {official_name(n): p for n, p in port.named_parameters()}


def codebook_trace(port, images, drec):  # USER CODE (codebook, compare)
    rec, names = {}, {m: n for n, m in port.named_modules() if n}

    def hook(module, args, out):
        out = out[0] if isinstance(out, tuple) else out  # the quantizer returns (quantized, loss, codes)
        out = torch.nn.functional.silu(out) if names[module].endswith(("norm1", "norm2", "norm_out")) else out
        rec[names[module]] = out.retain_grad() or out  # pyvf fuses Normalize and swish: record swish(norm(x))

    handles = [m.register_forward_hook(hook) for m in names]
    rec_out = port(torch.tensor(images))[0]
    [h.remove() for h in handles]
    (rec_out * torch.tensor(drec)).sum().backward()
    return ({n: t.detach().numpy() for n, t in rec.items()},
            {**{n: t.grad.numpy() for n, t in rec.items() if t.grad is not None},
             **{n: p.grad.numpy() for n, p in port.named_parameters()}})


# ---------------------------------------------------------------------------------------
# the transformer


def transformer_setup(rng, bug=None, dtype="float64", **config):
    """A random tiny model in dtype, pyvf's torch port of it (bug planted) in the same dtype, a
    batch and random upstream gradients."""
    cfg = pyvf.TransformerConfig(**TINY, dtype=dtype, pose_multiplier=0.5, **config)
    model = random_model(cfg, rng)
    tokens, poses = random_batch(rng, 2, 3, 16, cfg.n_embeddings, dtype=dtype)
    port = TransformerPort(cfg, bug=bug).to(getattr(torch, dtype))
    sd = model.state_dict(layout="torch")  # nn.Linear's (out, in): the port's weights are pyvf's
    port.load_state_dict({n: torch.tensor(sd[official_name(n)]) for n in port.state_dict()})
    dl = rng.normal(size=(*tokens.shape, cfg.n_embeddings)).astype(dtype)
    dp = rng.normal(size=(*tokens.shape, 7)).astype(dtype)
    return model, port, tokens, poses, dl, dp


# the first wrong quantity compare names (in the port's recorded trace), the layers teacher forcing names
TRANSFORMER_EXPECT = {
    None: (None, []),
    "qkv_order": ("blocks.1.attn.c_proj", ["blocks.1.attn"]),  # c_attn's output is right, its reading is not
    "ln_eps": ("blocks.0.ln_2", ["blocks.0.ln_2"]),
    "wrong_branch": ("blocks.0.attn.c_proj", ["blocks.0.attn", "blocks.1.attn"]),  # one mask, every attention
    "gelu_tanh": ("blocks.0.mlp.gelu", ["blocks.0.mlp"]),
    "attn_scale": ("blocks.0.attn.c_proj", ["blocks.0.attn", "blocks.1.attn"]),  # the Attention class's scale
    "wpe_shift": ("embed.positions", ["embed"]),
}
assert set(TRANSFORMER_EXPECT) == {None, *TRANSFORMER_BUGS}


@pytest.mark.parametrize("bug", list(TRANSFORMER_EXPECT), ids=str)
def test_transformer_bug_found_by_compare_and_teacher_forcing(bug, rng):
    model, port, tokens, poses, dl, dp = transformer_setup(rng, bug)
    first, wrong = TRANSFORMER_EXPECT[bug]
    # compare: the traced forward names the first wrong quantity ...
    out = model.forward(tokens, poses, trace=True)
    grads = model.backward(dlogits=dl, dpose=dp)
    mine, mine_grads = port_trace(port, tokens, poses, dl, dp)
    report = pyvf.compare(mine, out.trace)
    assert report.first == first, str(report)
    assert len(report.rows) >= 2 * TINY["n_layer"] * 6, "the port's trace covers every block"
    mine_grads = pyvf.params_from_layout(model, mine_grads, "torch")  # nn.Linear's (out, in) -> pyvf's
    if bug is None:  # the correct port agrees everywhere, forward and backward, parameters included
        g = pyvf.compare(mine_grads, grads)
        assert g.first is None and len(g.rows) > len(model.params), str(g)  # module outputs pyvf does not name:
        assert "blocks.0.attn" in g.only_mine  # listed as only_mine
    else:  # ... everything after it differs (which is why only the first one says where) ...
        assert not {r.name: r for r in report.rows}["logits"].ok
        # ... and so does the backward: the gradients of the buggy layer's parameters among them
        g = pyvf.compare(mine_grads, grads)
        assert g.first is not None and any(not r.ok for r in g.rows if "/" in r.name), str(g)
    # teacher forcing: each layer on pyvf's input, forward and VJP: only the buggy layer(s)
    layers, params = port_layers(port, tokens.shape[1], tokens.shape[2])
    tf = pyvf.teacher_force(model, (tokens, poses), layers, params=params, layout="torch",
                            upstream=dict(dlogits=dl, dpose=dp))
    assert tf.wrong == wrong, str(tf)
    assert tf.unchecked == [] and len(tf.checks) == 4 * TINY["n_layer"] + 4
    assert all(c.error is None and c.backward is not None for c in tf.checks)  # both ways, every layer
    assert {r.name for c in tf.checks for r in c.backward.rows} >= set(model.params)  # every parameter
    if bug is None:  # float64 both sides: within 1e-12 of pyvf, the default tolerance 1e-10
        assert max(r.rel for c in tf.checks for comp in (c.forward, c.backward) for r in comp.rows) < 1e-12, str(tf)
    else:
        assert f"layers wrong: {', '.join(wrong)}" in str(tf)


def test_teacher_forcing_without_upstream_checks_the_forward(rng):
    model, port, tokens, poses, _, _ = transformer_setup(rng, "ln_eps")
    layers, _ = port_layers(port, tokens.shape[1], tokens.shape[2])
    tf = pyvf.teacher_force(model, (tokens, poses), layers)
    assert tf.wrong == ["blocks.0.ln_2"] and all(c.backward is None for c in tf.checks)


@pytest.mark.parametrize("kw, error, name", [  # kw(layers, params, dlogits) -> teacher_force's keywords
    (lambda l, p, dl: dict(layers={"blocks.9.attn": l["embed"]}), ValueError, "blocks.9.attn"),  # not a layer
    (lambda l, p, dl: dict(layers=l, params=p), ValueError, "layout"),  # params without their layout
    (lambda l, p, dl: dict(layers=l, params={**p, "h.0/attn/c_proj/weight": p["h.0/attn/c_attn/weight"]},
                           layout="torch"), ValueError, "h.0/attn/c_proj/weight"),  # another's shape
    (lambda l, p, dl: dict(layers=l, params={**p, "nope": p["ln_f/gamma"]}, layout="torch"), ValueError, "nope"),
    (lambda l, p, dl: dict(layers=l, upstream=dict(dlogits=dl.astype(np.float32))), TypeError, "dlogits"),
])
def test_teacher_force_refusals_name_the_argument(rng, kw, error, name):
    model, port, tokens, poses, dl, dp = transformer_setup(rng, None)
    layers, params = port_layers(port, tokens.shape[1], tokens.shape[2])
    with pytest.raises(error, match=rf"\b{re.escape(name)}\b"):
        pyvf.teacher_force(model, (tokens, poses), **kw(layers, params, dl))


# ---------------------------------------------------------------------------------------
# the codebook


def codebook_setup(rng, bug):
    cfg = pyvf.CodebookConfig(**SMALL, dtype="float64")
    cb = random_codebook(cfg, rng)
    port = CodebookPort(cfg, bug=bug).double()
    port.load_state_dict({k: torch.tensor(v) for k, v in cb.state_dict().items()})  # the published names
    x = images_for(cfg, rng)
    return cb, port, x, rng.normal(size=x.shape)


CODEBOOK_EXPECT = {  # bug: (train mode, compare's first, teacher forcing's wrong layers)
    None: (True, None, []),
    "padding": (False, "encoder.down.0.downsample.conv", ["encoder.down.0.downsample"]),
    "ema_first": (True, "quantize", ["quantize"]),  # shows in training mode only (docs/math.md §4)
}
assert set(CODEBOOK_EXPECT) == {None, *CODEBOOK_BUGS}


@pytest.mark.parametrize("bug", list(CODEBOOK_EXPECT), ids=str)
def test_codebook_bug_found_by_compare_and_teacher_forcing(bug, rng):
    cb, port, x, drec = codebook_setup(rng, bug)
    train, first, wrong = CODEBOOK_EXPECT[bug]
    state = cb.state_dict()  # the EMA buffers before a training step
    port.train(train)
    out = cb.forward(x, train=train, trace=True)
    grads = cb.backward(drec=drec)
    mine, mine_grads = codebook_trace(port, x, drec)
    report = pyvf.compare(mine, out.trace)
    assert report.first == first, str(report)
    assert len(report.rows) > 40
    # atol: the conv biases feeding a GroupNorm of one channel per group (level 0: 32 channels, 32
    # groups) have an exactly zero gradient, rounding noise on both sides (compare's docstring)
    g = pyvf.compare(mine_grads, grads, atol=1e-10 * max(np.abs(v).max() for v in grads.values()))
    if bug is None:
        assert report.ok is False and set(report.only_ref) >= {"rec_loss", "loss"}  # losses not recorded: listed
        assert g.first is None, str(g)
    else:
        assert not {r.name: r for r in report.rows}["decoder.conv_out"].ok and g.first is not None
    # teacher forcing: the port's own modules, named as published, with their own parameters
    cb.load_official(state)  # both sides' EMA buffers as before the step above
    port.load_state_dict({k: torch.tensor(v) for k, v in state.items()})
    tf = pyvf.teacher_force(cb, x, pyvf.verify.teacher.torch_modules(port, cb), params=dict(port.named_parameters()),
                            upstream=dict(drec=drec), train=train)
    assert tf.wrong == wrong, str(tf)
    assert tf.unchecked == [] and len(tf.checks) == len(pyvf.verify.teacher.layer_names(cb))
    assert {r.name for c in tf.checks for r in c.backward.rows} >= set(cb.params)  # every parameter, at its layer
    if bug is None:  # float64: within 1e-11 of pyvf, but for the exactly-zero gradients, under the layer's atol
        assert max(pyvf.verify.teacher.LayerCheck._worst(comp) for c in tf.checks for comp in (c.forward, c.backward)) \
            < 1e-11, str(tf)
        zero = [r for c in tf.checks for r in c.backward.rows if r.rel > r.rtol]
        assert {r.name.rsplit(".", 2)[-2] for r in zero} <= {"conv1", "conv2", "nin_shortcut", "k"}, zero
        assert all(r.name.endswith(".bias") and r.max_abs < 1e-13 for r in zero), zero


def test_empty_code_checked_at_the_quantize_layer(rng):
    """Under the empty code (pyvf's own, docs/math.md §4) the quantize layer reads the images too:
    the port's empty code agrees in training mode; a quantizer that ignores it is wrong there only."""
    cfg = pyvf.CodebookConfig(**SMALL, dtype="float64", empty_code=True)
    cb = random_codebook(cfg, rng)
    port = CodebookPort(cfg).double()
    port.load_state_dict({k: torch.tensor(v) for k, v in cb.state_dict().items()})
    x = with_empty_patches(images_for(cfg, rng), cfg.image_size // cfg.token_size)
    layers = pyvf.verify.teacher.torch_modules(port, cb)
    for quantize, wrong in ((layers["quantize"], []), (lambda z, x: port.quantize(z), ["quantize"])):
        tf = pyvf.teacher_force(cb, x, {**layers, "quantize": quantize}, params=dict(port.named_parameters()),
                                upstream=dict(drec=rng.normal(size=x.shape)), train=True)
        assert tf.wrong == wrong and not tf.unchecked, str(tf)


# ---------------------------------------------------------------------------------------
# more planted bugs, each found at the layer that has them (a correct float32 port passes): the
# bugs the ports' bug lists do not plant, and the defects of the tools these found


def force(model, port, tokens, poses, dl, dp, layers=None):
    mine, params = port_layers(port, *tokens.shape[1:])
    return pyvf.teacher_force(model, (tokens, poses), {**mine, **(layers or {})}, params=params, layout="torch",
                              upstream=dict(dlogits=dl, dpose=dp))


class ScaleGrad(torch.autograd.Function):
    """The identity forward, its gradient scaled by s: a backward-only bug (a hand-written VJP)."""

    @staticmethod
    def forward(ctx, x, s):
        ctx.s = s
        return x.view_as(x)

    @staticmethod
    def backward(ctx, g):
        return g * ctx.s, None


# ---------------------------------------------------------------------------------------
# tolerances


def test_correct_port_passes_in_float32(rng):
    """No false alarm: the correct port in float32 against a float32 pyvf (float64: the bug table's
    None), forward and backward, every layer; and a float32 port's trace against a float64 pyvf's
    (compare's tolerance follows the less precise side)."""
    model, port, tokens, poses, dl, dp = transformer_setup(rng, dtype="float32")
    assert force(model, port, tokens, poses, dl, dp).wrong == []
    model64 = transformer_setup(np.random.default_rng(0))[0]
    model64.load_official(model.params)
    out = model64.forward(tokens, poses.astype(np.float64), trace=True)
    mine, _ = port_trace(port, tokens, poses, dl, dp)
    report = pyvf.compare(mine, out.trace)
    assert report.first is None and len(report.rows) > 20, str(report)


@pytest.mark.parametrize("layer, dtype", [("blocks.1.mlp", "float32"), ("pose_head", "float64")])
def test_a_wrong_input_gradient_is_not_hidden_under_the_parameters_gradients(layer, dtype, rng):
    """A layer whose VJP scales its input's gradient by 1.003 (3 times float32's rtol, 3e7 times
    float64's) is wrong. The gradient of the layer's input was judged with an atol of rtol times the
    layer's largest gradient, which is a parameter's (a sum over every token, here 6-15 times
    larger and growing with the batch): an input gradient up to 15 rtol off passed (1.4% in float32,
    so this failed there; float64 keeps the promise for the same bug)."""
    model, port, tokens, poses, dl, dp = transformer_setup(rng, dtype=dtype)
    f = port_layers(port, *tokens.shape[1:])[0][layer]
    tf = force(model, port, tokens, poses, dl, dp, {layer: lambda x: f(ScaleGrad.apply(x, 1.003))})
    assert tf.wrong == [layer], str(tf)
    assert tf[layer].backward.first.startswith("d "), str(tf)


# ---------------------------------------------------------------------------------------
# planted bugs, found at their layer (float64: the exact-math check)


def transposed_c_proj(port):  # a square kernel loaded without its transpose
    w = port.h[0].attn.c_proj.weight
    w.data = w.data.T.contiguous()


def ln_eps_1e6(port):  # published: 1e-5; a relative error of about 1e-6, over float64's rtol only
    port.h[1].ln_1.eps = 1e-6


def bias_dropped(port):
    port.h[1].mlp.c_fc.bias.data.zero_()


def quaternion_negated(port):  # the pose head's quaternion in the other sign convention
    head = port.pose_head.forward
    port.pose_head.forward = lambda x: head(x) * torch.tensor([1.0] * 3 + [-1.0] * 4, dtype=x.dtype)


PLANTED = {  # planting: (compare's first wrong quantity, teacher forcing's wrong layers)
    transposed_c_proj: ("blocks.0.attn.c_proj", ["blocks.0.attn"]),
    ln_eps_1e6: ("blocks.1.ln_1", ["blocks.1.ln_1"]),
    bias_dropped: ("blocks.1.mlp.c_fc", ["blocks.1.mlp"]),
    quaternion_negated: ("pose", ["pose_head"]),
}


@pytest.mark.parametrize("plant", list(PLANTED), ids=lambda f: f.__name__)
def test_planted_transformer_bug_found_at_its_layer(plant, rng):
    model, port, tokens, poses, dl, dp = transformer_setup(rng)
    plant(port)
    first, wrong = PLANTED[plant]
    out = model.forward(tokens, poses, trace=True)
    mine, _ = port_trace(port, tokens, poses, dl, dp)
    report = pyvf.compare(mine, out.trace)
    assert report.first == first, str(report)
    assert force(model, port, tokens, poses, dl, dp).wrong == wrong


def test_label_smoothing_off_found_at_the_cross_entropy(rng):
    """pyvf trained with label_smoothing 0.1, a port's loss without it: ce_loss, not the logits."""
    model, port, tokens, poses, dl, dp = transformer_setup(rng, label_smoothing=0.1)
    out = model.forward(tokens, poses, trace=True)
    logits, _ = port(torch.tensor(tokens), torch.tensor(poses))
    S, V = model.config.n_loss_skip, model.config.n_embeddings
    for smoothing, first in ((0.1, None), (0.0, "ce_loss")):
        ce = torch.nn.functional.cross_entropy(logits[:, S:].reshape(-1, V), torch.tensor(tokens[:, S:]).reshape(-1),
                                               reduction="none", label_smoothing=smoothing)
        report = pyvf.compare({"logits": logits, "ce_loss": ce.reshape(len(tokens), -1).mean(1)}, out.trace)
        assert report.first == first and len(report.rows) == 2, str(report)


def test_groupnorm_groups_16_found_at_that_norm(rng):
    """GroupNorm(16, c) where the published one has 32 groups, in one norm of the decoder."""
    cb, port, x, drec = codebook_setup(rng, None)
    port.eval()  # no EMA step: the quantizer's codes stay pyvf's
    port.decoder.up[0].block[1].norm2.num_groups = 16
    out = cb.forward(x, trace=True)
    cb.backward(drec=drec)
    mine, _ = codebook_trace(port, x, drec)
    assert pyvf.compare(mine, out.trace).first == "decoder.up.0.block.1.norm2"
    tf = pyvf.teacher_force(cb, x, pyvf.verify.teacher.torch_modules(port, cb), params=dict(port.named_parameters()),
                            upstream=dict(drec=drec))
    assert tf.wrong == ["decoder.up.0.block.1.norm2"], str(tf)
