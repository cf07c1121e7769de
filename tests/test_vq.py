"""vq_nearest against float64 brute force: random data, the large-offset cancellation cases
where the published |x|^2 - 2 x.e + |e|^2 formula fails, exact ties, duplicated codes, bad input."""


import numpy as np
import pytest

import pyvf
from conftest import assert_bitwise_equal
from pyvf.nn.quantizer import vq_nearest

# every test here runs once per kernel path this machine executes (conftest.kernel_path)
pytestmark = pytest.mark.usefixtures("kernel_path")


def brute_force(x, codes):
    """Exact distances in float64 by direct differences; argmin takes the first minimum."""
    x = x.astype(np.float64)
    d = np.stack([((x - c) ** 2).sum(axis=1) for c in codes.astype(np.float64)], axis=1)  # (M, K)
    return d.argmin(axis=1), d.min(axis=1), d


def published(x, codes):
    """The published quantizer: -(|x|^2 - 2 x.e + |e|^2) in the input dtype, first maximum."""
    d = (x ** 2).sum(axis=1, keepdims=True) - 2 * x @ codes.T + (codes ** 2).sum(axis=1)
    return (-d).argmax(axis=1)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("M, K, D", [(500, 64, 16), (300, 1024, 256), (7, 5, 3), (1, 1, 1), (65, 33, 17)])
def test_matches_brute_force(M, K, D, dtype, rng):
    x = rng.standard_normal((M, D)).astype(dtype)
    codes = rng.standard_normal((K, D)).astype(dtype)
    index, sq = vq_nearest(x, codes)
    want, want_d, _ = brute_force(x, codes)
    assert index.dtype == np.int64 and sq.dtype == dtype
    np.testing.assert_array_equal(index, want)
    # the distance is the float64 one rounded to the dtype; the kernel sums the D nonnegative
    # terms in order, numpy pairwise: they may differ by up to D * 2^-53 relative (1.2e-15
    # measured at D = 256), plus the rounding to the dtype
    np.testing.assert_allclose(sq, want_d.astype(dtype), rtol=4 * np.finfo(dtype).eps + D * 2.0 ** -53, atol=0)
    assert (sq >= 0).all()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("offset", [1e2, 1e3, 1e4, 1e5])
def test_large_offsets_stay_exact(offset, dtype, rng):
    """Vectors far from the origin beside small gaps between codes: |x|^2, 2 x.e and |e|^2 are
    huge and cancel. The published float32 formula picks wrong codes; vq_nearest must not."""
    x = (rng.standard_normal((400, 32)) + offset).astype(dtype)
    codes = (rng.standard_normal((128, 32)) + offset).astype(dtype)
    index, sq = vq_nearest(x, codes)
    want, want_d, _ = brute_force(x, codes)
    np.testing.assert_array_equal(index, want)
    np.testing.assert_allclose(sq, want_d.astype(dtype), rtol=4 * np.finfo(dtype).eps + 32 * 2.0 ** -53)
    if dtype == np.float32 and offset >= 1e3:
        assert (published(x, codes) != want).mean() > 0.1  # the case is a real trap


def test_exact_ties_go_to_the_smallest_index(rng):
    codes = rng.standard_normal((10, 8))
    codes[7] = codes[3]  # duplicated code (the published EMA leaves unused codes equal, at 0)
    codes[9] = codes[3]
    index, sq = vq_nearest(codes[[3, 7, 9, 1]].copy(), codes)
    np.testing.assert_array_equal(index, [3, 3, 3, 1])
    assert (sq == 0).all()
    # a point equidistant from three codes: the first of them
    index, sq = vq_nearest(np.zeros((1, 2)), np.array([[0.0, 2.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]]))
    assert index[0] == 1 and sq[0] == 1.0
    # every code zero (an EMA after a step where no code was used): index 0, distance |x|^2
    x = rng.standard_normal((5, 4)).astype(np.float32)
    index, sq = vq_nearest(x, np.zeros((6, 4), np.float32))
    assert (index == 0).all()
    np.testing.assert_allclose(sq, (x.astype(np.float64) ** 2).sum(1), rtol=1e-6)


