"""Leaderboard, CSVs and charts regenerate deterministically from results files."""

from __future__ import annotations

import json
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
from benchmark.synthetic.digest import expected_digest

# (method, scene, seed) -> mIoU; Acc = mIoU - 10; fps and fit time per method
MIOU = {("alpha", "s1"): [50.0, 52.0, 54.0], ("alpha", "s2"): [60.0, 60.0, 60.0],
        ("beta", "s1"): [70.0, 71.0, 72.0], ("beta", "s2"): [40.0, 44.0, 48.0]}
FPS = {"alpha": 100.0, "beta": 2.0, "gamma": 1.0, "delta": 1.0, "epsilon": 1.0, "zeta": 1.0, "nearest-frame": 1.0}
FIT = {"alpha": 0.5, "beta": 300.0, "gamma": 10.0, "delta": 10.0, "epsilon": 10.0, "zeta": 10.0, "nearest-frame": 1.0}
S1, S2 = "americano", "keyboard"
"""Two official scenes (the leaderboard ranks official scenes only; "s1" and "s2" are other scenes)."""
OFFICIAL = {"s1": S1, "s2": S2}
AGNOSTIC_QUERIES = ("cup", "table", "pitcher")


def _doc(method: str, scene: str, seed: int, miou: float) -> dict:
    """A run with three time-agnostic queries around ``miou`` (their mean is ``miou``) and one time-sensitive."""
    frames = []
    for i, t in enumerate(range(0, 20, 2)):
        frames.append({"scene": scene, "query": "cracked cookie", "kind": "sensitive", "frame": f"f{t:03d}",
                       "time_index": t, "camera_id": "0", "iou": 0.5, "acc": 0.9, "pred_pixels": 3,
                       "gt_pixels": 4, "score": 0.1 * (i % 5), "smoothed": 0.1 * (i % 5) + 0.01,
                       "decision": i % 5 >= 2, "label": 6 <= t <= 12})
    spread = min(2.0, miou, 100.0 - miou)
    acc = max(miou - 10.0, 0.0)
    agnostic = [{"scene": scene, "query": q, "kind": "agnostic", "frames": 10, "mIoU": miou + d * spread,
                 "mAcc": 90.0 + seed} for q, d in zip(AGNOSTIC_QUERIES, (-1, 0, 1))]
    digest = expected_digest(scene, 128) or "d" * 24  # an official preset at its committed version
    return {"method": method, "dataset": "synthetic", "scene": scene, "track": "oracle", "seed": seed,
            "splits": ["test"], "protocol": PROTOCOLS["release"].to_dict(),
            "metrics": {"mIoU": miou, "mAcc": 90.0 + seed, "Acc": acc, "vIoU": miou / 2,
                        "agnostic_queries": 3, "sensitive_queries": 1, "frames_scored": 40},
            "timing": {"fit_seconds": FIT[method], "fit_cached": False,
                       "query_agnostic": {"seconds_per_frame": 1 / FPS[method], "fps": FPS[method]},
                       "query_sensitive": {"seconds_per_frame": 1 / FPS[method], "fps": FPS[method]}},
            "memory": {"peak_cpu_mib": 100.0, "peak_gpu_mib": None},
            "environment": {"device": "cpu", "git": {"commit": "abc", "dirty": False}},
            "scene_info": {"generated": {"preset": scene, "size": 128, "seed": 0, "digest": digest}},
            "scores": {"queries": agnostic + [{"scene": scene, "query": "cracked cookie", "kind": "sensitive",
                                               "frames": 10, "Acc": acc, "vIoU": miou / 2, "threshold": 0.2}],
                       "frames": frames, "skipped": []}}


def _write_all(root: Path, order_seed: int, scenes: dict[str, str] | None = None) -> None:
    """:data:`MIOU`'s runs, written in a shuffled order; ``scenes`` renames s1 and s2 (e.g. :data:`OFFICIAL`)."""
    items = [(m, s, seed, v) for (m, s), vals in MIOU.items() for seed, v in enumerate(vals)]
    random.Random(order_seed).shuffle(items)
    for m, s, seed, v in items:
        scene = (scenes or {}).get(s, s)
        write_results(results_path(root, "synthetic", scene, m, "oracle", seed), _doc(m, scene, seed, v))


def _section(text: str, title: str, after: str = "") -> str:
    """The Markdown from heading ``title`` (after ``after``) to the next heading of its level or higher."""
    start = text.index(title, text.index(after) if after else 0)
    level = title.split(" ")[0]
    rest = text[start + len(title):]
    ends = [rest.find("\n" + "#" * n + " ") for n in range(1, len(level) + 1)]
    ends = [e for e in ends if e >= 0]
    return rest[:min(ends)] if ends else rest


def _rows(table: str) -> dict[str, list[str]]:
    """Method cell -> the row's cells (method first), of the table rows in ``table``."""
    out = {}
    for line in table.splitlines():
        if line.startswith("| ") and not line.startswith("| method") and not line.startswith("|---"):
            cells = [c.strip() for c in line.split("|")[1:-1]]
            out[cells[0]] = cells
    return out


def _header(table: str) -> list[str]:
    line = next(line for line in table.splitlines() if line.startswith("| method"))
    return [c.strip() for c in line.split("|")[1:-1]]


def _ceiling_file(path: Path, measured: dict, version=None) -> None:
    """A ceiling file as ``bench4d ablate ceiling`` writes it: ``measured`` maps (scene, split, scene seed) ->
    variant -> values; ``version(scene, seed)`` is the scene version recorded (default: the committed one)."""
    from benchmark.core.atomic import write_json

    version = version or (lambda scene, seed: {"preset": scene, "size": 128, "seed": seed,
                                               "digest": expected_digest(scene, 128, seed), "current": True})
    scenes: dict = {}
    for (scene, split, seed), variants in measured.items():
        scenes.setdefault(scene, {"splits": {}})["splits"].setdefault(split, {"seeds": {}})["seeds"][str(seed)] = {
            "frames": 5, "split": split, "variants": variants, "scene_version": version(scene, seed)}
    write_json(path, {"format": "bench4d-protocol-ceiling", "version": 2, "scenes": scenes})


def _split_doc(method: str, scene: str, seed: int, miou: float, split: str = "paper", scene_seed: int = 0) -> dict:
    """:func:`_doc` of a run on evaluation split ``split`` that fitted the scene of generator seed ``scene_seed``."""
    doc = _doc(method, scene, seed, miou)
    generated = {**doc["scene_info"]["generated"], "seed": scene_seed,
                 "digest": expected_digest(scene, 128, scene_seed) or "d" * 24}
    return {**doc, "split": split, "scene_seed": scene_seed, "scene_info": {"generated": generated}}


