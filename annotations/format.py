"""The project's annotation file: one versioned, validated JSON per scene.

Files live in ``annotations/scenes/<dataset>/<scene>.json``. They are COCO-shaped (``images``,
``categories``, ``annotations`` with COCO RLE masks) so COCO tools can read the masks, plus the
time-sensitive labels and the scene facts COCO has no place for.

Schema (``"version": 1``)
-------------------------
.. code-block:: text

    {
      "format": "bench4d-annotations",         # required, exactly this string
      "version": 1,                            # required, exactly 1
      "scene": "split-cookie",                 # required, non-empty string
      "num_time_steps": 100,                   # required, positive int or null (= unknown)
      "info": {...},                           # optional object: provenance (tool, sources, annotator)
      "images": [                              # the evaluated frames
        {"id": 1,                              # int, unique
         "file_name": "000123",                # the scene's frame name (Frame.name), unique; not a path
         "width": 536, "height": 960,          # ints > 0: the size the masks are drawn at
         "time_index": 123,                    # int >= 0 (< num_time_steps when that is known)
         "camera_id": "0"}                     # optional string, default "0"
      ],
      "categories": [                          # the queries
        {"id": 1, "name": "cookie",            # id int unique; name = query text, non-empty, unique
         "kind": "agnostic",                   # "agnostic" | "sensitive" (optional, default "agnostic")
         "level": "whole",                     # optional string or null (informational)
         "review": "draft"},                   # optional: "draft" (not yet checked) or null/absent (reviewed)
        {"id": 2, "name": "cracked cookie", "kind": "sensitive",
         "base": 1}                            # sensitive only, required: id of an agnostic category
      ],
      "annotations": [                         # one per annotated (agnostic category, image)
        {"id": 1, "image_id": 1, "category_id": 1,
         "segmentation": {"size": [960, 536], "counts": "<COCO compressed RLE string>"},
         "area": 1234,                         # optional on load; when given must equal the mask's area
         "bbox": [x, y, w, h],                 # optional, informational (COCO toBbox of the mask)
         "iscrowd": 1,                         # optional, informational (COCO: RLE masks are "crowd")
         "absent": false,                      # optional on load; see "absent" below
         "made_by": "box"}                     # optional: how the mask was made (see "Provenance")
      ],
      "time_segments": {"2": [[0, 10], [40, 55]]}   # category id (as a JSON string key) -> intervals
    }

Rules
-----
* **Absent vs. not annotated.** An entry in ``annotations`` for (category, image) means *annotated*.
  An annotated mask with no foreground pixel means *absent* ("the object is not in this frame"): a
  frame that scores a false positive as IoU 0. A (category, image) pair with *no entry* is *not
  annotated* and is never scored. The RLE is authoritative; ``absent`` is written as a convenience
  and, when given on load, must agree with the mask (``true`` exactly when the RLE is empty). A
  hand-written file may give ``"absent": true`` with no ``segmentation`` at all: that is an empty
  mask of the image's size.
* **Provenance.** ``made_by`` of an annotation says how its mask was made, one of
  :data:`benchmark.core.annotation.MADE_BY`: ``drawn``, ``box``, ``clicks``, ``propagated``,
  ``corrected``, ``absent`` (marked absent by hand) or ``scripted`` (computed by a program, e.g. from an
  alpha channel); absent or null = not recorded. A category with ``"review": "draft"`` has masks and
  intervals nobody has checked yet (made by a program or a person); without it the category is reviewed.
  Older files keep these notes in ``info.made_by = {category id: {frame name: how}}``: such a file
  loads with each note moved onto its annotation (a note must name an annotated pair and agree with
  the annotation's own ``made_by``), and ``info.made_by`` is not written back.
* Only time-agnostic categories own masks; a time-sensitive category inherits the masks of its
  ``base`` (the release's rule) and owns its ``time_segments``. At most one annotation per
  (category, image).
* ``time_segments`` intervals ``[l, r]`` are inclusive at both ends, in 0-based ``time_index``
  units, ``0 <= l <= r`` and ``r < num_time_steps`` when that is known. Only sensitive categories may
  have them; a sensitive category without an entry holds nowhere.
* RLE ``size`` is ``[height, width]`` and must equal the image's size. ``counts`` is a COCO
  compressed string (written) or an uncompressed list of run lengths (accepted on load); either
  must describe exactly ``height * width`` pixels, every run between 0 and ``height * width``
  (checked run by run before anything is decoded: :func:`benchmark.core.annotation.rle_runs`).
* Limits: ``width * height`` at most :data:`benchmark.core.annotation.MAX_MASK_PIXELS`; ``time_index``,
  interval ends and ``num_time_steps - 1`` at most :data:`MAX_TIME_INDEX` (2**31 - 1); ``bbox``
  numbers finite. Files are read by :func:`benchmark.core.atomic.read_json` (nesting at most
  :data:`benchmark.core.atomic.MAX_JSON_DEPTH` levels) and written as standard JSON (a NaN in ``info``
  is written as ``null``).

:func:`save_annotations` writes atomically and :func:`load_annotations` reproduces the same
:class:`~benchmark.core.annotation.AnnotationSet` (every field, intervals and masks bit-exact).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Optional

import numpy as np
from pycocotools import mask as mask_utils

from benchmark.core.atomic import json_ready, read_json, write_text
from benchmark.core.errors import InputError, short_repr
from benchmark.core.strict import (MAX_COUNT, canonical_int_key, check_finite, check_int, check_keys, check_name,
                                   check_text, text_key)

from benchmark.core.annotation import (DRAFT, MADE_BY, MAX_MASK_PIXELS, AnnotatedFrame, AnnotationSet, Query,
                                       check_rle, rle_runs, runs_to_string)

FORMAT_NAME = "bench4d-annotations"
FORMAT_VERSION = 1

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "annotation_set_to_dict", "annotation_set_from_dict",
           "save_annotations", "load_annotations", "validate_against_scene", "validate_rle",
           "rle_area", "rle_bbox", "rle_is_empty"]


# ---------------------------------------------------------------------------------------------
# RLE helpers
# ---------------------------------------------------------------------------------------------
def validate_rle(rle: Any, file: str | Path | None, field: str,
                 size: Optional[tuple[int, int]] = None) -> dict:
    """Check a COCO RLE and return it as ``{"size": [h, w], "counts": str}``.

    ``size`` is the expected ``(height, width)``. Every check of
    :func:`benchmark.core.annotation.rle_runs` applies (size first, then each run bounded before any sum).
    Raises :class:`InputError` naming ``field``.
    """
    return check_rle(rle, file, field, size)


def _checked_rle(rle: Any, file, field: str, size: Optional[tuple[int, int]]) -> tuple[dict, int]:
    """(JSON-ready checked RLE, foreground pixel count) from one pass over the runs."""
    h, w, runs = rle_runs(rle, file, field, size)
    counts = rle["counts"]
    if isinstance(counts, bytes):
        counts = counts.decode("ascii")
    elif not isinstance(counts, str):
        counts = runs_to_string(runs)
    return {"size": [h, w], "counts": counts}, int(runs[1::2].sum())


def rle_area(rle: dict) -> int:
    """Foreground pixel count of a (compressed) RLE (checked: :class:`InputError` if malformed)."""
    return int(rle_runs(rle, None, "rle")[2][1::2].sum())


def rle_bbox(rle: dict) -> list[float]:
    """COCO ``[x, y, w, h]`` of a (compressed) RLE (zeros when empty); checked before pycocotools
    sees it."""
    checked = check_rle(rle, None, "rle")
    coco = {"size": checked["size"], "counts": checked["counts"].encode("ascii")}
    return [float(v) for v in mask_utils.toBbox(coco)]


def rle_is_empty(rle: dict) -> bool:
    return rle_area(rle) == 0


def _is_int(v: Any) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


MAX_TIME_INDEX = 2 ** 31 - 1
"""Largest ``time_index`` (and interval end) a file may give: time indices are stored in int32-safe
columns when scored."""

TOP_KEYS = ("format", "version", "scene", "num_time_steps", "info", "images", "categories", "annotations",
            "time_segments")
IMAGE_KEYS = ("id", "file_name", "width", "height", "time_index", "camera_id")
CATEGORY_KEYS = ("id", "name", "kind", "level", "review", "base", "supercategory")
ANNOTATION_KEYS = ("id", "image_id", "category_id", "segmentation", "area", "bbox", "iscrowd", "absent", "made_by")
"""The keys of each object of the schema: a key that varies one of them (case, spaces, Unicode form) is
refused (:func:`benchmark.core.strict.check_keys`); other keys are kept out of the way."""
MAX_ID = MAX_COUNT
"""Largest absolute image, category or annotation id."""


def _check_info(info: dict, file) -> None:
    """The provenance fields the annotation tool reads and extends, typed (the rest of ``info`` is free):
    ``revision`` a count, ``annotator`` a text, ``annotators`` a list of texts, ``annotation_seconds``
    ``{frame name: seconds}``, ``imported`` a list of objects. A field of another type would make every
    later save fail."""
    check_keys(info, ("revision", "annotator", "annotators", "annotation_seconds", "imported", "made_by", "tool",
                      "saved", "segmenter", "method", "protocol"), file, "info")
    if "revision" in info and info["revision"] is not None:
        check_int(info["revision"], file, "info.revision")
    if "annotator" in info and not isinstance(info["annotator"], str):
        raise InputError(file, "info.annotator", f"expected a text, got {short_repr(info['annotator'])}")
    annotators = info.get("annotators")
    if "annotators" in info and not (isinstance(annotators, list) and all(isinstance(a, str) for a in annotators)):
        raise InputError(file, "info.annotators", f"expected a list of texts, got {short_repr(annotators)}")
    seconds = info.get("annotation_seconds")
    if "annotation_seconds" in info:
        if not isinstance(seconds, dict):
            raise InputError(file, "info.annotation_seconds", f"expected {{frame name: seconds}}, got "
                                                              f"{short_repr(seconds)}")
        for name, value in seconds.items():
            check_finite(value, file, f"info.annotation_seconds.{name}", 0.0, 1e12)
    imported = info.get("imported")
    if "imported" in info and not (isinstance(imported, list) and all(isinstance(x, dict) for x in imported)):
        raise InputError(file, "info.imported", f"expected a list of objects, got {short_repr(imported)}")


# ---------------------------------------------------------------------------------------------
# AnnotationSet <-> dict
# ---------------------------------------------------------------------------------------------
def annotation_set_to_dict(aset: AnnotationSet) -> dict:
    """The JSON object of the schema above (raises :class:`InputError` if ``aset`` is inconsistent)."""
    # validate by the same rules the loader applies, so a saved file always loads
    images = [{"id": int(f.id), "file_name": str(f.name), "width": int(f.width), "height": int(f.height),
               "time_index": int(f.time_index), "camera_id": str(f.camera_id)} for f in aset.frames]
    categories = []
    for q in aset.queries:
        cat: dict[str, Any] = {"id": int(q.id), "name": q.text, "kind": q.kind}
        if q.base is not None:
            cat["base"] = int(q.base)
        if q.level is not None:
            cat["level"] = q.level
        if q.review is not None:
            cat["review"] = q.review
        categories.append(cat)
    annotations = []
    frame_order = {f.id: i for i, f in enumerate(aset.frames)}
    query_order = {q.id: i for i, q in enumerate(aset.queries)}
    keys = sorted(aset.masks, key=lambda k: (frame_order.get(k[1], math.inf), query_order.get(k[0], math.inf),
                                              k[1], k[0]))
    frame_by_id = {f.id: f for f in aset.frames}
    orphans = sorted(set(aset.made_by) - set(aset.masks))
    if orphans:
        raise InputError("<in-memory AnnotationSet>", f"made_by[{orphans[0][0]}, {orphans[0][1]}]",
                         "records how a mask was made but the pair has no mask")
    for ann_id, (qid, fid) in enumerate(keys, start=1):
        frame = frame_by_id.get(fid)
        size = None if frame is None else (int(frame.height), int(frame.width))
        # in-memory masks are checked like a file's before pycocotools computes the bbox
        seg, area = _checked_rle(aset.masks[(qid, fid)], "<in-memory AnnotationSet>", f"masks[{qid}, {fid}]", size)
        ann = {"id": ann_id, "image_id": int(fid), "category_id": int(qid), "segmentation": seg,
               "area": area, "bbox": rle_bbox(seg), "iscrowd": 1, "absent": area == 0}
        if (qid, fid) in aset.made_by:
            ann["made_by"] = aset.made_by[(qid, fid)]
        annotations.append(ann)
    for q in aset.queries:
        if q.kind != "sensitive" and q.intervals:
            raise InputError("<in-memory AnnotationSet>", f"queries[{q.id}].intervals",
                             f"time-agnostic query {q.text!r} has time intervals; only sensitive queries do")
    time_segments = {str(q.id): [[int(a), int(b)] for a, b in q.intervals]
                     for q in aset.queries if q.kind == "sensitive"}
    doc = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "scene": aset.scene,
           "num_time_steps": None if aset.num_time_steps is None else int(aset.num_time_steps),
           "info": dict(aset.info), "images": images, "categories": categories,
           "annotations": annotations, "time_segments": time_segments}
    annotation_set_from_dict(doc, file="<in-memory AnnotationSet>")
    return doc


def annotation_set_from_dict(doc: Any, file: str | Path | None = None) -> AnnotationSet:
    """Validate a parsed annotation JSON and build the :class:`AnnotationSet` (rules above)."""
    if not isinstance(doc, dict):
        raise InputError(file, None, f"expected a JSON object at the top level, got {type(doc).__name__}")
    check_keys(doc, TOP_KEYS, file, None)
    for key in ("format", "version", "scene", "num_time_steps", "images", "categories", "annotations"):
        if key not in doc:
            raise InputError(file, key, "missing required key")
    if doc["format"] != FORMAT_NAME:
        raise InputError(file, "format", f"expected {FORMAT_NAME!r}, got {short_repr(doc['format'])}")
    if not _is_int(doc["version"]) or doc["version"] != FORMAT_VERSION:
        raise InputError(file, "version",
                         f"unsupported version {short_repr(doc['version'])}; this bench4d reads version {FORMAT_VERSION}")
    scene = check_name(doc["scene"], file, "scene")  # joined to folders (a predictions folder per scene)
    nts = doc["num_time_steps"]
    if nts is not None and not (_is_int(nts) and 0 < nts <= MAX_TIME_INDEX + 1):
        raise InputError(file, "num_time_steps",
                         f"expected a positive integer up to {MAX_TIME_INDEX + 1} or null, got {short_repr(nts)}")
    info = doc.get("info", {})
    if not isinstance(info, dict):
        raise InputError(file, "info", f"expected an object, got {type(info).__name__}")
    _check_info(info, file)

    frames = _parse_images(doc["images"], nts, file)
    queries = _parse_categories(doc["categories"], file)
    frame_by_id = {f.id: f for f in frames}
    query_by_id = {q.id: q for q in queries}
    masks, made_by = _parse_annotations(doc["annotations"], frame_by_id, query_by_id, file)
    _parse_time_segments(doc.get("time_segments", {}), query_by_id, nts, file)
    if "made_by" in info:
        _move_info_made_by(info["made_by"], frames, query_by_id, masks, made_by, file)
        info = {k: v for k, v in info.items() if k != "made_by"}  # a copy: the caller's document is left as it was
    return AnnotationSet(scene=scene, frames=frames, queries=queries, masks=masks,
                         num_time_steps=None if nts is None else int(nts), info=info, made_by=made_by)


def _require_list(value: Any, file, field: str) -> list:
    if not isinstance(value, list):
        raise InputError(file, field, f"expected a list, got {type(value).__name__}")
    return value


def _get(item: Any, key: str, file, field: str, *, types: tuple = (), default: Any = ..., check=None,
         expect: str = "") -> Any:
    """``item[key]`` with presence/type checks; errors name ``field.key``."""
    if not isinstance(item, dict):
        raise InputError(file, field, f"expected an object, got {type(item).__name__}")
    name = f"{field}.{key}"
    if key not in item:
        if default is ...:
            raise InputError(file, name, "missing required key")
        return default
    value = item[key]
    ok = (_is_int(value) if types == (int,) else isinstance(value, types)) if types else True
    if ok and check is not None:
        ok = check(value)
    if not ok:
        raise InputError(file, name, f"expected {expect or '/'.join(t.__name__ for t in types)}, got {short_repr(value)}")
    return value


def _parse_images(images: Any, nts: Optional[int], file) -> list[AnnotatedFrame]:
    frames: list[AnnotatedFrame] = []
    seen_ids: dict[int, int] = {}
    seen_names: dict[str, int] = {}
    for i, im in enumerate(_require_list(images, file, "images")):
        field = f"images[{i}]"
        check_keys(im, IMAGE_KEYS, file, field)
        fid = _get(im, "id", file, field, types=(int,), check=lambda v: abs(v) <= MAX_ID, expect=f"an integer id within +-{MAX_ID}")
        name = _get(im, "file_name", file, field, types=(str,), check=bool, expect="a non-empty frame name")
        width = _get(im, "width", file, field, types=(int,), check=lambda v: v > 0, expect="a positive int")
        height = _get(im, "height", file, field, types=(int,), check=lambda v: v > 0, expect="a positive int")
        if width * height > MAX_MASK_PIXELS:  # masks of this size are decoded when scored
            raise InputError(file, f"{field}.width/height", f"{width}x{height} is larger than the "
                                                            f"{MAX_MASK_PIXELS} pixels any frame may have")
        ti = _get(im, "time_index", file, field, types=(int,), check=lambda v: 0 <= v <= MAX_TIME_INDEX,
                  expect=f"an int in 0..{MAX_TIME_INDEX}")
        cam = _get(im, "camera_id", file, field, types=(str,), default="0")
        if nts is not None and ti >= nts:
            raise InputError(file, f"{field}.time_index", f"{ti} is out of range for num_time_steps={nts}")
        if fid in seen_ids:
            raise InputError(file, f"{field}.id", f"duplicate image id {fid} (also images[{seen_ids[fid]}])")
        if name in seen_names:
            raise InputError(file, f"{field}.file_name",
                             f"duplicate frame name {name!r} (also images[{seen_names[name]}])")
        seen_ids[fid] = i
        seen_names[name] = i
        frames.append(AnnotatedFrame(id=int(fid), name=name, time_index=int(ti), width=int(width),
                                     height=int(height), camera_id=cam))
    return frames


def _parse_categories(categories: Any, file) -> list[Query]:
    queries: list[Query] = []
    seen_ids: dict[int, int] = {}
    seen_names: dict[str, int] = {}
    for i, cat in enumerate(_require_list(categories, file, "categories")):
        field = f"categories[{i}]"
        check_keys(cat, CATEGORY_KEYS, file, field)
        qid = _get(cat, "id", file, field, types=(int,), check=lambda v: abs(v) <= MAX_ID, expect=f"an integer id within +-{MAX_ID}")
        name = check_text(_get(cat, "name", file, field, types=(str,)), file, f"{field}.name")
        kind = _get(cat, "kind", file, field, types=(str,), default="agnostic",
                    check=lambda v: v in ("agnostic", "sensitive"), expect="'agnostic' or 'sensitive'")
        level = _get(cat, "level", file, field, types=(str, type(None)), default=None)
        if level is not None:
            level = check_text(level, file, f"{field}.level", max_chars=100)
        review = _get(cat, "review", file, field, types=(str, type(None)), default=None,
                      check=lambda v: v is None or v == DRAFT, expect=f"{DRAFT!r} or null")
        base = _get(cat, "base", file, field, types=(int, type(None)), default=None)
        if isinstance(base, bool):
            raise InputError(file, f"{field}.base", f"expected a category id, got {base!r}")
        if qid in seen_ids:
            raise InputError(file, f"{field}.id", f"duplicate category id {qid} (also categories[{seen_ids[qid]}])")
        if text_key(name) in seen_names:
            raise InputError(file, f"{field}.name", f"duplicate query text {name!r} (also "
                                                    f"categories[{seen_names[text_key(name)]}], up to case, spaces "
                                                    "and Unicode form)")
        if kind == "agnostic" and base is not None:
            raise InputError(file, f"{field}.base", "only a time-sensitive category has a base")
        if kind == "sensitive" and base is None:
            raise InputError(file, f"{field}.base",
                             "a time-sensitive category needs 'base': the agnostic category whose masks it uses")
        seen_ids[qid] = i
        seen_names[text_key(name)] = i
        queries.append(Query(id=int(qid), text=name, kind=kind, base=None if base is None else int(base),
                             level=level, review=review))
    by_id = {q.id: (i, q) for i, q in enumerate(queries)}
    for i, q in enumerate(queries):
        if q.base is None:
            continue
        if q.base not in by_id:
            raise InputError(file, f"categories[{i}].base", f"unknown category id {q.base}")
        if by_id[q.base][1].kind != "agnostic":
            raise InputError(file, f"categories[{i}].base",
                             f"base {q.base} ({by_id[q.base][1].text!r}) is not a time-agnostic category")
    return queries


def _parse_annotations(annotations: Any, frame_by_id: dict[int, AnnotatedFrame], query_by_id: dict[int, Query],
                       file) -> tuple[dict[tuple[int, int], dict], dict[tuple[int, int], str]]:
    """(masks, made_by) of the ``annotations`` list, both keyed by (category id, image id)."""
    masks: dict[tuple[int, int], dict] = {}
    made_by: dict[tuple[int, int], str] = {}
    seen_ids: dict[int, int] = {}
    where: dict[tuple[int, int], int] = {}
    for i, ann in enumerate(_require_list(annotations, file, "annotations")):
        field = f"annotations[{i}]"
        check_keys(ann, ANNOTATION_KEYS, file, field)
        aid = _get(ann, "id", file, field, types=(int,), check=lambda v: abs(v) <= MAX_ID, expect=f"an integer id within +-{MAX_ID}")
        fid = _get(ann, "image_id", file, field, types=(int,))
        qid = _get(ann, "category_id", file, field, types=(int,))
        absent = _get(ann, "absent", file, field, types=(bool,), default=None)
        how = _get(ann, "made_by", file, field, types=(str, type(None)), default=None,
                   check=lambda v: v is None or v in MADE_BY, expect=f"one of {', '.join(MADE_BY)} or null")
        if aid in seen_ids:
            raise InputError(file, f"{field}.id", f"duplicate annotation id {aid} (also annotations[{seen_ids[aid]}])")
        seen_ids[aid] = i
        if fid not in frame_by_id:
            raise InputError(file, f"{field}.image_id", f"unknown image id {fid}")
        if qid not in query_by_id:
            raise InputError(file, f"{field}.category_id", f"unknown category id {qid}")
        query = query_by_id[qid]
        if query.kind != "agnostic":
            raise InputError(file, f"{field}.category_id",
                             f"category {qid} ({query.text!r}) is time-sensitive: it inherits the masks of its "
                             f"base {query.base}; annotate the base instead")
        if (qid, fid) in where:
            raise InputError(file, field, f"second annotation of category {qid} on image {fid} "
                                          f"(also annotations[{where[(qid, fid)]}]); one mask per pair")
        where[(qid, fid)] = i
        frame = frame_by_id[fid]
        size = (frame.height, frame.width)
        if "segmentation" not in ann:
            if absent is not True:
                raise InputError(file, f"{field}.segmentation",
                                 "missing required key (only an annotation with \"absent\": true may omit it)")
            rle = {"size": [frame.height, frame.width], "counts": _empty_counts(frame.height, frame.width)}
            area = 0
        else:
            rle, area = _checked_rle(ann["segmentation"], file, f"{field}.segmentation", size)
        if absent is not None and absent != (area == 0):
            raise InputError(file, f"{field}.absent",
                             f"says {str(absent).lower()} but the mask has {area} foreground pixels")
        if "area" in ann:
            given = ann["area"]
            if not isinstance(given, (int, float, np.number)) or isinstance(given, bool) or given != area:
                raise InputError(file, f"{field}.area", f"is {short_repr(given)} but the mask has {area} foreground pixels")
        if "bbox" in ann:
            bbox = ann["bbox"]
            if (not isinstance(bbox, list) or len(bbox) != 4
                    or not all(_is_finite_number(v) for v in bbox)):
                raise InputError(file, f"{field}.bbox", f"expected [x, y, w, h] finite numbers, got {short_repr(bbox)}")
        masks[(qid, fid)] = rle
        if how is not None:
            made_by[(qid, fid)] = how
    return masks, made_by


def _move_info_made_by(notes: Any, frames: list[AnnotatedFrame], query_by_id: dict[int, Query],
                       masks: dict[tuple[int, int], dict], made_by: dict[tuple[int, int], str], file) -> None:
    """Move the older ``info.made_by = {category id: {frame name: how}}`` onto ``made_by`` (in place)."""
    expect = "expected an object {category id: {frame name: how the mask was made}}"
    if not isinstance(notes, dict):
        raise InputError(file, "info.made_by", f"{expect}, got {type(notes).__name__}")
    frame_id = {f.name: f.id for f in frames}
    for key, per_frame in notes.items():
        field = f"info.made_by.{key}"
        qid = int(key) if _is_int(key) or (isinstance(key, str) and key.isascii() and key.isdigit()) else None
        if qid not in query_by_id:
            raise InputError(file, field, f"{short_repr(key)} is not a category id of this file")
        if not isinstance(per_frame, dict):
            raise InputError(file, field, f"{expect}, got {type(per_frame).__name__}")
        for name, how in per_frame.items():
            where = f"{field}.{name}"
            if name not in frame_id:
                raise InputError(file, where, f"{short_repr(name)} is not the file_name of an image")
            if how not in MADE_BY:
                raise InputError(file, where, f"expected one of {', '.join(MADE_BY)}, got {short_repr(how)}")
            pair = (qid, frame_id[name])
            if pair not in masks:
                raise InputError(file, where, f"category {qid} has no annotation on image {pair[1]}")
            if made_by.get(pair, how) != how:
                raise InputError(file, where, f"says {how!r} but the annotation says {made_by[pair]!r}")
            made_by[pair] = how


def _empty_counts(height: int, width: int) -> str:
    # one run of background, written without allocating the (possibly large) mask
    return runs_to_string([height * width])


def _is_finite_number(v: Any) -> bool:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    return isinstance(v, int) or math.isfinite(v)


def _parse_time_segments(segments: Any, query_by_id: dict[int, Query], nts: Optional[int], file) -> None:
    if not isinstance(segments, dict):
        raise InputError(file, "time_segments", f"expected an object {{category id: intervals}}, "
                                                f"got {type(segments).__name__}")
    for key, intervals in segments.items():
        field = f"time_segments.{key}"
        qid = canonical_int_key(key, file, field)  # not int(): it reads " 9 ", "+9", "0_9" and "٩" as 9
        if qid not in query_by_id:
            raise InputError(file, field, f"unknown category id {qid}")
        query = query_by_id[qid]
        if query.kind != "sensitive":
            raise InputError(file, field, f"category {qid} ({query.text!r}) is time-agnostic; "
                                          "only time-sensitive categories have time segments")
        parsed = []
        for j, iv in enumerate(_require_list(intervals, file, field)):
            if not (isinstance(iv, list) and len(iv) == 2 and all(_is_int(v) for v in iv)):
                raise InputError(file, f"{field}[{j}]", f"expected [l, r] integers, got {short_repr(iv)}")
            lo, hi = int(iv[0]), int(iv[1])
            if lo < 0:
                raise InputError(file, f"{field}[{j}]", f"negative time index in {short_repr(iv)}")
            if lo > hi:
                raise InputError(file, f"{field}[{j}]", f"l > r in {iv} (intervals are inclusive [l, r])")
            if hi > MAX_TIME_INDEX:
                raise InputError(file, f"{field}[{j}]", f"{short_repr(iv)} reaches past time index {MAX_TIME_INDEX}")
            if nts is not None and hi >= nts:
                raise InputError(file, f"{field}[{j}]", f"{iv} reaches past num_time_steps={nts}")
            parsed.append((lo, hi))
        query.intervals = parsed


# ---------------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------------
def save_annotations(aset: AnnotationSet, path: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``aset`` to ``path`` atomically (schema above); returns the path.

    An existing file is a user's work: it is replaced only with ``overwrite=True`` (an editor saving
    the file it opened passes that); otherwise :class:`InputError`.
    """
    path = Path(path)
    if not overwrite and path.exists():
        raise InputError(path, None, "file exists; pass overwrite=True to replace it")
    doc = annotation_set_to_dict(aset)
    write_text(path, dumps_annotations(doc))
    return path