def test_near_ties_resolved_by_exact_distances(rng):
    """Two codes whose distances differ by one part in 1e12: far below float32's resolution of
    the fast scores; the re-rank must still pick the truly nearer one."""
    x = rng.standard_normal((50, 16))
    a = rng.standard_normal(16)
    for m in range(50):
        base = x[m] + a
        c = np.stack([base, base])
        c[1] = x[m] + a * (1 - 1e-12)  # very slightly nearer
        index, _ = vq_nearest(x[m:m + 1].copy(), c)
        assert index[0] == 1


def test_same_result_for_any_thread_count(rng):
    x = rng.standard_normal((3000, 64)).astype(np.float32) + 300
    codes = rng.standard_normal((512, 64)).astype(np.float32) + 300
    n = pyvf.num_threads()
    try:
        pyvf.set_num_threads(1)
        one = vq_nearest(x, codes)
        pyvf.set_num_threads(2)
        two = vq_nearest(x, codes)
    finally:
        pyvf.set_num_threads(n)
    assert_bitwise_equal("index", two[0], one[0])
    assert_bitwise_equal("sq", two[1], one[1])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("x_offset", [1e2, 1e4])
def test_vectors_far_from_every_code(x_offset, dtype, rng):
    """x far from the codes themselves (the shift cannot remove that): large |x'|, wide error
    intervals, more codes re-ranked; the answer must still be exact."""
    x = (rng.standard_normal((300, 16)) + x_offset).astype(dtype)
    codes = rng.standard_normal((64, 16)).astype(dtype)
    index, sq = vq_nearest(x, codes)
    want, want_d, _ = brute_force(x, codes)
    np.testing.assert_array_equal(index, want)
    np.testing.assert_allclose(sq, want_d.astype(dtype), rtol=4 * np.finfo(dtype).eps + 16 * 2.0 ** -53)


@pytest.mark.parametrize("x, codes, exc, name", [
    (np.zeros((3, 4), np.int64), np.zeros((2, 4)), TypeError, "x"),
    (np.zeros((3, 4), np.float16), np.zeros((2, 4), np.float16), TypeError, "x"),
    (np.zeros((3, 4)), np.zeros((2, 4), np.float32), TypeError, "codes"),
    (np.zeros((3, 4)), np.zeros((2, 5)), ValueError, "codes"),
    (np.zeros(4), np.zeros((2, 4)), ValueError, "x"),
    (np.zeros((3, 4)), np.zeros((0, 4)), ValueError, "codes"),
    (np.zeros((3, 8))[:, ::2], np.zeros((2, 4)), ValueError, "x"),  # not C-contiguous: never copied silently
    (np.full((3, 4), np.nan), np.zeros((2, 4)), ValueError, "x"),
    (np.zeros((3, 4)), np.full((2, 4), np.inf), ValueError, "codes"),
    ([[0.0]], np.zeros((2, 1)), TypeError, "x"),
])
def test_refusals_name_the_argument(x, codes, exc, name):
    with pytest.raises(exc, match=rf"\b{name}\b"):
        vq_nearest(x, codes)


def test_a_subnormal_float64_row_finds_its_equal_code():
    """The smallest case of the subnormal rerank: x equal to the second code, distance 0."""
    index, sq = vq_nearest(np.array([[1e-310]]), np.array([[0.0], [1e-310]]))
    assert index.tolist() == [1] and sq.tolist() == [0.0]


def test_no_rows_gives_empty_results():
    index, sq = vq_nearest(np.zeros((0, 4), np.float32), np.zeros((3, 4), np.float32))
    assert index.shape == (0,) and sq.shape == (0,) and sq.dtype == np.float32


def scaled_brute_force(x, codes, scale):
    """Nearest codes of x / scale among codes / scale (exact scaling by a power of two), by
    float64 brute force: the reference where the unscaled squared distances leave float64."""
    xs, cs = x.astype(np.float64) / scale, codes.astype(np.float64) / scale
    return ((xs[:, None, :] - cs[None]) ** 2).sum(-1).argmin(1)


