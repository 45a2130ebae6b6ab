"""The paper's tables beside ours: ``reports/paper-tables.md`` (``bench4d paper-tables``).

Every table of 4D LangSplat (CVPR 2025) -- time-agnostic per dataset, time-sensitive, the captioner's
visual- and text-prompt Delta-sim, the number of states, query speed -- with the published numbers
(:mod:`methods.specs.paper_numbers`) beside our runs on the analogous scenes: the synthetic presets
named after the HyperNeRF scenes, and ``cook-spinach`` for Neu3D's ``cook_spinach``. Ours are the
results files' means over seeds under one protocol (default: ``release``), one track (default: oracle)
and one split (default: the paper's where results have it), counted as the leaderboard counts them
(:func:`benchmark.leaderboard.ranked_values`: every query, unanswered ones at 0, drafts left out), each
dataset mean with its 95 % interval (:mod:`benchmark.stats`). Only paper-config runs are read: a run whose
recorded config is not its method's default (the paper's components) is left out, and so is every
registered variant. For each table with a method ordering: Kendall's tau between the paper's ordering and
ours over the methods both have, with its exact permutation p-value, and whether the paper's best method
is also best here (tied where the 95 % intervals overlap).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Optional, Sequence

import pandas as pd

from benchmark.core.atomic import read_json
from benchmark.core.errors import InputError
from benchmark.core.protocol import DEFAULT_PROTOCOL, RELEASE_DEFECTS_NOT_COPIED, SCORED_FRAMES_NOTE
from . import stats
from .leaderboard import (LEGACY_SPLIT, SPLIT_TITLE, _Cells, _fmt, _machine_spread, check_provenance, load_runs, md,
                          ranked_values, split_order, with_defaults)
from .results import ACCURACY_METRICS, MEAN_SCENE, comparable_runs, seed_summary

SYNTHETIC_ANALOGUE = {("hypernerf", s): s for s in
                      ("americano", "chickchicken", "split-cookie", "espresso", "keyboard", "torchocolate")}
SYNTHETIC_ANALOGUE[("neu3d", "cook_spinach")] = "cook-spinach"
"""(paper dataset, paper scene) -> the synthetic preset modelled on it (same objects, states and camera kind)."""

AGNOSTIC_METHODS = ("feature-3dgs", "gaussian-grouping", "langsplat", "4d-langsplat")
"""The paper's time-agnostic comparison, in its table's order (weakest first)."""
SENSITIVE_METHODS = ("langsplat", "deformable-clip", "non-status-field", "4d-langsplat")
"""The paper's time-sensitive comparison (Table 1), in its order."""


def kendall_tau(paper: dict[str, float], ours: dict[str, float]) -> tuple[float, int, float]:
    """(Kendall's tau-b between the two scorings over the methods both give a finite value, that count, the
    two-sided p-value of an exact permutation test: :func:`benchmark.stats.kendall_tau_test`); NaN below two
    methods. Our tied means (:func:`_comparable`) are one value."""
    merged = _comparable(paper, ours)
    if len(merged) < 2:
        return math.nan, len(merged), math.nan
    tau, p = stats.kendall_tau_test([paper[m] for m in merged], list(merged.values()))
    return tau, len(merged), p


def _comparable(paper: dict[str, float], ours: dict[str, float]) -> dict[str, float]:
    """Our value of each method both give a finite value for (in ``paper``'s order), means within
    :data:`TIE_TOLERANCE` of a neighbour in sorted order set to the first of their run: one tie rule for the
    rank agreement and the best-method verdict."""
    common = [m for m in paper if m in ours and _finite(paper[m]) and _finite(ours[m])]
    merged = {m: float(ours[m]) for m in common}
    order = sorted(common, key=lambda m: ours[m])
    for prev, cur in zip(order, order[1:]):
        if ours[cur] - ours[prev] <= TIE_TOLERANCE:
            merged[cur] = merged[prev]
    return merged


