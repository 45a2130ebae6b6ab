"""How far the time-sensitive Acc of recorded runs can be trusted, and what the threshold rule costs:
``bench4d ablate decisions``.

Reads only what a results file records (per-frame smoothed scores, labels, each query's ``tau``), so
it needs no fit and no scene. Per time-sensitive query of a run:

* ``acc``: the recorded Acc (the protocol's mean-threshold rule).
* ``acc_low`` / ``acc_high``: the lowest and highest Acc of any threshold within
  :data:`~benchmark.metrics.temporal.NEAR_THRESHOLD_FRACTION` of the query's score range of ``tau``
  (:func:`accuracy_span`): the span a small change of the fit can move it through.
* ``auc``, ``near``: the query's diagnostics, as the scorer records them (``metrics.AUC`` / ``nearTau``).
* ``best_cut``: Acc at the best single threshold (:func:`~benchmark.metrics.temporal.best_cut_accuracy`),
  an oracle choice, and ``chance_best_cut``: the same oracle on scores unrelated to the labels (the
  mean over :data:`CHANCE_PERMUTATIONS` seeded shuffles of the labels), its optimism on so few frames.
  ``best_cut`` well below a target says no threshold rule reaches it on these scores.

Combining: queries -> run (mean) -> (method, scene) (mean over seeds) -> method (mean over scenes),
as the leaderboard combines Acc.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Iterable, Optional, Sequence

import numpy as np
import pandas as pd

from benchmark.core.errors import InputError
from benchmark.metrics.temporal import (NEAR_THRESHOLD_FRACTION, accuracy_at_threshold, best_cut_accuracy,
                                        near_threshold_fraction, score_auc)
from benchmark.results import find_results, load_results, scene_status, sensitive_query_records

from ._report import Report, stderr_log, write_report

CHANCE_PERMUTATIONS = 200
"""Label shuffles behind ``chance_best_cut`` (seeded, so the report is deterministic)."""
CHANCE_SEED = 0
"""Seed of those shuffles."""
QUERY_VALUES = ("acc", "acc_low", "acc_high", "auc", "near", "best_cut", "chance_best_cut")
"""Per-query values (percent), in table order."""


def accuracy_span(smoothed: np.ndarray, labels: np.ndarray, tau: float, shift: float) -> tuple[float, float]:
    """(lowest, highest) Acc of ``s~_t >= c`` over every cut ``c`` in ``[tau - shift, tau + shift]``
    (fractions; NaN, NaN when ``tau`` is NaN). Acc only changes where ``c`` passes a score, so the
    interval's ends and each score inside it, taken and just passed, are every case."""
    if math.isnan(tau):
        return math.nan, math.nan
    s = np.asarray(smoothed, dtype=np.float64)
    inside = s[(~np.isnan(s)) & (np.abs(s - tau) <= shift)]
    cuts = [tau - shift, tau + shift, *inside, *np.nextafter(inside, np.inf)]
    accs = [accuracy_at_threshold(s, labels, float(c)) for c in cuts]
    return min(accs), max(accs)


def query_rows(doc: dict, *, path: Optional[Path] = None) -> list[dict]:
    """One row per time-sensitive query the run decided from scores (percent values)."""
    rows = []
    for query, smoothed, labels, decisions, tau in sensitive_query_records(doc):
        if not smoothed.size:
            continue
        defined = smoothed[~np.isnan(smoothed)]
        span = float(defined.max() - defined.min()) if defined.size else 0.0
        shift = NEAR_THRESHOLD_FRACTION * span
        rng = np.random.default_rng(CHANCE_SEED)
        chance = np.mean([best_cut_accuracy(smoothed, rng.permutation(labels)) for _ in range(CHANCE_PERMUTATIONS)])
        low, high = accuracy_span(smoothed, labels, tau, shift)
        rows.append({
            "method": doc["method"], "scene": doc["scene"], "seed": int(doc["seed"]), "query": query.get("query"),
            "frames": int(smoothed.size), "positives": int(labels.sum()),
            "acc": 100.0 * float((decisions == labels).mean()),
            "acc_low": 100.0 * low, "acc_high": 100.0 * high,
            "auc": 100.0 * score_auc(smoothed, labels),
            "near": 100.0 * near_threshold_fraction(smoothed, tau),
            "best_cut": 100.0 * best_cut_accuracy(smoothed, labels),
            "chance_best_cut": 100.0 * float(chance),
            "results": "" if path is None else str(path),
        })
    return rows


