"""The ViewFormer codebook: a VQ-VAE (taming-transformers style), docs/math.md §4, in NumPy.

    cfg = CodebookConfig(ch=32, ch_mult=(1, 1, 2, 2), num_res_blocks=1, attn_resolutions=(8,),
                         z_channels=32, embed_dim=32, n_embed=64, image_size=64)
    cb = Codebook(cfg, seed=0)
    codes = cb.encode(images)            # images (B, 3, S, S) in [-1, 1] -> (B, k, k) int64
    images = cb.decode_code(codes)
    out = cb.forward(images, train=True) # reconstruction, codes, rec_loss, commitment_loss, loss
    grads = cb.backward()                # d out.loss / d every parameter, torch names
    out = cb.forward(images, trace=True) # out.trace: name -> activation, execution order (pyvf.compare)

Parameters use the published torch names, conv weights (out, in, kh, kw); the quantizer's
buffers (`quantize.*`) live in an EMAQuantizer. The model is its layer table (layer_table(config)):
the forward records every row it runs on a tape, (row, cache), the backward replays it in reverse.
"""

import dataclasses
import hashlib

import numpy as np

from .. import _checks
from ..nn.conv import (attnblock_backward, attnblock_forward, conv2d_backward, conv2d_forward, groupnorm_swish_backward,
                       groupnorm_swish_forward, upsample_nearest2x_backward, upsample_nearest2x_forward)
from ..nn.quantizer import EMAQuantizer
from .io import Layer, ModelWeights, parameters, trace_order

BUFFERS = ("quantize.embeddings", "quantize.ema_cluster_size_hidden", "quantize.ema_dw_hidden", "quantize.counter")

# load_official's layouts: layout -> how it holds the conv kernels, the published one first
LAYOUTS = {"torch": "nn.Conv2d kernels (out, in, kh, kw), the published state dict",
           "tf": "conv kernels (kh, kw, in, out), channels-last as TF/Keras Conv2D and Flax nn.Conv hold them"}

# row kind -> its layer pair (forward, backward); "quantize" is the model's own
LAYER_PAIRS = {"conv": (conv2d_forward, conv2d_backward),
               "norm_swish": (groupnorm_swish_forward, groupnorm_swish_backward),
               "upsample": (upsample_nearest2x_forward, upsample_nearest2x_backward),
               "attn": (attnblock_forward, attnblock_backward)}

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
    codebook_weight: float = 1.0  # loss = rec_loss + codebook_weight * commitment
    perceptual_weight: float = 0.0  # the published LPIPS term's weight: not implemented, must be 0 (docs/math.md §4)
    dtype: str = "float32"
    # pyvf's own, not published: code 0 stands for the empty patch, whose every pixel has the colour
    # of the image's top-left pixel (a flat background, as SM7's); such patches take code 0 and no
    # other patch does (Codebook.empty_patches). False: every patch takes its nearest code.
    empty_code: bool = False

    ADDED_FIELDS = ("empty_code",)  # fields newer than some saved files; a file without one loads with the default

    def __post_init__(self):
        # integers: Python or NumPy (not bool), stored as int (the configuration is saved as JSON)
        for name in ("ch", "num_res_blocks", "z_channels", "embed_dim", "n_embed", "image_size", "in_channels",
                     "out_ch"):
            object.__setattr__(self, name, _checks.positive_integer(f"CodebookConfig.{name}", getattr(self, name)))
        for name in ("ch_mult", "attn_resolutions"):  # tuples of int (JSON-safe, hashable)
            object.__setattr__(self, name, tuple(_checks.positive_integer(f"CodebookConfig.{name}[{i}]", v)
                                                 for i, v in enumerate(getattr(self, name))))
        if not self.ch_mult:
            raise ValueError("CodebookConfig.ch_mult must name at least one level, got ()")
        # real numbers, stored as float; decay and eps in the quantizer's ranges
        for name, kw in (("decay", dict(lo=0.0, hi=1.0, lo_open=True, hi_open=True)),
                         ("eps", dict(lo=0.0, lo_open=True)), ("codebook_weight", {}), ("perceptual_weight", {})):
            object.__setattr__(self, name, _checks.real(f"CodebookConfig.{name}", getattr(self, name), **kw))
        if self.perceptual_weight:
            raise ValueError("CodebookConfig.perceptual_weight must be 0: pyvf has no LPIPS term (docs/math.md §4)")
        if self.image_size % 2 ** (len(self.ch_mult) - 1):
            raise ValueError(f"CodebookConfig.image_size={self.image_size} is not divisible by 2^{len(self.ch_mult) - 1}")
        if any((self.ch * m) % 32 for m in self.ch_mult):
            raise ValueError("CodebookConfig: every level's channels ch * ch_mult must be divisible by the 32 "
                             "GroupNorm groups")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"CodebookConfig.dtype must be 'float32' or 'float64', got {self.dtype!r}")
        object.__setattr__(self, "empty_code", bool(self.empty_code))  # a NumPy bool is not JSON

    @property
    def token_size(self):
        """k: a code image is k x k."""
        return self.image_size // 2 ** (len(self.ch_mult) - 1)


