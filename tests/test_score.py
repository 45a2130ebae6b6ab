"""Scoring scenes, prediction files, and ``bench4d score`` (hand-computed scene + error cases)."""

from __future__ import annotations

import copy
import json
import math
import random

import numpy as np
import pytest

from annotations.format import save_annotations
from benchmark.core.annotation import AnnotatedFrame, AnnotationSet, Query
from benchmark.cli import main
from benchmark.core.errors import InputError
from benchmark.metrics import ScoreConfig, TemporalRule, aggregate_scenes, score_scene
from benchmark.core.protocol import PROTOCOLS
from benchmark.predictions import (JSON_FILE, QueryPrediction, ScenePredictions, query_slug, read_predictions,
                                   write_predictions)

H, W = 4, 5


def square() -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[:2, :2] = True                      # 4 pixels
    return m


def bottom_row() -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[-1, :] = True                       # 5 pixels
    return m


def make_gt(scene: str = "kitchen") -> AnnotationSet:
    """6 frames (t = 0..5, listed out of order); "cookie" on every frame; "plate" on t = 1..4 with
    t = 2 annotated absent (empty mask); "cracked cookie" inherits cookie's masks, holds on t = 2..4."""
    frames = [AnnotatedFrame(id=10 + t, name=f"f{t:03d}", time_index=t, width=W, height=H) for t in (3, 0, 5, 1, 4, 2)]
    aset = AnnotationSet(scene=scene, frames=frames, num_time_steps=6, queries=[
        Query(1, "cookie"), Query(2, "plate"), Query(3, "cracked cookie", "sensitive", base=1, intervals=[(2, 4)])])
    for t in range(6):
        aset.set_mask(1, 10 + t, square())
    for t in (1, 3, 4):
        aset.set_mask(2, 10 + t, bottom_row())
    aset.set_mask(2, 12, np.zeros((H, W), bool))
    return aset


def perfect_predictions(aset: AnnotationSet) -> ScenePredictions:
    preds = ScenePredictions(scene=aset.scene, method="oracle")
    for q in aset.queries:
        frames = aset.annotated_frames(q.id)
        pred = QueryPrediction(q.text, kind=q.kind, masks={f.name: aset.get_mask(q.id, f.id) for f in frames})
        if q.kind == "sensitive":
            pred.scores = {f.name: float(q.holds_at(f.time_index)) for f in frames}
        preds.add(pred)
    return preds


def hand_predictions(aset: AnnotationSet) -> ScenePredictions:
    preds = perfect_predictions(aset)
    preds.queries["cookie"].masks["f000"] = np.zeros((H, W), bool)       # missed on t = 0
    fp = np.zeros((H, W), bool)
    fp[0, 4] = True
    preds.queries["plate"].masks["f002"] = fp                            # 1 px on the absent frame
    extra = square()
    extra[3, 3] = True
    preds.queries["cracked cookie"].masks["f003"] = extra                # IoU 4/5 on t = 3
    preds.queries["cracked cookie"].scores = {f"f{t:03d}": s for t, s in enumerate([0, 0, 1, 1, 0, 0])}
    return preds


# -- scoring -----------------------------------------------------------------------------------------
STRICT = ScoreConfig(absent_frames="score-empty")
"""Absent frames scored against the empty mask (the benchmark's stricter option)."""


def test_perfect_predictions_score_100():
    aset = make_gt()
    summary = score_scene(aset, perfect_predictions(aset)).summary()
    assert [summary[k] for k in ("mIoU", "mAcc", "Acc", "vIoU")] == [100.0] * 4
    # release: plate's absent frame (t = 2) is not scored; its (empty) mask is looked at for absentFP
    assert (summary["agnostic_queries"], summary["sensitive_queries"], summary["frames_scored"]) == (2, 1, 15)
    assert (summary["absent_frames"], summary["absentFP"]) == (1, 0.0)
    strict = score_scene(aset, perfect_predictions(aset), STRICT).summary()
    assert strict["frames_scored"] == 16 and strict["mIoU"] == 100.0 and strict["absentFP"] == 0.0


def test_complement_predictions_score_0():
    aset = make_gt()
    preds = perfect_predictions(aset)
    for p in preds.queries.values():
        p.masks = {f: ~m for f, m in p.masks.items()}
        if p.scores:
            p.decisions = {f: not bool(s) for f, s in p.scores.items()}
            p.scores = {}
    summary = score_scene(aset, preds).summary()
    assert [summary[k] for k in ("mIoU", "mAcc", "Acc", "vIoU")] == [0.0] * 4


