"""The SM7 renderer and dataset checked against independent oracles: the pinhole projection of
cube corners written out from pyvf.geometry's quat_rotate (not the renderer's pose_matrix),
depth order, the pose a view is tagged with, and the dataset's bytes re-rendered scene by scene."""

import hashlib
import json
import shutil

import numpy as np
import pytest

import pyvf.scenes as sc
from pyvf.geometry import quat_rotate

BG = np.floor(np.array(sc.BACKGROUND) * 255 + 0.5).astype(np.uint8)
MARGIN = 1e-3  # pixels: pixel centres this close to a silhouette's edge are not judged


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


@pytest.mark.parametrize("seed", [0, 1, 2])
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


@pytest.mark.parametrize("index", [0, 5])
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


def test_scene_is_reproducible_from_its_seed_alone():
    """A scene's bytes do not depend on what was generated before or on the batch it is in."""
    a = sc.generate_scene(11, 4, views=3, size=16)
    sc.generate_scenes(12, 3, views=2, size=16)
    b = sc.generate_scenes(11, 2, views=3, size=16, start=3)
    assert np.array_equal(a[0], b[0][1]) and np.array_equal(a[1], b[1][1])
    assert a[1].tobytes() == sc.generate_scene(11, 4, views=3, size=16)[1].tobytes()


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("answers") / "ds"
    manifest = sc.write_dataset(out, 5, seed=4, views=3, size=16, shard_size=2, progress=False)
    return out, manifest


def test_every_image_pose_pair_re_renders(written):
    """Each stored view is the render of its scene's object under the stored pose (no scene's
    poses paired with another's images, no shard shifted), and the shards' sha256 are the files'."""
    out, manifest = written
    ds = sc.load_dataset(out)
    assert ds.images.shape == (5, 3, 16, 16, 3)
    for i in range(5):
        cells, colours = sc.make_object(np.random.default_rng([4, i]))
        assert np.array_equal(sc.render_views(cells, colours, ds.poses[i], 16), ds.images[i]), f"scene {i}"
    for entry in manifest["shards"]:
        data = (out / entry["file"]).read_bytes()
        assert (len(data), hashlib.sha256(data).hexdigest()) == (entry["bytes"], entry["sha256"])


def test_any_flipped_shard_byte_is_detected(written, tmp_path):
    """One flipped bit anywhere in a shard (zip headers, compressed data, central directory) is an
    error naming the shard, never a silently different dataset."""
    out, _ = written
    shutil.copytree(out, tmp_path / "c")
    path = tmp_path / "c" / "shard-00001.npz"
    clean = path.read_bytes()
    for at in (0, 40, 100, len(clean) // 2, len(clean) - 30, len(clean) - 1):
        data = bytearray(clean)
        data[at] ^= 0x10
        path.write_bytes(bytes(data))
        with pytest.raises(ValueError, match=r"shard-00001\.npz"):
            sc.load_dataset(tmp_path / "c")
    path.write_bytes(clean)
    assert np.array_equal(sc.load_dataset(tmp_path / "c").images, sc.load_dataset(out).images)


def test_manifest_counts_that_disagree_with_the_shards_are_refused(written, tmp_path):
    """Scene counts moved between shard entries (the total kept) do not match the shards' arrays."""
    out, _ = written
    shutil.copytree(out, tmp_path / "c")
    mpath = tmp_path / "c" / "manifest.json"
    m = json.loads(mpath.read_text())
    m["shards"][0]["n_scenes"], m["shards"][1]["first_scene"], m["shards"][1]["n_scenes"] = 1, 1, 3
    mpath.write_text(json.dumps(m))
    with pytest.raises(ValueError, match=r"shard-0000[01]\.npz"):
        sc.load_dataset(tmp_path / "c")


def test_manifest_shard_size_that_disagrees_with_the_shards_is_refused(written, tmp_path):
    """The format promises shard k holds scenes k*shard_size onwards (the last one fewer); a
    manifest whose shard_size says otherwise (or is missing) describes another layout than its
    shards, and a reader trusting it would look for scenes in the wrong shard."""
    out, _ = written
    shutil.copytree(out, tmp_path / "c")
    mpath = tmp_path / "c" / "manifest.json"
    m = json.loads(mpath.read_text())
    for value in (3, 1, None):
        edited = dict(m)
        if value is None:
            del edited["shard_size"]
        else:
            edited["shard_size"] = value
        mpath.write_text(json.dumps(edited))
        with pytest.raises(ValueError, match="shard_size"):
            sc.load_dataset(tmp_path / "c")
