"""What the stress suite writes: per family a chart of each metric against strength (one line per
method, its seed band shaded), the breaking-point table, a failure gallery per family, and the README
that ties them together (``reports/stability/``).

A gallery shows, at the family's strongest strength run, the whole-object queries and frames where
the methods did worst: the frame, the ground truth, and each method's mask (with its IoU), each such row
below the same frame and query on the clean scene (the clean runs of the same seed); last, the timeline of
the first time-sensitive query at the strongest strength: its ground truth and each method's decision per
frame.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from benchmark.core.atomic import read_json, write_text
from benchmark.synthetic.perturb import FAMILIES
from ._report import markdown_table, number_cell
from .stress import (METRICS, SCORES_FILE, Score, SuiteConfig, breaking_point, held_at, mean_by_strength,
                     TRACK, read_scores_table, seed_interval, strength_label, write_scores_table)

GALLERY_FRAMES = 3
"""(query, frame) pairs a gallery shows."""
DPI = 150
"""Resolution of the charts (palette images, :func:`benchmark.plots.write_png`: small enough to commit)."""
GALLERY_DPI = 80
"""A gallery's resolution: a 1.9 in tile is then 152 px, above the 96 px of a suite scene, and a gallery is
about half its size at :data:`DPI` (about 130 KB against 270 KB, one per family)."""


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save_png(fig, path: Path, dpi: int = DPI) -> Path:
    from ..plots import write_png

    write_png(fig, path, dpi=dpi)
    _pyplot().close(fig)
    return path


def _seeds_text(seeds: Sequence[int]) -> str:
    seeds = sorted(set(seeds))
    return f"seed {seeds[0]}" if len(seeds) == 1 else "seeds " + ", ".join(map(str, seeds))


def family_chart(scores: Sequence[Score], fam: str, methods: Sequence[str], path: Path) -> Optional[Path]:
    """One panel per metric: the seeds' mean against strength per method (a line), the seeds' range
    shaded, and half of the method's clean mean dotted in its colour (the method breaks where its seeds'
    interval lies below half of its clean interval: :func:`~benchmark.studies.stress.breaking_point`); the
    legend says so."""
    import textwrap

    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    plt = _pyplot()
    fig, axes = plt.subplots(1, len(METRICS), figsize=(4.0 * len(METRICS), 3.6), squeeze=False, layout="constrained")
    drawn = False
    seeds_seen: set[int] = set()
    unit = textwrap.fill(FAMILIES[fam].unit, width=42)
    for ax, metric in zip(axes[0], METRICS):
        for k, method in enumerate(methods):
            values = mean_by_strength(scores, fam, method, metric)
            if not values:
                continue
            seeds_seen |= {s.seed for s in scores if s.family == fam and s.method == method
                           and s.metrics.get(metric) is not None}
            x = np.array(list(values))
            color = f"C{k % 10}"  # one colour per method in every panel (a panel may lack some methods)
            ax.plot(x, [np.mean(v) for v in values.values()], marker="o", ms=4, label=method, color=color)
            ax.fill_between(x, [min(v) for v in values.values()], [max(v) for v in values.values()], alpha=0.2,
                            color=color)
            if values.get(0.0):
                ax.axhline(0.5 * float(np.mean(values[0.0])), color=color, linestyle=":", linewidth=1.2,
                           label=f"half of {method}'s clean score")
            drawn = True
        ax.set_title(metric, fontsize=11)
        ax.tick_params(labelsize=9)
        ax.set_ylim(0, 100)
        ax.set_xlabel(unit, fontsize=9)
        ax.grid(True, alpha=0.3)
    if not drawn:
        plt.close(fig)
        return None
    axes[0][0].set_ylabel("score (%)", fontsize=9)
    shown = {}
    for ax in axes[0]:  # every method once, in the order given, whichever panel has it
        for handle, label in zip(*ax.get_legend_handles_labels()):
            if not label.startswith("half of "):
                shown.setdefault(label, handle)
    handles = list(shown.values()) + [
        Line2D([], [], color="0.3", marker="o", ms=4, label="line: mean over the seeds"),
        Patch(facecolor="0.3", alpha=0.2, label=f"shaded: lowest to highest seed ({_seeds_text(seeds_seen)})"),
        Line2D([], [], color="0.3", linestyle=":", label="dotted, the method's colour: half its clean score\n"
                                                          "(it breaks where its seed interval falls below)")]
    fig.legend(handles=handles, fontsize=9, loc="outside right center")  # beside, not over, the lines
    fig.suptitle(fam, fontsize=12)
    return _save_png(fig, path)


def _unprobed_below(fam: str, values: dict, point: float) -> bool:
    """Whether a strength of ``fam`` between the strongest run that held and the break ``point`` was not run
    (a screen): the method may break there already, so the break reads "by", not "from"."""
    held = max((k for k in values if k < point), default=0.0)
    return any(held < k < point and k not in values for k in FAMILIES[fam].strengths)


def breaking_rows(scores: Sequence[Score], families: Sequence[str], methods: Sequence[str],
                  metrics: Sequence[str] = ("mIoU", "Acc")) -> tuple[list[str], list[list[str]]]:
    """The breaking-point table: per family, per method and metric, the strength at which the seeds'
    interval lies below half the clean interval (:func:`~benchmark.studies.stress.breaking_point`; ``≤ s``
    when weaker strengths were not run, ``> s`` when it holds up to the strongest ``s`` run, ``–`` when there
    is no clean score or no run past it)."""
    header = ["family", "unit"] + [f"{m} {metric}" for m in methods for metric in metrics]
    rows = []
    for fam in families:
        row = [fam, FAMILIES[fam].unit]
        for method in methods:
            for metric in metrics:
                values = mean_by_strength(scores, fam, method, metric)
                point = breaking_point(values)
                strongest = max((s for s in values if s > 0), default=None)
                if point is not None:
                    skipped = _unprobed_below(fam, values, point)
                    row.append(("≤ " if skipped else "") + strength_label(point))
                elif strongest is None or not values.get(0.0) or float(np.mean(values[0.0])) == 0:
                    row.append("–")
                else:
                    row.append(f"> {strength_label(strongest)}")
        rows.append(row)
    return header, rows


def _overlay(image: np.ndarray, mask: np.ndarray, color=(1.0, 0.2, 0.2)) -> np.ndarray:
    out = np.asarray(image, dtype=np.float32)[..., :3].copy()
    out[mask] = 0.45 * out[mask] + 0.55 * np.asarray(color, dtype=np.float32)
    return out


def _frame_rows(doc: dict) -> list[dict]:
    frames = doc["scores"]["frames"]
    return [dict(zip(frames["columns"], r)) for r in frames["rows"]]


def _worst_pairs(docs: dict[str, dict], aset) -> list[tuple[str, str]]:
    """The (query, frame) pairs of whole-object queries with ground truth where the methods' mean IoU is
    lowest."""
    wholes = {q.text for q in aset.queries if q.kind == "agnostic" and q.level == "whole"}
    ious: dict[tuple[str, str], list[float]] = {}
    for doc in docs.values():
        for row in _frame_rows(doc):
            if row["query"] in wholes and row["gt_pixels"]:
                ious.setdefault((row["query"], row["frame"]), []).append(float(row["iou"]))
    return sorted(ious, key=lambda k: (np.mean(ious[k]), k))[:GALLERY_FRAMES]


def _timeline_panel(ax, docs: dict[str, dict]) -> None:
    """Label and each method's decision per evaluated frame of the first time-sensitive query."""
    rows = {m: [r for r in _frame_rows(doc) if r["kind"] == "sensitive"] for m, doc in docs.items()}
    first = next((r[0]["query"] for r in rows.values() if r), None)
    ax.set_axis_off()
    if first is None:
        return
    # a method that answers no time query keeps its row, blank and named so (not read as "never decided")
    names = ["truth"] + [m if rows[m] else f"{m} (no time answers)" for m in docs]
    labelled = next(m for m in docs if rows[m])
    truth = sorted((r for r in rows[labelled] if r["query"] == first), key=lambda r: r["time_index"])
    grid = [[float(bool(r["label"])) for r in truth]]
    for method in docs:
        chosen = sorted((r for r in rows[method] if r["query"] == first), key=lambda r: r["time_index"])
        grid.append([np.nan if r["decision"] is None else float(bool(r["decision"])) for r in chosen])
    width = max(len(g) for g in grid)
    grid = [g + [np.nan] * (width - len(g)) for g in grid]
    ax.set_axis_on()
    ax.imshow(np.array(grid), aspect="auto", cmap="Greens", vmin=0, vmax=1, interpolation="nearest")
    ax.set_yticks(range(len(names)), names, fontsize=8)
    ax.set_xticks([])
    ax.set_title(f"'{first}' over the evaluated frames (dark: state holds / decided)", fontsize=9)


