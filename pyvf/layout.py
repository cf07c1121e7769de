"""Token layouts: pyvf's tree layout and the flat layout most ports hold.

pyvf runs the transformer on the tree of SPEC.md: every activation is (R, B, N, L, ...) with
R tree rows (the trunk and its branches), B the batch, N views, L tokens per view. A port
usually holds one flat sequence per batch element, (B, T, ...) with T = R*N*L, ordered
[row][view][token]:

    flat[b, r*N*L + n*L + l, ...] == tree[r, b, n, l, ...]

tree_to_flat and flat_to_tree convert between the two (always a new C-contiguous array; the
caller's is never aliased). Any dtype: activations, gradients or integer tokens.
"""

import numpy as np

from . import _checks


def tree_to_flat(x):
    """x (R, B, N, L, ...) -> (B, R*N*L, ...), the sequence ordered [row][view][token]."""
    if not isinstance(x, np.ndarray):
        raise TypeError(f"x must be a numpy.ndarray of shape (R, B, N, L, ...), got {type(x).__name__}")
    if x.ndim < 4:
        raise ValueError(f"x must have shape (R, B, N, L, ...) (at least 4 dimensions), got shape {x.shape}")
    R, B, N, L = x.shape[:4]
    flat = np.moveaxis(x, 1, 0)  # (B, R, N, L, ...)
    return flat.copy(order="C").reshape(B, R * N * L, *x.shape[4:])  # (B, T, ...)


def flat_to_tree(x, R, N, L):
    """x (B, T, ...) with T = R*N*L ordered [row][view][token] -> (R, B, N, L, ...)."""
    R = _checks.integer("R", R, lo=1)
    N = _checks.integer("N", N, lo=1)
    L = _checks.integer("L", L, lo=1)
    if not isinstance(x, np.ndarray):
        raise TypeError(f"x must be a numpy.ndarray of shape (B, T, ...), got {type(x).__name__}")
    if x.ndim < 2:
        raise ValueError(f"x must have shape (B, T, ...) (at least 2 dimensions), got shape {x.shape}")
    B, T = x.shape[:2]
    if T != R * N * L:
        raise ValueError(f"x has T = {T} tokens (shape {x.shape}), but R*N*L = {R}*{N}*{L} = {R * N * L}")
    tree = x.reshape(B, R, N, L, *x.shape[2:])  # (B, R, N, L, ...)
    return np.moveaxis(tree, 1, 0).copy(order="C")  # (R, B, N, L, ...)
