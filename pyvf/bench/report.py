"""docs/performance.md and docs/accuracy.md, generated: never typed by hand.

    pyvf bench report                   # the full runs into docs/
    pyvf bench report --quick --out D   # the --quick runs into D/ (a few minutes)

Runs on --threads threads `pyvf bench scaling` (full: --sizes 12x64 --max-point-seconds 30, then
--sizes 4x32 --max-point-seconds 60), `accuracy` and `hardcases`; writes OUT/performance.md (the
conclusions, each number computed from the same run's measurements: how the attention's memory
and time grow with N, pyvf's time and error against torch's per op; then the evidence),
OUT/accuracy.md (every op's variants and the hard cases), their plots in OUT/img/ and every number
in OUT/measurements/. The guardrails' speed ratios are `pyvf bench attention|transformer|codebook`'s.
"""

import datetime
import os
import time

from pyvf._io import atomic_write_text
from pyvf.bench import accuracy, hardcases, scaling
from pyvf.bench.common import MEMORY_METHOD, write_json

# the scaling runs: the command line that repeats each (in the documents), and scaling.run's options
SCALING_FULL = [("--sizes 12x64 --max-point-seconds 30", dict(sizes=((12, 64),), max_point_seconds=30)),
                ("--sizes 4x32 --max-point-seconds 60", dict(sizes=((4, 32),), max_point_seconds=60))]


def scaling_line(scal, kind):
    """The memory (kind "bytes") or time ("seconds") conclusion at the scaling report's first size:
    pyvf's fitted slope, each other method's and its forward+backward value over pyvf's at the
    largest N every method measured; the methods not measured, with the reason."""
    title, what, key = dict(bytes=("Memory", "peak memory", "fb_bytes"), seconds=("Time", "time", "fb_seconds"))[kind]
    H, dh = scal["config"]["sizes"][0]
    fit = scal["slopes"][f"{H}x{dh}"]
    pts = [p for p in scal["points"] if (p["H"], p["dh"]) == (H, dh)]
    vals = {m: {p["N"]: p[key] for p in pts if p["method"] == m and p.get(key)} for m in scal["config"]["methods"]}
    missing = {m: next((p.get("skipped") or p.get("error", "?")).splitlines()[0][:120] for p in pts if p["method"] == m)
               for m, v in vals.items() if not v}
    if "pyvf" in missing:
        return f"* **{title}**: pyvf's forward+backward {what} was not measured ({missing['pyvf']})."
    vals = {m: v for m, v in vals.items() if v}
    n = max(set.intersection(*(set(v) for v in vals.values())), default=None)
    line = (f"* **{title}**: pyvf's forward+backward {what} grows as **N^{scaling._s(fit['pyvf'][key])}** "
            f"(N={min(vals['pyvf'])}..{max(vals['pyvf'])}; H={H} dh={dh}, R=3, B=1, L=64, float32)")
    if n is not None and len(vals) > 1:
        line += f"; at N={n}, the largest N every method measured: " + "; ".join(
            f"{scaling.METHODS[m]} N^{scaling._s(fit[m][key])}, {v[n] / vals['pyvf'][n]:.3g}x pyvf's"
            for m, v in vals.items() if m != "pyvf")
    if missing:
        line += ". Not measured: " + "; ".join(f"{scaling.METHODS[m]}: {why}" for m, why in missing.items())
    return line + "."


def against(res):
    """One op of the accuracy report: (pyvf float32's variant, the one it is compared with: torch
    float32, else NumPy float32), each None where it failed validation or was not run."""
    timed = {r["name"]: r for r in res["variants"] if "seconds" in r}
    return timed.get("pyvf float32"), timed.get("torch float32") or timed.get("numpy float32")


def speed_error_line(acc):
    """The speed-against-error conclusion: per op, pyvf float32's time and error over the other's."""
    pairs = [(res["op"], *against(res)) for res in acc["results"]]
    done = [(op, p, r) for op, p, r in pairs if p and r]
    return (f"* **Speed against error**: pyvf float32 (kernel path {acc['machine']['kernel_path']}) against "
            f"{done[0][2]['name'] if done else 'no other variant'}, time ratio / error ratio: "
            + ", ".join(f"{op} {p['seconds'] / r['seconds']:.2g} / {p['rel'] / r['rel']:.2g}" for op, p, r in done)
            + f"; faster on {sum(p['seconds'] < r['seconds'] for _, p, r in done)} of {len(pairs)} ops, at most "
            f"its error on {sum(p['rel'] <= r['rel'] for _, p, r in done)}.")


def _img(path, out):
    return f"![{os.path.basename(path)}]({os.path.relpath(path, out)})" if path else "(no plot: matplotlib is not installed)"


