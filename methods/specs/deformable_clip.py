"""Specs of ``deformable-clip`` (4D-GS with the time-agnostic three-level language field) and its variant
``deformable-clip+`` (uncovered pixels supervised as background)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from methods.registry import MethodSpec
from methods.specs._language import LanguageExtensions, LanguageMethodConfig, benchmark_extensions


@dataclass
class DeformableCLIPConfig(LanguageMethodConfig):
    """Options of :class:`methods.deformable_clip.DeformableCLIP` (shared with the other language fields)."""


@dataclass
class DeformableCLIPPlusConfig(DeformableCLIPConfig):
    """``deformable-clip`` with the benchmark's extension on (the time-agnostic half of ``4d-langsplat+``)."""

    extensions: LanguageExtensions = dataclasses.field(default_factory=benchmark_extensions)
    """Departures from the paper: uncovered pixels supervised as "background"."""


SPECS = [
    MethodSpec(
        name="deformable-clip",
        description="Deformable CLIP baseline: 4D-GS + time-agnostic three-level language field; "
                    "time-sensitive score = mean relevance in the spatial mask",
        entry_point="methods.deformable_clip:DeformableCLIP",
        config=DeformableCLIPConfig,
        paper="baseline defined in Li et al., 4D LangSplat, CVPR 2025",
        tracks=("oracle", "real"),
        queries=("agnostic", "sensitive"),
        answer_rule="relevance",
        sensitive_rule="relevance",
    ),
    MethodSpec(
        name="deformable-clip+",
        description="deformable-clip with the benchmark's extension: pixels no mask covers supervised as "
                    "background",
        entry_point="methods.deformable_clip:DeformableCLIP",
        config=DeformableCLIPPlusConfig,
        tracks=("oracle", "real"),
        queries=("agnostic", "sensitive"),
        variant_of="deformable-clip",
        answer_rule="relevance",
        sensitive_rule="relevance",
    ),
]
