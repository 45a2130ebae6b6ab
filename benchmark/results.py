"""Run results files: the schema, atomic writing, reading, and tables over many runs.

One file per run, ``<results>/<dataset>/<scene>/<method>/<track>/seed<N>.json`` for the ``paper`` evaluation
split and ``<results>/<dataset>/<scene>/<method>/<track>/<split>/seed<N>.json`` for another (``novel-view``),
so both splits of one (scene, method, track, seed) sit side by side (:func:`results_path`; written by
:func:`benchmark.runner.evaluate`), each beside its predictions folder ``seed<N>.predictions/``. Writers of
one file take turns (:func:`results_lock`); a file being replaced goes to ``<results>/archive/`` first.
Files written before evaluation splits existed record none: they are read as :data:`LEGACY_EVAL_SPLIT`
(``legacy-dense``, the old split that trained on three frames of every four).

Schema: :class:`RunResults` (``"format": "bench4d-run"``, ``"version": 1``), one typed record per
object of the file, each field with its meaning; metrics in percent, times in seconds, memory in MiB,
``null`` = not applicable. :func:`write_results` checks a document against it before writing, and
:func:`read_results` after reading: a file that does not match is an :class:`InputError` naming the
first wrong, missing or unknown field.

:func:`runs_table` flattens files into one row per run; :func:`seed_summary` gives mean, std and
count over seeds per (dataset, track, method, scene), plus a ``"mean"`` scene that averages the
scenes of each seed first (the dataset number), then over seeds.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import shutil
import types
from pathlib import Path
from typing import (Any, Iterable, Iterator, Literal, NotRequired, Optional, TypedDict, Union, get_args, get_origin,
                    get_type_hints)

import numpy as np
import pandas as pd

from benchmark.core.atomic import read_json, write_json, write_text
from benchmark.core.errors import InputError, short_repr
from benchmark.core.scene import DEFAULT_EVAL_SPLIT, EVAL_SPLITS, LEGACY_EVAL_SPLIT, EvalSplit

RESULTS_FORMAT = "bench4d-run"
RESULTS_VERSION = 1
ACCURACY_METRICS: dict[str, tuple[str, str]] = {"agnostic": ("mIoU", "mAcc"), "sensitive": ("Acc", "vIoU")}
"""Query kind -> its two reported metrics (percent, higher is better)."""
DIAGNOSTIC_METRICS = ("AUC", "nearTau")
"""Diagnostics of the time-sensitive decisions (percent; :mod:`benchmark.metrics.temporal`): the
scores' ROC AUC against the labels, and the share of decisions near the threshold."""
RUN_COLUMNS = ["dataset", "track", "protocol", "split", "method", "scene", "seed", "scene_seed", "mIoU", "mAcc", "Acc",
               "vIoU", *DIAGNOSTIC_METRICS, "fps_agnostic", "fps_sensitive", "fit_seconds", "peak_cpu_mib",
               "peak_gpu_mib", "peak_cpu_needed_mib", "peak_gpu_needed_mib", "peak_measured", "device",
               "cpu_model", "cpu_capability", "gpu", "machine_kind",
               "git_commit", "git_dirty", "scene_digest", "scene_current", "draft_queries", "path"]
RUN_KEYS = ["dataset", "track", "protocol", "split", "method", "scene", "seed"]
"""What identifies a run in :func:`runs_table`: two files with the same values are an error."""
UNKNOWN_MACHINE = "unknown"
"""``machine_kind`` of a run that recorded neither a GPU nor a CPU model."""
VALUE_COLUMNS = ["mIoU", "mAcc", "Acc", "vIoU", *DIAGNOSTIC_METRICS, "fps_agnostic", "fps_sensitive", "fit_seconds",
                 "peak_cpu_mib", "peak_gpu_mib", "peak_cpu_needed_mib", "peak_gpu_needed_mib"]
MEAN_SCENE = "mean"
"""Scene label of the dataset-level row in :func:`seed_summary`."""


# -- the schema --------------------------------------------------------------------------------------
# A results file is a JSON object; each TypedDict below is one object of it. NotRequired fields may be
# absent (files written before the field existed lack it); Optional ones may be null. Free-form objects
# (a method's config, the supervision's description, the protocol) are typed ``dict[str, Any]``: their
# own modules define them. :func:`check_results` checks a document against :class:`RunResults`.
class GitState(TypedDict):
    """The checkout the run's command started on."""

    commit: Optional[str]
    """HEAD's commit id; null outside a git checkout."""
    dirty: Optional[bool]
    """Whether the code (not results or reports) had tracked changes; null outside a git checkout."""


class QueryTiming(TypedDict):
    """Per-frame time of one query kind (:func:`benchmark.runner.time_queries`)."""

    query: NotRequired[str]
    """The query text timed."""
    frames: NotRequired[int]
    """Frames timed."""
    repeats: NotRequired[int]
    """Timed calls per frame, after one warm-up call."""
    seconds_per_frame: NotRequired[Optional[float]]
    """Median seconds of one single-frame call."""
    fps: NotRequired[Optional[float]]
    """Frames per second: the inverse of ``seconds_per_frame``."""
    min_seconds: NotRequired[Optional[float]]
    """Fastest timed call."""
    max_seconds: NotRequired[Optional[float]]
    """Slowest timed call."""


class Timing(TypedDict):
    """Seconds the run took."""

    fit_seconds: NotRequired[Optional[float]]
    """The fit's own seconds (a cached fit: as it recorded them)."""
    fit_cached: NotRequired[bool]
    """Whether the fit was loaded from the cache."""
    answer_all_seconds: NotRequired[Optional[float]]
    """Answering every query on every evaluated frame, text encoding included."""
    note: NotRequired[str]
    """How the query times were taken."""
    query_agnostic: NotRequired[QueryTiming]
    """Time of a time-agnostic query."""
    query_sensitive: NotRequired[QueryTiming]
    """Time of a time-sensitive query (absent when the method answers none)."""


