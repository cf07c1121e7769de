"""Tests of pyvf.scenes (docs/math.md §7): procedural Shepard-Metzler-7 scenes.

Against closed forms and independent oracles: a unit cube seen head-on covers exactly the pixel
square its face projects to, in its face's Lambertian colour; any cube covers the convex hull of
its corners' pinhole projection (written here from quat_rotate, not the renderer's pose_matrix);
the nearer cube hides the farther; every camera looks at the origin without roll; the GQN form
round-trips and matches the published conversion; the object is 7 face-adjacent cells. Then
determinism (bitwise, a pinned sha256), the dataset on disk (round trip, re-render of every stored
pair, damage, Ctrl-C and resume, refusals), and the command.

Shapes: images (V, H, W, 3) uint8, poses (V, 7) = xyz + unit quaternion (w, x, y, z).
"""

import hashlib
import json
import math
import os
import shutil

import numpy as np
import pytest

from pyvf import quat_mul, quat_rotate
from pyvf import scenes as sc
from pyvf.scenes import dataset as dataset_module
from pyvf.cli import build_parser

from conftest import assert_bitwise_equal, assert_close

# Poses are a few exactly rounded operations on O(10) numbers: the optical axis, the unit norm
# and the GQN round trip agree to a few ulp; 1e-12 leaves three orders of magnitude of headroom.
TOL = 1e-12

E_X, E_Y, E_Z = np.eye(3)
BG = np.floor(np.array(sc.BACKGROUND) * 255 + 0.5).astype(np.uint8)
MARGIN = 1e-3  # pixels: pixel centres this close to a silhouette's edge are not judged


def to_uint8(v):
    """The renderer's quantisation, restated: floor(255 clip(v, 0, 1) + 0.5)."""
    return np.floor(np.clip(np.asarray(v, dtype=np.float64), 0, 1) * 255 + 0.5).astype(np.uint8)


def face_colour(colour, normal):
    """Closed-form colour of a face with outward normal `normal` under the module's light."""
    nl = float(np.dot(normal, sc.LIGHT_DIR))
    return to_uint8(np.asarray(colour) * (sc.AMBIENT + sc.DIFFUSE * max(0.0, nl) + sc.BACK * max(0.0, -nl)))


def axis_quat(axis, angle):
    """The unit quaternion of a rotation by `angle` about the unit `axis` (built here, not in pyvf)."""
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * np.asarray(axis, dtype=np.float64)])


def wrap(a):
    """An angle difference into [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


def project(points, pose, H, W):
    """Pinhole projection of world points (N, 3) by a pose (7,), written from the docs' convention:
    camera-frame coordinates c_k = (X - p) . rotate(q, e_k), pixel (x, y) = f c_xy / c_z + (W, H) / 2,
    where pixel (i, j) has its centre at (j + 0.5, i + 0.5). -> (N, 2) as (x, y), and depths (N,)."""
    p, q = pose[:3], pose[3:]
    axes = np.stack([quat_rotate(q, e) for e in np.eye(3)])  # (3, 3) rows: camera axes in the world
    c = (np.asarray(points, dtype=np.float64) - p) @ axes.T  # (N, 3)
    f = (min(H, W) / 2) / sc.TAN_HALF_FOV
    return np.stack([f * c[:, 0] / c[:, 2] + W / 2, f * c[:, 1] / c[:, 2] + H / 2], axis=1), c[:, 2]


def cube_corners(lo, hi):
    return np.array([[(lo, hi)[a][0], (lo, hi)[b][1], (lo, hi)[c][2]]
                     for a in (0, 1) for b in (0, 1) for c in (0, 1)])  # (8, 3)


def hull_equations(points):
    """The edges of the convex hull of 2-D points (N, 2) -> (F, 3) rows (n_x, n_y, offset), n the
    unit outward normal: n . x + offset <= 0 inside. Andrew's monotone chain, counter-clockwise."""
    def turn(o, a, b):  # > 0: o -> a -> b turns counter-clockwise
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    def chain(pts):
        out = []
        for p in pts:
            while len(out) >= 2 and turn(out[-2], out[-1], p) <= 0:
                out.pop()
            out.append(p)
        return out[:-1]
    pts = np.unique(np.asarray(points, dtype=np.float64), axis=0)  # sorted by x, then y
    v = np.array(chain(pts) + chain(pts[::-1]))  # (F, 2) counter-clockwise
    e = np.roll(v, -1, axis=0) - v  # (F, 2) edges
    n = np.stack([e[:, 1], -e[:, 0]], axis=1) / np.linalg.norm(e, axis=1, keepdims=True)  # outward for CCW
    return np.concatenate([n, -(n * v).sum(axis=1, keepdims=True)], axis=1)


