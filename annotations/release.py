"""Import and export the annotation files as the 4D LangSplat release ships them.

The release's ``annotations/`` folder of a scene holds:

``train/_annotations.coco.json``
    A Roboflow COCO export. ``categories[].name`` is the query text; Roboflow adds a root category
    (the ``supercategory`` of the others) that owns no annotation: it is dropped. ``images[].file_name``
    is ``<frame>_png.rf.<hash>.jpg`` where ``<frame>`` (the text before the first ``_``) is the video
    frame number, 1-based for HyperNeRF and 0-based for Neu3D (``frame_base``). Masks are polygons
    (flat ``[x0, y0, ...]`` lists); **every** polygon of every annotation of a label in an image is
    OR-ed (the release reads only the first polygon of each annotation: a bug not copied here). RLE
    ``segmentation`` objects (COCO "crowd" annotations) are accepted too. An annotation with an empty
    polygon list marks the label as annotated-but-absent in that image (how :func:`export_release`
    writes an empty mask; the release itself cannot express "absent").
``video_annotations.json`` (HyperNeRF, time-sensitive queries)
    ``{base_label: {time_query: [[l, r], ...]}}``: intervals inclusive at both ends; the time query
    inherits the masks of ``base_label``. The release compares ``l, r`` with the 0-based frame index
    it derives from the COCO file name (``frame - 1`` for HyperNeRF, ``frame`` for Neu3D), i.e. with
    ``time_index``; hence ``interval_base = 0`` by default (a frame number ``n`` in this file is
    ``time_index = n - interval_base``).

Polygons are rasterised by :func:`annotations.polygons.polygons_to_mask` (pixel-centre rule, see
there); a polygon drawn on an image of another size is rescaled to ``target_size`` first.

Limits on hostile files (each an :class:`~benchmark.core.errors.InputError` naming the file and field):
image sizes within :data:`benchmark.core.annotation.MAX_MASK_PIXELS`; RLE checked run by run before it is
decoded; polygon vertices finite and at most one image size outside the image; and the polygons of
one label in one image at most :func:`polygon_budget` long (edge lengths in pixels, max(|dx|, |dy|),
plus one per vertex), which bounds the rasteriser's working memory to a fixed multiple of the frame.
A mask drawn with polygons stays far below it (about 0.2-3 x height x width even for noisy masks);
:func:`export_release` writes a mask as RLE where its polygons would exceed it.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Literal, Mapping, Optional, Sequence, Union

import numpy as np
from pycocotools import mask as mask_utils

from benchmark.core.atomic import read_json, write_json, write_text
from benchmark.core.errors import InputError, short_repr
from benchmark.core.strict import check_text, text_key

from .format import MAX_TIME_INDEX, validate_against_scene
from benchmark.core.annotation import MAX_MASK_PIXELS, AnnotatedFrame, AnnotationSet, Query, decode_mask, encode_mask
from .polygons import (Rasterizer, check_polygon, mask_to_polygons, polygon_budget, polygon_cost,
                       polygons_to_mask)

COCO_RELATIVE_PATH = Path("train") / "_annotations.coco.json"
"""Where the COCO file lives inside a release ``annotations/`` folder."""
VIDEO_RELATIVE_PATH = Path("video_annotations.json")
"""Where the time-sensitive intervals live inside a release ``annotations/`` folder."""

FrameNames = Union[str, Callable[[int], str], Mapping[int, str], Sequence[str], Any]
MissingMeans = Literal["not_annotated", "absent"]

__all__ = ["COCO_RELATIVE_PATH", "VIDEO_RELATIVE_PATH", "ReleaseImportOptions", "import_release",
           "import_release_folder", "export_release", "frame_number_from_file_name", "check_polygon",
           "polygon_budget", "polygon_cost"]


@dataclass
class ReleaseImportOptions:
    """How to read a release's files where the files themselves do not say."""

    interval_base: int = 0
    """A frame number ``n`` in ``video_annotations.json`` means ``time_index = n - interval_base``.
    0 = the release's usage (it compares intervals with the 0-based frame index)."""
    missing_means: MissingMeans = "not_annotated"
    """A label with no annotation on an image that has other annotations: ``"not_annotated"``
    (the release: that pair is not scored) or ``"absent"`` (empty mask: false positives count)."""
    rasterizer: Rasterizer = "coco"
    """``"coco"``: pixel-centre rule via pycocotools (default); ``"release_cv2"``: the release's
    int32-truncated ``cv2.fillPoly`` (see :mod:`annotations.polygons`)."""
    root_category: Optional[str] = None
    """Name of the Roboflow root category to drop. ``None``: detect it (a category that owns no
    annotation and is the ``supercategory`` of another one)."""


