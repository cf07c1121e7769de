"""Weight layouts (load_official / state_dict with layout="tf" | "torch") and the token-layout
helpers between pyvf's tree (R, B, N, L, ...) and a port's flat (B, T, ...)."""

import numpy as np
import pytest
import torch

import pyvf
from conftest import assert_bitwise_equal
from pyvf.models.transformer import is_dense_kernel

TINY = dict(n_embeddings=64, n_head=2, d_model=32, n_layer=2, token_image_size=4, sequence_size=5, n_loss_skip=1)


def random_model(rng, dtype="float64"):
    """Every parameter random (not the init's ones and zeros), so a wrong transpose shows."""
    model = pyvf.Transformer(pyvf.TransformerConfig(**TINY, dtype=dtype))
    model.load_official({k: rng.normal(size=v.shape) for k, v in model.params.items()})
    return model


def torch_layout(state):
    """A tf-layout state dict -> torch nn.Linear's layout, by hand: every Dense kernel
    transposed to (out, in), every Dense bias flattened to (out,)."""
    return {k: (v.T.copy() if is_dense_kernel(k) else v.reshape(-1).copy() if k.endswith("/bias") else v)
            for k, v in state.items()}


def test_torch_layout_is_nn_linear(rng):
    """A kernel given to nn.Linear in torch layout computes what pyvf's x @ W + b computes."""
    model = random_model(rng)
    sd = model.state_dict(layout="torch")
    name = "h.1/attn/c_proj"
    lin = torch.nn.Linear(32, 32, dtype=torch.float64)
    lin.load_state_dict({"weight": torch.tensor(sd[name + "/weight"]), "bias": torch.tensor(sd[name + "/bias"])})
    x = rng.normal(size=(3, 32))
    want = x @ model.params[name + "/weight"] + model.params[name + "/bias"][0]
    np.testing.assert_allclose(lin(torch.tensor(x)).detach().numpy(), want, rtol=1e-14, atol=1e-14)


def test_tf_dict_with_torch_layout_fails_or_differs(rng):
    """The published dict said to be in torch's layout: refused naming its first non-square kernel,
    the model unchanged; the square kernels alone cannot tell (they load, transposed)."""
    model = random_model(rng)
    tf = model.state_dict()
    target = pyvf.Transformer(model.config, seed=1)
    before = target.state_dict()
    with pytest.raises(ValueError, match="'pose_embedding/c_fc/weight'"):
        target.load_official(tf, layout="torch")
    for name, value in before.items():  # unchanged
        assert_bitwise_equal(name, target.params[name], value)
    sq = torch_layout(tf)
    sq["h.0/attn/c_proj/weight"] = tf["h.0/attn/c_proj/weight"]  # forgot the transpose
    target.load_official(sq, layout="torch")
    assert_bitwise_equal("square kernel", target.params["h.0/attn/c_proj/weight"], model.params["h.0/attn/c_proj/weight"].T)


def test_tensors_that_require_grad_load(rng):
    """torch tensors as a training script holds them (requiring grad, a Lightning "model." prefix)
    load; a dtype numpy cannot hold (bfloat16) is refused naming the weight, never cast."""
    model, cb = random_model(rng, dtype="float32"), random_codebook(rng, "float32")
    for m, prefix in ((model, ""), (cb, "model.")):
        for layout in m.LAYOUTS:
            sd = {prefix + k: torch.tensor(v, requires_grad=np.asarray(v).dtype.kind == "f")
                  for k, v in m.state_dict(layout=layout).items()}
            loaded = type(m)(m.config, seed=1)
            loaded.load_official(sd, layout=layout)
            assert_same_state(loaded, m)
            assert all(p.dtype == np.float32 and p.flags.c_contiguous for p in loaded.params.values())
    sd = {k: torch.tensor(v) for k, v in model.state_dict().items()}
    with pytest.raises(TypeError, match="'ln_f/beta'"):
        model.load_official({**sd, "ln_f/beta": torch.zeros(32, dtype=torch.bfloat16)})
    with pytest.raises(TypeError, match="'model.decoder.conv_out.bias'"):
        cb.load_official({"model." + k: torch.tensor(v) for k, v in cb.state_dict().items()}
                         | {"model.decoder.conv_out.bias": torch.zeros(3, dtype=torch.bfloat16)})


