"""The temporal threshold per method kind, against an independent transcription of the release's
``eval/eval.py`` (4D LangSplat): its ``video_thresh`` is the mean of ``video_similarity``, the raw scores
of the time-varying feature; its ``clip_thresh`` is the mean of ``sorted_clip_similarity`` after that
list was overwritten with the smoothed values, the CLIP-only baselines' relevance peaks. Both compare the
smoothed scores with their threshold (``>=``). The transcription below is plain Python and numpy and
shares nothing with :mod:`benchmark.metrics.temporal`."""

from __future__ import annotations

import numpy as np
import pytest

from benchmark.core.errors import InputError
from benchmark.core.protocol import PROTOCOLS, TIME_SCORES, TemporalRule
from benchmark.metrics import ScoreConfig, score_scene
from benchmark.metrics.temporal import apply_temporal_rule
from methods import registry


def _release_smooth(raw: list[float], coeffs: tuple[float, ...] = (0.1, 0.8, 0.1)) -> list[float]:
    """The release's ``smooth_feature_post`` loop: a frame missing a neighbour keeps its raw value."""
    half = len(coeffs) // 2
    out = []
    for i in range(len(raw)):
        acc = 0.0
        for j in range(-half, half + 1):
            if 0 <= i + j < len(raw):
                acc += raw[i + j] * coeffs[j + half]
            else:
                acc = raw[i]
                break
        out.append(acc)
    return out


def _release_decisions(raw: list[float], kind: str) -> tuple[float, list[bool]]:
    """(threshold, decisions) as the release computes them for the feature (``video``) or the CLIP
    baselines' (``clip``) scores."""
    smoothed = _release_smooth(raw)
    if kind == "video":
        thresh = sum(raw) / len(raw)  # video_similarity: never overwritten
    else:
        thresh = sum(smoothed) / len(smoothed)  # sorted_clip_similarity, overwritten with smoothed values
    return thresh, [s >= thresh for s in smoothed]


RELEASE_KIND = {"feature": "video", "relevance-peak": "clip"}


def _sequences(count: int = 200) -> list[list[float]]:
    rng = np.random.default_rng(7)
    out = []
    for _ in range(count):
        n = int(rng.integers(3, 20))
        steps = rng.random() < 0.5  # state switches with noise, or peaked noise
        base = (np.arange(n) >= rng.integers(1, n)).astype(float) if steps else rng.random(n) ** 3
        out.append([float(round(x, 3)) for x in base + rng.normal(0, 0.2, n)])  # 3 decimals: exact ties happen
    return out


@pytest.mark.parametrize("time_score", TIME_SCORES)
def test_release_preset_reproduces_the_releases_threshold_per_method_kind(time_score):
    rule = PROTOCOLS["release"].temporal
    differ = 0
    for raw in _sequences():
        thresh, decisions = _release_decisions(raw, RELEASE_KIND[time_score])
        got = apply_temporal_rule(np.array(raw), rule, time_score)
        assert got.threshold == pytest.approx(thresh, rel=1e-12, abs=1e-12)
        assert got.smoothed.tolist() == pytest.approx(_release_smooth(raw), rel=1e-12, abs=1e-12)
        assert got.decisions.tolist() == decisions, raw
        other = "relevance-peak" if time_score == "feature" else "feature"
        differ += _release_decisions(raw, RELEASE_KIND[other])[1] != decisions
    assert differ >= 5  # the two rules decide differently on many of these sequences: the kind matters


def test_paper_text_takes_the_smoothed_mean_for_every_kind_and_kinds_are_declared():
    paper = PROTOCOLS["paper-text"].temporal
    assert {paper.tau_source(k) for k in TIME_SCORES} == {"smoothed"}
    release = PROTOCOLS["release"].temporal
    assert (release.tau_source("feature"), release.tau_source("relevance-peak")) == ("raw", "smoothed")
    with pytest.raises(ValueError, match="time_score"):
        release.tau_source("clip")
    with pytest.raises(ValueError, match="relevance_peak_tau_from"):
        TemporalRule(relevance_peak_tau_from="mean")
    # the release's CLIP-only baselines declare a relevance-peak score; the 4D heads a feature score
    assert {name: registry.get(name).time_score for name in ("deformable-clip", "langsplat", "4d-langsplat",
                                                              "non-status-field")} == {
        "deformable-clip": "relevance-peak", "langsplat": "relevance-peak", "4d-langsplat": "feature",
        "non-status-field": "feature"}


def test_the_scorer_applies_the_declared_kind():
    from tests.test_score import hand_predictions, make_gt  # the hand-computed scene of the scoring tests

    aset = make_gt()
    preds = hand_predictions(aset)
    raw = [0.2, 1.0, 0.5, 1.0, 1.0, 0.0]
    preds.queries["cracked cookie"].scores = {f"f{t:03d}": s for t, s in enumerate(raw)}
    rows = {}
    for kind in TIME_SCORES:
        preds.info["time_score"] = kind
        row = score_scene(aset, preds).query_table().set_index("query").loc["cracked cookie"]
        thresh, decisions = _release_decisions(raw, RELEASE_KIND[kind])
        assert row["threshold"] == pytest.approx(thresh) and row["predicted"] == sum(decisions)
        rows[kind] = row
    assert rows["feature"]["acc"] != rows["relevance-peak"]["acc"]
    # the config overrides the predictions' declaration; an unknown declaration is an input error
    forced = score_scene(aset, preds, ScoreConfig(time_score="feature")).query_table().set_index("query")
    assert forced.loc["cracked cookie", "threshold"] == pytest.approx(rows["feature"]["threshold"])
    preds.info["time_score"] = "clip"
    with pytest.raises(InputError, match="info.time_score"):
        score_scene(aset, preds)
