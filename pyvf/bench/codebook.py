"""Time of the codebook, pyvf against the same model in torch (pyvf/verify/torch_codebook.py), one run.

    pyvf bench codebook                 # the official tiny and the paper configuration
    pyvf bench codebook --configs tiny
    pyvf bench codebook --quick         # the tiny one (seconds)

Per configuration: encode + decode (images -> codes -> images) and one forward + backward
(train=True, the EMA update included), and for the tiny one a whole training step at batch 16
(Adam, as `pyvf train-codebook`) in images per second; medians, float32, each framework in its
own process (so that neither's thread pool waits on the other's). Memory: the measured peak
resident memory of one call above what was resident before it (pyvf.bench.common.peak_memory;
gradients of the step included, weights not). Both compute the loss of the same weights and
batch, the output of encode + decode, the gradients of the first forward + backward and (tiny)
the loss after the first training step's update, and the tool prints no time if they differ
(pyvf.bench.common.first_step_differs). torch is imported only in the torch worker. Then, for
pyvf, where one forward + backward spends its time: the exclusive time of each layer type
(layer_times), from one more step with every layer function of pyvf.nn.conv wrapped in a timer.
"""

import sys
import time

import numpy as np

import pyvf
from pyvf.bench.common import (checksums, first_step_differs, format_bytes, median_time, peak_memory, run_configs,
                               run_worker, worker_main)

WORKER = "pyvf.bench.codebook"  # this module, run as `python -m WORKER SPEC` (worker_main)

CONFIGS = {
    "tiny": dict(ch=32, ch_mult=(1, 1, 2, 2), num_res_blocks=1, attn_resolutions=(8,), z_channels=32, embed_dim=32,
                 n_embed=64, image_size=64, batch=4),
    "paper": dict(ch=128, ch_mult=(1, 1, 2, 2, 4), num_res_blocks=2, attn_resolutions=(16,), z_channels=256,
                  embed_dim=256, n_embed=1024, image_size=128, batch=2),
}


# the training step measured beside: the shipped tiny codebook's (pyvf train-codebook: batch 16,
# Adam lr 1.584e-3, betas (0.5, 0.9), the EMA update), on the tiny configuration only
TRAIN = dict(config="tiny", batch=16, lr=1.584e-3, betas=(0.5, 0.9))


def setup(name, batch=None):
    spec = dict(CONFIGS[name])
    B = spec.pop("batch") if batch is None else batch
    spec.pop("batch", None)
    cfg = pyvf.CodebookConfig(**spec)
    cb = pyvf.Codebook(cfg, seed=0)
    images = np.tanh(np.random.default_rng(0).standard_normal((B, 3, cfg.image_size, cfg.image_size)))
    return cfg, cb, images.astype(np.float32)


# pyvf.nn.conv's layer functions -> the layer type they are timed under. An AttnBlock's time is its
# own work only (softmax, products): its GroupNorm and 1x1 convs count under their own types.
LAYER_FUNCS = {
    "conv2d_forward": "conv", "conv2d_backward": "conv",
    "groupnorm_swish_forward": "groupnorm+swish", "groupnorm_swish_backward": "groupnorm+swish",
    "groupnorm_forward": "groupnorm", "groupnorm_backward": "groupnorm",
    "swish_forward": "swish", "swish_backward": "swish",
    "upsample_nearest2x_forward": "upsample", "upsample_nearest2x_backward": "upsample",
    "attnblock_forward": "attention", "attnblock_backward": "attention",
}


def _conv_kind(w, stride):
    kh, kw = w.shape[2:]
    return f"conv {kh}x{kw}" + (f" stride {stride}" if stride != 1 else "")


def _layer_key(name, args, kwargs):
    """(layer type, 'forward' | 'backward') of one call; convs split by kernel and stride."""
    kind = LAYER_FUNCS[name]
    if name == "conv2d_forward":
        kind = _conv_kind(args[1], kwargs.get("stride", args[3] if len(args) > 3 else 1))
    elif name == "conv2d_backward":
        _, w, stride, _ = args[1]
        kind = _conv_kind(w, stride)
    return kind, "forward" if name.endswith("_forward") else "backward"


def layer_times(fn, clock=time.perf_counter):
    """Run fn() once with every function of LAYER_FUNCS wrapped in a timer, wherever pyvf bound
    it (pyvf.nn.conv and the modules that imported it by name). Returns ({(type, direction): seconds
    of exclusive time}, total seconds of fn()); exclusive: a layer called inside another (the
    AttnBlock's convs) counts under its own type only. clock: wall time by default;
    time.process_time (CPU time of the whole process) is steadier on a busy machine when the
    kernels run on one thread."""
    from pyvf.nn import conv
    originals = {name: getattr(conv, name) for name in LAYER_FUNCS if hasattr(conv, name)}
    times, stack = {}, []

    def wrap(name, f):
        def timed(*args, **kwargs):
            stack.append(0.0)  # time spent in the layers this one calls
            t0 = clock()
            try:
                return f(*args, **kwargs)
            finally:
                elapsed = clock() - t0
                inner = stack.pop()
                key = _layer_key(name, args, kwargs)
                times[key] = times.get(key, 0.0) + elapsed - inner
                if stack:
                    stack[-1] += elapsed
        return timed

    patched = []
    for mod in [m for n, m in list(sys.modules.items()) if n == "pyvf" or n.startswith("pyvf.")]:
        for name, f in originals.items():
            if getattr(mod, name, None) is f:
                patched.append((mod, name, f))
                setattr(mod, name, wrap(name, f))
    try:
        t0 = clock()
        fn()
        total = clock() - t0
    finally:
        for mod, name, f in patched:
            setattr(mod, name, f)
    return times, total


