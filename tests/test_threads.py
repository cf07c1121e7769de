"""pyvf's thread setting (pyvf/_threads.py): the setting made at import (PYVF_NUM_THREADS), a count
that holds for every path module and every Python thread, and inference calls made from several
Python threads at once."""

import argparse
import threading

import numpy as np
import pytest

import pyvf
from pyvf import _core, _threads


def blas_threads():
    from threadpoolctl import threadpool_info
    return max(p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas")


@pytest.fixture
def restore_threads():
    from threadpoolctl import threadpool_limits
    kernels, blas = pyvf.num_threads(), blas_threads()
    yield
    pyvf.set_num_threads(kernels)
    threadpool_limits(limits=blas, user_api="blas")


def test_set_from_environment(restore_threads):
    """At import: PYVF_NUM_THREADS sets the kernels and numpy's BLAS; without it nothing is set."""
    assert _threads.set_from_environment({"PYVF_NUM_THREADS": " 3 "}) == 3
    assert pyvf.num_threads() == 3 and blas_threads() == 3
    assert _threads.set_from_environment({"OMP_NUM_THREADS": "4"}) is None
    assert pyvf.num_threads() == 3  # left as it was


def test_the_count_holds_for_every_path_and_python_thread(restore_threads):
    seen = {}
    for n in (1, 3):
        pyvf.set_num_threads(n)
        previous = _core.current_path()
        try:
            for path in _core.available_paths():
                _core.use_path(path)
                t = threading.Thread(target=lambda: seen.__setitem__((n, path), pyvf.num_threads()))
                t.start()
                t.join()
        finally:
            _core.use_path(previous)
    assert seen == {(n, p): n for n in (1, 3) for p in _core.available_paths()}


def test_inference_from_several_python_threads_at_once():
    """A server's pattern: one model, one encoded scene, calls from several Python threads at once
    (the kernels release the GIL, so their OpenMP teams run side by side): every render,
    localization and encoding is bitwise the one made alone."""
    import numpy as np
    from pyvf.train.loops import TINY_CODEBOOK, TINY_TRANSFORMER
    cfg = TINY_TRANSFORMER
    rng = np.random.default_rng(0)
    tokens = rng.integers(0, cfg.n_embeddings, (2, 8, cfg.token_image_size ** 2))
    poses = rng.normal(size=(2, 8, 7)).astype(np.float32)
    poses[..., 3:] = pyvf.quat_normalize(poses[..., 3:])
    model = pyvf.Transformer(cfg, seed=0)
    scene = model.encode_scene(tokens[:, :4], poses[:, :4])
    codebook = pyvf.Codebook(TINY_CODEBOOK, seed=0)
    S = TINY_CODEBOOK.image_size
    images = np.random.default_rng(1).uniform(-1, 1, (4, 3, S, S)).astype(np.float32)

    def job(i):
        q = np.s_[:, 4 + i % 4: 5 + i % 4]
        return (model.render_scene(scene, poses[q]), model.localize_scene(scene, tokens[q]),
                codebook.encode(images[i % 4: i % 4 + 1]))

    alone = [job(i) for i in range(6)]
    together = [None] * len(alone)
    workers = [threading.Thread(target=lambda i=i: together.__setitem__(i, job(i))) for i in range(len(alone))]
    for w in workers:
        w.start()
    for w in workers:
        w.join()
    for i, (a, b) in enumerate(zip(alone, together)):
        assert b is not None, f"call {i} raised"
        for what, x, y in zip(("render", "localize", "encode"), a, b):
            assert np.array_equal(np.asarray(x), np.asarray(y)), f"call {i}: {what} differs run beside the others"


# a count beyond MAX_THREADS was accepted, and the next parallel kernel ended the process (OpenMP
# cannot create them under the process's limits); bools are not counts
@pytest.mark.parametrize("bad", [0, -1, 1.5, "2", True, np.bool_(True), np.uint64(2 ** 31), _threads.MAX_THREADS + 1])
@pytest.mark.parametrize("call", [pyvf.set_num_threads, pyvf.threads], ids=["set_num_threads", "threads"])
def test_refusals_name_the_argument(call, bad, restore_threads):
    n0 = pyvf.num_threads()
    with pytest.raises((TypeError, ValueError), match=r"\bn\b"):
        call(bad)
    assert pyvf.num_threads() == n0


# superscript digits are digits to str.isdigit but not to int()
@pytest.mark.parametrize("value", ["0", "two", "-1", "1.5", str(2 ** 31), str(_threads.MAX_THREADS + 1), "³", "¹⁰"])
def test_malformed_thread_variable_is_named(value):
    with pytest.raises(ImportError, match="PYVF_NUM_THREADS"):
        _threads.set_from_environment({"PYVF_NUM_THREADS": value})


def test_what_the_refusals_take(restore_threads):
    """NumPy integers (np.arange, an array of core counts) are counts like any other; MAX_THREADS
    itself is one, also to the commands' --threads (whose larger counts are refused when parsed)."""
    from pyvf.cli.options import thread_count
    pyvf.set_num_threads(np.int64(1))
    assert pyvf.num_threads() == 1 and blas_threads() == 1 and type(pyvf.num_threads()) is int
    pyvf.set_num_threads(2)
    with pyvf.threads(np.int32(1)):
        assert pyvf.num_threads() == 1 and blas_threads() == 1
    assert pyvf.num_threads() == 2
    assert thread_count(str(_threads.MAX_THREADS)) == _threads.MAX_THREADS
    with pytest.raises(argparse.ArgumentTypeError):
        thread_count(str(_threads.MAX_THREADS + 1))
