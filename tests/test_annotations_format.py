"""The annotation file format, the release importer/exporter and the DAVIS importer."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from annotations.davis import import_davis
from annotations.format import (annotation_set_to_dict, load_annotations, save_annotations,
                                validate_against_scene, validate_rle)
from benchmark.core.annotation import AnnotatedFrame, AnnotationSet, Query, decode_mask, encode_mask
from annotations.polygons import mask_to_polygons, polygons_to_mask
from annotations.release import (ReleaseImportOptions, export_release, import_release,
                                 import_release_folder)
from benchmark.core.errors import InputError
from benchmark.core.scene import Camera, Frame, Scene


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------
def random_blobs(rng: np.random.Generator, h: int, w: int, noise: float = 0.0) -> np.ndarray:
    """(h, w) bool: a few discs with holes (and islands in holes), plus optional salt noise."""
    m = np.zeros((h, w), np.uint8)
    for _ in range(int(rng.integers(1, 4))):
        c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        r = int(rng.integers(3, max(4, min(h, w) // 2)))
        cv2.circle(m, c, r, 1, -1)
        cv2.circle(m, c, max(1, r // 2), 0, -1)      # a hole
        cv2.circle(m, c, max(0, r // 5), 1, -1)      # an island inside the hole
    if noise:
        m ^= (rng.random((h, w)) < noise).astype(np.uint8)
    return m.astype(bool)


def make_set(rng: np.random.Generator, h: int = 24, w: int = 32, n_frames: int = 4) -> AnnotationSet:
    aset = AnnotationSet(scene="toy", num_time_steps=20, info={"annotator": "test", "notes": ["a", "b"]})
    for k in range(n_frames):
        aset.frames.append(AnnotatedFrame(id=10 + k, name=f"{3 * k + 1:06d}", time_index=3 * k, width=w, height=h))
    aset.queries = [Query(1, "cookie", level="whole"), Query(2, "cup", review="draft"),
                    Query(5, "cracked cookie", "sensitive", base=1, intervals=[(0, 4), (9, 19)]),
                    Query(6, "empty cup", "sensitive", base=2, intervals=[])]
    for f in aset.frames:
        aset.set_mask(1, f.id, random_blobs(rng, h, w, noise=0.02), made_by="box" if f.id != 12 else None)
        if f.id != 11:  # frame 11: "cup" not annotated
            aset.set_mask(2, f.id, np.zeros((h, w), bool) if f.id == 12 else random_blobs(rng, h, w))
    return aset


def masks_by_name(aset: AnnotationSet) -> dict[tuple[str, str], np.ndarray]:
    return {(aset.query(q).text, aset.frame(f).name): decode_mask(r) for (q, f), r in aset.masks.items()}


def make_scene(n: int = 10, w: int = 32, h: int = 24, cameras=("0",)) -> Scene:
    frames = []
    for cam in cameras:
        camera = Camera(w, h, 30.0, 30.0, w / 2, h / 2, np.eye(4))
        for t in range(n):
            name = f"{t + 1:06d}" if len(cameras) == 1 else f"{cam}_{t:04d}"
            frames.append(Frame(name=name, camera=camera, time=t / max(1, n - 1), time_index=t, split="test",
                                camera_id=cam))
    return Scene(name="toy", dataset="synthetic", frames=frames, bounds=np.array([[-1, -1, -1], [1, 1, 1]]))


# ---------------------------------------------------------------------------------------------
# project format
# ---------------------------------------------------------------------------------------------
def test_save_load_round_trip_is_exact(tmp_path: Path) -> None:
    aset = make_set(np.random.default_rng(0))
    path = save_annotations(aset, tmp_path / "toy.json")
    back = load_annotations(path)
    assert back == aset  # every field: frames, queries (+ intervals, level, review), RLEs, made_by, info, ...
    assert back.made_by and back.draft_queries() == [back.query("cup")]
    assert back.get_mask(5, 10) is not None and np.array_equal(back.get_mask(5, 10), back.get_mask(1, 10))
    assert back.get_mask(2, 11) is None  # not annotated
    assert not back.get_mask(2, 12).any()  # annotated, absent
    # saving what was loaded gives the same bytes
    save_annotations(back, tmp_path / "again.json")
    assert (tmp_path / "again.json").read_bytes() == path.read_bytes()
    doc = json.loads(path.read_text())
    absent = {(a["category_id"], a["image_id"]): a["absent"] for a in doc["annotations"]}
    assert absent[(2, 12)] is True and absent[(1, 10)] is False
    assert doc["time_segments"] == {"5": [[0, 4], [9, 19]], "6": []}


def test_save_refuses_to_overwrite_and_is_atomic(tmp_path: Path) -> None:
    aset = make_set(np.random.default_rng(1))
    path = save_annotations(aset, tmp_path / "toy.json")
    before = path.read_bytes()
    with pytest.raises(InputError, match="exists"):
        save_annotations(aset, path)
    bad = copy.deepcopy(aset)
    bad.masks[(1, 999)] = bad.masks[(1, 10)]  # unknown frame: refused before anything is written
    with pytest.raises(InputError, match="image_id"):
        save_annotations(bad, path, overwrite=True)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["toy.json"]  # no temp file left behind
    aset.queries[0].text = "biscuit"
    save_annotations(aset, path, overwrite=True)
    assert load_annotations(path).query(1).text == "biscuit"


def test_absent_may_omit_segmentation(tmp_path: Path) -> None:
    doc = annotation_set_to_dict(make_set(np.random.default_rng(2)))
    ann = next(a for a in doc["annotations"] if a["absent"])
    del ann["segmentation"], ann["area"], ann["bbox"]
    (tmp_path / "a.json").write_text(json.dumps(doc))
    back = load_annotations(tmp_path / "a.json")
    m = back.get_mask(ann["category_id"], ann["image_id"])
    assert m is not None and m.shape == (24, 32) and not m.any()


def _valid_doc() -> dict:
    return annotation_set_to_dict(make_set(np.random.default_rng(3), h=6, w=8, n_frames=3))


def _set(path: str, value):
    def mutate(doc):
        *parents, last = path.split(".")
        node = doc
        for p in parents:
            node = node[int(p)] if p.isdigit() else node[p]
        node[int(last) if last.isdigit() and isinstance(node, list) else last] = value
    return mutate


def _delete(path: str):
    def mutate(doc):
        *parents, last = path.split(".")
        node = doc
        for p in parents:
            node = node[int(p)] if p.isdigit() else node[p]
        del node[int(last) if last.isdigit() else last]
    return mutate


def _append(path: str, make):
    def mutate(doc):
        node = doc
        for p in path.split("."):
            node = node[int(p)] if p.isdigit() else node[p]
        node.append(make(doc))
    return mutate


BAD_DOCS = [
    # (case id, mutation, field the error must name)
    ("missing-format", _delete("format"), "format"),
    ("wrong-format", _set("format", "coco"), "format"),
    ("missing-version", _delete("version"), "version"),
    ("wrong-version", _set("version", 2), "version"),
    ("version-as-string", _set("version", "1"), "version"),
    ("missing-scene", _delete("scene"), "scene"),
    ("missing-num-time-steps", _delete("num_time_steps"), "num_time_steps"),
    ("zero-num-time-steps", _set("num_time_steps", 0), "num_time_steps"),
    ("missing-images", _delete("images"), "images"),
    ("images-not-list", _set("images", {}), "images"),
    ("missing-categories", _delete("categories"), "categories"),
    ("missing-annotations", _delete("annotations"), "annotations"),
    ("info-not-object", _set("info", []), "info"),
    ("image-missing-id", _delete("images.0.id"), "images[0].id"),
    ("image-missing-width", _delete("images.1.width"), "images[1].width"),
    ("image-zero-height", _set("images.0.height", 0), "images[0].height"),
    ("image-float-width", _set("images.0.width", 8.0), "images[0].width"),
    ("image-empty-name", _set("images.0.file_name", ""), "images[0].file_name"),
    ("duplicate-image-id", _set("images.1.id", 10), "images[1].id"),
    ("duplicate-frame-name", _set("images.1.file_name", "000001"), "images[1].file_name"),
    ("time-index-out-of-range", _set("images.2.time_index", 20), "images[2].time_index"),
    ("negative-time-index", _set("images.2.time_index", -1), "images[2].time_index"),
    ("category-missing-name", _delete("categories.0.name"), "categories[0].name"),
    ("empty-category-name", _set("categories.1.name", "  "), "categories[1].name"),
    ("duplicate-category-name", _set("categories.1.name", "cookie"), "categories[1].name"),
    ("duplicate-category-id", _set("categories.1.id", 1), "categories[1].id"),
    ("unknown-kind", _set("categories.0.kind", "temporal"), "categories[0].kind"),
    ("sensitive-without-base", _delete("categories.2.base"), "categories[2].base"),
    ("base-unknown", _set("categories.2.base", 42), "categories[2].base"),
    ("base-not-agnostic", _set("categories.2.base", 6), "categories[2].base"),
    ("agnostic-with-base", _set("categories.1.base", 1), "categories[1].base"),
    ("annotation-unknown-image", _set("annotations.0.image_id", 77), "annotations[0].image_id"),
    ("annotation-unknown-category", _set("annotations.0.category_id", 77), "annotations[0].category_id"),
    ("annotation-on-sensitive", _set("annotations.0.category_id", 5), "annotations[0].category_id"),
    ("duplicate-annotation-id", _set("annotations.1.id", 1), "annotations[1].id"),
    ("second-mask-same-pair", _append("annotations", lambda d: {**d["annotations"][0], "id": 999}),
     "annotations["),
    ("mask-size-differs", _set("annotations.0.segmentation.size", [6, 9]), "annotations[0].segmentation.size"),
    ("rle-size-malformed", _set("annotations.0.segmentation.size", [6]), "annotations[0].segmentation.size"),
    ("rle-missing-counts", _delete("annotations.0.segmentation.counts"), "annotations[0].segmentation.counts"),
    ("rle-bad-characters", _set("annotations.0.segmentation.counts", "~~~"), "annotations[0].segmentation.counts"),
    ("rle-truncated", _set("annotations.0.segmentation.counts", "0`"), "annotations[0].segmentation.counts"),
    ("rle-wrong-pixel-count", _set("annotations.0.segmentation.counts", "02"), "annotations[0].segmentation.counts"),
    ("rle-list-wrong-sum", _set("annotations.0.segmentation.counts", [3, 4]), "annotations[0].segmentation.counts"),
    ("rle-list-negative", _set("annotations.0.segmentation.counts", [50, -2]), "annotations[0].segmentation.counts"),
    ("rle-not-object", _set("annotations.0.segmentation", [[0, 0, 1, 0, 1, 1]]), "annotations[0].segmentation"),
    ("segmentation-missing", _delete("annotations.0.segmentation"), "annotations[0].segmentation"),
    ("absent-disagrees", _set("annotations.0.absent", True), "annotations[0].absent"),
    ("area-disagrees", _set("annotations.0.area", 123456), "annotations[0].area"),
    ("bbox-malformed", _set("annotations.0.bbox", [1, 2]), "annotations[0].bbox"),
    ("segments-not-object", _set("time_segments", [[0, 1]]), "time_segments"),
    ("segment-l-greater-r", _set("time_segments.5", [[4, 2]]), "time_segments.5[0]"),
    ("segment-negative", _set("time_segments.5", [[-1, 2]]), "time_segments.5[0]"),
    ("segment-past-end", _set("time_segments.5", [[3, 20]]), "time_segments.5[0]"),
    ("segment-not-pair", _set("time_segments.5", [[1, 2, 3]]), "time_segments.5[0]"),
    ("segment-unknown-category", _set("time_segments.99", [[0, 1]]), "time_segments.99"),
    ("segment-on-agnostic", _set("time_segments.1", [[0, 1]]), "time_segments.1"),
    ("segment-key-not-id", _set("time_segments.abc", [[0, 1]]), "time_segments.abc"),
    ("made-by-unknown", _set("annotations.0.made_by", "magic"), "annotations[0].made_by"),
    ("made-by-not-string", _set("annotations.1.made_by", 3), "annotations[1].made_by"),
    ("review-unknown", _set("categories.0.review", "approved"), "categories[0].review"),
    ("review-not-string", _set("categories.1.review", True), "categories[1].review"),
    # the older place of the notes: info.made_by = {category id: {frame name: how}}
    ("old-made-by-not-object", _set("info.made_by", []), "info.made_by"),
    ("old-made-by-unknown-category", _set("info.made_by", {"77": {}}), "info.made_by.77"),
    ("old-made-by-frame-not-object", _set("info.made_by", {"1": "box"}), "info.made_by.1"),
    ("old-made-by-unknown-frame", _set("info.made_by", {"1": {"nope": "box"}}), "info.made_by.1.nope"),
    ("old-made-by-bad-value", _set("info.made_by", {"1": {"000001": "magic"}}), "info.made_by.1.000001"),
    ("old-made-by-not-annotated", _set("info.made_by", {"2": {"000004": "box"}}), "info.made_by.2.000004"),
    ("old-made-by-disagrees", _set("info.made_by", {"1": {"000001": "drawn"}}), "info.made_by.1.000001"),
]


@pytest.mark.parametrize("mutate, field", [(m, f) for _, m, f in BAD_DOCS], ids=[c for c, _, _ in BAD_DOCS])
def test_bad_files_name_file_and_field(tmp_path: Path, mutate, field: str) -> None:
    doc = _valid_doc()
    load_annotations_from(doc, tmp_path)  # the unmutated file is valid
    mutate(doc)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        load_annotations(path)
    assert err.value.file == str(path)
    assert err.value.field is not None and err.value.field.startswith(field), (err.value.field, str(err.value))
    assert str(path) in str(err.value) and field in str(err.value)


def test_provenance_and_review_are_optional_and_the_older_notes_move_onto_the_masks(tmp_path: Path) -> None:
    aset = make_set(np.random.default_rng(4), h=6, w=8, n_frames=3)
    doc = annotation_set_to_dict(aset)
    assert [a.get("made_by") for a in doc["annotations"] if a["category_id"] == 1] == ["box", "box", None]
    assert [c.get("review") for c in doc["categories"]] == [None, "draft", None, None]
    for ann in doc["annotations"]:
        ann.pop("made_by", None)
    for cat in doc["categories"]:
        cat.pop("review", None)
    plain = load_annotations_from(doc, tmp_path)  # a file without them loads as before
    assert plain.made_by == {} and plain.draft_queries() == [] and plain.masks == aset.masks
    doc["info"]["made_by"] = {"1": {"000001": "box", "000004": "box"}}
    old = load_annotations_from(doc, tmp_path)
    assert old.made_by == aset.made_by and "made_by" not in old.info
    assert doc["info"]["made_by"]  # the parsed document is left as it was
    save_annotations(old, tmp_path / "again.json")
    again = json.loads((tmp_path / "again.json").read_text())
    assert "made_by" not in again["info"] and load_annotations(tmp_path / "again.json").made_by == aset.made_by


def test_the_writer_refuses_notes_it_cannot_keep() -> None:
    aset = make_set(np.random.default_rng(5), h=6, w=8, n_frames=3)
    orphan = copy.deepcopy(aset)
    orphan.made_by[(2, 11)] = "box"  # "cup" is not annotated on frame 11
    with pytest.raises(InputError, match=r"made_by\[2, 11\]"):
        annotation_set_to_dict(orphan)
    unknown = copy.deepcopy(aset)
    unknown.made_by[(1, 10)] = "magic"
    with pytest.raises(InputError, match="made_by"):
        annotation_set_to_dict(unknown)
    with pytest.raises(ValueError, match="magic"):
        aset.set_mask(1, 10, np.zeros((6, 8), bool), made_by="magic")
    aset.set_mask(1, 10, np.zeros((6, 8), bool))  # a replaced mask that does not say forgets the note
    assert (1, 10) not in aset.made_by and (1, 11) in aset.made_by
    aset.set_mask(1, 11, None)
    assert (1, 11) not in aset.made_by and (1, 11) not in aset.masks


def load_annotations_from(doc: dict, tmp_path: Path) -> AnnotationSet:
    path = tmp_path / "good.json"
    path.write_text(json.dumps(doc))
    return load_annotations(path)


def test_not_json_and_missing_file(tmp_path: Path) -> None:
    (tmp_path / "x.json").write_text("{not json")
    with pytest.raises(InputError, match="x.json"):
        load_annotations(tmp_path / "x.json")
    with pytest.raises(InputError, match="not found"):
        load_annotations(tmp_path / "nope.json")
    (tmp_path / "list.json").write_text("[]")
    with pytest.raises(InputError, match="top level"):
        load_annotations(tmp_path / "list.json")


def test_validate_rle_reads_uncompressed_and_matches_pycocotools() -> None:
    rng = np.random.default_rng(4)
    for _ in range(50):
        h, w = (int(v) for v in rng.integers(1, 30, 2))
        m = rng.random((h, w)) < rng.random()
        flat = m.T.ravel()
        edges = np.flatnonzero(np.diff(flat.astype(np.int8))) + 1
        runs = np.diff(np.concatenate([[0], edges, [flat.size]])).tolist()
        if flat[0]:
            runs = [0] + runs
        assert validate_rle({"size": [h, w], "counts": runs}, None, "x") == encode_mask(m)
        assert validate_rle(encode_mask(m), None, "x", (h, w)) == encode_mask(m)


def test_validate_against_scene(tmp_path: Path) -> None:
    scene = make_scene(n=10)
    aset = AnnotationSet("toy", frames=[AnnotatedFrame(1, "000003", 2, 32, 24)],
                         queries=[Query(1, "ball"), Query(2, "moving ball", "sensitive", 1, [(0, 9)])],
                         num_time_steps=10)
    aset.set_mask(1, 1, np.ones((24, 32), bool))
    validate_against_scene(aset, scene)
    path = save_annotations(aset, tmp_path / "ok.json")
    assert load_annotations(path, scene=scene) == aset

    cases = [
        ("images[0].file_name", lambda a: setattr(a.frames[0], "name", "999999")),
        ("images[0].time_index", lambda a: setattr(a.frames[0], "time_index", 3)),
        ("images[0].camera_id", lambda a: setattr(a.frames[0], "camera_id", "cam01")),
        ("images[0].width/height", lambda a: setattr(a.frames[0], "width", 64)),
        ("num_time_steps", lambda a: setattr(a, "num_time_steps", 5)),
        ("time_segments.2[0]", lambda a: setattr(a.queries[1], "intervals", [(0, 12)])),
    ]
    for field, mutate in cases:
        bad = copy.deepcopy(aset)
        mutate(bad)
        with pytest.raises(InputError) as err:
            validate_against_scene(bad, scene, file=path)
        assert err.value.field == field and str(path) in str(err.value)


# ---------------------------------------------------------------------------------------------
# polygons
# ---------------------------------------------------------------------------------------------
def test_polygon_pixel_centre_convention() -> None:
    # a 2x2 square on pixel edges covers exactly those 4 pixels
    m = polygons_to_mask([[1, 1, 3, 1, 3, 3, 1, 3]], 5, 5)
    expected = np.zeros((5, 5), bool)
    expected[1:3, 1:3] = True
    assert np.array_equal(m, expected)
    # triangle (0,0)-(4,0)-(0,4): pixel (i, j) is inside iff its centre is, i.e. i + j < 3
    tri = polygons_to_mask([[0, 0, 4, 0, 0, 4]], 5, 5)
    i, j = np.mgrid[:5, :5]
    assert np.array_equal(tri, (i + 0.5) + (j + 0.5) < 4)
    # the release's truncating cv2.fillPoly includes boundary pixels: a different, larger mask
    assert polygons_to_mask([[1, 1, 3, 1, 3, 3, 1, 3]], 5, 5, rasterizer="release_cv2").sum() == 9


def test_mask_to_polygons_is_exact_on_random_blobs() -> None:
    rng = np.random.default_rng(5)
    for k in range(120):
        h, w = (int(v) for v in rng.integers(1, 48, 2))
        m = random_blobs(rng, h, w, noise=0.0 if k % 3 else 0.08)
        if k == 0:
            m = np.indices((h, w)).sum(0) % 2 == 0  # checkerboard: every vertex a pinch point
        if k == 1:
            m = np.ones((h, w), bool)
        polys = mask_to_polygons(m)
        assert np.array_equal(polygons_to_mask(polys, h, w), m), k
        assert all(float(v).is_integer() for p in polys for v in p)
    assert mask_to_polygons(np.zeros((4, 4), bool)) == []


# ---------------------------------------------------------------------------------------------
# release (Roboflow COCO + video_annotations.json)
# ---------------------------------------------------------------------------------------------
def roboflow_doc() -> dict:
    """A small hand-written export in Roboflow's shape: root category, 1-based frames, polygons."""
    return {
        "info": {"description": "Exported from roboflow.com"},
        "categories": [{"id": 0, "name": "objects-x1", "supercategory": "none"},
                       {"id": 1, "name": "cookie", "supercategory": "objects-x1"},
                       {"id": 2, "name": "cup", "supercategory": "objects-x1"}],
        "images": [{"id": 0, "file_name": "1_png.rf.aaa.jpg", "width": 8, "height": 6},
                   {"id": 1, "file_name": "5_png.rf.bbb.jpg", "width": 8, "height": 6}],
        "annotations": [
            # two polygons in ONE annotation: the second must not be dropped
            {"id": 0, "image_id": 0, "category_id": 1, "iscrowd": 0, "bbox": [0, 0, 8, 6], "area": 8,
             "segmentation": [[0, 0, 2, 0, 2, 2, 0, 2], [6, 4, 8, 4, 8, 6, 6, 6]]},
            # a second annotation of the same label in the same image: OR-ed
            {"id": 1, "image_id": 0, "category_id": 1, "iscrowd": 0, "bbox": [3, 0, 1, 1], "area": 1,
             "segmentation": [[3, 0, 4, 0, 4, 1, 3, 1]]},
            {"id": 2, "image_id": 1, "category_id": 2, "iscrowd": 0, "bbox": [0, 0, 8, 6], "area": 48,
             "segmentation": [[0, 0, 8, 0, 8, 6, 0, 6]]},
        ],
    }


