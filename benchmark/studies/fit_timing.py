"""Fit time of a method, stage by stage, for two commits side by side on one machine in one run.

``bench4d ablate timing --baseline REV`` exports the commit ``REV`` (``git archive``, no ``.git``) into a
temporary folder and runs the same fits -- ``bench4d eval`` of one method on each scene and seed with the
same options, single-threaded -- with that code and with the candidate's (the working tree, or
``--candidate REV``), one after the other in fresh subprocesses whose ``PYTHONPATH`` is their own tree,
alternating which side goes first. Every run has a cache folder of its own, so nothing fitted is reused;
each scene is generated once per seed by the candidate's code (generator seed = fit seed) and read by both. The stage times are the ones each
results file records (:data:`STAGES`); per stage the report gives both sides' time (per scene and seed
the median over rounds, then the mean over scenes and seeds) and their ratio, new over old: a
measurement of the two codes under the same load, not a comparison of runs made on different days. It
also lists every scene and seed's scores on both sides, which a change of speed alone moves only by the
fits' own noise (the spread between seeds is given beside them).

Writes ``<out>/<name>.json``, ``<out>/<name>.md`` (default ``reports/fit-timing/fit-timing``) and every
run's results file under ``<out>/<name>-runs/`` atomically.
"""

from __future__ import annotations

import io
import json
import os
import resource
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from benchmark.core.errors import InputError

from ._report import Report, markdown_table, write_report

REPORTS = Path("reports/fit-timing")
"""Default output folder."""

REPO = Path(__file__).resolve().parents[2]
"""The checkout this module belongs to: the candidate's code by default."""


def _path(doc: dict, *keys: Any) -> Optional[float]:
    """``doc[k1][k2]...`` as a float, ``None`` where a key is missing or the value is not a number."""
    node: Any = doc
    for key in keys:
        if isinstance(node, dict) and key in node:
            node = node[key]
        elif isinstance(node, list) and isinstance(key, str):  # a list of stages, found by name
            node = next((s for s in node if isinstance(s, dict) and s.get("stage") == key), None)
            if node is None:
                return None
        else:
            return None
    return float(node) if isinstance(node, (int, float)) and not isinstance(node, bool) else None


STAGES: tuple[tuple[str, tuple], ...] = (
    ("geometry: static stage", ("fit", "info", "geometry", "stages", "static", "seconds")),
    ("geometry: deformation stage", ("fit", "info", "geometry", "stages", "deformation", "seconds")),
    ("geometry: whole (with set-up and held-out PSNR)", ("fit", "info", "geometry", "session_seconds")),
    ("autoencoder", ("fit", "info", "autoencoder", "seconds")),
    ("language field", ("fit", "info", "field", "seconds")),
    ("time-varying: captions", ("fit", "info", "time_varying", "captioning", "seconds")),
    ("time-varying: caption autoencoder", ("fit", "info", "time_varying", "autoencoder", "seconds")),
    ("time-varying: blend operators", ("fit", "info", "time_varying", "blend_operators", "seconds")),
    ("time-varying: static field", ("fit", "info", "time_varying", "static_field", "seconds")),
    ("time-varying: status field", ("fit", "info", "time_varying", "train", "seconds")),
    ("time-varying: whole", ("fit", "info", "time_varying", "seconds")),
    ("whole fit", ("timing", "fit_seconds")),
)
"""(label, path in a results file) of every stage timed: wall seconds as the fit recorded them."""

CPU_STAGES: tuple[tuple[str, tuple], ...] = (
    ("geometry: static stage (CPU)", ("fit", "info", "geometry", "stages", "static", "cpu_seconds")),
    ("geometry: deformation stage (CPU)", ("fit", "info", "geometry", "stages", "deformation", "cpu_seconds")),
)
"""Stages whose CPU seconds the results file records too (less sensitive to a busy machine)."""

