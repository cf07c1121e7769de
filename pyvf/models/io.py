"""How a model is described and how its weights get in and out, the same for Codebook and Transformer.

The layer table: each layer written once, as a row (Layer); the parameters (name -> (shape, role)),
the trace's names, the forward and teacher forcing's layers (pyvf.verify.teacher) are read off it.
A residual block is a row whose `body` (the main path) and `shortcut` are rows.

ModelWeights: the layouts load_official speaks (a layout differs from the published one only in
the parameters whose role ROLES lists for it), load_official itself, and the model file (save, load).
"""

import collections
import dataclasses
import json
import os
from collections.abc import Mapping

import numpy as np

from .. import _checks
from .._io import CheckpointError, atomic_savez, load_npz

__all__ = ["Layer", "ROLES", "ModelWeights", "parameters", "trace_order"]


@dataclasses.dataclass(frozen=True)
class Layer:
    """One row of a model's layer table."""
    name: str  # the published module's name; the trace name of its output
    kind: str  # the layer pair that computes it (the model's layer_forward / layer_backward)
    params: tuple = ()  # (suffix, shape, role) per parameter, in the layer pair's argument order;
    #                     the parameter is named prefix + suffix; role: see ROLES; a tied one is
    #                     listed by every row that reads it (the parameter table keeps the first)
    prefix: str = None  # the parameters' prefix; None: name (the codebook's torch names)
    stride: int = 1  # conv rows only
    padding: object = 0  # conv rows only: an int, or (left, right, top, bottom)
    body: tuple = ()  # kind "res": the main path's rows
    shortcut: tuple = ()  # kind "res": the shortcut's rows; () the identity
    module: str = None  # teacher forcing: the published module this row is part of; None: a layer itself
    calls: tuple = None  # teacher forcing: per call (((input, tree row), ...), output); None: one call
    #                      on the previous row's output, output `name`

    @property
    def param_names(self):
        """The full names of the row's own parameters, in params' order."""
        prefix = self.name if self.prefix is None else self.prefix
        return tuple(prefix + suffix for suffix, _, _ in self.params)


def leaves(rows):
    """The rows that compute something, in execution order: a residual block's body, then its shortcut."""
    for row in rows:
        if row.kind == "res":
            yield from leaves(row.body)
            yield from leaves(row.shortcut)
        else:
            yield row


def trace_order(rows):
    """Every row's name in execution order, a residual block's own (its output) after its children's."""
    names = []
    for row in rows:
        if row.kind == "res":
            names += trace_order(row.body) + trace_order(row.shortcut)
        names.append(row.name)
    return names


def parameters(rows):
    """Parameter name -> (shape, role) of every row, in execution order."""
    return {full: (tuple(shape), role) for row in leaves(rows) for full, (_, shape, role) in zip(row.param_names, row.params)}


Role = collections.namedtuple("Role", "layout shapes to_layout from_layout")

# role -> the layout holding it otherwise than the published one: its shapes there (from the
# published shape, the preferred first), published -> that layout, that layout -> published (a view)
ROLES = {
    # the codebook's nn.Conv2d kernels (out, in, kh, kw) <-> channels-last (kh, kw, in, out), TF/Flax
    "conv_kernel": Role("tf", lambda s: [(s[2], s[3], s[1], s[0])],
                        lambda p: p.transpose(2, 3, 1, 0), lambda a: a.transpose(3, 2, 0, 1)),
    # the transformer's TF Dense kernels (in, out) <-> nn.Linear's (out, in)
    "dense_kernel": Role("torch", lambda s: [(s[1], s[0])], lambda p: p.T, lambda a: a.T),
    # TF Dense biases (1, out) <-> nn.Linear's (out,) (the published (1, out) accepted too)
    "dense_bias": Role("torch", lambda s: [(s[1],), tuple(s)], lambda p: p.reshape(-1), lambda a: a.reshape(1, -1)),
}


def checkpoint_array(name, a):
    """A checkpoint's entry -> a numpy array (a torch tensor, on any device, through its .detach()),
    or `a` as given, for the caller to refuse; TypeError naming `name` for a bfloat16 tensor."""
    if hasattr(a, "detach") and not isinstance(a, np.ndarray):
        try:
            return a.detach().cpu().numpy()
        except (TypeError, RuntimeError) as e:
            raise TypeError(f"{name!r} ({type(a).__name__}) cannot become a numpy array: {e}") from None
    return a


