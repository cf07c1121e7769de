"""Each model is described once, by its layer table (pyvf/models/io.py): a changed table changes
the forward and teacher forcing alike. The oracle is independent of the table: the torch port of
pyvf/verify/torch_ports.py, written from docs/math.md with its own strides and paddings."""

import dataclasses

import torch

import pyvf
import pyvf.verify.teacher as teacher
from pyvf.models import codebook
from pyvf.verify.torch_ports import CodebookPort
from test_codebook_trace import SMALL, images_for, random_codebook
from test_teacher import codebook_trace


def _replaced(rows, name, changes):
    """-> (rows with row `name` changed, at any depth: a residual block's body or shortcut; how many)."""
    out, found = [], 0
    for row in rows:
        if row.name == name:
            row, found = dataclasses.replace(row, **changes), found + 1
        elif row.kind == "res":
            (body, n1), (shortcut, n2) = _replaced(row.body, name, changes), _replaced(row.shortcut, name, changes)
            row, found = dataclasses.replace(row, body=body, shortcut=shortcut), found + n1 + n2
        out.append(row)
    return tuple(out), found


def replace_row(rows, which, **changes):
    """The table with the one row named `which` changed (dataclasses.replace's keywords)."""
    rows, found = _replaced(rows, which, changes)
    assert found == 1, f"{found} rows named {which!r}"
    return rows



def test_a_changed_codebook_padding_is_read_by_the_forward_and_teacher_forcing(rng):
    """The Downsample padded (1, 1, 1, 1) instead of the published (0, 1, 0, 1) (docs/math.md §4):
    the table's padding is what pyvf runs and what teacher forcing's VJP uses, so the port padded
    (1, 1, 1, 1) now agrees everywhere and the published port is wrong at exactly that layer."""
    cfg = pyvf.CodebookConfig(**SMALL, dtype="float64")
    rows = replace_row(codebook.layer_table(cfg), "encoder.down.0.downsample.conv", padding=(1, 1, 1, 1))
    cb = random_codebook(cfg, rng)
    other = pyvf.Codebook(cfg, layers=rows)
    other.load_official(cb.state_dict())
    assert other.parameter_shapes() == cb.parameter_shapes()
    x = images_for(cfg, rng)
    drec = rng.normal(size=x.shape)
    ports = {}
    for bug in (None, "padding"):  # the published port, and the one padded (1, 1, 1, 1)
        ports[bug] = CodebookPort(cfg, bug=bug).double().eval()  # eval: no EMA step in the port's quantizer
        ports[bug].load_state_dict({k: torch.tensor(v) for k, v in cb.state_dict().items()})
    out = other.forward(x, trace=True)
    for bug, first in ((None, "encoder.down.0.downsample.conv"), ("padding", None)):
        assert pyvf.compare(codebook_trace(ports[bug], x, drec)[0], out.trace).first == first
    # (the published port against the published table: tests/test_teacher.py's padding bug)
    tf = pyvf.teacher_force(other, x, teacher.torch_modules(ports["padding"], other),
                            params=dict(ports["padding"].named_parameters()), upstream=dict(drec=drec))
    assert tf.wrong == [], str(tf)
