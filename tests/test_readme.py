"""The README's Python examples run as written (in a temporary folder)."""

import os
import re

import numpy as np
import pytest

README = os.path.join(os.path.dirname(__file__), "..", "README.md")


def python_blocks():
    with open(README) as f:
        return re.findall(r"```python\n(.*?)```", f.read(), flags=re.S)


def test_readme_has_examples():
    assert len(python_blocks()) >= 2


def _check_paths(ns, out):
    assert ns["o_base"].shape == ns["q"].shape and np.allclose(ns["o_base"], ns["o_best"], rtol=1e-12, atol=1e-12)
    assert ns["pyvf"].kernel_path() in ns["pyvf"].kernel_paths() and "kernel path" in out


def _check_attention(ns, out):
    R, N, L = ns["R"], ns["N"], ns["L"]
    assert ns["mask"].shape == (R * N * L, R * N * L)
    assert ns["o"].shape == ns["q"].shape and ns["lse"].dtype == np.float64
    np.testing.assert_allclose(ns["o"], ns["o_ref"], rtol=1e-4, atol=1e-5)  # float32 against the dense oracle


def _check_transformer(ns, out):
    B, V = 2, 64
    assert ns["out"].logits.shape == (B, 5, 16, V) and ns["logits"].shape == (B, 2, 16, V)
    assert ns["est"].shape == (B, 2, 7) and set(ns["grads"]) == set(ns["model"].params)
    assert np.isfinite(ns["loss"]) and np.isfinite(ns["norm"])  # global clipping: one norm


def _check_codebook(ns, out):
    assert ns["codes"].shape == (4, 8, 8) and ns["codes"].max() < 16 and ns["recon"].shape == (4, 3, 16, 16)
    assert set(ns["grads"]) == set(ns["cb"].params)
    assert ns["index"].shape == (100,) and ns["index"].max() < 16 and ns["sq_dist"].shape == (100,)


def _check_compare(ns, out):
    assert ns["report"].first == "blocks.2.ln_2"
    assert out.splitlines()[0] == "blocks.2.ln_2"


# each example's checks, found by a line that only it has
CHECKS = {"use_kernel_path": _check_paths, "branching_attention_reference": _check_attention,
          "render_scene": _check_transformer, "decode_code": _check_codebook, "pyvf.compare": _check_compare}


def test_every_example_has_checks():
    assert [sum(key in block for key in CHECKS) for block in python_blocks()] == [1] * len(python_blocks())


@pytest.mark.parametrize("i", range(len(python_blocks())))
def test_readme_example_runs(i, tmp_path, monkeypatch, capsys):
    """Each example runs as written, and what it computes (or prints) is what its comments say."""
    monkeypatch.chdir(tmp_path)
    block = python_blocks()[i]
    ns = {}
    exec(compile(block, f"README.md python block {i}", "exec"), ns)
    out = capsys.readouterr().out
    for key, check in CHECKS.items():
        if key in block:
            check(ns, out)
