"""Synthetic test material for the annotation tool: a textured object in rigid motion.

Used by the tests and by :mod:`annotations.tool.latency` to measure box-to-mask and propagation
against exact masks. The object's texture lives in its own coordinates and every frame is rendered
by one affine warp, so the true mask of every frame is known exactly. With ``recolour_at`` the object
changes colour at a known frame (a change of state that only the pixels show), for measuring how
time segments are found from the images.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import cv2
import numpy as np


@dataclass
class RigidSequence:
    """Frames of an object moving rigidly over a textured background."""

    images: list[np.ndarray]
    """(H, W, 3) uint8 RGB per frame."""
    masks: list[np.ndarray]
    """(H, W) bool true object mask per frame."""
    boxes: list[tuple[int, int, int, int]]
    """True ``(x0, y0, x1, y1)`` box of the object per frame (exclusive ends)."""


def _smooth_noise(rng: np.random.Generator, height: int, width: int, cell: int, channels: int = 3) -> np.ndarray:
    """(H, W, C) float32 in [0, 1]: random values on a coarse grid, cubic-upsampled."""
    small = rng.random((max(2, height // cell), max(2, width // cell), channels)).astype(np.float32)
    big = cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
    return np.clip(big.reshape(height, width, channels), 0.0, 1.0)  # resize drops a single channel axis


def _background(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    # every hue, in blobs: some of them close to the object's colours, so edges are not trivial
    base = 0.15 + 0.7 * _smooth_noise(rng, height, width, 40)
    fine = 0.12 * (_smooth_noise(rng, height, width, 4, 1) - 0.5)
    return np.clip(base + fine, 0.0, 1.0)


def _object_sprite(rng: np.random.Generator, radius: int, palette: str) -> tuple[np.ndarray, np.ndarray]:
    """(S, S, 3) float texture and (S, S) float alpha of a lobed blob centred in the sprite.

    ``palette="warm"``: red-orange, distinct from most of the background; ``"scene"``: drawn from
    the background's own distribution (colour alone cannot separate object and background).
    """
    size = 2 * radius + 8
    c = size / 2.0
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) + 0.5
    theta = np.arctan2(yy - c, xx - c)
    r = np.hypot(xx - c, yy - c)
    phase = rng.uniform(0, 2 * np.pi, 2)
    edge = radius * (0.78 + 0.14 * np.sin(3 * theta + phase[0]) + 0.08 * np.sin(5 * theta + phase[1]))
    alpha = (r <= edge).astype(np.float32)
    if palette == "warm":
        tex = 0.55 + 0.35 * _smooth_noise(rng, size, size, 10)
        tex[..., 2] *= 0.35
        tex += 0.15 * (_smooth_noise(rng, size, size, 3, 1) - 0.5)
    elif palette == "scene":
        # a patch of another background at full scale: same colours, same blob sizes
        other = _background(rng, max(size, 2 * radius * 3), max(size, 2 * radius * 3))
        tex = other[:size, :size]
    else:
        raise ValueError(f"unknown palette {palette!r} (warm or scene)")
    return np.clip(tex, 0.0, 1.0), alpha


def rigid_sequence(num_frames: int = 60, width: int = 960, height: int = 540, *, seed: int = 0,
                   radius_frac: float = 0.16, travel_frac: float = 0.5, total_turn_deg: float = 45.0,
                   scale_change: float = 0.1, palette: str = "warm", noise: float = 3.0,
                   blur: float = 0.8, recolour_at: Optional[int] = None) -> RigidSequence:
    """Render ``num_frames`` frames of one textured blob translating, rotating and scaling slightly.

    The object (radius ``radius_frac * height``) crosses ``travel_frac`` of the width, turns by
    ``total_turn_deg`` and grows by ``scale_change`` (relative) over the sequence. ``palette`` as in
    :func:`_object_sprite`; ``noise`` is the standard deviation of per-frame sensor noise, in 8-bit levels;
    ``blur`` the sigma (pixels) of a Gaussian lens blur. The true mask is the object's coverage >= 0.5.
    From frame ``recolour_at`` on (``None``: never) the object's texture has its red and blue channels
    swapped: the same object, moving on as before, in another state.
    """
    rng = np.random.default_rng(seed)
    background = _background(rng, height, width)
    radius = max(6, int(radius_frac * height))
    sprite, alpha = _object_sprite(rng, radius, palette)
    recoloured = np.ascontiguousarray(sprite[..., ::-1])
    c = sprite.shape[0] / 2.0
    images, masks, boxes = [], [], []
    for t in range(num_frames):
        s = t / max(1, num_frames - 1)
        cx = width * (0.5 - travel_frac / 2 + travel_frac * s)
        cy = height * (0.5 + 0.12 * np.sin(2 * np.pi * s))
        angle = total_turn_deg * s
        scale = 1.0 + scale_change * s
        # sprite pixel-centre coordinates -> image coordinates: rotate/scale about c, move to (cx, cy)
        m = cv2.getRotationMatrix2D((c, c), angle, scale)
        m[:, 2] += np.array([cx - c, cy - c])
        source = recoloured if recolour_at is not None and t >= recolour_at else sprite
        tex = cv2.warpAffine(source, m, (width, height), flags=cv2.INTER_LINEAR, borderValue=0)
        a = cv2.warpAffine(alpha, m, (width, height), flags=cv2.INTER_LINEAR, borderValue=0)
        mask = a >= 0.5
        # soft (anti-aliased) edge and a slight lens blur, as a camera would record it
        frame = a[..., None] * tex + (1.0 - a[..., None]) * background
        frame = cv2.GaussianBlur(frame, (0, 0), blur) if blur > 0 else frame
        frame = frame * 255.0 + rng.normal(0.0, noise, frame.shape)
        images.append(np.clip(frame + 0.5, 0, 255).astype(np.uint8))
        masks.append(mask)
        ys, xs = np.nonzero(mask)
        boxes.append((int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1))
    return RigidSequence(images, masks, boxes)


def write_dnerf_scene(sequence: RigidSequence, out_dir: str | Path, *, split: str = "train",
                      ext: str = ".png") -> Path:
    """Write ``sequence`` as a D-NeRF-layout scene folder (one static camera, ``time = t / (n - 1)``).

    Returns the folder. Lets the tool's tests and measurements load frames through the real loader.
    """
    from benchmark.core.atomic import write_json
    from benchmark.core.imageio import write_image

    out = Path(out_dir)
    (out / split).mkdir(parents=True, exist_ok=True)
    n = len(sequence.images)
    frames = []
    for t, img in enumerate(sequence.images):
        rel = f"{split}/r_{t:03d}"
        write_image(out / f"{rel}{ext}", img)
        # OpenGL camera-to-world: 4 units in front of the origin, looking down -z
        c2w = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0], [0.0, 0.0, 0.0, 1.0]]
        shown = f"./{rel}" if ext == ".png" else f"./{rel}{ext}"  # D-NeRF leaves out only .png
        frames.append({"file_path": shown, "time": t / max(1, n - 1), "transform_matrix": c2w})
    write_json(out / f"transforms_{split}.json", {"camera_angle_x": 0.69, "frames": frames})
    if split != "train":
        write_json(out / "transforms_train.json", {"camera_angle_x": 0.69, "frames": []})
    return out
