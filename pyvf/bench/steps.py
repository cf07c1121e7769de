"""One training step, pyvf against the same model in torch: time and memory, after checking that
both compute the same step (`pyvf bench transformer`, `pyvf bench codebook`).

    pyvf bench transformer           # the tiny and the paper configuration (forward, backward, AdamW)
    pyvf bench transformer --quick   # the tiny one, 5 steps
    pyvf bench codebook              # forward with the EMA update, backward, Adam: `pyvf train-codebook`'s step
    pyvf bench codebook --quick      # the tiny one on a batch of two 32x32 images, 5 steps

The torch models are pyvf/verify/torch_transformer.py (SDPA with a boolean mask) and
torch_codebook.py. Each framework runs in its own worker process, so that neither's thread pool
waits on the other's. Before timing, the first step's loss and gradients of pyvf and torch (same
weights, same batch) and the loss after their first update are compared (first_step_differs); the
tool stops if they differ. Memory: the peak resident memory of one step above what was resident
before it, after a first step (which makes the optimizer's moments). torch is imported only in the
torch worker.
"""

import sys
import zlib

import numpy as np

import pyvf
from pyvf.bench.common import format_bytes, median_time, ms, peak_memory, run_worker, table, worker_main

WORKER = "pyvf.bench.steps"  # this module, run as `python -m WORKER SPEC` (worker_main)
FULL = ("tiny", "paper")

# pyvf's and torch's first step, compared before any time is printed: the loss and the loss after
# the first update to LOSS_RTOL (float32 both, the same weights and batch); each gradient's
# checksums to CHECK_RTOL of its norm (measured: 3e-5 at most, the paper codebook). A gradient
# below CHECK_FLOOR of the largest one's norm is compared at that level: the biases that feed a
# normalisation have a gradient of exactly 0, computed as rounding noise.
LOSS_RTOL, CHECK_RTOL, CHECK_FLOOR = 1e-4, 1e-3, 1e-3


def checksums(arrays):
    """{name: [2-norm, projection]} of each array, the projection its dot product with unit-normal
    numbers seeded by its name (the same in every process): what a worker sends of a gradient. An
    array zeroed, transposed or missing a term moves the projection by about its norm."""
    out = {}
    for name, a in arrays.items():
        a = np.asarray(a, dtype=np.float64).ravel()
        r = np.random.default_rng(zlib.crc32(name.encode())).standard_normal(a.size)
        out[name] = [float(np.sqrt(a @ a)), float(a @ r)]
    return out


def first_step_differs(p, t):
    """How pyvf's first step differs from torch's, or None. p, t: {loss, gradients (checksums),
    loss_after_update}. NaN differs from everything."""
    if not abs(p["loss"] - t["loss"]) <= LOSS_RTOL * abs(t["loss"]):
        return f"the loss: pyvf {p['loss']}, torch {t['loss']}"
    pg, tg = p["gradients"], t["gradients"]
    if set(pg) != set(tg):
        return f"the gradients named: pyvf only {sorted(set(pg) - set(tg))}, torch only {sorted(set(tg) - set(pg))}"
    floor = CHECK_FLOOR * max(norm for norm, _ in tg.values())
    wrong = [n for n in tg if not all(abs(a - b) <= CHECK_RTOL * max(tg[n][0], floor) for a, b in zip(pg[n], tg[n]))]
    if wrong:
        return f"the gradients of {', '.join(wrong[:3])}: (norm, projection) pyvf {pg[wrong[0]]}, torch {tg[wrong[0]]}"
    if not abs(p["loss_after_update"] - t["loss_after_update"]) <= LOSS_RTOL * abs(t["loss_after_update"]):
        return f"the loss after update: pyvf {p['loss_after_update']}, torch {t['loss_after_update']}"
    return None


def step_figures(step, steps):
    """A training step's figures (step() -> the loss before its update): a warm-up call (it makes
    the optimizer's moments, resident from then on as the weights are), the next one under
    peak_memory (its loss, after one update, checks the optimizer), then the median of `steps`."""
    step()
    after, memory = peak_memory(step)
    return dict(loss_after_update=after, memory=memory, time=median_time(step, steps, warmup=0)[0])


def run(model, configs, steps=None, threads=2):
    """pyvf's and torch's training step of MODELS[model] on each configuration named, each framework
    in a worker process; their first steps compared (first_step_differs) before any time is
    printed. steps: timed steps (default the model's, 3 for the paper's). -> {config, results
    {name: {"pyvf", "torch"}}, failures}: a configuration whose steps differ is a failure, and
    nothing after it runs."""
    m = MODELS[model]
    report = dict(config=dict(configs=list(configs), threads=threads), results={}, failures=[])
    for name in configs:
        n = steps or (3 if name == "paper" else m["steps"])
        p, t = (run_worker(WORKER, dict(model=model, framework=f, config=name, steps=n, threads=threads))
                for f in ("pyvf", "torch"))
        differs = first_step_differs(p, t)
        if differs:
            print(f"{name}: pyvf and torch differ in {differs}", file=sys.stderr)
            report["failures"].append(f"{name}: the first steps of pyvf and torch differ")
            break
        print(f"\n## {name}: {m['describe'](name)}, float32, {threads} threads, median of {n} steps, each "
              "framework in its own process")
        print(f"first-step loss: pyvf {p['loss']:.6f}, torch {t['loss']:.6f} (and the gradients, and the loss after "
              "an update, agree)\n")
        print(table(["", "step time", "peak memory of a step"],
                    [["pyvf", ms(p["time"]), format_bytes(p["memory"])],
                     ["torch", ms(t["time"]), format_bytes(t["memory"])],
                     ["torch / pyvf", f"{t['time'] / p['time']:.2f}", f"{t['memory'] / p['memory']:.2f}"]]))
        report["results"][name] = {"pyvf": p, "torch": t}
    return report