def write_release(tmp_path: Path, coco: dict, video: dict | None = None) -> Path:
    folder = tmp_path / "annotations"
    (folder / "train").mkdir(parents=True)
    (folder / "train" / "_annotations.coco.json").write_text(json.dumps(coco))
    if video is not None:
        (folder / "video_annotations.json").write_text(json.dumps(video))
    return folder


def test_import_roboflow_ors_every_polygon_and_drops_root(tmp_path: Path) -> None:
    folder = write_release(tmp_path, roboflow_doc(), {"cookie": {"cracked cookie": [[2, 3], [4, 4]]}})
    aset = import_release_folder(folder, scene_name="toy", frame_base=1)
    assert [q.text for q in aset.agnostic_queries] == ["cookie", "cup"]  # root "objects-x1" dropped
    assert [(f.name, f.time_index) for f in aset.frames] == [("000001", 0), ("000005", 4)]
    cookie = aset.get_mask(1, 0)
    expected = np.zeros((6, 8), bool)
    expected[0:2, 0:2] = True   # first polygon
    expected[4:6, 6:8] = True   # second polygon of the same annotation (the release drops it)
    expected[0, 3] = True       # second annotation of the same label
    assert np.array_equal(cookie, expected)
    assert aset.get_mask(2, 0) is None  # cup not annotated on frame 1
    assert aset.get_mask(2, 1).all()
    cracked = aset.query("cracked cookie")
    assert cracked.kind == "sensitive" and cracked.base == 1 and cracked.intervals == [(2, 3), (4, 4)]
    assert np.array_equal(aset.get_mask(cracked.id, 0), cookie)  # inherits the base's mask