def _finite(value: Any) -> bool:
    return value is not None and isinstance(value, (int, float)) and math.isfinite(float(value))


def _mean(values: Sequence[Optional[float]]) -> float:
    """Mean of ``values``; NaN if one is missing."""
    return float(sum(values) / len(values)) if values and all(_finite(v) for v in values) else math.nan


def _cell(paper: Optional[float], ours: Optional[float]) -> str:
    p = f"{paper:.2f}" if _finite(paper) else "–"
    o = f"{ours:.2f}" if _finite(ours) else "–"
    return f"{p} / {o}"


TIE_TOLERANCE = 1e-6
"""Our means closer than this (percentage points) are one value: means of the same per-scene scores summed in
another order differ in the last bits."""


def _agreement(paper: dict[str, float], ours: dict[str, float], display: dict[str, str],
               intervals: Optional[dict[str, tuple[float, float]]] = None) -> str:
    """One line: Kendall's tau of the two orderings with its p-value, and whether the paper's best is best here:
    our best are tie group 1 (:func:`benchmark.stats.tie_groups`) by ``intervals`` (our 95 % intervals), or,
    without them, the means equal to the top one."""
    tau, n, p = kendall_tau(paper, ours)
    if n < 2:
        return f"_Rank agreement: not measurable ({n} method(s) with both numbers)._"
    merged = _comparable(paper, ours)
    paper_best = max(merged, key=lambda m: paper[m])
    if intervals:
        groups = stats.tie_groups(merged, {m: intervals.get(m, (math.nan, math.nan)) for m in merged})
        best_here = [m for m in merged if groups.get(m) == 1]
    else:
        top = max(merged.values())
        best_here = [m for m in merged if merged[m] == top]  # tied means count as a shared best
    tie = "within 95 % intervals" if intervals else "equal means"
    if paper_best in best_here:
        others = [display.get(m, m) for m in best_here if m != paper_best]
        wins = "yes" if not others else f"tied ({tie}) with {', '.join(others)}"
    else:
        wins = f"no (best here: {', '.join(display.get(m, m) for m in best_here)})"
    p_text = f"p = {p:.3f}" if math.isfinite(p) else "p not defined"
    return (f"_Rank agreement over {n} methods: Kendall's tau = {tau:+.2f} ({p_text}, exact permutation test; "
            f"with {n} methods the smallest possible p is {2 / math.factorial(n):.3f}); the paper's best "
            f"({display.get(paper_best, paper_best)}) is best here: {wins}._")


def _paper_config(doc: dict) -> Optional[bool]:
    """Whether a run ran its method's default config (the paper's components) and is no registered variant;
    None for a method the registry does not know."""
    from methods import registry

    try:
        spec = registry.get(str(doc.get("method")))
    except InputError:
        return None
    if getattr(spec, "variant_of", None):
        return False
    return bool(spec.recorded_as(doc.get("method_config")))


