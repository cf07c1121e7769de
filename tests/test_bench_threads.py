"""pyvf.bench.threads's parts: the busy processes stop, a result that depends on the thread
setting is caught, and the cores counted are the process's affinity. (Its quick run from a
temporary folder is in test_cli.py.)"""

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
    keys = bench.settings(2)
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


def test_cores_are_the_process_affinity(monkeypatch):
    assert pyvf._threads.cores() == len(os.sched_getaffinity(0))
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {3})
    assert pyvf._threads.cores() == 1


@pytest.mark.parametrize("n", [1, 2])
def test_blas_limit_sets_and_restores(n):
    before = pyvf._threads.blas_num_threads()
    with pyvf._threads.blas_limit(n):
        assert pyvf._threads.blas_num_threads() == n
    assert pyvf._threads.blas_num_threads() == before
