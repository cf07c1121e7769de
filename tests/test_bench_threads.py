"""pyvf.bench.threads's parts: the busy processes stop, a result that depends on the thread
setting is caught. (Its quick run from a temporary folder is in test_cli.py; the cores it counts,
pyvf._threads.cores(), in test_threads.py.)"""

import os

import numpy as np
import pytest

import pyvf
from pyvf.bench import threads as bench


def test_busy_processes_spin_then_stop():
    with bench.busy(2) as load:
        assert len(load.procs) == 2 and all(p.poll() is None for p in load.procs)
    assert all(p.returncode is not None for p in load.procs)


def test_check_results_catches_a_result_that_depends_on_the_threads():
    assert bench.settings(2, 16) == ["default", 1, 2, 16, "blas1"]  # a CPU limit of 2 on 16 CPUs
    keys = bench.settings(2, 2)
    assert keys == ["default", 1, 2, "blas1"]
    base = pyvf.num_threads()
    fns = {"steady": lambda: np.arange(4.0),
           "planted": lambda: np.array([1.0 + (pyvf.num_threads() != base)])}  # moves with the kernels' threads
    same, failures = bench.check_results(fns, keys)
    assert same["steady"] == {k: True for k in keys}
    moved = [k for k in keys if not same["planted"][k]]
    assert moved == [k for k in (1, 2) if k != base]  # the settings that change the kernels' threads
    assert failures and all(f.startswith("planted:") for f in failures)
    assert pyvf.num_threads() == base  # every setting put back


@pytest.mark.parametrize("n", [1, 2])
def test_blas_limit_sets_and_restores(n):
    before = pyvf._threads.blas_num_threads()
    with pyvf._threads.blas_limit(n):
        assert pyvf._threads.blas_num_threads() == n
    assert pyvf._threads.blas_num_threads() == before


@pytest.mark.parametrize("n, want", [(1, [1]), (2, [1, 2]), (6, [1, 2, 4, 6]), (16, [1, 2, 4, 8, 16])])
def test_thread_counts(n, want):
    assert bench.thread_counts(n) == want


def test_scale_catches_a_result_that_depends_on_the_threads(monkeypatch):
    """A call whose result moves with the thread count fails the scaling (the paper sizes are left
    out of quick mode: only the two fake calls run); a steady one passes, and the table shows the
    speed-up of the recorded times."""
    def fake(result):
        def prepare():
            return (lambda: None), result
        return lambda quick: prepare
    monkeypatch.setattr(bench, "SCALING_CALLS", {
        "steady": (fake(lambda: np.arange(3.0)), True),
        "planted": (fake(lambda: np.array([float(pyvf.num_threads())])), True),
        "paper, not in quick": (fake(lambda: 1 / 0), False)})
    rep = bench.scale(True, 2, log=lambda *a: None)
    assert rep["bitwise"] == {"steady": True, "planted": False}
    assert rep["failures"] == ["scaling: planted on 2 threads is not bitwise its result on 1"]
    assert rep["threads"] == [1, 2]


def test_scale_runs_the_chosen_calls_and_counts_and_saves_after_each(monkeypatch):
    """--calls and --counts choose the scaling's calls (by SCALING_IDS name, run in that order) and
    thread counts;
    save(report) is called after each call with the calls finished so far (a run killed part-way
    keeps them)."""
    def fake(result):
        return lambda quick: (lambda: ((lambda: None), result))
    calls = {"a step, tiny": (fake(lambda: np.zeros(2)), True), "b step, tiny": (fake(lambda: np.ones(2)), True),
             "c": (fake(lambda: 1 / 0), True)}
    monkeypatch.setattr(bench, "SCALING_CALLS", calls)
    monkeypatch.setattr(bench, "SCALING_IDS", {"a": "a step, tiny", "b": "b step, tiny", "c": "c"})
    saved = []
    rep = bench.scale(True, 2, log=lambda *a: None, calls=["b", "a"], counts=[2, 1, 2],
                      save=lambda r: saved.append(sorted(r["times"])))
    assert rep["threads"] == [1, 2] and list(rep["times"]) == ["b step, tiny", "a step, tiny"]  # as asked
    assert saved == [["b step, tiny"], ["a step, tiny", "b step, tiny"]]


