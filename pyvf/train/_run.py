"""The run folder every training loop writes: its checkpoint, logs, config and progress bar.

    checkpoint.npz   the last checkpoint (atomic): __meta__ (JSON: kind, step, config, hyper, the
                     optimiser's step and hyperparameters, elapsed seconds, the held-out set's
                     fingerprint), model/<name>, optimizer/exp_avg/<name>, optimizer/exp_avg_sq/<name>
    log.csv          a row every LOG_EVERY steps and at the last; rows past the checkpoint are dropped on resume
    eval.csv         with held-out evaluation: one row per evaluation, likewise
    parity.csv       with the torch engine: its check against pyvf at each checkpoint, likewise
    config.json      the configuration, hyperparameters, and each call's command line
    <kind>.npz       the trained model, loadable by Codebook.load / Transformer.load

`hyper` holds everything the trajectory depends on besides the configuration (learning rate, batch
size, seed, the data's fingerprint...): a resume with other values raises. Its "init" (the model
file a fresh run started from) counts at step 0 only. An interrupted run resumes from its last
checkpoint (the steps after it are trained again, to the same bits).
"""

import csv
import hashlib
import io
import json
import os
import sys
import time

import numpy as np

from .. import _core
from .._io import CheckpointError, atomic_savez, atomic_write_text, load_npz, remove_stale_temps
from .._machine import cpu_name
from .curves import eval_line, plot_eval

CHECKPOINT, LOG, CONFIG, EVAL_LOG, PARITY_LOG = "checkpoint.npz", "log.csv", "config.json", "eval.csv", "parity.csv"
PARITY_COLUMNS = ["step", "worst", "rel_err", "bound"]
FORMAT_VERSION = 1
LOG_EVERY = 10  # steps between log.csv rows
RECORDED = ("command", "threads", "engine", "device", "precision")  # the RunOptions config.json records


def jsonable(x):
    """x with tuples as lists, as it reads back from JSON (so saved and current values compare)."""
    return json.loads(json.dumps(x))


def fingerprint(*arrays):
    """A short hash of the arrays' shapes, dtypes and bytes: the data a run was trained on."""
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(memoryview(a).cast("B"))
    return h.hexdigest()


