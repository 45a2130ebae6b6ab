"""How far one fit's scores move when torch's CPU kernels change instruction set.

``bench4d ablate kernels`` fits one method on each scene and seed once per kernel setting -- torch's
``ATEN_CPU_CAPABILITY`` set to ``default`` (the x86-64 baseline), ``avx2``, or left unset (``native``: the
best the CPU has) -- each in a fresh subprocess with its own cache, single-threaded, so nothing fitted is
shared. The code, seed, scene and options are the same: what differs is float rounding in torch's
vectorised kernels, which the fit can amplify (densification thresholds, ties in sorts, the order of
reductions). The compiled kernels of :mod:`methods.gaussians.backends.native_cpu` are built to give the same
numbers whatever vector width they run with; torch's own operators are not.

The report gives every scene and seed's scores under each setting, their spread (largest minus smallest),
and, where a results folder holds runs of the same method, split and scenes (the leaderboard's), the
95 % interval of their mean over scenes (stratified bootstrap over seeds, :mod:`benchmark.stats`) and
whether each setting's mean over the study's scenes falls inside it: a spread inside that interval is
part of the noise the leaderboard already states; one outside it is not.

Writes ``<out>/<name>.json``, ``<out>/<name>.md`` (default ``reports/kernel-spread/kernel-spread``) and
every run's results file under ``<out>/<name>-runs/`` atomically; a run whose kept results file matches
the configuration is read, not redone, so an interrupted study resumes.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np

from benchmark.core.errors import InputError
from benchmark.core.scene import DEFAULT_EVAL_SPLIT, check_eval_split

from . import fit_timing
from .kernel_trace import TraceConfig, pairings, run_trace, trace_markdown
from ._report import Report, markdown_table, write_report

REPORTS = Path("reports/kernel-spread")
"""Default output folder."""

REPO = Path(__file__).resolve().parents[2]
"""The checkout whose code every run uses."""

CAPABILITIES = ("default", "avx2", "native")
"""Kernel settings: a value of ``ATEN_CPU_CAPABILITY``, or ``native`` (the variable unset)."""

SCORES = fit_timing.SCORES
"""Scores listed per run, as the timing study lists them (the first three are compared with the interval)."""
COMPARED = ("mIoU", "Acc", "vIoU")
"""Scores whose spread is set beside the results folder's interval."""


@dataclass
class KernelSpreadConfig:
    """What to fit under each kernel setting."""

    method: str = "4d-langsplat"
    """The method fitted."""
    scenes: tuple[str, ...] = ("split-cookie", "espresso", "chickchicken")
    """Synthetic presets (seed s generates the scene with generator seed s) or scene folders."""
    seeds: tuple[int, ...] = (0,)
    """The fits' seeds."""
    size: int = 128
    """Image size of a generated preset."""
    capabilities: tuple[str, ...] = CAPABILITIES
    """Kernel settings (:data:`CAPABILITIES`)."""
    split: str = DEFAULT_EVAL_SPLIT
    """Evaluation split scored."""
    overrides: dict[str, str] = field(default_factory=dict)
    """Method options (``--set KEY=VALUE``) of every run."""
    results_dir: Optional[Path] = Path("results")
    """Runs of the same method and split whose interval the spread is set beside (``None``: none)."""
    cache_dir: Path = Path("cache")
    """Where a generated preset is kept (fits never are: each run has a cache of its own)."""
    timeout: float = 4 * 3600.0
    """Seconds one run may take before it counts as failed."""
    trace: bool = False
    """Also run :mod:`.kernel_trace`: a short fit per setting (default, avx2, native) with its loss at every
    iteration, to show where the fits part."""
    trace_config: TraceConfig = field(default_factory=TraceConfig)
    """The trace's fit."""
    name: str = "kernel-spread"
    """Output file stem."""
    out: Path = REPORTS
    """Output folder."""


def _path(doc: dict, keys: tuple) -> Optional[float]:
    node: Any = doc
    for key in keys:
        if not isinstance(node, dict) or key not in node:
            return None
        node = node[key]
    return float(node) if isinstance(node, (int, float)) and not isinstance(node, bool) else None