class OurNumbers:
    """Mean over seeds per (method, preset, metric) of one protocol, track and split's comparable paper-config
    runs on the official synthetic presets, with 95 % intervals of dataset means."""

    def __init__(self, results_dir: str | Path, *, protocol: str, track: str, split: Optional[str] = None,
                 allow_dirty: bool = False) -> None:
        runs, queries = load_runs(results_dir, extra=lambda doc: {"paper_config": _paper_config(doc)})
        self.not_paper_config = 0
        self.splits: list[str] = []
        self.dirty = 0
        if len(runs):
            runs = comparable_runs(with_defaults(runs))[0]
            runs = runs[(runs["protocol"] == protocol) & (runs["track"] == track) & (runs["dataset"] == "synthetic")
                        & runs["official"].astype(bool)]
            self.splits = sorted(set(runs["split"]), key=split_order)
        self.split = split or (self.splits[0] if self.splits else LEGACY_SPLIT)
        if len(runs):
            runs = runs[runs["split"] == self.split]
            check_provenance(runs, allow_dirty, results_dir)
            self.not_paper_config = int((runs["paper_config"] != True).sum())  # noqa: E712 (None counts as not)
            runs = runs[runs["paper_config"] == True]  # noqa: E712
            self.dirty = int(runs["dirty"].sum())
            for kind in ACCURACY_METRICS:
                adjusted = ranked_values(runs, queries, kind)
                for metric in (*ACCURACY_METRICS[kind], *(("AUC",) if kind == "sensitive" else ())):
                    runs[metric] = adjusted[metric].to_numpy()
        self.runs = runs
        self.queries = queries
        self.summary = seed_summary(runs) if len(runs) else pd.DataFrame()
        self.seeds = sorted(set(runs["seed"])) if len(runs) else []
        self.machines = sorted(set(runs["machine_kind"])) if len(runs) else []
        self._cells: dict[str, _Cells] = {}

    def header_notes(self) -> str:
        """The split, machine kinds and runs left out, for the page's header."""
        text = f"split `{md(self.split)}` ({SPLIT_TITLE.get(self.split, 'a split of the scenes')})"
        others = [s for s in self.splits if s != self.split]
        if others:
            text += f"; other splits with results: {', '.join(md(s) for s in others)} (`--split`)"
        text += "; machine kinds: " + (", ".join(md(m) for m in self.machines) or "none")
        if len(self.machines) > 1:
            text += " (mixed within the means)"
        if self.not_paper_config:
            text += (f"; {self.not_paper_config} run(s) left out whose recorded config is not their method's default "
                     "(the paper's components) or that are of a registered variant")
        if self.dirty:
            text += f"; {self.dirty} run(s) from a dirty or changing checkout included (`--allow-dirty`)"
        return text

    def machine_spread(self, method: str, scenes: Sequence[str], metric: str) -> float:
        """The spread of ``method``'s mean ``metric`` over ``scenes`` between the machine kinds its runs ran on
        (:func:`benchmark.leaderboard._machine_spread`); NaN for one kind."""
        if not len(self.runs):
            return math.nan
        mine = self.runs[(self.runs["method"] == method) & self.runs["scene"].isin(list(scenes))]
        return _machine_spread(mine, metric)[1]

    def interval(self, methods: Sequence[str], scenes: Sequence[str], metric: str) -> dict[str, tuple[float, float]]:
        """Method -> the 95 % interval of its mean over ``scenes`` of its per-scene means (every seed it has on
        each): stratified bootstrap over seeds and queries (:func:`benchmark.stats.bootstrap_means`)."""
        if not len(self.runs) or not scenes:
            return {}
        kind = next(k for k, names in ACCURACY_METRICS.items() if metric in names)
        if metric not in self._cells:
            self._cells[metric] = _Cells(self.runs, self.queries, kind, metric)
        cells = self._cells[metric]
        arrays = {}
        for m in methods:
            mine = self.runs[self.runs["method"] == m]
            per_scene = [cells.array(m, s, set(mine[mine["scene"] == s]["seed"])) for s in scenes]
            if all(a.shape[0] for a in per_scene):
                arrays[m] = per_scene
        if not arrays:
            return {}
        reps = stats.bootstrap_means(arrays, seed=stats.stable_seed("paper-tables", metric, *scenes),
                                     resample_queries=cells.by_query)
        return {m: stats.percentile_interval(r) for m, r in reps.items()}

    def seeds_note(self) -> str:
        """The seeds the means are over, and how many (method, preset) cells lack some of them."""
        if not self.seeds:
            return "seeds none"
        text = "seeds " + ", ".join(str(s) for s in self.seeds)
        cells = self.summary[self.summary["scene"] != MEAN_SCENE]
        short = cells[cells["seeds"] < len(self.seeds)]
        if len(short):
            text += (f" ({len(short)} of {len(cells)} (method, preset) cells have fewer: each cell is the "
                     "mean of the seeds it has)")
        return text

    def get(self, method: str, scene: str, metric: str) -> float:
        if not len(self.summary):
            return math.nan
        rows = self.summary[(self.summary["method"] == method) & (self.summary["scene"] == scene)]
        return float(rows[f"{metric}_mean"].iloc[0]) if len(rows) else math.nan

    def mean(self, method: str, scenes: Sequence[str], metric: str) -> float:
        """Mean over ``scenes`` of the per-scene means (the paper's dataset averages); NaN if one is missing."""
        values = [self.get(method, s, metric) for s in scenes]
        return float(sum(values) / len(values)) if values and all(_finite(v) for v in values) else math.nan