def frame_number_from_file_name(file_name: str, file: str | Path | None = None, field: str = "file_name") -> int:
    """``"12_png.rf.ab12.jpg"`` -> 12 (the text before the first ``_``, or the stem if none)."""
    stem = Path(file_name).name
    head = stem.split("_", 1)[0] if "_" in stem else stem.split(".", 1)[0]
    # ASCII digits only: int() would also take " 12", "1_2" or other scripts' digits
    if not (head.isascii() and head.isdigit()) or len(head) > 12:
        raise InputError(file, field, f"cannot read a frame number from {short_repr(file_name)} "
                                      "(expected '<frame>_png.rf.<hash>.jpg')")
    return int(head)


# ---------------------------------------------------------------------------------------------
# import
# ---------------------------------------------------------------------------------------------
def import_release_folder(folder: str | Path, **kwargs) -> AnnotationSet:
    """:func:`import_release` on a release ``annotations/`` folder (video file used if present)."""
    folder = Path(folder)
    video = folder / VIDEO_RELATIVE_PATH
    return import_release(folder / COCO_RELATIVE_PATH, video if video.is_file() else None, **kwargs)


def import_release(coco_json: str | Path, video_json: str | Path | None = None, *, scene_name: str,
                   frame_base: int, target_size: Optional[tuple[int, int]] = None,
                   frame_names: Optional[FrameNames] = None, camera_id: Optional[str] = None,
                   num_time_steps: Optional[int] = None,
                   options: Optional[ReleaseImportOptions] = None) -> AnnotationSet:
    """Read a release's COCO (and optional video-interval) file into an :class:`AnnotationSet`.

    Parameters
    ----------
    frame_base:
        Frame number of the first video frame in the COCO file names: 1 for HyperNeRF, 0 for Neu3D.
        ``time_index = frame_number - frame_base``.
    target_size:
        ``(width, height)`` the masks should have (the scene's image size). Polygons drawn on an
        image of another size are rescaled. ``None``: the scene frame's size when ``frame_names`` is
        a Scene, else the COCO image size.
    frame_names:
        How a ``time_index`` becomes the scene's frame name: a format string with fields ``number``
        (as in the file name) and ``time_index``, a callable, a mapping or sequence indexed by
        ``time_index``, or a :class:`benchmark.core.scene.Scene` (its frame at that time index and
        ``camera_id``; then the result is also checked against the scene). ``None`` (default): the
        ``frame_name`` an :func:`export_release` file records per image, else ``"{number:06d}"``
        (HyperNeRF's image ids, e.g. ``1_png...jpg`` -> ``"000001"``).
    camera_id:
        Camera of the annotated view (Neu3D: the test camera). ``None``: the scene's only camera
        at that time index, the ``camera_id`` an exported file records, or ``"0"``.
    num_time_steps:
        Video length; ``None``: the scene's (``max time_index + 1``) when a Scene is given, else
        ``info.bench4d.num_time_steps`` of a file written by :func:`export_release`, else unknown.
    """
    opts = options or ReleaseImportOptions()
    coco_path = Path(coco_json)
    coco = read_json(coco_path)
    scene = frame_names if _is_scene(frame_names) else None
    if not isinstance(coco, dict):
        raise InputError(coco_path, None, f"expected a COCO JSON object, got {type(coco).__name__}")
    for key in ("images", "annotations", "categories"):
        if key not in coco:
            raise InputError(coco_path, key, "missing required key")
        if not isinstance(coco[key], list):
            raise InputError(coco_path, key, f"expected a list, got {type(coco[key]).__name__}")
    bench_info = coco.get("info", {}).get("bench4d", {}) if isinstance(coco.get("info"), dict) else {}
    if num_time_steps is None:
        if scene is not None and scene.frames:
            num_time_steps = max(f.time_index for f in scene.frames) + 1
        elif isinstance(bench_info, dict) and bench_info.get("num_time_steps") is not None:
            nts = bench_info["num_time_steps"]
            if not isinstance(nts, int) or isinstance(nts, bool) or not 0 < nts <= MAX_TIME_INDEX + 1:
                raise InputError(coco_path, "info.bench4d.num_time_steps",
                                 f"expected a positive integer up to {MAX_TIME_INDEX + 1} or null, got {short_repr(nts)}")
            num_time_steps = nts
    if target_size is not None:
        _check_size(target_size[0], target_size[1], None, "target_size")

    queries, cat_ids = _read_categories(coco, coco_path, opts)
    frames, image_size = _read_images(coco, coco_path, frame_base=frame_base, target_size=target_size,
                                      frame_names=frame_names, camera_id=camera_id,
                                      num_time_steps=num_time_steps)
    masks = _read_masks(coco, coco_path, frames, image_size, cat_ids, opts)

    info = {"source": "4D LangSplat release (Roboflow COCO)", "coco_file": str(coco_path),
            "frame_base": frame_base, "rasterizer": opts.rasterizer, "missing_means": opts.missing_means}
    aset = AnnotationSet(scene=scene_name, frames=list(frames.values()), queries=queries, masks=masks,
                         num_time_steps=num_time_steps, info=info)
    if video_json is not None:
        _read_video(Path(video_json), aset, opts)
        info["video_file"] = str(video_json)
        info["interval_base"] = opts.interval_base
    if scene is not None:
        validate_against_scene(aset, scene, file=coco_path)
    return aset


