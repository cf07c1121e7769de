"""Argument checks shared by pyvf's modules: every error names the argument and says what was
expected; nothing is cast or copied silently. Shape rules stay with the function that has them.
Also the checks of a checkpoint's entries (checkpoint_array, weight_problem, converted_weight, problems_error:
every wrong entry named in one error), which pyvf.models.io's loader and the quantizer share."""

import numpy as np

from . import _core

FLOATS = (np.dtype(np.float32), np.dtype(np.float64))


def _masked(name, a):
    """The message refusing `a` when it is a masked array with masked elements, else None: the
    kernels (and NumPy's indexing, np.array, np.ascontiguousarray) read the data under the mask as
    values, a silently wrong answer. A masked array with nothing masked is its data. Free for a
    plain ndarray; a masked array's mask is scanned (bool, one byte an element)."""
    if isinstance(a, np.ma.MaskedArray) and np.ma.is_masked(a):
        return (f"{name} is a masked array with masked elements: pyvf would compute with the values under "
                "the mask; fill them (np.ma.filled) or leave those elements out")
    return None


def plain_array(name, a):
    """Refuse the ndarray subclasses whose values or operators are not an ndarray's (TypeError):
    masked elements (_masked), and np.matrix, which stays 2-D under indexing and makes * a
    matrix product (quat_mul of a matrix returned a (1, 4) array for (3, 4) inputs, and NumPy's
    np.stack of the matrices it made corrupted the heap). Other subclasses (np.memmap, ones with
    __array_finalize__) are plain arrays to pyvf. float_array and int_array call it; a check of
    its own (uint8 pictures, say) calls it after its isinstance test. Costs no pass over a plain
    ndarray's data."""
    if isinstance(a, np.matrix):
        raise TypeError(f"{name} is a numpy.matrix (2-D only, * a matrix product): pass np.asarray({name})")
    problem = _masked(name, a)
    if problem:
        raise TypeError(problem)


def all_finite(a):
    """True when every element of the float array a is finite; a C-contiguous array is scanned by
    the C++ kernel, which allocates nothing (np.isfinite would allocate a bool array as large)."""
    if isinstance(a, np.ndarray) and a.dtype in FLOATS and a.flags.c_contiguous:
        return _core.all_finite(a)
    return bool(np.isfinite(a).all())


def float_array(name, a, like=None, like_name="x"):
    """a must be a float32 or float64 ndarray, of like's dtype when like is given."""
    if not isinstance(a, np.ndarray):
        raise TypeError(f"{name} must be a numpy.ndarray, got {type(a).__name__}")
    plain_array(name, a)
    if a.dtype not in FLOATS:
        if a.dtype.newbyteorder("=") in FLOATS:  # the kernels would read its bytes as native ones: refused too
            raise TypeError(f"{name} is {a.dtype.newbyteorder('=')} in non-native byte order ({a.dtype.str}): the "
                            f"kernels read native bytes; pass {name}.astype({name}.dtype.newbyteorder('='))")
        raise TypeError(f"{name} must be float32 or float64, got {a.dtype} (pyvf never casts silently)")
    if like is not None and a.dtype != like.dtype:
        raise TypeError(f"{name} is {a.dtype} but {like_name} is {like.dtype}: both must share one dtype "
                        "(pyvf never casts silently)")
    return a


def finite_float(name, a, like=None, like_name="x"):
    """a: a finite float32/float64 ndarray (of like's dtype, when given); errors name the argument."""
    float_array(name, a, like, like_name)
    return finite(name, a)


def c_order(a):
    """a itself when C-contiguous, else a C-ordered copy (a layout copy, never a cast): the C++
    kernels take C order only. Not np.ascontiguousarray alone: that turns a 0-d array into
    shape (1,), while a 0-d array is always contiguous and returned as it is."""
    return a if a.flags.c_contiguous else np.ascontiguousarray(a)


def contiguous(name, a):
    if not a.flags.c_contiguous:
        raise ValueError(f"{name} is not C-contiguous (a transposed or sliced view?): "
                         f"pass np.ascontiguousarray({name})")
    return a


def finite(name, a):
    """a's values are all finite numbers; masked elements are not values (_masked): TypeError."""
    problem = _masked(name, a)
    if problem:  # the arrays checked here without float_array first (a model's images, poses)
        raise TypeError(problem)
    if not all_finite(a):
        raise ValueError(f"{name} contains NaN or inf")
    return a