def _comparison(title: str, dataset: str, methods: Sequence[str], metrics: tuple[str, str], ours: OurNumbers,
                paper_numbers: dict, note: str) -> list[str]:
    """One table: per scene the primary metric (paper / ours), then both metrics' dataset means."""
    primary, secondary = metrics
    display = {m: paper_numbers[m]["display"] for m in methods if m in paper_numbers}
    paper_scenes = [s for s in next(iter(paper_numbers[m]["results"].get(dataset, {})
                                         for m in methods if m in paper_numbers))
                    if s != "average"]
    scenes = [s for s in paper_scenes if any(primary in paper_numbers[m]["results"][dataset].get(s, {})
                                              for m in methods if m in paper_numbers)]
    presets = [SYNTHETIC_ANALOGUE.get((dataset, s)) for s in scenes]
    analogues = [p for p in presets if p]
    header = ["method"] + [f"{s}{'' if p else ' (no analogue)'} {primary}" for s, p in zip(scenes, presets)]
    header += [f"mean {primary}", f"mean {secondary}"]
    lines = [f"## {title}", "", note, "", "Cells: **paper / ours** (percent; ours: mean over seeds).", "",
             "| " + " | ".join(header) + " |", "|---|" + "---:|" * (len(header) - 1)]
    for m in methods:
        data = paper_numbers.get(m, {}).get("results", {}).get(dataset, {})
        cells = [_cell(data.get(s, {}).get(primary), ours.get(m, p, primary) if p else None)
                 for s, p in zip(scenes, presets)]
        avg = data.get("average", {})
        full = len(analogues) == len(scenes)  # our mean covers the paper's scenes only where all have analogues
        cells += [_cell(avg.get(primary), ours.mean(m, analogues, primary) if full else None),
                  _cell(avg.get(secondary), ours.mean(m, analogues, secondary) if full else None)]
        lines.append(f"| {display.get(m, m)} | " + " | ".join(cells) + " |")
    lines.append("")
    # orderings are compared on the scenes both sides have: the paper's per-scene numbers averaged over
    # the scenes whose analogue every method ran here
    shared = [(sc, p) for sc, p in zip(scenes, presets)
              if p and all(_finite(ours.get(m, p, primary)) for m in methods)]
    if not shared:
        return lines + ["_Rank agreement: not measurable (no scene with an analogue that every method ran)._", ""]
    where = ("the paper's scenes" if len(shared) == len(scenes)
             else f"the {len(shared)} scenes both have ({', '.join(sc for sc, _ in shared)})")
    for metric in dict.fromkeys((primary, secondary if secondary == "vIoU" else primary)):
        paper_on = {m: _mean([paper_numbers.get(m, {}).get("results", {}).get(dataset, {}).get(sc, {}).get(metric)
                              for sc, _ in shared]) for m in methods}
        ours_on = {m: ours.mean(m, [p for _, p in shared], metric) for m in methods}
        intervals = ours.interval(methods, [p for _, p in shared], metric)
        lines.append(f"{metric}, mean over {where}: " + _agreement(paper_on, ours_on, display, intervals))
        lines.append("")
        spreads = {m: ours.machine_spread(m, [p for _, p in shared], metric) for m in methods}
        lines.append(f"Ours, mean {metric} over {where} with its 95 % interval"
                     + (" (Δ: its spread between machine kinds)" if any(_finite(v) for v in spreads.values()) else "")
                     + ": " + "; ".join(f"{display.get(m, m)} {ours_on[m]:.2f} "
                                        f"{stats.interval_text(*intervals.get(m, (None, None)))}"
                                        + (f" (Δ {spreads[m]:.2f})" if _finite(spreads[m]) else "")
                                        for m in methods if _finite(ours_on[m])) + ".")
        lines.append("")
    return lines


