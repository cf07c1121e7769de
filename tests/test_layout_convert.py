"""Weight layouts (load_official / state_dict with layout="tf" | "torch") and the token-layout
helpers between pyvf's tree (R, B, N, L, ...) and a port's flat (B, T, ...)."""

import numpy as np
import pytest
import torch

import pyvf
from conftest import assert_bitwise_equal
from pyvf.transformer import is_dense_kernel, parameter_shapes

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


def assert_same_params(got, want):
    assert list(got.params) == list(want.params)
    for name in want.params:
        assert_bitwise_equal(name, got.params[name], want.params[name])


def test_dense_kernels_are_the_linear_weights_only():
    shapes = parameter_shapes(pyvf.TransformerConfig(**TINY))
    kernels = [n for n in shapes if is_dense_kernel(n)]
    assert "wte/weight" not in kernels and "wpe/embeddings" not in kernels
    assert all(len(shapes[n]) == 2 and n.endswith(("c_fc/weight", "c_proj/weight", "c_attn/weight")) for n in kernels)
    assert len(kernels) == 2 + 4 * TINY["n_layer"] + 2


def test_torch_layout_loads_to_the_same_params(rng):
    model = random_model(rng)
    sd = torch_layout(model.state_dict())
    assert sd["h.0/attn/c_attn/weight"].shape == (96, 32) and sd["h.0/attn/c_attn/bias"].shape == (96,)
    loaded = pyvf.Transformer(model.config, seed=1)
    loaded.load_official(sd, layout="torch")
    assert_same_params(loaded, model)
    # state_dict(layout="torch") is that same dict, and round-trips
    back = model.state_dict(layout="torch")
    assert list(back) == list(sd)
    for name in sd:
        assert_bitwise_equal(name, back[name], sd[name])
        assert back[name].flags.c_contiguous
    again = pyvf.Transformer(model.config, seed=2)
    again.load_official(back, layout="torch")
    assert_same_params(again, model)
    # the published (1, out) bias is accepted in torch layout too: unambiguous
    again.load_official({**back, "h.1/mlp/c_fc/bias": model.params["h.1/mlp/c_fc/bias"]}, layout="torch")
    assert_same_params(again, model)


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
    model = random_model(rng)
    tf = model.state_dict()
    target = pyvf.Transformer(model.config, seed=1)
    before = target.state_dict()
    with pytest.raises(ValueError) as e:
        target.load_official(tf, layout="torch")
    msg = str(e.value)
    for j in range(TINY["n_layer"]):  # every non-square kernel named, the square c_proj not
        for k, want in [("attn/c_attn", "(96, 32)"), ("mlp/c_fc", "(128, 32)"), ("mlp/c_proj", "(32, 128)")]:
            assert f"'h.{j}/{k}/weight' has shape {tuple(tf[f'h.{j}/{k}/weight'].shape)}, expected {want}" in msg
        assert f"h.{j}/attn/c_proj/weight" not in msg
    assert "pose_embedding/c_fc/weight" in msg and "layout='torch'" in msg
    for name, value in before.items():  # unchanged
        assert_bitwise_equal(name, target.params[name], value)
    # the square kernels alone: they load, transposed, so the params differ from the model's
    sq = torch_layout(tf)
    for j in range(TINY["n_layer"]):
        sq[f"h.{j}/attn/c_proj/weight"] = tf[f"h.{j}/attn/c_proj/weight"]  # forgot the transpose
    target.load_official(sq, layout="torch")
    for j in range(TINY["n_layer"]):
        name = f"h.{j}/attn/c_proj/weight"
        assert not np.array_equal(target.params[name], model.params[name])
        assert_bitwise_equal(name, target.params[name], model.params[name].T)


def test_tensors_that_require_grad_load(rng):
    model = random_model(rng, dtype="float32")
    for layout in ("tf", "torch"):
        sd = {k: torch.tensor(v, requires_grad=True) for k, v in model.state_dict(layout=layout).items()}
        loaded = pyvf.Transformer(model.config, seed=1)
        loaded.load_official(sd, layout=layout)
        assert_same_params(loaded, model)
        assert all(p.dtype == np.float32 and p.flags.c_contiguous for p in loaded.params.values())
    # a wrong dtype is still refused, tensor or not, and bfloat16 (numpy has none) is named
    sd = {k: torch.tensor(v) for k, v in model.state_dict().items()}
    sd["ln_f/gamma"] = torch.ones(32, dtype=torch.int32)
    sd["ln_f/beta"] = torch.zeros(32, dtype=torch.bfloat16)
    with pytest.raises(TypeError, match=r"'ln_f/gamma' has dtype int32.*'ln_f/beta' \(Tensor\) cannot become"):
        loaded.load_official(sd)
    # other array-likes are not cast
    with pytest.raises(TypeError, match="'ln_f/gamma' is a list, not a numpy array"):
        loaded.load_official({**model.state_dict(), "ln_f/gamma": [1.0] * 32})


def test_bad_layout_raises():
    model = pyvf.Transformer(pyvf.TransformerConfig(**TINY))
    for bad in ("TF", "jax", None, 0):
        with pytest.raises(ValueError, match="layout"):
            model.load_official(model.state_dict(), layout=bad)
        with pytest.raises(ValueError, match="layout"):
            model.state_dict(layout=bad)


@pytest.mark.parametrize("shape", [(1, 2, 3, 4), (3, 2, 5, 16, 8), (2, 1, 3, 4, 2, 7)])
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


def test_tree_flat_bad_shapes():
    with pytest.raises(ValueError, match=r"x must have shape \(R, B, N, L, \.\.\.\)"):
        pyvf.tree_to_flat(np.zeros((2, 3, 4)))
    with pytest.raises(TypeError, match="x must be a numpy.ndarray"):
        pyvf.tree_to_flat([[[[1.0]]]])
    with pytest.raises(ValueError, match=r"x has T = 10 .* R\*N\*L = 1\*3\*4 = 12"):
        pyvf.flat_to_tree(np.zeros((2, 10, 5)), 1, 3, 4)
    with pytest.raises(ValueError, match=r"x must have shape \(B, T, \.\.\.\)"):
        pyvf.flat_to_tree(np.zeros(12), 1, 3, 4)
    with pytest.raises(ValueError, match="N must be >= 1"):
        pyvf.flat_to_tree(np.zeros((2, 0)), 1, 0, 4)
    with pytest.raises(TypeError, match="L must be an integer"):
        pyvf.flat_to_tree(np.zeros((2, 12)), 1, 3, 4.0)