def hull_distance(corners_px, H, W):
    """Signed distance (pixels) of each pixel centre to the convex hull of the projected corners:
    negative inside. -> (H, W)."""
    eq = hull_equations(corners_px)  # (F, 3): unit normal . x + offset <= 0 inside
    x = np.arange(W) + 0.5
    y = np.arange(H) + 0.5
    pts = np.stack(np.meshgrid(x, y), axis=-1)  # (H, W, 2)
    return (pts @ eq[:, :2].T + eq[:, 2]).max(axis=-1)


def silhouette(cells, pose, H, W):
    """Where the union of the cubes' projected hulls surely covers (inside), surely misses (outside)."""
    lo, hi = sc.object_boxes(cells)
    dist = np.full((H, W), np.inf)
    for k in range(len(lo)):
        px, depth = project(cube_corners(lo[k], hi[k]), pose, H, W)
        assert (depth > 0).all()  # the whole cube is in front of the camera
        dist = np.minimum(dist, hull_distance(px, H, W))
    return dist < -MARGIN, dist > MARGIN


def random_pose(rng, distance):
    """A camera at `distance` from the origin looking roughly at it, with an arbitrary roll:
    a random unit quaternion, the camera placed behind the origin along its optical axis plus
    a sideways offset, so the object is off the image centre."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    q = q if q[0] >= 0 else -q
    axes = np.stack([quat_rotate(q, e) for e in np.eye(3)])
    p = -distance * axes[2] + 0.8 * axes[0] - 0.5 * axes[1]  # the origin sits right of and above the centre
    return np.concatenate([p, q])


# ---------------------------------------------------------------------------------------
# rendering


def axis_cameras():
    """Cameras at distance 10 on the six half-axes, looking at the origin: (position, pose).
    On +-x and +-z by look_at_poses; on +-y (where look_at refuses: no roll-free camera looks
    straight down) by an explicit quaternion, a quarter turn about x."""
    out = []
    for p in (10 * E_X, -10 * E_X, 10 * E_Z, -10 * E_Z):
        out.append((p, sc.look_at_poses(p)))
    for p, angle in ((-10 * E_Y, -math.pi / 2), (10 * E_Y, math.pi / 2)):
        out.append((p, np.concatenate([p, axis_quat(E_X, angle)])))
    return out


@pytest.mark.parametrize("size", [64, 33, (24, 40)])
def test_cube_head_on_covers_the_predicted_square(size):
    """The face at distance 9.5 with half-side 0.5 projects to |x|, |y| < f * 0.5 / 9.5 in pixels
    from the image centre (f = (min(H, W)/2) / TAN_HALF_FOV). Pixel centres inside are the face's
    Lambertian colour, all others the background. Size 33 puts the centre column's ray exactly
    parallel to the cube's side faces (the slab test's d == 0 branch)."""
    H, W = (size, size) if isinstance(size, int) else size
    colour = np.array([[0.9, 0.35, 0.6]])
    f = (min(H, W) / 2) / sc.TAN_HALF_FOV
    half = f * 0.5 / (sc.CAMERA_RADIUS - 0.5)  # half-side of the projected square, in pixels
    rows = np.abs(np.arange(H) + 0.5 - H / 2)  # distances of the pixel centres from the centre
    cols = np.abs(np.arange(W) + 0.5 - W / 2)
    # the test is well posed only if no pixel centre lies on the square's edge
    assert np.abs(rows - half).min() > 1e-6 and np.abs(cols - half).min() > 1e-6
    inside = (rows[:, None] < half) & (cols[None, :] < half)  # (H, W)
    assert inside.sum() > 0
    for p, pose in axis_cameras():
        forward = quat_rotate(pose[3:], E_Z)
        assert_close("optical axis", forward, -p / 10, rtol=TOL)
        img = sc.render_views(np.zeros((1, 3), dtype=np.int64), colour, pose[None], size)[0]  # (H, W, 3)
        want = np.where(inside[..., None], face_colour(colour[0], p / 10), to_uint8(sc.BACKGROUND))
        assert_bitwise_equal(f"cube seen from {p}", img, want)


def test_ray_on_a_face_plane_hits_the_closed_box():
    """Boxes are closed: a ray that runs inside a cube's face plane (here the centre ray of a
    33 x 33 image from a camera at x = 0.5, looking along +z) hits the cube, at its -z face.
    The slab test sees 0/0 there and must not let the NaN turn the hit into a miss."""
    colour = np.array([[0.3, 0.8, 0.5]])
    pose = np.array([[0.5, 0.0, -10.0, 1.0, 0.0, 0.0, 0.0]])  # identity rotation: looks along +z
    img = sc.render_views(np.zeros((1, 3), dtype=np.int64), colour, pose, 33)[0]
    assert_bitwise_equal("centre pixel", img[16, 16], face_colour(colour[0], -E_Z))


def test_straight_chain_stays_in_frame():
    """The object farthest from its centroid (7 cubes in a line, corners at sqrt(12.75)) seen from
    random cameras never reaches the image border: every border pixel is background."""
    cells = np.array([[i, 0, 0] for i in range(7)])
    colours = np.full((7, 3), 0.8)
    rng = np.random.default_rng(0)
    poses = sc.look_at_poses(sc.sample_camera_positions(rng, 40))
    imgs = sc.render_views(cells, colours, poses, 64)  # (40, 64, 64, 3)
    bg = to_uint8(sc.BACKGROUND)
    border = np.concatenate([imgs[:, 0], imgs[:, -1], imgs[:, :, 0], imgs[:, :, -1]], axis=1)  # (40, 256, 3)
    assert (border == bg).all()
    assert (imgs != bg).any(axis=-1).sum(axis=(1, 2)).min() > 50  # and the object is there


@pytest.mark.parametrize("seed", [0, 1])
def test_cube_silhouette_is_the_pinhole_projection_of_its_corners(seed):
    """A cube seen by a rolled, off-centre camera covers exactly the pixel centres inside the
    convex hull of its 8 projected corners (the pose's own projection), on a non-square image."""
    rng = np.random.default_rng(seed)
    pose = random_pose(rng, 6.0)
    H, W = 40, 56
    cells = np.zeros((1, 3), dtype=np.int64)
    img = sc.render_views(cells, [[0.9, 0.35, 0.6]], pose[None], (H, W))[0]
    inside, outside = silhouette(cells, pose, H, W)
    assert inside.sum() > 50 and outside.sum() > 50
    covered = (img != BG).any(axis=-1)
    assert covered[inside].all(), "a pixel inside the projected cube shows the background"
    assert not covered[outside].any(), "a pixel outside the projected cube shows the cube"


def test_nearer_cube_hides_the_farther():
    """Two cubes on the camera's axis: from either side the nearer one's colour fills the centre,
    whichever comes first in the cell list, and its whole projected square is its colour."""
    H = W = 48
    colours = np.array([[1.0, 0.2, 0.2], [0.2, 0.2, 1.0]])
    for order in ((0, 1), (1, 0)):
        cells = np.array([[0, 0, 0], [0, 0, 3]], dtype=np.int64)[list(order)]
        cols = colours[list(order)]
        lo, hi = sc.object_boxes(cells)
        for z in (10.0, -10.0):
            pose = sc.look_at_poses(np.array([0.0, 0.0, z]))
            img = sc.render_views(cells, cols, pose[None], (H, W))[0]
            near = int(np.argmax(np.sign(z) * (lo[:, 2] + hi[:, 2])))  # the cube nearer the camera
            px, _ = project(cube_corners(lo[near], hi[near]), pose, H, W)
            surely = hull_distance(px, H, W) < -MARGIN
            assert surely.sum() > 4
            shade = sc.face_shades()[2, 0 if z > 0 else 1]  # the face turned to the camera: normal +-z
            want = np.floor(np.clip(cols[near] * shade, 0, 1) * 255 + 0.5).astype(np.uint8)
            assert (img[surely] == want).all(), f"order {order}, camera z={z}: the farther cube shows through"


@pytest.mark.parametrize("index", [5])
def test_scene_views_are_the_projection_of_their_tagged_poses(index):
    """Every view of a generated scene covers the union of its cubes' projected hulls under the
    pose it is tagged with, and nothing else: the pose is the camera that rendered it."""
    rng = np.random.default_rng([3, index])
    cells, _ = sc.make_object(rng)  # the scene's object: the first draws of its generator
    images, poses = sc.generate_scene(3, index, views=6, size=32)
    for v in range(len(poses)):
        inside, outside = silhouette(cells, poses[v], 32, 32)
        covered = (images[v] != BG).any(axis=-1)
        assert covered[inside].all() and not covered[outside].any(), f"view {v}"


@pytest.mark.parametrize("index", [0, 1, 2])
def test_cameras_look_at_the_origin(index):
    """Every camera of a scene: unit sign-canonical quaternion, at distance CAMERA_RADIUS, optical
    axis rotate(q, e_z) = -p/|p|, no roll (its x axis horizontal, its y axis pointing down),
    elevation within MAX_ELEVATION_DEG."""
    _, poses = sc.generate_scene(5, index, views=15, size=16)
    p, q = poses[:, :3], poses[:, 3:]
    assert np.abs(np.sqrt((q * q).sum(-1)) - 1).max() < TOL
    assert (q[:, 0] >= 0).all()
    r = np.sqrt((p * p).sum(-1))
    assert np.abs(r - sc.CAMERA_RADIUS).max() < TOL * sc.CAMERA_RADIUS
    assert_close("optical axis", quat_rotate(q, E_Z), -p / r[:, None], rtol=TOL)
    assert np.abs(quat_rotate(q, E_X)[:, 1]).max() < TOL  # right is horizontal (up is -y)
    assert (quat_rotate(q, E_Y)[:, 1] > 0).all()  # down points down
    elevation = np.degrees(np.arcsin(-p[:, 1] / r))
    assert np.abs(elevation).max() <= sc.MAX_ELEVATION_DEG
    with pytest.raises(ValueError, match=r"\bpositions\b"):  # on the vertical axis: no roll-free camera
        sc.look_at_poses(np.array([0.0, 5.0, 0.0]))


def test_camera_elevations_cover_the_band():
    """The sampler fills both hemispheres of the band, up to near its edge."""
    pos = sc.sample_camera_positions(np.random.default_rng(1), 2000)
    s = -pos[:, 1] / sc.CAMERA_RADIUS  # sin(elevation)
    limit = math.sin(math.radians(sc.MAX_ELEVATION_DEG))
    assert np.abs(s).max() <= limit + TOL
    assert s.max() > 0.95 * limit and s.min() < -0.95 * limit
    assert abs(s.mean()) < 0.05  # uniform on the band: mean 0, std ~ 0.5


def random_gqn(rng, n):
    """GQN cameras away from the poles (at pitch = +-90 degrees yaw is undefined)."""
    xyz = rng.standard_normal((n, 3)) * 5
    yaw = rng.uniform(-np.pi, np.pi, n)
    pitch = rng.uniform(-1.4, 1.4, n)
    return np.concatenate([xyz, yaw[:, None], pitch[:, None]], axis=1)  # (n, 5)


def test_gqn_round_trips(rng):
    cams = random_gqn(rng, 500)
    back = sc.pose_to_gqn(sc.gqn_to_pose(cams))
    assert_close("gqn xyz", back[:, :3], cams[:, :3], rtol=TOL)
    assert np.abs(wrap(back[:, 3:] - cams[:, 3:])).max() < TOL
    poses = sc.look_at_poses(rng.standard_normal((500, 3)) * 5)
    assert_close("pose", sc.gqn_to_pose(sc.pose_to_gqn(poses.reshape(2, 250, 7))), poses.reshape(2, 250, 7), rtol=TOL)


def test_gqn_matches_the_published_conversion(rng):
    """gqn_to_pose is the published fix_legacy_gqn_cameras: xyz = (y, -z, -x) and
    q = q_y(pi - yaw) * q_x(pitch) (here by pyvf's Hamilton product of axis-angle quaternions
    built in this file), up to the quaternion's sign. Its optical axis is GQN's viewing
    direction (cos yaw cos pitch, sin yaw cos pitch, sin pitch) written in pyvf's frame."""
    cams = random_gqn(rng, 200)
    poses = sc.gqn_to_pose(cams)
    x, y, z, yaw, pitch = cams.T
    assert_bitwise_equal("xyz", poses[:, :3], np.stack([y, -z, -x], axis=1))
    for c, q in zip(cams, poses[:, 3:]):
        want = quat_mul(axis_quat(E_Y, np.pi - c[3]), axis_quat(E_X, c[4]))
        want = want if want[0] >= 0 else -want
        assert_close("quaternion", q, want, rtol=TOL)
    g = np.stack([np.cos(yaw) * np.cos(pitch), np.sin(yaw) * np.cos(pitch), np.sin(pitch)], axis=1)
    assert_close("optical axis", quat_rotate(poses[:, 3:], E_Z), np.stack([g[:, 1], -g[:, 2], -g[:, 0]], axis=1),
                 rtol=TOL)


# ---------------------------------------------------------------------------------------
# the object and determinism


@pytest.mark.parametrize("index", range(5))
def test_object_is_a_self_avoiding_chain(index):
    cells, colours = sc.make_object(np.random.default_rng([11, index]))
    assert cells.shape == (sc.N_CUBES, 3) and cells.dtype == np.int64
    assert len({tuple(c) for c in cells.tolist()}) == sc.N_CUBES  # distinct cells
    steps = np.abs(np.diff(cells, axis=0))
    assert (steps.sum(axis=1) == 1).all()  # each cube shares a face with the previous one
    lo, hi = sc.object_boxes(cells)
    centres = (lo + hi) / 2
    assert np.abs(centres.mean(axis=0)).max() < 1e-15 * 8
    assert_close("centre differences", np.diff(centres, axis=0), np.diff(cells, axis=0).astype(np.float64), rtol=TOL)
    assert_close("unit boxes", hi - lo, np.ones((sc.N_CUBES, 3)), rtol=TOL)
    # the face two neighbours share is one float: no hairline gap between them
    for k in range(sc.N_CUBES - 1):
        a = int(np.flatnonzero(cells[k + 1] != cells[k])[0])
        shared = (hi[k, a], lo[k + 1, a]) if cells[k + 1, a] > cells[k, a] else (lo[k, a], hi[k + 1, a])
        assert shared[0] == shared[1]
    # saturated colours: HSV value 1, saturation 0.8, so max channel 1 and min channel 0.2
    assert colours.shape == (sc.N_CUBES, 3)
    assert_close("max channel", colours.max(axis=1), np.ones(sc.N_CUBES), rtol=TOL)
    assert_close("min channel", colours.min(axis=1), np.full(sc.N_CUBES, 0.2), rtol=TOL)


# sha256 of generate_scene(7, 3, views=3, size=32): its images' bytes, then its poses' bytes
# (little-endian float64). Bitwise equality across machines is a legitimate claim here: the
# scene's random numbers are the generator's own doubles and integers (PCG64; numpy keeps
# Generator.random/integers streams stable in practice, though NEP 19 does not promise it), and
# sampling, look-at and rendering use only exactly rounded IEEE operations (+ - * /, sqrt,
# comparisons, floor), never BLAS, float reductions or SIMD transcendental functions, so every
# CPU computes the same bits. A change of this hash means the scenes changed: bump the dataset
# FORMAT_VERSION.
PINNED_SHA256 = "8cc3f554d1bc7fa518289a8f44422bc0bd73b141a66ec60f2c8dee64cdadced5"


def scene_digest(images, poses):
    assert poses.dtype == np.float64
    return hashlib.sha256(images.tobytes() + poses.astype("<f8").tobytes()).hexdigest()


def test_pinned_hash():
    assert scene_digest(*sc.generate_scene(7, 3, views=3, size=32)) == PINNED_SHA256


def test_scenes_differ_and_batch_equals_single():
    img0, pose0 = sc.generate_scene(7, 0, views=4, size=16)
    img1, pose1 = sc.generate_scene(7, 1, views=4, size=16)
    img2, pose2 = sc.generate_scene(8, 0, views=4, size=16)
    assert not np.array_equal(img0, img1) and not np.array_equal(pose0, pose1)
    assert not np.array_equal(img0, img2) and not np.array_equal(pose0, pose2)
    imgs, poses = sc.generate_scenes(7, 2, views=4, size=16)
    assert imgs.shape == (2, 4, 16, 16, 3) and imgs.dtype == np.uint8 and poses.shape == (2, 4, 7)
    assert_bitwise_equal("scene 1 in a batch", imgs[1], img1)
    assert_bitwise_equal("poses 1 in a batch", poses[1], pose1)


# ---------------------------------------------------------------------------------------
# the dataset on disk


N_SCENES, VIEWS, SIZE, SHARD = 3, 4, 16, 2


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    """3 scenes of 4 views, 16x16, in 2 shards (2 + 1 scenes), written once for the module."""
    out = tmp_path_factory.mktemp("sm7") / "ds"
    sc.write_dataset(out, N_SCENES, seed=9, views=VIEWS, size=SIZE, shard_size=SHARD, progress=False)
    return out


@pytest.fixture
def damaged(dataset_dir, tmp_path):
    """A fresh copy of the dataset, to be damaged by the test."""
    copy = tmp_path / "copy"
    shutil.copytree(dataset_dir, copy)
    return copy


def test_dataset_round_trip(dataset_dir):
    assert sorted(os.listdir(dataset_dir)) == ["manifest.json", "shard-00000.npz", "shard-00001.npz"]  # no temp files
    ds = sc.load_dataset(dataset_dir)
    imgs, poses = sc.generate_scenes(9, N_SCENES, views=VIEWS, size=SIZE)
    assert_bitwise_equal("images", ds.images, imgs)
    assert_bitwise_equal("poses", ds.poses, poses)
    assert ds.seed == 9
    m = ds.manifest
    assert (m["format"], m["version"], m["n_scenes"], m["views"], m["height"], m["width"]) == \
        (sc.FORMAT, sc.FORMAT_VERSION, N_SCENES, VIEWS, SIZE, SIZE)
    assert [(s["file"], s["first_scene"], s["n_scenes"]) for s in m["shards"]] == \
        [("shard-00000.npz", 0, 2), ("shard-00001.npz", 2, 1)]


def test_every_image_pose_pair_re_renders(dataset_dir):
    """Each stored view is the render of its scene's object under the stored pose (no scene's
    poses paired with another's images, no shard shifted). (The same bytes again: the resumed write
    of test_interrupted_write_resumes_bitwise.)"""
    ds = sc.load_dataset(dataset_dir)
    for i in range(N_SCENES):
        cells, colours = sc.make_object(np.random.default_rng([9, i]))
        assert np.array_equal(sc.render_views(cells, colours, ds.poses[i], SIZE), ds.images[i]), f"scene {i}"


def flip(at):
    def damage(data):
        data = bytearray(data)
        data[at(len(data)) if callable(at) else at] ^= 0x10
        return bytes(data)
    return damage


@pytest.mark.parametrize("damage", [lambda d: d[: len(d) // 2], lambda d: None]
                         + [flip(at) for at in (40, -30)] + [flip(lambda n: n // 2)],
                         ids=["truncated", "missing", "flip 40", "flip -30", "flip middle"])
def test_damaged_shard_is_named(damaged, damage):
    """A shard cut short, missing, or with one bit flipped anywhere (zip headers, compressed data,
    central directory) is an error naming the shard, never a silently different dataset."""
    path = damaged / "shard-00001.npz"
    data = damage(path.read_bytes())
    if data is None:
        os.remove(path)
    else:
        path.write_bytes(data)
    with pytest.raises(FileNotFoundError if data is None else ValueError, match=r"shard-00001\.npz"):
        sc.load_dataset(damaged)


@pytest.mark.parametrize("damage, name", [
    (lambda m: json.dumps({**m, "views": VIEWS + 1}), r"shard-00000\.npz"),  # matches its hash, not the shape
    (lambda m: json.dumps({**m, "n_scenes": 4}), "n_scenes"),
    (lambda m: "{not json", r"manifest\.json"),
])
def test_damaged_manifest_is_named(damaged, damage, name):
    mpath = damaged / "manifest.json"
    mpath.write_text(damage(json.loads(mpath.read_text())))
    with pytest.raises(ValueError, match=name):
        sc.load_dataset(damaged)


SMALL = dict(views=2, size=16, shard_size=2, progress=False)  # 5 scenes: shards of 2, 2, 1


def interrupt_after(monkeypatch, calls, error=KeyboardInterrupt):
    """Make the dataset writer's generate_scene raise `error` (Ctrl-C) after `calls` calls; -> [calls so far]."""
    real, count = sc.generate_scene, [0]  # the renderer itself (not a stand-in set earlier)

    def scene(*args):
        count[0] += 1
        if count[0] > calls:
            raise error
        return real(*args)

    monkeypatch.setattr(dataset_module, "generate_scene", scene)
    return count


def assert_same_files(got, want):
    assert sorted(os.listdir(got)) == sorted(os.listdir(want))
    for name in os.listdir(want):
        assert (got / name).read_bytes() == (want / name).read_bytes(), name


def test_interrupted_write_resumes_bitwise(tmp_path, monkeypatch):
    """Ctrl-C in the third scene leaves shard 0, the progress record and no manifest; the same
    call again keeps shard 0 (its scenes not rendered again), renders the rest, and the folder
    has the bytes of an uninterrupted write."""
    want, out = tmp_path / "want", tmp_path / "out"
    sc.write_dataset(want, 5, seed=3, **SMALL)
    interrupt_after(monkeypatch, 3)
    with pytest.raises(KeyboardInterrupt):
        sc.write_dataset(out, 5, seed=3, **SMALL)
    assert sorted(os.listdir(out)) == ["progress.jsonl", "shard-00000.npz"]
    with pytest.raises(FileNotFoundError, match="did not finish"):
        sc.load_dataset(out)
    rendered = interrupt_after(monkeypatch, 10**9)
    assert sc.write_dataset(out, 5, seed=3, **SMALL) == json.loads((want / "manifest.json").read_text())
    assert rendered[0] == 3
    assert_same_files(out, want)


def pyvf_scenes(*argv):
    """`pyvf scenes *argv --quiet` in this process -> its exit status."""
    args = build_parser().parse_args(["scenes", *map(str, argv), "--quiet"])
    return args.func(args)


@pytest.mark.parametrize("state", ["finished", "unfinished", "shards without progress"])
def test_a_folder_holding_another_dataset_is_refused_until_overwrite(state, tmp_path, monkeypatch, capsys):
    """A finished dataset, an unfinished write of other arguments, or shards without their progress
    record: write_dataset names out_dir, the command --out and --overwrite (one line, status 2);
    --overwrite replaces it, its stale shards removed."""
    out = tmp_path / "ds"
    if state == "finished":
        sc.write_dataset(out, 5, seed=3, **SMALL)
    else:
        interrupt_after(monkeypatch, 3)
        with pytest.raises(KeyboardInterrupt):
            sc.write_dataset(out, 5, seed=3, **SMALL)
        monkeypatch.undo()
        if state != "unfinished":
            os.remove(out / "progress.jsonl")
    with pytest.raises(FileExistsError, match="out_dir"):
        sc.write_dataset(out, 1, seed=4, **SMALL)
    argv = ["--out", out, "--scenes", 1, "--seed", 4, "--views", 2, "--size", 16, "--shard-size", 2]
    assert pyvf_scenes(*argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("pyvf scenes: error: argument --out:") and "--overwrite" in err and err.count("\n") == 1
    assert pyvf_scenes(*argv, "--overwrite") == 0 and sc.load_dataset(out).seed == 4
    assert sorted(os.listdir(out)) == ["manifest.json", "shard-00000.npz"]


@pytest.mark.parametrize("name, value", [
    ("n_scenes", 0), ("size", 7), ("seed", -1), ("shard_size", 0),
])
def test_write_dataset_refusals_write_nothing(tmp_path, name, value):
    args = dict(n_scenes=1, seed=0, views=2, size=8, shard_size=1, progress=False) | {name: value}
    with pytest.raises(ValueError, match=rf"\b{name}\b"):
        sc.write_dataset(tmp_path / "ds", **args)
    assert not (tmp_path / "ds").exists()


# ---------------------------------------------------------------------------------------
# the command line


def test_cli_writes_dataset_and_preview(tmp_path, capsys):
    out, png = tmp_path / "ds", tmp_path / "preview.png"
    assert pyvf_scenes("--out", out, "--scenes", 2, "--seed", 4, "--views", 3, "--size", 16, "--shard-size", 1,
                       "--preview", png) == 0
    ds = sc.load_dataset(out)
    assert ds.images.shape == (2, 3, 16, 16, 3)
    from PIL import Image
    with Image.open(png) as im:
        grid = np.asarray(im.convert("RGB"))
    assert_bitwise_equal("preview", grid[::2, ::2], sc.preview_grid(ds.images))  # saved enlarged twice
    # a bad argument: exit status 2 and the argument's name on stderr
    assert pyvf_scenes("--out", tmp_path / "bad", "--scenes", 0, "--seed", 1) == 2
    assert "n_scenes" in capsys.readouterr().err


@pytest.mark.parametrize("bad, option", [
    (["--out", "{tmp}/afile/ds"], "--out"),  # under a file
    (["--preview", "{tmp}/nodir/p.png"], "--preview"),  # its folder missing
])
def test_cli_checks_paths_before_rendering(bad, option, tmp_path, capsys, monkeypatch):
    """A --out or --preview that cannot be written is one line naming the option, status 2,
    before any scene is rendered or any file written."""
    (tmp_path / "afile").write_text("")
    rendered = interrupt_after(monkeypatch, 0, AssertionError("a scene was rendered"))
    argv = ["--out", tmp_path / "ds", "--scenes", 2, "--seed", 0, "--size", 16]
    assert pyvf_scenes(*argv, *[a.format(tmp=tmp_path) for a in bad]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"pyvf scenes: error: argument {option}:") and err.count("\n") == 1, err
    assert rendered[0] == 0 and not (tmp_path / "ds").exists()