def _states_runs(results_dir: Path, *, protocol: str, track: str, split: str, allow_dirty: bool) -> pd.DataFrame:
    """The ``4d-langsplat`` runs of ``bench4d ablate states`` (``<results>/ablations/states-k<K>/``) of one protocol,
    track and split on the committed scene versions, each with its recorded ``num_states``; runs from a dirty or
    changing checkout refused unless ``allow_dirty``."""
    from methods import registry

    def num_states(doc: dict) -> dict[str, Any]:
        options = registry.get(doc["method"]).recorded_options(doc.get("method_config"))
        return {"num_states": options.get("status.num_states")}

    folders = [root for root in sorted(results_dir.glob("ablations/states-k*")) if root.is_dir()]
    parts = [runs for runs in (load_runs(root, extra=num_states)[0] for root in folders) if len(runs)]
    if not parts:
        return pd.DataFrame()
    runs = comparable_runs(with_defaults(pd.concat(parts, ignore_index=True)))[0]
    runs = runs[(runs["method"] == "4d-langsplat") & runs["num_states"].notna() & (runs["protocol"] == protocol)
                & (runs["track"] == track) & (runs["split"] == split)]
    check_provenance(runs, allow_dirty, results_dir / "ablations")
    return runs.assign(num_states=runs["num_states"].astype(int))


def _states_table(runs: pd.DataFrame, paper_ablations: dict) -> list[str]:
    """Paper Table 5 beside ours: per K, the mean over seeds (each seed's mean over the scenes run) of Acc and
    vIoU with its 95 % t interval; the K whose Acc is best here and every K not separated from it."""
    paper = paper_ablations["states_chickchicken"]
    lines = ["## Number of states K of the status field (paper Table 5: chickchicken)", ""]
    if not len(runs):
        return lines + ["Ours: not run (`bench4d ablate states`).", ""]
    per_seed = runs.groupby(["num_states", "seed"])[["Acc", "vIoU"]].mean()  # mean over the scenes of a seed
    ours = {int(k): group.droplevel(0) for k, group in per_seed.groupby(level=0)}
    seeds = sorted(set(runs["seed"]))
    lines += [f"Ours: `results/ablations/states-k*/`, scenes {', '.join(sorted(set(runs['scene'])))}, seeds "
              f"{' '.join(map(str, seeds))}, protocol {runs['protocol'].iloc[0]}, track {runs['track'].iloc[0]}, "
              f"split {runs['split'].iloc[0]} (`bench4d ablate states`). Cells: Acc / vIoU; ours the mean over seeds "
              "± their sample std, with the 95 % t interval of the mean Acc.", "",
              "| K | paper | ours | ours Acc [95 % CI] | seeds |", "|---:|---:|---:|---:|---:|"]
    intervals = {str(k): stats.t_interval(v["Acc"].tolist()) for k, v in ours.items()}
    for k in sorted(set(paper) | set(ours)):
        p, o = paper.get(k, {}), ours.get(k)
        cell = "–" if o is None else " / ".join(_fmt(o[m].mean(), o[m].std(ddof=1) if len(o) > 1 else None)
                                               for m in ("Acc", "vIoU"))
        ci = "–" if o is None else f"{o['Acc'].mean():.2f} {stats.interval_text(*intervals[str(k)])}"
        lines.append(f"| {k} | {_cell(p.get('Acc'), p.get('vIoU'))} | {cell} | {ci} | "
                     f"{'–' if o is None else len(o)} |")
    paper_acc = {str(k): v["Acc"] for k, v in paper.items()}
    ours_acc = {str(k): float(v["Acc"].mean()) for k, v in ours.items()}
    tau, n, p = kendall_tau(paper_acc, ours_acc)
    best_p = max(paper_acc, key=paper_acc.get)
    groups = stats.tie_groups(ours_acc, intervals)
    best = sorted((k for k, g in groups.items() if g == 1), key=int)
    verdict = (f"ours: K = {best[0]}" if len(best) == 1 else
               f"ours: no single best, K = {', '.join(best)} tied (95 % intervals of the mean Acc overlap)")
    p_text = f"p = {p:.3f}" if math.isfinite(p) else "p not defined"
    lines += ["", f"_Acc over K: Kendall's tau = {tau:+.2f} ({p_text}) over {n} values of K (mean Acc); the paper's "
              f"best K = {best_p}; {verdict}._" if n >= 2 else
              f"_Acc over K: not measurable ({n} values of K with both numbers)._", ""]
    return lines


