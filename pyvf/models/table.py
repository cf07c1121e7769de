"""A model's layer table: each layer written once, as a row; its parameters (name -> (shape, role)),
its trace's names, its forward and teacher forcing's layers (pyvf.verify.teacher) are read off it.
A residual block is a row whose `body` (the main path) and `shortcut` are rows.
"""

import dataclasses


@dataclasses.dataclass(frozen=True)
class Layer:
    """One row of a model's layer table."""
    name: str  # the published module's name; the trace name of its output
    kind: str  # the layer pair that computes it (the model's layer_forward / layer_backward)
    params: tuple = ()  # (suffix, shape, role) per parameter, in the layer pair's argument order;
    #                     the parameter is named prefix + suffix; role: see pyvf.models.io.ROLES
    prefix: str = None  # the parameters' prefix; None: name (the codebook's torch names)
    stride: int = 1  # conv rows only
    padding: object = 0  # conv rows only: an int, or (left, right, top, bottom)
    body: tuple = ()  # kind "res": the main path's rows
    shortcut: tuple = ()  # kind "res": the shortcut's rows; () the identity
    module: str = None  # teacher forcing: the published module this row is part of; None: a layer itself
    calls: tuple = None  # teacher forcing: per call (((input, tree row), ...), output); None: one call
    #                      on the previous row's output, output `name`
    reads: tuple = ()  # parameters of other rows this one also reads (tied weights), by full name

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
