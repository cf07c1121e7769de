"""The ViewFormer codebook: a VQ-VAE (taming-transformers style), docs/math.md §4, in NumPy.

    cfg = CodebookConfig(ch=32, ch_mult=(1, 1, 2, 2), num_res_blocks=1, attn_resolutions=(8,),
                         z_channels=32, embed_dim=32, n_embed=64, image_size=64)
    cb = Codebook(cfg, seed=0)
    codes = cb.encode(images)            # images (B, 3, S, S) in [-1, 1] -> (B, k, k) int64
    images = cb.decode_code(codes)
    out = cb.forward(images, train=True) # reconstruction, codes, rec_loss, commitment_loss, loss
    grads = cb.backward()                # d out.loss / d every parameter, torch names

Traces, for checking a port layer by layer (pyvf.compare):

    out = cb.forward(images, trace=True)
    out.trace                            # name -> activation, in execution order (trace_names(cfg))
    g = cb.backward(drec=d)              # a VJP of the reconstruction: activations' gradients
                                         # (backward order), then the parameters'

Parameters use the published torch names (tests/data/official-codebook-*.json), conv weights
(out, in, kh, kw). The quantizer's buffers (`quantize.*`) live in an EMAQuantizer.
load_official / state_dict also speak channels-last kernels (layout="tf": TF, Flax).

The forward records every layer it runs on a tape, (kind, parameter name, cache); the backward
replays the tape in reverse, so it reads as the forward read backwards, whatever the
configuration's number of levels and blocks. A traced forward records each op's output under
its name as it runs (the published torch module's name; the activations the forward keeps
anyway, as read-only views: nothing is copied or recomputed); without trace=True nothing extra
is kept or computed. Names: every `_op` of the tape, nested ones included, in execution order:

    encoder.conv_in
    encoder.down.{l}.block.{i}.norm1 .conv1 .norm2 .conv2 [.nin_shortcut], then encoder.down.{l}.block.{i}
    encoder.down.{l}.attn.{i}                (the AttnBlock's output, x + proj_out(...))
    encoder.down.{l}.downsample.conv
    encoder.mid.block_1 (and its children), encoder.mid.attn_1, encoder.mid.block_2
    encoder.norm_out, encoder.conv_out, quant_conv (z), quantize (the quantized z),
    post_quant_conv, decoder.conv_in, decoder.mid.*, decoder.up.{l}.block.{i}(.*),
    decoder.up.{l}.attn.{i}, decoder.up.{l}.upsample.interp (nearest 2x), decoder.up.{l}.upsample.conv,
    decoder.norm_out, decoder.conv_out (the reconstruction); then rec_loss, commitment_loss,
    [perceptual_loss,] loss (scalars, no gradient).

pyvf fuses Normalize and swish: `*.norm1`, `*.norm2`, `*.norm_out` are swish(GroupNorm(x)),
not the torch GroupNorm module's output (record `nonlinearity(norm(x))` on a port's side).
"""

import dataclasses
from collections.abc import Mapping

import numpy as np

from .. import _checks
from .._io import save_model
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
from ..nn.quantizer import EMAQuantizer

ATTN_PARAMS = (".norm.weight", ".norm.bias", ".q.weight", ".q.bias", ".k.weight", ".k.bias",
               ".v.weight", ".v.bias", ".proj_out.weight", ".proj_out.bias")
BUFFERS = ("quantize.embeddings", "quantize.ema_cluster_size_hidden", "quantize.ema_dw_hidden", "quantize.counter")


WEIGHT_LAYOUTS = ("torch", "tf")


def _weight_layout(layout):
    if not isinstance(layout, str) or layout not in WEIGHT_LAYOUTS:
        raise ValueError(f"layout must be one of {WEIGHT_LAYOUTS} (the conv kernels' convention: torch "
                         f"nn.Conv2d (out, in, kh, kw) or channels-last TF/Flax (kh, kw, in, out)), got {layout!r}")
    return layout


def is_conv_kernel(name, shape):
    """True for the conv kernels: the 4-d `.weight`s (GroupNorm weights are 1-d)."""
    return name.endswith(".weight") and len(shape) == 4


def _layout_shape(name, shape, layout):
    """The shape parameter `name` (published shape `shape`) has in `layout`."""
    if layout == "tf" and is_conv_kernel(name, shape):
        return tuple(shape[2:]) + (shape[1], shape[0])  # (out, in, kh, kw) -> (kh, kw, in, out)
    return tuple(shape)