def test_hand_computed_scene():
    aset = make_gt()
    score = score_scene(aset, hand_predictions(aset), STRICT)
    q = score.query_table().set_index("query")
    # cookie: IoU [0,1,1,1,1,1] -> 5/6 ; pixel acc t0 = 16/20 -> (0.8 + 5)/6
    assert q.loc["cookie", "miou"] == pytest.approx(5 / 6)
    assert q.loc["cookie", "macc"] == pytest.approx(5.8 / 6)
    # plate (t = 1..4): false positive on the absent frame -> IoU 0, acc 19/20 -> 3/4 and 3.95/4
    assert q.loc["plate", "miou"] == pytest.approx(0.75)
    assert q.loc["plate", "macc"] == pytest.approx(3.95 / 4)
    # cracked cookie: scores [0,0,1,1,0,0] -> smoothed [0,.1,.9,.9,.1,0], tau = 2/6 -> pred t = 2,3;
    # labels t = 2..4 -> Acc 5/6 ; S_u = {2,3,4}, S_i = {2,3}: (1 + 0.8)/3 = 0.6
    row = q.loc["cracked cookie"]
    assert (row["acc"], row["viou"], row["threshold"]) == (pytest.approx(5 / 6), pytest.approx(0.6), pytest.approx(1 / 3))
    assert (row["positives"], row["predicted"], row["decision_source"]) == (3, 2, "rule")
    assert math.isnan(row["miou"]) and math.isnan(q.loc["cookie", "viou"])
    s = score.summary()
    assert s["mIoU"] == pytest.approx(100 * (5 / 6 + 0.75) / 2)
    assert s["mAcc"] == pytest.approx(100 * (5.8 / 6 + 3.95 / 4) / 2)
    assert (s["Acc"], s["vIoU"]) == (pytest.approx(100 * 5 / 6), pytest.approx(60.0))
    # records: one per (query, frame), sensitive ones carry the rule's values, in time order
    rec = score.records_table()
    assert len(rec) == 16
    cc = rec[rec["query"] == "cracked cookie"]
    assert cc["time_index"].tolist() == list(range(6))
    assert cc["decision"].tolist() == [False, False, True, True, False, False]
    assert cc["smoothed"].tolist() == pytest.approx([0, 0.1, 0.9, 0.9, 0.1, 0])
    assert s["absentFP"] == 100.0 and s["absent_frames"] == 1  # the 1-px false positive on plate's absent frame


def test_release_skips_absent_frames_and_reports_their_false_positives_apart():
    """The release queries a label only where it is annotated: plate's absent frame (t = 2) is not scored;
    the 1-px false positive there shows in absentFP instead of in mIoU."""
    aset = make_gt()
    score = score_scene(aset, hand_predictions(aset), ScoreConfig.from_protocol(PROTOCOLS["release"]))
    q = score.query_table().set_index("query")
    assert q.loc["plate", "frames"] == 3 and q.loc["plate", "miou"] == 1.0
    assert q.loc["cookie", "miou"] == pytest.approx(5 / 6)  # present everywhere: as under the strict rule
    s = score.summary()
    assert s["mIoU"] == pytest.approx(100 * (5 / 6 + 1) / 2)
    assert (s["absentFP"], s["absent_frames"], s["frames_scored"]) == (100.0, 1, 15)
    assert score.absent == {"plate": (1, 1)}
    assert "f002" not in set(score.records_table().query("query == 'plate'")["frame"])
    # a query of the base's frames: cracked cookie's base (cookie) is present everywhere, so all 6 frames count
    assert q.loc["cracked cookie", "frames"] == 6
    # an empty prediction on the absent frame: no false positive
    preds = hand_predictions(aset)
    preds.queries["plate"].masks["f002"] = np.zeros((H, W), bool)
    assert score_scene(aset, preds).summary()["absentFP"] == 0.0
    # the base absent on a frame: the time-sensitive query is not scored there either (the release adds a
    # time query's label only where its base label is annotated)
    gone = make_gt()
    gone.set_mask(1, 13, np.zeros((H, W), bool))  # cookie absent at t = 3
    preds = perfect_predictions(gone)
    release = score_scene(gone, preds).query_table().set_index("query")
    strict = score_scene(gone, preds, STRICT).query_table().set_index("query")
    assert (release.loc["cracked cookie", "frames"], strict.loc["cracked cookie", "frames"]) == (5, 6)
    assert release.loc["cookie", "frames"] == 5
    # a query whose object is absent on every scored frame is not scored under the release's rule
    only_absent = score_scene(aset, perfect_predictions(aset), ScoreConfig(eval_frames=("f002",)))
    assert "plate" in only_absent.skipped and only_absent.absent == {"plate": (1, 0)}  # looked at: empty
    assert (only_absent.summary()["absent_frames"], only_absent.summary()["absentFP"]) == (1, 0.0)
    # the mask on an absent frame is still required (it gives absentFP)
    preds = perfect_predictions(aset)
    del preds.queries["plate"].masks["f002"]
    with pytest.raises(InputError, match=r"queries\['plate'\]\.masks\['f002'\].*missing mask"):
        score_scene(aset, preds)


