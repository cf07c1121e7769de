"""ViewFormer written as a port author would: torch nn.Modules named as the published modules,
the tree as one flat sequence (B, T, d) with T = 3*N*L in [row][view][token] and a dense mask.

A template for a port, and the subject of pyvf's verification tests: `bug=` plants one typical
port bug (None, the default, is the published math), which pyvf.compare and pyvf.teacher_force
must find at its layer (tests/test_teacher.py, docs/verify.md). Written from docs/math.md, not from
pyvf's code. Module and parameter names:

    TransformerPort: embed (wte, wpe, pose_embedding.{c_fc, gelu, c_proj}), h.{j}.{ln_1, attn.{c_attn,
    c_proj}, ln_2, mlp.{c_fc, gelu, c_proj}}, ln_f, pose_head.{c_fc, gelu, c_proj}; nn.Linear
    weights (out, in): load pyvf's with model.state_dict(layout="torch") and official_name().
    CodebookPort: the published torch state dict's names exactly (taming-transformers' tree).

transformer_forward and codebook_forward run the ports as functions of a parameter dict by the
official names (torch.func.functional_call): the oracles of the tests, the torch side of `pyvf bench
transformer` / `codebook`; transformer_losses is also the torch engine's.
"""

import functools
from collections import OrderedDict

import torch
import torch.nn as nn
import torch.nn.functional as F

TRANSFORMER_BUGS = {
    "qkv_order": "block 1 reads its fused projection in GPT-2's q, k, v order (published: v, q, k)",
    "ln_eps": "block 0's ln_2 has LayerNorm eps 1e-3 (published: 1e-5)",
    "wrong_branch": "the mask lets each branch see the other branch's block of its view",
    "gelu_tanh": "block 0's MLP uses GELU's tanh form (published: exact erf)",
    "attn_scale": "every attention scales its logits by 1/sqrt(dh) (published: 1)",
    "wpe_shift": "token t gets positional row t + 1",
}
CODEBOOK_BUGS = {
    "padding": "the Downsample pads (1, 1, 1, 1) (published: (0, 1, 0, 1))",
    "ema_first": "the quantizer applies its EMA update before gathering the codes (published: after)",
}


# ---------------------------------------------------------------------------------------
# the transformer


class MLP(nn.Module):
    def __init__(self, d_in, d_hidden, d_out, approximate="none"):
        super().__init__()
        self.c_fc, self.gelu, self.c_proj = nn.Linear(d_in, d_hidden), nn.GELU(approximate), nn.Linear(d_hidden, d_out)

    def forward(self, x):
        return self.c_proj(self.gelu(self.c_fc(x)))


def tree_mask(N, L, bug=None, device=None):
    """(T, T) bool, T = 3*N*L: query (row r, view i) sees the trunk's views before i and its own
    row's view i (docs/math.md §2)."""
    t = torch.arange(3 * N * L, device=device)
    row, view = t // (N * L), t // L % N
    qr, qi, kr, ki = row[:, None], view[:, None], row[None, :], view[None, :]
    mask = ((kr == 0) & (ki < qi)) | ((kr == qr) & (ki == qi))
    if bug == "wrong_branch":
        mask |= (qr > 0) & (kr > 0) & (ki == qi)
    return mask


