"""Leaderboard, CSVs and charts regenerate deterministically from results files."""

from __future__ import annotations

import math
import random
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from benchmark.core.errors import InputError
from benchmark.core.protocol import PROTOCOLS
from benchmark.leaderboard import build_leaderboard
from benchmark.plots import chart_points, label_groups, pareto, pareto_front, timeline, write_png
from benchmark.results import MEAN_SCENE, find_results, load_results, results_path, runs_table, seed_summary, write_results

# (method, scene, seed) -> mIoU; Acc = mIoU - 10; fps and fit time per method
MIOU = {("alpha", "s1"): [50.0, 52.0, 54.0], ("alpha", "s2"): [60.0, 60.0, 60.0],
        ("beta", "s1"): [70.0, 71.0, 72.0], ("beta", "s2"): [40.0, 44.0, 48.0]}
FPS = {"alpha": 100.0, "beta": 2.0, "gamma": 1.0, "delta": 1.0, "epsilon": 1.0, "zeta": 1.0, "nearest-frame": 1.0}
FIT = {"alpha": 0.5, "beta": 300.0, "gamma": 10.0, "delta": 10.0, "epsilon": 10.0, "zeta": 10.0, "nearest-frame": 1.0}


def _doc(method: str, scene: str, seed: int, miou: float) -> dict:
    frames = []
    for i, t in enumerate(range(0, 20, 2)):
        frames.append({"scene": scene, "query": "cracked cookie", "kind": "sensitive", "frame": f"f{t:03d}",
                       "time_index": t, "camera_id": "0", "iou": 0.5, "acc": 0.9, "pred_pixels": 3,
                       "gt_pixels": 4, "score": 0.1 * (i % 5), "smoothed": 0.1 * (i % 5) + 0.01,
                       "decision": i % 5 >= 2, "label": 6 <= t <= 12})
    return {"method": method, "dataset": "synthetic", "scene": scene, "track": "oracle", "seed": seed,
            "splits": ["test"], "protocol": PROTOCOLS["release"].to_dict(),
            "metrics": {"mIoU": miou, "mAcc": 90.0 + seed, "Acc": miou - 10.0, "vIoU": miou / 2,
                        "agnostic_queries": 3, "sensitive_queries": 1, "frames_scored": 40},
            "timing": {"fit_seconds": FIT[method], "fit_cached": False,
                       "query_agnostic": {"seconds_per_frame": 1 / FPS[method], "fps": FPS[method]},
                       "query_sensitive": {"seconds_per_frame": 1 / FPS[method], "fps": FPS[method]}},
            "memory": {"peak_cpu_mib": 100.0, "peak_gpu_mib": None},
            "environment": {"device": "cpu", "git": {"commit": "abc", "dirty": False}},
            # a versioned generated scene (no committed digest for these names: comparable)
            "scene_info": {"generated": {"preset": scene, "size": 128, "seed": 0, "digest": "d" * 24}},
            "scores": {"queries": [{"scene": scene, "query": "cracked cookie", "kind": "sensitive", "frames": 10,
                                    "Acc": miou - 10.0, "vIoU": miou / 2, "threshold": 0.2}],
                       "frames": frames, "skipped": []}}


def _write_all(root: Path, order_seed: int) -> None:
    items = [(m, s, seed, v) for (m, s), vals in MIOU.items() for seed, v in enumerate(vals)]
    random.Random(order_seed).shuffle(items)
    for m, s, seed, v in items:
        write_results(results_path(root, "synthetic", s, m, "oracle", seed), _doc(m, s, seed, v))