def test_merge_scaling_and_many_core_targets():
    """Two runs of one machine (some calls at some counts each) merge into one table: the counts'
    union, "-" where a call was not run, a call bitwise only if every run found it so; the
    16-thread targets (paper steps 8x, tiny 4x) read off the merged times, a miss reported."""
    one = {"scaling": {"threads": [1, 2, 16], "bitwise": {"codebook step, tiny": True, "Codebook.encode": True},
                       "times": {"codebook step, tiny": {"1": 1.0, "2": 0.5, "16": 0.2},
                                 "Codebook.encode": {"1": 0.4, "2": 0.2, "16": 0.1}}}}
    two = {"scaling": {"threads": [1, 16], "bitwise": {"transformer step, paper (1 x 20 views)": False},
                       "times": {"transformer step, paper (1 x 20 views)": {"1": 30.0, "16": 5.0}}}}
    merged = bench.merge_scaling([two, one])
    assert merged["threads"] == [1, 2, 16]
    assert list(merged["times"]) == ["codebook step, tiny", "transformer step, paper (1 x 20 views)",
                                     "Codebook.encode"]  # SCALING_CALLS' order
    _, rows = bench.scaling_table(merged)
    assert rows[1] == ["transformer step, paper (1 x 20 views)", "30000 ms (1.00x)", "-", "5000 ms (6.00x)", "NO"]
    assert bench.many_core_targets(merged) == [
        ("codebook step, tiny: 5.00x on 16 threads (target at least 4)", True),
        ("transformer step, paper (1 x 20 views): 6.00x on 16 threads (target at least 8)", False)]


def test_the_ceilings_are_validated_pyvf_kernels_bitwise_across_threads():
    """The machine's ceilings (quick sizes): pyvf's GEMM and add, each validated when made (the GEMM
    within n u of float64 on 64 rows, the add bitwise NumPy's), bitwise the same on 1 and 2 threads;
    ceilings_text reads their speed-ups and nothing else."""
    rep = bench.scale(True, 2, log=lambda *a: None, calls=["gemm", "stream"])
    assert list(rep["times"]) == ["ceiling: compute (GEMM)", "ceiling: memory (add)"]
    assert rep["bitwise"] == {"ceiling: compute (GEMM)": True, "ceiling: memory (add)": True}
    made = {"threads": [1, 16], "bitwise": {}, "times": {"ceiling: compute (GEMM)": {"1": 1.0, "16": 0.1},
            "ceiling: memory (add)": {"1": 1.0, "16": 0.4}, "codebook step, tiny": {"1": 1.0, "16": 0.5}}}
    assert bench.ceilings_text(made, 16) == "compute (GEMM) 10.00x, memory (add) 2.50x"
    assert bench.ceilings_text(made, 8) == ""


def test_a_wrong_gemm_is_refused_before_timing(monkeypatch):
    """The compute ceiling checks its product: a GEMM that transposes b (a planted bug) raises."""
    monkeypatch.setattr(bench, "matmul", lambda a, b: np.ascontiguousarray(a @ b.T))
    with pytest.raises(AssertionError, match="GEMM of n = 512"):
        bench._gemm(512)


def test_scaling_table_and_targets_on_made_up_times():
    rep = {"threads": [1, 2], "bitwise": {"transformer step, paper": True, "Codebook.encode": False},
           "times": {"transformer step, paper": {"1": 30.0, "2": 15.0}, "Codebook.encode": {"1": 0.2, "2": 0.125}}}
    header, rows = bench.scaling_table(rep)
    assert header == ["call", "1 thr (speed-up)", "2 thr (speed-up)", "bitwise the same"]
    assert rows == [["transformer step, paper", "30000 ms (1.00x)", "15000 ms (2.00x)", "yes"],
                    ["Codebook.encode", "200 ms (1.00x)", "125 ms (1.60x)", "NO"]]
    assert bench.scaling_targets(rep) == ["transformer step, paper: 2.00x on 2 threads (target at least 1.8)"]


