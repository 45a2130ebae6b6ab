"""The ``states`` captioner (ORACLE track, scenes without generator truth: D-NeRF): captions from the
annotation file's time segments on the training frames.

A scene such as D-NeRF's has no generator truth to write captions from, but its annotation file says in
which time intervals each state holds (the ``time_segments`` of its time-sensitive queries). The harness
reads them at the TRAINING frames' time indices only (:func:`methods.api.training_states`) and hands them
over as :attr:`methods.supervision.base.Supervision.states`; this captioner turns them into one caption per
tracked object and training frame:

* a frame inside one state's interval is captioned with that state's text (the same text over the whole
  interval: one state caption per interval), several states that hold at once joined with ``"; "``;
* a frame in no interval is captioned with the object's name (no stated state, as the ``template``
  captioner words an object without states).

The scene's one object is its alpha (:func:`alpha_tracks`). Images are not looked at.
"""

from __future__ import annotations

from typing import Any, Mapping, Optional, Sequence

import numpy as np

from benchmark.core.cache_keys import stable_hash
from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from .base import Captioner, ObjectTracks

OBJECT = 0
"""The id of the scene's one tracked object in :func:`alpha_tracks`."""


class StatesCaptioner(Captioner):
    name = "states"
    track = "oracle"
    uses_images = False

    def __init__(self, scene: Scene, *, states: Mapping[str, Sequence[str]], object_name: str) -> None:
        """
        Args:
            states: training frame name -> the states that hold at its time (``Supervision.states``).
            object_name: the object's name (the caption of a frame where no state holds).
        """
        if not states:
            raise InputError(scene.root, "states", f"scene {scene.name!r}: no training frame has states to caption "
                             "(the annotation file has no time-sensitive query with time segments)")
        if not object_name:
            raise InputError(scene.root, "object_name", "the states captioner needs the object's name")
        split = {f.name: f.split for f in scene.frames}
        for name in states:
            if split.get(name) != "train":
                from methods.supervision.truth_access import EVAL_TRUTH_MESSAGE, EvaluatedFrameTruthError

                raise EvaluatedFrameTruthError(f"states of frame {name!r} ({split.get(name, 'not in the scene')}): "
                                               f"only training frames' states are captions; {EVAL_TRUTH_MESSAGE}")
        self.states = {str(k): tuple(v) for k, v in states.items()}
        self.object_name = str(object_name)

    def config(self) -> dict[str, Any]:
        return {"name": self.name, "object_name": self.object_name,
                "states": stable_hash({k: list(v) for k, v in sorted(self.states.items())}, 16)}

    def describe_video(self, obj: int, frames: Sequence[Frame], images: Sequence[np.ndarray]) -> str:
        # what the object is; its course of states would reveal evaluated times, so it is not told
        return self.object_name

    def caption_frame(self, obj: int, frame: Frame, images: Sequence[np.ndarray], *,
                      description: Optional[str]) -> str:
        if frame.split != "train" or frame.name not in self.states:
            from methods.supervision.truth_access import EVAL_TRUTH_MESSAGE, EvaluatedFrameTruthError

            raise EvaluatedFrameTruthError(f"frame {frame.name!r} is a {frame.split} frame without training states: "
                                           f"{EVAL_TRUTH_MESSAGE}")
        held = self.states[frame.name]
        return "; ".join(held) if held else self.object_name


def alpha_tracks(scene: Scene, object_name: str, frames: Optional[list[Frame]] = None) -> ObjectTracks:
    """The one object of a scene with RGBA training frames (D-NeRF): its training alphas, as the ``alpha``
    segmenter cuts them (oracle track; evaluated frames' alphas are never read)."""
    from methods.supervision.alpha import training_alpha

    from .tracks import tracked_frames

    frames = tracked_frames(scene) if frames is None else frames
    ids = [np.where(training_alpha(f), OBJECT, -1).astype(np.int32) for f in frames]
    return ObjectTracks(source="alpha", frame_names=[f.name for f in frames], ids=ids,
                        labels={OBJECT: str(object_name)})


def create(scene: Scene, *, states: Mapping[str, Sequence[str]], object_name: str) -> StatesCaptioner:
    return StatesCaptioner(scene, states=states, object_name=object_name)
