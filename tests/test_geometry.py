"""Tests of pyvf.geometry (docs/math.md §3 poses, §6 pose metrics): the quaternion algebra in closed
form, rotations against the textbook rotation matrix of a quaternion and the Hamilton sandwich,
relative/absolute poses (round trip, the reference view, invariance to moving
the whole scene), the orientation error against the published asin form and closed-form angles,
the pose average, hard cases and argument checks.

Shapes: quaternions (..., 4) as (w, x, y, z); vectors (..., 3); poses (..., 7) = xyz then the
quaternion. Relative errors are normwise (conftest.assert_close): max|got - want| / max|want|.
"""

import math
import warnings

import numpy as np
import pytest

from pyvf import geometry as geo

from conftest import assert_bitwise_equal, assert_close

U32 = 2.0 ** -24  # float32 unit roundoff
U64 = 2.0 ** -53  # float64 unit roundoff

# A quaternion product or rotation is a handful of multiply-adds of O(1) numbers: a few ulp.
# 8 ulp of headroom in float64, 16 in float32 (the float32 inputs are themselves rounded).
RTOL64 = 8 * U64 * 4  # 3.6e-15
RTOL32 = 16 * U32 * 4  # 3.8e-6

DTYPES = [np.float64, np.float32]
RTOL = {np.float64: RTOL64, np.float32: RTOL32}


# ---------------------------------------------------------------------------------------
# independent helpers (not taken from pyvf)


def unit_quats(rng, shape, dtype=np.float64):
    """Random unit quaternions (uniform on the sphere), normalised here in float64."""
    q = rng.standard_normal(tuple(shape) + (4,))
    return (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(dtype)


def axis_angle_quat(axis, angle):
    """q = (cos(angle/2), sin(angle/2) * axis/|axis|), float64."""
    n = np.asarray(axis, dtype=np.float64)
    n = n / np.linalg.norm(n)
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * n])


def hamilton_left_matrix(a):
    """(..., 4, 4) matrix L(a) with a * b = L(a) @ b, written from i^2 = j^2 = k^2 = ijk = -1."""
    w, x, y, z = (a[..., i] for i in range(4))
    return np.stack([
        np.stack([w, -x, -y, -z], -1),
        np.stack([x, w, -z, y], -1),
        np.stack([y, z, w, -x], -1),
        np.stack([z, -y, x, w], -1),
    ], -2)


def random_poses(rng, shape, dtype=np.float64, scale=3.0):
    xyz = scale * rng.standard_normal(tuple(shape) + (3,))
    return np.concatenate([xyz, unit_quats(rng, shape)], -1).astype(dtype)


def published_orientation_error(q1, q2):
    """The published metric (viewformer/utils/metrics.py): normalise both, then
    2 * asin(|vec(q1 * conj(q2))|), in degrees. Uses pyvf's product (tested above)."""
    a, b = geo.quat_normalize(q1), geo.quat_normalize(q2)
    r = geo.quat_mul(a, geo.quat_conj(b))
    with np.errstate(invalid="ignore"):
        return np.degrees(2 * np.arcsin(np.sqrt(np.sum(r[..., 1:] ** 2, axis=-1))))


# ---------------------------------------------------------------------------------------
# the quaternion algebra


def test_quat_algebra_identities(rng):
    """The product against its matrix form L(a) b (its identities follow from it), and q conj(q) =
    |q|^2 (vector part exactly 0, by the pairing of terms in the product). float64, random non-unit
    quaternions."""
    a, b = rng.standard_normal((50, 4)), rng.standard_normal((3, 4))
    m, cj = geo.quat_mul, geo.quat_conj
    assert_close("ab vs L(a) @ b", m(a[:, None], b), np.einsum("nij,mj->nmi", hamilton_left_matrix(a), b),
                 rtol=RTOL64)  # broadcast (50, 1, 4) x (3, 4)
    for r in (m(a, cj(a)), m(cj(a), a)):
        assert (r[:, 1:] == 0).all()
        assert_close("q conj(q)", r[:, 0], np.sum(a * a, axis=-1), rtol=RTOL64)


