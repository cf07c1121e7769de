"""The Shepard-Metzler object and its renderer: exact ray casting against unit cubes, in NumPy.

The object (docs/math.md §7): N_CUBES = 7 unit cubes on the integer lattice, each attached face
to face to the previous one by a step along one of +-x, +-y, +-z, chosen uniformly among the
steps that reach a free cell (self-avoiding; a chain of 7 never runs into a dead end). Each cube
has its own colour, a uniform random hue at saturation SATURATION and value VALUE. Translated so
that the centroid of the cube centres is the origin.

The renderer casts one ray per pixel centre from the camera (pinhole: cameras.py) and intersects
it with every cube by the slab method; the nearest entry point wins. A pixel that hits a cube gets

    colour * (AMBIENT + DIFFUSE * max(0, n.l) + BACK * max(0, -n.l))

with n the outward normal of the face hit and l = LIGHT_DIR, a directional light up and to the
side. The BACK term, a weak fill light from the opposite direction, gives the three faces turned
away from the key light three different shades (face_shades), so adjacent faces never merge. A
pixel that hits nothing is BACKGROUND. Values are clipped to [0, 1] and stored as uint8
floor(255 v + 0.5). No anti-aliasing, no shadows, no specular light.

Determinism: the render path uses only exactly rounded IEEE operations (+ - * /, sqrt,
comparisons, min/max, floor), written out elementwise (no `@`, einsum, BLAS, float reductions or
SIMD transcendental functions), and the generator's own doubles and integers: a seed gives the
same bytes on every machine and numpy build (the tests pin a scene's sha256).
"""

import numpy as np

from .cameras import CAMERA_RADIUS, TAN_HALF_FOV, look_at_poses, pose_matrix, sample_camera_positions

__all__ = ["N_CUBES", "SATURATION", "VALUE", "LIGHT_DIR", "AMBIENT", "DIFFUSE", "BACK", "BACKGROUND", "make_object",
           "object_boxes", "hue_to_rgb", "face_shades", "render_views", "generate_scene",
           "generate_scenes"]

N_CUBES = 7
SATURATION = 0.8  # HSV saturation and value of every cube's colour: saturated, never white or black
VALUE = 1.0
AMBIENT = 0.25  # shade of a face that neither light reaches
DIFFUSE = 0.9  # the key light's Lambertian weight (the brightest face: 0.25 + 0.9 * 0.696 = 0.88, no clipping)
BACK = 0.45  # the fill light's weight, half the key's (see the module docstring)
_LIGHT_RAW = (0.4, -0.5, 0.325)  # towards the light: up (-y) and to the side, three different magnitudes
_n = np.sqrt(_LIGHT_RAW[0] * _LIGHT_RAW[0] + _LIGHT_RAW[1] * _LIGHT_RAW[1] + _LIGHT_RAW[2] * _LIGHT_RAW[2])
LIGHT_DIR = tuple(float(c / _n) for c in _LIGHT_RAW)  # unit (to rounding): (0.557, -0.696, 0.453)
del _n
BACKGROUND = (0.15, 0.15, 0.15)  # RGB of every pixel that misses the object: a dark neutral grey

_STEPS = ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))  # the 6 face neighbours
_RAYS_PER_CHUNK = 1 << 16  # rays cast together (memory: ~20 arrays of rays x cubes float64)


# the object
def hue_to_rgb(h, s=SATURATION, v=VALUE):
    """HSV -> RGB, hue h (...) in [0, 1): (...) -> (..., 3) in [0, 1], by the piecewise-linear formula
    channel(n) = v - v s clip(min(k, 4 - k), 0, 1), k = (n + 6h) mod 6, n = 5, 3, 1 for R, G, B."""
    h6 = np.asarray(h, dtype=np.float64) * 6
    out = []
    for n in (5, 3, 1):
        k = n + h6
        k = np.where(k >= 6, k - 6, k)  # (n + 6h) mod 6, as n + 6h < 12
        t = np.maximum(np.minimum(np.minimum(k, 4 - k), 1), 0)
        out.append(v - v * s * t)
    return np.stack(out, axis=-1)  # (..., 3)