# ---------------------------------------------------------------------------------------
# the transformer

TRANSFORMER = {
    "tiny": dict(n_embeddings=64, n_head=2, d_model=32, n_layer=2, token_image_size=4, sequence_size=5,
                 n_loss_skip=1, batch=8),
    # the paper's InteriorNet model: GPT-2 base, 20 views of 8x8 tokens, B = 1
    "paper": dict(n_embeddings=1024, n_head=12, d_model=768, n_layer=12, token_image_size=8, sequence_size=20,
                  n_loss_skip=4, batch=1),
}


def transformer_setup(name, seed=0):
    spec = dict(TRANSFORMER[name])
    B = spec.pop("batch")
    cfg = pyvf.TransformerConfig(**spec)
    rng = np.random.default_rng(seed)
    tokens = rng.integers(0, cfg.n_embeddings, (B, cfg.sequence_size, cfg.L))
    poses = rng.normal(size=(B, cfg.sequence_size, 7))
    poses[..., 3:] /= np.linalg.norm(poses[..., 3:], axis=-1, keepdims=True)
    return cfg, tokens, pyvf.make_relative(poses)[0].astype(np.float32), pyvf.Transformer(cfg, seed=seed)


def transformer_pyvf(name, steps):
    cfg, tokens, poses, model = transformer_setup(name)
    loss = model.forward(tokens, poses).loss  # the first step's loss and gradients, for the cross-check
    gradients = checksums(model.backward())
    opt = pyvf.AdamW(model.params, lr=1e-4, weight_decay=0.01)

    def step():  # -> the loss before its update
        loss = model.forward(tokens, poses).loss
        opt.step(model.backward())
        return loss
    return dict(loss=loss, gradients=gradients, **step_figures(step, steps))


def transformer_torch(name, steps):
    import torch

    from pyvf.verify import torch_transformer

    torch.set_num_threads(pyvf.num_threads())
    cfg, tokens, poses, model = transformer_setup(name)
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


def transformer_describe(name):
    s = TRANSFORMER[name]
    return (f"d={s['d_model']}, H={s['n_head']}, {s['n_layer']} layers, N={s['sequence_size']}, "
            f"L={s['token_image_size'] ** 2}, V={s['n_embeddings']}, B={s['batch']}")


# ---------------------------------------------------------------------------------------
# the codebook

CODEBOOK = {  # the tiny one at pyvf train-codebook's batch
    "tiny": dict(ch=32, ch_mult=(1, 1, 2, 2), num_res_blocks=1, attn_resolutions=(8,), z_channels=32, embed_dim=32,
                 n_embed=64, image_size=64, batch=16),
    "paper": dict(ch=128, ch_mult=(1, 1, 2, 2, 4), num_res_blocks=2, attn_resolutions=(16,), z_channels=256,
                  embed_dim=256, n_embed=1024, image_size=128, batch=2),
}
CODEBOOK["quick"] = dict(CODEBOOK["tiny"], image_size=32, batch=2)  # --quick: the tiny one on a small batch
LR, BETAS = 1.584e-3, (0.5, 0.9)  # the published codebook's Adam


def codebook_setup(name):
    spec = dict(CODEBOOK[name])
    B = spec.pop("batch")
    cfg = pyvf.CodebookConfig(**spec)
    images = np.tanh(np.random.default_rng(0).standard_normal((B, 3, cfg.image_size, cfg.image_size)))
    return cfg, pyvf.Codebook(cfg, seed=0), images.astype(np.float32)


def codebook_pyvf(name, steps):
    _, cb, images = codebook_setup(name)
    loss = float(cb.forward(images, train=True).loss)  # the first step's loss and gradients
    gradients = checksums(cb.backward())
    _, cb, images = codebook_setup(name)  # a fresh model: the forward above moved the EMA
    opt = pyvf.Adam(cb.params, LR, betas=BETAS)
    step = lambda: float(pyvf.codebook_train_step(cb, opt, images).loss)  # noqa: E731  (the loss before its update)
    return dict(loss=loss, gradients=gradients, **step_figures(step, steps))


def codebook_torch(name, steps):
    import torch

    from pyvf.verify import torch_codebook

    torch.set_num_threads(pyvf.num_threads())
    cfg, cb, images = codebook_setup(name)
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


def codebook_describe(name):
    s = CODEBOOK[name]
    return (f"ch={s['ch']}, ch_mult={s['ch_mult']}, {s['num_res_blocks']} res blocks, {s['image_size']}x"
            f"{s['image_size']} images, K={s['n_embed']}, D={s['embed_dim']}, batch {s['batch']}")


MODELS = {
    "transformer": dict(configs=TRANSFORMER, pyvf=transformer_pyvf, torch=transformer_torch,
                        describe=transformer_describe, steps=20),
    "codebook": dict(configs=CODEBOOK, pyvf=codebook_pyvf, torch=codebook_torch, describe=codebook_describe, steps=10),
}


def worker(spec):
    """One framework's step: {model, framework: "pyvf" | "torch", config, steps, threads}."""
    pyvf.set_num_threads(spec["threads"])
    return MODELS[spec["model"]][spec["framework"]](spec["config"], spec["steps"])


if __name__ == "__main__":  # a worker: `python -m pyvf.bench.steps SPEC`
    worker_main(worker)