def test_protocols_get_their_own_tables_floors_are_not_ranked_and_means_show_their_ceiling_share(tmp_path):
    root = tmp_path / "results"
    for method, protocol, values in (("alpha", "release", (56.0, 42.0)), ("gamma", "release", (28.0, 21.0)),
                                     ("nearest-frame", "release", (99.0, 99.0)), ("beta", "paper-text", (30.0, 30.0))):
        for scene, v in zip((S1, S2), values):
            doc = {**_split_doc(method, scene, 0, v), "protocol": PROTOCOLS[protocol].to_dict()}
            write_results(results_path(root, "synthetic", scene, method, "oracle", 0), doc)
    reports = tmp_path / "rep"
    _ceiling_file(reports / "ablations" / "protocol-ceiling.json", {
        (S1, "paper", 0): {"release": {"mIoU": 0.8, "vIoU": 0.5}, "paper-text": {"mIoU": 0.5, "vIoU": 0.25}},
        (S2, "paper", 0): {"release": {"mIoU": 0.6, "vIoU": 0.5}, "paper-text": {"mIoU": 0.5, "vIoU": 0.25}}})
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=reports, csv_dir=reports)
    text = (tmp_path / "lb.md").read_text()
    release, paper = text.index("protocol: release (default)"), text.index("protocol: paper-text")
    assert release < paper
    table = _section(text[release:paper], "#### Time-agnostic queries")
    header = _header(table)
    # the ceiling's own value beside the share: (80 + 60) / 2 = 70
    share = header.index("% of ceiling (mIoU 70.00) ↑")
    rows = _rows(table)
    assert rows["alpha"][share].startswith("**70.00 [")  # (56 + 42) / 2 = 49 of 70, its interval beside it
    assert rows["gamma"][share].startswith("35.00 [")
    floor = rows["_nearest-frame (floor, not ranked; answers by relevance)_"]
    assert floor[share].startswith("141.43") and "**" not in "|".join(floor)  # above the ceiling, never ranked
    assert list(rows)[-1].startswith("_nearest-frame")  # below the methods it is a floor for
    paper_table = _section(text[paper:], "#### Time-agnostic queries")
    assert _rows(paper_table)["beta"][_header(paper_table).index("% of ceiling (mIoU 50.00) ↑")].startswith("60.00")
    assert (reports / "leaderboard_synthetic_oracle_release_paper.csv").is_file()
    # a seed that ran one scene only is in that scene's column, not in the mean, nor in the mean's share
    write_results(results_path(root, "synthetic", S1, "alpha", "oracle", 1),
                  {**_split_doc("alpha", S1, 1, 0.0), "protocol": PROTOCOLS["release"].to_dict()})
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=reports)
    table = _section((tmp_path / "lb.md").read_text(), "#### Time-agnostic queries")
    alpha = _rows(table)["alpha"]
    assert alpha[1] == "28.00 ± 39.60" and alpha[share].startswith("**70.00 [")


def test_each_split_s_section_shares_its_own_split_s_ceiling_at_the_scene_seeds_its_runs_fitted(tmp_path):
    root, reports = tmp_path / "results", tmp_path / "rep"
    ceiling = reports / "ablations" / "protocol-ceiling.json"
    for split in ("paper", "novel-view"):
        for scene, v in ((S1, 50.0), (S2, 30.0)):
            for seed in (0, 1):  # alpha: run seed s fitted scene seed s
                write_results(results_path(root, "synthetic", scene, "alpha", "oracle", seed, split=split),
                              _split_doc("alpha", scene, seed, v, split, scene_seed=seed))
            if split == "paper":  # beta: seeds 0 and 1 both fitted scene seed 0
                for seed in (0, 1):
                    write_results(results_path(root, "synthetic", scene, "beta", "oracle", seed, split=split),
                                  _split_doc("beta", scene, seed, v, split, scene_seed=0))
    release = lambda miou: {"release": {"mIoU": miou, "vIoU": 0.5}}  # noqa: E731
    measured = {(S1, "paper", 0): release(0.8), (S1, "paper", 1): release(0.6), (S1, "paper", 2): release(0.0),
                (S2, "paper", 0): release(0.6), (S2, "paper", 1): release(0.4), (S2, "paper", 2): release(0.0),
                (S1, "novel-view", 0): release(0.4), (S1, "novel-view", 1): release(0.2),
                (S2, "novel-view", 0): release(0.2), (S2, "novel-view", 1): release(0.2)}
    _ceiling_file(ceiling, measured)
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=reports)
    text = (tmp_path / "lb.md").read_text()
    paper, novel = text.index("## Split: paper"), text.index("## Split: novel-view")
    table = _section(text[paper:novel], "#### Time-agnostic queries")
    share = _header(table).index("% of ceiling (mIoU) ↑")  # two bounds: no single one in the header
    rows = _rows(table)
    # alpha: scene seeds 0 and 1, each scene the mean over them: ((0.8 + 0.6) / 2 + (0.6 + 0.4) / 2) / 2 = 60
    assert rows["alpha"][share].startswith("66.67 [") and rows["alpha"][share].endswith(" of 60.00")
    # beta: scene seed 0 alone (its seed 1 refitted scene seed 0): (0.8 + 0.6) / 2 = 70
    assert rows["beta"][share].startswith("57.14 [") and rows["beta"][share].endswith(" of 70.00")
    novel_table = _section(text[novel:], "#### Time-agnostic queries")
    # the novel-view split's own ceiling: ((0.4 + 0.2) / 2 + 0.2) / 2 = 25
    assert _rows(novel_table)["alpha"][_header(novel_table).index("% of ceiling (mIoU 25.00) ↑")].startswith("160.00")
    # a scene seed measured on another scene version than the committed one gives no ceiling: none, and why
    for scene in (S1, S2):
        write_results(results_path(root, "synthetic", scene, "alpha", "oracle", 2, split="paper"),
                      _split_doc("alpha", scene, 2, 40.0, "paper", scene_seed=2))
    committed = lambda scene, seed: {"preset": scene, "size": 128, "seed": seed,  # noqa: E731
                                     "digest": expected_digest(scene, 128, seed) if seed < 2 else "f" * 24,
                                     "current": True}  # a stale flag is not trusted: the digest decides
    _ceiling_file(ceiling, measured, committed)
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=reports)
    text = (tmp_path / "lb.md").read_text()
    paper, novel = text.index("## Split: paper"), text.index("## Split: novel-view")
    table = _section(text[paper:novel], "#### Time-agnostic queries")
    share = _header(table).index("% of ceiling (mIoU 70.00) ↑")  # beta's alone
    assert _rows(table)["alpha"][share] == "–" and _rows(table)["beta"][share].startswith("57.14 [")
    assert ("_% of ceiling – on a row: the perfect-feature ceiling (`bench4d ablate ceiling`) has not measured mIoU "
            "on every scene and scene seed of this table under this protocol and split on the committed scene "
            f"version (missing: {S1} scene seed 2, {S2} scene seed 2)._") in table
    assert "% of ceiling (mIoU 25.00)" in text[novel:]


