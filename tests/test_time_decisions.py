"""``bench4d ablate decisions``: how far recorded time-sensitive Acc can be trusted (hand-made runs)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmark.cli import main
from benchmark.results import results_path, write_results
from benchmark.studies.time_decisions import accuracy_span, query_rows, summarise


def _run(method: str, seed: int, smoothed: list[float], labels: list[bool], tau: float) -> dict:
    decisions = [s >= tau for s in smoothed]
    frames = [{"scene": "s1", "query": "open box", "kind": "sensitive", "frame": f"f{t:03d}", "time_index": t,
               "camera_id": "0", "iou": 1.0, "acc": 1.0, "pred_pixels": 1, "gt_pixels": 1, "score": s,
               "smoothed": s, "decision": d, "label": y}
              for t, (s, d, y) in enumerate(zip(smoothed, decisions, labels))]
    acc = 100.0 * float(np.mean(np.array(decisions) == np.array(labels)))
    return {"method": method, "dataset": "synthetic", "scene": "s1", "track": "oracle", "seed": seed,
            "metrics": {"mIoU": None, "Acc": acc, "vIoU": 50.0}, "timing": {"fit_seconds": 1.0},
            # a versioned generated scene with no committed digest: comparable, as on the leaderboard
            "scene_info": {"generated": {"preset": "s1", "size": 128, "seed": 0, "digest": "d" * 24}},
            "scores": {"queries": [{"scene": "s1", "query": "open box", "kind": "sensitive", "frames": len(frames),
                                    "threshold": tau, "decision_source": "rule", "Acc": acc}],
                       "frames": frames, "skipped": []}}


# six frames, positives t = 3..5; a score that orders them perfectly but sits mostly near tau
SEPARATED = ([0.0, 0.47, 0.49, 0.51, 0.52, 1.0], [False, False, False, True, True, True], 0.5)
# scores unrelated to the labels
NOISE = ([0.9, 0.1, 0.5, 0.2, 0.8, 0.3], [False, False, False, True, True, True], 0.4667)


def test_accuracy_span_covers_every_cut_near_tau():
    smoothed, labels, tau = np.array(SEPARATED[0]), np.array(SEPARATED[1]), SEPARATED[2]
    # cuts in [.45, .55]: at .45 or .47 frames 1, 2 turn positive (4/6), at .55 frames 3, 4 negative (4/6);
    # only a cut between .49 and .51, inside the interval, gets all six: the ends alone would miss it
    low, high = accuracy_span(smoothed, labels, tau, 0.05)
    assert (low, high) == (pytest.approx(4 / 6), 1.0)
    assert accuracy_span(smoothed, labels, tau, 0.0) == (1.0, 1.0)
    assert np.isnan(accuracy_span(smoothed, labels, float("nan"), 0.1)[0])


def test_query_rows_and_summary_by_hand():
    rows = query_rows(_run("alpha", 0, *SEPARATED))
    assert len(rows) == 1
    r = rows[0]
    assert r["acc"] == 100.0 and r["auc"] == 100.0 and r["best_cut"] == 100.0
    # range 1.0: |s - 0.5| < 0.05 for .47, .49, .51, .52 -> 4 of 6 near tau
    assert r["near"] == pytest.approx(100 * 4 / 6)
    assert (r["acc_low"], r["acc_high"]) == (pytest.approx(100 * 4 / 6), 100.0)  # 5 % of range = 0.05
    # the oracle cut on shuffled labels is above 50 on six frames, below a perfect order
    assert 50.0 < r["chance_best_cut"] < 100.0
    noise = query_rows(_run("beta", 0, *NOISE))[0]
    assert noise["auc"] == pytest.approx(100 * 4 / 9)  # positives .2 .8 .3 vs .9 .1 .5: 4 of 9 pairs
    # a decisions-only query has nothing to analyse
    given = _run("gamma", 0, *NOISE)
    given["scores"]["queries"][0]["decision_source"] = "decisions"
    assert query_rows(given) == []
    per_scene, per_method = summarise(rows + query_rows(_run("alpha", 1, *NOISE)) + [noise])
    alpha = per_scene[per_scene["method"] == "alpha"].iloc[0]
    assert alpha["seeds"] == 2 and alpha["auc"] == pytest.approx((100 + 100 * 4 / 9) / 2)
    assert set(per_method["method"]) == {"alpha", "beta"} and per_method["scenes"].tolist() == [1, 1]


def test_cli_writes_the_report_and_rejects_an_empty_selection(tmp_path, capsys):
    root = tmp_path / "results"
    write_results(results_path(root, "synthetic", "s1", "alpha", "oracle", 0), _run("alpha", 0, *SEPARATED))
    write_results(results_path(root, "synthetic", "s1", "beta", "oracle", 0), _run("beta", 0, *NOISE))
    out = tmp_path / "out"
    assert main(["ablate", "decisions", "--results-dir", str(root), "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "time-decisions.json").read_text())
    assert {r["method"] for r in doc["per_method"]} == {"alpha (synthetic, oracle)", "beta (synthetic, oracle)"}
    md = (out / "time-decisions.md").read_text()
    assert "| alpha (synthetic, oracle) | 1 | 100.0 | 66.7–100.0 | 100.0 | 66.7 | 100.0 |" in md
    assert main(["ablate", "decisions", "--results-dir", str(root), "--methods", "nobody", "--out", str(out)]) != 0
    assert "no recorded run" in capsys.readouterr().err
