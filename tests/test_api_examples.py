"""docs/api.md's Python examples run as written (in a temporary folder), and compute and print
what their comments say."""

import importlib.util
import os
import re

import numpy as np
import pytest

ROOT = os.path.join(os.path.dirname(__file__), "..")
API_DOC = os.path.join(ROOT, "docs", "api.md")


def python_blocks():
    with open(API_DOC) as f:
        return re.findall(r"```python\n(.*?)```", f.read(), flags=re.S)


def test_api_doc_has_examples():
    assert len(python_blocks()) >= 2


def expected_paths():
    """(the path in use, the paths this process can use, the paths built), found without pyvf's own
    detection: the built ones by Python's import system, what the CPU runs from /proc/cpuinfo's flags
    (x86-64 Linux; docs/api.md: avx2 = AVX2 + FMA, avx512 = AVX-512 F/DQ/BW/VL), PYVF_ISA as set."""
    # an installed copy keeps the modules beside pyvf/__init__.py, an editable one in its build folder
    needs = {"baseline": set(), "avx2": {"avx2", "fma"},
             "avx512": {"avx2", "fma", "avx512f", "avx512dq", "avx512bw", "avx512vl"}, "neon": set()}
    built = [p for p in needs if importlib.util.find_spec(f"pyvf._core_{p}") is not None]
    with open("/proc/cpuinfo") as f:
        flags = set(next((line for line in f if line.startswith("flags")), ":").split(":")[1].split())
    runs = [p for p in built if needs[p] <= flags]
    forced = os.environ.get("PYVF_ISA", "").strip()
    allowed = runs[:runs.index(forced) + 1] if forced else runs
    return allowed[-1], allowed, built


def _check_paths(ns, out):
    assert ns["o_base"].shape == ns["q"].shape and np.allclose(ns["o_base"], ns["o_best"], rtol=1e-12, atol=1e-12)
    # show_config's lines against the version in pyproject.toml and the paths found independently
    with open(os.path.join(ROOT, "pyproject.toml")) as f:
        version = re.search(r'^version = "(.*)"', f.read(), flags=re.M).group(1)
    current, allowed, built = expected_paths()
    lines = out.splitlines()
    assert lines[0] == f"pyvf {version}", out
    assert lines[1].startswith(f"kernel path: {current} ("), out
    assert f"paths this process can use: {', '.join(allowed)}" in lines, out
    assert f"paths built: {', '.join(built)}" in lines, out
    assert (ns["pyvf"].kernel_path(), ns["pyvf"].kernel_paths()) == (current, allowed)  # the comment's pair


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
    assert ns["loss"] == pytest.approx(float(ns["out"].loss), rel=1e-5)
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
    ns = {}
    exec(compile(block, f"docs/api.md python block {i}", "exec"), ns)
    out = capsys.readouterr().out
    for key, check in CHECKS.items():
        if key in block:
            check(ns, out)
