"""The house's layout, read from the source with `ast` (nothing imported, so code that runs only
on some path is seen too): each home imports only from its own rank and below, no import cycles,
argparse only in the command line, no function longer than 80 lines, and `import pyvf` loads no
training code."""

import ast
import os
import subprocess
import sys

PKG = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "pyvf")

# The homes, lowest first. root: pyvf/*.py (kernels, checks, files, pose math); facade:
# pyvf/__init__.py, which imports from the homes up to train; cli: pyvf/cli/ and pyvf/__main__.py.
HOMES = ["root", "nn", "models", "verify", "scenes", "evaluate", "train", "facade", "bench", "cli"]
RANK = {home: i for i, home in enumerate(HOMES)}


def _modules():
    """{dotted name: file} of every module under pyvf/ (a package as its __init__.py)."""
    found = {}
    for folder, _, files in os.walk(PKG):
        for name in files:
            if name.endswith(".py"):
                parts = os.path.relpath(os.path.join(folder, name), os.path.dirname(PKG))[:-3].split(os.sep)
                found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = os.path.join(folder, name)
    return found


MODULES = _modules()
TREES = {m: ast.parse(open(path).read(), path) for m, path in MODULES.items()}


def home(module):
    parts = module.split(".")
    if parts == ["pyvf"]:
        return "facade"
    if parts[1] == "__main__":
        return "cli"
    return parts[1] if parts[1] in RANK else "root"


def imports(module):
    """The pyvf modules that `module` imports anywhere (module level or in a function); relative
    imports resolved; `from pkg import x` names pkg.x where that is a module, else pkg."""
    package = module if MODULES[module].endswith("__init__.py") else module.rsplit(".", 1)[0]
    for node in ast.walk(TREES[module]):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names if a.name.split(".")[0] == "pyvf")
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[:len(package.split(".")) - node.level + 1] if node.level else []
            source = ".".join(base + ([node.module] if node.module else []))
            if source.split(".")[0] == "pyvf":
                yield from (f"{source}.{a.name}" if f"{source}.{a.name}" in MODULES else source for a in node.names)


def upward():
    return [f"{MODULES[m]} ({home(m)}) imports {t} ({home(t)})"
            for m in MODULES if m != "pyvf" for t in imports(m) if RANK[home(t)] > RANK[home(m)]]


def test_no_home_imports_a_higher_home(monkeypatch):
    assert {home(m) for m in MODULES} == set(HOMES)
    assert "pyvf.bench.common" in set(imports("pyvf.cli.bench"))  # relative imports are resolved
    assert not upward(), "imports that reach a higher home:\n" + "\n".join(upward())
    # planted in a models module: an import from train in a function, `import pyvf`, `from .. import`
    planted = "def f():\n    from ..train import optim\nimport pyvf\nfrom .. import kernel_path\n"
    monkeypatch.setitem(TREES, "pyvf.models.io", ast.parse(planted))
    assert {b.split(" imports ")[1] for b in upward()} == {"pyvf.train.optim (train)", "pyvf (facade)"}, upward()


def cycles(edges):
    """The import cycles of {module: modules it imports}, each as the path that closes it."""
    found, state = [], {}

    def visit(m, path):
        state[m] = "open"
        for n in sorted(edges.get(m, ())):
            if state.get(n) == "open":
                found.append(path[path.index(n):] + [n])
            elif n not in state:
                visit(n, path + [n])
        state[m] = "done"

    for m in sorted(edges):
        if m not in state:
            visit(m, [m])
    return found


def test_no_import_cycles():
    """A package's __init__ and its own submodules aside (a package imports its parts)."""
    edges = {m: {t for t in imports(m) if not (t.startswith(m + ".") or m.startswith(t + ".") or t == m)}
             for m in MODULES}
    assert not cycles(edges), cycles(edges)
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c", "a"]]


def test_argparse_only_in_the_command_line_and_no_function_over_80_lines():
    argparse = [MODULES[m] for m in MODULES if home(m) != "cli" for node in ast.walk(TREES[m])
                if isinstance(node, ast.Import) and any(a.name == "argparse" for a in node.names)
                or isinstance(node, ast.ImportFrom) and node.module == "argparse"]
    assert not argparse, argparse
    lengths = {f"{MODULES[m]}:{node.lineno} {node.name}": node.end_lineno - node.lineno + 1
               for m in MODULES for node in ast.walk(TREES[m]) if isinstance(node, ast.FunctionDef)}
    assert max(lengths.values()) > 20, "the scan saw no real functions"
    assert not {k: n for k, n in lengths.items() if n > 80}


def test_import_pyvf_loads_no_training_code(tmp_path):
    """The training names (pyvf.AdamW, ...) load pyvf.train on first use, not before."""
    code = ("import sys, pyvf; print(sorted(m for m in sys.modules if m.startswith('pyvf.train'))); "
            "pyvf.AdamW; print('pyvf.train.optim' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.stdout.split("\n")[:2] == ["[]", "True"], proc.stdout + proc.stderr