def _prompt_tables(paper_ablations: dict) -> list[str]:
    lines = []
    for key, title in (("visual_prompt_delta_sim", "Visual prompt of the captioner (paper Table 3)"),
                       ("text_prompt_delta_sim", "Text prompt of the captioner (paper Table 4)")):
        lines += [f"## {title}: Delta-sim", "",
                  "Not measured here: the rows are prompt variants of Qwen2-VL-7B on the real HyperNeRF videos, "
                  "and the oracle track captions from the generator's states (no prompt to vary). On the real "
                  "track `bench4d ablate delta-sim` measures them.", "",
                  "| variant | paper Delta-sim | ours |", "|---|---:|---:|"]
        lines += [f"| {variant} | {value:.2f} | – |" for variant, value in paper_ablations[key].items()]
        lines.append("")
    return lines


def speed_report_files(reports_dir: str | Path) -> list[Path]:
    """The query-speed reports (536x960, CUDA) under ``reports_dir`` that the speed table reads."""
    return sorted(Path(reports_dir).glob("ablations/query-speed-*-536x960-cuda.json"))


def _speed_table(ours: OurNumbers, reports_dir: Path, paper_numbers: dict) -> list[str]:
    from methods.registry import paper_reference

    QUERY_FPS_DEVICE = paper_reference().query_fps_device

    lines = ["## Query speed (paper: HyperNeRF, frames per second)", "",
             f"Paper: {QUERY_FPS_DEVICE}, 960x536. Ours (CPU): the results files' median per-frame query, mean over "
             "the HyperNeRF analogues with that query kind, at their generated size; ours (GPU): `bench4d ablate query-speed` on random "
             "Gaussians at 536x960 where a report exists.", "",
             "| method | query | paper FPS | ours, CPU | ours, GPU |", "|---|---|---:|---:|---:|"]
    presets = [p for (d, _), p in SYNTHETIC_ANALOGUE.items() if d == "hypernerf"]
    gpu = {}
    for path in speed_report_files(reports_dir):
        doc = read_json(path)
        gpu[int(doc.get("gaussians", 0))] = float(doc.get("fps", math.nan))
    gpu_cell = "; ".join(f"{fps:.1f} ({n // 1000}k Gaussians)" for n, fps in sorted(gpu.items())) or "–"
    for method in ("gaussian-grouping", "4d-langsplat"):
        for kind in ("agnostic", "sensitive"):
            paper = paper_numbers.get(method, {}).get("query_fps", {}).get(kind)
            measured = [v for v in (ours.get(method, p, f"fps_{kind}") for p in presets) if _finite(v)]
            cpu = sum(measured) / len(measured) if measured else math.nan
            if paper is None and not _finite(cpu):
                continue
            lines.append(f"| {paper_numbers.get(method, {}).get('display', method)} | {kind} | "
                         + (f"{paper:.2f}" if paper is not None else "–") + " | "
                         + (f"{cpu:.2f}" if _finite(cpu) else "–") + " | "
                         + (gpu_cell if method == "4d-langsplat" and kind == "agnostic" else "–") + " |")
    return lines + [""]