def print_layer_times(times, total):
    """The table of layer_times' result: per layer type forward and backward ms and share of the step."""
    kinds = sorted({k for k, _ in times}, key=lambda k: -sum(times.get((k, d), 0.0) for d in ("forward", "backward")))
    print(f"pyvf, one forward + backward ({total * 1e3:.0f} ms), exclusive time per layer type:")
    print("| layer type | forward | backward | share of the step |")
    print("|---|---|---|---|")
    for k in kinds:
        f, b = times.get((k, "forward"), 0.0), times.get((k, "backward"), 0.0)
        print(f"| {k} | {f * 1e3:.1f} ms | {b * 1e3:.1f} ms | {(f + b) / total:.0%} |")
    rest = total - sum(times.values())
    print(f"| everything else (quantizer, loss, residual adds, Python) | | | {rest / total:.0%} ({rest * 1e3:.0f} ms) |")


CODEC = "encode + decode"  # the codec's output, as the workers name it for first_step_differs


def median(fn, repeat):
    """The median seconds of `repeat` calls, no warm-up (the workers make their own first call)."""
    return median_time(fn, repeat=repeat, warmup=0)[0]


def worker_pyvf(name, repeat):
    cfg, cb, images = setup(name)
    loss = cb.forward(images).loss
    codec_fn = lambda: cb.decode_code(cb.encode(images))  # noqa: E731
    outputs = checksums({CODEC: codec_fn()})  # (also the codec's warm-up)
    codec = median(codec_fn, repeat)

    def step():
        cb.forward(images, train=True)
        return cb.backward()
    gradients = checksums(step())  # the first step's (also the step's warm-up)
    result = dict(loss=loss, outputs=outputs, gradients=gradients, codec=codec, step=median(step, repeat))
    times, total = layer_times(step)
    result["layers"] = [[k, d, t] for (k, d), t in times.items()]
    result["layers_total"] = total
    if name == TRAIN["config"]:
        _, cb_t, images_t = setup(name, TRAIN["batch"])  # new names: codec_fn and step keep theirs
        opt = pyvf.Adam(cb_t.params, TRAIN["lr"], betas=TRAIN["betas"])
        train = lambda: float(pyvf.codebook_train_step(cb_t, opt, images_t).loss)  # noqa: E731  (before its update)
        train()  # the warm-up, and the first update
        result["loss_after_update"] = train()  # (the cross-check of Adam and the EMA update)
        result["train"] = median(train, repeat)
    # memory last: peak_memory makes every later large allocation map fresh pages (bench/common.py)
    result["codec_mem"], result["step_mem"] = peak_memory(codec_fn)[1], peak_memory(step)[1]
    return result