def test_a_ceiling_file_from_before_splits_is_refused_with_a_reason(tmp_path):
    from benchmark.core.atomic import write_json
    from benchmark.leaderboard import load_ceiling_file, load_ceilings

    root, reports = tmp_path / "results", tmp_path / "rep"
    for scene in (S1, S2):
        write_results(results_path(root, "synthetic", scene, "alpha", "oracle", 0, split="paper"),
                      _split_doc("alpha", scene, 0, 50.0))
    path = reports / "ablations" / "protocol-ceiling.json"
    write_json(path, {"scenes": {s: {"scene_version": {"current": True}, "variants": {"release": {"mIoU": 0.8}}}
                                 for s in (S1, S2)}})  # one value per scene: every split's frames mixed
    assert load_ceiling_file(path).refused and load_ceilings(path) == {}
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=reports)
    text = (tmp_path / "lb.md").read_text()
    assert "% of ceiling (" not in text
    assert "is not read: " in text and "was written before the ceiling was measured per evaluation split" in text
    write_json(path, {"scenes": {S1: {"splits": {"paper": {"seeds": {"zero": {"variants": {}}}}}}}})
    with pytest.raises(InputError, match=r"scenes\.americano\.splits\.paper\.seeds\.zero"):
        load_ceiling_file(path)


def test_a_table_without_ceiling_says_why(tmp_path):
    _write_all(tmp_path / "results", 0, OFFICIAL)
    build_leaderboard(tmp_path / "results", markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    text = (tmp_path / "lb.md").read_text()
    assert "% of ceiling (" not in text
    assert text.count("_No ceiling column: the perfect-feature ceiling (`bench4d ablate ceiling`) has no") == 2

def test_a_table_of_real_scenes_says_the_ceiling_needs_a_generated_scene(tmp_path):
    root = tmp_path / "results"
    for scene in ("lego", "standup"):
        for seed in (0, 1):
            doc = {**_doc("alpha", scene, seed, 60.0 + seed), "dataset": "dnerf", "scene_info": {}}
            write_results(results_path(root, "dnerf", scene, "alpha", "oracle", seed), doc)
    _write_all(root, 0, OFFICIAL)
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    real = _section((tmp_path / "lb.md").read_text(), "### dnerf")
    assert real.count("answers from a generated scene's per-pixel truth") == 2  # both kinds' tables
    assert "has no mIoU" not in real
    synthetic = _section((tmp_path / "lb.md").read_text(), "### synthetic")
    assert "per-pixel truth" not in synthetic and "has no mIoU" in synthetic


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
    # gamma: S1 with seeds 0-2, S2 with seed 0 only -> seeds 1 and 2 would average S1 alone
    root = tmp_path / "results"
    for seed, v in enumerate([50.0, 60.0, 70.0]):
        write_results(results_path(root, "synthetic", S1, "gamma", "oracle", seed), _doc("gamma", S1, seed, v))
    write_results(results_path(root, "synthetic", S2, "gamma", "oracle", 0), _doc("gamma", S2, 0, 90.0))
    # delta: one scene only, complete seeds
    for seed in (0, 1):
        write_results(results_path(root, "synthetic", S1, "delta", "oracle", seed), _doc("delta", S1, seed, 99.0))
    summary = seed_summary(runs_table(find_results(root)))
    mean = summary[(summary.method == "gamma") & (summary.scene == MEAN_SCENE)].iloc[0]
    assert mean["mIoU_mean"] == pytest.approx((50 + 90) / 2)  # seed 0 only, not mean(70, 60, 70)
    assert mean["seeds"] == 1 and mean["partial_seeds"] == 2 and mean["scenes"] == 2
    # epsilon: S1 on seed 0 only, S2 on seed 1 only -> no complete seed, an empty mean row
    for seed, scene in ((0, S1), (1, S2)):
        write_results(results_path(root, "synthetic", scene, "epsilon", "oracle", seed), _doc("epsilon", scene, seed, 50.0))
    summary = seed_summary(runs_table(find_results(root)))
    eps = summary[(summary.method == "epsilon") & (summary.scene == MEAN_SCENE)].iloc[0]
    assert math.isnan(eps["mIoU_mean"]) and eps["seeds"] == 0 and eps["partial_seeds"] == 2
    s1 = summary[(summary.method == "gamma") & (summary.scene == S1)].iloc[0]
    assert s1["mIoU_mean"] == pytest.approx(60.0) and s1["seeds"] == 3  # the scene column keeps every seed
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    rows = _rows(_section((tmp_path / "lb.md").read_text(), "#### Time-agnostic queries"))
    assert rows["gamma"][-2:] == ["2/2", "1 (+2 partial)"] and rows["delta"][-2:] == ["1/2", "2"]
    assert rows["epsilon"][-2:] == ["2/2", "0 (+2 partial)"]  # listed, with no mean
    # delta's mean (99, one scene) is higher but not comparable with gamma's two-scene 70: nobody ranks
    # first in the mean column (columns: method, S1, S2, mean, ...)
    assert rows["gamma"][3].startswith("70.00 [") and rows["delta"][3].startswith("99.00 [")
    assert rows["delta"][1] == "**99.00 ± 0.00**"  # the per-scene column still ranks S1 (its interval is apart)
    assert list(rows) == ["gamma", "delta", "epsilon"]  # ranked first, then the methods with fewer scenes


def test_leaderboard_is_deterministic_ties_overlapping_intervals_and_separates_paper_numbers(tmp_path):
    outputs = []
    for order in (0, 1):
        base = tmp_path / f"run{order}"
        _write_all(base / "results", order, OFFICIAL)
        build_leaderboard(base / "results", markdown=base / "leaderboard.md", reports_dir=base / "reports",
                          csv_dir=base / "reports")
        files = sorted(p.relative_to(base) for p in (base / "reports").iterdir())
        outputs.append({str(p): (base / p).read_bytes() for p in files} | {"md": (base / "leaderboard.md").read_bytes()})
    # same files written in another order -> byte-identical outputs (results dir label aside)
    first, second = ({k: v.replace(b"run0", b"runX").replace(b"run1", b"runX") for k, v in o.items()} for o in outputs)
    assert first == second
    md = outputs[0]["md"].decode()
    assert md.startswith("<!-- GENERATED by `bench4d leaderboard`")
    assert "**mean mIoU** [95 % CI] ↑" in md and "fit (s) ↓" in md and "query FPS ↑" in md
    agnostic = _section(md, "#### Time-agnostic queries")
    rows, header = _rows(agnostic), _header(agnostic)
    assert rows["alpha"][1] == "52.00 ± 2.00" and rows["beta"][1] == "**71.00 ± 1.00**"  # S1: apart, beta best
    assert rows["alpha"][header.index("fit (s) ↓")] == "**0.5 ± 0**"  # fit: lower is better
    assert rows["alpha"][header.index("query FPS ↑")] == "**100 ± 0**"  # FPS: higher
    # the means (beta 57.5: 40 to 48 on S2 over seeds; alpha 56) overlap: one tie group, nobody bold
    mean = header.index("**mean mIoU** [95 % CI] ↑")
    assert rows["beta"][mean].startswith("57.50 [") and rows["alpha"][mean].startswith("56.00 [")
    assert rows["beta"][header.index("tie group")] == rows["alpha"][header.index("tie group")] == "1"
    assert list(rows) == ["beta", "alpha"]  # ordered by mean
    p_next = float(rows["beta"][header.index("P(> next)")])
    assert p_next == pytest.approx(((3 * 3 + 0) / 9 + (0 + 0) / 9) / 2)  # beta beats alpha on every S1 pair only
    assert "_Tie group 1 (95 % intervals of mean mIoU overlapping the best's): beta, alpha: no single best._" in agnostic
    lo, hi = (float(v) for v in rows["beta"][mean].split("[")[1].rstrip("]").split(", "))
    assert lo < 57.5 < hi and hi - lo < 20
    # paper numbers: their own clearly marked tables, never rows of our tables
    assert "Paper, reported" in md and "4D LangSplat (paper)" in md
    assert "(paper)" not in agnostic
    runs_csv = pd.read_csv(tmp_path / "run0" / "reports" / "runs.csv")
    assert len(runs_csv) == 12 and set(runs_csv["method"]) == {"alpha", "beta"}
    table_csv = pd.read_csv(tmp_path / "run0" / "reports" / "leaderboard_synthetic_oracle_release_legacy-dense.csv")
    beta = table_csv[(table_csv.method == "beta") & (table_csv.scene == MEAN_SCENE)].iloc[0]
    assert beta["mIoU_lo"] == pytest.approx(lo, abs=0.01) and beta["mIoU_tie_group"] == 1
    paper_csv = pd.read_csv(tmp_path / "run0" / "reports" / "paper_numbers.csv")
    assert ((paper_csv.method == "4d-langsplat") & (paper_csv.scene == "chickchicken") & (paper_csv.metric == "Acc")
            ).sum() == 1


def test_leaderboard_out_writes_only_what_it_is_asked_for(tmp_path, monkeypatch):
    """``--out`` writes that file alone; CSVs only where ``--csv-dir`` says; without ``--out`` the repository's
    leaderboard and its CSVs in the reports folder."""
    from benchmark.cli import main

    _write_all(tmp_path / "results", 0, OFFICIAL)
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "runs.csv").write_text("the main leaderboard's runs")
    main(["leaderboard", "--results-dir", str(tmp_path / "results"), "--out", str(tmp_path / "lb2.md"),
          "--reports-dir", str(tmp_path / "reports")])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lb2.md", "reports", "results"]
    assert [p.name for p in (tmp_path / "reports").iterdir()] == ["runs.csv"]
    assert (tmp_path / "reports" / "runs.csv").read_text() == "the main leaderboard's runs"
    main(["leaderboard", "--results-dir", str(tmp_path / "results"), "--out", str(tmp_path / "reports" / "lb2.md"),
          "--reports-dir", str(tmp_path / "reports"), "--csv-dir", str(tmp_path / "scratch")])
    assert (tmp_path / "reports" / "runs.csv").read_text() == "the main leaderboard's runs"
    assert len(pd.read_csv(tmp_path / "scratch" / "runs.csv")) == 12
    assert (tmp_path / "reports" / "lb2.md").read_text().startswith("<!-- GENERATED by `bench4d leaderboard`")
    monkeypatch.chdir(tmp_path)
    main(["leaderboard"])
    assert (tmp_path / "leaderboard.md").is_file() and len(pd.read_csv(tmp_path / "reports" / "runs.csv")) == 12


