"""Spec of ``deformable-clip``: 4D-GS with the time-agnostic three-level language field."""

from __future__ import annotations

from dataclasses import dataclass

from methods.registry import MethodSpec
from methods.specs._language import LanguageMethodConfig


@dataclass
class DeformableCLIPConfig(LanguageMethodConfig):
    """Options of :class:`methods.deformable_clip.DeformableCLIP` (shared with the other language fields)."""


SPEC = MethodSpec(
    name="deformable-clip",
    description="Deformable CLIP baseline: 4D-GS + time-agnostic three-level language field; "
                "time-sensitive score = mean relevance in the spatial mask",
    entry_point="methods.deformable_clip:DeformableCLIP",
    config=DeformableCLIPConfig,
    paper="baseline defined in Li et al., 4D LangSplat, CVPR 2025",
    tracks=("oracle", "real"),
    queries=("agnostic", "sensitive"),
    time_score="relevance-peak",
)