SCORES: tuple[tuple[str, tuple], ...] = (
    ("mIoU", ("metrics", "mIoU")),
    ("Acc", ("metrics", "Acc")),
    ("vIoU", ("metrics", "vIoU")),
    ("held-out PSNR (dB)", ("fit", "info", "geometry", "test_psnr")),
    ("Gaussians", ("fit", "info", "geometry", "gaussians")),
)
"""Scores and sizes listed beside the times (a faster fit should not move them beyond its noise)."""


@dataclass
class TimingConfig:
    """What to time, and how."""

    baseline: str
    """The old commit (any ``git rev-parse`` name: ``HEAD~3``, a hash, a branch)."""
    candidate: Optional[str] = None
    """The new commit; ``None``: the working tree of this checkout as it is."""
    method: str = "4d-langsplat"
    """The method fitted."""
    scenes: tuple[str, ...] = ("split-cookie",)
    """Synthetic presets (generated once per seed, by the candidate's code, with generator seed = the fit's
    seed) or scene folders."""
    size: int = 128
    """Image size of a generated preset."""
    overrides: dict[str, str] = field(default_factory=dict)
    """Method options (``--set KEY=VALUE``) given to both sides, e.g. a shortened schedule."""
    candidate_overrides: dict[str, str] = field(default_factory=dict)
    """Method options (``--candidate-set KEY=VALUE``) of the candidate side only, after ``overrides``: a
    config change timed together with the code's."""
    rounds: int = 1
    """Runs per side; sides alternate which goes first from round to round."""
    seeds: tuple[int, ...] = (0,)
    """The fits' seeds (every scene with every seed)."""
    cache_dir: Path = Path("cache")
    """Where a generated preset is kept (fits never are: each run gets a cache of its own)."""
    timeout: float = 4 * 3600.0
    """Seconds one run may take before it counts as failed."""
    name: str = "fit-timing"
    """Output file stem."""
    out: Path = REPORTS
    """Output folder."""


@dataclass
class RunRecord:
    """One timed fit."""

    side: str
    """``"baseline"`` or ``"candidate"``."""
    round: int
    scene: str
    seed: int
    stages: dict[str, Optional[float]]
    """Stage label -> seconds (:data:`STAGES`, :data:`CPU_STAGES`; ``None``: not recorded by that code)."""
    scores: dict[str, Optional[float]]
    process_cpu_seconds: float
    """CPU seconds of the whole ``bench4d eval`` process (supervision, fit, answers)."""
    process_wall_seconds: float
    results_file: str
    """The run's results file (relative to the report's folder once kept there)."""
    track: Optional[str] = None
    """The supervision track the run was scored on (its results file's)."""


def _git(*args: str, repo: Path = REPO) -> subprocess.CompletedProcess:
    return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, timeout=600)


def resolve_commit(rev: str, repo: Path = REPO) -> str:
    """The full hash of ``rev`` in ``repo``; :class:`InputError` when it names no commit."""
    done = _git("rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}", repo=repo)
    if done.returncode != 0:
        raise InputError(repo, "--baseline/--candidate", f"{rev!r} names no commit of this repository")
    return done.stdout.decode().strip()


def export_commit(commit: str, dest: Path, repo: Path = REPO) -> Path:
    """The files of ``commit`` (as ``git archive`` gives them) extracted into ``dest``."""
    done = _git("archive", "--format=tar", commit, repo=repo)
    if done.returncode != 0:
        raise InputError(repo, "git archive", done.stderr.decode(errors="replace").strip())
    dest.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(done.stdout)) as archive:
        try:
            archive.extractall(dest, filter="data")
        except TypeError:  # Python before the extraction filters (3.10.11, 3.11.3): git's own archive
            archive.extractall(dest)
    return dest


def side_overrides(config: TimingConfig, side: str) -> dict[str, str]:
    """The method options of ``side``: ``overrides``, and for the candidate ``candidate_overrides`` over them."""
    return {**config.overrides, **(config.candidate_overrides if side == "candidate" else {})}


