"""Time of the calls a user makes, idle and beside busy processes, for each thread setting.

    pyvf bench threads            # every call, setting and policy, idle and under load, and the
                                  # scaling with the paper sizes (about 14 minutes on 2 cores)
    pyvf bench threads --quick    # smaller batches, fewer repeats, no paper sizes (under a minute)
    pyvf bench threads --profile --calls codebook-paper --counts 1 16   # where the speed-up goes,
                                  # kernel by kernel (pyvf.bench.profile)

The calls: the demo's cached render + localization (TINY_TRANSFORMER, 4 scenes of 5 context views,
5 queries each, the scene encoded once beforehand), a codebook training step (TINY_CODEBOOK,
batch 16, Adam), a transformer training step (TINY_TRANSFORMER, batch 8 of 6 views, AdamW) and
Codebook.encode (32 images). The settings: pyvf's default (nothing set: what a user's script
gets), `pyvf.threads(n)` for n = 1..cores (pyvf's kernels and numpy's BLAS pool on n threads),
and numpy's BLAS on 1 thread with the kernels left at their default (what
OPENBLAS_NUM_THREADS=1 does). The conditions: idle, and under load: `cores` busy processes
(each a spinning Python loop, bounded in time and stopped at the end) on the same cores.

Before timing, every call runs once in every setting from the same weights and inputs: each
result must be finite and within RESULT_RTOL of the default's, and the table says which are
bitwise equal to it. The table gives each call's median time per setting and condition, the
best setting (the smallest median), and the default's time over the best's (the target: at most
1.1), the median of the rounds' ratios: each round times every setting back to back, 7 rounds
idle and 25 under load, where one call's time varies by 20% or more.

Two more measurements follow (skipped by `run(..., policies=False, scaling=False)`):
- The OpenMP runtime's waiting between parallel regions (WAIT_POLICIES): each choice in a worker
  process of its own (the runtime reads it when it loads), all alive at once and timed back to back
  in each round, the default setting's time of every call idle and under load.
- Scaling (SCALING_CALLS): the codebook's and the transformer's training steps at the shipped
  (tiny) and the paper's sizes, the evaluation's calls, and the machine's two ceilings (pyvf's
  GEMM, compute-bound, and its add of arrays far beyond the caches, memory-bound: what the
  cores give those kinds of work, which the steps' speed-ups are read against), at 1, 2, 4, ...
  up to every usable core; each from the same fresh model for every thread count, whose first
  step's result must be bitwise 1 thread's; after a second step untimed (a training loop's steady state: the first
  steps grow the heap to its high-water mark, page-faulting in what later steps reuse), the next
  ones are timed. Quick: the paper sizes left out, small batches.
"""

import contextlib
import os
import statistics
import subprocess
import sys
import time

import numpy as np

import pyvf
from pyvf.bench import codebook as _bench_codebook, transformer as _bench_transformer
from pyvf.bench.common import Worker, cpu_name, median_time, run_worker, table, worker_main
from pyvf._threads import affinity, blas_limit, blas_num_threads, cores, cpu_limits_text
from pyvf.nn.layers import add, matmul
from pyvf.train.loops import TINY_CODEBOOK, TINY_TRANSFORMER

MODULE = "pyvf.bench.threads"  # run_worker's module: __name__ is "__main__" where a worker runs this file
LOAD_SECONDS = 600  # a busy process stops by itself after this, should the benchmark die first
# repeat: rounds idle; loaded_repeat: beside the busy processes, whose scheduling makes one call
# vary by 20% or more
QUICK = dict(scenes=2, cb_batch=4, tf_batch=2, images=8, repeat=3, loaded_repeat=3)
# (25 rounds under load: with 15, the median ratio of two settings that run the same code, the
# default and BLAS 1 for the cached render, which has no BLAS product, still read 1.10, as far from
# 1 as the 10% the target allows)
FULL = dict(scenes=4, cb_batch=16, tf_batch=8, images=32, repeat=7, loaded_repeat=25)
LIMIT = 1.1  # the default's time may be at most this much over the best setting's
# pyvf's kernels and products give the same bits for any thread count (its models use no BLAS
# product), so every setting's result must be bitwise the default's; a result that is not fails
# the run. Beyond that, a non-finite result, or one further than this (normwise) from the
# default's, is reported as the larger failure it is.
RESULT_RTOL = 1e-4


