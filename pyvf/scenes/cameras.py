"""Cameras of the Shepard-Metzler scenes: where they stand, how they look, and GQN's camera form.

    pos = sample_camera_positions(rng, V)     # (V, 3)   on the sphere |p| = CAMERA_RADIUS
    poses = look_at_poses(pos)                # (V, 7)   xyz + unit quaternion (w, x, y, z)
    R = pose_matrix(poses[..., 3:])           # (V, 3, 3) camera-to-world rotation
    poses = gqn_to_pose(cams)                 # (..., 5) GQN (x, y, z, yaw, pitch) -> (..., 7)
    cams = pose_to_gqn(poses)                 # (..., 7) -> (..., 5)

Conventions (tested in tests/test_scenes.py):

* **World frame (pyvf's, the published ViewFormer's):** right-handed, units of one cube
  side, the object's centroid at the origin, **up is -y**: the frame the published code converts
  GQN's cameras into (`fix_legacy_gqn_cameras`), as for the real SM7.
* **Camera frame (OpenCV):** x right, y down, z forward (the optical axis, the camera looks
  along its local +z). A pixel (row i, column j) of an H x W image looks along
  ((j + 0.5 - W/2) / f, (i + 0.5 - H/2) / f, 1) in the camera frame, with the focal length
  f = (min(H, W) / 2) / TAN_HALF_FOV pixels: square pixels, TAN_HALF_FOV fixes the field of
  view across the shorter side (both sides of the default square images).
* **Pose:** camera position xyz (world), then the sign-canonical (w >= 0) unit quaternion
  (w, x, y, z) of the camera-to-world rotation: a camera-frame vector v points along
  quat_rotate(q, v) in the world.
* **Cameras of a scene:** on the sphere of radius CAMERA_RADIUS = 10 around the origin,
  looking at the origin, no roll (the camera's x axis is horizontal, its y axis points
  down as far as it can), elevation within +-MAX_ELEVATION_DEG = 60 degrees, direction
  uniform on that band of the sphere. With TAN_HALF_FOV = 0.39 (a field of view of
  2 atan(0.39) = 42.6 degrees) the whole object is always in the frame, as large as that
  allows: no point of a 7-cube chain is farther than sqrt(12.75) = 3.571 from its centroid
  (a cube centre c has |c|_2 <= |c|_1 <= 3, the mean of its lattice distances 0..6 along
  the chain, so a corner c + e, |e_i| = 1/2, has |c + e|^2 <= |c|^2 + |c|_1 + 3/4 <= 12.75;
  the straight chain's end cubes attain it), and that sphere seen from distance 10 lies in
  the cone of half-angle tangent 3.571 / sqrt(100 - 12.75) = 0.382 < 0.39.
* **GQN form** (x, y, z, yaw, pitch), radians, in GQN's world frame where **z is up**:
  yaw is the azimuth of the viewing direction about GQN's z axis (0 = looking along +x,
  pi/2 = along +y), pitch its elevation (positive = looking up); gqn_to_pose is the published
  conversion, pose_to_gqn its inverse for roll-free cameras (every camera here).

Determinism: sampling and look-at use only exactly rounded IEEE operations (+ - * /, sqrt,
comparisons), never a transcendental function or a BLAS call: the same bits on every machine.
"""

import numpy as np

from ..geometry import _canonical

__all__ = ["CAMERA_RADIUS", "TAN_HALF_FOV", "MAX_ELEVATION_DEG", "sample_camera_positions", "look_at_poses",
           "pose_matrix", "gqn_to_pose", "pose_to_gqn"]

CAMERA_RADIUS = 10.0  # distance of every camera from the object's centroid, in cube sides
TAN_HALF_FOV = 0.39  # tan(vertical field of view / 2): 42.6 degrees, the whole object always fits
MAX_ELEVATION_DEG = 60  # |elevation| of a camera above the object's horizontal plane
_MAX_SIN2_ELEVATION = 0.75  # sin(60 degrees)^2, exact in binary: the sampler compares with it


# sampling and look-at (exactly rounded operations only)
def sample_camera_positions(rng, n, radius=CAMERA_RADIUS):
    """n camera positions (n, 3), uniform on the band |elevation| <= 60 degrees of |p| = radius.
    By rejection: u uniform in [-1, 1]^3, kept when 1e-6 < |u|^2 <= 1 (inside the ball: a uniform
    direction) and u_y^2 <= sin(60 deg)^2 |u|^2 (up is -y), then u / |u|; drawn in batches of 2n,
    kept in order. No Gaussian: its tails use exp/log, not exactly rounded."""
    out = np.empty((0, 3))
    while len(out) < n:
        u = rng.random((2 * n, 3)) * 2 - 1  # (2n, 3) exact: a double in [0, 1) times 2, minus 1
        r2 = u[:, 0] * u[:, 0] + u[:, 1] * u[:, 1] + u[:, 2] * u[:, 2]  # (2n,)
        keep = (r2 > 1e-6) & (r2 <= 1) & (u[:, 1] * u[:, 1] <= _MAX_SIN2_ELEVATION * r2)
        u, r2 = u[keep], r2[keep]
        out = np.concatenate([out, u / np.sqrt(r2)[:, None]])
    return out[:n] * radius  # (n, 3)


