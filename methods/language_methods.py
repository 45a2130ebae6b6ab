"""What ``langsplat``, ``deformable-clip`` and ``4d-langsplat`` share: geometry, autoencoder, field, query.

The three methods differ only in their geometry and their time-sensitive behaviour:

=================  ==============  ================================================================
method             geometry        time-sensitive answer
=================  ==============  ================================================================
``langsplat``      static 3D-GS    relevance score (mean relevance inside the spatial mask); time
                                   is ignored by the geometry (Qin et al., CVPR 2024)
``deformable-clip`` 4D-GS          relevance score, as the paper's baseline
``4d-langsplat``   4D-GS           the status field (a :class:`TimeVaryingHead`,
                                   :mod:`methods.time_sensitive`)
=================  ==============  ================================================================

Fitting (:func:`fit_language_field`):

1. **Geometry** (:func:`fit_geometry`): 3D-GS or 4D-GS on the training frames' RGB with the Gaussian
   core's trainer, then frozen (:class:`~methods.fields.language_field.FrozenGeometry`). Cached per
   (scene's training data, geometry kind, geometry options, seed, device kind, the code digest of the
   Gaussian core's trainer) under ``<cache>/language/<dataset>-<scene>/``, so every 4D-GS method
   (``deformable-clip``, ``4d-langsplat``, ``non-status-field``, ``feature-3dgs``,
   ``gaussian-grouping``) shares ONE 4D-GS fit.
2. **Autoencoder** D -> ``autoencoder.latent_dim`` on the distinct mask features of all levels and
   training frames, drawn as ``autoencoder.sample_weighting`` says (default: once per mask and image, as
   the release's autoencoder data), at least ``autoencoder.min_steps`` steps; its reconstruction cosine is
   recorded. With the ``extensions.unmasked_text`` extension (the ``+`` variants: "background"; off in the
   papers' configs, as the release), pixels that no mask covers first become one more mask per level named
   by it (:func:`with_unmasked_as`): the paper's SAM masks cover the background, the oracle segmenter does
   not, and unsupervised Gaussians decode to arbitrary features.
3. **Field** (:func:`~methods.fields.language_field.train_language_field`): per-Gaussian latents of
   the three levels on the frozen geometry, L1 inside valid masks. Cached per (geometry, supervision
   fingerprint, autoencoder and field options, seed, the code digest of this module), shared like
   the geometry.

Querying (:class:`LanguageFieldModel`): render the 3 x ``autoencoder.latent_dim`` latent channels at the frame's
camera and time in one rasterizer call, decode each level, and run the protocol's
:func:`~methods.fields.relevance.query_levels` (relevance against the canonical phrases, 29x29
smoothing, min-max threshold, 7x7 majority filter, level with the highest peak) on exactly reduced
features (:func:`~methods.fields.language_field.decode_for_relevance`).
"""

from __future__ import annotations

import abc
import dataclasses
import functools
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from benchmark.core.atomic import atomic_path, write_json
from benchmark.core.cache_keys import code_digest, scene_fingerprint, stable_hash
from benchmark.core.errors import InputError
from benchmark.core.memory import StagePeak
from benchmark.core.scene import DEFAULT_EVAL_SPLIT, EVAL_SPLITS_KEY, Frame, Scene, scene_split_frames

from .api import AgnosticAnswer, Method, Model, Progress, SensitiveAnswer
from .fields.autoencoder import AutoencoderConfig, FeatureAutoencoder, train_autoencoder
from .fields.configs import AE_SAMPLE_WEIGHTINGS
from .fields.language_field import (DecodeTable, FieldTarget, FrozenGeometry, LanguageField, LanguageFieldConfig,
                                    decode_for_relevance, matmul_precision, make_target, project_phrases,
                                    relevance_basis, train_language_field)
from .fields.relevance import AgnosticResult, encode_canonical, query_levels, spatial_mask  # noqa: F401
from .specs._language import LanguageMethodConfig
from .specs._recorded import config_from_record
from .supervision.base import LEVELS, Supervision, TextEncoder

MODEL_FILE = "language_model.pt"
META_FILE = "language_model.json"
HEAD_DIR = "time_varying"
CACHE_SUBDIR = "language"

HELD_OUT_PSNR_FRAMES = 16
"""At most this many held-out frames of an evaluation split (evenly spaced over it) are rendered for the
geometry's held-out PSNR on it (``info["test_psnr"]``: the paper split; ``info["novel_view_psnr"]``)."""
NOVEL_VIEW_SPLIT = "novel-view"
"""The evaluation split of held-out cameras (:data:`benchmark.core.scene.EVAL_SPLITS`) scored apart in
:func:`held_out_psnr`."""

GEOMETRY_CODE = "methods.gaussians.train"
"""The module that runs a geometry fit: its code digest (with every module it imports) is part of the
geometry cache key."""
FIELD_CODE = "methods.language_methods"
"""The module that runs a field fit (this one): its code digest is part of the field cache key."""


def _stable_hash(obj: Any) -> str:
    return stable_hash(obj, 24)


def device_kind(device: str | torch.device) -> str:
    return "cuda" if torch.device(device).type == "cuda" else "cpu"


