"""pyvf's compiled kernels, on the instruction-set path this process uses.

csrc/ is compiled once per path into `pyvf._core_<path>`: x86-64 baseline (SSE2), avx2 (AVX2 +
FMA), avx512 (AVX-512 F/DQ/BW/VL + FMA); aarch64 neon. The base module asks the CPU what it
supports; the best path built that it runs is used, unless PYVF_ISA names another. `_core.<kernel>`
is the current path's (PEP 562 __getattr__), so `use_path` switches every kernel at once.
"""

import importlib
import importlib.util
import os
import platform

# Paths of each architecture, lowest first; the first is the base that runs anywhere.
_ARCH_PATHS = {"x86_64": ("baseline", "avx2", "avx512"), "aarch64": ("neon",)}
# CPU features (cpu_features() names) each path needs.
_NEEDS = {"avx2": ("avx2", "fma"), "avx512": ("avx512f", "avx512dq", "avx512bw", "avx512vl", "avx2", "fma")}

_machine = platform.machine().lower()
_machine = {"amd64": "x86_64", "x64": "x86_64", "arm64": "aarch64"}.get(_machine, _machine)
_order = _ARCH_PATHS.get(_machine, ("baseline",))
_built_paths = tuple(p for p in _order if importlib.util.find_spec(f"pyvf._core_{p}") is not None)
if not _built_paths:
    _here = os.path.dirname(os.path.abspath(__file__))
    if os.path.exists(os.path.join(os.path.dirname(_here), "csrc")):  # a source checkout, not an installed copy
        raise ImportError(
            f"Python imported pyvf from the source tree {_here}, which has no compiled kernels (the checkout "
            "shadows any installed pyvf): install it editable, which builds them (`pip install scikit-build-core "
            "pybind11 cmake ninja && pip install --no-build-isolation -e .`), or run Python from another folder")
    raise ImportError("pyvf's compiled extension (pyvf._core_<path>) is missing: install pyvf with `pip install .`")
_base = importlib.import_module(f"pyvf._core_{_built_paths[0]}")
_features = dict(_base.cpu_features())
_runs = tuple(p for p in _built_paths if all(_features.get(f, False) for f in _NEEDS.get(p, ())))

_forced = os.environ.get("PYVF_ISA", "").strip() or None
if _forced is not None and _forced not in _runs:
    raise ImportError(f"PYVF_ISA={_forced!r} is not a kernel path this build and CPU run: choose one of "
                      f"{', '.join(_runs)} (built: {', '.join(_built_paths)})")
_current = _forced or _runs[-1]
# the paths this process may use: those the CPU runs, up to the forced one; each module loaded now
_allowed = _runs[: _runs.index(_current) + 1]
_modules = {p: importlib.import_module(f"pyvf._core_{p}") for p in _allowed}
_impl = _modules[_current]


def set_num_threads(n):
    """The kernels' threads in every path module (pyvf.set_num_threads is public)."""
    for m in _modules.values():
        m.set_num_threads(n)


def num_threads():
    """The kernels' threads: set_num_threads's count, else OpenMP's default."""
    return _impl.num_threads()


def available_paths():
    """The kernel paths this process can use, lowest first: built, run by this CPU, not above PYVF_ISA."""
    return _allowed


def current_path():
    return _current


def use_path(path):
    """Make every kernel use `path` (one of available_paths()); returns the previous path."""
    global _current, _impl
    if path not in _allowed:
        raise ValueError(f"path must be one of {', '.join(_allowed)} (the kernel paths this process can use), "
                         f"got {path!r}")
    previous, _current, _impl = _current, path, _modules[path]
    return previous


def config_lines():
    """What show_config prints after the version: the path, the paths, the CPU's features, the threads."""
    needs = _NEEDS.get(_current)
    cpu = f"needs {', '.join(needs)}" if needs else f"any {platform.machine()} CPU"
    forced = f", forced by PYVF_ISA={_forced}" if _forced else ""
    return [f"kernel path: {_current} ({cpu}; {_impl.simd_bytes}-byte vectors){forced}",
            f"paths this process can use: {', '.join(_allowed)}",
            f"paths built: {', '.join(_built_paths)}",
            f"cpu features: {', '.join(k for k, v in _features.items() if v) or '-'}",
            f"threads: {_impl.num_threads()} (OpenMP {'on' if _impl.openmp else 'off'})"]


def __getattr__(name):  # any kernel: the current path's
    return getattr(_impl, name)
