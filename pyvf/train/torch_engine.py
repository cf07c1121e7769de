"""The torch engines of train_transformer and train_codebook (docs/howto-torch-engine.md): pyvf's
loop, batches, schedule and run folder, with the model (pyvf.verify's ports) and the update
(optim.adam_update on torch tensors, the moments saved in pyvf's layout) in torch: a checkpoint of
either engine resumes in the other. bf16 autocasts the arithmetic (not the codebook's lookup and EMA).

At every checkpoint pyvf runs a fixed batch with the torch model's weights: the worst error goes
to parity.csv, one over PARITY_RTOL stops the run. Data-parallel (the transformer, under torchrun):
every process draws the batch of (seed, step) and runs its shard of the rows, its mean loss weighted
by its share of the batch; rank 0 alone writes the run folder.
"""

import os
import re

import numpy as np

from ..geometry import make_relative
from ..nn.quantizer import code_statistics
from ..verify.compare import compare
from ..verify.layout import params_from_layout, params_to_layout
from .optim import adam_update

# The parity bound: pyvf.compare's normwise relative error, float32 torch against float32 pyvf.
# Both round every dot product (length up to 4d) to float32 (u = 6e-8) in another order: about
# sqrt(4d) * u = 1.4e-6 per layer at d = 128, compounded over the blocks and amplified by the
# LayerNorms; the tiny model measures 1e-6 to 1e-5, the codebook 3.8e-6. 1e-3 is compare's float32
# default: two orders above that, below what one wrong layer gives (>= 1e-2). One model's forward in
# two engines: it does not grow with the steps a run took to reach the weights.
PARITY_RTOL = 1e-3


def import_torch():
    try:
        import torch
    except ImportError as e:
        raise ImportError("engine='torch' needs torch: pip install 'pyvf[torch]'") from e
    return torch


def check_engine(engine, device, precision, dtype=None, one_process=False):
    """engine 'pyvf' | 'torch'; device 'cpu' | 'cuda' | 'cuda:N' and precision 'fp32' | 'bf16' (the
    torch engine's only); bf16 with a float64 dtype, and with one_process a torchrun, are refused."""
    if engine not in ("pyvf", "torch"):
        raise ValueError(f"engine must be 'pyvf' or 'torch', got {engine!r}")
    if precision not in ("fp32", "bf16"):
        raise ValueError(f"precision must be 'fp32' or 'bf16', got {precision!r}")
    if not isinstance(device, str) or not re.fullmatch(r"cpu|cuda|cuda:(0|[1-9][0-9]*)", device):
        raise ValueError(f"device must be 'cpu', 'cuda' or 'cuda:N', got {device!r}")
    if engine == "pyvf" and (device != "cpu" or precision != "fp32"):
        raise ValueError(f"device={device!r} and precision={precision!r} need engine='torch'")
    if engine == "torch" and device != "cpu":
        torch = import_torch()
        n = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if int(device[5:] or 0) >= n:
            raise ValueError(f"device={device!r}, but torch sees {n} CUDA devices")
    if dtype is not None and precision == "bf16" and str(dtype) != "float32":
        raise ValueError(f"precision='bf16' autocasts float32 arithmetic, but the configuration's dtype is {dtype}")
    if one_process and engine == "torch" and world_size() > 1:
        raise ValueError(f"the codebook's torch engine runs in one process, got {world_size()} (torchrun's WORLD_SIZE)")


class DataParallel:
    """This process's rank in a data-parallel run, the world size, the collectives."""

    def __init__(self, dist, device, created):
        self.dist, self.device, self.created = dist, device, created
        self.rank, self.world = dist.get_rank(), dist.get_world_size()

    def shard(self, batch_size):
        """This process's rows lo:hi of a batch: contiguous shards, sizes differing by at most one."""
        base, extra = divmod(batch_size, self.world)
        lo = self.rank * base + min(self.rank, extra)
        return lo, lo + base + (self.rank < extra)

    def all_reduce(self, tensors):
        """Sum each tensor across the processes, in place, in one all-reduce."""
        flat = import_torch().cat([t.reshape(-1) for t in tensors])
        self.dist.all_reduce(flat)
        for t, summed in zip(tensors, flat.split([t.numel() for t in tensors])):
            t.copy_(summed.view_as(t))

    def broadcast(self, tensors):
        """Rank 0's values of the tensors into every process's, in place."""
        with import_torch().no_grad():
            for t in tensors:
                self.dist.broadcast(t, 0)

    def broadcast_int(self, value):
        t = import_torch().tensor([int(value)], device=self.device)
        self.broadcast([t])
        return int(t.item())

    def close(self):
        if self.created:
            self.dist.destroy_process_group()


