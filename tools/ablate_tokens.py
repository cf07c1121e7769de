"""Codebook recipes for learnable tokens (issue 48), ablated at equal wall time.

    PYVF_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \
    python tools/ablate_tokens.py --data runs/sm7-train --out runs/abl [--only baseline,worst]

For each candidate, in out/<name>/: a codebook trained for --codebook-minutes of the process's
CPU time at one thread (equal compute: the machine is shared, and wall time would charge a
candidate for another's load; the model of its last checkpoint before the budget ran out is
kept, and its step recorded), the training scenes tokenized, a fixed transformer run (same
configuration, steps, batch, lr and seed for all), then one judgement on --scenes held-out
scenes of --seed (never 1000, the final evaluation's): reconstruction (whole image and object
pixels), the empty-patch code entropy, the transformer's held-out cross-entropy (empty / object
patches) and rendering MAE beside the nearest-view baseline's. Every stage is skipped when its
output exists and resumes from its checkpoint otherwise. out/ablation.json and out/ablation.md
gather the candidates' results.

The transformer's recipe (issue 48), on one codebook candidate's tokens:

    python tools/ablate_tokens.py --data runs/sm7-train --out runs/abl --tokens-from empty-worst-reseat

trains each of TRANSFORMERS (width, depth, batch, learning rate) for --transformer-minutes of CPU
time at one thread (its steps are those a probe run times to fill it, so that the schedule's
cosine ends where the budget does), judged on the same held-out scenes: out/tf-<name>/, gathered in
out/ablation-transformer.json and .md.
"""

import argparse
import dataclasses
import json
import os
import shutil
import signal
import time

import numpy as np

from pyvf.evaluate.health import codebook_health, object_mask, transformer_health
from pyvf.evaluate.metrics import to_model_images, to_uint8
from pyvf.models.codebook import Codebook
from pyvf.scenes import generate_scenes, load_dataset
from pyvf.train._run import CHECKPOINT, read_checkpoint
from pyvf.train.loops import (TINY_CODEBOOK, TINY_TRANSFORMER, RunOptions, TransformerRecipe, held_out_set,
                              load_tokens, save_tokens, tokenize, train_codebook, train_transformer)

# name -> (train_codebook keywords, CodebookConfig changes); all on the small-batch recipe
CANDIDATES = {  # in the order they run: the likeliest to matter first
    "baseline": ({}, {}),
    "worst-reseat": ({"restart": "worst", "reseat": 32}, {}),
    "kmeans-worst-reseat": ({"restart": "worst", "reseat": 32, "kmeans": 10}, {}),
    "worst": ({"restart": "worst"}, {}),
    "empty": ({}, {"empty_code": True}),
    "empty-worst-reseat": ({"restart": "worst", "reseat": 32}, {"empty_code": True}),
    "empty-kmeans-worst-reseat": ({"restart": "worst", "reseat": 32, "kmeans": 10}, {"empty_code": True}),
    "empty-kmeans-worst": ({"restart": "worst", "kmeans": 10}, {"empty_code": True}),
    "empty-kmeans-worst-n128": ({"restart": "worst", "kmeans": 10}, {"empty_code": True, "n_embed": 128}),
    "empty-kmeans-worst-decay0.95": ({"restart": "worst", "kmeans": 10}, {"empty_code": True, "decay": 0.95}),
    "empty-kmeans-worst-d16": ({"restart": "worst", "kmeans": 10}, {"empty_code": True, "embed_dim": 16}),  # narrow codes
    "empty-kmeans-worst-d8": ({"restart": "worst", "kmeans": 10}, {"empty_code": True, "embed_dim": 8}),
}
# name -> (TransformerConfig changes, batch, lr, warmup (None: train_transformer's default)); each
# trained on one codebook candidate's tokens (--tokens-from) for the same CPU time
TRANSFORMERS = {
    "b8-lr5e-4": ({}, 8, 5e-4, None),
    "b8-lr1e-3": ({}, 8, 1e-3, None),
    "b8-lr2e-3": ({}, 8, 2e-3, None),
    "b16-lr1e-3": ({}, 16, 1e-3, None),
    "l2-lr1e-3": ({"n_layer": 2}, 8, 1e-3, None),
    "l2-lr5e-4": ({"n_layer": 2}, 8, 5e-4, None),
    "d96-l3-lr1e-3": ({"d_model": 96, "n_layer": 3}, 8, 1e-3, None),
    "l2-lr5e-4-sqrt": ({"n_layer": 2, "attention_scale": 32 ** -0.5}, 8, 5e-4, None),  # logits / sqrt(dh)
    "l2-lr1e-3-sqrt": ({"n_layer": 2, "attention_scale": 32 ** -0.5}, 8, 1e-3, None),
    "l2-b4-lr5e-4": ({"n_layer": 2}, 4, 5e-4, None),  # more, smaller steps in the same CPU time
    "l2-b2-lr5e-4": ({"n_layer": 2}, 2, 5e-4, None),
    "l2-b2-lr5e-4-w0": ({"n_layer": 2}, 2, 5e-4, 0),  # warmup: none, and a third of the steps (default a tenth)
    "l2-b2-lr5e-4-w1000": ({"n_layer": 2}, 2, 5e-4, 1000),
}
TF_COLUMNS = [("steps", "steps", 0), ("ce_c3", "CE c3", 3), ("ce_object_c3", "CE object c3", 3),
              ("token_accuracy_object_c3", "acc object c3", 3), ("mae_c3", "MAE c3", 2),
              ("mean_image_mae_c3", "mean image c3", 2), ("mae_c5", "MAE c5", 2), ("mean_image_mae_c5", "mean image c5", 2),
              ("nearest_view_mae_c5", "nearest c5", 2), ("position_c5", "position c5", 2),
              ("orientation_c5", "orientation c5", 1)]