def test_a_method_that_declines_a_query_kind_is_named_under_that_table(tmp_path):
    root = tmp_path / "results"
    _write_all(root, 0, OFFICIAL)
    # zeta answers the time-agnostic queries of S1 but leaves its time-sensitive one unanswered
    doc = _doc("zeta", S1, 0, 65.0)
    doc["metrics"].update({"Acc": None, "vIoU": None, "sensitive_queries": 0})
    doc["scores"]["queries"] = [q for q in doc["scores"]["queries"] if q["kind"] == "agnostic"]
    doc["scores"]["frames"] = []
    doc["unanswered_queries"] = ["cracked cookie"]
    write_results(results_path(root, "synthetic", S1, "zeta", "oracle", 0), doc)
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    md = (tmp_path / "lb.md").read_text()
    agnostic = _section(md, "#### Time-agnostic queries")
    sensitive = _section(md, "#### Time-sensitive queries")
    assert "zeta" in _rows(agnostic) and "zeta" not in _rows(sensitive)
    assert f"_Not in this table: zeta ({S1}): ran these scenes but answered none" in sensitive
    assert "Not in this table" not in agnostic  # every method that ran has a time-agnostic number


def test_an_unanswered_query_counts_zero_and_coverage_is_shown(tmp_path):
    """A hand-made submission with one failed query listed as unanswered ranks at its full mean, not above it."""
    root = tmp_path / "results"
    for method, unanswered in (("alpha", False), ("beta", True)):
        for scene in (S1, S2):
            doc = _doc(method, scene, 0, 60.0)
            if unanswered:  # beta answers two of the three time-agnostic queries: 58 and 60 (its own mean: 59)
                doc["scores"]["queries"] = [q for q in doc["scores"]["queries"] if q["query"] != "pitcher"]
                doc["metrics"]["mIoU"] = 59.0
                doc["unanswered_queries"] = ["pitcher"]
            write_results(results_path(root, "synthetic", scene, method, "oracle", 0), doc)
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    table = _section((tmp_path / "lb.md").read_text(), "#### Time-agnostic queries")
    rows, header = _rows(table), _header(table)
    assert rows["beta"][1] == "39.33"  # (58 + 60 + 0) / 3, not 59
    assert rows["beta"][header.index("**mean mIoU** [95 % CI] ↑")].startswith("39.33 [")
    assert rows["beta"][header.index("answered / asked")] == "4/6"
    assert rows["alpha"][header.index("answered / asked")] == "6/6"
    assert list(rows) == ["alpha", "beta"]


def test_only_official_scenes_are_ranked_others_are_listed_apart(tmp_path):
    root = tmp_path / "results"
    _write_all(root, 0, OFFICIAL)
    build_leaderboard(root, markdown=tmp_path / "before.md", reports_dir=tmp_path / "rep")
    # a user's smoke run, and a scene named after a preset but generated from another one
    write_results(results_path(root, "synthetic", "smoke", "alpha", "oracle", 0), _doc("alpha", "smoke", 0, 5.0))
    imposter = _doc("beta", "espresso", 0, 99.0)
    imposter["scene_info"]["generated"]["preset"] = "smoke"
    imposter["scene_info"]["generated"]["digest"] = expected_digest("smoke", 128)
    write_results(results_path(root, "synthetic", "espresso", "beta", "oracle", 0), imposter)
    build_leaderboard(root, markdown=tmp_path / "after.md", reports_dir=tmp_path / "rep")
    before, after = (tmp_path / "before.md").read_text(), (tmp_path / "after.md").read_text()
    ranked = after[:after.index("## Other scenes (not ranked)")]
    assert _section(ranked, "#### Time-agnostic queries") == _section(before, "#### Time-agnostic queries")
    other = _section(after, "## Other scenes (not ranked)")
    rows = _rows(_section(other, "#### Time-agnostic queries"))
    assert rows["alpha"][2] == "5.00" and rows["beta"][1] == "99.00"  # columns: espresso, smoke
    assert not any(c.startswith("**") for r in rows.values() for c in r)  # nothing ranked