def file_sha256(path):
    """The sha256 of a file's bytes, hex: the file a run started from (a warm start's model file)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_checkpoint(path, kind):
    """-> (meta, model state dict, optimizer state dict). kind: "codebook", "transformer" (another
    raises ValueError) or None for either. Not a pyvf checkpoint: CheckpointError naming the file."""
    arrays = load_npz(path, "checkpoint", required=("__meta__",))
    meta = json.loads(str(arrays.pop("__meta__")))
    if meta.get("format") != "pyvf-checkpoint" or meta.get("version") != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {path}: not a pyvf checkpoint of format version {FORMAT_VERSION}")
    if kind is not None and meta["kind"] != kind:
        raise ValueError(f"checkpoint {path} is a {meta['kind']!r} run, not a {kind!r} run: use another output folder")

    def group(prefix):
        return {k[len(prefix):]: a for k, a in arrays.items() if k.startswith(prefix)}

    opt = {"exp_avg": group("optimizer/exp_avg/"), "exp_avg_sq": group("optimizer/exp_avg_sq/"), **meta["optimizer"]}
    return meta, group("model/"), opt


class Run:
    """The run folder of one call of a training loop.

        run = Run(out_dir, "codebook", config_dict, hyper, LOG_COLUMNS, opts)   # opts: loops.RunOptions
        (restore the model and optimiser from run.model_state, run.optimizer_state when run.resumed)
        for t in run.steps():              # run.start + 1 .. steps
            ...                            # one update
            run.log(t, {"loss": ...})
            run.checkpoint(t, model.state_dict, optimizer)  # when due
        run.save_final(model.state_dict())

    call: what config.json records of this call beside opts' RECORDED fields. evaluation: None, or
    (eval.csv's columns, the fingerprint of the held-out set; a resume refuses another).
    """

    def __init__(self, out_dir, kind, config, hyper, columns, opts, *, call=None, evaluation=None):
        self.steps_total, self.checkpoint_every = opts.steps, opts.checkpoint_every
        self.kind, self.config, self.hyper = kind, jsonable(config), jsonable(hyper)
        self.columns = ["step", *columns, "seconds"]
        self.progress = opts.progress
        self.out_dir = os.fspath(out_dir)
        os.makedirs(self.out_dir, exist_ok=True)
        self.ckpt_path, self.log_path, self.eval_path, self.config_path, self.final_path, self.parity_path = (
            os.path.join(self.out_dir, name) for name in (CHECKPOINT, LOG, EVAL_LOG, CONFIG, f"{kind}.npz", PARITY_LOG))
        eval_columns, self.eval_fingerprint = evaluation or (None, None)
        self.eval_columns = None if eval_columns is None else ["step", *eval_columns, "seconds"]
        for path in (self.ckpt_path, self.log_path, self.config_path, self.final_path, self.eval_path):
            remove_stale_temps(path)  # left by a process killed mid-write

        self.start, self.elapsed0 = 0, 0.0
        self.model_state = self.optimizer_state = None
        if opts.resume and os.path.exists(self.ckpt_path):
            self._resume()
        self.resumed = self.model_state is not None
        if not self.resumed:  # starting over: an older run's files must not be resumed later, nor kept
            for path in (self.ckpt_path, self.final_path, self.eval_path, self.parity_path):
                if os.path.exists(path):
                    os.remove(path)
        self._write_config(call, opts)
        self._truncate_log(self.log_path, self.columns)
        if self.eval_columns is not None:
            self._truncate_log(self.eval_path, self.eval_columns)
        if opts.engine == "torch":
            self._truncate_log(self.parity_path, PARITY_COLUMNS)
        self._bar = None
        self._t0 = time.perf_counter()

    def _resume(self):
        """Read the checkpoint; raise when it is another run's."""
        meta, self.model_state, self.optimizer_state = read_checkpoint(self.ckpt_path, self.kind)
        self.hyper = {k: v for k, v in self.hyper.items() if k != "init"}  # the model file counts at step 0 only
        if "init" in meta["hyper"]:
            self.hyper["init"] = meta["hyper"]["init"]
        for what, saved, now in (("configuration", meta["config"], self.config),
                                 ("hyperparameters", meta["hyper"], self.hyper)):
            if saved != now:
                differ = {k: saved.get(k) for k in set(saved) | set(now) if saved.get(k) != now.get(k)}
                raise ValueError(f"checkpoint {self.ckpt_path} was written with another {what} (saved: {differ}): "
                                 "pass the saved values, another output folder, or --no-resume to start over")
        self.start, self.elapsed0 = int(meta["step"]), float(meta["elapsed"])
        if self.start > self.steps_total:
            raise ValueError(f"checkpoint {self.ckpt_path} is at step {self.start}, past steps={self.steps_total}")
        saved = meta.get("eval")
        if saved is not None and self.eval_fingerprint is not None and saved != self.eval_fingerprint:
            raise ValueError(f"{self.eval_path} holds evaluations on another held-out set than this call's: "
                             "resume with the run's one, or without evaluation (--eval-every 0)")
        self.eval_fingerprint = self.eval_fingerprint or saved

    def _write_config(self, call, opts):
        """config.json: the configuration, hyperparameters, and one entry per call of the run, with
        the machine it ran on (a resumed run's calls may run on different machines)."""
        calls = []
        if self.resumed and os.path.exists(self.config_path):
            with open(self.config_path, encoding="utf-8") as f:
                calls = json.load(f)["calls"]
        calls.append({"started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "steps": self.steps_total,
                      "resumed_from_step": self.start if self.resumed else None,
                      "checkpoint_every": self.checkpoint_every, "numpy": np.__version__,
                      "machine": {"cpus": os.cpu_count(), "processor": cpu_name(), "kernel_path": _core.current_path(),
                                  "kernel_threads": int(_core.num_threads())},
                      **jsonable({**{k: getattr(opts, k) for k in RECORDED}, **(call or {})})})
        atomic_write_text(self.config_path, json.dumps(
            {"kind": self.kind, "config": self.config, "hyperparameters": self.hyper, "calls": calls},
            indent=2) + "\n")

    def _truncate_log(self, path, columns):
        """Keep the header and the rows up to the checkpoint's step (none on a fresh start); a
        torn line (a process killed mid-write) is dropped with the rows past it."""
        kept = []
        if self.resumed and os.path.exists(path):
            with open(path, newline="", encoding="utf-8", errors="replace") as f:
                rows = list(csv.reader(f))
            for row in rows[1:]:
                if len(row) != len(columns) or not row[0].isdigit() or int(row[0]) > self.start:
                    break  # torn, or past the checkpoint
                kept.append(row)
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerows([columns, *kept])
        atomic_write_text(path, buf.getvalue())

    def seconds(self):
        return self.elapsed0 + (time.perf_counter() - self._t0)

    def log(self, step, values):
        """values: column -> float, written every LOG_EVERY steps and at the last."""
        self._bar.set_postfix(loss=f"{values['loss']:.4f}", refresh=False)
        if step % LOG_EVERY == 0 or step == self.steps_total:
            self._append(self.log_path, step, values, self.columns)

    def log_eval(self, step, values):
        """Append one row of held-out figures to eval.csv, print it (curves.eval_line), redraw eval.png."""
        self._append(self.eval_path, step, values, self.eval_columns)
        line = f"{self.kind} held-out at step {step}: {eval_line(values)}"  # as it trains, not only at the end
        (print if self._bar is None else self._bar.write)(line, file=sys.stderr)  # above the bar, if any
        plot_eval(self.out_dir)

    def _append(self, path, step, values, columns):
        """Append the row of `step` (values: column -> float) to a CSV log; repr: floats round-trip
        exactly, so two runs' logs compare bit for bit."""
        row = [str(step)] + [repr(float(values[c])) for c in columns[1:-1]] + [f"{self.seconds():.3f}"]
        with open(path, "a", newline="", encoding="utf-8") as f:
            csv.writer(f, lineterminator="\n").writerow(row)

    def log_parity(self, step, worst, rel_err, bound):
        """Append the torch engine's parity check of `step` to parity.csv."""
        with open(self.parity_path, "a", newline="", encoding="utf-8") as f:
            csv.writer(f, lineterminator="\n").writerow([step, worst, repr(float(rel_err)), repr(float(bound))])

    def steps(self):
        """start + 1 .. steps, with a progress bar on stderr (opts.progress)."""
        from tqdm.auto import tqdm
        self._bar = tqdm(total=self.steps_total, initial=self.start, desc=f"train {self.kind}", unit="step",
                         dynamic_ncols=True, disable=not self.progress)
        with self._bar:
            for t in range(self.start + 1, self.steps_total + 1):
                yield t
                self._bar.update(1)

    def checkpoint(self, step, state, optimizer, check=None):
        """After `step`, when due: check(self, step) (the torch engine's parity), then the checkpoint."""
        if step % self.checkpoint_every == 0 or step == self.steps_total:
            if check is not None:
                check(self, step)
            model, elapsed, opt = state(), self.seconds(), optimizer.state_dict()
            meta = {"format": "pyvf-checkpoint", "version": FORMAT_VERSION, "kind": self.kind, "step": int(step),
                    "config": self.config, "hyper": self.hyper, "elapsed": float(elapsed),
                    "optimizer": {"step": int(opt["step"]), "hyperparameters": opt["hyperparameters"]},
                    "eval": self.eval_fingerprint}
            arrays = {"__meta__": json.dumps(meta), **{"model/" + k: v for k, v in model.items()}}
            for key in ("exp_avg", "exp_avg_sq"):
                arrays.update({f"optimizer/{key}/{k}": v for k, v in opt[key].items()})
            atomic_savez(self.ckpt_path, **arrays)  # atomic: a killed process leaves the previous one intact

    def save_final(self, arrays):
        """The trained model as Codebook.save / Transformer.save write it. Returns its path."""
        fp = self.hyper.get("codebook_fingerprint")  # a transformer's
        meta = {} if fp is None else {"__codebook_fingerprint__": fp}
        atomic_savez(self.final_path, __config__=json.dumps(self.config), **meta, **arrays)
        return self.final_path
