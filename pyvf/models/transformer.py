"""The ViewFormer transformer ("MIGT" in the published code), docs/math.md §3, in NumPy.

One forward builds the three rows of the tree from tokens and poses, runs every block on all
rows at once (rows meet only in the branching attention), and gives the generation logits, the
pose predictions and both losses; backward() is the same code read in reverse.

    cfg = TransformerConfig(n_embeddings=64, n_head=2, d_model=32, n_layer=2,
                            token_image_size=4, sequence_size=5, n_loss_skip=1)
    model = Transformer(cfg, seed=0)
    out = model.forward(tokens, poses)      # tokens (B, N, L) ints in [0, V), poses (B, N, 7)
    grads = model.backward()                # d out.loss / d every parameter, official names
    out = model.forward(tokens, poses, trace=True)  # out.trace: name -> activation (TRACE_NAMES)

Rows (each (B, N, L, d)), E = wte[tokens], W = wpe[0:L], P = pose_embedding(poses):
    0 trunk:        E + W + P
    1 generation:   wte[V] + W + P        (image hidden, pose kept)
    2 localization: E + W + wte[V + 1]    (image kept, pose replaced by the localization token)

Parameters are named as in the published checkpoint (tests/data/official-transformer-tiny.json, without
the `migt/` prefix and `:0` suffix); linear weights are (in, out), biases (1, out).
"""

import dataclasses

import numpy as np

from .. import _checks
from ..geometry import absolute_poses, average_pose, make_relative, quat_canonical, quat_normalize, relative_poses
from ..nn.attention import _fused_heads, attention_layer_backward, attention_layer_forward
from ..nn.layers import (embedding_backward, embedding_forward, layernorm_backward, layernorm_forward, matmul,
                         mlp_backward, mlp_forward)
from ..nn.losses import cross_entropy_backward, cross_entropy_forward, pose_loss_backward, pose_loss_forward
from .io import Layer, ModelWeights, parameters

MAX_TOKENS_PER_VIEW = 256  # wpe has 256 rows: token t of every view gets row t
DENSE_PAIR = ("c_fc/weight", "c_fc/bias", "c_proj/weight", "c_proj/bias")  # an MLP's parameters, mlp_forward's order
ATTN_PARAMS = ("c_attn/weight", "c_attn/bias", "c_proj/weight", "c_proj/bias")  # attention_layer_forward's order
NORM = ("gamma", "beta")
# row kind -> its layer pair (forward, backward); "embed" and "logits" are the model's own
LAYER_PAIRS = {"layernorm": (layernorm_forward, layernorm_backward), "mlp": (mlp_forward, mlp_backward),
               "attention": (attention_layer_forward, attention_layer_backward)}
POSE_HEAD = "quaternion_pose_representation/pose_classifier/"

# What forward(..., trace=True) records, in execution order ("{j}": every block). Layouts are the
# tree's: R = 3 rows (trunk, generation, localization), heads split as the kernel takes them.
# A port holding (B, T, d) with T in [row][view][token] reshapes to (B, R, N, L, d) and moves R first.
TRACE_NAMES = (
    "embed.tokens",              # (B, N, L, d)     E = wte[tokens]
    "embed.positions",           # (L, d)           W = wpe[0:L]
    "pose_embedding.input",      # (B, N, 7)        xyz * pose_multiplier, quaternion
    "pose_embedding.c_fc",       # (B, N, 2d)       before GELU
    "pose_embedding.gelu",       # (B, N, 2d)
    "pose_embedding.c_proj",     # (B, N, d)        P, before the broadcast over L
    "embed.out",                 # (R, B, N, L, d)  the three rows: E+W+P, wte[V]+W+P, E+W+wte[V+1]
    "blocks.{j}.ln_1",           # (R, B, N, L, d)
    "blocks.{j}.attn.c_attn",    # (R, B, N, L, 3d) fused columns [v | q | k] (docs/math.md §3)
    "blocks.{j}.attn.q",         # (R, B, H, N, L, dh)
    "blocks.{j}.attn.k",         # (R, B, H, N, L, dh)
    "blocks.{j}.attn.v",         # (R, B, H, N, L, dh)
    "blocks.{j}.attn.out",       # (R, B, H, N, L, dh) branching attention's output, before the heads merge
    "blocks.{j}.attn.lse",       # (R, B, H, N, L)  log-sum-exp of each query's attended logits, float64
                                 #                  even in a float32 model (compare(..., dtype="float32"))
    "blocks.{j}.attn.c_proj",    # (R, B, N, L, d)
    "blocks.{j}.resid_1",        # (R, B, N, L, d)  x + attn(ln_1(x))
    "blocks.{j}.ln_2",           # (R, B, N, L, d)
    "blocks.{j}.mlp.c_fc",       # (R, B, N, L, 4d) before GELU
    "blocks.{j}.mlp.gelu",       # (R, B, N, L, 4d)
    "blocks.{j}.mlp.c_proj",     # (R, B, N, L, d)
    "blocks.{j}.out",            # (R, B, N, L, d)  resid_1 + mlp(ln_2(resid_1))
    "ln_f.generation",           # (B, N, L, d)     ln_f of row 1
    "ln_f.localization",         # (B, N, L, d)     ln_f of row 2
    "logits",                    # (B, N, L, V)
    "pose_head.c_fc",            # (B, N, L, 2d)    quaternion_pose_representation/pose_classifier
    "pose_head.gelu",            # (B, N, L, 2d)
    "pose",                      # (B, N, L, 7)     the raw pose head output (what the loss uses)
    "ce_loss",                   # (B,)
    "pose_loss",                 # (B,)
    "loss",                      # ()               a scalar of the model's dtype (out.loss is a float)
)
# backward() gives no gradient for attn.lse (nothing downstream uses it) nor for the losses (the seed)


