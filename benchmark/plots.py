"""Charts from results files (matplotlib, Agg backend; PNG and PDF side by side).

* :func:`pareto`: accuracy against query FPS and against fit time (log x), mean over the scenes every
  method ran and over seeds with the seed std as error bars, and the Pareto front (no method both
  more accurate and faster) drawn as a step line. One figure per (dataset, track).
* :func:`timeline`: one time-sensitive query over time: the method's raw score ``s_t``, the smoothed
  score, the decision threshold ``tau`` and the ground-truth intervals shaded (the paper's Figure 4
  analogue), read from the per-frame records a results file keeps.
"""

from __future__ import annotations

import io
import math
import textwrap
from pathlib import Path
from typing import TYPE_CHECKING, Optional, Sequence

import numpy as np

from benchmark.core.errors import InputError
from .results import ACCURACY_METRICS, MEAN_SCENE, comparable_runs, find_results, load_results, results_path, runs_table, seed_summary

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def NullFormatter():  # noqa: N802 - mirrors matplotlib's class name
    from matplotlib.ticker import NullFormatter as _Null

    return _Null()


def _save(fig, stem: Path) -> list[Path]:
    from benchmark.core.atomic import atomic_path

    stem.parent.mkdir(parents=True, exist_ok=True)
    write_png(fig, stem.with_suffix(".png"), dpi=150)
    pdf = stem.with_suffix(".pdf")
    with atomic_path(pdf) as tmp:
        # fixed metadata keeps files reproducible from the same results
        fig.savefig(tmp, format="pdf", dpi=150, bbox_inches="tight",
                    metadata={"Creator": "bench4d", "Producer": "bench4d", "CreationDate": None})
    return [stem.with_suffix(".png"), pdf]


def write_png(fig, path: Path, *, dpi: int) -> Path:
    """Write ``fig`` (cropped to its contents) to ``path`` atomically as a PNG of at most 256 colours.

    Charts and galleries hold few colours: the palette file is about a third of the RGBA one matplotlib
    writes, with no visible change (on the committed charts and galleries no channel moves by more than 16
    of 255 levels). Opaque (figures have a background), no dithering (a line keeps one colour) and no
    timestamp (the same figure gives the same bytes).
    """
    from benchmark.core.atomic import write_bytes

    rgba = io.BytesIO()
    fig.savefig(rgba, format="png", dpi=dpi, bbox_inches="tight", metadata={"Software": None})
    write_bytes(path, palette_png(rgba.getvalue()))
    return path


def palette_png(png: bytes) -> bytes:
    """The PNG ``png`` with its colours reduced to a palette of at most 256 (:func:`write_png`)."""
    from PIL import Image

    with Image.open(io.BytesIO(png)) as image:
        palette = image.convert("RGB").quantize(256, method=Image.Quantize.MAXCOVERAGE, dither=Image.Dither.NONE)
    out = io.BytesIO()
    palette.save(out, format="png", optimize=True)
    return out.getvalue()


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


def chart_points(runs: "pd.DataFrame", kind: str) -> tuple["pd.DataFrame", list[str], bool]:
    """Per-method points of one chart row: ``(means, scenes, common)``.

    ``runs`` are the runs of one (dataset, track) (:func:`~benchmark.results.runs_table`); ``kind`` is
    ``"agnostic"`` or ``"sensitive"``. Only runs with that kind's metric count, and only on the scenes
    that *every* such method ran: a mean over seven scenes beside a mean over four would compare scene
    sets, not methods. ``means`` are the :data:`~benchmark.results.MEAN_SCENE` rows of
    :func:`~benchmark.results.seed_summary` over those scenes (one per method, sorted by name);
    ``scenes`` the scene names; ``common`` is False when no scene is common to all methods, and each
    method is then averaged over its own scenes (the chart says so).
    """
    metric = ACCURACY_METRICS[kind][0]
    have = runs[runs[metric].notna()]
    scene_sets = [set(g["scene"]) for _, g in have.groupby("method")]
    scenes = set.intersection(*scene_sets) if scene_sets else set()
    common = bool(scenes)
    if common:
        have = have[have["scene"].isin(scenes)]
    else:
        scenes = set(have["scene"])
    summary = seed_summary(have)
    means = summary[summary["scene"] == MEAN_SCENE].sort_values("method").reset_index(drop=True)
    return means, sorted(scenes), common


