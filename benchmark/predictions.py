"""Prediction files: what any method (ours, or another release's outputs converted) hands to scoring.

One folder per (method, scene). Two layouts, read by :func:`read_predictions`:

**JSON layout** (default; what :func:`write_predictions` writes)::

    DIR/predictions.json       # or DIR/predictions.json.gz, the same JSON gzip-compressed (what a run writes)
    {
      "format": "bench4d-predictions", "version": 1,
      "scene": "split-cookie",            # optional; checked against the GT scene when given
      "method": "4dlangsplat",            # optional, informational
      "info": {...},                      # optional, free provenance
      "queries": {
        "<query text>": {
          "kind": "agnostic" | "sensitive",             # optional; checked against the GT when given
          "masks": {"<frame name>": <COCO RLE>, ...},    # required for every evaluated frame
          "scores": {"<frame name>": float | null, ...}, # sensitive: s_t (null = undefined)
          "decisions": {"<frame name>": bool, ...}       # sensitive, optional: used only without scores
        }
      }
    }

COCO RLE is ``{"size": [H, W], "counts": "<compressed string>"}`` (or uncompressed list counts),
as :func:`benchmark.core.annotation.encode_mask` writes. Frame names are
:attr:`benchmark.core.annotation.AnnotatedFrame.name`.

**PNG layout** (easy to produce from any code)::

    DIR/masks/<query slug>/<frame name>.png   # single channel, nonzero = positive (see below)
    DIR/scores.json                            # optional for time-agnostic-only predictions
    {
      "format": "bench4d-predictions", "version": 1, "scene": ..., "method": ..., "masks": "png",
      "queries": {"<query text>": {"kind": ..., "slug": "<folder name>", "frames": [...],
                                   "scores": {...}, "decisions": {...}}}
    }

``slug`` defaults to :func:`query_slug` of the text (lower case, runs of non-word characters ->
``-``); ``frames`` (optional) lists the PNGs to read, otherwise every PNG in the folder is read.
A ``masks/<folder>`` not listed in ``scores.json`` is matched to the GT query whose slug it is.

Mask PNGs must be PNG files (checked by signature) of the frame's size (checked from the header
before decoding). Single-channel: non-zero = positive; colour: positive where **any** channel is
non-zero; with alpha: transparent pixels are negative, and an image that is black everywhere with
varying alpha is an alpha-only mask (:mod:`benchmark.core.imageio` states the rule in full).

Numbers: a score is a finite number with ``|s| <= 1e30`` (:data:`SCORE_LIMIT`; larger values
would overflow the mean the temporal rule takes) or ``null``. RLE is checked run by run before
anything is decoded (:func:`benchmark.core.annotation.rle_runs`), and a mask's declared size is checked
against the frame's before decoding when the frame is known (:meth:`QueryPrediction.mask`).

A time-sensitive query needs a mask (its spatial answer, scored against the base object's GT mask
for vIoU) and a score or decision on every evaluated frame. When scores are given the harness's
temporal rule decides; ``decisions`` are used only when ``scores`` are absent (methods that only
give yes/no).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import numpy as np

from benchmark.core.annotation import check_mask_size, check_rle, decode_mask, encode_mask

from benchmark.core.atomic import read_json, write_json
from benchmark.core.errors import InputError, short_repr
from benchmark.core.strict import check_keys, text_key
from benchmark.core.imageio import read_mask, write_image

FORMAT = "bench4d-predictions"
VERSION = 1
JSON_FILE = "predictions.json"
JSON_GZ_FILE = JSON_FILE + ".gz"
SCORES_FILE = "scores.json"
MASKS_DIR = "masks"
KINDS = ("agnostic", "sensitive")
TOP_KEYS = ("format", "version", "scene", "method", "info", "queries", "masks")
ENTRY_KEYS = ("kind", "masks", "scores", "decisions", "slug", "frames")
"""The keys of the document and of a query's entry: a key that varies one of them (``Masks``, ``masks ``) is
refused (:func:`benchmark.core.strict.check_keys`), never silently ignored."""
SCORE_LIMIT = 1e30
"""Largest ``|score|`` accepted: a mean of any number of such scores stays finite in float64."""

MaskSource = Union[np.ndarray, dict, Path]
"""A mask as held in memory: (H, W) bool array, COCO RLE dict, or a PNG path (read lazily)."""


def query_slug(text: str) -> str:
    """Folder-safe name of a query: ``"Cracked cookie!"`` -> ``"cracked-cookie"``."""
    slug = re.sub(r"[\W_]+", "-", text.strip().lower()).strip("-")
    return slug or "query"


def field_name(query: str, part: Optional[str] = None, frame: Optional[str] = None) -> str:
    """The field path used in error messages: ``queries['cup'].masks['000012']``."""
    name = f"queries[{query!r}]"
    if part:
        name += f".{part}"
    if frame is not None:
        name += f"[{frame!r}]"
    return name


@dataclass
class QueryPrediction:
    """A method's answer to one query on one scene."""

    text: str
    """Query text (or, for a PNG folder not listed in scores.json, its slug)."""
    kind: Optional[str] = None
    """``"agnostic"``, ``"sensitive"``, or ``None`` (take the GT's)."""
    masks: dict[str, MaskSource] = field(default_factory=dict)
    """Frame name -> (H, W) bool mask / COCO RLE / PNG path."""
    scores: dict[str, float] = field(default_factory=dict)
    """Sensitive: frame name -> raw score ``s_t`` (NaN = undefined)."""
    decisions: dict[str, bool] = field(default_factory=dict)
    """Sensitive, optional: frame name -> yes/no, used only when ``scores`` is empty."""
    source: Optional[Path] = None
    """File it was read from, for error messages (``None`` when built in memory)."""

    def mask(self, frame: str, size: Optional[tuple[int, int]] = None) -> np.ndarray:
        """The (H, W) bool mask of ``frame``; malformed data raises :class:`InputError`.

        ``size`` = the frame's ``(height, width)``: an RLE or PNG declaring another size is refused
        before it is decoded (without it, only :data:`benchmark.core.annotation.MAX_MASK_PIXELS` bounds it).
        """
        where = field_name(self.text, "masks", frame)
        if frame not in self.masks:
            raise InputError(self.source, where, "missing mask for this evaluated frame")
        value = self.masks[frame]
        if isinstance(value, Path):
            return read_mask(value, size) > 0
        if isinstance(value, dict):
            return decode_mask(value, self.source, where, size)  # checks every run before decoding
        arr = np.asarray(value)
        if arr.ndim != 2:
            raise InputError(self.source, where, f"mask must be 2-D (H, W), got shape {arr.shape}")
        if size is not None and arr.shape != tuple(size):
            raise InputError(self.source, where, f"mask is {arr.shape[0]}x{arr.shape[1]}, the frame is "
                                                 f"{size[0]}x{size[1]} (H x W)")
        return arr.astype(bool, copy=False)


