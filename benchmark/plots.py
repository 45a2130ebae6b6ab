"""Charts from results files (matplotlib, Agg backend; PNG and PDF side by side).

* :func:`pareto`: accuracy against query FPS and against fit time (log x), mean over the scenes every
  method ran and over seeds with the seed std as error bars, and the Pareto front (no method both
  more accurate and faster) drawn as a step line. One figure per (dataset, track, protocol) and kind of
  machine the runs were timed on. Floors are labelled reference lines, never on the front; the
  perfect-feature ceiling is a line; methods with identical accuracy on every scene and seed (one
  shared stage) are one point with one label; a time-sensitive panel whose methods are all at chance
  says so.
* :func:`timeline`: one time-sensitive query over time: the method's raw score ``s_t``, the smoothed
  score, the decision threshold ``tau`` and the ground-truth intervals shaded (the paper's Figure 4
  analogue), read from the per-frame records a results file keeps.
"""

from __future__ import annotations

import io
import math
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Optional, Sequence

import numpy as np

from benchmark.core.errors import InputError
from benchmark.core.scene import DEFAULT_EVAL_SPLIT
from .results import ACCURACY_METRICS, MEAN_SCENE, comparable_runs, find_results, load_results, results_path, seed_summary

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


def chart_points(runs: "pd.DataFrame", kind: str, *,
                 references: frozenset[str] = frozenset()) -> tuple["pd.DataFrame", list[str], bool]:
    """Per-method points of one chart row: ``(means, scenes, common)``.

    ``runs`` are the runs of one (dataset, track) (:func:`~benchmark.results.runs_table`); ``kind`` is
    ``"agnostic"`` or ``"sensitive"``. Only runs with that kind's metric count, and only on the scenes
    that *every* such method ran: a mean over seven scenes beside a mean over four would compare scene
    sets, not methods. ``means`` are the :data:`~benchmark.results.MEAN_SCENE` rows of
    :func:`~benchmark.results.seed_summary` over those scenes (one per method, sorted by name);
    ``scenes`` the scene names; ``common`` is False when no scene is common to all methods, and each
    method is then averaged over its own scenes (the chart says so). ``references`` (floors) do not
    narrow the scenes: one is kept only where it ran all of them.
    """
    metric = ACCURACY_METRICS[kind][0]
    have = runs[runs[metric].notna()]
    scene_sets = {m: set(g["scene"]) for m, g in have.groupby("method")}
    ranked_sets = [s for m, s in scene_sets.items() if m not in references] or list(scene_sets.values())
    scenes = set.intersection(*ranked_sets) if ranked_sets else set()
    common = bool(scenes)
    if common:
        kept = [m for m, s in scene_sets.items() if scenes <= s]
        have = have[have["scene"].isin(scenes) & have["method"].isin(kept)]
    else:
        scenes = set(have["scene"])
    summary = seed_summary(have)
    means = summary[summary["scene"] == MEAN_SCENE].sort_values("method").reset_index(drop=True)
    return means, sorted(scenes), common


SAME_STAGE_TOLERANCE = 1e-3
"""Largest difference (percentage points) between two methods' accuracy on one (scene, seed) that still
reads as the same number: methods that answer a query kind from one shared stage score identically, up
to float rounding in the fifth digit (the query sets around it differ)."""
CHANCE_AUC = 50.0
"""The ROC AUC of scores that do not order the states (a coin flip)."""
CHANCE_STANDARD_ERRORS = 2.0
"""A method is at chance on the time-sensitive queries when its mean AUC over the chart's runs lies within
this many standard errors (over those runs) of :data:`CHANCE_AUC`."""
UNKNOWN_MACHINE = "unknown"


def machine_kinds(runs: "pd.DataFrame") -> "pd.Series":
    """The kind of machine each run was timed on: the runs table's ``machine_kind`` where it has one
    (prefixed with the ``device`` when it does not name it: a GPU run is never charted with CPU runs),
    else the ``device``, else :data:`UNKNOWN_MACHINE`."""
    import pandas as pd

    def text(row, column: str) -> str:
        value = row.get(column)
        if value is None or (not isinstance(value, str) and bool(pd.isna(value))):  # None, NaN, pd.NA
            return ""
        return str(value).strip()

    kinds = []
    for row in runs.to_dict(orient="records"):
        kind, device = text(row, "machine_kind"), text(row, "device")
        if kind and device and device.lower() not in kind.lower():
            kind = f"{device}: {kind}"
        kinds.append(kind or device or UNKNOWN_MACHINE)
    return pd.Series(kinds, index=runs.index, dtype=object)


