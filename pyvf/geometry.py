"""Camera poses and quaternions (docs/math.md §3 poses, §6 pose metrics).

A pose is 7 numbers: the camera position xyz, then its orientation as a unit quaternion
(w, x, y, z), scalar first. Quaternions multiply by the Hamilton product (i*j = k); a unit
quaternion q rotates a 3-vector v to vec(q * (0, v) * conj(q)).

    q = quat_mul(a, b)                      # (..., 4)    Hamilton product, broadcasting
    v2 = quat_rotate(q, v)                  # (..., 3)    v rotated by the unit quaternion q
    rel = relative_poses(poses, ref)        # (..., 7)    poses seen from the camera ref
    poses = absolute_poses(rel, ref)        # (..., 7)    the inverse
    rel, ref = make_relative(poses)         # (..., N, 7) relative to view 0, the model's input
    e_pos = position_error(p1, p2)          # (...)       Euclidean
    e_ori = orientation_error(q1, q2)       # (...)       degrees, in [0, 180]
    mean = average_pose(poses, axis=-2)     # a view's pose from its L token predictions

Conventions (each one decided here, tested in tests/test_geometry.py):

* Inputs are float32 or float64 numpy arrays; the result has the input's dtype, and two
  arrays in one call must share it (nothing is cast). Integer arrays, a wrong last
  dimension and NaN/inf raise TypeError/ValueError naming the argument; a result that
  overflows the dtype (e.g. positions 1e308 apart) raises ValueError instead of returning inf.
* Functions that use a quaternion as a rotation (quat_rotate, relative_poses,
  absolute_poses, make_relative) require it to be unit: | |q|^2 - 1 | <= 1e-5 (float32) or
  1e-9 (float64), far above the rounding of any chain of products (a few ulp) and far below
  a quaternion that was never normalised. Anything else raises ValueError: for a non-unit q
  the rotation formula is not a rotation (it scales by |q|^2), and quietly normalising would
  hide a data bug. Call quat_normalize first. The published code asserts the same (its
  `assert_normalized`, with a tighter tolerance).
* orientation_error is scale-invariant (it uses only the direction of q1 * conj(q2)), so it
  takes any non-zero quaternions; a zero quaternion there raises.
* quat_normalize follows TF's l2_normalize, q / sqrt(max(|q|^2, eps)): a zero quaternion
  maps to zero, not NaN (the published code's pose prediction and average rely on it). It is
  computed for every finite q, also where |q| itself overflows the dtype (float32 components
  of 3e38) or is subnormal: q is scaled by a power of two first (exact), as in orientation_error.
* quat_canonical multiplies by -1 where w < 0, exactly as the published code
  (`quaternion_remove_sign`: sign = +1 where w >= 0). At w == 0 (and w == -0.0) the
  quaternion is left unchanged, so q and -q with w == 0, the same 180-degree rotation,
  stay different arrays. That is kept for parity: the model's pose predictions and
  average_pose are defined by it.
"""

import numpy as np

from . import _checks

__all__ = [
    "quat_mul",
    "quat_conj",
    "quat_rotate",
    "quat_normalize",
    "quat_canonical",
    "relative_poses",
    "absolute_poses",
    "make_relative",
    "position_error",
    "orientation_error",
    "average_pose",
]


# | |q|^2 - 1 | allowed for a quaternion used as a rotation (see the module docstring)
_UNIT_TOL = {np.dtype(np.float32): 1e-5, np.dtype(np.float64): 1e-9}


# ---------------------------------------------------------------------------------------
# argument checks: every error names the argument and says what was expected


def _check(name, x, last, what, like=None, like_name=None):
    """x: a finite float32/float64 ndarray whose last dimension is one of `last`
    (and of like's dtype, when given)."""
    _checks.float_array(name, x, like, like_name)
    if x.ndim == 0 or x.shape[-1] not in last:
        want = " or ".join(str(n) for n in last)
        raise ValueError(f"{name} must have last dimension {want} ({what}), got shape {x.shape}")
    return _checks.finite(name, x)