@pytest.mark.parametrize("shape", [(3, 2, 5, 16, 8), (2, 1, 3, 4, 2, 7)])
def test_tree_flat_round_trip(rng, shape):
    x = rng.normal(size=shape)
    R, B, N, L = shape[:4]
    flat = pyvf.tree_to_flat(x)
    assert flat.shape == (B, R * N * L, *shape[4:]) and flat.flags.c_contiguous
    back = pyvf.flat_to_tree(flat, R, N, L)
    assert_bitwise_equal("round trip", back, x)
    assert back.flags.c_contiguous and not np.shares_memory(back, flat) and not np.shares_memory(flat, x)
    for r in range(R):
        for b in range(B):
            for n in range(N):
                for l in range(L):
                    assert np.array_equal(flat[b, r * N * L + n * L + l], x[r, b, n, l])
    tokens = rng.integers(0, 9, size=(B, R * N * L))  # integers too, and flat -> tree -> flat
    assert np.array_equal(pyvf.tree_to_flat(pyvf.flat_to_tree(tokens, R, N, L)), tokens)
    with pytest.raises(ValueError):
        pyvf.flat_to_tree(flat[:, 1:], R, N, L)  # another token count


# ---------------------------------------------------------------------------------------
# the codebook: the published torch state dict (= nn.Conv2d's layout) and channels-last "tf"

CB = dict(ch=32, ch_mult=(1, 2), num_res_blocks=1, attn_resolutions=(8,), z_channels=32, embed_dim=8, n_embed=16,
          image_size=16)


def random_codebook(rng, dtype="float64"):
    cb = pyvf.Codebook(pyvf.CodebookConfig(**CB, dtype=dtype))
    state = cb.state_dict()
    def value(k, v):  # cluster sizes are never negative
        if k == "quantize.counter":
            return 3
        return np.abs(rng.normal(size=v.shape)) if k.endswith("cluster_size_hidden") else rng.normal(size=v.shape)
    cb.load_official({k: value(k, v) for k, v in state.items()})
    return cb


def assert_same_state(got, want):
    a, b = got.state_dict(), want.state_dict()
    assert list(a) == list(b)
    for name in b:
        assert_bitwise_equal(name, np.asarray(a[name]), np.asarray(b[name]))


def test_codebook_torch_layout_is_nn_conv2d_and_tf_is_channels_last(rng):
    cb = random_codebook(rng)
    torch_sd, tf_sd = cb.state_dict(), cb.state_dict(layout="tf")
    assert list(torch_sd) == list(cb.state_dict(layout="torch"))
    name = "encoder.down.0.downsample.conv.weight"
    assert torch_sd[name].shape == (32, 32, 3, 3) and tf_sd[name].shape == (3, 3, 32, 32)
    assert tf_sd["quant_conv.weight"].shape == (1, 1, 32, 8) and tf_sd["quant_conv.bias"].shape == (8,)
    assert tf_sd["quantize.embeddings"].shape == (8, 16)  # never transposed: codes are columns in both
    # torch layout = nn.Conv2d's: the module computes pyvf's conv
    conv = torch.nn.Conv2d(32, 8, 1, dtype=torch.float64)
    conv.load_state_dict({"weight": torch.tensor(torch_sd["quant_conv.weight"]),
                          "bias": torch.tensor(torch_sd["quant_conv.bias"])})
    x = rng.normal(size=(2, 32, 4, 4))
    want, _ = pyvf.nn.conv.conv2d_forward(x, cb.params["quant_conv.weight"], cb.params["quant_conv.bias"])
    np.testing.assert_allclose(conv(torch.tensor(x)).detach().numpy(), want, rtol=1e-13, atol=1e-13)
    # tf layout = channels-last: TF's conv (NHWC, HWIO) computes the same, checked by hand with einsum
    w = tf_sd["quant_conv.weight"]  # (1, 1, in, out)
    np.testing.assert_allclose(np.einsum("bhwi,io->bhwo", x.transpose(0, 2, 3, 1), w[0, 0]) + tf_sd["quant_conv.bias"],
                               want.transpose(0, 2, 3, 1), rtol=1e-13, atol=1e-13)  # (round trips: test_model_files.py)


