"""pyvf: a reference implementation of ViewFormer (ECCV 2022) in NumPy with C++ kernels.

Every layer has a hand-written forward and backward pass; docs/math.md is the math.
"""

import os
import sys

# OpenMP threads that spin after a parallel region steal the cores other work needs: numpy's, the
# user's, other processes'. Sleep at once instead, unless the user chose a policy or a spin count.
# Read by libgomp when _core loads it, so it must be set before the import.
if "OMP_WAIT_POLICY" not in os.environ and "GOMP_SPINCOUNT" not in os.environ:
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"


def _running_the_pyvf_command():
    """Whether this process is the `pyvf` command (its console script, or `python -m pyvf`)."""
    if os.path.splitext(os.path.basename(sys.argv[0]))[0] == "pyvf":
        return True
    argv = list(getattr(sys, "orig_argv", []))  # while -m finds its module, sys.argv[0] is "-m"
    return sys.argv[0] == "-m" and ("-mpyvf" in argv or any(a == "-m" and b == "pyvf" for a, b in zip(argv, argv[1:])))


try:
    from . import _core  # the compiled kernels, on the best instruction-set path (or PYVF_ISA's)
except ImportError as e:
    if _running_the_pyvf_command():  # a bad PYVF_ISA or a missing build: one line, not a traceback
        raise SystemExit(f"pyvf: error: {e}") from None
    raise
from . import _threads
from ._threads import num_threads, set_num_threads, threads  # the kernels' and numpy's BLAS threads
from ._memory import reuse_freed_memory  # page faults of each step's fresh arrays (every command calls it)
from ._version import __version__

from .nn.attention import (branching_attention, branching_attention_backward, branching_attention_forward,
                           branching_attention_reference, branching_attention_reference_vjp, branching_attention_vjp,
                           branching_mask)
from .geometry import (absolute_poses, average_pose, make_relative, orientation_error, position_error, quat_canonical,
                       quat_conj, quat_mul, quat_normalize, quat_rotate, relative_poses)
from .models.codebook import Codebook, CodebookConfig, CodebookOutput
from .nn.quantizer import EMAQuantizer, QuantizerOutput, vq_nearest
from .models.transformer import Scene, Transformer, TransformerConfig, TransformerOutput
from .verify.compare import Comparison, compare, rel_err
from .verify.layout import flat_to_tree, params_from_layout, params_to_layout, trace_from_flat, tree_to_flat
from .verify.teacher import TeacherReport, teacher_force


# The training names, imported on first use (PEP 562): `import pyvf` loads no training code.
_TRAINING = {name: "train.optim" for name in ("Adam", "AdamW", "WarmupCosine", "clip_grad_norm",
                                             "published_weight_decay", "warmup_cosine_lr")}
_TRAINING.update(codebook_train_step="train", train_step="train")


def __getattr__(name):
    if name not in _TRAINING:
        raise AttributeError(f"module 'pyvf' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f".{_TRAINING[name]}", __name__), name)
    globals()[name] = value
    return value


def kernel_path():
    """The instruction-set path every C++ kernel uses now: 'baseline', 'avx2', 'avx512' (x86-64)
    or 'neon' (aarch64)."""
    return _core.current_path()


def kernel_paths():
    """The paths this process can use, lowest first: built, run by this CPU, and not above the
    one the environment variable PYVF_ISA names (it forces a path for the whole process)."""
    return list(_core.available_paths())


class use_kernel_path:
    """Switch every kernel to `path` (one of kernel_paths()) now; as a context manager, switch
    back on exit: `with pyvf.use_kernel_path("baseline"): o = pyvf.branching_attention(q, k, v)`."""

    def __init__(self, path):
        self.previous = _core.use_path(path)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        _core.use_path(self.previous)


def show_config(file=None):
    """Print the version, the kernels' instruction-set path, the paths this CPU and build offer,
    and the threads: the first thing to include in a bug report or a benchmark."""
    print("\n".join([f"pyvf {__version__}", *_core.config_lines()]), file=file)


# PYVF_NUM_THREADS for the kernels and numpy's BLAS
_threads.set_from_environment()


__all__ = [
    "reuse_freed_memory", "Comparison", "compare", "rel_err", "flat_to_tree", "tree_to_flat", "params_from_layout",
    "params_to_layout", "trace_from_flat", "TeacherReport", "teacher_force",  # verification
    "Codebook", "CodebookConfig", "CodebookOutput", "codebook_train_step", "EMAQuantizer", "QuantizerOutput",
    "vq_nearest", "Scene", "Transformer", "TransformerConfig", "TransformerOutput", "train_step",  # the models
    "Adam", "AdamW", "WarmupCosine", "clip_grad_norm", "published_weight_decay", "warmup_cosine_lr",  # training
    "absolute_poses", "average_pose", "make_relative", "orientation_error", "position_error", "quat_canonical",
    "quat_conj", "quat_mul", "quat_normalize", "quat_rotate", "relative_poses",  # geometry
    "branching_attention", "branching_attention_backward", "branching_attention_forward",
    "branching_attention_reference", "branching_attention_reference_vjp", "branching_attention_vjp",
    "branching_mask",  # the attention kernel
    "num_threads", "set_num_threads", "threads", "kernel_path", "kernel_paths", "use_kernel_path", "show_config",
]
