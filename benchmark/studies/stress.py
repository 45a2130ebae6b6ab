"""The stress suite: where methods fail. Families x strengths x methods x seeds on one base preset.

Every run is an ordinary evaluation (:mod:`benchmark.runner`), written as a results file under
``<runs>/<family>/<strength>/`` (the clean runs, strength 0 of every family, once under
``<runs>/clean/``); a run whose results file exists is read, not redone, so the suite resumes where
it stopped. The report's ``scores.csv`` keeps every run's scores with the digests of its scene and its
method config, so a run whose results file is gone (another machine, a cleared cache) still counts, and is
not redone, while both digests are those of today's scene and config. Scene-side families are generated
scenes (:mod:`benchmark.synthetic.perturb`); the supervision-side families put noise on what the oracle
track gives a method, here, so no method changes:

* ``mask-erode`` / ``mask-dilate``: every mask of every level shrinks or grows by a radius (pixels at
  48 px, scaled with the image width); a dilated mask grows over uncovered pixels and larger masks;
* ``mask-id-swap``: in a share of the training frames the masks' features are shuffled (each mask
  carries the label of another);
* ``mask-drop``: a share of the masks is removed (their pixels carry no mask);
* ``caption-swap``: a share of the template captions is replaced by a caption the same object had in
  another state (methods with a ``captions`` group, fed through the ``file`` captioner);
* ``caption-lag``: the template captions describe each change later, by a share of the video on top of the
  scene's own caption noise (:func:`benchmark.core.caption_noise.with_extra_lag`; methods with a
  ``captions`` group);
* ``query-paraphrase``: a share of the queries is put to the model in other words (a synonym of the
  object, a caption of the state) and scored against the query's ground truth.
"""

from __future__ import annotations

import functools
import hashlib
import os
import shutil
import time
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np

from benchmark.core.atomic import read_json
from benchmark.core.errors import InputError
from benchmark.core.scene import DEFAULT_EVAL_SPLIT, check_eval_split
from benchmark.synthetic.perturb import FAMILIES, family

from ._report import keep_replaced_table, number_cell

METRICS = ("mIoU", "Acc", "vIoU")
"""Scores the suite charts and breaks down (higher is better)."""
REFERENCE_WIDTH = 48
"""Image width the mask-noise radii are given at."""
CLEAN = "clean"
TRACK = "oracle"
"""Supervision track of every run of the suite: the generator's exact 2D supervision, on which the
supervision-side families put their noise."""


SUITE_METHODS = ("nearest-frame", "nearest-frame-masks", "gaussian-grouping", "feature-3dgs", "deformable-clip",
                 "non-status-field", "4d-langsplat", "langsplat")
"""The suite's methods: both 2D floors and the six paper methods (their benchmark variants are not run)."""


@dataclass
class SuiteConfig:
    """One stress suite."""

    preset: str = "split-cookie"
    """Base preset every perturbation is applied to."""
    size: int = 96
    """Image width of the generated scenes: the smallest measured (64, 96, 128 px) at which every method that
    clears both floors at the leaderboard's 128 px clears them too."""
    frames: int = 60
    """Video length of the generated scenes."""
    methods: tuple[str, ...] = SUITE_METHODS
    families: tuple[str, ...] = tuple(FAMILIES)
    strengths: Optional[tuple[float, ...]] = None
    """Strengths run for every family (None: each family's own, :data:`FAMILIES`)."""
    strongest_only: bool = False
    """Run each family at its clean end and its strongest strength only: the screen of which families break
    a method or separate two, before the strengths between are paid for."""
    seeds: tuple[int, ...] = (0, 1, 2)
    """Seeds of the generated scene, of the fit and of the supervision noise: seed ``s`` generates the base
    preset with scene seed ``s`` and fits on it with seed ``s``, so the seeds vary scene and fit together."""
    split: str = "novel-view"
    """Evaluation split the runs score (:data:`benchmark.core.scene.EVAL_SPLITS`): ``novel-view`` (default),
    the question a copy of the nearest training frame cannot answer; one fit answers both."""
    method_options: dict[str, dict[str, str]] = field(default_factory=dict)
    """Method -> dotted config overrides (short schedules)."""
    out_dir: Path = Path("reports/stability")
    """Where the tables, charts and galleries go."""
    cache_dir: Path = Path("cache")
    device: str = "cpu"
    force: bool = False
    """Run again where a results file exists."""

    def __post_init__(self) -> None:
        check_eval_split(self.split)
        for value in self.strengths or ():
            if not np.isfinite(float(value)) or float(value) < 0:  # before any run starts, not at the first scene
                raise InputError(None, "strengths", f"expected finite strengths >= 0, got {value!r}")
        for name in self.families:
            family(name)  # an unknown family: one line with the valid names

    @property
    def stress_dir(self) -> Path:
        return Path(self.cache_dir) / "stress" / f"{self.preset}-{self.size}px-{self.frames}f"

    @property
    def runs_dir(self) -> Path:
        return self.stress_dir / "runs"

    def strengths_of(self, name: str) -> tuple[float, ...]:
        chosen = self.strengths if self.strengths is not None else family(name).strengths
        if self.strongest_only and chosen:
            chosen = (max(map(float, chosen)),)
        return tuple(sorted({0.0, *map(float, chosen)}))


