"""One training step of the tiny models, pyvf against the same model in torch, timed side by side in
one run after checking that both compute the same step.

    pyvf bench transformer [--quick]   # forward, backward, AdamW; 20 steps (5 quick)
    pyvf bench codebook [--quick]      # forward with the EMA update, backward, Adam, at `pyvf
                                       # train-codebook`'s batch; 10 steps (5 on two 32x32 images)

The torch side: pyvf/verify/torch_ports.py. Each framework runs in a worker process of its own
(neither's thread pool waits on the other's). Before any time is reported, the first step's loss
and gradients (same weights, same batch) and the loss after the first update are compared.
"""

import dataclasses
import zlib

import numpy as np

import pyvf
from pyvf.bench.common import machine, median_time, ms, run_worker, worker_main

# the first steps, compared: the loss and the loss after the first update to LOSS_RTOL (float32
# both); each gradient's checksums to CHECK_RTOL of its norm (measured: 3e-5 at most). A gradient
# below CHECK_FLOOR of the largest one's norm is compared at that level: the biases that feed a
# normalisation have a gradient of exactly 0, computed as rounding noise.
LOSS_RTOL, CHECK_RTOL, CHECK_FLOOR = 1e-4, 1e-3, 1e-3

CONFIGS = {  # (the tiny model, the batch); the codebook at `pyvf train-codebook`'s batch
    "transformer": (pyvf.TransformerConfig(n_embeddings=64, n_head=2, d_model=32, n_layer=2, token_image_size=4,
                                           sequence_size=5, n_loss_skip=1), 8),
    "codebook": (pyvf.CodebookConfig(ch=32, ch_mult=(1, 1, 2, 2), num_res_blocks=1, attn_resolutions=(8,),
                                     z_channels=32, embed_dim=32, n_embed=64, image_size=64), 16),
}
CONFIGS["codebook-quick"] = (dataclasses.replace(CONFIGS["codebook"][0], image_size=32), 2)
LR, BETAS = 1.584e-3, (0.5, 0.9)  # the published codebook's Adam


def checksums(arrays):
    """{name: [2-norm, projection onto unit-normal numbers seeded by the name]}: what a worker sends of a
    gradient. A gradient zeroed, transposed or missing a term moves the projection by about its norm."""
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


def step_figures(loss, gradients, step, steps):
    """The first step's loss and gradient checksums; step() (-> the loss before its update) once to
    warm up, once for the loss after an update, then timed."""
    step()
    return dict(loss=loss, gradients=checksums(gradients), loss_after_update=step(),
                time=median_time(step, steps, warmup=0)[0])


def transformer_setup(config):
    cfg, B = CONFIGS[config]
    rng = np.random.default_rng(0)
    tokens = rng.integers(0, cfg.n_embeddings, (B, cfg.sequence_size, cfg.L))
    poses = rng.normal(size=(B, cfg.sequence_size, 7))
    poses[..., 3:] /= np.linalg.norm(poses[..., 3:], axis=-1, keepdims=True)
    return cfg, tokens, pyvf.make_relative(poses)[0].astype(np.float32), pyvf.Transformer(cfg, seed=0)


def transformer_pyvf(config, steps):
    cfg, tokens, poses, model = transformer_setup(config)
    loss = model.forward(tokens, poses).loss  # the first step's loss and gradients, for the cross-check
    gradients = model.backward()
    opt = pyvf.AdamW(model.params, lr=1e-4, weight_decay=0.01)

    def step():
        loss = model.forward(tokens, poses).loss
        opt.step(model.backward())
        return loss
    return step_figures(loss, gradients, step, steps)


def torch_figures(P, opt, loss_of, steps):
    """step_figures of a torch model: P {name: leaf tensor}, its optimizer, loss_of() -> the loss
    tensor at the current parameters."""
    import torch

    torch.set_num_threads(pyvf.num_threads())
    loss = loss_of()
    loss.backward()
    gradients = {k: p.grad.numpy() if p.grad is not None else np.zeros(p.shape) for k, p in P.items()}

    def step():
        opt.zero_grad()
        loss = loss_of()
        loss.backward()
        opt.step()
        return loss.item()
    return step_figures(loss.item(), gradients, step, steps)


