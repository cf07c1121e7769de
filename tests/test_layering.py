"""The house's layout, read from the source: one home per kind of work, each importing
only from the homes below it; argparse only in the command line; no function longer than 80 lines.

Every module under pyvf/ is parsed with `ast`; every import in it, at module level or inside a
function, is resolved (relative imports against the module's package) to the pyvf module it
names and that module's home. Nothing is imported, so a violation is found even in code that
runs only on some path (a fallback, a command).
"""

import ast
import os

PKG = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "pyvf")

# The homes, lowest first: a home imports only from its own rank and below.
#   root:     the helpers at the package root (pyvf/_core.py, _checks.py, _io.py, _machine.py,
#             geometry.py): the kernels, argument checks, files, the machine's facts, pose math
#   nn:       the layer pairs             models:   Transformer, Codebook, their weights
#   verify:   traces, compare, teacher forcing, converters
#   scenes:   the renderer and the dataset on disk
#   evaluate: metrics, pictures, the demo  train:    optimisers, steps, the training loops
#   facade:   pyvf/__init__.py, the public API (`import pyvf`): it imports from the homes up to
#             train, so a home below bench that imports it (or a name it defines) looks upward
#   bench:    every benchmark and report  cli:      the `pyvf` command (and pyvf/__main__.py)
HOMES = ["root", "nn", "models", "verify", "scenes", "evaluate", "train", "facade", "bench", "cli"]
RANK = {home: i for i, home in enumerate(HOMES)}
MAX_FUNCTION_LINES = 80


def modules():
    """{dotted name: file} of every module under pyvf/ (a package as its __init__.py)."""
    found = {}
    for folder, dirs, files in os.walk(PKG):
        dirs[:] = sorted(d for d in dirs if not d.startswith((".", "__pycache__")))
        for name in sorted(files):
            if name.endswith(".py"):
                rel = os.path.relpath(os.path.join(folder, name), os.path.dirname(PKG))[:-3].split(os.sep)
                if rel[-1] == "__init__":
                    rel = rel[:-1]
                found[".".join(rel)] = os.path.join(folder, name)
    return found


MODULES = modules()
TREES = {}


def tree(module):
    if module not in TREES:
        with open(MODULES[module]) as f:
            TREES[module] = ast.parse(f.read(), MODULES[module])
    return TREES[module]


def home(module):
    """The home of a pyvf module: 'pyvf' itself is the facade, pyvf.__main__ belongs to the
    command line, a top-level module is a root helper, and pyvf.<home>.* is <home>."""
    parts = module.split(".")
    if parts == ["pyvf"]:
        return "facade"
    if parts[1] == "__main__":
        return "cli"
    if len(parts) == 2 and not os.path.isdir(os.path.join(PKG, parts[1])):
        return "root"
    if parts[1] not in RANK or parts[1] in ("root", "facade"):
        raise AssertionError(f"pyvf/{parts[1]}/ is no home in HOMES: add it to the rank list")
    return parts[1]


def package_of(module):
    """The package a module's relative imports start from (a package is its own)."""
    is_package = MODULES[module].endswith("__init__.py")
    return module if is_package else module.rsplit(".", 1)[0]


def facade_names():
    """{name: home} of the names pyvf/__init__.py offers: an imported name belongs to the home it
    comes from, a name the facade defines itself (kernel_path, num_threads) to the facade."""
    names = {}
    for node in tree("pyvf").body:
        if isinstance(node, ast.ImportFrom):
            for module, name in targets("pyvf", node):
                names[name] = home(module)
        elif isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            names[node.name] = "facade"
        elif isinstance(node, ast.Assign):
            names.update((t.id, "facade") for t in node.targets if isinstance(t, ast.Name))
    return names


def targets(module, node):
    """[(pyvf module, bound name)] that an Import/ImportFrom node in `module` names; other
    packages' imports are left out. `from pkg import x` names pkg.x where that is a module,
    else pkg (x is one of pkg's names)."""
    if isinstance(node, ast.Import):
        return [(a.name, a.asname or a.name) for a in node.names if a.name.split(".")[0] == "pyvf"]
    if node.level:
        base = package_of(module).split(".")
        base = base[:len(base) - (node.level - 1)]
        source = ".".join(base + ([node.module] if node.module else []))
    else:
        source = node.module
    if source.split(".")[0] != "pyvf":
        return []
    return [(f"{source}.{a.name}" if f"{source}.{a.name}" in MODULES else source, a.name) for a in node.names]