def machine_lines(m, total):
    return "\n".join([
        f"* machine: {m['processor']}, {m['cpu_count']} CPUs, {m['platform']}",
        f"* pyvf {m['pyvf']}, kernel path **{m['kernel_path']}** (this CPU runs {', '.join(m['kernel_paths'])}), "
        f"**{m['threads']} threads** (pyvf, torch and numpy's BLAS)",
        f"* Python {m['python']}, NumPy {m['numpy']}, torch {m['torch'] or 'not installed'}",
        f"* measured {m['generated']}; the whole report took {total / 60:.1f} minutes"])


def performance_md(out, quick, m, total, scalings, acc, jsons):
    """The conclusions, the machine, then the evidence of the attention's scaling."""
    s = [f"<!-- generated by `pyvf bench report{quick}`: do not edit by hand; rerun it -->", "",
         "# pyvf performance", "", "## At a glance", "",
         scaling_line(scalings[0][1], "bytes"), scaling_line(scalings[0][1], "seconds"), speed_error_line(acc),
         "* **More**: every op's time and error, and the hard cases, in [accuracy.md](accuracy.md); every number as JSON: "
         + ", ".join(f"`{os.path.relpath(p, out)}`" for p in jsons) + ".", "",
         "## The machine", "", machine_lines(m, total), "", "Every timed result was validated first.", "",
         "## Attention memory and time against the number of views", ""]
    for args, rep in scalings:
        s += [f"`pyvf bench scaling {args}`: each point in its own process; memory: the extra peak of one call "
              f"({MEMORY_METHOD}); every point in the JSON.", ""] + [_img(p, out) + "\n" for p in rep.get("plots") or [None]]
        s += scaling.tables(rep["slopes"], [tuple(x) for x in rep["config"]["sizes"]], rep["config"]["methods"]) + [""]
    return "\n".join(s)


def accuracy_md(out, quick, m, total, acc, hc, jsons):
    fails = acc["failures"] + hc["failures"]
    doc = {mod: "\n\n".join(mod.__doc__.strip().split("\n\n")[2:]) for mod in (accuracy, hardcases)}
    s = [f"<!-- generated by `pyvf bench report{quick}`: do not edit by hand; rerun it -->", "", "# pyvf accuracy", "",
         machine_lines(m, total), "",
         f"**{'FAIL' if fails else 'PASS'}**: " + (f"{len(fails)} result(s) outside pyvf's stated bound: "
                                                   + "; ".join(fails) if fails else
                                                   "every pyvf variant and every hard-case line within its stated bound."),
         "", "JSON: " + ", ".join(f"`{os.path.relpath(p, out)}`" for p in jsons) + ".", "",
         f"## Error of each op, each variant (`pyvf bench accuracy{quick}`)", "", doc[accuracy], ""]
    for res in acc["results"]:
        s += [f"### {res['op']}, size {tuple(res['size']) if isinstance(res['size'], list) else res['size']}", "",
              accuracy.op_table(res), "", _img(res.get("plot"), out), ""]
    s += ["## Hard cases", "", f"`pyvf bench hardcases{quick}`: " + doc[hardcases], ""]
    for sw in hc["sweeps"]:
        s += [f"### {sw['title']}", "", hardcases.sweep_summary(sw), "", _img(sw.get("plot"), out), ""]
    return "\n".join(s)


def run(quick=False, threads=2, out="docs", log=print):
    """Every run, then the documents (module docstring): {failures, files}."""
    t0 = time.perf_counter()
    img, meas = os.path.join(out, "img"), os.path.join(out, "measurements")
    os.makedirs(meas, exist_ok=True)
    suffix, quiet = "-quick" if quick else "", lambda *a, **k: None
    scalings, jsons = [], []
    for args, options in [("--quick", {})] if quick else SCALING_FULL:
        log(f"pyvf bench scaling {args}", flush=True)
        scalings.append((args, scaling.run(quick, threads, plots=img, log=quiet, **options)))
        sizes = "-".join(f"H{h}-dh{d}" for h, d in scalings[-1][1]["config"]["sizes"])
        jsons.append(os.path.join(meas, f"scaling-{sizes}{suffix}.json"))
        write_json(jsons[-1], scalings[-1][1])
    log("pyvf bench accuracy, hardcases", flush=True)
    reps = dict(accuracy=accuracy.run(quick, threads, plots=img, log=quiet),
                hardcases=hardcases.run(quick, threads, plots=img, log=quiet))
    for name, rep in reps.items():
        jsons.append(os.path.join(meas, f"{name}{suffix}.json"))
        write_json(jsons[-1], rep)
    total = time.perf_counter() - t0
    m = dict(reps["accuracy"]["machine"], generated=datetime.date.today().isoformat())
    q = " --quick" if quick else ""
    files = [os.path.join(out, "performance.md"), os.path.join(out, "accuracy.md")]
    atomic_write_text(files[0], performance_md(out, q, m, total, scalings, reps["accuracy"], jsons) + "\n")
    atomic_write_text(files[1], accuracy_md(out, q, m, total, reps["accuracy"], reps["hardcases"], jsons[-2:]) + "\n")
    return dict(failures=[f for rep in [r for _, r in scalings] + list(reps.values()) for f in rep["failures"]],
                files=files)