def check_config(config: KernelSpreadConfig) -> None:
    """:class:`InputError` for a configuration no run could satisfy (before anything is fitted)."""
    if not config.scenes or not config.seeds:
        raise InputError(None, "--scenes/--seeds", "need at least one scene and one seed")
    bad = [c for c in config.capabilities if c not in CAPABILITIES]
    if bad or not config.capabilities:
        raise InputError(None, "--capabilities", f"expected some of {', '.join(CAPABILITIES)}, got {bad or 'none'}")
    if len(set(config.capabilities)) != len(config.capabilities):
        raise InputError(None, "--capabilities", "a setting is named twice")
    check_eval_split(config.split)


def run_env(capability: str, base: Optional[dict] = None) -> dict[str, str]:
    """The environment of a run under ``capability``: one thread, this checkout's code, and
    ``ATEN_CPU_CAPABILITY`` set (or removed for ``native``)."""
    env = {**(os.environ if base is None else base), "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1",
           "MKL_NUM_THREADS": "1"}
    env.pop("ATEN_CPU_CAPABILITY", None)
    if capability != "native":
        env["ATEN_CPU_CAPABILITY"] = capability
    return env


def eval_command(config: KernelSpreadConfig, scene_dir: Path, seed: int, cache: Path, results: Path,
                 python: str = sys.executable) -> list[str]:
    """The ``bench4d eval`` command line of one run."""
    cmd = [python, "-m", "benchmark.cli", "eval", "--method", config.method, "--scene", str(scene_dir),
           "--seed", str(seed), "--split", config.split, "--cache-dir", str(cache), "--results-dir", str(results),
           "--threads", "1", "--quiet"]
    for key, value in sorted(config.overrides.items()):
        cmd += ["--set", f"{key}={value}"]
    return cmd


def _kept_name(scene: str, seed: int, capability: str) -> str:
    return f"{Path(scene).name}-seed{seed}-{capability}.json"


def _matches(doc: dict, config: KernelSpreadConfig, seed: int, capability: str) -> bool:
    """Whether a kept results file is this configuration's run (method, seed, split, kernels, options)."""
    mine = doc.get("kernel_spread") if isinstance(doc.get("kernel_spread"), dict) else {}
    wanted = {k: str(v) for k, v in config.overrides.items()}
    return (doc.get("method") == config.method and doc.get("seed") == seed
            and doc.get("split", DEFAULT_EVAL_SPLIT) == config.split and mine.get("capability") == capability
            and mine.get("overrides") == wanted and mine.get("size") == config.size)


def run_one(config: KernelSpreadConfig, scene_dir: Path, seed: int, capability: str, kept: Path,
            log: Callable[[str], None]) -> dict:
    """One fit under ``capability`` in a subprocess; its results file copied to ``kept`` (atomically)."""
    from benchmark.core.atomic import write_bytes

    with tempfile.TemporaryDirectory(prefix="bench4d-kernel-spread-") as tmp:
        cache, results = Path(tmp) / "cache", Path(tmp) / "results"
        cmd = eval_command(config, scene_dir, seed, cache, results)
        log(f"{scene_dir.name} seed {seed}: {capability} kernels")
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        done = subprocess.run(cmd, cwd=str(REPO), env=run_env(capability), capture_output=True, text=True,
                              timeout=config.timeout)
        wall = time.perf_counter() - start
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if done.returncode != 0:
            raise RuntimeError(f"the {capability} fit of {scene_dir} seed {seed} failed (exit {done.returncode}): "
                               f"{done.stderr.strip()[-3000:]}")
        files = sorted(p for p in results.rglob("*.json") if p.parent.name != "ablations")
        if len(files) != 1:
            raise RuntimeError(f"expected one results file under {results}, found {len(files)}")
        doc = json.loads(files[0].read_text())
        doc["kernel_spread"] = {"capability": capability, "overrides": {k: str(v) for k, v in config.overrides.items()},
                                "size": config.size, "wall_seconds": wall,
                                "cpu_seconds": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)}
        write_bytes(kept, (json.dumps(doc, indent=1, sort_keys=True) + "\n").encode())
    return doc


