"""The leaderboard's statistics against cases with a known answer."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmark import stats


def test_constant_scores_give_a_zero_width_interval_at_the_value():
    cells = {"a": [np.full((3, 5), 42.0), np.full((3, 4), 42.0)]}
    reps = stats.bootstrap_means(cells, reps=500, seed=1)["a"]
    assert stats.percentile_interval(reps) == (pytest.approx(42.0), pytest.approx(42.0))


def test_scenes_are_strata_never_resampled():
    # one scene scores 10 everywhere, the other 30: every replicate is their mean, 20
    cells = {"a": [np.full((2, 3), 10.0), np.full((2, 3), 30.0)]}
    reps = stats.bootstrap_means(cells, reps=300, seed=0)["a"]
    assert np.allclose(reps, 20.0)


def test_a_normal_sample_gives_the_analytic_interval():
    rng = np.random.default_rng(7)
    sample = rng.normal(50.0, 10.0, size=400)
    reps = stats.bootstrap_means({"a": [sample[None, :]]}, reps=4000, seed=3)["a"]
    lo, hi = stats.percentile_interval(reps)
    half = 1.959964 * sample.std(ddof=1) / math.sqrt(sample.size)  # about 0.98
    assert lo == pytest.approx(sample.mean() - half, abs=0.12)
    assert hi == pytest.approx(sample.mean() + half, abs=0.12)


def test_seeds_alone_are_resampled_with_replacement_within_a_scene():
    # two seeds scoring 0 and 100, one value each: a replicate draws two seeds, so it is 0, 50 or 100 with
    # probabilities 1/4, 1/2, 1/4
    reps = stats.bootstrap_means({"a": [np.array([[0.0], [100.0]])]}, reps=8000, seed=5, resample_queries=False)["a"]
    values, counts = np.unique(reps, return_counts=True)
    assert list(values) == [0.0, 50.0, 100.0]
    assert counts / reps.size == pytest.approx([0.25, 0.5, 0.25], abs=0.02)


def test_the_resampling_is_seeded_and_identical_scores_get_identical_intervals():
    rng = np.random.default_rng(0)
    scene = [rng.random((3, 6)) * 100, rng.random((2, 6)) * 100]
    first = stats.bootstrap_means({"a": scene, "b": [s.copy() for s in scene]}, reps=200, seed=11)
    again = stats.bootstrap_means({"a": scene, "b": scene}, reps=200, seed=11)
    other = stats.bootstrap_means({"a": scene}, reps=200, seed=12)
    assert np.array_equal(first["a"], again["a"]) and np.array_equal(first["a"], first["b"])
    assert not np.array_equal(first["a"], other["a"])


def test_missing_query_scores_are_left_out_of_a_seeds_mean():
    cells = {"a": [np.array([[10.0, np.nan, 10.0]])]}
    reps = stats.bootstrap_means(cells, reps=200, seed=0)["a"]
    finite = reps[np.isfinite(reps)]
    assert finite.size > 150 and np.allclose(finite, 10.0)  # a draw of the missing query alone is NaN (1 in 27)
    assert stats.percentile_interval(reps) == (10.0, 10.0)


def test_tie_groups_open_at_the_best_and_do_not_chain():
    means = {"a": 10.0, "b": 9.0, "c": 8.0, "d": 1.0}
    intervals = {"a": (9.0, 11.0), "b": (8.0, 10.0), "c": (7.0, 8.5), "d": (0.0, 2.0)}
    # c overlaps b but not a: it opens the second group rather than joining the first through b
    assert stats.tie_groups(means, intervals) == {"a": 1, "b": 1, "c": 2, "d": 3}
    # lower is better: the smallest opens group 1
    assert stats.tie_groups(means, intervals, higher_is_better=False)["d"] == 1
    # an unknown interval separates nobody
    assert stats.tie_groups({"a": 10.0, "b": 1.0}, {"a": (9.0, 11.0)}) == {"a": 1, "b": 1}


def test_probability_of_improvement_counts_seed_pairs_per_scene_ties_half():
    assert stats.probability_of_improvement([[1.0, 2.0, 3.0]], [[0.0, 0.0]]) == 1.0
    assert stats.probability_of_improvement([[5.0]], [[5.0]]) == 0.5
    assert stats.probability_of_improvement([[1.0], [0.0]], [[0.0], [1.0]]) == 0.5  # one scene each way
    assert stats.probability_of_improvement([[1.0, 3.0]], [[2.0]]) == 0.5
    assert stats.probability_of_improvement([[1.0, 3.0, 2.0]], [[2.0]]) == pytest.approx(0.5)
    assert math.isnan(stats.probability_of_improvement([[np.nan]], [[1.0]]))


def test_interquartile_mean_is_the_mean_of_the_middle_half():
    from scipy.stats import trim_mean

    assert stats.interquartile_mean(np.arange(1.0, 9.0)) == pytest.approx(4.5)
    assert stats.interquartile_mean(np.arange(1.0, 9.0)) == pytest.approx(trim_mean(np.arange(1.0, 9.0), 0.25))
    # five values: the quarter cuts fall inside the 2nd and 4th, which count three quarters each
    assert stats.interquartile_mean([1.0, 2.0, 3.0, 4.0, 100.0]) == pytest.approx((0.75 * 2 + 3 + 0.75 * 4) / 2.5)
    assert math.isnan(stats.interquartile_mean([]))


def test_kendall_tau_permutation_p_value_is_exact():
    from scipy.stats import kendalltau

    tau, p = stats.kendall_tau_test([1, 2, 3, 4], [10, 20, 30, 40])
    assert tau == pytest.approx(1.0) and p == pytest.approx(2 / 24)  # the ordering and its reverse of 24
    x, y = [1, 2, 3, 4, 5, 6], [2, 1, 4, 3, 6, 5]
    tau, p = stats.kendall_tau_test(x, y)
    reference = kendalltau(x, y, method="exact")
    assert tau == pytest.approx(reference.statistic) and p == pytest.approx(reference.pvalue)
    # ties: tau-b as scipy computes it
    x, y = [1, 2, 3, 4, 5], [1, 1, 2, 3, 3]
    assert stats.kendall_tau_test(x, y)[0] == pytest.approx(kendalltau(x, y).statistic)
    # above the exact limit: sampled orderings, close to the exact distribution's p
    x = list(range(10))
    y = [0, 2, 1, 4, 3, 5, 7, 6, 9, 8]
    tau, p = stats.kendall_tau_test(x, y, seed=1)
    assert p == pytest.approx(kendalltau(x, y, method="exact").pvalue, abs=0.01)
    assert all(math.isnan(v) for v in stats.kendall_tau_test([1, 2], [3, 3]))
    assert all(math.isnan(v) for v in stats.kendall_tau_test([1], [1]))


def test_overlap_and_interval_text():
    assert stats.overlaps((1.0, 2.0), (2.0, 3.0)) and not stats.overlaps((1.0, 2.0), (2.5, 3.0))
    assert stats.overlaps((1.0, 2.0), (math.nan, 3.0))
    assert stats.interval_text(1.234, 5.678) == "[1.23, 5.68]" and stats.interval_text(math.nan, 1.0) == "–"
    assert stats.stable_seed("a", 1) == stats.stable_seed("a", 1) != stats.stable_seed("a", 2)


def test_the_sign_flip_test_against_known_answers():
    # six differences of one sign: only "all down" and "all up" are as extreme, 2 of 2^6 patterns
    assert stats.sign_flip_test([np.array([-1.0, -1.2]), np.array([-0.9, -1.1]), np.array([-1.3, -1.0])]) \
        == pytest.approx(2 / 64)
    # no difference at all, and one pair of each sign: nothing beyond chance
    assert stats.sign_flip_test([np.zeros(3)]) == 1.0
    assert stats.sign_flip_test([np.array([1.0, -1.0])]) == 1.0
    # scenes weigh the same: a big pair in a scene of one is half the statistic, as two pairs are in another
    assert stats.sign_flip_test([np.array([4.0]), np.array([1.0, 1.0])]) == pytest.approx(2 / 8)
    assert math.isnan(stats.sign_flip_test([]))
