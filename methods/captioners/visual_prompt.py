"""Object-wise visual prompts for the MLLM captioner (4D LangSplat, Sec. 3.3).

To caption object ``i`` in frame ``t`` the MLLM sees the frame with the object singled out: a red
contour around it, the background turned grayscale, and the background blurred. Each cue is
switchable, for the paper's Table 3 ablation (blur / +gray / +contour).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class VisualPromptConfig:
    """Which cues single out the object, and their sizes (paper values by default)."""

    contour: bool = True
    """Draw the object's outline in red."""
    contour_radius: int = 2
    """Half-thickness of the outline in pixels (drawn with thickness ``2 * radius``)."""
    contour_color: tuple[float, float, float] = (1.0, 0.0, 0.0)
    """Outline colour, RGB in [0, 1]."""
    grayscale_background: bool = True
    """Convert everything outside the object to gray."""
    blur_background: bool = True
    """Blur everything outside the object."""
    blur_radius: int = 10
    """Gaussian blur radius of the background in pixels (kernel side ``2 * radius + 1``)."""

    @staticmethod
    def ablation(name: str) -> "VisualPromptConfig":
        """The paper's Table 3 rows: ``"blur"``, ``"blur+gray"``, ``"blur+gray+contour"``, ``"none"``."""
        table = {
            "none": VisualPromptConfig(contour=False, grayscale_background=False, blur_background=False),
            "blur": VisualPromptConfig(contour=False, grayscale_background=False, blur_background=True),
            "blur+gray": VisualPromptConfig(contour=False, grayscale_background=True, blur_background=True),
            "blur+gray+contour": VisualPromptConfig(),
        }
        if name not in table:
            raise ValueError(f"unknown visual prompt ablation {name!r}; choose from {sorted(table)}")
        return table[name]


def visual_prompt(image: np.ndarray, mask: np.ndarray, cfg: VisualPromptConfig | None = None) -> np.ndarray:
    """Single out the object ``mask`` in ``image``.

    Args:
        image: (H, W, 3) float RGB in [0, 1].
        mask:  (H, W) bool, the object.
    Returns:
        (H, W, 3) float32 RGB in [0, 1]; object pixels unchanged unless the contour covers them.
    """
    cfg = cfg or VisualPromptConfig()
    img = np.asarray(image, dtype=np.float32)
    mask = np.asarray(mask, dtype=bool)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image must be (H, W, 3), got {img.shape}")
    if mask.shape != img.shape[:2]:
        raise ValueError(f"mask shape {mask.shape} differs from image {img.shape[:2]}")
    background = img.copy()
    if cfg.grayscale_background:
        gray = cv2.cvtColor(background, cv2.COLOR_RGB2GRAY)
        background = np.repeat(gray[:, :, None], 3, axis=2)
    if cfg.blur_background and cfg.blur_radius > 0:
        k = 2 * cfg.blur_radius + 1
        background = cv2.GaussianBlur(background, (k, k), 0)
    out = np.where(mask[:, :, None], img, background).astype(np.float32)
    if cfg.contour and mask.any():
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, contours, -1, tuple(float(c) for c in cfg.contour_color),
                         thickness=max(1, 2 * cfg.contour_radius))
    return np.clip(out, 0.0, 1.0)