def shared_stages(runs: "pd.DataFrame", metric: str, methods: Sequence[str]) -> list[list[str]]:
    """``methods`` grouped by identical ``metric`` on every (scene, seed) of ``runs`` (the same runs, values
    equal within :data:`SAME_STAGE_TOLERANCE`): methods answering from one shared stage, found from the
    numbers, never from the names. Groups in order of their first member; members in ``methods``' order."""
    values: dict[str, dict[tuple[str, int], float]] = {}
    for m in methods:
        rows = runs[(runs["method"] == m) & runs[metric].notna()]
        values[m] = {(str(sc), int(sd)): float(v) for sc, sd, v in zip(rows["scene"], rows["seed"], rows[metric])}
    groups: list[list[str]] = []
    for m in methods:
        for group in groups:
            ref = values[group[0]]
            if ref and ref.keys() == values[m].keys() and all(
                    abs(ref[k] - values[m][k]) <= SAME_STAGE_TOLERANCE for k in ref):
                group.append(m)
                break
        else:
            groups.append([m])
    return groups


def at_chance(runs: "pd.DataFrame", methods: Sequence[str]) -> bool:
    """Whether every one of ``methods`` is at chance on the time-sensitive queries of ``runs``
    (:data:`CHANCE_STANDARD_ERRORS`); False where a method has fewer than two AUC values (no spread to judge
    by) or there are no methods."""
    if not methods or "AUC" not in runs:
        return False
    for m in methods:
        auc = runs[(runs["method"] == m)]["AUC"].dropna().to_numpy(float)
        if auc.size < 2:
            return False
        standard_error = float(auc.std(ddof=1)) / math.sqrt(auc.size)
        if abs(float(auc.mean()) - CHANCE_AUC) > CHANCE_STANDARD_ERRORS * standard_error:
            return False
    return True


@dataclass
class ChartPoint:
    """One drawn point: a method, or methods sharing a stage (same accuracy, speed averaged)."""

    methods: tuple[str, ...]
    """The methods it stands for (several: identical accuracy on every scene and seed)."""
    x: float
    """Mean of the members' mean speed or fit time."""
    x_low: float
    """Left end of the horizontal bar (the lowest member's mean minus its seed std; > 0 on a log axis)."""
    x_high: float
    """Right end of the horizontal bar (the highest member's mean plus its seed std)."""
    y: float
    """Mean accuracy (percent)."""
    yerr: float
    """Seed std of the accuracy (the largest of the members'; 0 for one seed)."""

    @property
    def label(self) -> str:
        return " = ".join(self.methods)

    @property
    def finite(self) -> bool:
        return bool(np.isfinite(self.x) and np.isfinite(self.y) and self.x > 0)


@dataclass
class ParetoPanel:
    """One panel: accuracy of one query kind against query speed or fit time."""

    kind: str
    metric: str
    x_column: str
    higher_is_better: bool
    """Whether larger x is better (speed) or smaller (fit time)."""
    points: list[ChartPoint]
    front: list[int]
    """Indices into ``points`` of the Pareto front (floors are never part of it)."""
    floors: list[ChartPoint]
    """Floors (registry ``floor=True``), drawn as labelled reference lines, not as methods."""
    ceiling: Optional[float]
    """The perfect-feature ceiling (percent, mean over the panel's scenes) where measured for ``metric``."""
    ceiling_note: str
    """Why there is no ceiling line, or an empty string."""
    at_chance: bool
    """Every method (floors aside) is at chance (:func:`at_chance`)."""
    scenes: list[str]
    common: bool


@dataclass
class ParetoChart:
    """One figure: a (dataset, track, protocol, split) timed on one kind of machine, one row of panels per kind."""

    dataset: str
    track: str
    protocol: str
    machine: str
    stem: str
    rows: list[list[ParetoPanel]]
    split: str = DEFAULT_EVAL_SPLIT
    """The evaluation split its runs scored."""