@pytest.mark.parametrize("dtype", DTYPES)
def test_quat_rotate_against_the_matrix(rng, dtype):
    """Broadcast q (5, 1, 4) against v (1, 6, 3): equals R(q) v (the textbook matrix, in float64
    on the same numbers)."""
    q, v = unit_quats(rng, (5, 1), dtype), rng.standard_normal((1, 6, 3)).astype(dtype)
    assert_close("rotate vs matrix", geo.quat_rotate(q, v), rotated(q, v), rtol=RTOL[dtype])  # (5, 6, 3)


@pytest.mark.parametrize("dtype", DTYPES)
def test_quat_normalize_tf_convention(rng, dtype):
    """q / sqrt(max(|q|^2, 1e-12)): random q as the formula; a zero quaternion gives exactly 0
    with no warning; |q| = 1e-7 < sqrt(eps) gives q / 1e-6 (TF's floor), not a unit quaternion."""
    q = rng.standard_normal((30, 4)).astype(dtype)
    q64 = q.astype(np.float64)
    want = q64 / np.sqrt(np.maximum(np.sum(q64 * q64, -1, keepdims=True), 1e-12))
    assert_close("normalize", geo.quat_normalize(q), want, rtol=RTOL[dtype])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        z = geo.quat_normalize(np.zeros((2, 4), dtype))
    assert_bitwise_equal("normalize(0)", z, np.zeros((2, 4), dtype))
    tiny = np.array([1e-7, 0, 0, 0], dtype)
    assert_close("normalize below the floor", geo.quat_normalize(tiny), np.array([0.1, 0, 0, 0]), rtol=RTOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES)
def test_quat_canonical(rng, dtype):
    """-q where w < 0, q where w > 0; at w == 0 (either sign of zero) q unchanged, bit for bit, as
    the published quaternion_remove_sign."""
    q = unit_quats(rng, (20,), dtype)
    assert_bitwise_equal("canonical", geo.quat_canonical(q), np.where(q[:, :1] < 0, -q, q))  # dtype too
    w0 = np.array([[0.0, -0.6, 0.8, 0], [-0.0, -0.6, 0.8, 0], [0, 0, -1, 0]], dtype)
    assert_bitwise_equal("w == 0 kept", geo.quat_canonical(w0), w0)
    assert_bitwise_equal("w == 0 kept for -q", geo.quat_canonical(-w0), -w0)


# ---------------------------------------------------------------------------------------
# poses


def test_relative_poses_closed_form():
    """ref at (1, 2, 3) turned +90 degrees about z (its x axis points along world y). A camera at
    (1, 3, 3) (one unit along the ref's x) turned +90 + 30 degrees about z is, seen from ref, at
    (1, 0, 0) and turned 30 degrees about z."""
    ref = np.concatenate([[1.0, 2, 3], axis_angle_quat([0, 0, 1], math.pi / 2)])
    pose = np.concatenate([[1.0, 3, 3], axis_angle_quat([0, 0, 1], math.pi / 2 + math.pi / 6)])
    want = np.concatenate([[1.0, 0, 0], axis_angle_quat([0, 0, 1], math.pi / 6)])
    assert_close("relative pose", geo.relative_poses(pose, ref), want, rtol=RTOL64)


@pytest.mark.parametrize("dtype", DTYPES)
def test_make_relative_first_view_is_identity(rng, dtype):
    """rel[:, 0] = (0, 0, 0, 1, 0, 0, 0): the position and the quaternion's vector part exactly 0,
    w = 1 to the ulp; ref is a copy of view 0; every w >= 0 and |q| = 1; otherwise rel is
    relative_poses (the round trip through absolute_poses: test_relative_poses_large_translations)."""
    poses = random_poses(rng, (3, 5), dtype)
    rel, ref = geo.make_relative(poses)
    assert rel.shape == (3, 5, 7) and ref.shape == (3, 7) and rel.dtype == ref.dtype == dtype
    assert_bitwise_equal("ref", ref, poses[:, 0])
    assert not np.shares_memory(ref, poses)
    assert (rel[:, 0, :3] == 0).all() and (rel[:, 0, 4:] == 0).all()
    assert_close("w of view 0", rel[:, 0, 3], np.ones(3), rtol=2 * np.finfo(dtype).eps)
    assert (rel[..., 3] >= 0).all()
    assert_close("|q| = 1", np.linalg.norm(rel[..., 3:].astype(np.float64), axis=-1), np.ones((3, 5)),
                 rtol=RTOL[dtype])
    plain = geo.relative_poses(poses, ref[:, None])
    plain[..., 3:] = geo.quat_canonical(geo.quat_normalize(plain[..., 3:]))
    assert_bitwise_equal("relative_poses, normalised and canonical", rel, plain)


