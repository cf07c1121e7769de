"""Hard and wrong input to the codebook's public entry points (Codebook.encode / forward /
backward, codebook_train_step) and to its image layers (pyvf.nn.conv): a failed training step
leaves the model and the optimiser as they were, a perceptual module's gradient is never
dropped and its outputs are checked, errors name the public argument (or the model's layer)."""

import warnings

import numpy as np
import pytest

from conftest import assert_close
from pyvf.models.codebook import Codebook, CodebookConfig
from pyvf.models.transformer import Transformer, TransformerConfig
from pyvf.nn import conv
from pyvf.train.optim import Adam, AdamW
from pyvf.train.step import codebook_train_step, train_step

# the smallest codebook: one level, 32 channels (the GroupNorm groups), 2x2 images, no attention
TINY = dict(ch=32, ch_mult=(1,), num_res_blocks=1, attn_resolutions=(), z_channels=4, embed_dim=3, n_embed=5,
            image_size=2)


def images(rng, B=2, dtype="float32"):
    return rng.uniform(-1, 1, (B, 3, 2, 2)).astype(dtype)


def same_state(a, b):
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def optimiser_state(opt):
    s = opt.state_dict()
    return {"step": np.array(s["step"]), **{"m." + k: v for k, v in s["exp_avg"].items()},
            **{"v." + k: v for k, v in s["exp_avg_sq"].items()}}


class StatefulDistance:
    """A perceptual term that keeps what its backward needs on itself and returns cache None, as
    pyvf's own models keep theirs (Codebook._cache): per image, the mean square of x_hat - x."""

    def __init__(self, dtype=np.float64):
        self.dtype = dtype
        self.d = None

    def forward(self, x, x_hat):
        self.d = x_hat - x
        return (self.d ** 2).mean(axis=(1, 2, 3)), None

    def backward(self, dloss, cache):
        # forward was loss_b = mean(d_b^2), so dloss_b / dx_hat_b = 2 d_b / n
        return (2 * self.d * dloss[:, None, None, None] / self.d[0].size).astype(self.dtype)


class Rigged:
    """A perceptual term whose forward and backward return what it is given (a broken plug-in)."""

    def __init__(self, loss=None, dx_hat=None):
        self.loss, self.dx_hat = loss, dx_hat

    def forward(self, x, x_hat):
        return (np.zeros(x.shape[0], x.dtype) if self.loss is None else self.loss), "cache"

    def backward(self, dloss, cache):
        return self.dx_hat


# ---------------------------------------------------------------------------------------
# codebook_train_step: a step that raises changes nothing


def test_failed_codebook_step_leaves_the_ema_buffers_and_the_optimiser(rng):
    """The optimiser refuses an update that overflows float32 (lr 1e39): the step raises, and the
    EMA buffers, which the training forward had already moved, must be as before the call (a
    retry would otherwise move them twice)."""
    cb = Codebook(CodebookConfig(**TINY), seed=3)
    opt = Adam(cb.params, 1e39)
    model0, opt0 = cb.state_dict(), optimiser_state(opt)
    with pytest.raises(ValueError, match="overflows"):
        codebook_train_step(cb, opt, images(rng))
    assert same_state(cb.state_dict(), model0), "the model (parameters or EMA buffers) changed"
    assert same_state(optimiser_state(opt), opt0), "the optimiser changed"


def test_failed_codebook_backward_leaves_the_ema_buffers(rng):
    """The backward raises (the perceptual module's gradient is NaN): nothing changed."""
    bad = np.full((2, 3, 2, 2), np.nan, np.float32)
    cb = Codebook(CodebookConfig(**TINY, perceptual_weight=1.0), seed=3, perceptual=Rigged(dx_hat=bad))
    opt = Adam(cb.params, 1e-3)
    model0, opt0 = cb.state_dict(), optimiser_state(opt)
    with pytest.raises(ValueError, match="perceptual"):
        codebook_train_step(cb, opt, images(rng))
    assert same_state(cb.state_dict(), model0)
    assert same_state(optimiser_state(opt), opt0)