def _broadcast(name_a, a_shape, name_b, b_shape):
    try:
        return np.broadcast_shapes(a_shape, b_shape)
    except ValueError:
        raise ValueError(f"{name_a} of shape {a_shape} and {name_b} of shape {b_shape} "
                         "do not broadcast against each other") from None


def _check_unit(name, q):
    """q (..., 4) must be a unit quaternion up to _UNIT_TOL."""
    n2 = np.einsum("...i,...i->...", q, q)  # (...) |q|^2
    dev = np.abs(n2 - 1)
    if dev.size and dev.max() > _UNIT_TOL[q.dtype]:
        i = np.unravel_index(np.argmax(dev), dev.shape)
        raise ValueError(f"{name} must hold unit quaternions (| |q|^2 - 1 | <= {_UNIT_TOL[q.dtype]:g} in "
                         f"{q.dtype}), but at index {tuple(map(int, i))} |q|^2 = {float(n2[i])!r}: "
                         "normalise it first with quat_normalize")


def _pow2_split(q):
    """q (..., 4) = qs * 2^k per quaternion: qs (..., 4) with its largest |component| in [0.5, 1),
    k (..., 1) integers. Exact (a power of two only moves the exponent), except that components
    more than the dtype's exponent range (2^-126 in float32) below the largest become subnormal
    and round: negligible next to the largest. A zero quaternion gives qs = 0, k = 0."""
    k = np.frexp(np.abs(q).max(axis=-1, keepdims=True))[1]  # (..., 1)
    return np.ldexp(q, -k).astype(q.dtype, copy=False), k  # (..., 4), (..., 1)


def _norm3(v):
    """|v| over the last axis of (..., 3), by hypot: no overflow or underflow of the squares."""
    return np.hypot(np.hypot(v[..., 0], v[..., 1]), v[..., 2])


# ---------------------------------------------------------------------------------------
# the quaternion algebra, unchecked: every public function checks its arguments once and
# then composes these


def _mul(a, b):
    """Hamilton product a * b, (..., 4) x (..., 4) -> (..., 4), broadcasting.

    The terms are grouped in pairs that cancel exactly for q * conj(q) and conj(q) * q,
    so those products have a vector part of exactly 0 (the relative pose of the reference
    view is the identity rotation to the bit, and orientation_error(q, q) is exactly 0)."""
    aw, ax, ay, az = (a[..., i] for i in range(4))
    bw, bx, by, bz = (b[..., i] for i in range(4))
    w = aw * bw - ax * bx - ay * by - az * bz
    x = (aw * bx + ax * bw) + (ay * bz - az * by)
    y = (aw * by + ay * bw) + (az * bx - ax * bz)
    z = (aw * bz + az * bw) + (ax * by - ay * bx)
    return np.stack([w, x, y, z], axis=-1)  # (..., 4)


def _conj(q):
    return q * np.array([1, -1, -1, -1], dtype=q.dtype)  # (w, -x, -y, -z)


def _rotate_expanded(q, v):
    """vec(q * (0, v) * conj(q)) for unit q, expanded: with u = vec(q), t = 2 u x v, the rotated
    vector is v + w t + u x t (18 multiplies instead of the 32 of two Hamilton products; equal for
    |q| = 1). (..., 4) x (..., 3) -> (..., 3)."""
    w, u = q[..., :1], q[..., 1:]  # (..., 1), (..., 3)
    t = 2 * np.cross(u, v)  # (..., 3)
    return v + w * t + np.cross(u, t)  # (..., 3)


def _rotate(q, v):
    """vec(q * (0, v) * conj(q)) for unit q, (..., 4) x (..., 3) -> (..., 3), broadcasting.

    The rotation keeps |v|, but the expanded formula's t = 2 u x v reaches 2 |v|: a v near the
    dtype's largest value (float32 (3e38, 3e38, 0) turned 90 degrees) overflows in between although
    its rotation fits. Those vectors are rotated again as v / 16 and scaled back (powers of two:
    exact, but for components that become subnormal, negligible next to |v|); every intermediate
    then stays below max / 1.8 (|v| <= sqrt(3) max, |t|, |w t|, |u x t| <= 2 |v|). A rotation that
    really does not fit stays inf, for the caller's finite_result. Elsewhere bit for bit the formula."""
    with np.errstate(over="ignore", invalid="ignore"):
        out = _rotate_expanded(q, v)  # (..., 3)
    over = ~np.isfinite(out).all(axis=-1, keepdims=True)  # (..., 1)
    if over.any():
        with np.errstate(over="ignore", under="ignore"):
            small = _rotate_expanded(q, np.ldexp(v, -4).astype(v.dtype, copy=False))
            out = np.where(over, np.ldexp(small, 4).astype(v.dtype, copy=False), out)
    return out


