"""Time and memory of one codebook training step (forward with the EMA update, backward, Adam),
pyvf against the same model in torch (pyvf/verify/torch_codebook.py).

    pyvf bench codebook           # the official tiny and the paper configuration
    pyvf bench codebook --quick   # the tiny one on a batch of two 32x32 images, 5 steps

The step is `pyvf train-codebook`'s (pyvf.codebook_train_step: Adam, lr 1.584e-3, betas (0.5,
0.9)); checked and measured as `pyvf bench transformer` is (pyvf/bench/transformer.py).
"""

import numpy as np

import pyvf
from pyvf.bench.common import checksums, compare_steps, step_figures, step_worker, worker_main

WORKER = "pyvf.bench.codebook"  # this module, run as `python -m WORKER SPEC` (worker_main)

CONFIGS = {  # the tiny one at pyvf train-codebook's batch
    "tiny": dict(ch=32, ch_mult=(1, 1, 2, 2), num_res_blocks=1, attn_resolutions=(8,), z_channels=32, embed_dim=32,
                 n_embed=64, image_size=64, batch=16),
    "paper": dict(ch=128, ch_mult=(1, 1, 2, 2, 4), num_res_blocks=2, attn_resolutions=(16,), z_channels=256,
                  embed_dim=256, n_embed=1024, image_size=128, batch=2),
}
CONFIGS["quick"] = dict(CONFIGS["tiny"], image_size=32, batch=2)  # --quick: the tiny one on a small batch
FULL = ("tiny", "paper")
LR, BETAS = 1.584e-3, (0.5, 0.9)  # the published codebook's Adam


def setup(name):
    spec = dict(CONFIGS[name])
    B = spec.pop("batch")
    cfg = pyvf.CodebookConfig(**spec)
    images = np.tanh(np.random.default_rng(0).standard_normal((B, 3, cfg.image_size, cfg.image_size)))
    return cfg, pyvf.Codebook(cfg, seed=0), images.astype(np.float32)


def worker_pyvf(name, steps):
    _, cb, images = setup(name)
    loss = float(cb.forward(images, train=True).loss)  # the first step's loss and gradients
    gradients = checksums(cb.backward())
    _, cb, images = setup(name)  # a fresh model: the forward above moved the EMA
    opt = pyvf.Adam(cb.params, LR, betas=BETAS)
    step = lambda: float(pyvf.codebook_train_step(cb, opt, images).loss)  # noqa: E731  (the loss before its update)
    return dict(loss=loss, gradients=gradients, **step_figures(step, steps))


def worker_torch(name, steps):
    import torch

    from pyvf.verify import torch_codebook

    torch.set_num_threads(pyvf.num_threads())
    cfg, cb, images = setup(name)
    P = {k: torch.tensor(v, requires_grad=True) for k, v in cb.params.items()}
    q = cb.quantizer
    state = {"buffers": {"quantize.embeddings": torch.tensor(q.embeddings),
                         "quantize.ema_cluster_size_hidden": torch.tensor(q.ema_cluster_size_hidden),
                         "quantize.ema_dw_hidden": torch.tensor(q.ema_dw_hidden), "quantize.counter": q.counter}}
    x = torch.tensor(images)
    out = torch_codebook.forward(P, state["buffers"], x, cfg, train=True)
    out["loss"].backward()
    loss = out["loss"].item()
    gradients = checksums({k: p.grad.numpy() if p.grad is not None else np.zeros(p.shape) for k, p in P.items()})
    opt = torch.optim.Adam(P.values(), LR, betas=BETAS)

    def step():  # -> the loss before its update, from the weights and buffers the forward above started from
        opt.zero_grad()
        out = torch_codebook.forward(P, state["buffers"], x, cfg, train=True)
        out["loss"].backward()
        opt.step()
        state["buffers"] = out["buffers"]  # the EMA update kept, as pyvf's codebook keeps it
        return out["loss"].item()
    return dict(loss=loss, gradients=gradients, **step_figures(step, steps))


worker = step_worker(worker_pyvf, worker_torch)  # one framework's run in a worker process


def describe(name):
    s = CONFIGS[name]
    return (f"ch={s['ch']}, ch_mult={s['ch_mult']}, {s['num_res_blocks']} res blocks, {s['image_size']}x"
            f"{s['image_size']} images, K={s['n_embed']}, D={s['embed_dim']}, batch {s['batch']}")


def run(configs=FULL, steps=None, threads=2):
    """common.compare_steps on each configuration named (steps: timed steps, default 10 tiny, 3 paper)."""
    return compare_steps(WORKER, configs, lambda name: steps or (3 if name == "paper" else 10), threads, describe)


if __name__ == "__main__":  # a worker: `python -m pyvf.bench.codebook SPEC`
    worker_main(worker)