def summarise(rows: Iterable[dict]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(per (method, scene): means over seeds of each run's query means, with the seed count;
    per method: means over its scenes)."""
    table = pd.DataFrame(list(rows))
    if not len(table):
        return (pd.DataFrame(columns=["method", "scene", "seeds", *QUERY_VALUES]),
                pd.DataFrame(columns=["method", "scenes", *QUERY_VALUES]))
    per_run = table.groupby(["method", "scene", "seed"], sort=True)[list(QUERY_VALUES)].mean().reset_index()
    per_scene = per_run.groupby(["method", "scene"], sort=True)[list(QUERY_VALUES)].mean().reset_index()
    per_scene.insert(2, "seeds", per_run.groupby(["method", "scene"], sort=True)["seed"].nunique().to_numpy())
    per_method = per_scene.groupby("method", sort=True)[list(QUERY_VALUES)].mean().reset_index()
    per_method.insert(1, "scenes", per_scene.groupby("method", sort=True)["scene"].nunique().to_numpy())
    return per_scene, per_method


def markdown(per_scene: pd.DataFrame, per_method: pd.DataFrame, *, sources: str) -> str:
    """The report's Markdown (tables of :func:`summarise`)."""
    def f(v: float) -> str:
        return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.1f}"

    head = ["Acc (rule)", f"Acc, tau ± {100 * NEAR_THRESHOLD_FRACTION:.0f} % of range", "AUC",
            "near tau (%)", "Acc at the best cut (oracle)", "best cut on shuffled labels"]
    lines = ["# Time-sensitive decisions: how far Acc can be trusted", "",
             f"Generated by `bench4d ablate decisions` from {sources}. Per time-sensitive query, from the recorded",
             "smoothed scores, labels and threshold (no refit): Acc of the protocol's mean-threshold rule; the span",
             f"of Acc when tau moves by {100 * NEAR_THRESHOLD_FRACTION:.0f} % of the query's score range either way; the scores' ROC AUC",
             "(50 = no order); the share of decisions that near tau; Acc at the best single threshold, chosen",
             "knowing the labels (an optimistic bound on any threshold rule over these scores), beside the",
             "same oracle on shuffled labels (what it reaches on scores that carry no information).",
             "Queries -> run (mean) -> scene (mean over seeds) -> method (mean over scenes).", "",
             "## Per method", "",
             "| method | scenes | " + " | ".join(head) + " |", "|---|---:|" + "---:|" * len(head)]
    for r in per_method.to_dict(orient="records"):
        lines.append(f"| {r['method']} | {r['scenes']} | {f(r['acc'])} | {f(r['acc_low'])}–{f(r['acc_high'])} | "
                     f"{f(r['auc'])} | {f(r['near'])} | {f(r['best_cut'])} | {f(r['chance_best_cut'])} |")
    lines += ["", "## Per method and scene", "",
              "| method | scene | seeds | " + " | ".join(head) + " |", "|---|---|---:|" + "---:|" * len(head)]
    for r in per_scene.to_dict(orient="records"):
        lines.append(f"| {r['method']} | {r['scene']} | {r['seeds']} | {f(r['acc'])} | {f(r['acc_low'])}–{f(r['acc_high'])} | "
                     f"{f(r['auc'])} | {f(r['near'])} | {f(r['best_cut'])} | {f(r['chance_best_cut'])} |")
    return "\n".join(lines) + "\n"


def decisions_report(results_dir: Path, *, methods: Optional[Sequence[str]] = None,
                     datasets: Optional[Sequence[str]] = None, scenes: Optional[Sequence[str]] = None,
                     name: str = "time-decisions", out: Path, quiet: bool = False) -> Report:
    """The decisions of every run in ``results_dir`` (only ``methods`` / ``datasets`` / ``scenes`` when
    given) that answered a time-sensitive query from scores, written to ``<out>/<name>.{json,md}``.
    Runs measured on another scene version are left out, as the leaderboard leaves them out."""
    if not results_dir.is_dir():
        raise InputError(results_dir, None, "results folder not found")
    rows = []
    for path in find_results(results_dir):
        doc = load_results(path)
        if scene_status(doc)[1] is False:
            continue
        if ((methods and doc["method"] not in methods) or (datasets and doc["dataset"] not in datasets)
                or (scenes and doc["scene"] not in scenes)):
            continue
        rows += [{**r, "dataset": doc["dataset"], "track": doc["track"]} for r in query_rows(doc, path=path)]
    if not rows:
        raise InputError(results_dir, None, "no recorded run answers a time-sensitive query from scores "
                                            "(with these filters)")
    for r in rows:  # a method on two datasets or tracks: keep them apart
        r["method"] = f"{r['method']} ({r['dataset']}, {r['track']})"
    per_scene, per_method = summarise(rows)
    table = markdown(per_scene, per_method, sources=f"`{results_dir.as_posix()}/`")
    doc = {"per_method": per_method.to_dict(orient="records"), "per_scene": per_scene.to_dict(orient="records"),
           "queries": rows}
    paths = write_report(out, name, doc, table)
    stderr_log(quiet)("wrote " + ", ".join(str(p) for p in paths))
    return Report(table, paths)