def _normalize(q, eps):
    """TF's l2_normalize q / sqrt(max(|q|^2, eps)) = q / max(|q|, floor), floor = sqrt(eps),
    for any finite q (..., 4) -> (..., 4).

    |q| itself may overflow (float32 components of 3e38: |q| > 3.4e38) or be a subnormal that
    keeps few digits (1e-45), so q is first split as qs * 2^k (_pow2_split) and the norm taken
    of qs, |qs| in [0.5, 2]: then |q| >= floor  <=>  |qs| >= floor / 2^k, and there the result is
    qs / |qs| (= q / |q|: a power of two cancels; bit for bit the unscaled formula wherever |q|
    is representable, since hypot and division commute with powers of two). Below the floor it
    is q / floor, as in TF. A zero quaternion gives zero, not NaN."""
    qs, k = _pow2_split(q)  # (..., 4), (..., 1)  q = qs 2^k
    ns = np.hypot(np.hypot(qs[..., 0:1], qs[..., 1:2]), np.hypot(qs[..., 2:3], qs[..., 3:4]))  # (..., 1) |q| / 2^k
    # floor in q's dtype (as TF's eps), and at least the smallest subnormal: only q = 0 is below
    # that, so an eps whose root underflows the dtype still maps zero to zero
    floor = max(q.dtype.type(np.sqrt(eps)), np.finfo(q.dtype).smallest_subnormal)
    with np.errstate(over="ignore"):  # floor / 2^k = inf: then |q| is far below the floor, as compared
        above = ns >= np.ldexp(floor, -k)  # (..., 1)  |q| >= floor
    unit = qs / np.where(above, ns, 1)  # (..., 4)  q / |q| where above (ns >= floor / 2^k > 0 there)
    small = np.where(above, 0, q) / floor  # (..., 4)  q / floor where not above (no overflow elsewhere)
    return np.where(above, unit, small)  # (..., 4)


def _canonical(q):
    # docs/math.md §3 and the published quaternion_remove_sign: flip where w < 0 only
    # (w == 0 and w == -0.0 keep their sign)
    return np.where(q[..., :1] < 0, -q, q)


# ---------------------------------------------------------------------------------------
# quaternions


def quat_mul(a, b):
    """Hamilton product a * b.   a (..., 4), b (..., 4) -> (..., 4), broadcasting.

    (w, x, y, z) order: 1 = (1, 0, 0, 0), i = (0, 1, 0, 0), j, k; i*j = k, j*i = -k.
    Any quaternions (not only unit ones)."""
    _check("a", a, (4,), "a quaternion (w, x, y, z)")
    _check("b", b, (4,), "a quaternion (w, x, y, z)", like=a, like_name="a")
    _broadcast("a", a.shape, "b", b.shape)
    with np.errstate(over="ignore", invalid="ignore"):  # checked
        return _checks.finite_result("quat_mul", _mul(a, b))


def quat_conj(q):
    """Conjugate (w, -x, -y, -z).   q (..., 4) -> (..., 4). The inverse of a unit quaternion."""
    _check("q", q, (4,), "a quaternion (w, x, y, z)")
    return _conj(q)


def quat_rotate(q, v):
    """Rotate 3-vectors by unit quaternions: vec(q * (0, v) * conj(q)).

    q (..., 4) unit, v (..., 3), broadcasting -> (..., 3). q must be unit (see the module
    docstring: a non-unit q raises ValueError). Argument order (q, v); the published
    `quaternion_rotate(point, quaternion)` takes them the other way round."""
    _check("q", q, (4,), "a quaternion (w, x, y, z)")
    _check("v", v, (3,), "3-vectors", like=q, like_name="q")
    _broadcast("q", q.shape[:-1], "v", v.shape[:-1])
    _check_unit("q", q)
    with np.errstate(over="ignore", invalid="ignore"):  # checked
        return _checks.finite_result("quat_rotate", _rotate(q, v))