def _gallery_rows(runs: dict[str, Path], scene_root: Path, pairs: Sequence[tuple[str, str]], label: str) -> list:
    """Per (query, frame) of ``pairs``: the panels (picture, caption) of one row, the frame of ``scene_root``,
    its truth and each method's mask of ``runs``; None for a pair whose frame or query the scene lacks."""
    from annotations.format import load_annotations
    from benchmark.loaders import load_scene
    from benchmark.predictions import read_predictions

    docs = {m: read_json(p) for m, p in runs.items()}
    aset = load_annotations(scene_root / "annotations.json")
    predictions = {m: read_predictions((p.parent / docs[m]["predictions"]).parent) for m, p in runs.items()}
    scene = load_scene(scene_root)
    query_id = {q.text: q.id for q in aset.queries}
    frame_id = {f.name: f.id for f in aset.frames}
    rows: list = []
    for text, frame in pairs:
        if text not in query_id or frame not in frame_id:
            rows.append(None)
            continue
        image = scene.frame(frame).image()
        truth = aset.get_mask(query_id[text], frame_id[frame])
        truth = np.zeros(image.shape[:2], bool) if truth is None else truth.astype(bool)
        panels = [(image[..., :3], f"{label}: frame {frame}"), (_overlay(image, truth, (0.2, 0.9, 0.2)), f"truth: {text}")]
        for method, preds in predictions.items():
            found = preds.find(text)
            mask = found.mask(frame, truth.shape) if found is not None else np.zeros_like(truth)
            iou = next((r["iou"] for r in _frame_rows(docs[method]) if r["query"] == text and r["frame"] == frame), None)
            panels.append((_overlay(image, mask.astype(bool)),
                           f"{method}\nIoU {number_cell(100 * iou if iou is not None else None, 0)}"))
        rows.append(panels)
    return rows


def gallery(runs: dict[str, Path], scene_root: Path, title: str, path: Path, *,
            clean_runs: Optional[dict[str, Path]] = None, clean_root: Optional[Path] = None,
            label: str = "perturbed") -> Optional[Path]:
    """The failure gallery of one (family, strength, seed): ``runs`` maps method -> results file. With
    ``clean_runs`` (method -> results file of the clean run, same seed) and ``clean_root`` (the clean scene),
    each (query, frame) row of the perturbed runs (``label``) has the clean row above it: the same frame and
    query, answered by the same methods without the perturbation."""
    if not runs:
        return None
    plt = _pyplot()
    docs = {m: read_json(p) for m, p in runs.items()}
    from annotations.format import load_annotations

    pairs = _worst_pairs(docs, load_annotations(scene_root / "annotations.json"))
    if not pairs:
        return None
    perturbed = _gallery_rows(runs, scene_root, pairs, label)
    clean = (_gallery_rows({m: p for m, p in clean_runs.items() if m in runs}, clean_root, pairs, "clean")
             if clean_runs and clean_root is not None else [None] * len(pairs))
    rows: list = []
    for before, after in zip(clean, perturbed):
        if clean_runs and clean_root is not None:
            rows.append(before if before is not None else "the clean scene has no such frame or query")
        rows.append(after)
    columns = 2 + len(runs)
    fig, axes = plt.subplots(len(rows) + 1, columns, figsize=(1.9 * columns, 2.0 * len(rows) + 1.8), squeeze=False,
                             layout="constrained", height_ratios=[1.0] * len(rows) + [0.9])
    for row, panels in enumerate(rows):
        if isinstance(panels, str):
            axes[row][0].text(0, 0.5, panels, fontsize=8, transform=axes[row][0].transAxes)
            panels = []
        for ax, (picture, caption) in zip(axes[row], panels or []):
            ax.imshow(np.clip(picture, 0, 1), interpolation="nearest")
            ax.set_title(caption, fontsize=8)
        for ax in axes[row]:
            ax.set_axis_off()
    for ax in axes[-1][1:]:
        ax.set_axis_off()
    grid = axes[-1][0].get_gridspec()
    axes[-1][0].remove()
    for ax in axes[-1][1:]:
        ax.remove()
    _timeline_panel(fig.add_subplot(grid[-1, :]), docs)
    import textwrap

    fig.suptitle(textwrap.fill(title, width=max(40, int(columns * 1.9 * 10))), fontsize=10)  # no wider than the panels
    return _save_png(fig, path, GALLERY_DPI)


