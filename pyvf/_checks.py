"""Argument checks for pyvf's public entry points (docs/contributing.md): every error names the
argument; nothing is cast silently."""

import numpy as np

from . import _core

FLOATS = (np.dtype(np.float32), np.dtype(np.float64))


def all_finite(a):
    """True when every element of the float array a is finite (a C-contiguous one is scanned by
    the C++ kernel, which allocates nothing)."""
    if isinstance(a, np.ndarray) and a.dtype in FLOATS and a.flags.c_contiguous:
        return _core.all_finite(a)
    return bool(np.isfinite(a).all())


def plain_array(name, a):
    """Refuse np.matrix (2-D under indexing, * a matrix product) and a masked array with masked
    elements (pyvf would compute with the values under the mask): TypeError."""
    if isinstance(a, np.matrix) or (isinstance(a, np.ma.MaskedArray) and np.ma.is_masked(a)):
        raise TypeError(f"{name} must be a plain numpy array, got a {type(a).__name__}: pass np.asarray({name})")


def float_array(name, a, like=None, like_name="x"):
    """a must be a float32 or float64 ndarray, of like's dtype when like is given."""
    if not isinstance(a, np.ndarray):
        raise TypeError(f"{name} must be a numpy.ndarray, got {type(a).__name__}")
    plain_array(name, a)
    if a.dtype not in FLOATS:
        raise TypeError(f"{name} must be float32 or float64, got {a.dtype} (pyvf never casts silently)")
    if like is not None and a.dtype != like.dtype:
        raise TypeError(f"{name} is {a.dtype} but {like_name} is {like.dtype}: both must share one dtype")
    return a


def contiguous(name, a):
    if not a.flags.c_contiguous:
        raise ValueError(f"{name} is not C-contiguous: pass np.ascontiguousarray({name})")
    return a


def finite(name, a):
    if not all_finite(a):
        raise ValueError(f"{name} contains NaN or inf")
    return a


def int_array(name, a):
    """a must be an ndarray of a signed or unsigned integer dtype."""
    if not isinstance(a, np.ndarray):
        raise TypeError(f"{name} must be a numpy.ndarray of integers, got {type(a).__name__}")
    plain_array(name, a)
    if a.dtype.kind not in "iu":
        raise TypeError(f"{name} must be an integer array, got {a.dtype} (pyvf never casts silently)")
    return a


def integer(name, x, lo=None):
    """x: a Python or NumPy integer (not bool), >= lo when lo is given -> int."""
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {type(x).__name__} {x!r}")
    if lo is not None and x < lo:
        raise ValueError(f"{name} must be >= {lo}, got {x!r}")
    return int(x)


def positive_integer(name, x):
    """x: a Python or NumPy integer (not bool), >= 1 -> int."""
    return integer(name, x, 1)


def real(name, x, lo=None, hi=None, lo_open=False, hi_open=False):
    """x: a finite real number (not bool), in [lo, hi] (open ends where asked) -> float."""
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a real number, got {type(x).__name__} {x!r}")
    x = float(x)
    ok = np.isfinite(x) and (lo is None or (x > lo if lo_open else x >= lo)) \
        and (hi is None or (x < hi if hi_open else x <= hi))
    if not ok:
        raise ValueError(f"{name} must be finite and in {'(' if lo_open else '['}{'-inf' if lo is None else lo}, "
                         f"{'inf' if hi is None else hi}{')' if hi_open else ']'}, got {x!r}")
    return x

