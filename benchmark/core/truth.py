"""Exact per-frame ground truth of a generated scene, and the guarded accessor methods may use.

Files (``<scene>/truth/``)::

    scene_truth.json           preset, seed, generator version, layout, frames (name, split, time,
                               camera), object catalogue per level, semantic state timelines
    levels/<frame name>.npz    subpart, part, whole: (H, W) uint16 ids (0 = background / none);
                               depth: (H, W) float32 camera-space z (inf where no surface)

Fairness guard
--------------
Methods on the *oracle* supervision track may use the truth of **training frames only**.
:meth:`SceneTruth.levels`, :meth:`SceneTruth.depth`, :meth:`SceneTruth.mask` and the state
look-ups raise :class:`TruthAccessError` for a frame (or time index) that no training frame covers,
unless ``allow_eval=True`` - which only the harness (scoring, annotation building, visualisation)
passes. Reading the files directly bypasses the guard; methods must not.

Damaged files (truncated, flipped bytes, keys missing) are an :class:`~benchmark.core.errors.InputError`
naming the file and the field, never a traceback from ``zipfile`` or a ``KeyError``;
:func:`check_truth` reads everything once, so a cache can tell a damaged scene from a sound one
(the runner regenerates a damaged preset).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Optional, Protocol, Union

import numpy as np

from .atomic import read_json, write_json
from .errors import InputError
from .strict import MAX_ARRAY_FILE_BYTES, error_reason, load_npz
from .scene import Camera, Frame

Level = Literal["whole", "part", "subpart"]
LEVELS: tuple[Level, ...] = ("subpart", "part", "whole")
"""Segmentation levels, finest first (the order of every id stack)."""


class Catalogue(Protocol):
    """What :func:`write_truth` reads of the generator's object catalogue."""

    def timelines(self) -> list[tuple[Any, Any]]: ...

    def to_dict(self) -> dict: ...

TRUTH_DIR = "truth"
TRUTH_FILE = "scene_truth.json"
LEVELS_DIR = "levels"
FORMAT = "bench4d-synthetic-truth"
FORMAT_VERSION = 1
FRAME_KEYS = ("name", "split", "time_index", "time", "camera_id", "camera", "image")
"""Keys of every entry of ``frames`` in ``scene_truth.json``."""
ARRAYS = (*LEVELS, "depth")
"""Arrays of every ``levels/<frame>.npz``."""
TRUTH_BYTES_PER_PIXEL = 64
"""Bytes a pixel a frame's truth file may declare (its id maps and depth take about 10): a header claiming
more is refused before anything is allocated."""


class TruthAccessError(PermissionError):
    """Ground truth of an evaluated frame was requested without ``allow_eval=True``."""


@dataclass(frozen=True)
class TruthFrame:
    """One rendered frame as the truth records it."""

    name: str
    split: str
    time_index: int
    time: float
    camera_id: str
    camera: Camera
    """Camera at the resolution of the truth maps."""
    image_file: str


def save_levels(truth_dir: Path, name: str, ids: np.ndarray, depth: np.ndarray) -> None:
    """Write one frame's (3, H, W) uint16 ids (finest first) and (H, W) float32 depth."""
    path = Path(truth_dir) / LEVELS_DIR / f"{name}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:  # inside the generator's staging folder: published atomically
        np.savez_compressed(fh, **{lv: ids[k].astype(np.uint16) for k, lv in enumerate(LEVELS)},
                            depth=depth.astype(np.float32))


def write_truth(truth_dir: Path, *, frames: list[TruthFrame], catalogue: Catalogue, info: dict) -> None:
    """Write ``scene_truth.json`` (``info`` carries preset, seed, version, layout, num_frames ...)."""
    states = []
    for entry, timeline in catalogue.timelines():
        states.append({"object": entry.name, "level": entry.level, "id": entry.id, "states": timeline.to_dict()})
    doc = {
        "format": FORMAT, "version": FORMAT_VERSION, **info,
        "levels_order": list(LEVELS),
        "depth": "camera-space z (OpenCV, along the optical axis) in scene units; inf = no surface",
        "frames": [{"name": f.name, "split": f.split, "time_index": f.time_index, "time": f.time,
                    "camera_id": f.camera_id, "image": f.image_file, "camera": f.camera.to_dict()}
                   for f in frames],
        "catalogue": catalogue.to_dict(),
        "states": states,
    }
    write_json(Path(truth_dir) / TRUTH_FILE, doc)


