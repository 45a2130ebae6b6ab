"""Pareto charts: floors are references off the front, the ceiling is a line, methods with identical
accuracy are one point, one kind of machine per chart, and an all-at-chance panel says so."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from benchmark.core.atomic import write_json
from benchmark.plots import (ChartPoint, at_chance, label_clusters, machine_kinds, pareto, pareto_charts,
                             shared_stages)
from benchmark.results import RUN_COLUMNS, results_path, write_results

SCENES = ("s1", "s2")
SEEDS = (0, 1, 2)


def _run(method: str, scene: str, seed: int, *, miou: float, acc: float = math.nan, auc: float = math.nan,
         fps: float = 1.0, fit: float = 100.0, device: str = "cpu", **extra) -> dict:
    row = {c: None for c in RUN_COLUMNS}
    row.update(dataset="synthetic", track="oracle", protocol="release", method=method, scene=scene, seed=seed,
               mIoU=miou, mAcc=90.0, Acc=acc, vIoU=math.nan if math.isnan(acc) else acc / 2, AUC=auc,
               nearTau=math.nan, fps_agnostic=fps, fps_sensitive=fps, fit_seconds=fit, peak_cpu_mib=100.0,
               peak_gpu_mib=math.nan, peak_cpu_needed_mib=100.0, peak_gpu_needed_mib=math.nan,
               peak_measured=True, device=device, scene_current=True, path=f"{method}/{scene}/{seed}")
    row.update(extra)
    return row


def _table(rows: list[dict]) -> pd.DataFrame:
    table = pd.DataFrame(rows)
    return table[[c for c in table.columns if c in RUN_COLUMNS or c == "machine_kind"]]


def _runs(**overrides) -> list[dict]:
    """alpha and beta share a stage (identical mIoU everywhere), gamma is fast and less accurate, floor is
    far faster than all and a point more accurate than gamma."""
    rows = []
    for scene in SCENES:
        for seed in SEEDS:
            base = 50.0 + 5 * seed + (10.0 if scene == "s2" else 0.0)
            rows += [_run("alpha", scene, seed, miou=base, fps=2.0, fit=1000.0),
                     _run("beta", scene, seed, miou=base + 1e-5, fps=2.2, fit=800.0),
                     _run("gamma", scene, seed, miou=base - 21, fps=20.0, fit=50.0),
                     _run("floor", scene, seed, miou=base - 20, fps=5000.0, fit=0.01)]
    return [{**r, **overrides} for r in rows]


def test_floors_are_reference_lines_never_on_the_front():
    charts = pareto_charts(_table(_runs()), floors=frozenset({"floor"}))
    assert len(charts) == 1
    for panel in charts[0].rows[0]:
        drawn = [p.methods for p in panel.points]
        assert all("floor" not in members for members in drawn)
        assert [f.methods for f in panel.floors] == [("floor",)]
        assert panel.floors[0].y == pytest.approx(40.0)  # mean over s1/s2 and the seeds: 55 + 5 - 20
        front = {panel.points[i].methods for i in panel.front}
        # without the floor both the shared point and gamma are on the front (the floor would dominate gamma)
        assert front == {("alpha", "beta"), ("gamma",)}
    # the same runs, no floor declared: the floor is a method again and dominates gamma on both axes
    panel = pareto_charts(_table(_runs()), floors=frozenset())[0].rows[0][0]
    assert {panel.points[i].methods for i in panel.front} == {("alpha", "beta"), ("floor",)}


def test_methods_with_identical_accuracy_are_one_point_with_both_names():
    table = _table(_runs())
    assert shared_stages(table, "mIoU", ["alpha", "beta", "gamma", "floor"]) == [["alpha", "beta"], ["gamma"], ["floor"]]
    # one (scene, seed) apart by more than rounding: two points
    moved = table.copy()
    moved.loc[(moved["method"] == "beta") & (moved["scene"] == "s2") & (moved["seed"] == 1), "mIoU"] += 0.5
    assert shared_stages(moved, "mIoU", ["alpha", "beta"]) == [["alpha"], ["beta"]]
    # the same numbers on different seeds do not count as the same runs
    fewer = table[~((table["method"] == "beta") & (table["seed"] == 2))]
    assert shared_stages(fewer, "mIoU", ["alpha", "beta"]) == [["alpha"], ["beta"]]
    speed, fit = pareto_charts(table, floors=frozenset({"floor"}))[0].rows[0]
    point = next(p for p in speed.points if p.methods == ("alpha", "beta"))
    assert point.label == "alpha = beta"
    assert point.x == pytest.approx(2.1)  # mean of the two speeds
    assert point.x_low <= 2.0 and point.x_high >= 2.2  # the bar spans both
    fit_point = next(p for p in fit.points if p.methods == ("alpha", "beta"))
    assert fit_point.x_low <= 800.0 and fit_point.x_high >= 1000.0


def test_the_ceiling_is_the_mean_over_the_charted_scenes_and_absent_where_not_measured():
    ceilings = {("release", "paper", "agnostic"): {"s1": {0: 0.8}, "s2": {0: 0.9}}}
    panel = pareto_charts(_table(_runs()), floors=frozenset({"floor"}), ceilings=ceilings)[0].rows[0][0]
    assert panel.ceiling == pytest.approx(85.0) and panel.ceiling_note == ""
    half = {("release", "paper", "agnostic"): {"s1": {0: 0.8}}}
    panel = pareto_charts(_table(_runs()), floors=frozenset({"floor"}), ceilings=half)[0].rows[0][0]
    assert panel.ceiling is None and "1 of these 2 scenes" in panel.ceiling_note
    other = {("paper-text", "paper", "agnostic"): {"s1": {0: 0.8}, "s2": {0: 0.9}}}  # another protocol's ceiling
    panel = pareto_charts(_table(_runs()), floors=frozenset({"floor"}), ceilings=other)[0].rows[0][0]
    assert panel.ceiling is None and "no perfect-feature ceiling" in panel.ceiling_note
    novel = {("release", "novel-view", "agnostic"): {"s1": {0: 0.8}, "s2": {0: 0.9}}}  # another split's is not either
    panel = pareto_charts(_table(_runs()), floors=frozenset({"floor"}), ceilings=novel)[0].rows[0][0]
    assert panel.ceiling is None


def test_each_split_gets_its_own_chart_with_its_ceiling_over_the_scene_seeds_its_runs_used():
    rows = [{**r, "split": "paper", "scene_seed": r["seed"]} for r in _runs()]
    rows += [{**r, "split": "novel-view", "scene_seed": r["seed"], "mIoU": r["mIoU"] - 10} for r in _runs()]
    table = _table(rows)
    seeds = sorted(set(table["seed"]))
    ceilings = {("release", "paper", "agnostic"): {s: {k: 0.5 + 0.1 * k for k in seeds} for s in SCENES},
                ("release", "novel-view", "agnostic"): {s: {k: 0.4 for k in seeds} for s in SCENES}}
    charts = {c.split: c for c in pareto_charts(table, floors=frozenset({"floor"}), ceilings=ceilings)}
    assert sorted(charts) == ["novel-view", "paper"]
    assert charts["paper"].stem.endswith("_release_paper") and charts["novel-view"].stem.endswith("_novel-view")
    paper = charts["paper"].rows[0][0]
    assert paper.ceiling == pytest.approx(100 * float(np.mean([0.5 + 0.1 * k for k in seeds])))
    assert charts["novel-view"].rows[0][0].ceiling == pytest.approx(40.0)
    missing = {("release", "paper", "agnostic"): {s: {0: 0.5} for s in SCENES}}  # only scene seed 0 measured
    panel = next(c for c in pareto_charts(table, floors=frozenset({"floor"}), ceilings=missing)
                 if c.split == "paper").rows[0][0]
    assert panel.ceiling is None


def test_each_kind_of_machine_gets_its_own_chart_named_in_the_title(tmp_path):
    rows = _runs()
    gpu = [{**r, "device": "cuda", "fps_agnostic": r["fps_agnostic"] * 30} for r in _runs() if r["method"] != "floor"]
    for r in gpu:
        r["seed"] += 10
    table = _table(rows + gpu)
    charts = pareto_charts(table, floors=frozenset({"floor"}))
    assert sorted((c.machine, c.stem) for c in charts) == [
        ("cpu", "pareto_synthetic_oracle_release_paper_cpu"), ("cuda", "pareto_synthetic_oracle_release_paper_cuda")]
    cuda = next(c for c in charts if c.machine == "cuda")
    assert cuda.rows[0][0].points[0].x == pytest.approx(2.1 * 30)  # GPU speeds never mixed with CPU ones
    # machine_kind (when recorded) names the machine; a run without one falls back to its device
    kinds = machine_kinds(_table([_run("a", "s1", 0, miou=1.0, machine_kind="xeon-2c"),
                                  _run("a", "s1", 1, miou=1.0, machine_kind=None),
                                  _run("a", "s1", 2, miou=1.0, device=None, machine_kind="H200", ),
                                  _run("a", "s1", 3, miou=1.0, device="cuda", machine_kind="H200"),
                                  _run("a", "s1", 4, miou=1.0, device=None)]))
    assert kinds.tolist() == ["cpu: xeon-2c", "cpu", "H200", "cuda: H200", "unknown"]
    # two CPU kinds: two charts even on one device
    mixed = [{**r, "machine_kind": "epyc" if r["seed"] == 0 else "xeon"} for r in _runs()]
    assert sorted(c.machine for c in pareto_charts(_table(mixed), floors=frozenset({"floor"}))) == ["cpu: epyc",
                                                                                                    "cpu: xeon"]


def test_a_time_sensitive_panel_whose_methods_are_all_at_chance_says_so():
    rows = []
    for scene in SCENES:
        for seed in SEEDS:
            wobble = (-4.0, 1.0, 3.0)[seed] + (1.0 if scene == "s2" else -1.0)
            rows += [_run("alpha", scene, seed, miou=60.0, acc=50.0 + wobble, auc=50.0 + wobble),
                     _run("gamma", scene, seed, miou=40.0, acc=48.0 - wobble, auc=50.0 - wobble),
                     _run("floor", scene, seed, miou=30.0, acc=60.0)]
    table = _table(rows)
    assert at_chance(table, ["alpha", "gamma"])
    chart = pareto_charts(table, floors=frozenset({"floor"}))[0]
    sensitive = chart.rows[1]
    assert all(p.at_chance for p in sensitive) and not any(p.at_chance for p in chart.rows[0])
    # one method that orders the states is enough to make the panel meaningful
    good = table.copy()
    good.loc[good["method"] == "alpha", "AUC"] = 95.0 + good.loc[good["method"] == "alpha", "seed"]
    assert not at_chance(good, ["alpha", "gamma"])
    assert not pareto_charts(good, floors=frozenset({"floor"}))[0].rows[1][0].at_chance
    assert not at_chance(table[(table["seed"] == 0) & (table["scene"] == "s1")], ["alpha"])  # one value: no spread


def test_labels_of_points_whose_bars_and_labels_overlap_are_stacked_into_one():
    def point(name: str, x: float, y: float, low: float, high: float) -> ChartPoint:
        return ChartPoint((name,), x, low, high, y, 0.0)

    near = [point("a", 8.0, 61.2, 5.0, 11.0), point("b", 16.0, 62.3, 8.5, 25.0), point("c", 10.0, 40.0, 7.0, 13.0)]
    assert label_clusters(near, x_span=2.0, y_span=30.0) == [[1, 0], [2]]
    apart = [point("a", 8.0, 61.2, 7.0, 9.0), point("b", 80.0, 62.3, 70.0, 90.0)]
    assert label_clusters(apart, x_span=2.0, y_span=30.0) == [[0], [1]]


def test_the_written_chart_draws_floor_and_ceiling_lines(tmp_path, monkeypatch):
    import benchmark.plots as plots
    from benchmark.core.protocol import PROTOCOLS

    root = tmp_path / "results"
    for row in _runs():
        doc = {"method": row["method"], "dataset": "synthetic", "scene": row["scene"], "track": "oracle",
               "seed": row["seed"], "split": "paper", "splits": ["test"], "protocol": PROTOCOLS["release"].to_dict(),
               "metrics": {"mIoU": row["mIoU"], "mAcc": 90.0, "agnostic_queries": 3, "sensitive_queries": 0,
                           "frames_scored": 10},
               "timing": {"fit_seconds": row["fit_seconds"], "fit_cached": False,
                          "query_agnostic": {"seconds_per_frame": 1 / row["fps_agnostic"], "fps": row["fps_agnostic"]}},
               "memory": {"peak_cpu_mib": 100.0, "peak_gpu_mib": None},
               "environment": {"device": "cpu", "git": {"commit": "abc", "dirty": False}},
               "scene_info": {"generated": {"preset": row["scene"], "size": 128, "seed": 0, "digest": "d" * 24}},
               "scores": {"queries": [], "frames": [], "skipped": []}}
        write_results(results_path(root, "synthetic", row["scene"], row["method"], "oracle", row["seed"]), doc)
    ceiling = tmp_path / "ceiling.json"
    measured = {"scene_version": {"current": True}, "variants": {"release": {"mIoU": 0.85}}}
    write_json(ceiling, {"scenes": {s: {"splits": {"paper": {"seeds": {"0": measured}}}} for s in SCENES}})
    monkeypatch.setattr(plots, "floor_methods", lambda: frozenset({"floor"}))
    drawn: list = []
    real_save = plots._save

    def keep(fig, stem):
        drawn.append([(line.get_label(), list(line.get_ydata())) for ax in fig.axes for line in ax.get_lines()])
        return real_save(fig, stem)

    monkeypatch.setattr(plots, "_save", keep)
    written = pareto(root, tmp_path / "reports", ceiling=ceiling)
    assert sorted(p.name for p in written) == ["pareto_synthetic_oracle_release_paper.pdf",
                                               "pareto_synthetic_oracle_release_paper.png"]
    labels = [label for label, _ in drawn[0]]
    assert sum(label.startswith("2D floor floor (not ranked)") for label in labels) == 2  # one per panel
    ceilings = [ys for label, ys in drawn[0] if label.startswith("perfect-feature ceiling")]
    assert len(ceilings) == 2 and all(ys[0] == pytest.approx(85.0) for ys in ceilings)


def test_floor_lines_closer_than_a_label_share_one_label():
    from benchmark.plots import LABEL_LINE_HEIGHT, line_label_groups

    gap = LABEL_LINE_HEIGHT * 100.0
    assert line_label_groups([64.2, 30.0, 64.18], y_span=100.0) == [[1], [2, 0]]
    assert line_label_groups([10.0, 10.0 + 1.01 * gap], y_span=100.0) == [[0], [1]]
    assert line_label_groups([], y_span=100.0) == []


def test_a_missing_machine_kind_of_any_form_falls_back_to_the_device():
    table = _table([_run("a", "s1", 0, miou=1.0, machine_kind="xeon"), _run("a", "s1", 1, miou=1.0)])
    table["machine_kind"] = pd.array(["xeon", pd.NA], dtype="string")
    assert machine_kinds(table).tolist() == ["cpu: xeon", "cpu"]


def test_every_method_of_a_chart_gets_a_colour_of_its_own():
    from benchmark.plots import method_colours

    for count in (3, 10, 14, 20):
        names = [f"m{i:02d}" for i in range(count)]
        colours = method_colours(names)
        assert len({str(c) for c in colours.values()}) == count, count