def _transformer_inputs(batch, views, seed=0):
    cfg = TINY_TRANSFORMER
    rng = np.random.default_rng(seed)
    tokens = rng.integers(0, cfg.n_embeddings, (batch, views, cfg.token_image_size ** 2))
    poses = rng.normal(size=(batch, views, 7)).astype(np.float32)
    poses[..., 3:] = pyvf.quat_normalize(poses[..., 3:])
    return cfg, tokens, poses


def _fresh_step(prepare):
    """-> fn() taking one training step from a fresh model (prepare(): a scaling stepper's),
    returning the loss and the weights after it."""
    def fn():
        step, result = prepare()
        step()
        return result()
    return fn


def _render_localize(size):
    cfg, tokens, poses = _transformer_inputs(size, 10)
    model = pyvf.Transformer(cfg, seed=0)
    scene = model.encode_scene(tokens[:, :5], poses[:, :5])

    def fn():
        logits = model.render_scene(scene, poses[:, 5:])
        est = model.localize_scene(scene, tokens[:, 5:])
        return np.concatenate([logits.ravel(), est.ravel()])
    return fn


def _encode(size):
    cb = pyvf.Codebook(TINY_CODEBOOK, seed=0)
    S = TINY_CODEBOOK.image_size
    images = np.random.default_rng(1).uniform(-1, 1, (size, 3, S, S)).astype(np.float32)
    return lambda: cb.encode(images)


# name -> (maker(size) -> fn, which size of QUICK/FULL)
CALLS = {
    "render + localize, cached": (_render_localize, "scenes"),
    "codebook training step": (lambda size: _fresh_step(_codebook_stepper("tiny", size)), "cb_batch"),
    "transformer training step": (lambda size: _fresh_step(_transformer_stepper("tiny", size)), "tf_batch"),
    "Codebook.encode": (_encode, "images"),
}


def _setting(key):
    """A thread setting as a context: "default" (nothing set), n (pyvf.threads(n)), or "blas1"
    (numpy's BLAS on 1 thread, the kernels as they are; the limit holds from this call)."""
    if key == "default":
        return contextlib.nullcontext()
    return blas_limit(1) if key == "blas1" else pyvf.threads(key)


def settings(n_cores, n_affinity=None):
    """The settings compared: the default, 1..n_cores threads, the affinity's n_affinity CPUs where
    a CPU limit makes cores() fewer (what OpenMP and the BLAS would run by themselves), numpy's BLAS
    on one thread."""
    more = [n_affinity] if n_affinity is not None and n_affinity > n_cores else []
    return ["default", *range(1, n_cores + 1), *more, "blas1"]


def label(key):
    return {"default": "default", "blas1": "BLAS 1"}.get(key, f"{key} thr")


def check_results(fns, keys, log=print):
    """Run each call once in every setting from the same weights and inputs. -> ({call: {setting:
    True where bitwise equal to the default's result}}, failures): a failure is a result that is
    not bitwise the default's (saying how far, and whether beyond RESULT_RTOL or not finite)."""
    same, failures = {}, []
    for name, fn in fns.items():
        with _setting("default"):
            want = np.asarray(fn(), np.float64)
        same[name] = {"default": True}
        for key in keys[1:]:
            with _setting(key):
                got = np.asarray(fn(), np.float64)
            same[name][key] = bool(np.array_equal(got, want))
            if not same[name][key]:
                err = np.abs(got - want).max() / max(np.abs(want).max(), 1e-30) if np.isfinite(got).all() else np.inf
                how = "beyond the bound" if not err <= RESULT_RTOL else "within the bound, but not bitwise"
                failures.append(f"{name}: {label(key)} is {err:.2g} from the default's result ({how} {RESULT_RTOL})")
    return same, failures