def charts_from_csv(csv: Path, out_dir: Path) -> list[Path]:
    """Redraw every family's chart of a written ``scores.csv`` into ``<out_dir>/charts/``."""
    scores = read_scores_table(csv)
    methods = list(dict.fromkeys(s.method for s in scores))
    families = [f for f in FAMILIES if any(s.family == f and s.strength > 0 for s in scores)]
    made = [family_chart(scores, fam, methods, Path(out_dir) / "charts" / f"{fam}.png") for fam in families]
    return [p for p in made if p is not None]


def family_gallery(config: SuiteConfig, scores: Sequence[Score], fam: str, path: Path) -> Optional[Path]:
    """The gallery of ``fam`` at its strongest strength run (first seed)."""
    from .stress import scene_folder

    strengths = sorted({s.strength for s in scores if s.family == fam and s.strength > 0})
    if not strengths:
        return None
    strongest, seed = strengths[-1], min(config.seeds)
    shown = [s for s in scores if s.family == fam and s.strength == strongest and s.seed == seed]
    runs = {s.method: s.path for s in shown if s.path is not None}
    if len(runs) < len(shown) and path.is_file():
        return None  # drawn before with runs whose results files are not here: kept, not redrawn without them
    clean_runs = {s.method: s.path for s in scores
                  if s.family == fam and s.strength == 0 and s.seed == seed and s.path is not None}
    label = f"at {strength_label(strongest)}"
    title = (f"{fam} at {strength_label(strongest)} ({FAMILIES[fam].unit}), seed {seed}: each row of the "
             f"strongest strength below its clean row (the same frame and query without the perturbation)"
             if clean_runs else f"{fam} at {strength_label(strongest)} ({FAMILIES[fam].unit}), seed {seed}")
    return gallery(runs, scene_folder(config, fam, strongest, seed), title, path, clean_runs=clean_runs,
                   clean_root=scene_folder(config, fam, 0.0, seed) if clean_runs else None, label=label)


def clean_interval(scores: Sequence[Score], method: str, metric: str = "mIoU") -> Optional[tuple[float, float]]:
    """The 95 % interval over seeds of ``method``'s clean ``metric`` (:func:`~benchmark.studies.stress.seed_interval`);
    None where it has no clean value."""
    values = {s.seed: s.metrics.get(metric) for s in scores if s.method == method and s.strength == 0}
    values = [float(v) for v in values.values() if v is not None]
    return seed_interval(values) if values else None


def floor_clearance(scores: Sequence[Score], methods: Sequence[str], metric: str = "mIoU") -> dict[str, Optional[bool]]:
    """Per fitted (non-floor) method of ``methods``: whether its clean interval of ``metric`` lies wholly above
    the clean interval of every floor among ``methods`` (:attr:`methods.registry.MethodSpec.floor`) -- the
    base scene asks a question the floors cannot answer for it; None where a floor or the method has no
    clean value. The suite's size is the smallest where every fitted method clears."""
    from methods import registry

    floors = [m for m in methods if registry.get(m).floor]
    floor_tops = [clean_interval(scores, f, metric) for f in floors]
    out: dict[str, Optional[bool]] = {}
    for method in methods:
        if method in floors:
            continue
        own = clean_interval(scores, method, metric)
        out[method] = None if own is None or not floors or None in floor_tops else \
            all(own[0] > top[1] for top in floor_tops)
    return out


def floor_at_strongest(scores: Sequence[Score], families: Sequence[str], methods: Sequence[str],
                       metric: str = "mIoU") -> str:
    """Per family, at its strongest strength run: the fitted methods whose interval over seeds of ``metric`` lies
    wholly below a floor's (the floor answers better) and those whose interval overlaps a floor's (a tie), as a
    table of the families where any fitted method no longer clears every floor; an empty string where none."""
    from methods import registry

    floors = [m for m in methods if registry.get(m).floor]
    fitted = [m for m in methods if m not in floors]
    rows = []
    for fam in families:
        top = max((s.strength for s in scores if s.family == fam), default=0.0)
        if top <= 0:
            continue

        spans = {m: seed_interval(v) for m in methods if (v := mean_by_strength(scores, fam, m, metric).get(top))}
        floor_spans = {f: spans[f] for f in floors if f in spans}
        if not floor_spans:
            continue
        below, tied = [], []
        for method in fitted:
            own = spans.get(method)
            if own is None:
                continue
            if any(own[1] < span[0] for span in floor_spans.values()):
                below.append(f"{method} [{own[0]:.1f}, {own[1]:.1f}]")
            elif any(own[0] <= span[1] for span in floor_spans.values()):
                tied.append(f"{method} [{own[0]:.1f}, {own[1]:.1f}]")
        if below or tied:
            shown = ", ".join(f"{f} [{a:.1f}, {b:.1f}]" for f, (a, b) in floor_spans.items())
            rows.append([fam, strength_label(top), shown, ", ".join(below) or "–", ", ".join(tied) or "–"])
    if not rows:
        return ""
    return markdown_table(["family", "strength", "floors", "fitted methods below a floor",
                           "fitted methods tied with a floor"], rows)