@dataclass(frozen=True)
class RunKey:
    """One cell of the suite."""

    family: str
    strength: float
    method: str
    seed: int

    @property
    def clean(self) -> bool:
        return self.strength == 0

    def folder(self, runs: Path) -> Path:
        return runs / CLEAN if self.clean else runs / self.family / strength_label(self.strength)


def score_line(metrics: dict) -> str:
    """The suite's scores of one run for the log; a metric the method does not answer is ``–``, not 0."""
    return ", ".join(f"{m} {number_cell(metrics.get(m), 1)}" for m in METRICS)


def strength_label(strength: float) -> str:
    return f"{strength:g}"


# -- scenes ---------------------------------------------------------------------------------------------
def scene_folder(config: SuiteConfig, family_name: str, strength: float, seed: int) -> Path:
    """The generated scene a run of (family, strength, seed) reads (the clean scene for supervision
    families), generated with scene seed ``seed``, as the generator's code now makes it
    (:func:`current_scene`)."""
    from benchmark.results import exclusive_lock

    scene_side = strength != 0 and family(family_name).side == "scene"
    name = f"{config.preset}-{family_name}-{strength_label(strength)}" if scene_side else f"{config.preset}-clean"
    name = f"{name}-s{int(seed)}"
    folder = config.stress_dir / "scenes" / name
    folder.parent.mkdir(parents=True, exist_ok=True)
    with exclusive_lock(folder.parent / f".{name}.lock"):
        perturbation = (family_name, strength) if scene_side else None
        return current_scene(folder, lambda out: _generate(config, out, perturbation, seed))


def changes_nothing(config: SuiteConfig, family_name: str, seed: int) -> Optional[str]:
    """Why a scene-side family leaves the base preset of scene seed ``seed`` as it is (it has nothing the
    family acts on, e.g. no freely moving part for the motion families), else None. Such a family's runs are
    not made: they would fit the clean scene again under another name."""
    if family(family_name).side != "scene":
        return None
    return _changes_nothing(config.preset, family_name, int(seed), int(config.frames))


@functools.lru_cache(maxsize=256)
def _changes_nothing(preset: str, family_name: str, seed: int, frames: int) -> Optional[str]:
    from benchmark.synthetic.generate import perturbation_changes_nothing

    return perturbation_changes_nothing(preset, (family_name, 1.0), seed=seed, frames=frames)


def unchanged_families(config: SuiteConfig) -> dict[str, str]:
    """The suite's families that change nothing on the base preset at any of its seeds: family -> why."""
    out = {}
    for name in config.families:
        reasons = {changes_nothing(config, name, seed) for seed in config.seeds}
        if reasons and None not in reasons:
            out[name] = "; ".join(sorted(reasons))
    return out


def skipped(config: SuiteConfig, key: RunKey) -> bool:
    """Whether the run is not made: its family does not apply to its method (:func:`applies`), or it is a
    perturbed run of a family that changes nothing on its seed's scene."""
    return not applies(key) or (not key.clean and changes_nothing(config, key.family, key.seed) is not None)


def _generate(config: SuiteConfig, out: Path, perturbation: Optional[tuple], seed: int) -> Path:
    from benchmark.synthetic.generate import generate

    return Path(generate(config.preset, out, size=config.size, frames=config.frames, seed=int(seed),
                         overwrite=True, perturbation=perturbation))


SCENE_STAMP = "stress_scene"
"""Key of the suite's stamp in a scene's ``bench4d_meta.json``: the generator code that last checked the
scene and the scene's digest then."""