def test_dataset_is_mean_over_scenes():
    a, b = make_gt("a"), make_gt("b")
    d = aggregate_scenes([score_scene(a, hand_predictions(a)), score_scene(b, perfect_predictions(b))])
    assert d.summary()["mIoU"] == pytest.approx((100 * (5 / 6 + 1) / 2 + 100) / 2)
    assert d.summary()["absentFP"] == pytest.approx((100 + 0) / 2) and d.summary()["absent_frames"] == 2
    assert d.summary()["scenes"] == 2
    assert d.scene_table()["scene"].tolist() == ["a", "b"]
    with pytest.raises(InputError, match="more than once"):
        aggregate_scenes([score_scene(a, perfect_predictions(a))] * 2)


def test_order_of_frames_and_queries_is_irrelevant():
    aset = make_gt()
    ref = score_scene(aset, hand_predictions(aset))
    rng = random.Random(0)
    for _ in range(3):
        shuffled = copy.deepcopy(aset)
        rng.shuffle(shuffled.frames)
        rng.shuffle(shuffled.queries)
        preds = hand_predictions(aset)
        items = list(preds.queries.items())
        rng.shuffle(items)
        preds.queries = dict(items)
        for p in preds.queries.values():
            keys = list(p.masks)
            rng.shuffle(keys)
            p.masks = {k: p.masks[k] for k in keys}
        got = score_scene(shuffled, preds)
        assert got.summary() == ref.summary()
        assert got.query_table().equals(ref.query_table())
        assert got.records_table().equals(ref.records_table())


def test_release_rule_changes_only_the_temporal_part():
    aset = make_gt()
    preds = hand_predictions(aset)
    preds.queries["cracked cookie"].scores = {f"f{t:03d}": s for t, s in enumerate([0.2, 1.0, 0.5, 1.0, 1.0, 0.0])}
    paper = score_scene(aset, preds, ScoreConfig(temporal=TemporalRule(ends="keep", tau_from="smoothed"))).summary()
    release = score_scene(aset, preds, ScoreConfig(temporal=PROTOCOLS["release"].temporal)).summary()
    assert paper["mIoU"] == release["mIoU"] and paper["mAcc"] == release["mAcc"]
    # keep: smoothed = [.2, .87, .6, .95, .9, 0]; labels t = 2..4; IoU_3 = .8, other IoUs 1
    # paper tau = 3.52/6 = .5867 -> pred t = 1..4: Acc 5/6, vIoU (1 + .8 + 1)/4 = .7
    assert (paper["Acc"], paper["vIoU"]) == (pytest.approx(100 * 5 / 6), pytest.approx(70.0))
    # release tau = 3.7/6 = .6167 -> t = 2 drops out: pred t = 1,3,4: Acc 4/6, vIoU (.8 + 1)/4 = .45
    assert (release["Acc"], release["vIoU"]) == (pytest.approx(100 * 4 / 6), pytest.approx(45.0))


def test_eval_frames_and_skipped_queries():
    aset = make_gt()
    preds = perfect_predictions(aset)
    s = score_scene(aset, preds, ScoreConfig(eval_frames=("f000", "f005")))
    # plate has no annotation on t = 0 or 5: not scored
    assert s.skipped == ["plate"]
    assert s.summary()["frames_scored"] == 4
    with pytest.raises(InputError, match="eval_frames"):
        score_scene(aset, preds, ScoreConfig(eval_frames=("nope",)))