def test_codebook_load_refusal_changes_nothing(rng):
    """A wrong counter (the last entry, after every parameter passed) raises naming it, and the
    model is left as it was: nothing is assigned before every entry passed."""
    target = pyvf.Codebook(random_codebook(rng).config, seed=5)
    before = target.state_dict()
    with pytest.raises(ValueError, match=r"quantize\.counter"):
        target.load_official({**random_codebook(rng).state_dict(), "quantize.counter": -1})
    after = target.state_dict()
    for k, v in before.items():
        assert_bitwise_equal(k, np.asarray(after[k]), np.asarray(v))


# ---------------------------------------------------------------------------------------
# a port's gradients and traces into pyvf's layouts


def test_params_from_and_to_layout(rng):
    model = random_model(rng)
    grads = {"blocks.0.ln_1": np.ones(3), **{k: rng.normal(size=v.shape) for k, v in model.params.items()}}
    as_torch = pyvf.params_to_layout(model, grads, "torch")
    assert as_torch["h.0/attn/c_attn/weight"].shape == (96, 32) and as_torch["h.0/attn/c_attn/bias"].shape == (96,)
    assert as_torch["blocks.0.ln_1"] is grads["blocks.0.ln_1"]  # activations pass unchanged
    tensors = {k: torch.tensor(v, requires_grad=True) if k != "blocks.0.ln_1" else v for k, v in as_torch.items()}
    back = pyvf.params_from_layout(model, tensors, "torch")
    for k in model.params:
        assert_bitwise_equal(k, back[k], grads[k])
    assert back["h.1/attn/c_proj/weight"].shape == (32, 32)
    assert_bitwise_equal("square kernel transposed", back["h.1/attn/c_proj/weight"], grads["h.1/attn/c_proj/weight"])
    with pytest.raises(ValueError, match=r"'h.0/mlp/c_fc/weight' has shape \(32, 128\).*layout='torch'"):
        pyvf.params_from_layout(model, {"h.0/mlp/c_fc/weight": grads["h.0/mlp/c_fc/weight"]}, "torch")
    cb = random_codebook(rng)
    g = {k: rng.normal(size=v.shape) for k, v in cb.params.items()}
    tf = pyvf.params_to_layout(cb, g, "tf")
    assert tf["encoder.conv_in.weight"].shape == (3, 3, 3, 32)
    for k, v in pyvf.params_from_layout(cb, tf, "tf").items():
        assert_bitwise_equal(k, v, g[k])


def test_trace_from_flat(rng):
    R, B, H, N, L, dh = 3, 2, 2, 3, 4, 5
    tree = rng.normal(size=(R, B, N, L, H * dh))
    q_tree = rng.normal(size=(R, B, H, N, L, dh))
    lse_tree = rng.normal(size=(R, B, H, N, L))
    flat_q = q_tree.transpose(1, 2, 0, 3, 4, 5).reshape(B, H, R * N * L, dh)  # a port's (B, H, T, dh)
    flat_lse = lse_tree.transpose(1, 2, 0, 3, 4).reshape(B, H, R * N * L)
    rows = rng.normal(size=(B, N, L, 7))
    got = pyvf.trace_from_flat({"embed.out": torch.tensor(pyvf.tree_to_flat(tree)), "blocks.0.attn.q": flat_q,
                                "blocks.0.attn.lse": flat_lse, "pose": rows, "no.grad": None}, N, L)
    assert list(got) == ["embed.out", "blocks.0.attn.q", "blocks.0.attn.lse", "pose"]
    assert_bitwise_equal("embed.out", got["embed.out"], tree)
    assert_bitwise_equal("q", got["blocks.0.attn.q"], q_tree)
    assert_bitwise_equal("lse", got["blocks.0.attn.lse"], lse_tree)
    assert_bitwise_equal("pose", got["pose"], rows)
    assert not np.shares_memory(got["pose"], rows)  # a copy: the caller's array is never aliased
    with pytest.raises(ValueError, match=r"'blocks.1.ln_1'"):
        pyvf.trace_from_flat({"blocks.1.ln_1": np.zeros((2, 35, 8))}, N, L)


