"""Oracle supervision for scenes whose only truth is a foreground alpha (D-NeRF): ``alpha`` + ``object-name``.

D-NeRF's RGBA frames carry an exact whole-object mask. On TRAINING frames:

* the ``alpha`` segmenter cuts each frame into two masks at every level: the object (alpha) and the
  background (everything else), so every pixel is supervised as a real segmenter's would be;
* the ``object-name`` image-text source gives the object mask the text embedding of the scene's
  object name (the scene's whole-object query: its annotation file, or the run's ``object_query``) and the
  background mask the embedding of ``background_text``, as passages of the run's text encoder.

The time-sensitive counterpart, the states of the annotation file's time segments at the training
frames, captions the time-varying heads and the caption-replay floor (:mod:`methods.captioners.states`).

Like the synthetic oracle, they isolate the 3D/4D method from 2D foundation models; evaluated frames'
alpha (the ground truth of the whole-object query) is never read: asking raises.
"""

from __future__ import annotations

from typing import Any, Optional

import numpy as np

from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from .base import LEVELS, ImageTextEncoder, Segmenter, TextEncoder
from .truth_access import EVAL_TRUTH_MESSAGE, EvaluatedFrameTruthError

OBJECT_ID = 1
BACKGROUND_ID = 0


def training_alpha(frame: Frame) -> np.ndarray:
    """(H, W) bool alpha of a TRAINING frame (any other frame raises :class:`EvaluatedFrameTruthError`)."""
    if frame.split != "train":
        raise EvaluatedFrameTruthError(f"frame {frame.name!r} is a {frame.split} frame: {EVAL_TRUTH_MESSAGE}")
    alpha = frame.alpha()
    if alpha is None:
        raise InputError(frame.image_path, "alpha", f"frame {frame.name!r} has no alpha channel: the alpha oracle "
                                                    "needs RGBA frames (D-NeRF)")
    return np.asarray(alpha, dtype=bool)


class AlphaSegmenter(Segmenter):
    """Object / background from the training frame's alpha, the same at every level."""

    name = "alpha"
    track = "oracle"

    def segment(self, frame: Frame) -> np.ndarray:
        """(3, H, W) int32: 1 on the object, 0 on the background, at every level."""
        alpha = training_alpha(frame)
        ids = np.where(alpha, OBJECT_ID, BACKGROUND_ID).astype(np.int32)
        return np.broadcast_to(ids, (len(LEVELS), *ids.shape)).copy()


class ObjectNameEncoder(ImageTextEncoder):
    """Text embedding of the object's name on object masks, of ``background_text`` on the others."""

    name = "object-name"
    track = "oracle"

    def __init__(self, scene: Scene, text_encoder: TextEncoder, background_text: str = "background",
                 object_name: Optional[str] = None) -> None:
        if not object_name:
            raise InputError(scene.root, "object_name", "the object-name source needs the object's name (the "
                             "scene's whole-object query, or --object-query); a folder name is no name")
        self._text_encoder = text_encoder
        self.object_name = object_name
        self.background_text = background_text

    @property
    def text_encoder(self) -> TextEncoder:
        return self._text_encoder

    def config(self) -> dict[str, Any]:
        return {"name": self.name, "text_encoder": self._text_encoder.config(), "object_name": self.object_name,
                "background_text": self.background_text}

    def encode_masks(self, image: np.ndarray, masks: np.ndarray, *, frame: Frame,
                     levels: Optional[np.ndarray] = None) -> np.ndarray:
        """(M, D) unit rows: a mask is the object when most of its pixels are inside the alpha."""
        alpha = training_alpha(frame)
        masks = np.asarray(masks, dtype=bool)
        inside = (masks & alpha).reshape(len(masks), -1).sum(1)
        area = masks.reshape(len(masks), -1).sum(1)
        names = [self.object_name if 2 * i > a else self.background_text for i, a in zip(inside, area)]
        return self._text_encoder.encode(names, kind="passage")


def create_segmenter(scene: Scene, *, text_encoder=None, device: str = "cpu") -> AlphaSegmenter:
    return AlphaSegmenter()


def create_encoder(scene: Scene, *, text_encoder: TextEncoder, device: str = "cpu",
                   background_text: str = "background", object_name: Optional[str] = None) -> ObjectNameEncoder:
    return ObjectNameEncoder(scene, text_encoder, background_text, object_name)
