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
gradients are compared with pyvf's contribution of that layer (a tied weight, wte, gets one
per layer that reads it).

The layers (`layer_table(model)`, `layer_names(model)`, in execution order), each a function of its inputs only:

  Transformer   input -> output (pyvf's trace names)                   parameters
    embed              tokens, poses -> embed.out                      wte, wpe, pose_embedding/*
    blocks.{j}.ln_1    blocks.{j-1}.out (embed.out) -> blocks.{j}.ln_1  h.{j}/ln_1/*
    blocks.{j}.attn    blocks.{j}.ln_1 -> blocks.{j}.attn.c_proj        h.{j}/attn/* (branching attention)
    blocks.{j}.ln_2    blocks.{j}.resid_1 -> blocks.{j}.ln_2           h.{j}/ln_2/*
    blocks.{j}.mlp     blocks.{j}.ln_2 -> blocks.{j}.mlp.c_proj        h.{j}/mlp/*
    ln_f               called twice: rows 1 and 2 of the last block's output ->
                       ln_f.generation, ln_f.localization              ln_f/*
    logits             ln_f.generation -> logits                       wte/weight (tied: its first V rows)
    pose_head          ln_f.localization -> pose                       quaternion_pose_representation/...

  Codebook: every module of the published tree that is a leaf of the computation:
    *.conv_in, *.conv1, *.conv2, *.nin_shortcut, *.conv_out, quant_conv, post_quant_conv (Conv2d);
    *.norm1, *.norm2, *.norm_out: GroupNorm **then swish** (pyvf fuses them; torch_modules wraps
    a GroupNorm module in swish); *.attn.{i}, *.mid.attn_1 (the AttnBlock, residual included);
    encoder.down.{l}.downsample (pad (0, 1, 0, 1), conv 3x3 stride 2: output
    encoder.down.{l}.downsample.conv); decoder.up.{l}.upsample (nearest 2x, conv: output
    decoder.up.{l}.upsample.conv); quantize (z -> the straight-through quantized z; with
    train=True the port's EMA step runs too: a port whose codes see the update differs here).

Not layers: the residual additions (x + attn, x + mlp, a ResnetBlock's shortcut + h) and the
losses; pyvf.compare on a trace covers them. The model's inputs (tokens, poses, images) get no
gradient.

Layouts. Transformer activations of the whole tree, pyvf's (R, B, N, L, d), reach a callable in
`token_layout`: "flat" (default) as most ports hold them, (B, T, d) with T = R*N*L ordered
[row][view][token] (pyvf.tree_to_flat), or "tree". The heads' rows stay (B, N, L, ...). Codebook
activations are NCHW. The tensors have pyvf's dtype: run pyvf in the port's dtype (float64 for a
check of the math: see compare's tolerances, which apply here per layer).

Backward: upstream holds model.backward's seeds (Transformer: dlogits, dpose, dloss; Codebook:
drec only, since the quantize layer's commitment loss is a second output no layer VJP sees).
pyvf's gradient of each layer's output is the layer's upstream gradient; the port's VJP is taken
by torch autograd ((out * dout).sum().backward()) and compared with pyvf's own layer pair run on
the same input: the gradient of each float input ("d <input name>") and of each parameter. The
parameters' .grad are cleared per layer and restored afterwards.
"""

import dataclasses
from collections.abc import Mapping

import numpy as np

from ..models import codebook as _codebook
from ..models import transformer as _transformer
from ..nn.attention import attention_layer_backward, attention_layer_forward
from .compare import Comparison, compare
from ..nn.conv import (
    attnblock_backward,
    attnblock_forward,
    conv2d_backward,
    conv2d_forward,
    groupnorm_swish_backward,
    groupnorm_swish_forward,
    upsample_nearest2x_backward,
    upsample_nearest2x_forward,
)
from ..nn.layers import layernorm_backward, layernorm_forward, mlp_backward, mlp_forward
from .layout import flat_to_tree, tree_to_flat

__all__ = ["Layer", "LayerCheck", "TeacherReport", "layer_names", "layer_table", "teacher_force", "torch_modules"]

TOKEN_LAYOUTS = ("flat", "tree")
MODEL_INPUTS = ("tokens", "poses", "images")


@dataclasses.dataclass(frozen=True)
class Layer:
    name: str  # the key of `layers`
    kind: str  # how pyvf computes it (its reference pair): "layernorm", "attention", "conv", ...
    calls: tuple  # per call: (inputs, output); inputs a tuple of (name, row): a trace name or a
    #               model input ("tokens", "poses", "images"), row None or the tree row taken
    params: tuple  # official parameter names the layer reads


def _label(name, row):
    return name if row is None else f"{name}[{row}]"


# ---------------------------------------------------------------------------------------
# the layers of each model


def _transformer_layers(cfg):
    head = "quaternion_pose_representation/pose_classifier/"
    dense = lambda p: (p + "/c_fc/weight", p + "/c_fc/bias", p + "/c_proj/weight", p + "/c_proj/bias")  # noqa: E731
    out = [Layer("embed", "embed", (((("tokens", None), ("poses", None)), "embed.out"),),
                 ("wte/weight", "wpe/embeddings", *dense("pose_embedding")))]
    prev = "embed.out"
    for j in range(cfg.n_layer):
        b, h = f"blocks.{j}.", f"h.{j}/"
        out += [
            Layer(b + "ln_1", "layernorm", ((((prev, None),), b + "ln_1"),), (h + "ln_1/gamma", h + "ln_1/beta")),
            Layer(b + "attn", "attention", ((((b + "ln_1", None),), b + "attn.c_proj"),),
                  (h + "attn/c_attn/weight", h + "attn/c_attn/bias", h + "attn/c_proj/weight", h + "attn/c_proj/bias")),
            Layer(b + "ln_2", "layernorm", ((((b + "resid_1", None),), b + "ln_2"),),
                  (h + "ln_2/gamma", h + "ln_2/beta")),
            Layer(b + "mlp", "mlp", ((((b + "ln_2", None),), b + "mlp.c_proj"),), dense(h + "mlp")),
        ]
        prev = b + "out"
    out += [
        Layer("ln_f", "layernorm", ((((prev, 1),), "ln_f.generation"), (((prev, 2),), "ln_f.localization")),
              ("ln_f/gamma", "ln_f/beta")),
        Layer("logits", "logits", (((("ln_f.generation", None),), "logits"),), ("wte/weight",)),
        Layer("pose_head", "mlp", (((("ln_f.localization", None),), "pose"),), dense(head[:-1])),
    ]
    return out


def _codebook_layers(cfg):
    names = [n for n in _codebook.trace_names(cfg) if not n.endswith("_loss") and n != "loss"]
    resblocks = {n for n in names if n + ".norm1" in names}
    out, prev, block_in, before_interp = [], "images", {}, None
    conv_params = lambda n: (n + ".weight", n + ".bias")  # noqa: E731
    for n in names:
        if n in resblocks:  # the block's output: shortcut + h, not a layer
            prev = n
            continue
        last = n.rsplit(".", 1)[-1]
        if last == "norm1":
            block_in[n[:-len(".norm1")]] = prev
        if n.endswith(".upsample.interp"):
            before_interp = prev
        elif n.endswith(".upsample.conv"):
            out.append(Layer(n[:-len(".conv")], "upsample", ((((before_interp, None),), n),), conv_params(n)))
        elif n.endswith(".downsample.conv"):
            out.append(Layer(n[:-len(".conv")], "downsample", ((((prev, None),), n),), conv_params(n)))
        elif last == "nin_shortcut":
            out.append(Layer(n, "conv", ((((block_in[n[:-len(".nin_shortcut")]], None),), n),), conv_params(n)))
        elif last in ("norm1", "norm2", "norm_out"):
            out.append(Layer(n, "norm_swish", ((((prev, None),), n),), conv_params(n)))
        elif last == "quantize":
            out.append(Layer(n, "quantize", ((((prev, None),), n),), ()))
        elif ".attn" in n:
            out.append(Layer(n, "attnblock", ((((prev, None),), n),), tuple(n + s for s in _codebook.ATTN_PARAMS)))
        else:
            out.append(Layer(n, "conv", ((((prev, None),), n),), conv_params(n)))
        if last != "nin_shortcut":  # the shortcut runs beside the main path
            prev = n
    return out


def layer_names(model):
    """The names teacher_force's `layers` may hold for this model, in execution order."""
    return [l.name for l in layer_table(model)]


def layer_table(model):
    """The model's teacher-forcing layers (see the module's docstring), in execution order."""
    if isinstance(model, _transformer.Transformer):
        return _transformer_layers(model.config)
    if isinstance(model, _codebook.Codebook):
        return _codebook_layers(model.config)
    raise TypeError(f"model must be a pyvf.Transformer or pyvf.Codebook, got {type(model).__name__}")


# ---------------------------------------------------------------------------------------
# pyvf's side of each layer's VJP: its own layer pair, run again on the traced input


def _conv_geometry(name, w):
    """(stride, padding) of a codebook conv, docs/math.md §4: the Downsample pads (0, 1, 0, 1) and
    strides 2; every other 3x3 conv pads 1, every 1x1 conv 0."""
    if name.endswith(".downsample.conv"):
        return 2, (0, 1, 0, 1)
    return 1, w.shape[-1] // 2


def _reference_vjp(model, layer, xs, douts):
    """xs: per call, the list of input arrays; douts: per call, the output's gradient.
    -> (per call, the list of the float inputs' gradients (None for the model's inputs),
        official parameter name -> gradient)."""
    P, kind = model.params, layer.kind
    dparams = {n: np.zeros_like(P[n]) for n in layer.params}
    dxs = []
    for x, dy in zip(xs, douts):
        x = x[0]
        if kind == "embed":
            tokens, poses = xs[0]
            _, cache = model._embed_forward(tokens, poses)
            model._embed_backward(dy, cache, dparams)
            dxs.append([None, None])  # the model's inputs: no gradient
            continue
        if kind == "layernorm":
            _, c = layernorm_forward(x, *(P[n] for n in layer.params))
            dx, *dp = layernorm_backward(dy, c)
        elif kind == "attention":
            cfg = model.config
            _, c = attention_layer_forward(x, *(P[n] for n in layer.params), cfg.n_head, cfg.attention_scale)
            dx, *dp = attention_layer_backward(dy, c)
        elif kind == "mlp":
            _, c = mlp_forward(x, *(P[n] for n in layer.params))
            dx, *dp = mlp_backward(dy, c)
        elif kind == "logits":  # forward was logits = g @ wte[:V]^T
            V, d = model.config.n_embeddings, x.shape[-1]
            dl2 = dy.reshape(-1, V)
            dx = (dl2 @ P["wte/weight"][:V]).reshape(x.shape)
            dp = [np.zeros_like(P["wte/weight"])]
            dp[0][:V] = dl2.T @ x.reshape(-1, d)
        elif kind in ("conv", "downsample"):
            w, b = (P[n] for n in layer.params)
            out_name = layer.calls[0][1]
            _, c = conv2d_forward(x, w, b, *_conv_geometry(out_name, w))
            dx, *dp = conv2d_backward(dy, c)
        elif kind == "upsample":  # nearest 2x, then conv 3x3 pad 1
            u, cu = upsample_nearest2x_forward(x)
            _, cc = conv2d_forward(u, *(P[n] for n in layer.params), 1, 1)
            du, *dp = conv2d_backward(dy, cc)
            (dx,) = upsample_nearest2x_backward(du, cu)
        elif kind == "norm_swish":
            _, c = groupnorm_swish_forward(x, *(P[n] for n in layer.params))
            dx, *dp = groupnorm_swish_backward(dy, c)
        elif kind == "attnblock":
            _, c = attnblock_forward(x, *(P[n] for n in layer.params))
            dx, *dp = attnblock_backward(dy, c)
        elif kind == "quantize":  # forward was quantized = z + sg(e - z): the identity for the gradient
            dx, dp = dy, []
        else:
            raise AssertionError(kind)
        for n, g in zip(layer.params, dp):
            dparams[n] += g
        dxs.append([dx])
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
        """The largest relative error of the rows judged by it (not those accepted by atol)."""
        return max((r.rel for r in c.rows if r.rel <= r.rtol or not r.ok), default=0.0) if c is not None else None


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
        return next(c for c in self.checks if c.name == name)

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
    if not isinstance(params, Mapping):
        raise TypeError(f"params must be a dict official parameter name -> torch tensor, got {type(params).__name__}")
    is_tf = isinstance(model, _transformer.Transformer)
    shapes = _transformer.parameter_shapes(model.config) if is_tf else _codebook.parameter_shapes(model.config)
    if is_tf:
        if layout is None:
            raise ValueError("layout must be given with params for a Transformer: 'tf' (Dense kernels (in, out)) or "
                             "'torch' (nn.Linear (out, in)); the gradients are transposed accordingly")
        layout = _transformer._weight_layout(layout)
        want = lambda n: _transformer._layout_shapes(n, shapes[n], layout)  # noqa: E731
        convert = lambda n, a: _transformer._from_layout(n, a, layout)  # noqa: E731
    else:
        layout = _codebook._weight_layout("torch" if layout is None else layout)
        want = lambda n: [_codebook._layout_shape(n, shapes[n], layout)]  # noqa: E731
        convert = lambda n, a: _codebook._from_layout(n, a, layout)  # noqa: E731
    out, problems = {}, []
    for raw, t in params.items():
        name = _transformer.official_name(raw) if is_tf and isinstance(raw, str) else raw
        if name not in shapes:
            problems.append(f"{raw!r} is not a parameter of this model")
        elif not (hasattr(t, "requires_grad") and hasattr(t, "grad")):
            problems.append(f"{raw!r} is a {type(t).__name__}, not a torch tensor")
        elif not t.requires_grad:
            problems.append(f"{raw!r} does not require grad (its gradient could not be read)")
        elif tuple(t.shape) not in want(name):
            problems.append(f"{raw!r} has shape {tuple(t.shape)}, expected {' or '.join(map(str, want(name)))} "
                            f"in layout={layout!r}")
        else:
            out[name] = t
    if problems:
        raise ValueError(f"teacher_force: params: {len(problems)} problem{'s' * (len(problems) > 1)}: "
                         + "; ".join(problems))
    return out, convert


def teacher_force(model, inputs, layers, *, params=None, layout=None, upstream=None, train=False,
                  token_layout="flat", dtype=None, rtol=None):
    """Run each of the port's layers on pyvf's input to it; see the module's docstring.

    model: a pyvf.Transformer or pyvf.Codebook holding the port's weights. inputs: (tokens,
    poses) for a Transformer, images for a Codebook (numpy arrays as model.forward takes them).
    layers: dict layer name -> callable (names from layer_names(model); an unknown name raises).
    params: optional dict official parameter name -> the port's torch tensor (requires grad), in
    `layout` ("tf" | "torch" for a Transformer, required with params; "torch" (default) | "tf" for
    a Codebook): their per-layer gradients are compared. upstream: optional dict of
    model.backward's seeds; with it every layer's VJP is checked too. train: the codebook's
    forward mode (the quantizer's EMA step; the model's buffers are restored afterwards).
    token_layout: "flat" | "tree" (Transformer). dtype, rtol: compare's tolerance arguments.
    Returns a TeacherReport (.wrong: the wrong layers' names)."""
    table = layer_table(model)
    by_name = {l.name: l for l in table}
    if not isinstance(layers, Mapping):
        raise TypeError(f"layers must be a dict layer name -> callable, got {type(layers).__name__}")
    unknown = [n for n in layers if n not in by_name]
    if unknown:
        raise ValueError(f"layers: unknown layer names {unknown}; this model's layers are "
                         f"{[l.name for l in table]} (pyvf.verify.teacher.layer_names(model))")
    not_callable = [n for n, f in layers.items() if not callable(f)]
    if not_callable:
        raise TypeError(f"layers: not callable: {not_callable}")
    if token_layout not in TOKEN_LAYOUTS:
        raise ValueError(f"token_layout must be one of {TOKEN_LAYOUTS}, got {token_layout!r}")
    if not isinstance(train, (bool, np.bool_)):
        raise TypeError(f"train must be True or False, got {train!r}")
    if upstream is not None and not isinstance(upstream, Mapping):
        raise TypeError(f"upstream must be a dict of model.backward's seeds, got {type(upstream).__name__}")
    params, convert = _check_params(model, params, layout)
    import torch  # only here: pyvf itself never needs it

    # pyvf's run: the trace (every layer's input and output) and, seeded, every activation's gradient
    is_tf = isinstance(model, _transformer.Transformer)
    if is_tf:
        if train:
            raise ValueError("train=True is for a Codebook (its EMA step); the transformer has no training mode")
        if not (isinstance(inputs, (tuple, list)) and len(inputs) == 2):
            raise TypeError("inputs must be (tokens, poses) for a Transformer")
        tokens, poses = inputs
        out = model.forward(tokens, poses, trace=True)
        given = {"tokens": tokens, "poses": poses}
        saved = None
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
    trace = {**given, **out.trace}
    grads = model.backward(**upstream) if upstream is not None else None
    R = 3
    if is_tf:
        B, N, L = tokens.shape

    def to_port(name, row, a):
        a = trace[name] if a is None else a
        a = a[row] if row is not None else a
        if _is_tree(model, name, row) and token_layout == "flat":
            a = tree_to_flat(np.asarray(a))
        return torch.from_numpy(np.array(a))  # a copy: the port may write into it

    def from_port(name, row, t):
        a = t.detach().cpu().numpy() if hasattr(t, "detach") else np.asarray(t)
        if _is_tree(model, name, row) and token_layout == "flat" and a.ndim >= 2 and a.shape[1] == R * N * L:
            a = flat_to_tree(a, R, N, L)
        return a

    checks, unchecked = [], []
    saved_grads = {n: t.grad for n, t in params.items()}
    try:
        for layer in table:
            fn = layers.get(layer.name)
            if fn is None:
                unchecked.append(layer.name)
                continue
            checks.append(_check_layer(torch, model, layer, fn, trace, grads, params, convert, to_port, from_port,
                                       dtype, rtol))
    finally:
        for n, t in params.items():
            t.grad = saved_grads[n]
    return TeacherReport(checks=checks, unchecked=unchecked)


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
    bwd = compare(mine, ref, dtype=dtype, rtol=rtol)
    # each gradient is judged normwise against at least the layer's largest one: a gradient that is
    # zero in exact arithmetic (a conv bias feeding a GroupNorm of one channel per group) is rounding
    # on both sides, its own relative error meaningless
    scale = max((float(np.abs(np.asarray(a, dtype=np.float64)).max()) for a in ref.values() if np.size(a)), default=0.0)
    if bwd.rows and scale > 0:
        bwd = compare(mine, ref, dtype=dtype, rtol=rtol, atol=min(r.rtol for r in bwd.rows) * scale)
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
    if not callable(getattr(port, "get_submodule", None)):
        raise TypeError(f"port must be a torch nn.Module, got {type(port).__name__}")
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
