"""``feature-3dgs``: Feature 3DGS (Zhou et al., CVPR 2024) on the shared 4D-GS, time-agnostic only.

Feature 3DGS distils a dense 2D feature map into one feature per Gaussian, rendered like a colour,
and decodes the rendered map per pixel with a learned 1x1 convolution (its speed-up module: render
few channels, decode to the encoder's D). 4D LangSplat reports it on dynamic scenes as a
time-agnostic baseline; here it is built as follows.

* **Geometry**: the 4D-GS the other 4D language methods share (:func:`methods.language_methods.fit_geometry`,
  one cached fit per scene, geometry options and seed), frozen. The original trains the features
  jointly with RGB (and densifies on both); the shared frozen geometry makes the comparison with
  ``deformable-clip`` and ``4d-langsplat`` about the feature field alone. Features do not deform.
* **Target**: at each training frame, pixel p gets the feature of the mask covering p at ONE SAM
  level (``feature.level``); pixels no mask covers get the ``extensions.unmasked_text`` passage embedding
  (:func:`~methods.language_methods.with_unmasked_as`), as for the language fields. Feature 3DGS
  distils one feature map per image, with no hierarchy, so each pixel must carry one granularity:
  the middle level (parts, and wholes that have none) lies between the two others, so a whole is
  still covered by its parts' embeddings and a subpart by its part's: the nearest one map gets to all.
* **Fit**: zero-initialised per-Gaussian features (as the original) and the decoder, jointly by Adam,
  L1 between the decoded rendered features and the target over the supervised pixels (the original's
  feature loss), one training view per step. Cached per (geometry, supervision, options, seed, device
  kind, code) in the shared cache folder, like the language field.
* **Query**: render at the frame's camera and time, decode, LERF relevance against the canonical
  phrases, then the protocol's smoothing, min-max threshold and majority filter on that one level
  (:func:`~methods.fields.relevance.answer_from_relevance`). Pixels whose accumulated opacity is below
  ``answer.uncovered_alpha`` read as ``extensions.unmasked_text``. The features carry no time, so time-sensitive
  queries are not answered.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Optional, Sequence

import numpy as np
import torch
import torch.nn as nn

from benchmark.core.atomic import atomic_path, write_json
from benchmark.core.errors import InputError
from benchmark.core.memory import StagePeak
from benchmark.core.scene import Camera, Frame, Scene

from .api import AgnosticAnswer, Method, Progress
from .fields.language_field import FrozenGeometry, GaussianState, LanguageField, LanguageFieldConfig
from .fields.relevance import answer_from_relevance, relevance
from .language_methods import (config_to_dict, device_kind, fit_geometry, scene_cache_folder, shared_cache_root,
                               with_unmasked_as)
from .fields.texts import EncodedQueryModel
from .fields.views import ViewCycle
from .specs._recorded import config_from_record
from .specs.feature_3dgs import FEATURE_LEVEL_NAMES, Feature3DGSConfig
from .supervision.base import Supervision, TextEncoder
from benchmark.core.cache_keys import code_digest, stable_hash

METHOD_NAME = "feature-3dgs"
GEOMETRY_KIND = "4dgs"
MODEL_FILE = "feature_3dgs.pt"
META_FILE = "feature_3dgs.json"
CACHE_PREFIX = "feature3dgs"

FIT_CODE = "methods.feature_3dgs"
"""The module that runs a feature fit (this one): its code digest is part of the feature cache key."""
TRAIN_PIXEL_CHUNK = {"cpu": 1 << 10, "cuda": 1 << 15}
"""Pixels decoded at once in training, by device kind. On a CPU each [chunk, D] temporary of the loss
(2 MiB at D = 512) stays in cache: at 200 px the loss step is 3x faster than with 1 << 15 pixels (134
against 404 ms, one core), and a whole feature fit about twice as fast. On CUDA a large chunk keeps the
kernel launches few (64 MiB a temporary). Fixed per device kind, not an option: the chunking sets the
order of float sums, so it must not vary between fits that share a cache key (the key names the device
kind)."""


# ---------------------------------------------------------------------------------------------------
# The field
# ---------------------------------------------------------------------------------------------------
class FeatureField(nn.Module):
    """Per-Gaussian features [N, feature_dim] and the 1x1 decoder ``feature_dim -> output_dim``.

    The features are rendered by the language field's rasterizer call (a :class:`LanguageField` of one
    level), zero-initialised as in the original.
    """

    def __init__(self, num_gaussians: int, feature_dim: int, output_dim: int, *, render_backend: str = "auto",
                 device: torch.device | str = "cpu") -> None:
        super().__init__()
        cfg = LanguageFieldConfig(num_levels=1, latent_dim=int(feature_dim), init_std=0.0,
                                  render_backend=render_backend)
        self.renderer = LanguageField(num_gaussians, cfg, device=device)
        self.decoder = nn.Linear(int(feature_dim), int(output_dim)).to(device)

    @property
    def features(self) -> nn.Parameter:
        """[N, feature_dim] per-Gaussian features."""
        return self.renderer.features

    @property
    def feature_dim(self) -> int:
        return int(self.decoder.in_features)

    @property
    def output_dim(self) -> int:
        return int(self.decoder.out_features)

    def render_with_alpha(self, state: GaussianState, camera: Camera,
                          prepared=None) -> tuple[torch.Tensor, torch.Tensor]:
        """([H, W, feature_dim] rendered features, [H, W] accumulated opacity); differentiable in the features.
        ``prepared``: the view's frozen rendering (:meth:`methods.fields.views.ViewCycle.prepared`)."""
        maps, alpha = self.renderer.render_with_alpha(state, camera, prepared)  # [1, H, W, C], [H, W]
        return maps[0], alpha


