"""docs/api.md's Python examples run as written (in a temporary folder), and compute and print
what their comments say; the attention example at a small size (PAPER_SIZE replaced by SMALL),
since its dense reference at the paper's takes GiBs and tens of seconds."""

import os
import re

import numpy as np
import pytest

ROOT = os.path.join(os.path.dirname(__file__), "..")
PAPER_SIZE, SMALL = "R, B, H, N, L, dh = 3, 1, 12, 20, 64, 64", "R, B, H, N, L, dh = 3, 1, 2, 4, 16, 8"
API_DOC = os.path.join(ROOT, "docs", "api.md")


def python_blocks():
    with open(API_DOC) as f:
        return re.findall(r"```python\n(.*?)```", f.read(), flags=re.S)


def test_api_doc_has_examples():
    assert len(python_blocks()) >= 2


def _check_paths(ns, out):
    """Both paths compute the same; show_config's first lines name the version and the path in use."""
    assert ns["o_base"].shape == ns["q"].shape and np.allclose(ns["o_base"], ns["o_best"], rtol=1e-12, atol=1e-12)
    with open(os.path.join(ROOT, "pyproject.toml")) as f:
        version = re.search(r'^version = "(.*)"', f.read(), flags=re.M).group(1)
    pyvf = ns["pyvf"]
    lines = out.splitlines()
    assert lines[0] == f"pyvf {version}" and lines[1].startswith(f"kernel path: {pyvf.kernel_path()} ("), out
    assert pyvf.kernel_path() == pyvf.kernel_paths()[-1], "the best path this process can use"


def _check_attention(ns, out):
    R, N, L = ns["R"], ns["N"], ns["L"]
    assert ns["mask"].shape == (R * N * L, R * N * L)
    assert ns["o"].shape == ns["q"].shape and ns["lse"].dtype == np.float64
    np.testing.assert_allclose(ns["o"], ns["o_ref"], rtol=1e-4, atol=1e-5)  # float32 against the dense oracle


def _check_transformer(ns, out):
    B, V = 2, 64
    assert ns["out"].logits.shape == (B, 5, 16, V) and ns["logits"].shape == (B, 2, 16, V)
    assert ns["est"].shape == (B, 2, 7) and set(ns["grads"]) == set(ns["model"].params)
    # train_step's loss is forward's on the relative poses, and its norm (global clipping: one norm)
    # that of backward's gradients: the same parameters, forward and backward change none.
    # float32 sums in other orders: 1e-5
    assert ns["step"].loss == pytest.approx(float(ns["out"].loss), rel=1e-5)
    norm = np.sqrt(sum((g.astype(np.float64) ** 2).sum() for g in ns["grads"].values()))
    assert ns["norm"] == pytest.approx(norm, rel=1e-5)


def _check_codebook(ns, out):
    assert ns["codes"].shape == (4, 8, 8) and ns["codes"].max() < 16 and ns["recon"].shape == (4, 3, 16, 16)
    assert set(ns["grads"]) == set(ns["cb"].params)
    assert ns["index"].shape == (100,) and ns["index"].max() < 16 and ns["sq_dist"].shape == (100,)


def _check_compare(ns, out):
    """Only blocks.2.ln_2 differs, by the planted factor 1.01: relative error 0.01, absolute 0.01
    max|x|; every other quantity is the trace itself, error 0. The print shows the first lines."""
    rows = [r.split(" | ") for r in ns["report"].table().splitlines()[2:]]  # | # | name | ... | err | rel | rtol | |
    bad = [r for r in rows if r[4:6] != ["0.000e+00", "0.000e+00"]]
    x = ns["out"].trace["blocks.2.ln_2"].astype(np.float64)
    assert [r[1] for r in bad] == ["blocks.2.ln_2"] and bad[0][-1] == "FIRST |", bad
    assert bad[0][4:6] == [f"{0.01 * np.abs(x).max():.3e}", "1.000e-02"], bad
    assert all(r[-1] == "ok |" for r in rows if r is not bad[0])
    assert out == f"blocks.2.ln_2\n{ns['report'].table()[:300]}\n", out


# each example's checks, found by a line that only it has
CHECKS = {"use_kernel_path": _check_paths, "branching_attention_reference": _check_attention,
          "render_scene": _check_transformer, "decode_code": _check_codebook, "pyvf.compare": _check_compare}


def test_every_example_has_checks():
    assert [sum(key in block for key in CHECKS) for block in python_blocks()] == [1] * len(python_blocks())


@pytest.mark.parametrize("i", range(len(python_blocks())))
def test_api_example_runs(i, tmp_path, monkeypatch, capsys):
    """Each example runs as written, and what it computes (or prints) is what its comments say."""
    monkeypatch.chdir(tmp_path)
    block = python_blocks()[i]
    if "branching_attention_reference" in block:
        assert PAPER_SIZE in block
        block = block.replace(PAPER_SIZE, SMALL)
    ns = {}
    exec(compile(block, f"docs/api.md python block {i}", "exec"), ns)
    out = capsys.readouterr().out
    for key, check in CHECKS.items():
        if key in block:
            check(ns, out)
