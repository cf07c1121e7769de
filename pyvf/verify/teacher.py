"""Teacher forcing: run a port's own layers, each on **pyvf's** input to that layer, and compare
each output (and, given upstream gradients, each layer's VJP) with pyvf's. A bug then shows at
exactly the layer that has it, instead of in everything after it (as in pyvf.compare's table).

    report = pyvf.teacher_force(model, (tokens, poses), layers,          # Transformer
                                params=params, layout="torch", upstream=dict(dlogits=dl, dpose=dp))
    report = pyvf.teacher_force(cb, images, layers, params=params, upstream=dict(drec=d))  # Codebook
    report.wrong      # ["blocks.1.attn"]: the layers whose output or VJP is over tolerance
    print(report)     # one row per layer, then every wrong layer's comparison

layers: a dict layer name -> callable (a function or a torch nn.Module) taking the layer's
inputs as torch tensors and returning its output (a tuple's first element is taken);
`torch_modules(port, model)` builds it from a module whose children are named as the published
modules. Layers without a callable are listed as not checked. params (for the backward): the
port's own parameter tensors by pyvf's official name, in `layout`; each layer's parameters'
gradients are compared with pyvf's contribution of that layer (a tied weight, wte, gets one per
layer that reads it).

The layers (`layer_table(model)`, `layer_names(model)`, in execution order) are read off the
model's own layer table (model.layers, pyvf.models.table): each a function of its inputs only.
The transformer's: embed (tokens, poses -> embed.out), per block ln_1, attn (the branching
attention, ln_1 -> attn.c_proj), ln_2 (resid_1 -> ln_2), mlp (ln_2 -> mlp.c_proj); ln_f
(called twice: rows 1 and 2 of the last block's output), logits (the tied wte), pose_head. The
codebook's: every module of the published tree that is a leaf of the computation (convs,
norm+swish, AttnBlocks, Downsample, Upsample, quantize; with train=True the port's EMA step runs
too). The residual additions and the losses are not layers (pyvf.compare on a trace covers them);
the model's inputs get no gradient.

Transformer activations of the whole tree, pyvf's (R, B, N, L, d), reach a callable flat:
(B, T, d), T = R*N*L ordered [row][view][token], as most ports hold them; the heads' rows stay
(B, N, L, ...); codebook activations are NCHW, in pyvf's dtype (run pyvf in the port's dtype: compare's tolerances apply per layer).

Backward: upstream holds model.backward's seeds (a Codebook's drec only: the quantize layer's
commitment loss is a second output no layer VJP sees). pyvf's gradient of each layer's output
seeds the port's VJP (torch autograd, (out * dout).sum().backward()), compared with pyvf's own
layer pair run on the same input: the gradient of each float input ("d <input name>") and of
each parameter. The parameters' .grad are cleared per layer (and left holding the last layer's).
"""

import dataclasses

import numpy as np

from ..models import transformer as _transformer
from .compare import Comparison, compare
from .layout import flat_to_tree, tree_to_flat

__all__ = ["Layer", "LayerCheck", "TeacherReport", "layer_names", "layer_table", "teacher_force", "torch_modules"]

MODEL_INPUTS = ("tokens", "poses", "images")


@dataclasses.dataclass(frozen=True)
class Layer:
    name: str  # the key of `layers`
    kind: str  # how pyvf computes it (its reference pair): "layernorm", "attention", "conv", ...
    calls: tuple  # per call: (inputs, output); inputs a tuple of (name, row): a trace name or a
    #               model input ("tokens", "poses", "images"), row None or the tree row taken
    params: tuple  # official parameter names the layer reads
    rows: tuple = ()  # the model's layer-table rows it runs (model.layers), in order


def _label(name, row):
    return name if row is None else f"{name}[{row}]"


# ---------------------------------------------------------------------------------------
# the layers of each model


