"""The ``gt`` segmenter (oracle track): the generator's exact id maps of TRAINING frames.

Levels: subpart / part / whole = small / middle / large. The background and static surroundings
(id 0) belong to no mask. Asking for an evaluated frame raises: its ground truth is for scoring.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from benchmark.core.scene import Frame, Scene

from .base import Segmenter
from .truth_access import open_truth, training_id_maps


class GroundTruthSegmenter(Segmenter):
    name = "gt"
    track = "oracle"

    def __init__(self, scene: Scene) -> None:
        self.truth = open_truth(scene)

    def config(self) -> dict[str, Any]:
        return {"name": self.name, "generator_version": self.truth.generator_version, "preset": self.truth.preset,
                "seed": self.truth.seed}

    def segment(self, frame: Frame) -> np.ndarray:
        """(3, H, W) int32 truth ids of a training frame; -1 = no mask."""
        return training_id_maps(self.truth, frame)


def create(scene: Scene, *, text_encoder=None, device: str = "cpu") -> GroundTruthSegmenter:
    return GroundTruthSegmenter(scene)