def current_scene(folder: Path, make: Callable[[Path], Path]) -> Path:
    """``folder`` as ``make`` (the generator) makes it with today's code. A cached scene stamped by other
    generator code is made again beside it and compared by digest: the same scene keeps its folder (and
    so its runs); another replaces it, and the runs measured on the old one are stale (:func:`results_file`
    compares the digest they recorded)."""
    from benchmark.core.atomic import write_json
    from benchmark.synthetic.digest import META_FILE, generator_code, scene_digest

    code = generator_code()
    stamp = _scene_stamp(folder)
    if stamp is not None and stamp.get("code") == code:
        return folder
    if (folder / "annotations.json").is_file():
        fresh = make(folder.parent / f".{folder.name}.check-{os.getpid()}")
        digest = scene_digest(fresh)
        try:
            old = scene_digest(folder)
        except Exception:  # noqa: BLE001 - a damaged cached scene is made again
            old = None
        if old != digest:
            trash = folder.parent / f".{folder.name}.replaced-{os.getpid()}"
            os.replace(folder, trash)
            os.replace(fresh, folder)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            shutil.rmtree(fresh, ignore_errors=True)
    else:
        digest = scene_digest(make(folder))
    meta = read_json(folder / META_FILE)
    meta[SCENE_STAMP] = {"code": code, "digest": digest}
    write_json(folder / META_FILE, meta)
    return folder


def _scene_stamp(folder: Path) -> Optional[dict]:
    from benchmark.synthetic.digest import META_FILE

    try:
        stamp = read_json(folder / META_FILE).get(SCENE_STAMP)
    except Exception:  # noqa: BLE001 - missing or unreadable: the scene is checked again
        return None
    return stamp if isinstance(stamp, dict) and (folder / "annotations.json").is_file() else None


# -- supervision noise ----------------------------------------------------------------------------------
def _noise_rng(family_name: str, strength: float, seed: int, frame: str = "") -> np.random.Generator:
    return np.random.default_rng([int(seed), zlib.crc32(family_name.encode()), int(round(strength * 1e6)),
                                  zlib.crc32(frame.encode())])


def _disk(radius: int) -> np.ndarray:
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def erode_levels(levels: np.ndarray, radius: int) -> np.ndarray:
    """(3, H, W) mask indices with every mask eroded by ``radius`` pixels (removed pixels: -1)."""
    import cv2

    out = levels.copy()
    if radius <= 0:
        return out
    kernel = _disk(radius)
    for lv in range(levels.shape[0]):
        for index in np.unique(levels[lv][levels[lv] >= 0]):
            mask = (levels[lv] == index).astype(np.uint8)
            out[lv][(mask > 0) & (cv2.erode(mask, kernel, borderType=cv2.BORDER_REPLICATE) == 0)] = -1
    return out


def dilate_levels(levels: np.ndarray, radius: int) -> np.ndarray:
    """(3, H, W) mask indices with every mask grown by ``radius`` pixels over the pixels no mask covers and the
    pixels of larger masks at its level: a part spills over what surrounds it, as a loose segmenter's mask does.
    Where several masks reach one pixel the smallest takes it (equal areas: the lower index). Oracle masks cover
    every pixel (the background is a mask), so growing into uncovered pixels alone would change nothing."""
    import cv2

    out = levels.copy()
    if radius <= 0:
        return out
    kernel = _disk(radius)
    for lv in range(levels.shape[0]):
        indices, areas = np.unique(levels[lv][levels[lv] >= 0], return_counts=True)
        area_of = dict(zip(indices.tolist(), areas.tolist()))
        # the area of each pixel's owner so far (uncovered: larger than any mask)
        owner_area = np.full(levels.shape[1:], np.inf)
        for index, area in area_of.items():
            owner_area[levels[lv] == index] = area
        for index in indices.tolist():  # ascending, so among equal areas the lower index keeps a pixel
            grown = cv2.dilate((levels[lv] == index).astype(np.uint8), kernel) > 0
            take = grown & (area_of[index] < owner_area)
            out[lv][take] = index
            owner_area[take] = area_of[index]
    return out


def drop_masks(levels: np.ndarray, share: float, rng: np.random.Generator) -> np.ndarray:
    """(3, H, W) mask indices with each mask removed (its pixels -1) with probability ``share``."""
    out = levels.copy()
    for lv in range(levels.shape[0]):
        for index in np.unique(levels[lv][levels[lv] >= 0]):
            if rng.random() < share:
                out[lv][levels[lv] == index] = -1
    return out