def test_import_frame_base_target_size_and_missing_means(tmp_path: Path) -> None:
    folder = write_release(tmp_path, roboflow_doc())
    coco = folder / "train" / "_annotations.coco.json"
    neu = import_release(coco, scene_name="toy", frame_base=0, frame_names="cam00_{time_index:04d}",
                         camera_id="cam00", target_size=(16, 12))
    assert [(f.name, f.time_index, f.camera_id, f.width, f.height) for f in neu.frames] == [
        ("cam00_0001", 1, "cam00", 16, 12), ("cam00_0005", 5, "cam00", 16, 12)]
    big = neu.get_mask(1, 0)
    assert big.shape == (12, 16) and big[0:4, 0:4].all() and big[8:12, 12:16].all() and big.sum() == 16 * 2 + 4
    absent = import_release(coco, scene_name="toy", frame_base=1,
                            options=ReleaseImportOptions(missing_means="absent"))
    assert absent.get_mask(2, 0) is not None and not absent.get_mask(2, 0).any()
    assert absent.get_mask(1, 1) is not None and not absent.get_mask(1, 1).any()


def test_import_with_scene_resolves_names_sizes_and_checks(tmp_path: Path) -> None:
    folder = write_release(tmp_path, roboflow_doc())
    coco = folder / "train" / "_annotations.coco.json"
    scene = make_scene(n=10, w=16, h=12)
    aset = import_release(coco, scene_name="toy", frame_base=1, frame_names=scene)
    assert [f.name for f in aset.frames] == ["000001", "000005"] and aset.num_time_steps == 10
    assert aset.get_mask(1, 0).shape == (12, 16)
    multi = make_scene(n=10, w=8, h=6, cameras=("cam00", "cam01"))
    with pytest.raises(InputError, match="camera_id"):
        import_release(coco, scene_name="toy", frame_base=0, frame_names=multi)
    aset = import_release(coco, scene_name="toy", frame_base=0, frame_names=multi, camera_id="cam00")
    assert [f.name for f in aset.frames] == ["cam00_0001", "cam00_0005"]
    short = make_scene(n=3, w=8, h=6)
    with pytest.raises(InputError, match="images\\[1\\].file_name"):
        import_release(coco, scene_name="toy", frame_base=1, frame_names=short)


