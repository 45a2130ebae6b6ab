"""How caption embeddings become a time-varying field's targets: windowed means over nearby times, or
the mean of each state found by change points (a permutation test on the captions' similarity)."""

from __future__ import annotations

import functools
from typing import Optional

import numpy as np


def window_caption_embeddings(caption_times: np.ndarray, caption_embeddings: np.ndarray, window: int) -> np.ndarray:
    """(N, D) float64 unit vectors: each caption embedding (N, D) replaced by the renormalised mean of
    the embeddings whose time index (N,) lies within ``window`` steps of its own (itself included,
    and every caption at its own time: several cameras at one time are averaged even at window 0).
    The targets a field fitted with the ``extensions.caption_window`` option sees
    (:func:`methods.fields.time_varying.smooth_caption_embeddings` calls this per object). ``window``
    below 0 raises; a mean of zero length (opposite embeddings) stays zero."""
    if int(window) < 0:
        raise ValueError(f"window must be >= 0 time steps, got {window}")
    times = np.asarray(caption_times, dtype=np.float64)
    emb = np.asarray(caption_embeddings, dtype=np.float64)
    if emb.ndim != 2 or times.shape != (emb.shape[0],):
        raise ValueError(f"shapes: times {times.shape}, embeddings {emb.shape} do not fit (N,), (N, D)")
    near = np.abs(times[:, None] - times[None, :]) <= int(window)  # [N, N]
    mean = (near @ emb) / near.sum(1, keepdims=True)
    return mean / np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)


SEGMENT_PERMUTATIONS = 999
"""Shuffles of a segment's captions a change point is tested against (:func:`caption_change_points`)."""


SEGMENT_SIGNIFICANCE = 0.01
"""Level of that one-sided permutation test: a change point is kept when at most this share of the
shuffles (counting the observed order itself) split as well."""


def _split_candidates(n: int, min_length: int) -> tuple[np.ndarray, np.ndarray]:
    """(first, last) of every circular split of a sequence of ``n`` rows: rows [first, last) form one
    group and the rest another, the pieces [0, first), [first, last), [last, n) that are not empty each
    at least ``min_length`` long (``first = 0`` or ``last = n`` is an ordinary split into two)."""
    first, last = np.triu_indices(n + 1, 1)
    inside = last - first
    ok = ((inside >= min_length) & (n - inside >= min_length) & ((first == 0) | (first >= min_length))
          & ((last == n) | (n - last >= min_length)))
    return first[ok], last[ok]


