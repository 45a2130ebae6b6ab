"""The temporal decision rule for time-sensitive queries, and the metrics Acc and vIoU.

One rule shared by every method (the harness owns it; methods only report per-frame scores ``s_t``).
For one query, over its evaluated frames in time order:

1. **Smoothing** (paper Sec. 4 / release ``smooth_feature_post``):
   ``s~_t = sum_k w_k s_{t+k}`` with ``w = (0.1, 0.8, 0.1)`` over neighbouring *evaluated* frames.
   A neighbour is *missing* when it falls outside the sequence or its score is undefined (NaN);
   :attr:`~benchmark.core.protocol.TemporalRule.ends` says what happens then (default, the release's: the
   frame keeps its raw value; the ``paper-text`` protocol renormalises the remaining weights).
2. **Threshold** ``tau``: the mean over frames of the unsmoothed scores while thresholding the
   smoothed ones (``"raw"``), or of the smoothed scores (``"smoothed"``). Which one depends on how the
   method makes its scores (:meth:`~benchmark.core.protocol.TemporalRule.tau_source`): the release
   takes the raw mean for 4D LangSplat's feature scores and the smoothed mean for its CLIP-only
   baselines' relevance peaks; the paper's wording, the smoothed mean for both. Undefined scores are
   left out of the mean.
3. **Decision** ``pred_t = s~_t >= tau`` (equality up to a tiny relative float tolerance). A frame whose own score is undefined (the method's
   spatial mask was empty, so there is nothing to average) is decided
   :attr:`TemporalRule.undefined_decision` (default: negative). If every score is undefined,
   ``tau`` is NaN and every frame gets that decision.

Metrics (fractions in [0, 1]):
* :func:`temporal_accuracy`: fraction of evaluated frames with ``pred_t == label_t``.
* :func:`video_iou`: ``vIoU = (1 / |S_u|) sum_{t in S_i} IoU_t`` with ``S_u`` the frames predicted
  or labelled positive and ``S_i`` the frames both; empty ``S_u`` -> :data:`EMPTY_UNION_VIOU`.

Diagnostics beside them (not in the paper; they say how far Acc can be trusted):
* :func:`score_auc`: ROC AUC of the smoothed scores against the labels, threshold-free: whether
  the scores order the states at all, whatever the mean threshold then does with them.
* :func:`near_threshold_fraction`: fraction of the frames whose decision would flip if ``tau``
  moved by :data:`NEAR_THRESHOLD_FRACTION` of the query's smoothed score range: how many of the
  Acc's decisions are coin flips of the fitted model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from benchmark.core.protocol import TemporalRule

EMPTY_UNION_VIOU = 1.0
"""vIoU when no frame is predicted positive and none is labelled positive (``S_u`` empty): the
method correctly says "never", the temporal analogue of the both-empty IoU rule. (The release
returns 0 here; with its annotations the case never arises because every time query holds somewhere.)"""

NEAR_THRESHOLD_FRACTION = 0.05
"""A decision is *near the threshold* when ``|s~_t - tau| < 0.05 (max s~ - min s~)`` over the query's
defined frames (:func:`near_threshold_fraction`). Not a paper constant: a diagnostic of how fragile
the mean-threshold decisions are (on 15 evaluated frames one flipped decision moves Acc by 6.7
points)."""


@dataclass(frozen=True)
class TemporalDecision:
    """Everything the rule computed for one query (arrays in time order)."""

    scores: np.ndarray
    """(T,) float64 raw scores ``s_t`` (NaN = undefined)."""
    smoothed: np.ndarray
    """(T,) float64 smoothed scores ``s~_t`` (NaN where ``s_t`` is NaN)."""
    threshold: float
    """``tau`` (NaN if every score is undefined)."""
    decisions: np.ndarray
    """(T,) bool ``pred_t``."""


def _scores_array(scores: np.ndarray) -> np.ndarray:
    s = np.asarray(scores, dtype=np.float64)
    if s.ndim != 1:
        raise ValueError(f"scores must be a 1-D array over frames, got shape {s.shape}")
    if np.isinf(s).any():
        raise ValueError("scores contain inf (use NaN for an undefined score)")
    return s


def smooth_scores(scores: np.ndarray, config: TemporalRule = TemporalRule()) -> np.ndarray:
    """Smooth ``scores`` (T,) in time order -> (T,) float64 (see :class:`TemporalRule`).

    NaN scores stay NaN and count as missing neighbours for the frames beside them.
    """
    s = _scores_array(scores)
    w = np.asarray(config.weights)
    r = w.size // 2
    if s.size == 0 or r == 0:
        return s.copy()
    padded = np.full(s.size + 2 * r, np.nan)
    padded[r : r + s.size] = s
    windows = sliding_window_view(padded, w.size)  # (T, K): frame t's neighbours t-r .. t+r
    present = ~np.isnan(windows)
    weighted = (np.where(present, windows, 0.0) * w).sum(axis=1)
    if config.ends == "renormalise":
        total = (present * w).sum(axis=1)  # >= centre weight > 0 wherever s_t is defined
        out = np.divide(weighted, total, out=np.full_like(weighted, np.nan), where=total > 0)
    elif config.ends == "replicate":
        out = weighted + (~present * w).sum(axis=1) * s
    else:  # "keep"
        out = np.where(present.all(axis=1), weighted, s)
    out[np.isnan(s)] = np.nan
    return out


def temporal_threshold(scores: np.ndarray, smoothed: np.ndarray, config: TemporalRule,
                       time_score: str = "feature") -> float:
    """``tau``: mean of ``smoothed`` or of the raw ``scores`` over defined values (NaN if none), as
    :meth:`TemporalRule.tau_source` says for a method whose time score is ``time_score``."""
    source = smoothed if config.tau_source(time_score) == "smoothed" else scores
    defined = source[~np.isnan(source)]
    return float(defined.mean()) if defined.size else float("nan")


def apply_temporal_rule(scores: np.ndarray, config: TemporalRule = TemporalRule(),
                        time_score: str = "feature") -> TemporalDecision:
    """Run the whole rule on ``scores`` (T,) in time order (NaN = undefined), made by a method whose time
    score is ``time_score`` (:data:`~benchmark.core.protocol.TIME_SCORES`: it picks ``tau``'s source)."""
    s = _scores_array(scores)
    smoothed = smooth_scores(s, config)
    tau = temporal_threshold(s, smoothed, config, time_score)
    defined = ~np.isnan(smoothed)
    if np.isnan(tau):
        decisions = np.full(s.shape, bool(config.undefined_decision))
    else:
        tol = config.tie_tolerance * float(np.nanmax(np.abs(smoothed)))
        above = smoothed >= tau - tol if config.inclusive else smoothed > tau + tol
        decisions = np.where(defined, above, bool(config.undefined_decision))
    return TemporalDecision(scores=s, smoothed=smoothed, threshold=tau, decisions=decisions.astype(bool))


def decide_temporal(scores: np.ndarray, config: TemporalRule = TemporalRule(),
                    time_score: str = "feature") -> np.ndarray:
    """``pred_t`` (T,) bool for ``scores`` (T,) in time order; see :func:`apply_temporal_rule`."""
    return apply_temporal_rule(scores, config, time_score).decisions


def temporal_accuracy(decisions: np.ndarray, labels: np.ndarray) -> float:
    """Fraction of frames with ``decisions`` (T,) == ``labels`` (T,). No frames (T = 0) -> NaN."""
    d = np.asarray(decisions, dtype=bool)
    y = np.asarray(labels, dtype=bool)
    if d.shape != y.shape or d.ndim != 1:
        raise ValueError(f"decisions {d.shape} and labels {y.shape} must be equal 1-D shapes")
    return float((d == y).mean()) if d.size else float("nan")


def video_iou(decisions: np.ndarray, labels: np.ndarray, frame_iou: np.ndarray) -> float:
    """vIoU of ``decisions`` (T,) bool vs ``labels`` (T,) bool with spatial ``frame_iou`` (T,).

    ``(1 / |S_u|) sum_{t in S_i} frame_iou_t``; ``S_u = decisions | labels``, ``S_i = decisions & labels``.
    Empty ``S_u`` -> :data:`EMPTY_UNION_VIOU` (1.0). ``frame_iou`` must be defined on ``S_i``.
    """
    d = np.asarray(decisions, dtype=bool)
    y = np.asarray(labels, dtype=bool)
    v = np.asarray(frame_iou, dtype=np.float64)
    if not (d.shape == y.shape == v.shape) or d.ndim != 1:
        raise ValueError(f"decisions {d.shape}, labels {y.shape}, frame_iou {v.shape} must be equal 1-D shapes")
    union = d | y
    both = d & y
    if not union.any():
        return EMPTY_UNION_VIOU
    if np.isnan(v[both]).any():
        raise ValueError("frame_iou is NaN on a frame predicted and labelled positive")
    return float(v[both].sum() / union.sum())


def threshold_margins(smoothed: np.ndarray, threshold: float) -> np.ndarray:
    """Signed margin of each decision, ``(s~_t - tau) / (max s~ - min s~)`` (T,) float64, for the
    smoothed scores ``smoothed`` (T,) (NaN = undefined) and ``tau`` ``threshold``.

    NaN where ``s~_t`` is undefined or ``tau`` is NaN. Constant scores (zero range) give margin 0
    everywhere: every decision then rests on the tie rule alone."""
    s = _scores_array(smoothed)
    out = np.full(s.shape, np.nan)
    defined = ~np.isnan(s)
    if not defined.any() or math.isnan(threshold):
        return out
    span = float(s[defined].max() - s[defined].min())
    out[defined] = 0.0 if span == 0.0 else (s[defined] - threshold) / span
    return out


def near_threshold_fraction(smoothed: np.ndarray, threshold: float,
                            fraction: float = NEAR_THRESHOLD_FRACTION) -> float:
    """Fraction of the T frames whose decision lies within ``fraction`` of the score range of
    ``tau`` (``|margin| < fraction``, see :func:`threshold_margins`). A frame with an undefined score
    is decided by convention (not by ``tau``) and counts as not near. T = 0 -> NaN."""
    if not fraction >= 0:
        raise ValueError(f"fraction must be >= 0, got {fraction}")
    margins = threshold_margins(smoothed, threshold)
    if margins.size == 0:
        return float("nan")
    near = np.abs(margins[~np.isnan(margins)]) < fraction
    return float(near.sum() / margins.size)


def accuracy_at_threshold(smoothed: np.ndarray, labels: np.ndarray, threshold: float,
                          undefined_decision: bool = False) -> float:
    """Acc of the decisions ``s~_t >= threshold`` against ``labels`` (T,) bool; an undefined score
    is decided ``undefined_decision``. T = 0 -> NaN. (The rule's own Acc uses its ``tau`` and tie
    tolerance: :func:`apply_temporal_rule`.)"""
    s = _scores_array(smoothed)
    y = np.asarray(labels, dtype=bool)
    if s.shape != y.shape:
        raise ValueError(f"smoothed {s.shape} and labels {y.shape} must be the same (T,) shape")
    defined = ~np.isnan(s)
    decisions = np.where(defined, s >= threshold, bool(undefined_decision))  # NaN >= x is False, replaced
    return temporal_accuracy(decisions, y)


def best_cut_accuracy(smoothed: np.ndarray, labels: np.ndarray, undefined_decision: bool = False) -> float:
    """The largest Acc any single threshold on ``smoothed`` (T,) reaches against ``labels`` (T,):
    an *oracle* that picks the cut knowing the labels, so it is optimistic (scores unrelated to the
    labels reach well above 50 % on a few frames); it bounds what a better threshold rule could gain
    from these scores. Candidate cuts: every defined value, and above all of them (all negative)."""
    s = _scores_array(smoothed)
    cuts = np.unique(s[~np.isnan(s)])
    candidates = [*cuts, np.inf]
    return max(accuracy_at_threshold(s, labels, float(c), undefined_decision) for c in candidates)


def score_auc(scores: np.ndarray, positive: np.ndarray) -> float:
    """ROC AUC (a fraction) of ``scores`` (N,) as a detector of ``positive`` (N,) bool: the fraction of
    (positive, negative) pairs the scores order right, ties counting half. Threshold-free, so it says
    whether scores separate the states at all, whatever a decision rule then does with them. NaN
    scores are left out; no positive or no negative sample left -> NaN."""
    s = np.asarray(scores, dtype=np.float64)
    pos = np.asarray(positive, dtype=bool)
    if s.shape != pos.shape or s.ndim != 1:
        raise ValueError(f"scores {s.shape} and positive {pos.shape} must be the same (N,) shape")
    keep = np.isfinite(s)
    s, pos = s[keep], pos[keep]
    if not pos.any() or pos.all():
        return float("nan")
    diff = s[pos][:, None] - s[~pos][None, :]
    return float(((diff > 0).sum() + 0.5 * (diff == 0).sum()) / diff.size)