def _clean_table(scores: Sequence[Score], methods: Sequence[str]) -> str:
    rows = []
    clears = floor_clearance(scores, methods)
    for method in methods:
        clean = [s for s in scores if s.method == method and s.strength == 0]
        by_seed = {s.seed: s for s in clean}
        cells = [number_cell(np.mean([s.metrics[m] for s in by_seed.values() if s.metrics.get(m) is not None])
                             if any(s.metrics.get(m) is not None for s in by_seed.values()) else None, 1)
                 for m in METRICS]
        interval = clean_interval(scores, method)
        span = "–" if interval is None else f"[{interval[0]:.1f}, {interval[1]:.1f}]"
        verdict = {True: "yes", False: "no", None: "–"}[clears.get(method)] if method in clears else "floor"
        rows.append([method, str(len(by_seed))] + cells + [span, verdict])
    return markdown_table(["method", "seeds", *METRICS, "mIoU 95 % interval", "above every floor"], rows)


def _run_time_table(scores: Sequence[Score], methods: Sequence[str]) -> str:
    """Per method: its distinct runs (a clean run shared by families counts once) and the sum and median of
    their own wall times, stages reused from the cache not included: the suite's cost on the machine that
    ran it, whatever invocations it took."""
    rows, every = [], []
    for method in methods:
        seconds = list({s.run: s.wall_seconds for s in scores if s.method == method}.values())
        if seconds:
            rows.append([method, str(len(seconds)), f"{sum(seconds) / 60:.1f}", f"{float(np.median(seconds)):.0f}"])
            every += seconds
    if len(rows) > 1:
        rows.append([f"all ({sum(every) / 3600:.1f} h)", str(len(every)), f"{sum(every) / 60:.1f}",
                     f"{float(np.median(every)):.0f}"])
    return markdown_table(["method", "runs", "run time (min)", "median run (s)"], rows)


def reported_families(config: SuiteConfig, scores: Sequence[Score]) -> list[str]:
    """The suite's families with a perturbed run among ``scores``: those the tables and charts show."""
    families = [f for f in config.families if any(s.family == f and s.strength > 0 for s in scores)]
    if not families and all(config.strengths_of(f) == (0.0,) for f in config.families):
        families = list(config.families)[:1]  # a clean-only suite (--strengths 0): its clean runs are the suite
    return families


def coverage(config: SuiteConfig, scores: Sequence[Score]) -> str:
    """What the scores cover, counted from them: the distinct runs present against those the suite names
    (its methods x families x strengths x seeds, where the family applies to the method; a clean run shared
    by the families counts once), and per method the (family, seed) cells missing at some strength."""
    from .stress import CLEAN, RunKey, skipped, unchanged_families

    families = reported_families(config, scores)
    present = {(s.family, s.strength, s.method, s.seed) for s in scores}
    expected, missing = set(), {}
    for fam in families:
        for strength in config.strengths_of(fam):
            for method in config.methods:
                for seed in config.seeds:
                    if skipped(config, RunKey(fam, strength, method, seed)):
                        continue
                    expected.add((CLEAN if strength == 0 else fam, strength, method, seed))
                    if (fam, strength, method, seed) not in present:
                        missing.setdefault(method, {}).setdefault((fam, seed), []).append(strength)
    done = {(CLEAN if s.strength == 0 else s.family, s.strength, s.method, s.seed) for s in scores} & expected
    methods = f"{len(config.methods)} method" + ("s" if len(config.methods) != 1 else "")
    fams = f"{len(families)} " + ("family" if len(families) == 1 else "families")
    head = (f"{len(done)} distinct runs of the {len(expected)} the suite names ({methods}, {fams} at their "
            f"strengths, {_seeds_text(config.seeds)}; a clean run shared by the families counts once)")
    # a family asked for with no perturbed run is in no table below: named here, so a partial suite says so
    unchanged = unchanged_families(config)
    unrun = [f for f in config.families
             if f not in families and f not in unchanged and config.strengths_of(f) != (0.0,)]
    if unchanged:
        head += (f". Families that change nothing on `{config.preset}`, not run ({len(unchanged)}): "
                 + "; ".join(f"{f} ({why})" for f, why in unchanged.items()))
    if unrun:
        head += (f". Families asked for with no perturbed run yet, in no table below ({len(unrun)}): "
                 + ", ".join(unrun))
    # families where every method and seed lacks the same strengths between the clean end and the strongest (a
    # screen, or a screen filled in part): one line per family, not a gap per method and seed
    screened, partial = [], []
    for fam in families:
        between = sorted(v for v in config.strengths_of(fam) if 0 < v < max(config.strengths_of(fam)))
        cells = [(method, seed) for method in config.methods for seed in config.seeds
                 if not skipped(config, RunKey(fam, max(config.strengths_of(fam)), method, seed))]
        gaps = {tuple(sorted(missing.get(m, {}).get((fam, seed), []))) for m, seed in cells}
        if len(gaps) != 1:
            continue
        gap = list(gaps.pop())
        if not gap or not set(gap) <= set(between):
            continue
        if gap == between:
            screened.append(fam)
        else:
            partial.append(f"{fam} ({', '.join(strength_label(v) for v in gap)} not run)")
        for method, seed in cells:
            del missing[method][fam, seed]
    missing = {m: gaps for m, gaps in missing.items() if gaps}
    if screened:
        head += (f". Screened at the clean end and the strongest strength only, every method and seed (the "
                 f"strengths between not run) ({len(screened)}): " + ", ".join(screened))
    if partial:
        head += (f". Run at some of the strengths between, every method and seed ({len(partial)}): "
                 + ", ".join(partial))
    if not missing:
        if unrun or screened or partial or unchanged:
            return head + ".\n"
        return head + ": complete, every method on every family at every strength with every seed.\n"
    lines = [head + f". Not run ({len(expected) - len(done)}):", ""]
    for method in config.methods:
        gaps = missing.get(method)
        if not gaps:
            continue
        phrases: dict[str, list[str]] = {}  # one phrase per gap, the families that share it
        for (fam, seed), strengths in sorted(gaps.items()):
            perturbed = [v for v in config.strengths_of(fam) if v > 0]
            if len(strengths) == len(config.strengths_of(fam)):
                where = "at any strength, clean included"
            elif sorted(strengths) == perturbed:
                where = "at any strength past clean"
            else:
                where = "at " + ", ".join(strength_label(v) for v in sorted(strengths))
            phrases.setdefault(f"seed {seed} {where}", []).append(fam)
        lines.append(f"* `{method}`: " + "; ".join(f"{phrase} on {', '.join(fams)}"
                                                     for phrase, fams in phrases.items()) + ".")
    return "\n".join(lines) + "\n"


