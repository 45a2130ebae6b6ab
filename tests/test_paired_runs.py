"""``bench4d ablate paired``: runs of two configs paired by place, differences with intervals, unpaired runs
named, fit seconds net of the geometry a run fitted."""

from __future__ import annotations

import json

import pytest

from benchmark.results import results_path, write_results
from benchmark.studies.paired_runs import added_seconds, compare, pair_runs, paired_report


METHOD = "langsplat"
"""A registered method: the report reads recorded options as it does."""


def _doc(scene, seed, miou, *, acc=None, digest="d", fit=100.0, geometry=None, steps=1200, method=METHOD):
    info = {"cached": {"geometry": geometry is None}}
    if geometry is not None:
        info["geometry"] = {"seconds": geometry}
    return {"dataset": "synthetic", "track": "oracle", "method": method, "scene": scene, "seed": seed,
            "split": "paper", "metrics": {"mIoU": miou, "Acc": acc, "vIoU": None},
            "method_config": {"field": {"iterations": steps}},
            "scene_info": {"generated": {"digest": f"{digest}-{scene}-{seed}"}},
            "timing": {"fit_seconds": fit, "fit_cached": False}, "fit": {"key": "k", "info": info}}


def _write(root, doc):
    write_results(results_path(root, "synthetic", doc["scene"], doc["method"], "oracle", doc["seed"]), doc)


def _folders(tmp_path, shifts, *, acc_shift=None):
    old, new = tmp_path / "old", tmp_path / "new"
    for i, (scene, seed) in enumerate((s, k) for s in ("a", "b", "c") for k in (0, 1)):
        base = 50.0 + 7 * i
        _write(old, _doc(scene, seed, base, acc=60.0))
        acc = None if acc_shift is None else 60.0 + acc_shift[i]
        _write(new, _doc(scene, seed, base + shifts[i], acc=acc, steps=400, fit=30.0))
    return old, new


def test_a_drop_every_scene_agrees_on_is_beyond_the_noise(tmp_path):
    old, new = _folders(tmp_path, [-1.0, -1.2, -0.9, -1.1, -1.3, -1.0], acc_shift=[5, -5, 5, -5, 0, 0])
    pairs, unpaired = pair_runs(old, new)
    assert len(pairs) == 6 and not unpaired
    assert pairs[0].options == {"field.iterations": (1200, 400)}
    rows = {r["score"]: r for r in compare(pairs)}
    miou = rows["mIoU"]
    assert miou["difference"] == pytest.approx(-1.0833, abs=1e-3)
    assert miou["interval"][1] < 0 and miou["beyond_noise"] and (miou["down"], miou["up"]) == (6, 0)
    assert miou["p_value"] == pytest.approx(2 / 64)  # six pairs, all down: the smallest p six pairs allow
    # time answers that move both ways in every scene are a tie
    acc = rows["Acc"]
    assert acc["interval"][0] < 0 < acc["interval"][1] and not acc["beyond_noise"]
    assert "vIoU" not in rows  # answered by neither side: no row, not a score of 0


def test_one_pair_per_scene_gives_no_interval(tmp_path):
    old, new = tmp_path / "old", tmp_path / "new"
    for scene in ("a", "b"):
        _write(old, _doc(scene, 0, 50.0))
        _write(new, _doc(scene, 0, 40.0))
    row = compare(pair_runs(old, new)[0])[0]
    assert row["difference"] == -10.0 and not row["beyond_noise"]
    report = paired_report("one", old, new, tmp_path / "out")
    assert "fewer than 2 pairs in a scene" in report.table


def test_runs_without_a_baseline_or_on_another_scene_are_named_not_paired(tmp_path):
    old, new = _folders(tmp_path, [0.0] * 6)
    _write(new, _doc("d", 0, 10.0))  # no baseline run
    _write(new, _doc("a", 0, 10.0, digest="other"))  # regenerated scene: another question
    pairs, unpaired = pair_runs(old, new)
    assert len(pairs) == 5
    assert sorted(unpaired) == [f"synthetic/a/{METHOD}/oracle/seed0.json: another scene (generated-scene digests "
                                "differ)", f"synthetic/d/{METHOD}/oracle/seed0.json: no baseline run"]


