""".ci/run fails when a step fails: run on a copy with stand-ins for python3 (its venv), pip, pyvf and
pytest on PATH. And every third-party module that pyvf/, tests/ or tools/ imports is declared."""

import ast
import importlib.metadata
import os
import re
import shutil
import stat
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CI = os.path.join(ROOT, ".ci", "run")


def _stub(folder, name, status):
    path = os.path.join(folder, name)
    with open(path, "w") as f:
        if name == "python3":  # `python3 -m venv DIR`: an empty activate, so the other stand-ins stay on PATH
            f.write(f"#!/bin/sh\necho python3 \"$1 $2\" >> \"$STUB_LOG\"\nmkdir -p \"$3/bin\"\n"
                    f": > \"$3/bin/activate\"\nexit {status}\n")
        else:
            f.write(f"#!/bin/sh\necho {name} \"$@\" >> \"$STUB_LOG\"\nexit {status}\n")
    os.chmod(path, os.stat(path).st_mode | stat.S_IEXEC)


VENV = "python3 -m venv"


@pytest.mark.parametrize("broken, ran", [
    ("python3", [VENV]),  # no fresh environment: nothing runs in the machine's own
    ("pip", [VENV, "pip install ."]),  # a failed build stops the run: no demo, no tests on an older install
    ("pyvf", [VENV, "pip install .", "pyvf demo"]),
    ("pytest", [VENV, "pip install .", "pyvf demo", "pip install -r tests/requirements.txt", "pytest"]),
])
def test_a_failed_step_fails_the_ci_script(tmp_path, broken, ran):
    assert os.path.exists(CI) and shutil.which("bash"), "the tests run from the source tree, with bash"
    repo = tmp_path / "repo"
    (repo / ".ci").mkdir(parents=True)
    shutil.copy(CI, repo / ".ci" / "run")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for name in ("python3", "pip", "pyvf", "pytest"):
        _stub(str(bin_dir), name, 1 if name == broken else 0)
    log = tmp_path / "calls"
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}", STUB_LOG=str(log))
    proc = subprocess.run(["bash", str(repo / ".ci" / "run")], env=env, capture_output=True, text=True,
                          stdin=subprocess.DEVNULL, timeout=60)
    assert proc.returncode != 0, proc.stdout + proc.stderr
    assert "failed" in proc.stderr
    assert log.read_text().split("\n")[:-1] == ran


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