# ---------------------------------------------------------------------------------------
# the layer table: every layer once; the parameters, the trace, the forward and teacher forcing read it


def _conv(name, cin, cout, k, *, stride=1, padding=0, module=None):
    return Layer(name, "conv", ((".weight", (cout, cin, k, k), "conv_kernel"), (".bias", (cout,), None)),
                 stride=stride, padding=padding, module=module)


def _norm(name, c):
    """Normalize (32 groups, eps 1e-6, docs/math.md §4) then swish, fused."""
    return Layer(name, "norm_swish", ((".weight", (c,), None), (".bias", (c,), None)))


def _resblock(name, cin, cout):
    """ResnetBlock: norm1, swish, conv1, norm2, swish, conv2; + x (or nin_shortcut(x))."""
    body = (_norm(name + ".norm1", cin), _conv(name + ".conv1", cin, cout, 3, padding=1),
            _norm(name + ".norm2", cout), _conv(name + ".conv2", cout, cout, 3, padding=1))
    shortcut = (_conv(name + ".nin_shortcut", cin, cout, 1),) if cin != cout else ()
    return Layer(name, "res", body=body, shortcut=shortcut)


def _attn(name, c):
    """AttnBlock: x + proj_out(attention(q, k, v of norm(x))), residual included."""
    params = [(".norm.weight", (c,), None), (".norm.bias", (c,), None)]
    for p in ("q", "k", "v", "proj_out"):
        params += [(f".{p}.weight", (c, c, 1, 1), "conv_kernel"), (f".{p}.bias", (c,), None)]
    return Layer(name, "attn", tuple(params))


def _mid(part, c):
    return [_resblock(part + ".mid.block_1", c, c), _attn(part + ".mid.attn_1", c),
            _resblock(part + ".mid.block_2", c, c)]


