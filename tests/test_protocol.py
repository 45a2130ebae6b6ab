"""The evaluation protocol object: presets, the release default, and the release's time-agnostic query
rebuilt from its steps, written here in plain numpy without any of the benchmark's query code."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from benchmark.core.protocol import (DEFAULT_PROTOCOL, PROTOCOLS, SCORED_FRAMES_NOTE, SHARED_CHOICES,
                                     WINDOW_SCALING_NOTE, AgnosticQuery, Protocol, ScoringRule, SensitiveQuery,
                                     TemporalRule, get_protocol)
from benchmark.results import protocol_of
from methods.fields.relevance import AgnosticResult, answer_from_relevance


# -- the release's steps, transcribed independently (shared/docs/protocol.md, steps 3-6) -------------------
def _box_mean_excluding_padding(v: np.ndarray, k: int) -> np.ndarray:
    """Mean over the k x k window centred on each pixel, over the pixels inside the image only."""
    h, w = v.shape
    r = k // 2
    integral = np.zeros((h + 1, w + 1))
    integral[1:, 1:] = v.cumsum(0).cumsum(1)
    rows, cols = np.arange(h), np.arange(w)
    top, bottom = np.clip(rows - r, 0, h), np.clip(rows + r + 1, 0, h)
    left, right = np.clip(cols - r, 0, w), np.clip(cols + r + 1, 0, w)
    total = (integral[bottom][:, right] - integral[top][:, right] - integral[bottom][:, left]
             + integral[top][:, left])
    count = (bottom - top)[:, None] * (right - left)[None, :]
    return total / count


def _release_answer(levels: np.ndarray, smoothing: int = 29, majority: int = 7, threshold: float = 0.4,
                    stretched: bool = True) -> tuple[np.ndarray, np.ndarray, int]:
    """(mask, mask before the majority filter, chosen level) of relevance maps ``levels`` [L, H, W]."""
    smoothed = np.stack([0.5 * (v + _box_mean_excluding_padding(v, smoothing)) for v in levels])
    level = int(np.argmax(smoothed.reshape(len(levels), -1).max(1)))
    v = smoothed[level]
    x = (v - v.min()) / (v.max() - v.min())
    if stretched:
        x = np.clip(2.0 * x - 1.0, 0.0, 1.0)
    raw = x > threshold
    mask = _box_mean_excluding_padding(raw.astype(np.float64), majority) > 0.5
    return mask, raw, level


def _random_relevance(seed: int, height: int = 536, width: int = 960) -> np.ndarray:
    """[3, H, W] relevance-like maps in (0, 1): smooth blobs plus pixel noise, so that masks have both
    large regions and ragged edges for the majority filter to decide."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width] / max(height, width)
    maps = []
    for _ in range(3):
        v = rng.normal(0.0, 0.15, (height, width))
        for _ in range(4):
            cy, cx, s, a = rng.uniform(0, 0.56), rng.uniform(0, 1), rng.uniform(0.03, 0.15), rng.uniform(0.5, 3)
            v += a * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * s * s))
        maps.append(1.0 / (1.0 + np.exp(-v)))
    return np.stack(maps)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_default_query_rebuilds_the_releases_masks_pixel_for_pixel(seed):
    levels = _random_relevance(seed)
    protocol = get_protocol(DEFAULT_PROTOCOL)
    got = answer_from_relevance(torch.from_numpy(levels), protocol.agnostic)
    mask, raw, level = _release_answer(levels)
    assert got.level == level
    assert 0.002 < raw.mean() < 0.5  # the maps exercise the threshold (not all or nothing)
    assert np.array_equal(got.mask_unfiltered.numpy(), raw)
    assert np.array_equal(got.mask.numpy(), mask)
    assert (raw != mask).sum() > 0  # and the majority filter changes something


def test_the_paper_text_query_cuts_lower_on_the_same_maps():
    levels = _random_relevance(3)
    got = answer_from_relevance(torch.from_numpy(levels), PROTOCOLS["paper-text"].agnostic)
    mask, raw, _ = _release_answer(levels, stretched=False)
    assert np.array_equal(got.mask.numpy(), mask) and np.array_equal(got.mask_unfiltered.numpy(), raw)
    release = answer_from_relevance(torch.from_numpy(levels), PROTOCOLS["release"].agnostic)
    assert release.mask_unfiltered.sum() < got.mask_unfiltered.sum()


def test_release_is_the_default_everywhere():
    from benchmark.runner import EvalOptions

    assert DEFAULT_PROTOCOL == "release" and EvalOptions(method="m", scene="s").protocol == "release"
    assert Protocol() == PROTOCOLS["release"]
    release = PROTOCOLS["release"]
    assert release.agnostic.threshold_rule == "stretched" and release.agnostic.rescaled_cut == pytest.approx(0.7)
    assert (release.temporal.tau_from, release.temporal.ends) == ("raw", "keep")
    assert release.sensitive == SensitiveQuery(mask="unfiltered", relevance_score="peak")
    paper = PROTOCOLS["paper-text"]
    assert paper.agnostic.rescaled_cut == pytest.approx(0.4)
    assert (paper.temporal.tau_from, paper.temporal.ends, paper.sensitive.relevance_score) == (
        "smoothed", "renormalise", "mask-mean")
    # tau per method kind: the release's CLIP-only baselines take the smoothed mean, the paper's wording for all
    assert (release.temporal.relevance_peak_tau_from, paper.temporal.relevance_peak_tau_from) == ("smoothed", "smoothed")
    # absent frames: not scored, as the release queries a label only where it is annotated
    assert release.scoring == paper.scoring == ScoringRule(absent_frames="skip")
    # the two presets share every other constant
    assert paper.agnostic.canonical_phrases == release.agnostic.canonical_phrases
    assert paper.temporal.weights == release.temporal.weights == (0.1, 0.8, 0.1)
    # tables say which frames were scored, and never that the release scores its training views
    assert "held-out" in SCORED_FRAMES_NOTE and "release" not in SCORED_FRAMES_NOTE
    # the stated window sizes are the ones the query uses
    assert release.agnostic.kernels_for(536, 960) == (29, 7) and release.agnostic.kernels_for(128, 170) == (5, 1)
    assert "5 and 1" in WINDOW_SCALING_NOTE and WINDOW_SCALING_NOTE in SHARED_CHOICES


