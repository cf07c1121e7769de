"""Argument checks shared by pyvf's modules: every error names the argument and says what was
expected; nothing is cast or copied silently. Shape rules stay with the function that has them."""

import numpy as np

from . import _core

FLOATS = (np.dtype(np.float32), np.dtype(np.float64))


def all_finite(a):
    """True when every element of the float array a is finite; a C-contiguous array is scanned by
    the C++ kernel, which allocates nothing (np.isfinite would allocate a bool array as large)."""
    if a.dtype in FLOATS and a.flags.c_contiguous:
        return _core.all_finite(a)
    return bool(np.isfinite(a).all())


def float_array(name, a, like=None, like_name="x"):
    """a must be a float32 or float64 ndarray, of like's dtype when like is given."""
    if not isinstance(a, np.ndarray):
        raise TypeError(f"{name} must be a numpy.ndarray, got {type(a).__name__}")
    if a.dtype not in FLOATS:
        raise TypeError(f"{name} must be float32 or float64, got {a.dtype} (pyvf never casts silently)")
    if like is not None and a.dtype != like.dtype:
        raise TypeError(f"{name} is {a.dtype} but {like_name} is {like.dtype}: both must share one dtype "
                        "(pyvf never casts silently)")
    return a


def contiguous(name, a):
    if not a.flags.c_contiguous:
        raise ValueError(f"{name} is not C-contiguous (a transposed or sliced view?): "
                         f"pass np.ascontiguousarray({name})")
    return a


def finite(name, a):
    if not all_finite(a):
        raise ValueError(f"{name} contains NaN or inf")
    return a


def weight(name, a, shape, dtype):
    """A checkpoint's array for parameter `name` -> a C-contiguous array of `dtype`: it must be a
    float array of `shape` with finite values. The conversion to the model's dtype is the one
    pyvf makes, on purpose (a float32 checkpoint loads into a float64 model for a float64 check)."""
    a = np.asarray(a)
    if a.dtype.kind != "f":
        raise TypeError(f"load_official: {name!r} has dtype {a.dtype}, expected a float array")
    if a.shape != tuple(shape):
        raise ValueError(f"load_official: {name!r} has shape {a.shape}, expected {tuple(shape)}")
    if not np.isfinite(a).all():
        raise ValueError(f"load_official: {name!r} contains NaN or inf")
    return np.ascontiguousarray(a, dtype=dtype)