def floor_methods() -> frozenset[str]:
    """Registered methods whose spec says they are floors."""
    from methods import registry

    return frozenset(name for name in registry.names() if registry.get(name).floor)


def _chart_point(means: "pd.DataFrame", members: Sequence[str], metric: str, x_column: str) -> ChartPoint:
    by = means.set_index("method")
    xs = by.loc[list(members), f"{x_column}_mean"].to_numpy(float)
    xerr = np.nan_to_num(by.loc[list(members), f"{x_column}_std"].to_numpy(float))
    ys = by.loc[list(members), f"{metric}_mean"].to_numpy(float)
    yerr = np.nan_to_num(by.loc[list(members), f"{metric}_std"].to_numpy(float))
    x = float(np.mean(xs))
    # on a log axis a bar reaches down to a thousandth of its value at most (a spread larger than the
    # mean, as of a fit that lasts milliseconds, would reach zero)
    low = float(np.min(np.maximum(xs - xerr, xs * 0.001))) if len(xs) else math.nan
    return ChartPoint(tuple(members), x, low, float(np.max(xs + xerr)), float(np.mean(ys)), float(np.max(yerr)))


def _slug(text: str) -> str:
    import re

    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or UNKNOWN_MACHINE


def scene_ceilings(measured: Optional[Mapping[str, Mapping[int, float]]], runs: "pd.DataFrame") -> dict[str, float]:
    """Scene -> the ceiling (fraction) of the scene instances ``runs`` measured: the mean over the scene seeds
    its runs used (a run without a recorded scene seed fitted seed 0's scene); a scene some of whose seeds
    have no measured ceiling is left out."""
    import pandas as pd

    out: dict[str, float] = {}
    if not measured:
        return out
    seeds = runs["scene_seed"] if "scene_seed" in runs else pd.Series(0, index=runs.index)
    for scene, used in seeds.fillna(0).astype(int).groupby(runs["scene"]):
        values = measured.get(str(scene), {})
        wanted = sorted(set(used))
        if wanted and all(s in values for s in wanted):
            out[str(scene)] = float(np.mean([values[s] for s in wanted]))
    return out


def pareto_charts(runs: "pd.DataFrame", *, floors: frozenset[str] = frozenset(),
                  ceilings: Optional[Mapping[tuple[str, str, str], Mapping[str, Mapping[int, float]]]] = None
                  ) -> list[ParetoChart]:
    """What :func:`pareto` draws, from a runs table: one chart per (dataset, track, protocol, evaluation split)
    and kind of machine (:func:`machine_kinds`; timings of different machines are never compared on one
    axis), named ``pareto_<dataset>_<track>_<protocol>_<split>``, with ``_<machine>`` added where one was timed
    on several. ``floors`` are reference lines, never points of the front; ``ceilings`` is
    :attr:`benchmark.leaderboard.Ceilings.values` ((protocol, split, kind) -> scene -> scene seed -> value)."""
    from .leaderboard import CEILING_METRIC

    ceilings = ceilings or {}
    runs = runs.assign(machine=machine_kinds(runs))
    split_of = runs["split"].fillna(DEFAULT_EVAL_SPLIT) if "split" in runs else DEFAULT_EVAL_SPLIT
    runs = runs.assign(split=split_of)
    charts: list[ParetoChart] = []
    for (dataset, track, protocol, split), group in runs.groupby(["dataset", "track", "protocol", "split"],
                                                                 sort=True):
        machines = sorted(group["machine"].unique())
        for machine in machines:
            mine = group[group["machine"] == machine]
            rows: list[list[ParetoPanel]] = []
            for kind in ("agnostic", "sensitive"):
                metric = ACCURACY_METRICS[kind][0]
                if not mine[mine[metric].notna() & ~mine["method"].isin(floors)].shape[0]:
                    continue  # nothing but floors (or nothing) answered this kind
                means, scenes, common = chart_points(mine, kind, references=floors)
                have = mine[mine[metric].notna() & mine["scene"].isin(scenes)]
                ranked = [m for m in means["method"] if m not in floors]
                stages = shared_stages(have, metric, ranked)
                chance = kind == "sensitive" and at_chance(have, ranked)
                measured = scene_ceilings(ceilings.get((protocol, split, kind)), have)
                ceiling, note = None, ""
                if CEILING_METRIC.get(kind) != metric:
                    note = (f"no ceiling line: the perfect-feature ceiling is measured for {CEILING_METRIC.get(kind)}, "
                            f"not {metric} (perfect features make no temporal decisions)")
                elif common and scenes and all(s in measured for s in scenes):
                    ceiling = 100.0 * sum(measured[s] for s in scenes) / len(scenes)
                elif any(s in measured for s in scenes):
                    note = (f"no ceiling line: the ceiling is measured on {sum(s in measured for s in scenes)} of "
                            f"these {len(scenes)} scenes")
                else:
                    note = "no ceiling line: no perfect-feature ceiling measured on these scenes"
                row = []
                for x_column, higher in ((f"fps_{kind}", True), ("fit_seconds", False)):
                    points = [_chart_point(means, members, metric, x_column) for members in stages]
                    front = pareto_front([p.x if p.finite else math.nan for p in points], [p.y for p in points],
                                         x_higher_better=higher)
                    floor_points = [_chart_point(means, [m], metric, x_column)
                                    for m in means["method"] if m in floors]
                    row.append(ParetoPanel(kind, metric, x_column, higher, points, front, floor_points, ceiling,
                                           note, chance, scenes, common))
                rows.append(row)
            if rows:
                stem = (f"pareto_{dataset}_{track}_{protocol}_{split}"
                        + (f"_{_slug(machine)}" if len(machines) > 1 else ""))
                charts.append(ParetoChart(dataset, track, protocol, machine, stem, rows, split))
    return charts


