"""Procedural Shepard-Metzler-7 scenes (docs/math.md §7): the object, the cameras, a NumPy ray caster,
and the dataset on disk. Deterministic: a seed gives the same bytes on every machine.

    images, poses = generate_scene(seed, index)          # (15, 64, 64, 3) uint8, (15, 7) float64
    images, poses = generate_scenes(seed, n)             # (n, 15, 64, 64, 3), (n, 15, 7)
    write_dataset("data/sm7", n_scenes=2000, seed=0)     # shard-00000.npz ..., manifest.json
    ds = load_dataset("data/sm7")                        # ds.images, ds.poses, ds.seed, ds.manifest
    poses = gqn_to_pose(cams); cams = pose_to_gqn(poses) # GQN's (x, y, z, yaw, pitch)

Conventions (details and reasons in the submodules' docstrings):

* **Object** (render.py): 7 unit cubes on the integer lattice, a self-avoiding chain of face
  neighbours, each cube a random hue at HSV saturation 0.8, value 1; the centroid of the cube
  centres at the origin. Units: one cube side.
* **World frame** (cameras.py): right-handed, **up is -y**, the frame the published ViewFormer
  converts GQN's cameras into. **Camera frame**: OpenCV, x right, y down, z forward (the
  camera looks along its local +z). **Pose**: position xyz, then the sign-canonical (w >= 0)
  unit quaternion (w, x, y, z) of the camera-to-world rotation (pyvf.geometry's Hamilton
  product): the optical axis is quat_rotate(q, (0, 0, 1)).
* **Cameras**: on the sphere of radius 10 around the origin, looking at it, no roll, elevation
  within +-60 degrees, uniform on that band; pinhole with tan(fov/2) = 0.39 (42.6 degrees,
  across the shorter image side), so the whole object is always in view.
* **Light** (render.py): colour * (0.25 + 0.9 max(0, n.l) + 0.45 max(0, -n.l)), l = LIGHT_DIR
  = (0.557, -0.696, 0.453) (from above and the side; the last term a weak fill light from the
  opposite side, so every face direction has its own shade). **Background**: grey 0.15.
  uint8 = floor(255 clip(v, 0, 1) + 0.5).
* **GQN form**: (x, y, z, yaw, pitch) in radians in GQN's z-up world; converted as the
  published code does (position (y, -z, -x), rotation q_y(pi - yaw) * q_x(pitch)).
* **On disk** (dataset.py): `shard-00000.npz`, ... each with `images` (n, V, H, W, 3) uint8,
  `poses` (n, V, 7) float64 and `scene_index` (n,) int64, then `manifest.json` (format
  "pyvf-sm7-scenes" version 1: seed, counts, sizes, these constants, each shard's file,
  scene range, bytes and sha256), every file written atomically; load_dataset verifies all.
* **Determinism**: scene i draws only from numpy.random.default_rng([seed, i]), and sampling
  and rendering use only exactly rounded IEEE operations (no BLAS, no SIMD trig).
"""

from .cameras import (
    CAMERA_RADIUS,
    MAX_ELEVATION_DEG,
    TAN_HALF_FOV,
    gqn_to_pose,
    look_at_poses,
    pose_matrix,
    pose_to_gqn,
    sample_camera_positions,
)
from .preview import preview_grid, save_preview
from .dataset import FORMAT, FORMAT_VERSION, SceneDataset, load_dataset, write_dataset
from .render import (
    AMBIENT,
    BACK,
    BACKGROUND,
    DIFFUSE,
    LIGHT_DIR,
    N_CUBES,
    face_shades,
    generate_scene,
    generate_scenes,
    make_object,
    object_boxes,
    object_centres,
    render_views,
)

__all__ = [
    # scenes
    "generate_scene",
    "generate_scenes",
    "make_object",
    "object_centres",
    "object_boxes",
    "render_views",
    "face_shades",
    # cameras
    "sample_camera_positions",
    "look_at_poses",
    "pose_matrix",
    "gqn_to_pose",
    "pose_to_gqn",
    # dataset
    "SceneDataset",
    "write_dataset",
    "load_dataset",
    "FORMAT",
    "FORMAT_VERSION",
    # command line
    "preview_grid",
    "save_preview",
    # constants
    "N_CUBES",
    "CAMERA_RADIUS",
    "TAN_HALF_FOV",
    "MAX_ELEVATION_DEG",
    "LIGHT_DIR",
    "AMBIENT",
    "DIFFUSE",
    "BACK",
    "BACKGROUND",
]