def machine_line(scores: Sequence[Score]) -> str:
    """The kinds of machine the runs ran on, with their run counts, counted from the scores; where there are
    several, a warning that a cell's seeds may come from different kinds (a re-fit on another CPU moves a
    cell beyond its seed noise: ``reports/history.md``). A score kept without a recorded machine counts as
    unrecorded."""
    counts: dict[str, int] = {}
    for s in {s.run: s for s in scores}.values():  # a clean run shared by the families counts once
        kind = s.machine or "not recorded"
        counts[kind] = counts.get(kind, 0) + 1
    if not counts:
        return "Machine: no runs.\n"
    kinds = "; ".join(f"{kind} ({n} run{'s' if n != 1 else ''})" for kind, n in sorted(counts.items()))
    if len(counts) == 1:
        return f"Machine kind of every run: {kinds}.\n"
    return (f"Machine kinds: {kinds}. The runs mix kinds of machine: a cell's seeds may come from different "
            f"kinds, and a re-fit on another kind moves a cell beyond its seed noise.\n")


ACC_FLOOR = 50.0
"""Acc of a method that does not tell states apart (every frame one answer on a balanced query): below or at
it, a method's Acc says nothing about a family and is left out of the findings."""


def _seed_note(scores: Sequence[Score], fam: str, method: str, metric: str) -> str:
    """``"; only seed 0 at 0.5, 1"``-style note where the perturbed strengths of ``fam`` were not run with every
    seed of the clean runs (their means are then of fewer seeds), else empty."""
    clean = {s.seed for s in scores if s.family == fam and s.method == method and s.strength == 0
             and s.metrics.get(metric) is not None}
    by_strength: dict[float, set[int]] = {}
    for s in scores:
        if s.family == fam and s.method == method and s.strength > 0 and s.metrics.get(metric) is not None:
            by_strength.setdefault(s.strength, set()).add(s.seed)
    fewer = {frozenset(v) for v in by_strength.values() if v != clean}
    if not fewer:
        return ""
    return "; " + "; ".join(f"only {_seeds_text(sorted(v))} at " + ", ".join(
        strength_label(k) for k, seen in sorted(by_strength.items()) if seen == v) for v in sorted(fewer, key=sorted))


def _interval_text(seeds: Sequence[float]) -> str:
    """`` [lo, hi]``: the 95 % interval over seeds a breaking point reads (:func:`seed_interval`); empty for one
    seed, whose interval is its value."""
    if len(seeds) < 2:
        return ""
    low, high = seed_interval(seeds)
    return f" [{low:.1f}, {high:.1f}]"


def _family_parts(scores, fam: str, methods: Sequence[str], metric: str) -> tuple[list[str], list[tuple]]:
    """Per method: the clean -> strongest sentence of ``metric`` and its (break strength, kept share, method)."""
    parts, order = [], []
    for method in methods:
        values = mean_by_strength(scores, fam, method, metric)
        strongest = max((s for s in values if s > 0), default=None)
        if strongest is None or 0.0 not in values:
            continue
        clean, last = float(np.mean(values[0.0])), float(np.mean(values[strongest]))
        if metric == "Acc" and clean <= ACC_FLOOR:
            continue
        point = breaking_point(values)
        skipped = point is not None and _unprobed_below(fam, values, point)
        fate = ("never below half" if point is None else
                f"below half by {strength_label(point)}; weaker strengths not run" if skipped else
                f"below half from {strength_label(point)}")
        parts.append(f"{method} {clean:.1f}{_interval_text(values[0.0])} -> {last:.1f}"
                     f"{_interval_text(values[strongest])} at {strength_label(strongest)} ({fate}"
                     f"{_seed_note(scores, fam, method, metric)})")
        order.append((point if point is not None else np.inf, last / max(clean, 1e-9), method, skipped))
    return parts, order