# ---------------------------------------------------------------------------------------------------
# The parts' configs: what the Gaussian core and the field read, from the method config's groups
# ---------------------------------------------------------------------------------------------------
def recon_config(config: LanguageMethodConfig, seed: int):
    """The Gaussian core's :class:`~methods.gaussians.config.ReconConfig` for the ``geometry`` group of
    ``config`` (the core's recipe constants are its own defaults)."""
    from methods.gaussians.config import DeformationConfig, GaussianConfig, HexPlaneConfig, ReconConfig

    g = config.geometry
    gaussians = GaussianConfig(max_gaussians=g.max_gaussians,
                               gaussians_per_foreground_pixel=g.gaussians_per_foreground_pixel)
    deformation = DeformationConfig(hexplane=HexPlaneConfig(spatial_resolution=g.hexplane_resolution))
    return ReconConfig(gaussians=gaussians, deformation=deformation, static_iterations=g.static_iterations,
                       deformation_iterations=g.deformation_iterations, reference_iterations=g.static_model_iterations,
                       seed=seed)


def autoencoder_config(config: LanguageMethodConfig, num_features: Optional[int] = None) -> AutoencoderConfig:
    """The ``autoencoder`` group of ``config``; with ``num_features`` (distinct features) its epochs raised to
    run at least ``min_steps`` steps (:meth:`~methods.fields.configs.AutoencoderConfig.for_features`)."""
    return config.autoencoder if num_features is None else config.autoencoder.for_features(num_features)


def autoencoder_inputs(supervision: Supervision,
                       config: LanguageMethodConfig) -> tuple[np.ndarray, np.ndarray, AutoencoderConfig]:
    """What the scene's autoencoder trains on: the distinct mask features of ``supervision`` (give it
    :func:`with_unmasked_as` first, as the fit does), their sampling weights under
    ``autoencoder.sample_weighting``, and the autoencoder's config."""
    feats, weights = distinct_features(supervision, config.autoencoder.sample_weighting)
    return feats, weights, autoencoder_config(config, feats.shape[0])


def field_config(config: LanguageMethodConfig) -> LanguageFieldConfig:
    """The field's config: the ``field`` group of ``config`` with the field's shape (three levels of the
    autoencoder's latent) and the geometry's rasterizer."""
    return LanguageFieldConfig(**dataclasses.asdict(config.field), num_levels=len(LEVELS),
                               latent_dim=config.autoencoder.latent_dim,
                               render_backend=config.geometry.render_backend)


def config_to_dict(config: Any) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(config), default=str))


# ---------------------------------------------------------------------------------------------------
# Shared cache
# ---------------------------------------------------------------------------------------------------
def shared_cache_root(config: LanguageMethodConfig, work_dir: Optional[Path]) -> Optional[Path]:
    """Root of the shared geometry/field cache: ``config.shared_cache_dir``, else the runner's cache
    folder (the runner's ``work_dir`` is ``<cache>/fits/<method>/<scene>/<key>.work``), else ``None``."""
    if config.shared_cache_dir:
        return Path(config.shared_cache_dir)
    if work_dir is None:
        return None
    for parent in Path(work_dir).resolve().parents:
        if parent.name == "fits":
            return parent.parent
    return None


def scene_cache_folder(root: Path, scene: Scene) -> Path:
    return root / CACHE_SUBDIR / f"{scene.dataset}-{scene.name}"


def _torch_load(path: Path, device: str | torch.device) -> Optional[dict]:
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except Exception:  # a corrupt or incompatible cache file is refitted, never trusted
        return None


