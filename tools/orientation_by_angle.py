"""Where a transformer's orientation error comes from (issue 48): the median error of each pair's
pose estimates, and of the closest-image baseline's, by how far the query is turned from the first
context view (the frame the model predicts in), with the median rotation the model predicts there.

    python tools/orientation_by_angle.py --pair shipped=shipped --pair si=CB.npz,TF.npz [--scenes 60 --seed 2]

NAME=shipped: pyvf's shipped pair; otherwise a codebook and a transformer file. Held-out scenes of
--seed (never 1000, the final evaluation's), contexts views 0..C-1, queries views 10..14. Prints a
markdown table.
"""

import argparse

import numpy as np

from pyvf.evaluate.metrics import closest_image_pose, orientation_error, position_error
from pyvf.geometry import make_relative, quat_normalize
from pyvf.models import load_pretrained
from pyvf.models.codebook import Codebook
from pyvf.models.transformer import Transformer
from pyvf.scenes import generate_scenes
from pyvf.train.loops import tokenize

BINS = ((0, 45), (45, 90), (90, 135), (135, 181))  # degrees the query is turned from the first context view
QUERIES = np.arange(10, 15)


def turn(poses, ref):
    """poses (n, M, 7), ref (n, 7) -> (n, M): the angle (degrees) of each pose's rotation relative to its ref."""
    rel = make_relative(np.concatenate([ref[:, None], poses], axis=1))[0][:, 1:]  # (n, M, 7)
    return orientation_error(rel, np.array([0, 0, 0, 1.0, 0, 0, 0]))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pair", action="append", required=True, metavar="NAME=CB,TF", help="'shipped' or two files")
    p.add_argument("--scenes", type=int, default=60)
    p.add_argument("--seed", type=int, default=2)
    p.add_argument("--context", default="3,5")
    args = p.parse_args()
    images, poses = generate_scenes(args.seed, args.scenes, size=64)
    truth = poses[:, QUERIES]
    true_turn = turn(truth, poses[:, 0])  # (n, M)
    head = "| pair | C | position | orientation | " + " | ".join(f"{a}-{min(b, 180)} deg" for a, b in BINS)
    rows = [head + " | predicted turn at 135-180 |", "|---|---:|" + "---:|" * (len(BINS) + 3)]
    counts = [int(((true_turn >= a) & (true_turn < b)).sum()) for a, b in BINS]
    pairs = {}  # name -> (transformer, the scenes' tokens by its codebook), loaded and tokenized once
    for pair in args.pair:
        name, files = pair.split("=")
        cb, tf = load_pretrained() if files == "shipped" else (Codebook.load(files.split(",")[0]),
                                                                Transformer.load(files.split(",")[1]))
        pairs[name] = tf, tokenize(cb, images).reshape(args.scenes, 15, -1).astype(np.int64)
    for C in map(int, args.context.split(",")):
        estimates = {"closest image": closest_image_pose(images[:, :C], poses[:, :C], images[:, QUERIES])}
        for name, (tf, tok) in pairs.items():
            est = tf.localize(tok[:, :C], poses[:, :C].astype(tf.dtype), tok[:, QUERIES]).astype(np.float64)
            est[..., 3:] = quat_normalize(est[..., 3:])
            estimates[name] = est
        for name, est in estimates.items():
            err, got = orientation_error(est, truth), turn(est, poses[:, 0])
            cells = [f"{np.median(err[(true_turn >= a) & (true_turn < b)]):.1f}" for a, b in BINS]
            rows.append(f"| {name} | {C} | {np.median(position_error(est, truth)):.2f} | {np.median(err):.1f} | "
                        + " | ".join(cells) + f" | {np.median(got[true_turn >= BINS[-1][0]]):.1f} |")
    print(f"{args.scenes} scenes of seed {args.seed}, queries views 10-14; queries per bin: {counts}\n")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
