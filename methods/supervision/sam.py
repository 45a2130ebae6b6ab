"""The ``sam`` segmenter (real track): Segment Anything automatic masks split into small / middle / large.

How the release (LangSplat, reused by 4D LangSplat) gets three levels out of SAM: a grid of point
prompts (32 x 32), each answered with SAM's three multimask outputs; output 0, 1, 2 of every point
go to the small, middle and large level. Per level, masks are filtered as SAM's automatic generator
does (predicted IoU > 0.7, stability score >= 0.85, box NMS at 0.7, small regions and holes below
100 px removed), then by the release's mask NMS (IoU 0.8, score = stability x predicted IoU > 0.7,
nested-mask rule with 0.5), and painted into one id map per level. 4D LangSplat makes ids consistent
over time with DEVA tracking; here ids are carried across frames by overlap
(:mod:`methods.supervision.association`).

Differences from the release, stated: the release also runs SAM on image crops (``crop_n_layers=1``)
and merges them; not done here (one full-image pass). The release paints masks in generator order,
so a later large mask can hide an earlier small one; here masks are painted largest first, so every
kept mask stays visible.

Model backends (:class:`MultimaskPredictor`), weights from a local path on the user's machine:

* ``backend="segment-anything"``: the official ``segment_anything`` package (optional extra
  ``bench4d[sam]``). It imports torchvision at package import, which the core install does not have,
  so here it is an optional import that fails with a clear error.
* ``backend="hf"``: ``transformers.SamModel`` (same architecture and weights, e.g.
  ``facebook/sam-vit-huge``), with SAM's own preprocessing (longest side to the model's input size,
  ImageNet normalisation in 0-255 units, zero padding) done here in torch.
"""

from __future__ import annotations

import abc
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch
import torch.nn.functional as F

from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from ..backends import WEIGHT_DTYPES
from .association import AssociationConfig, TemporalAssociator
from .base import LEVELS, Segmenter

SAM_PIXEL_MEAN: tuple[float, float, float] = (123.675, 116.28, 103.53)
"""SAM's input mean, 0-255 units."""
SAM_PIXEL_STD: tuple[float, float, float] = (58.395, 57.12, 57.375)
"""SAM's input standard deviation, 0-255 units."""
DEFAULT_HF_MODEL = "facebook/sam-vit-huge"
"""Hub id of SAM ViT-H in transformers format (loaded on a user's machine)."""
SAM_CPU_POINTS = 64
"""Point prompts decoded at once on the CPU (SAM's automatic generator's default)."""
SAM_MAX_POINTS = 256
"""Most point prompts decoded at once on CUDA (a quarter of the 32 x 32 grid)."""
SAM_INPUT_SIZE = 1024
"""Side of SAM's square input (ViT-H)."""


@dataclass
class SamConfig:
    """SAM automatic-mask settings of the release, the level split's filters, and association."""

    points_per_side: int = 32
    """Point prompts per image side (release: 32)."""
    points_per_batch: Optional[int] = None
    """Point prompts decoded at once (memory only, so not part of the cache key); ``None``: the memory plan's
    (:func:`plan_sam`: :data:`SAM_CPU_POINTS` on the CPU, from the free memory on CUDA)."""
    pred_iou_thresh: float = 0.7
    """Keep masks whose predicted IoU exceeds this (release: 0.7)."""
    stability_score_thresh: float = 0.85
    """Keep masks whose stability score reaches this (release: 0.85)."""
    stability_score_offset: float = 1.0
    """Logit offset of the stability score (SAM: 1.0)."""
    mask_threshold: float = 0.0
    """Logit above which a pixel is in the mask (SAM: 0.0)."""
    box_nms_thresh: float = 0.7
    """Box IoU above which the lower-scoring of two masks is dropped (release: 0.7)."""
    min_mask_region_area: int = 100
    """Holes and islands smaller than this many pixels are removed from each mask (release: 100,
    at about 1K px images)."""
    nms_iou_thresh: float = 0.8
    """Release mask NMS: drop a mask overlapping a better one with IoU above this (release: 0.8)."""
    nms_score_thresh: float = 0.7
    """Release mask NMS: keep masks whose stability x predicted IoU exceeds this (release: 0.7)."""
    nms_inner_thresh: float = 0.5
    """Release mask NMS: nested-mask rule threshold (release: 0.5)."""
    association_min_iou: float = 0.3
    """A mask continues the id of a mask of the previous frame of its camera above this IoU."""


