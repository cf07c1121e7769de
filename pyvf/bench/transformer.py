"""Time and memory of one transformer training step (forward, backward, AdamW), pyvf against the
same model in torch (pyvf/verify/torch_transformer.py, SDPA with the tree's boolean mask), one run.

    pyvf bench transformer                  # tiny and paper configurations
    pyvf bench transformer --configs tiny   # just the tiny one (seconds)
    pyvf bench transformer --quick          # the tiny one, 10 steps

Each framework runs in its own worker process, so that neither's thread pool waits on the
other's (harmless on a quiet machine; 10x and more on small calls when other work loads it).
pyvf's step is split into the branching-attention kernel (forward and backward), the linear
layers (every x @ w, forward and backward) and the rest (LayerNorm, GELU, embeddings, losses,
the tied logits, AdamW), by timing those functions inside the step. Before timing, the first
step's loss and gradients of pyvf and torch (same weights, same batch), and the loss after
their first AdamW update, are compared (pyvf.bench.common.first_step_differs), and the tool
stops if they differ. Memory: the measured peak resident memory of one step above what was
resident before it (pyvf.bench.common.peak_memory), after a first step (it makes the optimizer's
moments, resident before every later step, as the weights). torch is imported only in the
torch worker.
"""

import contextlib
import sys
import time

import numpy as np

import pyvf
import pyvf.nn.attention
import pyvf.nn.layers
from pyvf.bench.common import checksums, first_step_differs, format_bytes, peak_memory, run_configs, run_worker, \
    worker_main

WORKER = "pyvf.bench.transformer"  # this module, run as `python -m WORKER SPEC` (worker_main)

CONFIGS = {
    "tiny": dict(n_embeddings=64, n_head=2, d_model=32, n_layer=2, token_image_size=4, sequence_size=5,
                 n_loss_skip=1, batch=8),
    # the paper's InteriorNet model: GPT-2 base, 20 views of 8x8 tokens, B = 1
    "paper": dict(n_embeddings=1024, n_head=12, d_model=768, n_layer=12, token_image_size=8, sequence_size=20,
                  n_loss_skip=4, batch=1),
}


@contextlib.contextmanager
def timed(totals):
    """Accumulate the time spent in the kernel and in the linear layers into totals."""
    patches = [(pyvf.nn.attention, "branching_attention_forward", "attention"),
               (pyvf.nn.attention, "branching_attention_backward", "attention"),
               (pyvf.nn.attention, "linear_forward", "linear"), (pyvf.nn.attention, "linear_backward", "linear"),
               (pyvf.nn.layers, "linear_forward", "linear"), (pyvf.nn.layers, "linear_backward", "linear")]
    saved = []
    for module, name, key in patches:
        fn = getattr(module, name)
        saved.append((module, name, fn))

        def wrapper(*a, _fn=fn, _key=key, **kw):
            t = time.perf_counter()
            try:
                return _fn(*a, **kw)
            finally:
                totals[_key] += time.perf_counter() - t
        setattr(module, name, wrapper)
    try:
        yield
    finally:
        for module, name, fn in saved:
            setattr(module, name, fn)


def batch(cfg, B, rng):
    tokens = rng.integers(0, cfg.n_embeddings, (B, cfg.sequence_size, cfg.L))
    poses = rng.normal(size=(B, cfg.sequence_size, 7))
    poses[..., 3:] /= np.linalg.norm(poses[..., 3:], axis=-1, keepdims=True)
    return tokens, pyvf.make_relative(poses)[0].astype(np.float32)


def setup(name, seed=0):
    spec = dict(CONFIGS[name])
    B = spec.pop("batch")
    cfg = pyvf.TransformerConfig(**spec)
    rng = np.random.default_rng(seed)
    tokens, poses = batch(cfg, B, rng)
    return cfg, B, tokens, poses, pyvf.Transformer(cfg, seed=seed)


def worker_pyvf(name, steps):
    cfg, B, tokens, poses, model = setup(name)
    loss = model.forward(tokens, poses).loss  # the first step's loss and gradients, for the cross-check
    gradients = checksums(model.backward())
    opt = pyvf.AdamW(model.params, lr=1e-4, weight_decay=0.01)

    def step():  # -> the loss before its update
        loss = model.forward(tokens, poses).loss
        opt.step(model.backward())
        return loss

    step()  # the warm-up: the first update writes the moments (one-time, as the weights: not a step's memory)
    after, mem = peak_memory(step)  # (its loss: the loss after one update, for the cross-check of AdamW)
    times, shares = [], {"attention": 0.0, "linear": 0.0}
    for _ in range(steps):
        t = time.perf_counter()
        with timed(shares):
            step()
        times.append(time.perf_counter() - t)
    total = sum(times)
    return dict(loss=loss, loss_after_update=after, gradients=gradients, time=float(np.median(times)), memory=mem,
                attention=shares["attention"] / total, linear=shares["linear"] / total,
                params=int(sum(p.size for p in model.params.values())))