COLUMNS = [("steps", "codebook steps", 0), ("codebook_seconds", "wall s", 0), ("mae", "rec MAE", 2), ("psnr", "rec PSNR", 2),
           ("object_mae", "object MAE", 2), ("object_psnr", "object PSNR", 2), ("empty_entropy", "empty H", 2),
           ("codes_in_use", "codes", 0), ("colour_r2", "colour r2", 2), ("ce_c3", "CE c3", 3),
           ("ce_empty_c3", "CE empty", 3), ("ce_object_c3", "CE object", 3),
           ("token_accuracy_object_c3", "acc object", 3), ("mae_c3", "MAE c3", 2),
           ("nearest_view_mae_c3", "nearest c3", 2), ("mae_c5", "MAE c5", 2), ("nearest_view_mae_c5", "nearest c5", 2)]


def _out_of_time(signum, frame):
    raise KeyboardInterrupt  # raised here, not by sending SIGINT: a job started in the background ignores SIGINT


def train_codebook_for(seconds, images, config, out, opts, **kw):
    """train_codebook until `seconds` of this process's CPU time (ITIMER_PROF: user + system; at one
    thread, the compute spent), interrupted when the timer fires, then its final model
    written from its last checkpoint (opts.checkpoint_every). A run killed before its budget ran
    out starts again from nothing: its CPU time is not recorded, and its wall time would charge it
    for the machine's load (a run resumed so had 45 steps where the others had 400). -> Codebook."""
    ckpt = os.path.join(out, CHECKPOINT)
    if os.path.exists(ckpt):
        shutil.rmtree(out)
    old = signal.signal(signal.SIGPROF, _out_of_time)
    signal.setitimer(signal.ITIMER_PROF, seconds)
    try:
        return train_codebook(images, config, out, dataclasses.replace(opts, steps=10 ** 7), **kw)  # the timer stops it
    except KeyboardInterrupt:
        pass
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.signal(signal.SIGPROF, old)
    step = read_checkpoint(ckpt, "codebook")[0]["step"]
    return train_codebook(images, config, out, dataclasses.replace(opts, steps=step), **kw)  # the final model


def object_scores(codebook, images):
    """Reconstruction MAE and PSNR over the object pixels (object_mask) of uint8 images (M, S, S, 3)."""
    rec = np.concatenate([to_uint8(codebook.decode_code(codebook.encode(to_model_images(images[i:i + 64],
                                                                                          codebook.dtype))))
                          for i in range(0, len(images), 64)])  # (M, S, S, 3)
    err = (rec.astype(np.float64) - images)[object_mask(images)]  # (n_object_pixels, 3)
    return {"object_mae": float(np.abs(err).mean()), "object_psnr": float(10 * np.log10(255 ** 2 / (err ** 2).mean()))}