class busy:
    """`with busy(n):` n processes spinning on the CPU (each stops by itself after LOAD_SECONDS),
    stopped when the block ends."""

    def __init__(self, n):
        self.n, self.procs = n, []

    def __enter__(self):
        code = f"import time\nt = time.time() + {LOAD_SECONDS}\nwhile time.time() < t: pass"
        self.procs = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(self.n)]
        time.sleep(0.2)  # let them start spinning
        return self

    def __exit__(self, *exc):
        for p in self.procs:
            p.kill()
        for p in self.procs:
            p.wait()
        return False


def rotated(keys, r):
    """keys starting r places further on (round r of a back-to-back comparison: no setting always
    follows the same one)."""
    r %= len(keys)
    return keys[r:] + keys[:r]


def time_all(fns, keys, repeat):
    """{call: {setting: [seconds of each round]}}: for each call, one warm-up per setting, then `repeat`
    rounds that time it once in every setting, so that a drift of the machine's speed (a busy
    process's scheduling, another program) reaches every setting alike; each round starts one
    setting further on, so that no setting always follows the same one (a setting's exit, such
    as the BLAS pool's limit lifted, can slow the next call)."""
    out = {}
    for name, fn in fns.items():
        times = {key: [] for key in keys}
        for r in range(repeat + 1):
            for key in rotated(keys, r):
                with _setting(key):
                    if r == 0:
                        fn()  # the warm-up
                    else:
                        times[key].append(median_time(fn, repeat=1, warmup=0)[0])
        out[name] = times
    return out


def medians(rounds):
    """{call: {setting: median seconds}} of time_all's rounds."""
    return {name: {key: statistics.median(t) for key, t in ts.items()} for name, ts in rounds.items()}


def configurations(keys):
    """{setting: [kernel threads, BLAS threads]} in effect inside each setting."""
    out = {}
    for key in keys:
        with _setting(key):
            out[str(key)] = [pyvf.num_threads(), blas_num_threads()]
    return out


def as_default(configs):
    """The settings that are the default's own configuration (the same kernel and BLAS threads:
    on 2 cores, "2 thr" and "BLAS 1" may be); [] without a record (reports from before it)."""
    if not configs:
        return []
    return [k for k, c in configs.items() if k != "default" and c == configs["default"]]


def default_over_best(ts, configs=None):
    """(the default's time over the best setting's, the best setting) for one call's rounds
    {setting: [s]}: the best is the setting of the smallest median; the ratio is the median of the
    rounds' ratios default / best, each pair timed back to back (a slow phase of the machine
    reaches both), not the ratio of two medians. A setting that is the default's configuration
    (as_default(configs)) is not a better setting: the smallest of several medians of one
    configuration is below its true time by the noise alone (measured here under load: the same
    configuration 1.13x apart), so it is not a candidate."""
    same = set(as_default(configs))
    best = min((k for k in ts if k not in same), key=lambda k: statistics.median(ts[k]))
    return statistics.median(d / b for d, b in zip(ts["default"], ts[best])), best


def rows_of(rounds, condition, keys, same, configs=None):
    """Table rows: the median time in ms per setting (* where the result is not bitwise the
    default's), the best setting and default_over_best."""
    rows = []
    for name, ts in rounds.items():
        ratio, best = default_over_best(ts, configs)
        rows.append([name, condition, *(f"{statistics.median(ts[k]) * 1e3:.1f}{'' if same[name][k] else '*'}"
                                        for k in keys), label(best), f"{ratio:.2f}"])
    return rows


def worst_default(rep):
    """(the default's largest default_over_best, the call, the condition) of a report's rounds."""
    conditions = (("idle", rep["idle_rounds"]), (f"beside {rep['cores']} busy processes", rep["loaded_rounds"]))
    configs = rep.get("configurations")
    return max((default_over_best(ts, configs)[0], name, cond) for cond, rounds in conditions
               for name, ts in rounds.items())


def configurations_note(configs):
    """Which settings are the default's configuration (and so not counted as better ones)."""
    same = as_default(configs)
    if not same:
        return ""
    k, b = configs["default"]
    return (f"; {', '.join(map(label, same))} {'is' if len(same) == 1 else 'are'} the default's "
            f"configuration here ({k} kernel threads, {b} BLAS thread{'s' if b != 1 else ''}), not counted as a "
            "better setting")