def shuffle_features(features: tuple, rng: np.random.Generator) -> tuple:
    """Per level, the mask features moved round a random cycle: every mask (of two or more) carries the
    feature of another."""
    out = []
    for feats in features:
        cycle = rng.permutation(feats.shape[0])
        source = np.empty_like(cycle)
        source[cycle] = np.roll(cycle, -1)
        out.append(feats[source])
    return tuple(out)


def noisy_frame(frame, family_name: str, strength: float, seed: int, width: int):
    """One :class:`methods.supervision.base.FrameSupervision` with the family's noise."""
    rng = _noise_rng(family_name, strength, seed, frame.name)
    radius = int(round(strength * width / REFERENCE_WIDTH))
    if family_name == "mask-erode":
        return replace(frame, levels=erode_levels(frame.levels, radius))
    if family_name == "mask-dilate":
        return replace(frame, levels=dilate_levels(frame.levels, radius))
    if family_name == "mask-drop":
        return replace(frame, levels=drop_masks(frame.levels, strength, rng))
    if family_name == "mask-id-swap":
        return replace(frame, features=shuffle_features(frame.features, rng)) if rng.random() < strength else frame
    raise InputError(None, "family", f"{family_name!r} is no mask-noise family")


MASK_FAMILIES = ("mask-erode", "mask-dilate", "mask-id-swap", "mask-drop")


def noisy_supervision(supervision, family_name: str, strength: float, seed: int):
    """``supervision`` with the family's noise on every training frame, under a fingerprint of its own
    (fits on it are cached apart from the clean ones). Strength 0 returns it as it is."""
    if strength == 0:
        return supervision
    width = max(int(f.levels.shape[-1]) for f in supervision.frames)
    frames = [noisy_frame(f, family_name, strength, seed, width) for f in supervision.frames]
    # the noisy masks and features themselves, not only the family's name: fits are cached by this
    # fingerprint, so a perturbation whose code changes must not find the fits of its former output
    content = hashlib.sha256()
    for f in frames:
        content.update(np.ascontiguousarray(f.levels).tobytes())
        for level_features in f.features:
            content.update(np.ascontiguousarray(level_features).tobytes())
    tag = f"{supervision.fingerprint}|{family_name}|{strength!r}|{seed}|{content.hexdigest()}"
    return replace(supervision, frames=frames, fingerprint=hashlib.sha256(tag.encode()).hexdigest()[:24])


# -- caption noise ----------------------------------------------------------------------------------------
def _state_signature(truth, stateful: list[str], time_index: int) -> tuple:
    return tuple(truth.state_at(name, time_index)["state"] for name in stateful)


def swapped_captions(scene, share: float, seed: int, captions_seed: int = 0):
    """(captions, tracks): the template captioner's captions of ``scene`` with a ``share`` of them (per
    frame and object, drawn with ``seed``) replaced by a caption the object had in another state."""
    from methods.captioners import get_captioner
    from methods.captioners.base import caption_objects
    from methods.captioners.tracks import truth_tracks, whole_of
    from methods.supervision.truth_access import open_truth

    tracks = truth_tracks(scene)
    captions = caption_objects(get_captioner("template", scene, seed=captions_seed), scene, tracks)
    truth = open_truth(scene)
    stateful: dict[int, list[str]] = {}
    for name in truth.stateful_objects:
        level, ids = truth.ids_named(name)
        for id_ in ids:
            stateful.setdefault(whole_of(truth, level, id_), []).append(name)
    time_of = {f.name: f.time_index for f in scene.frames}
    frames = dict(captions.frames)
    for (frame, obj), text in sorted(captions.frames.items()):
        names = stateful.get(obj)
        rng = _noise_rng("caption-swap", share, seed, f"{frame}|{obj}")
        if not names or rng.random() >= share:
            continue
        own = _state_signature(truth, names, time_of[frame])
        others = sorted(f for (f, o) in captions.frames if o == obj
                        and _state_signature(truth, names, time_of[f]) != own)
        if others:
            frames[(frame, obj)] = captions.frames[(others[int(rng.integers(len(others)))], obj)]
    return replace(captions, frames=frames), tracks


