"""Per-(frame, query) records and their documented aggregation.

Scoring a scene (:mod:`benchmark.metrics.scoring`) produces one :class:`FrameRecord` per evaluated
(query, frame) and one query row per query; combining is separate and the same everywhere:

    frame rows --mean over the query's evaluated frames--> query
    query rows --mean over the scene's queries----------> scene
    scene rows --mean over scenes-----------------------> dataset

Undefined (NaN) values are skipped at every level, so a metric that does not apply to a row (e.g.
vIoU for a time-agnostic query) does not count, and a scene without time-sensitive queries is left
out of the dataset's Acc / vIoU rather than counted as 0.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Iterable, Optional, Sequence

import pandas as pd

LEVELS = ("frame", "query", "scene", "dataset")
"""Aggregation levels, finest first."""
_KEYS = {"frame": ["scene", "query", "frame"], "query": ["scene", "query"], "scene": ["scene"], "dataset": []}


@dataclass(frozen=True)
class FrameRecord:
    """One evaluated (query, frame): spatial metrics, and the temporal rule's values for a
    time-sensitive query. Metric values are fractions in [0, 1]."""

    scene: str
    query: str
    """Query text."""
    kind: str
    """``"agnostic"`` or ``"sensitive"``."""
    frame: str
    """Frame name (:attr:`benchmark.core.annotation.AnnotatedFrame.name`)."""
    time_index: int
    camera_id: str
    iou: float
    """IoU of the predicted mask vs the GT mask (the base query's mask for a sensitive query)."""
    acc: float
    """Per-pixel accuracy (TP + TN) / (H W) (see :func:`benchmark.metrics.masks.pixel_accuracy`)."""
    pred_pixels: int
    """Positive pixels in the prediction."""
    gt_pixels: int
    """Positive pixels in the ground truth."""
    score: float = float("nan")
    """Sensitive: the method's raw score ``s_t`` (NaN = undefined or not given)."""
    smoothed: float = float("nan")
    """Sensitive: ``s~_t`` after temporal smoothing (NaN if the method gave decisions)."""
    decision: Optional[bool] = None
    """Sensitive: ``pred_t``."""
    label: Optional[bool] = None
    """Sensitive: ground-truth ``label_t`` (the query holds at this frame)."""


RECORD_COLUMNS = [f.name for f in fields(FrameRecord)]


def records_table(records: Iterable[FrameRecord]) -> pd.DataFrame:
    """Records -> a DataFrame with one column per :class:`FrameRecord` field."""
    return pd.DataFrame([r.__dict__ for r in records], columns=RECORD_COLUMNS)


def aggregate(table: pd.DataFrame, metrics: Sequence[str], *, start: str = "frame",
              to: str = "dataset") -> pd.DataFrame:
    """Mean of ``metrics`` from level ``start`` up to level ``to`` (see the module docstring).

    ``table`` has one row per ``start``-level item with the key columns of that level (``scene``,
    ``query``, ``frame`` for frames; ``scene``, ``query`` for queries; ``scene`` for scenes) and
    the metric columns. Returns one row per ``to``-level item: its key columns, the metrics, and
    ``count`` (the number of ``start``-level rows under it). Row and column order in ``table``
    does not matter (the result is sorted by key).
    """
    if start not in LEVELS or to not in LEVELS or LEVELS.index(to) < LEVELS.index(start):
        raise ValueError(f"cannot aggregate from {start!r} to {to!r}; levels are {LEVELS}")
    metrics = list(metrics)
    missing = [c for c in _KEYS[start] + metrics if c != "frame" and c not in table.columns]
    if missing:
        raise ValueError(f"table lacks columns {missing}")
    current = table[[c for c in _KEYS[start] if c != "frame"] + metrics].copy()
    current[metrics] = current[metrics].astype("float64")
    current["count"] = 1
    for level in LEVELS[LEVELS.index(start) + 1 : LEVELS.index(to) + 1]:
        keys = _KEYS[level]
        if keys:
            grouped = current.groupby(keys, sort=True)
            counts = grouped["count"].sum()
            current = grouped[metrics].mean()  # skips NaN; all-NaN group -> NaN
            current["count"] = counts
            current = current.reset_index()
        else:
            row = {m: current[m].mean() for m in metrics}
            row["count"] = int(current["count"].sum())
            current = pd.DataFrame([row])
    return current.reset_index(drop=True)