@pytest.mark.parametrize("kw, kind, match", [
    (dict(max_grad_norm=-1.0), ValueError, "^max_grad_norm "),  # was "max_norm must be ...", clip_grad_norm's name
    (dict(max_grad_norm="1"), TypeError, "^max_grad_norm "),
    (dict(max_grad_norm=1.0, clip_mode="per-tensor"), ValueError, "^clip_mode "),  # was "mode must be ..."
    (dict(clip_mode="per-tensor"), ValueError, "^clip_mode "),  # was ignored without clipping
    (dict(relative="no"), TypeError, "^relative "),  # was truthy: the poses made relative
    (dict(relative=None), TypeError, "^relative "),  # was falsy: the absolute poses used
])
def test_train_step_names_its_own_arguments(kw, kind, match, rng):
    """train_step's settings are checked under their own names, before the step runs."""
    m = Transformer(TransformerConfig(n_embeddings=6, n_head=2, d_model=4, n_layer=1, token_image_size=1,
                                      sequence_size=3, n_loss_skip=1), seed=3)
    opt = AdamW(m.params, 1e-3)
    tokens = rng.integers(0, 6, (2, 3, 1))
    q = rng.standard_normal((2, 3, 4))
    poses = np.concatenate([rng.standard_normal((2, 3, 3)), q / np.linalg.norm(q, axis=-1, keepdims=True)],
                           axis=-1).astype(np.float32)
    params0, opt0 = {k: v.copy() for k, v in m.params.items()}, optimiser_state(opt)
    with pytest.raises(kind, match=match):
        train_step(m, opt, tokens, poses, **kw)
    assert same_state(m.params, params0) and same_state(optimiser_state(opt), opt0)


# ---------------------------------------------------------------------------------------
# the perceptual term


def test_perceptual_gradient_of_a_module_whose_cache_is_none(rng):
    """backward() called the perceptual module only when its cache was not None: a module that
    keeps its state on itself had its term's gradient silently dropped. Oracle, in closed form:
    decoder.conv_out.bias[o] adds to every pixel of channel o of the reconstruction, so its
    gradient is the sum over (b, y, x) of d loss / d rec = sign(d) / numel + w * 2 d / (n * B),
    d = rec - x, n = 3 * S * S the values per image, w = perceptual_weight."""
    w = 5.0
    cb = Codebook(CodebookConfig(**TINY, perceptual_weight=w, dtype="float64"), seed=3,
                  perceptual=StatefulDistance())
    x = images(rng, dtype="float64")
    d = cb.forward(x).reconstruction - x
    B, n = d.shape[0], d[0].size
    want = (np.sign(d) / d.size + w * 2 * d / (n * B)).sum(axis=(0, 2, 3))
    # float64, sums of 8 terms of size <= 1: rounding ~1e-15; without the perceptual term the
    # difference is w * 2 * mean(d) per channel, of order 1
    assert_close("decoder.conv_out.bias", cb.backward()["decoder.conv_out.bias"], want, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("loss, match", [
    (np.full(2, np.nan, np.float32), "perceptual.*NaN or inf"),
    (np.ones(5, np.float32), r"perceptual.*shape \(2,\)"),  # averaged silently over 5 "images"
    (np.float32(1.0), "perceptual.*numpy"),  # a scalar, not one loss per image
    ([1.0, 2.0], "perceptual.*numpy"),
])
def test_perceptual_forward_output_is_checked(loss, match, rng):
    """perceptual.forward must return a finite (B,) float array; a NaN gave a NaN loss, a wrong
    length a silently averaged one. A training forward that raises leaves the EMA buffers."""
    cb = Codebook(CodebookConfig(**TINY, perceptual_weight=1.0), seed=3, perceptual=Rigged(loss=loss))
    before = cb.quantizer.state_dict()
    with pytest.raises((TypeError, ValueError), match=match):
        cb.forward(images(rng), train=True)
    assert same_state(cb.quantizer.state_dict(), before)


@pytest.mark.parametrize("dx_hat, kind, match", [
    (np.zeros((2, 3, 2, 2)), TypeError, "perceptual.*float64.*float32"),  # was blamed on an internal dy
    (np.ones((3, 2, 2), np.float32), ValueError, r"perceptual.*shape \(2, 3, 2, 2\)"),  # broadcast silently
    (np.float32(1.0), TypeError, "perceptual.*numpy"),
    (np.full((2, 3, 2, 2), np.inf, np.float32), ValueError, "perceptual.*NaN or inf"),
    (None, TypeError, "perceptual.*numpy"),
])
def test_perceptual_backward_output_is_checked(dx_hat, kind, match, rng):
    cb = Codebook(CodebookConfig(**TINY, perceptual_weight=1.0), seed=3, perceptual=Rigged(dx_hat=dx_hat))
    cb.forward(images(rng))
    with pytest.raises(kind, match=match):
        cb.backward()


# ---------------------------------------------------------------------------------------
# Codebook.backward's seeds, encode's batch


def test_backward_dloss_too_large_for_the_dtype_names_dloss(rng):
    """dloss = 1e300 on a float32 model: the seed overflows float32. It raised "dy contains NaN
    or inf" (an internal name), after an overflow RuntimeWarning from the cast."""
    cb = Codebook(CodebookConfig(**TINY), seed=3)
    cb.forward(images(rng))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match="^dloss"):
            cb.backward(dloss=1e300)
        # each seed finite, their sum not: 3e38 * sign / 24 + 3.4e38 > float32's largest where the sign is +
        with pytest.raises(ValueError, match="^drec.*dloss"):
            cb.backward(drec=np.full((2, 3, 2, 2), 3.4e38, np.float32), dloss=3e38)
    # the check refuses only an overflow: the gradient is linear in dloss, and a power of two
    # scales every rounding exactly, so dloss = 4 gives 4 times dloss = 1's gradient, bitwise
    g1, g4 = cb.backward(), cb.backward(dloss=4.0)
    for k in g1:
        np.testing.assert_array_equal(g4[k], 4 * g1[k])


