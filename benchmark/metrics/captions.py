"""Delta-sim: how well caption embeddings separate the frames where a time-sensitive query holds.

The paper (Tables 3-4) reports "the mean cosine similarity between the query embedding and the
caption embedding for positive samples minus negative samples"; the release has no code, so the
definition here is ours:

* A **sample** is the caption of one object at one frame (its embedding, e.g. e5 of the
  Qwen2-VL caption).
* For a time-sensitive query ``q`` about base object ``b``, the samples are the captions of ``b``;
  a sample at ``time_index`` t is **positive** if ``q`` holds at t, else **negative**. Captions of
  other objects are not used: they would measure object identity, not state.
* Per query: ``mean_{pos} cos(e_q, e_c) - mean_{neg} cos(e_q, e_c)``.
  Empty rule: no positive or no negative sample -> NaN (the difference is undefined); that query
  is left out of the mean.
* Dataset: mean over queries with a defined value (pooled over scenes), times 100 (percent);
  NaN if none is defined.

Delta-sim compares state *means*. Two companions say whether single captions separate the states,
which is what a field fitted frame by frame sees:

* :func:`caption_auc`: the probability that a positive caption is nearer the query than a negative
  one (ties half), i.e. the ROC AUC of the cosine as a detector of the state; 1 = every caption alone
  tells the states apart, 0.5 = chance. Same empty rule.
* :func:`caption_replay_accuracy`: the temporal Acc (shared rule of :mod:`.temporal`) of answering
  each evaluated frame with the query's cosine to the caption of the nearest captioned frame (the
  mean of both neighbours on a tie): what a time-varying field that reproduced every training
  caption exactly, and nothing else, would score.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
import pandas as pd

from benchmark.core.annotation import AnnotationSet

from .temporal import score_auc


def cosine_similarity(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cosine similarity of ``a`` (..., D) and ``b`` (..., D), broadcast -> (...). Zero vectors raise."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    na = np.linalg.norm(a, axis=-1)
    nb = np.linalg.norm(b, axis=-1)
    if np.any(na == 0) or np.any(nb == 0):
        raise ValueError("cosine similarity of a zero vector is undefined")
    return (a * b).sum(axis=-1) / (na * nb)


def _caption_cosines(query_embedding: np.ndarray, caption_embeddings: np.ndarray,
                     positive: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((N,) cosine of each caption to the query, (N,) bool ``positive``), shapes checked."""
    q = np.asarray(query_embedding, dtype=np.float64)
    c = np.asarray(caption_embeddings, dtype=np.float64)
    pos = np.asarray(positive, dtype=bool)
    if q.ndim != 1 or c.ndim != 2 or c.shape[1] != q.shape[0] or pos.shape != (c.shape[0],):
        raise ValueError(f"shapes: query {q.shape}, captions {c.shape}, positive {pos.shape} do not fit (D,), (N, D), (N,)")
    return cosine_similarity(c, q[None, :]), pos


def delta_sim(query_embedding: np.ndarray, caption_embeddings: np.ndarray, positive: np.ndarray) -> float:
    """Mean cosine over positive samples minus over negative samples (a fraction, not percent).

    ``query_embedding`` (D,); ``caption_embeddings`` (N, D); ``positive`` (N,) bool.
    No positive or no negative sample -> NaN.
    """
    cos, pos = _caption_cosines(query_embedding, caption_embeddings, positive)
    if not pos.any() or pos.all():
        return float("nan")
    return float(cos[pos].mean() - cos[~pos].mean())


def caption_auc(query_embedding: np.ndarray, caption_embeddings: np.ndarray, positive: np.ndarray) -> float:
    """ROC AUC (a fraction) of the caption cosine to the query as a detector of ``positive``.

    Shapes as :func:`delta_sim`; no positive or no negative sample -> NaN.
    """
    cos, pos = _caption_cosines(query_embedding, caption_embeddings, positive)
    return score_auc(cos, pos)


