"""``bench4d ablate timing``: the side-by-side fit timing of two commits."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from benchmark.core.errors import InputError
from benchmark.studies import fit_timing
from benchmark.studies.fit_timing import (RunRecord, TimingConfig, read_run, score_rows, score_summary, summarize,
                                          timing_markdown)

TINY = {"geometry.static_iterations": "6", "geometry.deformation_iterations": "6", "autoencoder.min_steps": "5",
        "autoencoder.max_steps": "5", "field.iterations": "5", "caption_autoencoder.min_steps": "5",
        "caption_autoencoder.max_steps": "5", "status.static_iterations": "3", "status.iterations": "5"}
"""A schedule that fits the smoke preset in seconds."""


def _run(side: str, round_: int, deform: float, field_s: float, cpu: float, miou: float = 50.0,
         scene: str = "a", seed: int = 0) -> RunRecord:
    stages = {label: None for label, _ in fit_timing.STAGES + fit_timing.CPU_STAGES}
    stages.update({"geometry: deformation stage": deform, "language field": field_s,
                   "whole fit": deform + field_s})
    scores = {label: None for label, _ in fit_timing.SCORES}
    scores["mIoU"] = miou
    return RunRecord(side, round_, scene, seed, stages, scores, cpu, cpu + 1.0, f"/tmp/{side}{round_}.json")


def test_the_table_takes_medians_per_side_and_divides_new_by_old():
    runs = [_run("baseline", 0, 30.0, 10.0, 50.0), _run("candidate", 0, 10.0, 4.0, 20.0),
            _run("candidate", 1, 12.0, 6.0, 22.0), _run("baseline", 1, 34.0, 14.0, 54.0),
            _run("baseline", 2, 32.0, 12.0, 52.0), _run("candidate", 2, 11.0, 5.0, 21.0)]
    rows = {r["stage"]: r for r in summarize(runs)}
    deform = rows["geometry: deformation stage"]
    assert deform["baseline_seconds"] == 32.0 and deform["candidate_seconds"] == 11.0
    assert deform["ratio"] == pytest.approx(11.0 / 32.0) and deform["speedup"] == pytest.approx(32.0 / 11.0)
    assert rows["whole fit"]["ratio"] == pytest.approx((11.0 + 5.0) / (32.0 + 12.0))
    assert rows["process CPU (whole eval)"]["ratio"] == pytest.approx(21.0 / 52.0)
    # a stage neither side recorded stays empty instead of becoming a number
    empty = rows["time-varying: status field"]
    assert empty["baseline_seconds"] is None and empty["ratio"] is None and empty["speedup"] is None
    md = timing_markdown(TimingConfig(baseline="abc", rounds=3), {"baseline": "abc", "candidate": "def"},
                         summarize(runs), runs)
    assert "| geometry: deformation stage | 32.0 | 11.0 | 0.344 | 2.91 |" in md
    assert "| time-varying: status field | – | – | – | – |" in md
    assert "| a | 0 | mIoU | 50.00 | 50.00 | 0.00 |" in md


def test_several_scenes_and_seeds_average_their_medians_and_list_every_score():
    runs = [_run("baseline", 0, 30.0, 10.0, 50.0, miou=60.0, scene="a", seed=0),
            _run("candidate", 0, 10.0, 5.0, 20.0, miou=58.0, scene="a", seed=0),
            _run("baseline", 0, 90.0, 30.0, 150.0, miou=70.0, scene="b", seed=0),
            _run("candidate", 0, 45.0, 15.0, 75.0, miou=71.0, scene="b", seed=0),
            _run("baseline", 0, 50.0, 10.0, 50.0, miou=64.0, scene="a", seed=1),
            _run("candidate", 0, 20.0, 5.0, 20.0, miou=61.0, scene="a", seed=1)]
    rows = {r["stage"]: r for r in summarize(runs)}
    deform = rows["geometry: deformation stage"]
    assert deform["baseline_seconds"] == pytest.approx((30 + 90 + 50) / 3)
    assert deform["ratio"] == pytest.approx((10 + 45 + 20) / (30 + 90 + 50))
    scores = [r for r in score_rows(runs) if r["score"] == "mIoU"]
    assert [(r["scene"], r["seed"], r["difference"]) for r in scores] == [("a", 0, -2.0), ("a", 1, -3.0),
                                                                          ("b", 0, 1.0)]
    summary = {r["score"]: r for r in score_summary(score_rows(runs))}["mIoU"]
    assert summary["mean_difference"] == pytest.approx(-4.0 / 3) and summary["min_difference"] == -3.0
    # seed spread: scene a only has two seeds (64 - 60 old, 61 - 58 new)
    assert summary["baseline_seed_spread"] == 4.0 and summary["candidate_seed_spread"] == 3.0


def test_a_run_is_read_from_its_results_file(tmp_path):
    doc = {"timing": {"fit_seconds": 100.0}, "metrics": {"mIoU": 61.5, "Acc": 90.0, "vIoU": None},
           "fit": {"info": {"geometry": {"session_seconds": 70.0, "test_psnr": 27.5, "gaussians": 4000,
                                         "stages": [{"stage": "static", "seconds": 10.0, "cpu_seconds": 9.5},
                                                    {"stage": "deformation", "seconds": 55.0, "cpu_seconds": 50.0}]},
                            "autoencoder": {"seconds": 5.0}, "field": {"seconds": 12.0}}}}
    results = tmp_path / "results" / "synthetic" / "smoke" / "4d-langsplat" / "oracle"
    results.mkdir(parents=True)
    (results / "seed0.json").write_text(json.dumps(doc))
    run = read_run(tmp_path / "results", "baseline", 0, 120.0, 130.0, "smoke", 0)
    assert run.stages["geometry: deformation stage"] == 55.0 and run.stages["geometry: static stage (CPU)"] == 9.5
    assert run.stages["language field"] == 12.0 and run.stages["whole fit"] == 100.0
    assert run.stages["time-varying: whole"] is None  # a fit without the stage
    assert run.scores["mIoU"] == 61.5 and run.scores["vIoU"] is None and run.scores["Gaussians"] == 4000
    (results / "seed1.json").write_text(json.dumps(doc))
    with pytest.raises(RuntimeError, match="one results file"):
        read_run(tmp_path / "results", "baseline", 0, 1.0, 1.0)


def test_an_unknown_commit_is_an_input_error():
    if shutil.which("git") is None or not (fit_timing.REPO / ".git").exists():
        pytest.skip("needs a git checkout")
    with pytest.raises(InputError, match="no commit"):
        fit_timing.resolve_commit("no-such-revision-anywhere")


@pytest.mark.slow
def test_head_against_the_working_tree_on_a_tiny_fit(tmp_path):
    """The whole study on the smoke preset: HEAD exported and the working tree, one round each."""
    if shutil.which("git") is None or subprocess.run(["git", "-C", str(fit_timing.REPO), "rev-parse", "HEAD"],
                                                     capture_output=True).returncode != 0:
        pytest.skip("needs a git checkout")
    config = TimingConfig(baseline="HEAD", scenes=("smoke",), size=24, overrides=TINY, rounds=1, seeds=(1,),
                          cache_dir=tmp_path / "cache", out=tmp_path / "out", name="tiny")
    report = fit_timing.fit_timing_report(config)
    assert [p.name for p in report.paths] == ["tiny.json", "tiny.md"]
    kept = sorted(p.name for p in (tmp_path / "out" / "tiny-runs").iterdir())
    assert kept == ["baseline-smoke-seed1-round0.json", "candidate-smoke-seed1-round0.json"]
    assert [r["results_file"] for r in json.loads((tmp_path / "out" / "tiny.json").read_text())["runs"]] == [
        "tiny-runs/baseline-smoke-seed1-round0.json", "tiny-runs/candidate-smoke-seed1-round0.json"]
    for name in kept:  # seed 1 fits the scene generated with seed 1, as every run of the benchmark
        assert json.loads((tmp_path / "out" / "tiny-runs" / name).read_text())["scene_seed"] == 1
    doc = json.loads((tmp_path / "out" / "tiny.json").read_text())
    assert doc["commits"]["candidate"].startswith("working tree at ")
    runs = doc["runs"]
    assert [r["side"] for r in runs] == ["baseline", "candidate"]
    rows = {r["stage"]: r for r in doc["stages"]}
    for label in ("geometry: static stage", "geometry: deformation stage", "whole fit", "process CPU (whole eval)"):
        old, new = rows[label]["baseline_seconds"], rows[label]["candidate_seconds"]
        assert old > 0 and new > 0
        assert rows[label]["ratio"] == pytest.approx(new / old)
    whole = {r["side"]: r["stages"]["whole fit"] for r in runs}
    assert rows["whole fit"]["baseline_seconds"] == whole["baseline"]
    assert all(r["scores"]["mIoU"] is not None for r in runs)
    assert "| whole fit |" in report.table and Path(report.paths[1]).read_text() == report.table
    assert "## Scores (oracle track)" in report.table  # the scores name the supervision they were fitted on


def test_candidate_options_reach_the_candidate_side_only(tmp_path):
    config = TimingConfig(baseline="HEAD", overrides={"field.iterations": "5"},
                          candidate_overrides={"geometry.deformation_iterations": "1000", "field.iterations": "7"})
    old = fit_timing.eval_command(config, tmp_path, 0, tmp_path / "c", tmp_path / "r", side="baseline")
    new = fit_timing.eval_command(config, tmp_path, 0, tmp_path / "c", tmp_path / "r", side="candidate")
    assert [old[i + 1] for i, a in enumerate(old) if a == "--set"] == ["field.iterations=5"]
    assert sorted(new[i + 1] for i, a in enumerate(new) if a == "--set") == [
        "field.iterations=7", "geometry.deformation_iterations=1000"]  # the candidate's own value wins
    text = fit_timing.timing_markdown(config, {"baseline": "a", "candidate": "b"}, [], [])
    assert "the candidate's own: `geometry.deformation_iterations=1000`" in text


def test_the_scores_name_their_track():
    import dataclasses

    config = TimingConfig(baseline="HEAD")
    runs = [dataclasses.replace(_run("baseline", 0, 10.0, 5.0, 20.0), track="oracle"),
            dataclasses.replace(_run("candidate", 0, 5.0, 5.0, 12.0), track="oracle")]
    text = fit_timing.timing_markdown(config, {"baseline": "a", "candidate": "b"}, summarize(runs), runs)
    assert "## Scores (oracle track)" in text
    unknown = fit_timing.timing_markdown(config, {"baseline": "a", "candidate": "b"}, [], [_run("baseline", 0, 1, 1, 1)])
    assert "## Scores (unrecorded track)" in unknown
