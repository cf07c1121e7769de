"""Procedural Shepard-Metzler-7 scenes (docs/math.md §7): the object, the cameras, a NumPy ray caster,
and the dataset on disk. Deterministic: a seed gives the same bytes on every machine.

    images, poses = generate_scene(seed, index)          # (15, 64, 64, 3) uint8, (15, 7) float64
    images, poses = generate_scenes(seed, n)             # (n, 15, 64, 64, 3), (n, 15, 7)
    write_dataset("data/sm7", n_scenes=2000, seed=0)     # shard-00000.npz ..., manifest.json
    ds = load_dataset("data/sm7")                        # ds.images, ds.poses, ds.seed, ds.manifest

The conventions are in the submodules' docstrings: render.py the object and the renderer,
cameras.py the frames and the cameras, dataset.py the files.
"""

from .cameras import (CAMERA_RADIUS, MAX_ELEVATION_DEG, TAN_HALF_FOV, gqn_to_pose, look_at_poses, pose_matrix,
                      pose_to_gqn, sample_camera_positions)
from .dataset import FORMAT, FORMAT_VERSION, SceneDataset, load_dataset, preview_grid, save_preview, write_dataset
from .render import (AMBIENT, BACK, BACKGROUND, DIFFUSE, LIGHT_DIR, N_CUBES, face_shades, generate_scene,
                     generate_scenes, make_object, object_boxes, render_views)

__all__ = [
    "generate_scene", "generate_scenes", "make_object", "object_boxes", "render_views",
    "face_shades",  # scenes
    "sample_camera_positions", "look_at_poses", "pose_matrix", "gqn_to_pose", "pose_to_gqn",  # cameras
    "SceneDataset", "write_dataset", "load_dataset", "FORMAT", "FORMAT_VERSION",  # the dataset on disk
    "preview_grid", "save_preview",  # the command's preview
    "N_CUBES", "CAMERA_RADIUS", "TAN_HALF_FOV", "MAX_ELEVATION_DEG", "LIGHT_DIR", "AMBIENT", "DIFFUSE", "BACK",
    "BACKGROUND",
]