# ---------------------------------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------------------------------
@dataclass
class FeatureTarget:
    """The dense distillation target of one training view, as indices into a feature table."""

    camera: Camera
    time: float
    index: torch.Tensor
    """[H, W] int64 row of :attr:`table` per pixel; -1 = not supervised."""
    table: torch.Tensor
    """[M, D] features of this view's masks at the chosen level."""


def feature_targets(scene: Scene, supervision: Supervision, level: int,
                    device: torch.device | str) -> list[FeatureTarget]:
    """One :class:`FeatureTarget` per training frame with a supervised pixel at ``level`` (give
    ``supervision`` :func:`with_unmasked_as` first, as the fit does)."""
    dim = supervision.feature_dim
    targets = []
    for fs in supervision.frames:
        frame = scene.frame(fs.name)
        size = (frame.camera.height, frame.camera.width)
        if tuple(fs.levels.shape[1:]) != size:
            raise InputError(frame.image_path, "supervision",
                             f"masks of frame {fs.name!r} are {fs.levels.shape[1:]} but its camera is {size}")
        index = torch.as_tensor(np.asarray(fs.levels[level], dtype=np.int64), device=device)  # [H, W]
        if not bool((index >= 0).any()):
            continue
        table = torch.as_tensor(np.asarray(fs.features[level], dtype=np.float32).reshape(-1, dim), device=device)
        targets.append(FeatureTarget(frame.camera, float(frame.time), index, table))
    return targets


def l1_backward(decoder: nn.Module, rendered: torch.Tensor, target: FeatureTarget,
                chunk: Optional[int] = None) -> float:
    """Backpropagate the mean L1 between ``decoder(rendered)`` and the target over its supervised
    pixels (mean over pixels and the D channels, as the original's ``l1_loss``); returns the loss.

    The decoded [P, D] map is formed ``chunk`` pixels at a time (default: :data:`TRAIN_PIXEL_CHUNK` of the
    device): gradients of the rendered map and the decoder accumulate chunk by chunk, then flow through the
    rasterizer once.
    Args:
        rendered: [H, W, C] rendered features (attached to the per-Gaussian features).
    """
    index = target.index.reshape(-1)  # [H W]
    rows = torch.nonzero(index >= 0).squeeze(1)  # [P]
    if rows.numel() == 0:
        return 0.0
    if chunk is None:
        chunk = TRAIN_PIXEL_CHUNK[device_kind(rendered.device)]
    denominator = float(rows.numel() * target.table.shape[1])
    leaf = rendered.detach().reshape(-1, rendered.shape[-1]).requires_grad_(True)  # [H W, C]
    total = 0.0
    for start in range(0, rows.numel(), chunk):
        picked = rows[start:start + chunk]
        decoded = decoder(leaf[picked])  # [c, D]
        loss = (decoded - target.table[index[picked]]).abs().sum() / denominator
        loss.backward()
        total += float(loss.detach())
    rendered.backward(leaf.grad.reshape(rendered.shape))
    return total