def test_encode_of_an_empty_batch_says_why(rng):
    """(0, 3, 2, 2) was refused as "images must have shape (B, 3, 2, 2), got (0, 3, 2, 2)",
    which it matches: the message must say the batch is empty."""
    cb = Codebook(CodebookConfig(**TINY), seed=3)
    with pytest.raises(ValueError, match="^images.*empty"):
        cb.encode(np.zeros((0, 3, 2, 2), np.float32))


# ---------------------------------------------------------------------------------------
# a wrong parameter (assigned to Codebook.params by hand) is named by its layer


@pytest.mark.parametrize("how", ["float64", "nan", "shape"])
def test_wrong_parameter_names_its_layer(how, rng):
    """forward raised "w contains NaN or inf" / "w is float64 but x is float32": conv2d's own
    argument names, not the model's parameter."""
    cb = Codebook(CodebookConfig(**TINY), seed=3)
    name = "encoder.mid.block_1.conv1.weight"
    p = cb.params[name]
    if how == "float64":
        cb.params[name] = p.astype(np.float64)
    elif how == "nan":
        cb.params[name] = p.copy()
        cb.params[name].flat[7] = np.nan
    else:
        cb.params[name] = p[:, :16].copy()
    with pytest.raises((TypeError, ValueError), match="encoder.mid.block_1.conv1"):
        cb.forward(images(rng))
    with pytest.raises((TypeError, ValueError), match="encoder.mid.block_1.conv1"):
        cb.encode(images(rng))


# ---------------------------------------------------------------------------------------
# pyvf.nn.conv: attnblock_forward names its own arguments


def _attn_args(rng, C=32):
    args = {"norm_gamma": np.ones(C, np.float32), "norm_beta": np.zeros(C, np.float32)}
    for p in ("q", "k", "v", "o"):
        args["w" + p] = (rng.standard_normal((C, C, 1, 1)) * 0.2).astype(np.float32)
        args["b" + p] = rng.standard_normal(C).astype(np.float32)
    return args


