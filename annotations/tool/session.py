"""The annotation tool's state, apart from HTTP: one scene, one annotation file, one writer.

:class:`AnnotationSession` owns the :class:`~benchmark.core.annotation.AnnotationSet` being edited. Every
accepted change is written to disk at once (temporary file, flush + fsync, atomic replace) with a
new revision number; a change made against an older revision is refused (:class:`Conflict`), so a
second browser tab cannot overwrite the first. A lock file held with ``flock`` keeps a second
server off the same file; the kernel drops the lock when the process dies, so a killed server
leaves nothing to clean up by hand.

Clients name things by index and id only (frame index in the tool's frame list, query id); every
file the session writes lies under the project root (the folder of the annotation file).
"""

from __future__ import annotations

import base64
import collections
import copy
import datetime as _dt
import fcntl
import io
import json
import math
import os
import re
import shutil
import stat
import threading
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import cv2
import numpy as np

from benchmark.core.errors import InputError
from benchmark.core.strict import check_keys, check_text, file_problem, text_key
from benchmark.core.scene import Frame, Scene

from ..assist import GrabCutSegmenter, Segmenter
from ..format import load_annotations, save_annotations, validate_against_scene
from benchmark.core.annotation import (MADE_BY, AnnotatedFrame, AnnotationSet, Query, decode_mask, encode_mask,
                                       normalise_intervals)
from ..propagate import PropagationConfig, propagate_between, propagate_chain
from .review import ReviewConfig, review

TOOL_NAME = "bench4d annotate"
SCORED = "scored"
"""The ``split`` that offers the frames the benchmark scores (the held-out test frames)."""
MAX_CLICKS = 1000
"""Most corrective clicks one segmentation request may carry."""
MAX_COORDINATE = 1e6
"""Box and click coordinates (pixels) beyond this are refused: far outside any frame, and near the
limits of the integer pixel arithmetic of the segmenters."""


MASK_KEYS = ("counts", "absent", "size", "state", "made_by")
"""Keys of a mask object in a request (the page's ``{counts}`` / ``{absent}``, or a mask as the server sends
it): any other key is refused."""


class Conflict(Exception):
    """A write based on an old revision (HTTP 409)."""

    def __init__(self, current: int, given: Any):
        super().__init__(f"stale revision {given!r}: the file is at revision {current}; reload to continue")
        self.current = current


class Locked(InputError):
    """Another process holds the annotation set's lock file."""


@dataclass
class SessionConfig:
    """Settings of one annotation session."""

    split: str = "scored"
    """Frames offered for annotation: ``scored`` (the held-out test frames the benchmark scores; every
    frame if the scene has none), ``all``, or a comma list of splits (``test``, ``train,val``)."""
    annotator: str = "human"
    """Recorded in ``info.annotator``: ``human`` (a person), ``simulated`` (a simulated annotator
    against exact truth; :attr:`protocol` says how) or ``scripted`` (a fixed plan)."""
    protocol: Optional[dict] = None
    """Recorded in ``info.protocol`` when given: how a simulated annotator chose its interactions and
    its target IoU."""
    method: Optional[str] = None
    """Recorded in ``info.method`` when given (how masks were made, for scripted sessions)."""
    record_timing: bool = True
    """Add the page's active editing time per frame to ``info.annotation_seconds`` (off for scripted
    sessions, whose timings would say nothing about human effort)."""
    autosave_delay_ms: int = 1000
    """The page saves this long after an edit (and at once on frame change)."""
    image_cache: int = 48
    """Decoded frames kept in memory (uint8 RGB)."""
    jpeg_quality: int = 92
    """Quality of the frames sent to the page (display only: masks never go through JPEG)."""
    thumb_width: int = 96
    """Width of review-mode thumbnails, in pixels."""
    max_propagation_frames: int = 60
    """Most frames one propagation request may fill."""
    max_import_bytes: int = 64 * 1024 * 1024
    """Largest import accepted (the uploaded file; a release export of a scene is a few MiB)."""
    max_archive_members: int = 20000
    """Most entries an imported zip archive may have."""
    max_unpacked_bytes: int = 512 * 1024 * 1024
    """Most bytes the JSON members of an imported archive may unpack to (zip bombs)."""
    propagation: PropagationConfig = field(default_factory=PropagationConfig)
    """Settings of mask propagation."""
    review: ReviewConfig = field(default_factory=ReviewConfig)
    """Thresholds of the review checks."""


EXPORT_FORMATS = {
    "project": "bench4d annotation JSON (this tool's format)",
    "coco-rle": "COCO JSON with RLE masks (agnostic queries)",
    "release": "4D LangSplat release: Roboflow COCO (polygons) + video_annotations.json",
}
IMPORT_FORMATS = {
    "project": "bench4d annotation JSON",
    "coco-rle": "COCO JSON with RLE or polygon masks, file names = frame names",
    "release": "Roboflow COCO (.json or .zip of the release folder), optional video_annotations.json",
    "video-annotations": "video_annotations.json: time intervals of time-sensitive queries",
}