class Metrics(TypedDict):
    """The run's scores in percent (null: no query of that kind was scored), and what they count."""

    mIoU: NotRequired[Optional[float]]
    """Mean IoU of the time-agnostic queries asked, an unanswered one counting 0 (files written before
    coverage was recorded: of the answered ones)."""
    mAcc: NotRequired[Optional[float]]
    """Mean pixel accuracy of the time-agnostic queries asked, an unanswered one counting 0."""
    Acc: NotRequired[Optional[float]]
    """Temporal accuracy of the time-sensitive queries asked, an unanswered one counting 0."""
    vIoU: NotRequired[Optional[float]]
    """Video IoU of the time-sensitive queries asked, an unanswered one counting 0."""
    mIoU_answered: NotRequired[Optional[float]]
    """Mean IoU of the answered time-agnostic queries only."""
    mAcc_answered: NotRequired[Optional[float]]
    """Mean pixel accuracy of the answered time-agnostic queries only."""
    Acc_answered: NotRequired[Optional[float]]
    """Temporal accuracy of the answered time-sensitive queries only."""
    vIoU_answered: NotRequired[Optional[float]]
    """Video IoU of the answered time-sensitive queries only."""
    absentFP: NotRequired[Optional[float]]
    """Share of the absent (time-agnostic query, frame) pairs with a non-empty predicted mask (null: none)."""
    absent_frames: NotRequired[int]
    """Absent (time-agnostic query, frame) pairs: evaluated frames where the query's object is absent."""
    answered_agnostic_queries: NotRequired[int]
    """Time-agnostic queries answered and scored."""
    asked_agnostic_queries: NotRequired[int]
    """Time-agnostic queries asked: answered, or declared unanswered, with a scored frame."""
    answered_sensitive_queries: NotRequired[int]
    """Time-sensitive queries answered and scored."""
    asked_sensitive_queries: NotRequired[int]
    """Time-sensitive queries asked: answered, or declared unanswered, with a scored frame."""
    AUC: NotRequired[Optional[float]]
    """Diagnostic: ROC AUC of the time-sensitive scores (absent: computed from the frames, :func:`temporal_diagnostics`)."""
    nearTau: NotRequired[Optional[float]]
    """Diagnostic: share of time-sensitive decisions near the threshold."""
    agnostic_queries: NotRequired[int]
    """Time-agnostic queries scored."""
    sensitive_queries: NotRequired[int]
    """Time-sensitive queries scored."""
    frames_scored: NotRequired[int]
    """(query, frame) pairs scored."""
    scenes: NotRequired[int]
    """Scenes averaged (one per run)."""


class Memory(TypedDict):
    """Peak memory in MiB (null: nothing ran on that device)."""

    peak_cpu_mib: NotRequired[Optional[float]]
    """High-water resident memory of the run."""
    peak_cpu_fit_mib: NotRequired[Optional[float]]
    """The fit's own peak (a cached fit: as it recorded it)."""
    baseline_cpu_fit_mib: NotRequired[Optional[float]]
    """Resident memory when the fit began (its peak less this: what the fit itself added)."""
    peak_gpu_mib: NotRequired[Optional[float]]
    """Peak CUDA memory of the run."""
    peak_gpu_fit_mib: NotRequired[Optional[float]]
    """The fit's own peak CUDA memory."""
    peak_window: NotRequired[Literal["run", "process"]]
    """``run``: the peaks are this run's alone; ``process``: the process's so far (absent: the latter)."""
    peak_fit_window: NotRequired[Literal["run", "process"]]
    """The same for the fit's peaks."""
    note: NotRequired[str]
    """How the peaks were taken."""


class FitSummary(TypedDict):
    """The fit the run answered with."""

    key: str
    """Its cache key (folder name under ``<cache>/fits/<method>/<dataset>-<scene>/``)."""
    cached: NotRequired[bool]
    """Whether it was loaded from the cache."""
    code_version: NotRequired[str]
    """The digest of the method's code at the run (:meth:`methods.registry.MethodSpec.code_digest`)."""
    head_refit_of: NotRequired[str]
    """Key of the cached fit whose time-varying head alone this fit made anew."""
    info: NotRequired[Optional[dict[str, Any]]]
    """What the model describes of itself (stages, their seconds and peaks: :data:`FIT_STAGES`)."""


class Environment(TypedDict):
    """Where and on what code the run ran."""

    packages: NotRequired[dict[str, str]]
    """Versions of Python, bench4d and the packages that matter (:data:`benchmark.runner.PACKAGES`)."""
    git: NotRequired[GitState]
    """The checkout as the command started."""
    code_changed_during_run: NotRequired[Optional[bool]]
    """Whether the code differed at the run's end; null: unknown."""
    device: NotRequired[str]
    """The device asked for (``cpu``, ``cuda:0``)."""
    platform: NotRequired[str]
    """Operating system and its version."""
    machine: NotRequired[str]
    """CPU architecture."""
    cpu_count: NotRequired[Optional[int]]
    """Logical CPU cores of the machine."""
    processor: NotRequired[Optional[str]]
    """CPU model name; null when it cannot be read."""
    numpy_blas_core: NotRequired[Optional[str]]
    """The kernel set numpy's OpenBLAS runs (generated pixels depend on it); null: another BLAS."""
    cpu_capability: NotRequired[Optional[str]]
    """The instruction set torch's CPU kernels dispatch to (``torch.backends.cpu.get_cpu_capability()``:
    ``DEFAULT``, ``AVX2``, ``AVX512``; ``ATEN_CPU_CAPABILITY`` lowers it): fitted numbers move with it.
    Null: torch was not installed. Absent: written before it was recorded."""
    native_kernels: NotRequired[str]
    """``loaded``: the Gaussian core's compiled CPU kernels ran; ``not used: <why>``: the PyTorch passes did
    (float rounding differs between the two). Absent: written before it was recorded."""
    gpu: NotRequired[Optional[str]]
    """Name of the CUDA device; null off CUDA (absent in files written before: off CUDA too)."""
    torch_threads: NotRequired[Optional[int]]
    """torch's intra-op threads; null where torch was not loaded."""
    concurrent_runs: NotRequired[int]
    """Runs sharing the machine at the time (inflates the timings)."""