def caption_replay_accuracy(query_embedding: np.ndarray, caption_times: np.ndarray, caption_embeddings: np.ndarray,
                            eval_times: np.ndarray, labels: np.ndarray, config=None) -> float:
    """Temporal Acc (percent) of the caption-replay answer (module docstring).

    ``caption_times`` (N,) time indices of ``caption_embeddings`` (N, D); ``eval_times`` (T,) and
    ``labels`` (T,) bool of the evaluated frames, in time order. No caption or no evaluated frame -> NaN.
    """
    from .temporal import TemporalRule, apply_temporal_rule, temporal_accuracy

    if np.asarray(caption_times).size == 0 or len(eval_times) == 0:
        return float("nan")
    scores = caption_replay_scores(query_embedding, caption_times, caption_embeddings, eval_times)
    decision = apply_temporal_rule(scores, config or TemporalRule())
    return 100.0 * temporal_accuracy(decision.decisions, np.asarray(labels, dtype=bool))


def caption_replay_scores(query_embedding: np.ndarray, caption_times: np.ndarray, caption_embeddings: np.ndarray,
                          eval_times: np.ndarray) -> np.ndarray:
    """(T,) cosine of the query (D,) to the mean embedding of the captions (N, D) at the training time
    nearest each of ``eval_times`` (T,) (ties: their mean): the per-frame scores of the caption replay."""
    times = np.asarray(caption_times, dtype=np.float64)
    emb = np.asarray(caption_embeddings, dtype=np.float64)
    q = np.asarray(query_embedding, dtype=np.float64)
    scores = np.empty(len(eval_times))
    for i, t in enumerate(np.asarray(eval_times, dtype=np.float64)):
        gap = np.abs(times - t)
        scores[i] = float(cosine_similarity(emb[gap == gap.min()].mean(0), q))
    return scores


def delta_sim_scene(aset: AnnotationSet, query_embeddings: Mapping[str, np.ndarray],
                    caption_embeddings: Mapping[tuple[str, int], np.ndarray]) -> pd.DataFrame:
    """Delta-sim of every time-sensitive query of ``aset`` (percent, one row per query).

    ``query_embeddings``: query text -> (D,). ``caption_embeddings``: (base object's query text,
    time_index) -> (D,) caption embedding of that object at that frame. A sensitive query missing
    from ``query_embeddings`` raises ``KeyError``. Columns: scene, query, positives, negatives,
    delta_sim, auc (:func:`caption_auc`), replay_acc (:func:`caption_replay_accuracy` on the query's
    annotated frames), all percent, NaN under the empty rules.
    """
    rows = []
    for q in aset.sensitive_queries:
        base = aset.mask_owner(q).text
        keys = sorted(k for k in caption_embeddings if k[0] == base)
        eval_times = np.array(sorted({f.time_index for f in aset.annotated_frames(q.id)}))
        if keys:
            emb = np.stack([np.asarray(caption_embeddings[k], dtype=np.float64) for k in keys])
            pos = np.array([q.holds_at(t) for _, t in keys])
            value = delta_sim(query_embeddings[q.text], emb, pos)
            auc = caption_auc(query_embeddings[q.text], emb, pos)
            replay = caption_replay_accuracy(query_embeddings[q.text], np.array([t for _, t in keys]), emb, eval_times,
                                             np.array([q.holds_at(int(t)) for t in eval_times], dtype=bool))
        else:
            pos, value, auc, replay = np.zeros(0, bool), float("nan"), float("nan"), float("nan")
        rows.append({"scene": aset.scene, "query": q.text, "positives": int(pos.sum()),
                     "negatives": int((~pos).sum()), "delta_sim": 100.0 * value, "auc": 100.0 * auc,
                     "replay_acc": replay})
    return pd.DataFrame(rows, columns=["scene", "query", "positives", "negatives", "delta_sim", "auc", "replay_acc"])


def mean_delta_sim(table: pd.DataFrame) -> float:
    """Dataset Delta-sim (percent): mean of the defined per-query values; NaN if none."""
    values = table["delta_sim"].to_numpy(dtype=np.float64)
    values = values[~np.isnan(values)]
    return float(values.mean()) if values.size else float("nan")
