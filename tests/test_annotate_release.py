"""The 4D LangSplat release's own annotation files (Roboflow COCO polygons + ``video_annotations.json``,
as Roboflow writes them: a root category, hashed ``<frame>_png.rf.<hash>.jpg`` names) open in the
tool, take an edit, and go out and back in again without loss."""

from __future__ import annotations

import base64
import io
import json
import zipfile

import numpy as np
import pytest

from annotations.format import load_annotations
from annotations.polygons import mask_to_polygons
from annotations.tool.exchange import same_content
from annotations.tool.session import AnnotationSession, mask_to_runs
from benchmark.loaders import load_scene
from benchmark.synthetic import generate


@pytest.fixture(scope="module")
def scene_and_truth(tmp_path_factory):
    scene_dir = generate("smoke", tmp_path_factory.mktemp("release") / "smoke", size=48)
    truth = load_annotations(scene_dir / "annotations.json")
    # the release annotates its video's camera: the paper split's frames, not the generated novel-view path
    paper = set(truth.info["splits"]["paper"])
    truth.frames = [f for f in truth.frames if f.name in paper]
    return load_scene(scene_dir), truth


def roboflow_zip(truth) -> bytes:
    """A release ``annotations/`` folder for the truth's box and ball, zipped as one downloads it."""
    wanted = ["box", "ball"]
    categories = [{"id": 0, "name": "objects", "supercategory": "none"}]
    categories += [{"id": k + 1, "name": t, "supercategory": "objects"} for k, t in enumerate(wanted)]
    images, anns = [], []
    for f in truth.frames:
        image_id = len(images)
        # HyperNeRF frames are numbered from 1 in the release
        images.append({"id": image_id, "file_name": f"{f.time_index + 1}_png.rf.{f.name}a1b2c3.jpg",
                       "width": f.width, "height": f.height})
        for k, text in enumerate(wanted):
            mask = truth.get_mask(truth.query(text).id, f.id)
            ys, xs = np.nonzero(mask)
            anns.append({"id": len(anns), "image_id": image_id, "category_id": k + 1, "iscrowd": 0,
                         "segmentation": mask_to_polygons(mask), "area": int(mask.sum()),
                         "bbox": [int(xs.min()), int(ys.min()), int(np.ptp(xs)) + 1, int(np.ptp(ys)) + 1]})
    coco = {"info": {"description": "Exported from roboflow.com"}, "categories": categories, "images": images,
            "annotations": anns}
    video = {"box": {"closed box": [[0, 1]], "open box": [[2, 7]]}}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("annotations/train/_annotations.coco.json", json.dumps(coco))
        zf.writestr("annotations/video_annotations.json", json.dumps(video))
    return buf.getvalue()


def _zip_export(root, files) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for f in files:
            zf.write(root / f, "annotations/" + str((root / f).relative_to(root / "exports" / "smoke.release")))
    return buf.getvalue()


def test_a_release_export_opens_edits_and_exports_back_losslessly(scene_and_truth, tmp_path):
    scene, truth = scene_and_truth
    s = AnnotationSession(scene, tmp_path / "smoke.json")
    try:
        s.import_data(s.revision, "release", "annotations.zip", base64.b64encode(roboflow_zip(truth)).decode())
        opened = load_annotations(s.path)
        assert sorted(q.text for q in opened.queries) == ["ball", "box", "closed box", "open box"]
        assert opened.query("open box").intervals == [(2, 7)]
        for f in truth.frames:  # the polygons rasterise back to the truth's pixels
            for text in ("box", "ball"):
                got = opened.get_mask(opened.query(text).id, opened.frame(f.name).id)
                assert np.array_equal(got, truth.get_mask(truth.query(text).id, f.id)), (text, f.name)
        # an edit in the tool: the ball grows a square on the first scored frame
        index = s.index_of[truth.frames[0].name]
        ball = s.mask(opened.query("ball").id, index).copy()
        ball[2:8, 2:8] = True
        s.apply(s.revision, [{"type": "mask", "query": opened.query("ball").id, "frame": index,
                              "mask": {"counts": mask_to_runs(ball)}, "made_by": "drawn"},
                             {"type": "intervals", "query": opened.query("open box").id, "intervals": [[3, 7]]}])
        edited = load_annotations(s.path)
        files = s.export("release")["files"]
        s.import_data(s.revision, "release", "back.zip", base64.b64encode(_zip_export(s.root, files)).decode())
        back = load_annotations(s.path)
        assert same_content(edited, back) is None
        assert back.query("open box").intervals == [(3, 7)]
        assert np.array_equal(back.get_mask(back.query("ball").id, back.frame(truth.frames[0].name).id), ball)
    finally:
        s.close()