FrameKey = Union[str, Frame]


class SceneTruth:
    """Read access to a generated scene's truth, with the training-frames-only guard."""

    def __init__(self, truth_dir: Path, doc: dict):
        self.root = Path(truth_dir)
        file = self.root / TRUTH_FILE
        _check_doc(doc, file)
        self.doc = doc
        self.preset: str = doc["preset"]
        self.seed: int = doc["seed"]
        self.layout: str = doc["layout"]
        self.num_frames: int = doc["num_frames"]
        self.generator_version: str = doc["generator_version"]
        self.frames: dict[str, TruthFrame] = {}
        for i, f in enumerate(doc["frames"]):
            try:
                camera = Camera.from_dict(f["camera"])
            except (KeyError, TypeError, ValueError) as err:
                raise InputError(file, f"frames[{i}].camera", f"not a camera ({error_reason(err, 160)})") from None
            self.frames[f["name"]] = TruthFrame(f["name"], f["split"], f["time_index"], f["time"], str(f["camera_id"]),
                                                camera, f["image"])
        self._by_cam_time = {(f.camera_id, f.time_index): f.name for f in self.frames.values()}
        self._train_times = {f.time_index for f in self.frames.values() if f.split == "train"}
        try:
            self.catalogue: dict[str, dict[int, dict]] = {
                lv: {int(k): v for k, v in doc["catalogue"][lv].items()} for lv in LEVELS}
        except (TypeError, ValueError, AttributeError) as err:
            raise InputError(file, "catalogue", f"expected {{level: {{id: entry}}}} ({error_reason(err, 160)})") from None

    # -- frames -----------------------------------------------------------------------------------
    def frame_name(self, frame: FrameKey) -> str:
        """Resolve a frame name or a :class:`Frame` (matched by camera and time index) to a name."""
        if isinstance(frame, Frame):
            if frame.name in self.frames:
                return frame.name
            key = (str(frame.camera_id), frame.time_index)
            if key in self._by_cam_time:
                return self._by_cam_time[key]
            raise KeyError(f"no truth for frame {frame.name!r} (camera {frame.camera_id}, t={frame.time_index})")
        if frame not in self.frames:
            raise KeyError(f"scene {self.preset!r} has no frame {frame!r}")
        return frame

    @property
    def training_frames(self) -> list[str]:
        return [n for n, f in self.frames.items() if f.split == "train"]

    @property
    def evaluated_frames(self) -> list[str]:
        return [n for n, f in self.frames.items() if f.split == "test"]

    def _guard_frame(self, name: str, allow_eval: bool) -> None:
        if not allow_eval and self.frames[name].split != "train":
            raise TruthAccessError(f"frame {name!r} is a {self.frames[name].split} frame: its ground truth is for "
                                   f"scoring only (pass allow_eval=True from harness code, never from a method)")

    def _guard_time(self, time_index: int, allow_eval: bool) -> None:
        if not allow_eval and time_index not in self._train_times:
            raise TruthAccessError(f"time index {time_index} is seen by no training frame: its state is for "
                                   f"scoring only (allow_eval=True from harness code)")

    # -- per-pixel truth --------------------------------------------------------------------------
    def _load(self, name: str) -> dict[str, np.ndarray]:
        path = self.root / LEVELS_DIR / f"{name}.npz"
        if not path.is_file():
            raise InputError(path, None, "truth file of this frame not found")
        camera = self.frames[name].camera if name in self.frames else None
        # what each header declares, before anything is allocated: a frame's maps need some bytes a pixel
        budget = (MAX_ARRAY_FILE_BYTES if camera is None
                  else TRUTH_BYTES_PER_PIXEL * camera.width * camera.height + (1 << 20))
        try:
            arrays = load_npz(path, max_bytes=budget)
        except InputError as err:
            raise InputError(path, err.field, f"damaged truth file ({err.message}); regenerate the scene") from None
        for key in ARRAYS:
            if key not in arrays:
                raise InputError(path, key, "missing array; regenerate the scene")
            if arrays[key].ndim != 2:
                raise InputError(path, key, f"expected an (H, W) map, got shape {arrays[key].shape}")
        for key in ARRAYS:
            if camera is not None and arrays[key].shape != (camera.height, camera.width):
                raise InputError(path, key, f"map is {arrays[key].shape[0]}x{arrays[key].shape[1]}, the frame is "
                                            f"{camera.height}x{camera.width}; regenerate the scene")
        return arrays

    def levels(self, frame: FrameKey, *, allow_eval: bool = False) -> dict[Level, np.ndarray]:
        """Level name -> (H, W) uint16 id map of ``frame``."""
        name = self.frame_name(frame)
        self._guard_frame(name, allow_eval)
        data = self._load(name)
        return {lv: data[lv] for lv in LEVELS}

    def id_maps(self, frame: FrameKey, *, allow_eval: bool = False) -> np.ndarray:
        """(3, H, W) uint16 ids, finest level first (subpart, part, whole)."""
        lv = self.levels(frame, allow_eval=allow_eval)
        return np.stack([lv[k] for k in LEVELS])

    def depth(self, frame: FrameKey, *, allow_eval: bool = False) -> np.ndarray:
        """(H, W) float32 camera-space depth (inf where nothing is hit)."""
        name = self.frame_name(frame)
        self._guard_frame(name, allow_eval)
        return self._load(name)["depth"]

    def mask(self, text: str, frame: FrameKey, *, allow_eval: bool = False) -> np.ndarray:
        """(H, W) bool pixels of every node declared with name ``text``."""
        level, ids = self.ids_named(text)
        return np.isin(self.levels(frame, allow_eval=allow_eval)[level], ids)

    # -- catalogue ----------------------------------------------------------------------------------
    def names(self, level: Level) -> dict[int, str]:
        """Id -> name at ``level`` (0, background, is not listed)."""
        return {i: e["name"] for i, e in self.catalogue[level].items()}

    def name(self, level: Level, id_: int) -> Optional[str]:
        """Name of ``id_`` at ``level``; ``None`` for 0 (background)."""
        return None if id_ == 0 else self.catalogue[level][int(id_)]["name"]

    def synonyms(self, level: Level, id_: int) -> list[str]:
        return list(self.catalogue[level][int(id_)]["synonyms"])

    def ids_named(self, text: str) -> tuple[Level, list[int]]:
        """(level where ``text`` is declared, its ids there)."""
        for level in ("whole", "part", "subpart"):
            ids = [i for i, e in self.catalogue[level].items() if e["name"] == text and not e["implicit"]]
            if ids:
                return level, ids  # type: ignore[return-value]
        raise KeyError(f"no object or part named {text!r} in {self.preset!r}")

    def query_names(self) -> list[str]:
        """Every declared name (whole, part and subpart nouns), whole level first."""
        seen: dict[str, None] = {}
        for level in ("whole", "part", "subpart"):
            for e in self.catalogue[level].values():
                if not e["implicit"]:
                    seen.setdefault(e["name"], None)
        return list(seen)

    # -- semantic states ----------------------------------------------------------------------------
    @property
    def stateful_objects(self) -> list[str]:
        """Names of the objects/parts that have a state timeline."""
        return [s["object"] for s in self.doc["states"]]

    def state_at(self, obj: str, time_index: int, *, allow_eval: bool = False) -> dict:
        """``{"state", "phrase", "captions"}`` of ``obj`` at ``time_index``."""
        self._guard_time(time_index, allow_eval)
        for s in self.doc["states"]:
            if s["object"] == obj:
                for st in s["states"]:
                    if any(a <= time_index <= b for a, b in st["intervals"]):
                        return {"state": st["state"], "phrase": st["phrase"], "captions": list(st["captions"])}
                raise KeyError(f"{obj!r} has no state at time index {time_index}")
        raise KeyError(f"{obj!r} has no state timeline")

    def timelines(self, *, allow_eval: bool = False) -> list[dict]:
        """The full state timelines (they reveal evaluated times, hence the guard)."""
        if not allow_eval:
            raise TruthAccessError("full state timelines are for scoring only (allow_eval=True from harness code); "
                                   "methods use state_at() on training time indices")
        return self.doc["states"]