# ---------------------------------------------------------------------------------------------------
# Model backends
# ---------------------------------------------------------------------------------------------------
class MultimaskPredictor(abc.ABC):
    """SAM's promptable decoder with three outputs per point."""

    @abc.abstractmethod
    def set_image(self, image: np.ndarray) -> None:
        """Embed one (H, W, 3) uint8 RGB image."""

    @abc.abstractmethod
    def predict(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[P, 2] ``(x, y)`` pixel prompts -> ([P, 3, H, W] mask logits at image size, [P, 3] predicted IoU)."""

    def config(self) -> dict[str, Any]:
        return {"backend": type(self).__name__}


def load_segment_anything(checkpoint: str | Path, model_type: str = "vit_h", device: str = "cpu"):
    """A ``segment_anything.SamPredictor`` of the local weights ``checkpoint`` (architecture ``model_type``:
    ``vit_b``, ``vit_l`` or ``vit_h``), in eval mode on ``device``: the one loader of the official package's
    models, for this segmenter and the annotation tool's assisted segmentation. Every failure is an
    :class:`InputError` that says what to do."""
    try:
        from segment_anything import SamPredictor, sam_model_registry
    except Exception as err:  # ImportError of segment_anything itself or of torchvision inside it
        raise InputError(None, "sam backend segment-anything",
                         f"cannot import segment_anything ({err.__class__.__name__}: {err}); it needs "
                         "torchvision: pip install 'bench4d[sam]', or use backend='hf' (transformers)") from None
    path = Path(checkpoint)
    if not path.is_file():
        raise InputError(path, "sam checkpoint", "file not found (weights load from a local path only)")
    if model_type not in sam_model_registry:
        raise InputError(None, "sam model_type", f"unknown SAM model {model_type!r} "
                                                 f"(known: {', '.join(sorted(sam_model_registry))})")
    try:
        model = sam_model_registry[model_type](checkpoint=str(path))
    except Exception as err:  # torch's messages for a wrong checkpoint are long
        raise InputError(path, "sam checkpoint",
                         f"cannot load as SAM {model_type}: {type(err).__name__}: {str(err)[:200]}") from None
    return SamPredictor(model.to(device).eval())


class SegmentAnythingPredictor(MultimaskPredictor):
    """The official ``segment_anything`` package (needs torchvision: optional extra ``bench4d[sam]``)."""

    def __init__(self, checkpoint: str | Path, model_type: str = "vit_h", device: str = "cpu") -> None:
        self.predictor = load_segment_anything(checkpoint, model_type, device)
        self.model_type, self.checkpoint = model_type, Path(checkpoint)
        self.device = torch.device(device)
        self._size: Optional[tuple[int, int]] = None

    def set_image(self, image: np.ndarray) -> None:
        self.predictor.set_image(image)
        self._size = image.shape[:2]

    @torch.no_grad()
    def predict(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        pts = self.predictor.transform.apply_coords_torch(points.to(self.device).float(), self._size)
        labels = torch.ones(pts.shape[0], 1, dtype=torch.int, device=self.device)
        masks, iou, _ = self.predictor.predict_torch(pts[:, None, :], labels, multimask_output=True, return_logits=True)
        return masks, iou

    def config(self) -> dict[str, Any]:
        return {"backend": "segment-anything", "model_type": self.model_type, "checkpoint": self.checkpoint.name}


class HFSamPredictor(MultimaskPredictor):
    """``transformers.SamModel`` from a local folder or hub id, SAM's preprocessing done in torch."""

    def __init__(self, model: str | Path = DEFAULT_HF_MODEL, *, device: str = "cpu", dtype: str = "float32",
                 local_files_only: bool = True) -> None:
        try:
            from transformers import SamModel
        except ImportError as err:  # pragma: no cover - transformers is a declared extra
            raise InputError(None, "sam backend hf", "package 'transformers' is not installed") from err
        if dtype not in WEIGHT_DTYPES:
            raise InputError(None, "sam dtype", f"unknown dtype {dtype!r}; use one of {', '.join(WEIGHT_DTYPES)}")
        self.model_name = str(model)
        self.device = torch.device(device)
        self.dtype = getattr(torch, dtype)
        try:
            self.model = SamModel.from_pretrained(self.model_name, local_files_only=local_files_only,
                                                  torch_dtype=self.dtype).to(self.device).eval()
        except (OSError, ValueError) as err:
            raise InputError(Path(self.model_name) if Path(self.model_name).exists() else None, "sam model",
                             f"cannot load SAM weights from {self.model_name!r} ({err.__class__.__name__}); pass "
                             f"model=<local folder of a transformers SAM model> (default hub id {DEFAULT_HF_MODEL!r}, "
                             "fetched on your machine with local_files_only=False)") from None
        size = self.model.config.vision_config.image_size
        self.input_size = int(size[0] if isinstance(size, (list, tuple)) else size)
        self._embeddings: Optional[torch.Tensor] = None
        self._size: tuple[int, int] = (0, 0)
        self._resized: tuple[int, int] = (0, 0)

    def set_image(self, image: np.ndarray) -> None:
        h, w = image.shape[:2]
        scale = self.input_size / max(h, w)
        nh, nw = int(h * scale + 0.5), int(w * scale + 0.5)  # SAM's ResizeLongestSide rounding
        x = torch.as_tensor(np.ascontiguousarray(image), device=self.device).permute(2, 0, 1)[None].float()
        x = F.interpolate(x, size=(nh, nw), mode="bilinear", align_corners=False, antialias=True)
        mean = torch.tensor(SAM_PIXEL_MEAN, device=self.device).view(1, 3, 1, 1)
        std = torch.tensor(SAM_PIXEL_STD, device=self.device).view(1, 3, 1, 1)
        x = F.pad((x - mean) / std, (0, self.input_size - nw, 0, self.input_size - nh)).to(self.dtype)
        with torch.no_grad():
            self._embeddings = self.model.get_image_embeddings(x)
        self._size, self._resized = (h, w), (nh, nw)

    @torch.no_grad()
    def predict(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self._embeddings is None:
            raise RuntimeError("call set_image first")
        (h, w), (nh, nw) = self._size, self._resized
        pts = points.to(self.device).float() * torch.tensor([nw / w, nh / h], device=self.device)
        out = self.model(image_embeddings=self._embeddings, input_points=pts[None, :, None, :],
                         input_labels=torch.ones(1, pts.shape[0], 1, dtype=torch.long, device=self.device),
                         multimask_output=True)
        low = out.pred_masks[0]  # [P, 3, h', w'] low-resolution logits of the padded input
        up = F.interpolate(low, size=(self.input_size, self.input_size), mode="bilinear", align_corners=False)
        up = up[..., :nh, :nw]
        logits = F.interpolate(up, size=(h, w), mode="bilinear", align_corners=False)
        return logits, out.iou_scores[0]

    def config(self) -> dict[str, Any]:
        return {"backend": "transformers", "model": Path(self.model_name).name or self.model_name,
                "dtype": str(self.dtype).replace("torch.", "")}


# ---------------------------------------------------------------------------------------------------
# Level split and filters
# ---------------------------------------------------------------------------------------------------
def point_grid(points_per_side: int, height: int, width: int) -> torch.Tensor:
    """[n^2, 2] ``(x, y)`` pixel prompts at the centres of an n x n grid (SAM's layout)."""
    offset = 1.0 / (2 * points_per_side)
    ticks = torch.linspace(offset, 1 - offset, points_per_side)
    gy, gx = torch.meshgrid(ticks, ticks, indexing="ij")
    return torch.stack([gx.reshape(-1) * width, gy.reshape(-1) * height], -1)


def stability_scores(logits: torch.Tensor, threshold: float, offset: float) -> torch.Tensor:
    """[K, H, W] logits -> [K] IoU between the masks at ``threshold + offset`` and ``threshold - offset``."""
    inter = (logits > threshold + offset).flatten(1).sum(1).float()
    union = (logits > threshold - offset).flatten(1).sum(1).float()
    return inter / union.clamp_min(1.0)


def boxes_of(masks: torch.Tensor) -> torch.Tensor:
    """[K, H, W] bool -> [K, 4] float ``(x0, y0, x1, y1)`` inclusive pixel boxes (zeros for empty masks)."""
    k, h, w = masks.shape
    if k == 0:
        return masks.new_zeros(0, 4, dtype=torch.float32)
    rows, cols = masks.any(2), masks.any(1)
    ar_h = torch.arange(h, device=masks.device).float()
    ar_w = torch.arange(w, device=masks.device).float()
    inf = torch.tensor(float("inf"), device=masks.device)
    x0 = torch.where(cols, ar_w, inf).amin(1)
    x1 = torch.where(cols, ar_w, -inf).amax(1)
    y0 = torch.where(rows, ar_h, inf).amin(1)
    y1 = torch.where(rows, ar_h, -inf).amax(1)
    box = torch.stack([x0, y0, x1, y1], 1)
    return torch.where(torch.isfinite(box), box, torch.zeros_like(box))


def box_nms(boxes: torch.Tensor, scores: torch.Tensor, threshold: float) -> torch.Tensor:
    """Indices (by decreasing score) of the boxes kept by greedy NMS at IoU ``threshold``."""
    order = torch.argsort(scores, descending=True)
    b = boxes[order]
    area = (b[:, 2] - b[:, 0] + 1) * (b[:, 3] - b[:, 1] + 1)
    lt = torch.maximum(b[:, None, :2], b[None, :, :2])
    rb = torch.minimum(b[:, None, 2:], b[None, :, 2:])
    wh = (rb - lt + 1).clamp_min(0)
    inter = wh[..., 0] * wh[..., 1]
    iou = inter / (area[:, None] + area[None, :] - inter).clamp_min(1e-9)
    keep = torch.ones(len(order), dtype=torch.bool, device=boxes.device)
    for i in range(len(order)):
        if keep[i]:
            later = torch.arange(len(order), device=boxes.device) > i
            keep &= ~(later & (iou[i] > threshold))
    return order[keep]


def remove_small_regions(mask: np.ndarray, area: int) -> np.ndarray:
    """Fill holes and drop islands smaller than ``area`` pixels (SAM's post-processing, OpenCV)."""
    import cv2

    if area <= 0:
        return mask
    out = mask.copy()
    for fill in (True, False):  # holes first, then islands
        work = (~out if fill else out).astype(np.uint8)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(work, connectivity=8)
        small = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] < area]
        if not small:
            continue
        hit = np.isin(labels, small)
        out = out | hit if fill else out & ~hit
    return out


