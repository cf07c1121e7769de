"""Teacher forcing: run a port's own layers, each on **pyvf's** input to that layer, and compare
each output (and, given upstream gradients, each layer's VJP) with pyvf's, so that a bug shows at
the layer that has it (docs/verify.md §2 walks through both models).

    report = pyvf.teacher_force(model, (tokens, poses), layers,          # Transformer
                                params=params, layout="torch", upstream=dict(dlogits=dl, dpose=dp))
    report = pyvf.teacher_force(cb, images, layers, params=params, upstream=dict(drec=d))  # Codebook
    report.wrong      # ["blocks.1.attn"]: the layers whose output or VJP is over tolerance

The layers (layer_names(model), in execution order) are read off the model's layer table
(model.layers, pyvf.models.io); teacher_force's docstring says what is compared.
"""

import dataclasses

import numpy as np

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
        params = row.param_names
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
            for n, g in zip(row.param_names, dps):
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
        """The largest relative error of the rows not accepted by atol (nan if any); None: none."""
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
    return model.INPUTS[0] == "tokens" and row is None and (name == "embed.out" or name.startswith("blocks."))


def _check_params(model, params, layout):
    """params -> (official name -> tensor, the layout they are in); the first wrong one raises."""
    if params is None:
        return {}, None
    if layout is None:  # a torch port holds torch's layout: the default only where it is the published one
        if next(iter(model.LAYOUTS)) != "torch":
            raise ValueError(f"layout must be given with params for a {type(model).__name__}: one of "
                             f"{tuple(model.LAYOUTS)}")
        layout = "torch"
    model.check_layout(layout)
    shapes, out = model.parameter_shapes(), {}
    for raw, t in params.items():
        name = model.official_name(raw)
        if name not in shapes or not getattr(t, "requires_grad", False):
            raise ValueError(f"teacher_force: params: {raw!r} is not a parameter of this model, or not a "
                             "tensor that requires grad")
        if tuple(t.shape) not in model.layout_shapes(name, layout):
            raise ValueError(f"teacher_force: params: {raw!r} has shape {tuple(t.shape)}, not its shape in "
                             f"layout={layout!r}")
        out[name] = t
    return out, layout


def teacher_force(model, inputs, layers, *, params=None, layout=None, upstream=None, train=False):
    """Run each of the port's layers on pyvf's input to it -> TeacherReport.

    model: a pyvf.Transformer or pyvf.Codebook holding the port's weights; inputs: (tokens, poses)
    or images, as model.forward takes them. layers: layer name -> callable (a function or torch
    module) taking the layer's inputs as torch tensors, returning its output (of a tuple, the
    first); the tree's activations reach it flat, (B, T, d) (tree_to_flat). params: optional official parameter name -> the port's tensor (requires grad), in
    `layout` (required for a Transformer; a Codebook's default "torch"). upstream: optional
    model.backward seeds (a Codebook's drec only); with it every layer's VJP is checked too:
    the gradients of its float inputs ("d <input>") and of its parameters.
    train: the codebook's EMA step (its buffers restored afterwards). Tolerances: compare's
    defaults. The model's last forward stays the caller's."""
    table = layer_table(model)
    unknown = [n for n in layers if n not in {l.name for l in table}]  # a misspelt name: silently unchecked
    if unknown:
        raise ValueError(f"layers: unknown layer names {unknown}; this model's layers are {[l.name for l in table]}")
    params, layout = _check_params(model, params, layout)
    if upstream is not None and model.INPUTS == ("images",) and set(upstream) - {"drec"}:
        raise ValueError(f"upstream for a Codebook takes drec only, got {sorted(upstream)}: the commitment "
                         "loss (dloss) is a second output of the quantize layer, which no layer VJP sees")
    inputs = tuple(inputs) if model.INPUTS[0] == "tokens" else (inputs,)
    cache = model._cache  # the user's last forward: a model.backward() after this call differentiates it
    saved = model.quantizer.state_dict() if train else None  # (copies)
    try:
        out = model.forward(*inputs, trace=True, **({"train": True} if train else {}))
        trace = {**dict(zip(model.INPUTS, inputs)), **out.trace}
        grads = model.backward(**upstream) if upstream is not None else None
    finally:
        model._cache = cache
        if saved is not None:
            model.quantizer.load_state_dict(saved)
    run = _Run(model, trace, grads, params, layout)
    return TeacherReport(checks=[run.check(l, layers[l.name]) for l in table if l.name in layers],
                         unchecked=[l.name for l in table if l.name not in layers])


