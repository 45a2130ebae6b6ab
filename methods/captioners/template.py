"""The ``template`` captioner (ORACLE track): captions written from a generated scene's semantic states.

Stands in for the MLLM so that the time-varying field can be measured apart from caption quality.
For a tracked object (a truth ``whole`` id, :func:`methods.captioners.tracks.truth_tracks`) at a
training frame:

* if the object, or one of its parts, has a state timeline, the caption is one of that state's
  paraphrases (the generator's truth lists several per state), drawn per frame with a seeded
  generator, as an MLLM words the same state differently from frame to frame; several stateful
  parts are joined with ``"; "``;
* otherwise the caption is the object's name, the same in every frame (its semantics never change).

Only the truth of TRAINING frames is read (``SceneTruth.state_at`` refuses other time indices).
Images are not looked at, so the visual and text prompts change nothing here: on the oracle track
the prompt ablation measures the caption and text-encoder path only.
"""

from __future__ import annotations

import zlib
from typing import Any, Optional, Sequence

import numpy as np

from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from .base import Captioner
from .tracks import whole_of


class TemplateCaptioner(Captioner):
    name = "template"
    track = "oracle"
    uses_images = False

    def __init__(self, scene: Scene, *, seed: int = 0, paraphrases: bool = True) -> None:
        """
        Args:
            seed: seed of the per-frame paraphrase draw.
            paraphrases: draw one of the state's paraphrases per frame (True) or always use the first.
        """
        from methods.supervision.truth_access import open_truth

        self.truth = open_truth(scene)
        self.scene_name = scene.name
        self.seed = int(seed)
        self.paraphrases = bool(paraphrases)
        self._stateful = self._stateful_by_whole()

    def config(self) -> dict[str, Any]:
        return {"name": self.name, "seed": self.seed, "paraphrases": self.paraphrases,
                "generator_version": self.truth.generator_version}

    def _stateful_by_whole(self) -> dict[int, list[str]]:
        """Whole id -> names of the stateful nodes inside it (itself or its parts), in truth order."""
        out: dict[int, list[str]] = {}
        for name in self.truth.stateful_objects:
            level, ids = self.truth.ids_named(name)
            for id_ in ids:
                whole = whole_of(self.truth, level, id_)
                if name not in out.setdefault(whole, []):
                    out[whole].append(name)
        return out

    def describe_video(self, obj: int, frames: Sequence[Frame], images: Sequence[np.ndarray]) -> str:
        # What the object is; its course of states would reveal evaluated times, so it is not told.
        return self._name(obj)

    def _name(self, obj: int) -> str:
        if int(obj) not in self.truth.catalogue["whole"]:
            raise InputError(None, "template captioner", f"object {obj} is no whole-level object of the truth "
                             f"of {self.scene_name!r}: the template captioner needs truth tracks")
        return self.truth.name("whole", int(obj)) or f"object {obj}"

    def caption_frame(self, obj: int, frame: Frame, images: Sequence[np.ndarray], *,
                      description: Optional[str]) -> str:
        if frame.split != "train":
            from methods.supervision.truth_access import EVAL_TRUTH_MESSAGE, EvaluatedFrameTruthError

            raise EvaluatedFrameTruthError(f"frame {frame.name!r} is a {frame.split} frame: {EVAL_TRUTH_MESSAGE}")
        name = self._name(obj)
        stateful = self._stateful.get(int(obj), [])
        if not stateful:
            return name
        rng = np.random.default_rng([self.seed, zlib.crc32(frame.name.encode()), int(obj)])
        parts = []
        for node in stateful:
            options = self.truth.state_at(node, frame.time_index)["captions"]
            parts.append(options[int(rng.integers(len(options)))] if self.paraphrases else options[0])
        return "; ".join(parts)
