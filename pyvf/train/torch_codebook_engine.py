"""The torch engine of train_codebook: the same loop, batches, recipe (Adam, object-pixel
weighting, dead-code restarts), run folder and checkpoints as pyvf's engine, with the model and
the update in torch, on a CPU or a GPU (docs/howto-torch-engine.md).

The model is pyvf.verify's CodebookPort (taming-transformers' module tree with the published
state dict's names, written from docs/math.md §4 and tested against pyvf's Codebook), loaded
with pyvf's Codebook(config, seed), parameters and EMA buffers, so both engines start alike. The
update is torch_engine.TorchAdamW on the pyvf Adam of the run (betas, eps and the torch epsilon
convention are that Adam's; its moments are saved in pyvf's layout). The port's quantizer does
the EMA update of docs/math.md §4 in training mode, after the lookup, in float32 whatever the
precision (bf16 autocast covers the encoder and the decoder only). The object-pixel weighting is
Codebook.forward's weighted mean, and the dead-code restart is pyvf's own
EMAQuantizer.reset_dead_codes run on the port's buffers and encoder output (on the CPU, every
reset_dead_codes steps), so a checkpoint of either engine resumes in the other.

At every checkpoint pyvf loads the torch model's weights and buffers, runs a fixed batch
(parity_images) and compares its codes, reconstruction and losses with the torch model's
(evaluation mode: no EMA update) within torch_engine.PARITY_RTOL; parity.csv logs the worst
error and a larger one stops the run naming the first divergent quantity. The codes must be
equal: a code chosen otherwise by a float32 near-tie (two codes equidistant to rounding) would
stop the run too, and shows as `codes`. tests/test_torch_engine.py checks a float64 run (gradients,
Adam, EMA, restarts) against pyvf's to 1e-9 of the weights' movement; a free float32 run drifts
further from pyvf's (8.7e-4 of the movement in 20 steps on the tests' model), as Adam normalises
gradient entries that are below their own rounding error, and pyvf's float32 run drifts as far
from its float64 one.

One process: the EMA statistics are sums over the whole batch (a data-parallel codebook would
all-reduce them too, which this engine does not).
"""

import numpy as np

from ..nn.quantizer import code_statistics
from .batches import codebook_batch
from .torch_engine import TorchAdamW, TorchEngine, check_engine, import_torch, world_size

_QUANTIZE = "quantize."  # the buffers' prefix in the state dict


def check_codebook_engine(engine, device, precision, dtype):
    """torch_engine.check_engine, and the codebook's torch engine runs in one process: torchrun's
    WORLD_SIZE > 1 is refused (train_codebook checks all of it before it touches the run folder)."""
    check_engine(engine, device, precision, dtype)
    if engine == "torch" and world_size() > 1:
        raise ValueError(f"the codebook's torch engine runs in one process, got {world_size()} (torchrun's "
                         "WORLD_SIZE): run pyvf train-codebook without torchrun")


