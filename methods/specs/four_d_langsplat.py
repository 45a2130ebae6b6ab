"""Spec of ``4d-langsplat`` (time-agnostic half; the status field adds the time-sensitive half)."""

from __future__ import annotations

from dataclasses import dataclass

from methods.registry import MethodSpec
from methods.specs._language import LanguageMethodConfig


@dataclass
class FourDLangSplatConfig(LanguageMethodConfig):
    """Options of :class:`methods.four_d_langsplat.FourDLangSplat` (time-agnostic half: shared with
    ``deformable-clip``, so both methods reuse one cached 4D-GS and field per scene and seed)."""


SPEC = MethodSpec(
    name="4d-langsplat",
    description="4D LangSplat: 4D-GS + three-level language field (time-agnostic half; the status "
                "field for time-sensitive queries plugs in later)",
    entry_point="methods.four_d_langsplat:FourDLangSplat",
    config=FourDLangSplatConfig,
    paper="Li et al., 4D LangSplat: 4D Language Gaussian Splatting via Multimodal Large Language Models, CVPR 2025",
    tracks=("oracle", "real"),
    queries=("agnostic",),
)