def worker_torch(name, repeat):
    import torch

    from pyvf.verify import torch_codebook
    torch.set_num_threads(pyvf.num_threads())
    cfg, cb, images = setup(name)
    P = {k: torch.tensor(v, requires_grad=True) for k, v in cb.params.items()}
    q = cb.quantizer
    buffers = {"quantize.embeddings": torch.tensor(q.embeddings),
               "quantize.ema_cluster_size_hidden": torch.tensor(q.ema_cluster_size_hidden),
               "quantize.ema_dw_hidden": torch.tensor(q.ema_dw_hidden), "quantize.counter": q.counter}
    x = torch.tensor(images)
    with torch.no_grad():
        loss = torch_codebook.forward(P, buffers, x, cfg, train=False)["loss"].item()

        def codec():  # under no_grad, as pyvf's encode and decode_code keep nothing for a backward
            # torch_codebook.forward's path: the 1x1 quant_conv after the encoder, post_quant_conv
            # before the decoder (its shapes match without them: z_channels = embed_dim)
            z = torch_codebook.conv(torch_codebook.encoder(x, P, cfg), P, "quant_conv")
            flat = z.permute(0, 2, 3, 1).reshape(-1, cfg.embed_dim)
            e = buffers["quantize.embeddings"]
            idx = ((flat[:, :, None] - e[None]) ** 2).sum(1).argmin(1)
            zq = e.T[idx].reshape(z.shape[0], z.shape[2], z.shape[3], -1).permute(0, 3, 1, 2)
            return torch_codebook.decoder(torch_codebook.conv(zq, P, "post_quant_conv"), P, cfg)
        outputs = checksums({CODEC: codec().numpy()})  # (also the codec's warm-up)
        t_codec = median(codec, repeat)

    def step():
        for p in P.values():
            p.grad = None
        torch_codebook.forward(P, buffers, x, cfg, train=True)["loss"].backward()
    step()  # the first step (also the warm-up): its gradients for the cross-check
    gradients = checksums({k: p.grad.numpy() if p.grad is not None else np.zeros(p.shape) for k, p in P.items()})
    result = dict(loss=loss, outputs=outputs, gradients=gradients, codec=t_codec, step=median(step, repeat))
    if name == TRAIN["config"]:
        _, cb_t, images_t = setup(name, TRAIN["batch"])  # new names: codec and step keep theirs
        P_t = {k: torch.tensor(v, requires_grad=True) for k, v in cb_t.params.items()}
        opt = torch.optim.Adam(P_t.values(), TRAIN["lr"], betas=TRAIN["betas"])
        x_t = torch.tensor(images_t)
        state = {"buffers": buffers}

        def train():  # -> the loss before its update
            opt.zero_grad()
            out = torch_codebook.forward(P_t, state["buffers"], x_t, cfg, train=True)
            out["loss"].backward()
            opt.step()
            state["buffers"] = out["buffers"]  # the EMA update kept, as pyvf's codebook keeps it
            return out["loss"].item()
        train()  # as worker_pyvf's
        result["loss_after_update"] = train()
        result["train"] = median(train, repeat)
    with torch.no_grad():  # memory last, as in worker_pyvf
        result["codec_mem"] = peak_memory(codec)[1]
    result["step_mem"] = peak_memory(step)[1]
    return result


def worker(spec):
    """One framework's run in a worker process: {framework: "pyvf" | "torch", config, repeat,
    threads} -> worker_pyvf's or worker_torch's dict."""
    pyvf.set_num_threads(spec["threads"])
    return (worker_pyvf if spec["framework"] == "pyvf" else worker_torch)(spec["config"], spec["repeat"])


def bench(name, repeat, threads):
    """Run both workers on one configuration and print the tables: {"pyvf": ..., "torch": ...},
    or None (printed to stderr) when their losses, codec outputs or first gradients differ."""
    p, t = (run_worker(WORKER, dict(framework=f, config=name, repeat=repeat, threads=threads))
            for f in ("pyvf", "torch"))
    differs = first_step_differs(p, t)
    if differs:
        print(f"{name}: pyvf and torch differ in {differs}", file=sys.stderr)
        return None
    spec = CONFIGS[name]
    print(f"\n## {name}: ch={spec['ch']}, ch_mult={spec['ch_mult']}, {spec['num_res_blocks']} res blocks, "
          f"{spec['image_size']}x{spec['image_size']} images, K={spec['n_embed']}, D={spec['embed_dim']}, "
          f"B={spec['batch']}, float32, {threads} threads, median of {repeat}, each in its own process")
    print(f"loss of the same weights and batch: pyvf {p['loss']:.6f}, torch {t['loss']:.6f} (and the codec's output and "
          "the first step's gradients agree)")
    print("| | encode + decode | forward + backward (train) |")
    print("|---|---|---|")
    print(f"| pyvf | {p['codec'] * 1e3:.0f} ms | {p['step'] * 1e3:.0f} ms |")
    print(f"| torch | {t['codec'] * 1e3:.0f} ms | {t['step'] * 1e3:.0f} ms |")
    print(f"| ratio torch / pyvf | {t['codec'] / p['codec']:.2f} | {t['step'] / p['step']:.2f} |")
    print(f"| peak memory pyvf | {format_bytes(p['codec_mem'])} | {format_bytes(p['step_mem'])} |")
    print(f"| peak memory torch | {format_bytes(t['codec_mem'])} | {format_bytes(t['step_mem'])} |")
    if "train" in p:
        B = TRAIN["batch"]
        print(f"training step (batch {B}, Adam, the EMA update; pyvf.codebook_train_step, as pyvf train-codebook): "
              f"pyvf {p['train'] * 1e3:.0f} ms = {B / p['train']:.1f} images/s, torch {t['train'] * 1e3:.0f} ms = "
              f"{B / t['train']:.1f} images/s, ratio torch / pyvf {t['train'] / p['train']:.2f}")
    print()
    print_layer_times({(k, d): sec for k, d, sec in p["layers"]}, p["layers_total"])
    return {"pyvf": p, "torch": t}


def run(configs=tuple(CONFIGS), repeat=3, threads=2):
    """bench() on each configuration of CONFIGS named, medians of `repeat` calls. Returns the
    report; report["failures"] names a configuration whose first steps differed (nothing after it is run)."""
    return run_configs(lambda name: bench(name, repeat, threads), configs,
                       dict(configs=list(configs), repeat=repeat, threads=threads), threads)


if __name__ == "__main__":  # a worker: `python -m pyvf.bench.codebook SPEC` (bench, run_worker)
    worker_main(worker)