def world_size():
    """The processes of this run: the process group's size, else torchrun's WORLD_SIZE, else 1."""
    import_torch()
    import torch.distributed as dist
    if dist.is_available() and dist.is_initialized():
        return dist.get_world_size()
    return int(os.environ.get("WORLD_SIZE", "1"))


def data_parallel(device, batch_size):
    """-> (DataParallel or None, the device this process trains on): the caller's process group, or
    one made from torchrun's environment (gloo on the CPU, nccl on cuda:LOCAL_RANK)."""
    torch = import_torch()
    import torch.distributed as dist
    initialised, world = dist.is_available() and dist.is_initialized(), world_size()
    if world <= 1:
        return None, device
    if device.startswith("cuda:"):
        raise ValueError(f"device={device!r} names one GPU for {world} processes: pass device 'cuda'")
    if batch_size < world:
        raise ValueError(f"batch_size={batch_size} is smaller than the {world} processes")
    if device == "cuda":
        local = int(os.environ.get("LOCAL_RANK", dist.get_rank() if initialised else 0))
        device = f"cuda:{local % torch.cuda.device_count()}"
        torch.cuda.set_device(device)
    if not initialised:
        dist.init_process_group("nccl" if device.startswith("cuda") else "gloo")
    return DataParallel(dist, torch.device(device), created=not initialised), device


class Follower:
    """Run's stand-in on the processes other than rank 0: the same steps, nothing read or written."""

    resumed, model_state, optimizer_state = False, None, None

    def __init__(self, start, steps_total):
        self.start, self.steps_total = start, steps_total

    def steps(self):
        return range(self.start + 1, self.steps_total + 1)

    def checkpoint(self, *args):
        pass

    log = save_final = checkpoint


class TorchEngine:
    """What both torch engines share: the port's parameters by official name (_names); the update
    (optim.adam_update on torch tensors, with opt's settings, schedule and step count; _sync() puts
    the moments in opt); the parity check; to_pyvf() -> the pyvf model and opt as the engine has them."""

    def __init__(self, model, opt, device, precision, parity_batch):
        self.torch = torch = import_torch()
        self.config, self.pyvf_model, self.opt = model.config, model, opt
        self.device, self.precision, self.parity_batch = torch.device(device), precision, parity_batch
        self.dtype = getattr(torch, str(model.dtype))  # torch.float32 or torch.float64

    def _load_moments(self):
        """The optimiser's moments as tensors beside the port's parameters (_names)."""
        def on_device(arrays):
            arrays = params_to_layout(self.pyvf_model, arrays, "torch")  # pyvf's layout -> nn.Linear's
            return {k: self.torch.as_tensor(arrays[k]).to(p.device, p.dtype).contiguous()
                    for k, p in self._names.items()}
        self.exp_avg, self.exp_avg_sq = on_device(self.opt.exp_avg), on_device(self.opt.exp_avg_sq)

    def _update(self):
        """AdamW.step from the parameters' .grad (finite: the caller checked)."""
        r = self.opt
        lr, t = r.lr_at(r.step_count), r.step_count + 1
        with self.torch.no_grad():
            for k, p in self._names.items():
                wd = r.weight_decay if k in r.decayed else 0.0
                p1, self.exp_avg[k], self.exp_avg_sq[k] = adam_update(
                    p, self.exp_avg[k], self.exp_avg_sq[k], p.grad, lr, t, *r.betas, r.eps, wd,
                    r.eps_convention == "keras", sqrt=self.torch.sqrt)
                p.copy_(p1)
        r.step_count = t

    def _sync(self):
        for mine, theirs in ((self.exp_avg, "exp_avg"), (self.exp_avg_sq, "exp_avg_sq")):
            arrays = {k: a.detach().cpu().numpy() for k, a in mine.items()}
            setattr(self.opt, theirs, params_from_layout(self.pyvf_model, arrays, "torch"))  # pyvf's layout, numpy

    def _refuse_nonfinite(self, stats, names):
        if not np.isfinite(stats).all():
            raise ValueError(f"the gradients or the loss are not finite at step {self.opt.step_count + 1} "
                             f"({names} = {stats.tolist()}): no update applied; lower the learning rate")

    def _parity(self, mine, out):
        return compare(mine, {k: np.asarray(getattr(out, k)) for k in mine}, rtol=PARITY_RTOL)

    def check(self, run, step):
        """Before the checkpoint of `step`: the parity, logged to parity.csv; a failure raises."""
        comparison = self.parity(*self.parity_batch)
        worst = max(comparison.rows, key=lambda r: (not np.isfinite(r.rel), r.rel))
        run.log_parity(step, worst.name, worst.rel, PARITY_RTOL)
        if not comparison.ok:
            raise RuntimeError(f"parity check at step {step}: the torch model and pyvf differ first in "
                               f"{comparison.first!r} (normwise relative error over {PARITY_RTOL}); the "
                               f"checkpoint before it is intact. Comparison:\n{comparison}")