def test_protocols_get_their_own_tables_floors_are_not_ranked_and_means_show_their_ceiling_share(tmp_path):
    from benchmark.core.atomic import write_json

    root = tmp_path / "results"
    for method, protocol, values in (("alpha", "release", (56.0, 42.0)), ("gamma", "release", (28.0, 21.0)),
                                     ("nearest-frame", "release", (99.0, 99.0)), ("beta", "paper-text", (30.0, 30.0))):
        for scene, v in zip(("s1", "s2"), values):
            doc = {**_doc(method, scene, 0, v), "protocol": PROTOCOLS[protocol].to_dict()}
            write_results(results_path(root, "synthetic", scene, method, "oracle", 0), doc)
    reports = tmp_path / "rep"
    current = {"current": True}
    write_json(reports / "ablations" / "protocol-ceiling.json", {"scenes": {
        "s1": {"scene_version": current, "variants": {"release": {"mIoU": 0.8, "vIoU": 0.5},
                                                      "paper-text": {"mIoU": 0.5, "vIoU": 0.25}}},
        "s2": {"scene_version": current, "variants": {"release": {"mIoU": 0.6, "vIoU": 0.5},
                                                      "paper-text": {"mIoU": 0.5, "vIoU": 0.25}}}}})
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=reports)
    text = (tmp_path / "lb.md").read_text()
    release, paper = text.index("protocol: release (default)"), text.index("protocol: paper-text")
    assert release < paper
    table = text[release:paper].split("### Time-agnostic queries")[1].split("###")[0]
    header = next(line for line in table.splitlines() if line.startswith("| method |")).split("|")
    share = header.index(" % of ceiling (mIoU) ↑ ")
    rows = {line.split("|")[1].strip(): line.split("|") for line in table.splitlines() if line.startswith("| ")}
    assert rows["alpha"][share].strip() == "**70.00**"  # (56 + 42) / 2 = 49 of (80 + 60) / 2 = 70
    assert rows["gamma"][share].strip() == "35.00"
    floor = rows["_nearest-frame (2D floor, not ranked)_"]
    assert floor[share].strip() == "141.43" and "**" not in "|".join(floor)  # above the ceiling, never ranked
    assert list(rows)[-1].startswith("_nearest-frame")  # below the methods it is a floor for
    paper_table = text[paper:].split("### Time-agnostic queries")[1].split("###")[0]
    beta = next(line for line in paper_table.splitlines() if line.startswith("| beta |")).split("|")
    assert beta[share].strip() == "60.00"  # against the paper-text ceiling, not the release one
    assert (reports / "leaderboard_synthetic_oracle_release.csv").is_file()
    # a seed that ran s1 only is in s1's column, not in the mean, nor in the mean's share of the ceiling
    write_results(results_path(root, "synthetic", "s1", "alpha", "oracle", 1),
                  {**_doc("alpha", "s1", 1, 0.0), "protocol": PROTOCOLS["release"].to_dict()})
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=reports)
    table = (tmp_path / "lb.md").read_text().split("### Time-agnostic queries")[1].split("###")[0]
    alpha = next(line for line in table.splitlines() if line.startswith("| alpha |")).split("|")
    assert alpha[2].strip().startswith("**28.00") and alpha[share].strip() == "**70.00**"


def test_summary_means_stds_and_dataset_mean_per_seed(tmp_path):
    _write_all(tmp_path / "results", 0)
    # an ablation run (config changed on purpose) is never a leaderboard entry
    write_results(results_path(tmp_path / "results" / "ablations" / "states-k2", "synthetic", "s1", "alpha", "oracle", 0),
                  _doc("alpha", "s1", 0, 99.0))
    runs = runs_table(find_results(tmp_path / "results"))
    assert len(runs) == 12
    summary = seed_summary(runs)
    row = summary[(summary.method == "beta") & (summary.scene == "s2")].iloc[0]
    assert row["mIoU_mean"] == pytest.approx(44.0) and row["mIoU_std"] == pytest.approx(4.0)
    mean = summary[(summary.method == "alpha") & (summary.scene == MEAN_SCENE)].iloc[0]
    per_seed = [(50 + 60) / 2, (52 + 60) / 2, (54 + 60) / 2]
    assert mean["mIoU_mean"] == pytest.approx(np.mean(per_seed))
    assert mean["mIoU_std"] == pytest.approx(np.std(per_seed, ddof=1))
    assert mean["seeds"] == 3 and mean["scenes"] == 2