def import_nodes(node, in_function=False):
    """(Import/ImportFrom node, whether it sits inside a function) of every import under node."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, (ast.Import, ast.ImportFrom)):
            yield child, in_function
        yield from import_nodes(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)))


def imports():
    """[(importing module, line, imported module, name, imported home, inside a function)] of
    every pyvf import under pyvf/; a facade name (`from .. import name`) gets its own home."""
    offered = facade_names()
    found = []
    for module in MODULES:
        for node, in_function in import_nodes(tree(module)):
            for target, name in targets(module, node):
                where = home(target)
                if where == "facade" and isinstance(node, ast.ImportFrom):
                    where = offered.get(name, "facade")
                found.append((module, node.lineno, target, name, where, in_function))
    return found


def upward(found):
    """The imports of `found` that reach a home above the importer's (the facade's own are its job).
    A facade name taken by `from .. import name` is looked up like any other; `import pyvf` is the
    facade wherever it stands, at module level or inside a function (the settings every home
    needs, threads and the version, live in root helpers: pyvf/_threads.py, pyvf/_version.py)."""
    return [f"{MODULES[m]}:{line} ({home(m)}) imports {name} from {target} ({where})"
            for m, line, target, name, where, in_function in found
            if m != "pyvf" and RANK[where] > RANK[home(m)]]


def test_the_scan_sees_every_home_and_resolves_relative_imports():
    # the scan is not vacuous: it finds imports from every home into the ones below, and resolves
    # the relative forms the package uses to the modules they name
    found = imports()
    assert {home(m) for m in MODULES} == set(HOMES), sorted({home(m) for m in MODULES})
    pairs = {(m, target) for m, _, target, *_ in found}
    assert ("pyvf.cli.bench", "pyvf.bench.common") in pairs  # `from ..bench.common import ...`
    assert ("pyvf.geometry", "pyvf._checks") in pairs
    assert ("pyvf.bench.common", "pyvf") in pairs  # a function-level `import pyvf`
    assert len(found) > 100, len(found)


def test_no_home_imports_a_higher_home():
    bad = upward(imports())
    assert not bad, "imports that reach a higher home (rank: " + " < ".join(HOMES) + "):\n" + "\n".join(bad)


def test_the_scan_names_a_planted_upward_import():
    # planted in memory, in a models module: an import from train inside a function, a name the
    # facade defines, `import pyvf` at module level and inside a function: each is found
    planted = ast.parse("def f():\n    from ..train import optim\n    import pyvf\n"
                        "from .. import kernel_path\nimport pyvf\n")
    real = tree("pyvf.models.io")
    TREES["pyvf.models.io"] = planted
    try:
        bad = upward(imports())
    finally:
        TREES["pyvf.models.io"] = real
    assert any("models/io.py:2 (models) imports optim from pyvf.train.optim (train)" in b for b in bad), bad
    assert any("models/io.py:4 (models) imports kernel_path from pyvf (facade)" in b for b in bad), bad
    assert any("models/io.py:5 (models) imports pyvf from pyvf (facade)" in b for b in bad), bad
    assert any("models/io.py:3 (models) imports pyvf from pyvf (facade)" in b for b in bad), bad


def test_argparse_only_in_the_command_line():
    users = [f"{MODULES[m]}:{node.lineno} imports argparse" for m in MODULES for node in ast.walk(tree(m))
             if isinstance(node, (ast.Import, ast.ImportFrom)) and home(m) != "cli"
             and any((a.name if isinstance(node, ast.Import) else node.module or "").split(".")[0] == "argparse"
                     for a in node.names)]
    assert not users, "argparse outside pyvf/cli/:\n" + "\n".join(users)


def test_no_function_longer_than_80_lines():
    long = sorted((node.end_lineno - node.lineno + 1, f"{MODULES[m]}:{node.lineno} {node.name}")
                  for m in MODULES for node in ast.walk(tree(m))
                  if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)))
    offenders = [f"{where}: {n} lines" for n, where in long if n > MAX_FUNCTION_LINES]
    assert long and long[-1][0] > 20, long[-3:]  # the scan saw real functions
    assert not offenders, f"functions over {MAX_FUNCTION_LINES} lines:\n" + "\n".join(offenders)


def test_import_pyvf_loads_no_training_code(tmp_path):
    """`import pyvf` is the library: the training names (pyvf.AdamW, pyvf.train_step, ...) load
    pyvf.train on first use, not before."""
    import subprocess
    import sys

    code = ("import sys, pyvf; print(sorted(m for m in sys.modules if m.startswith('pyvf.train'))); "
            "pyvf.AdamW; print('pyvf.train.optim' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.stdout.split("\n")[:2] == ["[]", "True"], proc.stdout + proc.stderr


def cycles(edges):
    """The import cycles of a graph {module: set of modules it imports}, each as the path that
    closes it (a depth-first search; each cycle reported once from its first module)."""
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
    """No module imports one that imports it back, through any chain, at module level or inside a
    function (a package's __init__ and its submodules aside: a package imports its own parts)."""
    edges = {}
    for m, _, target, _, _, _ in imports():
        if not (m.startswith(target + ".") or target.startswith(m + ".")) and target != m:
            edges.setdefault(m, set()).add(target)
    assert not cycles(edges), cycles(edges)


def test_the_cycle_scan_finds_a_planted_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c", "a"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