def trace_names(n_layer):
    """TRACE_NAMES with "{j}" expanded for blocks 0..n_layer-1: forward's trace keys, in order."""
    block = [n for n in TRACE_NAMES if n.startswith("blocks.")]
    at = TRACE_NAMES.index(block[0])  # the block's names are contiguous
    return [*TRACE_NAMES[:at], *(b.format(j=j) for j in range(n_layer) for b in block), *TRACE_NAMES[at + len(block):]]


def _accumulate(grads, prefix, names, dparams):
    """grads[prefix + name] += its gradient, for names and dparams in the layer pair's order."""
    for name, dp in zip(names, dparams):
        grads[prefix + name] += dp


def _trace_mlp(tr, name, cache, y):
    """Record an mlp_forward's hidden layer, its GELU and its output (the cache keeps the first two)."""
    (_, _), h, (a, _) = cache  # ((x, w_fc), h, (a, w_proj))
    tr[name + ".c_fc"] = h  # (..., dh) before GELU
    tr[name + ".gelu"] = a  # (..., dh)
    tr[name + ".c_proj"] = y  # (..., dout)


@dataclasses.dataclass(frozen=True)
class TransformerConfig:
    n_embeddings: int  # V, the codebook size; wte has V + 2 rows: V = mask token, V + 1 = localization token
    n_head: int  # H; the head width is d_model / n_head
    d_model: int  # d
    n_layer: int  # transformer blocks
    token_image_size: int  # k: a view is k x k tokens, L = k*k (at most 256)
    sequence_size: int  # N the model is trained on (context + queries); forward accepts any N >= 1
    n_loss_skip: int  # the first views are pure context, never a loss target (paper: 4; tiny: 1)
    pose_multiplier: float = 1.0  # positions are scaled by this before the pose MLP and in the loss (SM7: 0.2); != 0
    localization_weight: float = 1.0  # weight of the pose loss in the total loss
    image_generation_weight: float = 1.0  # weight of the cross-entropy in the total loss
    label_smoothing: float = 0.0  # eps: the CE target is (1 - eps) onehot + eps / V
    attention_scale: float = 1.0  # logit = scale * q.k; the published model uses 1, not 1/sqrt(dh)
    dtype: str = "float32"  # parameters and activations: "float32" or "float64"
    # pyvf's own, not published: the pose loss takes the sign of the target quaternion nearer the
    # prediction (pose_loss_forward), as q and -q are one rotation. False: the published loss, whose
    # sign-canonical targets (w >= 0) flip near half-turns, where a network's fit shrinks to small angles.
    sign_invariant_pose: bool = False

    ADDED_FIELDS = ("sign_invariant_pose",)  # newer than some saved files; a file without it loads with the default

    def __post_init__(self):
        # Python or NumPy numbers, stored as int and float: the configuration is saved as JSON
        for name in ("n_embeddings", "n_head", "d_model", "n_layer", "token_image_size", "sequence_size"):
            object.__setattr__(self, name, _checks.positive_integer(f"TransformerConfig.{name}", getattr(self, name)))
        object.__setattr__(self, "n_loss_skip", _checks.integer("TransformerConfig.n_loss_skip", self.n_loss_skip, lo=0))
        for name in ("pose_multiplier", "localization_weight", "image_generation_weight", "attention_scale"):
            object.__setattr__(self, name, _checks.real(f"TransformerConfig.{name}", getattr(self, name)))
        object.__setattr__(self, "label_smoothing", _checks.real("TransformerConfig.label_smoothing",
                                                                 self.label_smoothing, lo=0.0, hi=1.0, hi_open=True))
        if self.d_model % self.n_head:
            raise ValueError(f"TransformerConfig: d_model={self.d_model} is not divisible by n_head={self.n_head}")
        if self.token_image_size ** 2 > MAX_TOKENS_PER_VIEW:
            raise ValueError(f"TransformerConfig.token_image_size={self.token_image_size}: wpe has "
                             f"{MAX_TOKENS_PER_VIEW} rows")
        if not isinstance(self.sign_invariant_pose, bool):
            raise TypeError(f"TransformerConfig.sign_invariant_pose must be a bool, got {self.sign_invariant_pose!r}")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"TransformerConfig.dtype must be 'float32' or 'float64', got {self.dtype!r}")
        if self.pose_multiplier == 0:  # predictions are divided by it
            raise ValueError("TransformerConfig.pose_multiplier must be nonzero")

    @property
    def L(self):
        return self.token_image_size ** 2