class TorchCodebook(TorchEngine):
    """The torch engine's model and optimiser for train_codebook's loop.

    model: the pyvf Codebook holding the starting weights and buffers (a fresh one, or restored
    from a checkpoint); opt_ref: the pyvf Adam built on model.params (restored too)."""

    def __init__(self, model, opt_ref, *, device="cpu", precision="fp32"):
        torch = import_torch()
        from ..verify.torch_ports import CodebookPort
        check_codebook_engine("torch", device, precision, str(model.dtype))
        self.torch, self.config, self.pyvf_model = torch, model.config, model
        self.device, self.precision = torch.device(device), precision
        self.dtype = {"float32": torch.float32, "float64": torch.float64}[str(model.dtype)]
        self.port = CodebookPort(model.config).to(self.device, self.dtype)  # training mode: EMA updates
        self._names = dict(self.port.named_parameters())  # the published names, as model.params'
        self.load(model.state_dict())
        self.opt = TorchAdamW(self._names, opt_ref, model)

    def load(self, state):
        """state: Codebook.state_dict(): the parameters and the quantizer's buffers."""
        self.port.load_state_dict({k: self.torch.as_tensor(v) for k, v in state.items()})

    def to_pyvf(self):
        """The pyvf Codebook, given the torch model's current weights and buffers."""
        self.pyvf_model.load_official({k: v.detach().cpu().numpy() for k, v in self.port.state_dict().items()})
        return self.pyvf_model

    def _forward(self, x, autocast):
        """x (B, C, S, S) on the device -> reconstruction (B, C, S, S), commitment loss, codes
        (B, k, k); in training mode the quantizer applies one EMA update (after the lookup)."""
        port, torch = self.port, self.torch
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=autocast):
            z = port.quant_conv(port.encoder(x))  # (B, D, k, k)
        q, commitment, codes = port.quantize(z.to(self.dtype))  # the lookup and the EMA never in bf16
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=autocast):
            rec = port.decoder(port.post_quant_conv(q))
        return rec.to(self.dtype), commitment, codes

    def step(self, images, pixel_weights=None):
        """One update on images (B, C, S, S) in [-1, 1] (numpy; pixel_weights (B, 1, S, S) or None,
        as Codebook.forward's) -> the log's values: loss, rec_loss, commitment, perplexity, usage."""
        torch = self.torch
        x = torch.as_tensor(images).to(self.device)
        self._zero_grad()
        rec, commitment, codes = self._forward(x, self.precision == "bf16")
        diff = (rec - x).abs()  # (B, C, S, S)
        if pixel_weights is None:
            rec_loss = diff.mean()
        else:  # sum w |rec - x| / (C sum w): Codebook.forward's weighted mean
            w = torch.as_tensor(pixel_weights).to(self.device)  # (B, 1, S, S)
            rec_loss = (w * diff).sum() / (diff.shape[1] * w.sum())
        loss = rec_loss + self.config.codebook_weight * commitment
        loss.backward()
        norm = torch.stack(torch._foreach_norm([p.grad for p in self._names.values()])).square().sum()
        stats = torch.stack([loss.detach(), rec_loss.detach(), commitment.detach(), norm]).cpu().numpy()
        self._refuse_nonfinite(stats, "loss, rec_loss, commitment, |g|^2")
        self.opt.step()
        counts = torch.bincount(codes.reshape(-1), minlength=self.config.n_embed).cpu().numpy()  # (K,)
        usage, perplexity = code_statistics(counts)
        return {"loss": float(stats[0]), "rec_loss": float(stats[1]), "commitment": float(stats[2]),
                "perplexity": perplexity, "usage": usage}

    def reset_dead_codes(self, images, rng, **codes):
        """pyvf's EMAQuantizer.reset_dead_codes on the port's buffers, with the encoder's output
        z of images (B, C, S, S) by the updated weights, as pyvf's loop. Returns the codes reset."""
        torch, quantizer = self.torch, self.pyvf_model.quantizer
        with torch.no_grad():
            z = self.port.quant_conv(self.port.encoder(torch.as_tensor(images).to(self.device)))  # (B, D, k, k)
        quantizer.load_state_dict({k: v.cpu().numpy() for k, v in self.port.quantize.state_dict().items()})
        n = quantizer.reset_dead_codes(z.cpu().numpy(), rng=rng, **codes)
        self.port.quantize.load_state_dict({k: torch.as_tensor(v) for k, v in quantizer.state_dict().items()})
        return n

    def parity(self, images):
        """pyvf against the torch model (evaluation mode, no autocast) on images (B, C, S, S):
        pyvf.compare's Comparison of codes, reconstruction, losses."""
        torch = self.torch
        x = torch.as_tensor(images).to(self.device)
        self.port.eval()  # no EMA update
        try:
            with torch.no_grad():
                rec, commitment, codes = self._forward(x, False)
        finally:
            self.port.train()
        rec_loss = (rec - x).abs().mean()
        mine = {"codes": codes.cpu().numpy(), "reconstruction": rec.cpu().numpy(),
                "rec_loss": np.asarray(rec_loss.item()), "commitment_loss": np.asarray(commitment.item()),
                "loss": np.asarray((rec_loss + self.config.codebook_weight * commitment).item())}
        return self._parity(mine, self.to_pyvf().forward(images))


def parity_images(images, seed, dtype):
    """The fixed batch the codebook's parity checks run: 4 views drawn as codebook_batch draws,
    from a seed no training run of `seed` uses for its batches. images (M, S, S, C) uint8."""
    return codebook_batch(images, 4, seed + 1_000_003, 0, dtype)


__all__ = ["TorchCodebook", "check_codebook_engine", "parity_images"]