def dumps_annotations(doc: dict) -> str:
    """JSON text with one line per image / category / annotation / time segment (diff-friendly)."""
    def one(v: Any) -> str:  # standard JSON only: a NaN (e.g. in ``info``) is written as null
        return json.dumps(json_ready(v), ensure_ascii=False, separators=(", ", ": "), allow_nan=False)

    lines = ["{"]
    keys = list(doc)
    for n, key in enumerate(keys):
        value = doc[key]
        comma = "," if n < len(keys) - 1 else ""
        if isinstance(value, list) and value:
            items = [f"    {one(v)}" for v in value]
            lines.append(f"  {one(key)}: [\n" + ",\n".join(items) + f"\n  ]{comma}")
        elif isinstance(value, dict) and value:
            items = [f"    {one(str(k))}: {one(v)}" for k, v in value.items()]
            lines.append(f"  {one(key)}: {{\n" + ",\n".join(items) + f"\n  }}{comma}")
        else:
            lines.append(f"  {one(key)}: {one(value)}{comma}")
    return "\n".join(lines) + "\n}\n"


def load_annotations(path: str | Path, scene=None) -> AnnotationSet:
    """Read and validate an annotation file; with a :class:`benchmark.core.scene.Scene`, also check it
    against the scene (:func:`validate_against_scene`)."""
    path = Path(path)
    aset = annotation_set_from_dict(read_json(path), file=path)
    if scene is not None:
        validate_against_scene(aset, scene, file=path)
    return aset