@dataclass
class FeatureReport:
    """How training the feature field went."""

    iterations: int
    seconds: float
    final_loss: float
    losses: list[float]
    supervised_fraction: float
    """Mean fraction of pixels with a target over the training views."""
    rendered_by: str = "rasterizer"
    """How the training views were rendered (:attr:`methods.fields.views.ViewCycle.rendered_by`)."""


def train_feature_field(geometry: FrozenGeometry, targets: Sequence[FeatureTarget], config: Feature3DGSConfig, *,
                        output_dim: int, seed: int, progress: Optional[Progress] = None,
                        log_every: int = 100) -> tuple[FeatureField, FeatureReport]:
    """Fit the per-Gaussian features and the decoder jointly on ``geometry`` (frozen), one random view per step."""
    if not targets:
        raise ValueError("the feature field needs at least one training view")
    device = geometry.device
    with torch.random.fork_rng(devices=[]):  # the decoder's initial weights depend on the seed only
        torch.manual_seed(seed)
        fld = FeatureField(geometry.num_gaussians, config.feature.dim, output_dim,
                           render_backend=config.geometry.render_backend, device=device)
    opt = torch.optim.Adam([{"params": [fld.features], "lr": config.feature.learning_rate},
                            {"params": list(fld.decoder.parameters()), "lr": config.feature.decoder_learning_rate}])
    budgets = LanguageFieldConfig()
    views = ViewCycle(geometry, [t.time for t in targets], seed, budgets.cache_view_geometry_mib * 2 ** 20,
                      cameras=[t.camera for t in targets], near=budgets.near,
                      render_backend=config.geometry.render_backend,
                      matrix_budget_bytes=budgets.blend_matrix_mib * 2 ** 20)
    losses: list[float] = []
    loss_value = float("nan")
    iterations = config.feature.iterations
    steps = range(iterations)
    if progress is not None:
        steps = progress(steps, desc="feature field", total=iterations)
    start = time.perf_counter()
    for step in steps:
        view, state = views.next()
        target = targets[view]
        opt.zero_grad(set_to_none=True)
        rendered, _ = fld.render_with_alpha(state, target.camera, views.prepared(view, state))  # [H, W, C]
        loss = l1_backward(fld.decoder, rendered, target)
        opt.step()
        if step % max(1, log_every) == 0 or step == iterations - 1:
            loss_value = loss
            losses.append(loss)
    seconds = time.perf_counter() - start
    fraction = float(np.mean([float((t.index >= 0).float().mean()) for t in targets]))
    fld.requires_grad_(False)
    return fld, FeatureReport(iterations, seconds, loss_value, losses, fraction, views.rendered_by)


# ---------------------------------------------------------------------------------------------------
# Fit, cached
# ---------------------------------------------------------------------------------------------------
@dataclass
class FeatureFit:
    geometry: FrozenGeometry
    field: FeatureField
    info: dict
    """Fit facts: ``geometry`` and ``field`` stages (seconds, peaks), cache key, what came from the cache."""


def feature_cache_key(geometry_key: str, supervision: Supervision, config: Feature3DGSConfig, seed: int,
                      device: str) -> str:
    """Key of a feature fit: geometry, supervision, the options it depends on beyond the geometry's (the
    ``feature`` group, ``extensions.unmasked_text``, the rasterizer), seed, device kind, code."""
    options = {"feature": config_to_dict(config.feature), "unmasked_text": config.extensions.unmasked_text,
               "render_backend": config.geometry.render_backend}
    return stable_hash({"geometry": geometry_key, "supervision": supervision.fingerprint, "options": options,
                        "seed": seed, "device": device_kind(device), "code": code_digest(FIT_CODE)}, 24)


