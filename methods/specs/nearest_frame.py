"""Specs of the 2D floors: ``nearest-frame`` (the nearest training view's supervision through the protocol's
query rule; its captions replayed for time-sensitive queries) and ``nearest-frame-masks`` (the best-matching
mask of that view, no query rule)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from methods.registry import MethodSpec
from methods.specs._time_varying import CaptionConfig

REPLAY_CHOICES = ("auto", "on", "off")
"""Values of :attr:`NearestFrameConfig.replay`."""


@dataclass
class NearestViewConfig:
    """How a floor picks the training view it answers from: the one at the least distance
    ``angle + time_weight * steps``, where ``angle`` is the angle (radians) between the two cameras' viewing
    directions and ``steps`` the time difference in training-frame steps (the median gap between training
    times); ties go to the first training view in (time, camera, name) order."""

    time_weight: float = 0.1
    """Radians of viewing angle one training-frame step of time difference counts as (0: nearest in viewing
    direction only; large: nearest in time, the viewing angle breaking ties)."""

    def __post_init__(self) -> None:
        if not self.time_weight >= 0:
            raise ValueError(f"time_weight must be >= 0, got {self.time_weight!r}")


@dataclass
class NearestFrameConfig(NearestViewConfig):
    """Options of :class:`methods.nearest_frame.NearestFrame`. Time-agnostic answers: each level's mask
    features of the nearest training view give their masks' LERF relevance, painted over their pixels
    (0 where no mask is), and the protocol's query rule (smoothing, min-max threshold, majority filter,
    level choice) makes the mask. Time-sensitive answers replay that view's captions: the mean cosine,
    over the time-agnostic answer's mask, between the query and the caption embedding of the tracked object
    under each pixel (NaN where the mask covers no captioned object), through the same text encoder and
    temporal rule as the time-varying heads."""

    captions: CaptionConfig = dataclasses.field(default_factory=CaptionConfig)
    """Object tracks and captions of the training frames (the time-varying heads' captions, cached once
    per scene for all of them)."""
    replay: str = "auto"
    """Caption replay for time-sensitive queries: ``"on"``, ``"off"`` (time-agnostic answers only) or
    ``"auto"``: on wherever the track can caption the scene."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.replay not in REPLAY_CHOICES:
            raise ValueError(f"replay must be one of {REPLAY_CHOICES}, got {self.replay!r}")


@dataclass
class NearestFrameMasksConfig(NearestViewConfig):
    """Options of :class:`methods.nearest_frame.NearestFrameMasks`: ``"canonical"`` matching asks for LERF
    relevance > 0.5 at the protocol's temperature; an unanswered frame's time-sensitive score is undefined
    (NaN)."""

    match_rule: str = "canonical"
    """``"canonical"``: a mask answers only where the query beats every canonical phrase on it (else no
    answer); ``"best"``: always the best-matching mask."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.match_rule not in ("canonical", "best"):
            raise ValueError(f"match_rule must be 'canonical' or 'best', got {self.match_rule!r}")


SPECS = [
    MethodSpec(
        name="nearest-frame",
        description="2D floor: the nearest training view's mask features (by viewing angle and time) through "
                    "the protocol's query rule; time-sensitive queries by replaying that view's captions",
        entry_point="methods.nearest_frame:NearestFrame",
        config=NearestFrameConfig,
        paper="",
        tracks=("oracle", "real"),
        queries=("agnostic", "sensitive"),
        floor=True,
        answer_rule="relevance",
        sensitive_rule="caption",
    ),
    MethodSpec(
        name="nearest-frame-masks",
        description="2D floor: the nearest training view's mask whose feature best matches the query, no query "
                    "rule; time-sensitive score = that mask feature's cosine to the query",
        entry_point="methods.nearest_frame:NearestFrameMasks",
        config=NearestFrameMasksConfig,
        paper="",
        tracks=("oracle", "real"),
        queries=("agnostic", "sensitive"),
        floor=True,
        answer_rule="mask-selection",
        sensitive_rule="mask-selection",
    ),
]