def validate_against_scene(aset: AnnotationSet, scene, file: str | Path | None = None) -> None:
    """Check that ``aset`` describes ``scene`` (a :class:`benchmark.core.scene.Scene`).

    Every annotated frame must be a frame of the scene with the same ``time_index`` and
    ``camera_id``, and masks must have the size of that frame's camera image. ``num_time_steps``
    (when known) must cover every time index the scene has, and time segments must lie inside the
    scene's time range. Errors name ``file`` (default: ``<annotations of SCENE>``) and the field.
    """
    file = file if file is not None else f"<annotations of {aset.scene}>"
    names = {f.name: f for f in scene.frames}
    for i, af in enumerate(aset.frames):
        field = f"images[{i}]"
        sf = names.get(af.name)
        if sf is None:
            sample = ", ".join(repr(n) for n in list(names)[:3])
            raise InputError(file, f"{field}.file_name",
                             f"frame {af.name!r} is not in scene {scene.name!r} (its frames are named like {sample})")
        if sf.time_index != af.time_index:
            raise InputError(file, f"{field}.time_index",
                             f"frame {af.name!r} has time_index {af.time_index} but the scene says {sf.time_index}")
        if str(sf.camera_id) != str(af.camera_id):
            raise InputError(file, f"{field}.camera_id",
                             f"frame {af.name!r} has camera {af.camera_id!r} but the scene says {sf.camera_id!r}")
        if (sf.camera.width, sf.camera.height) != (af.width, af.height):
            raise InputError(file, f"{field}.width/height",
                             f"frame {af.name!r} is annotated at {af.width}x{af.height} but the scene's image is "
                             f"{sf.camera.width}x{sf.camera.height} (re-import with that target size)")
    if not scene.frames:
        return
    last = max(f.time_index for f in scene.frames)
    if aset.num_time_steps is not None and aset.num_time_steps <= last:
        raise InputError(file, "num_time_steps",
                         f"{aset.num_time_steps} but scene {scene.name!r} has frames up to time_index {last}")
    for q in aset.sensitive_queries:
        for j, (lo, hi) in enumerate(q.intervals):
            if hi > last:
                raise InputError(file, f"time_segments.{q.id}[{j}]",
                                 f"[{lo}, {hi}] reaches past the scene's last time_index {last}")
