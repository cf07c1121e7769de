"""The ViewFormer codebook in torch as a function of its parameters: the oracle pyvf's codebook is
checked against (tests/test_codebook.py) and the benchmark's torch side (pyvf bench codebook).

It is torch_ports.CodebookPort (written from docs/math.md §4, not from pyvf's code) called on a
dict of parameters by their official torch names, through torch.func.functional_call: autograd
gives the gradients, the EMA step runs without gradient on a copy of the buffers.
"""

import functools

import torch
import torch.nn.functional as F

from .torch_ports import CodebookPort


@functools.lru_cache(maxsize=8)
def _port(cfg):
    return CodebookPort(cfg)


def forward(P, buffers, images, cfg, codebook_weight=1.0, train=True):
    """P: official name -> tensor; buffers: the four quantize.* entries; images (B, C, S, S).
    -> dict: reconstruction, codes (B, k, k), rec_loss, commitment_loss, loss (codebook_weight
    times the commitment loss added) and buffers (after one EMA step when train, else the same)."""
    port = _port(cfg).train(train)
    new = {k: torch.as_tensor(v).clone() for k, v in buffers.items()}  # the EMA step writes into these
    rec, commitment, codes = torch.func.functional_call(port, {**P, **new}, (images,))
    rec_loss = F.l1_loss(rec, images)
    new["quantize.counter"] = int(new["quantize.counter"])
    return {"reconstruction": rec, "codes": codes, "rec_loss": rec_loss, "commitment_loss": commitment,
            "loss": rec_loss + codebook_weight * commitment, "buffers": new if train else dict(buffers)}