def test_empty_spatial_mask_gives_undefined_score():
    aset = make_gt()
    preds = perfect_predictions(aset)
    cc = preds.queries["cracked cookie"]
    cc.masks["f003"] = np.zeros((H, W), bool)
    cc.scores["f003"] = float("nan")          # the method could not average over an empty mask
    row = score_scene(aset, preds).query_table().set_index("query").loc["cracked cookie"]
    # t = 3 is predicted negative (undefined score) though labelled positive: Acc 5/6, vIoU 2/3
    assert row["acc"] == pytest.approx(5 / 6) and row["viou"] == pytest.approx(2 / 3)


@pytest.mark.parametrize("mutate, match", [
    (lambda p: p.queries.pop("plate"), r"queries\['plate'\].*missing"),
    (lambda p: p.queries["cookie"].masks.pop("f004"), r"queries\['cookie'\]\.masks\['f004'\].*missing mask"),
    (lambda p: p.queries["cookie"].masks.__setitem__("f004", np.zeros((W, H), bool)), r"masks\['f004'\].*5x4"),
    (lambda p: p.queries["cookie"].masks.__setitem__("f999", np.zeros((H, W), bool)), r"f999.*not in the ground truth"),
    (lambda p: p.queries["cracked cookie"].scores.pop("f002"), r"scores\['f002'\].*missing score"),
    (lambda p: setattr(p.queries["cracked cookie"], "scores", {}), r"needs 'scores'"),
    (lambda p: setattr(p.queries["plate"], "kind", "sensitive"), r"kind.*ground truth says 'agnostic'"),
    (lambda p: p.add(QueryPrediction("spoon", masks={})), r"queries\['spoon'\].*not a query"),
    (lambda p: setattr(p, "scene", "garage"), r"scene.*garage"),
])
def test_mismatches_are_input_errors(mutate, match):
    aset = make_gt()
    preds = perfect_predictions(aset)
    mutate(preds)
    with pytest.raises(InputError, match=match):
        score_scene(aset, preds)


def test_allow_extra_ignores_unknown_queries():
    aset = make_gt()
    preds = perfect_predictions(aset)
    preds.add(QueryPrediction("spoon", masks={}))
    assert score_scene(aset, preds, ScoreConfig(allow_extra=True)).summary()["mIoU"] == 100.0


# -- prediction files ------------------------------------------------------------------------------------
@pytest.mark.parametrize("layout", ["json", "png"])
def test_prediction_files_round_trip(tmp_path, layout):
    aset = make_gt()
    preds = hand_predictions(aset)
    preds.queries["cracked cookie"].scores["f001"] = float("nan")
    write_predictions(tmp_path, preds, layout=layout)
    back = read_predictions(tmp_path)
    assert (back.scene, back.method) == ("kitchen", "oracle")
    for text, p in preds.queries.items():
        q = back.find(text)
        assert q.kind == p.kind and sorted(q.masks) == sorted(p.masks)
        for frame in p.masks:
            assert np.array_equal(q.mask(frame), p.mask(frame))
    got = back.queries["cracked cookie"].scores
    assert math.isnan(got["f001"]) and got["f003"] == 1.0
    # scores with a NaN re-read equal the in-memory scores
    assert score_scene(aset, back).query_table().equals(score_scene(aset, preds).query_table())
    with pytest.raises(InputError, match="already exists"):
        write_predictions(tmp_path, preds, layout=layout)
    write_predictions(tmp_path, preds, layout=layout, overwrite=True)


def test_png_layout_without_scores_json_matches_by_slug(tmp_path):
    aset = make_gt()
    preds = perfect_predictions(aset)
    del preds.queries["cracked cookie"]
    preds.queries["Cookie"] = preds.queries.pop("cookie")
    write_predictions(tmp_path, preds, layout="png")
    (tmp_path / "scores.json").unlink()
    back = read_predictions(tmp_path)
    assert sorted(back.queries) == ["cookie", "plate"]          # folder names
    assert query_slug("Cracked  cookie!") == "cracked-cookie"
    # a slug shared by two GT queries is never matched by slug
    clash = make_gt()
    clash.queries = clash.queries[:2] + [Query(4, "Cookie")]
    clash.set_mask(4, 10, square())
    with pytest.raises(InputError, match=r"queries\['Cookie'\].*missing"):
        score_scene(clash, read_predictions(tmp_path))
    aset.queries = aset.queries[:2]
    assert score_scene(aset, back).summary()["mIoU"] == 100.0


