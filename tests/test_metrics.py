"""Metrics core: hand-computed cases (numbers worked out in the comments) and property tests."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from benchmark.core.annotation import AnnotationSet, Query
from benchmark.core.protocol import PROTOCOLS
from benchmark.metrics import (EMPTY_IOU, EMPTY_UNION_VIOU, TemporalRule, aggregate, apply_temporal_rule,
                               decide_temporal, delta_sim, delta_sim_scene, iou, mean_delta_sim, pixel_accuracy,
                               score_agnostic, score_sensitive, smooth_scores, temporal_accuracy, video_iou)

FAST = settings(max_examples=60, deadline=None)
masks_2d = st.tuples(st.integers(1, 6), st.integers(1, 6)).flatmap(
    lambda hw: st.tuples(arrays(bool, hw), arrays(bool, hw)))


# -- spatial -------------------------------------------------------------------------------------------
def test_iou_and_pixel_accuracy_by_hand():
    pred = np.array([[1, 1, 0], [0, 0, 0]], bool)
    gt = np.array([[0, 1, 1], [0, 0, 0]], bool)
    # intersection = 1 pixel (0,1); union = 3 pixels -> 1/3
    assert iou(pred, gt) == pytest.approx(1 / 3)
    # disagreeing pixels (0,0), (0,2) -> 2 of 6 wrong -> 4/6
    assert pixel_accuracy(pred, gt) == pytest.approx(4 / 6)


def test_empty_mask_rules():
    empty = np.zeros((2, 3), bool)
    some = np.zeros((2, 3), bool)
    some[0, 0] = some[1, 2] = True
    assert iou(empty, empty) == EMPTY_IOU == 1.0          # both empty: DAVIS convention
    assert pixel_accuracy(empty, empty) == 1.0
    assert iou(empty, some) == 0.0                         # missed object
    assert pixel_accuracy(empty, some) == pytest.approx(4 / 6)
    assert iou(some, empty) == 0.0                         # false positive on an "absent" frame
    assert pixel_accuracy(some, empty) == pytest.approx(4 / 6)


def test_batched_and_scalar_shapes():
    rng = np.random.default_rng(1)
    p, g = rng.random((2, 5, 4, 3)) > 0.5, rng.random((2, 5, 4, 3)) > 0.5
    batch = iou(p, g)
    assert batch.shape == (2, 5)
    assert batch[1, 3] == pytest.approx(float(iou(p[1, 3], g[1, 3])))
    assert pixel_accuracy(p, g).shape == (2, 5)
    assert np.ndim(iou(p[0, 0], g[0, 0])) == 0


def test_score_agnostic_stack_or_sequence():
    rng = np.random.default_rng(2)
    p, g = rng.random((3, 4, 5)) > 0.5, rng.random((3, 4, 5)) > 0.5
    stacked, listed = score_agnostic(p, g), score_agnostic(list(p), list(g))
    np.testing.assert_allclose(stacked.iou, listed.iou)
    np.testing.assert_allclose(stacked.acc, listed.acc)
    assert stacked.miou == pytest.approx(np.mean([iou(a, b) for a, b in zip(p, g)]))
    with pytest.raises(ValueError):
        score_agnostic(list(p), list(g[:2]))


def test_bad_mask_shapes_raise():
    with pytest.raises(ValueError, match="differs"):
        iou(np.zeros((2, 3)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="no pixels"):
        pixel_accuracy(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match="2 axes"):
        iou(np.zeros(3), np.zeros(3))


@FAST
@given(masks_2d)
def test_spatial_properties(pair):
    p, g = pair
    # perfect prediction scores 1 (100%) for every mask, empty included
    assert iou(g, g) == 1.0 and pixel_accuracy(g, g) == 1.0
    # the complement scores 0 for every mask: union = all pixels, intersection and agreement empty
    assert iou(~g, g) == 0.0 and pixel_accuracy(~g, g) == 0.0
    v, a = float(iou(p, g)), float(pixel_accuracy(p, g))
    assert 0.0 <= v <= 1.0 and 0.0 <= a <= 1.0
    assert v == float(iou(g, p)) and a == float(pixel_accuracy(g, p))
    # integer 0/1 masks mean the same as bool masks
    assert v == float(iou(p.astype(np.uint8), g.astype(np.int64)))


# -- temporal rule ----------------------------------------------------------------------------------------
S = np.array([0.2, 0.6, 0.4, 0.9])


def test_smoothing_by_hand_each_end_mode():
    # interior: t1 = .1*.2 + .8*.6 + .1*.4 = .54 ; t2 = .1*.6 + .8*.4 + .1*.9 = .47
    # renormalise: t0 = (.8*.2 + .1*.6)/.9 = .22/.9 ; t3 = (.1*.4 + .8*.9)/.9 = .76/.9
    np.testing.assert_allclose(smooth_scores(S, TemporalRule(ends="renormalise")), [0.22 / 0.9, 0.54, 0.47, 0.76 / 0.9])
    # keep (release, the default): the ends keep their raw score
    np.testing.assert_allclose(smooth_scores(S, TemporalRule()), [0.2, 0.54, 0.47, 0.9])
    # replicate: t0 = .9*.2 + .1*.6 = .24 ; t3 = .1*.4 + .9*.9 = .85
    np.testing.assert_allclose(smooth_scores(S, TemporalRule(ends="replicate")), [0.24, 0.54, 0.47, 0.85])
    # weights (1,) disable smoothing
    np.testing.assert_allclose(smooth_scores(S, TemporalRule(weights=(1.0,))), S)


def test_rule_by_hand_paper_text():
    # smoothed (renormalise) = [.24444, .54, .47, .84444]; tau = 2.09889 / 4 = .524722
    r = apply_temporal_rule(S, PROTOCOLS["paper-text"].temporal)
    assert r.threshold == pytest.approx((0.22 / 0.9 + 0.54 + 0.47 + 0.76 / 0.9) / 4)
    assert r.decisions.tolist() == [False, True, False, True]
    assert decide_temporal(S, PROTOCOLS["paper-text"].temporal).tolist() == r.decisions.tolist()


def test_rule_by_hand_default_is_the_release():
    # smoothed (keep) = [.2, .54, .47, .9]; tau = mean of the raw scores = 2.1 / 4 = .525
    r = apply_temporal_rule(S)
    assert r.threshold == pytest.approx(0.525)
    np.testing.assert_allclose(r.smoothed, [0.2, 0.54, 0.47, 0.9])
    assert r.decisions.tolist() == [False, True, False, True]
    assert TemporalRule() == PROTOCOLS["release"].temporal


def test_paper_and_release_thresholds_differ_by_hand():
    s = np.array([0.5, 0.2, 0.2, 1.0])
    # ends=keep: smoothed = [.5, .05+.16+.02=.23, .02+.16+.1=.28, 1.0]
    # paper tau = (.5+.23+.28+1)/4 = .5025 -> frame 0 (0.5) negative
    paper = apply_temporal_rule(s, TemporalRule(ends="keep", tau_from="smoothed"))
    np.testing.assert_allclose(paper.smoothed, [0.5, 0.23, 0.28, 1.0])
    assert paper.threshold == pytest.approx(0.5025)
    assert paper.decisions.tolist() == [False, False, False, True]
    # release tau = mean of raw = 1.9/4 = .475 -> frame 0 positive
    release = apply_temporal_rule(s, PROTOCOLS["release"].temporal)
    assert release.threshold == pytest.approx(0.475)
    assert release.decisions.tolist() == [True, False, False, True]


def test_undefined_scores_by_hand():
    s = np.array([0.2, np.nan, 0.6, 0.4])
    # renormalise, NaN = missing neighbour: t0 = .8*.2/.8 = .2 ; t2 = (.8*.6 + .1*.4)/.9 = .52/.9 ;
    # t3 = (.1*.6 + .8*.4)/.9 = .38/.9 ; paper tau = (.2 + .52/.9 + .38/.9)/3 = (.2 + 1)/3 = .4
    r = apply_temporal_rule(s, PROTOCOLS["paper-text"].temporal)
    np.testing.assert_allclose(r.smoothed[[0, 2, 3]], [0.2, 0.52 / 0.9, 0.38 / 0.9])
    assert math.isnan(r.smoothed[1])
    assert r.threshold == pytest.approx(0.4)
    assert r.decisions.tolist() == [False, False, True, True]   # the NaN frame is negative
    # keep: every frame next to the NaN keeps its raw value
    np.testing.assert_allclose(smooth_scores(s, TemporalRule(ends="keep"))[[0, 2, 3]], [0.2, 0.6, 0.4])
    # the undefined frame's decision is a named option
    assert apply_temporal_rule(s, TemporalRule(undefined_decision=True)).decisions.tolist() == [False, True, True, True]
    # all undefined: tau NaN, every frame negative
    r = apply_temporal_rule(np.full(3, np.nan))
    assert math.isnan(r.threshold) and not r.decisions.any()
    assert apply_temporal_rule(np.zeros(0)).decisions.shape == (0,)


def test_rule_config_validation():
    for bad in ({"weights": (0.5, 0.5)}, {"weights": (0.2, 0.7, 0.2)}, {"weights": (-0.1, 1.2, -0.1)},
                {"weights": (0.5, 0.0, 0.5)}, {"ends": "wrap"}, {"tau_from": "mean"},
                {"tie_tolerance": -1.0}):
        with pytest.raises(ValueError):
            TemporalRule(**bad)
    with pytest.raises(ValueError, match="inf"):
        smooth_scores(np.array([0.0, np.inf]))
    assert TemporalRule(weights=(0.1, 0.2, 0.4, 0.2, 0.1)).weights == (0.1, 0.2, 0.4, 0.2, 0.1)


CONFIGS = [TemporalRule(ends=e, tau_from=v) for e in ("renormalise", "keep", "replicate")
           for v in ("smoothed", "raw")]
ten_scores = st.lists(st.integers(0, 10), min_size=1, max_size=12).map(lambda v: np.array(v) / 10)


@FAST
@given(st.floats(-5, 5, allow_nan=False, allow_subnormal=False).filter(lambda v: v == 0 or abs(v) > 1e-200),
       st.integers(1, 12), st.sampled_from(CONFIGS))
def test_constant_scores_are_all_positive(value, n, config):
    # ties must not be split by float rounding: s~_t == tau everywhere (values near the float
    # minimum are left out: the test process flushes subnormals to zero, which breaks any sum)
    assert apply_temporal_rule(np.full(n, value), config).decisions.all()


@FAST
@given(ten_scores, st.sampled_from([0.5, 2.0, 3.0]), st.sampled_from([-1.0, 0.0, 0.7]), st.sampled_from(CONFIGS))
def test_rule_invariant_to_positive_affine_maps(scores, a, b, config):
    r = apply_temporal_rule(scores, config)
    assert (apply_temporal_rule(a * scores + b, config).decisions == r.decisions).all()
    assert np.nanmin(scores) - 1e-12 <= r.threshold <= np.nanmax(scores) + 1e-12


@FAST
@given(st.lists(st.booleans(), min_size=2, max_size=12).filter(lambda v: 0 < sum(v) < len(v)),
       st.sampled_from(["smoothed", "raw"]))
def test_perfect_and_complement_scores_without_smoothing(labels, variant):
    y = np.array(labels)
    config = TemporalRule(weights=(1.0,), tau_from=variant)
    ious = np.ones(y.size)
    perfect = score_sensitive(y, ious, scores=y.astype(float), config=config)
    assert perfect.accuracy == 1.0 and perfect.viou == 1.0
    worst = score_sensitive(y, np.zeros(y.size), scores=(~y).astype(float), config=config)
    assert worst.accuracy == 0.0 and worst.viou == 0.0


@FAST
@given(st.lists(st.booleans(), min_size=1, max_size=12))
def test_perfect_and_complement_decisions(labels):
    y = np.array(labels)
    perfect = score_sensitive(y, np.ones(y.size), decisions=y)
    assert perfect.accuracy == 1.0 and perfect.viou == 1.0 and perfect.rule is None
    worst = score_sensitive(y, np.ones(y.size), decisions=~y)
    assert worst.accuracy == 0.0 and worst.viou == 0.0


def test_temporal_accuracy_and_viou_by_hand():
    d = np.array([True, True, False, False])
    y = np.array([False, True, True, False])
    assert temporal_accuracy(d, y) == 0.5                       # frames 1 and 3 agree
    # S_u = {0, 1, 2}, S_i = {1} -> IoU_1 / 3 = .6 / 3
    assert video_iou(d, y, np.array([0.9, 0.6, 0.3, 0.1])) == pytest.approx(0.2)
    # empty S_u: nothing predicted, nothing labelled
    assert video_iou(np.zeros(3, bool), np.zeros(3, bool), np.full(3, np.nan)) == EMPTY_UNION_VIOU == 1.0
    assert math.isnan(temporal_accuracy(np.zeros(0, bool), np.zeros(0, bool)))
    with pytest.raises(ValueError, match="NaN"):
        video_iou(d, y, np.array([0.9, np.nan, 0.3, 0.1]))
    with pytest.raises(ValueError):
        video_iou(d, y[:3], np.zeros(4))


# -- Delta-sim ------------------------------------------------------------------------------------------------
def test_delta_sim_by_hand():
    q = np.array([1.0, 0.0])
    caps = np.array([[2.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    # cos = [1, 0, 1/sqrt(2)]; positives {0}: 1 ; negatives {1, 2}: (0 + .70711)/2 = .35355
    assert delta_sim(q, caps, np.array([True, False, False])) == pytest.approx(1 - 0.5 / math.sqrt(2))
    assert math.isnan(delta_sim(q, caps, np.zeros(3, bool)))       # no positive
    assert math.isnan(delta_sim(q, caps, np.ones(3, bool)))        # no negative
    with pytest.raises(ValueError):
        delta_sim(q, np.zeros((3, 2)), np.array([True, False, False]))   # zero vectors
    with pytest.raises(ValueError):
        delta_sim(q, caps, np.array([True, False]))


def test_delta_sim_scene_and_mean():
    aset = AnnotationSet(scene="s", queries=[
        Query(0, "cookie"), Query(1, "cracked cookie", "sensitive", base=0, intervals=[(2, 3)]),
        Query(2, "whole cookie", "sensitive", base=0, intervals=[(0, 9)])])
    caps = {("cookie", t): np.array([1.0, 0.0]) if t >= 2 else np.array([0.0, 1.0]) for t in range(4)}
    table = delta_sim_scene(aset, {"cracked cookie": np.array([1.0, 0.0]), "whole cookie": np.array([0.0, 1.0])}, caps)
    row = table.set_index("query").loc["cracked cookie"]
    # positives t=2,3 have cos 1, negatives t=0,1 cos 0 -> 100 percent
    assert (row["positives"], row["negatives"], row["delta_sim"]) == (2, 2, pytest.approx(100.0))
    assert row["auc"] == pytest.approx(100.0) and math.isnan(row["replay_acc"])  # no annotated frames to replay on
    assert math.isnan(table.set_index("query").loc["whole cookie", "delta_sim"])   # no negatives
    assert mean_delta_sim(table) == pytest.approx(100.0)                            # NaN left out
    assert math.isnan(mean_delta_sim(table.iloc[1:]))


def test_caption_auc_and_replay_accuracy():
    from benchmark.metrics import caption_auc, caption_replay_accuracy

    q = np.array([1.0, 0.0])
    # positives at cos 0.9 and 0.2, negatives at 0.5 and 0.0: 3 of 4 pairs ordered right
    caps = np.array([[0.9, math.sqrt(1 - 0.81)], [0.2, math.sqrt(1 - 0.04)], [0.5, math.sqrt(0.75)], [0.0, 1.0]])
    assert caption_auc(q, caps, np.array([True, True, False, False])) == pytest.approx(0.75)
    assert caption_auc(q, caps[:2], np.array([True, True])) != caption_auc(q, caps[:2], np.array([True, True]))  # NaN
    assert caption_auc(q, caps[[0, 0]], np.array([True, False])) == pytest.approx(0.5)  # a tie counts half
    # captions at t = 0..7: the query holds (cos 1) from t = 4 on, except a misleading caption at t = 5
    times = np.arange(8)
    emb = np.array([[0.0, 1.0]] * 4 + [[1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 0.0]])
    eval_t, labels = np.array([1, 5, 6]), np.array([False, True, True])
    assert caption_replay_accuracy(q, times, emb, eval_t, labels) == pytest.approx(100 * 2 / 3)  # t = 5 copies the bad one
    # between captions (t = 4.5 has neighbours 4 and 5): their mean, cos 1/sqrt(2)
    assert caption_replay_accuracy(q, times, emb, np.array([1.0, 4.5, 6.0]), labels) == pytest.approx(100.0)
    assert math.isnan(caption_replay_accuracy(q, times[:0], emb[:0], eval_t, labels))


def test_window_caption_embeddings_by_hand():
    """Each embedding becomes the unit mean of those within the window, itself and same-time ones included."""
    from methods.fields.caption_targets import window_caption_embeddings

    times = np.array([0, 1, 2, 5, 5])
    emb = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [0.0, 1.0], [1.0, 0.0]])
    out = window_caption_embeddings(times, emb, 1)
    r = 1 / math.sqrt(2)
    want = [[r, r],                                        # t = 0: itself and t = 1
            [2 / math.sqrt(5), 1 / math.sqrt(5)],          # t = 1: t = 0, 1, 2
            [r, r],                                        # t = 2: t = 1, 2 (t = 5 is 3 steps away)
            [r, r], [r, r]]                                # t = 5: both captions at t = 5
    np.testing.assert_allclose(out, want, atol=1e-12)
    same = window_caption_embeddings(times[:3], emb[:3], 0)  # window 0 without shared times: unchanged
    np.testing.assert_allclose(same, emb[:3], atol=1e-12)
    np.testing.assert_allclose(window_caption_embeddings(times, emb, 10), np.tile([[0.6, 0.4]] , (5, 1)) /
                               np.linalg.norm([0.6, 0.4]), atol=1e-12)  # everything: 3 of 5 along x
    with pytest.raises(ValueError, match="window"):
        window_caption_embeddings(times, emb, -1)
    with pytest.raises(ValueError, match="shapes"):
        window_caption_embeddings(times[:2], emb, 1)


def _paraphrases(states: list[int], seed: int = 0, dim: int = 16) -> np.ndarray:
    """Unit caption embeddings of a state sequence: each state a direction, each frame one of two
    paraphrases of it drawn at random (the wording varies as much as a state's two phrasings do)."""
    rng = np.random.default_rng(seed)
    centre = rng.standard_normal((max(states) + 1, dim))
    wording = rng.standard_normal((max(states) + 1, 2, dim)) * 0.6
    x = np.stack([centre[s] + wording[s, rng.integers(2)] for s in states])
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_caption_change_points_find_held_states_not_paraphrases():
    from methods.fields.caption_targets import caption_change_points, fitted_caption_targets, segment_caption_embeddings

    times = np.arange(40)
    step = [0] * 22 + [1] * 18
    assert caption_change_points(times, _paraphrases(step), min_length=4) == [22.0]
    # a state that comes and goes, symmetric: no single split is significant (one split at a time found
    # nothing here), the inner run is, and both its ends are found in one test
    there_and_back = [0] * 13 + [1] * 14 + [0] * 13
    assert caption_change_points(times, _paraphrases(there_and_back), min_length=4) == [13.0, 27.0]
    # paraphrases of one state alone: no split beats its shuffles
    for seed in range(5):
        assert caption_change_points(times, _paraphrases([0] * 40, seed=seed), min_length=4) == []
    # a change 3 frames from the end is shorter than a segment may be
    assert caption_change_points(times, _paraphrases([0] * 37 + [1] * 3), min_length=4) == []
    # several cameras at a time are averaged first; times need not be sorted
    emb = _paraphrases(step)
    order = np.random.default_rng(0).permutation(40)
    doubled = np.concatenate([times[order], times[order]])
    assert caption_change_points(doubled, np.concatenate([emb[order], emb[order]]), min_length=4) == [22.0]
    # segment means by hand
    targets = segment_caption_embeddings(times, emb, [22.0])
    for part in (slice(0, 22), slice(22, 40)):
        mean = emb[part].mean(0)
        np.testing.assert_allclose(targets[part], np.tile(mean / np.linalg.norm(mean), (len(emb[part]), 1)),
                                   atol=1e-12)
    np.testing.assert_allclose(fitted_caption_targets(times, emb, segment_min_length=4), targets, atol=1e-12)
    np.testing.assert_allclose(fitted_caption_targets(times, emb), emb, atol=1e-12)
    with pytest.raises(ValueError, match="alternatives"):
        fitted_caption_targets(times, emb, window=2, segment_min_length=4)
    with pytest.raises(ValueError, match="significance"):
        caption_change_points(times, emb, min_length=4, significance=1.5)


def test_caption_segment_states_merge_only_what_comes_back():
    from methods.fields.caption_targets import caption_segment_states, caption_segments, segment_caption_embeddings

    times = np.arange(40)
    for seed in range(4):
        back = _paraphrases([0] * 13 + [1] * 14 + [0] * 13, seed=seed)
        cuts, states, targets = caption_segments(times, back, min_length=4)
        assert (cuts, states) == ([13.0, 27.0], [0, 1, 0])
        closed = np.r_[0:13, 27:40]
        mean = back[closed].mean(0)
        np.testing.assert_allclose(targets[closed], np.tile(mean / np.linalg.norm(mean), (26, 1)), atol=1e-12)
        onward = _paraphrases([0] * 13 + [1] * 14 + [2] * 13, seed=seed)
        assert caption_segment_states(times, onward, [13.0, 27.0]) == [0, 1, 2]
    # neighbours never merge, even when their captions agree (their change point was kept already)
    same = _paraphrases([0] * 40)
    assert caption_segment_states(times, same, [20.0]) == [0, 1]
    assert caption_segment_states(times, same, [10.0, 20.0, 30.0]) == [0, 1, 0, 1]
    assert caption_segment_states(times, same, []) == [0]
    with pytest.raises(ValueError, match="state labels"):
        segment_caption_embeddings(times, same, [20.0], [0])
    with pytest.raises(ValueError, match="shapes"):
        caption_segment_states(times[:-1], same, [20.0])


# -- aggregation -----------------------------------------------------------------------------------------------
def _frames_table() -> pd.DataFrame:
    return pd.DataFrame([
        ("A", "q1", "f1", 1.0), ("A", "q1", "f2", 0.0), ("A", "q2", "f1", 1.0), ("B", "q1", "f1", 0.25),
    ], columns=["scene", "query", "frame", "iou"])


def test_aggregation_levels_by_hand():
    t = _frames_table()
    # query: A/q1 = .5, A/q2 = 1, B/q1 = .25 ; scene: A = .75, B = .25 ; dataset = .5
    q = aggregate(t, ["iou"], to="query")
    assert q["iou"].tolist() == [0.5, 1.0, 0.25] and q["count"].tolist() == [2, 1, 1]
    s = aggregate(t, ["iou"], to="scene")
    assert s["iou"].tolist() == [0.75, 0.25] and s["count"].tolist() == [3, 1]
    d = aggregate(t, ["iou"])
    # not the pooled frame mean (.5625) nor the pooled query mean (.5833)
    assert d["iou"].iloc[0] == pytest.approx(0.5) and d["count"].iloc[0] == 4
    assert aggregate(q, ["iou"], start="query")["iou"].iloc[0] == pytest.approx(0.5)


def test_aggregation_skips_nan_and_ignores_row_order():
    t = _frames_table()
    t["viou"] = [np.nan, np.nan, np.nan, 0.4]
    d = aggregate(t, ["iou", "viou"])
    assert d["viou"].iloc[0] == pytest.approx(0.4)      # scene A has no value: left out, not 0
    shuffled = t.sample(frac=1.0, random_state=3)[["iou", "frame", "viou", "query", "scene"]]
    pd.testing.assert_frame_equal(aggregate(shuffled, ["iou", "viou"], to="query"), aggregate(t, ["iou", "viou"], to="query"))
    with pytest.raises(ValueError):
        aggregate(t, ["iou"], start="scene", to="query")
    with pytest.raises(ValueError, match="lacks"):
        aggregate(t, ["acc"])


def test_score_auc_counts_ordered_pairs_ties_half_and_leaves_out_undefined_scores():
    from benchmark.metrics import score_auc

    labels = np.array([False, False, True, True])
    assert score_auc(np.array([0.1, 0.2, 0.3, 0.4]), labels) == 1.0
    assert score_auc(np.array([0.4, 0.3, 0.2, 0.1]), labels) == 0.0  # inverted: the states swapped
    assert score_auc(np.array([0.1, 0.3, 0.3, 0.4]), labels) == pytest.approx(0.875)  # one tie of four pairs
    assert score_auc(np.array([0.1, np.nan, 0.3, 0.0]), labels) == pytest.approx(0.5)  # NaN frame left out
    assert np.isnan(score_auc(np.array([0.1, 0.2, np.nan, np.nan]), labels))  # no positive left
    with pytest.raises(ValueError, match="same"):
        score_auc(np.zeros(3), labels)


def test_threshold_margins_and_near_threshold_fraction_by_hand():
    from benchmark.metrics import NEAR_THRESHOLD_FRACTION, near_threshold_fraction, threshold_margins

    smoothed = np.array([0.0, 0.1, 0.9, 0.9, 0.1, 0.0])
    tau = 1 / 3
    # range 0.9: margins (s - 1/3) / 0.9
    assert threshold_margins(smoothed, tau) == pytest.approx([-1 / 2.7, -0.7 / 2.7, 1.7 / 2.7, 1.7 / 2.7, -0.7 / 2.7, -1 / 2.7])
    assert near_threshold_fraction(smoothed, tau) == 0.0  # nothing within 5 % of the range
    assert near_threshold_fraction(smoothed, tau, 0.3) == pytest.approx(2 / 6)  # the two 0.1s: |-0.259| < 0.3
    assert near_threshold_fraction(smoothed, tau, 0.0) == 0.0
    # constant scores: every decision rests on the tie rule alone
    assert near_threshold_fraction(np.full(4, 0.88), 0.88) == 1.0
    # an undefined score is decided by convention: not near, but still one of the T frames
    assert near_threshold_fraction(np.array([0.0, 0.5, np.nan, 1.0]), 0.5) == pytest.approx(1 / 4)
    assert np.isnan(threshold_margins(np.array([0.0, np.nan]), 0.0)[1])
    assert near_threshold_fraction(np.array([np.nan, np.nan]), float("nan")) == 0.0
    assert np.isnan(near_threshold_fraction(np.array([]), 0.0))
    assert NEAR_THRESHOLD_FRACTION == 0.05
    with pytest.raises(ValueError, match="fraction"):
        near_threshold_fraction(smoothed, tau, -0.1)


def test_score_sensitive_reports_auc_and_near_threshold_only_with_scores():
    labels = np.array([False, False, True, True, True, False])
    frame_iou = np.ones(6)
    res = score_sensitive(labels, frame_iou, scores=np.array([0, 0, 1, 1, 0, 0], float))
    # smoothed [0, .1, .9, .9, .1, 0]; positives {.9, .9, .1} vs negatives {0, .1, 0}:
    # each .9 beats 3 (6), the .1 beats the two 0s (2) and ties the .1 (0.5) -> 8.5 / 9
    assert res.auc == pytest.approx(8.5 / 9)
    assert res.near_threshold == 0.0
    given = score_sensitive(labels, frame_iou, decisions=labels)
    assert np.isnan(given.auc) and np.isnan(given.near_threshold)


def test_accuracy_at_threshold_and_best_cut_by_hand():
    from benchmark.metrics import accuracy_at_threshold, best_cut_accuracy

    labels = np.array([False, True, False, True, True])
    scores = np.array([0.1, 0.4, 0.3, 0.2, np.nan])
    # cut 0.25: decisions [F, T, T, F, F(undefined)] -> right on frames 0, 1 -> 2/5
    assert accuracy_at_threshold(scores, labels, 0.25) == pytest.approx(2 / 5)
    assert accuracy_at_threshold(scores, labels, 0.25, undefined_decision=True) == pytest.approx(3 / 5)
    # cuts: 0.1 -> [T,T,T,T,F] 2/5; 0.2 -> [F,T,T,T,F] 3/5; 0.3 -> [F,T,T,F,F] 2/5; 0.4 -> [F,T,F,F,F] 3/5;
    # above all -> all negative 2/5: best 3/5, below what a perfect order gives
    assert best_cut_accuracy(scores, labels) == pytest.approx(3 / 5)
    assert best_cut_accuracy(np.array([0.1, 0.9, 0.2, 0.8, 0.7]), labels) == 1.0
    assert best_cut_accuracy(np.array([0.5, 0.5]), np.array([False, False])) == 1.0  # all negative is a cut
    with pytest.raises(ValueError, match="shape"):
        accuracy_at_threshold(scores, labels[:3], 0.2)


def test_caption_segments_leave_captions_without_a_found_change_as_captioned():
    """Below 11 caption times no split is rarer than 1 % of the shuffles, so the change-point test
    cannot find even the cleanest change: the captions stay their own targets (and the fit's spread test
    decides), instead of one mean that erases the states."""
    from methods.fields.caption_targets import caption_segments, change_points_testable

    def two_states(n):
        emb = np.zeros((n, 2))
        emb[: n // 2, 0] = 1.0
        emb[n // 2:, 1] = 1.0
        return np.arange(float(n)), emb

    assert not change_points_testable(9, 4) and change_points_testable(13, 4)
    times, emb = two_states(9)
    cuts, states, targets = caption_segments(times, emb, min_length=4)
    assert cuts is None and states is None
    np.testing.assert_array_equal(targets, emb)
    times, emb = two_states(13)
    cuts, states, targets = caption_segments(times, emb, min_length=4)
    assert (cuts, states) == ([6.0], [0, 1])
    np.testing.assert_array_equal(targets, emb)  # each state's captions agree: the means are the captions
    # a testable length in which the test finds no change keeps its captions too: equal captions are their
    # own mean, and one caption of the other state among twelve hides a change the test finds without it
    same = np.tile([0.6, 0.8], (13, 1))
    cuts, states, targets = caption_segments(times, same, min_length=4)
    assert cuts is None and states is None
    np.testing.assert_array_equal(targets, same)
    times, emb = two_states(12)
    assert caption_segments(times, emb, min_length=4)[:2] == ([6.0], [0, 1])
    emb[2] = emb[-1]
    cuts, states, targets = caption_segments(times, emb, min_length=4)
    assert cuts is None and states is None
    np.testing.assert_array_equal(targets, emb)  # not one mean: the spread tolerance still sees two states
