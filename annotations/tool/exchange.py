"""Import and export for the annotation tool.

Every export is written to a temporary file beside its target, **reloaded and checked** (pycocotools
reads it and every mask decodes to exactly the mask in memory; intervals match), and only then
moved over the previous export. Imports read uploaded bytes (never a path from the client); a zip
is checked for path escapes and size before any member is read, and only the JSON members the
format needs are read, into memory.
"""

from __future__ import annotations

import copy
import json
import os
import posixpath
import shutil
import tempfile
import zipfile
from pathlib import Path
from typing import Optional

import numpy as np
from pycocotools import mask as mask_utils

from benchmark.core.atomic import atomic_path
from benchmark.core.errors import InputError
from benchmark.core.scene import Scene, paper_camera
from benchmark.core.strict import check_int, check_keys, check_text, error_reason, loads, text_key, unpacking_errors

from ..format import annotation_set_from_dict, load_annotations, save_annotations
from benchmark.core.annotation import MAX_MASK_PIXELS, AnnotatedFrame, AnnotationSet, Query, decode_mask, encode_mask, normalise_intervals
from ..polygons import checked_polygons_mask
from ..release import COCO_RELATIVE_PATH, VIDEO_RELATIVE_PATH, export_release, import_release


MAX_MASK_SIDE = 16384
"""Largest mask side an imported file may declare (a decoder allocates height x width first)."""
MAX_ID = 2 ** 53
"""Largest absolute image or category id an import may give."""


def _frame_base(scene: Scene) -> int:
    """The release numbers HyperNeRF frames from 1 and everything else from 0."""
    return 1 if scene.dataset == "hypernerf" else 0


def same_content(a: AnnotationSet, b: AnnotationSet, *, intervals: bool = True, masks: bool = True) -> Optional[str]:
    """``None`` if ``a`` and ``b`` hold the same masks (by query text and frame name, bit-exact) and
    intervals (by query text); else a description of the first difference."""
    if masks:
        def keyed(s: AnnotationSet) -> dict:
            fname = {f.id: f.name for f in s.frames}
            qtext = {q.id: q.text for q in s.queries}
            return {(qtext[q], fname[f]): rle for (q, f), rle in s.masks.items()}

        ka, kb = keyed(a), keyed(b)
        if set(ka) != set(kb):
            diff = sorted(set(ka) ^ set(kb))[:3]
            return f"annotated (query, frame) pairs differ, e.g. {diff}"
        for key in ka:
            if not np.array_equal(decode_mask(ka[key]), decode_mask(kb[key])):
                return f"mask of {key} differs"
    if intervals:
        ia = {q.text: list(q.intervals) for q in a.sensitive_queries}
        ib = {q.text: list(q.intervals) for q in b.sensitive_queries}
        if ia != ib:
            return f"time intervals differ: {ia} vs {ib}"
    return None


