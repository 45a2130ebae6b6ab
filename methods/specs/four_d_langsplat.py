"""Specs of ``4d-langsplat`` (the paper's method: time-agnostic three-level field + the status field for
time-sensitive queries) and its variant ``4d-langsplat+`` (the benchmark's extensions on)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from methods.registry import MethodSpec
from methods.specs._time_varying import (TimeVaryingExtensions, TimeVaryingMethodConfig,
                                         benchmark_time_varying_extensions)


@dataclass
class FourDLangSplatConfig(TimeVaryingMethodConfig):
    """Options of :class:`methods.four_d_langsplat.FourDLangSplat`: the time-agnostic half (shared with
    ``deformable-clip``, so both methods reuse one cached 4D-GS and field per scene and seed) and the
    status field (``status``: K states per semantically changing Gaussian mixed by an MLP)."""


@dataclass
class FourDLangSplatPlusConfig(FourDLangSplatConfig):
    """``4d-langsplat`` with the benchmark's extensions on (its time-agnostic half is ``deformable-clip+``'s)."""

    extensions: TimeVaryingExtensions = dataclasses.field(default_factory=benchmark_time_varying_extensions)
    """Departures from the paper: caption targets averaged per state, K chosen per scene, states only on
    Gaussians of changing objects, uncovered pixels supervised as "background"."""


PAPER = "Li et al., 4D LangSplat: 4D Language Gaussian Splatting via Multimodal Large Language Models, CVPR 2025"

SPECS = [
    MethodSpec(
        name="4d-langsplat",
        description="4D LangSplat: 4D-GS + three-level language field; time-sensitive queries by the status "
                    "deformable network on object-wise captions",
        entry_point="methods.four_d_langsplat:FourDLangSplat",
        config=FourDLangSplatConfig,
        paper=PAPER,
        tracks=("oracle", "real"),
        queries=("agnostic", "sensitive"),
        answer_rule="relevance",
        sensitive_rule="caption",
    ),
    MethodSpec(
        name="4d-langsplat+",
        description="4d-langsplat with the benchmark's extensions: caption targets averaged per state, K "
                    "chosen per scene, static-caption Gaussians without states, uncovered pixels as background",
        entry_point="methods.four_d_langsplat:FourDLangSplat",
        config=FourDLangSplatPlusConfig,
        tracks=("oracle", "real"),
        queries=("agnostic", "sensitive"),
        variant_of="4d-langsplat",
        answer_rule="relevance",
        sensitive_rule="caption",
    ),
]