def test_eval_on_a_scene_that_is_not_official_says_where_its_results_went(capsys):
    from benchmark.commands.eval import _say_if_unranked

    _say_if_unranked({"dataset": "synthetic", "scene": "smoke", "scene_info": {}}, Path("results/x/seed0.json"))
    out = capsys.readouterr().out
    assert "results: results/x/seed0.json" in out and "Other scenes (not ranked)" in out
    _say_if_unranked({"dataset": "synthetic", "scene": S1, "scene_info": {"generated": {"preset": S1}}}, Path("p"))
    assert capsys.readouterr().out == ""


def test_official_scenes_are_registered_presets_and_annotated_dnerf_scenes():
    from benchmark.core.official import OFFICIAL_SCENES
    from benchmark.synthetic.presets import PRESETS

    assert set(OFFICIAL_SCENES["synthetic"]) <= set(PRESETS) and "smoke" not in OFFICIAL_SCENES["synthetic"]
    root = Path(__file__).resolve().parents[1] / "annotations" / "scenes" / "dnerf"
    assert all((root / f"{scene}.json").is_file() for scene in OFFICIAL_SCENES["dnerf"])


def test_results_from_a_dirty_checkout_are_refused_unless_allowed_and_then_marked(tmp_path):
    from benchmark.cli import main

    root = tmp_path / "results"
    _write_all(root, 0, OFFICIAL)
    build_leaderboard(root, markdown=tmp_path / "clean.md", reports_dir=tmp_path / "rep")
    assert "‡" not in (tmp_path / "clean.md").read_text()  # no legend for a mark nobody carries
    doc = _doc("alpha", S1, 0, 50.0)
    doc["environment"]["code_changed_during_run"] = True
    write_results(results_path(root, "synthetic", S1, "alpha", "oracle", 0), doc)
    (tmp_path / "lb.md").write_text("the leaderboard a user has")
    with pytest.raises(InputError, match=r"seed0\.json: environment\.code_changed_during_run: 1 results file"):
        build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    assert (tmp_path / "lb.md").read_text() == "the leaderboard a user has"
    assert main(["leaderboard", "--results-dir", str(root), "--out", str(tmp_path / "lb.md"), "--allow-dirty",
                 "--reports-dir", str(tmp_path / "rep")]) == 0
    md = (tmp_path / "lb.md").read_text()
    rows = _rows(_section(md, "#### Time-agnostic queries"))
    assert "alpha ‡" in rows and "beta" in rows
    assert "_‡: some of this row's runs come from a checkout with uncommitted code changes" in md
    from benchmark.paper_tables import render

    with pytest.raises(InputError, match="--allow-dirty"):
        render(root, tmp_path / "rep")
    assert "Paper: " in render(root, tmp_path / "rep", allow_dirty=True)


@pytest.mark.parametrize("where, value, field", [
    ("metrics.mIoU", 1e308, "metrics.mIoU"), ("metrics.Acc", -5.0, "metrics.Acc"),
    ("scores.queries.0.mIoU", 250.0, r"scores.queries\[0\].mIoU"),
    ("timing.query_agnostic.fps", -1.0, "timing.query_agnostic.fps"), ("metrics.vIoU", math.inf, None)])
def test_metrics_out_of_range_or_not_finite_are_refused_naming_file_and_field(tmp_path, where, value, field):
    root = tmp_path / "results"
    path = results_path(root, "synthetic", S1, "alpha", "oracle", 0)
    write_results(path, _doc("alpha", S1, 0, 50.0))
    doc = json.loads(path.read_text())
    node = doc
    *parents, last = where.split(".")
    for key in parents:
        node = node[int(key)] if key.isdigit() else node[key]
    node[last] = value
    path.write_text(json.dumps(doc))  # Infinity as Python writes it
    with pytest.raises(InputError, match=r"seed0\.json" + (f": {field}" if field else "")):
        build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    assert not (tmp_path / "lb.md").exists()


def test_names_from_files_are_escaped_in_the_markdown(tmp_path):
    from benchmark.leaderboard import md as escape

    assert escape("a|b") == "a\\|b" and escape("<b>x</b>") == "&lt;b&gt;x&lt;/b&gt;"
    assert escape("**big** [x](y) `c` a_b\nnext\x1b[2J") == "\\*\\*big\\*\\* \\[x\\](y) \\`c\\` a\\_b next \\[2J"
    root = tmp_path / "results"
    _write_all(root, 0, OFFICIAL)
    write_results(results_path(root, "synthetic", S1, "m|<img src=x>", "oracle", 0), _doc("alpha", S1, 0, 50.0)
                  | {"method": "m|<img src=x>"})
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    md = (tmp_path / "lb.md").read_text()
    assert "<img" not in md and "m\\|&lt;img src=x&gt;" in md
    table = _section(md, "#### Time-agnostic queries")
    widths = {len(line.replace("\\|", "").split("|")) for line in table.splitlines() if line.startswith("|")}
    assert len(widths) == 1  # every row has the header's cells


def test_methods_sharing_a_time_agnostic_field_are_marked_with_the_stage_they_share(tmp_path):
    root = tmp_path / "results"
    for method, key in (("alpha", "field-1"), ("gamma", "field-1"), ("beta", "field-2")):
        for scene in (S1, S2):
            doc = _doc(method, scene, 0, 60.0 if method != "beta" else 50.0)
            doc["fit"] = {"key": f"{method}-{scene}", "info": {"key": f"{key}-{scene}"}}
            write_results(results_path(root, "synthetic", scene, method, "oracle", 0), doc)
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    md = (tmp_path / "lb.md").read_text()
    agnostic = _section(md, "#### Time-agnostic queries")
    assert set(_rows(agnostic)) == {"alpha =F1", "gamma =F1", "beta"}
    assert ("_=F1: alpha, gamma answer time-agnostic queries with one shared time-agnostic field (geometry, "
            "autoencoder and language field: the same fit record key on every run they share); their time-agnostic "
            "scores are identical") in agnostic
    assert "=F1" not in _section(md, "#### Time-sensitive queries")


def test_a_method_at_chance_is_never_bold(tmp_path):
    root = tmp_path / "results"
    for method, acc, auc in (("alpha", 90.0, 50.0), ("beta", 40.0, 95.0), ("gamma", 20.0, 96.0)):
        for seed in range(3):
            for scene in (S1, S2):
                doc = _doc(method, scene, seed, 60.0)
                sensitive = doc["scores"]["queries"][-1]
                doc["scores"]["queries"] += [dict(sensitive, query=f"{sensitive['query']} {i}") for i in range(3)]
                for i, q in enumerate(doc["scores"]["queries"][3:]):
                    q.update({"Acc": acc + (i - 1.5) + seed, "AUC": auc + (-10.0 if i % 2 else 10.0) * (auc < 90)})
                write_results(results_path(root, "synthetic", scene, method, "oracle", seed), doc)
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    md = (tmp_path / "lb.md").read_text()
    table = _section(md, "#### Time-sensitive queries")
    rows, header = _rows(table), _header(table)
    mean = header.index("**mean Acc** [95 % CI] ↑")
    assert list(rows) == ["alpha (at chance)", "beta", "gamma"]  # the best mean, at chance
    assert not any(c.startswith("**") for c in rows["alpha (at chance)"])
    assert rows["beta"][mean].startswith("**41.00 [")  # the best not at chance, apart from gamma
    assert "_(at chance): the method's mean AUC interval covers 50" in table
    assert "at chance" not in _section(md, "#### Time-agnostic queries")


