"""In-memory ground truth: queries, evaluated frames, one mask per (query, frame), time intervals.

This is the data model; :mod:`annotations.format` reads and writes it as the project's versioned
JSON (COCO-style images/categories, COCO RLE masks, time segments), and the importers in
:mod:`annotations.release` / :mod:`annotations.davis` produce it from other formats.

Semantics
---------
* A **time-agnostic** query ("coffee cup") has a mask on every evaluated frame where it was annotated.
  A mask that is present but empty means "annotated: absent in this frame"; a missing
  (query, frame) pair means "not annotated" and is never scored.
* A **time-sensitive** query ("cracked cookie") names a ``base`` time-agnostic query whose masks it
  inherits (the release's rule), plus inclusive 0-based ``time_index`` intervals in which it holds.
  Its label at frame t is ``any(l <= t <= r)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Literal, Optional

import numpy as np
from pycocotools import mask as mask_utils

QueryKind = Literal["agnostic", "sensitive"]
Interval = tuple[int, int]


def encode_mask(mask: np.ndarray) -> dict:
    """(H, W) bool -> COCO RLE dict with ``counts`` as str (JSON-ready)."""
    m = np.asfortranarray(np.asarray(mask, dtype=np.uint8))
    rle = mask_utils.encode(m)
    rle["counts"] = rle["counts"].decode("ascii")
    return {"size": [int(rle["size"][0]), int(rle["size"][1])], "counts": rle["counts"]}


def decode_mask(rle: dict) -> np.ndarray:
    """COCO RLE dict (compressed str/bytes counts or uncompressed list counts) -> (H, W) bool."""
    r = dict(rle)
    if isinstance(r["counts"], list):
        r = mask_utils.frPyObjects(r, r["size"][0], r["size"][1])
    elif isinstance(r["counts"], str):
        r["counts"] = r["counts"].encode("ascii")
    return mask_utils.decode(r).astype(bool)


def normalise_intervals(intervals: Iterable[Iterable[int]]) -> list[Interval]:
    """Sort and merge inclusive intervals (touching ones merge: [0,3],[4,6] -> [0,6])."""
    ivs = sorted((int(a), int(b)) for a, b in intervals)
    merged: list[list[int]] = []
    for a, b in ivs:
        if merged and a <= merged[-1][1] + 1:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    return [(a, b) for a, b in merged]


@dataclass
class Query:
    """One query of a scene."""

    id: int
    """Category id, unique in the set (COCO ``categories[].id``)."""
    text: str
    """The query text, e.g. ``"cookie"`` or ``"cracked cookie"``."""
    kind: QueryKind = "agnostic"
    """``"agnostic"`` (where is X) or ``"sensitive"`` (when and where is X in state S)."""
    base: Optional[int] = None
    """For time-sensitive queries: id of the time-agnostic query whose masks it inherits."""
    intervals: list[Interval] = field(default_factory=list)
    """Inclusive 0-based ``time_index`` intervals where a time-sensitive query holds."""
    level: Optional[str] = None
    """Informational: the part level of the answer (``"subpart"``, ``"part"``, ``"whole"``)."""

    def holds_at(self, time_index: int) -> bool:
        return any(a <= time_index <= b for a, b in self.intervals)


@dataclass
class AnnotatedFrame:
    """An evaluated frame (COCO ``images[]``)."""

    id: int
    """Image id, unique in the set."""
    name: str
    """Frame name in the scene (:attr:`benchmark.scene.Frame.name`, the image file stem)."""
    time_index: int
    """0-based video frame number."""
    width: int
    height: int
    camera_id: str = "0"
    """Camera that took it (multi-camera rigs); ``"0"`` for monocular scenes."""


@dataclass
class AnnotationSet:
    """All ground truth of one scene."""

    scene: str
    """Scene name."""
    frames: list[AnnotatedFrame] = field(default_factory=list)
    queries: list[Query] = field(default_factory=list)
    masks: dict[tuple[int, int], dict] = field(default_factory=dict)
    """(query id, frame id) -> COCO RLE. Only time-agnostic queries own masks."""
    num_time_steps: Optional[int] = None
    """Length of the video in frames (for time-sensitive labels); ``None`` = unknown."""
    info: dict = field(default_factory=dict)
    """Provenance: tool, source files, annotator, date, supervision notes."""

    # -- lookups --------------------------------------------------------------------------------
    def query(self, key: int | str) -> Query:
        for q in self.queries:
            if q.id == key or q.text == key:
                return q
        raise KeyError(f"scene {self.scene!r} has no query {key!r}")

    def frame(self, key: int | str) -> AnnotatedFrame:
        for f in self.frames:
            if f.id == key or f.name == key:
                return f
        raise KeyError(f"scene {self.scene!r} has no annotated frame {key!r}")

    @property
    def agnostic_queries(self) -> list[Query]:
        return [q for q in self.queries if q.kind == "agnostic"]

    @property
    def sensitive_queries(self) -> list[Query]:
        return [q for q in self.queries if q.kind == "sensitive"]

    def mask_owner(self, query: Query) -> Query:
        """The query whose masks ``query`` uses (itself, or its base)."""
        return self.query(query.base) if query.kind == "sensitive" and query.base is not None else query

    def get_mask(self, query_id: int, frame_id: int) -> Optional[np.ndarray]:
        """(H, W) bool ground-truth mask, or ``None`` if this (query, frame) is not annotated."""
        owner = self.mask_owner(self.query(query_id))
        rle = self.masks.get((owner.id, frame_id))
        return None if rle is None else decode_mask(rle)

    def set_mask(self, query_id: int, frame_id: int, mask: Optional[np.ndarray]) -> None:
        """Store a mask (an all-False mask means "absent"); ``None`` removes the annotation."""
        if mask is None:
            self.masks.pop((query_id, frame_id), None)
        else:
            self.masks[(query_id, frame_id)] = encode_mask(mask)

    def annotated_frames(self, query_id: int) -> list[AnnotatedFrame]:
        """Frames where ``query_id`` (or its base) has a mask, sorted by time."""
        owner = self.mask_owner(self.query(query_id))
        ids = {fid for (qid, fid) in self.masks if qid == owner.id}
        return sorted((f for f in self.frames if f.id in ids), key=lambda f: (f.time_index, f.camera_id))

    def label(self, query_id: int, time_index: int) -> bool:
        return self.query(query_id).holds_at(time_index)