def test_relative_poses_invariant_to_moving_the_scene(rng):
    """Moving every camera by one rigid transform G = (t_g, g) (xyz -> g xyz + t_g, q -> g q) leaves
    the relative poses unchanged: rel = conj(g q0) (g q) = conj(q0) q. float64, |t_g| ~ 100."""
    poses = random_poses(rng, (2, 7))
    G = np.concatenate([100 * rng.standard_normal((2, 1, 3)), unit_quats(rng, (2, 1))], -1)
    moved = geo.absolute_poses(poses, G)  # exactly the rigid motion: rotate(g, xyz) + t_g, g q
    a = geo.relative_poses(poses, poses[:, :1])
    b = geo.relative_poses(moved, moved[:, :1])
    # the moved positions carry rounding errors of ~1e-14 (|t_g| = 100); measured 4.2e-15 normwise
    # over 50 draws, 1e-12 allowed (a wrong order of rotations is an O(1) error)
    assert_close("relative poses after moving the scene", b, a, rtol=1e-12)


def test_relative_poses_large_translations(rng):
    """Cameras 1e6 from the origin, a few units apart: the relative positions keep the digits of
    the offsets (differences are taken before rotating). Offsets are multiples of 1/64, so
    xyz - t0 is exact and the answer is rotate(conj(q0), offset) to a few ulp of the offset."""
    t0 = 1e6 * np.array([1.0, -2.0, 0.5])
    off = np.round(64 * rng.standard_normal((6, 3))) / 64
    q = unit_quats(rng, (6,))
    poses = np.concatenate([t0 + off, q], -1)
    ref = np.concatenate([t0, q[0]])
    rel = geo.relative_poses(poses, ref)
    want = geo.quat_rotate(geo.quat_conj(q[0]), off)
    assert_close("relative xyz at 1e6", rel[:, :3], want, rtol=RTOL64)
    assert_close("round trip at 1e6", geo.absolute_poses(rel, ref), poses, rtol=RTOL64)


# ---------------------------------------------------------------------------------------
# metrics


@pytest.mark.parametrize("dtype", DTYPES)
def test_position_error(rng, dtype):
    """3-4-5 and 1e6-scale cases exactly; poses use their xyz only; broadcasting; float64 1e200
    differences (squares overflow) are still exact."""
    p1 = np.array([[0, 0, 0], [1e6, 1e6, 0]], dtype)
    p2 = np.array([[3, 4, 0], [1e6, 1e6 + 12, 5]], dtype)
    np.testing.assert_array_equal(geo.position_error(p1, p2), np.array([5, 13], dtype))
    poses = random_poses(rng, (2, 3), dtype)
    assert_close("poses", geo.position_error(poses, poses[:1]),
                 np.linalg.norm(poses[..., :3].astype(np.float64) - poses[:1, :, :3], axis=-1), rtol=RTOL[dtype])
    big = geo.position_error(np.array([3e200, 0, 0]), np.array([0, -4e200, 0]))
    assert_close("1e200", big, 5e200, rtol=RTOL64)


