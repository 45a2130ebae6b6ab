"""Temporal association of per-frame segment ids by overlap (used by the ``classical`` and ``sam`` segmenters).

Segmenters cut each frame on its own, so a segment's id means nothing across frames. 4D LangSplat
tracks SAM masks through the video with DEVA; here a lighter rule gives the same property (one id
per thing over time where the thing is visible in consecutive frames): per level, the segments of a
frame are matched one-to-one to the ids of the previous frame of the same camera by maximum total
IoU (Hungarian assignment on the IoU matrix), a pair counting only above ``min_iou``; a matched
segment inherits the previous id, an unmatched one gets a fresh id. Ids are never reused.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np


@dataclass
class AssociationConfig:
    """When two segments of consecutive frames are the same thing."""

    min_iou: float = 0.3
    """A segment continues a previous id only when their IoU exceeds this (in image space: camera
    and object motion between consecutive training frames is small at the frame rates used)."""


def iou_matrix(previous: np.ndarray, current: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IoU of every pair of segments of two id maps.

    Args:
        previous, current: (H, W) int ids, -1 = none.
    Returns:
        ((P, C) IoU, (P,) previous ids, (C,) current ids) over the ids >= 0.
    """
    prev_ids, prev_inv = np.unique(previous, return_inverse=True)
    cur_ids, cur_inv = np.unique(current, return_inverse=True)
    inter = np.bincount(prev_inv.ravel() * cur_ids.size + cur_inv.ravel(),
                        minlength=prev_ids.size * cur_ids.size).reshape(prev_ids.size, cur_ids.size)
    prev_size, cur_size = inter.sum(1), inter.sum(0)
    keep_p, keep_c = prev_ids >= 0, cur_ids >= 0
    inter = inter[keep_p][:, keep_c]
    union = prev_size[keep_p][:, None] + cur_size[keep_c][None, :] - inter
    return inter / np.maximum(union, 1), prev_ids[keep_p], cur_ids[keep_c]


class TemporalAssociator:
    """Carries ids from frame to frame, per camera and level (call :meth:`associate` in time order)."""

    def __init__(self, cfg: Optional[AssociationConfig] = None) -> None:
        self.cfg = cfg or AssociationConfig()
        self._previous: dict[tuple[str, int], np.ndarray] = {}
        self._next_id: dict[int, int] = {}

    def reset(self) -> None:
        self._previous.clear()
        self._next_id.clear()

    def associate(self, ids: np.ndarray, camera_id: str = "0") -> np.ndarray:
        """(L, H, W) per-frame ids (-1 = none) -> (L, H, W) int32 ids consistent with earlier frames."""
        from scipy.optimize import linear_sum_assignment

        ids = np.asarray(ids)
        out = np.full(ids.shape, -1, dtype=np.int32)
        for level in range(ids.shape[0]):
            plane = ids[level]
            cur_ids = np.unique(plane[plane >= 0])
            mapping: dict[int, int] = {}
            prev = self._previous.get((camera_id, level))
            if prev is not None and prev.shape == plane.shape and cur_ids.size:
                iou, prev_ids, cur_index = iou_matrix(prev, plane)
                if iou.size:
                    rows, cols = linear_sum_assignment(-iou)
                    for r, c in zip(rows, cols):
                        if iou[r, c] > self.cfg.min_iou:
                            mapping[int(cur_index[c])] = int(prev_ids[r])
            counter = self._next_id.get(level, 0)
            if prev is not None:
                counter = max(counter, int(prev.max()) + 1)
            lut_src = cur_ids
            lut_dst = np.empty(cur_ids.size, dtype=np.int64)
            for k, cid in enumerate(cur_ids.tolist()):
                if cid in mapping:
                    lut_dst[k] = mapping[cid]
                else:
                    lut_dst[k] = counter
                    counter += 1
            self._next_id[level] = counter
            if cur_ids.size:
                pos = np.searchsorted(lut_src, plane)
                valid = plane >= 0
                out[level][valid] = lut_dst[pos[valid]]
            self._previous[(camera_id, level)] = out[level].copy()
        return out