RELEASE_BAD = [
    ("odd-coordinates", lambda c, v: c["annotations"][0]["segmentation"].append([1, 2, 3]),
     "coco", "annotations[0].segmentation[2]"),
    ("non-number", lambda c, v: c["annotations"][0]["segmentation"].append([1, "a", 3, 4, 5, 6]),
     "coco", "annotations[0].segmentation[2]"),
    ("unknown-image", lambda c, v: c["annotations"][0].update(image_id=9), "coco", "annotations[0].image_id"),
    ("unknown-category", lambda c, v: c["annotations"][0].update(category_id=7),
     "coco", "annotations[0].category_id"),
    ("bad-file-name", lambda c, v: c["images"][0].update(file_name="frame_png.jpg"), "coco", "images[0].file_name"),
    ("frame-below-base", lambda c, v: c["images"][0].update(file_name="0_png.rf.a.jpg"),
     "coco", "images[0].file_name"),
    ("duplicate-frame", lambda c, v: c["images"][1].update(file_name="1_png.rf.zzz.jpg"),
     "coco", "images[1].file_name"),
    ("duplicate-name", lambda c, v: c["categories"][2].update(name="cookie"), "coco", "categories[2].name"),
    ("missing-images", lambda c, v: c.pop("images"), "coco", "images"),
    ("rle-wrong-size", lambda c, v: c["annotations"][2].update(segmentation=encode_mask(np.ones((5, 8), bool))),
     "coco", "annotations[2].segmentation.size"),
    ("unknown-base", lambda c, v: v.update(plate={"empty plate": [[0, 1]]}), "video", "plate"),
    ("l-greater-r", lambda c, v: v["cookie"].update({"cracked cookie": [[3, 1]]}), "video", "cookie.cracked cookie[0]"),
    ("time-query-repeats-label", lambda c, v: v["cookie"].update({"cup": [[0, 1]]}), "video", "cookie.cup"),
]