def run_candidate(name, args, data, held):
    kw, changes = CANDIDATES[name]
    folder = os.path.join(args.out, name)
    result_path = os.path.join(folder, "result.json")
    if os.path.exists(result_path):
        with open(result_path) as f:
            return json.load(f)
    cb_config = dataclasses.replace(TINY_CODEBOOK, **changes)
    tf_config = dataclasses.replace(TINY_TRANSFORMER, n_embeddings=cb_config.n_embed)
    cb_path = os.path.join(folder, "codebook", "codebook.npz")
    if os.path.exists(cb_path):
        cb = Codebook.load(cb_path)
    else:
        cb = train_codebook_for(60 * args.codebook_minutes, data.images, cb_config, os.path.join(folder, "codebook"),
                                RunOptions(steps=1, threads=1, progress=False, checkpoint_every=5), **kw)
    tokens_path = os.path.join(folder, "tokens.npz")
    if not os.path.exists(tokens_path):
        save_tokens(tokens_path, tokenize(cb, data.images), data.poses, cb_config.n_embed)
    tokens, poses = load_tokens(tokens_path)[:2]
    tf = train_transformer(tokens, poses, tf_config, os.path.join(folder, "transformer"),
                           RunOptions(steps=args.transformer_steps, batch_size=8, checkpoint_every=50, threads=1,
                                      progress=False), TransformerRecipe(lr=5e-4))
    meta = read_checkpoint(os.path.join(folder, "codebook", CHECKPOINT), "codebook")[0]
    images, poses = held
    views = images.reshape(-1, *images.shape[2:])  # (n V, S, S, 3)
    result = {"name": name, "train_codebook": kw, "config": changes, "steps": meta["step"],
              "codebook_seconds": meta["elapsed"], "transformer_steps": args.transformer_steps,
              **codebook_health(cb, views), **object_scores(cb, views)}
    ev = held_out_set(cb, images, poses)
    result.update(transformer_health(cb, tf, images, poses, ev["tokens"], (1, 3, 5)))
    with open(result_path, "w") as f:
        json.dump(result, f, indent=2)
    print(f"{name}: done", flush=True)
    return result


def table(results, columns=COLUMNS):
    head = "| candidate | " + " | ".join(c[1] for c in columns) + " |"
    rows = [head, "|" + "---|" * (len(columns) + 1)]
    for r in results:
        rows.append(f"| {r['name']} | " + " | ".join(f"{r[k]:.{d}f}" for k, _, d in columns) + " |")
    return "\n".join(rows) + "\n"


def transformer_steps_for(seconds, tokens, poses, config, folder, batch, lr):
    """The steps that fill `seconds` of CPU time: a probe run of 2 then 6 steps (its folder
    removed), the per-step time of the last 4 (the first steps pay for the setup)."""
    probe = os.path.join(folder, "probe")
    times = []
    for steps in (2, 6):
        t = time.process_time()
        train_transformer(tokens, poses, config, probe, RunOptions(steps=steps, batch_size=batch, checkpoint_every=2,
                                                                   threads=1, progress=False),
                          TransformerRecipe(lr=lr, total_steps=6))
        times.append(time.process_time() - t)
    shutil.rmtree(probe)
    return max(int(seconds / (times[1] / 4)), 10)


