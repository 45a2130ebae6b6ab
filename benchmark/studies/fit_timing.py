"""Fit time of a method, stage by stage, for two commits side by side on one machine in one run.

``bench4d ablate timing --baseline REV`` exports the commit ``REV`` (``git archive``, no ``.git``) into a
temporary folder and runs the same fit -- ``bench4d eval`` of one method on one scene with the same
options, single-threaded -- with that code and with the candidate's (the working tree, or
``--candidate REV``), alternating which goes first in each round, in fresh subprocesses whose
``PYTHONPATH`` is their own tree. Every run has a cache folder of its own, so nothing fitted is reused;
the scene is generated once by the candidate's code and read by both. The stage times are the ones each
results file records (:data:`STAGES`); per stage the report gives the median over rounds of both sides
and their ratio, new over old: a measurement of the two codes under the same load, not a comparison of
runs made on different days. It also lists the runs' scores, which a change of speed alone leaves alone
up to the fits' own noise.

Writes ``<out>/<name>.json`` and ``<out>/<name>.md`` (default ``reports/fit-timing/fit-timing``) atomically.
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
    scene: str = "split-cookie"
    """A synthetic preset (generated once, by the candidate's code) or a scene folder."""
    size: int = 128
    """Image size of a generated preset."""
    overrides: dict[str, str] = field(default_factory=dict)
    """Method options (``--set KEY=VALUE``) given to both sides, e.g. a shortened schedule."""
    rounds: int = 1
    """Runs per side; sides alternate which goes first from round to round."""
    seed: int = 0
    """The fit's seed."""
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
    stages: dict[str, Optional[float]]
    """Stage label -> seconds (:data:`STAGES`, :data:`CPU_STAGES`; ``None``: not recorded by that code)."""
    scores: dict[str, Optional[float]]
    process_cpu_seconds: float
    """CPU seconds of the whole ``bench4d eval`` process (supervision, fit, answers)."""
    process_wall_seconds: float
    results_file: str


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


def eval_command(config: TimingConfig, scene_dir: Path, cache: Path, results: Path,
                 python: str = sys.executable) -> list[str]:
    """The ``bench4d eval`` command line both sides run (in their own tree)."""
    cmd = [python, "-m", "benchmark.cli", "eval", "--method", config.method, "--scene", str(scene_dir),
           "--seed", str(config.seed), "--cache-dir", str(cache), "--results-dir", str(results), "--threads", "1",
           "--quiet"]
    for key, value in config.overrides.items():
        cmd += ["--set", f"{key}={value}"]
    return cmd


def read_run(results: Path, side: str, round_: int, cpu: float, wall: float) -> RunRecord:
    """The :class:`RunRecord` of the one results file under ``results``."""
    files = sorted(p for p in results.rglob("*.json") if p.parent.name != "ablations")
    if len(files) != 1:
        raise RuntimeError(f"expected one results file under {results}, found {len(files)}")
    doc = json.loads(files[0].read_text())
    stages = {label: _path(doc, *keys) for label, keys in STAGES + CPU_STAGES}
    scores = {label: _path(doc, *keys) for label, keys in SCORES}
    return RunRecord(side, round_, stages, scores, cpu, wall, str(files[0]))


def run_side(tree: Path, side: str, round_: int, config: TimingConfig, scene_dir: Path, work: Path,
             log: Callable[[str], None]) -> RunRecord:
    """One fit with the code of ``tree`` in a subprocess; its CPU time from the children's usage."""
    run_dir = work / f"{side}-round{round_}"
    cache, results = run_dir / "cache", run_dir / "results"
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    cmd = eval_command(config, scene_dir, cache, results)
    log(f"round {round_}: {side} ({tree})")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(cmd, cwd=str(tree), env=env, capture_output=True, text=True, timeout=config.timeout)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise RuntimeError(f"the {side} fit failed (exit {done.returncode}): {done.stderr.strip()[-3000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return read_run(results, side, round_, cpu, wall)


def _median(values: Sequence[Optional[float]]) -> Optional[float]:
    got = [v for v in values if v is not None]
    return statistics.median(got) if got else None


def summarize(runs: Sequence[RunRecord]) -> list[dict]:
    """Per stage (:data:`STAGES`, :data:`CPU_STAGES`, then the processes'): the median seconds of each side
    over its runs and ``ratio`` = candidate / baseline (``speedup`` its inverse); ``None`` where a side
    did not record the stage."""
    labels = [label for label, _ in STAGES + CPU_STAGES] + ["process CPU (whole eval)", "process wall (whole eval)"]

    def value(run: RunRecord, label: str) -> Optional[float]:
        if label == "process CPU (whole eval)":
            return run.process_cpu_seconds
        if label == "process wall (whole eval)":
            return run.process_wall_seconds
        return run.stages.get(label)

    rows = []
    for label in labels:
        old = _median([value(r, label) for r in runs if r.side == "baseline"])
        new = _median([value(r, label) for r in runs if r.side == "candidate"])
        ratio = new / old if old and new is not None else None
        rows.append({"stage": label, "baseline_seconds": old, "candidate_seconds": new, "ratio": ratio,
                     "speedup": (1.0 / ratio) if ratio else None})
    return rows


def _cell(value: Optional[float], digits: int = 1) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def timing_markdown(config: TimingConfig, commits: dict[str, str], rows: Sequence[dict],
                    runs: Sequence[RunRecord]) -> str:
    """The report's Markdown: the stage table, then every run's scores."""
    head = (f"# Fit time side by side: {config.method} on {config.scene} ({config.size} px)\n\n"
            f"Baseline `{commits['baseline']}`, candidate `{commits['candidate']}`; {config.rounds} round(s), "
            f"sides alternating, one thread each, run one after the other on this machine. Options: "
            f"{', '.join(f'`{k}={v}`' for k, v in config.overrides.items()) or 'the method defaults'}.\n"
            f"Seconds are medians over the rounds (wall time as each fit recorded it, unless marked CPU); "
            f"ratio = candidate / baseline.\n\n")
    table = markdown_table(["stage", "baseline s", "candidate s", "ratio", "speed-up"],
                           [[r["stage"], _cell(r["baseline_seconds"]), _cell(r["candidate_seconds"]),
                             _cell(r["ratio"], 3), _cell(r["speedup"], 2)] for r in rows])
    score_labels = [label for label, _ in SCORES]
    score_rows = [[r.side, str(r.round)] + [_cell(r.scores.get(k), 2) for k in score_labels] for r in runs]
    scores = markdown_table(["side", "round"] + score_labels, score_rows)
    return head + table + "\n## Scores of the runs\n\n" + scores


def fit_timing_report(config: TimingConfig, *, log: Callable[[str], None] = lambda m: None,
                      repo: Path = REPO) -> Report:
    """Run the comparison of :class:`TimingConfig` and write its report."""
    from benchmark.runner import resolve_scene

    if config.rounds < 1:
        raise InputError(None, "--rounds", f"must be >= 1, got {config.rounds}")
    commits = {"baseline": resolve_commit(config.baseline, repo)}
    commits["candidate"] = resolve_commit(config.candidate, repo) if config.candidate else "working tree"
    if config.candidate is None:
        head = resolve_commit("HEAD", repo)
        dirty = bool(_git("status", "--porcelain", "--untracked-files=no", repo=repo).stdout.strip())
        commits["candidate"] = f"working tree at {head}" + (" (with uncommitted changes)" if dirty else "")
    scene_dir = resolve_scene(config.scene, Path(config.cache_dir), size=config.size, log=log)
    runs: list[RunRecord] = []
    with tempfile.TemporaryDirectory(prefix="bench4d-fit-timing-") as tmp:
        work = Path(tmp)
        trees = {"baseline": export_commit(commits["baseline"], work / "baseline-code", repo)}
        trees["candidate"] = (export_commit(commits["candidate"], work / "candidate-code", repo) if config.candidate
                              else repo)
        for r in range(config.rounds):
            order = ("baseline", "candidate") if r % 2 == 0 else ("candidate", "baseline")
            for side in order:
                runs.append(run_side(trees[side], side, r, config, scene_dir, work, log))
    rows = summarize(runs)
    doc = {"config": {**asdict(config), "cache_dir": str(config.cache_dir), "out": str(config.out)},
           "commits": commits, "scene_dir": str(scene_dir), "stages": rows,
           "runs": [asdict(r) for r in runs],
           "machine": {"cpu_count": os.cpu_count(), "load_average": list(os.getloadavg()),
                       "python": sys.version.split()[0]}}
    table = timing_markdown(config, commits, rows, runs)
    return Report(table, write_report(Path(config.out), config.name, doc, table))