def findings(scores: Sequence[Score], families: Sequence[str], methods: Sequence[str]) -> str:
    """Per family, from the measurements: each method's clean and strongest mean mIoU (and Acc, for the
    methods whose clean Acc is above :data:`ACC_FLOOR`), where it falls below half its clean score, and
    which methods break first on either (all of those breaking at the earliest strength: a tie is named)."""
    lines = []
    for fam in families:
        space, space_order = _family_parts(scores, fam, methods, "mIoU")
        time_, time_order = _family_parts(scores, fam, methods, "Acc")
        if not space and not time_:
            continue
        breaks = sorted([(o[0], o[1], o[2], "mIoU", o[3]) for o in space_order]
                        + [(o[0], o[1], o[2], "Acc", o[3]) for o in time_order])
        found = [b for b in breaks if np.isfinite(b[0])]
        if any(b[4] for b in found):
            # a screen: a break "by s" may be at any weaker strength, so no order among the breaks is known
            broken = sorted(set(b[2] for b in found))
            lead = (f"{' and '.join(broken)} {'breaks' if len(broken) == 1 else 'break'} by the strongest "
                    f"strength run, {strength_label(max(b[0] for b in found))} "
                    f"(weaker strengths not run: which breaks first is not measured)")
        elif found:
            # every method breaking at the earliest strength leads: no secondary sort picks one of them
            at = found[0][0]
            first = [b for b in found if b[0] == at]
            names = sorted(set(b[2] for b in first))
            metrics = ", ".join(dict.fromkeys(b[3] for b in first))
            # "first" only where every other method held there outside the noise, its interval wholly above half
            # its clean one; an interval across that line is neither a break nor a hold
            others = [(b[2], mean_by_strength(scores, fam, b[2], b[3])) for b in breaks if b[2] not in names]
            undecided = sorted({m for m, values in others if values.get(at) and not held_at(values, at)})
            if undecided:
                lead = (f"{' and '.join(names)} {'breaks' if len(names) == 1 else 'break'} at {strength_label(at)} "
                        f"({metrics}), the weakest strength of any break; whether {' and '.join(undecided)} "
                        f"{'does' if len(undecided) == 1 else 'do'} too is inside the seed noise there (an interval "
                        f"across half the clean one), so no method is said to break first")
            else:
                lead = (f"{names[0]} breaks first ({metrics})" if len(names) == 1 else
                        f"{' and '.join(names)} break first, at the same strength {strength_label(at)} "
                        f"({metrics}): a tie")
        else:
            lead = "no method breaks outside the seed noise"
        text = f"* **{fam}** ({FAMILIES[fam].unit}): {lead}."
        if space:
            text += " mIoU: " + "; ".join(space) + "."
        if time_:
            text += " Acc: " + "; ".join(time_) + "."
        lines.append(text)
    return "\n".join(lines) + "\n"


ALWAYS_KEPT = ("caption-swap", "state-ramp", "caption-lag")
"""Families kept whatever the measurements: wrong-state captions, gradual changes and late captions are what
the status field is argued for, so they compare it with the directly time-varying field under stress."""


def _drops(scores: Sequence[Score], fam: str, method: str, metric: str, top: float) -> dict[int, float]:
    """Seed -> clean minus strength-``top`` ``metric`` of ``method`` on ``fam`` (seeds with both)."""
    by = {(s.strength, s.seed): s.metrics.get(metric) for s in scores if s.family == fam and s.method == method}
    return {seed: float(by[0.0, seed]) - float(v) for (k, seed), v in by.items()
            if k == top and v is not None and by.get((0.0, seed)) is not None}


def separated_pairs(scores: Sequence[Score], fam: str, methods: Sequence[str],
                    metric: str) -> list[tuple[str, str, float]]:
    """Pairs of ``methods`` whose drops from the clean scene to the family's strongest strength differ outside the
    seed noise: the 95 % t interval (:func:`benchmark.stats.t_interval`) of their paired difference over seeds
    (same seed, so the same scene) excludes 0 and the mean difference is at least :data:`MIN_SEPARATION`.
    ``(a, b, d)``: ``a`` drops ``d`` points more than ``b``. A t
    interval, not the bootstrap of the breaking points: with two or three seeds a bootstrap interval is about
    their range, and the same sign on three seeds happens by chance one time in four."""
    from benchmark.stats import t_interval

    # one strength for every method: the family's strongest run (a method without it is not compared)
    top = max((s.strength for s in scores if s.family == fam), default=0.0)
    if top <= 0:
        return []
    drops = {m: _drops(scores, fam, m, metric, top) for m in methods}
    out = []
    for i, a in enumerate(methods):
        for b in methods[i + 1:]:
            common = sorted(set(drops[a]) & set(drops[b]))
            diffs = [drops[a][k] - drops[b][k] for k in common]
            lo, hi = t_interval(diffs)
            if lo > 0 and np.mean(diffs) >= MIN_SEPARATION:
                out.append((a, b, float(np.mean(diffs))))
            elif hi < 0 and -np.mean(diffs) >= MIN_SEPARATION:
                out.append((b, a, -float(np.mean(diffs))))
    return out


SHOWN_PAIRS = 3
"""Separated pairs a family's reason names (the largest differences); the rest are counted."""
MIN_SEPARATION = 5.0
"""Points (of a 0-100 score) by which two methods' drops must differ, beyond the seed noise, to separate them:
a difference can be outside the noise and still too small to tell a reader anything."""


def _pair_phrase(scores: Sequence[Score], fam: str, metric: str, a: str, b: str, d: float) -> str:
    """``a`` drops ``d`` more than ``b``, in words; where both gain on the family (a rig of cameras helps),
    "``b`` gains ``d`` more than ``a``"."""
    top = max((s.strength for s in scores if s.family == fam), default=0.0)
    mean_drop = {m: np.mean(list(_drops(scores, fam, m, metric, top).values()) or [0.0]) for m in (a, b)}
    if mean_drop[a] < 0 and mean_drop[b] < 0:
        return f"{b} gains {d:.1f} more than {a}"
    return f"{a} drops {d:.1f} more than {b}"


def _changes_nothing(scores: Sequence[Score], fam: str) -> bool:
    """Whether ``fam`` has perturbed runs and each one's scores equal those of the clean run of its method and
    seed: the perturbation left the base as it was (a mask growing only into uncovered pixels, where every
    pixel is covered)."""
    clean = {(s.method, s.seed): s.metrics for s in scores if s.family == fam and s.strength == 0}
    perturbed = [s for s in scores if s.family == fam and s.strength > 0]
    return bool(perturbed) and all(clean.get((s.method, s.seed)) == s.metrics for s in perturbed)