def _torch_save(path: Path, obj: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


# ---------------------------------------------------------------------------------------------------
# 1. geometry
# ---------------------------------------------------------------------------------------------------
@dataclass
class GeometryFit:
    geometry: FrozenGeometry
    key: str
    info: dict
    cached: bool


def geometry_key(scene: Scene, kind: str, config: LanguageMethodConfig, seed: int, device: str) -> str:
    return _stable_hash({"kind": kind, "recon": config_to_dict(recon_config(config, seed)), "seed": seed,
                         "device": device_kind(device), "scene": scene_fingerprint(scene, scene.train_frames),
                         "code": code_digest(GEOMETRY_CODE)})


def fit_geometry(scene: Scene, kind: str, config: LanguageMethodConfig, *, seed: int, device: str,
                 progress: Progress, cache_root: Optional[Path]) -> GeometryFit:
    """Static 3D-GS (``kind="3dgs"``) or 4D-GS (``"4dgs"``) on the training frames, cached (see module docstring)."""
    if kind not in ("3dgs", "4dgs"):
        raise ValueError(f"geometry kind must be '3dgs' or '4dgs', got {kind!r}")
    key = geometry_key(scene, kind, config, seed, device)
    path = None if cache_root is None else scene_cache_folder(cache_root, scene) / f"geometry-{kind}-{key}.pt"
    if path is not None and path.is_file():
        saved = _torch_load(path, device)
        if saved is not None and saved.get("key") == key:
            progress.log(f"geometry: cached {kind} fit {path.name}")
            return GeometryFit(FrozenGeometry.from_state_dict(saved["geometry"], device), key,
                               json.loads(saved["info"]), True)
    from methods.gaussians.rasterize import rasterize
    from methods.gaussians.train import Checkpointing, Trainer

    recon = recon_config(config, seed)
    # an interrupted geometry fit (the longest stage of a run on the CPU) resumes from its checkpoint
    checkpoint = None if path is None else Checkpointing(path.with_name(path.stem + ".partial.pt"), key)
    trainer = Trainer(scene, recon, device=device,
                      rasterize_fn=functools.partial(rasterize, backend=config.geometry.render_backend),
                      progress=progress,
                      checkpoint=checkpoint)
    resuming = checkpoint is not None and checkpoint.path.is_file()
    progress.log(f"geometry: fitting {kind} on {len(trainer.views)} training views (cap {trainer.cap} Gaussians)"
                 + (f"; resuming from {checkpoint.path.name} if it is this fit's" if resuming else ""))
    start = time.perf_counter()
    with StagePeak(device) as peak:  # reused from the cache by other runs, which are charged this peak
        result = trainer.fit_3dgs() if kind == "3dgs" else trainer.fit_4dgs()
    seconds = time.perf_counter() - start
    geometry = FrozenGeometry(result.model)
    info = {"kind": kind, "key": key, "seconds": result.fit_seconds, "session_seconds": seconds, **peak.record(),
            "resumed_at": result.resumed_at, "gaussians": geometry.num_gaussians,
            "cap": result.cap, "extent": result.extent,
            "stages": [{k: v for k, v in s.items() if k != "events"} for s in result.stages]}
    if geometry.deformable is not None:
        info["dynamic_gaussians"] = geometry.deformable.num_dynamic()
    info.update(held_out_psnr(result.model, scene, trainer.rasterize, device))
    if path is not None:
        _torch_save(path, {"key": key, "geometry": geometry.state_dict(), "info": json.dumps(info)})
    return GeometryFit(geometry, key, info, False)


def held_out_psnr(model: object, scene: Scene, rasterize_fn, device: str) -> dict:
    """``test_psnr`` (dB, mean over frames) and ``test_psnr_frames`` of a fitted geometry (colours still on) on
    at most :data:`HELD_OUT_PSNR_FRAMES` of the ``paper`` evaluation split's frames
    (:func:`benchmark.core.scene.scene_split_frames`); where the scene records a ``novel-view`` split, also
    ``novel_view_psnr`` and ``novel_view_psnr_frames`` on that split's frames (the same cap). A PSNR is
    ``None`` where its split has no frames.

    A score for reports (the capacity study charts it against the Gaussian budget): it reads held-out
    images once the fit is done and changes nothing fitted. The splits are scored apart: the novel views are
    seen from cameras no training frame uses, so one mean over both would mix two questions."""
    from methods.gaussians.train import evaluate

    splits = [(DEFAULT_EVAL_SPLIT, "test_psnr")]
    if NOVEL_VIEW_SPLIT in (scene.metadata.get(EVAL_SPLITS_KEY) or {}):
        splits.append((NOVEL_VIEW_SPLIT, "novel_view_psnr"))
    out: dict[str, Any] = {}
    for split, key in splits:
        frames = scene_split_frames(scene, split)
        if len(frames) > HELD_OUT_PSNR_FRAMES:
            frames = [frames[i] for i in np.linspace(0, len(frames) - 1, HELD_OUT_PSNR_FRAMES).round().astype(int)]
        psnr = evaluate(model, frames, scene.background, rasterize_fn, device=device)["psnr"] if frames else None
        out.update({key: psnr, f"{key}_frames": len(frames)})
    return out


# ---------------------------------------------------------------------------------------------------
# 2. autoencoder
# ---------------------------------------------------------------------------------------------------
def distinct_features(supervision: Supervision, weighting: str = "pixels") -> tuple[np.ndarray, np.ndarray]:
    """The distinct mask features of all training frames and levels, with their weights.

    ``weighting``: ``"pixels"`` = total pixel area of the masks carrying each feature; ``"masks"`` =
    number of masks (frame x level) carrying it, the release's autoencoder data (one vector per mask
    and image, its ``*_f.npy`` files); ``"uniform"`` = 1 each. Returns ((M, D) float32 features, (M,)
    float64 weights). Features equal up to 1e-6 (the oracle track gives one vector per object name)
    are merged; features no pixel carries are dropped.
    """
    if weighting not in AE_SAMPLE_WEIGHTINGS:
        raise ValueError(f"weighting must be one of {AE_SAMPLE_WEIGHTINGS}, got {weighting!r}")
    rows, areas = [], []
    for fs in supervision.frames:
        for level in range(len(LEVELS)):
            feats = fs.features[level]
            if feats.shape[0] == 0:
                continue
            plane = fs.levels[level]
            counts = np.bincount(plane[plane >= 0].ravel(), minlength=feats.shape[0])[: feats.shape[0]]
            rows.append(np.asarray(feats, dtype=np.float32))
            areas.append(counts.astype(np.float64))
    if not rows:
        raise InputError(None, "supervision", "no mask has a feature: the language field has nothing to learn")
    feats = np.concatenate(rows, 0)
    area = np.concatenate(areas, 0)
    keys = np.round(feats * 1e6).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    total = np.bincount(inverse.ravel(), weights=area, minlength=first.size)
    keep = total > 0
    if weighting == "masks":
        weight = np.bincount(inverse.ravel(), weights=(area > 0).astype(np.float64), minlength=first.size)
    elif weighting == "uniform":
        weight = np.ones(first.size)
    else:
        weight = total
    return feats[first][keep], weight[keep]


def with_unmasked_as(supervision: Supervision, text: Optional[str]) -> Supervision:
    """A copy of ``supervision`` where, at every level, the pixels no mask covers form one more mask
    whose feature is the passage embedding of ``text`` (``None``: ``supervision`` unchanged)."""
    if not text:
        return supervision
    feature = np.asarray(supervision.text_encoder.encode([text], kind="passage"), dtype=np.float32)  # [1, D]
    frames = []
    for fs in supervision.frames:
        levels = fs.levels.copy()
        feats = list(fs.features)
        for level in range(len(LEVELS)):
            hole = levels[level] < 0
            if hole.any():
                levels[level][hole] = feats[level].shape[0]
                feats[level] = np.concatenate([np.asarray(feats[level], np.float32).reshape(-1, feature.shape[1]),
                                               feature], 0)
        frames.append(dataclasses.replace(fs, levels=levels, features=tuple(feats)))
    return dataclasses.replace(supervision, frames=frames)


# ---------------------------------------------------------------------------------------------------
# 3. field
# ---------------------------------------------------------------------------------------------------
@dataclass
class SharedField:
    """The time-agnostic half of every language-field method on one scene."""

    geometry: FrozenGeometry
    field: LanguageField
    autoencoder: FeatureAutoencoder
    info: dict
    """Fit facts: geometry (kind, Gaussians, seconds), autoencoder (reconstruction cosine), field
    (loss, seconds), cache keys and whether each part came from the cache."""


def field_targets(scene: Scene, supervision: Supervision, autoencoder: FeatureAutoencoder,
                  device: str | torch.device) -> list[FieldTarget]:
    """One :class:`FieldTarget` per supervised training frame (mask latents from the autoencoder)."""
    targets = []
    with torch.no_grad():
        for fs in supervision.frames:
            frame = scene.frame(fs.name)
            size = (frame.camera.height, frame.camera.width)
            if tuple(fs.levels.shape[1:]) != size:
                raise InputError(frame.image_path, "supervision",
                                 f"masks of frame {fs.name!r} are {fs.levels.shape[1:]} but its camera is {size}")
            latents = [autoencoder.encode(torch.as_tensor(np.asarray(f, dtype=np.float32), device=device))
                       if f.shape[0] else torch.zeros(0, autoencoder.cfg.latent_dim, device=device)
                       for f in fs.features]
            targets.append(make_target(frame.camera, frame.time, fs.levels, latents, device))
    return targets


def field_key(geometry_key: str, supervision: Supervision, config: LanguageMethodConfig, ae_cfg: AutoencoderConfig,
              f_cfg: LanguageFieldConfig, *, seed: int, device: str) -> str:
    """Key of a field fit: the geometry's key, the supervision (with its unmasked pixels filled), the
    autoencoder and field options, seed, device kind and the code digest of :data:`FIELD_CODE`."""
    return _stable_hash({"geometry": geometry_key, "supervision": supervision.fingerprint,
                         "unmasked_text": config.extensions.unmasked_text, "autoencoder": config_to_dict(ae_cfg),
                         "field": config_to_dict(f_cfg), "seed": seed, "device": device_kind(device),
                         "code": code_digest(FIELD_CODE)})


def fit_language_field(scene: Scene, supervision: Supervision, config: LanguageMethodConfig, *, kind: str,
                       seed: int, device: str, progress: Progress,
                       cache_root: Optional[Path]) -> SharedField:
    """Geometry, autoencoder and field of ``scene`` (each cached when ``cache_root`` is given)."""
    geo = fit_geometry(scene, kind, config, seed=seed, device=device, progress=progress, cache_root=cache_root)
    supervision = with_unmasked_as(supervision, config.extensions.unmasked_text)
    feats, areas, ae_cfg = autoencoder_inputs(supervision, config)
    f_cfg = field_config(config)
    key = field_key(geo.key, supervision, config, ae_cfg, f_cfg, seed=seed, device=device)
    path = None if cache_root is None else scene_cache_folder(cache_root, scene) / f"field-{kind}-{key}.pt"
    if path is not None and path.is_file():
        saved = _torch_load(path, device)
        if saved is not None and saved.get("key") == key:
            progress.log(f"language field: cached fit {path.name}")
            ae = FeatureAutoencoder(int(saved["input_dim"]), ae_cfg).to(device)
            ae.load_state_dict(saved["autoencoder"])
            fld = LanguageField(geo.geometry.num_gaussians, f_cfg, device=device)
            fld.features.data.copy_(saved["features"])
            info = json.loads(saved["info"])
            info["geometry"] = geo.info
            info["cached"] = {"geometry": geo.cached, "field": True}
            return SharedField(geo.geometry, fld.requires_grad_(False), ae.eval(), info)

    progress.log(f"autoencoder: {feats.shape[0]} distinct features of dimension {feats.shape[1]}")
    with StagePeak(device) as ae_peak:
        ae, ae_report = train_autoencoder(feats, ae_cfg, seed=seed, weights=areas, device=device)
    ae.eval().requires_grad_(False)
    with StagePeak(device) as field_peak:
        start = time.perf_counter()
        targets = field_targets(scene, supervision, ae, device)
        targets_seconds = time.perf_counter() - start
        fld, report = train_language_field(geo.geometry, targets, f_cfg, seed=seed, progress=progress)
    fld.requires_grad_(False)
    info = {"key": key,
            "autoencoder": {"distinct_features": int(feats.shape[0]), "feature_dim": int(feats.shape[1]),
                            "reconstruction_cosine": ae_report.reconstruction_cosine, "steps": ae_report.steps,
                            "seconds": ae_report.seconds, **ae_peak.record()},
            "field": {"iterations": report.iterations, "seconds": report.seconds, "final_loss": report.final_loss,
                      "losses": report.losses, "supervised_fraction": report.supervised_fraction,
                      "views": len(targets), "rendered_by": report.views, "targets_seconds": targets_seconds,
                      **field_peak.record()}}
    if path is not None:
        _torch_save(path, {"key": key, "input_dim": int(feats.shape[1]), "autoencoder": ae.state_dict(),
                           "features": fld.features.detach().cpu(), "info": json.dumps(info)})
    info = {**info, "geometry": geo.info, "cached": {"geometry": geo.cached, "field": False}}
    return SharedField(geo.geometry, fld, ae, info)


# ---------------------------------------------------------------------------------------------------
# The time-sensitive hook
# ---------------------------------------------------------------------------------------------------
@dataclass
class FitContext:
    """Everything a :class:`TimeVaryingHead` may fit on (the time-agnostic half is already fitted)."""

    scene: Scene
    supervision: Supervision
    config: Any
    seed: int
    device: str
    progress: Progress
    shared: SharedField
    """Frozen geometry (4D-GS: ``shared.geometry.hexplane_features(t)``), field and autoencoder."""
    cache_root: Optional[Path] = None
    work_dir: Optional[Path] = None


class TimeVaryingHead(abc.ABC):
    """The time-sensitive half of a language-field method (4D LangSplat's status field plugs in here).

    A head scores how much a query holds at a frame, given the time-agnostic answer of the same text
    (the spatial mask of the protocol's time-sensitive query).
    """

    name: ClassVar[str] = "time-varying"

    @classmethod
    @abc.abstractmethod
    def fit(cls, context: FitContext) -> "TimeVaryingHead":
        """Fit on the training frames (``context.supervision``) with the time-agnostic half frozen."""

    @abc.abstractmethod
    def score(self, text: str, frame: Frame, spatial: AgnosticResult, model: "LanguageFieldModel") -> float:
        """Score of ``text`` at ``frame`` (NaN = undefined) given the time-agnostic answer ``spatial``."""

    @abc.abstractmethod
    def save(self, directory: Path) -> None:
        """Write what :meth:`load` needs into the (existing) ``directory``."""

    @classmethod
    @abc.abstractmethod
    def load(cls, directory: Path, *, model: "LanguageFieldModel", device: str) -> "TimeVaryingHead":
        """Rebuild the head saved in ``directory`` on the loaded time-agnostic ``model``."""


# ---------------------------------------------------------------------------------------------------
# The fitted model
# ---------------------------------------------------------------------------------------------------
class LanguageFieldModel(Model):
    """A fitted language-field method on one scene (see the module docstring)."""

    def __init__(self, method: str, config: LanguageMethodConfig, text_encoder: TextEncoder, shared: SharedField, *,
                 sensitive: Optional[str], head: Optional[TimeVaryingHead] = None, device: str = "cpu") -> None:
        self.method = method
        self.config = config
        self.text_encoder = text_encoder
        self.geometry = shared.geometry
        self.field = shared.field
        self.autoencoder = shared.autoencoder
        self.fit_info = shared.info
        self.sensitive = sensitive
        self.head = head
        self.device = torch.device(device)
        kinds = {"agnostic"}
        if sensitive == "relevance" or head is not None:
            kinds.add("sensitive")
        self.supports = frozenset(kinds)
        self._canon: Optional[torch.Tensor] = None
        self._phrases: dict[str, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}
        self._query_vectors: dict[str, torch.Tensor] = {}
        self._background: dict[str, torch.Tensor] = {}
        self._prepared: Optional[tuple[tuple[str, ...], torch.Tensor]] = None  # (texts, [D, k] shared basis)
        self._reduced_cache: dict[str, torch.Tensor] = {}  # frame name -> [L, H, W, k + 1]
        self._decode_tables: dict[int, DecodeTable] = {}  # id(basis) -> its table (answer.decode_table)

    def use_answer_options(self, config: LanguageMethodConfig) -> None:
        """Answer with ``config``'s ``answer`` group, the fitted state unchanged; memoised query state is
        dropped."""
        self.config = dataclasses.replace(self.config, answer=config.answer)
        self._forget_query_state()

    def use_protocol(self, protocol) -> None:
        old = self.protocol
        super().use_protocol(protocol)
        if protocol.agnostic.canonical_phrases != old.agnostic.canonical_phrases:
            self._forget_query_state()  # the decoding bases span the canonical phrases

    def _forget_query_state(self) -> None:
        self._canon = None
        self._phrases.clear()
        self._prepared = None
        self._reduced_cache.clear()
        self._decode_tables.clear()

    @property
    def relevance_cfg(self):
        """The time-agnostic query rules answered under (:class:`benchmark.core.protocol.AgnosticQuery`)."""
        return self.protocol.agnostic

    def describe(self) -> dict:
        """What the fit did (geometry, autoencoder, field, and the time-varying head when there is one:
        stage seconds, Gaussian counts, memory per Gaussian), for the results file."""
        info = {k: v for k, v in self.fit_info.items() if k != "field"}
        if "field" in self.fit_info:
            info["field"] = {k: v for k, v in self.fit_info["field"].items() if k != "losses"}
        field = getattr(self.head, "field", None)
        if field is not None:
            tv = {k: v for k, v in getattr(field, "info", {}).items() if k not in ("losses",)}
            if hasattr(field, "memory"):
                tv["memory"] = field.memory()
            info["time_varying"] = tv
        return info

    # -- evaluation-wide sharing --------------------------------------------------------------------------
    MAX_CACHE_BYTES: ClassVar[int] = 1 << 30
    MAX_DECODE_TABLES: ClassVar[int] = 8
    """Memory for reduced decoded frames kept between queries (each is [3, H, W, k + 1] floats with
    k <= queries + 4: 3.5 MiB at 128x170 with 13 queries, 140 MiB at 960x536 with 20); the oldest frames
    are dropped beyond it."""

    def prepare(self, texts: Sequence[str]) -> None:
        """Decode each frame once for all ``texts``: one orthonormal basis spans every prepared query and
        the canonical phrases, so the reduced features of :func:`decode_for_relevance` are exact for each
        of them and are kept per frame (render + decode once per frame instead of once per query)."""
        self._reduced_cache.clear()
        texts = tuple(dict.fromkeys(texts))
        if not texts:
            self._prepared = None
            return
        queries = torch.stack([self.query_embedding(t) for t in texts])  # [N, D]
        self._prepared = (texts, relevance_basis(queries, self.canonical()))

    def _reduced(self, text: str, frame: Frame) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Reduced decoded features of ``frame`` and the query / canonical phrases in their coordinates."""
        prepared = self._prepared is not None and text in self._prepared[0]
        if prepared:
            basis = self._prepared[1]
            reduced = self._reduced_cache.get(frame.name)
        else:
            basis, zq, zc = self._reduced_phrases(text)
            reduced = None
        if reduced is None:
            latents, alpha = self.render_latents_and_alpha(frame)
            reduced = self.decode_reduced(latents, alpha, basis)
            if prepared:
                size = reduced.numel() * reduced.element_size()
                while self._reduced_cache and size * (len(self._reduced_cache) + 1) > self.MAX_CACHE_BYTES:
                    self._reduced_cache.pop(next(iter(self._reduced_cache)))
                if size <= self.MAX_CACHE_BYTES:
                    self._reduced_cache[frame.name] = reduced
        if prepared:  # unprepared texts got their coordinates with their own basis above
            zq, zc = project_phrases(basis, self.query_embedding_cached(text), self.canonical())
        return reduced, zq, zc

    def decode_reduced(self, latents: torch.Tensor, alpha: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
        """[L, H, W, k + 1] reduced decoded features (:func:`decode_for_relevance`) of the latent maps
        ``latents`` [L, H, W, d], with the pixels of ``alpha`` [H, W] below ``config.answer.uncovered_alpha`` set to the
        reduced ``extensions.unmasked_text`` embedding (see the config field). Only covered pixels are decoded:
        the others would be overwritten (object-centric scenes such as D-NeRF are mostly uncovered)."""
        with matmul_precision("high" if self.config.answer.decode_tf32 and latents.device.type == "cuda" else None):
            return self._decode_reduced(latents, alpha, basis)

    def _decode_reduced(self, latents: torch.Tensor, alpha: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
        chunk = self.config.answer.decode_chunk_for(latents.device)
        text = self.config.extensions.unmasked_text
        uncovered = alpha < self.config.answer.uncovered_alpha
        if not text or not bool(uncovered.any()):
            return self._decode(latents, basis, chunk)
        if text not in self._background:
            self._background[text] = F.normalize(torch.as_tensor(
                self.text_encoder.encode([text], kind="passage")[0], dtype=torch.float32, device=self.device), dim=0)
        e = self._background[text]
        par = e @ basis  # [k]
        g = torch.cat([par, (1.0 - (par * par).sum()).clamp_min(0.0).sqrt()[None]])
        reduced = g.to(latents.dtype).expand(*latents.shape[:-1], g.shape[0]).clone()
        covered = ~uncovered
        if bool(covered.any()):
            reduced[:, covered] = self._decode(latents[:, covered], basis, chunk)
        return reduced

    def _decode(self, latents: torch.Tensor, basis: torch.Tensor, chunk: int) -> torch.Tensor:
        """[..., d] latents -> [..., k + 1] reduced features: exactly, or through the query's decode table
        (``answer.decode_table`` / ``answer.decode_table_cuda``, 3-d latents)."""
        resolution = self.config.answer.decode_table_for(latents.device)
        if resolution <= 0 or latents.shape[-1] != 3:
            return decode_for_relevance(latents, self.autoencoder.decoder, basis, chunk)
        key = id(basis)
        if key not in self._decode_tables:
            if len(self._decode_tables) >= self.MAX_DECODE_TABLES:
                self._decode_tables.pop(next(iter(self._decode_tables)))
            lo, hi = self._latent_box()
            # the table keeps ``basis`` alive, so its id is not reused while the entry exists; a CPU decodes
            # only the grid points the latents reach (lazy), a GPU the whole grid at once
            self._decode_tables[key] = DecodeTable(self.autoencoder.decoder, basis, lo, hi, resolution, chunk,
                                                   lazy=latents.device.type != "cuda")
        return self._decode_tables[key](latents)

    def _latent_box(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-channel bounds of every rendered latent of every level: the extremes of the Gaussians' latents
        and the zero background (a rendered latent is their alpha blend)."""
        d = self.field.cfg.latent_dim
        features = self.field.features.detach().reshape(-1, d)
        zero = features.new_zeros(d)
        return torch.minimum(features.min(0).values, zero), torch.maximum(features.max(0).values, zero)

    @torch.no_grad()
    def render_latents_and_alpha(self, frame: Frame) -> tuple[torch.Tensor, torch.Tensor]:
        """([L, H, W, d] latent maps, [H, W] accumulated opacity) at the frame's camera and time."""
        return self.field.render_with_alpha(self.geometry.at(frame.time), frame.camera)

    def query_embedding_cached(self, text: str) -> torch.Tensor:
        """:meth:`query_embedding`, encoded once per text."""
        if text not in self._query_vectors:
            self._query_vectors[text] = self.query_embedding(text)
        return self._query_vectors[text]

    # -- query pieces ---------------------------------------------------------------------------------
    def canonical(self) -> torch.Tensor:
        """[P, D] canonical phrase embeddings (same text encoder as the queries)."""
        if self._canon is None:
            self._canon = encode_canonical(self.text_encoder, self.relevance_cfg.canonical_phrases).to(self.device)
        return self._canon

    def query_embedding(self, text: str) -> torch.Tensor:
        """[D] embedding of a query text."""
        return torch.as_tensor(self.text_encoder.encode([text], kind="query")[0], device=self.device)

    def _reduced_phrases(self, text: str) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        if text not in self._phrases:
            q = self.query_embedding_cached(text)
            canon = self.canonical()
            basis = relevance_basis(q, canon)
            zq, zc = project_phrases(basis, q, canon)
            self._phrases[text] = (basis, zq, zc)
        return self._phrases[text]

    @torch.no_grad()
    def render_latents(self, frame: Frame) -> torch.Tensor:
        """[L, H, W, d] rendered latent maps of every level at the frame's camera and time."""
        return self.field.render(self.geometry.at(frame.time), frame.camera)

    @torch.no_grad()
    def decode_levels(self, latents: torch.Tensor) -> torch.Tensor:
        """[L, H, W, D] decoded language features (full dimension: for inspection and the status field)."""
        return self.autoencoder.decode(latents)

    @torch.no_grad()
    def agnostic(self, text: str, frame: Frame) -> AgnosticResult:
        """The protocol's time-agnostic query on one frame (all tensors on the model's device)."""
        reduced, zq, zc = self._reduced(text, frame)
        return query_levels(reduced, zq, zc, self.relevance_cfg)

    def relevance_score(self, result: AgnosticResult) -> float:
        """A frame's time-sensitive score from relevance alone (the CLIP baselines), under the protocol's
        :attr:`~benchmark.core.protocol.SensitiveQuery.relevance_score`: the chosen level's peak smoothed
        relevance, or its mean inside the spatial mask (NaN when that mask is empty)."""
        rules = self.protocol.sensitive
        if rules.relevance_score == "peak":
            return float(result.level_peaks[result.level])
        mask = spatial_mask(result, rules)
        if not bool(mask.any()):
            return float("nan")
        return float(result.relevance[mask].mean())

    # -- the API ----------------------------------------------------------------------------------------
    def query_agnostic(self, text: str, frames: Sequence[Frame]) -> list[AgnosticAnswer]:
        out = []
        for frame in frames:
            res = self.agnostic(text, frame)
            out.append(AgnosticAnswer(mask=res.mask.cpu().numpy(), relevance=res.relevance.float().cpu().numpy()))
        return out

    def query_sensitive(self, text: str, frames: Sequence[Frame]) -> list[SensitiveAnswer]:
        if "sensitive" not in self.supports:
            raise NotImplementedError(f"{self.method} does not answer time-sensitive queries yet")
        out = []
        for frame in frames:
            res = self.agnostic(text, frame)
            score = (self.head.score(text, frame, res, self) if self.head is not None
                     else self.relevance_score(res))
            out.append(SensitiveAnswer(mask=res.mask.cpu().numpy(), score=score))
        return out

    # -- persistence --------------------------------------------------------------------------------------
    def save(self, directory: Path) -> None:
        directory = Path(directory)
        state = {"geometry": self.geometry.state_dict(), "features": self.field.features.detach().cpu(),
                 "autoencoder": {k: v.cpu() for k, v in self.autoencoder.state_dict().items()},
                 "input_dim": int(self.autoencoder.input_dim)}
        with atomic_path(directory / MODEL_FILE) as tmp:
            torch.save(state, tmp)
        write_json(directory / META_FILE, {"method": self.method, "config": config_to_dict(self.config),
                                           "sensitive": self.sensitive,
                                           "head": None if self.head is None else self.head.name,
                                           "fit_info": self.fit_info})
        if self.head is not None:
            (directory / HEAD_DIR).mkdir(exist_ok=True)
            self.head.save(directory / HEAD_DIR)


def _wants_head(config, scene: Scene, supervision: Supervision, progress: Progress) -> bool:
    """Whether to fit the time-varying head (``config.status.fit``, "auto" resolved on this scene)."""
    choice = config.status.fit
    if choice != "auto":
        return choice == "on"
    from .captioners import captioning_unavailable

    why = captioning_unavailable(config.captions, scene, supervision)
    if why:
        progress.log(f"time-varying head: off ({why}); time-sensitive queries stay unanswered")
        return False
    return True


class LanguageFieldMethod(Method):
    """Base of the language-field methods; subclasses set :attr:`geometry_kind` and :attr:`sensitive`."""

    name: ClassVar[str] = "language-field"
    geometry_kind: ClassVar[str] = "4dgs"
    """``"3dgs"`` (static) or ``"4dgs"`` (deformable)."""
    sensitive: ClassVar[Optional[str]] = "relevance"
    """``"relevance"``: time-sensitive score = mean relevance inside the spatial mask; ``None``: no
    time-sensitive answers unless :attr:`time_varying_head` is set."""
    time_varying_head: ClassVar[Optional[type[TimeVaryingHead]]] = None
    """The head fitted after the time-agnostic half (4D LangSplat's status field), or ``None``."""
    config_class: ClassVar[type] = LanguageMethodConfig

    @classmethod
    def fit(cls, scene: Scene, supervision: Supervision, config: LanguageMethodConfig, *, seed: int, device: str,
            progress: Progress, work_dir: Optional[Path] = None) -> LanguageFieldModel:
        shared = fit_language_field(scene, supervision, config, kind=cls.geometry_kind, seed=seed, device=device,
                                    progress=progress, cache_root=shared_cache_root(config, work_dir))
        return cls._with_head(shared, scene, supervision, config, seed=seed, device=device, progress=progress,
                              work_dir=work_dir)

    @classmethod
    def refit_head(cls, base: LanguageFieldModel, scene: Scene, supervision: Supervision, config: LanguageMethodConfig,
                   *, seed: int, device: str, progress: Progress, work_dir: Optional[Path] = None) -> LanguageFieldModel:
        """``base`` (a fitted model of this method) with its time-varying head fitted anew under ``config``;
        geometry, time-agnostic field and autoencoder are ``base``'s. For an ablation of head options
        on the very geometry a recorded run used (the head is the only stage they touch)."""
        if cls.time_varying_head is None:
            raise ValueError(f"{cls.name} has no time-varying head to refit")
        shared = SharedField(base.geometry, base.field, base.autoencoder, base.fit_info)
        return cls._with_head(shared, scene, supervision, config, seed=seed, device=device, progress=progress,
                              work_dir=work_dir)

    @classmethod
    def _with_head(cls, shared: SharedField, scene: Scene, supervision: Supervision, config: LanguageMethodConfig,
                   *, seed: int, device: str, progress: Progress, work_dir: Optional[Path]) -> LanguageFieldModel:
        """The model on the fitted time-agnostic half ``shared``, with its time-varying head fitted when
        the method has one and the scene asks for it."""
        head = None
        if cls.time_varying_head is not None and _wants_head(config, scene, supervision, progress):
            ctx = FitContext(scene, supervision, config, seed, device, progress, shared,
                             shared_cache_root(config, work_dir), work_dir)
            head = cls.time_varying_head.fit(ctx)
        return LanguageFieldModel(cls.name, config, supervision.text_encoder, shared, sensitive=cls.sensitive,
                                  head=head, device=device)

    @classmethod
    def load(cls, directory: Path, *, supervision: Supervision, device: str) -> LanguageFieldModel:
        directory = Path(directory)
        meta = json.loads((directory / META_FILE).read_text())
        config = config_from_record(cls.config_class, meta["config"], what=f"{directory / META_FILE}: config")
        state = torch.load(directory / MODEL_FILE, map_location=device, weights_only=True)
        geometry = FrozenGeometry.from_state_dict(state["geometry"], device)
        ae = FeatureAutoencoder(int(state["input_dim"]), autoencoder_config(config)).to(device)
        ae.load_state_dict(state["autoencoder"])
        fld = LanguageField(geometry.num_gaussians, field_config(config), device=device)
        fld.features.data.copy_(state["features"])
        shared = SharedField(geometry, fld.requires_grad_(False), ae.eval().requires_grad_(False), meta["fit_info"])
        model = LanguageFieldModel(meta["method"], config, supervision.text_encoder, shared, sensitive=cls.sensitive,
                                   device=device)
        if cls.time_varying_head is not None and meta.get("head"):
            model.head = cls.time_varying_head.load(directory / HEAD_DIR, model=model, device=device)
            model.supports = frozenset(model.supports | {"sensitive"})
        return model
