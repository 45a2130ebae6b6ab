"""Helpers shared by the dataset loaders: validated JSON fields, image headers, lazy pixel loaders,
scene bounds, and option parsing. Nothing here knows a dataset format."""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path
from typing import Any, Iterable, Optional, Sequence

import cv2
import numpy as np

from benchmark.core.errors import InputError
from benchmark.core.imageio import read_image
from benchmark.core.scene import Camera

# Tolerance on ||R R^T - I|| for a rotation read from a file (float32 sources reach ~1e-7).
ROTATION_TOLERANCE = 1e-3


# -- options ------------------------------------------------------------------------------------
def make_options(cls: type, layout: str, given: dict[str, Any]):
    """Build the options dataclass ``cls`` from keyword arguments, rejecting unknown names."""
    valid = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(given) - valid)
    if unknown:
        raise InputError(None, f"option {unknown[0]!r}",
                         f"not an option of the {layout} loader (valid: {', '.join(sorted(valid))})")
    return cls(**given)


# -- validated values ---------------------------------------------------------------------------
def get_key(mapping: Any, key: str, file: Path, parent: str = "") -> Any:
    """``mapping[key]``, or an :class:`InputError` naming ``parent.key`` in ``file``."""
    field = f"{parent}.{key}" if parent else key
    if not isinstance(mapping, dict):
        raise InputError(file, parent or None, f"expected a JSON object, got {type(mapping).__name__}")
    if key not in mapping:
        raise InputError(file, field, "missing required key")
    return mapping[key]


def as_array(value: Any, shape: tuple[int, ...], file: Path, field: str, *,
             limit: Optional[float] = None) -> np.ndarray:
    """``value`` as a finite float64 array of exactly ``shape`` (-1 = any length), every ``|entry|`` at most
    ``limit`` when given."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer beyond float range
        raise InputError(file, field, f"expected numbers of shape {shape}, got {value!r:.80}") from None
    if arr.ndim != len(shape) or any(s not in (-1, a) for s, a in zip(shape, arr.shape)):
        raise InputError(file, field, f"expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(file, field, "contains NaN or inf")
    if limit is not None and arr.size and float(np.abs(arr).max()) > limit:
        raise InputError(file, field, f"expected values within +-{limit:g}, got {arr.tolist()!r:.80}")
    return arr


def as_float(value: Any, file: Path, field: str, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(file, field, f"expected a number, got {value!r:.80}")
    try:
        out = float(value)
    except OverflowError:  # an integer beyond float range
        raise InputError(file, field, "is beyond the range of a float") from None
    if not math.isfinite(out):
        raise InputError(file, field, "is NaN or inf")
    if positive and out <= 0:
        raise InputError(file, field, f"must be positive, got {out}")
    return out


def as_int(value: Any, file: Path, field: str, *, minimum: Optional[int] = None) -> int:
    """An integer (``3`` or ``3.0``), optionally at least ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (
            isinstance(value, float) and not value.is_integer()):  # (a float that is inf or NaN is not either)
        raise InputError(file, field, f"expected an integer, got {value!r:.80}")
    out = int(value)
    if minimum is not None and out < minimum:
        raise InputError(file, field, f"must be >= {minimum}, got {out}")
    return out


def check_rotation(rot: np.ndarray, file: Path, field: str) -> np.ndarray:
    """Raise unless ``rot`` (3, 3) is a proper rotation (orthonormal, det +1)."""
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: an inf error, refused below
        err = float(np.abs(rot @ rot.T - np.eye(3)).max())
        det = float(np.linalg.det(rot))
    if not err <= ROTATION_TOLERANCE or not det > 0:
        raise InputError(file, field, f"not a rotation matrix (|R R^T - I| = {err:.2g}, det = {det:.3f})")
    return rot


# -- images -------------------------------------------------------------------------------------
def image_size(path: Path, field: str = "image") -> tuple[int, int]:
    """(width, height) from the file header only (no decoding); errors name the file."""
    from PIL import Image, UnidentifiedImageError

    from benchmark.core.annotation import MAX_MASK_PIXELS
    from benchmark.core.strict import file_problem, open_regular

    path = Path(path)
    problem = file_problem(path)
    if problem is not None:
        raise InputError(path, field, "image file not found" if problem == "missing" else f"is {problem}, "
                                                                                          "expected an image file")
    try:
        with warnings.catch_warnings():
            # PIL warns (two lines on stderr) of a header above its own limit before refusing twice that: the
            # size check below refuses such a header in one line, so the warning would only repeat it
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with open_regular(path) as fh, Image.open(fh) as img:
                width, height = int(img.size[0]), int(img.size[1])
    except Image.DecompressionBombError:  # a header declaring billions of pixels
        raise InputError(path, field, f"the image header declares more than the {MAX_MASK_PIXELS} pixels any "
                                      "frame may have") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError):
        raise InputError(path, field, "cannot read the image header (truncated or not an image)") from None
    if width * height > MAX_MASK_PIXELS:
        raise InputError(path, field, f"image of {width}x{height} pixels is larger than the {MAX_MASK_PIXELS} "
                                      "pixels any frame may have")
    return width, height