def _check_size(width: int, height: int, file, field: str) -> None:
    if width * height > MAX_MASK_PIXELS:  # masks of this size are allocated when rasterised
        raise InputError(file, field, f"{width}x{height} is larger than the {MAX_MASK_PIXELS} pixels any "
                                      "frame may have")


def _hashable_id(value: Any) -> bool:
    """An id as COCO writes it (an int); other JSON values (lists, objects) cannot be dict keys."""
    return isinstance(value, (int, str)) and not isinstance(value, bool)


def _is_scene(obj: Any) -> bool:
    return hasattr(obj, "frames_at") and hasattr(obj, "frames")


def _read_categories(coco: dict, file: Path, opts: ReleaseImportOptions) -> tuple[list[Query], dict[int, int]]:
    owners = {a.get("category_id") for a in coco["annotations"]
              if isinstance(a, dict) and _hashable_id(a.get("category_id"))}
    supers = {c.get("supercategory") for c in coco["categories"]
              if isinstance(c, dict) and isinstance(c.get("supercategory"), str)}
    queries: list[Query] = []
    ids: dict[int, int] = {}
    seen: dict[str, int] = {}
    for i, cat in enumerate(coco["categories"]):
        field = f"categories[{i}]"
        if not isinstance(cat, dict):
            raise InputError(file, field, f"expected an object, got {type(cat).__name__}")
        for key in ("id", "name"):
            if key not in cat:
                raise InputError(file, f"{field}.{key}", "missing required key")
        cid, name = cat["id"], cat["name"]
        if not isinstance(cid, int) or isinstance(cid, bool):
            raise InputError(file, f"{field}.id", f"expected an integer, got {short_repr(cid)}")
        check_text(name, file, f"{field}.name")
        is_root = (name == opts.root_category if opts.root_category is not None
                   else cid not in owners and name in supers and cat.get("supercategory") != name)
        if is_root:
            continue
        if cid in ids:
            raise InputError(file, f"{field}.id", f"duplicate category id {cid}")
        if text_key(name) in seen:
            raise InputError(file, f"{field}.name", f"query text {name!r} repeats categories[{seen[text_key(name)]}] "
                                                    "(up to case, spaces and Unicode form)")
        seen[text_key(name)] = i
        ids[cid] = cid
        level = cat.get("level") if isinstance(cat.get("level"), str) else None
        queries.append(Query(id=cid, text=name, kind="agnostic", level=level))
    return queries, ids


