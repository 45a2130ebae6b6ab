"""Two results folders of the same runs under two configs, compared run by run: did the change move the scores
beyond the noise, and what did it save?

A candidate run is paired with the baseline run of the same dataset, scene, method, track, split and seed
(the same relative path), on the same scene (the digest of a generated scene, ``scene_info.generated.digest``).
Per method, track, split and score the report gives the baseline and candidate means, their mean paired
difference (candidate - baseline, scenes weighted equally), its 95 % interval (each scene's pairs resampled,
:func:`benchmark.stats.bootstrap_means`; none where a scene has one pair) and how many pairs moved down and up.
With two or three pairs a scene that interval is too narrow to decide on, so the verdict is the exact
sign-flip test's (:func:`benchmark.stats.sign_flip_test`): beyond the noise where p < 0.05, which six pairs
can reach only when all six move the same way.

The geometry's own scores -- held-out PSNR on the paper split's frames and PSNR on the novel views -- are
compared on the paper-split runs (one fit answers both splits, so the novel-view runs would count it twice).

Cost is the fit seconds each run added beyond a geometry fit (``timing.fit_seconds`` less the geometry's
seconds where that run fitted it): the geometry of a scene and seed is fitted once and charged to whichever
method ran first, so the seconds a config's other stages cost are compared, summed per method. The geometry
fits themselves are compared apart, each counted once (by its cache key), stage by stage in CPU seconds, which a
shared machine disturbs less than wall seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from benchmark.results import find_results, read_results
from benchmark.stats import bootstrap_means, interval_text, percentile_interval, sign_flip_test, stable_seed

from ._report import Report, markdown_table, write_report

MIN_PAIRS_PER_SCENE = 2
"""A scene with fewer pairs leaves its row without an interval (its pairs still count in the test)."""
SIGNIFICANCE = 0.05
"""A difference is beyond the noise where the sign-flip test's two-sided p-value is below this."""
SCORES = ("mIoU", "Acc", "vIoU", "held-out PSNR (dB)", "novel-view PSNR (dB)")
"""Scores compared (higher is better); a score a method does not answer is left out."""
GEOMETRY_SCORES = {"held-out PSNR (dB)": "test_psnr", "novel-view PSNR (dB)": "novel_view_psnr"}
"""Scores of the geometry fit (``fit.info.geometry``), read from paper-split runs only."""
GEOMETRY_COSTS = ("static stage CPU s", "deformation stage CPU s", "whole geometry wall s")
"""The geometry fit's seconds compared (the stages as the fit recorded them)."""


@dataclass
class Pair:
    """One run under both configs."""

    dataset: str
    scene: str
    method: str
    track: str
    split: str
    seed: int
    baseline: dict[str, Optional[float]]
    candidate: dict[str, Optional[float]]
    baseline_seconds: float
    candidate_seconds: float
    options: dict[str, tuple[Any, Any]] = field(default_factory=dict)
    """Method option (dotted path) -> (baseline value, candidate value), where the two configs differ."""
    baseline_geometry: Optional[dict[str, Any]] = None
    """:func:`geometry_seconds` of the baseline run's geometry (None: the run records none)."""
    candidate_geometry: Optional[dict[str, Any]] = None
    """... and of the candidate run's."""


def _options(doc: dict) -> dict[str, Any]:
    """Dotted option path -> value of the run's recorded method config, read as its registered method reads
    records (older option names included); none for a method not registered here."""
    from methods import registry

    if doc["method"] not in registry.names():
        return {}
    return registry.get(doc["method"]).recorded_options(doc.get("method_config"))


def added_seconds(doc: dict) -> float:
    """Fit seconds of a run beyond the geometry it fitted itself (0 for a fit read from the cache)."""
    timing = doc.get("timing") or {}
    if timing.get("fit_cached"):
        return 0.0
    seconds = float(timing.get("fit_seconds") or 0.0)
    info = (doc.get("fit") or {}).get("info") or {}
    geometry = info.get("geometry") if isinstance(info, dict) else None
    cached = (info.get("cached") or {}).get("geometry", True) if isinstance(info, dict) else True
    if isinstance(geometry, dict) and not cached:
        seconds -= float(geometry.get("seconds") or 0.0)
    return max(0.0, seconds)


def _number(value: Any) -> Optional[float]:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    return float(value) if ok else None


def _geometry_info(doc: dict) -> Optional[dict]:
    info = (doc.get("fit") or {}).get("info")
    geometry = info.get("geometry") if isinstance(info, dict) else None
    return geometry if isinstance(geometry, dict) else None


def _scores(doc: dict) -> dict[str, Optional[float]]:
    metrics = doc.get("metrics") or {}
    geometry = _geometry_info(doc) if (doc.get("split") or "paper") == "paper" else None
    out: dict[str, Optional[float]] = {}
    for name in SCORES:
        if name in GEOMETRY_SCORES:
            out[name] = _number((geometry or {}).get(GEOMETRY_SCORES[name]))
        else:
            out[name] = _number(metrics.get(name))
    return out


