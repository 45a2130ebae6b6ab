"""The ``oracle-text`` image-text source (oracle track): a mask's feature is the text embedding of
the ground-truth name of what it covers.

For a mask cut at level ``l`` the name is that of the truth id covering most of its pixels at level
``l`` (for ``gt`` masks: exactly the mask's own object); without a level, the level and id whose
region overlaps the mask best (IoU). Masks over background only get the embedding of
:attr:`OracleTextEncoder.background_text`. Names are embedded as passages, queries as queries, by the
run's text encoder, so queries compare to masks in one space. TRAINING frames only.

Names carry no state ("box" whether its lid is open or shut), so a method that deforms these features over
time has nothing time-varying to learn from them. ``state_phrases=True`` (``--source-option
image_text.state_phrases=true``) names a mask of an object with a state timeline by its state's phrase at
the frame's time ("open box"), as a real CLIP crop would lean towards its current state. Off by default.
"""

from __future__ import annotations

from typing import Any, Optional

import numpy as np

from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from .base import LEVELS, ImageTextEncoder, TextEncoder
from .truth_access import open_truth, training_id_maps

TRUTH_LEVELS = ("subpart", "part", "whole")
"""The truth's level names, in the order of :data:`methods.supervision.base.LEVELS`."""


class OracleTextEncoder(ImageTextEncoder):
    name = "oracle-text"
    track = "oracle"

    def __init__(self, scene: Scene, text_encoder: TextEncoder, background_text: str = "background",
                 state_phrases: bool = False) -> None:
        self.truth = open_truth(scene)
        self._text_encoder = text_encoder
        self.background_text = background_text
        if not isinstance(state_phrases, bool):
            raise InputError(None, "image_text.state_phrases", f"expected true or false, got {state_phrases!r}")
        self.state_phrases = state_phrases
        self._stateful = set(self.truth.stateful_objects) if state_phrases else set()

    @property
    def text_encoder(self) -> TextEncoder:
        return self._text_encoder

    def config(self) -> dict[str, Any]:
        out = {"name": self.name, "text_encoder": self._text_encoder.config(),
               "background_text": self.background_text, "generator_version": self.truth.generator_version}
        if self.state_phrases:  # only when on: the default's supervision cache keys stay as they were
            out["state_phrases"] = True
        return out

    def mask_names(self, masks: np.ndarray, frame: Frame, levels: Optional[np.ndarray] = None) -> list[str]:
        """The ground-truth name of each (M, H, W) mask (see the module docstring)."""
        ids = training_id_maps(self.truth, frame)  # (3, H, W), -1 = none
        names = []
        for k, mask in enumerate(np.asarray(masks, dtype=bool)):
            if levels is not None:
                level = int(levels[k])
                covered = ids[level][mask]
                covered = covered[covered >= 0]
                best = int(np.bincount(covered).argmax()) if covered.size else -1
            else:
                level, best = self._best_overlap(ids, mask)
            name = self.background_text if best < 0 else self.truth.name(TRUTH_LEVELS[level], best)
            if name in self._stateful:
                name = self.truth.state_at(name, frame.time_index)["phrase"]
            names.append(name)
        return names

    @staticmethod
    def _best_overlap(ids: np.ndarray, mask: np.ndarray) -> tuple[int, int]:
        area = int(mask.sum())
        best, best_iou = (0, -1), 0.0
        for level in range(len(LEVELS)):
            plane = ids[level]
            inside = np.bincount(plane[mask & (plane >= 0)], minlength=1)
            if not inside.any():
                continue
            sizes = np.bincount(plane[plane >= 0], minlength=inside.size)[: inside.size]
            iou = inside / np.maximum(sizes + area - inside, 1)
            j = int(iou.argmax())
            if iou[j] > best_iou:
                best, best_iou = (level, j), float(iou[j])
        return best

    def encode_masks(self, image: np.ndarray, masks: np.ndarray, *, frame: Frame,
                     levels: Optional[np.ndarray] = None) -> np.ndarray:
        """(M, D) float32 unit rows: passage embeddings of the masks' ground-truth names."""
        names = self.mask_names(masks, frame, levels)
        return self._text_encoder.encode(names, kind="passage")


def create(scene: Scene, *, text_encoder: TextEncoder, device: str = "cpu",
           background_text: str = "background", state_phrases: bool = False) -> OracleTextEncoder:
    return OracleTextEncoder(scene, text_encoder, background_text, state_phrases)