def _frame_name(frame_names: Optional[FrameNames], number: int, time_index: int, camera_id: Optional[str],
                image: dict, file: Path, field: str) -> tuple[str, str, Optional[tuple[int, int]]]:
    """(frame name, camera id, scene image (width, height) or None) for one image."""
    if frame_names is None:
        recorded = image.get("frame_name")
        if camera_id is None and isinstance(image.get("camera_id"), str):
            camera_id = image["camera_id"]
        if isinstance(recorded, str) and recorded:
            return recorded, "0" if camera_id is None else str(camera_id), None
        frame_names = "{number:06d}"
    if _is_scene(frame_names):
        candidates = frame_names.frames_at(time_index, camera_id)
        if len(candidates) != 1:
            what = "no frame" if not candidates else f"{len(candidates)} frames ({[f.name for f in candidates][:4]})"
            hint = "; pass camera_id to pick the annotated camera" if len(candidates) > 1 else ""
            raise InputError(file, field, f"scene {frame_names.name!r} has {what} at time_index {time_index}"
                                          f"{'' if camera_id is None else f' for camera {camera_id!r}'}{hint}")
        f = candidates[0]
        return f.name, str(f.camera_id), (f.camera.width, f.camera.height)
    cam = "0" if camera_id is None else str(camera_id)
    if isinstance(frame_names, str):
        try:
            return frame_names.format(number=number, time_index=time_index), cam, None
        except (KeyError, IndexError, ValueError) as err:
            raise InputError(None, "frame_names", f"bad format string {frame_names!r}: {err}") from None
    if callable(frame_names):
        return str(frame_names(time_index)), cam, None
    try:
        return str(frame_names[time_index]), cam, None
    except (KeyError, IndexError):
        raise InputError(file, field, f"frame_names has no entry for time_index {time_index}") from None


