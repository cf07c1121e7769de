"""Argument checks for pyvf's public entry points (docs/contributing.md): every error names the
argument; nothing is cast silently. Also the checks of a checkpoint's entries, every wrong entry
named in one error (pyvf.models.io's loader and the quantizer)."""

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


def finite_result(what, a, name="the result"):
    """Raise ValueError when `a`, computed from finite inputs, is not finite: it overflowed."""
    if not all_finite(a):
        raise ValueError(f"{what}: {name} is not finite: it overflowed {a.dtype} (rescale the inputs, or use float64)")
    return a


def checkpoint_array(name, a):
    """A checkpoint's entry -> (numpy array or `a` unchanged, problem or None). Anything with
    `.detach()` (a torch tensor, on any device) becomes `a.detach().cpu().numpy()` (pyvf never
    imports torch); a tensor numpy cannot hold (bfloat16) is a TypeError problem naming `name`."""
    if hasattr(a, "detach") and not isinstance(a, np.ndarray):
        try:
            return a.detach().cpu().numpy(), None
        except (TypeError, RuntimeError, AttributeError) as e:
            return a, (TypeError, f"{name!r} ({type(a).__name__}) cannot become a numpy array: {e}")
    return a, None


def weight_problem(name, a, shape, *, hint=""):
    """What is wrong with a checkpoint's array for parameter `name`: None when it is a finite
    float32/float64 array of `shape` (or of one of a list of shapes), else (TypeError or
    ValueError, message). Only float32 <-> float64 converts (converted_weight), on purpose."""
    shapes = [tuple(s) for s in shape] if isinstance(shape, list) else [tuple(shape)]
    if not isinstance(a, np.ndarray) or a.dtype not in FLOATS:
        return TypeError, f"{name!r} is {getattr(a, 'dtype', type(a).__name__)}, expected a float32 or float64 array"
    if a.shape not in shapes:
        return ValueError, f"{name!r} has shape {a.shape}, expected {' or '.join(map(str, shapes))}{hint}"
    if not all_finite(a):
        return ValueError, f"{name!r} contains NaN or inf"
    return None


def problems_error(what, problems):
    """One exception naming every problem, a list of (exception class, message): TypeError when
    every problem is a TypeError, else ValueError."""
    kind = TypeError if all(k is TypeError for k, _ in problems) else ValueError
    n = len(problems)
    return kind(f"{what}: {n} problem{'s' if n > 1 else ''}: " + "; ".join(m for _, m in problems))


def converted_weight(name, a, dtype):
    """A finite float array (weight_problem accepted it) -> (a C-ordered copy of dtype, None); or
    (None, (ValueError, message naming `name`)) when a value is beyond dtype's range (float64 ->
    float32 would make it inf)."""
    with np.errstate(over="ignore"):  # checked below
        out = np.array(a, dtype=dtype, order="C", copy=True)
    if not all_finite(out):
        return None, (ValueError, f"{name!r} holds a value of magnitude {float(np.max(np.abs(a))):.4g}, "
                                  f"beyond {np.dtype(dtype)}'s range")
    return out, None