def caption_options(config: SuiteConfig, key: RunKey, scene_root: Optional[Path]) -> dict[str, str]:
    """The method options that feed a run of ``caption-swap`` its noisy captions (a captions file, written
    from ``scene_root`` when missing; ``None``: only named)."""
    from benchmark.loaders import load_scene
    from methods.captioners.file import write_captions_file

    path = config.stress_dir / "captions" / f"swap-{strength_label(key.strength)}-seed{key.seed}.json"
    if scene_root is not None and not path.is_file():
        captions, tracks = swapped_captions(load_scene(scene_root), key.strength, key.seed)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_captions_file(path, captions, tracks, overwrite=True)
    return {"captions.captioner": "file", "captions.file": str(path.resolve()), "captions.object_tracks": "truth"}


def reads_captions(method: str) -> bool:
    """Whether ``method``'s config has a ``captions`` group (a method fitted on captions)."""
    from methods import registry

    return hasattr(registry.get(method).make_config({}), "captions")


# -- query wording ----------------------------------------------------------------------------------------
def paraphrases(root: Path, aset) -> dict[str, list[str]]:
    """Query text -> other words for it: an object's synonyms, a state's captions."""
    from benchmark.core.truth import load_truth

    truth = load_truth(root)
    out: dict[str, list[str]] = {}
    for query in aset.queries:
        if query.kind == "agnostic":
            level, ids = truth.ids_named(query.text)
            out[query.text] = sorted({s for id_ in ids for s in truth.synonyms(level, id_)} - {query.text})
    for timeline in truth.timelines(allow_eval=True):  # wording only: the captions, not the intervals
        for state in timeline["states"]:
            out[state["phrase"]] = [c for c in state["captions"] if c != state["phrase"]]
    return out


def reworded_queries(root: Path, aset, share: float, seed: int) -> dict[str, str]:
    """Query text -> the words it is asked in, for a ``share`` of the queries (drawn with ``seed``)."""
    options = paraphrases(root, aset)
    out = {}
    for query in aset.queries:
        rng = _noise_rng("query-paraphrase", share, seed, query.text)
        words = options.get(query.text) or []
        if words and rng.random() < share:
            out[query.text] = words[int(rng.integers(len(words)))]
    return out


class RewordedModel:
    """A fitted model asked its queries in other words (answers are scored as the original query's)."""

    def __init__(self, model, wording: dict[str, str]) -> None:
        self._model = model
        self._wording = dict(wording)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._model, name)

    def prepare(self, texts: Sequence[str]) -> None:
        if hasattr(self._model, "prepare"):
            self._model.prepare([self._wording.get(t, t) for t in texts])

    def query_agnostic(self, text: str, frames):
        return self._model.query_agnostic(self._wording.get(text, text), frames)

    def query_sensitive(self, text: str, frames):
        return self._model.query_sensitive(self._wording.get(text, text), frames)


# -- runs ---------------------------------------------------------------------------------------------------
def run_keys(config: SuiteConfig) -> list[RunKey]:
    """Every run of the suite, clean runs once, in the order they are run (cheap families first)."""
    keys: list[RunKey] = []
    seen: set = set()
    for method in config.methods:
        for seed in config.seeds:
            for fam in config.families:
                for strength in config.strengths_of(fam):
                    key = RunKey(CLEAN if strength == 0 else fam, strength, method, seed)
                    if key not in seen:
                        seen.add(key)
                        keys.append(key)
    return keys


CAPTION_FAMILIES = ("caption-swap", "caption-lag")
"""Families that change a method's captions (they apply to methods with a ``captions`` group only)."""


def applies(key: RunKey) -> bool:
    """Whether the family changes anything for the method (caption noise needs a captioned method)."""
    return key.clean or key.family not in CAPTION_FAMILIES or reads_captions(key.method)


def run_options(config: SuiteConfig, key: RunKey, scene_root: Optional[Path]) -> dict[str, str]:
    """The method options of a run: the suite's for its method, a caption-swap run's captions file
    (:func:`caption_options`; ``scene_root`` None: named, not written) and a caption-lag run's extra lag."""
    options = dict(config.method_options.get(key.method, {}))
    if key.family == "caption-swap" and not key.clean:
        options.update(caption_options(config, key, scene_root))
    if key.family == "caption-lag" and not key.clean:
        from benchmark.core.caption_noise import LAG_SUFFIX

        options["captions.noise"] = f"scene{LAG_SUFFIX}{strength_label(key.strength)}"
    return options