def geometry_seconds(doc: dict) -> Optional[dict[str, Any]]:
    """The run's geometry fit as its record gives it (whether this run fitted it or read it from the cache):
    its cache ``key`` and :data:`GEOMETRY_COSTS`; None where the run records no geometry."""
    geometry = _geometry_info(doc)
    if geometry is None or not geometry.get("key"):
        return None
    stages = {s.get("stage"): s for s in geometry.get("stages") or [] if isinstance(s, dict)}
    return {"key": str(geometry["key"]),
            "static stage CPU s": _number((stages.get("static") or {}).get("cpu_seconds")),
            "deformation stage CPU s": _number((stages.get("deformation") or {}).get("cpu_seconds")),
            "whole geometry wall s": _number(geometry.get("seconds"))}


def _scene_digest(doc: dict) -> Optional[str]:
    """The digest of the generated scene a run read (None for a scene folder, which records none)."""
    generated = (doc.get("scene_info") or {}).get("generated")
    return generated.get("digest") if isinstance(generated, dict) else None


def pair_runs(baseline_dir: Path, candidate_dir: Path) -> tuple[list[Pair], list[str]]:
    """The candidate's runs paired with the baseline's; and, for each candidate run left unpaired, why."""
    pairs, unpaired = [], []
    for path in find_results(candidate_dir):
        rel = path.relative_to(candidate_dir)
        other = Path(baseline_dir) / rel
        if not other.is_file():
            unpaired.append(f"{rel}: no baseline run")
            continue
        new, old = read_results(path), read_results(other)
        if _scene_digest(new) != _scene_digest(old):
            unpaired.append(f"{rel}: another scene (generated-scene digests differ)")
            continue
        a, b = _options(old), _options(new)
        options = {k: (a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)}
        pairs.append(Pair(new["dataset"], new["scene"], new["method"], new["track"], new.get("split") or "paper",
                          int(new["seed"]), _scores(old), _scores(new), added_seconds(old), added_seconds(new),
                          options, geometry_seconds(old), geometry_seconds(new)))
    return pairs, unpaired


def compare(pairs: list[Pair]) -> list[dict[str, Any]]:
    """One row per (method, track, split, score) with its paired difference, interval and test."""
    rows = []
    for method, track, split in sorted({(p.method, p.track, p.split) for p in pairs}):
        mine = [p for p in pairs if (p.method, p.track, p.split) == (method, track, split)]
        for name in SCORES:
            both = [p for p in mine if p.baseline[name] is not None and p.candidate[name] is not None]
            if not both:
                continue
            scenes = sorted({(p.dataset, p.scene) for p in both})
            by_scene = [[p for p in both if (p.dataset, p.scene) == s] for s in scenes]
            diffs = [np.array([[p.candidate[name] - p.baseline[name]] for p in group]) for group in by_scene]
            old = [np.array([[p.baseline[name]] for p in group]) for group in by_scene]
            new = [np.array([[p.candidate[name]] for p in group]) for group in by_scene]
            if min(len(group) for group in by_scene) >= MIN_PAIRS_PER_SCENE:
                reps = bootstrap_means({"diff": diffs}, seed=stable_seed("paired", method, track, split, name),
                                       resample_queries=False)["diff"]
                lo, hi = percentile_interval(reps)
            else:  # one pair cannot be resampled: its "interval" would be a point
                lo = hi = math.nan
            mean = float(np.mean([d.mean() for d in diffs]))
            flat = np.concatenate([d.ravel() for d in diffs])
            p_value = sign_flip_test(diffs)
            rows.append({"method": method, "track": track, "split": split, "score": name, "pairs": int(flat.size),
                         "scenes": len(scenes), "baseline": float(np.mean([o.mean() for o in old])),
                         "candidate": float(np.mean([n.mean() for n in new])), "difference": mean,
                         "interval": [lo, hi], "down": int((flat < 0).sum()), "up": int((flat > 0).sum()),
                         "p_value": p_value, "beyond_noise": bool(p_value < SIGNIFICANCE)})
    return rows


def costs(pairs: list[Pair]) -> list[dict[str, Any]]:
    """Per method (paper split, where each fit is charged), the fit seconds beyond geometry on both sides."""
    rows = []
    fitted = [p for p in pairs if p.split == "paper"] or pairs
    for method in sorted({p.method for p in fitted}):
        mine = [p for p in fitted if p.method == method]
        old, new = sum(p.baseline_seconds for p in mine), sum(p.candidate_seconds for p in mine)
        rows.append({"method": method, "runs": len(mine), "baseline_seconds": old, "candidate_seconds": new})
    old, new = sum(r["baseline_seconds"] for r in rows), sum(r["candidate_seconds"] for r in rows)
    rows.append({"method": "all", "runs": sum(r["runs"] for r in rows), "baseline_seconds": old,
                 "candidate_seconds": new})
    return rows