def make_object(rng):
    """A random Shepard-Metzler object: (cells (7, 3) int64, colours (7, 3) float64 RGB in [0, 1]).
    Draws from rng: for each of cubes 1..6 one integer choosing among the free face neighbours of
    the previous cube (in _STEPS' order); then the 7 hues."""
    cells = [(0, 0, 0)]
    occupied = {cells[0]}
    for _ in range(N_CUBES - 1):
        last = cells[-1]
        free = [c for c in (tuple(a + b for a, b in zip(last, s)) for s in _STEPS) if c not in occupied]
        cell = free[int(rng.integers(len(free)))]  # never empty for 7 cubes (module docstring)
        cells.append(cell)
        occupied.add(cell)
    colours = hue_to_rgb(rng.random(N_CUBES))  # (7, 3)
    return np.array(cells, dtype=np.int64), colours


def object_boxes(cells):
    """The cubes as boxes lo <= x <= hi, centroid at the origin: cells (K, 3) int -> lo, hi (K, 3).
    Computed as (cell -+ 0.5) - centroid: cell -+ 0.5 is exact, so two cubes that share a face
    get bitwise the same coordinate for it (no hairline gap for a ray to slip through), which
    centre -+ 0.5 with a rounded centre would not guarantee."""
    m = cells.sum(axis=0) / len(cells)  # (3,) the centroid: the sum in integers (exact), divided once
    return (cells - 0.5) - m, (cells + 0.5) - m  # (K, 3), (K, 3)


# the renderer
def face_shades():
    """The shade of each face direction: (3, 2) float64, [axis, 0] for the normal +e_axis and
    [axis, 1] for -e_axis: AMBIENT + DIFFUSE max(0, n.l) + BACK max(0, -n.l), n.l = +-LIGHT_DIR[axis]."""
    shades = np.empty((3, 2))
    for a in range(3):
        for j, nl in enumerate((LIGHT_DIR[a], -LIGHT_DIR[a])):
            shades[a, j] = AMBIENT + DIFFUSE * max(0.0, nl) + BACK * max(0.0, -nl)
    return shades