class TorchTransformer(TorchEngine):
    """train_transformer's torch engine, continuing the pyvf Transformer `model` and its AdamW
    `opt_ref`. dp: a DataParallel (rank 0's state is broadcast to every process) or None."""

    def __init__(self, model, opt_ref, *, device="cpu", precision="fp32", max_grad_norm=None, dp=None,
                 parity_batch=None):
        super().__init__(model, opt_ref, device, precision, parity_batch)
        from ..verify.torch_ports import TransformerPort, official_name, transformer_losses
        self.max_grad_norm, self.dp, self._losses = max_grad_norm, dp, transformer_losses
        self.port = TransformerPort(model.config).to(self.device, self.dtype)
        self._names = {official_name(n): p for n, p in self.port.named_parameters()}
        with self.torch.no_grad():
            for k, a in model.state_dict(layout="torch").items():
                self._names[k].copy_(self.torch.as_tensor(a))
        self._load_moments()
        if dp is not None:  # every process continues rank 0's state (a fresh start, or its checkpoint)
            dp.broadcast([*self._names.values(), *self.exp_avg.values(), *self.exp_avg_sq.values()])
            opt_ref.step_count = dp.broadcast_int(opt_ref.step_count)

    def to_pyvf(self):
        self._sync()
        self.pyvf_model.load_official({k: p.detach().cpu().numpy() for k, p in self._names.items()},
                                      layout="torch")
        return self.pyvf_model

    def _outputs(self, tokens, poses, autocast):
        """tokens (B, N, L) int64, poses (B, N, 7) numpy, poses already relative -> logits,
        raw pose, ce (B,), pose loss (B,), loss, on the device."""
        torch = self.torch
        tok = torch.as_tensor(tokens).to(self.device, non_blocking=True)
        pos = torch.as_tensor(poses).to(self.device, non_blocking=True)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=autocast):
            logits, raw = self.port(tok, pos)
        logits, raw = logits.float() if autocast else logits, raw.float() if autocast else raw
        return (logits, raw, *self._losses(logits, raw, tok, pos, self.config))

    def step(self, tokens, poses):
        """One update on a batch (poses made relative here) -> the log's values but lr. The
        gradients are the batch's mean loss's, summed across the processes before the clipping."""
        torch, B = self.torch, len(tokens)
        lo, hi = (0, B) if self.dp is None else self.dp.shard(B)
        self.port.zero_grad(set_to_none=True)
        poses = make_relative(poses)[0]
        _, _, ce, pl, loss = self._outputs(tokens[lo:hi], poses[lo:hi], self.precision == "bf16")
        share = (hi - lo) / B  # loss = mean over the shard: its part of the batch mean is share * loss
        (loss * share).backward()
        grads = [p.grad for p in self._names.values()]
        sums = torch.stack([loss.detach() * share, ce.detach().sum() / B, pl.detach().sum() / B])
        if self.dp is not None:
            self.dp.all_reduce([*grads, sums])
        norms = torch.stack(torch._foreach_norm(grads))  # (n_params,) each tensor's |g|
        total = norms.square().sum().sqrt()
        stats = torch.cat([sums, total[None]]).cpu().numpy()
        self._refuse_nonfinite(stats, "loss, ce, pose loss, grad norm")
        if self.max_grad_norm is not None:  # tf.clip_by_norm per tensor, as pyvf's clip_grad_norm
            m = float(self.max_grad_norm)
            scale = torch.where(norms > m, m / norms, torch.ones_like(norms))
            torch._foreach_mul_(grads, list(scale.unbind()))
        self._update()
        return dict(zip(("loss", "ce_loss", "pose_loss", "grad_norm"), map(float, stats)))

    def parity(self, tokens, poses):
        """pyvf.compare's Comparison of the torch model (no autocast) against pyvf on one batch."""
        torch = self.torch
        pos = make_relative(poses)[0]
        with torch.no_grad():
            logits, raw, ce, pl, loss = self._outputs(tokens, pos, False)
        mine = {"logits": logits.cpu().numpy(), "pose_raw": raw.cpu().numpy(), "ce_loss": ce.cpu().numpy(),
                "pose_loss": pl.cpu().numpy(), "loss": np.asarray(loss.item())}
        return self._parity(mine, self.to_pyvf().forward(tokens, pos.astype(self.pyvf_model.dtype)))