def family_verdicts(scores: Sequence[Score], families: Sequence[str], methods: Sequence[str]) -> list[dict]:
    """Per family: the fitted methods that break on it (mIoU, or Acc where the clean Acc is above
    :data:`ACC_FLOOR`), the pairs of fitted methods it separates, and whether the suite keeps it, with the
    reason. The floors are left out: a family that moves only a floor says nothing of the methods."""
    from methods import registry

    methods = [m for m in methods if not registry.get(m).floor]
    out = []
    for fam in families:
        breaks, separates, said = [], [], []
        for metric in ("mIoU", "Acc"):
            scored = []
            for method in methods:
                values = mean_by_strength(scores, fam, method, metric)
                if not values.get(0.0) or not any(k > 0 for k in values):
                    continue
                if metric == "Acc" and float(np.mean(values[0.0])) <= ACC_FLOOR:
                    continue
                scored.append(method)
                if breaking_point(values) is not None:
                    breaks.append(f"{method} ({metric})")
            pairs = sorted(separated_pairs(scores, fam, scored, metric), key=lambda p: -p[2])
            separates += [{"metric": metric, "more": a, "less": b, "difference": d} for a, b, d in pairs]
            compared = len(scored) * (len(scored) - 1) // 2
            if pairs:
                shown = ", ".join(_pair_phrase(scores, fam, metric, a, b, d) for a, b, d in pairs[:SHOWN_PAIRS])
                rest = len(pairs) - SHOWN_PAIRS
                said.append(f"separates {len(pairs)} of {compared} pairs on {metric}: {shown}"
                            + (f" (+{rest} more)" if rest > 0 else "")
                            + (f"; the other {compared - len(pairs)} tie or differ by under {MIN_SEPARATION:g} points"
                               if compared > len(pairs) else ""))
            elif compared:
                said.append(f"none of its {compared} pairs on {metric} separate (ties, or under "
                            f"{MIN_SEPARATION:g} points)")
        if _changes_nothing(scores, fam):
            kept = fam in ALWAYS_KEPT
            reason = ("changes nothing on this base: every perturbed run scores exactly as its seed's clean run"
                      + ("; kept for the time-varying heads in any case" if kept else ""))
        elif breaks or separates:
            kept, reason = True, "; ".join((["breaks " + ", ".join(breaks)] if breaks else []) + said)
        elif fam in ALWAYS_KEPT:
            kept, reason = True, "kept for the time-varying heads (no break or separation measured)"
        else:
            kept, reason = False, ("no method breaks, and no two methods' drops differ outside the seed noise "
                                   "(mIoU, Acc)")
        out.append({"family": fam, "kept": kept, "reason": reason, "breaks": breaks, "separates": separates})
    return out


def verdict_markdown(verdicts: Sequence[dict]) -> str:
    """The kept and dropped families as a table, and the ``--families`` of the kept ones."""
    if not verdicts:
        return ""
    table = markdown_table(["family", "kept", "why"], [[v["family"], "yes" if v["kept"] else "dropped", v["reason"]]
                                                       for v in verdicts])
    kept = [v["family"] for v in verdicts if v["kept"]]
    return (f"{table}\nThe kept families, to fill in their strengths: `--families {' '.join(kept) or '(none)'}`.\n")


STATUS_PAIR = ("4d-langsplat", "non-status-field")
"""The status field and the directly time-varying field it is argued against: one CLIP field, one geometry,
only the time-varying head differs."""
STATUS_METRICS = ("Acc", "vIoU")
"""The time-sensitive scores the two heads are compared on."""


def status_comparison(scores: Sequence[Score], families: Sequence[str] = ALWAYS_KEPT,
                      pair: tuple[str, str] = STATUS_PAIR) -> list[dict]:
    """Per family (by default those kept for the time-varying heads), strength (the clean scene first) and
    time-sensitive metric: the paired difference ``pair[0]`` minus ``pair[1]`` per seed (same seed, same scene
    and supervision), its mean and 95 % t interval (:func:`benchmark.stats.t_interval`; NaN below two seeds)
    and a verdict: ahead where the interval excludes 0, else a tie. Families or metrics neither method answers are left out."""
    from benchmark.stats import t_interval

    a, b = pair
    rows = []
    for fam in families:
        runs = [s for s in scores if s.family == fam and s.method in pair]
        if not any(s.strength > 0 for s in runs):
            continue
        for metric in STATUS_METRICS:
            value = {(s.method, s.strength, s.seed): float(s.metrics[metric]) for s in runs
                     if s.metrics.get(metric) is not None}
            for strength in sorted({s.strength for s in runs}):
                seeds = sorted(seed for m, k, seed in value if m == a and k == strength and (b, k, seed) in value)
                if not seeds:
                    continue
                diffs = [value[a, strength, seed] - value[b, strength, seed] for seed in seeds]
                lo, hi = t_interval(diffs)
                verdict = (f"{a} ahead" if lo > 0 else f"{b} ahead" if hi < 0 else
                           "a tie" if np.isfinite(lo) else "one seed: undecided")
                rows.append({"family": fam, "strength": strength, "metric": metric, "seeds": len(diffs),
                             "difference": float(np.mean(diffs)), "low": lo, "high": hi, "verdict": verdict})
    return rows


def status_markdown(rows: Sequence[dict], pair: tuple[str, str] = STATUS_PAIR) -> str:
    """:func:`status_comparison` as a table, with a count of the cells outside the noise."""
    from benchmark.stats import interval_text

    if not rows:
        return f"Not measured: no family of {', '.join(ALWAYS_KEPT)} was run with both {pair[0]} and {pair[1]}.\n"
    table = markdown_table(
        ["family", "strength", "metric", "seeds", f"{pair[0]} − {pair[1]}", "95 % interval", "reading"],
        [[r["family"], strength_label(r["strength"]), r["metric"], str(r["seeds"]), number_cell(r["difference"], 2),
          interval_text(r["low"], r["high"]), r["verdict"]] for r in rows])
    decided = [r for r in rows if r["verdict"].endswith("ahead")]
    return (f"{table}\n{len(decided)} of {len(rows)} cells are outside the seed noise"
            + (": " + "; ".join(f"{r['family']} {strength_label(r['strength'])} {r['metric']}: {r['verdict']}"
                                for r in decided) if decided else "; the two heads cannot be told apart here")
            + ".\n")


NOTES_FILE = "notes.md"
"""A hand-written reading of the measurements in the report folder, copied into README.md when present."""