def test_fit_seconds_are_net_of_a_geometry_the_run_fitted():
    assert added_seconds(_doc("a", 0, 1.0, fit=700.0, geometry=640.0)) == 60.0
    assert added_seconds(_doc("a", 0, 1.0, fit=90.0)) == 90.0  # geometry read from the cache
    cached = _doc("a", 0, 1.0, fit=0.2)
    cached["timing"]["fit_cached"] = True
    assert added_seconds(cached) == 0.0


def test_the_report_states_options_and_costs(tmp_path):
    old, new = _folders(tmp_path, [-1.0, -1.2, -0.9, -1.1, -1.3, -1.0])
    report = paired_report("field-third", old, new, tmp_path / "out")
    assert "`field.iterations`: 1200 -> 400" in report.table
    doc = json.loads((tmp_path / "out" / "paired-field-third.json").read_text())
    assert doc["costs"][-1] == {"method": "all", "runs": 6, "baseline_seconds": 600.0, "candidate_seconds": 180.0}
    assert f"| {METHOD} | 6 | 600 | 180 | 0.30 |" in report.table
    assert f"| {METHOD} | oracle | paper | mIoU | 6 |" in report.table  # every row names its supervision track


def test_a_narrow_interval_from_few_pairs_is_not_a_verdict(tmp_path):
    # five of six pairs down by a little, one up by a little: the bootstrap interval of two pairs a scene can
    # miss 0 ([-0.23, -0.12] here), the exact test (p = 4/64) does not call it beyond the noise
    old, new = _folders(tmp_path, [-0.20, -0.22, -0.25, -0.21, -0.24, 0.05])
    row = next(r for r in compare(pair_runs(old, new)[0]) if r["score"] == "mIoU")
    assert (row["down"], row["up"]) == (5, 1)
    assert row["p_value"] >= 0.05 and not row["beyond_noise"]


def _geometry(key, static_cpu, deform_cpu, wall, psnr, novel):
    return {"key": key, "seconds": wall, "test_psnr": psnr, "novel_view_psnr": novel,
            "stages": [{"stage": "static", "cpu_seconds": static_cpu}, {"stage": "deformation", "cpu_seconds": deform_cpu}]}


def test_a_geometry_change_compares_its_psnr_and_its_stage_seconds_once_per_fit(tmp_path):
    old, new = tmp_path / "old", tmp_path / "new"
    for scene in ("a", "b"):
        for seed in (0, 1):
            for method in ("langsplat", "feature-3dgs"):  # two methods on one geometry fit: counted once
                base = _doc(scene, seed, 50.0, method=method)
                base["fit"]["info"]["geometry"] = _geometry(f"old-{scene}{seed}", 100.0, 400.0, 600.0, 25.0, 20.0)
                cand = _doc(scene, seed, 49.0, method=method)
                cand["fit"]["info"]["geometry"] = _geometry(f"new-{scene}{seed}", 50.0, 250.0, 350.0, 24.0, 19.5)
                _write(old, base)
                _write(new, cand)
    pairs, _ = pair_runs(old, new)
    rows = {(r["method"], r["score"]): r for r in compare(pairs)}
    assert rows["langsplat", "held-out PSNR (dB)"]["difference"] == pytest.approx(-1.0)
    assert rows["langsplat", "novel-view PSNR (dB)"]["difference"] == pytest.approx(-0.5)
    report = paired_report("geo", old, new, tmp_path / "out")
    doc = json.loads((tmp_path / "out" / "paired-geo.json").read_text())
    costs = {r["cost"]: r for r in doc["geometry_costs"]}
    assert costs["static stage CPU s"]["fits"] == 4  # four fits, not eight runs
    assert costs["static stage CPU s"]["baseline_seconds"] == pytest.approx(400.0)
    assert costs["deformation stage CPU s"]["candidate_seconds"] == pytest.approx(1000.0)
    assert "| deformation stage CPU s | 4 | 1600 | 1000 | 0.62 |" in report.table


def test_the_geometrys_psnr_is_read_from_paper_split_runs_only():
    from benchmark.studies.paired_runs import _scores

    doc = _doc("a", 0, 50.0)
    doc["fit"]["info"]["geometry"] = _geometry("k", 1.0, 1.0, 1.0, 25.0, 20.0)
    assert _scores(doc)["held-out PSNR (dB)"] == 25.0
    doc["split"] = "novel-view"  # the same fit answers this split: not counted twice
    assert _scores(doc)["held-out PSNR (dB)"] is None and _scores(doc)["novel-view PSNR (dB)"] is None