def resize(img: np.ndarray, width: Optional[int], height: Optional[int]) -> np.ndarray:
    """Resize (H, W, C) or (H, W) to ``width`` x ``height``: area averaging when shrinking.
    ``None`` keeps the image as it is (a mismatch with the camera then fails ``Frame.image``)."""
    if width is None or height is None or (img.shape[1] == width and img.shape[0] == height):
        return img
    shrink = width <= img.shape[1] and height <= img.shape[0]
    return cv2.resize(img, (int(width), int(height)),
                      interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def load_rgb(path: Path, width: Optional[int] = None, height: Optional[int] = None) -> np.ndarray:
    """(H, W, 3) float32 RGB of ``path``, resized to ``width`` x ``height`` when given (lazy loader body)."""
    return resize(read_image(path), width, height)


def missing_image(path: Path, reason: str) -> np.ndarray:
    """Loader body for frames whose pixels are not on disk: always raises a clear error."""
    raise InputError(path, "image", reason)


def target_size(width: int, height: int, scale: Optional[float], field: str = "scale") -> tuple[int, int]:
    """Image size after multiplying the resolution by ``scale`` (``None`` = unchanged)."""
    if scale is None:
        return int(width), int(height)
    factor = check_scale(scale, field)
    w, h = int(round(width * factor)), int(round(height * factor))
    if w < 1 or h < 1:
        raise InputError(None, field, f"scale {factor} makes a {width}x{height} image empty")
    return w, h


def check_scale(scale: Any, field: str = "scale") -> float:
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not math.isfinite(scale) or scale <= 0:
        raise InputError(None, field, f"expected a positive resolution multiplier (e.g. 0.5), got {scale!r}")
    return float(scale)


# -- bounds -------------------------------------------------------------------------------------
def box(points: np.ndarray) -> np.ndarray:
    """(2, 3) axis-aligned [min, max] of (N, 3) points."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return np.stack([points.min(axis=0), points.max(axis=0)])


def frustum_corners(camera: Camera, depths: Sequence[float]) -> np.ndarray:
    """(len(depths) * 5, 3) world points: the 4 image corners and the principal point at each depth."""
    px = np.array([[0.0, 0.0], [camera.width, 0.0], [0.0, camera.height],
                   [camera.width, camera.height], [camera.cx, camera.cy]])
    dirs = np.stack([(px[:, 0] - camera.cx) / camera.fx, (px[:, 1] - camera.cy) / camera.fy,
                     np.ones(len(px))], axis=-1)  # (5, 3) camera-frame rays with z = 1
    cam_pts = np.concatenate([dirs * d for d in depths])
    return (cam_pts - camera.t) @ camera.R  # R^T (x - t) for row vectors


def frustum_bounds(cameras: Iterable[Camera], near: Iterable[float], far: Iterable[float]) -> np.ndarray:
    """(2, 3) box of every camera's view frustum between its near and far depth."""
    pts = [frustum_corners(c, (n, f)) for c, n, f in zip(cameras, near, far)]
    return box(np.concatenate(pts))


def lookat_bounds(cameras: Sequence[Camera]) -> Optional[np.ndarray]:
    """(2, 3) cube around the point the cameras look at, or ``None`` when they do not converge.

    The centre is the least-squares point nearest to every optical axis; the half-size is the
    median camera distance to it times the tangent of the wider half field of view, i.e. the
    half-extent each camera sees at that depth (an object-centred capture, like D-NeRF, fits inside).
    """
    centers = np.stack([c.center for c in cameras])  # (N, 3)
    axes = np.stack([c.R[2] for c in cameras])  # (N, 3) optical axes (third row of R) in world
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]  # (N, 3, 3) I - d d^T
    lhs = proj.sum(axis=0)
    if np.linalg.cond(lhs) > 1e8:
        return None
    focus = np.linalg.solve(lhs, np.einsum("nij,nj->i", proj, centers))
    depth = np.einsum("ni,ni->n", focus[None] - centers, axes)
    if np.any(depth <= 0):
        return None  # the point is behind some camera: not a converging capture
    half_fov = max(max(c.fov_x, c.fov_y) for c in cameras) / 2.0
    half = float(np.median(np.linalg.norm(centers - focus, axis=1))) * math.tan(half_fov)
    return np.stack([focus - half, focus + half])
