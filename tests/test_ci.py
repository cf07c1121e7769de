"""Every third-party module that pyvf/, tests/ or tools/ imports is declared."""

import ast
import importlib.metadata
import os
import re
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _declared():
    """The distributions pyproject.toml (dependencies and every extra) and tests/requirements.txt
    name, normalised (lower case, '-' for '_' and '.')."""
    with open(os.path.join(ROOT, "pyproject.toml")) as f:
        project = f.read().split("[project.scripts]")[0]
    with open(os.path.join(ROOT, "tests", "requirements.txt")) as f:
        reqs = [line for line in f if not line.startswith("#")]
    names = re.findall(r'"([A-Za-z0-9_.-]+)\s*[<>=!~\[;"]', project) + [re.split(r"[<>=!~\[; ]", r.strip())[0] for r in reqs]
    return {re.sub(r"[-_.]+", "-", n).lower() for n in names if n}


def _imports(folder):
    """(top-level module, file) of every absolute import in the .py files under folder."""
    for dirpath, _, files in os.walk(os.path.join(ROOT, folder)):
        for name in files:
            if name.endswith(".py"):
                path = os.path.join(dirpath, name)
                with open(path) as f:
                    for node in ast.walk(ast.parse(f.read(), path)):
                        if isinstance(node, ast.Import):
                            yield from ((a.name.split(".")[0], path) for a in node.names)
                        elif isinstance(node, ast.ImportFrom) and node.level == 0:
                            yield node.module.split(".")[0], path


def test_every_third_party_import_is_declared():
    declared = _declared()
    distributions = importlib.metadata.packages_distributions()  # module -> the distributions providing it
    local = {"pyvf"} | {n[:-3] for folder in ("tests", "tools") for n in os.listdir(os.path.join(ROOT, folder))}
    undeclared = set()
    for folder in ("pyvf", "tests", "tools"):
        for module, path in _imports(folder):
            if module in sys.stdlib_module_names or module in local:
                continue
            dists = {re.sub(r"[-_.]+", "-", d).lower() for d in distributions.get(module, [module])}
            if not dists & declared:
                undeclared.add(f"{module} ({os.path.relpath(path, ROOT)})")
    assert not undeclared, f"imported but declared neither in pyproject.toml nor tests/requirements.txt: {undeclared}"


def test_an_undeclared_import_is_found(tmp_path, monkeypatch):
    """The check above can fail: scipy, declared nowhere, imported by a file of tools/."""
    monkeypatch.setattr(sys.modules[__name__], "ROOT", str(tmp_path))
    for folder in ("pyvf", "tests", "tools"):
        (tmp_path / folder).mkdir()
    (tmp_path / "pyproject.toml").write_text('[project]\ndependencies = ["numpy>=1"]\n')
    (tmp_path / "tests" / "requirements.txt").write_text("pytest\n")
    (tmp_path / "tools" / "a.py").write_text("import numpy\nimport os\nfrom scipy.spatial import ConvexHull\n")
    with pytest.raises(AssertionError, match=r"scipy \(tools/a.py\)"):
        test_every_third_party_import_is_declared()