def run_record(doc: dict, scene: str, seed: int, capability: str, path: Path) -> dict:
    """A run's row: its scores, the kernels it recorded and its time."""
    from benchmark.results import machine_of

    machine = machine_of(doc)
    return {"scene": Path(scene).name, "seed": seed, "capability": capability, "track": doc.get("track"),
            "recorded_capability": machine["cpu_capability"] or None, "machine_kind": machine["machine_kind"],
            "scores": {label: _path(doc, keys) for label, keys in SCORES},
            "fit_seconds": _path(doc, ("timing", "fit_seconds")), "results_file": path.name}


def spread_rows(runs: Sequence[dict]) -> list[dict]:
    """Per scene, seed and compared score: the value under each setting and max - min (None where fewer
    than two settings scored it)."""
    rows = []
    for scene, seed in sorted({(r["scene"], r["seed"]) for r in runs}):
        mine = [r for r in runs if (r["scene"], r["seed"]) == (scene, seed)]
        for label in COMPARED:
            values = {r["capability"]: r["scores"].get(label) for r in mine}
            got = [v for v in values.values() if v is not None and np.isfinite(v)]
            rows.append({"scene": scene, "seed": seed, "score": label, "values": values,
                         "spread": (max(got) - min(got)) if len(got) > 1 else None})
    return rows


def setting_means(runs: Sequence[dict], label: str) -> dict[str, Optional[float]]:
    """Per setting: the mean over scenes (each scene the mean over its seeds) of ``label``; None where a
    scene lacks it."""
    out: dict[str, Optional[float]] = {}
    for cap in sorted({r["capability"] for r in runs}):
        per_scene = []
        for scene in sorted({r["scene"] for r in runs}):
            values = [r["scores"].get(label) for r in runs if r["capability"] == cap and r["scene"] == scene]
            values = [v for v in values if v is not None and np.isfinite(v)]
            per_scene.append(float(np.mean(values)) if values else None)
        out[cap] = None if not per_scene or any(v is None for v in per_scene) else float(np.mean(per_scene))
    return out


def reference_interval(values: dict[str, list[float]], *, seed: int = 0) -> Optional[dict]:
    """The 95 % interval of the mean over scenes of ``values`` (scene -> per-seed scores), resampling seeds
    within each scene (:func:`benchmark.stats.bootstrap_means`); None where a scene has no score."""
    from benchmark.stats import bootstrap_means, percentile_interval

    if not values or any(not v for v in values.values()):
        return None
    cells = {"runs": [np.asarray(values[s], dtype=np.float64)[:, None] for s in sorted(values)]}
    replicates = bootstrap_means(cells, seed=seed, resample_queries=False)["runs"]
    lo, hi = percentile_interval(replicates)
    mean = float(np.mean([np.mean(values[s]) for s in sorted(values)]))
    return {"mean": mean, "low": lo, "high": hi, "seeds": {s: len(values[s]) for s in sorted(values)}}


def folder_values(results_dir: Path, method: str, split: str, scenes: Sequence[str], label: str,
                  machine_kind: Optional[str] = None, runs=None,
                  track: Optional[str] = None) -> dict[str, dict[int, float]]:
    """Scene -> seed -> ``label`` of ``method``'s runs on ``split`` under ``results_dir``, read as the
    leaderboard reads them (:func:`benchmark.leaderboard.load_runs`): runs of a clean, unchanging checkout
    only, of ``machine_kind`` and ``track`` where given. ``runs``: that folder's runs table, when already read."""
    from benchmark.leaderboard import load_runs

    if runs is None:
        runs, _ = load_runs(results_dir)
    if not len(runs):
        return {}
    names = {Path(s).name for s in scenes}
    keep = ((runs["method"] == method) & (runs["split"] == split) & runs["scene"].isin(names)
            & ~runs["dirty"].astype(bool) & ~runs["code_changed"].astype(bool))
    if machine_kind is not None:
        keep &= runs["machine_kind"] == machine_kind
    if track is not None:
        keep &= runs["track"] == track
    out: dict[str, dict[int, float]] = {}
    for _, row in runs[keep].sort_values(["scene", "seed"]).iterrows():
        value = row[label]
        if value is not None and np.isfinite(float(value)):
            out.setdefault(str(row["scene"]), {})[int(row["seed"])] = float(value)
    return out


