"""In-memory ground truth: queries, evaluated frames, one mask per (query, frame), time intervals.

This is the data model; :mod:`annotations.format` reads and writes it as the project's versioned
JSON (COCO-style images/categories, COCO RLE masks, time segments), and the importers in
:mod:`annotations.release` / :mod:`annotations.davis` produce it from other formats.

Masks are COCO RLE. Every RLE a reader meets passes :func:`rle_runs` before anything decodes it:
the size first (against the frame, and at most :data:`MAX_MASK_PIXELS`), then each run (an int in
``0..height * width``, bounded before anything is summed, so no sum wraps around), then the total
(exactly ``height * width``). Compressed strings are parsed by :func:`string_to_runs`, never by
pycocotools' C decoder; :func:`decode_mask` builds the mask from the checked runs.

Semantics
---------
* A **time-agnostic** query ("coffee cup") has a mask on every evaluated frame where it was annotated.
  A mask that is present but empty means "annotated: absent in this frame"; a missing
  (query, frame) pair means "not annotated" and is never scored.
* A **time-sensitive** query ("cracked cookie") names a ``base`` time-agnostic query whose masks it
  inherits (the release's rule), plus inclusive 0-based ``time_index`` intervals in which it holds.
  Its label at frame t is ``any(l <= t <= r)``.
* **Provenance** is kept per mask: each may record how it was made (:data:`MADE_BY`). A query may be
  a **draft** (:data:`DRAFT`): its masks or intervals were made by a program or a person and nobody
  has checked them yet.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Literal, Optional, Sequence

import numpy as np
from pycocotools import mask as mask_utils

from .errors import InputError, short_repr

QueryKind = Literal["agnostic", "sensitive"]
Interval = tuple[int, int]

MADE_BY = ("drawn", "box", "clicks", "propagated", "corrected", "absent", "scripted")
"""How a mask was made: ``drawn`` by hand (brush, polygon), from a ``box`` (with no clicks), by a box and
corrective ``clicks``, ``propagated`` from another frame and accepted as proposed, ``corrected`` (a
proposal edited by hand), marked ``absent`` (the object is not in the frame), or ``scripted``: computed
by a program with no person in the loop (an alpha channel, a colour rule)."""
DRAFT = "draft"
"""The review state of a query nobody has checked yet (``Query.review``); ``None`` = reviewed."""


def encode_mask(mask: np.ndarray) -> dict:
    """(H, W) bool -> COCO RLE dict with ``counts`` as str (JSON-ready)."""
    m = np.asfortranarray(np.asarray(mask, dtype=np.uint8))
    rle = mask_utils.encode(m)
    rle["counts"] = rle["counts"].decode("ascii")
    return {"size": [int(rle["size"][0]), int(rle["size"][1])], "counts": rle["counts"]}


MAX_MASK_PIXELS = 1 << 26
"""Largest mask (height x width, 67 M pixels, e.g. 8192 x 8192) any reader accepts. The benchmark's
frames are far smaller (Neu3D's 2704 x 2028 is 5.5 M pixels); the bound caps what a few bytes of
RLE or a PNG header can make a reader allocate, and keeps every run length exact in the 32-bit
counts of pycocotools."""

_MAX_GROUPS = 6
"""Characters per number in a compressed RLE string. Six 5-bit groups hold every value a valid
mask needs (|delta| <= MAX_MASK_PIXELS < 2**29), and pycocotools' C decoder shifts a C ``int`` by
``5 * k``, which is only defined for fewer than 7 groups."""


def check_mask_size(size: Any, file: str | Path | None = None, field: str = "size",
                    expected: Optional[tuple[int, int]] = None) -> tuple[int, int]:
    """``size`` as ``(height, width)`` of positive ints within :data:`MAX_MASK_PIXELS`.

    ``expected`` ``(height, width)``: the frame the mask belongs to; any other size is refused
    here, before a single pixel is decoded. Raises :class:`InputError` naming ``field``.
    """
    if (not isinstance(size, (list, tuple)) or len(size) != 2
            or not all(_is_int(v) and v > 0 for v in size)):
        raise InputError(file, field, f"expected [height, width] of positive ints, got {short_repr(size)}")
    h, w = int(size[0]), int(size[1])
    if expected is not None and (h, w) != (int(expected[0]), int(expected[1])):
        raise InputError(file, field, f"mask is {w}x{h} (WxH) but its frame is {int(expected[1])}x{int(expected[0])}")
    if h * w > MAX_MASK_PIXELS:
        raise InputError(file, field, f"mask of {w}x{h} pixels is larger than the {MAX_MASK_PIXELS} pixels "
                                      "any frame may have")
    return h, w


def rle_string_limit(pixels: int) -> int:
    """Most characters a compressed RLE string of a mask of ``pixels`` pixels can need: at most
    ``pixels + 1`` runs (a checkerboard, after a first empty run) of at most :data:`_MAX_GROUPS` characters
    each. A longer string is refused from its length, before anything is decoded."""
    return _MAX_GROUPS * (int(pixels) + 1)


_PARSE_CHUNK = 1 << 20
"""Characters of a compressed RLE string parsed at a time: the temporaries stay a few MiB whatever its length."""


def string_to_runs(counts: str | bytes, file: str | Path | None = None, field: str = "counts") -> np.ndarray:
    """Run lengths (int64) of COCO's compressed RLE string; malformed strings raise :class:`InputError`.

    COCO packs each number (after the first three, as a difference from the run two places back)
    into 5-bit groups, low first, as characters ``'0' + c`` where bit 0x20 of ``c`` says "more groups
    follow" and bit 0x10 of the last group is the sign. Parsed here, not by pycocotools, whose C
    decoder reads past the end of a string that stops inside a number, and in chunks of
    :data:`_PARSE_CHUNK` characters, so that the memory beyond the result is bounded. The values are not
    range checked here (see :func:`rle_runs`, which also bounds the string's length by the mask's before
    calling this); each is below 2**30 in magnitude and there are fewer than 2**32 of them, so no int64
    sum below can wrap.
    """
    if isinstance(counts, str):
        try:
            data = counts.encode("ascii")
        except UnicodeEncodeError:
            raise InputError(file, field, "compressed RLE string is not ASCII") from None
    else:
        data = bytes(counts)
    if len(data) >= 1 << 32:
        raise InputError(file, field, "compressed RLE string is too long")
    raw = np.frombuffer(data, dtype=np.uint8)
    if raw.size == 0:
        return np.zeros(0, dtype=np.int64)
    if raw.min() < 48 or raw.max() > 48 + 63:
        bad = int(np.flatnonzero((raw < 48) | (raw > 48 + 63))[0])
        raise InputError(file, field, f"character {chr(data[bad])!r} at {bad} is not in COCO's RLE alphabet '0'..'o'")
    if (int(raw[-1]) - 48) & 0x20:
        raise InputError(file, field, "compressed RLE string ends inside a number (truncated)")
    count = int(raw.size - np.count_nonzero((raw - 48) & 0x20))  # one terminating character per number
    values = np.empty(count, dtype=np.int64)
    done, pos = 0, 0
    while pos < raw.size:
        stop = min(pos + _PARSE_CHUNK, raw.size)
        chunk = raw[pos:stop].astype(np.int64) - 48
        more = (chunk & 0x20) != 0
        ends = np.flatnonzero(~more)
        if stop < raw.size:  # end the chunk after its last complete number
            if ends.size == 0:
                raise InputError(file, field, f"a number in the compressed RLE string has more than {_MAX_GROUPS} "
                                              "characters: no mask needs it")
            stop = pos + int(ends[-1]) + 1
            chunk, more = chunk[:stop - pos], more[:stop - pos]
        starts = np.concatenate([[0], ends[:-1] + 1])
        lengths = ends - starts + 1
        if lengths.max() > _MAX_GROUPS:
            raise InputError(file, field, f"a number in the compressed RLE string has more than {_MAX_GROUPS} "
                                          "characters: no mask needs it")
        k = np.arange(chunk.size) - np.repeat(starts, lengths)
        part = np.add.reduceat((chunk & 0x1F) << (5 * k), starts)
        negative = (chunk[ends] & 0x10) != 0
        part[negative] -= np.left_shift(np.int64(1), 5 * lengths[negative])
        values[done:done + part.size] = part
        done += part.size
        pos = stop
    # undo the delta coding: cnts[i] += cnts[i-2] for i > 2 (COCO's rule starts at index 3)
    if values.size > 3:
        values[3::2] = np.cumsum(values[1::2])[1:]
        values[4::2] = np.cumsum(values[2::2])[1:]
    return values


def runs_to_string(runs: Sequence[int] | np.ndarray) -> str:
    """COCO's compressed RLE string of checked run lengths (what pycocotools writes for them)."""
    out = bytearray()
    prev = [0, 0]
    for i, run in enumerate(int(r) for r in runs):
        x = run - prev[i % 2] if i > 2 else run
        prev[i % 2] = run
        while True:
            c = x & 0x1F
            x >>= 5
            more = x != -1 if c & 0x10 else x != 0
            out.append(48 + (c | 0x20 if more else c))
            if not more:
                break
    return out.decode("ascii")


def rle_runs(rle: Any, file: str | Path | None = None, field: str = "segmentation",
             size: Optional[tuple[int, int]] = None) -> tuple[int, int, np.ndarray]:
    """``(height, width, runs)`` of a COCO RLE after every check; the one gate all RLE passes.

    ``rle`` is ``{"size": [h, w], "counts": compressed str/bytes | list of run lengths}``. The size
    is checked first (against ``size`` = the frame's ``(height, width)`` when given, and against
    :data:`MAX_MASK_PIXELS`), then every run: an int, ``0 <= run <= h * w``, and together exactly
    ``h * w`` pixels. Each run is bounded before anything is summed, so no sum can wrap around, and
    nothing is decoded or handed to pycocotools before these checks pass. Raises :class:`InputError`.
    """
    if not isinstance(rle, dict):
        raise InputError(file, field, f"expected an RLE object with 'size' and 'counts', got {type(rle).__name__}")
    for key in ("size", "counts"):
        if key not in rle:
            raise InputError(file, f"{field}.{key}", "missing required key")
    h, w = check_mask_size(rle["size"], file, f"{field}.size", size)
    pixels = h * w
    counts = rle["counts"]
    where = f"{field}.counts"
    if isinstance(counts, (str, bytes)):
        limit = rle_string_limit(pixels)
        if len(counts) > limit:  # before any array as long as the string is made
            raise InputError(file, where, f"compressed RLE string of {len(counts)} characters; a {h}x{w} mask "
                                          f"never needs more than {limit}")
        runs = string_to_runs(counts, file, where)
    elif isinstance(counts, (list, tuple)):
        if len(counts) > pixels + 1:
            raise InputError(file, where, f"{len(counts)} run lengths; a {h}x{w} mask never has more than "
                                          f"{pixels + 1}")
        for i, c in enumerate(counts):
            if not _is_int(c):
                raise InputError(file, f"{where}[{i}]", f"run lengths are integers, got {short_repr(c)}")
            if not 0 <= c <= pixels:  # exact comparison of unbounded ints: nothing wraps
                raise InputError(file, f"{where}[{i}]", f"run length {short_repr(c)} is outside 0..{pixels} "
                                                        f"(the mask has {h}x{w} pixels)")
        runs = np.array([int(c) for c in counts], dtype=np.int64)
    else:
        raise InputError(file, where, f"expected a compressed string or a list of run lengths, "
                                      f"got {type(counts).__name__}")
    if runs.size:
        bad = np.flatnonzero((runs < 0) | (runs > pixels))
        if bad.size:
            i = int(bad[0])
            raise InputError(file, where, f"run {i} has length {int(runs[i])}, outside 0..{pixels} "
                                          f"(the mask has {h}x{w} pixels)")
    total = int(runs.sum())  # each run <= 2**26 and fewer than 2**32 runs: exact in int64
    if total != pixels:
        raise InputError(file, where, f"run lengths cover {total} pixels but size {h}x{w} has {pixels}")
    return h, w, runs


def runs_to_mask(runs: np.ndarray, height: int, width: int) -> np.ndarray:
    """(H, W) bool of checked run lengths (column-major, first run = background), as pycocotools
    decodes them. Only for runs that :func:`rle_runs` accepted."""
    values = np.zeros(len(runs), dtype=bool)
    values[1::2] = True
    return np.repeat(values, runs).reshape(width, height).T


def check_rle(rle: Any, file: str | Path | None = None, field: str = "segmentation",
              size: Optional[tuple[int, int]] = None) -> dict:
    """A checked RLE as ``{"size": [h, w], "counts": compressed str}`` (JSON-ready, COCO's layout);
    see :func:`rle_runs` for the checks. A compressed string is kept as given."""
    h, w, runs = rle_runs(rle, file, field, size)
    counts = rle["counts"]
    if isinstance(counts, bytes):
        counts = counts.decode("ascii")  # string_to_runs has checked it is ASCII
    elif not isinstance(counts, str):
        counts = runs_to_string(runs)
    return {"size": [h, w], "counts": counts}


def decode_mask(rle: dict, file: str | Path | None = None, field: str = "mask",
                size: Optional[tuple[int, int]] = None) -> np.ndarray:
    """COCO RLE dict (compressed str/bytes counts or uncompressed list counts) -> (H, W) bool.

    Checked by :func:`rle_runs` first (an :class:`InputError` names ``file`` and ``field``);
    ``size`` = the frame's ``(height, width)`` refuses any other size before decoding.
    """
    h, w, runs = rle_runs(rle, file, field, size)
    return runs_to_mask(runs, h, w)


def _is_int(v: Any) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


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
    review: Optional[str] = None
    """:data:`DRAFT` while its masks and intervals are unchecked (made by a program or a person, not yet
    reviewed); ``None`` once reviewed."""

    def holds_at(self, time_index: int) -> bool:
        return any(a <= time_index <= b for a, b in self.intervals)


@dataclass
class AnnotatedFrame:
    """An evaluated frame (COCO ``images[]``)."""

    id: int
    """Image id, unique in the set."""
    name: str
    """Frame name in the scene (:attr:`benchmark.core.scene.Frame.name`, the image file stem)."""
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
    made_by: dict[tuple[int, int], str] = field(default_factory=dict)
    """(query id, frame id) -> how that mask was made (one of :data:`MADE_BY`); a mask without an entry
    has no record of it. Only annotated pairs (keys of :attr:`masks`) have one."""

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

    def draft_queries(self) -> list[Query]:
        """Queries not yet reviewed (``review == DRAFT``), in file order."""
        return [q for q in self.queries if q.review == DRAFT]

    def mask_owner(self, query: Query) -> Query:
        """The query whose masks ``query`` uses (itself, or its base)."""
        return self.query(query.base) if query.kind == "sensitive" and query.base is not None else query

    def get_mask(self, query_id: int, frame_id: int) -> Optional[np.ndarray]:
        """(H, W) bool ground-truth mask, or ``None`` if this (query, frame) is not annotated."""
        owner = self.mask_owner(self.query(query_id))
        rle = self.masks.get((owner.id, frame_id))
        return None if rle is None else decode_mask(rle)

    def set_mask(self, query_id: int, frame_id: int, mask: Optional[np.ndarray],
                 made_by: Optional[str] = None) -> None:
        """Store a mask (an all-False mask means "absent") and how it was made (one of :data:`MADE_BY`;
        ``None`` forgets an earlier record: a replaced mask is no longer what that said); ``mask=None``
        removes the annotation and its record."""
        if made_by is not None and made_by not in MADE_BY:
            raise ValueError(f"made_by {made_by!r} is not one of {', '.join(MADE_BY)}")
        key = (query_id, frame_id)
        if mask is None:
            self.masks.pop(key, None)
        else:
            self.masks[key] = encode_mask(mask)
        if mask is None or made_by is None:
            self.made_by.pop(key, None)
        else:
            self.made_by[key] = made_by

    def annotated_frames(self, query_id: int) -> list[AnnotatedFrame]:
        """Frames where ``query_id`` (or its base) has a mask, sorted by time."""
        owner = self.mask_owner(self.query(query_id))
        ids = {fid for (qid, fid) in self.masks if qid == owner.id}
        return sorted((f for f in self.frames if f.id in ids), key=lambda f: (f.time_index, f.camera_id))

    def label(self, query_id: int, time_index: int) -> bool:
        return self.query(query_id).holds_at(time_index)