def release_mask_nms(masks: torch.Tensor, scores: torch.Tensor, iou_thr: float, score_thr: float,
                     inner_thr: float) -> torch.Tensor:
    """LangSplat's mask NMS (vectorised): indices of the kept masks, by decreasing score.

    A mask is dropped when a better-scoring mask overlaps it with IoU above ``iou_thr``, when its score
    is at most ``score_thr``, or when it is nested in another mask (>= 85 % of one inside the other,
    < 50 % the other way) with ``1 - ratio_a ratio_b > 1 - inner_thr``. When a criterion would drop
    every mask, the three best-scoring masks pass it (release).
    """
    scores, order = torch.sort(scores, descending=True)
    m = masks[order].flatten(1).float()  # [K, HW]
    k = m.shape[0]
    area = m.sum(1)
    inter = m @ m.T
    union = area[:, None] + area[None, :] - inter
    iou = torch.triu(inter / union.clamp_min(1e-9), diagonal=1)
    ratio = inter / area[:, None].clamp_min(1e-9)  # ratio[i, j] = inter / area_i
    ratio_t = ratio.T  # ratio_t[i, j] = inter / area_j
    upper = torch.triu(torch.ones(k, k, dtype=torch.bool, device=m.device), diagonal=0)
    inner_val = 1.0 - ratio * ratio_t
    # pair i <= j (i scores higher): j mostly inside i -> [i, j]; i mostly inside j -> [j, i]
    case_a = upper & (ratio < 0.5) & (ratio_t >= 0.85)
    case_b = upper & (ratio >= 0.85) & (ratio_t < 0.5)
    inner = torch.where(case_a, inner_val, torch.zeros_like(inner_val))
    inner = inner + torch.where(case_b, inner_val, torch.zeros_like(inner_val)).T
    inner_u = torch.triu(inner, diagonal=1).amax(0) if k else inner.new_zeros(0)
    inner_l = torch.tril(inner, diagonal=1).amax(0) if k else inner.new_zeros(0)
    keep = iou.amax(0) <= iou_thr if k else torch.zeros(0, dtype=torch.bool)
    for crit in (scores > score_thr, inner_u <= 1 - inner_thr, inner_l <= 1 - inner_thr):
        if k and not bool(crit.any()):
            crit = crit.clone()
            crit[: min(3, k)] = True
        keep = keep & crit
    return order[keep]