def label_groups(x: Sequence[float], y: Sequence[float], *, x_log: bool, tolerance: float = 0.08,
                 spans: Optional[tuple[float, float]] = None) -> list[list[int]]:
    """Indices of points that sit on top of each other, grouped (each group gets one stacked label).

    Positions are compared as fractions of each axis' span: ``spans`` = (x span, y span) of the
    drawn axes (x in decades when ``x_log``), by default the data's own. Two points closer than
    ``tolerance`` on both axes share a group, transitively. Non-finite points are left out. Members
    are listed top to bottom (highest y first, ties by index) so that a stacked label reads in the
    order the points are drawn; groups are in order of their first index.
    """
    xs = np.asarray(x, dtype=float)
    ys = np.asarray(y, dtype=float)
    ok = np.isfinite(xs) & np.isfinite(ys) & ((xs > 0) if x_log else True)
    idx = [int(i) for i in np.flatnonzero(ok)]
    if not idx:
        return []
    px = np.log10(xs[idx]) if x_log else xs[idx]
    py = ys[idx]
    span_x, span_y = spans if spans is not None else (float(np.ptp(px)), float(np.ptp(py)))
    span_x, span_y = max(span_x, 1e-12), max(span_y, 1e-12)
    parent = list(range(len(idx)))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a in range(len(idx)):
        for b in range(a + 1, len(idx)):
            if abs(px[a] - px[b]) / span_x < tolerance and abs(py[a] - py[b]) / span_y < tolerance:
                parent[root(b)] = root(a)
    groups: dict[int, list[int]] = {}
    for a in range(len(idx)):
        groups.setdefault(root(a), []).append(idx[a])
    ordered = [sorted(g, key=lambda i: (-ys[i], i)) for g in groups.values()]
    return sorted(ordered, key=min)


def pareto(results_dir: str | Path = "results", reports_dir: str | Path = "reports") -> list[Path]:
    """Write ``reports/pareto_<dataset>_<track>_<protocol>.{png,pdf}``; returns the files written.

    Each row of panels compares the methods on the scenes all of them ran (:func:`chart_points`),
    named in the row's title line; points that coincide share one stacked label."""
    plt = _pyplot()
    runs = comparable_runs(runs_table(find_results(results_dir), relative_to=Path(results_dir)))[0]
    if not len(runs):
        raise InputError(results_dir, None, "no results files to plot (run bench4d run-all first)")
    written: list[Path] = []
    for (dataset, track, protocol), group_runs in runs.groupby(["dataset", "track", "protocol"], sort=True):
        kinds = [k for k in ("agnostic", "sensitive") if group_runs[ACCURACY_METRICS[k][0]].notna().any()]
        fig, axes = plt.subplots(len(kinds), 2, figsize=(10, 4.4 * len(kinds)), squeeze=False, layout="constrained")
        palette = plt.rcParams["axes.prop_cycle"].by_key()["color"]
        colour = {m: palette[i % len(palette)] for i, m in enumerate(sorted(group_runs["method"].unique()))}
        for row, kind in enumerate(kinds):
            metric = ACCURACY_METRICS[kind][0]
            means, scenes, common = chart_points(group_runs, kind)
            names = means["method"].tolist()
            y = means[f"{metric}_mean"].to_numpy(float)
            yerr = np.nan_to_num(means[f"{metric}_std"].to_numpy(float))
            where = textwrap.fill(f"mean over the {len(scenes)} scene(s) every method ran: {', '.join(scenes)}"
                                  if common else "no scene common to all methods: each method's mean over its "
                                                 "own scenes", width=64)
            for col, (xcol, label, higher) in enumerate(
                    ((f"fps_{kind}", f"query FPS ({kind}) →", True), ("fit_seconds", "← fit time (s)", False))):
                ax = axes[row][col]
                x = means[f"{xcol}_mean"].to_numpy(float)
                xerr = np.nan_to_num(means[f"{xcol}_std"].to_numpy(float))
                # on a log axis a bar reaches down to a thousandth of its value at most (a spread larger
                # than the mean, as of a fit that lasts milliseconds, would reach zero)
                x_low = np.minimum(xerr, x * 0.999)
                ok = np.isfinite(x) & np.isfinite(y) & (x > 0)
                for i in np.flatnonzero(ok):
                    ax.errorbar(x[i], y[i], xerr=[[x_low[i]], [xerr[i]]], yerr=yerr[i],
                                fmt="o", capsize=3, label=names[i], color=colour[names[i]])
                front = pareto_front(np.where(ok, x, np.nan), y, x_higher_better=higher)
                if len(front) >= 1:
                    fx, fy = x[front], y[front]
                    ax.step(fx, fy, where="post" if not higher else "pre", color="0.4", linestyle="--",
                            linewidth=1, label="Pareto front")
                ax.set_xscale("log")
                if ok.any():  # at least a decade each side of the data, labels on powers of ten only
                    lo, hi = float(np.min(x[ok] - x_low[ok])), float(np.max(x[ok] + xerr[ok]))
                    ax.set_xlim(10 ** np.floor(np.log10(lo) - 0.5), 10 ** np.ceil(np.log10(hi) + 0.5))
                ax.margins(y=0.12)
                # one label per spot, placed after the limits are final: methods sharing a fit coincide
                x_lo, x_hi = ax.get_xlim()
                y_lo, y_hi = ax.get_ylim()
                for members in label_groups(np.where(ok, x, np.nan), y, x_log=True,
                                            spans=(math.log10(x_hi / x_lo), y_hi - y_lo)):
                    right = max(members, key=lambda i: x[i])  # the label starts right of every member
                    middle = (max(y[i] for i in members) + min(y[i] for i in members)) / 2
                    ax.annotate("\n".join(names[i] for i in members), (x[right], middle),
                                textcoords="offset points", xytext=(7, 0), fontsize=8, va="center")
                ax.xaxis.set_minor_formatter(NullFormatter())
                ax.set_xlabel(label)
                ax.set_ylabel(f"{metric} (%) ↑")
                ax.set_title(f"{dataset} / {track} / {protocol}: {metric} vs {'query speed' if col == 0 else 'fit time'}\n"
                             f"{where}", fontsize=9)
                ax.grid(True, which="both", alpha=0.3)
                if col == 0:
                    ax.legend(fontsize=7, loc="best")
        fig.suptitle("error bars: std over seeds (seeds that ran all the scenes named)", fontsize=9)
        written += _save(fig, Path(reports_dir) / f"pareto_{dataset}_{track}_{protocol}")
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