def eval_command(config: TimingConfig, scene_dir: Path, seed: int, cache: Path, results: Path,
                 python: str = sys.executable, side: str = "baseline") -> list[str]:
    """The ``bench4d eval`` command line ``side`` runs (in its own tree)."""
    cmd = [python, "-m", "benchmark.cli", "eval", "--method", config.method, "--scene", str(scene_dir),
           "--seed", str(seed), "--cache-dir", str(cache), "--results-dir", str(results), "--threads", "1",
           "--quiet"]
    for key, value in side_overrides(config, side).items():
        cmd += ["--set", f"{key}={value}"]
    return cmd


def read_run(results: Path, side: str, round_: int, cpu: float, wall: float, scene: str = "",
             seed: int = 0) -> RunRecord:
    """The :class:`RunRecord` of the one results file under ``results``."""
    files = sorted(p for p in results.rglob("*.json") if p.parent.name != "ablations")
    if len(files) != 1:
        raise RuntimeError(f"expected one results file under {results}, found {len(files)}")
    doc = json.loads(files[0].read_text())
    stages = {label: _path(doc, *keys) for label, keys in STAGES + CPU_STAGES}
    scores = {label: _path(doc, *keys) for label, keys in SCORES}
    return RunRecord(side, round_, scene, seed, stages, scores, cpu, wall, str(files[0]), doc.get("track"))


