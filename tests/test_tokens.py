"""Issue 48: the empty-patch health figures and the codebook's restart options, against
closed forms and brute force."""

import dataclasses
import json
import math

import numpy as np
import pytest

from pyvf.evaluate.health import empty_entropy, empty_patches
from pyvf.evaluate.metrics import to_model_images
from pyvf.evaluate.run import _token_scores
from pyvf.models.codebook import Codebook
from pyvf.nn.quantizer import EMAQuantizer, code_utility, low_utility_codes
from pyvf.train.loops import TINY_CODEBOOK


def test_empty_patches_marks_patches_without_object_pixels():
    img = np.full((2, 16, 16, 3), 100, np.uint8)  # background everywhere
    img[0, 9, 3] = (200, 0, 0)  # one object pixel in patch (1, 0) of a 2x2 grid of 8x8 patches
    e = empty_patches(img, 2)  # (2, 2, 2)
    assert e.shape == (2, 2, 2)
    assert e[1].all() and e[0].sum() == 3 and not e[0, 1, 0]


def test_empty_entropy_closed_forms():
    codes = np.zeros((4, 2, 2), np.int64)
    empty = np.zeros((4, 2, 2), bool)
    codes[:, 0, 0], empty[:, 0, 0] = 3, True  # always code 3 where empty: 0 nats
    codes[:, 0, 1], empty[:, 0, 1] = [5, 5, 7, 7], True  # half / half: log 2
    codes[:, 1, 0], empty[:, 1, 0] = [1, 2, 9, 9], [True, True, False, False]  # only the empty views count: log 2
    codes[:, 1, 1] = [1, 2, 3, 4]  # never empty: left out of the mean
    assert empty_entropy(codes, empty) == pytest.approx((0 + math.log(2) + math.log(2)) / 3, rel=1e-12)
    assert math.isnan(empty_entropy(codes, np.zeros_like(empty)))


def test_token_scores_split_empty_and_object():
    logits = np.log(np.array([[[[0.5, 0.5], [0.9, 0.1], [0.2, 0.8]]]]))  # (B=1, M=1, L=3, V=2)
    tokens = np.array([[[0, 0, 0]]])
    empty = np.array([[[True, True, False]]])
    s = _token_scores(logits, tokens, empty)
    assert np.mean(s["ce_empty"]) == pytest.approx(-(math.log(0.5) + math.log(0.9)) / 2, rel=1e-12)
    assert np.mean(s["ce_object"]) == pytest.approx(-math.log(0.2), rel=1e-12)
    assert np.mean(s["token_accuracy_empty"]) == 1.0 and np.mean(s["token_accuracy_object"]) == 0.0


def _brute_utility(x, codes):
    """The increase of the total squared error when code k is removed, by recomputing it."""
    def total(c):
        return ((x[:, None, :] - c[None]) ** 2).sum(-1).min(axis=1).sum()
    base = total(codes)
    return np.array([total(np.delete(codes, k, axis=0)) - base for k in range(len(codes))])


def test_code_utility_matches_brute_force():
    rng = np.random.default_rng(0)
    x, codes = rng.normal(size=(200, 3)), rng.normal(size=(7, 3))
    idx, util, second = code_utility(x, codes)
    np.testing.assert_allclose(util, _brute_utility(x, codes), rtol=1e-10, atol=1e-12)
    d = ((x[:, None] - codes[None]) ** 2).sum(-1)
    assert (idx == d.argmin(1)).all() and (d[np.arange(200), second] == np.sort(d, 1)[:, 1]).all()


def test_code_utility_ties_duplicate_codes_have_zero_utility():
    x = np.array([[0.0, 0.0], [0.1, 0.0], [5.0, 5.0]])
    codes = np.array([[0.0, 0.0], [0.0, 0.0], [5.0, 5.0]])  # codes 0 and 1 one point: removing either costs 0
    idx, util, _ = code_utility(x, codes)
    assert (idx[:2] == 0).all()  # ties to the smaller index
    np.testing.assert_allclose(util, _brute_utility(x, codes), atol=1e-12)
    assert util[0] == util[1] == 0.0 and util[2] > 0


def test_low_utility_codes_moves_one_of_a_split_cluster():
    # codes 0, 1, 2 split one tight cluster; code 3 holds another: moving 0 and 2 would be fine for
    # the cluster (1 stays), but 0's vectors go to 1, so 1 is kept; the far cluster's code is not moved
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.normal(0, 0.01, (30, 2)), rng.normal(10, 0.01, (10, 2))])
    codes = np.array([[0.0, 0.0], [0.001, 0.0], [0.0, 0.001], [10.0, 10.0]])
    idx, util, second = code_utility(x, codes)
    moved = low_utility_codes(idx, util, second, np.array([], np.int64), np.full(4, 1.0))
    assert 3 not in moved and 0 < len(moved) < 3
    for k in moved:  # no moved code takes another moved code's vectors
        assert not np.isin(second[idx == k], moved).any()
    assert len(low_utility_codes(idx, util, second, np.array([], np.int64), np.full(4, 0.0))) == 0  # no gain: none


def _quantizer(codes, counts, decay=0.99):
    q = EMAQuantizer(codes.shape[1], codes.shape[0], decay=decay, dtype="float64")
    q.embeddings = np.ascontiguousarray(codes.T)
    q.counter = 10
    q.ema_cluster_size_hidden = np.asarray(counts, np.float64) * (1 - decay ** 10)
    q.ema_dw_hidden = q.embeddings * q.ema_cluster_size_hidden
    return q