def _collect(rows, prev, out):
    """Append the teacher-forcing layers of the table's rows to out; prev: the input of the first
    row without its own calls -> the last output's name."""
    for row in rows:
        if row.kind == "res":  # a residual block: its rows are layers, its sum (shortcut + h) is not
            _collect(row.body, prev, out)
            _collect(row.shortcut, prev, out)  # beside the main path, on the block's input
            prev = row.name
            continue
        calls = row.calls if row.calls is not None else ((((prev, None),), row.name),)
        params = row.param_names + row.reads
        last = out[-1] if out else None
        if row.module is not None and last is not None and last.name == row.module:  # the module's next row
            out[-1] = Layer(last.name, f"{last.kind}+{row.kind}", ((last.calls[0][0], row.name),),
                            last.params + params, last.rows + (row,))
        else:
            out.append(Layer(row.module or row.name, row.kind, calls, params, (row,)))
        prev = calls[-1][1]
    return prev


def layer_names(model):
    """The names teacher_force's `layers` may hold for this model, in execution order."""
    return [l.name for l in layer_table(model)]


def layer_table(model):
    """The model's teacher-forcing layers (see the module's docstring), in execution order, read
    off its layer table (model.layers)."""
    out = []
    _collect(model.layers, model.INPUTS[0], out)
    return out


# ---------------------------------------------------------------------------------------
# pyvf's side of each layer's VJP: its own layer pair, run again on the traced input


def _reference_vjp(model, layer, xs, douts):
    """pyvf's VJP of one layer: its rows run again on the traced inputs through the model's own
    layer pairs (model.layer_forward, model.layer_backward).
    xs: per call, the list of input arrays; douts: per call, the output's gradient.
    -> (per call, the list of the inputs' gradients (None for the model's inputs),
        official parameter name -> gradient)."""
    dparams = {n: np.zeros_like(model.params[n]) for n in layer.params}
    dxs = []
    for x, dy in zip(xs, douts):
        caches = []
        for row in layer.rows:  # a module of several rows (the codebook's Upsample) runs them in turn
            y, c = model.layer_forward(row, *x)
            caches.append(c)
            x = (y,)
        for row, c in zip(reversed(layer.rows), reversed(caches)):
            dx, dps = model.layer_backward(row, dy, c)
            for n, g in zip(row.param_names + row.reads, dps):
                dparams[n] += g
            dy = dx[0]
        dxs.append(dx)
    return dxs, dparams


# ---------------------------------------------------------------------------------------
# the report


@dataclasses.dataclass
class LayerCheck:
    name: str
    forward: Comparison = None  # the port's output(s) vs pyvf's trace, by output name
    backward: Comparison = None  # "d <input>" and the parameters' gradients vs pyvf's layer VJP; None: not run
    error: str = None  # the port's callable raised (the layer counts as wrong)

    @property
    def ok(self):
        if self.error is not None:
            return False
        fwd = self.forward.first is None and not self.forward.only_ref
        return fwd and (self.backward is None or (self.backward.first is None and not self.backward.only_ref))

    @staticmethod
    def _worst(c):
        """The largest relative error of the rows judged by it (not those accepted by atol); nan
        where one is nan (Python's max keeps a nan only when it comes first); None where nothing
        was compared."""
        if c is None or not c.rows:
            return None
        rels = [r.rel for r in c.rows if r.rel <= r.rtol or not r.ok]
        return float("nan") if any(np.isnan(rels)) else max(rels, default=0.0)


@dataclasses.dataclass
class TeacherReport:
    checks: list  # LayerCheck per checked layer, in execution order
    unchecked: list  # the model's layers no callable was given for

    @property
    def wrong(self):
        """The names of the layers whose output or VJP differs from pyvf's (or that raised)."""
        return [c.name for c in self.checks if not c.ok]

    @property
    def ok(self):
        return not self.wrong

    def __getitem__(self, name):
        return {c.name: c for c in self.checks}[name]  # KeyError: not checked (no callable), or no layer

    def table(self):
        lines = ["| layer | forward rel err | backward rel err | rtol | |", "|---|---|---|---|---|"]
        for c in self.checks:
            f, b = LayerCheck._worst(c.forward), LayerCheck._worst(c.backward)
            rtol = c.forward.rows[0].rtol if c.forward is not None and c.forward.rows else float("nan")
            lines.append(f"| {c.name} | {'-' if f is None else f'{f:.1e}'} | {'-' if b is None else f'{b:.1e}'} "
                         f"| {rtol:.0e} | {'ok' if c.ok else 'WRONG'} |")
        return "\n".join(lines)

    def __str__(self):
        wrong = self.wrong
        head = (f"teacher forcing: all {len(self.checks)} layers agree with pyvf" if not wrong else
                f"teacher forcing: {len(wrong)} of {len(self.checks)} layers wrong: {', '.join(wrong)}")
        parts = [head, "", self.table()]
        if self.unchecked:
            parts += ["", f"not checked (no callable, {len(self.unchecked)}): {', '.join(self.unchecked)}"]
        for c in self.checks:
            if c.ok:
                continue
            parts += ["", f"## {c.name}"]
            if c.error is not None:
                parts.append(f"raised: {c.error}")
                continue
            for what, comp in (("forward", c.forward), ("backward", c.backward)):
                if comp is not None and not (comp.first is None and not comp.only_ref):
                    parts += [f"{what}: {str(comp).splitlines()[0]}", comp.table()]
                    if comp.only_ref:
                        parts.append(f"no gradient from the port for: {', '.join(comp.only_ref)}")
        return "\n".join(parts)