def layer_table(cfg):
    """The codebook's layers for configuration cfg, in execution order (pyvf.models.io.Layer rows):
    the encoder, quant_conv, quantize, post_quant_conv, the decoder."""
    ch, mult, nres = cfg.ch, cfg.ch_mult, cfg.num_res_blocks
    rows = [_conv("encoder.conv_in", cfg.in_channels, ch, 3, padding=1)]
    res, cin = cfg.image_size, ch
    for l, m in enumerate(mult):
        for i in range(nres):
            rows.append(_resblock(f"encoder.down.{l}.block.{i}", cin, ch * m))
            cin = ch * m
            if res in cfg.attn_resolutions:
                rows.append(_attn(f"encoder.down.{l}.attn.{i}", cin))
        if l != len(mult) - 1:
            # docs/math.md §4 Downsample: zero-pad right and bottom by one, then 3x3 stride 2 pad 0
            rows.append(_conv(f"encoder.down.{l}.downsample.conv", cin, cin, 3, stride=2, padding=(0, 1, 0, 1),
                              module=f"encoder.down.{l}.downsample"))
            res //= 2
    rows += _mid("encoder", cin)
    rows += [_norm("encoder.norm_out", cin), _conv("encoder.conv_out", cin, cfg.z_channels, 3, padding=1),
             _conv("quant_conv", cfg.z_channels, cfg.embed_dim, 1),
             # the EMA quantizer (its buffers are not parameters); the empty code reads the images too
             Layer("quantize", "quantize", calls=((((("quant_conv", None), ("images", None)), "quantize"),)
                                                  if cfg.empty_code else None)),
             _conv("post_quant_conv", cfg.embed_dim, cfg.z_channels, 1)]
    cin = ch * mult[-1]
    rows.append(_conv("decoder.conv_in", cfg.z_channels, cin, 3, padding=1))
    rows += _mid("decoder", cin)
    for l in reversed(range(len(mult))):  # decoder.up.{l} is indexed by level, run last to first
        for i in range(nres + 1):
            rows.append(_resblock(f"decoder.up.{l}.block.{i}", cin, ch * mult[l]))
            cin = ch * mult[l]
            if res in cfg.attn_resolutions:
                rows.append(_attn(f"decoder.up.{l}.attn.{i}", cin))
        if l != 0:  # Upsample: nearest 2x, then conv 3x3 pad 1
            up = f"decoder.up.{l}.upsample"
            rows += [Layer(up + ".interp", "upsample", module=up),
                     _conv(up + ".conv", cin, cin, 3, padding=1, module=up)]
            res *= 2
    rows += [_norm("decoder.norm_out", cin), _conv("decoder.conv_out", cin, cfg.out_ch, 3, padding=1)]
    return tuple(rows)


def parameter_table(layers):
    """A table's parameters: torch name -> (shape, role), in the published order: the state dict
    registers the encoder, then the decoder, then the 1x1 convs around the quantizer."""
    rank = {"encoder": 0, "decoder": 1}
    return dict(sorted(parameters(layers).items(), key=lambda kv: rank.get(kv[0].split(".", 1)[0], 2)))


def parameter_shapes(cfg):
    """torch name -> shape of every parameter (not the quantizer's buffers), in the published order."""
    return {name: shape for name, (shape, _) in parameter_table(layer_table(cfg)).items()}


def trace_names(cfg):
    """The names forward(..., trace=True) records for configuration cfg, in execution order."""
    return trace_order(layer_table(cfg)) + ["rec_loss", "commitment_loss", "loss"]


@dataclasses.dataclass
class CodebookOutput:
    reconstruction: np.ndarray  # (B, out_ch, S, S)
    codes: np.ndarray  # (B, k, k) int64
    rec_loss: float  # mean |x - x_hat|
    commitment_loss: float  # mean (sg(e) - z)^2
    loss: float  # rec_loss + codebook_weight * commitment_loss
    usage: float  # fraction of codes used by the batch
    perplexity: float
    trace: dict = None  # forward(..., trace=True) only: name -> activation, trace_names(cfg) order


