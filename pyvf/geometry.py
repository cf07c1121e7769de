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

Conventions (tested in tests/test_geometry.py):

* Inputs are float32 or float64 arrays; the result has the input's dtype. Integer arrays, a
  wrong last dimension and NaN/inf raise TypeError/ValueError naming the argument.
* A quaternion used as a rotation must be unit: | |q|^2 - 1 | <= 1e-5 (float32) or 1e-9
  (float64), far above the rounding of any chain of products; else ValueError (for a non-unit
  q the formula scales by |q|^2, and normalising quietly would hide a data bug).
* quat_canonical multiplies by -1 where w < 0 only, as the published `quaternion_remove_sign`:
  at w == 0 q and -q stay different (the model's pose predictions and average_pose rely on it).
"""

import numpy as np

from . import _checks

__all__ = ["quat_mul", "quat_conj", "quat_rotate", "quat_normalize", "quat_canonical", "relative_poses",
           "absolute_poses", "make_relative", "position_error", "orientation_error", "average_pose"]

# | |q|^2 - 1 | allowed for a quaternion used as a rotation (see the module docstring)
_UNIT_TOL = {np.dtype(np.float32): 1e-5, np.dtype(np.float64): 1e-9}


# argument checks: every error names the argument
def _check(name, x, last):  # a finite float32/float64 ndarray whose last dimension is one of `last`
    _checks.float_array(name, x)
    if x.ndim == 0 or x.shape[-1] not in last:
        raise ValueError(f"{name} must have last dimension {' or '.join(map(str, last))}, got shape {x.shape}")
    return _checks.finite(name, x)


def _check_unit(name, q):  # q (..., 4): unit quaternions up to _UNIT_TOL
    n2 = np.einsum("...i,...i->...", q, q)  # (...) |q|^2
    if n2.size and np.abs(n2 - 1).max() > _UNIT_TOL[q.dtype]:
        raise ValueError(f"{name} must hold unit quaternions (| |q|^2 - 1 | <= {_UNIT_TOL[q.dtype]:g} in "
                         f"{q.dtype}), not |q|^2 = {n2.ravel()[np.argmax(np.abs(n2 - 1))]!r}: normalise it "
                         "first with quat_normalize")


def _check_pose(name, p):
    _check(name, p, (7,))
    _check_unit(f"the quaternions of {name}", p[..., 3:])


# the quaternion algebra, unchecked: each public function checks its arguments, then composes these
def _norm3(v):
    """|v| over the last axis of (..., 3), by hypot: no overflow or underflow of the squares."""
    return np.hypot(np.hypot(v[..., 0], v[..., 1]), v[..., 2])


def _mul(a, b):
    """Hamilton product a * b, (..., 4) x (..., 4) -> (..., 4), broadcasting. The terms are
    grouped in pairs that cancel exactly for q * conj(q) and conj(q) * q, so those have a vector
    part of exactly 0 (the reference view's relative rotation is the identity to the bit)."""
    aw, ax, ay, az = (a[..., i] for i in range(4))
    bw, bx, by, bz = (b[..., i] for i in range(4))
    w = aw * bw - ax * bx - ay * by - az * bz
    x = (aw * bx + ax * bw) + (ay * bz - az * by)
    y = (aw * by + ay * bw) + (az * bx - ax * bz)
    z = (aw * bz + az * bw) + (ax * by - ay * bx)
    return np.stack([w, x, y, z], axis=-1)  # (..., 4)


def _conj(q):
    return q * np.array([1, -1, -1, -1], dtype=q.dtype)  # (w, -x, -y, -z)


def _rotate(q, v):
    """vec(q * (0, v) * conj(q)) for unit q, (..., 4) x (..., 3) -> (..., 3), broadcasting,
    expanded: with u = vec(q), t = 2 u x v, the rotated vector is v + w t + u x t."""
    w, u = q[..., :1], q[..., 1:]  # (..., 1), (..., 3)
    t = 2 * np.cross(u, v)  # (..., 3)
    return v + w * t + np.cross(u, t)  # (..., 3)


def _normalize(q, eps):
    """TF's l2_normalize q / sqrt(max(|q|^2, eps)) = q / max(|q|, sqrt(eps)), q (..., 4); |q| by
    hypot (no underflow of the squares). A zero quaternion gives zero."""
    n = np.hypot(np.hypot(q[..., 0:1], q[..., 1:2]), np.hypot(q[..., 2:3], q[..., 3:4]))  # (..., 1) |q|
    floor = max(q.dtype.type(np.sqrt(eps)), np.finfo(q.dtype).smallest_subnormal)  # > 0: zero maps to zero
    return q / np.maximum(n, floor)  # (..., 4)


def _canonical(q):
    # docs/math.md §3 and the published quaternion_remove_sign: flip where w < 0 only
    return np.where(q[..., :1] < 0, -q, q)


def _relative(poses, ref):
    """poses (..., 7) in the frame of the camera ref (..., 7), unchecked: rotate(conj(q0), xyz - t0),
    conj(q0) * q."""
    q0i = _conj(ref[..., 3:])  # (..., 4)
    xyz = _rotate(q0i, poses[..., :3] - ref[..., :3])  # (..., 3)
    return np.concatenate([xyz, _mul(q0i, poses[..., 3:])], axis=-1)  # (..., 7)


# quaternions
def quat_mul(a, b):
    """Hamilton product a * b of any quaternions.   a (..., 4), b (..., 4) -> (..., 4), broadcasting.
    (w, x, y, z) order: 1 = (1, 0, 0, 0), i = (0, 1, 0, 0), j, k; i*j = k, j*i = -k."""
    return _mul(_check("a", a, (4,)), _check("b", b, (4,)))


def quat_conj(q):
    """Conjugate (w, -x, -y, -z).   q (..., 4) -> (..., 4). The inverse of a unit quaternion."""
    return _conj(_check("q", q, (4,)))


def quat_rotate(q, v):
    """Rotate 3-vectors by unit quaternions: vec(q * (0, v) * conj(q)).   q (..., 4), v (..., 3),
    broadcasting -> (..., 3). The published `quaternion_rotate(point, quaternion)` takes them the
    other way round."""
    _check("q", q, (4,))
    _check_unit("q", q)
    return _rotate(q, _check("v", v, (3,)))


def quat_normalize(q, eps=1e-12):
    """q / sqrt(max(|q|^2, eps)), TF's l2_normalize (docs/math.md §3: eps 1e-12).   q (..., 4) ->
    (..., 4). A zero quaternion gives zero; |q| < sqrt(eps) gives q / sqrt(eps), as in TF. Any
    finite q normalises, also one whose |q| overflows the dtype or is subnormal (_normalize)."""
    return _normalize(_check("q", q, (4,)), float(eps))


def quat_canonical(q):
    """The sign representative of q: -q where w < 0, else q (docs/math.md §3).   q (..., 4) -> (..., 4)."""
    return _canonical(_check("q", q, (4,)))


# poses
def relative_poses(poses, ref):
    """Poses in the frame of the camera ref (docs/math.md §3).   poses (..., 7), ref (..., 7)
    broadcasting against poses (e.g. (B, N, 7) and (B, 1, 7)) -> (..., 7). With (t0, q0) = ref:
        xyz' = rotate(conj(q0), xyz - t0),   q' = conj(q0) * q.
    All quaternions must be unit. The inverse is absolute_poses."""
    _check_pose("poses", poses)
    _check_pose("ref", ref)
    return _relative(poses, ref)  # (..., 7)


def absolute_poses(rel, ref):
    """The inverse of relative_poses: xyz = rotate(q0, xyz') + t0, q = q0 * q'.
    rel (..., 7), ref (..., 7) broadcasting -> (..., 7). All quaternions must be unit."""
    _check_pose("rel", rel)
    _check_pose("ref", ref)
    t0, q0 = ref[..., :3], ref[..., 3:]
    xyz = _rotate(q0, rel[..., :3]) + t0  # (..., 3)
    q = _mul(q0, rel[..., 3:])  # (..., 4)
    return np.concatenate([xyz, q], axis=-1)  # (..., 7)


def make_relative(poses):
    """A sequence of views made relative to its first view: the model's pose input.
    poses (..., N, 7), N >= 1 -> rel (..., N, 7), ref (..., 7) = poses[..., 0, :] (a copy):
    relative_poses(poses, ref), then the relative quaternions L2-normalised and made sign-canonical,
    as the published input pipeline does (`process_batch`): the pose MLP is not sign-invariant, so
    this is part of the model's input. rel[..., 0, :] is the identity pose (0, 0, 0, 1, 0, 0, 0)."""
    _check_pose("poses", poses)
    ref = poses[..., 0, :].copy()  # (..., 7)
    rel = _relative(poses, ref[..., None, :])  # (..., N, 7)
    rel[..., 3:] = _canonical(_normalize(rel[..., 3:], 1e-12))
    return rel, ref  # (..., N, 7), (..., 7)


# metrics (docs/math.md §6)
def position_error(p1, p2):
    """Euclidean distance |xyz1 - xyz2| (by hypot: no overflow of the squares).   p1, p2 (..., 3)
    positions or (..., 7) poses (only xyz is used), broadcasting -> (...)."""
    _check("p1", p1, (3, 7))
    _check("p2", p2, (3, 7))
    return _norm3(p1[..., :3] - p2[..., :3])  # (...)


def orientation_error(q1, q2):
    """The angle in degrees of the rotation q1 * conj(q2), in [0, 180] (docs/math.md §6).
    q1, q2 (..., 4) quaternions or (..., 7) poses (only the quaternion is used), broadcasting
    -> (...).

        angle = 2 * atan2(|vec(r)|, |w(r)|),   r = q1 * conj(q2).

    The published 2 * asin(|vec(r)|) is equal for unit inputs, but NaN when rounding makes
    |vec(r)| > 1 and loses half its digits near 180 degrees; atan2 adds no error at any angle.
    Only r's direction counts, so q1, q2 need not be unit (a zero one raises ValueError)."""
    a, b = _check("q1", q1, (4, 7))[..., -4:], _check("q2", q2, (4, 7))[..., -4:]
    for name, q in (("q1", a), ("q2", b)):
        if (q == 0).all(axis=-1).any():
            raise ValueError(f"{name} contains a zero quaternion: it is no rotation, the angle is undefined")
    r = _mul(a, _conj(b))  # (..., 4)
    s, c = _norm3(r[..., 1:]), np.abs(r[..., 0])  # (...) |vec(r)|, |w(r)|
    return np.degrees(2 * np.arctan2(s, c))  # (...)


# averaging the per-token predictions of a view
def average_pose(poses, axis=-2):
    """The mean pose over `axis`, a leading axis (docs/math.md §3, the published
    `reduce`/`quaternion_reduce_mean`).   poses (..., 7) -> the same shape without `axis`.
    xyz: the arithmetic mean. Quaternions (need not be unit): normalised, sign-canonicalised,
    averaged, normalised and canonicalised again. Canonicalised quaternions that cancel (all zero,
    or opposite 180-degree rotations with w == 0) average to the zero quaternion, not NaN, as in
    the published code. Near w == 0 the sign rule splits nearby rotations into opposite
    hemispheres, so this is meant for predictions that agree (the L token predictions of a view)."""
    _check("poses", poses, (7,))
    if not -poses.ndim <= axis < poses.ndim - 1 or axis == -1:
        raise ValueError(f"axis must name one of the leading axes of poses {poses.shape}, got {axis}")
    xyz = poses[..., :3].mean(axis=axis)  # (..., 3)
    q = _canonical(_normalize(poses[..., 3:], 1e-12))  # (..., 4)
    q = _canonical(_normalize(q.mean(axis=axis), 1e-12))  # (..., 4)
    return np.concatenate([xyz, q], axis=-1)  # (..., 7)
