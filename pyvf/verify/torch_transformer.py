"""The torch port of pyvf.verify.torch_ports as a function of a parameter dict in the published ("tf")
layout, through torch.func.functional_call, and its losses (docs/math.md §5): the benchmark's torch
side (pyvf bench transformer) and the torch engine's losses. Autograd gives the gradients.
"""

import functools

import torch
import torch.nn.functional as F

from .torch_ports import TransformerPort, official_name


@functools.lru_cache(maxsize=8)
def _port(cfg):
    port = TransformerPort(cfg)
    return port, {n: official_name(n) for n in port.state_dict()}


def forward(P, tokens, poses, cfg, sdpa=True):
    """P: official name -> tensor (Dense kernels (in, out), biases (1, out)); tokens (B, N, L)
    long; poses (B, N, 7) -> logits (B, N, L, V), raw pose (B, N, L, 7), ce (B,), pose loss (B,),
    loss. (sdpa: unused, the port always runs scaled_dot_product_attention.)"""
    port, names = _port(cfg)
    # nn.Linear holds the published Dense kernel (in, out) as (out, in) and its bias (1, out) as (out,)
    state = {n: P[o].T if o.endswith("/weight") and o != "wte/weight" else P[o][0] if o.endswith("/bias") else P[o]
             for n, o in names.items()}
    logits, raw = torch.func.functional_call(port, state, (tokens, poses))
    return (logits, raw, *losses(logits, raw, tokens, poses, cfg))


def losses(logits, raw, tokens, poses, cfg):
    """-> the cross-entropy (B,) (label smoothing), the pose loss (B,), both over views >=
    n_loss_skip, and the weighted batch mean."""
    B, V, S = logits.shape[0], logits.shape[-1], cfg.n_loss_skip
    ce = F.cross_entropy(logits[:, S:].reshape(-1, V), tokens[:, S:].reshape(-1), reduction="none",
                         label_smoothing=cfg.label_smoothing).reshape(B, -1).mean(dim=1)
    target = poses[:, S:, None, :]
    pl = (((cfg.pose_multiplier * target[..., :3] - raw[:, S:, :, :3]) ** 2).mean(-1)
          + ((target[..., 3:] - raw[:, S:, :, 3:]) ** 2).mean(-1)).reshape(B, -1).mean(dim=1)
    return ce, pl, (cfg.image_generation_weight * ce + cfg.localization_weight * pl).mean()