def _read_images(coco: dict, file: Path, *, frame_base: int, target_size, frame_names, camera_id,
                 num_time_steps) -> tuple[dict[int, AnnotatedFrame], dict[int, tuple[int, int]]]:
    """COCO image id -> frame (sized to the target), and COCO image id -> its (width, height)."""
    frames: dict[int, AnnotatedFrame] = {}
    sizes: dict[int, tuple[int, int]] = {}
    by_name: dict[str, int] = {}
    for i, im in enumerate(coco["images"]):
        field = f"images[{i}]"
        if not isinstance(im, dict):
            raise InputError(file, field, f"expected an object, got {type(im).__name__}")
        for key in ("id", "file_name", "width", "height"):
            if key not in im:
                raise InputError(file, f"{field}.{key}", "missing required key")
        iid = im["id"]
        if not isinstance(iid, int) or isinstance(iid, bool):
            raise InputError(file, f"{field}.id", f"expected an integer, got {short_repr(iid)}")
        if iid in frames:
            raise InputError(file, f"{field}.id", f"duplicate image id {iid}")
        for key in ("width", "height"):
            v = im[key]
            if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
                raise InputError(file, f"{field}.{key}", f"expected a positive integer, got {short_repr(v)}")
        _check_size(im["width"], im["height"], file, f"{field}.width/height")
        if not isinstance(im["file_name"], str):
            raise InputError(file, f"{field}.file_name", f"expected a string, got {short_repr(im['file_name'])}")
        number = frame_number_from_file_name(im["file_name"], file, f"{field}.file_name")
        time_index = number - frame_base
        if time_index < 0:
            raise InputError(file, f"{field}.file_name",
                             f"frame number {number} is below frame_base={frame_base} (is frame_base right?)")
        if time_index > MAX_TIME_INDEX:
            raise InputError(file, f"{field}.file_name", f"frame number {number} is past time index {MAX_TIME_INDEX}")
        if num_time_steps is not None and time_index >= num_time_steps:
            raise InputError(file, f"{field}.file_name",
                             f"frame number {number} (time_index {time_index}) is past the video's "
                             f"{num_time_steps} frames (is frame_base right?)")
        name, cam, scene_size = _frame_name(frame_names, number, time_index, camera_id, im, file,
                                               f"{field}.file_name")
        if name in by_name:
            raise InputError(file, f"{field}.file_name",
                             f"frame {name!r} appears twice (also images[{by_name[name]}]); Roboflow "
                             "augmentations must be disabled in the export")
        by_name[name] = i
        width, height = target_size if target_size is not None else (scene_size or (im["width"], im["height"]))
        _check_size(width, height, file, f"{field}.width/height")
        frames[iid] = AnnotatedFrame(id=iid, name=name, time_index=time_index, width=int(width),
                                     height=int(height), camera_id=cam)
        sizes[iid] = (im["width"], im["height"])
    return frames, sizes


def _read_masks(coco: dict, file: Path, frames: dict[int, AnnotatedFrame], image_size: dict[int, tuple[int, int]],
                cat_ids: dict[int, int], opts: ReleaseImportOptions) -> dict[tuple[int, int], dict]:
    polys: dict[tuple[int, int], list] = {}
    cost: dict[tuple[int, int], float] = {}
    rles: dict[tuple[int, int], np.ndarray] = {}
    for i, ann in enumerate(coco["annotations"]):
        field = f"annotations[{i}]"
        if not isinstance(ann, dict):
            raise InputError(file, field, f"expected an object, got {type(ann).__name__}")
        for key in ("image_id", "category_id", "segmentation"):
            if key not in ann:
                raise InputError(file, f"{field}.{key}", "missing required key")
        iid, cid, seg = ann["image_id"], ann["category_id"], ann["segmentation"]
        if not _hashable_id(iid) or iid not in frames:
            raise InputError(file, f"{field}.image_id", f"unknown image id {short_repr(iid)}")
        if not _hashable_id(cid) or cid not in cat_ids:
            raise InputError(file, f"{field}.category_id", f"unknown (or root) category id {short_repr(cid)}")
        key = (cat_ids[cid], iid)
        w_img, h_img = image_size[iid]
        frame = frames[iid]
        if isinstance(seg, dict):
            # size checked against the image before decoding, every run before the mask is built
            m = decode_mask(seg, file, f"{field}.segmentation", (h_img, w_img))
            if (w_img, h_img) != (frame.width, frame.height):
                m = _resample_nearest(m, frame.height, frame.width)
            rles[key] = m | rles[key] if key in rles else m  # OR-ed at once: one mask per label and image
            polys.setdefault(key, [])
            continue
        if not isinstance(seg, list):
            raise InputError(file, f"{field}.segmentation",
                             f"expected a list of polygons or an RLE object, got {type(seg).__name__}")
        clean = []
        for j, poly in enumerate(seg):
            pfield = f"{field}.segmentation[{j}]"
            clean.append(check_polygon(poly, w_img, h_img, file, pfield))
        scale = (frame.width / w_img, frame.height / h_img)
        cost[key] = cost.get(key, 0.0) + polygon_cost(clean, scale)
        if cost[key] > polygon_budget(frame.height, frame.width):
            raise InputError(file, f"{field}.segmentation",
                             f"the polygons of this label in image {iid} are {cost[key]:.0f} pixels long, more than "
                             f"{polygon_budget(frame.height, frame.width)} for a {frame.width}x{frame.height} image")
        polys.setdefault(key, []).extend(clean)

    masks: dict[tuple[int, int], dict] = {}
    for (qid, iid), plist in polys.items():
        frame = frames[iid]
        w_img, h_img = image_size[iid]
        m = polygons_to_mask(plist, frame.height, frame.width,
                             scale=(frame.width / w_img, frame.height / h_img), rasterizer=opts.rasterizer)
        if (qid, iid) in rles:
            m |= rles[(qid, iid)]
        masks[(qid, iid)] = encode_mask(m)
    if opts.missing_means == "absent":
        annotated_images = {iid for (_, iid) in polys}
        for iid in annotated_images:
            frame = frames[iid]
            for qid in cat_ids.values():
                if (qid, iid) not in masks:
                    masks[(qid, iid)] = encode_mask(np.zeros((frame.height, frame.width), dtype=bool))
    return masks