def test_presets_round_trip_and_changes_are_named_custom():
    for preset in PROTOCOLS.values():
        assert Protocol.from_dict(preset.to_dict()) == preset
    changed = PROTOCOLS["release"].with_changes({"temporal.tau_from": "smoothed"})
    assert changed.name == "custom" and changed.temporal.tau_from == "smoothed"
    assert PROTOCOLS["release"].with_changes({"temporal.tau_from": "raw"}).name == "release"
    with pytest.raises(ValueError, match="did you mean agnostic.threshold"):
        PROTOCOLS["release"].with_changes({"agnostic.treshold": 0.5})
    with pytest.raises(ValueError, match="did you mean 'release'"):
        get_protocol("relase")
    with pytest.raises(ValueError, match="threshold_rule"):
        AgnosticQuery(threshold_rule="release")
    with pytest.raises(ValueError, match="tau_from"):
        TemporalRule(tau_from="paper")
    with pytest.raises(ValueError, match="unknown constant"):
        Protocol.from_dict({"name": "x", "temporal": {"threshold_variant": "paper"}})
    strict = PROTOCOLS["release"].with_changes({"scoring.absent_frames": "score-empty"})
    assert strict.name == "custom" and Protocol.from_dict(strict.to_dict()) == strict
    with pytest.raises(ValueError, match="absent_frames"):
        ScoringRule(absent_frames="empty")


def test_a_record_without_the_later_constants_reads_as_it_was_scored():
    """A results file written before ``relevance_peak_tau_from`` and ``scoring`` existed was scored with one
    tau rule for every method and with absent frames against the empty mask: it reads so, and is no longer
    named after the preset whose rules changed since."""
    old = PROTOCOLS["release"].to_dict()
    del old["temporal"]["relevance_peak_tau_from"], old["scoring"]
    before = Protocol.from_dict(old)
    assert before.name == "custom"
    assert (before.temporal.relevance_peak_tau_from, before.scoring.absent_frames) == ("raw", "score-empty")
    assert before.agnostic == PROTOCOLS["release"].agnostic and before.temporal.tau_from == "raw"
    assert protocol_of({"protocol": old}) == before
    paper = PROTOCOLS["paper-text"].to_dict()
    del paper["temporal"]["relevance_peak_tau_from"]
    assert Protocol.from_dict(paper).temporal.relevance_peak_tau_from == "smoothed"  # its one tau rule


def test_results_files_say_their_protocol_old_ones_included():
    assert protocol_of({"protocol": PROTOCOLS["release"].to_dict()}).name == "release"
    # written before protocols were named: the rules in the method config and the score config
    old = {"method_config": {"threshold_variant": "paper", "sensitive_mask": "unfiltered"},
           "score_config": {"temporal": {"weights": [0.1, 0.8, 0.1], "ends": "renormalise",
                                         "threshold_variant": "paper", "inclusive": True,
                                         "undefined_decision": False, "tie_tolerance": 1e-9}}}
    # the paper-text rules of the time, but absent frames were scored against the empty mask then
    assert protocol_of(old) == dataclasses.replace(PROTOCOLS["paper-text"], name="custom",
                                                   scoring=ScoringRule(absent_frames="score-empty"))
    floor = {"method_config": {"camera_weight": 1.0}, "score_config": old["score_config"]}
    assert protocol_of(floor) == protocol_of(old)
    mixed = {"method_config": {"threshold_variant": "release"}, "score_config": old["score_config"]}
    mixed_protocol = protocol_of(mixed)
    assert mixed_protocol.name == "custom" and mixed_protocol.agnostic.threshold_rule == "stretched"


def test_the_relevance_baselines_time_score_follows_the_protocol():
    from methods.language_methods import LanguageFieldModel

    relevance = torch.tensor([[0.2, 0.9], [0.4, 0.1]])
    result = AgnosticResult(mask=torch.tensor([[False, False], [True, False]]),
                            mask_unfiltered=torch.tensor([[True, False], [True, False]]), relevance=relevance,
                            level=1, level_peaks=torch.tensor([0.5, 0.9, 0.3]))
    model = LanguageFieldModel.__new__(LanguageFieldModel)  # only the protocol is read
    model.use_protocol(PROTOCOLS["release"])
    assert model.relevance_score(result) == pytest.approx(0.9)  # the chosen level's peak
    model._protocol = PROTOCOLS["paper-text"]
    assert model.relevance_score(result) == pytest.approx(0.3)  # mean inside the unfiltered mask
    model._protocol = PROTOCOLS["paper-text"].with_changes({"sensitive.mask": "filtered"})
    assert model.relevance_score(result) == pytest.approx(0.4)