def feature_cache_path(cache_root: Path, scene: Scene, key: str) -> Path:
    """Where the feature fit of ``key`` is kept: beside the shared geometry of ``scene``."""
    return scene_cache_folder(Path(cache_root), scene) / f"{CACHE_PREFIX}-{GEOMETRY_KIND}-{key}.pt"


def _field_state(fld: FeatureField) -> dict:
    decoder = {k: v.detach().cpu() for k, v in fld.decoder.state_dict().items()}
    return {"features": fld.features.detach().cpu(), "decoder": decoder, "feature_dim": fld.feature_dim,
            "output_dim": fld.output_dim}


def _field_from_state(state: dict, num_gaussians: int, render_backend: str,
                      device: str | torch.device) -> FeatureField:
    fld = FeatureField(num_gaussians, int(state["feature_dim"]), int(state["output_dim"]),
                       render_backend=render_backend, device=device)
    fld.features.data.copy_(state["features"])
    fld.decoder.load_state_dict(state["decoder"])
    return fld.requires_grad_(False)


def _cached_field(path: Path, key: str, geometry: FrozenGeometry, output_dim: int, config: Feature3DGSConfig,
                  device: str) -> Optional[tuple[FeatureField, dict]]:
    """The field and info saved at ``path`` when it is this fit's, intact; else ``None`` (refit)."""
    try:
        saved = torch.load(path, map_location=device, weights_only=True)
        if saved.get("key") != key:
            return None
        fld = _field_from_state(saved["field"], geometry.num_gaussians, config.geometry.render_backend, device)
        if fld.feature_dim != config.feature.dim or fld.output_dim != output_dim:
            return None
        return fld, json.loads(saved["info"])
    except Exception:  # a corrupt or incompatible cache file is refitted, never trusted
        return None


def fit_feature_field(scene: Scene, supervision: Supervision, config: Feature3DGSConfig, *, seed: int, device: str,
                      progress: Progress, cache_root: Optional[Path]) -> FeatureFit:
    """The shared 4D-GS and the feature field of ``scene`` (each cached when ``cache_root`` is given)."""
    geo = fit_geometry(scene, GEOMETRY_KIND, config, seed=seed, device=device, progress=progress,
                       cache_root=cache_root)
    supervision = with_unmasked_as(supervision, config.extensions.unmasked_text)
    output_dim = int(supervision.feature_dim)
    key = feature_cache_key(geo.key, supervision, config, seed, device)
    path = None if cache_root is None else feature_cache_path(cache_root, scene, key)
    if path is not None and path.is_file():
        cached = _cached_field(path, key, geo.geometry, output_dim, config, device)
        if cached is not None:
            progress.log(f"feature field: cached fit {path.name}")
            fld, info = cached
            return FeatureFit(geo.geometry, fld, {**info, "geometry": geo.info,
                                                  "cached": {"geometry": geo.cached, "field": True}})
        progress.log(f"feature field: {path.name} is unreadable or not this fit's; refitting")

    level = int(config.feature.level)
    with StagePeak(device) as peak:  # reused from the cache by other runs, which are charged this peak
        targets = feature_targets(scene, supervision, level, device)
        if not targets:
            raise InputError(None, "supervision", f"no training frame has a mask at level {level} "
                             f"({FEATURE_LEVEL_NAMES[level]}, feature.level) and extensions.unmasked_text is unset: "
                             "the feature field has nothing to learn")
        progress.log(f"feature field: {config.feature.dim} channels decoded to {output_dim}, "
                     f"{FEATURE_LEVEL_NAMES[level]} masks of {len(targets)} training views")
        fld, report = train_feature_field(geo.geometry, targets, config, output_dim=output_dim, seed=seed,
                                          progress=progress)
    info = {"key": key,
            "field": {"iterations": report.iterations, "seconds": report.seconds, "final_loss": report.final_loss,
                      "losses": report.losses, "supervised_fraction": report.supervised_fraction,
                      "views": len(targets), "rendered_by": report.rendered_by,
                      "level": FEATURE_LEVEL_NAMES[level], "feature_dim": config.feature.dim,
                      "output_dim": output_dim, **peak.record()}}
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            torch.save({"key": key, "field": _field_state(fld), "info": json.dumps(info)}, tmp)
    return FeatureFit(geo.geometry, fld, {**info, "geometry": geo.info,
                                          "cached": {"geometry": geo.cached, "field": False}})