def geometry_costs(pairs: list[Pair]) -> list[dict[str, Any]]:
    """Per geometry cost (:data:`GEOMETRY_COSTS`): the sums over the geometry fits both sides record, each fit
    counted once (pairs whose two geometries are the same fit, or that lack one, are left out)."""
    seen: dict[tuple[str, str], tuple[dict, dict]] = {}
    for p in pairs:
        a, b = p.baseline_geometry, p.candidate_geometry
        if a is None or b is None or a["key"] == b["key"]:
            continue
        seen.setdefault((a["key"], b["key"]), (a, b))
    rows = []
    for name in GEOMETRY_COSTS:
        both = [(a[name], b[name]) for a, b in seen.values() if a[name] is not None and b[name] is not None]
        if both:
            rows.append({"cost": name, "fits": len(both), "baseline_seconds": sum(x for x, _ in both),
                         "candidate_seconds": sum(y for _, y in both)})
    return rows


def _interval_cell(row: dict[str, Any]) -> str:
    if not all(math.isfinite(v) for v in row["interval"]):
        return f"– (fewer than {MIN_PAIRS_PER_SCENE} pairs in a scene)"
    return interval_text(*row["interval"])


def _noise_cell(row: dict[str, Any]) -> str:
    return ("yes" if row["beyond_noise"] else "no (a tie)") + f", p = {row['p_value']:.3f}"


def _seconds_cell(value: float) -> str:
    return f"{value:.0f}"


def paired_report(name: str, baseline_dir: Path, candidate_dir: Path, out: Path,
                  log: Callable[[str], None] = lambda m: None) -> Report:
    """Pair, compare and write ``<out>/paired-<name>.{json,md}``."""
    baseline_dir, candidate_dir = Path(baseline_dir), Path(candidate_dir)
    pairs, unpaired = pair_runs(baseline_dir, candidate_dir)
    for line in unpaired:
        log(f"unpaired: {line}")
    if not pairs:
        from benchmark.core.errors import InputError

        raise InputError(candidate_dir, "results", f"no run here has a baseline run at the same place under "
                                                    f"{baseline_dir}")
    rows, cost = compare(pairs), costs(pairs)
    options = sorted({(k, repr(v[0]), repr(v[1])) for p in pairs for k, v in p.options.items()})
    lines = [f"# Paired runs: {name}", "",
             f"Baseline `{baseline_dir}`, candidate `{candidate_dir}`: {len(pairs)} runs paired by dataset, scene, "
             f"method, track, split and seed ({len(unpaired)} left unpaired). Difference = candidate - baseline, "
             "mean over scenes of each scene's mean over its pairs; interval: 95 %, each scene's pairs resampled (too "
             "narrow with two pairs a scene to decide on); beyond noise: the exact sign-flip test's p < "
             f"{SIGNIFICANCE}; down / up: pairs that fell / rose.", ""]
    if options:
        lines += ["Options that differ (baseline -> candidate):", ""]
        lines += [f"* `{k}`: {a} -> {b}" for k, a, b in options] + [""]
    lines += [markdown_table(
        ["method", "track", "split", "score", "pairs", "baseline", "candidate", "difference", "95 % interval",
         "down / up", "beyond noise (sign-flip test)"],
        [[r["method"], r["track"], r["split"], r["score"], str(r["pairs"]), f"{r['baseline']:.2f}",
          f"{r['candidate']:.2f}", f"{r['difference']:+.2f}", _interval_cell(r), f"{r['down']} / {r['up']}",
          _noise_cell(r)] for r in rows])]
    lines += ["Fit seconds beyond geometry (paper-split runs; a stage read from the cache costs 0 there, so a "
              "method that reuses another's stage shows less than it needs alone):", "",
              markdown_table(["method", "runs", "baseline s", "candidate s", "ratio"],
                             [[r["method"], str(r["runs"]), _seconds_cell(r["baseline_seconds"]),
                               _seconds_cell(r["candidate_seconds"]),
                               f"{r['candidate_seconds'] / r['baseline_seconds']:.2f}" if r["baseline_seconds"] else "–"]
                              for r in cost])]
    geometry = geometry_costs(pairs)
    if geometry:
        lines += ["", "The geometry fits, each counted once (CPU seconds per stage as each fit recorded them, and its "
                  "wall seconds):", "",
                  markdown_table(["geometry", "fits", "baseline s", "candidate s", "ratio"],
                                 [[r["cost"], str(r["fits"]), _seconds_cell(r["baseline_seconds"]),
                                   _seconds_cell(r["candidate_seconds"]),
                                   f"{r['candidate_seconds'] / r['baseline_seconds']:.2f}" if r["baseline_seconds"]
                                   else "–"] for r in geometry])]
    table = "\n".join(lines)
    doc = {"name": name, "baseline": str(baseline_dir), "candidate": str(candidate_dir), "pairs": len(pairs),
           "unpaired": unpaired, "options": [list(o) for o in options], "scores": rows, "costs": cost,
           "geometry_costs": geometry}
    return Report(table, write_report(Path(out), f"paired-{name}", doc, table))