def quat_normalize(q, eps=1e-12):
    """q / sqrt(max(|q|^2, eps)), TF's l2_normalize (docs/math.md §3: eps 1e-12).

    q (..., 4) -> (..., 4). A zero quaternion gives zero (not NaN); |q| < sqrt(eps) = 1e-6
    gives q / 1e-6, a quaternion shorter than 1, as in TF. Any finite q normalises, also one
    whose |q| exceeds the dtype's largest value (float32 (3e38, 3e38, 0, 0) gives
    (0.7071, 0.7071, 0, 0)) or is subnormal (with an eps below |q|^2): |q| is taken of q scaled
    by a power of two (_normalize)."""
    _check("q", q, (4,), "a quaternion (w, x, y, z)")
    if not (np.isfinite(eps) and eps > 0):
        raise ValueError(f"eps must be finite and > 0, got {eps!r}")
    return _normalize(q, float(eps))


def quat_canonical(q):
    """The sign representative of q: -q where w < 0, else q (docs/math.md §3, the published
    `quaternion_remove_sign`).   q (..., 4) -> (..., 4).

    q and -q are the same rotation. At w == 0 exactly (either sign of zero) q is returned
    unchanged, as in the published code, so there q and -q stay distinct."""
    _check("q", q, (4,), "a quaternion (w, x, y, z)")
    return _canonical(q)


# ---------------------------------------------------------------------------------------
# poses


def _check_pose(name, p, like=None, like_name=None):
    _check(name, p, (7,), "a pose: xyz then the quaternion (w, x, y, z)", like=like, like_name=like_name)
    _check_unit(f"the quaternions of {name}", p[..., 3:])


def relative_poses(poses, ref):
    """Poses in the frame of the camera ref (docs/math.md §3).

    poses (..., 7), ref (..., 7) broadcasting against poses (e.g. poses (B, N, 7) and
    ref (B, 1, 7)) -> (..., 7). With (t0, q0) = ref and (xyz, q) = poses:
        xyz' = rotate(conj(q0), xyz - t0),   q' = conj(q0) * q.
    All quaternions must be unit. The inverse is absolute_poses."""
    _check_pose("poses", poses)
    _check_pose("ref", ref, like=poses, like_name="poses")
    _broadcast("poses", poses.shape, "ref", ref.shape)
    t0, q0i = ref[..., :3], _conj(ref[..., 3:])  # (..., 3), (..., 4)
    with np.errstate(over="ignore", invalid="ignore"):  # checked
        xyz = _rotate(q0i, poses[..., :3] - t0)  # (..., 3)
    q = _mul(q0i, poses[..., 3:])  # (..., 4)
    return _checks.finite_result("relative_poses", np.concatenate([xyz, q], axis=-1))  # (..., 7)


def absolute_poses(rel, ref):
    """The inverse of relative_poses: xyz = rotate(q0, xyz') + t0, q = q0 * q'.

    rel (..., 7), ref (..., 7) broadcasting -> (..., 7). All quaternions must be unit."""
    _check_pose("rel", rel)
    _check_pose("ref", ref, like=rel, like_name="rel")
    _broadcast("rel", rel.shape, "ref", ref.shape)
    t0, q0 = ref[..., :3], ref[..., 3:]
    with np.errstate(over="ignore", invalid="ignore"):  # checked
        xyz = _rotate(q0, rel[..., :3]) + t0  # (..., 3)
    q = _mul(q0, rel[..., 3:])  # (..., 4)
    return _checks.finite_result("absolute_poses", np.concatenate([xyz, q], axis=-1))  # (..., 7)