def worker_torch(name, steps):
    import torch

    from pyvf.verify import torch_transformer

    torch.set_num_threads(pyvf.num_threads())
    cfg, B, tokens, poses, model = setup(name)
    P = {k: torch.tensor(v.copy(), requires_grad=True) for k, v in model.params.items()}
    opt = torch.optim.AdamW(P.values(), lr=1e-4, weight_decay=0.01)
    t_tokens, t_poses = torch.tensor(tokens), torch.tensor(poses)
    out = torch_transformer.forward(P, t_tokens, t_poses, cfg, sdpa=True)[-1]
    out.backward()
    loss = out.item()
    gradients = checksums({k: p.grad.numpy() if p.grad is not None else np.zeros(p.shape) for k, p in P.items()})

    def step():  # -> the loss before its update
        opt.zero_grad()
        loss = torch_transformer.forward(P, t_tokens, t_poses, cfg, sdpa=True)[-1]
        loss.backward()
        opt.step()
        return loss.item()

    step()  # the warm-up, as worker_pyvf's: the first step makes the moments
    after, mem = peak_memory(step)
    times = []
    for _ in range(steps):
        t = time.perf_counter()
        step()
        times.append(time.perf_counter() - t)
    return dict(loss=loss, loss_after_update=after, gradients=gradients, time=float(np.median(times)), memory=mem)


def worker(spec):
    """One framework's run in a worker process: {framework: "pyvf" | "torch", config, steps,
    threads} -> worker_pyvf's or worker_torch's dict."""
    pyvf.set_num_threads(spec["threads"])
    return (worker_pyvf if spec["framework"] == "pyvf" else worker_torch)(spec["config"], spec["steps"])


def bench(name, steps, threads):
    """Run both workers on one configuration and print the table: {"pyvf": ..., "torch": ...}, or
    None (printed to stderr) when their first steps differ."""
    p, t = (run_worker(WORKER, dict(framework=f, config=name, steps=steps, threads=threads))
            for f in ("pyvf", "torch"))
    # validate: the same first-step loss and gradients from the same weights and batch, and the same
    # loss after the first update (float32 both)
    differs = first_step_differs(p, t)
    if differs:
        print(f"{name}: pyvf and torch differ in {differs}", file=sys.stderr)
        return None
    spec = dict(CONFIGS[name])
    print(f"\n## {name}: d={spec['d_model']}, H={spec['n_head']}, {spec['n_layer']} layers, "
          f"N={spec['sequence_size']}, L={spec['token_image_size'] ** 2}, V={spec['n_embeddings']}, "
          f"B={spec['batch']}, {p['params'] / 1e6:.2f}M parameters, float32, {threads} threads, "
          f"median of {steps} steps, each framework in its own process")
    print(f"first-step loss: pyvf {p['loss']:.6f}, torch {t['loss']:.6f} (and the gradients, and the loss after an "
          "update, agree)")
    print("| | step time | peak memory of a step |")
    print("|---|---|---|")
    print(f"| pyvf | {p['time'] * 1e3:.1f} ms | {format_bytes(p['memory'])} |")
    print(f"| torch (SDPA + bool mask) | {t['time'] * 1e3:.1f} ms | {format_bytes(t['memory'])} |")
    print(f"| ratio torch / pyvf | {t['time'] / p['time']:.2f} | {t['memory'] / p['memory']:.2f} |")
    print(f"pyvf step time shares: branching attention {p['attention']:.0%}, linear layers {p['linear']:.0%}, "
          f"the rest {1 - p['attention'] - p['linear']:.0%}")
    return {"pyvf": p, "torch": t}


def run(configs=tuple(CONFIGS), steps=None, threads=2):
    """bench() on each configuration of CONFIGS named (steps: timed steps, default 20 tiny, 3
    paper). Returns the report; report["failures"] names a configuration whose first steps
    differed (nothing after it is run)."""
    return run_configs(lambda name: bench(name, steps or (20 if name == "tiny" else 3), threads), configs,
                       dict(configs=list(configs), steps=steps, threads=threads), threads)


if __name__ == "__main__":  # a worker: `python -m pyvf.bench.transformer SPEC` (bench, run_worker)
    worker_main(worker)