class Codebook(ModelWeights):
    """The VQ-VAE: `params` (torch name -> array), `quantizer` (the EMA buffers), forward, backward."""

    LAYOUTS = LAYOUTS
    FILE_KIND = "codebook"
    CONFIG = CodebookConfig
    INPUTS = ("images",)  # the model's inputs (teacher forcing: the first row reads the first)

    def __init__(self, config, seed=0):
        layers = layer_table(config)
        self._describe(config, layers, parameter_table(layers))
        at = [row.kind for row in layers].index("quantize")  # the encoder's rows, quantize, the decoder's
        self._encoder_rows, self._quantize_row, self._decoder_rows = layers[:at], layers[at], layers[at + 1:]
        rng = np.random.default_rng(seed)
        self.params = {}
        for name, (shape, role) in self._param_table.items():
            if role == "conv_kernel":  # torch's default kaiming-uniform bound 1/sqrt(fan_in)
                bound = 1.0 / np.sqrt(np.prod(shape[1:]))
                p = rng.uniform(-bound, bound, shape)
            elif name.endswith(".weight"):  # GroupNorm gamma
                p = np.ones(shape)
            else:
                p = np.zeros(shape)
            self.params[name] = p.astype(self.dtype)
        self.quantizer = EMAQuantizer(config.embed_dim, config.n_embed, config.decay, config.eps,
                                      config.dtype, seed=seed + 1)
        D, K = config.embed_dim, config.n_embed
        self.BUFFERS = dict(zip(BUFFERS, [(D, K), (K,), (D, K), None]))  # their shapes; None: the EMA count

    # -----------------------------------------------------------------------------------
    # weights (the mechanism: pyvf.models.io.ModelWeights)

    def official_name(self, name):
        """A Lightning checkpoint's `model.` prefix is dropped."""
        return name.removeprefix("model.")

    def fingerprint(self):
        """The sha256 (first 16 hex digits) of every parameter and the codes, in name order (not the
        EMA statistics): what makes the tokens, recorded by Transformer.codebook_fingerprint."""
        h = hashlib.sha256()
        for name, a in sorted({**self.params, "quantize.embeddings": self.quantizer.embeddings}.items()):
            h.update(f"{name} {a.dtype.str} {a.shape}".encode())
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()[:16]

    def _buffers(self):  # quantize.embeddings is (embed_dim, n_embed) in every layout: codes are columns
        return {"quantize." + k: v for k, v in self.quantizer.state_dict().items()}

    def _set_buffers(self, buffers):
        self.quantizer.load_state_dict({k[len("quantize."):]: v for k, v in buffers.items()})

    # -----------------------------------------------------------------------------------
    # one row of the table at a time (teacher forcing's reference, pyvf.verify.teacher)

    def layer_forward(self, row, x, images=None):
        """Run the table's row (not a residual block) on x -> (output, cache); images: the
        quantize row's second input under the empty code."""
        P = [self.params[n] for n in row.param_names]
        if row.kind == "conv":
            return conv2d_forward(x, *P, row.stride, row.padding)
        if row.kind == "quantize":  # the quantized z (no EMA step); its gradient is the straight-through one
            empty = None if images is None else self.empty_patches(images)
            return self.quantizer.forward(x, empty=empty)[0].quantized, None
        return LAYER_PAIRS[row.kind][0](x, *P)

    def layer_backward(self, row, dy, cache):
        """layer_forward's VJP -> ([dx], the gradients of row.param_names, in order)."""
        if row.kind == "quantize":  # forward was quantized = z + sg(e - z): the identity for the gradient
            return [dy], []
        dx, *dp = LAYER_PAIRS[row.kind][1](dy, cache)
        return [dx], dp

    # -----------------------------------------------------------------------------------
    # the tape

    def _run(self, rows, x, tape=None, tr=None):
        """Run rows of the table in turn on x, each recorded on the tape as (row, cache) (None:
        inference, nothing kept) and in the trace tr (name -> output; None: not traced)."""
        for row in rows:
            if row.kind == "res":
                x, c = self._resblock_forward(row, x, tape is not None, tr)
            else:
                x, c = self.layer_forward(row, x)
            if tape is not None:
                tape.append((row, c))
            if tr is not None:
                tr[row.name] = x
        return x

    def _backward(self, tape, dy, grads, g=None):
        """Replay a tape in reverse: dy is the gradient of its last output -> that of its input.
        g: None, or a dict each op's output gradient is recorded in (by the op's name)."""
        for row, c in reversed(tape):
            if g is not None:
                g[row.name] = dy
            if row.kind == "res":
                dy = self._resblock_backward(dy, c, grads, g)
                continue
            (dy,), dparams = self.layer_backward(row, dy, c)
            for name, dp in zip(row.param_names, dparams):
                # the first gradient is stored as is (fresh from the layer: no zero-filled copy of every parameter)
                if name in grads:
                    grads[name] += dp
                else:
                    grads[name] = dp
        return dy

    def _resblock_forward(self, row, x, keep, tr):
        """ResnetBlock: its body + x (or nin_shortcut(x)). keep False: inference, nothing recorded."""
        main, short = ([], []) if keep else (None, None)
        h = self._run(row.body, x, main, tr)
        s = self._run(row.shortcut, x, short, tr)
        if tr is None and row.body:  # h, conv2's fresh output, is referenced nowhere else: add in place
            return np.add(h, s, out=h), (main, short)
        return s + h, (main, short)  # the trace keeps h itself

    def _resblock_backward(self, dy, cache, grads, g=None):
        main, short = cache
        ds = self._backward(short, dy, grads, g)  # first: g stays the trace's order reversed
        dh = self._backward(main, dy, grads, g)
        # y = s(x) + h(x): the sum goes into dh, the body's fresh dx, which nothing else holds (a
        # fresh array for it, 16 MiB at the paper's 128x128, cost 4x the add in page faults); not
        # where dh is dy or ds itself (an empty body)
        in_place = not (np.may_share_memory(dh, dy) or np.may_share_memory(dh, ds))
        return np.add(dh, ds, out=dh if in_place else None)

    def _encoder(self, tape, x, tr=None):
        """x (B, in_channels, S, S) -> z (B, embed_dim, k, k): the table's rows before quantize."""
        return self._run(self._encoder_rows, x, tape, tr)

    # -----------------------------------------------------------------------------------
    # the model

    def _check_images(self, images):
        """images (B, in_channels, S, S) of the model's dtype, finite, in [-1, 1] -> C-ordered."""
        cfg, S = self.config, self.config.image_size
        hint = ": convert uint8 pictures (B, S, S, 3) with pyvf.evaluate.metrics.to_model_images"
        self._check_array("images", images, ("B", cfg.in_channels, S, S), hint=hint)
        if images.min() < -1 - IMAGE_RANGE_SLACK or images.max() > 1 + IMAGE_RANGE_SLACK:
            raise ValueError(f"images must be in [-1, 1]{hint}")
        return np.ascontiguousarray(images)

    def empty_patches(self, images):
        """images (B, C, S, S) -> None without config.empty_code, else bool (B, k, k): the patches
        of the k x k grid whose every pixel has the colour of the image's top-left pixel."""
        if not self.config.empty_code:
            return None
        B, _, S, _ = images.shape
        k = self.config.token_size
        p = S // k
        differs = (images != images[:, :, :1, :1]).any(axis=1)  # (B, S, S): an object pixel
        return ~differs.reshape(B, k, p, k, p).any(axis=(2, 4))

    def encode(self, images, *, return_latent=False):
        """images (B, in_channels, S, S) in [-1, 1] -> codes (B, k, k) int64; with
        return_latent=True, (z, codes): also the encoder's unquantized output z (B, D, k, k)."""
        images = self._check_images(images)
        z = self._encoder(None, images)  # (B, D, k, k)
        out, _ = self.quantizer.forward(z, train=False, empty=self.empty_patches(images))
        return (z, out.codes) if return_latent else out.codes

    def decode_code(self, codes):
        """codes (B, k, k) ints in [0, n_embed) -> images (B, out_ch, S, S)."""
        cfg, k = self.config, self.config.token_size
        self._check_array("codes", codes, ("B", k, k), kind="iu")
        if codes.min() < 0 or codes.max() >= cfg.n_embed:
            raise ValueError(f"codes must be in [0, {cfg.n_embed})")
        e = self.quantizer.embeddings.T[codes]  # (B, k, k, D): the codes are columns
        return self._run(self._decoder_rows, np.ascontiguousarray(e.transpose(0, 3, 1, 2)))

    def decode_latent(self, z):
        """z (B, embed_dim, k, k), a point of the code space (e.g. the codes' expectation under a
        transformer's distribution) -> images (B, out_ch, S, S)."""
        k = self.config.token_size
        self._check_array("z", z, ("B", self.config.embed_dim, k, k))
        return self._run(self._decoder_rows, np.ascontiguousarray(z))

    def forward(self, images, train=False, *, trace=False, pixel_weights=None):
        """images (B, in_channels, S, S) -> CodebookOutput; train=True updates the EMA buffers
        (the output uses the codes from before the update). pixel_weights: None (rec_loss = mean
        |rec - x|, as published), or (B, 1, S, S) >= 0, not all zero: rec_loss = sum w |rec - x| /
        (in_channels sum w). trace=True: also every activation as `out.trace` (trace_names(config))."""
        images = self._check_images(images)
        if pixel_weights is not None:
            B, _, S, _ = images.shape
            self._check_array("pixel_weights", pixel_weights, (B, 1, S, S))
            if (pixel_weights < 0).any() or not pixel_weights.any():
                raise ValueError("pixel_weights must be non-negative and not all zero")
        enc, dec = [], []
        tr = {} if trace else None  # None: nothing is recorded, nothing extra is computed
        z = self._encoder(enc, images, tr)  # (B, D, k, k)
        q, c_q = self.quantizer.forward(z, train=train, empty=self.empty_patches(images))
        if tr is not None:
            tr[self._quantize_row.name] = q.quantized
        rec = self._run(self._decoder_rows, q.quantized, dec, tr)  # (B, out_ch, S, S)
        diff = rec - images
        if pixel_weights is None:
            rec_loss = float(np.mean(np.abs(diff)))
            drec_loss = np.sign(diff) / diff.size  # (B, C, S, S)
        else:  # sum w |diff| / (C sum w): the mean over channels of each pixel's weighted mean
            # normalised in float64 first, wn = w / (C sum w): in float32, C sum w (or w |diff|)
            # overflows for weights near float32's largest, and w / inf = 0 is a silent zero gradient
            wsum = float(pixel_weights.sum(dtype=np.float64)) * diff.shape[1]
            wn = np.divide(pixel_weights, wsum, dtype=np.float64)  # (B, 1, S, S) float64, each <= 1/C
            rec_loss = float(np.sum(wn * np.abs(diff), dtype=np.float64))
            drec_loss = np.sign(diff) * wn.astype(self.dtype)  # (B, C, S, S)
        loss = rec_loss + self.config.codebook_weight * q.commitment_loss
        if tr is not None:
            tr["rec_loss"] = self.dtype.type(rec_loss)
            tr["commitment_loss"] = self.dtype.type(q.commitment_loss)
            tr["loss"] = self.dtype.type(loss)
        self._cache = (enc, dec, c_q, drec_loss, rec.shape, trace)
        return CodebookOutput(reconstruction=rec, codes=q.codes, rec_loss=rec_loss, commitment_loss=q.commitment_loss,
                              loss=loss, usage=q.usage, perplexity=q.perplexity, trace=tr)

    def backward(self, drec=None, *, dloss=None):
        """The gradient of the last forward's dloss * loss + sum(reconstruction * drec), a term whose
        seed is None left out (no seed at all: dloss = 1) -> torch parameter name -> gradient; after
        forward(..., trace=True), first every traced activation's gradient (but the losses'), in
        backward order."""
        if self._cache is None:
            raise RuntimeError("backward() needs a forward() first (and differentiates the last one)")
        enc, dec, c_q, drec_loss, rec_shape, traced = self._cache
        if drec is None and dloss is None:
            dloss = 1.0
        if drec is not None:
            self._check_array("drec", drec, rec_shape)
        if dloss is not None:
            dloss = _checks.real("dloss", dloss)
        grads = {}  # filled by _backward; parameters the model did not use get zeros at the end
        total = np.zeros(rec_shape, dtype=self.dtype)  # (B, out_ch, S, S)
        dcommitment = 0.0
        if dloss is not None:
            # forward was rec_loss = mean |rec - x|, so drec = sign(rec - x) / numel (weighted: w / (C sum w))
            total = (dloss * drec_loss).astype(self.dtype)
            dcommitment = dloss * self.config.codebook_weight
        if drec is not None:
            total = total + drec
        g = {} if traced else None  # the activations' gradients, the trace's order reversed
        dq = self._backward(dec, total, grads, g)
        if g is not None:
            g[self._quantize_row.name] = dq
        (dz,) = self.quantizer.backward(dq, dcommitment, c_q)  # straight-through + commitment
        self._backward(enc, dz, grads, g)
        grads = {name: grads[name] if name in grads else np.zeros_like(p) for name, p in self.params.items()}
        return grads if g is None else {**g, **grads}  # (one array can be several names' gradient)
