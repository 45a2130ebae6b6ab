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
        # the clicks-only figure on the same frames, beside the box-first one
        assert r["clicks_frames"] == r["frames"] and 1 <= r["clicks_noc85"] <= r["clicks_noc90"] <= config.max_interactions
        assert r["human_s_per_frame_every"] > 0 and r["human_s_per_frame_propagation"] > 0
    # the box-only stand-in cannot follow the object's outline as GrabCut does
    assert rows["grabcut"]["final_iou"] > rows["sam"]["final_iou"]
    paths = bench.write([result], config, base / "report")
    text = paths[1].read_text()
    assert "NoC@90" in text and "Papadopoulos" in text and "smoke" in text
    assert "clicks only: NoC@85" in text and "box first: NoC@85" in text and "farthest from its boundary" in text
    assert f"standard deviation {config.box_jitter:g} times the object's width" in text
    tolerance = result["one_pixel_iou"]  # every mask query's, from the truth of the scored frames
    assert set(tolerance) == {q.text for q in truth.queries if q.kind == "agnostic"} - {
        q.text for q in truth.queries if q.kind == "agnostic"
        and all(m is None or not m.any() for m in (truth.mask(q.text, f) for f in truth.scored_frames))}
    # a mask of a few pixels (the smoke box's knob at 48 px) erodes to nothing: 0
    assert all(0 <= v < 1 for v in tolerance.values()) and "one-pixel IoU >= 0.9" in text


def test_intervals_are_marked_only_where_the_pixels_change(smoke):
    _, truth, _, result = smoke
    sensitive = [q for q in truth.queries if q.kind == "sensitive"]
    assert len(result["intervals"]) == len(sensitive) > 0
    times = sorted({0, *(t for r in result["intervals"] for iv in r["true"] for t in iv)})
    for row in result["intervals"]:
        assert row["keys"] == 2 * len(row["marked"])
        starts = {a for a, _ in row["marked"]} - {times[0]}
        ends = {b + 1 for _, b in row["marked"]} - {max(times) + 1}
        # every boundary marked is a change the detector found in the images, none is the truth's own
        assert (starts | ends) <= set(row["changes_found"]), row


def test_the_interval_marker_follows_the_pixels_not_the_truth():
    from annotations.tool.synthetic import rigid_sequence

    seq = rigid_sequence(40, 160, 120, seed=3, recolour_at=17)
    descriptors = [bench.region_descriptor(image, mask) for image, mask in zip(seq.images, seq.masks)]
    changes = bench.change_times(descriptors, window=3, threshold=3.0)
    assert changes == [17]
    times = list(range(40))
    # a truth that says the state starts at 25: the marked interval still starts where the colour changed
    holds = [t >= 25 for t in times]
    assert bench.intervals_from_changes(times, changes, holds) == [(17, 39)]
    assert bench.boundary_error(bench.intervals_from_changes(times, changes, holds), [(25, 39)]) == 8
    # the same motion without a change of state: nothing to mark, whatever the truth says
    still = rigid_sequence(40, 160, 120, seed=3)
    assert bench.change_times([bench.region_descriptor(i, m) for i, m in zip(still.images, still.masks)], 3, 3.0) == []
    assert bench.intervals_from_changes(times, [], [t >= 10 for t in times]) == [(0, 39)]  # one piece, mostly holding
    assert bench.intervals_from_changes(times, [], [t >= 30 for t in times]) == []
    # frames where the object is out of view are skipped, not read as a change
    gappy = descriptors[:10] + [None] * 3 + descriptors[13:]
    assert bench.change_times(gappy, window=3, threshold=3.0) == [17]


def test_boxes_are_noisy_by_the_stated_jitter_the_same_on_every_run():
    truth = np.zeros((100, 200), bool)
    truth[20:60, 50:130] = True  # 80 wide, 40 tall
    assert bench.noisy_box(truth, 2, 0.0, np.random.default_rng(1)) == [48.0, 18.0, 132.0, 62.0]
    assert bench.truth_box(truth, 2) == [48.0, 18.0, 132.0, 62.0]
    boxes = np.array([bench.noisy_box(truth, 0, 0.05, bench.box_rng(0, "cup", f"f{k}")) for k in range(400)])
    offsets = boxes - [50, 20, 130, 60]
    assert np.std(offsets, axis=0) == pytest.approx([4.0, 2.0, 4.0, 2.0], rel=0.2)  # 5 % of width / height
    assert abs(np.mean(offsets)) < 0.5
    assert bench.noisy_box(truth, 2, 0.05, bench.box_rng(0, "cup", "f1")) == bench.noisy_box(
        truth, 2, 0.05, bench.box_rng(0, "cup", "f1"))
    assert bench.box_rng(0, "cup", "f1").random() != bench.box_rng(1, "cup", "f1").random()
    edge = np.zeros((100, 200), bool)
    edge[0:5, 195:200] = True  # at the corner: the box stays in the frame and at least a pixel wide
    for k in range(50):
        x0, y0, x1, y1 = bench.noisy_box(edge, 2, 0.5, np.random.default_rng(k))
        assert 0 <= x0 < x1 <= 200 and 0 <= y0 < y1 <= 100 and x1 - x0 >= 1 and y1 - y0 >= 1


class _DiskClient:
    """A stand-in for the tool: each positive click adds a disk of radius 5, each negative one removes it."""

    def __init__(self, shape):
        self.shape = shape
        self.requests = []

    def segment(self, frame, box, clicks, current):
        self.requests.append((box, list(clicks)))
        mask = np.zeros(self.shape, bool)
        yy, xx = np.mgrid[:self.shape[0], :self.shape[1]]
        for x, y, label in clicks:
            mask[(xx + 0.5 - x) ** 2 + (yy + 0.5 - y) ** 2 <= 25] = bool(label)
        return mask, 0.001


def test_clicks_only_starts_at_the_deepest_interior_point_and_stops_at_20_clicks():
    truth = np.zeros((60, 80), bool)
    truth[10:50, 10:30] = True  # a tall bar: its deepest points lie on x = 20
    truth[40:50, 30:70] = True  # and a foot to the right
    x, y, label = bench.first_click(truth)
    assert label == 1 and 19 <= x <= 21 and 19 <= y <= 41
    client = _DiskClient(truth.shape)
    config = bench.BenchConfig(max_interactions=20, target_iou=0.85)
    mask, log = bench.annotate_clicks_only(client, 0, "f", truth, config)
    assert all(box is None for box, _ in client.requests)  # never a box
    assert client.requests[0][1] == [bench.first_click(truth)]
    assert log.made_by == "clicks-only" and len(log.ious) <= 20
    # disks of radius 5 cannot trace square corners: it runs to the cap short of 0.90 (NoC@90 = 20)
    assert log.noc(0.90, 20) == 20 or log.ious[-1] >= 0.90
    small = np.zeros((60, 80), bool)
    small[20:29, 20:29] = True  # nearly one disk: reached within a few clicks
    _, quick = bench.annotate_clicks_only(_DiskClient(small.shape), 0, "f", small, config)
    assert quick.ious[-1] >= 0.90 and quick.noc(0.90, 20) <= 5
    _, absent = bench.annotate_clicks_only(client, 0, "f", np.zeros_like(truth), config)
    assert absent.made_by == "absent"


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
