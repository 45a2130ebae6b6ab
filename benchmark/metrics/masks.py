"""Spatial mask metrics: IoU and per-pixel accuracy.

Pure functions over numpy arrays, vectorised over any leading axes: a batch ``(N, H, W)`` of
predictions against a batch of ground truths returns ``(N,)`` values; a single ``(H, W)`` pair
returns a numpy scalar. Any nonzero value counts as positive.

Values are fractions in [0, 1]; reports multiply by 100.
"""

from __future__ import annotations

import numpy as np

EMPTY_IOU = 1.0
"""IoU when prediction and ground truth are both empty (DAVIS convention): the method correctly says
"not here". Occurs when a frame is annotated with an empty mask ("absent in this frame")."""


def _as_mask_pair(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(pred).astype(bool, copy=False)
    g = np.asarray(gt).astype(bool, copy=False)
    if p.shape != g.shape:
        raise ValueError(f"prediction shape {p.shape} differs from ground-truth shape {g.shape}")
    if p.ndim < 2:
        raise ValueError(f"masks need at least 2 axes (H, W), got shape {p.shape}")
    if p.shape[-1] == 0 or p.shape[-2] == 0:
        raise ValueError(f"masks have no pixels (shape {p.shape})")
    return p, g


def confusion(pred: np.ndarray, gt: np.ndarray) -> dict[str, np.ndarray]:
    """Pixel counts ``tp, fp, fn, tn`` of ``pred`` (..., H, W) against ``gt`` (..., H, W).

    Returns int64 arrays of shape ``(...)``.
    """
    p, g = _as_mask_pair(pred, gt)
    axes = (-2, -1)
    tp = np.logical_and(p, g).sum(axis=axes, dtype=np.int64)
    pos_pred = p.sum(axis=axes, dtype=np.int64)
    pos_gt = g.sum(axis=axes, dtype=np.int64)
    total = p.shape[-1] * p.shape[-2]
    fp = pos_pred - tp
    fn = pos_gt - tp
    return {"tp": tp, "fp": fp, "fn": fn, "tn": total - tp - fp - fn}


def iou_from_confusion(c: dict[str, np.ndarray]) -> np.ndarray:
    """IoU from :func:`confusion` counts (same empty-mask rule as :func:`iou`)."""
    union = c["tp"] + c["fp"] + c["fn"]
    return np.where(union > 0, c["tp"] / np.maximum(union, 1), EMPTY_IOU).astype(np.float64)[()]


def accuracy_from_confusion(c: dict[str, np.ndarray]) -> np.ndarray:
    """Pixel accuracy from :func:`confusion` counts (see :func:`pixel_accuracy`)."""
    total = c["tp"] + c["fp"] + c["fn"] + c["tn"]
    return ((c["tp"] + c["tn"]) / total).astype(np.float64)[()]


def iou(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Intersection over union of ``pred`` (..., H, W) and ``gt`` (..., H, W) -> (...) float64.

    Empty-mask rule:
      * both empty -> :data:`EMPTY_IOU` (1.0, DAVIS convention);
      * prediction empty, ground truth non-empty -> 0.0;
      * prediction non-empty, ground truth empty -> 0.0.
    (The last two follow from the formula: the intersection is 0 and the union is not.)
    """
    return iou_from_confusion(confusion(pred, gt))


def pixel_accuracy(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-pixel accuracy ``(TP + TN) / (H W)`` of ``pred`` (..., H, W) vs ``gt`` (..., H, W) -> (...).

    ASSUMPTION: the paper's "mAcc" has no code in the release; values near 98% even for weak
    baselines imply this per-pixel accuracy, averaged like mIoU (frames -> query -> scene -> dataset).
    Empty-mask rule: always defined (H W > 0); both empty gives 1.0, as any exact match does.
    """
    return accuracy_from_confusion(confusion(pred, gt))