def look_at_poses(positions):
    """Poses (..., 7) of cameras at `positions` (..., 3), not on the vertical axis, looking at the
    origin without roll; the rotation's columns are the camera's axes [right, down, forward]:
        forward = -p / |p|,  right = (forward x up) / |.| with up = (0, -1, 0),
        down = forward x right."""
    p = positions
    px, py, pz = p[..., 0], p[..., 1], p[..., 2]
    horiz2 = px * px + pz * pz  # (...)
    if (horiz2 <= 1e-12 * (horiz2 + py * py)).any():
        raise ValueError("positions must not lie on the vertical (y) axis: looking straight up or "
                         "down, a camera without roll is undefined")
    norm = np.sqrt(horiz2 + py * py)
    fx, fy, fz = -px / norm, -py / norm, -pz / norm  # forward (optical axis)
    h = np.sqrt(fx * fx + fz * fz)
    rx, rz = fz / h, -fx / h  # right = forward x (0, -1, 0), normalised; its y is 0
    dx, dy, dz = fy * rz, fz * rx - fx * rz, -fy * rx  # down = forward x right
    zero = np.zeros_like(rx)
    # R (camera-to-world) by rows; its columns are right, down, forward
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = (rx, dx, fx), (zero, dy, fy), (rz, dz, fz)
    # its quaternion by Shepperd's method: of 4w^2 = 1 + tr, 4x^2 = 1 + R00 - R11 - R22, ..., take
    # the largest (the best conditioned square root) and get the other components from the
    # off-diagonal sums and differences; then normalised (R is orthonormal only to rounding), w >= 0
    cands = np.stack([1 + r00 + r11 + r22, 1 + r00 - r11 - r22,
                      1 + r11 - r00 - r22, 1 + r22 - r00 - r11])  # (4, ...) 4*(w, x, y, z)^2
    k = np.argmax(cands, axis=0)  # (...) which component is largest (first on ties)
    s = 2 * np.sqrt(np.max(cands, axis=0))  # (...) 4 * that component
    a, b, c = r21 - r12, r02 - r20, r10 - r01  # 4w * (x, y, z)
    d, e, g = r01 + r10, r02 + r20, r12 + r21  # 4 * (xy, xz, yz)
    q = np.stack([
        np.choose(k, [s / 4, a / s, b / s, c / s]),
        np.choose(k, [a / s, s / 4, d / s, e / s]),
        np.choose(k, [b / s, d / s, s / 4, g / s]),
        np.choose(k, [c / s, e / s, g / s, s / 4]),
    ], axis=-1)  # (..., 4)
    n = np.sqrt(q[..., 0] * q[..., 0] + q[..., 1] * q[..., 1] + q[..., 2] * q[..., 2] + q[..., 3] * q[..., 3])
    return np.concatenate([p, _canonical(q / n[..., None])], axis=-1)  # (..., 7)


def pose_matrix(q):
    """The rotation matrix of unit quaternions q (..., 4) -> (..., 3, 3), R[..., i, j] = e_i . rotate(q, e_j),
    written out term by term (no BLAS: the same bits on every machine)."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    R = np.stack([
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    ], axis=-1)  # (..., 9)
    return R.reshape(q.shape[:-1] + (3, 3))  # (..., 3, 3)


# GQN's camera form (trig allowed here: not on the rendering path)
def gqn_to_pose(cams):
    """GQN cameras (..., 5) = (x, y, z, yaw, pitch) in GQN's z-up frame -> poses (..., 7), the
    published conversion (fix_legacy_gqn_cameras): xyz = (y, -z, -x) and q = q_y(pi - yaw) *
    q_x(pitch), q_y(t) = (cos t/2, 0, sin t/2, 0), q_x(t) = (cos t/2, sin t/2, 0, 0), made w >= 0."""
    x, y, z, yaw, pitch = (cams[..., i] for i in range(5))
    half_y, half_x = (np.pi - yaw) / 2, pitch / 2
    cy, sy, cx, sx = np.cos(half_y), np.sin(half_y), np.cos(half_x), np.sin(half_x)
    q = np.stack([cy * cx, cy * sx, sy * cx, -sy * sx], axis=-1)  # (..., 4) q_y(pi - yaw) * q_x(pitch)
    return np.concatenate([np.stack([y, -z, -x], axis=-1), _canonical(q)], axis=-1)  # (..., 7)


def pose_to_gqn(poses):
    """Poses (..., 7) -> GQN cameras (..., 5) = (x, y, z, yaw, pitch), the inverse of gqn_to_pose.
    Position (x, y, z)_GQN = (-z, x, -y) of the pose; the optical axis f = rotate(q, (0, 0, 1)),
    written in GQN's frame as g = (-f_z, f_x, -f_y), gives yaw = atan2(g_y, g_x) in [-pi, pi]
    and pitch = atan2(g_z, hypot(g_x, g_y)) in [-pi/2, pi/2] (GQN cameras have no roll)."""
    R = pose_matrix(poses[..., 3:])  # (..., 3, 3)
    f = R[..., :, 2]  # (..., 3) the optical axis in pyvf's world
    gx, gy, gz = -f[..., 2], f[..., 0], -f[..., 1]
    yaw = np.arctan2(gy, gx)
    pitch = np.arctan2(gz, np.hypot(gx, gy))
    px, py, pz = poses[..., 0], poses[..., 1], poses[..., 2]
    return np.stack([-pz, px, -py, yaw, pitch], axis=-1)  # (..., 5)