@pytest.mark.parametrize("dtype", DTYPES)
def test_orientation_error_closed_form_angles(rng, dtype):
    """Rotations about an axis by known angles (0, tiny, 90, 180 degrees, beyond 180) against the
    identity and against a random common rotation g (q1 = q(angle) g, q2 = g).

    Against the identity the product is exact, so the angle is as accurate as the inputs'
    sin/cos: relative error <= 4 eps (measured 1.8 eps over 200 axes), and exactly 0 at angle 0.
    Against g the vector part of q1 conj(q2) carries an absolute rounding error of a few eps
    whatever the angle: absolute error <= 8 eps rad (measured 3.4 eps), which at 1e-9 rad is a
    relative 2e-6 in float64 -- the conditioning of the inputs, not of the formula."""
    eps = float(np.finfo(dtype).eps)
    angles = [0.0, 1e-9, 1e-7, 1e-4, 0.3, math.pi / 2, 2.0, math.pi - 1e-7, math.pi, 1.5 * math.pi]
    ident = np.array([1.0, 0, 0, 0], dtype)
    for _ in range(10):
        axis, g = rng.standard_normal(3), unit_quats(rng, ())
        for a in angles:
            want = math.degrees(min(a, 2 * math.pi - a))  # the shorter way round
            qa = axis_angle_quat(axis, a)
            got = geo.orientation_error(qa.astype(dtype), ident)
            assert abs(float(got) - want) <= 4 * eps * want, (a, float(got), want)
            got_g = geo.orientation_error(geo.quat_mul(qa, g).astype(dtype), g.astype(dtype))
            assert abs(float(got_g) - want) <= math.degrees(8 * eps), (a, float(got_g), want)
        np.testing.assert_array_equal(geo.orientation_error(g, g), 0.0)  # exactly: q conj(q) has vec 0


def test_orientation_error_vs_published_asin_form(rng):
    """Where the asin form is well conditioned (angles < 150 degrees) the two agree to 1e-12
    normwise (float64, random unit pairs; also non-unit inputs, which the published metric
    normalises and atan2 ignores). Both are sign-invariant: q vs -q changes neither, bit for bit."""
    q1, q2 = unit_quats(rng, (500,)), unit_quats(rng, (500,))
    ours, theirs = geo.orientation_error(q1, q2), published_orientation_error(q1, q2)
    ok = theirs < 150
    assert ok.sum() > 300
    assert_close("atan2 vs asin form", ours[ok], theirs[ok], rtol=1e-12)
    assert_close("non-unit inputs", geo.orientation_error(3.0 * q1, -0.25 * q2), ours, rtol=RTOL64 * 4)
    for a, b in [(-q1, q2), (q1, -q2), (-q1, -q2)]:
        assert_bitwise_equal("sign invariance", geo.orientation_error(a, b), ours)
    assert_bitwise_equal("symmetry", geo.orientation_error(q2, q1), ours)
    assert ((ours >= 0) & (ours <= 180)).all()


def test_orientation_error_asin_form_nan_where_rounding_exceeds_one(rng):
    """180-degree rotations (w = 0) with a unit vector part whose computed length rounds to
    1 + 2^-52 (about one in four random ones): the asin form gives NaN, atan2 gives 180."""
    for _ in range(100):
        v = rng.standard_normal(3)
        q = np.concatenate([[0.0], v / np.linalg.norm(v)])
        if np.sqrt(np.sum(q[1:] ** 2)) > 1:
            break
    else:
        pytest.fail("no rounding case found in 100 draws")
    ident = np.array([1.0, 0, 0, 0])
    assert np.isnan(published_orientation_error(q, ident))
    assert float(geo.orientation_error(q, ident)) == 180.0


@pytest.mark.parametrize("dtype", DTYPES)
def test_average_pose(rng, dtype):
    """Against the published recipe written out step by step (normalise, canonicalise, mean,
    normalise, canonicalise) over axis -2 of (B, N, L, 7); flipping the sign or scaling any input
    quaternion changes nothing."""
    poses = random_poses(rng, (2, 3, 16), dtype)
    poses[..., 3:] = (poses[..., 3:] + 0.1 * rng.standard_normal((2, 3, 1, 4))).astype(dtype)  # nearby, non-unit
    got = geo.average_pose(poses, axis=-2)
    assert got.shape == (2, 3, 7) and got.dtype == dtype
    p = poses.astype(np.float64)
    q = p[..., 3:] / np.linalg.norm(p[..., 3:], axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0, -q, q).mean(axis=-2)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0, -q, q)
    assert_close("average", got, np.concatenate([p[..., :3].mean(-2), q], -1), rtol=4 * RTOL[dtype])
    flipped = poses.copy()
    flipped[..., ::2, 3:] *= -3
    assert_close("sign and scale invariance", geo.average_pose(flipped, axis=2), got, rtol=4 * RTOL[dtype])