class ModelWeights:
    """The weight mechanism Codebook and Transformer share. A model calls _describe in its
    __init__, then sets `params` (name -> array, published layout)."""

    LAYOUTS = {}  # layout -> what it holds (for messages); the published layout first
    BUFFERS = {}  # state entries besides the parameters -> shape, None for a count (the quantizer's)
    CONFIG = None  # the configuration class a model file is read into
    FILE_KIND = "model"  # how a model file's errors call it
    INPUTS = ()  # the names of forward's inputs (teacher forcing's first layer reads the first)
    META = ()  # attributes a model file keeps beside the weights (strings or None), as entries __name__
    source = None  # the file a model was loaded from (load sets it; messages name it)

    def _describe(self, config, layers, table=None):
        """Take the configuration, the layer table and its parameters (name -> (shape, role);
        default parameters(layers), the execution order); no forward yet."""
        self.config, self.dtype, self._cache = config, np.dtype(config.dtype), None
        self.layers = tuple(layers)
        self._param_table = parameters(self.layers) if table is None else dict(table)

    # the entry points' array check ---------------------------------------------------------

    def _check_array(self, name, a, shape, kind=None, hint=""):
        """An entry point's array: an ndarray of the model's dtype (kind "iu": of an integer dtype),
        non-empty, of `shape` (an int: that extent; a letter: any), finite -> its shape."""
        want = "integer" if kind else str(self.dtype)
        if not isinstance(a, np.ndarray) or (a.dtype.kind not in kind if kind else a.dtype != self.dtype):
            raise TypeError(f"{name} must be a numpy array of {want} (the model's), got "
                            f"{getattr(a, 'dtype', type(a).__name__)}{hint}")
        if a.ndim != len(shape) or a.size == 0 or any(s != n for s, n in zip(shape, a.shape) if not isinstance(s, str)):
            raise ValueError(f"{name} must have shape ({', '.join(map(str, shape))}), got {a.shape}{hint}")
        if not kind:
            _checks.finite(name, a)
        return a.shape

    # the layouts -------------------------------------------------------------------------

    def parameter_shapes(self):
        """Parameter name -> shape, in the published layout and order (not the buffers)."""
        return {name: shape for name, (shape, _) in self._param_table.items()}

    def check_layout(self, layout):
        if layout not in self.LAYOUTS:
            raise ValueError(f"layout must be one of {tuple(self.LAYOUTS)}, got {layout!r}")
        return layout

    def _role(self, name, layout):
        """The Role that converts parameter `name` in `layout`, None where it is held as published."""
        layout, role = self.check_layout(layout), ROLES.get(self._param_table[name][1])
        return role if role is not None and role.layout == layout else None

    def layout_shapes(self, name, layout):
        """The shapes parameter `name` may have in `layout`, the preferred one first."""
        role, shape = self._role(name, layout), self._param_table[name][0]
        return [shape] if role is None else role.shapes(shape)

    def from_layout(self, name, a, layout):
        """An array of parameter `name` in `layout` -> the published layout (a view); ValueError
        naming it for a shape not in layout_shapes(name, layout)."""
        role, shapes = self._role(name, layout), self.layout_shapes(name, layout)
        if tuple(np.shape(a)) not in shapes:
            raise ValueError(f"{name!r} has shape {tuple(np.shape(a))}, expected {' or '.join(map(str, shapes))} "
                             f"in layout={layout!r}")
        return a if role is None else role.from_layout(a)

    def to_layout(self, name, p, layout):
        """An array of parameter `name` in the published layout -> a C-contiguous copy in `layout`."""
        role = self._role(name, layout)
        return np.array(p if role is None else role.to_layout(p), order="C", copy=True)

    def state_dict(self, layout=None):
        """Official name -> array (copies), the parameters in `layout` (None: the published one),
        then the buffers."""
        layout = next(iter(self.LAYOUTS)) if layout is None else layout
        return {**{name: self.to_layout(name, p, layout) for name, p in self.params.items()}, **self._buffers()}

    def _buffers(self):
        return {}

    # loading -----------------------------------------------------------------------------

    def _entry(self, raw, name, a, layout):
        """One checkpoint entry named raw -> a count (int), or a new C-ordered array in the published
        layout and the model's dtype, finite there too (float64 -> float32 may overflow)."""
        a = checkpoint_array(raw, a)
        if name in self.BUFFERS and self.BUFFERS[name] is None:  # a torch checkpoint may hold it as a float
            n = np.asarray(a)
            if n.shape != () or n.dtype.kind not in "iuf" or not (np.isfinite(n) and n == np.floor(n)
                                                                 and 0 <= int(n) <= np.iinfo(np.int64).max):
                raise ValueError(f"{raw!r} must be a non-negative integer count that int64 holds, got {a!r}")
            return int(n)
        if not isinstance(a, np.ndarray) or a.dtype not in _checks.FLOATS:
            raise TypeError(f"{raw!r} is {getattr(a, 'dtype', type(a).__name__)}, expected a float32 or float64 array")
        if name in self._param_table:
            a = self.from_layout(name, a, layout)  # ValueError for a shape it does not have in layout
        elif a.shape != self.BUFFERS[name]:
            raise ValueError(f"{raw!r} has shape {a.shape}, expected {self.BUFFERS[name]}")
        with np.errstate(over="ignore"):  # checked below
            out = np.array(a, self.dtype, order="C")
        if not _checks.all_finite(out):
            raise ValueError(f"{raw!r} contains NaN or inf, or a value beyond {self.dtype}'s range")
        return out

    def load_official(self, weights, *, layout=None):
        """Load a dict name -> array (or torch tensor) named as the published checkpoint (prefixes
        optional: official_name), every parameter and buffer, the parameters in `layout` (None: the
        published one; stated, so that a square kernel is never silently transposed). The first
        wrong entry raises naming its key; nothing is assigned before all pass."""
        layout = self.check_layout(next(iter(self.LAYOUTS)) if layout is None else layout)
        if not isinstance(weights, Mapping):
            raise TypeError(f"load_official: weights must be a dict name -> array, got {type(weights).__name__}")
        wanted = [*self._param_table, *self.BUFFERS]
        loaded, given_as = {}, {}
        for raw, arr in weights.items():
            name = self.official_name(raw) if isinstance(raw, str) else raw
            if name not in wanted:
                raise ValueError(f"load_official: unexpected key {raw!r} (not in this configuration)")
            if name in given_as:
                raise ValueError(f"load_official: {name!r} given twice (as {given_as[name]!r} and {raw!r})")
            given_as[name] = raw
            loaded[name] = self._entry(raw, name, arr, layout)
        missing = [k for k in wanted if k not in given_as]
        if missing:
            raise ValueError(f"load_official: {len(missing)} entries missing: {missing}")
        self.params = {name: loaded[name] for name in self._param_table}  # the published order
        self._set_buffers({name: loaded[name] for name in self.BUFFERS})

    def _set_buffers(self, buffers):
        """Assign the checked BUFFERS entries. No buffers here."""

    # the model file ----------------------------------------------------------------------

    def save(self, path):
        """Write the configuration (JSON, entry __config__), the META strings (entries __name__) and
        state_dict() (the published layout) to one .npz, atomically; ".npz" appended when missing
        (as np.savez does). Returns the path written."""
        meta = {f"__{k}__": str(getattr(self, k)) for k in self.META if getattr(self, k, None) is not None}
        path = os.fsdecode(os.fspath(path))
        if not path.endswith(".npz"):
            path += ".npz"
        atomic_savez(path, __config__=json.dumps(dataclasses.asdict(self.config)), **meta, **self.state_dict())
        return path

    @classmethod
    def load(cls, path):
        """Read a model written by save() (path as given). A missing file raises FileNotFoundError;
        anything else wrong, pyvf._io.CheckpointError (a ValueError) naming the file and the entry."""
        what, name, config_cls = cls.FILE_KIND, os.fspath(path), cls.CONFIG
        arrays = load_npz(path, what, required=("__config__",))
        later = getattr(config_cls, "ADDED_FIELDS", ())  # newer than some files: their defaults are what those did
        try:
            fields = json.loads(str(arrays.pop("__config__")))
            missing = [f.name for f in dataclasses.fields(config_cls) if f.init and f.name not in {*fields, *later}]
            if missing:  # never the other defaults: they may be another model than the file's
                raise ValueError(f"it lacks the fields {missing}")
            model = cls(config_cls(**fields))
        except (TypeError, ValueError, AttributeError) as e:
            raise CheckpointError(f"{what} {name}: entry '__config__' is not a {config_cls.__name__} written by "
                                  f"save(): {e}") from e
        meta = {k: str(arrays.pop(f"__{k}__")) for k in cls.META if f"__{k}__" in arrays}  # absent: older file
        try:
            model.load_official(arrays)
        except (TypeError, ValueError) as e:
            raise CheckpointError(f"{what} {name}: {e}") from e
        for k, v in meta.items():
            setattr(model, k, v)
        model.source = name
        return model
