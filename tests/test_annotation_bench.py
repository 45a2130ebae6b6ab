"""The simulated annotator: its clicks, its measurements, and what it leaves in the annotation file,
through the tool's real server on a generated scene with exact truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from annotations.assist import GrabCutSegmenter, PromptedSamConfig, PromptedSamSegmenter
from conftest import BoxSamPredictor
from annotations.format import load_annotations
from benchmark.commands.annotate_bench import tool_launcher
from benchmark.studies import annotation_bench as bench
from benchmark.synthetic import generate


def test_the_click_goes_to_the_centre_of_the_largest_error_region():
    truth = np.zeros((40, 60), bool)
    truth[5:35, 5:45] = True
    pred = truth.copy()
    pred[5:35, 5:25] = False  # a missed region 30 tall, 20 wide: its centre line is x = 15
    pred[36:39, 50:53] = True  # a small false region
    x, y, label = bench.corrective_click(pred, truth)
    assert label == 1 and 13 <= x <= 17 and 14 <= y <= 26
    pred = truth.copy()
    pred[0:40, 46:60] = True  # a false strip 40 x 14 touching the border, larger than any miss
    pred[10:12, 10:12] = False
    x, y, label = bench.corrective_click(pred, truth)
    assert label == 0 and 50 <= x <= 56  # the border counts as the region's edge
    assert bench.corrective_click(truth, truth) is None


def test_one_pixel_iou_is_the_lower_of_erosion_and_dilation():
    square = np.zeros((20, 20), bool)
    square[5:15, 5:15] = True  # 100 px; eroded 64, dilated 144
    assert bench.one_pixel_iou(square) == pytest.approx(0.64)
    big = np.zeros((200, 200), bool)
    big[20:180, 20:180] = True
    assert bench.one_pixel_iou(big) == pytest.approx(158 ** 2 / 160 ** 2)
    assert bench.one_pixel_iou(np.zeros((4, 4), bool)) is None


def test_noc_counts_interactions_to_the_threshold_and_caps():
    log = bench.FrameLog("f", [0.7, 0.86, 0.88, 0.93], [0.0] * 4, "clicks")
    assert log.noc(0.85, 20) == 2 and log.noc(0.90, 20) == 4 and log.noc(0.95, 20) == 20


def test_boundary_error_is_the_worst_boundary_in_frames():
    assert bench.boundary_error([(3, 10)], [(4, 10)]) == 1
    assert bench.boundary_error([(3, 10), (20, 22)], [(3, 10), (20, 25)]) == 3
    assert bench.boundary_error([(3, 10)], [(3, 10), (20, 25)]) is None


def test_page_runs_round_trip():
    rng = np.random.default_rng(0)
    for shape in [(7, 5), (1, 1), (16, 9)]:
        m = rng.random(shape) > 0.5
        assert np.array_equal(bench.runs_to_mask(bench.mask_to_runs(m), *shape), m)


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    base = tmp_path_factory.mktemp("bench")
    scene_dir = generate("smoke", base / "smoke", size=48)
    config = bench.BenchConfig(max_interactions=6, propagation_frames=5)
    segmenters = {"grabcut": GrabCutSegmenter(),
                  "sam": PromptedSamSegmenter(PromptedSamConfig(memory_cache=4), predictor=BoxSamPredictor())}
    truth = bench.synthetic_truth(scene_dir)
    result = bench.bench_scene(truth, tool_launcher(segmenters, config), base / "work", ["grabcut", "sam"], config)
    return base, truth, config, result


def test_the_bench_measures_both_backends_and_both_workflows(smoke):
    base, truth, config, result = smoke
    summary = bench.summarise([result], config)
    rows = {r["backend"]: r for r in summary["rows"]}
    assert set(rows) == {"grabcut", "sam"}
    for r in rows.values():
        assert r["frames"] > 0 and 1 <= r["noc90"] <= config.max_interactions
        assert r["human_s_per_frame_every"] > 0 and r["human_s_per_frame_propagation"] > 0
    # the box-only stand-in cannot follow the object's outline as GrabCut does
    assert rows["grabcut"]["final_iou"] > rows["sam"]["final_iou"]
    paths = bench.write([result], config, base / "report")
    text = paths[1].read_text()
    assert "NoC@90" in text and "Papadopoulos" in text and "smoke" in text
    tolerance = result["one_pixel_iou"]  # every mask query's, from the truth of the scored frames
    assert set(tolerance) == {q.text for q in truth.queries if q.kind == "agnostic"} - {
        q.text for q in truth.queries if q.kind == "agnostic"
        and all(m is None or not m.any() for m in (truth.mask(q.text, f) for f in truth.scored_frames))}
    # a mask of a few pixels (the smoke box's knob at 48 px) erodes to nothing: 0
    assert all(0 <= v < 1 for v in tolerance.values()) and "one-pixel IoU >= 0.9" in text


def test_intervals_are_marked_within_one_frame_of_the_truth(smoke):
    _, truth, _, result = smoke
    sensitive = [q for q in truth.queries if q.kind == "sensitive"]
    assert len(result["intervals"]) == len(sensitive) > 0
    assert all(r["boundary_error"] is not None and r["boundary_error"] <= 1 for r in result["intervals"])


def test_the_saved_masks_are_the_annotators_and_say_how_they_were_made(smoke):
    base, truth, config, result = smoke
    path = base / "work" / "smoke.every-frame.grabcut.json"
    aset = load_annotations(path)
    info = aset.info
    assert info["annotator"] == "simulated" and info["protocol"]["target_iou"] == config.target_iou
    logs = result["backends"]["grabcut"]["every_frame"]
    for text, frames in logs.items():
        q = aset.query(text)
        for f in frames:
            mask = aset.get_mask(q.id, aset.frame(f["frame"]).id)
            assert abs(bench.iou(mask, truth.mask(text, f["frame"])) - f["ious"][-1]) < 1e-3
            assert aset.made_by[(q.id, aset.frame(f["frame"]).id)] == f["made_by"]
    # the file is still plain JSON the format reads; made_by is optional
    doc = json.loads(path.read_text())
    for ann in doc["annotations"]:
        del ann["made_by"]
    path.write_text(json.dumps(doc))
    assert load_annotations(path).masks


def test_propagation_curve_covers_the_asked_frames(smoke):
    _, _, config, result = smoke
    curve = result["propagation_curve"]
    assert curve and all(len(c["ious"]) <= config.propagation_frames for c in curve)
    assert max(c["ious"][0] for c in curve) > 0.8  # one frame on: the propagation follows the object


def test_the_command_writes_the_report_and_refuses_unknown_backends(tmp_path, capsys):
    from benchmark.cli import main

    out = tmp_path / "report"
    assert main(["annotate-bench", "--backends", "magic", "--presets", "none", "--dnerf", "", "--out", str(out)]) == 2
    assert "--backends" in capsys.readouterr().err
    assert main(["annotate-bench", "--presets", "smoke", "--size", "48", "--dnerf", "", "--work", str(tmp_path / "w"),
                 "--out", str(out)]) == 0
    doc = json.loads((out / "annotation_bench.json").read_text())
    assert [r["scene"] for r in doc["scenes"]] == ["smoke"] and doc["human_seconds"]["box"] == bench.BOX_SECONDS
    assert "| smoke | grabcut |" in (out / "annotation_bench.md").read_text()


def test_truth_colours_paint_one_flat_distinct_colour_per_truth_region(tmp_path):
    import cv2

    from benchmark.core.truth import load_truth

    scene_dir = generate("smoke", tmp_path / "smoke", size=32, frames=6)
    regions = bench.paint_truth_regions(scene_dir)
    truth = load_truth(scene_dir)
    colour_of: dict = {}
    for name, frame in truth.frames.items():
        image = cv2.imread(str(scene_dir / frame.image_file))
        ids = truth.id_maps(name, allow_eval=True)
        for triple, colour in zip(ids.reshape(3, -1).T.tolist(), image.reshape(-1, 3).tolist()):
            assert colour_of.setdefault(tuple(triple), tuple(colour)) == tuple(colour)  # flat within a region
    assert len(colour_of) == regions > 3
    assert len(set(colour_of.values())) == regions  # distinct regions, distinct colours: every boundary an edge


def test_the_truth_colours_run_writes_its_own_report_and_leaves_dnerf_out(tmp_path, capsys):
    from benchmark.cli import main

    out = tmp_path / "report"
    assert main(["annotate-bench", "--presets", "smoke", "--size", "32", "--images", "truth-colours",
                 "--work", str(tmp_path / "w"), "--out", str(out)]) == 0
    doc = json.loads((out / "annotation_bench_truth_colours.json").read_text())
    assert doc["config"]["images"] == "truth-colours" and [r["scene"] for r in doc["scenes"]] == ["smoke"]
    assert "Images: truth colours" in (out / "annotation_bench_truth_colours.md").read_text()
    assert not (out / "annotation_bench.json").exists()
    painted = tmp_path / "w" / "scenes-truth-colours" / "smoke"
    assert (painted / "truth-colours.done").is_file()
    import cv2  # an interrupted repaint (no mark) is redone whole by the next run in the same --work

    image = next((painted / "rgb" / "1x").glob("*.png"))
    cv2.imwrite(str(image), np.zeros_like(cv2.imread(str(image))))
    (painted / "truth-colours.done").unlink()
    assert main(["annotate-bench", "--presets", "smoke", "--size", "32", "--images", "truth-colours",
                 "--work", str(tmp_path / "w"), "--out", str(out)]) == 0
    assert cv2.imread(str(image)).any() and (painted / "truth-colours.done").is_file()
    assert main(["annotate-bench", "--presets", "none", "--images", "truth-colours", "--adopt-dnerf",
                 "--out", str(out)]) == 2
    assert "--adopt-dnerf" in capsys.readouterr().err


def test_simulated_masks_are_adopted_only_where_they_reach_the_truth(tmp_path):
    from annotations.format import load_annotations, save_annotations
    from benchmark.core.annotation import AnnotatedFrame, AnnotationSet, Query
    from benchmark.studies.annotation_bench import TruthQuery, TruthScene, adopt_simulated_masks

    truth = np.zeros((2, 12, 12), bool)
    truth[:, 2:8, 3:9] = True
    frames = [AnnotatedFrame(1, "f0", 0, 12, 12), AnnotatedFrame(2, "f1", 1, 12, 12)]

    def file_with(masks, made_by, extra_query=False):
        queries = [Query(1, "ball", level="whole")] + ([Query(2, "stripe", level="part", review="draft")]
                                                       if extra_query else [])
        aset = AnnotationSet("toy", frames=list(frames), queries=queries, num_time_steps=2, info={"annotator": "x"})
        for frame, mask in zip(frames, masks):
            aset.set_mask(1, frame.id, mask, made_by=made_by)
            if extra_query:
                aset.set_mask(2, frame.id, mask[:, ::-1].copy(), made_by="scripted")
        return aset

    shipped = save_annotations(file_with(truth, "scripted", extra_query=True), tmp_path / "toy.json")
    good = truth[0].copy()
    good[2, 3] = False  # 35 of 36 pixels: IoU 0.97
    poor = np.zeros((12, 12), bool)
    poor[2:5, 3:9] = True  # half the object: IoU 0.5
    made = save_annotations(file_with([good, poor], "clicks"), tmp_path / "made.json")
    scene = TruthScene("toy", tmp_path, "dnerf", [TruthQuery("ball", "agnostic", None, "whole")], ["f0", "f1"],
                       lambda text, frame: truth[int(frame[1])])

    assert adopt_simulated_masks(shipped, made, scene, 0.95) == {"adopted": 1, "kept": 1}
    back = load_annotations(shipped)
    assert np.array_equal(back.get_mask(1, 1), good) and back.made_by[(1, 1)] == "clicks"
    assert np.array_equal(back.get_mask(1, 2), truth[1]) and back.made_by[(1, 2)] == "scripted"
    # the query without exact truth is untouched, and stays a draft
    assert np.array_equal(back.get_mask(2, 1), truth[0][:, ::-1]) and back.query(2).review == "draft"
    assert "simulated" in back.info["annotators"] and back.info["simulated_protocol"]["min_iou_against_truth"] == 0.95