# ---------------------------------------------------------------------------------------------
# RLE in the page's format: COCO *uncompressed* counts (column-major runs, first run = zeros)
# ---------------------------------------------------------------------------------------------
def mask_to_runs(mask: np.ndarray) -> list[int]:
    """(H, W) bool -> COCO uncompressed run lengths in column-major order, starting with zeros."""
    flat = np.asarray(mask, dtype=bool).ravel(order="F")
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    edges = np.concatenate([[0], change, [flat.size]])
    runs = np.diff(edges).tolist()
    if flat.size and flat[0]:
        runs = [0] + runs
    return runs


def check_runs(runs: Any, height: int, width: int, field: str = "mask", file: Optional[str] = None) -> list[int]:
    """Validate run lengths for an (H, W) mask before any decoder sees them; returns them.

    Every run must be a non-negative ``int`` and the runs must add up to exactly H x W, checked in
    Python integers: in int64, runs such as ``[HW, 2**63 - 1, 2**63 - 1, 2]`` wrap around to the
    right sum, and a decoder trusting that sum writes far past its buffer.
    """
    name = f"{field}.counts"
    if not isinstance(runs, list):
        raise InputError(file, name, "expected a list of integer run lengths")
    total = height * width
    if len(runs) > total + 1:  # even a checkerboard needs at most H x W + 1 runs
        raise InputError(file, name, f"{len(runs)} runs for a {height}x{width} frame (at most {total + 1})")
    if not all(isinstance(r, int) and not isinstance(r, bool) for r in runs):
        raise InputError(file, name, "expected a list of integer run lengths")
    if runs and min(runs) < 0:
        raise InputError(file, name, "negative run length")
    if runs and max(runs) > total:
        raise InputError(file, name, f"a run is longer than the frame's {height}x{width}={total} pixels")
    covered = sum(runs)  # Python ints: no wrap-around
    if covered != total:
        raise InputError(file, name, f"runs cover {covered} pixels, the frame has {height}x{width}={total}")
    return runs


def runs_to_mask(runs: Any, height: int, width: int, field: str = "mask") -> np.ndarray:
    """Inverse of :func:`mask_to_runs`, validated (an :class:`InputError` names ``field``)."""
    runs = check_runs(runs, height, width, field)
    try:
        counts = np.asarray(runs, dtype=np.int64)  # each run is at most H x W: no overflow
        values = (np.arange(counts.size) % 2).astype(bool)
        flat = np.repeat(values, counts)
        return flat.reshape(width, height).T.copy()
    except (ValueError, OverflowError) as err:  # not expected after check_runs: a second line of defence
        raise InputError(None, f"{field}.counts", f"cannot decode: {err}") from None


def _coordinate(v: Any) -> bool:
    """A finite number of reasonable size (``float()`` of a 400-digit int raises, ``inf`` poisons GrabCut)."""
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return False
    try:
        return math.isfinite(float(v)) and abs(float(v)) <= MAX_COORDINATE
    except OverflowError:
        return False


def _mask_payload(rle: Optional[dict]) -> Optional[dict]:
    if rle is None:
        return None
    mask = decode_mask(rle)
    return {"state": "mask" if mask.any() else "absent", "size": list(mask.shape), "counts": mask_to_runs(mask)}


# ---------------------------------------------------------------------------------------------
# lock file
# ---------------------------------------------------------------------------------------------
class LockFile:
    """``<annotations>.lock``, held with ``flock`` for the life of the session."""

    def __init__(self, target: Path):
        self.path = target.with_name(target.name + ".lock")
        self._fd: Optional[int] = None

    def acquire(self, note: dict) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        problem = file_problem(self.path)
        if problem not in (None, "missing"):  # a FIFO would block the open, a folder cannot be locked
            raise InputError(self.path, None, f"the lock file is {problem}, not a file: remove it (no session "
                                              "holds a lock that is not a file)")
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NONBLOCK | os.O_NOFOLLOW, 0o644)
        except OSError as err:
            raise InputError(self.path, None, f"cannot open the lock file: {err.strerror or err}") from None
        if not stat.S_ISREG(os.fstat(fd).st_mode):  # replaced between the check and the open
            os.close(fd)
            raise InputError(self.path, None, "the lock file is not a file")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = os.read(fd, 4096).decode("utf-8", "replace").strip()
            finally:
                os.close(fd)
            raise Locked(self.path, None, f"the annotation set is open in another session ({holder or 'unknown'}); "
                                          "close that one first") from None
        os.ftruncate(fd, 0)
        os.write(fd, (json.dumps(note) + "\n").encode())
        os.fsync(fd)
        self._fd = fd

    def release(self) -> None:
        if self._fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)
        finally:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None