def _to_uint8(v):
    """[0, 1] floats -> uint8 by floor(255 clip(v) + 0.5) (round half up, exactly rounded ops)."""
    return np.floor(np.clip(v, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)


def _slab(o, d, lo, hi):
    """One axis of the slab test: rays o + t d (o, d (M, 1)) against the slabs lo <= x <= hi (K,).
    Returns near, far (M, K): the ray parameters where it enters and leaves the slab. A ray
    parallel to the slab (d == 0) is inside it for all t or for none."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o) / d  # (M, K)
        t2 = (hi - o) / d
    near, far = np.minimum(t1, t2), np.maximum(t1, t2)
    parallel = d == 0  # (M, 1)
    if parallel.any():
        inside = (o >= lo) & (o <= hi)  # (M, K)
        near = np.where(parallel, np.where(inside, -np.inf, np.inf), near)
        far = np.where(parallel, np.where(inside, np.inf, -np.inf), far)
    return near, far


def _cast(o, d, lo, hi):
    """Nearest box hit of each ray.   o, d (M, 3), lo, hi (K, 3) ->
    (hit (M,) bool, box (M,) int, axis (M,) int of the face's normal; valid where hit).
    Entry t = max over axes of near, exit = min of far; a box is hit where entry <= exit and
    exit > 0 (cameras are outside every box, so then entry > 0). Ties go to the first box and
    the first axis: np.argmin / the comparisons below pick the lowest index."""
    nx, fx = _slab(o[:, :1], d[:, :1], lo[:, 0], hi[:, 0])  # (M, K) each
    ny, fy = _slab(o[:, 1:2], d[:, 1:2], lo[:, 1], hi[:, 1])
    nz, fz = _slab(o[:, 2:], d[:, 2:], lo[:, 2], hi[:, 2])
    t_in = np.maximum(np.maximum(nx, ny), nz)  # (M, K)
    t_out = np.minimum(np.minimum(fx, fy), fz)
    axis = np.where((nx >= ny) & (nx >= nz), 0, np.where(ny >= nz, 1, 2))  # (M, K)
    t = np.where((t_in <= t_out) & (t_out > 0), t_in, np.inf)  # (M, K)
    box = np.argmin(t, axis=1)  # (M,)
    rows = np.arange(len(t))
    return np.isfinite(t[rows, box]), box, axis[rows, box]


def render_views(cells, colours, poses, size=64):
    """Render unit cubes seen by cameras: cells (K, 3) integer lattice cells of the cubes, placed
    with their centroid at the origin (object_boxes), colours (K, 3) RGB in [0, 1], poses (V, 7)
    float64 camera poses (cameras.py), size: int (square) or (height, width) -> images (V, H, W, 3)
    uint8. The cameras must stand outside every (closed) cube."""
    lo, hi = object_boxes(cells)  # (K, 3) the boxes
    colours = np.asarray(colours, dtype=np.float64)
    H, W = (size, size) if np.ndim(size) == 0 else size
    V = len(poses)

    f = (min(H, W) / 2) / TAN_HALF_FOV  # focal length in pixels
    u = (np.arange(W) + 0.5 - W / 2) / f  # (W,) camera-frame x of each column's ray (z = 1)
    v = (np.arange(H) + 0.5 - H / 2) / f  # (H,) camera-frame y of each row's ray
    R = pose_matrix(poses[:, 3:])  # (V, 3, 3) camera-to-world
    # world direction of pixel (i, j) of view n: R[n] @ (u[j], v[i], 1), written out
    d = (R[:, None, None, :, 0] * u[None, None, :, None]
         + R[:, None, None, :, 1] * v[None, :, None, None]
         + R[:, None, None, :, 2])  # (V, H, W, 3)
    d = d.reshape(-1, 3)  # (V*H*W, 3)
    o = np.repeat(poses[:, :3], H * W, axis=0)  # (V*H*W, 3) every ray starts at its camera

    shades = face_shades()  # (3, 2)
    rgb = np.empty((len(d), 3))  # (V*H*W, 3)
    rgb[:] = BACKGROUND
    # Cull first against the object's bounding box (most rays miss the object), then cast the
    # rays that hit it against every cube.
    box_lo, box_hi = lo.min(axis=0)[None], hi.max(axis=0)[None]  # (1, 3) (min/max: exact)
    for start in range(0, len(d), _RAYS_PER_CHUNK):
        sl = slice(start, start + _RAYS_PER_CHUNK)
        near_obj, _, _ = _cast(o[sl], d[sl], box_lo, box_hi)  # (m,)
        idx = start + np.flatnonzero(near_obj)  # rays that may hit a cube
        hit, box, axis = _cast(o[idx], d[idx], lo, hi)
        idx, box, axis = idx[hit], box[hit], axis[hit]
        # the face hit faces the ray: its normal is -e_axis where the ray runs along +axis
        neg = d[idx, axis] > 0
        shade = shades[axis, neg.astype(np.intp)]  # (h,)
        rgb[idx] = colours[box] * shade[:, None]
    return _to_uint8(rgb).reshape(V, H, W, 3)


# scenes
def generate_scene(seed, index, views=15, size=64):
    """Scene `index` of the family `seed`: (images (V, size, size, 3) uint8, poses (V, 7) float64),
    from np.random.default_rng([seed, index]) alone: the object, then the cameras."""
    rng = np.random.default_rng([seed, index])
    cells, colours = make_object(rng)
    poses = look_at_poses(sample_camera_positions(rng, views, CAMERA_RADIUS))  # (V, 7)
    return render_views(cells, colours, poses, size), poses


def generate_scenes(seed, n, views=15, size=64):
    """Scenes 0..n-1: (images (n, V, size, size, 3) uint8, poses (n, V, 7) float64)."""
    images = np.empty((n, views, size, size, 3), dtype=np.uint8)
    poses = np.empty((n, views, 7))
    for i in range(n):
        images[i], poses[i] = generate_scene(seed, i, views, size)
    return images, poses
