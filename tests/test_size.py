"""The brake on growth (docs/contributing.md): pyvf's source (its .py files and csrc/) and its tests
stay within their line budgets, counted as `wc -l` counts them (docstrings and comments included).

Raising a budget is a decision in the diff: the issue "a minimal reference again" set them, half
the code with every capability kept.
"""

import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BUDGETS = {"source": 12_000, "tests": 10_000}


def lines(folder, suffixes):
    """The newline count of the files under ROOT/folder whose names end with one of suffixes."""
    total = 0
    for dirpath, dirs, files in os.walk(os.path.join(ROOT, folder)):
        dirs[:] = [d for d in dirs if d != "__pycache__"]
        for name in files:
            if name.endswith(suffixes):
                with open(os.path.join(dirpath, name), "rb") as f:
                    total += f.read().count(b"\n")
    return total


def counts():
    return {"source": lines("pyvf", (".py",)) + lines("csrc", (".cpp", ".h")), "tests": lines("tests", (".py",))}


@pytest.mark.parametrize("part", sorted(BUDGETS))
def test_within_the_line_budget(part):
    n = counts()[part]
    assert n <= BUDGETS[part], (f"{part}: {n} lines, over its budget of {BUDGETS[part]}: delete machinery, or "
                                "raise the budget in tests/test_size.py as a decision of the change")


def test_the_count_is_wc_l(tmp_path, monkeypatch):
    """The count is wc -l's: newlines, a last line without one not counted; caches not counted."""
    monkeypatch.setattr(sys.modules[__name__], "ROOT", str(tmp_path))
    (tmp_path / "pyvf" / "__pycache__").mkdir(parents=True)
    (tmp_path / "pyvf" / "a.py").write_text("x = 1\n\ny = 2")  # 2 newlines
    (tmp_path / "pyvf" / "__pycache__" / "b.py").write_text("\n" * 50)
    (tmp_path / "pyvf" / "c.txt").write_text("\n" * 50)
    assert lines("pyvf", (".py",)) == 2
