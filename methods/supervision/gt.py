"""The ``gt`` segmenter (oracle track): the generator's exact id maps of TRAINING frames.

Levels: subpart / part / whole = small / middle / large. The background and static surroundings (truth
id 0) form one mask at every level (``surroundings``, on by default): SAM's automatic mask generator, which
the paper's pipeline runs, segments the background too, so the paper's language field is supervised on
every pixel; with the surroundings in no mask the field is left free there and a paper-config method pays
for an artefact of the oracle. ``surroundings=False`` leaves them in no mask. Asking for an evaluated frame
raises: its ground truth is for scoring.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from .base import Segmenter
from .truth_access import open_truth, training_id_maps


class GroundTruthSegmenter(Segmenter):
    name = "gt"
    track = "oracle"

    def __init__(self, scene: Scene, surroundings: bool = True) -> None:
        if not isinstance(surroundings, bool):
            raise InputError(None, "segmenter.surroundings", f"expected true or false, got {surroundings!r}")
        self.truth = open_truth(scene)
        self.surroundings = surroundings

    def config(self) -> dict[str, Any]:
        out = {"name": self.name, "generator_version": self.truth.generator_version, "preset": self.truth.preset,
               "seed": self.truth.seed}
        if self.surroundings:
            out["surroundings"] = True
        return out

    def segment(self, frame: Frame) -> np.ndarray:
        """(3, H, W) int32 truth ids of a training frame; -1 = no mask; with :attr:`surroundings`, id 0 =
        the surroundings' mask (the truth's own id, which :func:`training_id_maps` reads as none)."""
        ids = training_id_maps(self.truth, frame)
        if self.surroundings:
            ids[ids < 0] = 0
        return ids


def create(scene: Scene, *, text_encoder=None, device: str = "cpu", surroundings: bool = True) -> GroundTruthSegmenter:
    return GroundTruthSegmenter(scene, surroundings)
