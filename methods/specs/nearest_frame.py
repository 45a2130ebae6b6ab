"""Spec of ``nearest-frame``: the 2D floor every 3D/4D method must clear."""

from __future__ import annotations

from dataclasses import dataclass

from methods.registry import MethodSpec


@dataclass
class NearestFrameConfig:
    """Options of :class:`methods.nearest_frame.NearestFrame`. Time distance is counted in training-frame
    steps (the median gap between training times), camera distance as centre distance over the scene's
    half-diagonal plus ``1 - cos`` of the angle between viewing directions; ``"canonical"`` matching asks
    for LERF relevance > 0.5 at the protocol's temperature, and an unanswered frame's time-sensitive score
    is undefined (NaN)."""

    camera_weight: float = 1.0
    """Weight of camera distance against time distance when picking the training frame (0: nearest in
    time only)."""
    match_rule: str = "canonical"
    """``"canonical"``: a mask answers only where the query beats every canonical phrase on it (else no
    answer); ``"best"``: always the best-matching mask."""

    def __post_init__(self) -> None:
        if self.match_rule not in ("canonical", "best"):
            raise ValueError(f"match_rule must be 'canonical' or 'best', got {self.match_rule!r}")
        if self.camera_weight < 0:
            raise ValueError("camera_weight must be >= 0")


SPEC = MethodSpec(
    name="nearest-frame",
    description="2D floor: copy the supervision of the training frame nearest in time and camera; "
                "pick the mask whose feature best matches the query",
    entry_point="methods.nearest_frame:NearestFrame",
    config=NearestFrameConfig,
    paper="",
    tracks=("oracle", "real"),
    queries=("agnostic", "sensitive"),
    floor=True,
)