def test_malformed_prediction_files(tmp_path):
    with pytest.raises(InputError, match="not a prediction folder"):
        read_predictions(tmp_path)
    path = tmp_path / JSON_FILE
    path.write_text("{bad json")
    with pytest.raises(InputError, match="invalid JSON"):
        read_predictions(tmp_path)
    doc = {"format": "bench4d-predictions", "version": 1, "queries": {"cookie": {"masks": {"f000": {"size": [H, W]}}}}}
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"predictions.json: queries\['cookie'\]\.masks\['f000'\]"):
        read_predictions(tmp_path)
    doc["queries"]["cookie"]["masks"]["f000"] = {"size": [H, W], "counts": "garbage!"}
    path.write_text(json.dumps(doc))
    preds = read_predictions(tmp_path)             # RLE decodes lazily ...
    with pytest.raises(InputError, match=r"masks\['f000'\]\.counts"):
        preds.queries["cookie"].mask("f000")       # ... and names the field when it is bad
    doc["queries"]["cookie"]["scores"] = {"f000": "high"}
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"scores\['f000'\].*finite number"):
        read_predictions(tmp_path)
    for key, value, match in [("format", "other", "format"), ("version", 2, "newer")]:
        path.write_text(json.dumps({**doc, key: value}))
        with pytest.raises(InputError, match=match):
            read_predictions(tmp_path)


# -- the command ---------------------------------------------------------------------------------------------
def test_cli_scores_and_writes_results(tmp_path, capsys):
    gts, root = [], tmp_path / "preds"
    for scene, make in (("a", hand_predictions), ("b", perfect_predictions)):
        aset = make_gt(scene)
        gts += ["--gt", str(save_annotations(aset, tmp_path / f"{scene}.json"))]
        write_predictions(root / scene, make(aset))
    out = tmp_path / "results.json"
    assert main(["score", *gts, "--pred", str(root), "--out", str(out), "--protocol", "release"]) == 0
    printed = capsys.readouterr().out
    assert "cracked cookie" in printed and "mean over 2 scene(s)" in printed
    assert "every asked query (unanswered = 0)" in printed and "answered queries only" in printed
    assert "time-agnostic 4 / 4, time-sensitive 2 / 2" in printed
    doc = json.loads(out.read_text())
    assert doc["format"] == "bench4d-results"
    assert doc["config"]["temporal"]["tau_from"] == "raw"
    assert doc["config"]["temporal"]["ends"] == "keep"
    assert doc["provenance"]["protocol"]["name"] == "release"
    # a temporal flag that changes the preset makes it a custom protocol, recorded as such
    assert main(["score", *gts, "--pred", str(root), "--out", str(out), "--tau-from", "smoothed"]) == 0
    doc = json.loads(out.read_text())
    assert doc["provenance"]["protocol"]["name"] == "custom"
    assert doc["provenance"]["protocol"]["temporal"]["tau_from"] == "smoothed"
    assert doc["metrics"]["dataset"]["mIoU"] == pytest.approx((100 * (5 / 6 + 1) / 2 + 100) / 2)
    assert doc["metrics"]["scenes"]["b"]["vIoU"] == 100.0
    assert len(doc["queries"]) == 6 and len(doc["frames"]) == 30
    assert doc["metrics"]["dataset"]["absentFP"] == pytest.approx(50.0)
    assert {"scene": "a", "query": "plate", "frames": 1, "predicted": 1} in doc["absent"]
    # the stricter option scores the absent frames against the empty mask
    assert main(["score", *gts, "--pred", str(root), "--out", str(out), "--absent-frames", "score-empty"]) == 0
    doc = json.loads(out.read_text())
    assert doc["provenance"]["protocol"]["name"] == "custom" and doc["config"]["absent_frames"] == "score-empty"
    assert doc["metrics"]["dataset"]["mIoU"] == pytest.approx((100 * (5 / 6 + 0.75) / 2 + 100) / 2)
    assert len(doc["frames"]) == 32
    assert doc["provenance"]["bench4d_version"] and doc["provenance"]["score_seconds"] >= 0
    # a frame subset, given as a file
    (tmp_path / "frames.txt").write_text("# held out\nf000\nf005\n")
    assert main(["score", *gts, "--pred", str(root), "--out", str(out), "--eval-frames", f"@{tmp_path / 'frames.txt'}"]) == 0
    doc = json.loads(out.read_text())
    assert doc["config"]["eval_frames"] == ["f000", "f005"] and len(doc["frames"]) == 8
    assert {"scene": "a", "query": "plate"} in doc["skipped"]
    assert main(["score", *gts, "--pred", str(root), "--eval-frames", "f000,nope"]) == 2