def bitwise_note(same):
    """What the table's * says, or that no result moved."""
    if all(all(v.values()) for v in same.values()):
        return "every setting's result is bitwise the default's"
    return "* the result is not bitwise the default's: a product left to NumPy's BLAS rounds otherwise on another thread count"


def run(quick=False, n_cores=None, log=print, policies=True, scaling=True, calls=True, scaling_calls=None,
        counts=None, save=None):
    """Measure every call idle and under load (unless calls=False), then (unless turned off) the
    waiting policies and the scaling (scaling_calls, counts: scale's calls and counts); -> report
    dict (times in seconds, failures). malloc's policy is a pyvf command's (reuse_freed_memory),
    also where a memory measurement of the same process turned it off. calls=False: the scaling
    alone, save(report) after each of its calls."""
    pyvf.reuse_freed_memory()
    size = QUICK if quick else FULL
    n_cores = n_cores or cores()
    if not calls:  # the scaling alone (`pyvf bench threads --scaling-only`): a larger machine's table
        log(f"# threads: {cpu_name()}, {n_cores} cores usable, kernel path {pyvf.kernel_path()}")
        report = {"failures": [], "cores": n_cores, "cpu": cpu_name(), "kernel_path": pyvf.kernel_path()}
        partial = (lambda sc: save(dict(report, scaling=sc, failures=sc["failures"]))) if save else None
        report["scaling"] = scale(quick, n_cores, log, scaling_calls, counts, partial)
        report["failures"] += report["scaling"]["failures"]
        return report
    keys = settings(n_cores, affinity())
    fns = {name: make(size[which]) for name, (make, which) in CALLS.items()}
    log(f"# threads: {cpu_name()}, {n_cores} cores usable ({cpu_limits_text()}), kernel path {pyvf.kernel_path()}; "
        f"default: {pyvf.num_threads()} kernel threads, {blas_num_threads()} BLAS threads")
    same, failures = check_results(fns, keys)
    configs = configurations(keys)
    if failures:
        for f in failures:
            log(f"FAILED: {f}")
        return {"failures": failures}
    idle = time_all(fns, keys, size["repeat"])
    with busy(n_cores):
        loaded = time_all(fns, keys, size["loaded_repeat"])
    header = ["call", "machine", *(f"{label(k)} (ms)" for k in keys), "best", "default / best"]
    rows = rows_of(idle, "idle", keys, same, configs) + rows_of(loaded, f"{n_cores} busy", keys, same, configs)
    log(table(header, rows))
    log(f"({bitwise_note(same)}{configurations_note(configs)})")
    report = {"failures": [], "cores": n_cores, "settings": [str(k) for k in keys], "idle": _jsonable(medians(idle)),
              "loaded": _jsonable(medians(loaded)), "idle_rounds": _jsonable(idle),
              "loaded_rounds": _jsonable(loaded), "bitwise_same": _jsonable(same), "configurations": configs,
              "cpu": cpu_name(), "kernel_path": pyvf.kernel_path()}
    report["worst_default_ratio"] = worst = worst_default(report)[0]
    log(f"# the default's worst ratio to the best setting: {worst:.2f} (target at most {LIMIT})")
    if policies:
        report["policies"] = wait_policies(quick, n_cores, log)
    if scaling:
        report["scaling"] = scale(quick, n_cores, log, scaling_calls, counts)
        report["failures"] += report["scaling"]["failures"]
    return report


def _jsonable(times):
    return {name: {str(k): v for k, v in t.items()} for name, t in times.items()}


# ---------------------------------------------------------------------------------------
# the OpenMP runtime's waiting between parallel regions

# libgomp's choices (pyvf's Linux build), each set in a worker process before the kernels load the
# runtime: sleep at once (what `import pyvf` sets unless the user set OMP_WAIT_POLICY or
# GOMP_SPINCOUNT), spin 300000 times first (libgomp's own default when nothing is set; its manual
# reckons about 3 ms, the time depends on the CPU), spin for minutes (ACTIVE).
WAIT_POLICIES = {"passive (pyvf)": {"OMP_WAIT_POLICY": "PASSIVE"},
                 "spin 10000": {"GOMP_SPINCOUNT": "10000"},
                 "spin 300000 (libgomp's default)": {"GOMP_SPINCOUNT": "300000"},
                 "active": {"OMP_WAIT_POLICY": "ACTIVE"}}