def leaderboard_values(results_dir: Path, method: str, split: str, scenes: Sequence[str], label: str,
                       machine_kind: Optional[str] = None, runs=None,
                       track: Optional[str] = None) -> dict[str, list[float]]:
    """Scene -> the per-seed ``label`` (in seed order) of :func:`folder_values`."""
    found = folder_values(results_dir, method, split, scenes, label, machine_kind=machine_kind, runs=runs,
                          track=track)
    return {scene: [seeds[k] for k in sorted(seeds)] for scene, seeds in found.items()}


def native_kind(runs: Sequence[dict]) -> Optional[str]:
    """The machine kind of the study's ``native`` runs (the kind the leaderboard's runs on this machine
    record); None without one."""
    kinds = {r.get("machine_kind") for r in runs if r["capability"] == "native"} - {None}
    return kinds.pop() if len(kinds) == 1 else None


def read_folder(config: KernelSpreadConfig):
    """The results folder's runs table (:func:`benchmark.leaderboard.load_runs`), or None without a folder."""
    from benchmark.leaderboard import load_runs

    if config.results_dir is None or not Path(config.results_dir).is_dir():
        return None
    return load_runs(Path(config.results_dir))[0]


def study_track(runs: Sequence[dict]) -> Optional[str]:
    """The supervision track of the study's runs (the folder's runs are read on it alone); None without one."""
    tracks = {r.get("track") for r in runs} - {None}
    return tracks.pop() if len(tracks) == 1 else None


def summarize(runs: Sequence[dict], config: KernelSpreadConfig, folder_runs=None) -> list[dict]:
    """Per compared score: each setting's mean over scenes, the spread of those means, the mean and largest
    per-run spread, and the results folder's interval with whether each setting's mean lies inside it.
    ``folder_runs``: the folder's runs table (:func:`read_folder`; None: no folder)."""
    out = []
    per_run = spread_rows(runs)
    track = study_track(runs)
    for label in COMPARED:
        means = setting_means(runs, label)
        got = [v for v in means.values() if v is not None]
        spreads = [r["spread"] for r in per_run if r["score"] == label and r["spread"] is not None]
        reference = None
        if folder_runs is not None:
            reference = reference_interval(leaderboard_values(Path(config.results_dir), config.method, config.split,
                                                              config.scenes, label, machine_kind=native_kind(runs),
                                                              runs=folder_runs, track=track))
            if reference is not None and set(reference["seeds"]) != {r["scene"] for r in runs}:
                reference = None  # the folder lacks one of the study's scenes: no like-for-like interval
        inside = ({cap: (v is not None and reference["low"] <= v <= reference["high"]) for cap, v in means.items()}
                  if reference else None)
        out.append({"score": label, "means": means, "spread_of_means": (max(got) - min(got)) if len(got) > 1 else None,
                    "mean_run_spread": float(np.mean(spreads)) if spreads else None,
                    "max_run_spread": max(spreads) if spreads else None, "reference": reference, "inside": inside})
    return out