# ---------------------------------------------------------------------------------------------------
# The fitted model
# ---------------------------------------------------------------------------------------------------
class Feature3DGSModel(EncodedQueryModel):
    """A fitted ``feature-3dgs`` on one scene: answers time-agnostic queries (see the module docstring)."""

    supports = frozenset({"agnostic"})

    MAX_CACHE_BYTES: ClassVar[int] = 1 << 30
    """Memory for rendered frames kept between the prepared queries (each is [H, W, feature_dim + 1]
    floats: 35 MiB at 960x536 with 16 channels); the oldest frames are dropped beyond it."""

    def __init__(self, config: Feature3DGSConfig, text_encoder: TextEncoder, geometry: FrozenGeometry,
                 field: FeatureField, info: dict, device: str | torch.device = "cpu") -> None:
        self.config = config
        self.text_encoder = text_encoder
        self.geometry = geometry
        self.field = field
        self.fit_info = info
        self.device = torch.device(device)
        self._prepared = False
        self._rendered_cache: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}  # frame name -> (features, alpha)

    def use_answer_options(self, config: Feature3DGSConfig) -> None:
        """Answer with ``config``'s ``answer`` group, the fitted state unchanged."""
        self.config = dataclasses.replace(self.config, answer=config.answer)

    def describe(self) -> dict:
        """What the fit did (geometry and feature field: seconds, peaks, loss), for the results file."""
        info = dict(self.fit_info)
        if "field" in info:
            info["field"] = {k: v for k, v in info["field"].items() if k != "losses"}
        return info

    def prepare(self, texts: Sequence[str]) -> None:
        """Render each frame once for all ``texts`` (rendering does not depend on the text, so answers
        are unchanged); a new call drops what earlier ones kept."""
        self._rendered_cache.clear()
        self._prepared = bool(texts)

    # -- query pieces ---------------------------------------------------------------------------------
    @torch.no_grad()
    def render(self, frame: Frame) -> tuple[torch.Tensor, torch.Tensor]:
        """([H, W, feature_dim] rendered features, [H, W] accumulated opacity) at the frame's camera and time."""
        kept = self._rendered_cache.get(frame.name)
        if kept is not None:
            return kept
        rendered = self.field.render_with_alpha(self.geometry.at(frame.time), frame.camera)
        if self._prepared:
            size = sum(t.numel() * t.element_size() for t in rendered)
            while self._rendered_cache and size * (len(self._rendered_cache) + 1) > self.MAX_CACHE_BYTES:
                self._rendered_cache.pop(next(iter(self._rendered_cache)))
            if size <= self.MAX_CACHE_BYTES:
                self._rendered_cache[frame.name] = rendered
        return rendered

    @torch.no_grad()
    def decode(self, rendered: torch.Tensor) -> torch.Tensor:
        """[..., D] decoded features of rendered features [..., feature_dim] (full dimension: for inspection)."""
        return self.field.decoder(rendered)

    @torch.no_grad()
    def relevance_map(self, text: str, frame: Frame) -> torch.Tensor:
        """[H, W] LERF relevance of ``text`` at every pixel of ``frame``, before smoothing.

        Covered pixels are decoded ``answer.decode_chunk`` at a time, never the whole [H, W, D] map; pixels
        whose opacity is below ``answer.uncovered_alpha`` take the relevance of the ``extensions.unmasked_text``
        embedding.
        """
        rendered, alpha = self.render(frame)  # [H, W, C], [H, W]
        query, canon = self.query_embedding(text), self.canonical()
        temperature = self.relevance_cfg.temperature
        flat = rendered.reshape(-1, rendered.shape[-1])  # [H W, C]
        out = flat.new_empty(flat.shape[0])  # [H W]
        background = self.config.extensions.unmasked_text
        uncovered = (alpha < self.config.answer.uncovered_alpha).reshape(-1) if background else None
        if uncovered is not None and bool(uncovered.any()):
            embedding = torch.as_tensor(self.text_encoder.encode([background], kind="passage")[0],
                                        dtype=flat.dtype, device=flat.device)  # [D]
            out[uncovered] = relevance(embedding[None], query, canon, temperature)[0]
            rows = torch.nonzero(~uncovered).squeeze(1)  # [P]
        else:
            rows = None
        count = flat.shape[0] if rows is None else rows.numel()
        chunk = self.config.answer.decode_chunk_for(self.device)
        for start in range(0, count, chunk):
            if rows is None:
                out[start:start + chunk] = relevance(self.field.decoder(flat[start:start + chunk]), query, canon,
                                                     temperature)
            else:
                picked = rows[start:start + chunk]
                out[picked] = relevance(self.field.decoder(flat[picked]), query, canon, temperature)
        return out.reshape(alpha.shape)

    # -- the API ----------------------------------------------------------------------------------------
    def query_agnostic(self, text: str, frames: Sequence[Frame]) -> list[AgnosticAnswer]:
        answers = []
        for frame in frames:
            result = answer_from_relevance(self.relevance_map(text, frame)[None], self.relevance_cfg)
            answers.append(AgnosticAnswer(mask=result.mask.cpu().numpy(),
                                          relevance=result.relevance.float().cpu().numpy()))
        return answers

    def save(self, directory: Path) -> None:
        directory = Path(directory)
        with atomic_path(directory / MODEL_FILE) as tmp:
            torch.save({"geometry": self.geometry.state_dict(), "field": _field_state(self.field)}, tmp)
        write_json(directory / META_FILE, {"method": METHOD_NAME, "config": config_to_dict(self.config),
                                           "fit_info": self.fit_info})