class GeneratedScene(TypedDict):
    """Which version of a generated scene a run measured (:func:`benchmark.synthetic.digest.scene_version`)."""

    preset: NotRequired[Optional[str]]
    """The preset it was generated from."""
    size: NotRequired[Optional[int]]
    """Image width in pixels."""
    seed: NotRequired[int]
    """The generator seed (the scene instance)."""
    generator_version: NotRequired[Optional[str]]
    """The generator's version string."""
    digest: NotRequired[str]
    """Content digest of the scene folder."""
    committed_digest: NotRequired[Optional[str]]
    """The digest the committed generator makes for (preset, size, seed); null: none committed."""
    perturbation: NotRequired[Optional[dict[str, Any]]]
    """The stress-suite knob it was generated with; null: the clean preset."""
    current: NotRequired[Optional[bool]]
    """Whether ``digest`` is ``committed_digest``; null: none committed."""


class SceneInfo(TypedDict):
    """The scene folder the run read."""

    root: NotRequired[str]
    """Its path."""
    summary: NotRequired[str]
    """Frames, cameras, resolution."""
    annotations: NotRequired[Optional[str]]
    """The ground-truth file; null for truth made from the alpha masks."""
    scale: NotRequired[Optional[float]]
    """Resolution multiplier it was loaded at; null: full size."""
    generated: NotRequired[Optional[GeneratedScene]]
    """Preset, size, seed and digest of a generated scene (:func:`scene_status`); null for others."""
    draft_queries: NotRequired[list[str]]
    """Scored queries whose ground truth is an unreviewed draft (``review: "draft"``, or the base of a
    time-sensitive query is): they count in the metrics, and the leaderboard names them."""


class Scores(TypedDict):
    """Scores per query and per frame (fractions per frame, percent per query)."""

    queries: NotRequired[list[dict[str, Any]]]
    """One row per scored query."""
    skipped: NotRequired[list[dict[str, Any]]]
    """Queries not scored: no evaluated frame."""
    frames: NotRequired[list[dict[str, Any]]]
    """One record per (query, frame); stored as a ``{"columns", "rows"}`` table."""
    frames_dropped: NotRequired[int]
    """How many per-frame records :func:`slim_results` removed (the metrics and per-query scores stay)."""


class RunResults(TypedDict):
    """One results file (``format`` and ``version`` are added by :func:`write_results`)."""

    format: Literal["bench4d-run"]
    """Always :data:`RESULTS_FORMAT`."""
    version: int
    """Schema version, 1 to :data:`RESULTS_VERSION`."""
    method: str
    """Registered method name."""
    dataset: str
    """Dataset the run is filed under (``synthetic`` for generated scenes)."""
    scene: str
    """Scene name."""
    layout: NotRequired[str]
    """The loader's dataset (folder layout) of the scene."""
    track: str
    """Supervision track: ``oracle`` or ``real``."""
    seed: int
    """Seed of the fit."""
    split: NotRequired[EvalSplit]
    """Evaluation split scored (:data:`benchmark.core.scene.EVAL_SPLITS`): ``paper`` (the dataset's held-out
    frames) or ``novel-view`` (held-out frames seen from cameras no training frame uses). Absent: written
    before splits existed, read as :data:`LEGACY_EVAL_SPLIT`."""
    scene_seed: NotRequired[Optional[int]]
    """Generator seed of the synthetic scene measured (seed ``s`` generates with ``s``); null: a scene the
    generator did not make. Absent: written when every seed measured scene seed 0."""
    splits: NotRequired[list[str]]
    """Frame splits whose annotated frames were scored (``test``; ``train`` too with ``--score-train``)."""
    metrics: Metrics
    """The run's scores."""
    unanswered_queries: NotRequired[list[str]]
    """Query texts of a kind the method does not answer: listed, 0 in the full means."""
    timing: Timing
    """Fit and query times."""
    memory: NotRequired[Memory]
    """Peak memory."""
    method_config: NotRequired[dict[str, Any]]
    """The method's config, every field."""
    fit: NotRequired[FitSummary]
    """The fit answered with."""
    supervision: NotRequired[dict[str, Any]]
    """The 2D supervision of the training frames: track, sources, their configs, fingerprint."""
    environment: NotRequired[Environment]
    """Package versions, git state, device, threads."""
    scene_info: NotRequired[SceneInfo]
    """The scene folder and its version."""
    protocol: NotRequired[dict[str, Any]]
    """The evaluation protocol, every constant (absent: rebuilt from the config, :func:`protocol_of`)."""
    score_config: NotRequired[dict[str, Any]]
    """The temporal rule and the frames scored."""
    scores: NotRequired[Scores]
    """Per-query and per-frame scores."""
    predictions: NotRequired[str]
    """Path of the run's predictions file (``predictions.json.gz``; older runs: ``predictions.json``),
    relative to this file."""
    wall_seconds: NotRequired[float]
    """The whole run, start to written."""
    created: NotRequired[str]
    """When it was written (ISO 8601, UTC)."""


@functools.lru_cache(maxsize=None)
def _fields(record: type) -> tuple[tuple[str, Any, bool], ...]:
    """``(name, type, required)`` of each field of the TypedDict ``record``, in order. Required-ness is
    read from ``NotRequired`` itself: with postponed annotations ``__required_keys__`` cannot see it."""
    out = []
    for name, hint in get_type_hints(record, include_extras=True).items():
        optional = get_origin(hint) is NotRequired
        out.append((name, get_args(hint)[0] if optional else hint, not optional))
    return tuple(out)


def _is_record(hint: Any) -> bool:
    return isinstance(hint, type) and issubclass(hint, dict) and hasattr(hint, "__required_keys__")


def _expected(hint: Any) -> str:
    """``hint`` in words, for an error message."""
    origin, args = get_origin(hint), get_args(hint)
    if origin in (Union, types.UnionType):
        return " or ".join(_expected(a) for a in args)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if hint is type(None):
        return "null"
    words = {str: "a string", int: "an integer", float: "a number", bool: "true or false", list: "a list",
             dict: "an object"}
    return words.get(origin or hint, "an object" if _is_record(hint) else str(hint))


