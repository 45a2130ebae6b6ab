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
"""

from __future__ import annotations

from typing import Mapping

import numpy as np
import pandas as pd

from annotations.model import AnnotationSet


def cosine_similarity(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cosine similarity of ``a`` (..., D) and ``b`` (..., D), broadcast -> (...). Zero vectors raise."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    na = np.linalg.norm(a, axis=-1)
    nb = np.linalg.norm(b, axis=-1)
    if np.any(na == 0) or np.any(nb == 0):
        raise ValueError("cosine similarity of a zero vector is undefined")
    return (a * b).sum(axis=-1) / (na * nb)


def delta_sim(query_embedding: np.ndarray, caption_embeddings: np.ndarray, positive: np.ndarray) -> float:
    """Mean cosine over positive samples minus over negative samples (a fraction, not percent).

    ``query_embedding`` (D,); ``caption_embeddings`` (N, D); ``positive`` (N,) bool.
    No positive or no negative sample -> NaN.
    """
    q = np.asarray(query_embedding, dtype=np.float64)
    c = np.asarray(caption_embeddings, dtype=np.float64)
    pos = np.asarray(positive, dtype=bool)
    if q.ndim != 1 or c.ndim != 2 or c.shape[1] != q.shape[0] or pos.shape != (c.shape[0],):
        raise ValueError(f"shapes: query {q.shape}, captions {c.shape}, positive {pos.shape} do not fit (D,), (N, D), (N,)")
    if not pos.any() or pos.all():
        return float("nan")
    cos = cosine_similarity(c, q[None, :])
    return float(cos[pos].mean() - cos[~pos].mean())


def delta_sim_scene(aset: AnnotationSet, query_embeddings: Mapping[str, np.ndarray],
                    caption_embeddings: Mapping[tuple[str, int], np.ndarray]) -> pd.DataFrame:
    """Delta-sim of every time-sensitive query of ``aset`` (percent, one row per query).

    ``query_embeddings``: query text -> (D,). ``caption_embeddings``: (base object's query text,
    time_index) -> (D,) caption embedding of that object at that frame. A sensitive query missing
    from ``query_embeddings`` raises ``KeyError``. Columns: scene, query, positives, negatives,
    delta_sim (percent; NaN under the empty rule).
    """
    rows = []
    for q in aset.sensitive_queries:
        base = aset.mask_owner(q).text
        keys = sorted(k for k in caption_embeddings if k[0] == base)
        if keys:
            emb = np.stack([np.asarray(caption_embeddings[k], dtype=np.float64) for k in keys])
            pos = np.array([q.holds_at(t) for _, t in keys])
            value = delta_sim(query_embeddings[q.text], emb, pos)
        else:
            pos, value = np.zeros(0, bool), float("nan")
        rows.append({"scene": aset.scene, "query": q.text, "positives": int(pos.sum()),
                     "negatives": int((~pos).sum()), "delta_sim": 100.0 * value})
    return pd.DataFrame(rows, columns=["scene", "query", "positives", "negatives", "delta_sim"])


def mean_delta_sim(table: pd.DataFrame) -> float:
    """Dataset Delta-sim (percent): mean of the defined per-query values; NaN if none."""
    values = table["delta_sim"].to_numpy(dtype=np.float64)
    values = values[~np.isnan(values)]
    return float(values.mean()) if values.size else float("nan")