def render(results_dir: str | Path = "results", reports_dir: str | Path = "reports", *,
           protocol: str = DEFAULT_PROTOCOL, track: str = "oracle", split: Optional[str] = None,
           allow_dirty: bool = False) -> str:
    """The markdown of ``reports/paper-tables.md``. ``split``: the split of our runs (default: the paper's where
    results have it, else the first in :data:`benchmark.leaderboard.SPLIT_ORDER`); ``allow_dirty``: read runs
    from a dirty or changing checkout instead of refusing them."""
    from methods.registry import paper_reference

    paper = paper_reference()
    PAPER_ABLATIONS, PAPER_NUMBERS, PAPER_SOURCE = paper.ablations, paper.numbers, paper.source

    results_dir, reports_dir = Path(results_dir), Path(reports_dir)
    if not results_dir.is_dir():  # a mistyped folder would give tables of the paper's numbers alone
        raise InputError(results_dir, "results-dir", "no such folder")
    ours = OurNumbers(results_dir, protocol=protocol, track=track, split=split, allow_dirty=allow_dirty)
    lines = ["<!-- GENERATED by `bench4d paper-tables` from the results files; do not edit by hand. -->", "",
             "# The paper's tables beside ours", "",
             f"Paper: {PAPER_SOURCE}. Ours: `{results_dir.as_posix()}/`, protocol `{protocol}`, track `{track}`, "
             f"{ours.seeds_note()}; {ours.header_notes()}; scored frames: {SCORED_FRAMES_NOTE}. Every query counts (an "
             "unanswered one at 0; draft ground truth left out). The paper's scenes are real videos; ours are "
             "the synthetic presets modelled on them (same objects, state changes and camera kind, exact "
             "ground truth), so the comparison is of orderings, not of values.", "",
             "Release behaviours not copied (both protocols): " + "; ".join(RELEASE_DEFECTS_NOT_COPIED) + ".", ""]
    lines += _comparison("Time-agnostic queries, HyperNeRF (paper Table 2 and per-scene table)", "hypernerf",
                         AGNOSTIC_METHODS, ("mIoU", "mAcc"), ours, PAPER_NUMBERS,
                         "Ours: the six HyperNeRF-like presets.")
    lines += _comparison("Time-agnostic queries, Neu3D (paper Table 2 and per-scene table)", "neu3d",
                         AGNOSTIC_METHODS, ("mIoU", "mAcc"), ours, PAPER_NUMBERS,
                         "Ours: `cook-spinach` (a 21-camera rig like Neu3D's) stands for `cook_spinach`; the other "
                         "five Neu3D scenes have no analogue, so the Neu3D mean is the paper's alone.")
    lines += _comparison("Time-sensitive queries, HyperNeRF (paper Table 1)", "hypernerf", SENSITIVE_METHODS,
                         ("Acc", "vIoU"), ours, PAPER_NUMBERS, "Ours: the four presets with state changes.")
    lines += _states_table(_states_runs(results_dir, protocol=protocol, track=track, split=ours.split,
                                        allow_dirty=allow_dirty), PAPER_ABLATIONS)
    lines += _prompt_tables(PAPER_ABLATIONS)
    lines += _speed_table(ours, reports_dir, PAPER_NUMBERS)
    return "\n".join(line.rstrip() for line in lines).rstrip() + "\n"