def metric_curves(stem: Path, lines: "dict[str, pd.DataFrame]", *, x: str, x_label: str,
                  panels: Sequence[tuple[str, str]], title: str = "", log_x: bool = False,
                  columns: int = 4) -> list[Path]:
    """One figure of small charts, one per ``panels`` entry (column, title), each drawing that column against
    ``x`` with one line per entry of ``lines`` (label -> table of points); written as ``stem``.png / .pdf.
    A panel whose column no table has a value in says so instead of drawing."""
    plt = _pyplot()
    rows = max(1, math.ceil(len(panels) / columns))
    fig, axes = plt.subplots(rows, columns, figsize=(3.2 * columns, 2.8 * rows), squeeze=False, layout="constrained")
    for ax, (column, name) in zip(axes.flat, panels):
        drawn = False
        for label, table in lines.items():
            xs = table[x].to_numpy(float)
            ys = table[column].to_numpy(float) if column in table else np.full(len(table), np.nan)
            ok = np.isfinite(xs) & np.isfinite(ys) & ((xs > 0) if log_x else True)
            if ok.any():
                ax.plot(xs[ok], ys[ok], marker="o", linewidth=1.2, markersize=4, label=label)
                drawn = True
        if not drawn:
            ax.text(0.5, 0.5, "not recorded", ha="center", va="center", transform=ax.transAxes, color="0.5")
        if log_x and drawn:
            ax.set_xscale("log")
            ax.xaxis.set_minor_formatter(NullFormatter())
        if drawn:  # a tick at every value the knob took
            ticks = sorted({float(v) for t in lines.values() for v in t[x].to_numpy(float)
                            if np.isfinite(v) and (v > 0 or not log_x)})
            ax.set_xticks(ticks, [f"{v:g}" for v in ticks])
        ax.set_title(name, fontsize=9)
        ax.set_xlabel(x_label, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, which="both", alpha=0.3)
    for ax in list(axes.flat)[len(panels):]:
        ax.set_visible(False)
    for ax in axes.flat:  # the first panel with lines gives the legend
        handles, labels = ax.get_legend_handles_labels()
        if handles:
            break
    if handles:
        fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 6), fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    written = _save(fig, Path(stem))
    plt.close(fig)
    return written
