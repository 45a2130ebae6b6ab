"""Uncertainty of the leaderboard's numbers: stratified bootstrap intervals, tie groups, probability of
improvement, the interquartile mean and an exact permutation test of Kendall's tau.

Pure functions of arrays (no files, no tables). The scheme follows rliable (Agarwal et al., "Deep
Reinforcement Learning at the Edge of the Statistical Precipice", NeurIPS 2021): a benchmark's tasks
(here: scenes) are fixed strata, and what varies is resampled within each stratum.

* :func:`bootstrap_means`: the distribution of a dataset mean, resampling within each scene its seeds
  (fits) and its queries (both with replacement). Query draws are shared by every method of one table
  and by every seed of one scene (the queries are one sample, asked of every fit); seed indices are drawn
  once per scene and seed count, so two methods with identical scores get identical intervals.
* :func:`percentile_interval`: the percentile interval of those replicates.
* :func:`tie_groups`: methods whose intervals overlap the best remaining method's interval share its group.
* :func:`probability_of_improvement`: rliable's P(X > Y): over scenes, the share of (seed of X, seed of Y)
  pairs where X scores higher, ties counted half.
* :func:`interquartile_mean`: the mean of the middle 50 % of scores (rliable's IQM).
* :func:`kendall_tau_test`: Kendall's tau-b with an exact two-sided permutation p-value (ties kept).
* :func:`sign_flip_test`: the exact two-sided p-value of a mean of paired differences (each sign a coin flip
  under no effect), valid for the two or three pairs a scene has, where a bootstrap interval is too narrow.
"""

from __future__ import annotations

import itertools
import math
import warnings
import zlib
from typing import Mapping, Optional, Sequence

import numpy as np

BOOTSTRAP_REPS = 2000
"""Bootstrap replicates per table: the 2.5th and 97.5th percentiles then move by well under 0.1 points
between seeds of the resampling on the leaderboard's tables."""
CONFIDENCE = 0.95
"""Coverage of every interval."""
EXACT_PERMUTATIONS_UP_TO = 8
"""Kendall's permutation test enumerates all n! orderings up to this many items (40320), else samples."""
SAMPLED_PERMUTATIONS = 20000
"""Random orderings drawn above :data:`EXACT_PERMUTATIONS_UP_TO`."""


def stable_seed(*parts: object) -> int:
    """A seed for the resampling of one table, from its identity: the same table resamples the same way
    in every process (Python's ``hash`` of a string changes between processes)."""
    return zlib.crc32("\x1f".join(str(p) for p in parts).encode())


def _nanmean(values: np.ndarray, axis: int) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN draw is NaN, on purpose
        return np.nanmean(values, axis=axis)


def bootstrap_means(cells: Mapping[str, Sequence[np.ndarray]], *, reps: int = BOOTSTRAP_REPS,
                    seed: int = 0, resample_queries: bool = True) -> dict[str, np.ndarray]:
    """Replicates (``reps``,) of each method's dataset mean.

    ``cells[method][s]`` is a (seeds, queries) array of scene ``s``'s per-query scores, one row per seed
    (fit) of that method, one column per query. Every method gives the same scenes in the same order, and
    scene ``s``'s columns are the same queries for every method (NaN: that seed has no score for that
    query; it is left out of that seed's mean). A replicate draws, per scene, queries with replacement
    (once, for every method and seed) and, per scene, seeds with replacement (one draw for every method with
as many seeds: each method's seeds are drawn independently of the queries); the statistic is
    the mean over scenes of the mean over the drawn seeds of each seed's mean over the drawn queries: the
    leaderboard's dataset mean, which weights scenes equally. ``resample_queries=False`` keeps every
    query (when the columns are not queries but one value per run). NaN replicates (every drawn value
    missing) stay NaN."""
    rng = np.random.default_rng(seed)
    names = sorted(cells)
    if not names:
        return {}
    scenes = len(cells[names[0]])
    if any(len(cells[m]) != scenes for m in names):
        raise ValueError("every method must give the same scenes")
    totals = {m: np.zeros(reps) for m in names}
    for s in range(scenes):
        width = {np.asarray(cells[m][s]).shape[1] for m in names}
        if len(width) != 1:
            raise ValueError(f"scene {s}: methods give different query columns {sorted(width)}")
        queries = width.pop()
        draw_q = (rng.integers(0, queries, size=(reps, queries)) if resample_queries and queries > 1
                  else np.broadcast_to(np.arange(queries), (reps, queries)))
        # one seed draw per seed count: methods with identical scores get identical intervals
        counts = sorted({np.asarray(cells[m][s]).shape[0] for m in names} - {0})
        draws_s = {n: rng.integers(0, n, size=(reps, n)) for n in counts}
        for m in names:
            values = np.asarray(cells[m][s], dtype=np.float64)
            seeds = values.shape[0]
            if seeds == 0 or queries == 0:
                totals[m] += math.nan
                continue
            per_seed = _nanmean(values[:, draw_q], axis=2)  # (seeds, reps): each seed's mean over the draw
            draw_s = draws_s[seeds]
            chosen = per_seed[draw_s, np.arange(reps)[:, None]]  # (reps, seeds drawn)
            totals[m] += _nanmean(chosen, axis=1)
    return {m: totals[m] / scenes for m in names}