def _from_layout(name, a, layout):
    """An array in `layout` -> the published layout (a view)."""
    if layout == "tf" and is_conv_kernel(name, a.shape):
        return a.transpose(3, 2, 0, 1)  # (kh, kw, in, out) -> (out, in, kh, kw)
    return a


def _to_layout(name, p, layout):
    """A parameter in the published layout -> a C-contiguous copy in `layout`."""
    if layout == "tf" and is_conv_kernel(name, p.shape):
        return np.ascontiguousarray(p.transpose(2, 3, 1, 0))  # (out, in, kh, kw) -> (kh, kw, in, out)
    return p.copy()


IMAGE_RANGE_SLACK = 1e-3  # images may leave [-1, 1] by this much (a user's own rounding), no more


@dataclasses.dataclass(frozen=True)
class CodebookConfig:
    ch: int  # channels of the first level
    ch_mult: tuple  # channel multiplier per level; the image shrinks by 2^(len - 1)
    num_res_blocks: int  # ResnetBlocks per level (the decoder has one more)
    attn_resolutions: tuple  # resolutions at which an AttnBlock follows each ResnetBlock
    z_channels: int  # the encoder's output channels
    embed_dim: int  # D, the code width
    n_embed: int  # K, the codebook size
    image_size: int  # S, images are S x S
    in_channels: int = 3
    out_ch: int = 3
    decay: float = 0.99  # EMA decay of the quantizer
    eps: float = 1e-5  # Laplace smoothing of the EMA cluster sizes
    codebook_weight: float = 1.0  # loss = rec_loss + perceptual_weight * perceptual + codebook_weight * commitment
    perceptual_weight: float = 0.0  # the LPIPS term (docs/math.md §4): needs a perceptual module, see Codebook
    dtype: str = "float32"

    def __post_init__(self):
        object.__setattr__(self, "ch_mult", tuple(self.ch_mult))
        object.__setattr__(self, "attn_resolutions", tuple(self.attn_resolutions))
        for name in ("ch", "num_res_blocks", "z_channels", "embed_dim", "n_embed", "image_size", "in_channels",
                     "out_ch"):
            val = getattr(self, name)
            if isinstance(val, bool) or not isinstance(val, int) or val < 1:
                raise ValueError(f"CodebookConfig.{name} must be a positive integer, got {val!r}")
        if not self.ch_mult or any(not isinstance(m, int) or m < 1 for m in self.ch_mult):
            raise ValueError(f"CodebookConfig.ch_mult must be positive integers, got {self.ch_mult}")
        if self.image_size % 2 ** (len(self.ch_mult) - 1):
            raise ValueError(f"CodebookConfig.image_size={self.image_size} is not divisible by "
                             f"2^{len(self.ch_mult) - 1}")
        if any((self.ch * m) % 32 for m in self.ch_mult):
            raise ValueError(f"CodebookConfig: every level's channels ch * ch_mult = "
                             f"{[self.ch * m for m in self.ch_mult]} must be divisible by the 32 GroupNorm groups")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"CodebookConfig.dtype must be 'float32' or 'float64', got {self.dtype!r}")

    @property
    def token_size(self):
        """k: a code image is k x k."""
        return self.image_size // 2 ** (len(self.ch_mult) - 1)


def _conv(shapes, name, cin, cout, k):
    shapes[name + ".weight"] = (cout, cin, k, k)
    shapes[name + ".bias"] = (cout,)


def _norm(shapes, name, c):
    shapes[name + ".weight"] = (c,)
    shapes[name + ".bias"] = (c,)


def _resblock(shapes, name, cin, cout):
    _norm(shapes, name + ".norm1", cin)
    _conv(shapes, name + ".conv1", cin, cout, 3)
    _norm(shapes, name + ".norm2", cout)
    _conv(shapes, name + ".conv2", cout, cout, 3)
    if cin != cout:
        _conv(shapes, name + ".nin_shortcut", cin, cout, 1)


def _attn(shapes, name, c):
    _norm(shapes, name + ".norm", c)
    for p in ("q", "k", "v", "proj_out"):
        _conv(shapes, f"{name}.{p}", c, c, 1)