# ---------------------------------------------------------------------------------------
# the layer table (pyvf.models.io): the parameters and teacher forcing's layers read it


# load_official's layouts: layout -> how it holds the Dense layers, the published one first
LAYOUTS = {"tf": "the published TF Dense layout: kernel (in, out), bias (1, out)",
           "torch": "nn.Linear's kernel (out, in), bias (out,)"}


def is_dense_kernel(name):
    """True for the Dense (linear) kernels, stored (in, out) in the published checkpoint: every
    official name ending in '/weight' but the token embedding 'wte/weight' (an embedding, never
    transposed; nor is 'wpe/embeddings')."""
    return name.endswith("/weight") and name != "wte/weight"


def _row(name, kind, prefix, params, calls):
    """A row whose parameters prefix + suffix take their role (pyvf.models.io.ROLES) from their name."""
    # Dense biases are (1, out) in the published checkpoint, (out,) in torch's layout
    role = lambda n: "dense_kernel" if is_dense_kernel(n) else "dense_bias" if n.endswith("/bias") else None  # noqa: E731
    return Layer(name, kind, tuple((s, shape, role(prefix + s)) for s, shape in params), prefix=prefix,
                 calls=calls)


def _dense(d_in, d_hidden, d_out, prefix=""):
    """An MLP's two Dense layers (c_fc, GELU, c_proj): (suffix, shape) pairs."""
    shapes = ((d_in, d_hidden), (1, d_hidden), (d_hidden, d_out), (1, d_out))
    return tuple((prefix + n, s) for n, s in zip(DENSE_PAIR, shapes))


def _one(inp, out):
    """One call on trace name `inp`, output trace name `out`."""
    return ((((inp, None),), out),)


def layer_table(cfg):
    """The transformer's layers for cfg, in execution order (pyvf.models.io.Layer rows): each a
    function of its inputs only (trace names or the model's inputs), its parameters in the
    published order. The residual additions are not layers (pyvf.compare on a trace covers them)."""
    V, d = cfg.n_embeddings, cfg.d_model
    norm = tuple((n, (d,)) for n in NORM)
    rows = [_row("embed", "embed", "", (("wte/weight", (V + 2, d)), ("wpe/embeddings", (MAX_TOKENS_PER_VIEW, d)),
                                        *_dense(7, 2 * d, d, "pose_embedding/")),
                 (((("tokens", None), ("poses", None)), "embed.out"),))]
    prev = "embed.out"
    for j in range(cfg.n_layer):
        b, h = f"blocks.{j}.", f"h.{j}/"
        attn = tuple(zip(ATTN_PARAMS, ((d, 3 * d), (1, 3 * d), (d, d), (1, d))))
        rows += [_row(b + "ln_1", "layernorm", h + "ln_1/", norm, _one(prev, b + "ln_1")),
                 _row(b + "attn", "attention", h + "attn/", attn, _one(b + "ln_1", b + "attn.c_proj")),
                 _row(b + "ln_2", "layernorm", h + "ln_2/", norm, _one(b + "resid_1", b + "ln_2")),
                 _row(b + "mlp", "mlp", h + "mlp/", _dense(d, 4 * d, d), _one(b + "ln_2", b + "mlp.c_proj"))]
        prev = b + "out"
    rows += [
        # ln_f runs twice: on the generation row (1) and the localization row (2) of the last block
        _row("ln_f", "layernorm", "ln_f/", norm,
             ((((prev, 1),), "ln_f.generation"), (((prev, 2),), "ln_f.localization"))),
        _row("logits", "logits", "", (("wte/weight", (V + 2, d)),), _one("ln_f.generation", "logits")),  # tied: wte[:V]
        _row("pose_head", "mlp", POSE_HEAD, _dense(d, 2 * d, 7),
             _one("ln_f.localization", "pose")),
    ]
    return tuple(rows)


def parameter_shapes(cfg):
    """Official name -> shape, in the published order of the blocks."""
    return {name: shape for name, (shape, _) in parameters(layer_table(cfg)).items()}


@dataclasses.dataclass
class TransformerOutput:
    logits: np.ndarray  # (B, N, L, V) generation logits
    pose_prediction: np.ndarray  # (B, N, L, 7) per token: xyz / pose_multiplier, unit canonical quaternion
    ce_loss: np.ndarray  # (B,) cross-entropy over views >= n_loss_skip
    pose_loss: np.ndarray  # (B,) pose loss over views >= n_loss_skip
    loss: float  # batch mean of image_generation_weight * ce + localization_weight * pose
    pose_raw: np.ndarray = None  # (B, N, L, 7) the pose head's output: what the loss and backward(dpose=) see
    trace: dict = None  # forward(..., trace=True) only: name -> activation, TRACE_NAMES order