def int_array(name, a):
    """a must be an ndarray of a signed or unsigned integer dtype (bool, float, object refused)."""
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
    """x: a Python or NumPy integer (not bool), >= 1 -> int (TypeError, or ValueError saying
    "must be a positive integer", naming the argument)."""
    x = integer(name, x)
    if x < 1:
        raise ValueError(f"{name} must be a positive integer, got {x!r}")
    return x


def real(name, x, lo=None, hi=None, lo_open=False, hi_open=False):
    """x: a finite real number (Python or numpy scalar, not bool), in [lo, hi] (open ends where
    asked) -> float."""
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name} must be a real number, got {type(x).__name__} {x!r}")
    x = float(x)
    ok = np.isfinite(x)
    if ok and lo is not None:
        ok = x > lo if lo_open else x >= lo
    if ok and hi is not None:
        ok = x < hi if hi_open else x <= hi
    if not ok:
        rng = (f"{'(' if lo_open else '['}{lo if lo is not None else '-inf'}, "
               f"{hi if hi is not None else 'inf'}{')' if hi_open else ']'}")
        raise ValueError(f"{name} must be finite and in {rng}, got {x!r}")
    return x


def finite_result(what, a, name="the result"):
    """Raise ValueError when `a`, computed from finite inputs, is not finite: it overflowed."""
    if not all_finite(a):
        raise ValueError(f"{what}: {name} is not finite: it overflowed {a.dtype} "
                         "(inputs too large for the dtype; rescale them, or use float64)")
    return a


def checkpoint_array(name, a):
    """A checkpoint's entry -> (numpy array or `a` unchanged, problem or None). Anything with
    `.detach()` (a torch tensor, also one that requires grad, on any device) becomes
    `a.detach().cpu().numpy()`, which keeps its dtype (pyvf never imports torch); a tensor numpy
    cannot hold (bfloat16) is a TypeError problem naming `name`. Anything else is returned
    as it is, for weight_problem to judge: nothing is cast (np.asarray is never called)."""
    if hasattr(a, "detach") and not isinstance(a, np.ndarray):
        try:
            return a.detach().cpu().numpy(), None
        except (TypeError, RuntimeError, AttributeError) as e:
            return a, (TypeError, f"{name!r} ({type(a).__name__}) cannot become a numpy array: {e}")
    return a, None


def weight_problem(name, a, shape, *, hint=""):
    """What is wrong with a checkpoint's array for parameter `name` (a str): None when it is a
    finite float32/float64 array of `shape`, else (TypeError or ValueError, message). float16,
    longdouble, integer, bool, complex and object arrays are refused: only float32 <-> float64
    converts, on purpose (see weight). `shape` may be a list of alternative shapes (a list of
    tuples); `hint` is appended to a wrong shape's message (e.g. the layout expected). Either byte
    order is accepted: converted_weight, which follows, makes the native copy (exact). A masked
    array with masked elements is a TypeError problem (np.array would load the data under the mask)."""
    alternatives = isinstance(shape, list) and len(shape) > 0 and all(isinstance(s, (tuple, list)) for s in shape)
    shapes = [tuple(s) for s in shape] if alternatives else [tuple(shape)]
    if not isinstance(a, np.ndarray):
        return TypeError, f"{name!r} is a {type(a).__name__}, not a numpy array"
    if a.dtype.newbyteorder("=") not in FLOATS:  # a big-endian float32 is float32 in the file's byte order
        return TypeError, f"{name!r} has dtype {a.dtype}, expected a float array (float32 or float64)"
    problem = _masked(repr(name), a)
    if problem:
        return TypeError, problem
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
    """A checkpoint's finite float array (one weight_problem accepted) -> (a C-ordered copy of
    dtype, None); or (None, (ValueError, message naming `name`)) when a value lies beyond
    dtype's range, so that the conversion (float64 -> float32) would make it inf. Nothing is
    assigned by this: the caller loads only when no entry has a problem."""
    dtype = np.dtype(dtype)
    with np.errstate(over="ignore"):  # checked below
        out = np.array(a, dtype=dtype, order="C", copy=True)
    if not all_finite(out):
        big = float(np.max(np.abs(a)))
        return None, (ValueError, f"{name!r} holds a value of magnitude {big:.4g}, beyond {dtype}'s range "
                                  f"(largest {float(np.finfo(dtype).max):.4g}): it would become inf in {dtype}")
    return out, None