READY = "ready"


def _policy_worker(spec):
    """A waiting policy's worker (its environment chose the policy), alive for the whole comparison:
    every call prepared and run once, then READY printed; each call name read from standard input
    is timed once in pyvf's default setting and its seconds printed. -> (at the end of input) the
    policy variables it saw and its threads."""
    pyvf.reuse_freed_memory()  # malloc's policy as a pyvf command's
    size = QUICK if spec["quick"] else FULL
    fns = {name: make(size[which]) for name, (make, which) in CALLS.items()}
    for fn in fns.values():
        fn()
    print(READY, flush=True)
    for line in sys.stdin:
        print(median_time(fns[line.strip()], repeat=1, warmup=0)[0], flush=True)
    return {"env": {v: os.environ.get(v) for v in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")},
            "threads": pyvf.num_threads()}


def _policy_rounds(workers, rounds):
    """{call: {policy: [seconds of each round]}}: each round times every call once in every
    policy's worker, back to back, starting one worker further on each round (time_all's rounds,
    across processes)."""
    names = list(workers)
    out = {call: {name: [] for name in names} for call in CALLS}
    for r in range(rounds):
        for call in CALLS:
            for name in rotated(names, r):
                out[call][name].append(float(workers[name].ask(call)))
    return out


def wait_policies(quick, n_cores, log=print):
    """{policy: {"idle_rounds": {call: [s]}, "loaded_rounds": ..., "env", "threads"}} for each of
    WAIT_POLICIES, and the table (policy_table). The runtime reads its policy when it loads, so each
    policy has a worker process of its own; all of them stay alive (each stopped while another is
    timed), and every round times each call in each of them back to back (time_all's method: a
    slow phase of the machine reaches every policy alike), idle and then beside n_cores busy
    processes."""
    size = QUICK if quick else FULL
    clear = {"OMP_WAIT_POLICY": None, "GOMP_SPINCOUNT": None}  # the parent's choice must not leak in
    with contextlib.ExitStack() as stack:
        # each stopped while the others are timed (a spinning policy's threads would take their cores)
        workers = {name: stack.enter_context(Worker(MODULE, {"quick": quick}, env={**clear, **env}, stopped=True))
                   for name, env in WAIT_POLICIES.items()}
        for name, w in workers.items():
            if w.read() != READY:
                raise RuntimeError(f"the worker of waiting policy {name!r} did not start")
        idle = _policy_rounds(workers, size["repeat"])
        with busy(n_cores):
            loaded = _policy_rounds(workers, size["loaded_repeat"])
        out = {name: dict(w.finish(), idle_rounds={c: t[name] for c, t in idle.items()},
                          loaded_rounds={c: t[name] for c, t in loaded.items()}) for name, w in workers.items()}
    log(table(*policy_table(out, n_cores)))
    return out


def over_fastest(policies, cond, call):
    """{policy: its time over the fastest policy's} for one call and condition ("idle" or
    "loaded"): the median of the rounds' ratios, each round's fastest policy the reference (as
    default_over_best)."""
    rounds = {name: p[f"{cond}_rounds"][call] for name, p in policies.items()}
    fastest = [min(ts) for ts in zip(*rounds.values())]
    return {name: statistics.median(t / f for t, f in zip(ts, fastest)) for name, ts in rounds.items()}


def policy_table(policies, n_cores):
    """(header, rows) of the waiting policies' times: each call's median ms per policy, and its
    time over the fastest policy's (over_fastest)."""
    names = list(policies)
    rows = []
    for cond, label_ in (("idle", "idle"), ("loaded", f"{n_cores} busy")):
        for call in policies[names[0]][f"{cond}_rounds"]:
            ratio = over_fastest(policies, cond, call)
            rows.append([call, label_, *(f"{statistics.median(policies[n][f'{cond}_rounds'][call]) * 1e3:.1f} "
                                         f"({ratio[n]:.2f})" for n in names)])
    return ["call", "machine", *(f"{n}: ms (/ fastest)" for n in names)], rows


# ---------------------------------------------------------------------------------------
# scaling: 1 thread to every core


def _codebook_stepper(config, batch):
    """-> prepare() -> (step, result): a fresh codebook and Adam; step() takes one training step,
    result() -> the last step's loss and the weights (outside the timed step)."""
    def prepare():
        cfg, cb, images = (_bench_codebook.setup("paper", batch=batch) if config == "paper" else
                           (TINY_CODEBOOK, pyvf.Codebook(TINY_CODEBOOK, seed=0), np.random.default_rng(0).uniform(
                               -1, 1, (batch, 3, TINY_CODEBOOK.image_size, TINY_CODEBOOK.image_size)).astype(np.float32)))
        opt = pyvf.Adam(cb.params, 1e-3)

        last = {}

        def step():
            last["loss"] = pyvf.codebook_train_step(cb, opt, images).loss
        return step, lambda: np.concatenate([[last["loss"]], *(p.ravel() for p in cb.params.values())])
    return prepare


def _transformer_stepper(config, batch):
    def prepare():
        if config == "paper":
            _, _, tokens, poses, model = _bench_transformer.setup("paper")
        else:
            cfg, tokens, poses = _transformer_inputs(batch, TINY_TRANSFORMER.sequence_size)
            model = pyvf.Transformer(cfg, seed=0)
        opt = pyvf.AdamW(model.params, lr=1e-4, weight_decay=0.01)

        last = {}

        def step():
            last["loss"] = pyvf.train_step(model, opt, tokens, poses, max_grad_norm=1.0)[0]
        return step, lambda: np.concatenate([[last["loss"]], *(p.ravel() for p in model.params.values())])
    return prepare


def _stateless(make, size):
    """A call without state (CALLS' makers) -> prepare() -> (step, result): its inputs made at each
    prepare (not while other calls run), step() keeping its output for result()."""
    def prepare():
        fn, last = make(size), {}

        def step():
            last["out"] = fn()
        return step, lambda: last["out"]
    return prepare


def _gemm(n):
    """pyvf's GEMM (pyvf.nn.layers.matmul) of two (n, n) float32 matrices: compute-bound work of
    the training steps' kind (their convolutions and products run the same register tiles), so its
    speed-up is what the machine's cores give such work: the ceiling of the steps' speed-ups."""
    a, b = np.random.default_rng(2).standard_normal((2, n, n), dtype=np.float32)
    c, want = matmul(a, b)[:64], a[:64].astype(np.float64) @ b  # validated on 64 rows before timing
    # each element one float32 sum of n products: normwise within n u of float64 (unit normal inputs)
    if not np.linalg.norm(c - want) <= n * 2.0 ** -24 * np.linalg.norm(want):
        raise AssertionError(f"ceiling: pyvf's GEMM of n = {n} is {np.linalg.norm(c - want) / np.linalg.norm(want):.3g} "
                             "from float64 normwise")
    return lambda: matmul(a, b)


def _stream(mib):
    """pyvf's add (pyvf.nn.layers.add) of two float32 arrays of `mib` MiB each into a third, made
    once: memory-bound (12 bytes moved per addition), its speed-up the machine's memory bandwidth
    over one core's, the ceiling of the passes that only stream (Adam, GroupNorm, the adds)."""
    a, b = np.random.default_rng(3).standard_normal((2, mib << 18), dtype=np.float32)  # no float64 copy
    out = np.empty_like(a)
    if not np.array_equal(add(a, b, out=out), a + b):  # one rounding each: bitwise NumPy's, checked before timing
        raise AssertionError("ceiling: pyvf's add is not bitwise NumPy's a + b")
    return lambda: add(a, b, out=out)


# name -> (maker(quick) -> prepare, whether quick mode runs it); prepare() -> (step, result)
SCALING_CALLS = {  # (the tiny batches: 4 and 2 in quick mode)
    "codebook step, tiny": (lambda q: _codebook_stepper("tiny", 4 if q else 16), True),
    "transformer step, tiny": (lambda q: _transformer_stepper("tiny", 2 if q else 8), True),
    "codebook step, paper (batch 2)": (lambda q: _codebook_stepper("paper", 2), False),
    "transformer step, paper (1 x 20 views)": (lambda q: _transformer_stepper("paper", 1), False),
    "render + localize, cached": (lambda q: _stateless(_render_localize, 2 if q else 4), True),
    "Codebook.encode": (lambda q: _stateless(_encode, 8 if q else 32), True),
    # the machine's ceilings: what its cores give compute-bound and memory-bound work
    # (GEMM of n = 2048, add of 2 x 256 MiB; quick: 512 and 2 x 16 MiB)
    "ceiling: compute (GEMM)": (lambda q: _stateless(_gemm, 512 if q else 2048), True),
    "ceiling: memory (add)": (lambda q: _stateless(_stream, 16 if q else 256), True),
}
# the names `pyvf bench threads --calls` takes
SCALING_IDS = dict(zip(("codebook-tiny", "transformer-tiny", "codebook-paper", "transformer-paper", "render",
                        "encode", "gemm", "stream"), SCALING_CALLS))
CEILING = "ceiling: "  # the names of the machine's ceilings start so
PAPER_SPEEDUP_2 = 1.8  # the paper-size steps on 2 threads against 1 (target)


def prepared(prepare):
    """A scaling call (prepare(): SCALING_CALLS') made ready to time: a fresh model, its first step
    (whose result the bitwise comparison across thread counts takes) and a second step untimed
    (the warm-up: a training loop's steady state, its heap and page tables at their high-water
    mark) -> (step, the first step's result as float64)."""
    step, result = prepare()
    step()
    got = np.asarray(result(), np.float64)
    step()
    return step, got


def thread_counts(n_cores):
    """1, 2, 4, ... below n_cores, then n_cores."""
    out, n = [], 1
    while n < n_cores:
        out.append(n)
        n *= 2
    return out + [n_cores]


def scale(quick, n_cores, log=print, calls=None, counts=None, save=None):
    """Each SCALING_CALLS call (or those of `calls`, SCALING_IDS names) at every thread_counts(n_cores)
    (or `counts`), in rounds over the counts: a fresh model (prepared untimed), its first step
    (untimed: its result must be bitwise the first count's) and a second one untimed (the warm-up:
    heap and page tables at their steady state), then its next steps timed. save(report), when
    given, is called after each call (a long run killed part-way keeps the calls it finished).
    -> {"threads", "times": {call: {n: median s}}, "bitwise": {call: bool}, "failures"}."""
    counts = sorted(set(counts)) if counts else thread_counts(n_cores)
    chosen = [SCALING_IDS[c] for c in calls] if calls else list(SCALING_CALLS)
    calls = {name: SCALING_CALLS[name][0](quick) for name in chosen if SCALING_CALLS[name][1] or not quick}
    times, bitwise, failures = {}, {}, []

    def report():
        return {"threads": counts, "times": _jsonable(times), "bitwise": dict(bitwise), "failures": list(failures)}
    for name, prepare in calls.items():
        # rounds x timed steps per thread count: the paper sizes' steps take seconds to a minute,
        # and vary by 10 to 20% on a shared machine, where a slow minute can fall on one count:
        # three rounds over the counts, one timed step each (the median of three drops one slow
        # round; two rounds' median, their mean, read 1.79x where a run of the scaling alone read 1.98x)
        rounds, timed = (3, 1) if "paper" in name else (3 if quick else 5, 1)
        t, want = {n: [] for n in counts}, None
        for _ in range(rounds):
            for n in counts:
                with pyvf.threads(n):
                    step, got = prepared(prepare)
                    for _ in range(timed):
                        t0 = time.perf_counter()
                        step()
                        t[n].append(time.perf_counter() - t0)
                want = got if want is None else want
                if not np.array_equal(got, want) and bitwise.get(name, True):
                    failures.append(f"scaling: {name} on {n} threads is not bitwise its result on {counts[0]}")
                bitwise[name] = bitwise.get(name, True) and bool(np.array_equal(got, want))
        times[name] = {n: statistics.median(v) for n, v in t.items()}
        log(f"# {name}: " + ", ".join(f"{n} thr {v * 1e3:.0f} ms" for n, v in times[name].items()))
        if save:
            save(report())
    rep = report()
    log(table(*scaling_table(rep)))
    for line in scaling_targets(rep):
        log("# " + line)
    return rep


def scaling_table(rep):
    """(header, rows): each call's median time per thread count and its speed-up over the first
    count ("-" where a call was not run at a count)."""
    counts = [str(n) for n in rep["threads"]]
    rows = []
    for name, t in rep["times"].items():
        first = t.get(counts[0])
        rows.append([name, *(f"{t[n] * 1e3:.0f} ms" + (f" ({first / t[n]:.2f}x)" if first else "") if n in t else "-"
                             for n in counts),
                     "yes" if rep["bitwise"][name] else "NO"])
    return ["call", *(f"{n} thr (speed-up)" for n in counts), "bitwise the same"], rows


MANY_CORES = 16  # the many-core targets: on 16 threads against 1, paper-size steps and tiny ones
MANY_SPEEDUP = {"paper": 8.0, "tiny": 4.0}


def many_core_targets(rep):
    """The training steps' speed-up on MANY_CORES threads against 1 and its target (when both
    counts were run); -> [(line, met)]."""
    out = []
    for name, t in rep["times"].items():
        size = next((k for k in MANY_SPEEDUP if k in name), None)
        if size and "step" in name and "1" in t and str(MANY_CORES) in t:
            up = t["1"] / t[str(MANY_CORES)]
            out.append((f"{name}: {up:.2f}x on {MANY_CORES} threads (target at least {MANY_SPEEDUP[size]:g})",
                        up >= MANY_SPEEDUP[size]))
    return out


def ceilings_text(rep, n):
    """The machine's ceilings' speed-ups on n threads against 1 ("compute (GEMM) 9.81x, memory (add)
    4.02x"), "" where neither was run at both counts."""
    return ", ".join(f"{name[len(CEILING):]} {t['1'] / t[str(n)]:.2f}x" for name, t in rep["times"].items()
                     if name.startswith(CEILING) and "1" in t and str(n) in t)


def merge_scaling(reports):
    """Scaling reports of one machine (`--scaling-only` runs, each of some calls and counts) as one:
    the counts' union, each call's times (a later report's cells replace an earlier one's), bitwise
    only if every run found it so."""
    counts, times, bitwise = set(), {}, {}
    for rep in reports:
        sc = rep["scaling"]
        counts |= set(sc["threads"])
        for name, t in sc["times"].items():
            times.setdefault(name, {}).update(t)
            bitwise[name] = bitwise.get(name, True) and sc["bitwise"][name]
    order = list(SCALING_CALLS)
    times = {n: times[n] for n in sorted(times, key=lambda n: order.index(n) if n in order else len(order))}
    return {"threads": sorted(counts), "times": times, "bitwise": {n: bitwise[n] for n in times}}


def scaling_targets(rep):
    """The paper-size steps' speed-up on 2 threads against the target (when 2 threads were run)."""
    if "2" not in rep["times"][next(iter(rep["times"]))]:
        return []
    return [f"{name}: {t['1'] / t['2']:.2f}x on 2 threads (target at least {PAPER_SPEEDUP_2})"
            for name, t in rep["times"].items() if "paper" in name]


def _worker(spec):
    """run_worker's (and Worker's) entry: the whole run (spec["whole"]: `pyvf bench report`
    measures the threads in a fresh process, as a user's, not after its other runs grew its heap by
    gigabytes), its log on stderr; else a waiting policy's worker."""
    if spec.get("whole"):
        return run(spec["quick"], spec["cores"], log=lambda *a, **k: print(*a, file=sys.stderr, **k))
    return _policy_worker(spec)


if __name__ == "__main__":  # pragma: no cover - run_worker's other end; `pyvf bench threads` runs the benchmark
    worker_main(_worker)