LABEL_LINE_HEIGHT = 0.045
"""Height of one line of a point label (8 pt) as a fraction of a chart panel's height."""


def line_label_groups(ys: Sequence[float], *, y_span: float) -> list[list[int]]:
    """Indices of horizontal lines at heights ``ys`` grouped so that lines closer than one label line
    (:data:`LABEL_LINE_HEIGHT` of ``y_span``) share one label: two floors at one height would print their
    names over each other. Groups in order of height."""
    order = sorted(range(len(ys)), key=lambda i: ys[i])
    groups: list[list[int]] = []
    for i in order:
        if groups and ys[i] - ys[groups[-1][-1]] < LABEL_LINE_HEIGHT * y_span:
            groups[-1].append(i)
        else:
            groups.append([i])
    return groups


def label_clusters(points: Sequence[ChartPoint], *, x_span: float, y_span: float) -> list[list[int]]:
    """Indices of ``points`` (finite, on a log x axis spanning ``x_span`` decades and a y axis spanning
    ``y_span``) whose labels share one stacked label: those that coincide (:func:`label_groups`), joined
    while two clusters' horizontal bars overlap and their labels (:data:`LABEL_LINE_HEIGHT` a line) would
    overlap. Members top to bottom."""
    xs = [p.x for p in points]
    ys = [p.y for p in points]
    clusters = label_groups(xs, ys, x_log=True, spans=(x_span, y_span))

    def lines(c: list[int]) -> int:
        return sum(len(points[i].methods) for i in c)

    def y_range(c: list[int]) -> tuple[float, float]:
        mid = (max(ys[i] for i in c) + min(ys[i] for i in c)) / 2
        half = lines(c) * LABEL_LINE_HEIGHT * y_span / 2
        return mid - half, mid + half

    merged = True
    while merged:
        merged = False
        for a in range(len(clusters)):
            for b in range(a + 1, len(clusters)):
                ca, cb = clusters[a], clusters[b]
                xa = (min(points[i].x_low for i in ca), max(points[i].x_high for i in ca))
                xb = (min(points[i].x_low for i in cb), max(points[i].x_high for i in cb))
                (la, ha), (lb, hb) = y_range(ca), y_range(cb)
                if xa[0] <= xb[1] and xb[0] <= xa[1] and la <= hb and lb <= ha:
                    clusters[a] = sorted(ca + cb, key=lambda i: (-ys[i], i))
                    del clusters[b]
                    merged = True
                    break
            if merged:
                break
    return sorted(clusters, key=min)


