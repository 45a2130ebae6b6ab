"""Image reading and writing with errors that name the file (OpenCV underneath)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .atomic import atomic_path
from .errors import InputError


def read_image(path: str | Path, *, keep_alpha: bool = False) -> np.ndarray:
    """Read an 8- or 16-bit PNG/JPEG as float32 RGB(A) in [0, 1], shape (H, W, 3) or (H, W, 4).

    Truncated or unreadable files raise :class:`InputError` naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "image file not found")
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise InputError(path, None, "cannot decode image (truncated or not an image)")
    if img.dtype == np.uint16:
        scale = 65535.0
    elif img.dtype == np.uint8:
        scale = 255.0
    else:
        raise InputError(path, "dtype", f"unsupported image dtype {img.dtype}")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
        if not keep_alpha:
            img = img[:, :, :3]
    else:
        img = cv2.cvtColor(img[:, :, :3], cv2.COLOR_BGR2RGB)
        if keep_alpha:
            full = np.full(img.shape[:2] + (1,), scale, dtype=img.dtype)
            img = np.concatenate([img, full], axis=2)
    return img.astype(np.float32) / scale


def read_mask(path: str | Path) -> np.ndarray:
    """Read a single-channel mask PNG as (H, W) uint8/uint16 values (no rescaling)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "mask file not found")
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise InputError(path, None, "cannot decode mask image (truncated or not an image)")
    if img.ndim == 3:
        img = img[:, :, 0]
    return img


def write_image(path: str | Path, image: np.ndarray) -> None:
    """Write float [0, 1] or uint8 RGB(A) / gray to PNG or JPEG, atomically."""
    path = Path(path)
    img = np.asarray(image)
    if img.dtype != np.uint8 and img.dtype != np.uint16:
        img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)
    ok, buf = cv2.imencode(path.suffix or ".png", img)
    if not ok:
        raise InputError(path, None, "cannot encode image")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())