def results_file(config: SuiteConfig, key: RunKey) -> Optional[Path]:
    """The run's results file, if it was written with the method config the run has now, on the scene the
    generator makes now: a file of a config since changed (a default that moved) or of a scene since
    changed is stale, neither read nor reported, and is redone."""
    from benchmark.results import results_path
    from methods import registry

    # any dataset and scene folder under the run's folder, the rest as results_path places a run's file
    pattern = results_path(".", "*", "*", key.method, TRACK, key.seed, config.split)
    found = sorted(key.folder(config.runs_dir).glob(pattern.as_posix()))
    if not found:
        return None
    try:
        doc = read_json(found[0])
    except InputError:  # a damaged results file: the run is made anew
        return None
    if not isinstance(doc, dict) or not registry.get(key.method).recorded_as(doc.get("method_config"),
                                                                            run_options(config, key, None)):
        return None
    # a run measured on a scene the generator no longer makes is stale too
    scene = scene_folder(config, key.family, key.strength, key.seed)
    recorded = ((doc.get("scene_info") or {}).get("generated") or {}).get("digest")
    return found[0] if recorded == (_scene_stamp(scene) or {}).get("digest") else None


def run_one(config: SuiteConfig, key: RunKey, log: Callable[[str], None] = print) -> Optional[Path]:
    """The run's results file: read where it exists (unless ``force``), else the run is made."""
    if not applies(key):
        return None
    existing = results_file(config, key)
    if existing is not None and not config.force:
        return existing
    from benchmark.runner import EvalOptions, answer_queries, obtain_fit, prepare_run, score_and_write

    start = time.perf_counter()
    root = scene_folder(config, key.family, key.strength, key.seed)
    options = run_options(config, key, root)
    prepared = prepare_run(EvalOptions(
        method=key.method, scene=str(root), seed=key.seed, split=config.split, results_dir=key.folder(config.runs_dir),
        cache_dir=Path(config.cache_dir), device=config.device, method_options=options, quiet=True,
        timing_frames=1, timing_repeats=1, refit=config.force))
    if key.family in MASK_FAMILIES:
        prepared.supervision = noisy_supervision(prepared.supervision, key.family, key.strength, key.seed)
    fit = obtain_fit(prepared)
    model = fit.model
    if key.family == "query-paraphrase" and not key.clean:
        model = RewordedModel(model, reworded_queries(prepared.root, prepared.annotations, key.strength, key.seed))
    outcome = score_and_write(prepared, fit, answer_queries(prepared, model))
    log(f"{key.method} {key.family} {strength_label(key.strength)} seed{key.seed}: "
        + score_line(outcome.results["metrics"])
        + f" ({time.perf_counter() - start:.0f} s)")
    return outcome.path


# -- collected scores ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Score:
    """One run's scores."""

    family: str
    strength: float
    method: str
    seed: int
    metrics: dict
    """Metric name -> value (None where the scene has no query of that kind)."""
    path: Optional[Path]
    """Its results file (None: a score kept in the report's ``scores.csv`` whose results file is not here)."""
    wall_seconds: float
    scene_digest: str = ""
    """Digest of the generated scene it was measured on."""
    config_digest: str = ""
    """:func:`config_digest` of the method config it ran with."""
    machine: str = ""
    """The kind of machine it ran on (:func:`benchmark.results.machine_of`'s ``machine_kind``)."""

    @property
    def run(self) -> tuple:
        """The run it is: a clean run shared by every family is one run."""
        return (CLEAN if self.strength == 0 else self.family, self.strength, self.method, self.seed)


def collect(config: SuiteConfig) -> list[Score]:
    """The scores of every run of the suite, the clean runs under every family: from its results file, or
    else kept from the report's ``scores.csv`` (:func:`kept_scores`) while its digests are current."""
    from benchmark.results import machine_of

    kept = kept_scores(config)
    out = []
    for method in config.methods:
        for seed in config.seeds:
            for fam in config.families:
                for strength in config.strengths_of(fam):
                    key = RunKey(CLEAN if strength == 0 else fam, strength, method, seed)
                    if skipped(config, RunKey(fam, strength, method, seed)):
                        continue
                    path = results_file(config, key)
                    if path is not None:
                        doc = read_json(path)
                        scene = ((doc.get("scene_info") or {}).get("generated") or {}).get("digest") or ""
                        out.append(Score(fam, strength, method, seed, {m: doc["metrics"].get(m) for m in METRICS},
                                         path, float(doc.get("wall_seconds") or 0.0), scene,
                                         config_digest(config, key), machine_of(doc)["machine_kind"]))
                    elif (key.family, strength, method, seed) in kept:
                        out.append(replace(kept[key.family, strength, method, seed], family=fam))
    return out