# ---------------------------------------------------------------------------------------------
# the session
# ---------------------------------------------------------------------------------------------
class AnnotationSession:
    """Edits one annotation file of one scene (see the module docstring)."""

    def __init__(self, scene: Scene, annotations_path: str | Path, *, segmenter: Optional[Segmenter] = None,
                 config: Optional[SessionConfig] = None, lock: bool = True):
        self.scene = scene
        self.config = config or SessionConfig()
        self.path = Path(annotations_path).resolve()
        self.root = self.path.parent
        self.segmenter = segmenter or GrabCutSegmenter()
        self.frames: list[Frame] = self._select_frames(scene, self.config.split)
        if not self.frames:
            raise InputError(scene.root, "--split", f"no frames of scene {scene.name!r} in split {self.config.split!r}")
        self.index_of = {f.name: i for i, f in enumerate(self.frames)}
        self._lock = threading.RLock()
        self._images: collections.OrderedDict[int, np.ndarray] = collections.OrderedDict()
        self._image_lock = threading.Lock()
        self._lockfile = LockFile(self.path) if lock else None
        self.removed_temp_files: list[str] = []
        """Temporary files of interrupted writes found and removed at start (see :func:`remove_interrupted_writes`)."""
        if self._lockfile is not None:
            self._lockfile.acquire({"pid": os.getpid(), "started": _now()})
        try:
            if self._lockfile is not None:  # only the lock holder writes these files
                self.removed_temp_files = remove_interrupted_writes(self.path)
            self.aset = self._open(self.path)
        except BaseException:
            self.close()
            raise
        self.revision = int(self.aset.info.get("revision", 0) or 0)

    # -- set-up ---------------------------------------------------------------------------------
    @staticmethod
    def _select_frames(scene: Scene, split: str) -> list[Frame]:
        if split in ("", "all"):
            return list(scene.frames)
        if split == SCORED:
            scored = [f for f in scene.frames if f.split == "test"]
            return scored or list(scene.frames)
        wanted = {s.strip() for s in split.split(",") if s.strip()}
        unknown = wanted - {"train", "val", "test"}
        if unknown:
            raise InputError(None, "--split", f"unknown split(s) {sorted(unknown)} (train, val, test, scored or all)")
        return [f for f in scene.frames if f.split in wanted]

    def _open(self, path: Path) -> AnnotationSet:
        if path.exists():
            aset = load_annotations(path, scene=self.scene)
        else:
            aset = AnnotationSet(scene=self.scene.name, num_time_steps=self._num_time_steps())
        if aset.num_time_steps is None:
            aset.num_time_steps = self._num_time_steps()
        aset.info.setdefault("tool", TOOL_NAME)
        return aset

    def _num_time_steps(self) -> int:
        return max(f.time_index for f in self.scene.frames) + 1

    def close(self) -> None:
        if self._lockfile is not None:
            self._lockfile.release()

    # -- reading --------------------------------------------------------------------------------
    def frame(self, index: Any) -> Frame:
        if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(self.frames):
            raise InputError(None, "frame", f"frame index {index!r} is not in 0..{len(self.frames) - 1}")
        return self.frames[index]

    def image(self, index: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB of frame ``index`` (cached)."""
        with self._image_lock:
            img = self._images.get(index)
            if img is not None:
                self._images.move_to_end(index)
                return img
        img = self.frame(index).image()
        img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        with self._image_lock:
            self._images[index] = img
            while len(self._images) > self.config.image_cache:
                self._images.popitem(last=False)
        return img

    def frame_jpeg(self, index: int) -> bytes:
        img = self.image(index)
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, self.config.jpeg_quality])
        if not ok:  # pragma: no cover - OpenCV encodes any uint8 image
            raise InputError(None, "frame", "cannot encode JPEG")
        for j in (index + 1, index - 1, index + 2):
            if 0 <= j < len(self.frames):
                self.segmenter.prefetch(self.frames[j].name, lambda j=j: self.image(j))
        self.segmenter.prefetch(self.frames[index].name, lambda: self.image(index))
        return buf.tobytes()

    def thumb_jpeg(self, index: int, query_id: Optional[int]) -> bytes:
        """A small frame with the query's mask tinted (review filmstrip)."""
        img = self.image(index)
        h, w = img.shape[:2]
        tw = self.config.thumb_width
        th = max(1, int(round(h * tw / w)))
        small = cv2.resize(img, (tw, th), interpolation=cv2.INTER_AREA).astype(np.float32)
        if query_id is not None:
            mask = self.mask(query_id, index)
            if mask is not None and mask.any():
                m = cv2.resize(mask.astype(np.float32), (tw, th), interpolation=cv2.INTER_AREA)[..., None]
                small = small * (1 - 0.55 * m) + np.array([255.0, 40.0, 200.0]) * 0.55 * m
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(small.astype(np.uint8), cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, 85])
        return buf.tobytes()

    def query(self, qid: Any) -> Query:
        if not isinstance(qid, int) or isinstance(qid, bool):
            raise InputError(None, "query", f"expected a query id, got {qid!r}")
        try:
            return self.aset.query(qid)
        except KeyError:
            raise InputError(None, "query", f"no query with id {qid}") from None

    def owner(self, qid: int) -> Query:
        """The query whose masks ``qid`` uses (a time-sensitive query uses its base's)."""
        return self.aset.mask_owner(self.query(qid))

    def _annotated_frame(self, index: int) -> Optional[AnnotatedFrame]:
        name = self.frames[index].name
        for f in self.aset.frames:
            if f.name == name:
                return f
        return None

    def mask(self, qid: int, index: int) -> Optional[np.ndarray]:
        """(H, W) bool mask of query ``qid`` (its owner) on frame ``index``; ``None`` = not annotated."""
        with self._lock:
            af = self._annotated_frame(index)
            if af is None:
                return None
            rle = self.aset.masks.get((self.owner(qid).id, af.id))
        return None if rle is None else decode_mask(rle)

    def state(self) -> dict:
        """Everything the page needs at start (and after a conflict): frames, queries, status."""
        with self._lock:
            by_id = {f.id: f for f in self.aset.frames}
            status: dict[int, dict[int, int]] = {}
            for (qid, fid), rle in self.aset.masks.items():
                af = by_id.get(fid)
                idx = self.index_of.get(af.name) if af is not None else None
                if idx is None:
                    continue
                status.setdefault(qid, {})[idx] = 1 if _rle_nonempty(rle) else 0
            return {
                "scene": self.scene.name,
                "file": self.path.name,
                "revision": self.revision,
                "num_time_steps": self.aset.num_time_steps,
                "frames": [{"index": i, "name": f.name, "time_index": f.time_index, "camera_id": f.camera_id,
                            "split": f.split, "width": f.camera.width, "height": f.camera.height}
                           for i, f in enumerate(self.frames)],
                "queries": [{"id": q.id, "text": q.text, "kind": q.kind, "base": q.base, "level": q.level,
                             "review": q.review, "intervals": [list(iv) for iv in q.intervals]}
                            for q in self.aset.queries],
                "status": {str(q): {str(i): v for i, v in d.items()} for q, d in status.items()},
                "autosave_delay_ms": self.config.autosave_delay_ms,
                "segmenter": self.segmenter.name,
                "export_formats": EXPORT_FORMATS,
                "import_formats": IMPORT_FORMATS,
                "annotator": self.aset.info.get("annotator", self.config.annotator),
                "frames_offered": self._frames_offered(),
            }

    def _frames_offered(self) -> str:
        """One line for the page: which frames the session offers and whether they are the scored ones."""
        n, total = len(self.frames), len(self.scene.frames)
        scored = sum(f.split == "test" for f in self.scene.frames)
        if self.config.split == SCORED and scored:
            return f"{n} scored frames (the test split the benchmark scores) of {total}"
        if self.config.split == SCORED:
            return f"all {n} frames (the scene has no test split)"
        return f"{n} of {total} frames (split {self.config.split}); the benchmark scores the {scored} test frames"

    def masks_of_frame(self, index: int) -> dict:
        """Masks of every mask-owning query on frame ``index`` in the page's RLE format."""
        frame = self.frame(index)
        with self._lock:
            af = self._annotated_frame(index)
            out = {}
            for q in self.aset.agnostic_queries:
                rle = None if af is None else self.aset.masks.get((q.id, af.id))
                payload = _mask_payload(rle)
                how = None if af is None else self.aset.made_by.get((q.id, af.id))
                if payload is not None and how is not None:
                    payload["made_by"] = how
                out[str(q.id)] = payload
            return {"frame": index, "name": frame.name, "time_index": frame.time_index,
                    "width": frame.camera.width, "height": frame.camera.height, "revision": self.revision,
                    "masks": out}

    # -- writing --------------------------------------------------------------------------------
    def _check_revision(self, given: Any) -> None:
        if given != self.revision:
            raise Conflict(self.revision, given)

    def _ensure_frame(self, index: int) -> AnnotatedFrame:
        af = self._annotated_frame(index)
        if af is not None:
            return af
        f = self.frames[index]
        new_id = max((x.id for x in self.aset.frames), default=0) + 1
        af = AnnotatedFrame(id=new_id, name=f.name, time_index=f.time_index, width=f.camera.width,
                            height=f.camera.height, camera_id=str(f.camera_id))
        self.aset.frames.append(af)
        self.aset.frames.sort(key=lambda x: (x.time_index, x.camera_id, x.name))
        return af

    def _commit(self) -> int:
        """Write the set with the next revision (atomic); returns the new revision."""
        self.revision += 1
        info = self.aset.info
        info["tool"] = TOOL_NAME
        info["revision"] = self.revision
        info["saved"] = _now()
        info.setdefault("annotator", self.config.annotator)
        # everyone who edited the file, so a scripted pass over a human file (or back) stays visible
        who = info.setdefault("annotators", [info["annotator"]])
        if self.config.annotator not in who:
            who.append(self.config.annotator)
        if self.config.method:
            info["method"] = self.config.method
        if self.config.protocol:
            info["protocol"] = self.config.protocol
        info["segmenter"] = self.segmenter.name
        try:
            save_annotations(self.aset, self.path, overwrite=True)
        except BaseException:
            self.revision -= 1
            raise
        return self.revision

    def apply(self, revision: Any, changes: Any, timing: Any = None) -> int:
        """Apply a batch of edits atomically; returns the new revision.

        ``changes``: list of ``{"type": "mask", "query": id, "frame": index, "mask": {"counts": [...]}
        | {"absent": true} | null, "made_by": optional, one of MADE_BY}`` (``null`` = back to "not
        annotated") and
        ``{"type": "intervals", "query": id, "intervals": [[l, r], ...]}``. ``timing``: optional
        ``{frame index: seconds}`` of active annotation time to add to ``info``.
        """
        if not isinstance(changes, list):
            raise InputError(None, "changes", "expected a list")
        with self._lock:
            self._check_revision(revision)
            # every change is checked before any is applied: a bad one leaves the file as it was
            staged = [self._stage_change(f"changes[{n}]", ch) for n, ch in enumerate(changes)]
            return self._apply_staged(staged, timing)

    def _stage_change(self, field_name: str, ch: Any) -> tuple:
        """One change, checked: ``("mask", query id, frame index, RLE or None, made_by or None)`` or
        ``("intervals", query id, intervals)``."""
        if not isinstance(ch, dict):
            raise InputError(None, field_name, "expected an object")
        kind = ch.get("type")
        if kind == "mask":
            check_keys(ch, ("type", "query", "frame", "mask", "made_by"), None, field_name, allow_unknown=False)
            return self._stage_mask(field_name, ch)
        if kind == "intervals":
            check_keys(ch, ("type", "query", "intervals"), None, field_name, allow_unknown=False)
            return self._stage_intervals(field_name, ch)
        raise InputError(None, f"{field_name}.type", f"unknown change type {kind!r} (mask or intervals)")

    def _stage_mask(self, field_name: str, ch: dict) -> tuple:
        index = ch.get("frame")
        frame = self.frame(index)
        owner = self.owner(ch.get("query"))
        payload = ch.get("mask")
        made_by = ch.get("made_by")
        if made_by is not None and made_by not in MADE_BY:
            raise InputError(None, f"{field_name}.made_by", f"expected one of {', '.join(MADE_BY)} or null")
        if payload is None:
            return ("mask", owner.id, index, None, None)
        if not isinstance(payload, dict):
            raise InputError(None, f"{field_name}.mask", "expected an object or null")
        check_keys(payload, MASK_KEYS, None, f"{field_name}.mask", allow_unknown=False)
        h, w = frame.camera.height, frame.camera.width
        if payload.get("absent") is True:
            mask = np.zeros((h, w), bool)
        else:
            mask = runs_to_mask(payload.get("counts"), h, w, f"{field_name}.mask")
        return ("mask", owner.id, index, encode_mask(mask), made_by)

    def _stage_intervals(self, field_name: str, ch: dict) -> tuple:
        q = self.query(ch.get("query"))
        if q.kind != "sensitive":
            raise InputError(None, f"{field_name}.query", f"{q.text!r} is time-agnostic: no intervals")
        ivs = ch.get("intervals")
        if not isinstance(ivs, list) or not all(
                isinstance(iv, list) and len(iv) == 2 and all(isinstance(v, int) and not isinstance(v, bool)
                                                              for v in iv) for iv in ivs):
            raise InputError(None, f"{field_name}.intervals", "expected a list of [l, r] integer pairs")
        last = self.aset.num_time_steps - 1
        clean = []
        for lo, hi in ivs:
            lo, hi = min(lo, hi), max(lo, hi)
            if lo < 0 or hi > last:
                raise InputError(None, f"{field_name}.intervals",
                                 f"[{lo}, {hi}] is outside the video's time indices 0..{last}")
            clean.append((lo, hi))
        return ("intervals", q.id, normalise_intervals(clean))

    def _apply_staged(self, staged: list[tuple], timing: Any) -> int:
        """Apply checked changes and commit; on any failure the annotation set is restored."""
        backup_masks = dict(self.aset.masks)
        backup_made_by = dict(self.aset.made_by)
        backup_frames = list(self.aset.frames)
        backup_intervals = {q.id: list(q.intervals) for q in self.aset.queries}
        backup_info = copy.deepcopy(self.aset.info)
        try:
            for item in staged:
                if item[0] == "mask":
                    _, qid, index, rle, made_by = item
                    if rle is None:
                        af = self._annotated_frame(index)
                        if af is not None:
                            self.aset.masks.pop((qid, af.id), None)
                            self.aset.made_by.pop((qid, af.id), None)
                    else:
                        af = self._ensure_frame(index)
                        self.aset.masks[(qid, af.id)] = rle
                        self._note_made_by((qid, af.id), made_by)
                else:
                    _, qid, ivs = item
                    self.aset.query(qid).intervals = ivs
            self._add_timing(timing)
            return self._commit()
        except BaseException:
            self.aset.masks = backup_masks
            self.aset.made_by = backup_made_by
            self.aset.frames = backup_frames
            for q in self.aset.queries:
                q.intervals = backup_intervals.get(q.id, [])
            self.aset.info = backup_info
            raise

    def _note_made_by(self, key: tuple[int, int], made_by: Optional[str]) -> None:
        """Keep how the mask of (query id, frame id) ``key`` was made; a change that does not say
        forgets the earlier note (an edited proposal is no longer "propagated")."""
        if made_by is None:
            self.aset.made_by.pop(key, None)
        else:
            self.aset.made_by[key] = made_by

    def _add_timing(self, timing: Any) -> None:
        if not timing or not self.config.record_timing:
            return
        if not isinstance(timing, dict):
            raise InputError(None, "timing", "expected {frame index: seconds}")
        spent = self.aset.info.setdefault("annotation_seconds", {})
        for key, seconds in timing.items():
            if not isinstance(key, str) or not re.fullmatch(r"[0-9]{1,9}", key):  # ASCII: int() takes '١'
                raise InputError(None, "timing", f"bad frame index {str(key)[:40]!r}")
            frame = self.frame(int(key))
            if not isinstance(seconds, (int, float)) or isinstance(seconds, bool) or not 0 <= seconds < 86400:
                raise InputError(None, f"timing.{key}", f"expected seconds in [0, 86400), got {seconds!r}")
            spent[frame.name] = round(float(spent.get(frame.name, 0.0)) + float(seconds), 2)

    def add_query(self, revision: Any, text: Any, kind: Any = "agnostic", base: Any = None,
                  level: Any = None) -> tuple[int, int]:
        """Add a query; returns (new query id, new revision)."""
        if not isinstance(text, str) or not text.strip():
            raise InputError(None, "text", "the query text must be a non-empty string")
        text = check_text(text.strip(), None, "text")
        if kind not in ("agnostic", "sensitive"):
            raise InputError(None, "kind", "expected 'agnostic' or 'sensitive'")
        if level is not None:
            level = check_text(level, None, "level", max_chars=100)
        with self._lock:
            self._check_revision(revision)
            same = next((q for q in self.aset.queries if text_key(q.text) == text_key(text)), None)
            if same is not None:  # "Ball" beside "ball" would read as one query in predictions (by slug)
                raise InputError(None, "text", f"a query {same.text!r} exists already (texts are compared up to "
                                               "case, spaces and Unicode form)")
            if kind == "sensitive":
                b = self.query(base)
                if b.kind != "agnostic":
                    raise InputError(None, "base", f"the base {b.text!r} must be a time-agnostic query")
                base = b.id
            else:
                base = None
            qid = max((q.id for q in self.aset.queries), default=0) + 1
            # a scripted session's queries are a program's guesses: drafts until a person reviews them
            review = "draft" if self.config.annotator == "scripted" else None
            self.aset.queries.append(Query(id=qid, text=text, kind=kind, base=base, level=level or None, review=review))
            try:
                return qid, self._commit()
            except BaseException:
                self.aset.queries.pop()
                raise

    def delete_query(self, revision: Any, qid: Any) -> int:
        """Delete a query and its masks (refused while a time-sensitive query uses it as base)."""
        with self._lock:
            self._check_revision(revision)
            q = self.query(qid)
            users = [s.text for s in self.aset.sensitive_queries if s.base == q.id]
            if users:
                raise InputError(None, "query", f"{q.text!r} is the base of {users}; delete those first")
            backup = (list(self.aset.queries), dict(self.aset.masks), dict(self.aset.made_by))
            self.aset.queries = [x for x in self.aset.queries if x.id != q.id]
            self.aset.masks = {k: v for k, v in self.aset.masks.items() if k[0] != q.id}
            self.aset.made_by = {k: v for k, v in self.aset.made_by.items() if k[0] != q.id}
            try:
                return self._commit()
            except BaseException:
                self.aset.queries, self.aset.masks, self.aset.made_by = backup
                raise

    def mark_reviewed(self, revision: Any, qid: Any) -> int:
        """Clear the draft mark of a query (its masks and intervals have been checked); returns the
        new revision (the current one when the query was not a draft: nothing is written)."""
        with self._lock:
            self._check_revision(revision)
            q = self.query(qid)
            before = q.review
            if before is None:
                return self.revision
            q.review = None
            try:
                return self._commit()
            except BaseException:
                q.review = before
                raise

    # -- assistance -----------------------------------------------------------------------------
    def segment(self, index: Any, box: Any, clicks: Any, current: Any) -> dict:
        """Assisted segmentation on frame ``index``; returns the mask in the page's format."""
        frame = self.frame(index)
        h, w = frame.camera.height, frame.camera.width
        if box is not None and (not isinstance(box, list) or len(box) != 4 or not all(_coordinate(v) for v in box)):
            raise InputError(None, "box", f"expected [x0, y0, x1, y1] of finite numbers within +-{MAX_COORDINATE:g} "
                                          "or null")
        if not isinstance(clicks, list):
            raise InputError(None, "clicks", "expected a list of [x, y, label]")
        if len(clicks) > MAX_CLICKS:
            raise InputError(None, "clicks", f"{len(clicks)} clicks; at most {MAX_CLICKS}")
        parsed = []
        for n, c in enumerate(clicks):
            if (not isinstance(c, list) or len(c) != 3 or isinstance(c[2], float) or c[2] not in (0, 1)
                    or not all(_coordinate(v) for v in c[:2])):
                raise InputError(None, f"clicks[{n}]", "expected [x, y, 1 (object) | 0 (not object)]")
            parsed.append((float(c[0]), float(c[1]), int(c[2])))
        cur = None
        if current is not None:
            if not isinstance(current, dict):
                raise InputError(None, "current", "expected a mask object or null")
            check_keys(current, MASK_KEYS, None, "current", allow_unknown=False)
            cur = runs_to_mask(current.get("counts"), h, w, "current")
        t0 = time.perf_counter()
        mask = self.segmenter.segment(frame.name, self.image(index), None if box is None else tuple(box), parsed, cur)
        return {"size": [h, w], "counts": mask_to_runs(mask), "seconds": round(time.perf_counter() - t0, 4),
                "segmenter": self.segmenter.name}

    def _neighbour(self, index: int, step: int) -> Optional[int]:
        """Next frame being annotated (the session's frames, whatever their split) in direction
        ``step`` from the same camera."""
        f = self.frames[index]
        j = index + step
        while 0 <= j < len(self.frames):
            g = self.frames[j]
            if g.camera_id == f.camera_id:
                return j
            j += step
        return None

    def propagate(self, qid: Any, index: Any, direction: Any, count: Any) -> dict:
        """Proposals for up to ``count`` frames after (``direction`` = 1) or before (-1) ``index``.

        The walk stops at the first frame already annotated for the query; if that keyframe has a
        mask, the frames in between are filled from both ends and blended.
        """
        self.frame(index)
        owner = self.owner(qid)
        if not isinstance(direction, int) or isinstance(direction, bool) or direction not in (1, -1):
            raise InputError(None, "direction", "expected 1 (forward) or -1 (backward)")
        if not isinstance(count, int) or isinstance(count, bool) or count < 1:
            raise InputError(None, "count", "expected a positive integer")
        count = min(count, self.config.max_propagation_frames)
        start = self.mask(owner.id, index)
        if start is None:
            raise InputError(None, "frame", f"frame {index} has no mask of {owner.text!r} to propagate from")
        chain = [index]
        keyframe_mask = None
        while len(chain) <= count:
            nxt = self._neighbour(chain[-1], direction)
            if nxt is None:
                break
            existing = self.mask(owner.id, nxt)
            if existing is not None:
                if existing.any():
                    chain.append(nxt)
                    keyframe_mask = existing
                break
            chain.append(nxt)
        t0 = time.perf_counter()
        images = lambda k: self.image(chain[k])  # noqa: E731 - lazy loading by chain position
        if keyframe_mask is not None and len(chain) > 2:
            masks = propagate_between(images, len(chain) - 1, start, keyframe_mask, self.config.propagation)
            methods = ["between"] * len(masks)
            targets = chain[1:-1]
        else:
            steps = propagate_chain(images, len(chain) - 1 - (1 if keyframe_mask is not None else 0), start,
                                    self.config.propagation)
            masks = [s.mask for s in steps]
            methods = [s.method for s in steps]
            targets = chain[1:1 + len(steps)]
        seconds = time.perf_counter() - t0
        return {"query": owner.id, "from": index, "direction": direction, "seconds": round(seconds, 4),
                "proposals": [{"frame": t, "method": m, "size": list(mk.shape), "counts": mask_to_runs(mk)}
                              for t, m, mk in zip(targets, methods, masks)]}

    def review(self) -> list[dict]:
        with self._lock:
            return review(self.aset, [(i, f.name, f.time_index, f.split) for i, f in enumerate(self.frames)],
                          self.config.review)

    # -- import / export ------------------------------------------------------------------------
    def export(self, fmt: Any) -> dict:
        """Write an export under ``<root>/exports/``; each file is reloaded and checked first."""
        from .exchange import export_set

        if fmt not in EXPORT_FORMATS:
            raise InputError(None, "format", f"unknown export format {fmt!r} ({', '.join(EXPORT_FORMATS)})")
        with self._lock:
            snapshot = copy.deepcopy(self.aset)
        written = export_set(snapshot, fmt, self.root / "exports", self.path.stem, self.scene)
        return {"format": fmt, "files": [str(p.relative_to(self.root)) for p in written]}

    def import_data(self, revision: Any, fmt: Any, filename: Any, data_b64: Any) -> dict:
        """Replace the working set by an imported one (the current file is backed up first)."""
        from benchmark.core.strict import error_reason, unpacking_errors

        from .exchange import import_set

        if fmt not in IMPORT_FORMATS:
            raise InputError(None, "format", f"unknown import format {fmt!r} ({', '.join(IMPORT_FORMATS)})")
        if not isinstance(filename, str) or not isinstance(data_b64, str):
            raise InputError(None, "data", "expected a file name and base64 data")
        filename = check_text(Path(filename).name or filename, None, "filename", max_chars=255)  # kept in info
        if len(data_b64) > self.config.max_import_bytes * 4 // 3 + 8:
            raise InputError(None, "data", f"import larger than {self.config.max_import_bytes} bytes")
        try:
            data = base64.b64decode(data_b64, validate=True)
        except (ValueError, TypeError):
            raise InputError(None, "data", "not valid base64") from None
        with self._lock:
            self._check_revision(revision)
            current = copy.deepcopy(self.aset)
            try:
                new = import_set(fmt, Path(filename).name, data, self.scene, current, self.config)
                validate_against_scene(new, self.scene, file=filename)
            except InputError:
                raise
            except (ValueError, TypeError, KeyError, IndexError, AttributeError, ArithmeticError,
                    *unpacking_errors()) as err:
                # the upload is untrusted data: whatever its parsers trip over is a malformed file, and
                # nothing has changed yet (RuntimeError, among the unpacking errors, covers RecursionError)
                raise InputError(Path(filename).name, None, f"cannot read the file: {error_reason(err)}") from None
            backup = None
            if self.path.exists():
                backup = self.root / ".bench4d-backups" / f"{self.path.stem}.rev{self.revision}.json"
                save_annotations(current, backup, overwrite=True)
            new.info = {**{k: v for k, v in current.info.items() if k in ("annotation_seconds",)}, **new.info}
            new.info.setdefault("imported", []).append({"format": fmt, "file": Path(filename).name, "at": _now()})
            old = self.aset
            self.aset = new
            try:
                rev = self._commit()
            except BaseException:
                self.aset = old
                raise
        return {"revision": rev, "backup": None if backup is None else str(backup.relative_to(self.root)),
                "queries": len(new.queries), "masks": len(new.masks)}