def test_cli_reports_input_errors_without_traceback(tmp_path, capsys):
    aset = make_gt()
    gt = save_annotations(aset, tmp_path / "gt.json")
    preds = perfect_predictions(aset)
    preds.queries["cookie"].masks["f001"] = np.zeros((2, 2), bool)
    write_predictions(tmp_path / "p", preds)
    assert main(["score", "--gt", str(gt), "--pred", str(tmp_path / "p")]) == 2
    err = capsys.readouterr().err
    assert "predictions.json" in err and "queries['cookie'].masks['f001']" in err and "Traceback" not in err
    assert main(["score", "--gt", str(gt), "--pred", str(tmp_path / "p"), "--smoothing-weights", "0.5,0.5"]) == 2
    assert "--smoothing-weights" in capsys.readouterr().err
    assert main(["score", "--gt", str(gt), "--pred", str(tmp_path / "missing")]) == 2


def test_time_sensitive_diagnostics_are_recorded_and_derivable_from_the_recorded_frames():
    """AUC / nearTau of a query row; a results file written before they existed gets the same values
    from its recorded frames (the leaderboard reads every file through one path)."""
    from benchmark.results import temporal_diagnostics

    aset = make_gt()
    preds = hand_predictions(aset)
    # scores [.2, .3, .9, .8, .6, .1]: the two middle-low frames sit near the threshold
    preds.queries["cracked cookie"].scores = {f"f{t:03d}": s for t, s in enumerate([0.2, 0.3, 0.9, 0.8, 0.6, 0.1])}
    score = aggregate_scenes([score_scene(aset, preds)])
    row = score.query_table().set_index("query").loc["cracked cookie"]
    assert 0.9 < row["auc"] <= 1.0 and 0.0 <= row["near_threshold"] <= 1.0
    assert math.isnan(score.query_table().set_index("query").loc["cookie", "auc"])
    doc = score.to_json()
    assert doc["metrics"]["dataset"]["AUC"] == pytest.approx(100 * row["auc"])
    assert doc["metrics"]["dataset"]["nearTau"] == pytest.approx(100 * row["near_threshold"])
    run = {"metrics": doc["metrics"]["dataset"], "scores": {"queries": doc["queries"], "frames": doc["frames"]}}
    assert temporal_diagnostics(run) == pytest.approx({"AUC": 100 * row["auc"], "nearTau": 100 * row["near_threshold"]})
    old = copy.deepcopy(run)
    for name in ("AUC", "nearTau"):
        del old["metrics"][name]
    assert temporal_diagnostics(old) == pytest.approx(temporal_diagnostics(run))
    # the derivation reads the frames: change one recorded score and it follows
    for f in old["scores"]["frames"]:
        if f["query"] == "cracked cookie" and f["frame"] == "f004":
            f["smoothed"] = 0.0
    assert temporal_diagnostics(old)["AUC"] < temporal_diagnostics(run)["AUC"]
    # a method that gave decisions has nothing to diagnose
    for q in old["scores"]["queries"]:
        q["decision_source"] = "decisions" if q["kind"] == "sensitive" else q["decision_source"]
    assert all(math.isnan(v) for v in temporal_diagnostics(old).values())