def write_reports(config: SuiteConfig, scores: Sequence[Score], *, wall_seconds: Optional[float] = None,
                  notes: Optional[str] = None) -> list[Path]:
    """Charts, galleries, the scores table and README.md under ``config.out_dir``; returns the paths.
    ``notes`` (default: the folder's :data:`NOTES_FILE`, if any) is copied into the README."""
    out = Path(config.out_dir)
    if notes is None:
        notes = (out / NOTES_FILE).read_text() if (out / NOTES_FILE).is_file() else ""
    written: list[Path] = []
    families = reported_families(config, scores)
    for fam in families:
        for made in (family_chart(scores, fam, config.methods, out / "charts" / f"{fam}.png"),
                     family_gallery(config, scores, fam, out / "galleries" / f"{fam}.png")):
            if made is not None:
                written.append(made)
    written.append(write_scores_table(scores, out / SCORES_FILE))
    header, rows = breaking_rows(scores, families, config.methods)
    text = _readme(config, scores, families, markdown_table(header, rows), wall_seconds, notes)
    write_text(out / "README.md", text)
    return written + [out / "README.md"]


def _floor_section(scores: Sequence[Score], families: Sequence[str], methods: Sequence[str]) -> str:
    table = floor_at_strongest(scores, families, methods)
    if not table:
        return ""
    return ("## Where a floor answers as well at the strongest strength\n\nFirst, because it says what a family's "
            "question no longer asks: the families at whose strongest strength a fitted method's mIoU interval over "
            "seeds lies wholly below a floor's (the floor answers better) or overlaps it (a tie).\n\n" + table + "\n")


def _verdicts(config: SuiteConfig, scores: Sequence[Score], families: Sequence[str]) -> list[dict]:
    """:func:`family_verdicts`, then a dropped row for each family that changes nothing on the base preset."""
    from .stress import unchanged_families

    out = family_verdicts(scores, families, config.methods)
    for fam, why in unchanged_families(config).items():
        if fam not in families:
            out.append({"family": fam, "kept": False, "reason": f"changes nothing on {config.preset} ({why}): not run",
                        "breaks": [], "separates": []})
    return out


def _readme(config: SuiteConfig, scores: Sequence[Score], families: Sequence[str], table: str,
            wall_seconds: Optional[float], notes: str) -> str:
    options = "; ".join(f"`{m}`: " + ", ".join(f"{k}={v}" for k, v in sorted(o.items()))
                        for m, o in sorted(config.method_options.items())) or "defaults"
    seeds = " ".join(map(str, config.seeds))
    wall = f"{wall_seconds / 60:.1f} min" if wall_seconds is not None else "not measured"
    charts = "\n".join(f"* [{f}](charts/{f}.png), gallery [{f}](galleries/{f}.png)" for f in families)
    return (f"# Where methods fail: the stress suite\n\n"
            f"Base preset `{config.preset}` at {config.size} px, {config.frames} frames, scored on the "
            f"`{config.split}` split, {TRACK} track (the generator's exact supervision, noised by the supervision-side "
            f"families); methods {', '.join(config.methods)}; seeds {seeds} (seed s generates the "
            f"scene with scene seed s and fits with seed s); device {config.device}. Method options: {options}.\n"
            f"{machine_line(scores)}"
            f"Wall time of this invocation: {wall} (runs already present are read, not redone). "
            f"Every run's scores: [scores.csv](scores.csv).\n\n"
            f"Coverage: {coverage(config, scores)}\n"
            f"Run time, each run on the core it ran on (a fit reused from the cache costs nothing here):\n\n"
            f"{_run_time_table(scores, config.methods)}\n"
            f"## Clean scores (strength 0, mean over seeds)\n\nA fitted method is *above every floor* where its "
            f"clean mIoU interval over seeds lies wholly above every floor's: on a base scene where it is not, the "
            f"floor answers the question as well, and a perturbation measures little.\n\n"
            f"{_clean_table(scores, config.methods)}\n"
            f"{_floor_section(scores, families, config.methods)}"
            f"## Breaking points\n\nThe first strength at which a method's 95 % interval over seeds lies wholly "
            f"below half of its clean interval's lower end: a drop outside the seed noise (`≤ s`: weaker strengths were not run; `> s`: it holds up to the strongest strength run; `–`: not run, or no clean score to halve).\n\n"
            f"{table}\n## Families kept and dropped\n\nA family is kept where a fitted method breaks on it, or where two "
            f"fitted methods' drops from the clean scene to its strongest strength differ outside the seed noise (the "
            f"95 % t interval over seeds of their paired difference excludes 0) by at least {MIN_SEPARATION:g} "
            f"points; floors are not counted; {', '.join(ALWAYS_KEPT)} are kept for the "
            f"time-varying heads in any case.\n\n{verdict_markdown(_verdicts(config, scores, families))}\n"
            f"## Findings per family (measured)\n\nMeans over the seeds run (the clean runs' and, "
            f"where a perturbed strength has fewer, which at which strengths), each with the 95 % interval over "
            f"seeds a breaking point reads: clean [interval] -> strongest strength [interval].\n\n"
            f"{findings(scores, families, config.methods)}\n"
            f"## The status field against the non-status field under {', '.join(ALWAYS_KEPT)}\n\nPer seed, "
            f"{STATUS_PAIR[0]} minus {STATUS_PAIR[1]} on the same scene and supervision (one CLIP field, one "
            f"geometry; only the time-varying head differs); the mean over seeds with its 95 % t interval. A "
            f"cell is a tie where the interval holds 0.\n\n{status_markdown(status_comparison(scores))}\n"
            + (f"{notes.strip()}\n\n" if notes.strip() else "")
            + f"## Charts and galleries\n\nA chart draws each metric against the family's strength: per method "
              f"a line through the mean over the seeds, shaded from its lowest to its highest seed, and a dotted "
              f"line in its colour at half its clean score (a method breaks where its whole seed interval falls below half of its clean interval). A gallery "
              f"shows the strongest strength's worst (query, frame) pairs, each below the same pair on the clean "
              f"scene, with the first time-sensitive query's decisions at the bottom.\n\n{charts}\n")