def test_dataset_mean_counts_only_seeds_that_ran_every_scene(tmp_path):
    # gamma: s1 with seeds 0-2, s2 with seed 0 only -> seeds 1 and 2 would average s1 alone
    root = tmp_path / "results"
    for seed, v in enumerate([50.0, 60.0, 70.0]):
        write_results(results_path(root, "synthetic", "s1", "gamma", "oracle", seed), _doc("gamma", "s1", seed, v))
    write_results(results_path(root, "synthetic", "s2", "gamma", "oracle", 0), _doc("gamma", "s2", 0, 90.0))
    # delta: one scene only, complete seeds
    for seed in (0, 1):
        write_results(results_path(root, "synthetic", "s1", "delta", "oracle", seed), _doc("delta", "s1", seed, 99.0))
    summary = seed_summary(runs_table(find_results(root)))
    mean = summary[(summary.method == "gamma") & (summary.scene == MEAN_SCENE)].iloc[0]
    assert mean["mIoU_mean"] == pytest.approx((50 + 90) / 2)  # seed 0 only, not mean(70, 60, 70)
    assert mean["seeds"] == 1 and mean["partial_seeds"] == 2 and mean["scenes"] == 2
    # epsilon: s1 on seed 0 only, s2 on seed 1 only -> no complete seed, an empty mean row
    for seed, scene in ((0, "s1"), (1, "s2")):
        write_results(results_path(root, "synthetic", scene, "epsilon", "oracle", seed), _doc("epsilon", scene, seed, 50.0))
    summary = seed_summary(runs_table(find_results(root)))
    eps = summary[(summary.method == "epsilon") & (summary.scene == MEAN_SCENE)].iloc[0]
    assert math.isnan(eps["mIoU_mean"]) and eps["seeds"] == 0 and eps["partial_seeds"] == 2
    s1 = summary[(summary.method == "gamma") & (summary.scene == "s1")].iloc[0]
    assert s1["mIoU_mean"] == pytest.approx(60.0) and s1["seeds"] == 3  # the scene column keeps every seed
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    table = (tmp_path / "lb.md").read_text().split("### Time-agnostic queries")[1].split("###")[0]
    gamma = next(line for line in table.splitlines() if line.startswith("| gamma |"))
    delta = next(line for line in table.splitlines() if line.startswith("| delta |"))
    assert gamma.endswith("| 2/2 | 1 (+2 partial) |") and delta.endswith("| 1/2 | 2 |")
    epsilon = next(line for line in table.splitlines() if line.startswith("| epsilon |"))
    assert epsilon.endswith("| 2/2 | 0 (+2 partial) |")  # listed, with no mean
    # delta's mean (99, one scene) is higher but not comparable with gamma's two-scene 70: nobody ranks
    # first in the mean column (columns: method, s1, s2, mean, ...)
    assert gamma.split("|")[4].strip() == "70.00" and delta.split("|")[4].strip() == "99.00 ± 0.00"
    assert "**99.00 ± 0.00**" in delta.split("|")[2]  # the per-scene column still ranks s1


def test_leaderboard_is_deterministic_marks_best_and_separates_paper_numbers(tmp_path):
    outputs = []
    for order in (0, 1):
        base = tmp_path / f"run{order}"
        _write_all(base / "results", order)
        build_leaderboard(base / "results", markdown=base / "leaderboard.md", reports_dir=base / "reports")
        files = sorted(p.relative_to(base) for p in (base / "reports").iterdir())
        outputs.append({str(p): (base / p).read_bytes() for p in files} | {"md": (base / "leaderboard.md").read_bytes()})
    # same files written in another order -> byte-identical outputs (results dir label aside)
    first, second = ({k: v.replace(b"run0", b"runX").replace(b"run1", b"runX") for k, v in o.items()} for o in outputs)
    assert first == second
    md = outputs[0]["md"].decode()
    assert md.startswith("<!-- GENERATED by `bench4d leaderboard`")
    assert "mIoU ↑" in md and "fit (s) ↓" in md and "query FPS ↑" in md
    agnostic = md.split("### Time-agnostic queries")[1].split("###")[0]
    alpha_row = next(line for line in agnostic.splitlines() if line.startswith("| alpha |"))
    beta_row = next(line for line in agnostic.splitlines() if line.startswith("| beta |"))
    assert "**52.00 ± 2.00**" not in alpha_row and "52.00 ± 2.00" in alpha_row  # alpha s1 is not best
    assert "**71.00 ± 1.00**" in beta_row  # beta s1 best
    assert "**0.5 ± 0**" in alpha_row and "**100 ± 0**" in alpha_row  # fit: lower is better; FPS: higher
    assert "**57.50 ± 2.50**" in beta_row  # dataset mean per seed (70+40)/2, (71+44)/2, (72+48)/2
    # paper numbers: their own clearly marked tables, never rows of our tables
    assert "Paper, reported" in md and "4D LangSplat (paper)" in md
    assert "(paper)" not in agnostic
    runs_csv = pd.read_csv(tmp_path / "run0" / "reports" / "runs.csv")
    assert len(runs_csv) == 12 and set(runs_csv["method"]) == {"alpha", "beta"}
    paper_csv = pd.read_csv(tmp_path / "run0" / "reports" / "paper_numbers.csv")
    assert ((paper_csv.method == "4d-langsplat") & (paper_csv.scene == "chickchicken") & (paper_csv.metric == "Acc")
            ).sum() == 1