class TorchCodebook(TorchEngine):
    """train_codebook's torch engine (one process), continuing the pyvf Codebook `model` and its Adam
    `opt_ref`. The port's quantizer does the EMA update in training mode."""

    def __init__(self, model, opt_ref, *, device="cpu", precision="fp32", parity_batch=None):
        super().__init__(model, opt_ref, device, precision, parity_batch)
        from ..verify.torch_ports import CodebookPort
        self.port = CodebookPort(model.config).to(self.device, self.dtype)  # training mode: EMA updates
        self._names = dict(self.port.named_parameters())  # the published names, as model.params'
        self.port.load_state_dict({k: self.torch.as_tensor(v) for k, v in model.state_dict().items()})
        self._load_moments()

    def to_pyvf(self):
        self._sync()
        self.pyvf_model.load_official({k: v.detach().cpu().numpy() for k, v in self.port.state_dict().items()})
        return self.pyvf_model

    def _forward(self, x, autocast):
        """x (B, C, S, S) on the device -> reconstruction (B, C, S, S), commitment loss, codes
        (B, k, k); in training mode the quantizer applies one EMA update (after the lookup)."""
        port, torch = self.port, self.torch
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=autocast):
            z = port.quant_conv(port.encoder(x))  # (B, D, k, k)
        q, commitment, codes = port.quantize(z.to(self.dtype), port.empty_patches(x))  # lookup and EMA never bf16
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=autocast):
            rec = port.decoder(port.post_quant_conv(q))
        return rec.to(self.dtype), commitment, codes

    def step(self, images, pixel_weights=None):
        """One update on images (B, C, S, S) (pixel_weights: Codebook.forward's) -> the log's values but lr."""
        torch = self.torch
        x = torch.as_tensor(images).to(self.device)
        self.port.zero_grad(set_to_none=True)
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
        self._update()
        counts = torch.bincount(codes.reshape(-1), minlength=self.config.n_embed).cpu().numpy()  # (K,)
        usage, perplexity = code_statistics(counts)
        return {"loss": float(stats[0]), "rec_loss": float(stats[1]), "commitment": float(stats[2]),
                "perplexity": perplexity, "usage": usage}

    def reset_dead_codes(self, images, rng, **codes):
        """pyvf's EMAQuantizer.reset_dead_codes on the port's buffers and the encoder's output of images."""
        torch, quantizer = self.torch, self.pyvf_model.quantizer
        with torch.no_grad():
            z = self.port.quant_conv(self.port.encoder(torch.as_tensor(images).to(self.device)))  # (B, D, k, k)
        quantizer.load_state_dict({k: v.cpu().numpy() for k, v in self.port.quantize.state_dict().items()})
        empty = self.pyvf_model.empty_patches(images)  # None without the empty code
        quantizer.reset_dead_codes(z.cpu().numpy(), rng=rng, empty=empty, **codes)
        self.port.quantize.load_state_dict({k: torch.as_tensor(v) for k, v in quantizer.state_dict().items()})

    def parity(self, images):
        """pyvf.compare's Comparison of the torch model (evaluation mode) against pyvf on images."""
        torch = self.torch
        x = torch.as_tensor(images).to(self.device)
        self.port.eval()  # no EMA update
        with torch.no_grad():
            rec, commitment, codes = self._forward(x, False)
        self.port.train()
        rec_loss = (rec - x).abs().mean()
        mine = {"codes": codes.cpu().numpy(), "reconstruction": rec.cpu().numpy(),
                "rec_loss": np.asarray(rec_loss.item()), "commitment_loss": np.asarray(commitment.item()),
                "loss": np.asarray((rec_loss + self.config.codebook_weight * commitment).item())}
        return self._parity(mine, self.to_pyvf().forward(images))