# ---------------------------------------------------------------------------------------
# teacher_force


def _is_tree(model, name, row):
    """True for the transformer activations of the whole tree, (R, B, N, L, ...)."""
    return (isinstance(model, _transformer.Transformer) and row is None
            and (name == "embed.out" or name.startswith("blocks.")))


def _check_params(model, params, layout):
    """params -> (official name -> tensor, the layout function), every problem in one error."""
    if params is None:
        return {}, None
    if layout is None:  # a torch port holds torch's layout: the default only where it is the published one
        if next(iter(model.LAYOUTS)) != "torch":
            raise ValueError(f"layout must be given with params for a {type(model).__name__}: one of "
                             f"{tuple(model.LAYOUTS)}")
        layout = "torch"
    layout = model.check_layout(layout)
    shapes, out, problems = model.parameter_shapes(), {}, []
    for raw, t in params.items():
        name = model.official_name(raw) if isinstance(raw, str) else raw
        if name not in shapes or not getattr(t, "requires_grad", False):
            problems.append(f"{raw!r} is not a parameter of this model, or not a tensor that requires grad")
        elif tuple(t.shape) not in model.layout_shapes(name, layout):
            problems.append(f"{raw!r} has shape {tuple(t.shape)}, not its shape in layout={layout!r}")
        else:
            out[name] = t
    if problems:
        raise ValueError("teacher_force: params: " + "; ".join(problems))
    return out, lambda n, a: model.from_layout(n, a, layout)


def teacher_force(model, inputs, layers, *, params=None, layout=None, upstream=None, train=False,
                  dtype=None, rtol=None):
    """Run each of the port's layers on pyvf's input to it; see the module's docstring.

    model: a pyvf.Transformer or pyvf.Codebook holding the port's weights. inputs: (tokens,
    poses) for a Transformer, images for a Codebook (numpy arrays as model.forward takes them).
    layers: dict layer name -> callable (names from layer_names(model); an unknown name raises).
    params: optional dict official parameter name -> the port's torch tensor (requires grad), in
    `layout` ("tf" | "torch" for a Transformer, required with params; "torch" (default) | "tf" for
    a Codebook): their per-layer gradients are compared. upstream: optional dict of
    model.backward's seeds; with it every layer's VJP is checked too. train: the codebook's
    forward mode (the quantizer's EMA step; the model's buffers are restored afterwards).
    dtype, rtol: compare's tolerance arguments.
    The model's last forward stays the caller's: a model.backward() after this call differentiates
    it, not teacher forcing's run. Returns a TeacherReport (.wrong: the wrong layers' names)."""
    table = layer_table(model)
    _check_layers(table, layers)
    params, convert = _check_params(model, params, layout)
    import torch  # only here: pyvf itself never needs it

    cache = model._cache  # the user's last forward: a model.backward() after this call differentiates it
    try:
        trace, grads, sizes = _pyvf_run(model, inputs, upstream, train)
    finally:
        model._cache = cache
    to_port, from_port = _port_converters(torch, model, trace, sizes)
    checks, unchecked = [], []
    for layer in table:
        fn = layers.get(layer.name)
        if fn is None:
            unchecked.append(layer.name)
            continue
        checks.append(_check_layer(torch, model, layer, fn, trace, grads, params, convert, to_port, from_port,
                                   dtype, rtol))
    return TeacherReport(checks=checks, unchecked=unchecked)