class Attention(nn.Module):
    def __init__(self, d, n_head, scale=1.0, qkv_order=False):
        super().__init__()
        self.c_attn, self.c_proj = nn.Linear(d, 3 * d), nn.Linear(d, d)
        self.n_head, self.scale, self.qkv_order = n_head, scale, qkv_order

    def forward(self, x, mask):  # x (B, T, d)
        B, T, d = x.shape
        v, q, k = self.c_attn(x).split(d, dim=-1)  # docs/math.md §3: the columns are [v | q | k]
        if self.qkv_order:
            q, k, v = v, q, k  # GPT-2's order
        q, k, v = (t.reshape(B, T, self.n_head, d // self.n_head).transpose(1, 2) for t in (q, k, v))
        o = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, scale=self.scale)  # (B, H, T, dh)
        return self.c_proj(o.transpose(1, 2).reshape(B, T, d))


class Block(nn.Module):
    def __init__(self, d, n_head, scale, ln_2_eps=1e-5, approximate="none", qkv_order=False):
        super().__init__()
        self.ln_1, self.attn = nn.LayerNorm(d, eps=1e-5), Attention(d, n_head, scale, qkv_order)
        self.ln_2, self.mlp = nn.LayerNorm(d, eps=ln_2_eps), MLP(d, 4 * d, d, approximate)

    def forward(self, x, mask):
        x = x + self.attn(self.ln_1(x), mask)
        return x + self.mlp(self.ln_2(x))


class Embedding(nn.Module):
    def __init__(self, V, d, pose_multiplier, shift=0):
        super().__init__()
        self.wte, self.wpe, self.pose_embedding = nn.Embedding(V + 2, d), nn.Embedding(256, d), MLP(7, 2 * d, d)
        self.V, self.pose_multiplier, self.shift = V, pose_multiplier, shift

    def forward(self, tokens, poses):  # (B, N, L), (B, N, 7) -> (B, 3*N*L, d), rows trunk, generation, localization
        B, N, L = tokens.shape
        E, W = self.wte(tokens), self.wpe(torch.arange(L, device=tokens.device) + self.shift)
        P = self.pose_embedding(torch.cat([poses[..., :3] * self.pose_multiplier, poses[..., 3:]], -1))[:, :, None]
        rows = [E + W + P, (self.wte.weight[self.V] + W + P).expand(E.shape), E + W + self.wte.weight[self.V + 1]]
        return torch.stack(rows, 1).reshape(B, 3 * N * L, -1)


class TransformerPort(nn.Module):
    def __init__(self, cfg, bug=None):
        super().__init__()
        self.bug = bug  # None or a key of TRANSFORMER_BUGS
        V, d, H = cfg.n_embeddings, cfg.d_model, cfg.n_head
        scale = (d // H) ** -0.5 if bug == "attn_scale" else cfg.attention_scale
        self.V = V
        self.embed = Embedding(V, d, cfg.pose_multiplier, shift=1 if bug == "wpe_shift" else 0)
        self.h = nn.ModuleList(Block(d, H, scale, ln_2_eps=1e-3 if (bug == "ln_eps" and j == 0) else 1e-5,
                                     approximate="tanh" if (bug == "gelu_tanh" and j == 0) else "none",
                                     qkv_order=bug == "qkv_order" and j == 1) for j in range(cfg.n_layer))
        self.ln_f, self.pose_head = nn.LayerNorm(d, eps=1e-5), MLP(d, 2 * d, 7)

    def mask(self, N, L, device=None):
        return tree_mask(N, L, self.bug, device)

    def logits(self, g):  # tied to the token embedding
        return g @ self.embed.wte.weight[:self.V].T

    def forward(self, tokens, poses):  # -> logits (B, N, L, V), raw pose (B, N, L, 7)
        B, N, L = tokens.shape
        x, mask = self.embed(tokens, poses), self.mask(N, L, tokens.device)
        for block in self.h:
            x = block(x, mask)
        x = x.reshape(B, 3, N, L, -1)
        return self.logits(self.ln_f(x[:, 1])), self.pose_head(self.ln_f(x[:, 2]))


def official_name(name):
    """A TransformerPort parameter name -> pyvf's official name ('h.0.ln_1.weight' -> 'h.0/ln_1/gamma')."""
    name = name.removeprefix("embed.").replace("pose_head", "quaternion_pose_representation.pose_classifier")
    if name == "wpe.weight":
        return "wpe/embeddings"
    if ".ln_" in "." + name:
        name = name.replace(".weight", ".gamma").replace(".bias", ".beta")
    return name.replace(".", "/").replace("h/", "h.", 1) if name.startswith("h.") else name.replace(".", "/")


# ---------------------------------------------------------------------------------------
# the codebook (taming-transformers' module tree)


def Normalize(c):
    return nn.GroupNorm(32, c, eps=1e-6)


class ResnetBlock(nn.Module):
    def __init__(self, cin, cout):
        super().__init__()
        self.norm1, self.conv1 = Normalize(cin), nn.Conv2d(cin, cout, 3, padding=1)
        self.norm2, self.conv2 = Normalize(cout), nn.Conv2d(cout, cout, 3, padding=1)
        self.nin_shortcut = nn.Conv2d(cin, cout, 1) if cin != cout else None

    def forward(self, x):
        h = self.conv2(F.silu(self.norm2(self.conv1(F.silu(self.norm1(x))))))
        return (x if self.nin_shortcut is None else self.nin_shortcut(x)) + h


class AttnBlock(nn.Module):
    def __init__(self, c):
        super().__init__()
        self.norm, self.q, self.k, self.v, self.proj_out = Normalize(c), *(nn.Conv2d(c, c, 1) for _ in range(4))

    def forward(self, x):
        B, C, H, W = x.shape
        h = self.norm(x)
        q, k, v = (m(h).reshape(B, C, H * W) for m in (self.q, self.k, self.v))
        w = torch.softmax(q.transpose(1, 2) @ k * C ** -0.5, dim=-1)  # (B, query, key)
        return x + self.proj_out((v @ w.transpose(1, 2)).reshape(B, C, H, W))


def Downsample(c, pad=(0, 1, 0, 1)):  # docs/math.md §4: zero-pad right and bottom only, then 3x3 stride 2
    return nn.Sequential(OrderedDict(pad=nn.ZeroPad2d(pad), conv=nn.Conv2d(c, c, 3, stride=2)))


def Upsample(c):
    return nn.Sequential(OrderedDict(interp=nn.Upsample(scale_factor=2, mode="nearest"),
                                     conv=nn.Conv2d(c, c, 3, padding=1)))


def Mid(c):
    return nn.Sequential(OrderedDict(block_1=ResnetBlock(c, c), attn_1=AttnBlock(c), block_2=ResnetBlock(c, c)))


class Level(nn.Module):
    """encoder.down.{l} / decoder.up.{l}: blocks, each with an AttnBlock at attention resolutions."""

    def __init__(self, cin, cout, n_blocks, attn):
        super().__init__()
        self.block = nn.ModuleList(ResnetBlock(cin if i == 0 else cout, cout) for i in range(n_blocks))
        self.attn = nn.ModuleList(AttnBlock(cout) for _ in range(n_blocks if attn else 0))

    def forward(self, x):
        for i, block in enumerate(self.block):
            x = block(x)
            x = self.attn[i](x) if len(self.attn) else x
        return x


class Encoder(nn.Module):
    def __init__(self, cfg, pad):
        super().__init__()
        ch, mult, res = cfg.ch, cfg.ch_mult, cfg.image_size
        self.conv_in, self.down = nn.Conv2d(cfg.in_channels, ch, 3, padding=1), nn.ModuleList()
        cin = ch
        for l, m in enumerate(mult):
            level = Level(cin, ch * m, cfg.num_res_blocks, res in cfg.attn_resolutions)
            cin = ch * m
            if l != len(mult) - 1:
                level.downsample, res = Downsample(cin, pad), res // 2
            self.down.append(level)
        self.mid, self.norm_out, self.conv_out = Mid(cin), Normalize(cin), nn.Conv2d(cin, cfg.z_channels, 3, padding=1)

    def forward(self, x):
        h = self.conv_in(x)
        for level in self.down:
            h = level(h)
            h = level.downsample(h) if hasattr(level, "downsample") else h
        return self.conv_out(F.silu(self.norm_out(self.mid(h))))


class Decoder(nn.Module):
    def __init__(self, cfg):
        super().__init__()
        ch, mult, res = cfg.ch, cfg.ch_mult, cfg.token_size
        cin = ch * mult[-1]
        self.conv_in, self.mid = nn.Conv2d(cfg.z_channels, cin, 3, padding=1), Mid(cin)
        levels = {}
        for l in reversed(range(len(mult))):
            levels[l] = Level(cin, ch * mult[l], cfg.num_res_blocks + 1, res in cfg.attn_resolutions)
            cin = ch * mult[l]
            if l != 0:
                levels[l].upsample, res = Upsample(cin), res * 2
        self.up = nn.ModuleList(levels[l] for l in range(len(mult)))  # indexed by level, run last to first
        self.norm_out, self.conv_out = Normalize(cin), nn.Conv2d(cin, cfg.out_ch, 3, padding=1)

    def forward(self, z):
        h = self.mid(self.conv_in(z))
        for level in reversed(self.up):
            h = level(h)
            h = level.upsample(h) if hasattr(level, "upsample") else h
        return self.conv_out(F.silu(self.norm_out(h)))


class Quantizer(nn.Module):
    """EMA vector quantizer; codes are the columns of `embeddings` (embed_dim, n_embed). In
    training mode each call applies one EMA update, after the lookup (docs/math.md §4)."""

    def __init__(self, D, K, decay=0.99, eps=1e-5, ema_first=False):
        super().__init__()
        self.register_buffer("embeddings", torch.zeros(D, K))
        self.register_buffer("ema_cluster_size_hidden", torch.zeros(K))
        self.register_buffer("ema_dw_hidden", torch.zeros(D, K))
        self.register_buffer("counter", torch.zeros((), dtype=torch.long))
        self.decay, self.eps, self.ema_first = decay, eps, ema_first

    @torch.no_grad()
    def ema_update(self, flat, codes):
        onehot = F.one_hot(codes, self.embeddings.shape[1]).to(flat.dtype)  # (M, K)
        a = 1 - self.decay
        self.ema_cluster_size_hidden += a * (onehot.sum(0) - self.ema_cluster_size_hidden)
        self.ema_dw_hidden += a * (flat.T @ onehot - self.ema_dw_hidden)
        self.counter += 1
        debias = 1 - self.decay ** self.counter.item()
        cs, dw = self.ema_cluster_size_hidden / debias, self.ema_dw_hidden / debias
        n = cs.sum()
        self.embeddings.copy_(dw / ((cs + self.eps) / (n + len(cs) * self.eps) * n))

    def forward(self, z, empty=None):  # (B, D, h, w) -> quantized (B, D, h, w), commitment loss, codes (B, h, w)
        B, D, h, w = z.shape
        flat = z.permute(0, 2, 3, 1).reshape(-1, D)
        dist = ((flat.detach()[:, :, None] - self.embeddings[None]) ** 2).sum(1)  # (M, K)
        if empty is None:
            codes = dist.argmin(1)
        else:  # the empty code (pyvf's CodebookConfig.empty_code): empty patches take code 0, the rest 1..K-1
            codes = torch.where(empty.reshape(-1), 0, dist[:, 1:].argmin(1) + 1)
        if self.training and self.ema_first:
            self.ema_update(flat.detach(), codes)
        e = self.embeddings.T[codes]  # (M, D), a copy
        if self.training and not self.ema_first:
            self.ema_update(flat.detach(), codes)
        quantized = flat + (e - flat).detach()  # straight-through
        return quantized.reshape(B, h, w, D).permute(0, 3, 1, 2), ((e - flat) ** 2).mean(), codes.reshape(B, h, w)


class CodebookPort(nn.Module):
    def __init__(self, cfg, bug=None):
        super().__init__()
        self.bug = bug  # None or a key of CODEBOOK_BUGS
        self.encoder = Encoder(cfg, (1, 1, 1, 1) if bug == "padding" else (0, 1, 0, 1))
        self.decoder = Decoder(cfg)
        self.quant_conv = nn.Conv2d(cfg.z_channels, cfg.embed_dim, 1)
        self.post_quant_conv = nn.Conv2d(cfg.embed_dim, cfg.z_channels, 1)
        self.quantize = Quantizer(cfg.embed_dim, cfg.n_embed, cfg.decay, cfg.eps, ema_first=bug == "ema_first")
        self.empty_code, self.k = getattr(cfg, "empty_code", False), cfg.token_size

    def empty_patches(self, x):  # (B, C, S, S) -> (B, k, k): every pixel of the patch is the top-left pixel's colour
        if not self.empty_code:  # as pyvf's Codebook.empty_patches: None without the empty code
            return None
        B, _, S, _ = x.shape
        p = S // self.k
        return ~(x != x[:, :, :1, :1]).any(1).reshape(B, self.k, p, self.k, p).any(4).any(2)

    def forward(self, x):  # -> reconstruction, commitment loss, codes
        q, commitment, codes = self.quantize(self.quant_conv(self.encoder(x)), self.empty_patches(x))
        return self.decoder(self.post_quant_conv(q)), commitment, codes


# ---------------------------------------------------------------------------------------
# the ports as functions of a parameter dict by the official names


@functools.lru_cache(maxsize=8)
def _transformer_port(cfg):
    port = TransformerPort(cfg)
    return port, {n: official_name(n) for n in port.state_dict()}


def transformer_forward(P, tokens, poses, cfg):
    """P: official name -> tensor, the published "tf" layout (Dense kernels (in, out), biases (1, out));
    tokens (B, N, L) long; poses (B, N, 7) -> logits (B, N, L, V), raw pose (B, N, L, 7), ce (B,),
    pose loss (B,), loss."""
    port, names = _transformer_port(cfg)
    # nn.Linear holds the published Dense kernel (in, out) as (out, in) and its bias (1, out) as (out,)
    state = {n: P[o].T if o.endswith("/weight") and o != "wte/weight" else P[o][0] if o.endswith("/bias") else P[o]
             for n, o in names.items()}
    logits, raw = torch.func.functional_call(port, state, (tokens, poses))
    return (logits, raw, *transformer_losses(logits, raw, tokens, poses, cfg))


def transformer_losses(logits, raw, tokens, poses, cfg):
    """(docs/math.md §3) -> the cross-entropy (B,) (label smoothing), the pose loss (B,), both over
    views >= n_loss_skip, and the weighted batch mean."""
    B, V, S = logits.shape[0], logits.shape[-1], cfg.n_loss_skip
    ce = F.cross_entropy(logits[:, S:].reshape(-1, V), tokens[:, S:].reshape(-1), reduction="none",
                         label_smoothing=cfg.label_smoothing).reshape(B, -1).mean(dim=1)
    target, q_raw = poses[:, S:, None, :], raw[:, S:, :, 3:]
    q = target[..., 3:]
    if cfg.sign_invariant_pose:  # the sign of q nearer the prediction
        q = torch.where((q * q_raw).sum(-1, keepdim=True) < 0, -q, q)
    pl = (((cfg.pose_multiplier * target[..., :3] - raw[:, S:, :, :3]) ** 2).mean(-1)
          + ((q - q_raw) ** 2).mean(-1)).reshape(B, -1).mean(dim=1)
    return ce, pl, (cfg.image_generation_weight * ce + cfg.localization_weight * pl).mean()


_codebook_port = functools.lru_cache(maxsize=8)(CodebookPort)


def codebook_forward(P, buffers, images, cfg):
    """P: torch name -> tensor; buffers: the four quantize.* entries; images (B, C, S, S) -> dict:
    reconstruction, codes (B, k, k), rec_loss, commitment_loss, loss (with cfg.codebook_weight) and
    buffers after one EMA step (new tensors: the ones given are left as they were)."""
    new = {k: torch.as_tensor(v).clone() for k, v in buffers.items()}  # the EMA step writes into these
    rec, commitment, codes = torch.func.functional_call(_codebook_port(cfg).train(), {**P, **new}, (images,))
    rec_loss = F.l1_loss(rec, images)
    new["quantize.counter"] = int(new["quantize.counter"])
    return {"reconstruction": rec, "codes": codes, "rec_loss": rec_loss, "commitment_loss": commitment,
            "loss": rec_loss + cfg.codebook_weight * commitment, "buffers": new}
