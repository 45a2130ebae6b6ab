"""Spec of ``4d-langsplat``: time-agnostic three-level field + the status field for time-sensitive queries."""

from __future__ import annotations

from dataclasses import dataclass

from methods.registry import MethodSpec
from methods.specs._time_varying import TimeVaryingMethodConfig


@dataclass
class FourDLangSplatConfig(TimeVaryingMethodConfig):
    """Options of :class:`methods.four_d_langsplat.FourDLangSplat`: the time-agnostic half (shared with
    ``deformable-clip``, so both methods reuse one cached 4D-GS and field per scene and seed) and the
    status field (``status``: K states per semantically changing Gaussian mixed by an MLP)."""


SPEC = MethodSpec(
    name="4d-langsplat",
    description="4D LangSplat: 4D-GS + three-level language field; time-sensitive queries by the status "
                "deformable network on object-wise captions",
    entry_point="methods.four_d_langsplat:FourDLangSplat",
    config=FourDLangSplatConfig,
    paper="Li et al., 4D LangSplat: 4D Language Gaussian Splatting via Multimodal Large Language Models, CVPR 2025",
    tracks=("oracle", "real"),
    queries=("agnostic", "sensitive"),
)
