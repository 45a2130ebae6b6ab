"""The protocol's constants and tie rules, pinned against their definitions (``shared/docs/protocol.md``)
rather than against today's output: the LERF temperature the release uses (10), the time-sensitive
decision ``s~_t >= tau`` (a score exactly at the threshold is a "yes"), and the time-agnostic threshold
``x > threshold`` (a pixel exactly at the threshold is out of the mask)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from benchmark.core.protocol import PROTOCOLS, AgnosticQuery, default_protocol
from benchmark.metrics.temporal import accuracy_at_threshold, best_cut_accuracy
from methods.fields.relevance import query_levels, threshold_mask

RELEASE_TEMPERATURE = 10.0
"""protocol.md, time-agnostic query step 2: ``exp(10 q.f) / (exp(10 q.f) + exp(10 c.f))``."""


def lerf(qf: float, cf: float, s: float) -> float:
    """The LERF relevance as protocol.md writes it, for one canonical phrase."""
    return math.exp(s * qf) / (math.exp(s * qf) + math.exp(s * cf))


# -- the temporal decision: s~_t >= threshold ------------------------------------------------------------
def test_a_score_exactly_at_the_threshold_is_decided_yes():
    labels = np.array([True, False, True])
    scores = np.array([0.5, 0.25, 0.75])
    assert accuracy_at_threshold(scores, labels, 0.5) == 1.0  # 0.5 >= 0.5 is a yes, 0.25 a no
    assert accuracy_at_threshold(np.array([0.5]), np.array([True]), 0.5) == 1.0
    assert accuracy_at_threshold(np.array([0.5]), np.array([False]), 0.5) == 0.0
    # the oracle cut at a defined value decides that value "yes": a perfect split exists at 0.5
    assert best_cut_accuracy(scores, labels) == 1.0


# -- the LERF temperature -----------------------------------------------------------------------------------
def test_the_release_protocol_uses_the_papers_temperature():
    assert AgnosticQuery().temperature == RELEASE_TEMPERATURE
    assert PROTOCOLS["release"].agnostic.temperature == RELEASE_TEMPERATURE
    assert default_protocol().agnostic.temperature == RELEASE_TEMPERATURE


@pytest.mark.parametrize("qf,cf", [(1.0, 0.0), (0.6, 0.8), (0.3, 0.1)])
def test_the_default_query_computes_lerf_relevance_with_temperature_ten(qf, cf):
    """A constant feature map whose pixels have ``q.f = qf`` and ``c.f = cf`` (unit vectors): the peak
    smoothed relevance the default rules compute equals protocol.md's formula with s = 10."""
    d = 4
    query = torch.zeros(d, dtype=torch.float64)
    query[0] = 1.0
    canon = torch.zeros(1, d, dtype=torch.float64)
    canon[0, 1] = 1.0
    # a unit feature with components qf (along q), cf (along c) and the rest in a third direction
    feat = torch.tensor([qf, cf, math.sqrt(max(0.0, 1 - qf * qf - cf * cf)), 0.0], dtype=torch.float64)
    features = feat.expand(3, 9, 9, d).clone()
    result = query_levels(features, query, canon, AgnosticQuery())
    assert float(result.level_peaks.max()) == pytest.approx(lerf(qf, cf, RELEASE_TEMPERATURE), rel=1e-9)


def test_language_methods_answer_with_the_protocols_temperature():
    """The relevance rules a fitted language-field model answers with are its protocol's own (release:
    temperature 10), under the default protocol and after the harness hands it one."""
    from methods.language_methods import LanguageFieldModel, LanguageMethodConfig

    shared = SimpleNamespace(geometry=None, field=None, autoencoder=None, info={})
    model = LanguageFieldModel("4d-langsplat", LanguageMethodConfig(), None, shared, sensitive=None)
    assert model.relevance_cfg.temperature == RELEASE_TEMPERATURE
    assert model.relevance_cfg == PROTOCOLS["release"].agnostic
    model.use_protocol(PROTOCOLS["release"])
    assert model.relevance_cfg.temperature == RELEASE_TEMPERATURE
    for name, protocol in PROTOCOLS.items():
        model.use_protocol(protocol)
        assert model.relevance_cfg.temperature == protocol.agnostic.temperature, name


# -- the time-agnostic threshold: x > threshold ---------------------------------------------------------
def test_a_pixel_exactly_at_the_threshold_is_out_of_the_mask():
    # stretched (release): clip(2 x - 1, 0, 1) > t; x = 0.75 gives exactly 0.5 = t (exact in binary)
    smoothed = torch.tensor([[0.0, 0.75, 1.0]], dtype=torch.float32)
    mask = threshold_mask(smoothed, AgnosticQuery(threshold=0.5, threshold_rule="stretched"))
    assert mask.tolist() == [[False, False, True]]
    # rescaled (paper text): x > t; x = 0.5 exactly at t
    smoothed = torch.tensor([[0.0, 0.5, 1.0]], dtype=torch.float32)
    mask = threshold_mask(smoothed, AgnosticQuery(threshold=0.5, threshold_rule="rescaled"))
    assert mask.tolist() == [[False, False, True]]