def has_truth(path: Optional[str | Path]) -> bool:
    """Whether ``path`` (a scene folder or its ``truth/``; None for an in-memory scene) holds a
    generated scene's truth file."""
    if path is None:
        return False
    root = Path(path)
    return (root / TRUTH_DIR / TRUTH_FILE).is_file() or (root / TRUTH_FILE).is_file()


def load_truth(path: str | Path) -> SceneTruth:
    """Open the truth of a generated scene (``path`` = the scene folder or its ``truth/``). A malformed
    ``scene_truth.json`` is an :class:`InputError` naming its field; the per-frame maps are read (and
    checked) when asked for, or all at once by :func:`check_truth`."""
    root = Path(path)
    truth_dir = root if (root / TRUTH_FILE).is_file() else root / TRUTH_DIR
    file = truth_dir / TRUTH_FILE
    doc = read_json(file)
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(file, "format", f"not a bench4d synthetic truth file (expected format {FORMAT!r})")
    if doc.get("version") != FORMAT_VERSION:
        raise InputError(file, "version", f"unsupported version {doc.get('version')!r} (expected {FORMAT_VERSION})")
    return SceneTruth(truth_dir, doc)


def check_truth(path: str | Path) -> SceneTruth:
    """:func:`load_truth` and every frame's maps read once: an :class:`InputError` naming the first damaged
    file and field, else the truth. What a cache of generated scenes runs before trusting one."""
    truth = load_truth(path)
    for name in truth.frames:
        truth._load(name)
    return truth


