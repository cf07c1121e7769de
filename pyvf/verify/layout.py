"""Token layouts: pyvf's tree layout (R, B, N, L, ...) and the flat one most ports hold, (B, T, ...)
with T = R*N*L ordered [row][view][token]: flat[b, r*N*L + n*L + l] == tree[r, b, n, l]; and
parameter layouts: a port's parameter-shaped arrays (its gradients) to and from the conventions
load_official speaks, through the models' own from_layout / to_layout (pyvf.models.io).
"""

import numpy as np

from ..models.io import checkpoint_array


def tree_to_flat(x):
    """x (R, B, N, L, ...) -> (B, R*N*L, ...), a new C-contiguous array."""
    R, B, N, L = x.shape[:4]
    flat = np.moveaxis(x, 1, 0)  # (B, R, N, L, ...)
    return flat.copy(order="C").reshape(B, R * N * L, *x.shape[4:])  # (B, T, ...)


def flat_to_tree(x, R, N, L):
    """x (B, T, ...) with T = R*N*L ordered [row][view][token] -> (R, B, N, L, ...)."""
    tree = x.reshape(x.shape[0], R, N, L, *x.shape[2:])  # (B, R, N, L, ...)
    return np.moveaxis(tree, 1, 0).copy(order="C")  # (R, B, N, L, ...)


_PER_HEAD = (".attn.q", ".attn.k", ".attn.v", ".attn.out", ".attn.lse")  # (R, B, H, N, L[, dh]) in pyvf


def trace_from_flat(trace, N, L, R=3):
    """A port's transformer trace (or its gradients) in the flat layout -> pyvf's, new arrays:
    embed.out and blocks.* (B, T, ...) -> (R, B, N, L, ...); the per-head blocks.j.attn.q, .k, .v,
    .out (B, H, T, dh) and .lse (B, H, T) -> (R, B, H, N, L[, dh]); other entries as numpy; None
    values (a tensor without a gradient) dropped."""
    out = {}
    for name, a in trace.items():
        if a is None:
            continue
        a = _readable(name, a)
        if name == "embed.out" or name.startswith("blocks."):
            try:  # numpy's reshape refuses T != R*N*L; the error names the entry
                if name.endswith(_PER_HEAD) and a.ndim in (3, 4):  # (B, H, T[, dh]) -> (R, B, H, N, L[, dh])
                    a = np.moveaxis(a.reshape(*a.shape[:2], R, N, L, *a.shape[3:]), 2, 0).copy(order="C")
                else:
                    a = flat_to_tree(a, R, N, L)
            except ValueError as e:
                raise ValueError(f"{name!r}: {e}") from None
        else:
            a = np.array(a)
        out[name] = a
    return out

def _readable(name, a):
    """A numpy array, or a torch tensor (also one that requires grad) -> a numpy array."""
    return np.asarray(checkpoint_array(name, a))


def params_from_layout(model, arrays, layout):
    """arrays: name -> array (or torch tensor) -> a new dict whose entries named as the model's
    parameters are converted from `layout` to pyvf's as load_official does; other entries pass
    unchanged. E.g. pyvf.compare(pyvf.params_from_layout(model, port_grads, "torch"), model.backward())."""
    shapes, out = model.parameter_shapes(), {}
    for raw, a in arrays.items():
        name = model.official_name(raw) if isinstance(raw, str) else raw
        out[raw] = model.from_layout(name, _readable(raw, a), layout) if name in shapes else a
    return out


def params_to_layout(model, arrays, layout):
    """The inverse of params_from_layout (copies)."""
    shapes, out = model.parameter_shapes(), {}
    for raw, a in arrays.items():
        name = model.official_name(raw) if isinstance(raw, str) else raw
        if name in shapes:
            a = _readable(raw, a)
            if a.shape != shapes[name]:
                raise ValueError(f"{raw!r} has shape {a.shape}, expected parameter {name!r}'s {shapes[name]}")
            a = model.to_layout(name, a, layout)
        out[raw] = a
    return out