def test_a_table_mixing_machine_kinds_shows_the_spread_between_them(tmp_path):
    root = tmp_path / "results"
    _write_all(root, 0, OFFICIAL)
    build_leaderboard(root, markdown=tmp_path / "one.md", reports_dir=tmp_path / "rep")
    one = (tmp_path / "one.md").read_text()
    assert "Machine kind: unknown (12 runs)." in one and "between machines" not in one
    for path in find_results(root):
        doc = json.loads(path.read_text())
        if doc["seed"] == 0:
            doc["environment"]["processor"] = "Intel Xeon"
            path.write_text(json.dumps(doc))
    build_leaderboard(root, markdown=tmp_path / "two.md", reports_dir=tmp_path / "rep")
    two = (tmp_path / "two.md").read_text()
    assert "Machine kinds: Intel Xeon (4 runs); unknown (8 runs). The tables below mix them" in two
    table = _section(two, "#### Time-agnostic queries")
    rows, header = _rows(table), _header(table)
    assert rows["beta"][header.index("machines")] == "A+B"
    # beta: seed 0 (Intel) means 70 and 40 -> 55; seeds 1 and 2 (unknown) -> (71.5 + 46) / 2 = 58.75
    assert rows["beta"][header.index("Δ mIoU between machines")] == "3.75"
    assert "_Machines: A = Intel Xeon; B = unknown." in table


def test_each_split_gets_its_own_tables_the_papers_first(tmp_path):
    from benchmark.leaderboard import load_runs, render_markdown

    root = tmp_path / "results"
    _write_all(root, 0, OFFICIAL)
    runs, queries = load_runs(root)
    paper = runs.copy()
    paper["split"] = "paper"
    paper["path"] = "paper/" + paper["path"]
    paper_queries = queries.assign(path="paper/" + queries["path"])
    both = pd.concat([runs, paper], ignore_index=True)
    md = render_markdown(both, "results", queries=pd.concat([queries, paper_queries], ignore_index=True))
    assert md.index("## Split: paper") < md.index("## Split: legacy-dense")
    assert "_the earlier 3-of-4 training split" in md
    assert "### synthetic — track: oracle — protocol: release (default) — split: paper" in md
    assert _section(md, "#### Time-agnostic queries", "## Split: paper") == \
        _section(md, "#### Time-agnostic queries", "## Split: legacy-dense")


def _floor_board(tmp_path, monkeypatch, specs, mious) -> None:
    """``tmp_path/lb.md`` from one seed of each (method, mIoU) of ``mious`` on both scenes, the methods' specs
    (floor or not, answering rule) those of ``specs``."""
    from benchmark import leaderboard

    monkeypatch.setattr(leaderboard, "_spec", lambda name: specs.get(name))
    root = tmp_path / "results"
    for method, value in mious:
        FIT.setdefault(method, 1.0)
        FPS.setdefault(method, 1.0)
        for scene in (S1, S2):
            write_results(results_path(root, "synthetic", scene, method, "oracle", 0), _doc(method, scene, 0, value))
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")


def test_a_ranked_method_that_does_not_clear_its_floor_is_told_in_words(tmp_path, monkeypatch):
    from types import SimpleNamespace


    specs = {"alpha": SimpleNamespace(floor=False, answer_rule="relevance"),
             "beta": SimpleNamespace(floor=False, answer_rule="mask-selection"),
             "alpha+": SimpleNamespace(floor=False, answer_rule="relevance", variant_of="alpha"),
             "floor-r": SimpleNamespace(floor=True, answer_rule="relevance"),
             "floor-m": SimpleNamespace(floor=True, answer_rule={"agnostic": "mask-selection"})}
    _floor_board(tmp_path, monkeypatch, specs, (("alpha", 60.0), ("alpha+", 80.0), ("beta", 40.0), ("floor-r", 61.0), ("floor-m", 70.0)))
    table = _section((tmp_path / "lb.md").read_text(), "#### Time-agnostic queries")
    rows = _rows(table)
    assert "alpha+ (variant of alpha)" in rows
    assert "_floor-r (floor, not ranked; answers by relevance)_" in rows
    assert ("_Floor `floor-r` (answers by relevance, as they do): mean mIoU 61.00 [" in table
            and "Not clear of the floor (intervals overlap): alpha 60.00 [" in table and "Clear of it: alpha+." in table)
    assert "_Floor `floor-m` (answers by mask-selection, as they do): mean mIoU 70.00 [" in table
    assert "Below the floor: beta 40.00 [" in table


def test_cells_that_read_the_same_never_make_a_winner_by_last_decimals(tmp_path):
    root = tmp_path / "results"
    # two methods sharing one fit can differ past the printed digits (float rounding)
    write_results(results_path(root, "synthetic", S1, "alpha", "oracle", 0), _doc("alpha", S1, 0, 70.001))
    write_results(results_path(root, "synthetic", S1, "beta", "oracle", 0), _doc("beta", S1, 0, 70.004))
    write_results(results_path(root, "synthetic", S1, "gamma", "oracle", 0), _doc("gamma", S1, 0, 69.99))
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    rows = _rows(_section((tmp_path / "lb.md").read_text(), "#### Time-agnostic queries"))
    assert {m: r[1] for m, r in rows.items()} == {"alpha": "70.00", "beta": "70.00", "gamma": "69.99"}
    assert list(rows) == ["alpha", "beta", "gamma"]  # equal as shown: by name


def test_time_sensitive_table_shows_score_auc_ranked_and_near_threshold_share_unranked(tmp_path):
    from benchmark.metrics import near_threshold_fraction, score_auc

    root = tmp_path / "results"
    alpha, beta = _doc("alpha", S1, 0, 70.0), _doc("beta", S1, 0, 60.0)
    # beta's scores order the states perfectly; its decisions all sit near the threshold
    for f in beta["scores"]["frames"]:
        f["smoothed"] = 0.2 + (0.005 if f["label"] else -0.005)
    beta["scores"]["frames"][0]["smoothed"] = 0.0  # a negative far below widens the range
    write_results(results_path(root, "synthetic", S1, "alpha", "oracle", 0), alpha)
    write_results(results_path(root, "synthetic", S1, "beta", "oracle", 0), beta)
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    table = _section((tmp_path / "lb.md").read_text(), "#### Time-sensitive queries")
    names, rows = _header(table), _rows(table)
    assert "mean AUC [95 % CI] ↑" in names and "near τ (%)" in names

    def expected(doc):
        frames = doc["scores"]["frames"]
        smoothed = np.array([f["smoothed"] for f in frames])
        labels = np.array([f["label"] for f in frames])
        return 100 * score_auc(smoothed, labels), 100 * near_threshold_fraction(smoothed, 0.2)

    auc_col, near_col = names.index("mean AUC [95 % CI] ↑"), names.index("near τ (%)")
    # alpha's scores do not order the states (AUC exactly 50): at chance, so never bold
    rows["alpha"] = rows.pop("alpha (at chance)")
    for name, doc in (("alpha", alpha), ("beta", beta)):
        auc, near = expected(doc)
        assert rows[name][auc_col].strip("*").startswith(f"{auc:.2f} [")
        assert rows[name][near_col] == f"{near:.2f}"  # never bold
    assert rows["beta"][auc_col].startswith("**100.00 [") and not rows["alpha"][auc_col].startswith("**")
    assert expected(beta)[1] == 90.0  # 9 of 10 decisions within 5 % of the range (0.205 - 0 = 0.205)

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
    assert sorted(p.name for p in written) == ["pareto_synthetic_oracle_release_legacy-dense.pdf",
                                               "pareto_synthetic_oracle_release_legacy-dense.png"]  # no split recorded
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