def _check_value(value: Any, hint: Any, path: Optional[Path], where: str) -> None:
    """An :class:`InputError` naming ``where`` (or a field below it) unless ``value`` is of type ``hint``."""
    origin, args = get_origin(hint), get_args(hint)
    if hint is Any:
        return
    nullable = origin in (Union, types.UnionType) and type(None) in args  # Optional[X] or X | None
    if nullable:
        if value is None:
            return
        (hint,) = [a for a in args if a is not type(None)]
        origin, args = get_origin(hint), get_args(hint)
    if origin is Literal:
        ok = value in args and isinstance(value, type(args[0]))
    elif _is_record(hint):
        ok = isinstance(value, dict)
    elif hint is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    elif hint is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, origin or hint)
    if not ok:
        null = " or null" if nullable else ""
        raise InputError(path, where, f"expected {_expected(hint)}{null}, got {short_repr(value)}")
    if _is_record(hint):
        _check_record(value, hint, path, where)
    elif origin is list:
        for i, item in enumerate(value):
            _check_value(item, args[0], path, f"{where}[{i}]")
    elif origin is dict and args[1] is not Any:
        for key, item in value.items():
            _check_value(item, args[1], path, f"{where}.{key}")


def _check_record(doc: dict, record: type, path: Optional[Path], prefix: str = "") -> None:
    names = set()
    for name, hint, required in _fields(record):
        names.add(name)
        where = f"{prefix}.{name}" if prefix else name
        if name not in doc:
            if required:
                raise InputError(path, where, "missing required key")
            continue
        _check_value(doc[name], hint, path, where)
    for name in doc:
        if name not in names:
            raise InputError(path, f"{prefix}.{name}" if prefix else str(name),
                             f"not a field of {RESULTS_FORMAT!r} version {RESULTS_VERSION} ({record.__name__})")


def _check_header(doc: Any, path: Optional[Path]) -> None:
    """An :class:`InputError` unless ``doc`` is an object of :data:`RESULTS_FORMAT` in a version this reads."""
    if not isinstance(doc, dict) or doc.get("format") != RESULTS_FORMAT:
        raise InputError(path, "format", f"not a bench4d run results file (expected {RESULTS_FORMAT!r})")
    version = doc.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or not 1 <= version <= RESULTS_VERSION:
        raise InputError(path, "version", f"unsupported version {version!r} (this bench4d reads up to {RESULTS_VERSION})")


def check_results(doc: Any, path: Optional[str | Path] = None) -> None:
    """Check ``doc`` (a results document, per-frame records as a list) against :class:`RunResults`: an
    :class:`InputError` naming ``path`` and the first field that is missing, of the wrong type or unknown."""
    path = None if path is None else Path(path)
    _check_header(doc, path)
    _check_record(doc, RunResults, path)


def results_path(results_dir: str | Path, dataset: str, scene: str, method: str, track: str, seed: int,
                 split: str = DEFAULT_EVAL_SPLIT) -> Path:
    """Where the results file of a run goes: ``<dataset>/<scene>/<method>/<track>/seed<N>.json`` for the
    ``paper`` split, ``.../<track>/<split>/seed<N>.json`` for another (module docstring)."""
    if split not in EVAL_SPLITS:
        raise InputError(None, "split", f"unknown evaluation split {split!r} (valid: {', '.join(EVAL_SPLITS)})")
    folder = Path(results_dir) / dataset / scene / method / track
    return (folder if split == DEFAULT_EVAL_SPLIT else folder / split) / f"seed{seed}.json"


_FRAMES_PLACEHOLDER = "__bench4d_frames__"


def write_results(path: str | Path, doc: RunResults | dict) -> None:
    """Check ``doc`` against :class:`RunResults` (``format`` and ``version`` added), then write it atomically
    (a reader never sees a partial file).

    The per-frame records (``scores.frames``, a list of dicts in memory) are stored as a table,
    ``{"columns": [...], "rows": [[...], ...]}`` with one row per line: compact and diff-friendly.
    """
    full = _sanitize({"format": RESULTS_FORMAT, "version": RESULTS_VERSION, **doc})
    check_results(full, path)
    frames = (full.get("scores") or {}).get("frames")
    if not frames:
        # no per-frame table (a slim file, as the committed tree keeps them): one compact line, a third smaller
        write_json(path, full, indent=None)
        return
    columns = list(frames[0])
    rows = [[_plain(record.get(c)) for c in columns] for record in frames]
    full["scores"] = {**full["scores"], "frames": _FRAMES_PLACEHOLDER}
    text = json.dumps(full, indent=1, default=_plain)
    table = ('{"columns": ' + json.dumps(columns) + ', "rows": [\n'
             + ",\n".join("  " + json.dumps(row) for row in rows) + "\n ]}")
    write_text(path, text.replace(json.dumps(_FRAMES_PLACEHOLDER), table, 1) + "\n")