def parameter_shapes(cfg):
    """torch name -> shape of every parameter (not the quantizer's buffers), in the published order."""
    s = {}
    ch, mult, nres = cfg.ch, cfg.ch_mult, cfg.num_res_blocks
    _conv(s, "encoder.conv_in", cfg.in_channels, ch, 3)
    res, cin = cfg.image_size, ch
    for l, m in enumerate(mult):
        for i in range(nres):
            _resblock(s, f"encoder.down.{l}.block.{i}", cin, ch * m)
            cin = ch * m
            if res in cfg.attn_resolutions:
                _attn(s, f"encoder.down.{l}.attn.{i}", cin)
        if l != len(mult) - 1:
            _conv(s, f"encoder.down.{l}.downsample.conv", cin, cin, 3)
            res //= 2
    _resblock(s, "encoder.mid.block_1", cin, cin)
    _attn(s, "encoder.mid.attn_1", cin)
    _resblock(s, "encoder.mid.block_2", cin, cin)
    _norm(s, "encoder.norm_out", cin)
    _conv(s, "encoder.conv_out", cin, cfg.z_channels, 3)
    cin = ch * mult[-1]
    _conv(s, "decoder.conv_in", cfg.z_channels, cin, 3)
    _resblock(s, "decoder.mid.block_1", cin, cin)
    _attn(s, "decoder.mid.attn_1", cin)
    _resblock(s, "decoder.mid.block_2", cin, cin)
    for l in reversed(range(len(mult))):
        for i in range(nres + 1):
            _resblock(s, f"decoder.up.{l}.block.{i}", cin, ch * mult[l])
            cin = ch * mult[l]
            if res in cfg.attn_resolutions:
                _attn(s, f"decoder.up.{l}.attn.{i}", cin)
        if l != 0:
            _conv(s, f"decoder.up.{l}.upsample.conv", cin, cin, 3)
            res *= 2
    _norm(s, "decoder.norm_out", cin)
    _conv(s, "decoder.conv_out", cin, cfg.out_ch, 3)
    _conv(s, "quant_conv", cfg.z_channels, cfg.embed_dim, 1)
    _conv(s, "post_quant_conv", cfg.embed_dim, cfg.z_channels, 1)
    return s


def trace_names(cfg):
    """The names forward(..., trace=True) records for configuration cfg, in execution order."""
    names = []

    def res(name, cin, cout):
        names.extend(name + s for s in (".norm1", ".conv1", ".norm2", ".conv2"))
        if cin != cout:
            names.append(name + ".nin_shortcut")
        names.append(name)

    def mid(p, c):
        res(p + ".mid.block_1", c, c)
        names.append(p + ".mid.attn_1")
        res(p + ".mid.block_2", c, c)

    ch, mult, L = cfg.ch, cfg.ch_mult, len(cfg.ch_mult)
    names.append("encoder.conv_in")
    r, cin = cfg.image_size, ch
    for l in range(L):
        for i in range(cfg.num_res_blocks):
            res(f"encoder.down.{l}.block.{i}", cin, ch * mult[l])
            cin = ch * mult[l]
            if r in cfg.attn_resolutions:
                names.append(f"encoder.down.{l}.attn.{i}")
        if l != L - 1:
            names.append(f"encoder.down.{l}.downsample.conv")
            r //= 2
    mid("encoder", cin)
    names += ["encoder.norm_out", "encoder.conv_out", "quant_conv", "quantize", "post_quant_conv", "decoder.conv_in"]
    cin = ch * mult[-1]
    mid("decoder", cin)
    for l in reversed(range(L)):
        for i in range(cfg.num_res_blocks + 1):
            res(f"decoder.up.{l}.block.{i}", cin, ch * mult[l])
            cin = ch * mult[l]
            if r in cfg.attn_resolutions:
                names.append(f"decoder.up.{l}.attn.{i}")
        if l != 0:
            names += [f"decoder.up.{l}.upsample.interp", f"decoder.up.{l}.upsample.conv"]
            r *= 2
    names += ["decoder.norm_out", "decoder.conv_out", "rec_loss", "commitment_loss"]
    if cfg.perceptual_weight:
        names.append("perceptual_loss")
    names.append("loss")
    return names


@dataclasses.dataclass
class CodebookOutput:
    reconstruction: np.ndarray  # (B, out_ch, S, S)
    codes: np.ndarray  # (B, k, k) int64
    rec_loss: float  # mean |x - x_hat|
    commitment_loss: float  # mean (sg(e) - z)^2
    loss: float  # rec_loss + perceptual_weight * perceptual_loss + codebook_weight * commitment_loss
    usage: float  # fraction of codes used by the batch
    perplexity: float
    perceptual_loss: float = None  # mean over images of the perceptual module's loss; None when off
    trace: dict = None  # forward(..., trace=True) only: name -> activation (read-only), trace_names(cfg) order


