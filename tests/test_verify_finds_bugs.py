"""Bugs planted in a port that pyvf's tools must find at the layer that has them (and a correct
port in float32 that they must pass): the planted bugs test_teacher.py and test_trace_compare.py
do not plant, and the defects of the tools these found (each such test failed before its fix)."""

import numpy as np
import pytest
import torch

import pyvf
import pyvf.verify.teacher
from pyvf.verify.torch_ports import TransformerPort, official_name, tree_mask
from test_teacher import codebook_setup, codebook_trace, port_layers, port_trace
from test_transformer import TINY, random_batch, random_model


def setup(dtype, rng, **config):
    """A random tiny model in dtype and pyvf's torch port of it, in the same dtype."""
    cfg = pyvf.TransformerConfig(**TINY, dtype=dtype, pose_multiplier=0.5, **config)
    model = random_model(cfg, rng)
    tokens, poses = random_batch(rng, 2, 3, 16, cfg.n_embeddings, dtype=dtype)
    port = TransformerPort(cfg).to(getattr(torch, dtype))
    sd = model.state_dict(layout="torch")
    port.load_state_dict({n: torch.tensor(sd[official_name(n)]) for n in port.state_dict()})
    dl = rng.normal(size=(*tokens.shape, cfg.n_embeddings)).astype(dtype)
    dp = rng.normal(size=(*tokens.shape, 7)).astype(dtype)
    return model, port, tokens, poses, dl, dp


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


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_correct_port_passes_in_its_own_dtype(dtype, rng):
    """No false alarm: the correct port in float32 against a float32 pyvf (and float64 against
    float64), forward and backward, every layer; and a float32 port's trace against a float64 pyvf's
    (compare's tolerance follows the less precise side)."""
    model, port, tokens, poses, dl, dp = setup(dtype, rng)
    assert force(model, port, tokens, poses, dl, dp).wrong == []
    model64, _, _, _, _, _ = setup("float64", np.random.default_rng(0))
    model64.load_official(model.params)
    out = model64.forward(tokens, poses.astype(np.float64), trace=True)
    mine, _ = port_trace(port, tokens, poses, dl, dp)
    report = pyvf.compare(mine, out.trace)
    assert report.first is None and len(report.rows) > 20, str(report)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("layer", ["blocks.1.mlp", "pose_head"])
def test_a_wrong_input_gradient_is_not_hidden_under_the_parameters_gradients(layer, dtype, rng):
    """A layer whose VJP scales its input's gradient by 1.003 (3 times float32's rtol, 3e7 times
    float64's) is wrong. The gradient of the layer's input was judged with an atol of rtol times the
    layer's largest gradient, which is a parameter's (a sum over every token, here 6-15 times
    larger and growing with the batch): an input gradient up to 15 rtol off passed (1.4% in float32,
    so this failed there; float64 keeps the promise for the same bug)."""
    model, port, tokens, poses, dl, dp = setup(dtype, rng)
    f = port_layers(port, *tokens.shape[1:])[0][layer]
    tf = force(model, port, tokens, poses, dl, dp, {layer: lambda x: f(ScaleGrad.apply(x, 1.003))})
    assert tf.wrong == [layer], str(tf)
    assert tf[layer].backward.first.startswith("d "), str(tf)


# ---------------------------------------------------------------------------------------
# planted bugs, found at their layer (float64: the exact-math check)


def transposed_c_proj(port):  # a square kernel loaded without its transpose
    w = port.h[0].attn.c_proj.weight
    w.data = w.data.T.contiguous()


def future_view_visible(port):  # view 0's queries also see the trunk's view 1
    def mask(N, L, device=None):
        t = torch.arange(3 * N * L, device=device)
        row, view = t // (N * L), t // L % N
        return tree_mask(N, L, None, device) | ((row[None] == 0) & (view[:, None] == 0) & (view[None] == 1))
    port.mask = mask


def ln_eps_1e6(port):  # published: 1e-5; a relative error of about 1e-6, over float64's rtol only
    port.h[1].ln_1.eps = 1e-6


def bias_dropped(port):
    port.h[1].mlp.c_fc.bias.data.zero_()


def quaternion_negated(port):  # the pose head's quaternion in the other sign convention
    head = port.pose_head.forward
    port.pose_head.forward = lambda x: head(x) * torch.tensor([1.0] * 3 + [-1.0] * 4, dtype=x.dtype)


PLANTED = {  # planting: (compare's first wrong quantity, teacher forcing's wrong layers)
    transposed_c_proj: ("blocks.0.attn.c_proj", ["blocks.0.attn"]),
    future_view_visible: ("blocks.0.attn.c_proj", ["blocks.0.attn", "blocks.1.attn"]),  # one mask, both blocks
    ln_eps_1e6: ("blocks.1.ln_1", ["blocks.1.ln_1"]),
    bias_dropped: ("blocks.1.mlp.c_fc", ["blocks.1.mlp"]),
    quaternion_negated: ("pose", ["pose_head"]),
}


@pytest.mark.parametrize("plant", list(PLANTED), ids=lambda f: f.__name__)
def test_planted_transformer_bug_found_at_its_layer(plant, rng):
    model, port, tokens, poses, dl, dp = setup("float64", rng)
    plant(port)
    first, wrong = PLANTED[plant]
    out = model.forward(tokens, poses, trace=True)
    mine, _ = port_trace(port, tokens, poses, dl, dp)
    report = pyvf.compare(mine, out.trace)
    assert report.first == first, str(report)
    assert force(model, port, tokens, poses, dl, dp).wrong == wrong


def test_label_smoothing_off_found_at_the_cross_entropy(rng):
    """pyvf trained with label_smoothing 0.1, a port's loss without it: ce_loss, not the logits."""
    model, port, tokens, poses, dl, dp = setup("float64", rng, label_smoothing=0.1)
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