def config_digest(config: SuiteConfig, key: RunKey) -> str:
    """A digest of the method config the run has today and the split it scores (a caption-swap run's captions
    file by its name in the suite's folder, so a moved cache keeps it)."""
    from benchmark.core.cache_keys import stable_hash
    from benchmark.runner import config_dict
    from methods import registry

    options = run_options(config, key, None)
    if "captions.file" in options:
        options["captions.file"] = Path(options["captions.file"]).name
    recorded = config_dict(registry.get(key.method).make_config(options))
    if config.split != DEFAULT_EVAL_SPLIT:  # the paper split's digests stay those written before splits
        recorded = {"config": recorded, "split": config.split}
    return stable_hash(recorded, 12)


def scene_digest_now(config: SuiteConfig, key: RunKey) -> str:
    """Digest of the scene the run reads, as the generator makes it today."""
    return (_scene_stamp(scene_folder(config, key.family, key.strength, key.seed)) or {}).get("digest") or ""


def kept_scores(config: SuiteConfig) -> dict[tuple, Score]:
    """The suite's runs in the report's ``scores.csv`` (``config.out_dir``) that are current, by :attr:`Score.run`:
    written with both digests, equal to today's scene and method config. A row without them (a table
    written before they were recorded) or with another is not kept: the run is made again."""
    csv = Path(config.out_dir) / SCORES_FILE
    if not csv.is_file():
        return {}
    # only this suite's runs: checking a row's scene digest generates its scene, which a run outside the
    # suite (another family or strength in the table) does not need
    wanted = {(key.family, key.strength, key.method, key.seed) for key in run_keys(config)}
    out = {}
    for score in read_scores_table(csv):
        if not score.scene_digest or not score.config_digest or score.run not in wanted:
            continue
        key = RunKey(*score.run)
        if (score.config_digest == config_digest(config, key)
                and score.scene_digest == scene_digest_now(config, key)):
            out[score.run] = score
    return out


SCORES_FILE = "scores.csv"
"""The report's table of every run's scores (with the digests that keep a run current)."""
_SCORE_COLUMNS = ("family", "strength", "method", "seed", *METRICS, "wall_seconds", "scene_digest", "config_digest",
                  "machine")


def read_scores_table(csv: Path) -> list[Score]:
    """The runs of a written ``scores.csv`` as :class:`Score` records (no results file behind them); the
    digest columns may be missing (a table written before they were recorded)."""
    import pandas as pd

    if not Path(csv).is_file():
        raise InputError(csv, None, "no stress scores here: run bench4d stress first")
    try:
        table = pd.read_csv(csv, dtype={"family": str, "method": str, "scene_digest": str, "config_digest": str,
                                        "machine": str})
    except (ValueError, pd.errors.ParserError) as exc:
        raise InputError(csv, None, f"not a readable scores table ({exc})") from None
    for column in ("family", "strength", "method", "seed", *METRICS):
        if column not in table.columns:
            raise InputError(csv, column, "column missing: not a stress scores table")
    unknown = sorted(set(table["family"]) - set(FAMILIES))
    if unknown:
        raise InputError(csv, "family", f"unknown family {unknown[0]!r}")

    def text(row, name: str) -> str:
        value = getattr(row, name, "")
        return "" if pd.isna(value) else str(value)

    try:
        return [Score(r.family, float(r.strength), r.method, int(r.seed),
                      {m: None if pd.isna(getattr(r, m)) else float(getattr(r, m)) for m in METRICS}, None,
                      float(getattr(r, "wall_seconds", 0.0) or 0.0), text(r, "scene_digest"),
                      text(r, "config_digest"), text(r, "machine")) for r in table.itertuples(index=False)]
    except (TypeError, ValueError) as exc:
        raise InputError(csv, None, f"a row that is not a score ({exc})") from None


def write_scores_table(scores: Sequence[Score], path: Path) -> Path:
    """``scores.csv``: one row per (family, strength, method, seed), the clean runs under every family. A
    table there already whose runs this one drops (stale ones, or all of a table written without digests)
    is kept beside it as ``scores-replaced-<UTC time>.csv``: no measurement is lost by rewriting."""
    import csv
    import io

    from benchmark.core.atomic import write_text

    rows = sorted(scores, key=lambda s: (s.family, s.strength, s.method, s.seed))
    table = io.StringIO()
    writer = csv.writer(table, lineterminator="\n")  # quotes a cell (a CPU model) that holds a comma
    writer.writerow(_SCORE_COLUMNS)
    for s in rows:
        cells = ["" if s.metrics.get(m) is None else f"{s.metrics[m]:.3f}" for m in METRICS]
        writer.writerow([s.family, strength_label(s.strength), s.method, s.seed, *cells, f"{s.wall_seconds:.1f}",
                         s.scene_digest, s.config_digest, s.machine])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.is_file():
        try:
            before = {(s.family, s.strength, s.method, s.seed) for s in read_scores_table(path)}
        except InputError:
            before = {None}  # unreadable: kept as it is
        keep_replaced_table(path, before, {(s.family, s.strength, s.method, s.seed) for s in rows})
    write_text(path, table.getvalue())
    return path


