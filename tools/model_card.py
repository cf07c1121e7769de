"""Write docs/models.md, the model card of the shipped tiny models, from their run folders and an
evaluation folder: nothing in it is typed by hand. Needs the source tree (it writes docs/).

    python tools/model_card.py --codebook-run RUN_CB --transformer-run RUN_TF --eval EVAL_DIR \\
        [--data DATA_DIR] [--remarks FILE.md] [--out docs]

RUN_CB, RUN_TF: the folders `pyvf train-codebook` / `pyvf train-transformer` wrote (config.json,
log.csv); EVAL_DIR: what `pyvf evaluate` wrote (metrics.json, metrics.md, views.png, poses.png).
Writes docs/models.md and docs/img/{codebook,transformer}-curves.png, and copies the evaluation's
pictures to docs/img/.
"""

import argparse
import json
import os
import shutil
import sys

from pyvf._io import atomic_write_text
from pyvf.evaluate.run import _SHORT, VERDICTS, _against, paper_line, verdict_lines
from pyvf.train.curves import eval_panels, plot_curves, plot_eval, read_log


_NAME = {m: short.removesuffix(" (deg)") for m, short in _SHORT.items()}  # in lists, without units
# The project's goal: pyvf beats every baseline of VERDICTS on each of its metrics at these contexts
GOAL_CONTEXTS = (3, 5)


def _listed(items):
    """{baseline: [metric, ...]} -> "nearest_view (MAE, RMSE), mean_pose (position)"."""
    return ", ".join(f"{b} ({', '.join(_NAME[m] for m in ms)})" for b, ms in items.items() if ms) or "none"


def goal_line(metrics, contexts=GOAL_CONTEXTS):
    """Whether pyvf beats every baseline of VERDICTS on each of its metrics at each of `contexts`;
    per context, the figures that hold and those that fail. -> str."""
    parts, failing, missing = [], False, False
    for C in map(str, contexts):
        if C not in metrics["context"]:
            parts.append(f"Context {C}: not evaluated.")
            missing = True
            continue
        table = metrics["context"][C]
        held, failed = {}, {}
        for base, names in VERDICTS.items():
            held[base], failed[base], _ = _against(table["pyvf"], table[base], names)
        failing = failing or any(failed.values())
        parts.append(f"Context {C}: beats {_listed(held)}" + (f"; does not beat {_listed(failed)}."
                                                                if any(failed.values()) else " (all)."))
    word = "not met" if failing else ("not shown (a context is missing)" if missing else "met")
    return (f"- the goal, at contexts {' and '.join(map(str, contexts))}: pyvf beats {_listed(VERDICTS)}: "
            f"{word}. " + " ".join(parts))


def _snapshot(run_dir, step, tmp):
    """A copy of the run folder's config.json, log.csv and eval.csv in tmp with the rows up to
    `step` only: the card of a model exported (`pyvf export`) from a run that trains on."""
    import csv
    tmp = os.path.join(tmp, os.path.basename(os.path.normpath(run_dir)))  # the plots' titles name the run
    os.makedirs(tmp)
    shutil.copyfile(os.path.join(run_dir, "config.json"), os.path.join(tmp, "config.json"))
    for name in ("log.csv", "eval.csv"):
        if os.path.exists(os.path.join(run_dir, name)):
            with open(os.path.join(run_dir, name), newline="") as f:
                rows = list(csv.reader(f))
            rows = rows[:1] + [r for r in rows[1:] if int(float(r[0])) <= step]
            with open(os.path.join(tmp, name), "w", newline="") as f:
                csv.writer(f).writerows(rows)
    return tmp


def _run(run_dir):
    with open(os.path.join(run_dir, "config.json")) as f:
        config = json.load(f)
    log = read_log(run_dir)
    return config, log


def _as_typed(path):
    """A path of a run's command line as the card shows it: an absolute one by its last name (not one
    machine's folders), a relative one as typed."""
    return os.path.basename(path.rstrip("/")) if os.path.isabs(path) else path


def _commands(config):
    """The command lines of every call of a run, as a user would type them."""
    out = []
    for call in config.get("calls", []):
        argv = (call.get("command") or {}).get("argv")
        if argv:  # folders by their names, not one machine's paths
            out.append(" ".join(["pyvf"] + [_as_typed(a) for a in argv[1:]]))
    return out


