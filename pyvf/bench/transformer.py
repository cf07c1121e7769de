"""Time and memory of one transformer training step (forward, backward, AdamW), pyvf against the
same model in torch (pyvf/verify/torch_transformer.py, SDPA with a boolean mask).

    pyvf bench transformer           # the tiny and the paper configuration
    pyvf bench transformer --quick   # the tiny one, 5 steps

Each framework runs in its own worker process, so that neither's thread pool waits on the
other's. Before timing, the first step's loss and gradients of pyvf and torch (same weights, same
batch) and the loss after their first update are compared (common.first_step_differs); the tool
stops if they differ. Memory: the peak resident memory of one step above what was resident
before it, after a first step (which makes the optimizer's moments).
"""

import numpy as np

import pyvf
from pyvf.bench.common import checksums, compare_steps, step_figures, step_worker, worker_main

WORKER = "pyvf.bench.transformer"  # this module, run as `python -m WORKER SPEC` (worker_main)

CONFIGS = {
    "tiny": dict(n_embeddings=64, n_head=2, d_model=32, n_layer=2, token_image_size=4, sequence_size=5,
                 n_loss_skip=1, batch=8),
    # the paper's InteriorNet model: GPT-2 base, 20 views of 8x8 tokens, B = 1
    "paper": dict(n_embeddings=1024, n_head=12, d_model=768, n_layer=12, token_image_size=8, sequence_size=20,
                  n_loss_skip=4, batch=1),
}
FULL = ("tiny", "paper")


def setup(name, seed=0):
    spec = dict(CONFIGS[name])
    B = spec.pop("batch")
    cfg = pyvf.TransformerConfig(**spec)
    rng = np.random.default_rng(seed)
    tokens = rng.integers(0, cfg.n_embeddings, (B, cfg.sequence_size, cfg.L))
    poses = rng.normal(size=(B, cfg.sequence_size, 7))
    poses[..., 3:] /= np.linalg.norm(poses[..., 3:], axis=-1, keepdims=True)
    return cfg, tokens, pyvf.make_relative(poses)[0].astype(np.float32), pyvf.Transformer(cfg, seed=seed)


def worker_pyvf(name, steps):
    cfg, tokens, poses, model = setup(name)
    loss = model.forward(tokens, poses).loss  # the first step's loss and gradients, for the cross-check
    gradients = checksums(model.backward())
    opt = pyvf.AdamW(model.params, lr=1e-4, weight_decay=0.01)

    def step():  # -> the loss before its update
        loss = model.forward(tokens, poses).loss
        opt.step(model.backward())
        return loss
    return dict(loss=loss, gradients=gradients, **step_figures(step, steps))


def worker_torch(name, steps):
    import torch

    from pyvf.verify import torch_transformer

    torch.set_num_threads(pyvf.num_threads())
    cfg, tokens, poses, model = setup(name)
    P = {k: torch.tensor(v.copy(), requires_grad=True) for k, v in model.params.items()}
    opt = torch.optim.AdamW(P.values(), lr=1e-4, weight_decay=0.01)
    t_tokens, t_poses = torch.tensor(tokens), torch.tensor(poses)
    out = torch_transformer.forward(P, t_tokens, t_poses, cfg, sdpa=True)[-1]
    out.backward()
    gradients = checksums({k: p.grad.numpy() if p.grad is not None else np.zeros(p.shape) for k, p in P.items()})

    def step():  # -> the loss before its update
        opt.zero_grad()
        loss = torch_transformer.forward(P, t_tokens, t_poses, cfg, sdpa=True)[-1]
        loss.backward()
        opt.step()
        return loss.item()
    return dict(loss=out.item(), gradients=gradients, **step_figures(step, steps))


worker = step_worker(worker_pyvf, worker_torch)  # one framework's run in a worker process


def describe(name):
    s = CONFIGS[name]
    return (f"d={s['d_model']}, H={s['n_head']}, {s['n_layer']} layers, N={s['sequence_size']}, "
            f"L={s['token_image_size'] ** 2}, V={s['n_embeddings']}, B={s['batch']}")


def run(configs=FULL, steps=None, threads=2):
    """common.compare_steps on each configuration named (steps: timed steps, default 20 tiny, 3 paper)."""
    return compare_steps(WORKER, configs, lambda name: steps or (3 if name == "paper" else 20), threads, describe)


if __name__ == "__main__":  # a worker: `python -m pyvf.bench.transformer SPEC`
    worker_main(worker)
