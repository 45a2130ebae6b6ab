"""Mask propagation between neighbouring frames: a proposal the annotator accepts or edits.

One step (:func:`propagate_step`) carries a mask from a source frame to the next frame:

1. dense optical flow source -> target with OpenCV's DIS;
2. an affine (or similarity) motion fitted with RANSAC to the flow sampled *inside the shrunken
   mask* (flow at the boundary mixes object and background motion);
3. the mask warped by that motion, then its edge refined with one GrabCut pass restricted to a thin
   band around the warped boundary;
4. where the affine fit is poor (few inliers: articulated or non-rigid motion), per-pixel warping
   with the backward flow instead.

Chained over many frames, a motion model keeps the shape intact where per-pixel warping
accumulates interpolation and flow errors at every step (it drifts and erodes).
:func:`propagate_between` fills the frames between two keyframes from both ends and blends the two
proposals by their signed distance fields, weighted by closeness to each keyframe.

Images are ``(H, W, 3)`` uint8 RGB, masks ``(H, W)`` bool.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Literal, Optional, Sequence

import cv2
import numpy as np

from benchmark.core.errors import InputError

MotionModel = Literal["affine", "similarity"]
_DIS_PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
                "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}


@dataclass
class PropagationConfig:
    """Settings of mask propagation."""

    flow_preset: str = "medium"
    """DIS optical flow preset: ``ultrafast``, ``fast`` or ``medium`` (more accurate, slower)."""
    context_px: int = 96
    """Flow is computed on a crop: the mask's box grown by this many pixels (and by half the box's
    size), which bounds the motion one step can follow and keeps the cost independent of frame size."""
    erode_px: int = 3
    """The mask is shrunk by this much before sampling flow for the motion fit."""
    max_points: int = 4000
    """At most this many flow samples enter the RANSAC fit (uniformly subsampled)."""
    motion_model: MotionModel = "affine"
    """``affine`` (6 dof, ``cv2.estimateAffine2D``) or ``similarity`` (4 dof, ``estimateAffinePartial2D``)."""
    ransac_threshold_px: float = 1.0
    """RANSAC inlier threshold on the flow end point, in pixels."""
    min_inlier_ratio: float = 0.6
    """Below this fraction of inliers the affine fit is "poor": per-pixel warping is used instead."""
    min_points: int = 20
    """Fewer flow samples than this (a tiny mask): per-pixel warping."""
    refine: bool = True
    """Refine the warped edge with one GrabCut pass in a thin band."""
    band_px: int = 3
    """Half-width of the band around the warped boundary that GrabCut may relabel."""
    grabcut_context_px: int = 24
    """Background context around the warped mask given to GrabCut for its colour model."""
    grabcut_iterations: int = 1
    """GrabCut iterations of the edge refinement."""
    grabcut_max_side: int = 384
    """A refinement crop larger than this is downscaled first (GrabCut's cost grows with area)."""
    compose_motion: bool = True
    """In a chain, warp the last anchor mask (the start, or the last refined / per-pixel result) by
    the composed motion instead of re-warping each step's output (one resampling, not one per step)."""
    max_refine_change: float = 0.2
    """If the refinement changes more than this fraction of the warped mask's area, it is rejected
    (GrabCut's colour model failed) and the warped mask kept."""


@dataclass
class StepResult:
    """One propagation step."""

    mask: np.ndarray
    """(H, W) bool proposal for the target frame."""
    method: str
    """``"affine"`` (motion model + warp), ``"flow"`` (per-pixel fallback) or ``"empty"``."""
    inlier_ratio: float = 0.0
    """RANSAC inlier fraction of the motion fit (0 when no fit was made)."""
    matrix: Optional[np.ndarray] = None
    """(2, 3) fitted affine source -> target, in full-image pixel coordinates."""
    refined: bool = False
    """Whether the GrabCut edge refinement was kept."""


def _gray(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 2:
        return np.ascontiguousarray(image.astype(np.uint8))
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(None, "image", f"expected (H, W, 3) RGB, got shape {image.shape}")
    if image.dtype != np.uint8:
        image = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def _as_uint8_rgb(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8:
        image = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return np.ascontiguousarray(image)


def dis_flow(src_gray: np.ndarray, dst_gray: np.ndarray, preset: str = "medium") -> np.ndarray:
    """(H, W) uint8, (H, W) uint8 -> (H, W, 2) float32 flow: ``dst[y + v, x + u] ~ src[y, x]``."""
    if preset not in _DIS_PRESETS:
        raise InputError(None, "flow_preset", f"unknown DIS preset {preset!r} ({', '.join(_DIS_PRESETS)})")
    dis = cv2.DISOpticalFlow_create(_DIS_PRESETS[preset])
    return dis.calc(np.ascontiguousarray(src_gray), np.ascontiguousarray(dst_gray), None)


def _crop_box(mask: np.ndarray, context: int) -> tuple[int, int, int, int]:
    ys, xs = np.nonzero(mask)
    h, w = mask.shape
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    pad_y = context + (y1 - y0) // 2
    pad_x = context + (x1 - x0) // 2
    return max(0, x0 - pad_x), max(0, y0 - pad_y), min(w, x1 + pad_x), min(h, y1 + pad_y)


def warp_by_flow(mask: np.ndarray, backward_flow: np.ndarray) -> np.ndarray:
    """Per-pixel warp: ``out[y, x] = mask[y + v, x + u]`` for the (H, W, 2) target -> source flow."""
    h, w = mask.shape
    grid_x, grid_y = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    warped = cv2.remap(mask.astype(np.float32), grid_x + backward_flow[..., 0], grid_y + backward_flow[..., 1],
                       interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return warped >= 0.5


def warp_by_affine(mask: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Warp a mask by a (2, 3) source -> target affine in pixel-centre coordinates."""
    h, w = mask.shape
    warped = cv2.warpAffine(mask.astype(np.float32), matrix, (w, h), flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return warped >= 0.5


def fit_motion(src_mask: np.ndarray, flow: np.ndarray, config: PropagationConfig,
               rng: Optional[np.random.Generator] = None) -> tuple[Optional[np.ndarray], float, int]:
    """RANSAC affine fit to ``flow`` (H, W, 2) sampled inside the shrunken ``src_mask`` (H, W).

    Returns ((2, 3) matrix or ``None``, inlier ratio, number of samples). Coordinates are pixel
    indices of ``flow``'s grid (the caller shifts them for crops).
    """
    inner = src_mask
    if config.erode_px > 0:
        k = 2 * config.erode_px + 1
        eroded = cv2.erode(src_mask.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
        if eroded.sum() >= config.min_points:
            inner = eroded
    ys, xs = np.nonzero(inner)
    n = ys.size
    if n < config.min_points:
        return None, 0.0, int(n)
    if n > config.max_points:
        rng = rng or np.random.default_rng(0)
        pick = rng.choice(n, size=config.max_points, replace=False)
        ys, xs = ys[pick], xs[pick]
    src_pts = np.stack([xs, ys], axis=1).astype(np.float32)
    dst_pts = src_pts + flow[ys, xs]
    estimate = cv2.estimateAffine2D if config.motion_model == "affine" else cv2.estimateAffinePartial2D
    matrix, inliers = estimate(src_pts, dst_pts, method=cv2.RANSAC,
                               ransacReprojThreshold=config.ransac_threshold_px, maxIters=2000, confidence=0.995)
    if matrix is None or inliers is None:
        return None, 0.0, int(src_pts.shape[0])
    return matrix, float(inliers.mean()), int(src_pts.shape[0])


def refine_edge(image: np.ndarray, mask: np.ndarray, config: PropagationConfig) -> tuple[np.ndarray, bool]:
    """One GrabCut pass that may relabel only a thin band around the boundary of ``mask``.

    Returns (refined (H, W) bool mask, whether the refinement was kept).
    """
    if not mask.any():
        return mask, False
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    pad = config.grabcut_context_px + config.band_px
    x0, y0 = max(0, xs.min() - pad), max(0, ys.min() - pad)
    x1, y1 = min(w, xs.max() + 1 + pad), min(h, ys.max() + 1 + pad)
    crop_img = image[y0:y1, x0:x1]
    crop_mask = mask[y0:y1, x0:x1].astype(np.uint8)
    ch, cw = crop_mask.shape
    scale = min(1.0, config.grabcut_max_side / max(ch, cw))
    if scale < 1.0:
        size = (max(2, int(round(cw * scale))), max(2, int(round(ch * scale))))
        crop_img = cv2.resize(crop_img, size, interpolation=cv2.INTER_AREA)
        crop_mask = cv2.resize(crop_mask, size, interpolation=cv2.INTER_NEAREST)
    band = max(1, int(round(config.band_px * scale)))
    kernel = np.ones((2 * band + 1, 2 * band + 1), np.uint8)
    inner = cv2.erode(crop_mask, kernel).astype(bool)
    outer = cv2.dilate(crop_mask, kernel).astype(bool)
    labels = np.where(outer, np.where(crop_mask > 0, cv2.GC_PR_FGD, cv2.GC_PR_BGD), cv2.GC_BGD).astype(np.uint8)
    labels[inner] = cv2.GC_FGD
    if not (labels == cv2.GC_BGD).any() or not (labels == cv2.GC_FGD).any():
        return mask, False  # no sure background or no sure object to learn colours from
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    try:
        cv2.grabCut(crop_img, labels, None, bgd, fgd, config.grabcut_iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return mask, False
    fg = np.isin(labels, (cv2.GC_FGD, cv2.GC_PR_FGD)).astype(np.float32)
    if scale < 1.0:
        fg = cv2.resize(fg, (cw, ch), interpolation=cv2.INTER_LINEAR)
        # outside the (upscaled) band the warped mask stands: resizing must not move it
        full_band = cv2.dilate(mask[y0:y1, x0:x1].astype(np.uint8),
                               np.ones((2 * config.band_px + 1,) * 2, np.uint8)).astype(bool) & \
            ~cv2.erode(mask[y0:y1, x0:x1].astype(np.uint8),
                       np.ones((2 * config.band_px + 1,) * 2, np.uint8)).astype(bool)
        fg_bool = np.where(full_band, fg >= 0.5, mask[y0:y1, x0:x1])
    else:
        fg_bool = fg > 0.5
    out = mask.copy()
    out[y0:y1, x0:x1] = fg_bool
    changed = np.count_nonzero(out ^ mask)
    if changed > config.max_refine_change * max(1, int(mask.sum())):
        return mask, False
    return out, True


def propagate_step(src_image: np.ndarray, dst_image: np.ndarray, src_mask: np.ndarray,
                   config: Optional[PropagationConfig] = None,
                   anchor: Optional[tuple[np.ndarray, np.ndarray]] = None) -> StepResult:
    """Carry ``src_mask`` (H, W) from ``src_image`` to ``dst_image`` (both (H, W, 3) uint8).

    ``anchor = (keyframe mask (H, W), (2, 3) affine keyframe -> source)``: when the motion fit
    succeeds, the *keyframe's* mask is warped by the composed motion instead of ``src_mask``, so a
    chain of steps resamples the mask once rather than once per step (no accumulated blur, no drift
    from re-thresholding). :attr:`StepResult.matrix` is then keyframe -> target.
    """
    config = config or PropagationConfig()
    src_mask = np.asarray(src_mask).astype(bool)
    if src_image.shape[:2] != src_mask.shape or dst_image.shape[:2] != src_mask.shape:
        raise InputError(None, "propagation", f"image sizes {src_image.shape[:2]} / {dst_image.shape[:2]} "
                                              f"and mask size {src_mask.shape} differ")
    if not src_mask.any():
        return StepResult(np.zeros_like(src_mask), "empty")
    x0, y0, x1, y1 = _crop_box(src_mask, config.context_px)
    src_gray = _gray(src_image)[y0:y1, x0:x1]
    dst_gray = _gray(dst_image)[y0:y1, x0:x1]
    crop_mask = src_mask[y0:y1, x0:x1]
    flow = dis_flow(src_gray, dst_gray, config.flow_preset)
    matrix, ratio, _ = fit_motion(crop_mask, flow, config)
    if matrix is not None and ratio >= config.min_inlier_ratio:
        # crop coordinates -> full image: T(+x0,+y0) . M . T(-x0,-y0)
        full = matrix.astype(np.float64).copy()
        full[:, 2] += np.array([x0, y0], np.float64) - full[:, :2] @ np.array([x0, y0], np.float64)
        if anchor is not None:
            anchor_mask, to_src = anchor
            full = compose_affine(full, to_src)
            warped = warp_by_affine(anchor_mask, full)
        else:
            warped = warp_by_affine(src_mask, full)
        result = StepResult(warped, "affine", ratio, full)
    else:
        back = dis_flow(dst_gray, src_gray, config.flow_preset)
        warped = np.zeros_like(src_mask)
        warped[y0:y1, x0:x1] = warp_by_flow(crop_mask, back)
        result = StepResult(warped, "flow", ratio, None)
    if config.refine and result.mask.any():
        result.mask, result.refined = refine_edge(_as_uint8_rgb(dst_image), result.mask, config)
    return result


def propagate_chain(images: Sequence[np.ndarray] | Callable[[int], np.ndarray], count: int,
                    start_mask: np.ndarray, config: Optional[PropagationConfig] = None) -> list[StepResult]:
    """Propagate ``start_mask`` from image 0 through images 1..count, each step from the last proposal.

    ``images`` is a sequence or a function ``i -> (H, W, 3) uint8`` (lazy loading).
    """
    get = images if callable(images) else images.__getitem__
    cfg = config or PropagationConfig()
    out: list[StepResult] = []
    mask = np.asarray(start_mask).astype(bool)
    anchor = (mask, IDENTITY.copy())
    prev = get(0)
    for i in range(1, count + 1):
        cur = get(i)
        step = propagate_step(prev, cur, mask, cfg, anchor=anchor)
        out.append(step)
        # motion fits compose from the last anchor; a refined or per-pixel step becomes the new anchor
        if step.method == "affine" and not step.refined and cfg.compose_motion:
            anchor = (anchor[0], step.matrix)
        else:
            anchor = (step.mask, IDENTITY.copy())
        mask, prev = step.mask, cur
    return out


IDENTITY = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def compose_affine(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """(2, 3) affine ``outer . inner`` (apply ``inner`` first)."""
    a = np.vstack([outer, [0.0, 0.0, 1.0]])
    b = np.vstack([inner, [0.0, 0.0, 1.0]])
    return (a @ b)[:2]


def signed_distance(mask: np.ndarray) -> np.ndarray:
    """(H, W) float32: distance to the boundary, positive inside ``mask``, negative outside."""
    m = mask.astype(np.uint8)
    inside = cv2.distanceTransform(m, cv2.DIST_L2, 5)
    outside = cv2.distanceTransform(1 - m, cv2.DIST_L2, 5)
    return inside - outside


def blend_masks(forward: np.ndarray, backward: np.ndarray, alpha: float) -> np.ndarray:
    """Blend two proposals for one frame: ``alpha`` = 0 means all ``forward``, 1 all ``backward``.

    The signed distance fields are interpolated, so the boundary moves smoothly from one proposal
    to the other rather than flipping at alpha = 0.5. An empty proposal (object gone) contributes
    "far outside".
    """
    if not forward.any() and not backward.any():
        return np.zeros_like(forward)
    far = float(max(forward.shape))
    sf = signed_distance(forward) if forward.any() else np.full(forward.shape, -far, np.float32)
    sb = signed_distance(backward) if backward.any() else np.full(backward.shape, -far, np.float32)
    return ((1.0 - alpha) * sf + alpha * sb) > 0


def propagate_between(images: Sequence[np.ndarray] | Callable[[int], np.ndarray], n: int,
                      first_mask: np.ndarray, last_mask: np.ndarray,
                      config: Optional[PropagationConfig] = None) -> list[np.ndarray]:
    """Fill frames 1..n-1 between keyframes 0 and ``n`` (masks given) from both ends and blend.

    Returns the ``n - 1`` in-between masks, in order.
    """
    if n < 2:
        return []
    get = images if callable(images) else images.__getitem__
    fwd = propagate_chain(get, n - 1, first_mask, config)
    bwd = propagate_chain(lambda i: get(n - i), n - 1, last_mask, config)
    out = []
    for k in range(1, n):
        alpha = k / n
        out.append(blend_masks(fwd[k - 1].mask, bwd[n - k - 1].mask, alpha))
    return out


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool masks; two empty masks agree perfectly (1.0)."""
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else np.count_nonzero(a & b) / union