def make_relative(poses, *, canonical=True):
    """A sequence of views made relative to its first view: the model's pose input.

    poses (..., N, 7), e.g. (B, N, 7) -> rel (..., N, 7), ref (..., 7) = poses[..., 0, :]
    (a copy). rel = relative_poses(poses, ref[..., None, :]), so rel[..., 0, :] is the
    identity pose (0, 0, 0, 1, 0, 0, 0).

    canonical=True then L2-normalises and sign-canonicalises the relative quaternions, as
    the published input pipeline does (`process_batch`: quaternion_normalize, then
    quaternion_remove_sign, after making the poses relative): the pose MLP is not
    sign-invariant, so this is part of the model's input. absolute_poses(rel, ref) then
    recovers the poses' rotations up to the sign of the quaternion."""
    _check_pose("poses", poses)
    if poses.ndim < 2 or poses.shape[-2] == 0:
        raise ValueError(f"poses must be (..., N, 7) with N >= 1 views, got shape {poses.shape}")
    ref = poses[..., 0, :].copy()  # (..., 7)
    t0, q0i = ref[..., None, :3], _conj(ref[..., None, 3:])  # (..., 1, 3), (..., 1, 4)
    with np.errstate(over="ignore", invalid="ignore"):  # checked
        xyz = _rotate(q0i, poses[..., :3] - t0)  # (..., N, 3)
    q = _mul(q0i, poses[..., 3:])  # (..., N, 4)
    if canonical:
        q = _canonical(_normalize(q, 1e-12))
    return _checks.finite_result("make_relative", np.concatenate([xyz, q], axis=-1)), ref  # (..., N, 7), (..., 7)


# ---------------------------------------------------------------------------------------
# metrics (docs/math.md §6)


def _check_pair(n1, a, n2, b, width, kind):
    """a, b: both (..., width) arrays of one kind, or both (..., 7) poses, of one dtype, broadcasting."""
    what = {"positions": "positions xyz, or poses", "quaternions": "quaternions (w, x, y, z), or poses"}[kind]
    _check(n1, a, (width, 7), what)
    _check(n2, b, (width, 7), what, like=a, like_name=n1)
    if a.shape[-1] != b.shape[-1]:
        raise ValueError(f"{n1} and {n2} must both be {kind} (..., {width}) or both poses (..., 7), "
                         f"got shapes {a.shape} and {b.shape}")
    _broadcast(n1, a.shape, n2, b.shape)


def position_error(p1, p2):
    """Euclidean distance |xyz1 - xyz2|.   p1, p2 (..., 3) positions or (..., 7) poses (only
    xyz is used), both the same kind, broadcasting -> (...). Computed by hypot (no overflow
    of the squares)."""
    _check_pair("p1", p1, "p2", p2, 3, "positions")
    with np.errstate(over="ignore", invalid="ignore"):  # checked
        return _checks.finite_result("position_error", _norm3(p1[..., :3] - p2[..., :3]))  # (...)


def orientation_error(q1, q2):
    """The angle in degrees of the rotation q1 * conj(q2), in [0, 180] (docs/math.md §6).

    q1, q2 (..., 4) quaternions or (..., 7) poses (only the quaternion is used), both the
    same kind, broadcasting -> (...).

        angle = 2 * atan2(|vec(r)|, |w(r)|),   r = q1 * conj(q2).

    The published metric is 2 * asin(|vec(r)|). Both are sign-invariant (q and -q give one
    angle) and agree for unit inputs, but the asin form is NaN when rounding makes
    |vec(r)| > 1 and loses half its digits near 180 degrees (asin is flat at 1), and the
    2 * acos(w) form loses everything near 0 (a 1e-9 rad rotation has w = 1 in float64).
    atan2 adds no error of its own at any angle and never leaves [0, 180]; what is left is the
    rounding of r, a few units of roundoff in radians, absolute: for q1 within a few ulp of q2
    the components of vec(r) cancel, and the angle there is right only to that absolute error
    (tests/test_geometry.py holds it to 8 eps rad), not to full relative accuracy.
    It depends only on the direction of r, so q1 and q2 need not be unit; zero quaternions
    (no rotation at all) raise ValueError. Each quaternion is first scaled by a power of two
    (exact: the same direction) to a largest component in [0.5, 1), so quaternions of any size,
    1e-300 or 1e300, give the angle to full precision instead of overflowing or losing digits
    to subnormal products."""
    _check_pair("q1", q1, "q2", q2, 4, "quaternions")
    a, b = q1[..., -4:], q2[..., -4:]
    for name, q in (("q1", a), ("q2", b)):
        if (q == 0).all(axis=-1).any():
            raise ValueError(f"{name} contains a zero quaternion: it is no rotation, the angle is undefined")
    with np.errstate(under="ignore"):  # components far below the largest may become subnormal: negligible
        # each scaled to a largest |component| in [0.5, 1): the same directions, and their
        # product neither overflows nor loses digits to subnormals
        r = _mul(_pow2_split(a)[0], _conj(_pow2_split(b)[0]))  # (..., 4)
    s, c = _norm3(r[..., 1:]), np.abs(r[..., 0])  # (...) |vec(r)|, |w(r)| >= 1/16 together: never 0/0
    return np.degrees(2 * np.arctan2(s, c))  # (...)