def test_a_second_leaderboard_writes_its_csvs_apart_from_the_main_ones(tmp_path):
    """``--csv-dir``: a leaderboard of another results folder keeps the main one's runs.csv as it is, while
    still reading the reports folder's ceiling and linking its reports."""
    from benchmark.cli import main

    _write_all(tmp_path / "results", 0)
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "runs.csv").write_text("the main leaderboard's runs")
    main(["leaderboard", "--results-dir", str(tmp_path / "results"), "--out", str(tmp_path / "reports" / "lb2.md"),
          "--reports-dir", str(tmp_path / "reports"), "--csv-dir", str(tmp_path / "scratch")])
    assert (tmp_path / "reports" / "runs.csv").read_text() == "the main leaderboard's runs"
    assert len(pd.read_csv(tmp_path / "scratch" / "runs.csv")) == 12
    assert (tmp_path / "reports" / "lb2.md").read_text().startswith("<!-- GENERATED by `bench4d leaderboard`")


def test_empty_results_dir_still_renders_paper_numbers(tmp_path):
    (tmp_path / "none").mkdir()
    build_leaderboard(tmp_path / "none", markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    md = (tmp_path / "lb.md").read_text()
    assert "No results yet" in md and "Paper, reported" in md


def test_paper_tables_of_a_missing_results_folder_is_an_error(tmp_path):
    from benchmark.paper_tables import render

    with pytest.raises(InputError, match="results-dir.*no such folder"):
        render(tmp_path / "reslts", tmp_path / "rep")


def test_a_missing_results_folder_is_an_error_and_leaves_the_leaderboard_as_it_was(tmp_path):
    (tmp_path / "lb.md").write_text("the leaderboard a user has")
    with pytest.raises(InputError, match="results-dir.*no such folder"):
        build_leaderboard(tmp_path / "reslts", markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    assert (tmp_path / "lb.md").read_text() == "the leaderboard a user has"
    assert not (tmp_path / "rep").exists()


def test_bad_results_file_is_an_input_error_naming_the_field(tmp_path):
    path = results_path(tmp_path, "synthetic", "s1", "alpha", "oracle", 0)
    write_results(path, _doc("alpha", "s1", 0, 50.0))
    doc = load_results(path)
    doc["metrics"]["mIoU"] = "high"
    import json

    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"metrics\.mIoU"):
        load_results(path)
    path.write_text(json.dumps({"format": "bench4d-run", "version": 99}))
    with pytest.raises(InputError, match="version"):
        load_results(path)


def test_pareto_front_keeps_only_non_dominated_points():
    acc = [50, 70, 60, 40, 70]
    fps = [100, 2, 50, 200, 1]
    assert pareto_front(fps, acc, x_higher_better=True) == [1, 2, 0, 3]  # 4 is dominated by 1
    fit = [1, 300, 10, 0.5, 400]
    assert pareto_front(fit, acc, x_higher_better=False) == [3, 0, 2, 1]
    assert pareto_front([math.nan, 1.0], [1.0, 0.5], x_higher_better=True) == [1]


def test_charts_are_written_as_png_and_pdf(tmp_path):
    _write_all(tmp_path / "results", 0)
    written = pareto(tmp_path / "results", tmp_path / "reports")
    assert sorted(p.name for p in written) == ["pareto_synthetic_oracle_release.pdf", "pareto_synthetic_oracle_release.png"]
    assert all(p.stat().st_size > 1000 for p in written)
    tl = timeline("beta", "s1", "cracked cookie", results_dir=tmp_path / "results", reports_dir=tmp_path / "reports")
    assert {p.suffix for p in tl} == {".png", ".pdf"}
    both = timeline(["alpha", "beta"], "s1", "cracked cookie", results_dir=tmp_path / "results",
                    reports_dir=tmp_path / "reports")
    assert sorted(p.name for p in both) == ["timeline_s1_alpha-vs-beta_cracked-cookie.pdf",
                                            "timeline_s1_alpha-vs-beta_cracked-cookie.png"]
    assert both[0].stat().st_size > tl[0].stat().st_size * 0.9  # two panels
    with pytest.raises(InputError, match="time-sensitive queries"):
        timeline("beta", "s1", "no such query", results_dir=tmp_path / "results", reports_dir=tmp_path / "reports")
    with pytest.raises(InputError, match="no results file"):
        timeline("gamma", "s1", "cracked cookie", results_dir=tmp_path / "results", reports_dir=tmp_path / "reports")


def test_chart_png_is_a_palette_image_close_to_the_full_colour_one_and_reproducible(tmp_path):
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    from PIL import Image

    fig, ax = plt.subplots(figsize=(3, 2))
    # more colours than a palette holds, beside a line
    ax.imshow(np.random.default_rng(0).random((32, 32, 3)), extent=(0.6, 1, 0, 0.4), aspect="auto")
    ax.plot([0, 1], [0, 1], color="#d62728", linewidth=6)
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_title("label")
    write_png(fig, tmp_path / "a.png", dpi=100)
    write_png(fig, tmp_path / "b.png", dpi=100)
    rgba = tmp_path / "rgba.png"
    fig.savefig(rgba, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()
    with Image.open(tmp_path / "a.png") as small, Image.open(rgba) as full:
        assert small.mode == "P" and small.size == full.size
        got, want = np.asarray(small.convert("RGB")), np.asarray(full.convert("RGB"))
    # the line stays one colour (no dithering), and no pixel moves far, with random colours beside it
    line = (want == (214, 39, 40)).all(-1)
    assert line.sum() > 100 and len(np.unique(got[line], axis=0)) == 1
    assert np.abs(got.astype(int) - want).max() < 40
    assert (tmp_path / "a.png").stat().st_size < rgba.stat().st_size


def test_chart_draws_a_fit_time_whose_spread_over_seeds_exceeds_its_mean(tmp_path):
    # a fit of milliseconds: 0.001 s on one seed, 0.1 s on the other (std 0.07 > mean 0.05); the axis
    # limits once came out of log10 of a negative number
    root = tmp_path / "results"
    for seed, fit in enumerate((0.001, 0.1)):
        for scene in ("s1", "s2"):
            doc = _doc("alpha", scene, seed, 50.0)
            doc["timing"]["fit_seconds"] = fit
            write_results(results_path(root, "synthetic", scene, "alpha", "oracle", seed), doc)
            write_results(results_path(root, "synthetic", scene, "beta", "oracle", seed), _doc("beta", scene, seed, 60.0))
    written = pareto(root, tmp_path / "reports")
    assert sorted(p.suffix for p in written) == [".pdf", ".png"] and all(p.stat().st_size > 1000 for p in written)


def test_chart_compares_methods_on_the_scenes_all_of_them_ran(tmp_path):
    _write_all(tmp_path / "results", 0)
    # gamma ran s1 only: the chart's means for everyone are then over s1, not over each one's own scenes
    for seed in range(2):
        write_results(results_path(tmp_path / "results", "synthetic", "s1", "gamma", "oracle", seed),
                      _doc("gamma", "s1", seed, 30.0 + seed))
    runs = runs_table(find_results(tmp_path / "results"))
    means, scenes, common = chart_points(runs, "agnostic")
    assert common and scenes == ["s1"]
    by = means.set_index("method")
    assert by.loc["alpha", "mIoU_mean"] == pytest.approx(52.0)  # s1 seeds 50, 52, 54 (s2 would give 56)
    assert by.loc["beta", "mIoU_mean"] == pytest.approx(71.0)
    assert by.loc["gamma", "mIoU_mean"] == pytest.approx(30.5)
    assert by.loc["gamma", "seeds"] == 2
    # without gamma the two methods share both scenes: the dataset means of the leaderboard
    means, scenes, common = chart_points(runs[runs["method"] != "gamma"], "agnostic")
    assert scenes == ["s1", "s2"]
    assert means.set_index("method").loc["alpha", "mIoU_mean"] == pytest.approx(56.0)
    # no common scene: each method over its own, and the chart says so
    only = runs[((runs["method"] == "alpha") & (runs["scene"] == "s2")) | (runs["method"] == "gamma")]
    means, scenes, common = chart_points(only, "agnostic")
    assert not common and scenes == ["s1", "s2"]
    assert means.set_index("method").loc["alpha", "mIoU_mean"] == pytest.approx(60.0)


def test_coinciding_chart_points_share_one_label():
    # three methods sharing one field land on one spot; a fourth is clearly apart, one is not plotted
    fps = [1.30, 1.58, 1.37, 3858.0, math.nan]
    miou = [47.54, 47.54, 47.54, 64.66, 50.0]
    assert label_groups(fps, miou, x_log=True) == [[0, 1, 2], [3]]
    assert label_groups([1.3, 1.3], [45.6, 47.5], x_log=True) == [[0], [1]]  # same speed, different accuracy
    # a 3-line label centred on 43.8 would run into one at 41.9 on axes spanning 29 points: one stack
    assert label_groups([1.6, 1.6, 1.9], [43.8, 43.8, 41.9], x_log=True, spans=(6.0, 29.0)) == [[0, 1, 2]]
    # on drawn axes spanning 35 points the two share a stacked label, listed top to bottom
    assert label_groups([1.3, 1.3, 1.3], [45.6, 47.5, 47.5], x_log=True, spans=(2.0, 35.0)) == [[1, 2, 0]]
    assert label_groups([10.0, 20.0, 1000.0], [50.0, 50.0, 60.0], x_log=False) == [[0, 1], [2]]
    assert label_groups([], [], x_log=True) == []
    # on the drawn axes (2 decades, 5 points of mIoU) 0.80 and 0.99 FPS at one mIoU are one spot
    assert label_groups([0.80, 0.99, 1.03], [59.4, 59.4, 54.7], x_log=True) == [[0], [1], [2]]
    assert label_groups([0.80, 0.99, 1.03], [59.4, 59.4, 54.7], x_log=True, spans=(2.0, 5.0)) == [[0, 1], [2]]


def test_fit_time_charges_shared_stages_a_run_reused():
    from benchmark.results import fit_seconds_with_shared

    reused = {"timing": {"fit_seconds": 0.2}, "fit": {"info": {"geometry": {"seconds": 600.0},
                                                               "autoencoder": {"seconds": 50.0},
                                                               "field": {"seconds": 250.0, "iterations": 1200}}}}
    assert fit_seconds_with_shared(reused) == pytest.approx(900.0)
    reused["fit"]["info"]["time_varying"] = {"seconds": 100.0}
    assert fit_seconds_with_shared(reused) == pytest.approx(1000.0)
    assert fit_seconds_with_shared({"timing": {"fit_seconds": 3.5}, "fit": {"key": "k"}}) == pytest.approx(3.5)


def test_a_method_that_declines_a_query_kind_is_named_under_that_table(tmp_path):
    root = tmp_path / "results"
    _write_all(root, 0)
    # zeta answers the time-agnostic queries of s1 but leaves its time-sensitive one unanswered
    doc = _doc("zeta", "s1", 0, 65.0)
    doc["metrics"].update({"Acc": None, "vIoU": None, "sensitive_queries": 0})
    doc["unanswered_queries"] = ["cracked cookie"]
    write_results(results_path(root, "synthetic", "s1", "zeta", "oracle", 0), doc)
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    md = (tmp_path / "lb.md").read_text()
    agnostic = md.split("### Time-agnostic queries")[1].split("###")[0]
    sensitive = md.split("### Time-sensitive queries")[1].split("##")[0]
    assert any(line.startswith("| zeta |") for line in agnostic.splitlines())
    assert not any(line.startswith("| zeta |") for line in sensitive.splitlines())
    assert "_Not in this table: zeta (s1): ran these scenes but answered none" in sensitive
    assert "Not in this table" not in agnostic  # every method that ran has a time-agnostic number


def test_cells_that_read_the_same_are_bolded_alike(tmp_path):
    root = tmp_path / "results"
    # two methods sharing one fit can differ past the printed digits (float rounding)
    write_results(results_path(root, "synthetic", "s1", "alpha", "oracle", 0), _doc("alpha", "s1", 0, 70.001))
    write_results(results_path(root, "synthetic", "s1", "beta", "oracle", 0), _doc("beta", "s1", 0, 70.004))
    write_results(results_path(root, "synthetic", "s1", "gamma", "oracle", 0), _doc("gamma", "s1", 0, 69.99))
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    table = (tmp_path / "lb.md").read_text().split("### Time-agnostic queries")[1].split("###")[0]
    rows = {line.split("|")[1].strip(): line.split("|")[2].strip() for line in table.splitlines()
            if line.startswith("| ") and not line.startswith("| method")}
    assert rows == {"alpha": "**70.00**", "beta": "**70.00**", "gamma": "69.99"}


def test_time_sensitive_table_shows_score_auc_ranked_and_near_threshold_share_unranked(tmp_path):
    from benchmark.metrics import near_threshold_fraction, score_auc

    root = tmp_path / "results"
    alpha, beta = _doc("alpha", "s1", 0, 70.0), _doc("beta", "s1", 0, 60.0)
    # beta's scores order the states perfectly; its decisions all sit near the threshold
    for f in beta["scores"]["frames"]:
        f["smoothed"] = 0.2 + (0.005 if f["label"] else -0.005)
    beta["scores"]["frames"][0]["smoothed"] = 0.0  # a negative far below widens the range
    write_results(results_path(root, "synthetic", "s1", "alpha", "oracle", 0), alpha)
    write_results(results_path(root, "synthetic", "s1", "beta", "oracle", 0), beta)
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    table = (tmp_path / "lb.md").read_text().split("### Time-sensitive queries")[1].split("###")[0]
    header = next(line for line in table.splitlines() if line.startswith("| method"))
    names = [c.strip() for c in header.split("|")[1:-1]]
    assert "mean AUC ↑" in names and "near τ (%)" in names
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[1:-1]] for line in table.splitlines()
            if line.startswith("| ") and not line.startswith("| method")}

    def expected(doc):
        frames = doc["scores"]["frames"]
        smoothed = np.array([f["smoothed"] for f in frames])
        labels = np.array([f["label"] for f in frames])
        return 100 * score_auc(smoothed, labels), 100 * near_threshold_fraction(smoothed, 0.2)

    auc_col, near_col = names.index("mean AUC ↑"), names.index("near τ (%)")
    for name, doc in (("alpha", alpha), ("beta", beta)):
        auc, near = expected(doc)
        assert rows[name][auc_col].strip("*") == f"{auc:.2f}"
        assert rows[name][near_col] == f"{near:.2f}"  # never bold
    assert rows["beta"][auc_col] == "**100.00**" and not rows["alpha"][auc_col].startswith("**")
    assert expected(beta)[1] == 90.0  # 9 of 10 decisions within 5 % of the range (0.205 - 0 = 0.205)