@dataclass
class ScenePredictions:
    """All of a method's answers on one scene."""

    scene: Optional[str] = None
    method: Optional[str] = None
    queries: dict[str, QueryPrediction] = field(default_factory=dict)
    """Query text -> prediction."""
    info: dict = field(default_factory=dict)
    """Free provenance (method config, timings)."""
    source: Optional[Path] = None
    """File or folder it was read from (``None`` when built in memory)."""

    def add(self, prediction: QueryPrediction) -> None:
        self.queries[prediction.text] = prediction

    def find(self, text: str, *, by_slug: bool = True) -> Optional[QueryPrediction]:
        """The prediction for query ``text``: exact text first, then (if ``by_slug``) the one
        prediction whose :func:`query_slug` equals the text's (PNG folders named by slug)."""
        if text in self.queries:
            return self.queries[text]
        if not by_slug:
            return None
        slug = query_slug(text)
        matches = [p for k, p in self.queries.items() if query_slug(k) == slug]
        return matches[0] if len(matches) == 1 else None


# -- writing ---------------------------------------------------------------------------------------
def _score_json(value: float, text: str = "", frame: Optional[str] = None) -> Optional[float]:
    v = float(value)
    if math.isnan(v):
        return None
    if not abs(v) <= SCORE_LIMIT:
        raise InputError(None, field_name(text, "scores", frame),
                         f"{v!r} is not a finite number with |s| <= {SCORE_LIMIT:g}")
    return v


