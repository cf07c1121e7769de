"""pyvf: a reference implementation of ViewFormer (ECCV 2022) in NumPy with C++ kernels.

Every layer has a hand-written forward and backward pass; SPEC.md is the math.
"""

try:
    from . import _core
except ImportError as e:  # running from a source tree that was never built
    raise ImportError(
        "pyvf's compiled extension pyvf._core is missing: install pyvf with `pip install .` "
        "(it compiles csrc/), and do not run Python from inside the source tree's pyvf/ folder"
    ) from e

from .attention import (
    branching_attention,
    branching_attention_backward,
    branching_attention_forward,
    branching_attention_reference,
    branching_attention_reference_vjp,
    branching_attention_vjp,
    branching_mask,
)

__version__ = "0.1.0"


def num_threads():
    """Threads the C++ kernels use (OpenMP; OMP_NUM_THREADS sets the default)."""
    return _core.num_threads()


def set_num_threads(n):
    """Set the threads the C++ kernels use, for this process."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    _core.set_num_threads(n)


__all__ = [
    "branching_attention",
    "branching_attention_backward",
    "branching_attention_forward",
    "branching_attention_reference",
    "branching_attention_reference_vjp",
    "branching_attention_vjp",
    "branching_mask",
    "num_threads",
    "set_num_threads",
]