def _check_doc(doc: dict, file: Path) -> None:
    """The structure :class:`SceneTruth` reads, field by field (a missing key or a wrong type is an
    :class:`InputError` naming it, not a ``KeyError`` deep inside)."""
    if not isinstance(doc, dict):
        raise InputError(file, None, f"expected a JSON object, got {type(doc).__name__}")
    for key in ("preset", "seed", "layout", "num_frames", "generator_version", "frames", "catalogue", "states"):
        if key not in doc:
            raise InputError(file, key, "missing required key")
    for key, kind in (("preset", str), ("layout", str), ("seed", int), ("num_frames", int), ("frames", list),
                      ("catalogue", dict), ("states", list)):
        if not isinstance(doc[key], kind) or isinstance(doc[key], bool):
            raise InputError(file, key, f"expected {kind.__name__}, got {type(doc[key]).__name__}")
    for i, frame in enumerate(doc["frames"]):
        if not isinstance(frame, dict):
            raise InputError(file, f"frames[{i}]", f"expected an object, got {type(frame).__name__}")
        for key in FRAME_KEYS:
            if key not in frame:
                raise InputError(file, f"frames[{i}].{key}", "missing required key")
        if not isinstance(frame["name"], str) or not isinstance(frame["split"], str):
            raise InputError(file, f"frames[{i}]", "name and split must be strings")
        if not isinstance(frame["time_index"], int) or isinstance(frame["time_index"], bool):
            raise InputError(file, f"frames[{i}].time_index", f"expected an integer, got {frame['time_index']!r}")
    for level in LEVELS:
        entries = doc["catalogue"].get(level)
        if not isinstance(entries, dict):
            raise InputError(file, f"catalogue.{level}", "missing or not an object {id: entry}")
        for k, entry in entries.items():
            if not isinstance(entry, dict) or not all(key in entry for key in ("name", "implicit")):
                raise InputError(file, f"catalogue.{level}[{k!r}]", "expected an object with name and implicit")
    for i, state in enumerate(doc["states"]):
        if not isinstance(state, dict) or "object" not in state or not isinstance(state.get("states"), list):
            raise InputError(file, f"states[{i}]", "expected an object with 'object' and a 'states' list")
