"""The ViewFormer transformer in torch as a function of its parameters: the benchmark's torch side
(pyvf bench transformer) and the losses of the torch engine and of pyvf's trace tests.

It is torch_ports.TransformerPort (written from docs/math.md §3, not from pyvf's code: the tree
as one flat sequence of T = 3*N*L tokens in [row][view][token] under a dense boolean mask, torch's
own layers) called on a dict of parameters by their official names in the published ("tf")
layout, through torch.func.functional_call; the losses are F.cross_entropy (label smoothing)
and the pose loss of docs/math.md §5. Autograd gives the gradients.
"""

import functools

import torch
import torch.nn.functional as F

from .torch_ports import TransformerPort, official_name


def tree_mask(R, N, L):
    """(T, T) bool: query (r, i) attends key (kr, j) iff (kr == 0 and j < i) or (kr == r and j == i)."""
    idx = torch.arange(R * N * L)
    row, view = idx // (N * L), (idx // L) % N
    qr, qi, kr, kj = row[:, None], view[:, None], row[None, :], view[None, :]
    return ((kr == 0) & (kj < qi)) | ((kr == qr) & (kj == qi))


@functools.lru_cache(maxsize=8)
def _port(cfg):
    port = TransformerPort(cfg)
    return port, {n: official_name(n) for n in port.state_dict()}


def forward(P, tokens, poses, cfg, sdpa=True):
    """P: official name -> torch tensor in the published layout (Dense kernels (in, out), biases
    (1, out)); tokens (B, N, L) long; poses (B, N, 7). Returns logits (B, N, L, V), raw pose
    (B, N, L, 7), ce (B,), pose loss (B,), loss. (sdpa: kept for callers; the port always uses
    scaled_dot_product_attention with the boolean mask.)"""
    port, names = _port(cfg)
    # nn.Linear holds the published Dense kernel (in, out) as (out, in) and its bias (1, out) as (out,)
    state = {n: P[o].T if o.endswith("/weight") and o != "wte/weight" else P[o][0] if o.endswith("/bias") else P[o]
             for n, o in names.items()}
    logits, raw = torch.func.functional_call(port, state, (tokens, poses))
    return (logits, raw, *losses(logits, raw, tokens, poses, cfg))


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
