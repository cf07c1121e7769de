"""Defects found auditing pyvf/verify (compare, teacher, layout, convert_torch): each test failed
before its fix. The oracles are closed-form values, never the code under test."""

import numpy as np
import pytest
import torch

import pyvf
from pyvf.models.codebook import CodebookConfig
from pyvf.verify import convert_torch
from test_codebook_trace import SMALL
from test_teacher import port_layers, transformer_setup


# ---------------------------------------------------------------------------------------
# compare


def test_rel_err_of_an_all_zero_ref_is_the_absolute_error():
    """max |x - ref| / max |ref| falls back to max |x - ref| where ref is all zero (its divisor
    1.0): the power-of-two scaling against overflow must not leak into the result (it returned
    a number in [0.5, 1) for any nonzero x, so 1e6 against 0 passed rtol=1)."""
    assert pyvf.rel_err([4.0], [0.0]) == 4.0
    assert pyvf.rel_err([1e-20, -3e-20], [0.0, 0.0]) == 3e-20
    assert pyvf.rel_err([1e6, 0.0], [0.0, 0.0]) == 1e6
    assert pyvf.rel_err([0.0], [0.0]) == 0.0
    assert pyvf.compare({"a": np.array([1e6])}, {"a": np.zeros(1)}, rtol=1.0).first == "a"
    assert pyvf.compare({"a": np.array([1e-20])}, {"a": np.zeros(1)}).first is None  # below 1e-10


def test_rel_err_refuses_complex_and_text():
    """np.asarray(..., dtype=float64) dropped the imaginary part (a warning, then rel_err 0)."""
    with pytest.raises(TypeError, match="x must be a real numeric array"):
        pyvf.rel_err(np.array([1 + 1j]), np.array([1.0]))
    with pytest.raises(TypeError, match="ref must be a real numeric array"):
        pyvf.rel_err(np.array([1.0]), np.array(["1.0"]))


def test_integer_ref_must_match_exactly_whatever_the_float_tolerance():
    """Integer arrays (codes, token ids) must match exactly (docs/verify.md): with dtype="float32"
    (as docs/verify.md passes for a float32 run) or a float port side, one wrong code of 1024 is a
    normwise error 1/1023 < 1e-3 and passed."""
    codes = np.arange(1024).reshape(4, 256)
    wrong = codes.copy()
    wrong[0, 5] += 1
    assert pyvf.compare({"codes": wrong}, {"codes": codes}, dtype="float32").first == "codes"
    r = pyvf.compare({"codes": wrong.astype(np.float32)}, {"codes": codes})
    assert r.first == "codes" and r.rows[0].rtol == 0.0
    assert pyvf.compare({"codes": codes.astype(np.float32)}, {"codes": codes}).ok  # exact: still equal
    assert pyvf.compare({"codes": wrong}, {"codes": codes}, rtol=1e-2).first is None  # an explicit rtol rules


def test_compare_bad_dtype_names_the_argument():
    ref = {"a": np.ones(3)}
    for bad in ("foo", torch.float32):
        with pytest.raises(ValueError, match="compare: dtype must be one of"):
            pyvf.compare(ref, ref, dtype=bad)


# ---------------------------------------------------------------------------------------
# teacher forcing's report


def test_teacher_table_shows_a_nan_and_no_error_for_nothing_compared():
    """A layer whose second call returns NaN showed the first call's 1e-16 in the table (Python's
    max drops a NaN that is not first); a backward that compared nothing (embed without params:
    its inputs are the model's) showed 0.0e+00 as if checked."""
    rng = np.random.default_rng(0)
    model, port, tokens, poses, dl, dp = transformer_setup(rng, None)
    layers, _ = port_layers(port, tokens.shape[1], tokens.shape[2])
    calls = []

    def ln_f(x):  # the generation row right, the localization row NaN
        calls.append(1)
        y = port.ln_f(x)
        return y if len(calls) % 2 else y * float("nan")

    tf = pyvf.teacher_force(model, (tokens, poses), {"ln_f": ln_f, "embed": layers["embed"]},
                            upstream=dict(dlogits=dl, dpose=dp))
    assert tf.wrong == ["ln_f"]
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ") for line in tf.table().splitlines()[2:]}
    assert rows["ln_f"][1] == "nan", tf.table()
    assert rows["embed"][2] == "-", tf.table()  # nothing compared: no error to show