def _resample_nearest(mask: np.ndarray, height: int, width: int) -> np.ndarray:
    """(h, w) bool -> (height, width) bool, sampling the source at each target pixel centre."""
    h, w = mask.shape
    rows = np.minimum(((np.arange(height) + 0.5) * h / height).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w / width).astype(np.int64), w - 1)
    return mask[rows[:, None], cols[None, :]]


def _read_video(path: Path, aset: AnnotationSet, opts: ReleaseImportOptions) -> None:
    doc = read_json(path)
    if not isinstance(doc, dict):
        raise InputError(path, None, "expected {base_label: {time_query: [[l, r], ...]}}")
    by_text = {q.text: q for q in aset.queries}
    forms = {text_key(q.text) for q in aset.queries}
    next_id = max((q.id for q in aset.queries), default=0) + 1
    for base_text, queries in doc.items():
        if base_text not in by_text:
            raise InputError(path, base_text, f"base label {short_repr(base_text)} is not a category of the COCO file "
                                              f"(known: {sorted(by_text)[:8]})")
        base = by_text[base_text]
        if base.kind != "agnostic":
            raise InputError(path, base_text, f"{base_text!r} is itself a time query; a base must be a COCO label")
        if not isinstance(queries, dict):
            raise InputError(path, base_text, "expected {time_query: [[l, r], ...]}")
        for text, intervals in queries.items():
            field = f"{base_text}.{text}"
            check_text(text, path, field)
            if text_key(text) in forms:
                raise InputError(path, field, f"time query {text!r} repeats an existing query text (up to case, "
                                              "spaces and Unicode form)")
            forms.add(text_key(text))
            if not isinstance(intervals, list):
                raise InputError(path, field, "expected a list of [l, r] frame intervals")
            parsed = []
            for j, iv in enumerate(intervals):
                if (not isinstance(iv, list) or len(iv) != 2
                        or not all(isinstance(v, int) and not isinstance(v, bool) for v in iv)):
                    raise InputError(path, f"{field}[{j}]", f"expected [l, r] integers, got {short_repr(iv)}")
                lo, hi = iv[0] - opts.interval_base, iv[1] - opts.interval_base
                if hi > MAX_TIME_INDEX:
                    raise InputError(path, f"{field}[{j}]", f"{short_repr(iv)} reaches past time index {MAX_TIME_INDEX}")
                if lo < 0:
                    raise InputError(path, f"{field}[{j}]", f"{iv} starts before the first frame "
                                                            f"(interval_base={opts.interval_base})")
                if lo > hi:
                    raise InputError(path, f"{field}[{j}]", f"l > r in {iv} (intervals are inclusive [l, r])")
                if aset.num_time_steps is not None and hi >= aset.num_time_steps:
                    raise InputError(path, f"{field}[{j}]", f"{iv} reaches past the video's "
                                                            f"{aset.num_time_steps} frames")
                parsed.append((lo, hi))
            q = Query(id=next_id, text=text, kind="sensitive", base=base.id, intervals=parsed)
            next_id += 1
            aset.queries.append(q)
            by_text[text] = q