def _tokenize_command(config, data_dir):
    """The `pyvf tokenize` line that wrote a transformer run's tokens file: the run's first call
    names the file and the codebook (--tokens, --codebook), data_dir the scenes; None when unknown."""
    calls = config.get("calls") or [{}]
    args = (calls[0].get("command") or {}).get("args") or {}
    if not (data_dir and args.get("tokens") and args.get("codebook")):
        return None
    return (f"pyvf tokenize --codebook {_as_typed(args['codebook'])} --data {os.path.basename(os.path.normpath(data_dir))} "
            f"--out {_as_typed(args['tokens'])}")


def _section(name, run_dir, config, log, columns, img_dir, log_y=(), where_note=None, before=None, previous=None):
    png = os.path.join(img_dir, f"{name}-curves.png")
    plot_curves(run_dir, png, columns, title=f"{name}: {', '.join(columns)} against the step", log_y=log_y)
    steps, seconds = int(log["step"][-1]), float(log["seconds"][-1])
    lines = [f"## The {name}", "",
             f"Trained for {steps} steps in {seconds / 60:.0f} min of wall time in all (the log's elapsed "
             "seconds, summed over the run's calls below; other work shared the cores part of the time)."]
    planned = config["hyperparameters"].get("total_steps")
    if planned and steps < planned:
        lines[-1] += (f" The run is planned for {planned} steps (its learning-rate schedule's length) and trains "
                      f"on: the shipped model is its state at step {steps}, written by `pyvf export`.")
    init = config["hyperparameters"].get("init")
    if init:  # a fine-tuning (--init): where its starting weights came from, as the first call named it
        given = ((config.get("calls") or [{}])[0].get("command") or {}).get("args", {}).get("init") or init["path"]
        lines[-1] += (f" It started (`--init`) from `{_as_typed(given)}` (sha256 {init['sha256'][:12]}...)"
                      + (f", the {name} of the pair described in [{os.path.basename(previous)}]"
                         f"({os.path.basename(previous)})." if previous else "."))
    lines += ["", "| call started | resumed from step | machine (CPUs, processor, kernel path, threads) |",
              "|---|---:|---|"]
    for call in config.get("calls", []):
        if (call.get("resumed_from_step") or 0) >= steps:  # a call after the exported step
            continue
        m = call.get("machine")
        where = (f"{m['cpus']} CPUs, {m['processor']}, {m['kernel_path']}, {m['kernel_threads']} threads" if m
                 else "not recorded (a call from before config.json recorded the machine)")
        resumed = call.get("resumed_from_step")
        lines.append(f"| {call.get('started', '?')} | {'-' if resumed is None else resumed} | {where} |")
    if where_note:
        lines += ["", where_note]
    lines += ["",
             "Configuration and hyperparameters (the run's config.json):", "", "```json",
             json.dumps({"config": config["config"], "hyperparameters": config["hyperparameters"]}, indent=1),
             "```", "", f"Commands ({'its tokens file, then ' if before else ''}each call of the run; a resumed run "
             "continues to the same total):", "", "```bash"]
    lines += ([before] if before else []) + (_commands(config) or ["(not recorded)"])
    lines += ["```", "", "Last logged values: " + ", ".join(f"{c} {log[c][-1]:.4g}" for c in columns), "",
              f"![{name} learning curves](img/{os.path.basename(png)})", ""]
    if os.path.exists(os.path.join(run_dir, "eval.csv")):  # the held-out evaluation during training
        ev = read_log(run_dir, "eval.csv")
        panels, baselines = eval_panels(list(ev))
        epng = plot_eval(run_dir, os.path.join(img_dir, f"{name}-eval.png"))
        last = ", ".join(f"{c} {ev[c][-1]:.4g}" for c in panels)
        base = ", ".join(f"{b} {ev[b][-1]:.4g}" for c in panels for b in baselines.get(c, ()))
        dashed = "; the baselines dashed" if baselines else ""
        lines += [f"Held-out evaluation during training (eval.csv{dashed}), last at step "
                  f"{int(ev['step'][-1])}: {last}" + (f"; baselines: {base}" if base else "") + ".", "",
                  f"![{name} held-out evaluation]({'img/' + os.path.basename(epng)})", ""]
    return lines