def test_teacher_report_lookup_names_the_missing_layer():
    rng = np.random.default_rng(0)
    model, port, tokens, poses, dl, dp = transformer_setup(rng, None)
    tf = pyvf.teacher_force(model, (tokens, poses), {"ln_f": port.ln_f})
    assert tf["ln_f"].ok
    with pytest.raises(KeyError, match="'embed' was not checked"):
        tf["embed"]
    with pytest.raises(KeyError, match="'nope' is not a layer"):
        tf["nope"]


# ---------------------------------------------------------------------------------------
# layout


def test_trace_from_flat_checks_its_sizes_first():
    """The per-head path used N, L unchecked: N=3.0 raised "'float' object cannot be interpreted
    as an integer", N=-3, L=-16 (R*N*L = 144 = T) numpy's "can only specify one unknown dimension"."""
    q = {"blocks.0.attn.q": np.zeros((2, 2, 144, 16))}
    with pytest.raises(TypeError, match="N must be an integer"):
        pyvf.trace_from_flat(q, N=3.0, L=16)
    with pytest.raises(ValueError, match="N must be >= 1"):
        pyvf.trace_from_flat(q, N=-3, L=-16)
    with pytest.raises(TypeError, match="trace must be a mapping"):
        pyvf.trace_from_flat([q], N=3, L=16)
    assert pyvf.trace_from_flat(q, N=3, L=16)["blocks.0.attn.q"].shape == (3, 2, 2, 3, 16, 16)


# ---------------------------------------------------------------------------------------
# convert_torch


def test_convert_torch_refuses_a_key_given_twice():
    """'model.x' and 'x' are one parameter: the later silently won (convert_tf raises for this)."""
    cfg = CodebookConfig(**SMALL)
    state = {k: torch.tensor(v) for k, v in pyvf.Codebook(cfg).state_dict().items()}
    name = "encoder.conv_in.bias"
    with pytest.raises(ValueError, match=r"'model.encoder.conv_in.bias' and 'encoder.conv_in.bias'"):
        convert_torch.convert({"model." + name: state[name] + 1, **state}, cfg)


def test_convert_torch_names_a_tensor_numpy_cannot_hold():
    cfg = CodebookConfig(**SMALL)
    state = {k: torch.tensor(v) for k, v in pyvf.Codebook(cfg).state_dict().items()}
    state["decoder.conv_out.weight"] = state["decoder.conv_out.weight"].to(torch.bfloat16)
    with pytest.raises(TypeError, match="'decoder.conv_out.weight'"):
        convert_torch.convert(state, cfg)


def test_teacher_force_leaves_the_users_last_forward_for_backward(rng):
    """model.backward() differentiates the model's last forward (its docstring); teacher_force runs
    the model's own forward on its inputs, and left that run in place of the user's: a backward
    after it returned the gradients of teacher forcing's batch, silently. The oracle: the same
    forward and backward without teacher_force between them, bitwise."""
    model, port, tokens, poses, dl, dp = transformer_setup(rng, None)
    layers, _ = port_layers(port, tokens.shape[1], tokens.shape[2])
    other = (tokens[::-1].copy(), poses[::-1].copy())  # the user's own batch: another one
    model.forward(*other)
    want = model.backward(dlogits=dl, dpose=dp)
    model.forward(*other)
    pyvf.teacher_force(model, (tokens, poses), layers, upstream={"dlogits": dl, "dpose": dp})
    got = model.backward(dlogits=dl, dpose=dp)
    assert want.keys() == got.keys() and all(np.array_equal(want[k], got[k]) for k in want)
