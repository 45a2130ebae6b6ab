"""Charts from results files (matplotlib, Agg backend; PNG and PDF side by side).

* :func:`pareto`: accuracy against query FPS and against fit time (log x), mean over scenes and
  seeds with the seed std as error bars, and the Pareto front (no method both more accurate and
  faster) drawn as a step line. One figure per (dataset, track).
* :func:`timeline`: one time-sensitive query over time: the method's raw score ``s_t``, the smoothed
  score, the decision threshold ``tau`` and the ground-truth intervals shaded (the paper's Figure 4
  analogue), read from the per-frame records a results file keeps.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from .errors import InputError
from .results import ACCURACY_METRICS, MEAN_SCENE, comparable_runs, find_results, load_results, results_path, runs_table, seed_summary


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def NullFormatter():  # noqa: N802 - mirrors matplotlib's class name
    from matplotlib.ticker import NullFormatter as _Null

    return _Null()


def _save(fig, stem: Path) -> list[Path]:
    from .atomic import atomic_path

    stem.parent.mkdir(parents=True, exist_ok=True)
    out = []
    for ext in ("png", "pdf"):
        path = stem.with_suffix(f".{ext}")
        with atomic_path(path) as tmp:
            # fixed metadata keeps files reproducible from the same results
            meta = {"Software": "bench4d"} if ext == "png" else {"Creator": "bench4d", "Producer": "bench4d",
                                                                 "CreationDate": None}
            fig.savefig(tmp, format=ext, dpi=150, bbox_inches="tight", metadata=meta)
        out.append(path)
    return out


def pareto_front(x: Sequence[float], y: Sequence[float], *, x_higher_better: bool) -> list[int]:
    """Indices of the non-dominated points (maximise ``y``; maximise or minimise ``x``), sorted by x.

    A point is dominated when another is at least as good on both axes and better on one.
    """
    pts = [(float(a), float(b), i) for i, (a, b) in enumerate(zip(x, y)) if np.isfinite(a) and np.isfinite(b)]
    front = []
    for a, b, i in pts:
        dominated = False
        for c, d, j in pts:
            if j == i:
                continue
            better_x = c >= a if x_higher_better else c <= a
            strictly = (c != a) or (d != b)
            if better_x and d >= b and strictly:
                dominated = True
                break
        if not dominated:
            front.append(i)
    return sorted(front, key=lambda i: float(x[i]))


def pareto(results_dir: str | Path = "results", reports_dir: str | Path = "reports") -> list[Path]:
    """Write ``reports/pareto_<dataset>_<track>.{png,pdf}``; returns the files written."""
    plt = _pyplot()
    runs = comparable_runs(runs_table(find_results(results_dir), relative_to=Path(results_dir)))[0]
    if not len(runs):
        raise InputError(results_dir, None, "no results files to plot (run bench4d run-all first)")
    summary = seed_summary(runs)
    written: list[Path] = []
    for (dataset, track), group in summary.groupby(["dataset", "track"], sort=True):
        means = group[group["scene"] == MEAN_SCENE].sort_values("method")
        kinds = [k for k in ("agnostic", "sensitive") if means[f"{ACCURACY_METRICS[k][0]}_mean"].notna().any()]
        fig, axes = plt.subplots(len(kinds), 2, figsize=(10, 4 * len(kinds)), squeeze=False, layout="constrained")
        for row, kind in enumerate(kinds):
            metric = ACCURACY_METRICS[kind][0]
            y = means[f"{metric}_mean"].to_numpy(float)
            yerr = np.nan_to_num(means[f"{metric}_std"].to_numpy(float))
            for col, (xcol, label, higher) in enumerate(
                    ((f"fps_{kind}", f"query FPS ({kind}) →", True), ("fit_seconds", "← fit time (s)", False))):
                ax = axes[row][col]
                x = means[f"{xcol}_mean"].to_numpy(float)
                xerr = np.nan_to_num(means[f"{xcol}_std"].to_numpy(float))
                ok = np.isfinite(x) & np.isfinite(y) & (x > 0)
                for i in np.flatnonzero(ok):
                    ax.errorbar(x[i], y[i], xerr=[[min(xerr[i], x[i] * 0.999)], [xerr[i]]], yerr=yerr[i],
                                fmt="o", capsize=3, label=means["method"].iloc[i])
                    ax.annotate(means["method"].iloc[i], (x[i], y[i]), textcoords="offset points", xytext=(5, 5),
                                fontsize=8)
                front = pareto_front(np.where(ok, x, np.nan), y, x_higher_better=higher)
                if len(front) >= 1:
                    fx, fy = x[front], y[front]
                    ax.step(fx, fy, where="post" if not higher else "pre", color="0.4", linestyle="--",
                            linewidth=1, label="Pareto front")
                ax.set_xscale("log")
                if ok.any():  # at least a decade each side of the data, labels on powers of ten only
                    lo, hi = float(np.min(x[ok] - xerr[ok] * 0.999)), float(np.max(x[ok] + xerr[ok]))
                    ax.set_xlim(10 ** np.floor(np.log10(lo) - 0.5), 10 ** np.ceil(np.log10(hi) + 0.5))
                ax.xaxis.set_minor_formatter(NullFormatter())
                ax.set_xlabel(label)
                ax.set_ylabel(f"{metric} (%) ↑")
                ax.set_title(f"{dataset} / {track}: {metric} vs {'query speed' if col == 0 else 'fit time'}")
                ax.grid(True, which="both", alpha=0.3)
                if col == 0:
                    ax.legend(fontsize=7, loc="best")
        fig.suptitle("mean over scenes; error bars: std over seeds", fontsize=9)
        written += _save(fig, Path(reports_dir) / f"pareto_{dataset}_{track}")
        plt.close(fig)
    return written


def _intervals(times: np.ndarray, labels: np.ndarray) -> list[tuple[float, float]]:
    """Spans [first - 0.5, last + 0.5] of consecutive evaluated frames labelled positive."""
    spans: list[tuple[float, float]] = []
    start = prev = None
    for t, lab in zip(times, labels):
        if lab and start is None:
            start = t
        if not lab and start is not None:
            spans.append((start - 0.5, prev + 0.5))
            start = None
        prev = t
    if start is not None:
        spans.append((start - 0.5, prev + 0.5))
    return spans


def _timeline_doc(method: str, scene: str, query: str, *, results_dir, track: str, seed: int,
                  dataset: Optional[str]) -> tuple[dict, dict, list]:
    """(results doc, the query's score row, its per-frame records sorted by time) of one method's run."""
    candidates = [p for p in find_results(results_dir)
                  if p.parent.name == track and p.parent.parent.name == method and p.parent.parent.parent.name == scene
                  and p.name == f"seed{seed}.json" and (dataset is None or p.parents[3].name == dataset)]
    if not candidates:
        where = results_path(results_dir, dataset or "<dataset>", scene, method, track, seed)
        raise InputError(where, None, "no results file (run bench4d eval first)")
    if len(candidates) > 1:
        raise InputError(results_dir, "dataset", f"scene {scene!r} exists in several datasets; pass --dataset")
    path = candidates[0]
    doc = load_results(path)
    scores = doc.get("scores", {})
    rows = [q for q in scores.get("queries", []) if q.get("query") == query]
    if not rows:
        texts = sorted({q.get("query") for q in scores.get("queries", []) if q.get("kind") == "sensitive"})
        raise InputError(path, "scores.queries", f"no query {query!r}; time-sensitive queries: {texts}")
    row = rows[0]
    if row.get("kind") != "sensitive":
        raise InputError(path, "scores.queries", f"{query!r} is a time-agnostic query; a timeline needs a time-sensitive one")
    frames = sorted((f for f in scores.get("frames", []) if f.get("query") == query),
                    key=lambda f: (f["time_index"], f.get("camera_id", ""), f["frame"]))
    if not frames:
        raise InputError(path, "scores.frames", f"no per-frame records for {query!r}")
    return doc, row, frames


def timeline(method: str | Sequence[str], scene: str, query: str, *, results_dir: str | Path = "results",
             reports_dir: str | Path = "reports", track: str = "oracle", seed: int = 0,
             dataset: Optional[str] = None) -> list[Path]:
    """Write ``reports/timeline_<scene>_<methods>_<query slug>.{png,pdf}`` for one time-sensitive query:
    one panel per method (stacked, shared time axis: methods score on different scales, e.g. relevance
    vs caption cosine), each with its scores, smoothed scores, threshold, decisions and the truth."""
    from .predictions import query_slug

    methods = [method] if isinstance(method, str) else list(method)
    if not methods:
        raise InputError(None, "--method", "give at least one method")
    runs = [_timeline_doc(m, scene, query, results_dir=results_dir, track=track, seed=seed, dataset=dataset)
            for m in methods]
    plt = _pyplot()
    fig, axes = plt.subplots(len(runs), 1, figsize=(9, 2.9 * len(runs)), layout="constrained", sharex=True,
                             squeeze=False)
    for ax, (doc, row, frames) in zip(axes[:, 0], runs):
        t = np.array([f["time_index"] for f in frames], dtype=float)
        s = np.array([np.nan if f.get("score") is None else f["score"] for f in frames], dtype=float)
        sm = np.array([np.nan if f.get("smoothed") is None else f["smoothed"] for f in frames], dtype=float)
        labels = np.array([bool(f.get("label")) for f in frames])
        decisions = np.array([bool(f.get("decision")) for f in frames])
        tau = row.get("threshold")
        for i, (a, b) in enumerate(_intervals(t, labels)):
            ax.axvspan(a, b, color="tab:green", alpha=0.15, label="ground truth holds" if i == 0 else None)
        ax.plot(t, s, "o-", color="tab:blue", markersize=3, linewidth=1, label="score $s_t$")
        if np.isfinite(sm).any():
            ax.plot(t, sm, "-", color="tab:orange", linewidth=1.5, label="smoothed $\\tilde s_t$")
        if tau is not None and math.isfinite(tau):
            ax.axhline(tau, color="tab:red", linestyle="--", linewidth=1, label=f"threshold τ = {tau:.3f}")
        # decisions as a strip along the bottom edge (axes coordinates), clear of the curves
        ax.scatter(t[decisions], np.full(decisions.sum(), 0.04), marker="|", color="black", s=80,
                   transform=ax.get_xaxis_transform(), label="predicted: holds")
        ax.set_ylabel("similarity")
        viou, acc = row.get("vIoU"), row.get("Acc")
        acc_txt = "–" if acc is None else f"{acc:.1f}"
        viou_txt = "–" if viou is None else f"{viou:.1f}"
        ax.set_title(f"{doc['method']} on {doc['dataset']}/{doc['scene']} ({doc['track']}, seed {doc['seed']}): "
                     f"“{query}”  Acc {acc_txt}%, vIoU {viou_txt}%", fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    axes[-1, 0].set_xlabel("time index (evaluated frames)")
    doc = runs[0][0]
    stem = Path(reports_dir) / f"timeline_{doc['scene']}_{'-vs-'.join(methods)}_{query_slug(query)}"
    written = _save(fig, stem)
    plt.close(fig)
    return written