def paint(masks: torch.Tensor) -> np.ndarray:
    """[K, H, W] bool -> (H, W) int32 id map, largest first so smaller masks stay visible; -1 = none."""
    k, h, w = masks.shape
    out = np.full((h, w), -1, dtype=np.int32)
    if k == 0:
        return out
    order = torch.argsort(masks.flatten(1).sum(1), descending=True).tolist()
    m = masks.cpu().numpy()
    for i in order:
        out[m[i]] = i
    return out


class SamSegmenter(Segmenter):
    """Automatic SAM masks split into the three levels (module docstring)."""

    name = "sam"
    track = "real"

    def __init__(self, predictor: MultimaskPredictor, cfg: Optional[SamConfig] = None) -> None:
        self.predictor = predictor
        self.cfg = cfg or SamConfig()
        self.associator = TemporalAssociator(AssociationConfig(min_iou=self.cfg.association_min_iou))

    def config(self) -> dict[str, Any]:
        settings = {k: v for k, v in asdict(self.cfg).items() if k != "points_per_batch"}  # memory only
        return {"name": self.name, **self.predictor.config(), **settings}

    def level_masks(self, image: np.ndarray) -> list[torch.Tensor]:
        """Per level, the [K, H, W] bool masks kept for one (H, W, 3) uint8 image."""
        c = self.cfg
        h, w = image.shape[:2]
        self.predictor.set_image(image)
        grid = point_grid(c.points_per_side, h, w)
        step = c.points_per_batch or SAM_CPU_POINTS
        kept: list[list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]] = [[] for _ in LEVELS]
        for s in range(0, grid.shape[0], step):
            logits, iou = self.predictor.predict(grid[s:s + step])
            for level in range(len(LEVELS)):
                lg, sc = logits[:, level], iou[:, level]
                ok = sc > c.pred_iou_thresh
                lg, sc = lg[ok], sc[ok]
                stab = stability_scores(lg, c.mask_threshold, c.stability_score_offset)
                ok = stab >= c.stability_score_thresh
                kept[level].append(((lg[ok] > c.mask_threshold).cpu(), sc[ok].cpu(), stab[ok].cpu()))
        out = []
        for level in range(len(LEVELS)):
            masks = torch.cat([m for m, _, _ in kept[level]]) if kept[level] else torch.zeros(0, h, w, dtype=torch.bool)
            iou = torch.cat([i for _, i, _ in kept[level]]) if kept[level] else torch.zeros(0)
            stab = torch.cat([s for _, _, s in kept[level]]) if kept[level] else torch.zeros(0)
            nonempty = masks.flatten(1).any(1)
            masks, iou, stab = masks[nonempty], iou[nonempty], stab[nonempty]
            if masks.shape[0]:
                keep = box_nms(boxes_of(masks), iou, c.box_nms_thresh)
                masks, iou, stab = masks[keep], iou[keep], stab[keep]
                if c.min_mask_region_area > 0:
                    masks = torch.stack([torch.as_tensor(remove_small_regions(m.numpy(), c.min_mask_region_area))
                                         for m in masks])
                nonempty = masks.flatten(1).any(1)
                masks, iou, stab = masks[nonempty], iou[nonempty], stab[nonempty]
            if masks.shape[0]:
                keep = release_mask_nms(masks, stab * iou, c.nms_iou_thresh, c.nms_score_thresh, c.nms_inner_thresh)
                masks = masks[keep]
            out.append(masks)
        return out

    def segment(self, frame: Frame) -> np.ndarray:
        """(3, H, W) int32 ids, consistent with the frames segmented before (call in time order)."""
        image = np.clip(np.asarray(frame.image()) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        ids = np.stack([paint(m) for m in self.level_masks(image)])
        return self.associator.associate(ids, frame.camera_id)


def sam_point_gb(height: int, width: int, input_size: int = SAM_INPUT_SIZE) -> float:
    """GPU memory of decoding one point prompt, GB: its three mask logits at the model's input size and at
    the image's, each held in about three float32 copies at once (upsampling, cropping, thresholds); an
    estimate."""
    from methods.backends import GIB

    return 3 * 3 * 4 * (input_size ** 2 + height * width) / GIB


def plan_sam(device: str, *, height: int = SAM_INPUT_SIZE, width: int = SAM_INPUT_SIZE,
             free_bytes: Optional[int] = None, dtype: Optional[str] = None, weights: str = "sam"):
    """The :class:`~methods.backends.MemoryPlan` of SAM on ``device`` for ``height`` x ``width`` frames: on the
    CPU full precision and :data:`SAM_CPU_POINTS` prompts at once; on CUDA half precision (``dtype``
    overrides it) and the prompts the free memory (``free_bytes``, else what the GPU reports) holds beside
    the weights (:func:`sam_point_gb` each), at most :data:`SAM_MAX_POINTS`. ``weights``: the
    :data:`methods.backends.BACKENDS` entry of the weights. A GPU without room for the weights is a one-line
    :class:`~benchmark.core.errors.InputError`."""
    from methods.backends import backend, plan_memory

    return plan_memory(backend(weights), device, per_item_gb=sam_point_gb(height, width), max_batch=SAM_MAX_POINTS,
                       cpu_batch=SAM_CPU_POINTS, free_bytes=free_bytes, dtype=dtype, offload=False)


def largest_frame(scene: Optional[Scene]) -> tuple[int, int]:
    """(height, width) of the scene's largest training frame; SAM's input size without a scene."""
    frames = scene.train_frames if scene is not None else []
    if not frames:
        return SAM_INPUT_SIZE, SAM_INPUT_SIZE
    biggest = max(frames, key=lambda f: f.camera.height * f.camera.width)
    return biggest.camera.height, biggest.camera.width


def create(scene: Scene, *, text_encoder=None, device: str = "cpu", backend: str = "hf",
           model: Optional[str] = None, checkpoint: Optional[str] = None, model_type: str = "vit_h",
           local_files_only: bool = True, dtype: Optional[str] = None, free_bytes: Optional[int] = None,
           **options: Any) -> SamSegmenter:
    """Factory of the registry.

    ``backend="hf"`` (default): ``model`` = local folder or hub id of a transformers SAM (default
    :data:`DEFAULT_HF_MODEL`; ``$BENCH4D_SAM`` overrides), ``dtype`` (default: the memory plan's).
    ``backend="segment-anything"``: ``checkpoint`` = local ``sam_vit_h_4b8939.pth`` (or
    ``$BENCH4D_SAM_CHECKPOINT``), ``model_type``; full precision (its predictor prepares float32 input).
    Other ``options`` are fields of :class:`SamConfig`; ``points_per_batch`` defaults to the memory plan's
    (:func:`plan_sam` for the scene's largest frame; ``free_bytes``: free GPU memory to plan with).
    """
    import os

    try:
        cfg = SamConfig(**options)
    except TypeError as err:
        raise InputError(None, "sam options", str(err)) from None
    if backend not in ("hf", "segment-anything"):
        raise InputError(None, "sam backend", f"unknown backend {backend!r}; use 'hf' or 'segment-anything'")
    height, width = largest_frame(scene)
    plan = plan_sam(device, height=height, width=width, free_bytes=free_bytes, dtype=dtype,
                    weights="sam" if backend == "hf" else "sam-checkpoint")
    if cfg.points_per_batch is None:
        cfg.points_per_batch = plan.batch_size
    if backend == "hf":
        predictor: MultimaskPredictor = HFSamPredictor(model or os.environ.get("BENCH4D_SAM", DEFAULT_HF_MODEL),
                                                       device=device, dtype=dtype or plan.dtype or "float32",
                                                       local_files_only=local_files_only)
    else:
        ckpt = checkpoint or os.environ.get("BENCH4D_SAM_CHECKPOINT")
        if not ckpt:
            raise InputError(None, "sam checkpoint", "pass checkpoint=<path of sam_vit_h_4b8939.pth> or set "
                                                     "$BENCH4D_SAM_CHECKPOINT (weights load from a local path only)")
        predictor = SegmentAnythingPredictor(ckpt, model_type=model_type, device=device)
    return SamSegmenter(predictor, cfg)