# ---------------------------------------------------------------------------------------------
# export
# ---------------------------------------------------------------------------------------------
def export_release(aset: AnnotationSet, out_dir: str | Path, *, frame_base: Optional[int] = None,
                   interval_base: int = 0,
                   root_category: str = "bench4d-queries", overwrite: bool = False) -> dict[str, Path]:
    """Write ``aset`` as a release ``annotations/`` folder: ``out_dir/train/_annotations.coco.json``
    and, when it has time-sensitive queries, ``out_dir/video_annotations.json``.

    Masks become exact pixel-edge polygons (:func:`annotations.polygons.mask_to_polygons`), checked
    by re-rasterising; a mask that would not survive that is written as COCO RLE (``iscrowd: 1``).
    An empty (absent) mask is written as an annotation with no polygon. Image and agnostic category
    ids are kept; ``info.bench4d`` records the scene and ``num_time_steps``. Existing files are
    replaced only with ``overwrite=True``. Returns ``{"coco": path, "video": path?}``.

    ``frame_base``: number of the first frame in the file names (1 HyperNeRF, 0 Neu3D); ``None``
    takes the ``frame_base`` recorded in ``aset.info`` by :func:`import_release`.
    """
    frame_base = _export_frame_base(aset, frame_base)
    out_dir = Path(out_dir)
    coco_path = out_dir / COCO_RELATIVE_PATH
    video_path = out_dir / VIDEO_RELATIVE_PATH
    sensitive = aset.sensitive_queries
    if not overwrite:
        for p in [coco_path] + ([video_path] if sensitive else []):
            if p.exists():
                raise InputError(p, None, "file exists; pass overwrite=True to replace it")
    coco = {"info": {"description": f"bench4d export of scene {aset.scene}",
                     "bench4d": {"scene": aset.scene, "num_time_steps": aset.num_time_steps,
                                 "frame_base": frame_base, "interval_base": interval_base}},
            "categories": _export_categories(aset, root_category), "images": _export_images(aset, frame_base),
            "annotations": _export_annotations(aset)}
    write_json(coco_path, coco, indent=None)
    written = {"coco": coco_path}
    if sensitive:
        write_text(video_path, _video_annotations_text(aset, interval_base))
        written["video"] = video_path
    return written


def _export_frame_base(aset: AnnotationSet, frame_base: Optional[int]) -> int:
    """``frame_base`` as given, else the one :func:`import_release` recorded in ``aset.info``."""
    if frame_base is None:
        frame_base = aset.info.get("frame_base")
        if not isinstance(frame_base, int) or isinstance(frame_base, bool):
            raise InputError(None, "frame_base", "not recorded in the annotation set's info: pass frame_base "
                                                 "(1 for HyperNeRF, 0 for Neu3D)")
    return frame_base


def _export_categories(aset: AnnotationSet, root_category: str) -> list[dict]:
    """COCO categories: the root (a free id) and one per time-agnostic query, ids kept."""
    agnostic = aset.agnostic_queries
    if any(q.text == root_category for q in aset.queries):
        raise InputError(None, "root_category", f"{root_category!r} is also a query text; pick another root name")
    root_id = 0 if all(q.id != 0 for q in agnostic) else max(q.id for q in agnostic) + 1
    categories = [{"id": root_id, "name": root_category, "supercategory": "none"}]
    for q in agnostic:
        cat = {"id": q.id, "name": q.text, "supercategory": root_category}
        if q.level is not None:
            cat["level"] = q.level
        categories.append(cat)
    return categories