def test_paper_tables_put_the_published_numbers_beside_ours_with_rank_agreement(tmp_path):
    from benchmark.cli import main
    from benchmark.paper_tables import AGNOSTIC_METHODS, kendall_tau
    from benchmark.synthetic.digest import expected_digest

    assert kendall_tau({"a": 1, "b": 2, "c": 3}, {"a": 3, "b": 2, "c": 1}) == (pytest.approx(-1.0), 3)
    assert math.isnan(kendall_tau({"a": 1}, {"a": 2, "b": 1})[0])
    # means equal up to their last bits are a tie: tau-b 5 / sqrt(6 * 5), not +1 from summation order
    tied_high = 97.50000000000001
    four = {"a": 1.0, "b": 2.0, "c": 3.0, "d": 4.0}
    assert kendall_tau(four, {"a": 1.0, "b": 2.0, "c": 97.5, "d": tied_high})[0] == pytest.approx(5 / math.sqrt(30))
    assert kendall_tau(four, {"a": 1.0, "b": 2.0, "c": 97.4, "d": 97.5})[0] == pytest.approx(1.0)
    # equal means are a shared best (the last bits of a mean depend on the order the scenes are summed in)
    from benchmark.paper_tables import _agreement

    paper, names = {"a": 90.0, "b": 80.0, "c": 70.0}, {"a": "A", "b": "B", "c": "C"}
    tied = (100 + 100 + 96.66666666666667 + 93.33333333333333) / 4
    assert "is best here: yes (tied with B)._" in _agreement(paper, {"a": tied, "b": 97.5, "c": 50.0}, names)
    assert "is best here: no (best here: B)._" in _agreement(paper, {"a": 97.4, "b": 97.5, "c": 50.0}, names)
    assert "is best here: yes._" in _agreement(paper, {"a": 97.6, "b": 97.5, "c": 50.0}, names)
    root = tmp_path / "results"
    presets = ("americano", "chickchicken", "split-cookie", "espresso", "keyboard", "torchocolate")
    # the paper's order reversed: Feature-3DGS best, 4D LangSplat worst
    for rank, method in enumerate(AGNOSTIC_METHODS):
        for scene in presets:
            current = {"preset": scene, "size": 128, "seed": 0, "digest": expected_digest(scene, 128)}
            write_results(results_path(root, "synthetic", scene, method, "oracle", 0),
                          {**_doc("alpha", scene, 0, 80.0 - 10 * rank), "method": method,
                           "scene_info": {"generated": current}})
    out = tmp_path / "paper-tables.md"
    assert main(["paper-tables", "--results-dir", str(root), "--reports-dir", str(tmp_path / "rep"),
                 "--out", str(out)]) == 0
    text = out.read_text()
    agnostic = text.split("## Time-agnostic queries, HyperNeRF")[1].split("## ")[0]
    row = next(line for line in agnostic.splitlines() if line.startswith("| Feature-3DGS |"))
    assert "| 34.65 / 80.00 |" in row and row.endswith("| 36.63 / 80.00 | 74.02 / 90.00 |")
    assert "Kendall's tau = -1.00" in agnostic and "is best here: no (best here: Feature-3DGS)" in agnostic
    assert "protocol `release`" in text and "held-out frames" in text and "track `oracle`, seeds 0; scored" in text
    assert "## Number of states K" in text and "## Query speed" in text
    # a second seed on one cell: the means stay per cell, and the header says how many cells lack it
    current = {"preset": "keyboard", "size": 128, "seed": 1, "digest": expected_digest("keyboard", 128, 1)}
    write_results(results_path(root, "synthetic", "keyboard", "langsplat", "oracle", 1),
                  {**_doc("alpha", "keyboard", 1, 0.0), "method": "langsplat", "scene_info": {"generated": current}})
    assert main(["paper-tables", "--results-dir", str(root), "--out", str(out)]) == 0
    text = out.read_text()
    assert "seeds 0, 1 (23 of 24 (method, preset) cells have fewer: each cell is the mean of the seeds it has)" in text
    # another protocol's runs are not this table's
    assert main(["paper-tables", "--results-dir", str(root), "--protocol", "paper-text", "--out", str(out)]) == 0
    assert "| 34.65 / – |" in out.read_text()