def test_paper_tables_put_the_published_numbers_beside_ours_with_rank_agreement(tmp_path):
    from benchmark.cli import main
    from benchmark.paper_tables import AGNOSTIC_METHODS, kendall_tau
    from benchmark.runner import config_dict
    from methods import registry

    assert kendall_tau({"a": 1, "b": 2, "c": 3}, {"a": 3, "b": 2, "c": 1})[:2] == (pytest.approx(-1.0), 3)
    assert kendall_tau({"a": 1, "b": 2, "c": 3}, {"a": 3, "b": 2, "c": 1})[2] == pytest.approx(2 / 6)
    assert math.isnan(kendall_tau({"a": 1}, {"a": 2, "b": 1})[0])
    # means equal up to their last bits are a tie: tau-b 5 / sqrt(6 * 5), not +1 from summation order
    tied_high = 97.50000000000001
    four = {"a": 1.0, "b": 2.0, "c": 3.0, "d": 4.0}
    assert kendall_tau(four, {"a": 1.0, "b": 2.0, "c": 97.5, "d": tied_high})[0] == pytest.approx(5 / math.sqrt(30))
    assert kendall_tau(four, {"a": 1.0, "b": 2.0, "c": 97.4, "d": 97.5})[0] == pytest.approx(1.0)
    # the best here: tie group 1 by our intervals; without intervals, equal means
    from benchmark.paper_tables import _agreement

    paper, names = {"a": 90.0, "b": 80.0, "c": 70.0}, {"a": "A", "b": "B", "c": "C"}
    tied = (100 + 100 + 96.66666666666667 + 93.33333333333333) / 4
    assert "is best here: tied (equal means) with B._" in _agreement(paper, {"a": tied, "b": 97.5, "c": 50.0}, names)
    assert "is best here: no (best here: B)._" in _agreement(paper, {"a": 97.4, "b": 97.5, "c": 50.0}, names)
    near = {"a": (96.0, 99.0), "b": (96.5, 98.5), "c": (45.0, 55.0)}
    assert "is best here: tied (within 95 % intervals) with B._" in _agreement(
        paper, {"a": 97.4, "b": 97.5, "c": 50.0}, names, near)
    apart = {"a": (97.55, 97.65), "b": (97.45, 97.54), "c": (45.0, 55.0)}
    assert "is best here: yes._" in _agreement(paper, {"a": 97.6, "b": 97.5, "c": 50.0}, names, apart)
    root = tmp_path / "results"
    presets = ("americano", "chickchicken", "split-cookie", "espresso", "keyboard", "torchocolate")
    # the paper's order reversed: Feature-3DGS best, 4D LangSplat worst
    for rank, method in enumerate(AGNOSTIC_METHODS):
        recorded = config_dict(registry.get(method).default_config())
        for scene in presets:
            write_results(results_path(root, "synthetic", scene, method, "oracle", 0),
                          {**_doc("alpha", scene, 0, 80.0 - 10 * rank), "method": method, "method_config": recorded})
    out = tmp_path / "paper-tables.md"
    assert main(["paper-tables", "--results-dir", str(root), "--reports-dir", str(tmp_path / "rep"),
                 "--out", str(out)]) == 0
    text = out.read_text()
    agnostic = text.split("## Time-agnostic queries, HyperNeRF")[1].split("## ")[0]
    row = next(line for line in agnostic.splitlines() if line.startswith("| Feature-3DGS |"))
    assert "| 34.65 / 80.00 |" in row and row.endswith("| 36.63 / 80.00 | 74.02 / 90.00 |")
    assert "Kendall's tau = -1.00 (p = 0.083, exact permutation test" in agnostic
    assert "is best here: no (best here: Feature-3DGS)" in agnostic
    assert "Ours, mean mIoU over the paper's scenes with its 95 % interval: Feature-3DGS 80.00 [" in agnostic
    assert "protocol `release`" in text and "held-out frames" in text and "track `oracle`, seeds 0; split" in text
    assert "## Number of states K" in text and "## Query speed" in text
    # a second seed on one cell: the means stay per cell, and the header says how many cells lack it
    write_results(results_path(root, "synthetic", "keyboard", "langsplat", "oracle", 1),
                  {**_doc("alpha", "keyboard", 1, 0.0), "method": "langsplat",
                   "method_config": config_dict(registry.get("langsplat").default_config())})
    assert main(["paper-tables", "--results-dir", str(root), "--out", str(out)]) == 0
    text = out.read_text()
    assert "seeds 0, 1 (23 of 24 (method, preset) cells have fewer: each cell is the mean of the seeds it has)" in text
    # a run whose recorded config is not its method's default is no paper-config run: left out, and counted
    other = config_dict(registry.get("feature-3dgs").default_config())
    other["geometry"] = {**other["geometry"], "hexplane_resolution": other["geometry"]["hexplane_resolution"] // 2}
    write_results(results_path(root, "synthetic", "americano", "feature-3dgs", "oracle", 0),
                  {**_doc("alpha", "americano", 0, 1.0), "method": "feature-3dgs", "method_config": other})
    assert main(["paper-tables", "--results-dir", str(root), "--out", str(out)]) == 0
    text = out.read_text()
    assert "1 run(s) left out whose recorded config is not their method's default" in text
    assert "| 34.65 / – |" in text
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


def test_draft_queries_stay_out_of_the_ranked_means_and_are_listed_under_their_tables(tmp_path):
    root = tmp_path / "results"
    _write_all(root, 0, OFFICIAL)
    build_leaderboard(root, markdown=tmp_path / "plain.md", reports_dir=tmp_path / "rep")
    assert "Draft ground truth" not in (tmp_path / "plain.md").read_text()
    for path in find_results(root):
        doc = json.loads(path.read_text())
        if doc["scene"] == S1:  # the highest of the three queries is a draft on S1
            doc["scene_info"]["draft_queries"] = ["pitcher"]
            path.write_text(json.dumps(doc))
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    md = (tmp_path / "lb.md").read_text()
    table = _section(md, "#### Time-agnostic queries")
    rows, header = _rows(table), _header(table)
    assert rows["alpha"][1] == "51.00 ± 2.00"  # the two lower queries of 50, 52, 54 (seeds): 52 - 1
    assert rows["alpha"][header.index("answered / asked")] == "15/15"  # S1: 2 queries a seed, S2: 3
    assert f"_Draft ground truth, left out of the means above: {S1} (pitcher)." in md
    assert md.count("Draft ground truth") == 1


def test_pareto_points_leave_draft_queries_out_as_the_leaderboard_does(tmp_path, monkeypatch):
    import benchmark.plots as plots

    root = tmp_path / "results"
    _write_all(root, 0, OFFICIAL)
    for path in find_results(root):
        doc = json.loads(path.read_text())
        if doc["scene"] == S1:
            doc["scene_info"]["draft_queries"] = ["pitcher"]
            path.write_text(json.dumps(doc))
    seen = {}

    def charts(runs, **_):
        seen["runs"] = runs
        return []

    monkeypatch.setattr(plots, "pareto_charts", charts)
    plots.pareto(root, tmp_path / "rep")
    runs = seen["runs"]
    alpha = runs[(runs["method"] == "alpha") & (runs["scene"] == S1)].sort_values("seed")
    # the two lower queries of 50, 52, 54 (seeds): the recorded mIoU (all three) would be 2 higher
    assert alpha["mIoU"].round(6).tolist() == [49.0, 51.0, 53.0]
    assert not [c for c in runs if c.startswith(("answered_", "asked_"))]


def test_runs_record_the_draft_queries_of_their_ground_truth():
    from benchmark.core.annotation import AnnotationSet, Query
    from benchmark.runner import draft_query_texts

    aset = AnnotationSet("toy", queries=[Query(1, "person"), Query(2, "shorts", level="part", review="draft"),
                                         Query(3, "jumping", kind="sensitive", base=1),
                                         Query(4, "shorts up", kind="sensitive", base=2)])
    assert draft_query_texts(aset) == ["shorts", "shorts up"]


def test_a_kind_declined_on_one_scene_counts_zero_there_and_is_not_left_out(tmp_path):
    """Declining every time-sensitive query of the harder scene must not lift a method's mean: the scene counts
    0, the method keeps full coverage of scenes, and answered / asked shows what it declined."""
    root = tmp_path / "results"
    _write_all(root, 0, OFFICIAL)
    for scene in (S1, S2):
        for seed in (0, 1, 2):
            doc = _doc("zeta", scene, seed, 65.0)
            if scene == S2:
                doc["metrics"].update({"Acc": None, "vIoU": None, "sensitive_queries": 0})
                doc["scores"]["queries"] = [q for q in doc["scores"]["queries"] if q["kind"] == "agnostic"]
                doc["scores"]["frames"] = []
                doc["unanswered_queries"] = ["cracked cookie"]
            write_results(results_path(root, "synthetic", scene, "zeta", "oracle", seed), doc)
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    sensitive = _section((tmp_path / "lb.md").read_text(), "#### Time-sensitive queries")
    rows = _rows(sensitive)
    zeta = [cell.strip("*") for cell in (rows.get("zeta") or rows["zeta (at chance)"])]
    assert zeta[1:3] == ["55.00 ± 0.00", "0.00 ± 0.00"]  # americano answered; keyboard declined: 0, not left out
    assert any(cell.startswith("27.50 [") for cell in zeta)  # the mean (55 + 0) / 2, not 55
    assert "3/6" in zeta and "2/2" in zeta  # answered / asked, and both scenes covered


def test_the_floor_comparisons_open_the_leaderboard_before_any_ranking(tmp_path, monkeypatch):
    from types import SimpleNamespace


    specs = {"alpha": SimpleNamespace(floor=False, answer_rule="relevance"),
             "beta": SimpleNamespace(floor=False, answer_rule="mask-selection"),
             "floor-r": SimpleNamespace(floor=True, answer_rule="relevance"),
             "floor-m": SimpleNamespace(floor=True, answer_rule={"agnostic": "mask-selection"})}
    _floor_board(tmp_path, monkeypatch, specs, (("alpha", 60.0), ("beta", 90.0), ("floor-r", 61.0), ("floor-m", 70.0)))
    md = (tmp_path / "lb.md").read_text()
    first = _section(md, "## Against the floors, first")
    assert md.index("## Against the floors, first") < md.index("## Split:") < md.index("| method |")
    lines = [line for line in first.splitlines() if line.startswith("* ") and "time-agnostic" in line]
    assert len(lines) == 2  # one per floor with methods of its rule
    # the time table: the relevance floor (Acc 51) above alpha (50), which every query agrees on
    sensitive = [line for line in first.splitlines() if line.startswith("* ") and "time-sensitive" in line]
    assert len(sensitive) == 1 and "**no method clears it**; tied: none; below: alpha." in sensitive[0]
    relevance = next(line for line in lines if "`floor-r`" in line)
    assert "(answers by relevance) 61.00 [" in relevance and "**no method clears it**; tied: alpha; below: none." in relevance
    masks = next(line for line in lines if "`floor-m`" in line)
    assert "clear of it: beta; tied: none; below: none." in masks


def test_a_floor_no_ranked_method_shares_a_rule_with_is_named_a_reference(tmp_path, monkeypatch):
    from types import SimpleNamespace


    specs = {"alpha": SimpleNamespace(floor=False, answer_rule="relevance"),
             "beta": SimpleNamespace(floor=False, answer_rule="relevance"),
             "floor-m": SimpleNamespace(floor=True, answer_rule={"agnostic": "mask-selection"})}
    _floor_board(tmp_path, monkeypatch, specs, (("alpha", 60.0), ("beta", 50.0), ("floor-m", 70.0)))
    first = _section((tmp_path / "lb.md").read_text(), "## Against the floors, first")
    line = next(line for line in first.splitlines() if "time-agnostic" in line)
    assert "floor `floor-m` (answers by mask-selection) 70.00 [" in line
    assert line.endswith("no ranked method answers by this rule; a reference only.")


def test_no_floor_no_opening_section():
    from benchmark.leaderboard import floors_first

    assert floors_first([]) == []


def test_runs_made_under_other_defaults_are_counted_with_the_options_that_moved(tmp_path):
    import dataclasses

    from methods import registry

    root = tmp_path / "results"
    _write_all(root, 0, OFFICIAL)
    spec = registry.get("deformable-clip")
    default = spec.make_config().geometry.gaussians_per_foreground_pixel
    for seed, options in ((0, {"geometry.gaussians_per_foreground_pixel": str(default * 2)}), (1, {})):
        doc = _doc("alpha", S1, seed, 50.0)
        doc["method"] = "deformable-clip"
        doc["method_config"] = json.loads(json.dumps(dataclasses.asdict(spec.make_config(options))))
        write_results(results_path(root, "synthetic", S1, "deformable-clip", "oracle", seed), doc)
    build_leaderboard(root, markdown=tmp_path / "lb.md", reports_dir=tmp_path / "rep")
    md = (tmp_path / "lb.md").read_text()
    assert ("**1 result file(s) were made under configs other than their methods' defaults today** (`bench4d "
            "run-all` archives and reruns them at today's defaults): 1 with "
            f"`geometry.gaussians_per_foreground_pixel={default * 2} (now {default})`." in md)
    assert spec.differences_from_defaults(doc["method_config"]) == {}
    assert spec.differences_from_defaults(None) is None