class Feature3DGS(Method):
    """Feature 3DGS's distilled feature field on the shared frozen 4D-GS (see the module docstring)."""

    name: ClassVar[str] = METHOD_NAME
    supports = frozenset({"agnostic"})
    config_class: ClassVar[type] = Feature3DGSConfig

    @classmethod
    def fit(cls, scene: Scene, supervision: Supervision, config: Feature3DGSConfig, *, seed: int, device: str,
            progress: Progress, work_dir: Optional[Path] = None) -> Feature3DGSModel:
        if not isinstance(config, Feature3DGSConfig):
            raise TypeError(f"{cls.name}: config must be a Feature3DGSConfig, got {type(config).__name__}")
        fit = fit_feature_field(scene, supervision, config, seed=seed, device=device, progress=progress,
                                cache_root=shared_cache_root(config, work_dir))
        return Feature3DGSModel(config, supervision.text_encoder, fit.geometry, fit.field, fit.info, device=device)

    @classmethod
    def load(cls, directory: Path, *, supervision: Supervision, device: str) -> Feature3DGSModel:
        directory = Path(directory)
        meta: dict[str, Any] = json.loads((directory / META_FILE).read_text())
        config = config_from_record(cls.config_class, meta["config"], what=f"{directory / META_FILE}: config")
        state = torch.load(directory / MODEL_FILE, map_location=device, weights_only=True)
        geometry = FrozenGeometry.from_state_dict(state["geometry"], device)
        fld = _field_from_state(state["field"], geometry.num_gaussians, config.geometry.render_backend, device)
        if fld.output_dim != supervision.feature_dim:
            raise InputError(directory / MODEL_FILE, "supervision",
                             f"the decoder outputs {fld.output_dim}-d features but the supervision's text encoder "
                             f"embeds in {supervision.feature_dim} dimensions")
        return Feature3DGSModel(config, supervision.text_encoder, geometry, fld, meta["fit_info"], device=device)