@pytest.mark.parametrize("mutate, which, field", [(m, w, f) for _, m, w, f in RELEASE_BAD],
                         ids=[c for c, *_ in RELEASE_BAD])
def test_release_bad_inputs(tmp_path: Path, mutate, which: str, field: str) -> None:
    coco, video = roboflow_doc(), {"cookie": {"cracked cookie": [[0, 2]]}}
    mutate(coco, video)
    folder = write_release(tmp_path, coco, video)
    with pytest.raises(InputError) as err:
        import_release_folder(folder, scene_name="toy", frame_base=1)
    path = folder / ("train/_annotations.coco.json" if which == "coco" else "video_annotations.json")
    assert err.value.file == str(path) and err.value.field == field, str(err.value)


def test_export_import_round_trip_is_exact(tmp_path: Path) -> None:
    aset = make_set(np.random.default_rng(6), h=40, w=56, n_frames=5)
    aset.frames[1].camera_id = "cam00"
    written = export_release(aset, tmp_path / "annotations", frame_base=1)
    assert set(written) == {"coco", "video"}
    coco = json.loads(written["coco"].read_text())
    assert all(isinstance(a["segmentation"], list) for a in coco["annotations"])  # real polygons, no RLE
    back = import_release_folder(tmp_path / "annotations", scene_name="toy", frame_base=1)
    want, got = masks_by_name(aset), masks_by_name(back)
    assert want.keys() == got.keys()  # same annotated pairs, absent ones included
    for key, m in want.items():
        inter, union = np.logical_and(m, got[key]).sum(), np.logical_or(m, got[key]).sum()
        assert union == 0 and not got[key].any() or inter / union == 1.0, key
    def described(s: AnnotationSet) -> list:
        return [(q.text, q.kind, q.intervals, q.level) for q in s.queries]

    assert described(back) == described(aset)
    assert [(f.id, f.name, f.time_index, f.camera_id, f.width, f.height) for f in back.frames] == \
        [(f.id, f.name, f.time_index, f.camera_id, f.width, f.height) for f in aset.frames]
    assert back.num_time_steps == aset.num_time_steps
    # and the time queries map to the same base text
    for q in back.sensitive_queries:
        assert back.query(q.base).text == aset.query(aset.query(q.text).base).text
    # the release's own reader only sees the first polygon; multi-component masks do have several
    assert any(len(a["segmentation"]) > 1 for a in coco["annotations"])


