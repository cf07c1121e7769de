"""Codebook recipes for learnable tokens (issue 48), ablated at equal wall time.

    PYVF_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \
    python tools/ablate_tokens.py --data runs/sm7-train --out runs/abl [--only baseline,worst]

For each candidate, in out/<name>/: a codebook trained for --codebook-minutes of the process's
CPU time at one thread (equal compute: the machine is shared, and wall time would charge a
candidate for another's load; the step it reaches is recorded; stopped through the run's own
Ctrl-C path, so its checkpoint is exact), the training scenes tokenized, a fixed transformer run (same configuration, steps, batch,
lr and seed for all), then one judgement on --scenes held-out scenes of --seed (never 1000, the
final evaluation's): reconstruction (whole image and object pixels), the empty-patch code entropy,
the transformer's held-out cross-entropy (empty / object patches) and rendering MAE beside the
nearest-view baseline's. Every stage is skipped when its output exists and resumes from its
checkpoint otherwise. out/ablation.json and out/ablation.md gather the candidates' results.
"""

import argparse
import dataclasses
import json
import os
import signal

import numpy as np

from pyvf.evaluate.health import codebook_health, object_mask, transformer_health
from pyvf.evaluate.metrics import to_model_images, to_uint8
from pyvf.models.codebook import Codebook
from pyvf.scenes import generate_scenes, load_dataset
from pyvf.train._run import CHECKPOINT, read_checkpoint
from pyvf.train.loops import (TINY_CODEBOOK, TINY_TRANSFORMER, held_out_set, load_tokens, save_tokens, tokenize,
                              train_codebook, train_transformer)

# name -> (train_codebook keywords, CodebookConfig changes); all on the small-batch recipe
CANDIDATES = {  # in the order they run: the likeliest to matter first
    "baseline": ({}, {}),
    "worst-reseat": ({"restart": "worst", "reseat": 32}, {}),
    "kmeans-worst-reseat": ({"restart": "worst", "reseat": 32, "kmeans": 10}, {}),
    "worst": ({"restart": "worst"}, {}),
    "empty": ({}, {"empty_code": True}),
    "empty-worst-reseat": ({"restart": "worst", "reseat": 32}, {"empty_code": True}),
    "empty-kmeans-worst-reseat": ({"restart": "worst", "reseat": 32, "kmeans": 10}, {"empty_code": True}),
    "worst-reseat-n128": ({"restart": "worst", "reseat": 32}, {"n_embed": 128}),
    "worst-reseat-decay0.95": ({"restart": "worst", "reseat": 32}, {"decay": 0.95}),
}
COLUMNS = [("steps", "codebook steps", 0), ("codebook_seconds", "wall s", 0), ("mae", "rec MAE", 2), ("psnr", "rec PSNR", 2),
           ("object_mae", "object MAE", 2), ("object_psnr", "object PSNR", 2), ("empty_entropy", "empty H", 2),
           ("codes_in_use", "codes", 0), ("colour_r2", "colour r2", 2), ("ce_c3", "CE c3", 3),
           ("ce_empty_c3", "CE empty", 3), ("ce_object_c3", "CE object", 3),
           ("token_accuracy_object_c3", "acc object", 3), ("mae_c3", "MAE c3", 2),
           ("nearest_view_mae_c3", "nearest c3", 2), ("mae_c5", "MAE c5", 2), ("nearest_view_mae_c5", "nearest c5", 2)]


def train_codebook_for(seconds, images, config, out, **kw):
    """train_codebook until `seconds` of this process's CPU time (ITIMER_PROF: user + system; at one
    thread, the compute spent), stopped by the run's Ctrl-C path (SIGINT when the timer fires), then
    its final model written at the step it reached. A run resumed after a kill counts its checkpoint's
    wall time as spent (at least the CPU time it had). Returns the Codebook."""
    ckpt = os.path.join(out, CHECKPOINT)
    done = read_checkpoint(ckpt, "codebook")[0]["elapsed"] if os.path.exists(ckpt) else 0.0
    if seconds > done:
        old = signal.signal(signal.SIGPROF, lambda *_: os.kill(os.getpid(), signal.SIGINT))
        signal.setitimer(signal.ITIMER_PROF, seconds - done)
        try:
            return train_codebook(images, config, out, steps=10 ** 7, **kw)  # stopped by the timer
        except KeyboardInterrupt:
            pass
        finally:
            signal.setitimer(signal.ITIMER_PROF, 0)
            signal.signal(signal.SIGPROF, old)
    step = read_checkpoint(ckpt, "codebook")[0]["step"]
    return train_codebook(images, config, out, steps=step, **kw)  # nothing left to run: the final model


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
                                threads=1, progress=False, checkpoint_every=25, **kw)
    tokens_path = os.path.join(folder, "tokens.npz")
    if not os.path.exists(tokens_path):
        save_tokens(tokens_path, tokenize(cb, data.images), data.poses, cb_config.n_embed)
    tokens, poses, _ = load_tokens(tokens_path)
    tf_path = os.path.join(folder, "transformer", "transformer.npz")
    tf = train_transformer(tokens, poses, tf_config, os.path.join(folder, "transformer"), steps=args.transformer_steps,
                           batch_size=8, lr=5e-4, seed=0, checkpoint_every=50, threads=1, progress=False)
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


def table(results):
    head = "| candidate | " + " | ".join(c[1] for c in COLUMNS) + " |"
    rows = [head, "|" + "---|" * (len(COLUMNS) + 1)]
    for r in results:
        rows.append(f"| {r['name']} | " + " | ".join(f"{r[k]:.{d}f}" for k, _, d in COLUMNS) + " |")
    return "\n".join(rows) + "\n"


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="training dataset folder (pyvf scenes)")
    p.add_argument("--out", required=True)
    p.add_argument("--only", default=",".join(CANDIDATES), help="comma-separated candidates, in order")
    p.add_argument("--codebook-minutes", type=float, default=8.0, help="CPU minutes per codebook")
    p.add_argument("--transformer-steps", type=int, default=250)
    p.add_argument("--scenes", type=int, default=40, help="held-out scenes")
    p.add_argument("--seed", type=int, default=2, help="held-out seed (not 0, training; not 1000, evaluation)")
    args = p.parse_args()
    if args.seed in (0, 1000):
        raise SystemExit("--seed must not be 0 (training) or 1000 (the final evaluation)")
    names = args.only.split(",")
    unknown = [n for n in names if n not in CANDIDATES]
    if unknown:
        raise SystemExit(f"unknown candidates {unknown}; known: {list(CANDIDATES)}")
    data = load_dataset(args.data)
    held = generate_scenes(args.seed, args.scenes, size=TINY_CODEBOOK.image_size)
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
