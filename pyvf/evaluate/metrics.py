"""The metrics of docs/math.md §6 and the four baselines pyvf is compared with, in NumPy.

Images here are uint8 (..., Hi, Wi, C), the form a picture is saved in: every method's prediction
is rounded to uint8 before it is scored, so a score is that of the picture a user sees.
Definitions (per image; the evaluation then takes the mean over images):

* MAE  = mean |pred - target| over pixels and channels, on the 0..255 scale.
* RMSE = sqrt(mean (pred - target)^2) over pixels and channels, on the 0..255 scale: per
  image, then the mean over images (as the paper's tables), not the root of the pooled mean.
* PSNR = 10 log10(1 / mse) with mse on the [0, 1] scale; a perfect image (mse = 0) is given
  psnr_cap(shape), so that a mean stays finite and a perfect image scores above every other.
* position and orientation errors: geometry.position_error and geometry.orientation_error.
"""

import numpy as np

from ..geometry import average_pose, orientation_error, position_error

__all__ = ["object_mask", "empty_patches", "empty_entropy", "encode_images", "to_model_images", "to_uint8",
           "psnr_cap", "image_metrics", "pose_metrics", "nearest_view", "mean_image", "closest_image_pose",
           "mean_pose", "QUERIES"]

QUERIES = 5  # query views per scene, its last ones: in evaluate() and in a training run's health


def object_mask(images):
    """uint8 (..., Hi, Wi, 3) -> bool (..., Hi, Wi): the pixels whose colour differs from the
    image's background, taken as the colour of its top-left pixel (SM7's backgrounds are one
    flat colour and objects never reach the corner)."""
    corner = images[..., :1, :1, :]  # (..., 1, 1, 3)
    return np.any(images != corner, axis=-1)


def empty_patches(images, k):
    """uint8 (..., Hi, Wi, 3) -> bool (..., k, k): the k x k grid's patches all background (object_mask)."""
    m = object_mask(images)  # (..., Hi, Wi)
    p = m.shape[-1] // k
    return ~m.reshape(m.shape[:-2] + (k, p, k, p)).any(axis=(-3, -1))


def empty_entropy(codes, empty):
    """codes (M, k, k) ints, empty (M, k, k) bool -> float: for each grid position the entropy
    (nats) of the code over the views where that patch is empty, averaged over the positions
    with at least one empty view (nan when there are none). 0 when the background has one code."""
    ents = []
    for c, e in zip(codes.reshape(len(codes), -1).T, empty.reshape(len(empty), -1).T):  # per position
        if e.any():
            p = np.unique(c[e], return_counts=True)[1] / e.sum()
            ents.append(-(p * np.log(p)).sum())
    return float(np.mean(ents)) if ents else float("nan")


def to_model_images(images, dtype):
    """uint8 (B, Hi, Wi, C) -> (B, C, Hi, Wi) of dtype in [-1, 1]: x / 127.5 - 1 (as the training data)."""
    if images.dtype != np.uint8 or images.ndim != 4:
        raise ValueError(f"images must be uint8 (B, Hi, Wi, C), got {images.dtype} {images.shape}")
    dtype = np.dtype(dtype)
    x = images.transpose(0, 3, 1, 2).astype(dtype, order="C")  # (B, C, Hi, Wi)
    x /= dtype.type(127.5)
    x -= dtype.type(1.0)
    return x


def encode_images(codebook, images, batch_size=64, dtype=np.int64, progress=None):
    """uint8 images (M, Hi, Wi, C) -> codebook.encode's codes (M, k, k) as dtype, batch_size images
    per encoder call. progress: None, or the description of a tqdm progress bar."""
    k = codebook.config.token_size
    out = np.empty((images.shape[0], k, k), dtype)  # (M, k, k)
    starts = range(0, images.shape[0], batch_size)
    if progress:
        from tqdm.auto import tqdm
        starts = tqdm(starts, desc=progress, unit="batch")
    for i in starts:
        out[i:i + batch_size] = codebook.encode(to_model_images(images[i:i + batch_size], codebook.dtype))  # (b, k, k)
    return out