def noise_rows(runs: Sequence[dict], config: KernelSpreadConfig, folder_runs=None) -> list[dict]:
    """Per scene, seed and compared score: the fit's values over the kernel settings -- with the results
    folder's own fit of that seed (``folder``) where the study did not refit ``native`` -- beside the folder's
    values over seeds, and the 95 % prediction interval those seeds give for one more fit
    (:func:`benchmark.stats.prediction_interval`) with whether each kernel setting's fit lies inside it.

    The kernel settings of one seed and the seeds of one setting are two sources of the same kind of
    variation when a fit amplifies float rounding: their spreads are set side by side."""
    from benchmark.stats import prediction_interval

    folder: dict[str, dict[str, dict[int, float]]] = {}
    if folder_runs is not None:
        for label in COMPARED:
            folder[label] = folder_values(Path(config.results_dir), config.method, config.split, config.scenes,
                                          label, machine_kind=native_kind(runs), runs=folder_runs,
                                          track=study_track(runs))
    refit_native = any(r["capability"] == "native" for r in runs)
    rows = []
    for scene, seed in sorted({(r["scene"], r["seed"]) for r in runs}):
        mine = [r for r in runs if (r["scene"], r["seed"]) == (scene, seed)]
        for label in COMPARED:
            kernels = {r["capability"]: r["scores"].get(label) for r in mine}
            kernels = {k: v for k, v in kernels.items() if v is not None and np.isfinite(v)}
            seeds = folder.get(label, {}).get(scene, {})
            if not refit_native and seed in seeds:
                kernels["folder"] = seeds[seed]
            k_values, s_values = list(kernels.values()), list(seeds.values())
            lo, hi = prediction_interval(s_values)
            inside = ({k: bool(lo <= v <= hi) for k, v in kernels.items() if k != "folder"}
                      if np.isfinite(lo) else None)
            rows.append({"scene": scene, "seed": seed, "score": label, "kernels": kernels,
                         "kernel_std": float(np.std(k_values, ddof=1)) if len(k_values) > 1 else None,
                         "kernel_range": (max(k_values) - min(k_values)) if len(k_values) > 1 else None,
                         "seeds": {str(k): v for k, v in sorted(seeds.items())},
                         "seed_std": float(np.std(s_values, ddof=1)) if len(s_values) > 1 else None,
                         "seed_range": (max(s_values) - min(s_values)) if len(s_values) > 1 else None,
                         "prediction_interval": None if inside is None else [lo, hi], "inside_prediction": inside})
    return rows


def noise_markdown(rows: Sequence[dict]) -> str:
    """The kernels-against-seeds section of the report."""
    if not rows:
        return ""
    table_rows = []
    for r in rows:
        pi = r["prediction_interval"]
        inside = "-" if r["inside_prediction"] is None else ", ".join(
            f"{k}: {'yes' if v else 'no'}" for k, v in sorted(r["inside_prediction"].items()))
        table_rows.append([r["scene"], str(r["seed"]), r["score"], str(len(r["kernels"])), _cell(r["kernel_std"]),
                           _cell(r["kernel_range"]), str(len(r["seeds"])), _cell(r["seed_std"]), _cell(r["seed_range"]),
                           "-" if pi is None else f"[{pi[0]:.2f}, {pi[1]:.2f}]", inside])
    table = markdown_table(["scene", "seed", "score", "kernel settings", "std over kernels", "range over kernels",
                            "seeds (results folder)", "std over seeds", "range over seeds",
                            "one fit's 95 % prediction interval (from the seeds)", "inside?"], table_rows)
    return ("\n\n## Kernels against seeds\n\nOne seed's fit under each kernel setting (with the results folder's own "
            "fit of that seed where the study did not refit `native`), beside the results folder's fits of the "
            "same scene over seeds: sample standard deviations and ranges. The last columns set each kernel "
            "setting's fit against the 95 % prediction interval of one fit given those seeds (t distribution, "
            "`benchmark.stats.prediction_interval`) -- the yardstick for a single fit, where the interval of the "
            "means above is the yardstick for a mean.\n\n" + table)


