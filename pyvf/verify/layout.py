"""Token layouts: pyvf's tree layout and the flat layout most ports hold.

pyvf runs the transformer on the tree of docs/math.md §2: every activation is (R, B, N, L, ...) with
R tree rows (the trunk and its branches), B the batch, N views, L tokens per view. A port
usually holds one flat sequence per batch element, (B, T, ...) with T = R*N*L, ordered
[row][view][token]:

    flat[b, r*N*L + n*L + l, ...] == tree[r, b, n, l, ...]

tree_to_flat and flat_to_tree convert between the two (always a new C-contiguous array; the
caller's is never aliased). Any dtype: activations, gradients or integer tokens.

trace_from_flat converts a whole trace (the names of pyvf.models.transformer.TRACE_NAMES).
params_from_layout / params_to_layout convert parameter-shaped arrays (a port's gradients)
between pyvf's layout and the conventions load_official speaks (layout="tf" | "torch"), through
the models' own mechanism (model.layout_shapes, from_layout, to_layout: pyvf.models.io).
"""

import numpy as np

from .. import _checks


def tree_to_flat(x):
    """x (R, B, N, L, ...) -> (B, R*N*L, ...), the sequence ordered [row][view][token]."""
    R, B, N, L = x.shape[:4]
    flat = np.moveaxis(x, 1, 0)  # (B, R, N, L, ...)
    return flat.copy(order="C").reshape(B, R * N * L, *x.shape[4:])  # (B, T, ...)


def flat_to_tree(x, R, N, L):
    """x (B, T, ...) with T = R*N*L ordered [row][view][token] -> (R, B, N, L, ...)."""
    B, T = x.shape[:2]
    if T != R * N * L:
        raise ValueError(f"x has T = {T} tokens (shape {x.shape}), but R*N*L = {R}*{N}*{L} = {R * N * L}")
    tree = x.reshape(B, R, N, L, *x.shape[2:])  # (B, R, N, L, ...)
    return np.moveaxis(tree, 1, 0).copy(order="C")  # (R, B, N, L, ...)


_PER_HEAD = (".attn.q", ".attn.k", ".attn.v", ".attn.out", ".attn.lse")  # (R, B, H, N, L[, dh]) in pyvf


def trace_from_flat(trace, N, L, R=3):
    """A port's transformer trace (or its gradients) in the flat layout -> pyvf's tree layout,
    to compare with out.trace: name -> array (numpy, or torch tensors: read through .detach()).

    Whole-tree activations (embed.out and blocks.*) of shape (B, T, ...), T = R*N*L ordered
    [row][view][token], become (R, B, N, L, ...); the attention's per-head ones (blocks.j.attn.q,
    .k, .v, .out) given as (B, H, T, dh), and .lse as (B, H, T), become pyvf's (R, B, H, N, L[, dh]).
    Every other entry (the heads' rows (B, N, L, ...), losses) is returned as it is, as numpy.
    None values (a tensor without a gradient) are dropped. Always new arrays."""
    out = {}
    for name, a in trace.items():
        if a is None:
            continue
        a = _readable(name, a)
        if name == "embed.out" or name.startswith("blocks."):
            if name.endswith(_PER_HEAD) and a.ndim in (3, 4):  # (B, H, T[, dh]) -> (R, B, H, N, L[, dh])
                B, H, T = a.shape[:3]
                if T != R * N * L:
                    raise ValueError(f"{name!r} has shape {a.shape}: T = {T}, but R*N*L = {R * N * L}")
                a = np.moveaxis(a.reshape(B, H, R, N, L, *a.shape[3:]), 2, 0).copy(order="C")
            else:
                try:
                    a = flat_to_tree(a, R, N, L)
                except ValueError as e:
                    raise ValueError(f"{name!r}: {e}") from None
        else:
            a = np.array(a)
        out[name] = a
    return out

# ---------------------------------------------------------------------------------------
# parameter layouts: the conventions load_official / state_dict speak, for any parameter-shaped
# arrays (a port's gradients, to compare with backward()'s)


def _readable(name, a):
    """A numpy array, or a torch tensor (also one that requires grad) -> a numpy array."""
    a, problem = _checks.checkpoint_array(name, a)
    if problem is not None:
        raise problem[0](problem[1])
    return np.asarray(a)


def params_from_layout(model, arrays, layout):
    """arrays: name -> array (numpy, or torch tensors) -> a new dict in pyvf's layout (the
    published one, model.params'): the entries named as the model's parameters (Transformer:
    official names, `migt/` and `:0` optional) are transposed from `layout` as load_official
    does ("tf" | "torch" for a Transformer, "torch" | "tf" for a Codebook), every other entry
    (activations) passes unchanged. For a port's parameter gradients:

        pyvf.compare(pyvf.params_from_layout(model, port_grads, "torch"), model.backward(...))

    A parameter of the wrong shape for `layout` raises ValueError naming it."""
    shapes, out = model.parameter_shapes(), {}
    for raw, a in arrays.items():
        name = model.official_name(raw) if isinstance(raw, str) else raw
        out[raw] = model.from_layout(name, _readable(raw, a), layout) if name in shapes else a
    return out


def params_to_layout(model, arrays, layout):
    """The inverse of params_from_layout: arrays in pyvf's layout (e.g. backward()'s gradients)
    -> a new dict whose parameters are in `layout` (copies); other entries pass unchanged."""
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