def mean_by_strength(scores: Sequence[Score], fam: str, method: str, metric: str) -> dict[float, list[float]]:
    """Strength -> the seeds' values of ``metric`` (runs without a value left out)."""
    out: dict[float, list[float]] = {}
    for s in scores:
        value = s.metrics.get(metric)
        if s.family == fam and s.method == method and value is not None:
            out.setdefault(s.strength, []).append(float(value))
    return dict(sorted(out.items()))


def seed_interval(values: Sequence[float]) -> tuple[float, float]:
    """The 95 % bootstrap interval of the mean of one cell's seeds (:mod:`benchmark.stats`: seeds resampled
    with replacement; one seed gives its value at both ends)."""
    from benchmark.stats import bootstrap_means, percentile_interval, stable_seed

    column = np.asarray(values, dtype=np.float64)[:, None]  # (seeds, 1)
    replicates = bootstrap_means({"cell": [column]}, resample_queries=False, seed=stable_seed(*values))["cell"]
    return percentile_interval(replicates)


def breaking_point(values: dict[float, list[float]]) -> Optional[float]:
    """The first strength whose interval over seeds (:func:`seed_interval`) lies wholly below half of the clean
    (strength 0) interval, i.e. its upper end below half the clean lower end: a drop outside the seed noise.
    None if no strength's does, or there is no clean score. With one seed per cell this is the seed's value
    against half the clean value."""
    if 0.0 not in values or not values[0.0]:
        return None
    line = break_line(values)
    for strength, seeds in values.items():
        if strength > 0 and seeds and seed_interval(seeds)[1] < line:
            return strength
    return None


def break_line(values: dict[float, list[float]]) -> float:
    """Half the clean (strength 0) interval's lower end: a strength's interval wholly below it is a break
    (:func:`breaking_point`), wholly at or above it a hold (:func:`held_at`), across it inside the seed noise."""
    return 0.5 * seed_interval(values[0.0])[0]


def held_at(values: dict[float, list[float]], strength: float) -> bool:
    """Whether the interval over seeds at ``strength`` lies wholly at or above :func:`break_line`: held outside
    the seed noise."""
    return seed_interval(values[strength])[0] >= break_line(values)


def run_suite(config: SuiteConfig, log: Callable[[str], None] = print) -> list[Score]:
    """Run every run of the suite that has neither a results file nor a kept score (:func:`kept_scores`),
    then return the scores."""
    from benchmark.results import exclusive_lock

    keys = run_keys(config)
    kept = {} if config.force else kept_scores(config)
    deferred: list[RunKey] = []
    for name, why in unchanged_families(config).items():
        log(f"{name}: not run, it changes nothing on {config.preset}: {why}")
    for k, key in enumerate(keys, start=1):
        if skipped(config, key) or (key.family, key.strength, key.method, key.seed) in kept:
            continue
        name = f"{key.method} {key.family} {strength_label(key.strength)} seed{key.seed}"
        with exclusive_lock(claim_file(config, key), wait=False) as claimed:
            if not claimed:
                log(f"[{k}/{len(keys)}] {name}: another process runs it; back to it at the end")
                deferred.append(key)
                continue
            if results_file(config, key) is None or config.force:
                log(f"[{k}/{len(keys)}] {name}")
            run_one(config, key, log)
    for key in deferred:  # wait for the other process, then read its results file (or run it, if it died)
        with exclusive_lock(claim_file(config, key)):
            run_one(replace(config, force=False), key, log)  # made just now, even under --force
    return collect(config)


def claim_file(config: SuiteConfig, key: RunKey) -> Path:
    """The lock a process holds while it makes a run, so two suites started on one cache (one per core)
    share the runs out rather than make the same run side by side."""
    return config.runs_dir / ".claims" / f"{key.family}-{strength_label(key.strength)}-{key.method}-seed{key.seed}.lock"