def run_side(tree: Path, side: str, round_: int, config: TimingConfig, scene: str, scene_dir: Path, seed: int,
             work: Path, log: Callable[[str], None]) -> RunRecord:
    """One fit with the code of ``tree`` in a subprocess; its CPU time from the children's usage."""
    run_dir = work / f"{side}-{Path(scene).name}-seed{seed}-round{round_}"
    cache, results = run_dir / "cache", run_dir / "results"
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    cmd = eval_command(config, scene_dir, seed, cache, results, side=side)
    log(f"round {round_}: {side}, {scene} seed {seed} ({tree})")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(cmd, cwd=str(tree), env=env, capture_output=True, text=True, timeout=config.timeout)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise RuntimeError(f"the {side} fit failed (exit {done.returncode}): {done.stderr.strip()[-3000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return read_run(results, side, round_, cpu, wall, scene, seed)


def _median(values: Sequence[Optional[float]]) -> Optional[float]:
    got = [v for v in values if v is not None]
    return statistics.median(got) if got else None


PROCESS_CPU = "process CPU (whole eval)"
PROCESS_WALL = "process wall (whole eval)"


def _value(run: RunRecord, label: str) -> Optional[float]:
    if label == PROCESS_CPU:
        return run.process_cpu_seconds
    if label == PROCESS_WALL:
        return run.process_wall_seconds
    return run.stages.get(label)


def _side_time(runs: Sequence[RunRecord], side: str, label: str) -> Optional[float]:
    """Per (scene, seed) the median over rounds, then the mean over them; ``None`` where none recorded it."""
    configs = sorted({(r.scene, r.seed) for r in runs})
    per_config = [_median([_value(r, label) for r in runs if r.side == side and (r.scene, r.seed) == key])
                  for key in configs]
    got = [v for v in per_config if v is not None]
    return sum(got) / len(got) if got else None


def summarize(runs: Sequence[RunRecord]) -> list[dict]:
    """Per stage (:data:`STAGES`, :data:`CPU_STAGES`, then the processes'): each side's seconds (per scene and
    seed the median over rounds, then the mean over scenes and seeds) and ``ratio`` = candidate / baseline
    (``speedup`` its inverse); ``None`` where a side did not record the stage."""
    rows = []
    for label in [label for label, _ in STAGES + CPU_STAGES] + [PROCESS_CPU, PROCESS_WALL]:
        old, new = _side_time(runs, "baseline", label), _side_time(runs, "candidate", label)
        ratio = new / old if old and new is not None else None
        rows.append({"stage": label, "baseline_seconds": old, "candidate_seconds": new, "ratio": ratio,
                     "speedup": (1.0 / ratio) if ratio else None})
    return rows


def score_rows(runs: Sequence[RunRecord]) -> list[dict]:
    """Per scene, seed and score (:data:`SCORES`): both sides' values (median over rounds) and new - old."""
    out = []
    for scene, seed in sorted({(r.scene, r.seed) for r in runs}):
        for label, _ in SCORES:
            old = _median([r.scores.get(label) for r in runs if r.side == "baseline" and (r.scene, r.seed) == (scene, seed)])
            new = _median([r.scores.get(label) for r in runs if r.side == "candidate" and (r.scene, r.seed) == (scene, seed)])
            out.append({"scene": scene, "seed": seed, "score": label, "baseline": old, "candidate": new,
                        "difference": None if old is None or new is None else new - old})
    return out


def score_summary(rows: Sequence[dict]) -> list[dict]:
    """Per score: the mean and range of new - old over scenes and seeds, beside the seed-to-seed spread of
    each side (per scene the largest minus the smallest seed's value, averaged over scenes): a speed change
    moves scores by about their spread between seeds, not beyond."""
    out = []
    for label, _ in SCORES:
        mine = [r for r in rows if r["score"] == label]
        diffs = [r["difference"] for r in mine if r["difference"] is not None]
        spread = {}
        for side in ("baseline", "candidate"):
            per_scene = []
            for scene in sorted({r["scene"] for r in mine}):
                values = [r[side] for r in mine if r["scene"] == scene and r[side] is not None]
                if len(values) > 1:
                    per_scene.append(max(values) - min(values))
            spread[side] = sum(per_scene) / len(per_scene) if per_scene else None
        out.append({"score": label, "mean_difference": sum(diffs) / len(diffs) if diffs else None,
                    "min_difference": min(diffs) if diffs else None, "max_difference": max(diffs) if diffs else None,
                    "baseline_seed_spread": spread["baseline"], "candidate_seed_spread": spread["candidate"]})
    return out


def _cell(value: Optional[float], digits: int = 1) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def timing_markdown(config: TimingConfig, commits: dict[str, str], rows: Sequence[dict],
                    runs: Sequence[RunRecord]) -> str:
    """The report's Markdown: the stage table, then the scores of every scene and seed."""
    scenes = ", ".join(Path(s).name for s in config.scenes)
    head = (f"# Fit time side by side: {config.method} on {scenes} ({config.size} px), seeds "
            f"{', '.join(map(str, config.seeds))}\n\n"
            f"Baseline `{commits['baseline']}`, candidate `{commits['candidate']}`; {config.rounds} round(s), "
            f"sides alternating, one thread each, run one after the other on this machine. Options: "
            f"{', '.join(f'`{k}={v}`' for k, v in config.overrides.items()) or 'the method defaults'}"
            + (f"; the candidate's own: {', '.join(f'`{k}={v}`' for k, v in config.candidate_overrides.items())}"
               if config.candidate_overrides else "") + ".\n"
            "Seconds: per scene and seed the median over rounds, then the mean over scenes and seeds (wall time as "
            "each fit recorded it, unless marked CPU); ratio = candidate / baseline.\n\n")
    table = markdown_table(["stage", "baseline s", "candidate s", "ratio", "speed-up"],
                           [[r["stage"], _cell(r["baseline_seconds"]), _cell(r["candidate_seconds"]),
                             _cell(r["ratio"], 3), _cell(r["speedup"], 2)] for r in rows])
    scores = score_rows(runs)
    tracks = sorted({r.track for r in runs if r.track}) or ["unrecorded"]
    score_table = markdown_table(["scene", "seed", "score", "baseline", "candidate", "new - old"],
                                 [[Path(r["scene"]).name, str(r["seed"]), r["score"], _cell(r["baseline"], 2),
                                   _cell(r["candidate"], 2), _cell(r["difference"], 2)] for r in scores])
    summary = markdown_table(["score", "mean new - old", "min", "max", "seed spread (old)", "seed spread (new)"],
                             [[r["score"], _cell(r["mean_difference"], 2), _cell(r["min_difference"], 2),
                               _cell(r["max_difference"], 2), _cell(r["baseline_seed_spread"], 2),
                               _cell(r["candidate_seed_spread"], 2)] for r in score_summary(scores)])
    return (head + table + f"\n## Scores ({', '.join(tracks)} track)\n\n" + score_table + "\nAcross scenes and seeds (seed spread: per scene the "
            "largest minus the smallest seed's value, averaged over scenes):\n\n" + summary)


def fit_timing_report(config: TimingConfig, *, log: Callable[[str], None] = lambda m: None,
                      repo: Path = REPO) -> Report:
    """Run the comparison of :class:`TimingConfig` and write its report."""
    from benchmark.core.atomic import write_bytes
    from benchmark.runner import resolve_scene

    if config.rounds < 1:
        raise InputError(None, "--rounds", f"must be >= 1, got {config.rounds}")
    if not config.scenes or not config.seeds:
        raise InputError(None, "--scenes/--seeds", "need at least one scene and one seed")
    commits = {"baseline": resolve_commit(config.baseline, repo)}
    commits["candidate"] = resolve_commit(config.candidate, repo) if config.candidate else "working tree"
    if config.candidate is None:
        head = resolve_commit("HEAD", repo)
        dirty = bool(_git("status", "--porcelain", "--untracked-files=no", repo=repo).stdout.strip())
        commits["candidate"] = f"working tree at {head}" + (" (with uncommitted changes)" if dirty else "")
    configs = [(scene, seed) for scene in config.scenes for seed in config.seeds]
    # seed s fits scene seed s, as every run of the benchmark does (a scene folder is read as it is)
    scene_dirs = {(scene, seed): resolve_scene(scene, Path(config.cache_dir), size=config.size, seed=seed, log=log)
                  for scene, seed in configs}
    runs: list[RunRecord] = []
    out = Path(config.out)
    kept = out / f"{config.name}-runs"
    with tempfile.TemporaryDirectory(prefix="bench4d-fit-timing-") as tmp:
        work = Path(tmp)
        trees = {"baseline": export_commit(commits["baseline"], work / "baseline-code", repo)}
        trees["candidate"] = (export_commit(commits["candidate"], work / "candidate-code", repo) if config.candidate
                              else repo)
        for r in range(config.rounds):
            for i, (scene, seed) in enumerate(configs):
                order = ("baseline", "candidate") if (r + i) % 2 == 0 else ("candidate", "baseline")
                for side in order:
                    run = run_side(trees[side], side, r, config, scene, scene_dirs[scene, seed], seed, work, log)
                    # the results file outlives the temporary folder, beside the report
                    target = kept / f"{side}-{Path(scene).name}-seed{seed}-round{r}.json"
                    write_bytes(target, Path(run.results_file).read_bytes())
                    run.results_file = str(target.relative_to(out))  # beside the report, wherever it moves
                    runs.append(run)
    rows = summarize(runs)
    doc = {"config": {**asdict(config), "cache_dir": str(config.cache_dir), "out": str(config.out)},
           "commits": commits, "scene_dirs": {k: str(v) for k, v in scene_dirs.items()}, "stages": rows,
           "scores": score_rows(runs), "score_summary": score_summary(score_rows(runs)),
           "runs": [asdict(r) for r in runs],
           "machine": {"cpu_count": os.cpu_count(), "load_average": list(os.getloadavg()),
                       "python": sys.version.split()[0]}}
    table = timing_markdown(config, commits, rows, runs)
    return Report(table, write_report(out, config.name, doc, table))