def _split_gains(gram: np.ndarray, first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """Drop of the within-group squared error of each split (:func:`_split_candidates`) of the rows
    x_t whose Gram matrix is ``gram`` (n, n)."""
    n = len(gram)
    cum = np.zeros((n + 1, n + 1))
    cum[1:, 1:] = gram.cumsum(0).cumsum(1)  # cum[a, b] = C_a . C_b, C_k = sum of the first k rows
    total = cum[n, n]
    inside = last - first
    in_sq = cum[last, last] + cum[first, first] - 2.0 * cum[first, last]  # |sum of rows in [i, j)|^2
    out_sq = total + in_sq - 2.0 * (cum[n, last] - cum[n, first])
    # the rows' own squared norms cancel: gain = |S_in|^2 / m + |S_out|^2 / (n - m) - |S|^2 / n
    return in_sq / inside + out_sq / (n - inside) - total / n


def caption_change_points(caption_times: np.ndarray, caption_embeddings: np.ndarray, *, min_length: int,
                          permutations: int = SEGMENT_PERMUTATIONS, significance: float = SEGMENT_SIGNIFICANCE,
                          seed: int = 0) -> list[float]:
    """Time indices where an object's captions (N,) times, (N, D) embeddings change state, by circular
    binary segmentation (Olshen et al., 2004): the captions of each distinct time are averaged
    (several cameras); the best split of a segment into an inner run and the rest (or into two), every
    piece at least ``min_length`` distinct times, is kept when its permutation p-value (the share of
    ``permutations`` seeded shuffles of that segment, and the observed order, whose best split gains
    at least as much) is at most ``significance``; the pieces are split again. Paraphrases of one state
    drawn frame by frame are exchangeable in time, so splitting them gains no more than a shuffle
    does, while a held state does; the inner run finds a state that comes and goes (closed, open,
    closed), which one split at a time can miss. Each returned time starts a new segment; [] = one state."""
    times = np.asarray(caption_times, dtype=np.float64)
    emb = np.asarray(caption_embeddings, dtype=np.float64)
    if emb.ndim != 2 or times.shape != (emb.shape[0],):
        raise ValueError(f"shapes: times {times.shape}, embeddings {emb.shape} do not fit (N,), (N, D)")
    if min_length < 1 or permutations < 1 or not 0 < significance < 1:
        raise ValueError("min_length and permutations must be >= 1, significance in (0, 1)")
    unique, x = _time_means(times, emb)
    gram = x @ x.T
    rng = np.random.default_rng(seed)
    cuts: list[int] = []
    pending = [(0, len(unique))]
    allowed = significance * (1 + permutations) - 1  # shuffles that may split as well for a kept change
    while pending:
        start, stop = pending.pop()
        first, last = _split_candidates(stop - start, min_length)
        if first.size == 0:
            continue
        block = gram[start:stop, start:stop]
        gains = _split_gains(block, first, last)
        best = int(np.argmax(gains))
        as_good = 0
        for _ in range(permutations):  # stops as soon as the change can no longer be kept
            order = rng.permutation(stop - start)
            as_good += _split_gains(block[order][:, order], first, last).max() >= gains[best]
            if as_good > allowed:
                break
        if as_good > allowed:
            continue
        bounds = sorted({start, start + int(first[best]), start + int(last[best]), stop})
        cuts += [b for b in bounds[1:-1]]
        pending += [(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
    return sorted(float(unique[c]) for c in cuts)


def _time_means(times: np.ndarray, emb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distinct times (U,), (U, D) mean embedding of the captions (N, D) at each: several cameras)."""
    unique, inverse = np.unique(times, return_inverse=True)
    x = np.zeros((len(unique), emb.shape[1]))
    np.add.at(x, inverse, emb)
    x /= np.bincount(inverse, minlength=len(unique))[:, None]
    return unique, x


def _two_group_gains(gram: np.ndarray, members: np.ndarray) -> np.ndarray:
    """(P,) drop of the within-group squared error when the rows whose Gram matrix is ``gram`` (n, n)
    are split into each row of ``members`` (P, n) bool and the rest:
    |S_a|^2 / m + |S_b|^2 / (n - m) - |S|^2 / n."""
    a = members.astype(np.float64)
    b = 1.0 - a
    m = a.sum(1)
    n = a.shape[1]
    return ((a @ gram) * a).sum(1) / m + ((b @ gram) * b).sum(1) / (n - m) - gram.sum() / n


def caption_segment_states(caption_times: np.ndarray, caption_embeddings: np.ndarray, change_points, *,
                           permutations: int = SEGMENT_PERMUTATIONS, significance: float = SEGMENT_SIGNIFICANCE,
                           seed: int = 0) -> list[int]:
    """State of each segment (``len(change_points) + 1`` labels, numbered in order of first appearance)
    of an object's captions (N,) times, (N, D) embeddings, cut at the sorted ``change_points``
    (:func:`caption_change_points`): a state that comes back (an egg closed, opened, closed again) is
    one state, not a new one. Two groups of segments share a state when a two-sample permutation test
    on their per-time mean captions cannot tell them apart: the share of ``permutations`` seeded
    relabellings of their pooled rows (and the observed labelling) whose two-group gain is at least
    the observed one is above ``significance``; the pair least distinguishable is merged first, then
    the test is repeated on the merged groups. Groups holding neighbouring segments never merge (the
    change point between them was found significant already)."""
    times = np.asarray(caption_times, dtype=np.float64)
    emb = np.asarray(caption_embeddings, dtype=np.float64)
    if emb.ndim != 2 or times.shape != (emb.shape[0],):
        raise ValueError(f"shapes: times {times.shape}, embeddings {emb.shape} do not fit (N,), (N, D)")
    cuts = np.asarray(sorted(change_points), dtype=np.float64)
    unique, x = _time_means(times, emb)
    segment_of_time = np.searchsorted(cuts, unique, side="right")  # (U,)
    groups: list[set[int]] = [{s} for s in range(len(cuts) + 1)]
    rng = np.random.default_rng(seed)
    while True:
        best: Optional[tuple[float, int, int]] = None
        for i in range(len(groups)):
            for j in range(i + 1, len(groups)):
                if any(abs(a - b) == 1 for a in groups[i] for b in groups[j]):
                    continue
                in_i = np.isin(segment_of_time, list(groups[i]))
                rows = np.nonzero(in_i | np.isin(segment_of_time, list(groups[j])))[0]
                if len(rows) < 3:
                    continue
                gram = x[rows] @ x[rows].T
                member = in_i[rows]
                observed = _two_group_gains(gram, member[None])[0]
                shuffled = np.stack([rng.permutation(member) for _ in range(permutations)])
                as_good = 1 + int((_two_group_gains(gram, shuffled) >= observed - 1e-12).sum())
                p_value = as_good / (1 + permutations)
                if p_value > significance and (best is None or p_value > best[0]):
                    best = (p_value, i, j)
        if best is None:
            break
        _, i, j = best
        groups[i] |= groups.pop(j)
    label_of_group: dict[int, int] = {}
    labels = []
    for s in range(len(cuts) + 1):
        g = next(k for k, members in enumerate(groups) if s in members)
        labels.append(label_of_group.setdefault(g, len(label_of_group)))
    return labels


def segment_caption_embeddings(caption_times: np.ndarray, caption_embeddings: np.ndarray, change_points,
                               segment_states=None) -> np.ndarray:
    """(N, D) float64 unit vectors: each caption embedding replaced by the renormalised mean of the
    embeddings of its segment, the segments starting at the times ``change_points`` (sorted); with
    ``segment_states`` (a state label per segment, :func:`caption_segment_states`), by the mean of
    every segment of its state."""
    times = np.asarray(caption_times, dtype=np.float64)
    emb = np.asarray(caption_embeddings, dtype=np.float64)
    segment = np.searchsorted(np.asarray(sorted(change_points), dtype=np.float64), times, side="right")
    if segment_states is not None:
        labels = np.asarray(segment_states, dtype=np.int64)
        if labels.shape != (len(change_points) + 1,):
            raise ValueError(f"{len(change_points) + 1} segments need as many state labels, got {labels.shape}")
        segment = labels[segment]
    out = np.empty_like(emb)
    for s in np.unique(segment):
        mean = emb[segment == s].mean(0)
        out[segment == s] = mean / max(float(np.linalg.norm(mean)), 1e-12)
    return out


@functools.lru_cache(maxsize=256)
def change_points_testable(num_times: int, min_length: int, seed: int = 0) -> bool:
    """Whether :func:`caption_change_points` can find any change in captions at ``num_times`` distinct
    times: it finds the cleanest one there is, two states of orthogonal captions each holding half of
    the times. With pieces of at least 4 times it cannot below 11 times: of 9 captions, 4 of one state then
    5 of another, 1.5 % of shuffles split as well as the ordered sequence (10: 0.7 %, too near the 1 %
    level for 999 shuffles; 11: 0.4 %)."""
    x = np.zeros((num_times, 2))
    x[: num_times // 2, 0] = 1.0
    x[num_times // 2:, 1] = 1.0
    return bool(caption_change_points(np.arange(num_times, dtype=np.float64), x, min_length=min_length, seed=seed))


def caption_segments(caption_times: np.ndarray, caption_embeddings: np.ndarray, *, min_length: int,
                     seed: int = 0) -> tuple[Optional[list[float]], Optional[list[int]], np.ndarray]:
    """(change points, state label per segment, (N, D) targets) of one object's captions (N,) times,
    (N, D) embeddings under the ``extensions.caption_segments`` option: :func:`caption_change_points`, then
    :func:`caption_segment_states` (a state that comes back is one target), then the state means
    (:func:`segment_caption_embeddings`). Captions in which the test found no change stay as they are:
    ``(None, None, embeddings)``, and the fit's spread tolerance decides whether the object changes, as
    without segments. Not finding a change is no proof of none: a short video (the test cannot find any
    change below 11 times, :func:`change_points_testable`) or one caption of another state among twelve
    (``bench4d stress``, family ``caption-swap``) hides a real one, and one mean target would erase the
    object's states; captions that never change are equal, so their spread is 0 either way."""
    cuts = caption_change_points(caption_times, caption_embeddings, min_length=min_length, seed=seed)
    if not cuts:
        return None, None, np.asarray(caption_embeddings, dtype=np.float64)
    states = caption_segment_states(caption_times, caption_embeddings, cuts, seed=seed)
    return cuts, states, segment_caption_embeddings(caption_times, caption_embeddings, cuts, states)


def fitted_caption_targets(caption_times: np.ndarray, caption_embeddings: np.ndarray, *, window: int = 0,
                           segment_min_length: int = 0, seed: int = 0) -> np.ndarray:
    """(N, D) float64: one object's caption embeddings (N, D) at times (N,) as a time-varying field's
    targets are made from them: as they are (both options 0), averaged over ``window`` time steps
    (:func:`window_caption_embeddings`; option ``extensions.caption_window``), or replaced by the mean of their
    state (``segment_min_length`` > 0: :func:`caption_segments`; option ``extensions.caption_segments``). Both at
    once raise."""
    if window and segment_min_length:
        raise ValueError("a caption window and caption segments are alternatives: give one")
    if segment_min_length:
        return caption_segments(caption_times, caption_embeddings, min_length=segment_min_length, seed=seed)[2]
    if window:
        return window_caption_embeddings(caption_times, caption_embeddings, window)
    return np.asarray(caption_embeddings, dtype=np.float64)