class _Run:
    """One teacher_force call: pyvf's trace and gradients, and the port's parameters."""

    def __init__(self, model, trace, grads, params, layout):
        import torch  # only here: pyvf itself never needs it

        self.torch, self.model, self.trace, self.grads = torch, model, trace, grads
        self.params, self.layout = params, layout
        self.sizes = trace["tokens"].shape[1:] if "tokens" in trace else None  # (N, L) of the tree

    def to_port(self, name, row, a=None):
        """An activation (trace[name], or the array given; row r of a per-row one) -> a torch tensor
        (a copy: the port may write into it), the tree's through the flat token layout."""
        a = self.trace[name] if a is None else a
        a = a[row] if row is not None else a
        if _is_tree(self.model, name, row):
            a = tree_to_flat(np.asarray(a))
        return self.torch.from_numpy(np.array(a))

    def from_port(self, name, row, t):
        a = t.detach().cpu().numpy() if hasattr(t, "detach") else np.asarray(t)
        if _is_tree(self.model, name, row) and a.ndim >= 2 and a.shape[1] == 3 * np.prod(self.sizes):
            a = flat_to_tree(a, 3, *self.sizes)
        return a

    def check(self, layer, fn):
        """Run the port's layer on pyvf's inputs, compare its outputs (and VJP) -> LayerCheck."""
        backward = self.grads is not None
        mine, ins, outs, fwd, stage = {}, [], [], None, ""
        try:
            for inputs, out_name in layer.calls:
                xs = [self.to_port(n, r) for n, r in inputs]
                for x, (n, _) in zip(xs, inputs):  # the model's inputs get no gradient
                    if backward and x.is_floating_point() and n not in MODEL_INPUTS:
                        x.requires_grad_(True)
                y = fn(*xs)
                y = y[0] if isinstance(y, (tuple, list)) else y
                ins.append(xs)
                outs.append(y)
                mine[out_name] = self.from_port(out_name, None, y)
            fwd, stage = compare(mine, {o: self.trace[o] for _, o in layer.calls}), "backward: "
            bwd = self.vjp(layer, ins, outs) if backward else None
        except Exception as e:  # noqa: BLE001 - the port's layer failed: report it at this layer
            return LayerCheck(layer.name, forward=fwd, error=f"{stage}{type(e).__name__}: {e}")
        return LayerCheck(layer.name, forward=fwd, backward=bwd)

    def vjp(self, layer, ins, outs):
        """The port's VJP (torch autograd) against pyvf's layer pair, both seeded with pyvf's
        gradient of the layer's output -> Comparison: "d <input>" then the parameters' gradients."""
        xs_ref = [[self.trace[n][r] if r is not None else self.trace[n] for n, r in inputs]
                  for inputs, _ in layer.calls]
        douts = [self.grads[o] for _, o in layer.calls]
        dxs_ref, dparams_ref = _reference_vjp(self.model, layer, xs_ref, douts)
        mine_params = {n: self.params[n] for n in layer.params if n in self.params}
        for t in mine_params.values():
            t.grad = None
        total = sum((y * self.to_port(o, None, dy).to(y.dtype)).sum()
                    for (_, o), y, dy in zip(layer.calls, outs, douts) if getattr(y, "requires_grad", False))
        if self.torch.is_tensor(total):  # (0: no port output depends on anything differentiable)
            total.backward()
        dins_ref, dins = {}, {}
        for (inputs, _), xs, dxs in zip(layer.calls, ins, dxs_ref):
            for (n, r), x, dx in zip(inputs, xs, dxs):
                if dx is not None and n not in MODEL_INPUTS:
                    label = f"d {n}" if r is None else f"d {n}[{r}]"
                    dins_ref[label] = dx
                    dins[label] = self.from_port(n, r, x.grad if x.grad is not None else 0 * x)
        ref_p = {n: g for n, g in dparams_ref.items() if n in mine_params}
        mine_p = {n: self.model.from_layout(n, t.grad.detach().cpu().numpy() if t.grad is not None
                                            else np.zeros(tuple(t.shape)), self.layout)
                  for n, t in mine_params.items()}
        # the inputs' gradients are judged each on its own scale; each parameter's gradient against
        # at least the layer's largest parameter gradient: one that is zero in exact arithmetic (a
        # conv bias feeding a GroupNorm of one channel per group) is rounding on both sides, its own
        # relative error meaningless. A parameter's gradient sums over every token, so its scale
        # (larger with the batch) would hide an input gradient wrong by several times rtol.
        dinputs = compare(dins, dins_ref)
        dparams = compare(mine_p, ref_p)
        scale = max((float(np.abs(a).max()) for a in ref_p.values() if np.size(a)), default=0.0)
        if dparams.rows and scale > 0:
            dparams = compare(mine_p, ref_p, atol=min(r.rtol for r in dparams.rows) * scale)
        rows = dinputs.rows + dparams.rows
        return Comparison(first=next((r.name for r in rows if not r.ok), None), rows=rows,
                          only_mine=dinputs.only_mine + dparams.only_mine, only_ref=dinputs.only_ref + dparams.only_ref)


# ---------------------------------------------------------------------------------------
# the module adapter


def torch_modules(port, model):
    """{layer name: callable} from a torch module whose children are named as the published
    modules: port.get_submodule(name) for each of layer_names(model) it has. A codebook's GroupNorm
    modules are wrapped in swish, as pyvf fuses them; under the empty code the quantize layer calls
    port.quantize(z, port.empty_patches(images))."""
    import torch

    out = {}
    for layer in layer_table(model):
        try:
            m = port.get_submodule(layer.name)
        except AttributeError:
            continue
        if layer.kind == "norm_swish":
            out[layer.name] = (lambda m: lambda x: torch.nn.functional.silu(m(x)))(m)
        elif layer.kind == "quantize" and len(layer.calls[0][0]) == 2:  # the empty code: (z, images)
            out[layer.name] = (lambda m: lambda z, x: m(z, port.empty_patches(x)))(m)
        else:
            out[layer.name] = m
    return out