def transformer_torch(config, steps):
    import torch

    from pyvf.verify.torch_ports import transformer_forward

    cfg, tokens, poses, model = transformer_setup(config)
    P = {k: torch.tensor(v.copy(), requires_grad=True) for k, v in model.params.items()}
    t_tokens, t_poses = torch.tensor(tokens), torch.tensor(poses)
    return torch_figures(P, torch.optim.AdamW(P.values(), lr=1e-4, weight_decay=0.01),
                         lambda: transformer_forward(P, t_tokens, t_poses, cfg)[-1], steps)


def codebook_setup(config):
    cfg, B = CONFIGS[config]
    images = np.tanh(np.random.default_rng(0).standard_normal((B, 3, cfg.image_size, cfg.image_size)))
    return cfg, pyvf.Codebook(cfg, seed=0), images.astype(np.float32)


def codebook_pyvf(config, steps):
    _, cb, images = codebook_setup(config)
    loss = float(cb.forward(images, train=True).loss)  # the first step's loss and gradients (and EMA update)
    gradients = cb.backward()
    opt = pyvf.Adam(cb.params, LR, betas=BETAS)
    step = lambda: float(pyvf.codebook_train_step(cb, opt, images).loss)  # noqa: E731  (the loss before its update)
    return step_figures(loss, gradients, step, steps)


def codebook_torch(config, steps):
    import torch

    from pyvf.verify.torch_ports import codebook_forward

    cfg, cb, images = codebook_setup(config)
    P = {k: torch.tensor(v, requires_grad=True) for k, v in cb.params.items()}
    x = torch.tensor(images)
    state = {"buffers": {f"quantize.{k}": torch.as_tensor(v) for k, v in cb.quantizer.state_dict().items()}}

    def loss_of():
        out = codebook_forward(P, state["buffers"], x, cfg)
        state["buffers"] = out["buffers"]  # the EMA update kept, as pyvf's codebook keeps it
        return out["loss"]
    return torch_figures(P, torch.optim.Adam(P.values(), LR, betas=BETAS), loss_of, steps)


FRAMEWORKS = {("transformer", "pyvf"): transformer_pyvf, ("transformer", "torch"): transformer_torch,
              ("codebook", "pyvf"): codebook_pyvf, ("codebook", "torch"): codebook_torch}


def run(model, quick=False, threads=2):
    """pyvf's and torch's step of `model` ("transformer", "codebook") (module docstring): {config,
    machine, results {"pyvf", "torch"}, torch_over_pyvf (the time ratio), failures}."""
    config = "codebook-quick" if quick and model == "codebook" else model
    steps = 5 if quick else 20 if model == "transformer" else 10
    report = dict(config=dict(model=model, config=config, steps=steps, threads=threads), machine=machine(threads),
                  failures=[])
    p, t = (run_worker(worker, dict(model=model, framework=f, config=config, steps=steps, threads=threads))
            for f in ("pyvf", "torch"))
    differs = first_step_differs(p, t)
    if differs:
        report["failures"].append(f"the first steps of pyvf and torch differ in {differs}: not timed")
        return report
    print(f"{CONFIGS[config][0]}, batch {CONFIGS[config][1]}, float32, {threads} threads, each framework in its own process\n"
          f"first-step loss: pyvf {p['loss']:.6f}, torch {t['loss']:.6f} (and the gradients, and the loss after an "
          f"update, agree)\nmedian step time of {steps}: pyvf {ms(p['time'])}, torch {ms(t['time'])}; "
          f"torch / pyvf {t['time'] / p['time']:.2f}")
    report.update(results=dict(pyvf=p, torch=t), torch_over_pyvf=t["time"] / p["time"])
    return report


def worker(spec):
    """One framework's step: {model, framework: "pyvf" | "torch", config, steps, threads}."""
    pyvf.set_num_threads(spec["threads"])
    return FRAMEWORKS[spec["model"], spec["framework"]](spec["config"], spec["steps"])


if __name__ == "__main__":  # a worker: `python -m pyvf.bench.steps SPEC`
    worker_main(worker)
