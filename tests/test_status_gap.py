"""``bench4d ablate status-gap`` (:mod:`benchmark.studies.status_gap`): both methods under the paper's components
on a tiny scene, the differences and their spread, the decisions by distance to a state change, and resuming."""

from __future__ import annotations

import json
import math

import pytest

from benchmark.core.errors import InputError
from benchmark.studies import status_gap
from benchmark.studies.status_gap import DIRECT_METHOD, PAPER_OPTIONS, STATUS_METHOD, StatusGapConfig

TINY = {"geometry.static_iterations": "20", "geometry.deformation_iterations": "20", "field.iterations": "30",
        "autoencoder.min_steps": "40", "autoencoder.max_steps": "60", "geometry.render_backend": "torch",
        "status.static_iterations": "20", "status.iterations": "30", "caption_autoencoder.min_steps": "40",
        "caption_autoencoder.max_steps": "60"}
"""Schedules short enough for a study of four runs to take seconds."""


def test_the_study_s_presets_are_found_by_their_state_changes_and_its_demo_schedule_is_the_demo_s():
    from benchmark.commands.demo import DEMO_OVERRIDES
    from benchmark.synthetic import PRESETS

    presets = status_gap.time_sensitive_presets()
    assert len(presets) == 4 and all(PRESETS[p].time_sensitive and PRESETS[p].state_changes for p in presets)
    assert status_gap.SCHEDULES["demo"] == {k: str(v) for k, v in DEMO_OVERRIDES.items()}
    with pytest.raises(InputError, match="fixed by the study"):
        StatusGapConfig(overrides={"extensions.caption_segments": "true"})
    with pytest.raises(InputError, match="caption noise level"):
        StatusGapConfig(captions=("loud",))
    with pytest.raises(InputError, match="schedule"):
        StatusGapConfig(schedule="week")


def test_spread_and_signed_cells():
    spread = status_gap._spread([1.0, 3.0, None, 2.0])
    assert spread["mean"] == 2.0 and spread["sd"] == pytest.approx(1.0) and (spread["min"], spread["max"]) == (1.0, 3.0)
    assert status_gap._spread([4.0])["sd"] is None and status_gap._spread([])["mean"] is None
    assert status_gap._pm(spread) == "+2.00 ± 1.00 [+1.00, +3.00]"


def test_tiny_study_runs_both_methods_under_the_paper_s_components_and_resumes(tmp_path, monkeypatch):
    config = StatusGapConfig(presets=("smoke",), seeds=(0, 1), size=32, schedule="default", overrides=TINY,
                             cache_dir=tmp_path / "cache", out=tmp_path / "out", quiet=True)
    report = status_gap.status_gap_report(config)
    doc = json.loads((tmp_path / "out" / "status-gap.json").read_text())
    assert [p.name for p in report.paths] == ["status-gap.json", "status-gap.md"]
    assert doc["paper_options"] == PAPER_OPTIONS and doc["seeds"] == [0, 1] and len(doc["runs"]) == 2
    assert doc["command"].startswith("bench4d ablate status-gap --presets smoke --seeds 0 1 --size 32")
    # every run was made with the paper's components, on one scene
    for path in sorted((config.runs_dir / "captions-scene").rglob("seed*.json")):
        recorded = json.loads(path.read_text())["method_config"]["extensions"]
        assert recorded["caption_segments"] is False and recorded["choose_states"] is False
        assert recorded["skip_static_semantics"] is False and recorded["unmasked_text"] is None
    # seeds sample scenes: one scene instance per seed, shared by both methods of that seed
    assert len({r["scene_digest"] for r in doc["runs"]}) == len(doc["seeds"])
    for run in doc["runs"]:
        for k in ("Acc", "vIoU"):
            assert run["difference"][k] == pytest.approx(run[STATUS_METHOD][k] - run[DIRECT_METHOD][k])
    (level,) = doc["levels"]
    acc = level["presets"][0]["Acc"]["difference"]
    diffs = [r["difference"]["Acc"] for r in doc["runs"]]
    assert acc["mean"] == pytest.approx(sum(diffs) / 2) and acc["n"] == 2
    assert level["overall"]["Acc"]["per_seed"] == pytest.approx(diffs)
    # every evaluated frame of a time query is in one distance bin, for each method
    frames = sum(b[STATUS_METHOD]["frames"] for b in level["by_distance"])
    assert frames == sum(b[DIRECT_METHOD]["frames"] for b in level["by_distance"]) > 0
    assert "Δ Acc" in report.table and "**all presets**" in report.table
    # the temporal half apart from the spatial mask: defined for both, and the captions replayed are the same
    for run in doc["runs"]:
        assert run[STATUS_METHOD]["object_mask AUC"] is not None and run[DIRECT_METHOD]["object_mask AUC"] is not None
        assert run[STATUS_METHOD]["captions Acc"] == run[DIRECT_METHOD]["captions Acc"] is not None
    assert "mask AUC" in report.table
    # a second report reads the runs and their diagnostics instead of making them
    monkeypatch.setattr("benchmark.runner.evaluate", lambda *a, **k: pytest.fail("a recorded run was redone"))
    monkeypatch.setattr("benchmark.studies.field_gap.temporal_gap", lambda *a, **k: pytest.fail("diagnosed again"))
    again = status_gap.run_study(config, log=lambda m: None)
    assert again["levels"] == doc["levels"]


def test_frames_are_placed_by_their_distance_to_the_midpoint_of_the_nearest_change(tmp_path, monkeypatch):
    results = {"scores": {"frames": {
        "columns": ["scene", "query", "kind", "frame", "time_index", "camera_id", "iou", "acc", "pred_pixels",
                    "gt_pixels", "score", "smoothed", "decision", "label"],
        "rows": [["s", "open box", "sensitive", "a", t, "0", 0.5, 1.0, 1, 1, 0.1, 0.1, True, True] for t in (2, 9, 30)]
        + [["s", "box", "agnostic", "a", 2, "0", 0.5, 1.0, 1, 1, None, None, None, None]]}}}
    monkeypatch.setattr(status_gap, "state_changes_of", lambda res: {"open box": [10, 20]})
    rows = status_gap.frame_rows(results)
    assert [r["distance"] for r in rows] == [7.5, 0.5, 10.5]
    monkeypatch.setattr(status_gap, "state_changes_of", lambda res: {})
    assert all(math.isinf(r["distance"]) for r in status_gap.frame_rows(results))