def method_colours(methods: Sequence[str]) -> dict[str, Any]:
    """A colour per method, no two alike: matplotlib's ten-colour cycle while it suffices, else ``tab20``
    (a base method and its ``+`` variant, sorted next to each other, get a dark and a light shade of one hue
    when their count fills the pairs)."""
    plt = _pyplot()
    palette = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    if len(methods) > len(palette):
        palette = [plt.get_cmap("tab20")(i) for i in range(20)]
    return {m: palette[i % len(palette)] for i, m in enumerate(methods)}


def _draw_pareto_panel(ax, panel: ParetoPanel, colour: dict[str, str], *, legend: bool) -> None:
    shown = [p for p in panel.points if p.finite]
    for p in shown:  # faded where all are at chance: their order means nothing
        ax.errorbar(p.x, p.y, xerr=[[p.x - p.x_low], [p.x_high - p.x]], yerr=p.yerr, fmt="o", capsize=3,
                    label=p.label, color=colour[p.methods[0]], alpha=0.45 if panel.at_chance else 1.0)
    if panel.front:
        fx = [panel.points[i].x for i in panel.front]
        fy = [panel.points[i].y for i in panel.front]
        ax.step(fx, fy, where="pre" if panel.higher_is_better else "post", color="0.4", linestyle="--",
                linewidth=1, label="Pareto front (floors left out)")
    ax.set_xscale("log")
    if shown:  # at least a decade each side of the methods (floors are lines: they do not stretch the axis)
        lo, hi = min(p.x_low for p in shown), max(p.x_high for p in shown)
        ax.set_xlim(10 ** np.floor(np.log10(lo) - 0.5), 10 ** np.ceil(np.log10(hi) + 0.5))
    speed = panel.x_column != "fit_seconds"
    for f in panel.floors:
        if not np.isfinite(f.y):
            continue
        where = "" if not np.isfinite(f.x) else (f", {_sig(f.x)} FPS" if speed else f", fit {_sig(f.x)} s")
        ax.axhline(f.y, color="0.35", linestyle=":", linewidth=1.4,
                   label=f"2D floor {f.label} (not ranked): {f.y:.1f}{where}")
    if panel.ceiling is not None:
        ax.axhline(panel.ceiling, color="tab:green", linestyle="-.", linewidth=1.2,
                   label=f"perfect-feature ceiling: {panel.ceiling:.1f}")
        ax.annotate("ceiling (perfect features)", (0.0, panel.ceiling), xycoords=ax.get_yaxis_transform(),
                    textcoords="offset points", xytext=(4, -2), ha="left", va="top", fontsize=7.5,
                    color="tab:green")
    ys = [p.y + e for p in shown for e in (p.yerr, -p.yerr)] + [f.y for f in panel.floors if np.isfinite(f.y)]
    ys += [] if panel.ceiling is None else [panel.ceiling]
    if ys:
        lo, hi = min(ys), max(ys)
        pad = max(0.12 * (hi - lo), 2.0)
        ax.set_ylim(lo - pad, hi + pad)
    # one label per cluster, placed after the limits are final, right of the cluster's bars
    x_lo, x_hi = ax.get_xlim()
    y_lo, y_hi = ax.get_ylim()
    floors = [f for f in panel.floors if np.isfinite(f.y)]
    for members in line_label_groups([f.y for f in floors], y_span=y_hi - y_lo):
        # at the left edge, below the lowest line of the group: method labels are right of their points
        names = ", ".join(floors[i].label for i in members)
        ax.annotate(f"floor{'s' if len(members) > 1 else ''}: {names}", (0.0, min(floors[i].y for i in members)),
                    xycoords=ax.get_yaxis_transform(), textcoords="offset points", xytext=(4, -2), ha="left",
                    va="top", fontsize=7.5, color="0.3")
    for members in label_clusters(shown, x_span=math.log10(x_hi / x_lo), y_span=y_hi - y_lo):
        middle = (max(shown[i].y for i in members) + min(shown[i].y for i in members)) / 2
        text = "\n".join(shown[i].methods[0] + "".join(f"\n= {m}" for m in shown[i].methods[1:]) for i in members)
        ax.annotate(text, (max(shown[i].x_high for i in members), middle), textcoords="offset points",
                    xytext=(6, 0), fontsize=8, va="center")
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel(f"query FPS ({panel.kind}) →" if speed else "← fit time (s), every stage")
    ax.set_ylabel(f"{panel.metric} (%) ↑")
    where = (f"mean over the {len(panel.scenes)} scene(s) every method ran: {', '.join(panel.scenes)}"
             if panel.common else "no scene common to all methods: each method's mean over its own scenes")
    lines = [f"{panel.metric} vs {'query speed' if speed else 'fit time'}", textwrap.fill(where, width=70)]
    if panel.ceiling_note:
        lines.append(textwrap.fill(panel.ceiling_note, width=70))
    if panel.at_chance:
        lines.append(textwrap.fill(f"ALL METHODS AT CHANCE: every method's AUC is within {CHANCE_STANDARD_ERRORS:g} "
                                   "standard errors of 50 (its scores do not order the states)", width=70))
    ax.set_title("\n".join(lines), fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    if legend:  # below the panel, clear of the points
        ax.legend(fontsize=7.5, loc="upper left", bbox_to_anchor=(0.0, -0.13), ncols=2, frameon=False)


def _sig(value: float) -> str:
    return f"{value:.0f}" if abs(value) >= 100 else f"{value:.3g}"


def pareto(results_dir: str | Path = "results", reports_dir: str | Path = "reports",
           ceiling: Optional[str | Path] = None) -> list[Path]:
    """Write ``reports/pareto_<dataset>_<track>_<protocol>_<split>[_<machine>].{png,pdf}`` (:func:`pareto_charts`);
    returns the files written. ``ceiling``: the protocol ceiling's JSON (default:
    ``<reports_dir>/ablations/protocol-ceiling.json``; no line where it is missing)."""
    from .leaderboard import CEILING_FILE, load_ceiling_file, load_runs, ranked_runs, with_defaults

    plt = _pyplot()
    # as the leaderboard reads them: each run under the name its recorded config stands for today, its
    # accuracy the ranked one (draft queries out), so a point sits where the leaderboard's mean does
    runs, queries = load_runs(results_dir)
    runs = ranked_runs(comparable_runs(with_defaults(runs))[0], queries)
    if not len(runs):
        raise InputError(results_dir, None, "no results files to plot (run bench4d run-all first)")
    ceilings = load_ceiling_file(Path(reports_dir) / CEILING_FILE if ceiling is None else ceiling).values
    written: list[Path] = []
    for chart in pareto_charts(runs, floors=floor_methods(), ceilings=ceilings):
        fig, axes = plt.subplots(len(chart.rows), 2, figsize=(11, 5.8 * len(chart.rows)), squeeze=False,
                                 layout="constrained")
        methods = sorted({p.methods[0] for row in chart.rows for panel in row for p in panel.points})
        colour = method_colours(methods)
        for r, row in enumerate(chart.rows):
            for c, panel in enumerate(row):
                _draw_pareto_panel(axes[r][c], panel, colour, legend=c == 0)
        fig.suptitle(f"{chart.dataset} / {chart.track} / {chart.protocol} / {chart.split} split, timed on: "
                     f"{chart.machine}\n"
                     "error bars: std over seeds (seeds that ran all the scenes named); methods with the same "
                     "accuracy on every scene and seed\n(one shared stage) are one point at their mean speed, "
                     "its bar spanning theirs", fontsize=9)
        written += _save(fig, Path(reports_dir) / chart.stem)
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
        why = (" (dropped by bench4d slim: rerun bench4d eval for them)" if scores.get("frames_dropped")
               else "")
        raise InputError(path, "scores.frames", f"no per-frame records for {query!r}{why}")
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
    A table with ``<column>_low`` and ``<column>_high`` gets that band shaded under its line (an interval).
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
                (line,) = ax.plot(xs[ok], ys[ok], marker="o", linewidth=1.2, markersize=4, label=label)
                if f"{column}_low" in table and f"{column}_high" in table:
                    lo, hi = table[f"{column}_low"].to_numpy(float)[ok], table[f"{column}_high"].to_numpy(float)[ok]
                    ax.fill_between(xs[ok], lo, hi, color=line.get_color(), alpha=0.15, linewidth=0)
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