def _sanitize(obj: Any) -> Any:
    """JSON-ready copy: NaN / inf -> null (strict JSON), numpy scalars and arrays -> Python, paths -> str."""
    if isinstance(obj, dict):
        return {str(k): _sanitize(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_sanitize(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _sanitize(obj.tolist())
    if isinstance(obj, Path):
        return str(obj)
    return _plain(obj)


def _plain(value: Any) -> Any:
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _expand_frames(doc: dict, path: Path) -> None:
    """``scores.frames`` table on disk -> list of dicts in memory."""
    scores = doc.get("scores")
    if not isinstance(scores, dict) or not isinstance(scores.get("frames"), dict):
        return
    table = scores["frames"]
    columns, rows = table.get("columns"), table.get("rows")
    if not isinstance(columns, list) or not isinstance(rows, list) or \
            any(not isinstance(r, list) or len(r) != len(columns) for r in rows):
        raise InputError(path, "scores.frames", "expected {\"columns\": [...], \"rows\": [[...], ...]} with "
                                                "one value per column in every row")
    scores["frames"] = [dict(zip(columns, row)) for row in rows]


def read_results(path: str | Path) -> dict:
    """Read one results file and check it against :class:`RunResults` (an :class:`InputError` naming the
    file and the first wrong, missing or unknown field); the per-frame records come back as a list."""
    path = Path(path)
    doc = read_json(path)
    _check_header(doc, path)
    _expand_frames(doc, path)
    check_results(doc, path)
    return doc


load_results = read_results
"""The same reader under the name the leaderboard, plots and studies call."""


ABLATIONS_DIR = "ablations"
"""Folder under a results directory that holds ablation runs (not leaderboard entries)."""
ARCHIVE_DIR = "archive"
"""Folder under a results directory that keeps runs no longer comparable (e.g. measured on a synthetic
scene version the committed generator does not make): kept, never read by the leaderboard."""


def needs_slimming(path: str | Path, doc: dict) -> bool:
    """Whether :func:`slim_results` would change the results file at ``path`` (read as ``doc``): it holds
    per-frame records or predictions, has a predictions folder beside it, or is written indented."""
    path = Path(path)
    return ("frames" in (doc.get("scores") or {}) or "predictions" in doc
            or path.with_suffix(".predictions").is_dir() or path.read_bytes().count(b"\n") > 1)


def slim_results(path: str | Path) -> int:
    """Rewrite the results file at ``path`` as the committed tree keeps it: what the leaderboard, the paper
    tables, the charts and the studies' tables read (metrics, per-query scores, timing, memory, provenance)
    stays; the per-frame records become their count (``scores.frames_dropped``) and the predictions folder
    beside it is deleted. Returns the bytes freed (0 for a file already slim)."""
    path = Path(path)
    before = path.stat().st_size
    doc = read_results(path)
    scores = doc.get("scores") or {}
    folder = path.with_suffix(".predictions")
    freed = 0
    if folder.is_dir():
        freed += sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
        shutil.rmtree(folder)
    if not needs_slimming(path, doc):
        return freed  # slim and compact already (an indented slim file from an older writer is compacted)
    if "frames" in scores:
        doc["scores"] = {**{k: v for k, v in scores.items() if k != "frames"},
                         "frames_dropped": len(scores["frames"]) + int(scores.get("frames_dropped", 0))}
    doc.pop("predictions", None)
    write_results(path, doc)
    return freed + before - path.stat().st_size


def find_results(results_dir: str | Path) -> list[Path]:
    """Every results file under ``results_dir``, sorted (hidden temp files are ignored, and so is
    ``results_dir/ablations/``: ablation runs such as ``bench4d ablate states`` change a method's
    config on purpose and are reported by their ablation, never ranked on the leaderboard; and
    ``results_dir/archive/``: runs kept for the record only)."""
    root = Path(results_dir)
    if not root.is_dir():
        return []
    return sorted(p for p in root.rglob("seed*.json")
                  if not any(part.startswith(".") for part in p.relative_to(root).parts)
                  and p.relative_to(root).parts[0] not in (ABLATIONS_DIR, ARCHIVE_DIR)
                  and not any(part.endswith(".predictions") for part in p.relative_to(root).parts))


def _number(value: Any) -> float:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan


FIT_STAGES = (("geometry", "seconds"), ("autoencoder", "seconds"), ("field", "seconds"), ("time_varying", "seconds"))
"""Stages of a fit record (``fit.info``) whose seconds add up to what the whole fit cost, including
stages a run reused from the shared cache (a method on another method's geometry and field)."""


def fit_seconds_with_shared(doc: dict) -> float:
    """Seconds the fit cost: the sum of its recorded stages (:data:`FIT_STAGES`) when the results file
    has a fit record, so a method reusing a cached geometry and field is charged for them; else the
    runner's ``timing.fit_seconds``."""
    info = (doc.get("fit") or {}).get("info") or {}
    stages = [_number((info.get(stage) or {}).get(key)) for stage, key in FIT_STAGES]
    stages = [v for v in stages if not math.isnan(v)]
    if stages:
        return float(sum(stages))
    return _number((doc.get("timing") or {}).get("fit_seconds"))


def peak_memory_with_shared(doc: dict) -> tuple[float, float, bool]:
    """``(cpu_mib, gpu_mib, measured)``: the most memory the run needed, MiB: the largest of its own
    peak, its fit's and the peak every stage of its fit record recorded (:data:`FIT_STAGES`), so a method
    reusing a cached geometry and field is charged for the memory they took, as for their seconds
    (:mod:`benchmark.core.memory`). GPU: NaN when nothing ran on one. ``measured`` is False when the number
    may be wrong: a peak over the process rather than the run (``memory.peak_window``; every results
    file made before per-run peaks), a cached fit that did not record its window
    (``memory.peak_fit_window``), or a stage of the fit record that recorded its seconds but no peak
    (made before stage peaks: a run reusing it would be charged too little)."""
    memory = doc.get("memory") or {}
    info = (doc.get("fit") or {}).get("info") or {}
    cpu = [_number(memory.get("peak_cpu_mib")), _number(memory.get("peak_cpu_fit_mib"))]
    gpu = [_number(memory.get("peak_gpu_mib")), _number(memory.get("peak_gpu_fit_mib"))]
    # no peak_fit_window: written before fits recorded it (those with stage peaks all fitted afresh)
    measured = memory.get("peak_window") == "run" and memory.get("peak_fit_window", "run") == "run"
    for stage, key in FIT_STAGES:
        record = info.get(stage)
        if not isinstance(record, dict) or math.isnan(_number(record.get(key))):
            continue
        if math.isnan(_number(record.get("peak_cpu_mib"))) or record.get("peak_window") != "run":
            measured = False
        cpu.append(_number(record.get("peak_cpu_mib")))
        gpu.append(_number(record.get("peak_gpu_mib")))

    def largest(values: list[float]) -> float:
        finite = [v for v in values if not math.isnan(v)]
        return max(finite) if finite else math.nan

    return largest(cpu), largest(gpu), measured


def scene_status(doc: dict) -> tuple[str, Optional[bool]]:
    """(digest, current) of the scene a run measured: ``current`` is True when a synthetic preset's
    recorded digest is the committed one (:mod:`benchmark.synthetic.digest`), False when it differs or
    a synthetic run recorded none (made before scenes were versioned), None for other scenes."""
    from .synthetic.digest import expected_digest

    generated = (doc.get("scene_info") or {}).get("generated")
    if not generated:
        return "", (False if doc.get("dataset") == "synthetic" else None)
    digest = str(generated.get("digest") or "")
    expected = expected_digest(str(generated.get("preset")), int(generated.get("size") or 0),
                               int(generated.get("seed") or 0))
    return digest, (None if expected is None else digest == expected)


def comparable_runs(runs: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(runs that may be compared, runs on a scene version other than the committed one)."""
    stale = runs["scene_current"].map(lambda v: v is not None and not pd.isna(v) and not bool(v)).astype(bool)
    return runs[~stale].reset_index(drop=True), runs[stale].reset_index(drop=True)


@contextlib.contextmanager
def exclusive_lock(lock_path: str | Path, *, wait: bool = True) -> Iterator[bool]:
    """Hold an exclusive ``flock`` on ``lock_path`` (created if missing) until the block ends; other
    processes locking the same path wait (``wait=False``: the block runs at once and is given False when
    another holds it, True when it holds it). The holder removes the file before it lets go, so no lock file
    outlives its writer (results folders are committed: one stray file per results file would litter
    them). A waiter that then wakes on the removed file finds the path gone or naming another file, and
    locks again. A process killed while holding it leaves the file behind: harmless, the next writer
    locks and removes it."""
    lock_path = Path(lock_path)
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    try:
        import fcntl
    except ImportError:  # no flock on this platform (Windows): writers are not serialised there
        yield True
        return
    while True:
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
            held, now = os.fstat(fd), os.stat(lock_path)
        except FileNotFoundError:  # removed by the holder we waited for: lock the path anew
            os.close(fd)
            continue
        except BlockingIOError:  # held by another, and the caller does not wait
            os.close(fd)
            yield False
            return
        except BaseException:
            os.close(fd)
            raise
        if (held.st_dev, held.st_ino) == (now.st_dev, now.st_ino):
            break
        os.close(fd)  # we locked a file its holder removed; another may hold the path's new file
    try:
        yield True
    finally:
        try:
            os.unlink(lock_path)
        finally:
            os.close(fd)  # unlinked first: a waiter on this file sees it gone and locks anew


def results_lock(path: str | Path) -> contextlib.AbstractContextManager:
    """The lock writers of results file ``path`` hold (``.<name>.lock`` beside it) across "archive the
    file being replaced, write the predictions, write the results": two runs of the same method, scene,
    track and seed finishing together would otherwise both find no file to archive, and the later would
    overwrite the earlier's record. Readers never take it (every file is replaced atomically)."""
    path = Path(path)
    return exclusive_lock(path.with_name(f".{path.name}.lock"))


def archive_results(path: str | Path, results_dir: str | Path, label: str) -> Path:
    """Move a results file and its predictions folder to ``results_dir/archive/<label>/`` (same
    relative path), so a rerun never overwrites what was measured; returns the new file's path. Where that
    label already holds a file of the name (two archivings in one second), ``<label>-2``, ``-3``, ... is used.
    A writer that may run beside others holds :func:`results_lock` around this and the writing that follows."""
    path, root = Path(path), Path(results_dir)
    target, n = root / ARCHIVE_DIR / label / path.relative_to(root), 1
    while target.exists():
        n += 1
        target = root / ARCHIVE_DIR / f"{label}-{n}" / path.relative_to(root)
    target.parent.mkdir(parents=True, exist_ok=True)
    predictions = path.with_suffix(".predictions")
    if predictions.is_dir():
        os.replace(predictions, target.with_suffix(".predictions"))
    os.replace(path, target)
    return target


def sensitive_query_records(doc: dict) -> Iterator[tuple[dict, np.ndarray, np.ndarray, np.ndarray, float]]:
    """For each time-sensitive query a run decided from scores (not one whose method gave decisions):
    (its query row, smoothed scores (T,) float64 with NaN = undefined, labels (T,) bool, decisions (T,)
    bool, tau), from the recorded per-frame records in time order."""
    scores = doc.get("scores") or {}
    frames = [f for f in scores.get("frames") or [] if isinstance(f, dict) and f.get("kind") == "sensitive"]
    for query in scores.get("queries") or []:
        if query.get("kind") != "sensitive" or query.get("decision_source") == "decisions":
            continue  # a method that gave decisions has no scores to diagnose
        rows = sorted((f for f in frames if f.get("query") == query.get("query")),
                      key=lambda f: (_number(f.get("time_index")), str(f.get("camera_id")), str(f.get("frame"))))
        yield (query, np.array([_number(f.get("smoothed")) for f in rows], dtype=np.float64),
               np.array([bool(f.get("label")) for f in rows]), np.array([bool(f.get("decision")) for f in rows]),
               _number(query.get("threshold")))


def temporal_diagnostics(doc: dict) -> dict[str, float]:
    """``{"AUC", "nearTau"}`` (percent, NaN where undefined) of one run: its recorded metrics when it
    has them, else computed from its recorded per-frame smoothed scores, labels and each query's
    ``tau`` (files written before the diagnostics existed), averaged over its time-sensitive queries
    as the scorer averages them (NaN skipped)."""
    from .metrics import near_threshold_fraction, score_auc

    metrics = doc.get("metrics", {})
    if all(name in metrics for name in DIAGNOSTIC_METRICS):
        return {name: _number(metrics.get(name)) for name in DIAGNOSTIC_METRICS}
    per_query: dict[str, list[float]] = {name: [] for name in DIAGNOSTIC_METRICS}
    for _, smoothed, labels, _, tau in sensitive_query_records(doc):
        per_query["AUC"].append(100.0 * score_auc(smoothed, labels))
        per_query["nearTau"].append(100.0 * near_threshold_fraction(smoothed, tau))
    out = {}
    for name, values in per_query.items():
        v = np.array(values, dtype=np.float64)
        out[name] = float(np.nanmean(v)) if np.isfinite(v).any() else math.nan
    return out


def protocol_of(doc: dict):
    """The :class:`~benchmark.core.protocol.Protocol` a run answered and was scored under. Files written before
    protocols were named recorded the query rules in their method config (``threshold_variant``,
    ``sensitive_mask``, ...) and the temporal rule in ``score_config``; their relevance baselines scored a
    frame by the mean relevance inside the mask, one ``tau`` rule held for every method, and absent frames
    were scored against the empty mask (:data:`~benchmark.core.protocol.CONSTANTS_BEFORE_RECORDED`
    says the same of files that record a protocol without those constants). A preset's name is given back where every constant is
    that preset's, else ``custom``."""
    import dataclasses

    from benchmark.core.protocol import PROTOCOLS, AgnosticQuery, Protocol, ScoringRule, SensitiveQuery, TemporalRule

    if doc.get("protocol"):
        return Protocol.from_dict(doc["protocol"])
    cfg = doc.get("method_config") or {}
    temporal = dict((doc.get("score_config") or {}).get("temporal") or {})
    default_query = AgnosticQuery()
    agnostic = AgnosticQuery(
        canonical_phrases=tuple(cfg.get("canonical_phrases") or default_query.canonical_phrases),
        temperature=float(cfg.get("temperature", default_query.temperature)),
        smoothing_kernel=int(cfg.get("smoothing_kernel", default_query.smoothing_kernel)),
        threshold=float(cfg.get("threshold", default_query.threshold)),
        threshold_rule="stretched" if cfg.get("threshold_variant") == "release" else "rescaled",
        majority_kernel=int(cfg.get("majority_kernel", default_query.majority_kernel)),
        majority_fraction=float(cfg.get("majority_fraction", default_query.majority_fraction)),
        kernel_scaling=cfg.get("kernel_scaling", default_query.kernel_scaling))
    sensitive = SensitiveQuery(mask=cfg.get("sensitive_mask", "unfiltered"), relevance_score="mask-mean")
    tau_from = "raw" if temporal.get("threshold_variant") == "release" else "smoothed"
    rule = TemporalRule(weights=tuple(temporal.get("weights") or (0.1, 0.8, 0.1)),
                        ends=temporal.get("ends", "renormalise"),
                        tau_from=tau_from, relevance_peak_tau_from=tau_from,  # one tau rule for every method then
                        inclusive=bool(temporal.get("inclusive", True)),
                        undefined_decision=bool(temporal.get("undefined_decision", False)),
                        tie_tolerance=float(temporal.get("tie_tolerance", 1e-9)))
    # absent frames were scored against the empty mask then
    found = Protocol("custom", agnostic, sensitive, rule, ScoringRule(absent_frames="score-empty"))
    return next((preset for name, preset in PROTOCOLS.items() if dataclasses.replace(found, name=name) == preset),
                found)


def run_split(doc: dict) -> str:
    """The evaluation split a run scored: its ``split``, or :data:`LEGACY_EVAL_SPLIT` for a file written before
    splits were recorded."""
    return str(doc.get("split") or LEGACY_EVAL_SPLIT)


def run_scene_seed(doc: dict) -> int:
    """The generator seed of the scene a run measured: ``scene_seed``, else the generated scene's recorded
    seed, else 0 (files written when every seed measured scene seed 0; scenes not generated)."""
    value = doc.get("scene_seed")
    if value is None:
        value = ((doc.get("scene_info") or {}).get("generated") or {}).get("seed")
    return int(value) if isinstance(value, int) and not isinstance(value, bool) else 0


def machine_of(doc: dict) -> dict[str, Any]:
    """``{"cpu_model", "cpu_capability", "gpu", "machine_kind"}`` of a run, from its ``environment``.
    ``machine_kind`` names the kind of machine its numbers came from: the GPU where it ran on one, else the CPU
    model with the instruction set torch's kernels used (``"AMD EPYC 7B13 (avx2)"``; files written before that
    was recorded: the model alone), else :data:`UNKNOWN_MACHINE`."""
    env = doc.get("environment") or {}
    cpu = env.get("processor") or None
    capability = env.get("cpu_capability") or None
    gpu = env.get("gpu") or None
    if gpu:
        kind = str(gpu)
    elif cpu:
        kind = f"{cpu} ({str(capability).lower()})" if capability else str(cpu)
    else:
        kind = UNKNOWN_MACHINE
    return {"cpu_model": cpu or "", "cpu_capability": capability or "", "gpu": gpu or "", "machine_kind": kind}


def run_row(doc: dict, path: Optional[Path] = None) -> dict[str, Any]:
    digest, current = scene_status(doc)
    metrics = doc.get("metrics", {})
    timing = doc.get("timing", {})
    memory = doc.get("memory", {})
    env = doc.get("environment", {})
    git = env.get("git", {}) or {}
    return {
        "dataset": doc["dataset"], "track": doc["track"], "protocol": protocol_of(doc).name, "split": run_split(doc),
        "method": doc["method"], "scene": doc["scene"], "seed": int(doc["seed"]), "scene_seed": run_scene_seed(doc),
        **{m: _number(metrics.get(m)) for m in ("mIoU", "mAcc", "Acc", "vIoU")},
        **temporal_diagnostics(doc),
        "fps_agnostic": _number((timing.get("query_agnostic") or {}).get("fps")),
        "fps_sensitive": _number((timing.get("query_sensitive") or {}).get("fps")),
        "fit_seconds": fit_seconds_with_shared(doc),
        "peak_cpu_mib": _number(memory.get("peak_cpu_mib")),
        "peak_gpu_mib": _number(memory.get("peak_gpu_mib")),
        **dict(zip(("peak_cpu_needed_mib", "peak_gpu_needed_mib", "peak_measured"), peak_memory_with_shared(doc))),
        "device": env.get("device", ""),
        **machine_of(doc),
        "git_commit": (git.get("commit") or "")[:12],
        "git_dirty": git.get("dirty"),
        "scene_digest": digest, "scene_current": current,
        "draft_queries": ", ".join((doc.get("scene_info") or {}).get("draft_queries") or []),
        "path": "" if path is None else str(path),
    }


def runs_table(paths: Iterable[Path], *, relative_to: Optional[Path] = None) -> pd.DataFrame:
    """One row per results file (:data:`RUN_COLUMNS`), sorted by dataset, track, protocol, split, method, scene,
    seed; two files of one run (:data:`RUN_KEYS`) are an :class:`InputError`."""
    rows = []
    for path in paths:
        doc = load_results(path)
        shown = path.relative_to(relative_to) if relative_to is not None else path
        rows.append(run_row(doc, Path(shown).as_posix() if relative_to is not None else path))
    table = pd.DataFrame(rows, columns=RUN_COLUMNS)
    if len(table):
        dupes = table.duplicated(RUN_KEYS, keep=False)
        if dupes.any():
            first = table[dupes].iloc[0]
            raise InputError(first["path"], None, f"two results files for {first['method']} on "
                             f"{first['dataset']}/{first['scene']} ({first['track']}, {first['split']} split, "
                             f"seed {first['seed']})")
    return table.sort_values(RUN_KEYS, kind="stable").reset_index(drop=True)


def _std(values: pd.Series) -> float:
    v = values.dropna().to_numpy(dtype=np.float64)
    return float(v.std(ddof=1)) if v.size >= 2 else math.nan


def seed_summary(runs: pd.DataFrame) -> pd.DataFrame:
    """Mean, std (sample, ddof=1; NaN for one seed) and seed count per (dataset, track, protocol, split, method,
    scene): runs of two evaluation splits are never averaged together.

    The extra scene :data:`MEAN_SCENE` per (dataset, track, protocol, split, method) first averages the scenes of each
    seed (the dataset-level number of that seed), then summarises over seeds. Only *complete* seeds
    enter it: seeds that ran every scene the method has in that (dataset, track); a seed that ran
    fewer would average a different scene set into the same number. Those are counted in
    ``partial_seeds`` and left out (if no seed is complete, the mean is NaN). Columns:
    ``<value>_mean``, ``<value>_std`` for every :data:`VALUE_COLUMNS`, ``seeds``, ``partial_seeds``,
    ``scenes``, ``peak_measured`` (every run's peak memory is its own and charges its reused stages:
    :func:`peak_memory_with_shared`).
    """
    keys = ["dataset", "track", "protocol", "split", "method", "scene"]
    columns = (keys + [f"{v}_{s}" for v in VALUE_COLUMNS for s in ("mean", "std")]
               + ["seeds", "partial_seeds", "scenes", "peak_measured"])
    if not len(runs):
        return pd.DataFrame(columns=columns)
    if "split" not in runs or runs["split"].isna().any():  # a table made by hand: runs that record no split
        runs = runs.assign(split=runs["split"].fillna(LEGACY_EVAL_SPLIT) if "split" in runs else LEGACY_EVAL_SPLIT)
    group_keys = ["dataset", "track", "protocol", "split", "method"]
    scene_sets = runs.groupby(group_keys)["scene"].agg(lambda s: frozenset(s))
    seed_sets = runs.groupby(group_keys + ["seed"])["scene"].agg(lambda s: frozenset(s)).reset_index()
    seed_sets["complete"] = [scenes == scene_sets[tuple(k)] for k, scenes in
                             zip(seed_sets[group_keys].itertuples(index=False), seed_sets["scene"])]
    complete = seed_sets[seed_sets["complete"]][group_keys + ["seed"]]
    partial = seed_sets[~seed_sets["complete"]].groupby(group_keys)["seed"].nunique()
    complete_runs = runs.merge(complete, on=group_keys + ["seed"])
    per_seed_dataset = complete_runs.groupby(group_keys + ["seed"], sort=True)[VALUE_COLUMNS].mean().reset_index()
    per_seed_dataset["scene"] = MEAN_SCENE
    measured = {**{tuple(k): bool(v.all()) for k, v in runs.groupby(keys, sort=True)["peak_measured"]},
                **{(*k, MEAN_SCENE): bool(v.all()) for k, v in complete_runs.groupby(group_keys)["peak_measured"]}}
    rows = []
    for source, with_scene in ((runs, True), (per_seed_dataset, False)):
        for key, group in source.groupby(keys, sort=True):
            row = dict(zip(keys, key))
            for v in VALUE_COLUMNS:
                col = group[v]
                row[f"{v}_mean"] = float(col.mean()) if col.notna().any() else math.nan
                row[f"{v}_std"] = _std(col)
            row["seeds"] = int(group["seed"].nunique())
            row["partial_seeds"] = 0 if with_scene else int(partial.get(key[:-1], 0))
            row["scenes"] = 1 if with_scene else len(scene_sets[key[:-1]])
            row["peak_measured"] = measured.get(tuple(key), False)
            rows.append(row)
    # a method none of whose seeds is complete still gets its (empty) mean row
    with_mean = {tuple(r[k] for k in group_keys) for r in rows if r["scene"] == MEAN_SCENE}
    for key, scenes in scene_sets.items():
        if key not in with_mean:
            row = dict(zip(keys, (*key, MEAN_SCENE)))
            row.update({f"{v}_{s}": math.nan for v in VALUE_COLUMNS for s in ("mean", "std")})
            row.update({"seeds": 0, "partial_seeds": int(partial.get(key, 0)), "scenes": len(scenes),
                        "peak_measured": False})
            rows.append(row)
    table = pd.DataFrame(rows)
    table["_order"] = (table["scene"] == MEAN_SCENE).astype(int)
    return (table.sort_values(["dataset", "track", "protocol", "split", "method", "_order", "scene"], kind="stable")
            .drop(columns="_order").reset_index(drop=True))