def _cell(value: Optional[float], digits: int = 2) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def spread_markdown(config: KernelSpreadConfig, runs: Sequence[dict], summary: Sequence[dict]) -> str:
    caps = list(config.capabilities)
    scenes = ", ".join(Path(s).name for s in config.scenes)
    recorded = sorted({f"{r['capability']} -> {r['recorded_capability']}" for r in runs})
    head = (f"# Kernel spread: {config.method} on {scenes} ({config.size} px), seeds "
            f"{', '.join(map(str, config.seeds))}, {config.split} split, {study_track(runs) or 'mixed'} track\n\n"
            "Made by `bench4d ablate kernels`. Each run is a fresh fit in its own process, single-threaded, with "
            "torch's CPU kernels set by `ATEN_CPU_CAPABILITY` (`native`: unset); code, seed, scene and options are "
            f"the same. Kernels each run recorded: {'; '.join(recorded)}.\n\n")
    rows = [[r["scene"], str(r["seed"]), r["score"]] + [_cell(r["values"].get(c)) for c in caps] + [_cell(r["spread"])]
            for r in spread_rows(runs)]
    table = markdown_table(["scene", "seed", "score"] + caps + ["spread"], rows)
    sum_rows = []
    for s in summary:
        ref = s["reference"]
        ref_text = (f"{ref['mean']:.2f} [{ref['low']:.2f}, {ref['high']:.2f}] "
                    f"({sum(ref['seeds'].values())} runs)") if ref else "no like-for-like runs"
        inside = (", ".join(f"{c}: {'yes' if s['inside'].get(c) else 'no'}" for c in caps if c in s["inside"])
                  if s["inside"] else "-")
        sum_rows.append([s["score"]] + [_cell(s["means"].get(c)) for c in caps]
                        + [_cell(s["spread_of_means"]), _cell(s["mean_run_spread"]), _cell(s["max_run_spread"]),
                           ref_text, inside])
    summary_table = markdown_table(["score"] + [f"mean, {c}" for c in caps]
                                   + ["spread of means", "mean run spread", "largest run spread",
                                      f"results folder's interval ({config.method}, same scenes)", "inside?"],
                                   sum_rows)
    return (head + table + "\n## Means over the scenes\n\nEach setting's mean over scenes (each scene the mean over "
            "its seeds), beside the 95 % interval of the same mean from the results folder's runs (stratified "
            "bootstrap over seeds within each scene, the leaderboard's scheme): a setting inside it moves the "
            "mean by no more than the seeds already do.\n\n" + summary_table)


def kernel_spread_report(config: KernelSpreadConfig, log: Callable[[str], None] = print) -> Report:
    """Run (or read) every fit of :class:`KernelSpreadConfig` and write its report."""
    from benchmark.runner import resolve_scene

    check_config(config)
    out = Path(config.out)
    kept_dir = out / f"{config.name}-runs"
    kept_dir.mkdir(parents=True, exist_ok=True)
    runs = []
    for scene in config.scenes:
        for seed in config.seeds:
            scene_dir = resolve_scene(scene, Path(config.cache_dir), size=config.size, seed=seed, log=log)
            for cap in config.capabilities:
                kept = kept_dir / _kept_name(scene, seed, cap)
                doc = None
                if kept.is_file():
                    try:
                        doc = json.loads(kept.read_text())
                    except (OSError, ValueError):
                        doc = None  # damaged: fitted again
                    if doc is not None and not _matches(doc, config, seed, cap):
                        doc = None
                if doc is None:
                    doc = run_one(config, scene_dir, seed, cap, kept, log)
                runs.append(run_record(doc, scene, seed, cap, kept))
    folder = read_folder(config)
    summary = summarize(runs, config, folder)
    noise = noise_rows(runs, config, folder)
    doc = {"config": {**asdict(config), "out": str(config.out), "cache_dir": str(config.cache_dir),
                      "results_dir": None if config.results_dir is None else str(config.results_dir)},
           "runs": runs, "spread": spread_rows(runs), "summary": summary, "kernels_against_seeds": noise}
    table = spread_markdown(config, runs, summary) + noise_markdown(noise)
    if config.trace:
        t = config.trace_config
        scene_dir = resolve_scene(t.preset, Path(config.cache_dir), size=t.size, seed=t.seed, log=log)
        traces = {cap: run_trace(t, cap, scene_dir, out / f"{config.name}-trace" / f"{cap}.json", log)
                  for cap in CAPABILITIES}
        pairs = pairings(traces, t.jump)
        doc["trace"] = {"config": asdict(t), "kernels": {cap: tr.get("capability") for cap, tr in traces.items()},
                        "pairs": pairs}
        table += "\n\n" + trace_markdown(t, traces, pairs)
    paths = write_report(out, config.name, doc, table)
    for path in paths:
        log(f"wrote {path}")
    return Report(table, paths)
