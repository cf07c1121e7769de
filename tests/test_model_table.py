"""Each model is described once, by its layer table (pyvf/models/table.py): a changed table changes
the parameters, the trace and teacher forcing alike. The oracles are independent of the table: the
default model run on the same weights (a renamed layer computes exactly what it did), and the torch
ports of pyvf/verify/torch_ports.py, written from docs/math.md with their own strides and paddings."""

import dataclasses

import numpy as np
import pytest
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


def renamed(names, renames):
    """Layer names and their parameters' names ('a.weight' -> 'b.weight' for a renamed 'a')."""
    def one(n):
        layer, _, suffix = n.rpartition(".")
        return renames[n] if n in renames else renames[layer] + "." + suffix if layer in renames else n
    return [one(n) for n in names]


def renamed_params(d, renames):
    return dict(zip(renamed(d, renames), d.values()))


# ---------------------------------------------------------------------------------------
# the codebook

# a top-level layer and one inside a residual block's body
RENAMES = {"encoder.conv_in": "encoder.stem", "decoder.up.1.block.0.conv1": "decoder.up.1.block.0.conv_a"}


def codebook_pair(rng, layers):
    """(the default codebook, one with `layers`, holding the same weights)."""
    cfg = pyvf.CodebookConfig(**SMALL, dtype="float64")
    cb = random_codebook(cfg, rng)
    other = pyvf.Codebook(cfg, layers=layers)
    other.load_official(renamed_params(cb.state_dict(), RENAMES))
    return cb, other


def renamed_table(cfg):
    rows = codebook.layer_table(cfg)
    for old, new in RENAMES.items():
        rows = replace_row(rows, old, name=new)
    return rows


def test_a_renamed_codebook_layer_is_renamed_everywhere(rng):
    cfg = pyvf.CodebookConfig(**SMALL, dtype="float64")
    cb, other = codebook_pair(rng, renamed_table(cfg))
    # the parameters: same shapes, same order, renamed
    want = renamed_params(cb.parameter_shapes(), RENAMES)
    assert list(other.parameter_shapes().items()) == list(want.items())
    assert "encoder.stem.weight" in other.params and "encoder.conv_in.weight" not in other.params
    assert set(other.state_dict()) == set(renamed_params(cb.state_dict(), RENAMES))
    # the trace and the forward walk: the same computation, bit for bit, under the new names
    x = images_for(cfg, rng)
    drec = rng.normal(size=x.shape)
    a, b = cb.forward(x, trace=True), other.forward(x, trace=True)
    assert list(b.trace) == renamed(list(a.trace), RENAMES) == other.trace_names()
    for n, v in a.trace.items():
        np.testing.assert_array_equal(b.trace[RENAMES.get(n, n)], v, err_msg=n)
    ga, gb = cb.backward(drec=drec), other.backward(drec=drec)
    assert list(gb) == renamed(ga, RENAMES)
    for n, v in renamed_params(ga, RENAMES).items():
        np.testing.assert_array_equal(gb[n], v, err_msg=n)
    # the layouts follow the table's roles: the renamed conv kernel is transposed for "tf"
    w = other.params["encoder.stem.weight"]
    assert other.to_layout("encoder.stem.weight", w, "tf").shape == w.shape[2:] + w.shape[1::-1]
    # the old names are now unexpected, the new ones missing
    with pytest.raises(ValueError,
                       match=r"missing: \['encoder.stem.weight'.*unexpected names .*'encoder.conv_in.weight'"):
        other.load_official(cb.state_dict())
    # teacher forcing: its layers carry the new names; the port's modules keep the published ones
    names = teacher.layer_names(other)
    assert names == renamed(teacher.layer_names(cb), RENAMES)
    port = CodebookPort(cfg).double()
    port.load_state_dict({k: torch.tensor(v) for k, v in cb.state_dict().items()})
    back = {v: k for k, v in RENAMES.items()}
    params = renamed_params(dict(port.named_parameters()), RENAMES)
    tf = pyvf.teacher_force(other, x, teacher.torch_modules(port, other, path=lambda n: back.get(n, n)),
                            params=params, upstream=dict(drec=drec))
    assert tf.wrong == [] and tf.unchecked == [], str(tf)
    assert {r.name for r in tf["encoder.stem"].backward.rows} == {"encoder.stem.weight", "encoder.stem.bias"}
    assert {"d decoder.up.1.block.0.norm1", "decoder.up.1.block.0.conv_a.weight"} <= \
        {r.name for r in tf["decoder.up.1.block.0.conv_a"].backward.rows}


def test_a_changed_codebook_padding_is_read_by_the_forward_and_teacher_forcing(rng):
    """The Downsample padded (1, 1, 1, 1) instead of the published (0, 1, 0, 1) (docs/math.md §4):
    the table's padding is what pyvf runs and what teacher forcing's VJP uses, so the port padded
    (1, 1, 1, 1) now agrees everywhere and the published port is wrong at exactly that layer."""
    cfg = pyvf.CodebookConfig(**SMALL, dtype="float64")
    rows = replace_row(codebook.layer_table(cfg), "encoder.down.0.downsample.conv", padding=(1, 1, 1, 1))
    cb = random_codebook(cfg, rng)
    other = pyvf.Codebook(cfg, layers=rows)
    other.load_official(cb.state_dict())
    assert other.parameter_shapes() == cb.parameter_shapes() and other.trace_names() == cb.trace_names()
    x = images_for(cfg, rng)
    drec = rng.normal(size=x.shape)
    ports = {}
    for bug in (None, "padding"):  # the published port, and the one padded (1, 1, 1, 1)
        ports[bug] = CodebookPort(cfg, bug=bug).double().eval()  # eval: no EMA step in the port's quantizer
        ports[bug].load_state_dict({k: torch.tensor(v) for k, v in cb.state_dict().items()})
    out = other.forward(x, trace=True)
    grads = other.backward(drec=drec)
    mine, mine_grads = codebook_trace(ports["padding"], x, drec)
    report = pyvf.compare(mine, out.trace)
    assert report.first is None and len(report.rows) > 40, str(report)
    assert pyvf.compare(mine_grads, grads, atol=1e-10 * max(np.abs(v).max() for v in grads.values())).first is None
    assert pyvf.compare(codebook_trace(ports[None], x, drec)[0], out.trace).first == "encoder.down.0.downsample.conv"
    for bug, wrong in ((None, ["encoder.down.0.downsample"]), ("padding", [])):
        tf = pyvf.teacher_force(other, x, teacher.torch_modules(ports[bug], other),
                                params=dict(ports[bug].named_parameters()), upstream=dict(drec=drec))
        assert tf.wrong == wrong, str(tf)