# ---------------------------------------------------------------------------------------
# averaging the per-token predictions of a view


def _mean(x, axis):
    """x.mean(axis) for finite x, without a spurious overflow: the mean lies between the smallest
    and the largest x, so it is finite, but the sum may overflow (float32 2e38 + 2e38). Where it
    does, the mean is taken again of x / 2^c with 2^c >= 2n (n = x.shape[axis]): every partial
    sum of n terms then stays below max/2, and dividing by a power of two is exact (but for
    subnormals, negligible next to a sum that overflowed). Elsewhere it is x.mean itself."""
    with np.errstate(over="ignore", invalid="ignore"):  # the overflowed entries are replaced below
        m = x.mean(axis=axis)  # x's shape without axis
    over = ~np.isfinite(m)
    if over.any():
        c = (2 * x.shape[axis] - 1).bit_length()  # 2^c >= 2n
        with np.errstate(under="ignore"):
            m_scaled = np.ldexp(x, -c).astype(x.dtype, copy=False).mean(axis=axis)
        # only rounding at the dtype's very top could overflow here; finite_result raises then
        with np.errstate(over="ignore"):
            m = np.where(over, np.ldexp(m_scaled, c).astype(x.dtype, copy=False), m)
    return m


def average_pose(poses, axis=-2):
    """The mean pose over `axis` (docs/math.md §3, the published `reduce`/`quaternion_reduce_mean`).

    poses (..., 7) -> the same shape without `axis` (which must not be the last one).
    xyz: the arithmetic mean, finite for every finite input (float32 positions of 2e38 whose
    sum overflows still average: _mean). Quaternions: normalised (quat_normalize, eps 1e-12),
    sign-canonicalised (quat_canonical), averaged, normalised and canonicalised again.
    Quaternions need not be unit. If the canonicalised quaternions cancel (e.g. all zero, or
    opposite 180-degree rotations with w == 0) the mean is the zero quaternion, not NaN, as
    in the published code. Near w == 0 the sign choice splits nearby rotations into
    opposite hemispheres, so this average is only meaningful for predictions that agree
    (which is what it is used for: the L token predictions of one view)."""
    _check("poses", poses, (7,), "a pose: xyz then the quaternion (w, x, y, z)")
    if isinstance(axis, (bool, np.bool_)) or not isinstance(axis, (int, np.integer)):
        raise TypeError(f"axis must be an integer, got {type(axis).__name__}")
    nd = poses.ndim
    if not -nd <= axis < nd or axis % nd == nd - 1:
        raise ValueError(f"axis must name one of the leading axes of poses {poses.shape} "
                         f"(not the last, the pose itself), got {axis}")
    axis = int(axis) % nd
    if poses.shape[axis] == 0:
        raise ValueError(f"poses has no entries along axis {axis}: shape {poses.shape}")
    xyz = _mean(poses[..., :3], axis)  # (..., 3)
    q = _canonical(_normalize(poses[..., 3:], 1e-12))  # (..., 4)
    q = _canonical(_normalize(q.mean(axis=axis), 1e-12))  # (..., 4)
    return _checks.finite_result("average_pose", np.concatenate([xyz, q], axis=-1))  # (..., 7)