def _rle_of(pred: QueryPrediction, frame: str) -> dict:
    value = pred.masks[frame]
    if isinstance(value, dict):  # written only when it would read back
        return check_rle(value, pred.source, field_name(pred.text, "masks", frame))
    return encode_mask(pred.mask(frame))


def _header(preds: ScenePredictions) -> dict:
    return {"format": FORMAT, "version": VERSION, "scene": preds.scene, "method": preds.method,
            "info": preds.info}


def write_predictions(directory: str | Path, predictions: ScenePredictions, *, layout: str = "json",
                      overwrite: bool = False, compress: bool = False) -> Path:
    """Write ``predictions`` into ``directory`` (atomically, file by file); return the main file.

    ``layout="json"`` writes ``predictions.json`` (``predictions.json.gz`` with ``compress``: a third of
    the size); ``layout="png"`` writes ``masks/<slug>/<frame>.png`` and ``scores.json``. An existing main
    file is an error unless ``overwrite``, which also removes the other JSON file, so that the folder
    holds one.
    """
    directory = Path(directory)
    if layout not in ("json", "png"):
        raise ValueError(f"layout must be 'json' or 'png', got {layout!r}")
    if compress and layout != "json":
        raise ValueError("compress applies to layout='json' only")
    main = directory / (SCORES_FILE if layout == "png" else JSON_GZ_FILE if compress else JSON_FILE)
    other = directory / (JSON_FILE if compress else JSON_GZ_FILE) if layout == "json" else None
    for existing in (main, other):
        if existing is not None and existing.exists() and not overwrite:
            raise InputError(existing, None, "already exists (pass overwrite=True to replace it)")
    for text, pred in predictions.queries.items():
        if pred.kind is not None and pred.kind not in KINDS:
            raise InputError(None, field_name(text, "kind"), f"must be one of {KINDS}, got {pred.kind!r}")
    doc = _header(predictions)
    queries: dict[str, dict] = {}
    if layout == "json":
        for text, pred in predictions.queries.items():
            entry: dict = {"kind": pred.kind} if pred.kind else {}
            entry["masks"] = {frame: _rle_of(pred, frame) for frame in pred.masks}
            if pred.scores:
                entry["scores"] = {f: _score_json(s, text, f) for f, s in pred.scores.items()}
            if pred.decisions:
                entry["decisions"] = {f: bool(d) for f, d in pred.decisions.items()}
            queries[text] = entry
    else:
        slugs: dict[str, str] = {}
        for text, pred in predictions.queries.items():
            slug = query_slug(text)
            if slug in slugs:
                raise InputError(None, field_name(text), f"folder name {slug!r} clashes with query {slugs[slug]!r}")
            slugs[slug] = text
            for frame in pred.masks:
                _check_file_name(frame, None, field_name(text, "masks", frame))
                mask = pred.mask(frame)
                write_image(directory / MASKS_DIR / slug / f"{frame}.png", mask.astype(np.uint8) * 255)
            entry = {"kind": pred.kind} if pred.kind else {}
            entry.update(slug=slug, frames=list(pred.masks))
            if pred.scores:
                entry["scores"] = {f: _score_json(s, text, f) for f, s in pred.scores.items()}
            if pred.decisions:
                entry["decisions"] = {f: bool(d) for f, d in pred.decisions.items()}
            queries[text] = entry
        doc["masks"] = "png"
    doc["queries"] = queries
    write_json(main, doc, indent=None if layout == "json" else 2)
    if other is not None and other.is_file():
        other.unlink()
    return main