@pytest.mark.parametrize("name", ["norm_gamma", "norm_beta", "wq", "bq", "wk", "bk", "wv", "bv", "wo", "bo"])
@pytest.mark.parametrize("how", ["float64", "list", "nan", "shape"])
def test_attnblock_forward_names_the_wrong_argument(name, how, rng):
    """The children (groupnorm, conv2d) named their own arguments: "w is float64 but x is
    float32" for wk, "b must have shape (32,)" for bo, "gamma contains NaN" for norm_gamma."""
    x = rng.standard_normal((1, 32, 2, 2)).astype(np.float32)
    args = _attn_args(rng)
    a = args[name]
    if how == "float64":
        bad, kind = a.astype(np.float64), TypeError
    elif how == "list":
        bad, kind = a.tolist(), TypeError
    elif how == "nan":
        bad, kind = a.copy(), ValueError
        bad.flat[0] = np.nan
    else:
        bad, kind = a[:16].copy(), ValueError
    args[name] = bad
    with pytest.raises(kind, match=rf"^{name} "):
        conv.attnblock_forward(x, **args)


@pytest.mark.parametrize("layer", ["conv2d", "groupnorm", "groupnorm_swish", "swish", "upsample", "attnblock"])
def test_a_list_upstream_gradient_is_a_type_error(layer, rng):
    """As pyvf.nn.layers' backwards (tests/test_nn_inputs.py) and _checks.float_array: not an
    array at all is a TypeError naming the gradient (dy; groupnorm_swish_backward's dz); it was a
    ValueError about the shape."""
    x = rng.standard_normal((1, 32, 2, 2)).astype(np.float32)
    g, b = np.ones(32, np.float32), np.zeros(32, np.float32)
    fwd, bwd = {
        "conv2d": (lambda: conv.conv2d_forward(x, np.ones((4, 32, 1, 1), np.float32), np.zeros(4, np.float32)),
                   conv.conv2d_backward),
        "groupnorm": (lambda: conv.groupnorm_forward(x, g, b), conv.groupnorm_backward),
        "groupnorm_swish": (lambda: conv.groupnorm_swish_forward(x, g, b), conv.groupnorm_swish_backward),
        "swish": (lambda: conv.swish_forward(x), conv.swish_backward),
        "upsample": (lambda: conv.upsample_nearest2x_forward(x), conv.upsample_nearest2x_backward),
        "attnblock": (lambda: conv.attnblock_forward(x, **_attn_args(rng)), conv.attnblock_backward),
    }[layer]
    y, cache = fwd()
    name = "dz" if layer == "groupnorm_swish" else "dy"  # the backward's own argument
    with pytest.raises(TypeError, match=f"^{name} must be a numpy.ndarray"):
        bwd(np.ones(y.shape, np.float32).tolist(), cache)


@pytest.mark.parametrize("layer", ["groupnorm", "groupnorm_swish", "attnblock"])
def test_groupnorm_eps_that_rounds_to_zero_names_eps(layer, rng):
    """eps = 1e-46 is positive but 0 in float32 (the kernel adds it in x's dtype): a constant group
    (var 0) then divided by 0, and the error said "y is not finite: it overflowed float32 (inputs
    too large for the dtype)" of inputs all equal to 3. float64 holds 1e-46: y = beta there,
    exactly (xhat = 0), the closed form for a constant group."""
    x = np.full((1, 32, 2, 2), 3.0, np.float32)
    g, b = np.ones(32, np.float32), np.arange(32, dtype=np.float32)
    call = {"groupnorm": lambda x, g, b, eps: conv.groupnorm_forward(x, g, b, eps=eps),
            "groupnorm_swish": lambda x, g, b, eps: conv.groupnorm_swish_forward(x, g, b, eps=eps),
            "attnblock": lambda x, g, b, eps: conv.attnblock_forward(x, **dict(_attn_args(rng), norm_gamma=g,
                                                                                norm_beta=b), eps=eps)}[layer]
    with pytest.raises(ValueError, match="^eps .*float32"):
        call(x, g, b, 1e-46)
    if layer == "groupnorm":
        y, _ = call(x.astype(np.float64), g.astype(np.float64), b.astype(np.float64), 1e-46)
        np.testing.assert_array_equal(y, np.broadcast_to(b.astype(np.float64)[:, None, None], (1, 32, 2, 2)))
