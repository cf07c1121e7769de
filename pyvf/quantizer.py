"""The codebook's vector quantizer (SPEC.md §4): the exact nearest-code lookup.

    indices, sq_distances = vq_nearest(x, codes)    # x (M, D), codes (K, D)

indices (M,) int64: for each row of x the index of the nearest code in squared Euclidean
distance, exactly (the argmin of sum_i (x_i - e_i)^2 computed in float64 from the given
values, ties to the smallest index), whatever the size of the vectors; sq_distances (M,) of
x's dtype: that distance, never negative. The C++ kernel (csrc/vq.cpp) scores codes by a fast
product and re-ranks exactly every code that its rounding-error bound cannot rule out.

Note the layouts: the published quantizer stores codes as the columns of
`quantize.embeddings` (embed_dim, n_embed); this function takes them as rows (K, D), i.e.
`embeddings.T` made contiguous.
"""

import numpy as np

from . import _core

__all__ = ["vq_nearest"]


def _check_2d(name, a, D=None, dtype=None):
    if not isinstance(a, np.ndarray):
        raise TypeError(f"{name} must be a numpy.ndarray, got {type(a).__name__}")
    if a.dtype not in (np.float32, np.float64):
        raise TypeError(f"{name} must be float32 or float64, got {a.dtype} (pyvf never casts silently)")
    if dtype is not None and a.dtype != dtype:
        raise TypeError(f"{name} is {a.dtype} but x is {dtype}: both must share one dtype")
    if a.ndim != 2:
        raise ValueError(f"{name} must be 2-dimensional, got shape {a.shape}")
    if D is not None and a.shape[1] != D:
        raise ValueError(f"{name} has width {a.shape[1]} but x has width {D}")
    if not a.flags.c_contiguous:
        raise ValueError(f"{name} is not C-contiguous: pass np.ascontiguousarray({name})")
    if not _core.all_finite(a):
        raise ValueError(f"{name} contains NaN or inf")


def vq_nearest(x, codes):
    """x (M, D), codes (K, D), one float dtype -> indices (M,) int64, sq_distances (M,)."""
    _check_2d("x", x)
    _check_2d("codes", codes, D=x.shape[1], dtype=x.dtype)
    if codes.shape[0] == 0:
        raise ValueError("codes is empty: there is no nearest code")
    if x.shape[1] == 0:
        raise ValueError("x and codes have width 0")
    index = np.empty(x.shape[0], dtype=np.int64)
    sq = np.empty(x.shape[0], dtype=x.dtype)
    if x.shape[0]:
        _core.vq_nearest(index, sq, x, codes)
    return index, sq