def to_uint8(x):
    """(B, C, Hi, Wi) floats in [-1, 1] -> uint8 (B, Hi, Wi, C): rint((x + 1) * 127.5) clipped to
    0..255 (a decoder's output can leave [-1, 1]; rint rounds halves to even). NaN raises ValueError."""
    if np.isnan(x).any():  # NaN has no picture (a cast to uint8 would give 0 silently); +-inf clip
        raise ValueError("x contains NaN")
    v = np.rint((x.astype(np.float64) + 1.0) * 127.5)  # (B, C, Hi, Wi)
    return np.clip(v, 0, 255).astype(np.uint8).transpose(0, 2, 3, 1).copy()  # (B, Hi, Wi, C)


# metrics
def psnr_cap(image_shape):
    """The PSNR in dB given to a perfect image of shape (Hi, Wi, C): that of one value off by half
    a level, 10 log10(4 * 255^2 * Hi * Wi * C) (95.0 dB at 64x64x3), 6.02 dB above one value off
    by one level, the largest finite PSNR."""
    n = int(np.prod(image_shape))
    return float(10.0 * np.log10(4 * 255.0 ** 2 * n))


def image_metrics(pred, target):
    """pred, target uint8 (..., Hi, Wi, C) of one shape -> {"mae", "rmse", "psnr"}, each a float64
    array (...) with one value per image (definitions in the module docstring)."""
    diff = pred.astype(np.float64) - target.astype(np.float64)  # (..., Hi, Wi, C) on 0..255
    mae = np.abs(diff).mean(axis=(-3, -2, -1))  # (...)
    mse = (diff * diff).mean(axis=(-3, -2, -1))  # (...) on 0..255
    rmse = np.sqrt(mse)
    with np.errstate(divide="ignore"):
        psnr = 10.0 * np.log10(255.0 ** 2 / mse)  # (...) = 10 log10(1 / mse_[0,1]); inf where mse == 0
    psnr = np.minimum(psnr, psnr_cap(pred.shape[-3:]))
    return {"mae": mae, "rmse": rmse, "psnr": psnr}


def pose_metrics(pred, target):
    """pred, target (..., 7) float64 poses of one shape -> {"position_error", "orientation_error_deg"},
    each (...)."""
    return {"position_error": position_error(pred, target),
            "orientation_error_deg": orientation_error(pred, target)}


# baselines: what the context alone gives, without a model
def nearest_view(context_images, context_poses, query_poses):
    """The context image whose camera stands nearest to each query camera; the first on a tie.
    context_images uint8 (B, C, Hi, Wi, 3), context_poses (B, C, 7), query_poses (B, M, 7)
    -> uint8 (B, M, Hi, Wi, 3)."""
    d = position_error(query_poses[:, :, None, :], context_poses[:, None, :, :])  # (B, M, C)
    idx = np.argmin(d, axis=2)  # (B, M)
    return context_images[np.arange(idx.shape[0])[:, None], idx]  # (B, M, Hi, Wi, 3)


def mean_image(context_images):
    """The mean of the context images, rounded to uint8.   uint8 (B, C, Hi, Wi, 3) -> (B, Hi, Wi, 3)."""
    return np.rint(context_images.mean(axis=1)).astype(np.uint8)  # (B, Hi, Wi, 3)


def closest_image_pose(context_images, context_poses, query_images):
    """The pose of the context view whose image is closest (mean squared difference of the
    pixels) to each query image; the first on a tie.   context_images uint8 (B, C, Hi, Wi, 3),
    context_poses (B, C, 7), query_images uint8 (B, M, Hi, Wi, 3) -> (B, M, 7)."""
    ctx = context_images.astype(np.float64)  # (B, C, Hi, Wi, 3)
    qry = query_images.astype(np.float64)  # (B, M, Hi, Wi, 3)
    diff = qry[:, :, None] - ctx[:, None]  # (B, M, C, Hi, Wi, 3)
    mse = (diff * diff).mean(axis=(-3, -2, -1))  # (B, M, C)
    idx = np.argmin(mse, axis=2)  # (B, M)
    return context_poses[np.arange(idx.shape[0])[:, None], idx]  # (B, M, 7)


def mean_pose(context_poses):
    """The mean context pose (B, C, 7) -> (B, 7): mean position; quaternions normalised,
    sign-canonicalised, averaged, normalised and canonicalised again (geometry.average_pose)."""
    return average_pose(context_poses, axis=1)