def test_policy_table_on_made_up_times():
    """ms: each policy's median; (/ fastest): the median of the rounds' ratios to each round's
    fastest policy."""
    pol = {"passive": {"idle_rounds": {"a": [0.012, 0.012, 0.030]}, "loaded_rounds": {"a": [0.020, 0.020, 0.020]}},
           "spin": {"idle_rounds": {"a": [0.010, 0.010, 0.010]}, "loaded_rounds": {"a": [0.050, 0.010, 0.050]}}}
    header, rows = bench.policy_table(pol, 2)
    assert header == ["call", "machine", "passive: ms (/ fastest)", "spin: ms (/ fastest)"]
    assert rows == [["a", "idle", "12.0 (1.20)", "10.0 (1.00)"], ["a", "2 busy", "20.0 (1.00)", "50.0 (2.50)"]]


def test_each_policy_runs_in_its_own_environment_all_timed_in_every_round(monkeypatch):
    """Real workers (quick sizes): each sees exactly its policy's variables (the parent's are
    removed), every call is timed in every worker in each round, idle and loaded, and the table
    has a row per call and condition."""
    monkeypatch.setattr(bench, "WAIT_POLICIES", {"passive": {"OMP_WAIT_POLICY": "PASSIVE"},
                                                 "spin 1000": {"GOMP_SPINCOUNT": "1000"}})
    monkeypatch.setattr(bench, "QUICK", dict(bench.QUICK, repeat=2, loaded_repeat=1))
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    logged = []
    out = bench.wait_policies(True, 1, log=logged.append)
    assert out["passive"]["env"] == {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": None}
    assert out["spin 1000"]["env"] == {"OMP_WAIT_POLICY": None, "GOMP_SPINCOUNT": "1000"}
    for p in out.values():
        assert set(p["idle_rounds"]) == set(p["loaded_rounds"]) == set(bench.CALLS)
        assert all(len(t) == 2 for t in p["idle_rounds"].values()) and all(
            len(t) == 1 for t in p["loaded_rounds"].values())
        assert all(s > 0 for t in p["idle_rounds"].values() for s in t)
    assert len(logged) == 1 and logged[0].count("\n") == 2 + 2 * len(bench.CALLS) - 1


def test_a_stopped_worker_is_stopped_between_answers_and_finishes():
    """Worker(stopped=True): between its answers the process is stopped (state T, taking no CPU
    while other workers are timed), it answers when asked, and finish() resumes it for its result."""
    from pyvf.bench.common import Worker

    def state(pid):  # the process's state letter, once a signal sent just now has taken effect (within 2 s)
        import time
        for _ in range(200):
            with open(f"/proc/{pid}/stat") as f:
                s = f.read().rsplit(")", 1)[1].split()[0]
            if s == "T":
                break
            time.sleep(0.01)
        return s
    with Worker("pyvf.bench.threads", {"quick": True}, env={"GOMP_SPINCOUNT": "1000"}, stopped=True) as w:
        assert w.read() == bench.READY and state(w.proc.pid) == "T"
        assert float(w.ask("Codebook.encode")) > 0 and state(w.proc.pid) == "T"
        assert w.finish()["env"]["GOMP_SPINCOUNT"] == "1000"


def test_a_worker_that_dies_is_an_error_naming_it():
    """A worker whose process ends before it answers: RuntimeError with its command and its
    standard error, and nothing left running."""
    from pyvf.bench.common import Worker
    with pytest.raises(RuntimeError, match="(?s)worker.*failed.*KeyError"):
        with Worker("pyvf.bench.threads", {"quick": True}) as w:
            assert w.read() == bench.READY
            w.ask("no such call")
    assert w.proc.poll() is not None


@pytest.mark.parametrize("env, want", [({}, "PASSIVE"), ({"GOMP_SPINCOUNT": "1000"}, None),
                                       ({"OMP_WAIT_POLICY": "ACTIVE"}, "ACTIVE")])
def test_import_sets_passive_waiting_unless_chosen(env, want):
    import json
    import subprocess
    import sys
    child = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    code = "import os, json, pyvf; print(json.dumps(os.environ.get('OMP_WAIT_POLICY')))"
    holds = os.path.dirname(os.path.dirname(pyvf.__file__))
    out = subprocess.run([sys.executable, "-c", code], env={**child, **env}, capture_output=True, text=True,
                         cwd=holds, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == want


def test_run_worker_removes_a_variable_given_none(monkeypatch):
    """With OMP_WAIT_POLICY set here, the worker, told None for it, must not see it, and sees the
    spin count it was given (a policy worker run to completion: its input is empty, so it answers
    nothing and returns what it saw)."""
    from pyvf.bench.common import run_worker
    monkeypatch.setenv("OMP_WAIT_POLICY", "PASSIVE")
    got = run_worker("pyvf.bench.threads", {"quick": True}, env={"OMP_WAIT_POLICY": None, "GOMP_SPINCOUNT": "1000"})
    assert got["env"] == {"OMP_WAIT_POLICY": None, "GOMP_SPINCOUNT": "1000"}


def test_kernels_see_a_busy_machine_and_give_the_same_results(rng):
    """With a busy process of pyvf's priority on every usable core, pyvf's threads wait on the run
    queue: oversubscribed() turns True within two seconds of kernel calls (it reads the calling
    thread's /proc/self/task/<tid>/schedstat at most every 50 ms; where there is no /proc it stays
    False); the product is bitwise the same as on the quiet machine (short calls then run on one
    thread)."""
    import time
    from pyvf import _core
    from pyvf.nn.layers import matmul
    x = rng.standard_normal((128, 256)).astype(np.float32)
    want = matmul(x, x.T)
    seen = False
    with bench.busy(pyvf._threads.cores()):
        t0 = time.perf_counter()
        while not seen and time.perf_counter() - t0 < 2.0:
            np.testing.assert_array_equal(matmul(x, x.T), want)
            seen = _core.oversubscribed()
    assert seen == os.path.exists("/proc/self/task"), "busy processes on every core were not noticed"


@pytest.mark.skipif(pyvf._threads.cores() < 2,
                    reason="needs two usable CPUs (affinity and CPU limit): one for the caller, one for the others")
def test_waits_of_other_threads_are_not_a_busy_machine():
    """Only the calling thread's run-queue waits count: the kernels' other threads wait on a run
    queue at each wake-up from sleep between regions (15 wake-ups a region on 16 threads, on an idle
    machine), which must not make short calls single-threaded. Here three threads of this process
    share one CPU (each waits two thirds of the time) while the caller, alone on another, calls a
    kernel for two seconds: oversubscribed() stays False (counting every thread's waits, it read
    True 97% of the time). A half is allowed for some other process that takes the caller's CPU
    for a moment."""
    import threading
    import time
    from pyvf import _core
    from pyvf.nn.layers import matmul
    mine = os.sched_getaffinity(0)
    cpu, other = sorted(mine)[:2]
    stop = time.perf_counter() + 3.0

    def crowd():  # np.sort releases the GIL: three threads runnable on one CPU
        os.sched_setaffinity(0, {other})  # pid 0: this thread only
        r = np.random.default_rng(0).standard_normal(2_000_000)
        while time.perf_counter() < stop:
            np.sort(r)
    threads = [threading.Thread(target=crowd) for _ in range(3)]
    x = np.random.default_rng(1).standard_normal((128, 256)).astype(np.float32)
    seen = []
    os.sched_setaffinity(0, {cpu})
    try:
        for t in threads:
            t.start()
        with pyvf.threads(1):
            t0 = time.perf_counter()
            while time.perf_counter() - t0 < 2.0:
                matmul(x, x.T)
                seen.append(_core.oversubscribed())
    finally:
        for t in threads:
            t.join()
        os.sched_setaffinity(0, mine)
    assert np.mean(seen) < 0.5, f"other threads' waits read as a busy machine in {np.mean(seen):.0%} of the calls"