def test_see_also_links_the_stability_and_capacity_reports_only_where_they_exist(tmp_path):
    _write_all(tmp_path / "results", 0)
    reports = tmp_path / "reports"

    def see_also() -> list[str]:
        build_leaderboard(tmp_path / "results", markdown=tmp_path / "leaderboard.md", reports_dir=reports)
        return [line for line in (tmp_path / "leaderboard.md").read_text().splitlines() if line.startswith("See also")]

    assert see_also() == []
    (reports / "stability").mkdir(parents=True)
    (reports / "stability" / "README.md").write_text("# breaking points\n")
    lines = see_also()
    assert len(lines) == 1 and "(reports/stability/README.md)" in lines[0] and "capacity" not in lines[0]
    (reports / "capacity").mkdir()
    (reports / "capacity" / "README.md").write_text("# capacity\n")
    lines = see_also()
    assert len(lines) == 1 and "(reports/stability/README.md)" in lines[0] and "(reports/capacity/README.md)" in lines[0]


def test_scenes_scored_on_draft_ground_truth_are_named_under_their_tables(tmp_path):
    root = tmp_path / "results"
    _write_all(root, 0)
    build_leaderboard(root, markdown=tmp_path / "plain.md", reports_dir=tmp_path / "rep")
    assert "Draft ground truth" not in (tmp_path / "plain.md").read_text()
    doc = _doc("zeta", "s1", 0, 65.0)
    doc.setdefault("scene_info", {})["draft_queries"] = ["denim shorts", "arms raised"]
    write_results(results_path(root, "synthetic", "s1", "zeta", "oracle", 0), doc)
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    md = (tmp_path / "lb.md").read_text()
    assert "_Draft ground truth: s1 (denim shorts, arms raised)" in md
    assert md.count("Draft ground truth") == 1


def test_runs_record_the_draft_queries_of_their_ground_truth():
    from benchmark.core.annotation import AnnotationSet, Query
    from benchmark.runner import draft_query_texts

    aset = AnnotationSet("toy", queries=[Query(1, "person"), Query(2, "shorts", level="part", review="draft"),
                                         Query(3, "jumping", kind="sensitive", base=1),
                                         Query(4, "shorts up", kind="sensitive", base=2)])
    assert draft_query_texts(aset) == ["shorts", "shorts up"]