def test_reset_dead_codes_worst_and_reseat():
    x = np.array([[0.0, 0.0], [0.0, 0.01], [3.0, 0.0], [0.0, 4.5], [0.0, 2.0]])  # (M=5, D=2)
    z = x.T.reshape(1, 2, 1, 5).copy()
    codes = np.array([[0.0, 0.0], [0.0, 0.005], [0.0, 1.0], [9.0, 9.0]])  # code 3 dead
    q = _quantizer(codes, [2.0, 2.0, 2.0, 0.0])
    assert q.reset_dead_codes(z, restart="worst") == 1
    np.testing.assert_array_equal(q.embeddings[:, 3], [0.0, 4.5])  # the worst vector (error 12.25)
    q = _quantizer(codes, [2.0, 2.0, 2.0, 0.0])
    err0 = ((x[:, None] - codes[None]) ** 2).sum(-1).min(1).sum()
    assert q.reset_dead_codes(z, restart="worst", reseat=2) == 2  # the dead code and one of 0 / 1
    moved = q.embeddings.T
    np.testing.assert_array_equal(moved[3], [0.0, 4.5])
    np.testing.assert_array_equal(moved[0], [3.0, 0.0])  # the split pair's least useful to the next worst
    np.testing.assert_array_equal(moved[1:3], codes[1:3])
    assert ((x[:, None] - moved[None]) ** 2).sum(-1).min(1).sum() < err0


def test_init_kmeans_finds_separated_clusters():
    rng = np.random.default_rng(0)
    centres = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    x = np.concatenate([c + rng.normal(0, 0.1, (50, 2)) for c in centres])
    z = x.T.reshape(1, 2, 1, -1).copy()
    q = EMAQuantizer(2, 3, dtype="float64")
    q.init_kmeans(z, 5, batch=1, rng=0)
    found = q.embeddings.T[np.argsort(q.embeddings.T @ [1.0, 2.0])]
    np.testing.assert_allclose(found, [x[:50].mean(0), x[50:100].mean(0), x[100:].mean(0)], atol=1e-12)
    before = q.embeddings.copy()
    q.forward(z, train=True)  # the EMA state keeps the codes where k-means put them
    np.testing.assert_allclose(q.embeddings, before, rtol=1e-3)


def test_empty_code_zero_exactly_at_empty_positions_nearest_of_the_rest_elsewhere():
    rng = np.random.default_rng(3)
    q = EMAQuantizer(3, 6, dtype="float64", seed=1)
    z = rng.normal(size=(2, 3, 4, 4))
    empty = rng.random((2, 4, 4)) < 0.5
    flat = z.transpose(0, 2, 3, 1).reshape(-1, 3)
    q.embeddings[:, 0] = flat[np.flatnonzero(~empty.ravel())[0]]  # code 0 nearest to a non-empty vector: not taken
    out, _ = q.forward(z, empty=empty)
    d = ((flat[:, None] - q.embeddings.T[None, 1:]) ** 2).sum(-1)  # (M, K - 1) brute force
    np.testing.assert_array_equal(out.codes.ravel(), np.where(empty.ravel(), 0, d.argmin(1) + 1))
    q.forward(z, train=True, empty=empty)  # first update (counter 1): code 0 = the empty vectors' mean
    np.testing.assert_allclose(q.embeddings[:, 0], flat[empty.ravel()].mean(0), rtol=1e-4)  # Laplace eps 1e-5


def test_empty_code_never_moves_and_codes_restart_on_object_vectors():
    x = np.array([[0.0, 0.0], [40.0, 40.0], [3.0, 0.0], [0.0, 4.5]])  # vector 1 is empty: far, yet not taken
    z = x.T.reshape(1, 2, 1, 4).copy()
    empty = np.array([[[False, True, False, False]]])
    q = _quantizer(np.array([[50.0, 50.0], [0.0, 0.0], [9.0, 9.0]]), [0.0, 2.0, 0.0])  # codes 0 and 2 dead
    assert q.reset_dead_codes(z, restart="worst", empty=empty) == 1
    np.testing.assert_array_equal(q.embeddings.T, [[50.0, 50.0], [0.0, 0.0], [0.0, 4.5]])
    q.init_kmeans(z, 3, batch=1, rng=0, empty=empty)
    np.testing.assert_array_equal(q.embeddings[:, 0], [40.0, 40.0])  # the empty vectors' mean


def test_codebook_empty_code_matches_the_uint8_empty_patches():
    rng = np.random.default_rng(4)
    img = np.full((3, 64, 64, 3), 128, np.uint8)
    img[:, 20:40, 10:30] = rng.integers(0, 256, (3, 20, 20, 3))  # objects
    img[1, 63, 63] = (128, 128, 129)  # one pixel off the background: that corner patch is not empty
    cb = Codebook(dataclasses.replace(TINY_CODEBOOK, empty_code=True), seed=0)
    codes = cb.encode(to_model_images(img, cb.dtype))
    np.testing.assert_array_equal(codes == 0, empty_patches(img, 8))
    assert not (codes == 0)[1, 7, 7] and (codes == 0).sum() > 100


def test_a_codebook_file_from_before_the_empty_code_loads_without_it(tmp_path):
    cb = Codebook(dataclasses.replace(TINY_CODEBOOK, n_embed=16), seed=0)
    cb.save(tmp_path / "new.npz")
    with np.load(tmp_path / "new.npz") as f:
        entries = dict(f)
    config = json.loads(str(entries["__config__"]))
    del config["empty_code"]  # as files saved before the field existed
    entries["__config__"] = np.array(json.dumps(config))
    np.savez(tmp_path / "old.npz", **entries)
    old = Codebook.load(tmp_path / "old.npz")
    assert old.config == cb.config and old.fingerprint() == cb.fingerprint()  # (another field missing: test_model_files)