# -- coverage: an unanswered query counts 0 in the full mean ---------------------------------------------------
def test_declaring_a_failed_query_unanswered_never_raises_the_full_mean(tmp_path, capsys):
    """A hand-made submission whose one failed query is then listed under ``unanswered_queries`` instead
    of answered scores at most its full mean (it used to score the mean of the other queries: 73.68 became
    84.20 on a real submission); the answered-only mean is reported beside it, labelled."""
    aset = make_gt()
    aset.queries.append(Query(4, "spoon"))
    for t in range(6):
        aset.set_mask(4, 10 + t, bottom_row())
    answered = perfect_predictions(aset)
    cookie = answered.queries["cookie"]
    cookie.masks = {f: np.zeros((H, W), bool) if f in ("f000", "f001", "f002", "f003") else m
                    for f, m in cookie.masks.items()}  # the failed query: IoU 2/6
    full = score_scene(aset, answered).summary()
    assert full["mIoU"] == pytest.approx(100 * (2 / 6 + 1 + 1) / 3)
    declined = perfect_predictions(aset)
    del declined.queries["cookie"]
    declined.info["unanswered_queries"] = ["cookie"]
    scored = score_scene(aset, declined)
    s = scored.summary()
    assert s["mIoU"] <= full["mIoU"]
    assert s["mIoU"] == pytest.approx(100 * (0 + 1 + 1) / 3) and s["mAcc"] == pytest.approx(100 * 2 / 3)
    assert s["mIoU_answered"] == 100.0 and s["mAcc_answered"] == 100.0
    assert (s["answered_agnostic_queries"], s["asked_agnostic_queries"]) == (2, 3)
    assert (s["answered_sensitive_queries"], s["asked_sensitive_queries"]) == (1, 1)
    assert scored.unanswered == ["cookie"] and "cookie" not in set(scored.query_table()["query"])
    # a kind declined as a whole on a scene: no full mean there (a time-agnostic-only method gets no
    # time-sensitive row) ...
    none = perfect_predictions(aset)
    del none.queries["cracked cookie"]
    none.info["unanswered_queries"] = ["cracked cookie"]
    declined_kind = score_scene(aset, none)
    s = declined_kind.summary()
    assert math.isnan(s["Acc"]) and math.isnan(s["vIoU"])
    assert math.isnan(s["Acc_answered"]) and math.isnan(s["vIoU_answered"])
    assert (s["answered_sensitive_queries"], s["asked_sensitive_queries"], s["mIoU"]) == (0, 1, 100.0)
    assert math.isnan(s["AUC"])  # diagnostics describe answered queries only
    other = make_gt("c")
    del_other = perfect_predictions(other)
    del del_other.queries["cracked cookie"]
    del_other.info["unanswered_queries"] = ["cracked cookie"]
    both = aggregate_scenes([declined_kind, score_scene(other, del_other)]).summary()
    assert math.isnan(both["Acc"]) and math.isnan(both["vIoU"])
    # ... but declining it on one scene while answering it on another counts that scene 0: declining the
    # hard scene never raises the dataset mean
    mixed = aggregate_scenes([declined_kind, score_scene(make_gt("b"), perfect_predictions(make_gt("b")))]).summary()
    assert (mixed["Acc"], mixed["vIoU"]) == (pytest.approx(50.0), pytest.approx(50.0))
    assert mixed["Acc_answered"] == 100.0
    # a query with no scored frame is not asked: declining it costs nothing
    early = score_scene(aset, declined, ScoreConfig(eval_frames=("f000",)))
    assert early.skipped == ["plate"] and early.summary()["asked_agnostic_queries"] == 2  # cookie, spoon
    # the dataset: mean over scenes of each scene's full mean; the command prints both, labelled
    b = make_gt("b")
    d = aggregate_scenes([scored, score_scene(b, perfect_predictions(b))]).summary()
    assert d["mIoU"] == pytest.approx((100 * 2 / 3 + 100) / 2) and d["mIoU_answered"] == 100.0
    assert (d["answered_agnostic_queries"], d["asked_agnostic_queries"]) == (4, 5)
    gt = save_annotations(aset, tmp_path / "gt.json")
    write_predictions(tmp_path / "p", declined)
    out = tmp_path / "r.json"
    assert main(["score", "--gt", str(gt), "--pred", str(tmp_path / "p"), "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    full_line = next(line for line in printed.splitlines() if line.startswith("every asked query"))
    answered_line = next(line for line in printed.splitlines() if line.startswith("answered queries only"))
    assert full_line.split()[6] == "66.67" and answered_line.split()[3] == "100.00"
    assert "time-agnostic 2 / 3" in printed
    metrics = json.loads(out.read_text())["metrics"]["dataset"]
    assert metrics["mIoU"] == pytest.approx(100 * 2 / 3) and metrics["mIoU_answered"] == 100.0
    assert (metrics["answered_agnostic_queries"], metrics["asked_agnostic_queries"]) == (2, 3)