def _baselines(metrics):
    """The section "Against the baselines", from metrics.json: at every context evaluated, pyvf's
    figure beside each baseline's and whether pyvf beats it (verdict_lines); then whether the
    project's goal holds (goal_line) and the paper's figures for scale."""
    lines = ["## Against the baselines", "",
             "Computed from the evaluation's metrics.json: every figure as in the tables above, lower is better."]
    for C in sorted(metrics["context"], key=int):
        lines += [""] + verdict_lines(metrics, context=C)
    return lines + ["", "Summary:", "", goal_line(metrics), paper_line(), ""]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--codebook-run", required=True)
    p.add_argument("--transformer-run", required=True)
    p.add_argument("--eval", required=True, help="a pyvf evaluate output folder")
    p.add_argument("--data", default=None, help="the training dataset folder (its manifest names the seed)")
    p.add_argument("--codebook-where", default=None,
                   help="where the codebook run's calls ran, for calls that did not record it")
    p.add_argument("--transformer-where", default=None,
                   help="where the transformer run's calls ran, for calls that did not record it")
    p.add_argument("--remarks", default=None, help="a markdown file appended after the evaluation")
    p.add_argument("--transformer-step", type=int, default=None,
                   help="the step the shipped transformer was exported at (`pyvf export`) from a run that "
                        "trains on: the card shows the run up to it")
    p.add_argument("--previous", default=None,
                   help="the card (in --out) of the pair the runs were fine-tuned from (--init)")
    p.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "..", "docs"))
    args = p.parse_args(argv)
    if args.transformer_step is not None:
        import tempfile
        with tempfile.TemporaryDirectory() as tmp:
            args.transformer_run = _snapshot(args.transformer_run, args.transformer_step, tmp)
            return _write(args)
    return _write(args)


def _write(args):

    img_dir = os.path.join(args.out, "img")
    os.makedirs(img_dir, exist_ok=True)
    cb_config, cb_log = _run(args.codebook_run)
    tf_config, tf_log = _run(args.transformer_run)
    with open(os.path.join(args.eval, "metrics.json")) as f:
        metrics = json.load(f)
    with open(os.path.join(args.eval, "metrics.md")) as f:
        metrics_md = f.read()
    for pic in ("views.png", "poses.png"):
        if os.path.exists(os.path.join(args.eval, pic)):
            shutil.copyfile(os.path.join(args.eval, pic), os.path.join(img_dir, pic))

    data_line = "SM7 scenes rendered by `pyvf scenes` (training seed 0)."
    if args.data:
        with open(os.path.join(args.data, "manifest.json")) as f:
            manifest = json.load(f)
        data_line = (f"{manifest.get('n_scenes', '?')} SM7 scenes x {manifest.get('views', '?')} views, "
                     f"{manifest.get('height', '?')}x{manifest.get('width', '?')}, rendered by "
                     f"`pyvf scenes --out {os.path.basename(os.path.normpath(args.data))} "
                     f"--scenes {manifest.get('n_scenes', '?')} --seed {manifest.get('seed', '?')}`.")
    meta = metrics.get("meta", {})
    lines = ["# The shipped tiny models (`pyvf.models.load_pretrained()`)", "",
             "Generated by `python tools/model_card.py` from the training runs and a `pyvf evaluate` run; "
             "every number below comes from those files.", "",
             "Files: `pyvf/models/sm7-codebook.npz`, `pyvf/models/sm7-transformer.npz`.", "",
             f"Training data: {data_line} Evaluation scenes use other seeds (the evaluation's seed: "
             f"{meta.get('seed', '?')}), so no evaluated scene was seen in training.", ""]
    lines += _section("codebook", args.codebook_run, cb_config, cb_log,
                      ["rec_loss", "commitment", "perplexity", "usage"], img_dir, where_note=args.codebook_where,
                      previous=args.previous)
    lines += _section("transformer", args.transformer_run, tf_config, tf_log,
                      ["ce_loss", "pose_loss", "lr"], img_dir, where_note=args.transformer_where,
                      before=_tokenize_command(tf_config, args.data), previous=args.previous)
    command = (f"pyvf evaluate --scenes {meta['scenes']} --context {','.join(map(str, meta['context_sizes']))} "
               f"--seed {meta['seed']} --out eval")  # what metrics.json's meta says was run
    # the section on the baselines goes right after the tables, before metrics.md's timings
    tables, timing, rest = metrics_md.strip().partition("\n## Timing")
    lines += ["## Held-out evaluation", "", "```bash", command, "```", "", tables.strip(), ""]
    lines += _baselines(metrics)
    if timing:
        lines += [(timing + rest).strip(), ""]
    for pic, what in (("views.png", "context views | ground truth | codebook reconstruction | pyvf's rendering"),
                      ("poses.png", "estimated against true camera positions")):
        if os.path.exists(os.path.join(img_dir, pic)):
            lines += [f"![{what}](img/{pic})", ""]
    if args.remarks:
        with open(args.remarks) as f:
            lines += [f.read().strip(), ""]
    atomic_write_text(os.path.join(args.out, "models.md"), "\n".join(lines))
    print(f"wrote {os.path.join(args.out, 'models.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