def percentile_interval(replicates: np.ndarray, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """The percentile interval of bootstrap ``replicates`` (NaN replicates left out); (NaN, NaN) if none."""
    values = np.asarray(replicates, dtype=np.float64)
    values = values[np.isfinite(values)]
    if not values.size:
        return math.nan, math.nan
    tail = 100.0 * (1.0 - confidence) / 2.0
    lo, hi = np.percentile(values, [tail, 100.0 - tail])
    return float(lo), float(hi)


def _t_parts(values: Sequence[float], confidence: float) -> Optional[tuple[float, float, int, float]]:
    """(mean, sample standard deviation, n, the t quantile of ``confidence``) of the finite ``values``; None
    below two."""
    from scipy.stats import t

    x = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    if x.size < 2:
        return None
    return float(x.mean()), float(x.std(ddof=1)), int(x.size), float(t.ppf(0.5 + confidence / 2.0, x.size - 1))


def t_interval(values: Sequence[float], confidence: float = CONFIDENCE) -> tuple[float, float]:
    """The t interval of the mean of ``values``: mean -+ t(n - 1) s / sqrt(n) (s the sample standard deviation);
    wide at few values, as it should be (three seeds: t = 4.30); (NaN, NaN) below two values."""
    parts = _t_parts(values, confidence)
    if parts is None:
        return math.nan, math.nan
    mean, s, n, q = parts
    return mean - q * s / math.sqrt(n), mean + q * s / math.sqrt(n)


def prediction_interval(values: Sequence[float], confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Where one more draw from the distribution of ``values`` falls with probability ``confidence``, under
    a normal model: mean -+ t(n - 1) s sqrt(1 + 1/n). The interval for a single new fit, where
    :func:`t_interval` and :func:`bootstrap_means` give intervals of a mean; (NaN, NaN) below two values."""
    parts = _t_parts(values, confidence)
    if parts is None:
        return math.nan, math.nan
    mean, s, n, q = parts
    return mean - q * s * math.sqrt(1.0 + 1.0 / n), mean + q * s * math.sqrt(1.0 + 1.0 / n)


def overlaps(a: tuple[float, float], b: tuple[float, float]) -> bool:
    """Whether two closed intervals share a point (an interval with a NaN end overlaps everything: an
    unknown interval never separates two methods)."""
    if not all(math.isfinite(v) for v in (*a, *b)):
        return True
    return a[0] <= b[1] and b[0] <= a[1]


def tie_groups(means: Mapping[str, float], intervals: Mapping[str, tuple[float, float]],
               higher_is_better: bool = True) -> dict[str, int]:
    """Method -> tie group (1 = the best). Methods are taken best mean first; the best not yet grouped
    opens a group, and every method not yet grouped whose interval overlaps the opener's joins it. So
    group 1 holds the best and every method not separated from it; no method is a winner by a few last
    decimals. Methods with a NaN mean get no group."""
    finite = [m for m in means if means[m] is not None and math.isfinite(means[m])]
    order = sorted(finite, key=lambda m: (-means[m] if higher_is_better else means[m], m))
    groups: dict[str, int] = {}
    number = 0
    for opener in order:
        if opener in groups:
            continue
        number += 1
        groups[opener] = number
        for other in order:
            if other not in groups and overlaps(intervals.get(opener, (math.nan, math.nan)),
                                                intervals.get(other, (math.nan, math.nan))):
                groups[other] = number
    return groups


def probability_of_improvement(x: Sequence[np.ndarray], y: Sequence[np.ndarray]) -> float:
    """rliable's probability of improvement P(X > Y): per scene ``s``, the share of pairs (a run of X on
    ``s``, a run of Y on ``s``) in which X's score is higher, a tie counting one half; then the mean over
    scenes. ``x[s]``, ``y[s]``: the runs' scores on scene ``s`` (NaN left out). NaN when no scene has runs
    of both."""
    shares = []
    for xs, ys in zip(x, y):
        a = np.asarray(xs, dtype=np.float64)
        b = np.asarray(ys, dtype=np.float64)
        a, b = a[np.isfinite(a)], b[np.isfinite(b)]
        if not a.size or not b.size:
            continue
        diff = a[:, None] - b[None, :]
        shares.append(float(((diff > 0).sum() + 0.5 * (diff == 0).sum()) / diff.size))
    return float(np.mean(shares)) if shares else math.nan


def interquartile_mean(values: Sequence[float]) -> float:
    """rliable's interquartile mean: the mean of the values between the 25th and 75th percentiles, with
    the values at the cut points weighted by the share of them inside (a trimmed mean that is defined for
    any count); NaN values left out, NaN when none remain."""
    v = np.sort(np.asarray(values, dtype=np.float64))
    v = v[np.isfinite(v)]
    n = v.size
    if not n:
        return math.nan
    lo, hi = 0.25 * n, 0.75 * n
    # each sorted value covers [i, i + 1) of the n positions; weight it by how much of that lies in [lo, hi)
    edges = np.arange(n)
    weights = np.clip(np.minimum(edges + 1, hi) - np.maximum(edges, lo), 0.0, 1.0)
    return float((v * weights).sum() / weights.sum())


def _sign_pairs(values: np.ndarray) -> np.ndarray:
    i, j = np.triu_indices(values.shape[-1], k=1)
    return np.sign(values[..., i] - values[..., j])


def kendall_tau_test(x: Sequence[float], y: Sequence[float], *, seed: int = 0) -> tuple[float, float]:
    """(Kendall's tau-b of ``x`` and ``y``, the two-sided p-value of a permutation test): the share of
    orderings of ``y`` whose |tau-b| is at least the observed one, all n! orderings up to
    :data:`EXACT_PERMUTATIONS_UP_TO` items, else :data:`SAMPLED_PERMUTATIONS` random ones (plus the
    observed). Ties in either list are kept (tau-b's denominator); a permutation keeps ``y``'s ties, so
    the denominator is the same for every ordering. (NaN, NaN) below two items or where one list is
    constant."""
    a = np.asarray(x, dtype=np.float64)
    b = np.asarray(y, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError("x and y must be two lists of one length")
    n = a.size
    if n < 2:
        return math.nan, math.nan
    sa = _sign_pairs(a)
    pairs = sa.size
    ties_a, ties_b = int((sa == 0).sum()), int((_sign_pairs(b) == 0).sum())
    denominator = math.sqrt((pairs - ties_a) * (pairs - ties_b))
    if denominator == 0:
        return math.nan, math.nan
    observed = float((sa * _sign_pairs(b)).sum() / denominator)
    if n <= EXACT_PERMUTATIONS_UP_TO:
        orders = np.array(list(itertools.permutations(range(n))))
    else:
        rng = np.random.default_rng(seed)
        orders = np.vstack([np.arange(n)[None, :],
                            np.argsort(rng.random((SAMPLED_PERMUTATIONS, n)), axis=1)])
    taus = (_sign_pairs(b[orders]) * sa).sum(axis=1) / denominator
    p = float(np.mean(np.abs(taus) >= abs(observed) - 1e-12))
    return observed, p


EXACT_SIGN_FLIPS_UP_TO = 16
""":func:`sign_flip_test` enumerates all 2^n sign patterns up to this many pairs (65 536), else samples."""


def sign_flip_test(differences: Sequence[np.ndarray], *, seed: int = 0) -> float:
    """Two-sided p-value of the mean over strata (scenes) of each stratum's mean paired difference, under the
    null that every difference is as likely negative as positive (Fisher's randomisation test): the share of
    sign patterns whose statistic is at least as far from 0 as the observed one. ``differences[s]``: stratum
    ``s``'s paired differences. With n pairs the smallest p-value is 2 / 2^n (6 pairs: 0.031)."""
    groups = [np.asarray(d, dtype=np.float64).ravel() for d in differences]
    groups = [g for g in groups if g.size]
    if not groups:
        return math.nan
    weighted = np.concatenate([g / (len(groups) * g.size) for g in groups])  # each stratum weighs the same
    n = weighted.size
    if n <= EXACT_SIGN_FLIPS_UP_TO:
        signs = 1.0 - 2.0 * ((np.arange(2 ** n)[:, None] >> np.arange(n)[None, :]) & 1)
    else:
        rng = np.random.default_rng(seed)
        signs = np.vstack([np.ones((1, n)), rng.choice([-1.0, 1.0], size=(SAMPLED_PERMUTATIONS, n))])
    observed = abs(float(weighted.sum()))
    return float(np.mean(np.abs(signs @ weighted) >= observed - 1e-12))


def interval_text(lo: Optional[float], hi: Optional[float], digits: int = 2) -> str:
    """``[lo, hi]`` for a table cell; ``–`` when either end is unknown."""
    if lo is None or hi is None or not (math.isfinite(lo) and math.isfinite(hi)):
        return "–"
    return f"[{lo:.{digits}f}, {hi:.{digits}f}]"