@pytest.mark.parametrize("dtype, magnitude", [
    (np.float64, 1e200), (np.float64, 1e300), (np.float64, 1e-200), (np.float64, 1e-300),
    (np.float64, 1e-310), (np.float64, 1e-320),  # subnormal: the rerank's scale 2^1030 overflowed (NaN, wrong codes)
    (np.float32, 1e20), (np.float32, 1e35), (np.float32, 1e-30), (np.float32, 1e-40),
])
def test_extreme_magnitudes_give_the_true_nearest_code(dtype, magnitude, rng):
    """Squared distances that overflow (1e200 in float64: 1e400) or underflow the dtype: the
    index is still the true nearest code (a valid index, never -1), and the distance is inf
    exactly when the true one exceeds the dtype's range (0 when below its smallest value)."""
    scale = 2.0 ** np.round(np.log2(magnitude))
    codes = (rng.standard_normal((50, 8)) * scale).astype(dtype)
    x = (rng.standard_normal((40, 8)) * scale).astype(dtype)
    index, sq = vq_nearest(x, codes)
    np.testing.assert_array_equal(index, scaled_brute_force(x, codes, scale))
    true = ((x.astype(np.float64) / scale - codes[index].astype(np.float64) / scale) ** 2).sum(-1)
    with np.errstate(over="ignore", under="ignore"):
        fits = true * scale * scale  # in float64 (inf or 0 where it does not fit float64 either)
    big = np.log2(true) + 2 * np.log2(scale) > np.log2(np.finfo(dtype).max)
    assert np.isinf(sq[big]).all() and np.isfinite(sq[~big]).all()
    if not big.any() and np.isfinite(fits).all() and (fits > np.finfo(dtype).tiny).all():
        np.testing.assert_allclose(sq, fits.astype(dtype), rtol=8 * np.finfo(dtype).eps)


def test_overflowing_fast_scores_fall_back_to_the_exact_rerank(rng):
    """float32 x at 1e20 beside codes near 0: x'.e' overflows float32 in the fast scores; the
    row must re-rank every code rather than return a wrong or invalid index."""
    codes = rng.standard_normal((30, 4)).astype(np.float32) * np.float32(1e19)
    x = rng.standard_normal((10, 4)).astype(np.float32) * np.float32(1e20)
    index, _ = vq_nearest(x, codes)
    np.testing.assert_array_equal(index, scaled_brute_force(x, codes, 2.0 ** 66))


def _plain_sum(x, e):
    """The documented exact distance: sum_i (x_i - e_i)^2 in double, in increasing i, each
    operation rounded once (Python floats: no fused multiply-add)."""
    s = 0.0
    for a, b in zip(x.tolist(), e.tolist()):
        t = a - b
        s = s + t * t
    return s


def test_float64_rerank_is_the_plain_sum_on_every_path(rng):
    """The re-rank's exact distances are sum (x_i - e_i)^2 in double with every product and sum
    rounded: where the compiler fused t * t + s into one FMA (-ffp-contract=fast on the avx2 and
    avx512 paths, not on baseline), float64 rows on a tie of that sum went to the larger index
    and the answer depended on the kernel path. The oracle: the argmin of the plain sum in Python
    floats, ties to the smallest index, and its distance rounded to float64."""
    x = np.array([[-0.001, 0.0, 0.0]])
    codes = np.array([[0.0, 0.002, 0.001], [0.001, 0.001, -0.001]])
    assert _plain_sum(x[0], codes[0]) == _plain_sum(x[0], codes[1])  # a tie of the documented sum
    assert vq_nearest(x, codes)[0].tolist() == [0]
    # random near-ties: codes of a few decimal steps, so that sums tie or differ in the last bits
    for _ in range(200):
        D = int(rng.integers(2, 6))
        x = rng.integers(-3, 4, size=(4, D)) * 1e-3
        codes = rng.integers(-3, 4, size=(6, D)) * 1e-3
        idx, dist = vq_nearest(x, codes)
        for m in range(len(x)):
            d = [_plain_sum(x[m], c) for c in codes]
            assert idx[m] == int(np.argmin(d)) and dist[m] == min(d), (x[m], codes)