# ---------------------------------------------------------------------------------------------
# export
# ---------------------------------------------------------------------------------------------
def coco_rle_document(aset: AnnotationSet) -> dict:
    """COCO JSON with compressed-RLE masks for the time-agnostic queries (``file_name`` = frame name)."""
    images = [{"id": f.id, "file_name": f.name, "width": f.width, "height": f.height,
               "time_index": f.time_index, "camera_id": f.camera_id} for f in aset.frames]
    categories = [{"id": q.id, "name": q.text, "supercategory": "query"} for q in aset.agnostic_queries]
    agnostic = {q.id for q in aset.agnostic_queries}
    annotations = []
    for (qid, fid), rle in sorted(aset.masks.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        if qid not in agnostic:
            continue
        m = decode_mask(rle)
        enc = encode_mask(m)
        coco = {"size": enc["size"], "counts": enc["counts"].encode("ascii")}
        annotations.append({"id": len(annotations) + 1, "image_id": fid, "category_id": qid, "segmentation": enc,
                            "area": int(mask_utils.area(coco)), "bbox": [float(v) for v in mask_utils.toBbox(coco)],
                            "iscrowd": 1})
    return {"info": {"description": f"bench4d masks of scene {aset.scene}", "scene": aset.scene,
                     "num_time_steps": aset.num_time_steps},
            "images": images, "categories": categories, "annotations": annotations}


def _check_coco_file(path: Path, aset: AnnotationSet) -> None:
    """pycocotools loads ``path`` and every annotation decodes to the in-memory mask."""
    import contextlib
    import io

    from pycocotools.coco import COCO

    with contextlib.redirect_stdout(io.StringIO()):  # COCO() prints progress lines
        coco = COCO(str(path))
    frames = {f.id: f for f in aset.frames}
    seen = set()
    for ann in coco.dataset["annotations"]:
        key = (ann["category_id"], ann["image_id"])
        seen.add(key)
        if key not in aset.masks:
            raise InputError(path, f"annotations[{ann['id']}]", "export holds a mask that is not in the set")
        f = frames[ann["image_id"]]
        got = coco.annToMask(ann).astype(bool) if ann["segmentation"] else np.zeros((f.height, f.width), bool)
        if not np.array_equal(got, decode_mask(aset.masks[key])):
            raise InputError(path, f"annotations[{ann['id']}]", "exported mask does not decode to the original")
    agnostic = {q.id for q in aset.agnostic_queries}
    missing = [k for k in aset.masks if k[0] in agnostic and k not in seen]
    if missing:
        raise InputError(path, "annotations", f"{len(missing)} masks missing from the export, e.g. {missing[0]}")


def export_set(aset: AnnotationSet, fmt: str, out_dir: Path, stem: str, scene: Scene) -> list[Path]:
    """Write ``aset`` in ``fmt`` under ``out_dir`` after checking the written files; returns them."""
    out_dir.mkdir(parents=True, exist_ok=True)
    if fmt == "project":
        target = out_dir / f"{stem}.json"
        with atomic_path(target) as tmp:
            save_annotations(aset, tmp, overwrite=True)
            back = load_annotations(tmp, scene=scene)
            problem = same_content(aset, back)
            if problem:
                raise InputError(target, None, f"export check failed: {problem}")
        return [target]
    if fmt == "coco-rle":
        target = out_dir / f"{stem}.coco-rle.json"
        with atomic_path(target) as tmp:
            tmp.write_text(json.dumps(coco_rle_document(aset)) + "\n", encoding="utf-8")
            _check_coco_file(tmp, aset)
            back = _import_coco(json.loads(tmp.read_text(encoding="utf-8")), str(tmp), scene, aset)
            problem = same_content(aset, back, intervals=False)
            if problem:
                raise InputError(target, None, f"export check failed: {problem}")
        return [target]
    if fmt == "release":
        final = out_dir / f"{stem}.release"
        stage = Path(tempfile.mkdtemp(prefix=f".{stem}.release.", dir=out_dir))
        try:
            written = export_release(aset, stage, frame_base=_frame_base(scene), overwrite=True)
            _check_coco_file(written["coco"], aset)
            back = import_release(written["coco"], written.get("video"), scene_name=aset.scene,
                                  frame_base=_frame_base(scene), num_time_steps=aset.num_time_steps)
            problem = same_content(aset, back)
            if problem:
                raise InputError(final, None, f"export check failed: {problem}")
            out = []
            for rel in (COCO_RELATIVE_PATH, VIDEO_RELATIVE_PATH):
                src, dst = stage / rel, final / rel
                if src.exists():
                    dst.parent.mkdir(parents=True, exist_ok=True)
                    os.replace(src, dst)  # same file system: atomic per file
                    out.append(dst)
                elif dst.exists():
                    dst.unlink()  # the set no longer has time-sensitive queries
            return out
        finally:
            shutil.rmtree(stage, ignore_errors=True)
    raise InputError(None, "format", f"unknown export format {fmt!r}")


# ---------------------------------------------------------------------------------------------
# import
# ---------------------------------------------------------------------------------------------
def _json(data: bytes, file: str):
    """An uploaded JSON file, parsed as strictly as a file on disk (:func:`benchmark.core.strict.loads`)."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(file, None, "not UTF-8 text") from None
    return loads(text, file)


def _frame_by_stem(scene: Scene) -> dict[str, object]:
    return {f.name: f for f in scene.frames}


def _import_coco(doc, file: str, scene: Scene, current: AnnotationSet) -> AnnotationSet:
    """A COCO file whose image ``file_name`` stems are the scene's frame names (RLE or polygons), checked as
    a file on disk is: ids bounded integers, image sizes positive and within the frame limit, query texts
    without control characters and unique, every polygon through :func:`annotations.polygons.checked_polygons_mask`
    and every RLE through :func:`benchmark.core.annotation.rle_runs` before anything rasterises or decodes it."""
    if not isinstance(doc, dict) or not all(isinstance(doc.get(k), list) for k in ("images", "categories", "annotations")):
        raise InputError(file, None, "expected a COCO object with images, categories and annotations lists")
    check_keys(doc, ("info", "licenses", "images", "categories", "annotations"), file, None)
    by_name = _frame_by_stem(scene)
    frames: dict[int, AnnotatedFrame] = {}
    source_size: dict[int, tuple[int, int]] = {}
    for i, im in enumerate(doc["images"]):
        field = f"images[{i}]"
        if not isinstance(im, dict) or "id" not in im or "file_name" not in im:
            raise InputError(file, field, "expected an object with id and file_name")
        check_keys(im, ("id", "file_name", "width", "height", "time_index", "camera_id"), file, field)
        iid = check_int(im["id"], file, f"{field}.id", -MAX_ID, MAX_ID)
        if iid in frames:
            raise InputError(file, f"{field}.id", f"duplicate image id {iid}")
        if not isinstance(im["file_name"], str):
            raise InputError(file, f"{field}.file_name", "expected a text")
        stem = Path(im["file_name"]).name
        name = stem if stem in by_name else Path(stem).stem
        if name not in by_name:
            raise InputError(file, f"{field}.file_name", f"{im['file_name']!r} names no frame of scene {scene.name!r}")
        f = by_name[name]
        size = (f.camera.width, f.camera.height)
        if "width" in im or "height" in im:  # the size the polygons were drawn at
            size = (check_int(im.get("width"), file, f"{field}.width", 1, MAX_MASK_SIDE),
                    check_int(im.get("height"), file, f"{field}.height", 1, MAX_MASK_SIDE))
            if size[0] * size[1] > MAX_MASK_PIXELS:
                raise InputError(file, f"{field}.width/height", f"{size[0]}x{size[1]} is larger than the "
                                                                f"{MAX_MASK_PIXELS} pixels any frame may have")
        source_size[iid] = size
        frames[iid] = AnnotatedFrame(id=iid, name=name, time_index=f.time_index,
                                     width=f.camera.width, height=f.camera.height, camera_id=str(f.camera_id))
    queries: dict[int, Query] = {}
    forms: dict[str, int] = {}
    for i, c in enumerate(doc["categories"]):
        field = f"categories[{i}]"
        if not isinstance(c, dict) or "id" not in c or "name" not in c:
            raise InputError(file, field, "expected an object with an int id and a name")
        check_keys(c, ("id", "name", "supercategory"), file, field)
        cid = check_int(c["id"], file, f"{field}.id", -MAX_ID, MAX_ID)
        name = check_text(c["name"], file, f"{field}.name")
        if cid in queries or text_key(name) in forms:
            raise InputError(file, field, f"duplicate category id {cid} or query text {name!r}")
        forms[text_key(name)] = cid
        queries[cid] = Query(id=cid, text=name)
    masks = {}
    for i, ann in enumerate(doc["annotations"]):
        field = f"annotations[{i}]"
        if not isinstance(ann, dict):
            raise InputError(file, field, "expected an object")
        check_keys(ann, ("id", "image_id", "category_id", "segmentation", "area", "bbox", "iscrowd"), file, field)
        iid, cid = ann.get("image_id"), ann.get("category_id")
        if isinstance(iid, bool) or isinstance(cid, bool) or iid not in frames or cid not in queries:
            raise InputError(file, field, "unknown image_id or category_id")
        f = frames[iid]
        seg = ann.get("segmentation")
        src_w, src_h = source_size[iid]
        if isinstance(seg, dict):
            from ..format import validate_rle
            from .session import check_runs

            size = seg.get("size")
            if (isinstance(size, list) and len(size) == 2
                    and all(isinstance(v, int) and not isinstance(v, bool) for v in size)):
                if not all(0 < v <= MAX_MASK_SIDE for v in size):
                    raise InputError(file, f"{field}.segmentation.size", f"expected sides in 1..{MAX_MASK_SIDE}")
                if isinstance(seg.get("counts"), list):
                    # the checks a decoder cannot be trusted with (int64 sums wrap), before it sees the runs
                    check_runs(seg["counts"], size[0], size[1], f"{field}.segmentation", file)
            rle = validate_rle(seg, file, f"{field}.segmentation")
            m = decode_mask(rle)
            if m.shape != (f.height, f.width):
                rows = np.minimum(((np.arange(f.height) + 0.5) * m.shape[0] / f.height).astype(int), m.shape[0] - 1)
                cols = np.minimum(((np.arange(f.width) + 0.5) * m.shape[1] / f.width).astype(int), m.shape[1] - 1)
                m = m[rows[:, None], cols[None, :]]
        elif isinstance(seg, list):
            # the one checked path of polygons: finite, near their image, within the budget
            m = checked_polygons_mask(seg, (src_w, src_h), f.height, f.width, file=file,
                                      field=f"{field}.segmentation")
        else:
            raise InputError(file, f"{field}.segmentation", "expected an RLE object or a list of polygons")
        key = (cid, iid)
        if key in masks:
            m = m | decode_mask(masks[key])
        masks[key] = encode_mask(m)
    aset = AnnotationSet(scene=scene.name, frames=sorted(frames.values(), key=lambda x: (x.time_index, x.name)),
                         queries=list(queries.values()), masks=masks,
                         num_time_steps=current.num_time_steps, info={"tool": "bench4d annotate"})
    _carry_sensitive(current, aset)
    return aset


def _carry_sensitive(current: AnnotationSet, new: AnnotationSet) -> None:
    """Keep the current time-sensitive queries whose base text exists in ``new`` (COCO has no time)."""
    by_text = {q.text: q for q in new.queries}
    next_id = max((q.id for q in new.queries), default=0) + 1
    for q in current.sensitive_queries:
        base = current.query(q.base)
        if base.text in by_text and q.text not in by_text:
            new.queries.append(Query(id=next_id, text=q.text, kind="sensitive", base=by_text[base.text].id,
                                     intervals=list(q.intervals), level=q.level))
            by_text[q.text] = new.queries[-1]
            next_id += 1


def _merge_video(doc, file: str, current: AnnotationSet) -> AnnotationSet:
    """``{base_label: {time_query: [[l, r], ...]}}`` merged into a copy of ``current``."""
    if not isinstance(doc, dict):
        raise InputError(file, None, "expected {base_label: {time_query: [[l, r], ...]}}")
    out = copy.deepcopy(current)
    by_text = {q.text: q for q in out.queries}
    next_id = max((q.id for q in out.queries), default=0) + 1
    last = (out.num_time_steps or 10 ** 9) - 1
    for base_text, items in doc.items():
        base = by_text.get(base_text)
        if base is None or base.kind != "agnostic":
            raise InputError(file, base_text, f"{base_text!r} is not a time-agnostic query of this set "
                                              f"(known: {sorted(q.text for q in out.agnostic_queries)[:8]})")
        if not isinstance(items, dict):
            raise InputError(file, base_text, "expected {time_query: [[l, r], ...]}")
        for text, ivs in items.items():
            field = f"{base_text}.{text}"
            if not isinstance(ivs, list) or not all(isinstance(iv, list) and len(iv) == 2 and all(
                    isinstance(v, int) and not isinstance(v, bool) for v in iv) for iv in ivs):
                raise InputError(file, field, "expected a list of [l, r] integer pairs")
            for lo, hi in ivs:
                if lo < 0 or hi < lo or hi > last:
                    raise InputError(file, field, f"[{lo}, {hi}] is not an interval inside 0..{last}")
            intervals = normalise_intervals(ivs)
            q = by_text.get(text)
            if q is None:
                q = Query(id=next_id, text=text, kind="sensitive", base=base.id)
                next_id += 1
                out.queries.append(q)
                by_text[text] = q
            elif q.kind != "sensitive" or q.base != base.id:
                raise InputError(file, field, f"{text!r} exists already with another kind or base")
            q.intervals = intervals
    return out


ZIP_METHODS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflate", zipfile.ZIP_BZIP2: "bzip2",
               zipfile.ZIP_LZMA: "lzma"}
"""Compression methods an uploaded zip's members may use (those Python's zipfile reads)."""


def _member_names(archive: zipfile.ZipFile, file: str) -> list[str]:
    """The names of the file members of an uploaded zip, once every member is found readable in principle: no
    name given twice (zipfile would silently read the last one), no encrypted member and no compression method
    zipfile lacks (which it reports as a RuntimeError or NotImplementedError on reading)."""
    seen: set[str] = set()
    for member in archive.infolist():
        # one path, however written: the archive check reads a backslash as a separator too, and "a//b" or
        # "a/./b" name the member "a/b" does
        key = posixpath.normpath(member.filename.replace("\\", "/"))
        if key in seen:
            raise InputError(file, member.filename, "appears twice in the archive (which one is meant?)")
        seen.add(key)
        if member.flag_bits & 0x1:
            raise InputError(file, member.filename, "is encrypted (upload an archive without a password)")
        if member.compress_type not in ZIP_METHODS:
            raise InputError(file, member.filename, f"uses compression method {member.compress_type}; "
                                                    f"supported: {', '.join(ZIP_METHODS.values())}")
    return [m.filename for m in archive.infolist() if not m.is_dir()]


def _read_member(archive: zipfile.ZipFile, name: str, file: str) -> bytes:
    """The unpacked bytes of member ``name`` of an uploaded zip; a damaged member (bad CRC, a compressed stream
    that does not decode, a local header that disagrees with the directory) is an :class:`InputError`."""
    try:
        return archive.read(name)
    except (*unpacking_errors(), OSError, ValueError) as err:  # bzip2 reports a damaged stream as an OSError
        raise InputError(file, name, f"cannot unpack this member (damaged archive: {error_reason(err)})") from None


def import_set(fmt: str, filename: str, data: bytes, scene: Scene, current: AnnotationSet, config) -> AnnotationSet:
    """Build the annotation set an upload describes (``current`` supplies what the format lacks)."""
    from .session import check_archive

    if fmt == "project":
        return annotation_set_from_dict(_json(data, filename), file=filename)
    if fmt == "coco-rle":
        return _import_coco(_json(data, filename), filename, scene, current)
    if fmt == "video-annotations":
        return _merge_video(_json(data, filename), filename, current)
    if fmt == "release":
        video_bytes = None
        if filename.lower().endswith(".zip") or data[:4] == b"PK\x03\x04":
            zf = check_archive(data, config, filename)
            names = _member_names(zf, filename)
            cocos = [n for n in names if n.endswith("_annotations.coco.json")]
            if not cocos:
                raise InputError(filename, None, "no '_annotations.coco.json' in the archive")
            # prefer the train split (where the release keeps its annotations)
            cocos.sort(key=lambda n: (0 if "/train/" in f"/{n}" else 1, len(n)))
            coco_bytes = _read_member(zf, cocos[0], filename)
            videos = [n for n in names if Path(n).name == "video_annotations.json"]
            if videos:
                video_bytes = _read_member(zf, sorted(videos, key=len)[0], filename)
        else:
            coco_bytes = data
        doc = _json(coco_bytes, filename)
        if video_bytes is not None:
            _json(video_bytes, "video_annotations.json")
        with tempfile.TemporaryDirectory(prefix="bench4d-import-") as tmp:
            coco_path = Path(tmp) / "_annotations.coco.json"
            coco_path.write_bytes(coco_bytes)
            video_path = None
            if video_bytes is not None:
                video_path = Path(tmp) / "video_annotations.json"
                video_path.write_bytes(video_bytes)
            images = doc.get("images") if isinstance(doc, dict) else None
            recorded = isinstance(images, list) and images and all(isinstance(i, dict) and "frame_name" in i for i in images)
            size = (scene.frames[0].camera.width, scene.frames[0].camera.height)
            aset = import_release(coco_path, video_path, scene_name=scene.name, frame_base=_frame_base(scene),
                                  target_size=None if recorded else size,
                                  frame_names=None if recorded else scene,
                                  # the release annotates one camera: the paper split's, where there are several
                                  camera_id=None if recorded else paper_camera(scene),
                                  num_time_steps=current.num_time_steps)
        aset.info["source_file"] = filename  # not the temporary path
        aset.info.pop("coco_file", None)
        aset.info.pop("video_file", None)
        if video_bytes is None:
            _carry_sensitive(current, aset)
        return aset
    raise InputError(None, "format", f"unknown import format {fmt!r}")