# -- reading ---------------------------------------------------------------------------------------
def _check_header(doc: object, path: Path) -> dict:
    if not isinstance(doc, dict):
        raise InputError(path, None, f"expected a JSON object at the top level, got {type(doc).__name__}")
    check_keys(doc, TOP_KEYS, path, None)
    if doc.get("format") != FORMAT:
        raise InputError(path, "format", f"expected {FORMAT!r}, got {short_repr(doc.get('format'))}")
    version = doc.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise InputError(path, "version", f"expected an integer >= 1, got {short_repr(version)}")
    if version > VERSION:
        raise InputError(path, "version", f"version {version} is newer than this bench4d reads ({VERSION})")
    for key in ("scene", "method"):
        if doc.get(key) is not None and not isinstance(doc[key], str):
            raise InputError(path, key, "must be a string")
    if not isinstance(doc.get("info", {}), dict):
        raise InputError(path, "info", "must be an object")
    queries = doc.get("queries", {})
    if not isinstance(queries, dict):
        raise InputError(path, "queries", "must be an object {query text: {...}}")
    forms: dict[str, str] = {}
    for text, entry in queries.items():
        if not isinstance(entry, dict):
            raise InputError(path, field_name(text), "must be an object")
        check_keys(entry, ENTRY_KEYS, path, field_name(text))
        if text_key(text) in forms:  # one query under two spellings: which answers the ground truth's?
            raise InputError(path, field_name(text), f"the same query as {forms[text_key(text)]!r} up to case, "
                                                     "spaces and Unicode form")
        forms[text_key(text)] = text
        kind = entry.get("kind")
        if kind is not None and kind not in KINDS:
            raise InputError(path, field_name(text, "kind"), f"must be one of {KINDS}, got {short_repr(kind)}")
    return doc


def _frame_map(entry: dict, part: str, path: Path, text: str) -> dict:
    value = entry.get(part, {})
    if not isinstance(value, dict):
        raise InputError(path, field_name(text, part), "must be an object {frame name: value}")
    return value


def _read_scores(entry: dict, path: Path, text: str) -> tuple[dict[str, float], dict[str, bool]]:
    scores: dict[str, float] = {}
    for frame, value in _frame_map(entry, "scores", path, text).items():
        if value is None:
            scores[frame] = float("nan")
        # compared before float(): an int too large for a float raises OverflowError, and a huge
        # finite score would overflow the mean of the temporal rule to inf
        elif isinstance(value, (int, float)) and not isinstance(value, bool) and abs(value) <= SCORE_LIMIT:
            scores[frame] = float(value)
        else:
            raise InputError(path, field_name(text, "scores", frame),
                             f"expected a finite number with |s| <= {SCORE_LIMIT:g} or null, got {short_repr(value)}")
    decisions: dict[str, bool] = {}
    for frame, value in _frame_map(entry, "decisions", path, text).items():
        if not isinstance(value, bool):
            raise InputError(path, field_name(text, "decisions", frame), f"expected true or false, got {short_repr(value)}")
        decisions[frame] = value
    return scores, decisions


def _check_rle(rle: object, path: Path, where: str) -> dict:
    if not isinstance(rle, dict) or "size" not in rle or "counts" not in rle:
        raise InputError(path, where, "expected a COCO RLE object {\"size\": [H, W], \"counts\": ...}")
    # the size now (a huge one is refused before anything is decoded); the runs when the mask is decoded
    check_mask_size(rle["size"], path, f"{where}.size")
    if not isinstance(rle["counts"], (str, list)):
        raise InputError(path, f"{where}.counts", "expected a compressed string or a list of run lengths")
    return rle


def _check_file_name(name: object, path: Path, where: str) -> str:
    """A frame name or folder name usable as one path component inside the prediction folder."""
    if (not isinstance(name, str) or not name or name.startswith(".") or "/" in name or "\\" in name
            or "\0" in name):
        raise InputError(path, where, f"not usable as a file name: {short_repr(name)}")
    return name


