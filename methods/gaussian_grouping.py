"""``gaussian-grouping``: Gaussian Grouping (Ye et al., ECCV 2024) on the shared deformable 4D-GS.

The 4D LangSplat paper's time-agnostic baseline, adapted to dynamic scenes as Segment Any 4D
Gaussians does: every Gaussian carries an identity encoding, rendered like a colour and classified
per pixel into the scene's mask identities; a query selects the identities whose feature matches it.

* **Geometry**: the 4D-GS the other 4D language methods use (:func:`~methods.language_methods.fit_geometry`,
  same options, so one cached fit per scene and seed serves them all), frozen. The original trains the
  identity encodings jointly with RGB; here only encodings and classifier are optimised.
* **Identities** (:func:`build_identities`): the masks of ONE SAM level (``identity.level``, default 2 =
  large, whole objects: the original's SAM "everything" masks), made consistent over time as the
  original's DEVA tracking makes them: an identity means the same thing in every training frame.
  Masks whose features are equal (to 1e-6, as :func:`~methods.language_methods.distinct_features`
  merges them) are one identity on any track: on the oracle track each mask's feature is its object's
  name embedding, so this alone gives one identity per name. The supervision's per-frame mask indices
  are NOT associated over time: the supervision cache relabels every frame to 0..M-1
  (:func:`~methods.supervision.base.relabel_levels`); the segmenters' associated ids are kept beside
  them (``FrameSupervision.segment_ids``) but not used here. So on the real track masks of consecutive
  training frames of one camera are linked here by overlap, with the segmenters' own rule
  (:class:`~methods.supervision.association.TemporalAssociator`, IoU above ``association.min_iou``).
  Cameras are not linked to each other. Pixels no mask covers are one more identity whose feature is
  the passage embedding of ``extensions.unmasked_text`` (:func:`~methods.language_methods.with_unmasked_as`).
  Each identity keeps its encoder feature, the L2-normalised mean of its masks' features: this makes
  the method open-vocabulary.
* **Fit** (:func:`train_identity_field`): per-Gaussian encodings of ``identity.dim`` channels rendered
  by the language field's rasterizer, a linear classifier to the identities, cross-entropy against each
  training frame's identity map (divided by log of the number of identities, as the original), plus
  the original's 3D regulariser every ``identity.reg_interval`` steps: for a random sample of Gaussians
  at the view's time, the KL divergence between each one's identity distribution and those of its
  ``identity.reg_k`` nearest Gaussians (itself included, as the original). Adam; seeded. Cached per
  (geometry, supervision, options, seed, device kind, code) beside the shared geometry.
* **Query** (time-agnostic only): LERF relevance of every identity's feature against the query and
  the canonical phrases, with the evaluation protocol's temperature and phrases
  (:attr:`methods.api.Model.protocol`); the identity encodings rendered at the frame's camera and time and classified
  per pixel (argmax; pixels of accumulated opacity below ``answer.uncovered_alpha`` are the unmasked
  identity); the pixel's relevance is its identity's; then the protocol's smoothing, min-max threshold
  and majority filter (:func:`~methods.fields.relevance.answer_from_relevance`) on that single map.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ClassVar, Optional, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from benchmark.core.atomic import atomic_path, write_json
from benchmark.core.cache_keys import code_digest, stable_hash
from benchmark.core.errors import InputError
from benchmark.core.memory import StagePeak
from benchmark.core.scene import Camera, Frame, Scene

from .api import AgnosticAnswer, Method, Progress
from .fields.language_field import FrozenGeometry, GaussianState, LanguageFieldConfig, camera_tensors
from .fields.relevance import AgnosticResult, answer_from_relevance, relevance
from .language_methods import (GeometryFit, config_to_dict, device_kind, fit_geometry, scene_cache_folder,
                               shared_cache_root, with_unmasked_as)
from .fields.texts import EncodedQueryModel
from .fields.views import ViewCycle
from .specs._recorded import config_from_record
from .specs.gaussian_grouping import GaussianGroupingConfig
from .supervision.association import AssociationConfig, TemporalAssociator
from .supervision.base import LEVELS, Supervision, TextEncoder

MODEL_FILE = "gaussian_grouping.pt"
META_FILE = "gaussian_grouping.json"
GEOMETRY_KIND = "4dgs"

IDENTITY_FIT_CODE = "methods.gaussian_grouping"
"""The module that runs an identity fit (this one): its code digest is part of the identity cache key."""

SH_C0 = 0.28209479177387814
"""Degree-0 spherical-harmonic constant: the original initialises encodings as ``RGB2SH(rand)``."""
KL_EPS = 1e-10
"""Added inside the logarithms of the regulariser's KL divergence (the original's)."""
VIEW_GEOMETRY_CACHE_MIB = 512.0
"""Deformed Gaussians of the training views are computed once and kept while they fit in this many MiB
(the language field's :attr:`~methods.fields.language_field.LanguageFieldConfig.cache_view_geometry_mib`)."""
KNN_CHUNK_ELEMENTS = 1 << 24
"""Distances computed at once by :func:`nearest_gaussians_brute_force` (64 MiB of float32)."""


# ---------------------------------------------------------------------------------------------------
# Identities
# ---------------------------------------------------------------------------------------------------
@dataclass
class IdentityTable:
    """The identities of a scene's training frames at one level."""

    frame_names: list[str]
    """Supervised training frames, in the supervision's order."""
    maps: list[np.ndarray]
    """Per frame, (H, W) int64 identity of each pixel; -1 = none (only without ``extensions.unmasked_text``)."""
    features: np.ndarray
    """(K, D) float32 L2-normalised feature of each identity: the mean of its masks' features."""
    mask_counts: np.ndarray
    """(K,) int64 number of (frame, mask) pairs of each identity."""
    unmasked: int
    """Index of the identity of pixels no mask covers; -1 = none (``extensions.unmasked_text`` is ``None``)."""

    @property
    def num_identities(self) -> int:
        return int(self.features.shape[0])


def uses_overlap_association(config: GaussianGroupingConfig, track: str) -> bool:
    """Whether masks are linked over time by overlap (``association.overlap``; ``"auto"``: real track)."""
    if config.association.overlap == "auto":
        return track == "real"
    return config.association.overlap == "on"


def build_identities(supervision: Supervision, level: int, unmasked_text: Optional[str], *,
                     overlap: bool, min_iou: float = 0.3) -> IdentityTable:
    """Temporally consistent identities of the masks of ``level`` (see the module docstring).

    Two masks are one identity when their features are equal to 1e-6, or (``overlap``) when the
    overlap association of consecutive training frames of one camera links them; the relation is
    closed transitively. Identities are numbered by first appearance (frame order, then mask index).
    """
    if level not in range(len(LEVELS)):
        raise ValueError(f"identity.level must be 0, 1 or 2, got {level!r}")
    filled = with_unmasked_as(supervision, unmasked_text)
    nodes = _mask_nodes(filled, level)
    groups = _UnionFind(nodes.features.shape[0])
    keys = np.round(nodes.features * 1e6).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    for n, group in enumerate(inverse.ravel().tolist()):
        groups.union(n, int(first[group]))
    if overlap:
        # the supervision's own frames (holes not filled): the unmasked region is linked by its feature
        _link_by_overlap(supervision, level, nodes.of_mask, groups, min_iou)

    roots = np.array([groups.root(n) for n in range(nodes.features.shape[0])])  # a group's root is its first node
    _, identity_of_node = np.unique(roots, return_inverse=True)  # so ranks number by first appearance
    identity_of_node = identity_of_node.ravel()
    k = int(identity_of_node.max()) + 1
    sums = np.zeros((k, nodes.features.shape[1]), np.float64)
    np.add.at(sums, identity_of_node, nodes.features)
    mask_counts = np.bincount(identity_of_node, minlength=k).astype(np.int64)
    features = sums / np.maximum(np.linalg.norm(sums, axis=1, keepdims=True), 1e-12)

    unmasked = -1
    if unmasked_text:
        text_feature = np.asarray(filled.text_encoder.encode([unmasked_text], kind="passage"), np.float32)  # [1, D]
        hit = np.flatnonzero((keys == np.round(text_feature * 1e6).astype(np.int64)).all(1))
        if hit.size:
            unmasked = int(identity_of_node[hit[0]])
        else:  # every pixel was masked: the identity exists for what no Gaussian covers at query time
            unmasked = k
            features = np.concatenate([features, text_feature.astype(np.float64)], 0)
            mask_counts = np.concatenate([mask_counts, [0]])

    maps = _identity_maps(filled, level, nodes.per_frame, identity_of_node)
    return IdentityTable([fs.name for fs in filled.frames], maps, features.astype(np.float32), mask_counts, unmasked)


@dataclass
class _MaskNodes:
    """The masks of one level that cover pixels, over all frames: the nodes identities are built from."""

    of_mask: dict[tuple[int, int], int]
    """(frame index, mask index) -> node."""
    per_frame: list[list[tuple[int, int]]]
    """Per frame, (mask index, node) of each of its masks."""
    features: np.ndarray
    """[nodes, D] float32 feature of each node's mask."""


def _mask_nodes(supervision: Supervision, level: int) -> _MaskNodes:
    """One node per mask of ``level`` that covers at least one pixel, numbered by frame then mask index."""
    of_mask: dict[tuple[int, int], int] = {}
    per_frame: list[list[tuple[int, int]]] = []
    features: list[np.ndarray] = []
    for i, fs in enumerate(supervision.frames):
        plane = fs.levels[level]
        feats = np.asarray(fs.features[level], dtype=np.float32)
        counts = np.bincount(plane[plane >= 0].ravel().astype(np.int64), minlength=feats.shape[0])
        if counts.shape[0] > feats.shape[0]:
            raise InputError(None, "supervision", f"frame {fs.name!r} level {LEVELS[level]} has mask index "
                             f"{counts.shape[0] - 1} but {feats.shape[0]} features")
        per_frame.append([])
        for j in np.flatnonzero(counts).tolist():
            of_mask[(i, j)] = len(features)
            per_frame[i].append((j, len(features)))
            features.append(feats[j])
    if not features:
        raise InputError(None, "supervision", f"no mask at level {LEVELS[level]!r} (identity.level={level}) "
                         "and no extensions.unmasked_text: there is no identity to learn")
    return _MaskNodes(of_mask, per_frame, np.stack(features))


class _UnionFind:
    """Disjoint sets of ``0..n-1``; a set's root is its smallest member."""

    def __init__(self, n: int) -> None:
        self.parent = np.arange(n)

    def root(self, n: int) -> int:
        parent = self.parent
        while parent[n] != n:
            parent[n] = parent[parent[n]]
            n = int(parent[n])
        return n

    def union(self, a: int, b: int) -> None:
        ra, rb = self.root(a), self.root(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


def _link_by_overlap(supervision: Supervision, level: int, node_of: dict[tuple[int, int], int],
                     groups: _UnionFind, min_iou: float) -> None:
    """Join the nodes of masks that the overlap association of consecutive training frames of one camera
    carries into one track (:class:`TemporalAssociator`, IoU above ``min_iou``)."""
    associator = TemporalAssociator(AssociationConfig(min_iou=min_iou))
    first_of_track: dict[int, int] = {}
    for i, fs in enumerate(supervision.frames):  # sorted by time within each camera
        plane = np.asarray(fs.levels[level], dtype=np.int64)
        tracked = associator.associate(plane[None], fs.camera_id)[0]  # (H, W) ids over time
        valid = plane >= 0
        pairs = np.unique(np.stack([plane[valid], tracked[valid]], 1), axis=0)  # [masks, 2]: (index, track)
        for j, track_id in pairs.tolist():
            node = node_of[(i, j)]
            groups.union(node, first_of_track.setdefault(track_id, node))


def _identity_maps(supervision: Supervision, level: int, per_frame: list[list[tuple[int, int]]],
                   identity_of_node: np.ndarray) -> list[np.ndarray]:
    """Per frame, the (H, W) int64 identity of each pixel of ``level`` (-1 where no mask covers it)."""
    maps = []
    for i, fs in enumerate(supervision.frames):
        plane = np.asarray(fs.levels[level], dtype=np.int64)
        lut = np.full(int(plane.max()) + 2 if plane.size else 1, -1, np.int64)  # last entry: -1 pixels
        for j, node in per_frame[i]:
            lut[j] = identity_of_node[node]
        maps.append(lut[plane])  # plane -1 reads the last entry, -1
    return maps


# ---------------------------------------------------------------------------------------------------
# The identity field
# ---------------------------------------------------------------------------------------------------
class IdentityField(nn.Module):
    """Per-Gaussian identity encodings [N, identity_dim] and the linear identity classifier."""

    def __init__(self, num_gaussians: int, identity_dim: int, num_identities: int, *,
                 generator: Optional[torch.Generator] = None, device: torch.device | str = "cpu",
                 render_backend: str = "auto", near: float = 0.01) -> None:
        super().__init__()
        if num_identities < 1:
            raise ValueError(f"num_identities must be >= 1, got {num_identities}")
        gen = generator if generator is not None else torch.Generator().manual_seed(0)
        # the original: RGB2SH(uniform [0, 1)), i.e. uniform in about [-1.77, 1.77]
        init = (torch.rand(num_gaussians, identity_dim, generator=gen) - 0.5) / SH_C0
        self.encodings = nn.Parameter(init.to(device))
        self.classifier = nn.Linear(identity_dim, num_identities).to(device)
        bound = 1.0 / math.sqrt(identity_dim)  # PyTorch's default Linear init, drawn from ``gen``
        with torch.no_grad():
            self.classifier.weight.copy_((torch.rand(num_identities, identity_dim, generator=gen) * 2 - 1) * bound)
            self.classifier.bias.copy_((torch.rand(num_identities, generator=gen) * 2 - 1) * bound)
        self.render_backend = render_backend
        self.near = near

    @property
    def identity_dim(self) -> int:
        return int(self.encodings.shape[1])

    @property
    def num_identities(self) -> int:
        return int(self.classifier.out_features)

    def render_with_alpha(self, state: GaussianState, camera: Camera,
                          prepared=None) -> tuple[torch.Tensor, torch.Tensor]:
        """([H, W, identity_dim] rendered encodings, [H, W] accumulated opacity), one rasterizer call, or one
        product with the view's frozen rendering ``prepared`` (:meth:`methods.fields.views.ViewCycle.prepared`)."""
        from methods.gaussians.rasterize import rasterize

        if prepared is not None:
            image, alpha = prepared.render(self.encodings)
            return (image.reshape(camera.height, camera.width, self.identity_dim),
                    alpha.reshape(camera.height, camera.width))
        viewmat, K, w, h = camera_tensors(camera, self.encodings.device)
        out = rasterize(state.means, state.quats, state.scales, state.opacities, self.encodings, viewmat, K, w, h,
                        near=self.near, backend=self.render_backend, channel_chunk=self.identity_dim)
        return out.image.reshape(h, w, self.identity_dim), out.alpha.reshape(h, w)

    def logits(self, encodings: torch.Tensor) -> torch.Tensor:
        """[..., K] identity logits of [..., identity_dim] encodings (rendered or per Gaussian)."""
        return self.classifier(encodings)


@dataclass
class IdentityTarget:
    """Supervision of one training view."""

    camera: Camera
    time: float
    identity: torch.Tensor
    """[H, W] int64 identity per pixel; -1 = not supervised."""


@dataclass
class IdentityReport:
    """How fitting the identity field went."""

    iterations: int
    seconds: float
    final_loss: float
    final_regulariser: float
    losses: list[float] = dataclasses.field(default_factory=list)
    rendered_by: str = "rasterizer"
    """How the training views were rendered (:attr:`methods.fields.views.ViewCycle.rendered_by`)."""


def nearest_gaussians(points: torch.Tensor, queries: torch.Tensor, k: int) -> torch.Tensor:
    """[S, k] int64 indices into ``points`` [N, 3] of the ``k`` nearest to each of ``queries`` [S, 3], exact
    (a query that is one of the points finds itself). A k-d tree on the CPU (brute force took 2.8 s for
    1 000 queries among 200 000 Gaussians, the tree 0.1 s with its construction), brute force elsewhere."""
    k = min(int(k), points.shape[0])
    if points.device.type != "cpu":
        return nearest_gaussians_brute_force(points, queries, k)
    from scipy.spatial import cKDTree

    tree = cKDTree(points.detach().numpy(), balanced_tree=False, compact_nodes=False)
    _, index = tree.query(queries.detach().numpy(), k)
    return torch.as_tensor(np.asarray(index, dtype=np.int64).reshape(queries.shape[0], k))


def nearest_gaussians_brute_force(points: torch.Tensor, queries: torch.Tensor, k: int,
                                  chunk_elements: int = KNN_CHUNK_ELEMENTS) -> torch.Tensor:
    """:func:`nearest_gaussians` by exhaustive distances, ``chunk_elements`` at a time."""
    k = min(int(k), points.shape[0])
    chunk = max(k, chunk_elements // max(1, queries.shape[0]))
    best_dist = best_index = None
    for start in range(0, points.shape[0], chunk):
        dist = torch.cdist(queries, points[start:start + chunk])  # [S, c]
        index = torch.arange(start, start + dist.shape[1], device=points.device).expand_as(dist)
        if best_dist is not None:
            dist, index = torch.cat([best_dist, dist], 1), torch.cat([best_index, index], 1)
        best_dist, pos = dist.topk(k, dim=1, largest=False)
        best_index = index.gather(1, pos)
    return best_index


def neighbour_kl(field: IdentityField, means: torch.Tensor, sample: torch.Tensor, k: int) -> torch.Tensor:
    """Mean over ``sample`` ([S] Gaussian indices) of the KL divergence between each Gaussian's identity
    distribution and those of its ``k`` nearest Gaussians at positions ``means`` [N, 3] (the original's
    ``loss_cls_3d`` before its weight and normalisation)."""
    neighbours = nearest_gaussians(means.detach(), means.detach()[sample], k).to(means.device)  # [S, k]
    rows = torch.cat([sample, neighbours.reshape(-1)])
    probs = torch.softmax(field.logits(field.encodings[rows]), dim=-1)  # [S + S k, K]
    p = probs[: sample.shape[0]].unsqueeze(1)  # [S, 1, K]
    q = probs[sample.shape[0]:].reshape(sample.shape[0], neighbours.shape[1], -1)  # [S, k, K]
    return (p * (torch.log(p + KL_EPS) - torch.log(q + KL_EPS))).sum(-1).mean()


def train_identity_field(geometry: FrozenGeometry, targets: Sequence[IdentityTarget], num_identities: int,
                         config: GaussianGroupingConfig, *, seed: int = 0,
                         progress: Optional[Callable] = None) -> tuple[IdentityField, IdentityReport]:
    """Fit an :class:`IdentityField` on ``geometry`` (frozen) to ``targets``, one random view per step."""
    if not targets:
        raise ValueError("the identity field needs at least one training view")
    device = geometry.device
    gen = torch.Generator().manual_seed(seed)
    options = config.identity
    field = IdentityField(geometry.num_gaussians, options.dim, num_identities, generator=gen, device=device,
                          render_backend=config.geometry.render_backend)
    opt = torch.optim.Adam([{"params": [field.encodings], "lr": options.learning_rate},
                            {"params": field.classifier.parameters(), "lr": options.classifier_learning_rate}])
    ce_scale = 1.0 / math.log(max(num_identities, 2))  # the original's normalisation to about [0, 1]
    supervised = [bool((t.identity >= 0).any()) for t in targets]
    views = ViewCycle(geometry, [t.time for t in targets], seed, VIEW_GEOMETRY_CACHE_MIB * 2 ** 20,
                      cameras=[t.camera for t in targets], near=field.near, render_backend=field.render_backend,
                      matrix_budget_bytes=LanguageFieldConfig().blend_matrix_mib * 2 ** 20)
    losses: list[float] = []
    loss_value = reg_value = float("nan")
    steps = range(options.iterations)
    if progress is not None:
        steps = progress(steps, desc="identities", total=options.iterations)
    start = time.perf_counter()
    for step in steps:
        v, state = views.next()
        target = targets[v]
        encodings, _ = field.render_with_alpha(state, target.camera, views.prepared(v, state))  # [H, W, d]
        logits = field.logits(encodings.reshape(-1, field.identity_dim))  # [H W, K]
        if supervised[v]:
            loss = ce_scale * F.cross_entropy(logits, target.identity.reshape(-1), ignore_index=-1)
        else:
            loss = logits.sum() * 0.0
        if options.reg_weight > 0 and step % options.reg_interval == 0:
            sample = torch.randperm(geometry.num_gaussians, generator=gen)[: options.reg_sample_size]
            kl = neighbour_kl(field, state.means, sample.to(device), options.reg_k)
            regulariser = options.reg_weight * kl / num_identities  # the original's normalisation
            loss = loss + regulariser
            reg_value = float(regulariser.detach())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % 100 == 0 or step == options.iterations - 1:
            loss_value = float(loss.detach())
            losses.append(loss_value)
    field.requires_grad_(False)
    return field, IdentityReport(options.iterations, time.perf_counter() - start, loss_value, reg_value, losses,
                                 views.rendered_by)


def identity_targets(scene: Scene, table: IdentityTable, device: str | torch.device) -> list[IdentityTarget]:
    """One :class:`IdentityTarget` per supervised training frame."""
    targets = []
    for name, identity in zip(table.frame_names, table.maps):
        frame = scene.frame(name)
        size = (frame.camera.height, frame.camera.width)
        if tuple(identity.shape) != size:
            raise InputError(frame.image_path, "supervision",
                             f"masks of frame {name!r} are {tuple(identity.shape)} but its camera is {size}")
        targets.append(IdentityTarget(frame.camera, float(frame.time), torch.as_tensor(identity, device=device)))
    return targets


# ---------------------------------------------------------------------------------------------------
# Fitting, cached
# ---------------------------------------------------------------------------------------------------
@dataclass
class IdentityFit:
    """The fitted identity field of a scene and what the query needs of its identities."""

    field: IdentityField
    features: torch.Tensor
    """[K, D] L2-normalised feature of each identity."""
    unmasked: int
    """Index of the unmasked identity; -1 = none."""
    info: dict
    """Fit facts: cache key, identities (count, level, association), the field stage (seconds, peaks)."""
    cached: bool = False
    """Whether it came from the shared cache."""


def identity_options(config: GaussianGroupingConfig, track: str) -> dict[str, Any]:
    """What an identity fit depends on besides geometry, supervision, seed, device and code."""
    return {"identity": config_to_dict(config.identity), "overlap": uses_overlap_association(config, track),
            "association_min_iou": config.association.min_iou, "unmasked_text": config.extensions.unmasked_text,
            "render_backend": config.geometry.render_backend}


def identity_key(geo: GeometryFit, supervision: Supervision, config: GaussianGroupingConfig, seed: int,
                 device: str) -> str:
    return stable_hash({"geometry": geo.key, "supervision": supervision.fingerprint,
                        "options": identity_options(config, supervision.track), "seed": seed,
                        "device": device_kind(device),
                        "code": code_digest(IDENTITY_FIT_CODE)}, 24)


def identity_cache_path(cache_root: Path, scene: Scene, key: str) -> Path:
    """Where the identity fit of ``key`` is kept: beside the scene's shared geometry."""
    return scene_cache_folder(Path(cache_root), scene) / f"identities-{GEOMETRY_KIND}-{key}.pt"


def _field_state(fit: IdentityFit) -> dict:
    return {"encodings": fit.field.encodings.detach().cpu(),
            "classifier": {k: v.detach().cpu() for k, v in fit.field.classifier.state_dict().items()},
            "features": fit.features.detach().cpu(), "unmasked": int(fit.unmasked)}


def _fit_from_state(state: dict, geometry: FrozenGeometry, config: GaussianGroupingConfig, info: dict,
                    device: str | torch.device) -> IdentityFit:
    """The :class:`IdentityFit` of a saved state; raises ``ValueError`` when it does not fit ``geometry``."""
    encodings, features = state["encodings"], state["features"]
    weight = state["classifier"]["weight"]
    k = int(weight.shape[0])
    dim = config.identity.dim
    if (tuple(encodings.shape) != (geometry.num_gaussians, dim)
            or tuple(weight.shape) != (k, dim) or features.shape[0] != k
            or not -1 <= int(state["unmasked"]) < k):
        raise ValueError("saved identity field does not match the geometry and options")
    field = IdentityField(geometry.num_gaussians, dim, k, device=device, render_backend=config.geometry.render_backend)
    field.encodings.data.copy_(encodings)
    field.classifier.load_state_dict(state["classifier"])
    field.requires_grad_(False)
    return IdentityFit(field, features.to(device=device, dtype=torch.float32), int(state["unmasked"]), info)


def fit_identities(scene: Scene, supervision: Supervision, config: GaussianGroupingConfig, geo: GeometryFit, *,
                   seed: int, device: str, progress: Progress, cache_root: Optional[Path]) -> IdentityFit:
    """The identity field of ``scene`` on the frozen ``geo`` (cached when ``cache_root`` is given)."""
    key = identity_key(geo, supervision, config, seed, device)
    path = None if cache_root is None else identity_cache_path(cache_root, scene, key)
    if path is not None and path.is_file():
        try:
            saved = torch.load(path, map_location=device, weights_only=True)
            if saved.get("key") != key:
                raise ValueError("key mismatch")
            fit = _fit_from_state(saved, geo.geometry, config, json.loads(saved["info"]), device)
            progress.log(f"identities: cached fit {path.name}")
            return dataclasses.replace(fit, cached=True)
        except Exception:  # a corrupt or foreign cache file is refitted, never trusted
            progress.log(f"identities: {path.name} unreadable; fitting again")

    overlap = uses_overlap_association(config, supervision.track)
    with StagePeak(device) as peak:
        level = config.identity.level
        table = build_identities(supervision, level, config.extensions.unmasked_text, overlap=overlap,
                                 min_iou=config.association.min_iou)
        progress.log(f"identities: {table.num_identities} at level {LEVELS[level]} over "
                     f"{len(table.maps)} training frames" + (" (overlap association)" if overlap else ""))
        targets = identity_targets(scene, table, device)
        field, report = train_identity_field(geo.geometry, targets, table.num_identities, config, seed=seed,
                                             progress=progress)
    info = {"key": key,
            "identities": {"count": table.num_identities, "level": LEVELS[level],
                           "unmasked": table.unmasked, "overlap_association": overlap,
                           "masks": int(table.mask_counts.sum()), "frames": len(table.maps)},
            "field": {"kind": "identity", "iterations": report.iterations, "seconds": report.seconds,
                      "final_loss": report.final_loss, "final_regulariser": report.final_regulariser,
                      "rendered_by": report.rendered_by,
                      "losses": report.losses, "views": len(targets), **peak.record()}}
    fit = IdentityFit(field, torch.as_tensor(table.features, device=device), table.unmasked, info)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            torch.save({"key": key, **_field_state(fit), "info": json.dumps(info)}, tmp)
    return fit


# ---------------------------------------------------------------------------------------------------
# The fitted model
# ---------------------------------------------------------------------------------------------------
class GaussianGroupingModel(EncodedQueryModel):
    """A fitted ``gaussian-grouping`` on one scene (see the module docstring)."""

    supports = frozenset({"agnostic"})
    MAX_CACHE_BYTES: ClassVar[int] = 1 << 28
    """Memory for per-frame identity maps kept between prepared queries (oldest dropped beyond it)."""

    def __init__(self, config: GaussianGroupingConfig, text_encoder: TextEncoder, geometry: FrozenGeometry,
                 fit: IdentityFit, *, device: str = "cpu") -> None:
        self.config = config
        self.text_encoder = text_encoder
        self.geometry = geometry
        self.field = fit.field
        self.identity_features = fit.features  # [K, D]
        self.unmasked = fit.unmasked
        self.fit_info = fit.info
        self.device = torch.device(device)
        self._keep_maps = False
        self._maps: dict[str, torch.Tensor] = {}  # frame name -> [H, W] identity map

    def use_answer_options(self, config: GaussianGroupingConfig) -> None:
        """Answer with ``config``'s ``answer`` group, the fitted state unchanged; kept identity maps are
        dropped (``answer.uncovered_alpha`` shapes them)."""
        self.config = dataclasses.replace(self.config, answer=config.answer)
        self._maps.clear()

    def describe(self) -> dict:
        """What the fit did (geometry, identities, identity field), for the results file."""
        info = {k: v for k, v in self.fit_info.items() if k != "field"}
        if "field" in self.fit_info:
            info["field"] = {k: v for k, v in self.fit_info["field"].items() if k != "losses"}
        return info

    def prepare(self, texts: Sequence[str]) -> None:
        """Keep each frame's identity map for the coming ``texts`` (they do not depend on the text)."""
        self._maps.clear()
        self._keep_maps = bool(texts)

    # -- query pieces ---------------------------------------------------------------------------------
    def identity_relevance(self, text: str) -> torch.Tensor:
        """[K] LERF relevance of each identity's feature to ``text``."""
        return relevance(self.identity_features, self.query_embedding(text), self.canonical(),
                         self.relevance_cfg.temperature)

    @torch.no_grad()
    def identity_map(self, frame: Frame) -> torch.Tensor:
        """[H, W] int64 identity of each pixel at the frame's camera and time (uncovered: the unmasked one)."""
        kept = self._maps.get(frame.name)
        if kept is not None:
            return kept
        encodings, alpha = self.field.render_with_alpha(self.geometry.at(frame.time), frame.camera)
        identity = self.field.logits(encodings).argmax(-1)  # [H, W]
        if self.unmasked >= 0:
            identity = torch.where(alpha < self.config.answer.uncovered_alpha, self.unmasked, identity)
        if self._keep_maps:
            size = identity.numel() * identity.element_size()
            while self._maps and size * (len(self._maps) + 1) > self.MAX_CACHE_BYTES:
                self._maps.pop(next(iter(self._maps)))
            self._maps[frame.name] = identity
        return identity

    @torch.no_grad()
    def agnostic(self, text: str, frame: Frame) -> AgnosticResult:
        """The protocol's time-agnostic steps on the identity relevance map of one frame."""
        rel = self.identity_relevance(text)[self.identity_map(frame)]  # [H, W]
        return answer_from_relevance(rel[None], self.relevance_cfg)

    def query_agnostic(self, text: str, frames: Sequence[Frame]) -> list[AgnosticAnswer]:
        out = []
        for frame in frames:
            res = self.agnostic(text, frame)
            out.append(AgnosticAnswer(mask=res.mask.cpu().numpy(), relevance=res.relevance.float().cpu().numpy()))
        return out

    # -- persistence --------------------------------------------------------------------------------------
    def save(self, directory: Path) -> None:
        directory = Path(directory)
        fit = IdentityFit(self.field, self.identity_features, self.unmasked, self.fit_info)
        with atomic_path(directory / MODEL_FILE) as tmp:
            torch.save({"geometry": self.geometry.state_dict(), **_field_state(fit)}, tmp)
        write_json(directory / META_FILE, {"method": GaussianGrouping.name, "config": config_to_dict(self.config),
                                           "fit_info": self.fit_info})


class GaussianGrouping(Method):
    """Gaussian Grouping on the shared 4D-GS (see the module docstring)."""

    name: ClassVar[str] = "gaussian-grouping"
    supports = frozenset({"agnostic"})

    @classmethod
    def fit(cls, scene: Scene, supervision: Supervision, config: GaussianGroupingConfig, *, seed: int, device: str,
            progress: Progress, work_dir: Optional[Path] = None) -> GaussianGroupingModel:
        if not isinstance(config, GaussianGroupingConfig):
            raise TypeError(f"config must be a GaussianGroupingConfig, got {type(config).__name__}")
        cache_root = shared_cache_root(config, work_dir)
        geo = fit_geometry(scene, GEOMETRY_KIND, config, seed=seed, device=device, progress=progress,
                           cache_root=cache_root)
        fit = fit_identities(scene, supervision, config, geo, seed=seed, device=device, progress=progress,
                             cache_root=cache_root)
        fit.info = {**fit.info, "geometry": geo.info, "cached": {"geometry": geo.cached, "identities": fit.cached}}
        return GaussianGroupingModel(config, supervision.text_encoder, geo.geometry, fit, device=device)

    @classmethod
    def load(cls, directory: Path, *, supervision: Supervision, device: str) -> GaussianGroupingModel:
        directory = Path(directory)
        meta = json.loads((directory / META_FILE).read_text())
        config = config_from_record(GaussianGroupingConfig, meta["config"], what=f"{directory / META_FILE}: config")
        state = torch.load(directory / MODEL_FILE, map_location=device, weights_only=True)
        geometry = FrozenGeometry.from_state_dict(state["geometry"], device)
        fit = _fit_from_state(state, geometry, config, meta["fit_info"], device)
        return GaussianGroupingModel(config, supervision.text_encoder, geometry, fit, device=device)