def _add_grad(grads, name, g):
    """grads[name] += g; the first gradient of a parameter is stored as is (a fresh array from the
    layer's backward: no zero-filled copy of every parameter, 270 MB for the paper's codebook)."""
    if name in grads:
        grads[name] += g
    else:
        grads[name] = g


class Codebook:
    """The VQ-VAE: `params` (torch name -> array), `quantizer` (the EMA buffers), forward, backward.

    perceptual: the optional perceptual term (LPIPS in the paper, whose pretrained VGG weights
    are not bundled), any object with `forward(x, x_hat) -> (loss (B,), cache)` and
    `backward(dloss (B,), cache) -> dx_hat`; weighted by config.perceptual_weight, which must
    then be positive. Without one, perceptual_weight must be 0: the term is never silently dropped.
    """

    def __init__(self, config, seed=0, perceptual=None):
        if not isinstance(config, CodebookConfig):
            raise TypeError(f"config must be a CodebookConfig, got {type(config).__name__}")
        if (perceptual is None) != (config.perceptual_weight == 0):
            raise ValueError(f"perceptual_weight={config.perceptual_weight} needs a perceptual module, and a "
                             "perceptual module needs perceptual_weight > 0 (LPIPS weights are not bundled)")
        if perceptual is not None and not (callable(getattr(perceptual, "forward", None))
                                           and callable(getattr(perceptual, "backward", None))):
            raise TypeError("perceptual must have forward(x, x_hat) and backward(dloss, cache)")
        self.perceptual = perceptual
        self.config = config
        self.dtype = np.dtype(config.dtype)
        rng = np.random.default_rng(seed)
        self.params = {}
        for name, shape in parameter_shapes(config).items():
            if len(shape) == 4:  # conv weights: torch's default kaiming-uniform bound 1/sqrt(fan_in)
                bound = 1.0 / np.sqrt(np.prod(shape[1:]))
                p = rng.uniform(-bound, bound, shape)
            elif name.endswith(".weight"):  # GroupNorm gamma
                p = np.ones(shape)
            else:
                p = np.zeros(shape)
            self.params[name] = p.astype(self.dtype)
        self.quantizer = EMAQuantizer(config.embed_dim, config.n_embed, config.decay, config.eps,
                                      config.dtype, seed=seed + 1)
        self._cache = None
        self._trace = None  # during a traced forward only: the dict _op records into

    # -----------------------------------------------------------------------------------
    # weights

    def state_dict(self, layout="torch"):
        """torch name -> array, the quantizer's buffers included (copies), in `layout` (see
        load_official): "torch", the published state dict (nn.Conv2d kernels (out, in, kh, kw)),
        or "tf", channels-last kernels (kh, kw, in, out) as TF/Keras Conv2D and Flax nn.Conv
        hold them. Every other entry is the same in both."""
        layout = _weight_layout(layout)
        state = {name: _to_layout(name, p, layout) for name, p in self.params.items()}
        state.update({"quantize." + k: v for k, v in self.quantizer.state_dict().items()})
        return state

    def load_official(self, state_dict, *, layout="torch"):
        """Load a state dict (name -> array): every parameter and the four quantize.* buffers,
        nothing else; names as the published torch state dict (a Lightning checkpoint's
        `model.` prefix is dropped; other keys of such a checkpoint, e.g. `loss.*`, are
        unexpected: `pyvf convert torch-codebook` skips them).

        layout: the caller states the convention of the conv kernels (every 4-d `.weight`), so a
        kernel is never silently transposed:
          "torch" the published state dict = torch nn.Conv2d's (out, in, kh, kw);
          "tf"    channels-last (kh, kw, in, out): TF/Keras Conv2D, Flax nn.Conv; transposed here.
        Biases, GroupNorm parameters and the quantizer's buffers (`quantize.embeddings` is
        (embed_dim, n_embed) in both: codes are columns) are never transposed.

        Entries may be numpy arrays or anything with `.detach()` (torch tensors, also ones that
        require grad: `.detach().cpu().numpy()` is called; pyvf never imports torch). Everything is
        checked before anything is assigned: names (missing, unexpected, given twice), every
        array (float32/float64 of the parameter's shape in `layout`, finite; other dtypes are
        refused, not cast; the counter a non-negative integer). Any problem raises one ValueError
        naming every wrong entry (TypeError when all of them are wrong types), and the model is
        left unchanged. Float arrays are converted to the model's dtype (the one conversion pyvf
        makes, on purpose); the model never aliases the caller's arrays."""
        layout = _weight_layout(layout)
        if not isinstance(state_dict, Mapping):
            raise TypeError(f"load_official: state_dict must be a dict name -> array, got {type(state_dict).__name__}")
        shapes = parameter_shapes(self.config)
        problems, entries, given_as, unexpected = [], {}, {}, []
        for raw_name, arr in state_dict.items():
            name = raw_name[len("model."):] if isinstance(raw_name, str) and raw_name.startswith("model.") else raw_name
            if name not in shapes and name not in BUFFERS:
                unexpected.append(repr(raw_name))
                continue
            if name in given_as:
                problems.append((ValueError, f"{name!r} given twice (as {given_as[name]!r} and {raw_name!r})"))
                continue
            given_as[name] = raw_name
            arr, problem = _checks.checkpoint_array(raw_name, arr)  # torch tensors -> numpy
            if problem is not None:
                problems.append(problem)
            else:
                entries[name] = arr
        missing = [k for k in (*shapes, *BUFFERS) if k not in given_as]
        if missing:
            problems.append((ValueError, f"{len(missing)} names missing: {missing}"))
        if unexpected:
            problems.append((ValueError, f"unexpected names {', '.join(sorted(unexpected))}"))
        params = {}
        hint = " (layout='tf': conv kernels (kh, kw, in, out))" if layout == "tf" else ""
        for name, shape in shapes.items():
            if name in entries:
                a = entries[name]
                problem = _checks.weight_problem(given_as[name], a, _layout_shape(name, shape, layout), hint=hint)
                if problem is None:
                    params[name] = np.array(_from_layout(name, a, layout), dtype=self.dtype, order="C", copy=True)
                else:
                    problems.append(problem)
        prefix = "quantize."
        buffers, buffer_problems = self.quantizer.check_state(
            {k[len(prefix):]: entries[k] for k in BUFFERS if k in entries}, prefix=prefix, require_all=False)
        problems += buffer_problems
        if problems:
            raise _checks.problems_error("load_official", problems)
        self.quantizer._assign(buffers)
        self.params = params

    def save(self, path):
        """Write the configuration, the parameters and the quantizer's buffers to one .npz file.

        path: a str or os.PathLike (".npz" appended when missing, so `Codebook.load` needs the
        name with ".npz"), written atomically, or an open binary file; see pyvf._io.save_model.
        Returns the path written (or the file)."""
        return save_model(path, self.config, self.state_dict())

    @classmethod
    def load(cls, path):
        """Read a codebook written by save(): path as given (no ".npz" appended), or an open
        binary file. A missing file raises FileNotFoundError; a truncated or corrupt file, a bad
        configuration or any missing, unexpected, wrongly shaped or non-finite entry raises
        pyvf._io.CheckpointError (a ValueError) naming the file and every wrong entry."""
        return _checks.load_model(path, "codebook", CodebookConfig, cls)

    # -----------------------------------------------------------------------------------
    # the tape

    def _op(self, tape, kind, name, x, **kw):
        """Run one layer, record it on the tape, return its output. tape None: inference, no
        backward will follow; nothing is kept, so each activation is freed once the next layer has
        read it (encode and decode_code: peak memory a few activations, not the whole network's)."""
        P = self.params
        keep = tape is not None
        if kind == "conv":
            y, c = conv2d_forward(x, P[name + ".weight"], P[name + ".bias"], kw.get("stride", 1), kw.get("padding", 0))
        elif kind == "norm_swish":  # Normalize (32 groups, eps 1e-6, docs/math.md §4) then swish, fused
            y, c = groupnorm_swish_forward(x, P[name + ".weight"], P[name + ".bias"])
        elif kind == "upsample":
            y, c = upsample_nearest2x_forward(x)
        elif kind == "res":
            y, c = self._resblock_forward(name, x, keep)
        elif kind == "attn":
            y, c = attnblock_forward(x, *(P[name + s] for s in ATTN_PARAMS))
        else:
            raise AssertionError(kind)
        if keep:
            tape.append((kind, name, c))
        if self._trace is not None:
            self._trace[name] = y
        return y

    def _backward(self, tape, dy, grads, g=None):
        """Replay a tape in reverse: dy is the gradient of its last output; returns that of its input.
        g: None, or a dict each op's output gradient is recorded in (by the op's name)."""
        for kind, name, c in reversed(tape):
            if g is not None:
                g[name] = dy
            if kind == "conv":
                dy, dw, db = conv2d_backward(dy, c)
                _add_grad(grads, name + ".weight", dw)
                _add_grad(grads, name + ".bias", db)
            elif kind == "norm_swish":
                dy, dg, db = groupnorm_swish_backward(dy, c)
                _add_grad(grads, name + ".weight", dg)
                _add_grad(grads, name + ".bias", db)
            elif kind == "upsample":
                (dy,) = upsample_nearest2x_backward(dy, c)
            elif kind == "res":
                dy = self._resblock_backward(dy, c, grads, g)
            elif kind == "attn":
                dy, *dparams = attnblock_backward(dy, c)
                for suffix, dp in zip(ATTN_PARAMS, dparams):
                    _add_grad(grads, name + suffix, dp)
        return dy

    def _resblock_forward(self, name, x, keep=True):
        """ResnetBlock: norm1, swish, conv1, norm2, swish, conv2; + x (or nin_shortcut(x)).
        keep False: inference (see _op), nothing recorded."""
        main, short = ([], []) if keep else (None, None)
        h = self._op(main, "norm_swish", name + ".norm1", x)
        h = self._op(main, "conv", name + ".conv1", h, padding=1)
        h = self._op(main, "norm_swish", name + ".norm2", h)
        h = self._op(main, "conv", name + ".conv2", h, padding=1)
        s = self._op(short, "conv", name + ".nin_shortcut", x) if name + ".nin_shortcut.weight" in self.params else x
        if self._trace is None:  # h, conv2's fresh output, is referenced nowhere else: add in place
            h += s
            return h, (main, short)
        return s + h, (main, short)  # the trace keeps h itself

    def _resblock_backward(self, dy, cache, grads, g=None):
        main, short = cache
        ds = self._backward(short, dy, grads, g)  # first: g stays the trace's order reversed
        return self._backward(main, dy, grads, g) + ds  # y = s(x) + h(x)

    # -----------------------------------------------------------------------------------
    # encoder and decoder

    def _encoder(self, tape, x):
        """x (B, in_channels, S, S) -> z (B, embed_dim, k, k), after quant_conv."""
        cfg = self.config
        h = self._op(tape, "conv", "encoder.conv_in", x, padding=1)
        res = cfg.image_size
        for l in range(len(cfg.ch_mult)):
            for i in range(cfg.num_res_blocks):
                h = self._op(tape, "res", f"encoder.down.{l}.block.{i}", h)
                if res in cfg.attn_resolutions:
                    h = self._op(tape, "attn", f"encoder.down.{l}.attn.{i}", h)
            if l != len(cfg.ch_mult) - 1:
                # docs/math.md §4 Downsample: zero-pad right and bottom by one, then 3x3 stride 2 pad 0
                h = self._op(tape, "conv", f"encoder.down.{l}.downsample.conv", h, stride=2, padding=(0, 1, 0, 1))
                res //= 2
        h = self._op(tape, "res", "encoder.mid.block_1", h)
        h = self._op(tape, "attn", "encoder.mid.attn_1", h)
        h = self._op(tape, "res", "encoder.mid.block_2", h)
        h = self._op(tape, "norm_swish", "encoder.norm_out", h)
        h = self._op(tape, "conv", "encoder.conv_out", h, padding=1)
        return self._op(tape, "conv", "quant_conv", h)

    def _decoder(self, tape, z):
        """z (B, embed_dim, k, k) quantized -> images (B, out_ch, S, S), from post_quant_conv on."""
        cfg = self.config
        h = self._op(tape, "conv", "post_quant_conv", z)
        h = self._op(tape, "conv", "decoder.conv_in", h, padding=1)
        h = self._op(tape, "res", "decoder.mid.block_1", h)
        h = self._op(tape, "attn", "decoder.mid.attn_1", h)
        h = self._op(tape, "res", "decoder.mid.block_2", h)
        res = cfg.token_size
        for l in reversed(range(len(cfg.ch_mult))):  # decoder.up.{l} is indexed by level, run last to first
            for i in range(cfg.num_res_blocks + 1):
                h = self._op(tape, "res", f"decoder.up.{l}.block.{i}", h)
                if res in cfg.attn_resolutions:
                    h = self._op(tape, "attn", f"decoder.up.{l}.attn.{i}", h)
            if l != 0:
                h = self._op(tape, "upsample", f"decoder.up.{l}.upsample.interp", h)
                h = self._op(tape, "conv", f"decoder.up.{l}.upsample.conv", h, padding=1)
                res *= 2
        h = self._op(tape, "norm_swish", "decoder.norm_out", h)
        return self._op(tape, "conv", "decoder.conv_out", h, padding=1)

    # -----------------------------------------------------------------------------------
    # the model

    def _check_images(self, images):
        cfg = self.config
        if not isinstance(images, np.ndarray) or images.dtype != self.dtype:
            raise TypeError(f"images must be a {self.dtype} numpy array, got "
                            f"{getattr(images, 'dtype', type(images).__name__)}")
        S = cfg.image_size
        if images.ndim != 4 or images.shape[1:] != (cfg.in_channels, S, S) or images.shape[0] < 1:
            raise ValueError(f"images must have shape (B, {cfg.in_channels}, {S}, {S}), got {images.shape}")
        _checks.finite("images", images)
        lo, hi = float(images.min()), float(images.max())
        if lo < -1 - IMAGE_RANGE_SLACK or hi > 1 + IMAGE_RANGE_SLACK:  # e.g. 0..255 pixels passed as they are
            raise ValueError(f"images must be in [-1, 1], got values in [{lo:.4g}, {hi:.4g}]: convert uint8 "
                             "pictures (B, S, S, 3) with pyvf.evaluate.metrics.to_model_images(pictures, dtype), "
                             "x / 127.5 - 1 in NCHW order")

    def encode(self, images, *, return_latent=False):
        """images (B, in_channels, S, S) in [-1, 1] -> codes (B, k, k) int64; with
        return_latent=True, (z, codes): also the encoder's unquantized output z (B, D, k, k)."""
        self._check_images(images)
        z = self._encoder(None, images)  # (B, D, k, k)
        out, _ = self.quantizer.forward(z, train=False)
        return (z, out.codes) if return_latent else out.codes

    def decode_code(self, codes):
        """codes (B, k, k) ints in [0, n_embed) -> images (B, out_ch, S, S)."""
        cfg = self.config
        if not isinstance(codes, np.ndarray) or codes.dtype.kind not in "iu":
            raise TypeError("codes must be an integer numpy array")
        k = cfg.token_size
        if codes.ndim != 3 or codes.shape[1:] != (k, k):
            raise ValueError(f"codes must have shape (B, {k}, {k}), got {codes.shape}")
        if codes.size and (codes.min() < 0 or codes.max() >= cfg.n_embed):
            raise ValueError(f"codes must be in [0, {cfg.n_embed})")
        e = self.quantizer.embeddings.T[codes]  # (B, k, k, D): the codes are columns
        return self._decoder(None, np.ascontiguousarray(e.transpose(0, 3, 1, 2)))

    def forward(self, images, train=False, *, trace=False, pixel_weights=None):
        """images (B, in_channels, S, S) -> CodebookOutput; train=True updates the EMA buffers
        (the output uses the codes from before the update). Keeps what backward() needs.

        pixel_weights: None (rec_loss = mean |rec - x|, as published), or non-negative weights
        (B, 1, S, S) of the model's dtype, not all zero: rec_loss = sum_b,c,y,x w_b,y,x |rec - x|
        / (in_channels * sum w), the weighted mean (equal weights give the plain mean).

        trace=True also returns, as `out.trace`, every intermediate activation by name
        (trace_names(config), in execution order; read-only views of what the forward keeps
        anyway: do not modify them), and makes the next backward() return every activation's
        gradient."""
        if not isinstance(trace, (bool, np.bool_)):
            raise TypeError(f"trace must be True or False, got {trace!r}")
        self._check_images(images)
        if pixel_weights is not None:
            _checks.float_array("pixel_weights", pixel_weights, images, "images")
            B, _, S, _ = images.shape
            if pixel_weights.shape != (B, 1, S, S):
                raise ValueError(f"pixel_weights must have shape {(B, 1, S, S)}, got {pixel_weights.shape}")
            _checks.finite("pixel_weights", pixel_weights)
            if (pixel_weights < 0).any() or not pixel_weights.any():
                raise ValueError("pixel_weights must be non-negative and not all zero")
        enc, dec = [], []
        tr = {} if trace else None  # None: nothing is recorded, nothing extra is computed
        saved = {k: v.copy() for k, v in self.quantizer.state_dict().items()} if train else None
        self._trace = tr
        try:
            z = self._encoder(enc, images)  # (B, D, k, k)
            q, c_q = self.quantizer.forward(z, train=train)
            if tr is not None:
                tr["quantize"] = q.quantized
            rec = self._decoder(dec, q.quantized)  # (B, out_ch, S, S)
        except BaseException:  # a failed call leaves the EMA buffers as they were
            if saved is not None:
                self.quantizer.load_state_dict(saved)
            raise
        finally:
            self._trace = None
        diff = rec - images
        if pixel_weights is None:
            rec_loss = float(np.mean(np.abs(diff)))
            drec_loss = np.sign(diff) / diff.size  # (B, C, S, S)
        else:  # sum w |diff| / (C sum w): the mean over channels of each pixel's weighted mean
            wsum = float(pixel_weights.sum(dtype=np.float64)) * diff.shape[1]
            rec_loss = float(np.sum(pixel_weights * np.abs(diff), dtype=np.float64) / wsum)
            drec_loss = np.sign(diff) * (pixel_weights / self.dtype.type(wsum))  # (B, C, S, S)
        loss = rec_loss + self.config.codebook_weight * q.commitment_loss
        perceptual, c_p = None, None
        if self.perceptual is not None:
            per_image, c_p = self.perceptual.forward(images, rec)  # (B,)
            perceptual = float(np.mean(per_image))
            loss += self.config.perceptual_weight * perceptual
        if tr is not None:
            tr["rec_loss"] = self.dtype.type(rec_loss)
            tr["commitment_loss"] = self.dtype.type(q.commitment_loss)
            if perceptual is not None:
                tr["perceptual_loss"] = self.dtype.type(perceptual)
            tr["loss"] = self.dtype.type(loss)
            for name, a in tr.items():  # read-only views: the caches behind them feed backward()
                if isinstance(a, np.ndarray):
                    tr[name] = a.view()
                    tr[name].flags.writeable = False
        self._cache = (enc, dec, c_q, drec_loss, c_p, images.shape[0], rec.shape, trace)
        return CodebookOutput(reconstruction=rec, codes=q.codes, rec_loss=rec_loss, commitment_loss=q.commitment_loss,
                              loss=loss, usage=q.usage, perplexity=q.perplexity, perceptual_loss=perceptual, trace=tr)

    def backward(self, drec=None, *, dloss=None):
        """Differentiate the last forward: the gradient of

            dloss * loss + sum(reconstruction * drec)

        (a vector-Jacobian product; a term whose seed is None is left out; with no seed at all,
        dloss = 1: the gradient of the loss, as training needs). drec (B, out_ch, S, S) is an
        array of the model's dtype, for out.reconstruction; dloss a real number. The commitment
        term (the encoder's only gradient besides the straight-through one) comes with dloss only.

        Returns torch parameter name -> gradient. After forward(..., trace=True) the dict first
        holds the gradient of every traced activation, in backward order (exactly the reverse of
        the trace), under the trace's names except the losses; then the parameters'."""
        if self._cache is None:
            raise RuntimeError("backward() needs a forward() first (and differentiates the last one)")
        enc, dec, c_q, drec_loss, c_p, B, rec_shape, traced = self._cache
        if drec is None and dloss is None:
            dloss = 1.0
        grads = {}  # filled by _add_grad; parameters the model did not use get zeros at the end
        total = np.zeros(rec_shape, dtype=self.dtype)  # (B, out_ch, S, S)
        dcommitment = 0.0
        if dloss is not None:
            dloss = _checks.real("dloss", dloss)
            # forward was rec_loss = mean |rec - x|, so drec = sign(rec - x) / numel (weighted: w / (C sum w))
            total = (dloss * drec_loss).astype(self.dtype)
            if c_p is not None:  # + perceptual_weight * mean_b perceptual(x, rec)_b
                dl = np.full(B, dloss * self.config.perceptual_weight / B, dtype=self.dtype)
                total = total + self.perceptual.backward(dl, c_p)
            dcommitment = dloss * self.config.codebook_weight
        if drec is not None:
            _checks.float_array("drec", drec)
            if drec.dtype != self.dtype:
                raise TypeError(f"drec is {drec.dtype} but the model is {self.dtype}: both must share one dtype "
                                "(pyvf never casts silently)")
            if drec.shape != tuple(rec_shape):
                raise ValueError(f"drec must have the reconstruction's shape {tuple(rec_shape)}, got {drec.shape}")
            _checks.finite("drec", drec)
            total = total + drec
        g = {} if traced else None  # the activations' gradients, the trace's order reversed
        dq = self._backward(dec, total, grads, g)
        if g is not None:
            g["quantize"] = dq
        (dz,) = self.quantizer.backward(dq, dcommitment, c_q)  # straight-through + commitment
        self._backward(enc, dz, grads, g)
        grads = {name: grads[name] if name in grads else np.zeros_like(p) for name, p in self.params.items()}
        if g is None:
            return grads
        for name, a in g.items():  # read-only views: one array can be several names' gradient
            g[name] = a.view()
            g[name].flags.writeable = False
        return {**g, **grads}
