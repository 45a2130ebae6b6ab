"""Spec of ``langsplat``: static 3D-GS with the three-level language field, time ignored."""

from __future__ import annotations

from dataclasses import dataclass

from methods.registry import MethodSpec
from methods.specs._language import LanguageMethodConfig


@dataclass
class LangSplatConfig(LanguageMethodConfig):
    """Options of :class:`methods.langsplat.LangSplat` (all shared with the other language fields)."""


SPEC = MethodSpec(
    name="langsplat",
    description="LangSplat: static 3D-GS + three-level language field (one shared geometry, 9 channels); "
                "time-sensitive score = mean relevance in the spatial mask",
    entry_point="methods.langsplat:LangSplat",
    config=LangSplatConfig,
    paper="Qin et al., LangSplat: 3D Language Gaussian Splatting, CVPR 2024",
    tracks=("oracle", "real"),
    queries=("agnostic", "sensitive"),
    time_score="relevance-peak",
)