def _export_images(aset: AnnotationSet, frame_base: int) -> list[dict]:
    """COCO images named as the release names them (``<number>_png.rf.<hash>.jpg``), one per time index."""
    images = []
    seen_numbers: dict[int, str] = {}
    for f in aset.frames:
        number = f.time_index + frame_base
        if number in seen_numbers:
            raise InputError(None, f"frames[{f.name}]",
                             f"frames {seen_numbers[number]!r} and {f.name!r} share frame number {number}: the "
                             "release format holds one camera per time index")
        seen_numbers[number] = f.name
        digest = hashlib.sha1(f"{aset.scene}/{f.name}".encode()).hexdigest()[:32]
        images.append({"id": f.id, "file_name": f"{number}_png.rf.{digest}.jpg", "width": f.width,
                       "height": f.height, "frame_name": f.name, "camera_id": str(f.camera_id)})
    return images


def _export_annotations(aset: AnnotationSet) -> list[dict]:
    """COCO annotations of every mask, in frame then query order."""
    frame_by_id = {f.id: f for f in aset.frames}
    frame_order = {f.id: i for i, f in enumerate(aset.frames)}
    query_order = {q.id: i for i, q in enumerate(aset.queries)}
    agnostic_ids = {q.id for q in aset.agnostic_queries}
    annotations = []
    for qid, fid in sorted(aset.masks, key=lambda k: (frame_order.get(k[1], 0), query_order.get(k[0], 0))):
        if fid not in frame_by_id:
            raise InputError(None, "masks", f"mask for unknown frame id {fid}")
        if qid not in agnostic_ids:
            raise InputError(None, f"masks[{qid}, {fid}]", "only time-agnostic queries own masks")
        f = frame_by_id[fid]
        m = decode_mask(aset.masks[(qid, fid)], None, f"masks[{qid}, {fid}]", (f.height, f.width))
        if m.shape != (f.height, f.width):
            raise InputError(None, f"masks[{qid}, {fid}]", f"mask is {m.shape[1]}x{m.shape[0]} but frame "
                                                           f"{f.name!r} is {f.width}x{f.height}")
        annotations.append(_export_annotation(len(annotations) + 1, fid, qid, m))
    return annotations


def _export_annotation(ann_id: int, image_id: int, category_id: int, mask: np.ndarray) -> dict:
    """One COCO annotation: exact polygons when they re-rasterise to ``mask`` within the importer's
    budget, else RLE (``iscrowd: 1``)."""
    height, width = mask.shape
    polygons = mask_to_polygons(mask)
    ann = {"id": ann_id, "image_id": image_id, "category_id": category_id, "iscrowd": 0}
    # polygons the importer would refuse as too long (e.g. checkerboard noise) are written as RLE
    if (polygon_cost(polygons) <= polygon_budget(height, width)
            and np.array_equal(polygons_to_mask(polygons, height, width), mask)):
        ann["segmentation"] = polygons
    else:  # kept so an export can never silently change a mask
        ann["segmentation"] = encode_mask(mask)
        ann["iscrowd"] = 1
    rle = encode_mask(mask)
    coco_rle = {"size": rle["size"], "counts": rle["counts"].encode("ascii")}
    ann["area"] = int(mask_utils.area(coco_rle))
    ann["bbox"] = [float(v) for v in mask_utils.toBbox(coco_rle)]
    return ann


def _video_annotations_text(aset: AnnotationSet, interval_base: int) -> str:
    """The release's ``video_annotations.json`` text: base label -> time-sensitive query -> intervals,
    one query a line."""
    video: dict[str, dict[str, list]] = {}
    for q in aset.sensitive_queries:
        base = aset.query(q.base)
        video.setdefault(base.text, {})[q.text] = [[a + interval_base, b + interval_base] for a, b in q.intervals]
    lines = []
    for base_text, queries in video.items():
        inner = ",\n".join(f"    {json.dumps(t, ensure_ascii=False)}: {json.dumps(iv)}"
                            for t, iv in queries.items())
        lines.append(f"  {json.dumps(base_text, ensure_ascii=False)}: {{\n{inner}\n  }}")
    return "{\n" + ",\n".join(lines) + "\n}\n"
