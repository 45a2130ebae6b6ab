"""The ``classical`` segmenter (real track): a three-level graph-segmentation hierarchy, no learned model.

Felzenszwalb-Huttenlocher graph segmentation (scikit-image) at three scales gives small, middle and
large regions. They are made a hierarchy (every small region inside one middle region, every middle
region inside one large region, like SAM's subpart / part / whole) by giving each region of a finer
level to the coarser-scale region that covers most of its pixels. Ids are then carried across
frames by overlap (:mod:`methods.supervision.association`), so a region keeps its id over time.

It needs no weights, so the real track runs anywhere; it knows nothing about objects, so its masks
follow colour edges rather than semantics (a floor for what real 2D supervision can give).
Felzenszwalb's ``scale`` acts on region sizes in pixels, so the scales are given at a reference image
area and scaled with the frame's area: the hierarchy looks the same at every resolution.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Optional

import numpy as np

from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from .association import AssociationConfig, TemporalAssociator
from .base import LEVELS, Segmenter


@dataclass
class ClassicalConfig:
    """Graph-segmentation hierarchy and its temporal association."""

    scales: tuple[float, float, float] = (60.0, 300.0, 1500.0)
    """Felzenszwalb ``scale`` of the small, middle and large level at :attr:`reference_pixels`
    (larger = coarser regions)."""
    min_size_fractions: tuple[float, float, float] = (0.001, 0.004, 0.02)
    """Smallest region of each level, as a fraction of the image area."""
    sigma: float = 0.8
    """Gaussian pre-smoothing of the image (Felzenszwalb-Huttenlocher's recommended 0.8)."""
    reference_pixels: int = 128 * 128
    """Image area at which :attr:`scales` apply; other sizes scale them by area ratio."""
    association_min_iou: float = 0.3
    """A region continues the id of a region of the previous frame of its camera above this IoU."""

    def __post_init__(self) -> None:
        self.scales = tuple(float(s) for s in self.scales)  # type: ignore[assignment]
        self.min_size_fractions = tuple(float(s) for s in self.min_size_fractions)  # type: ignore[assignment]
        if len(self.scales) != len(LEVELS) or len(self.min_size_fractions) != len(LEVELS):
            raise InputError(None, "classical segmenter", f"scales and min_size_fractions need {len(LEVELS)} values")
        if any(s <= 0 for s in self.scales) or list(self.scales) != sorted(self.scales):
            raise InputError(None, "classical segmenter", f"scales must be positive and increasing, got {self.scales}")


def nest(finer: np.ndarray, coarser: np.ndarray) -> np.ndarray:
    """Give every region of ``finer`` to the region of ``coarser`` covering most of its pixels.

    Args:
        finer, coarser: (H, W) int ids >= 0.
    Returns:
        (H, W) ids of the coarser level such that every finer region lies inside one coarser region.
    """
    f_ids, f_inv = np.unique(finer, return_inverse=True)
    c_ids, c_inv = np.unique(coarser, return_inverse=True)
    counts = np.bincount(f_inv.ravel() * c_ids.size + c_inv.ravel(),
                         minlength=f_ids.size * c_ids.size).reshape(f_ids.size, c_ids.size)
    owner = c_ids[counts.argmax(1)]  # (F,) coarser id of each finer region
    return owner[f_inv.reshape(finer.shape)]


def hierarchy(image: np.ndarray, cfg: ClassicalConfig) -> np.ndarray:
    """(3, H, W) int32 nested region ids of one (H, W, 3) float image in [0, 1]."""
    from skimage.segmentation import felzenszwalb

    h, w = image.shape[:2]
    area = h * w
    ratio = area / float(cfg.reference_pixels)
    raw = [felzenszwalb(image, scale=s * ratio, sigma=cfg.sigma, min_size=max(1, int(round(f * area))),
                        channel_axis=-1)
           for s, f in zip(cfg.scales, cfg.min_size_fractions)]
    levels = [raw[0].astype(np.int32)]
    for level in range(1, len(LEVELS)):
        levels.append(nest(levels[-1], raw[level]).astype(np.int32))
    return np.stack(levels)


class ClassicalSegmenter(Segmenter):
    """Felzenszwalb hierarchy + overlap association (see the module docstring)."""

    name = "classical"
    track = "real"

    def __init__(self, cfg: Optional[ClassicalConfig] = None) -> None:
        self.cfg = cfg or ClassicalConfig()
        self.associator = TemporalAssociator(AssociationConfig(min_iou=self.cfg.association_min_iou))

    def config(self) -> dict[str, Any]:
        return {"name": self.name, **asdict(self.cfg)}

    def segment(self, frame: Frame) -> np.ndarray:
        """(3, H, W) int32 ids, consistent with the frames segmented before (call in time order)."""
        image = np.asarray(frame.image(), dtype=np.float64)
        return self.associator.associate(hierarchy(image, self.cfg), frame.camera_id)


def create(scene: Scene, *, text_encoder=None, device: str = "cpu", **options: Any) -> ClassicalSegmenter:
    """Factory of the registry (``options``: fields of :class:`ClassicalConfig`)."""
    try:
        cfg = ClassicalConfig(**options)
    except TypeError as err:
        raise InputError(None, "classical segmenter options", str(err)) from None
    return ClassicalSegmenter(cfg)