class Transformer(ModelWeights):
    """The model: parameters in `self.params` (official name -> array), forward, backward."""

    LAYOUTS = LAYOUTS
    FILE_KIND = "transformer"
    CONFIG = TransformerConfig
    INPUTS = ("tokens", "poses")  # the model's inputs (teacher forcing: the first row reads the first)
    # the fingerprint of the codebook whose tokens it was trained on (Codebook.fingerprint; None:
    # not known, as in files saved before pyvf recorded it); kept in the model file
    META = ("codebook_fingerprint",)
    codebook_fingerprint = None

    def __init__(self, config, seed=0):
        self._describe(config, layer_table(config))
        rng = np.random.default_rng(seed)
        self.params = {}
        for name, shape in self.parameter_shapes().items():
            if name.endswith("gamma"):
                p = np.ones(shape)
            elif name.endswith(("bias", "beta")):
                p = np.zeros(shape)
            else:  # GPT-2's initialisation: normal(0, 0.02)
                p = rng.normal(0.0, 0.02, size=shape)
            self.params[name] = p.astype(self.dtype)

    def official_name(self, name):
        """A checkpoint's key -> the parameter's name: 'migt/h.0/ln_1/gamma:0' -> 'h.0/ln_1/gamma'."""
        return name.removeprefix("migt/").removesuffix(":0")

    # -----------------------------------------------------------------------------------
    # one row of the table at a time (teacher forcing's reference, pyvf.verify.teacher)

    def layer_forward(self, row, *xs):
        """Run the table's row on its inputs (the arrays its call names) -> (output, cache)."""
        P = [self.params[n] for n in row.param_names]
        if row.kind == "embed":  # tokens, poses -> the three rows (3, B, N, L, d)
            return self._embed_forward(*xs)
        (x,) = xs
        if row.kind == "attention":
            P += [self.config.n_head, self.config.attention_scale]
        if row.kind == "logits":  # logits = g @ wte[:V]^T (B, N, L, V), the embedding tied
            return self._logits(x), x
        return LAYER_PAIRS[row.kind][0](x, *P)

    def layer_backward(self, row, dy, cache):
        """layer_forward's VJP -> (per input its gradient, None for the model's inputs; the
        gradients of row.param_names, in order)."""
        if row.kind == "embed":
            grads = {n: np.zeros_like(self.params[n]) for n in row.param_names}
            self._embed_backward(dy, cache, grads)
            return [None, None], [grads[n] for n in row.param_names]  # tokens and poses get none
        if row.kind == "logits":  # g = cache (B, N, L, d); wte's rows past V get no gradient here
            dx, dwte = self._logits_backward(dy, cache)
            dp = [np.zeros_like(self.params["wte/weight"])]
            dp[0][:self.config.n_embeddings] = dwte
        else:
            dx, *dp = LAYER_PAIRS[row.kind][1](dy, cache)
        return [dx], dp

    # -----------------------------------------------------------------------------------
    # the entry points' one check of their tokens and poses

    def _check_inputs(self, B="B", L="L", unit=False, **arrays):
        """Arrays by the caller's argument names: `*tokens` (B, N, L) ints in [0, V), L <= 256;
        `*poses` (B, N, 7) finite, of the model's dtype, unit quaternions where unit. B, L: ints
        the sizes must equal. -> (B, N, L)."""
        N = "N"
        for name, a in arrays.items():
            if name.endswith("tokens"):
                B, N, L = self._check_array(name, a, (B, N, L), kind="iu")
                if L > MAX_TOKENS_PER_VIEW or a.min() < 0 or a.max() >= self.config.n_embeddings:
                    raise ValueError(f"{name} must be in [0, {self.config.n_embeddings}), at most "
                                     f"{MAX_TOKENS_PER_VIEW} a view")
                continue
            B, N, _ = self._check_array(name, a, (B, N, 7))
            tol = 1e-5 if self.dtype == np.float32 else 1e-9
            if unit and np.abs(np.einsum("...i,...i->...", a[..., 3:], a[..., 3:]) - 1).max() > tol:
                raise ValueError(f"the quaternions of {name} must be unit quaternions")
        return B, N, L

    # -----------------------------------------------------------------------------------
    # the tree's input rows

    def _embed_forward(self, tokens, poses, tr=None):
        """tokens (B, N, L), poses (B, N, 7) -> x (3, B, N, L, d): trunk, generation, localization.
        tr: None, or a dict the activations are recorded in (TRACE_NAMES)."""
        p, V, L = self.params, self.config.n_embeddings, tokens.shape[2]
        wte = p["wte/weight"]
        E, c_tok = embedding_forward(tokens, wte)  # (B, N, L, d)
        W = p["wpe/embeddings"][:L]  # (L, d): token t of every view gets row t
        pose_in = poses.copy()  # (B, N, 7)
        pose_in[..., :3] *= self.dtype.type(self.config.pose_multiplier)  # xyz scaled, quaternion unchanged
        P, c_pose = self._mlp("pose_embedding/", pose_in)  # (B, N, d)
        if tr is not None:
            tr["embed.tokens"], tr["embed.positions"], tr["pose_embedding.input"] = E, W, pose_in
            _trace_mlp(tr, "pose_embedding", c_pose, P)
        P = P[:, :, None, :]  # (B, N, 1, d), broadcast over the L tokens
        x = np.stack([E + W + P, wte[V] + W + P, E + W + wte[V + 1]])  # (3, B, N, L, d)
        if tr is not None:
            tr["embed.out"] = x
        return x, (c_tok, c_pose, L)

    def _embed_backward(self, dx, cache, grads, g=None):
        """dx (3, B, N, L, d) -> accumulates into grads; g: None, or a dict for the activations' gradients."""
        c_tok, c_pose, L = cache
        V = self.config.n_embeddings
        dtrunk, dgen, dloc = dx  # each (B, N, L, d)
        dE = dtrunk + dloc  # (B, N, L, d): E feeds the trunk and the localization row
        (dwte,) = embedding_backward(dE, c_tok)
        dwte[V] += dgen.sum(axis=(0, 1, 2))  # the mask token
        dwte[V + 1] += dloc.sum(axis=(0, 1, 2))  # the localization token
        grads["wte/weight"] += dwte
        dW = dx.sum(axis=(0, 1, 2))  # (L, d): W feeds all three rows
        grads["wpe/embeddings"][:L] += dW
        dP = (dtrunk + dgen).sum(axis=2)  # (B, N, d): P feeds the trunk and the generation row
        if g is not None:
            g["embed.out"], g["pose_embedding.c_proj"] = dx, dP
        dpose_in, *dps = mlp_backward(dP, c_pose, g, "pose_embedding")
        if g is not None:
            g["pose_embedding.input"], g["embed.positions"], g["embed.tokens"] = dpose_in, dW, dE
        _accumulate(grads, "pose_embedding/", DENSE_PAIR, dps)

    # -----------------------------------------------------------------------------------
    # one pre-LN block: x = x + attn(ln_1(x)); x = x + mlp(ln_2(x))

    def _block_forward(self, x, j, tr=None, context=None):
        """x (R, B, N, L, d) -> block j's output (R, B, N, L, d), cache; tr: None or the trace dict.
        context: None, or a scene's cached trunk (k, v) of block j (attention_layer_forward)."""
        p, h = self.params, f"h.{j}/"
        a, c_ln1 = layernorm_forward(x, p[h + "ln_1/gamma"], p[h + "ln_1/beta"])
        y, c_attn = attention_layer_forward(a, *(p[h + "attn/" + n] for n in ATTN_PARAMS),
                                            self.config.n_head, self.config.attention_scale, context=context)
        x = x + y  # (R, B, N, L, d)
        m, c_ln2 = layernorm_forward(x, p[h + "ln_2/gamma"], p[h + "ln_2/beta"])
        f, c_mlp = self._mlp(h + "mlp/", m)
        out = x + f  # (R, B, N, L, d)
        if tr is not None:
            b = f"blocks.{j}."
            _, _, q, k, v, o, lse, _, _ = c_attn  # (R, B, H, N, L, dh), lse (R, B, H, N, L)
            tr[b + "ln_1"] = a
            # the layer keeps q, k, v split by head, not the fused projection: rebuilt (same bits)
            tr[b + "attn.c_attn"] = _fused_heads(v, q, k)
            tr[b + "attn.q"], tr[b + "attn.k"], tr[b + "attn.v"] = q, k, v
            tr[b + "attn.out"], tr[b + "attn.lse"] = o, lse
            tr[b + "attn.c_proj"], tr[b + "resid_1"], tr[b + "ln_2"] = y, x, m
            _trace_mlp(tr, b + "mlp", c_mlp, f)
            tr[b + "out"] = out
        return out, (c_ln1, c_attn, c_ln2, c_mlp)

    def _block_backward(self, dx, cache, j, grads, g=None):
        """dx (R, B, N, L, d): gradient of block j's output -> of its input; g: None or a dict."""
        c_ln1, c_attn, c_ln2, c_mlp = cache
        h, b = f"h.{j}/", f"blocks.{j}."
        if g is not None:
            g[b + "out"] = g[b + "mlp.c_proj"] = dx
        # forward was x2 = x1 + mlp(ln_2(x1))
        dm, *dmlp = mlp_backward(dx, c_mlp, g, b + "mlp")
        dx1, *dln2 = layernorm_backward(dm, c_ln2)
        dx = dx + dx1
        if g is not None:
            g[b + "ln_2"] = dm
            g[b + "resid_1"] = g[b + "attn.c_proj"] = dx
        # forward was x1 = x0 + attn(ln_1(x0))
        da, *dattn = attention_layer_backward(dx, c_attn, g, b + "attn")
        dx0, *dln1 = layernorm_backward(da, c_ln1)
        if g is not None:
            g[b + "ln_1"] = da
        for part, names, dps in (("ln_1/", NORM, dln1), ("attn/", ATTN_PARAMS, dattn), ("ln_2/", NORM, dln2),
                                 ("mlp/", DENSE_PAIR, dmlp)):
            _accumulate(grads, h + part, names, dps)
        return dx + dx0

    # -----------------------------------------------------------------------------------
    # the heads

    def _mlp(self, prefix, x):
        """mlp_forward with the parameters named prefix + DENSE_PAIR."""
        return mlp_forward(x, *(self.params[prefix + n] for n in DENSE_PAIR))

    def _logits(self, g):
        """g (..., d): ln_f of generation rows -> logits (..., V), the embedding tied: g @ wte[:V]^T,
        one 2-D product."""
        V, d = self.config.n_embeddings, g.shape[-1]
        return matmul(g.reshape(-1, d), self.params["wte/weight"][:V], tb=True).reshape(*g.shape[:-1], V)

    def _logits_backward(self, dlogits, g):
        """forward was logits = g @ wte[:V]^T -> dg = dlogits @ wte[:V] (..., d), dwte[:V] = dlogits^T @ g (V, d)."""
        V, d = self.config.n_embeddings, g.shape[-1]
        dl2 = dlogits.reshape(-1, V)  # (M, V)
        return (matmul(dl2, self.params["wte/weight"][:V]).reshape(g.shape),  # dg = dlogits @ wte[:V]
                matmul(dl2, g.reshape(-1, d), ta=True))  # dlogits^T @ g

    def _heads_forward(self, hg, hl, tr=None):
        """hg, hl (B, N, L, d): the generation and localization rows after the last block.
        -> logits (B, N, L, V), raw pose (B, N, L, 7). tr: None or the trace dict."""
        p = self.params
        g, c_lng = layernorm_forward(hg, p["ln_f/gamma"], p["ln_f/beta"])  # (B, N, L, d)
        l, c_lnl = layernorm_forward(hl, p["ln_f/gamma"], p["ln_f/beta"])
        logits = self._logits(g)  # (B, N, L, V)
        raw, c_head = self._mlp(POSE_HEAD, l)  # (B, N, L, 7)
        if tr is not None:
            tr["ln_f.generation"], tr["ln_f.localization"], tr["logits"] = g, l, logits
            _trace_mlp(tr, "pose_head", c_head, raw)
            tr["pose"] = tr.pop("pose_head.c_proj")  # named as the model's output
        return logits, raw, (g, c_lng, c_lnl, c_head)

    def _heads_backward(self, dlogits, draw, cache, grads, g=None):
        """dlogits (B, N, L, V), draw (B, N, L, 7) -> dhg, dhl (B, N, L, d); g: None or a dict."""
        gen, c_lng, c_lnl, c_head = cache  # gen: ln_f of the generation row (B, N, L, d)
        V = self.config.n_embeddings
        dg, dwte = self._logits_backward(dlogits, gen)  # (B, N, L, d), (V, d)
        grads["wte/weight"][:V] += dwte
        dl, *dps = mlp_backward(draw, c_head, g, "pose_head")
        if g is not None:
            g["logits"] = dlogits
        _accumulate(grads, POSE_HEAD, DENSE_PAIR, dps)
        dhg, dgf1, dbf1 = layernorm_backward(dg, c_lng)
        dhl, dgf2, dbf2 = layernorm_backward(dl, c_lnl)
        grads["ln_f/gamma"] += dgf1 + dgf2
        grads["ln_f/beta"] += dbf1 + dbf2
        if g is not None:
            g["ln_f.localization"], g["ln_f.generation"] = dl, dg
        return dhg, dhl

    # -----------------------------------------------------------------------------------
    # the whole model

    def forward(self, tokens, poses, *, trace=False):
        """tokens (B, N, L) ints in [0, V), poses (B, N, 7) of the model's dtype (xyz, unit
        quaternion wxyz, in the caller's frame, usually the first view's: geometry.make_relative)
        -> TransformerOutput; the loss needs a view past n_loss_skip. Keeps what backward() needs.
        trace=True also returns, as `out.trace`, every activation by name (TRACE_NAMES, what the
        forward keeps anyway, not copies), and makes the next backward() return their gradients."""
        cfg = self.config
        B, N, L = self._check_inputs(tokens=tokens, poses=poses)
        S = cfg.n_loss_skip
        if N <= S:
            raise ValueError(f"tokens has N={N} views but n_loss_skip={S}: no view is a loss target")
        # the caches keep the tokens (the embedding's scatter ids, the cross-entropy's targets) for
        # backward(): the model's own copy, so that a caller refilling its buffer changes nothing
        tokens, poses = tokens.copy(), np.ascontiguousarray(poses)
        tr = {} if trace else None  # None: nothing is recorded, nothing extra is computed
        x, c_embed = self._embed_forward(tokens, poses, tr)  # (3, B, N, L, d)
        c_blocks = []
        for j in range(cfg.n_layer):
            x, c = self._block_forward(x, j, tr)
            c_blocks.append(c)
        logits, raw, c_heads = self._heads_forward(x[1], x[2], tr)  # (B, N, L, V), (B, N, L, 7)

        # losses over the views S.. (the first S views are pure context)
        V = cfg.n_embeddings
        lg = logits[:, S:].reshape(-1, V)  # (B*(N-S)*L, V)
        if np.may_share_memory(lg, logits):  # B = 1 or S = 0: a view; the cache must not be out.logits,
            lg = lg.copy()  # which is the caller's to change (otherwise the reshape copied already)
        ce_tok, c_ce = cross_entropy_forward(lg, tokens[:, S:].reshape(-1), cfg.label_smoothing)  # (B*(N-S)*L,)
        pl_tok, c_pl = pose_loss_forward(raw[:, S:], poses[:, S:, None, :], cfg.pose_multiplier,
                                          cfg.sign_invariant_pose)  # (B, N-S, L)
        ce = ce_tok.reshape(B, -1).mean(axis=1)  # (B,)
        pl = pl_tok.reshape(B, -1).mean(axis=1)  # (B,)
        loss = float(np.mean(cfg.image_generation_weight * ce + cfg.localization_weight * pl))
        pred = pose_prediction(raw, cfg.pose_multiplier)  # (B, N, L, 7)

        if tr is not None:
            tr["ce_loss"], tr["pose_loss"] = ce, pl
            tr["loss"] = self.dtype.type(loss)  # exact: loss is a float of the model's dtype, widened
        self._cache = (c_embed, c_blocks, c_heads, c_ce, c_pl, (B, N, L), trace)
        return TransformerOutput(logits=logits, pose_prediction=pred, ce_loss=ce, pose_loss=pl, loss=loss,
                                 pose_raw=raw, trace=tr)

    def backward(self, dlogits=None, dpose=None, *, dloss=None):
        """The gradient of the last forward's dloss * loss + sum(logits * dlogits) + sum(pose_raw * dpose),
        a term whose seed is None left out (no seed at all: dloss = 1); dpose is for out.pose_raw.
        -> official parameter name -> gradient; after forward(..., trace=True), first every traced
        activation's gradient (but attn.lse's and the losses'), in backward order."""
        if self._cache is None:
            raise RuntimeError("backward() needs a forward() first (and differentiates the last one)")
        c_embed, c_blocks, c_heads, c_ce, c_pl, (B, N, L), traced = self._cache
        cfg, dt = self.config, self.dtype
        S, V = cfg.n_loss_skip, cfg.n_embeddings
        if dlogits is None and dpose is None and dloss is None:
            dloss = 1.0
        grads = {name: np.zeros_like(p) for name, p in self.params.items()}
        dl_total = np.zeros((B, N, L, V), dtype=dt)  # (B, N, L, V)
        draw = np.zeros((B, N, L, 7), dtype=dt)  # (B, N, L, 7)
        if dloss is not None:
            dloss = _checks.real("dloss", dloss)
            # forward was loss = mean_b(wg * mean_{i >= S, t}(ce) + wl * mean_{i >= S, t}(pose))
            n_tok = (N - S) * L
            seeds = [dloss * w / (B * n_tok) for w in (cfg.image_generation_weight, cfg.localization_weight)]
            dce_tok = np.full(B * n_tok, seeds[0], dtype=dt)
            dpl_tok = np.full((B, N - S, L), seeds[1], dtype=dt)
            dl_total[:, S:] = cross_entropy_backward(dce_tok, c_ce)[0].reshape(B, N - S, L, V)
            draw[:, S:] = pose_loss_backward(dpl_tok, c_pl)[0]
        if dlogits is not None:
            self._check_array("dlogits", dlogits, (B, N, L, V))
            dl_total += dlogits
        if dpose is not None:
            self._check_array("dpose", dpose, (B, N, L, 7))
            draw += dpose
        g = {"pose": draw} if traced else None  # the activations' gradients, the trace's order reversed
        dhg, dhl = self._heads_backward(dl_total, draw, c_heads, grads, g)
        dx = np.zeros((3, B, N, L, cfg.d_model), dtype=dt)
        dx[1], dx[2] = dhg, dhl  # the trunk's output feeds no head
        for j in reversed(range(cfg.n_layer)):
            dx = self._block_backward(dx, c_blocks[j], j, grads, g)
        self._embed_backward(dx, c_embed, grads, g)
        return grads if g is None else {**g, **grads}

    # -----------------------------------------------------------------------------------
    # inference: only what a scene needs

    def encode_scene(self, context_tokens, context_poses):
        """context_tokens (B, Nc, L) ints, context_poses (B, Nc, 7) (any frame: made relative to the
        first context view) -> Scene, each layer's trunk keys and values, for render_scene and
        localize_scene to reuse for any number of queries. One trunk pass (R = 1, block-causal)."""
        _, _, L = self._check_inputs(unit=True, context_tokens=context_tokens, context_poses=context_poses)
        rel, ref = make_relative(context_poses)  # (B, Nc, 7), (B, 7)
        x, _ = self._embed_forward(context_tokens, rel)
        x = x[:1]  # (1, B, Nc, L, d): the trunk row only
        keys, values = [], []
        for j in range(self.config.n_layer):
            x, c = self._block_forward(x, j)
            _, _, q, k, v, _, _, _, _ = c[1]  # the attention layer's cache: (1, B, H, Nc, L, dh)
            keys.append(k[0])  # (B, H, Nc, L, dh)
            values.append(v[0])
        return Scene(ref=ref, keys=keys, values=values, tokens_per_view=L, config=self.config,
                     params=dict(self.params))

    def _check_scene(self, scene):
        """scene: encoded by this model with its present parameters (another trunk would be attended silently)."""
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a Scene from encode_scene, got {type(scene).__name__}")
        if scene.config != self.config or scene.params.keys() != self.params.keys() \
                or any(self.params[n] is not a for n, a in scene.params.items()):
            raise ValueError("scene was encoded by another model (or before its parameters were replaced): "
                             "encode the context again with this model's encode_scene")

    def _query_forward(self, scene, tokens, poses, row):
        """tokens (B, M, L), poses (B, M, 7) of M query views in the scene's frame -> ln_f of their
        tree row `row` (1 generation, 2 localization), each attending the scene's trunk: (M, B, L, d)."""
        p = self.params
        x = self._embed_forward(tokens, poses)[0][row]  # (B, M, L, d)
        x = np.ascontiguousarray(x.transpose(1, 0, 2, 3))[:, :, None]  # (M, B, 1, L, d): rows of one view each
        for j in range(self.config.n_layer):
            x, _ = self._block_forward(x, j, context=(scene.keys[j], scene.values[j]))
        return layernorm_forward(x[:, :, 0], p["ln_f/gamma"], p["ln_f/beta"])[0]

    def render_scene(self, scene, query_poses):
        """query_poses (B, M, 7), in the context's frame -> token logits (B, M, L, V) of each
        query view (the generation branch: image hidden, pose given)."""
        self._check_scene(scene)
        self._check_inputs(B=scene.ref.shape[0], unit=True, query_poses=query_poses)
        rel = relative_poses(query_poses, scene.ref[:, None, :])  # (B, M, 7)
        # as make_relative does for the context: the pose MLP is not sign-invariant
        rel[..., 3:] = quat_canonical(quat_normalize(rel[..., 3:]))
        hidden = np.zeros(rel.shape[:2] + (scene.tokens_per_view,), np.int64)  # (B, M, L): row 1 reads none
        g = self._query_forward(scene, hidden, rel, 1)  # (M, B, L, d)
        return self._logits(g).transpose(1, 0, 2, 3)  # (B, M, L, V)

    def localize_scene(self, scene, query_tokens):
        """query_tokens (B, M, L) ints -> one pose per query view (B, M, 7) in the context's
        frame: the token predictions averaged (geometry.average_pose)."""
        self._check_scene(scene)
        self._check_inputs(B=scene.ref.shape[0], L=scene.tokens_per_view, query_tokens=query_tokens)
        unknown = np.zeros(query_tokens.shape[:2] + (7,), self.dtype)  # (B, M, 7): row 2 reads none
        l = self._query_forward(scene, query_tokens, unknown, 2)  # (M, B, L, d)
        raw, _ = self._mlp(POSE_HEAD, l)  # (M, B, L, 7)
        rel = average_pose(pose_prediction(raw, self.config.pose_multiplier), axis=2)  # (M, B, 7)
        return absolute_poses(rel.transpose(1, 0, 2), scene.ref[:, None, :])  # (B, M, 7)

    def render(self, context_tokens, context_poses, query_poses):
        """Token logits (B, M, L, V) of M novel views: encode_scene, then render_scene."""
        return self.render_scene(self.encode_scene(context_tokens, context_poses), query_poses)

    def localize(self, context_tokens, context_poses, query_tokens):
        """Poses (B, M, 7) of M views given their tokens: encode_scene, then localize_scene."""
        return self.localize_scene(self.encode_scene(context_tokens, context_poses), query_tokens)


@dataclasses.dataclass
class Scene:
    """A context encoded once by Transformer.encode_scene."""
    ref: np.ndarray  # (B, 7) the first context view's pose: the frame the model sees
    keys: list  # per layer (B, H, Nc, L, dh): the trunk's attention keys
    values: list  # per layer (B, H, Nc, L, dh)
    tokens_per_view: int  # L
    config: "TransformerConfig"  # the encoding model's: render_scene / localize_scene check them
    params: dict = dataclasses.field(repr=False)  # its parameter arrays (references, not copies)


def pose_prediction(raw, pose_multiplier=1.0):
    """raw (..., 7) from the pose head -> (..., 7): xyz_raw / pose_multiplier and the raw
    quaternion L2-normalised (eps 1e-12, TF's convention) and sign-canonicalised (w >= 0)."""
    xyz = raw[..., :3] / raw.dtype.type(pose_multiplier)
    q = quat_canonical(quat_normalize(raw[..., 3:], eps=1e-12))
    return np.concatenate([xyz, q], axis=-1)
