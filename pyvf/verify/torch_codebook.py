"""The torch port of pyvf.verify.torch_ports.CodebookPort as a function of a parameter dict by the
official torch names (torch.func.functional_call; the EMA step runs on a copy of the buffers): the
oracle of tests/test_codebook.py and the benchmark's torch side (pyvf bench codebook).
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
