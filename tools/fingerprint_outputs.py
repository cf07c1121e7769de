"""Fingerprint what pyvf's commands write, to check a refactoring changed no output.

    python tools/fingerprint_outputs.py OUT.json        # run once before, once after
    python tools/fingerprint_outputs.py --compare BEFORE.json AFTER.json

Runs the installed `pyvf` (so run it against the version you want to fingerprint) from a temporary
folder: `pyvf demo --quick`, `pyvf evaluate` on 3 scenes, 20 steps of `train-codebook` and of
`train-transformer` on a small rendered dataset, and writes one sha256 per output: every array of
each .npz, and each metrics.json with its timing fields (keys naming seconds, time, speed, or
machine facts) removed. Two fingerprints agree key for key when the outputs are bitwise the same.
Needs the source tree only because it is a developer's check (a user has nothing to compare).
"""

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

# fields that measure the machine, not the math: dropped before hashing
_VOLATILE = ("second", "time", "speed", "_ms", "ms_", "machine", "date", "started", "host", "threads",
             "cpu", "wall", "elapsed", "timing", "kernel_path", "numpy", "python", "version", "argv", "command")


def _strip(obj):
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if not any(s in k.lower() for s in _VOLATILE)}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def _hash_json(path):
    with open(path) as f:
        data = _strip(json.load(f))
    return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()


def _hash_array(a):
    if a.dtype.kind == "U" and a.ndim == 0:  # a JSON record (a checkpoint's __meta__): its timings dropped
        try:
            data = _strip(json.loads(str(a)))
        except ValueError:
            pass
        else:
            return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()
    return hashlib.sha256(np.ascontiguousarray(a).tobytes() + str(a.dtype).encode() + str(a.shape).encode()).hexdigest()


def _hash_npz(path):
    with np.load(path, allow_pickle=False) as z:
        return {k: _hash_array(z[k]) for k in sorted(z.files)}


def _pyvf(*args, cwd):
    subprocess.run(["pyvf", *args], cwd=cwd, check=True, stdout=subprocess.DEVNULL)


def fingerprint(keep=None):
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        if keep:
            tmp = keep
            os.makedirs(tmp, exist_ok=True)
        _pyvf("demo", "--quick", "--no-progress", "--threads", "2", "--out", "demo", cwd=tmp)
        out["demo/metrics.json"] = _hash_json(os.path.join(tmp, "demo", "metrics.json"))
        _pyvf("evaluate", "--scenes", "3", "--context", "1,3", "--no-progress", "--threads", "2",
              "--out", "eval", cwd=tmp)
        out["evaluate/metrics.json"] = _hash_json(os.path.join(tmp, "eval", "metrics.json"))
        _pyvf("scenes", "--out", "data", "--scenes", "24", "--seed", "5", "--quiet", cwd=tmp)
        _pyvf("train-codebook", "--data", "data", "--out", "cb", "--steps", "20", "--batch", "4",
              "--checkpoint-every", "10", "--eval-every", "0", "--no-progress", "--threads", "2", cwd=tmp)
        for k, v in _hash_npz(os.path.join(tmp, "cb", "checkpoint.npz")).items():
            out[f"train-codebook/checkpoint/{k}"] = v
        _pyvf("tokenize", "--codebook", "cb/codebook.npz", "--data", "data", "--out", "tokens.npz",
              "--threads", "2", cwd=tmp)
        for k, v in _hash_npz(os.path.join(tmp, "tokens.npz")).items():
            out[f"tokenize/{k}"] = v
        _pyvf("train-transformer", "--tokens", "tokens.npz", "--out", "tf", "--steps", "20", "--batch", "4",
              "--checkpoint-every", "10", "--eval-every", "0", "--no-progress", "--threads", "2", cwd=tmp)
        for k, v in _hash_npz(os.path.join(tmp, "tf", "checkpoint.npz")).items():
            out[f"train-transformer/checkpoint/{k}"] = v
    return out


def compare(before, after):
    keys = sorted(set(before) | set(after))
    bad = [k for k in keys if before.get(k) != after.get(k)]
    for k in bad:
        print(f"differs: {k}")
    print(f"{len(keys) - len(bad)} of {len(keys)} outputs bitwise the same")
    return not bad


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", nargs="?", help="write the fingerprint here (JSON)")
    ap.add_argument("--compare", nargs=2, metavar=("BEFORE", "AFTER"))
    ap.add_argument("--keep", metavar="DIR", help="write the outputs into DIR (an empty folder) and keep them")
    a = ap.parse_args()
    if a.compare:
        with open(a.compare[0]) as f, open(a.compare[1]) as g:
            sys.exit(0 if compare(json.load(f), json.load(g)) else 1)
    if not a.out:
        ap.error("give OUT.json or --compare BEFORE AFTER")
    fp = fingerprint(a.keep)
    with open(a.out, "w") as f:
        json.dump(fp, f, indent=1, sort_keys=True)
    print(f"{len(fp)} outputs fingerprinted -> {a.out}")


if __name__ == "__main__":
    main()