_MKSTEMP = r"[a-z0-9_]{8}"  # the random part of tempfile.mkstemp / mkdtemp names


def remove_interrupted_writes(path: Path) -> list[str]:
    """Delete what a killed writer of annotation file ``path`` left behind; returns the names.

    Every write goes through :func:`benchmark.core.atomic.atomic_path` (a ``.<name>.<random>.tmp`` file
    beside the target, renamed over it when complete): a process killed before the rename leaves
    that file, never a damaged target. The caller must hold the file's lock, so no live writer owns
    one of these. Patterns are exact, so another annotation file's temporaries are left alone.
    """
    name, stem, root = re.escape(path.name), re.escape(path.stem), path.parent
    places = [
        (root, rf"\.{name}\.{_MKSTEMP}\.tmp"),
        (root / ".bench4d-backups", rf"\.{stem}\.rev[0-9]+\.json\.{_MKSTEMP}\.tmp"),
        (root / "exports", rf"\.?\.{stem}\.(?:json|coco-rle\.json)\.{_MKSTEMP}\.tmp(?:\.{_MKSTEMP}\.tmp)?"),
        (root / "exports", rf"\.{stem}\.release\.{_MKSTEMP}"),  # a release export's staging folder
    ]
    removed = []
    for folder, pattern in places:
        if not folder.is_dir():
            continue
        for p in folder.iterdir():
            if not re.fullmatch(pattern, p.name):
                continue
            try:
                if p.is_dir() and not p.is_symlink():
                    shutil.rmtree(p)
                else:
                    p.unlink()
                removed.append(str(p.relative_to(root)))
            except OSError:  # not ours to fight over: a later start tries again
                pass
    return removed


def _rle_nonempty(rle: dict) -> bool:
    from ..format import rle_area

    return rle_area(rle) > 0


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def check_archive(data: bytes, config: SessionConfig, file: str) -> zipfile.ZipFile:
    """Open an uploaded zip after checking every member name and the unpacked size."""
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except zipfile.BadZipFile:
        raise InputError(file, None, "not a zip archive") from None
    members = zf.infolist()
    if len(members) > config.max_archive_members:
        raise InputError(file, None, f"{len(members)} entries; at most {config.max_archive_members} allowed")
    total = 0
    for m in members:
        name = m.filename
        parts = Path(name.replace("\\", "/")).parts
        if name.startswith(("/", "\\")) or ".." in parts or (parts and ":" in parts[0]):
            raise InputError(file, name, "archive entry escapes the archive (absolute path or '..')")
        if (m.external_attr >> 16) & 0o170000 == 0o120000:
            raise InputError(file, name, "archive entry is a symbolic link")
        if name.endswith(".json"):
            total += m.file_size
    if total > config.max_unpacked_bytes:
        raise InputError(file, None, f"JSON members unpack to {total} bytes; at most {config.max_unpacked_bytes}")
    return zf