def run_transformer_candidate(name, args, held, ev):
    changes, batch, lr, warmup = TRANSFORMERS[name]
    folder = os.path.join(args.out, "tf-" + name)
    result_path = os.path.join(folder, "result.json")
    if os.path.exists(result_path):
        with open(result_path) as f:
            return json.load(f)
    source = os.path.join(args.out, args.tokens_from)
    cb = Codebook.load(os.path.join(source, "codebook", "codebook.npz"))
    tokens, poses = load_tokens(os.path.join(source, "tokens.npz"))[:2]
    config = dataclasses.replace(TINY_TRANSFORMER, n_embeddings=cb.config.n_embed, **changes)
    os.makedirs(folder, exist_ok=True)
    steps_path = os.path.join(folder, "steps.json")
    if not os.path.exists(steps_path):
        steps = transformer_steps_for(60 * args.transformer_minutes, tokens, poses, config, folder, batch, lr)
        with open(steps_path, "w") as f:
            json.dump({"steps": steps}, f)
    with open(steps_path) as f:
        steps = json.load(f)["steps"]
    tf = train_transformer(tokens, poses, config, os.path.join(folder, "run"),
                           RunOptions(steps=steps, batch_size=batch, checkpoint_every=50, threads=1, progress=False),
                           TransformerRecipe(lr=lr, warmup=warmup))
    images, poses_h = held
    result = {"name": name, "config": changes, "batch": batch, "lr": lr, "warmup": warmup, "steps": steps,
              "tokens_from": args.tokens_from,
              **transformer_health(cb, tf, images, poses_h, ev(cb)["tokens"], (1, 3, 5))}
    with open(result_path, "w") as f:
        json.dump(result, f, indent=2)
    print(f"tf-{name}: done", flush=True)
    return result


def transformer_main(args, held):
    names = args.only.split(",")
    unknown = [n for n in names if n not in TRANSFORMERS]
    if unknown:
        raise SystemExit(f"unknown transformer candidates {unknown}; known: {list(TRANSFORMERS)}")
    results = []
    for name in names:
        results.append(run_transformer_candidate(name, args, held, lambda cb: held_out_set(cb, *held)))
        with open(os.path.join(args.out, "ablation-transformer.json"), "w") as f:
            json.dump(results, f, indent=2)
        with open(os.path.join(args.out, "ablation-transformer.md"), "w") as f:
            f.write(f"Held-out: {args.scenes} scenes of seed {args.seed}; tokens of the {args.tokens_from} codebook; "
                    f"each transformer {args.transformer_minutes} min of CPU time at 1 thread.\n\n")
            f.write(table(results, TF_COLUMNS))


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="training dataset folder (pyvf scenes)")
    p.add_argument("--out", required=True)
    p.add_argument("--only", default=None, help="comma-separated candidates, in order (default: all)")
    p.add_argument("--tokens-from", default=None, metavar="CANDIDATE",
                   help="ablate the transformer's recipe (TRANSFORMERS) on this codebook candidate's tokens")
    p.add_argument("--transformer-minutes", type=float, default=8.0, help="CPU minutes per transformer "
                   "(with --tokens-from)")
    p.add_argument("--codebook-minutes", type=float, default=8.0, help="CPU minutes per codebook")
    p.add_argument("--transformer-steps", type=int, default=250)
    p.add_argument("--scenes", type=int, default=40, help="held-out scenes")
    p.add_argument("--seed", type=int, default=2, help="held-out seed (not 0, training; not 1000, evaluation)")
    args = p.parse_args()
    if args.seed in (0, 1000):
        raise SystemExit("--seed must not be 0 (training) or 1000 (the final evaluation)")
    held = generate_scenes(args.seed, args.scenes, size=TINY_CODEBOOK.image_size)
    if args.tokens_from:
        args.only = args.only or ",".join(TRANSFORMERS)
        return transformer_main(args, held)
    names = (args.only or ",".join(CANDIDATES)).split(",")
    unknown = [n for n in names if n not in CANDIDATES]
    if unknown:
        raise SystemExit(f"unknown candidates {unknown}; known: {list(CANDIDATES)}")
    data = load_dataset(args.data)
    results = []
    for name in names:
        results.append(run_candidate(name, args, data, held))
        with open(os.path.join(args.out, "ablation.json"), "w") as f:
            json.dump(results, f, indent=2)
        with open(os.path.join(args.out, "ablation.md"), "w") as f:
            f.write(f"Held-out: {args.scenes} scenes of seed {args.seed}; codebook {args.codebook_minutes} min of "
                    f"CPU time at 1 thread; transformer {args.transformer_steps} steps (batch 8, lr 5e-4).\n\n")
            f.write(table(results))


if __name__ == "__main__":
    main()
