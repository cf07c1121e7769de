"""pyvf: a reference implementation of ViewFormer (ECCV 2022) in NumPy with C++ kernels.

Every layer has a hand-written forward and backward pass; SPEC.md is the math.
"""

import os

# OpenMP threads that spin after a parallel region steal the cores numpy's BLAS threads need
# (measured on 2 cores: a tiny transformer's training step 57 ms spinning, 31.5 ms passive).
# Sleep instead, unless the user chose.
# Read by libgomp when _core loads it, so it must be set before the import.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

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

from .geometry import (
    absolute_poses,
    average_pose,
    make_relative,
    orientation_error,
    position_error,
    quat_canonical,
    quat_conj,
    quat_mul,
    quat_normalize,
    quat_rotate,
    relative_poses,
)
from .codebook import Codebook, CodebookConfig, CodebookOutput
from .quantizer import EMAQuantizer, QuantizerOutput, vq_nearest
from .optim import Adam, AdamW, WarmupCosine, clip_grad_norm, published_weight_decay, warmup_cosine_lr
from .train import codebook_train_step, train_step
from .transformer import Scene, Transformer, TransformerConfig, TransformerOutput

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
    "Codebook",
    "CodebookConfig",
    "CodebookOutput",
    "codebook_train_step",
    "EMAQuantizer",
    "QuantizerOutput",
    "vq_nearest",
    "Adam",
    "AdamW",
    "Scene",
    "Transformer",
    "TransformerConfig",
    "TransformerOutput",
    "WarmupCosine",
    "absolute_poses",
    "average_pose",
    "clip_grad_norm",
    "make_relative",
    "orientation_error",
    "position_error",
    "published_weight_decay",
    "quat_canonical",
    "quat_conj",
    "quat_mul",
    "quat_normalize",
    "quat_rotate",
    "relative_poses",
    "train_step",
    "warmup_cosine_lr",
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