def _check_layers(table, layers):
    """layers against the model's layer table: a misspelt name would be silently not checked."""
    unknown = [n for n in layers if n not in {l.name for l in table}]
    if unknown:
        raise ValueError(f"layers: unknown layer names {unknown}; this model's layers are {[l.name for l in table]}")


def _pyvf_run(model, inputs, upstream, train):
    """pyvf's run, the reference every layer is checked against: (trace, every layer's input and
    output by name, the model's inputs included; the activations' gradients from
    model.backward(**upstream), None without upstream; (N, L) of a Transformer's tokens, None for
    a Codebook). A Codebook's EMA buffers are restored after a train=True forward."""
    if isinstance(model, _transformer.Transformer):
        if train:
            raise ValueError("train=True is for a Codebook (its EMA step); the transformer has no training mode")
        tokens, poses = inputs
        out = model.forward(tokens, poses, trace=True)
        given = {"tokens": tokens, "poses": poses}
        _, N, L = tokens.shape
        sizes = (N, L)
    else:
        if upstream is not None and set(upstream) - {"drec"}:
            raise ValueError(f"upstream for a Codebook takes drec only, got {sorted(upstream)}: the commitment "
                             "loss (dloss) is a second output of the quantize layer, which no layer VJP sees")
        saved = {k: v.copy() for k, v in model.quantizer.state_dict().items()} if train else None
        try:
            out = model.forward(inputs, train=train, trace=True)
        finally:
            if saved is not None:
                model.quantizer.load_state_dict(saved)
        given = {"images": inputs}
        sizes = None
    trace = {**given, **out.trace}
    grads = model.backward(**upstream) if upstream is not None else None
    return trace, grads, sizes


def _port_converters(torch, model, trace, sizes):
    """(to_port, from_port): an activation (trace[name], or the array given; row r of a
    per-row one) as a torch tensor for the port, and the port's output back as a NumPy array.
    A Transformer's tree activations go through the flat token layout (R = 3 rows of N views of
    L tokens, sizes = (N, L))."""
    R = 3

    def to_port(name, row, a):
        a = trace[name] if a is None else a
        a = a[row] if row is not None else a
        if _is_tree(model, name, row):
            a = tree_to_flat(np.asarray(a))
        return torch.from_numpy(np.array(a))  # a copy: the port may write into it

    def from_port(name, row, t):
        a = t.detach().cpu().numpy() if hasattr(t, "detach") else np.asarray(t)
        if _is_tree(model, name, row) and a.ndim >= 2:
            N, L = sizes  # (a tree activation is a Transformer's: sizes is set)
            if a.shape[1] == R * N * L:
                a = flat_to_tree(a, R, N, L)
        return a

    return to_port, from_port