def test_average_pose_cancelling_quaternions_give_zero():
    """Opposite 180-degree rotations with w == 0 (kept apart by the published sign rule) and zero
    quaternions average to the zero quaternion, not NaN."""
    poses = np.array([[0, 0, 0, 0, 1, 0, 0], [2, 0, 0, 0, -1, 0, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = geo.average_pose(poses, axis=0)
        np.testing.assert_array_equal(got, [1, 0, 0, 0, 0, 0, 0])
        np.testing.assert_array_equal(geo.average_pose(np.zeros((3, 7)), axis=0), np.zeros(7))


# ---------------------------------------------------------------------------------------
# refusals: one table, the exception type and the argument's name


def _q(dtype=np.float64, n=2):
    return np.tile(np.array([1.0, 0, 0, 0], dtype), (n, 1))


def _p(dtype=np.float64, n=2):
    return np.tile(np.array([0.0, 0, 0, 1, 0, 0, 0], dtype), (n, 1))


def _v(dtype=np.float64, n=2):
    return np.ones((n, 3), dtype)


def _with(a, index, value):
    a = a.copy()
    a[index] = value
    return a


# (function, good arguments by name)
CALLS = [
    (geo.quat_mul, {"a": _q, "b": _q}),
    (geo.quat_conj, {"q": _q}),
    (geo.quat_rotate, {"q": _q, "v": _v}),
    (geo.quat_normalize, {"q": _q}),
    (geo.quat_canonical, {"q": _q}),
    (geo.relative_poses, {"poses": _p, "ref": _p}),
    (geo.absolute_poses, {"rel": _p, "ref": _p}),
    (geo.make_relative, {"poses": _p}),
    (geo.position_error, {"p1": _v, "p2": _v}),
    (geo.orientation_error, {"q1": _q, "q2": _q}),
    (geo.average_pose, {"poses": _p}),
]
BAD = {  # the ways an array argument can be wrong: (make it so, the exception)
    "int64": (lambda a: a.astype(np.int64), TypeError),
    "last dimension": (lambda a: np.concatenate([a, a[..., :1]], -1), ValueError),
    "nan": (lambda a: _with(a, (0, 0), np.nan), ValueError),
}


@pytest.mark.parametrize("kind", BAD)
@pytest.mark.parametrize("f, args, name", [(f, args, name) for f, args in CALLS for name in args],
                         ids=[f"{f.__name__}-{name}" for f, args in CALLS for name in args])
def test_bad_array_arguments_are_named(f, args, name, kind):
    """For every array argument of every function; the good call keeps either dtype."""
    for dt in (np.float32, np.float64):
        out = f(**{k: make(dt) for k, make in args.items()})
        assert all(o.dtype == dt for o in (out if isinstance(out, tuple) else (out,)))
    make_bad, error = BAD[kind]
    with pytest.raises(error, match=rf"\b{name}\b"):
        f(**{k: make_bad(make()) if k == name else make() for k, make in args.items()})


@pytest.mark.parametrize("call, error, name", [
    *[(lambda axis=axis: geo.average_pose(_p(), axis=axis), ValueError, "axis") for axis in (-1, 1, 2)],
    (lambda: geo.orientation_error(_q(), np.zeros((2, 4))), ValueError, "q2"),  # a zero quaternion
    # unit quaternions required (the zero quaternion too), named by the argument that holds them
    (lambda: geo.quat_rotate(1.001 * _q(), _v()), ValueError, "q"),
    (lambda: geo.relative_poses(_with(_p(), (1, 3), 2.0), _p()), ValueError, "poses"),
    (lambda: geo.relative_poses(_p(), _with(_p(), (0, 3), 0.0)), ValueError, "ref"),
    (lambda: geo.absolute_poses(_with(_p(), (1, 3), 2.0), _p()), ValueError, "rel"),
    (lambda: geo.make_relative(_with(_p(), (1, 3), 2.0)[None]), ValueError, "poses"),
])
def test_other_refusals_name_the_argument(call, error, name):
    with pytest.raises(error, match=rf"\b{name}\b"):
        call()


def rotation_matrix(q):
    """(..., 3, 3) float64 rotation matrix of unit quaternions q (..., 4), the textbook formula."""
    w, x, y, z = (np.asarray(q, np.float64)[..., i] for i in range(4))
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def rotated(q, v):
    """R(q) v in float64 (float32 inputs of 3e38 are far from float64's limit)."""
    return np.einsum("...ij,...j->...i", rotation_matrix(q), np.asarray(v, np.float64))