def _read_json_layout(path: Path) -> ScenePredictions:
    doc = _check_header(read_json(path), path)
    preds = ScenePredictions(scene=doc.get("scene"), method=doc.get("method"), info=doc.get("info", {}),
                             source=path)
    for text, entry in doc.get("queries", {}).items():
        masks = {frame: _check_rle(rle, path, field_name(text, "masks", frame))
                 for frame, rle in _frame_map(entry, "masks", path, text).items()}
        scores, decisions = _read_scores(entry, path, text)
        preds.add(QueryPrediction(text=text, kind=entry.get("kind"), masks=masks, scores=scores,
                                  decisions=decisions, source=path))
    return preds


def _read_png_layout(directory: Path) -> ScenePredictions:
    masks_dir = directory / MASKS_DIR
    scores_path = directory / SCORES_FILE
    doc = _check_header(read_json(scores_path), scores_path) if scores_path.exists() else {}
    preds = ScenePredictions(scene=doc.get("scene"), method=doc.get("method"), info=doc.get("info", {}),
                             source=directory)
    listed: set[str] = set()
    for text, entry in doc.get("queries", {}).items():
        slug = _check_file_name(entry.get("slug", query_slug(text)), scores_path, field_name(text, "slug"))
        listed.add(slug)
        folder = masks_dir / slug
        frames = entry.get("frames")
        if frames is None:
            files = sorted(folder.glob("*.png")) if folder.is_dir() else []
            masks = {f.stem: f for f in files}
        elif isinstance(frames, list) and all(isinstance(f, str) for f in frames):
            masks = {_check_file_name(f, scores_path, f"{field_name(text, 'frames')}[{i}]"): folder / f"{f}.png"
                     for i, f in enumerate(frames)}
        else:
            raise InputError(scores_path, field_name(text, "frames"), "must be a list of frame names")
        scores, decisions = _read_scores(entry, scores_path, text)
        preds.add(QueryPrediction(text=text, kind=entry.get("kind"), masks=masks, scores=scores,
                                  decisions=decisions, source=folder))
    if masks_dir.is_dir():
        for folder in sorted(p for p in masks_dir.iterdir() if p.is_dir() and p.name not in listed):
            masks = {f.stem: f for f in sorted(folder.glob("*.png"))}
            preds.add(QueryPrediction(text=folder.name, masks=masks, source=folder))
    return preds


def read_predictions(directory: str | Path) -> ScenePredictions:
    """Read a prediction folder in either layout (module docstring). Masks decode lazily.

    Structural problems raise :class:`InputError` naming the file and field; whether the
    predictions cover the ground truth is checked when scoring.
    """
    directory = Path(directory)
    if directory.is_file() and directory.name in (JSON_FILE, JSON_GZ_FILE, SCORES_FILE):
        directory = directory.parent
    if directory.is_file():
        raise InputError(directory, None,
                         f"is a file; expected a prediction folder (or its {JSON_FILE}[.gz] / {SCORES_FILE})")
    if not directory.is_dir():
        raise InputError(directory, None, "prediction folder not found")
    json_paths = [directory / name for name in (JSON_FILE, JSON_GZ_FILE) if (directory / name).exists()]
    has_png = (directory / MASKS_DIR).is_dir() or (directory / SCORES_FILE).exists()
    if len(json_paths) > 1:
        raise InputError(directory, None, f"holds both {JSON_FILE} and {JSON_GZ_FILE}; keep one")
    if json_paths and has_png:
        raise InputError(directory, None, f"holds both {json_paths[0].name} and the PNG layout ({MASKS_DIR}/, "
                                          f"{SCORES_FILE}); keep one")
    if json_paths:
        return _read_json_layout(json_paths[0])
    if has_png:
        return _read_png_layout(directory)
    raise InputError(directory, None, f"no {JSON_FILE}[.gz] and no {MASKS_DIR}/ folder: not a prediction folder")