def _check_layer(torch, model, layer, fn, trace, grads, params, convert, to_port, from_port, dtype, rtol):
    backward = grads is not None
    mine_out, ins, outs = {}, [], []
    try:
        for inputs, out_name in layer.calls:
            xs = [to_port(n, r, None) for n, r in inputs]
            if backward:  # the model's inputs get no gradient
                for x, (n, _) in zip(xs, inputs):
                    if x.is_floating_point() and n not in MODEL_INPUTS:
                        x.requires_grad_(True)
            y = fn(*xs)
            if isinstance(y, (tuple, list)):
                y = y[0]
            ins.append(xs)
            outs.append(y)
            mine_out[out_name] = from_port(out_name, None, y)
    except Exception as e:  # noqa: BLE001 - the port's layer failed: report it at this layer
        return LayerCheck(layer.name, error=f"{type(e).__name__}: {e}")
    fwd = compare(mine_out, {o: trace[o] for _, o in layer.calls}, dtype=dtype, rtol=rtol)
    if not backward:
        return LayerCheck(layer.name, forward=fwd)
    # pyvf's VJP of this layer, on its own input, seeded with pyvf's gradient of the layer's output
    xs_ref = [[trace[n][r] if r is not None else trace[n] for n, r in inputs] for inputs, _ in layer.calls]
    douts = [grads[o] for _, o in layer.calls]
    dxs_ref, dparams_ref = _reference_vjp(model, layer, xs_ref, douts)
    ref, mine = {}, {}
    for (inputs, _), dxs in zip(layer.calls, dxs_ref):
        for (n, r), dx in zip(inputs, dxs):
            if dx is not None and n not in MODEL_INPUTS:
                ref[f"d {_label(n, r)}"] = dx
    ref.update(dparams_ref)
    mine_params = {n: params[n] for n in layer.params if n in params}
    for n in layer.params:
        if n not in mine_params:
            del ref[n]  # the port's tensor was not given: nothing to compare
    try:
        for t in mine_params.values():
            t.grad = None
        total = 0
        for (inputs, out_name), y, dy in zip(layer.calls, outs, douts):
            if not getattr(y, "requires_grad", False):
                continue  # a port output that does not depend on anything differentiable
            total = total + (y * to_port(out_name, None, dy).to(y.dtype)).sum()
        if torch.is_tensor(total):
            total.backward()
    except Exception as e:  # noqa: BLE001
        return LayerCheck(layer.name, forward=fwd, error=f"backward: {type(e).__name__}: {e}")
    for (inputs, _), xs, dxs in zip(layer.calls, ins, dxs_ref):
        for (n, r), x, dx in zip(inputs, xs, dxs):
            if dx is None or n in MODEL_INPUTS:
                continue
            g = x.grad if x.grad is not None else torch.zeros_like(x)
            mine[f"d {_label(n, r)}"] = from_port(n, r, g)
    for n, t in mine_params.items():
        g = t.grad.detach().cpu().numpy() if t.grad is not None else np.zeros(tuple(t.shape))
        mine[n] = convert(n, g)
    # the inputs' gradients are judged each on its own scale; each parameter's gradient against at
    # least the layer's largest parameter gradient: one that is zero in exact arithmetic (a conv bias
    # feeding a GroupNorm of one channel per group) is rounding on both sides, its own relative error
    # meaningless. A parameter's gradient sums over every token, so its scale (larger with the batch)
    # would hide an input gradient wrong by several times rtol.
    dinputs = compare({n: g for n, g in mine.items() if n not in dparams_ref},
                      {n: g for n, g in ref.items() if n not in dparams_ref}, dtype=dtype, rtol=rtol)
    mine_p, ref_p = {n: mine[n] for n in mine if n in dparams_ref}, {n: ref[n] for n in ref if n in dparams_ref}
    dparams = compare(mine_p, ref_p, dtype=dtype, rtol=rtol)
    scale = max((float(np.abs(np.asarray(a, dtype=np.float64)).max()) for a in ref_p.values() if np.size(a)),
                default=0.0)
    if dparams.rows and scale > 0:
        dparams = compare(mine_p, ref_p, dtype=dtype, rtol=rtol, atol=min(r.rtol for r in dparams.rows) * scale)
    rows = dinputs.rows + dparams.rows  # ref's order: the inputs' gradients, then the parameters'
    bwd = Comparison(first=next((r.name for r in rows if not r.ok), None), rows=rows,
                     only_mine=dinputs.only_mine + dparams.only_mine, only_ref=dinputs.only_ref + dparams.only_ref)
    return LayerCheck(layer.name, forward=fwd, backward=bwd)


# ---------------------------------------------------------------------------------------
# the module adapter


def torch_modules(port, model, path=None):
    """{layer name: callable} from a torch module whose children are named as the published
    modules: for each of layer_names(model), the submodule port.get_submodule(path(name)) (path
    default: the name itself, which is the published module's name in the codebook), left out
    where there is none (or path returns None). A codebook's norm layers (GroupNorm modules) are
    wrapped in swish, as pyvf fuses them. The transformer's attention usually takes the tree
    mask too, and its embedding is rarely one module: give those as functions."""
    import torch

    out = {}
    for layer in layer_table(model):
        p = layer.name if path is None else path(layer.name)
        if p is None:
            continue
        try:
            m = port.get_submodule(p)
        except AttributeError:
            continue
        if layer.kind == "norm_swish":
            out[layer.name] = (lambda m: lambda x: torch.nn.functional.silu(m(x)))(m)
        else:
            out[layer.name] = m
    return out
