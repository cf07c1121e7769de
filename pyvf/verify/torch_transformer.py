"""The ViewFormer transformer written again in torch, as the oracle for pyvf.Transformer.

Written from docs/math.md §3 independently of pyvf's code: the tree is one flat sequence of
T = 3*N*L tokens in the order [row][view][token] with a dense boolean mask built here from the
rule, attention is plain masked softmax (masked logits set to -inf), every layer is torch's own
(F.layer_norm, F.gelu exact, F.cross_entropy with label_smoothing). Autograd gives the
gradients.
"""

import torch
import torch.nn.functional as F


def tree_mask(R, N, L):
    """(T, T) bool: query (r, i) attends key (kr, j) iff (kr == 0 and j < i) or (kr == r and j == i)."""
    idx = torch.arange(R * N * L)
    row, view = idx // (N * L), (idx // L) % N
    qr, qi, kr, kj = row[:, None], view[:, None], row[None, :], view[None, :]
    return ((kr == 0) & (kj < qi)) | ((kr == qr) & (kj == qi))


def gelu(x):
    return F.gelu(x, approximate="none")


def linear(x, P, name):
    return x @ P[name + "/weight"] + P[name + "/bias"][0]  # published layout: weight (in, out)


def mlp(x, P, name):
    return linear(gelu(linear(x, P, name + "/c_fc")), P, name + "/c_proj")


def layer_norm(x, P, name):
    return F.layer_norm(x, (x.shape[-1],), P[name + "/gamma"], P[name + "/beta"], eps=1e-5)


def forward(P, tokens, poses, cfg, sdpa=False):
    """P: official name -> torch tensor; tokens (B, N, L) long; poses (B, N, 7).
    Returns logits (B, N, L, V), raw pose (B, N, L, 7), ce (B,), pose loss (B,), loss.
    sdpa=True uses torch's scaled_dot_product_attention with the boolean mask (the benchmark's
    choice: the explicit softmax below keeps three (T, T) arrays per layer for autograd)."""
    V, d, H = cfg.n_embeddings, cfg.d_model, cfg.n_head
    B, N, L = tokens.shape
    R, T, dh = 3, 3 * N * L, d // H
    wte = P["wte/weight"]
    E = wte[tokens]  # (B, N, L, d)
    W = P["wpe/embeddings"][:L]
    pose_in = torch.cat([poses[..., :3] * cfg.pose_multiplier, poses[..., 3:]], dim=-1)
    Pe = mlp(pose_in, P, "pose_embedding")[:, :, None, :]  # (B, N, 1, d)
    rows = [E + W + Pe, (wte[V] + W + Pe).expand(B, N, L, d), E + W + wte[V + 1]]
    x = torch.stack(rows, dim=1).reshape(B, T, d)  # (B, T, d), T in [row][view][token]
    mask = tree_mask(R, N, L)
    for j in range(cfg.n_layer):
        h = f"h.{j}"
        a = layer_norm(x, P, h + "/ln_1")
        vqk = linear(a, P, h + "/attn/c_attn")
        v, q, k = vqk[..., :d], vqk[..., d:2 * d], vqk[..., 2 * d:]  # values, queries, keys
        q, k, v = (t.reshape(B, T, H, dh).transpose(1, 2) for t in (q, k, v))  # (B, H, T, dh)
        if sdpa:
            o = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, scale=cfg.attention_scale)
        else:
            s = cfg.attention_scale * (q @ k.transpose(-1, -2))
            s = s.masked_fill(~mask, float("-inf"))
            o = torch.softmax(s, dim=-1) @ v  # (B, H, T, dh)
        x = x + linear(o.transpose(1, 2).reshape(B, T, d), P, h + "/attn/c_proj")
        x = x + mlp(layer_norm(x, P, h + "/ln_2"), P, h + "/mlp")
    x = x.reshape(B, R, N, L, d)
    g = layer_norm(x[:, 1], P, "ln_f")
    loc = layer_norm(x[:, 2], P, "ln_f")
    logits = g @ wte[:V].T  # (B, N, L, V)
    raw = mlp(loc, P, "quaternion_pose_representation/pose_classifier")  # (B, N, L, 7)
    ce, pl, loss = losses(logits, raw, tokens, poses, cfg)
    return logits, raw, ce, pl, loss


def losses(logits, raw, tokens, poses, cfg):
    """logits (B, N, L, V), raw pose (B, N, L, 7), tokens (B, N, L), poses (B, N, 7) -> the
    cross-entropy (B,) (label smoothing), the pose loss (B,), both over views >= n_loss_skip,
    and the weighted batch mean (docs/math.md §5)."""
    B, V, S = logits.shape[0], logits.shape[-1], cfg.n_loss_skip
    ce = F.cross_entropy(logits[:, S:].reshape(-1, V), tokens[:, S:].reshape(-1), reduction="none",
                         label_smoothing=cfg.label_smoothing).reshape(B, -1).mean(dim=1)
    target = poses[:, S:, None, :]
    pl = (((cfg.pose_multiplier * target[..., :3] - raw[:, S:, :, :3]) ** 2).mean(-1)
          + ((target[..., 3:] - raw[:, S:, :, 3:]) ** 2).mean(-1)).reshape(B, -1).mean(dim=1)
    return ce, pl, (cfg.image_generation_weight * ce + cfg.localization_weight * pl).mean()