def test_export_refuses_to_overwrite(tmp_path: Path) -> None:
    aset = make_set(np.random.default_rng(7))
    export_release(aset, tmp_path, frame_base=0)
    before = (tmp_path / "train" / "_annotations.coco.json").read_bytes()
    aset.queries[0].text = "biscuit"
    with pytest.raises(InputError, match="exists"):
        export_release(aset, tmp_path, frame_base=0)
    assert (tmp_path / "train" / "_annotations.coco.json").read_bytes() == before
    export_release(aset, tmp_path, frame_base=0, overwrite=True)
    back = import_release_folder(tmp_path, scene_name="toy", frame_base=0)
    assert back.query(1).text == "biscuit"
    with pytest.raises(InputError, match="frame_base"):
        export_release(aset, tmp_path / "other")  # a hand-made set: the file numbering must be given
    export_release(back, tmp_path / "again")    # an imported set remembers its frame_base
    assert [f.time_index for f in import_release_folder(tmp_path / "again", scene_name="toy",
                                                        frame_base=0).frames] == [f.time_index for f in back.frames]


# ---------------------------------------------------------------------------------------------
# DAVIS-style indexed PNGs
# ---------------------------------------------------------------------------------------------
def test_import_davis(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    ids = []
    for t in range(3):
        arr = np.zeros((10, 12), np.uint8)
        arr[1:4, 1:5] = 1
        if t != 1:
            arr[6:9, 6:10] = 2  # object 2 absent at t = 1
        arr[0, 11] = 3          # object 3 is unmapped
        arr[9, 0] = 255         # void
        arr[5, 5] = 4           # object 4 maps to the same text as 1
        img = Image.fromarray(arr, mode="P")
        img.putpalette(list(rng.integers(0, 256, 768).astype(np.uint8)))
        img.save(tmp_path / f"{t:05d}.png")
        ids.append(arr)
    aset = import_davis(tmp_path, {1: "cookie", 2: "cup", 4: "cookie"}, scene_name="toy",
                        sensitive={"full cup": ("cup", [[0, 0], [2, 2]])})
    assert [(f.name, f.time_index) for f in aset.frames] == [("00000", 0), ("00001", 1), ("00002", 2)]
    cookie, cup = aset.query("cookie"), aset.query("cup")
    for f, arr in zip(aset.frames, ids):
        assert np.array_equal(aset.get_mask(cookie.id, f.id), (arr == 1) | (arr == 4))
        assert np.array_equal(aset.get_mask(cup.id, f.id), arr == 2)
    assert not aset.get_mask(cup.id, 2).any()  # absent, but annotated
    assert aset.info["unmapped_values"] == [3]
    full = aset.query("full cup")
    assert full.base == cup.id and full.intervals == [(0, 0), (2, 2)]
    # the result is a valid project file
    assert load_annotations(save_annotations(aset, tmp_path / "out" / "toy.json")) == aset

    Image.fromarray(np.zeros((10, 12, 3), np.uint8)).save(tmp_path / "00003.png")
    with pytest.raises(InputError, match="00003.png: mode"):
        import_davis(tmp_path, {1: "cookie"}, scene_name="toy")
    with pytest.raises(InputError, match="labels"):
        import_davis(tmp_path, {0: "background"}, scene_name="toy")
