"""Specs of ``langsplat`` (static 3D-GS with the three-level language field, time ignored) and its variant
``langsplat+`` (uncovered pixels supervised as background)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from methods.registry import MethodSpec
from methods.specs._language import LanguageExtensions, LanguageMethodConfig, benchmark_extensions


@dataclass
class LangSplatConfig(LanguageMethodConfig):
    """Options of :class:`methods.langsplat.LangSplat` (all shared with the other language fields)."""


@dataclass
class LangSplatPlusConfig(LangSplatConfig):
    """``langsplat`` with the benchmark's extension on."""

    extensions: LanguageExtensions = dataclasses.field(default_factory=benchmark_extensions)
    """Departures from the paper: uncovered pixels supervised as "background"."""


SPECS = [
    MethodSpec(
        name="langsplat",
        description="LangSplat: static 3D-GS + three-level language field (one shared geometry, 9 channels); "
                    "time-sensitive score = mean relevance in the spatial mask",
        entry_point="methods.langsplat:LangSplat",
        config=LangSplatConfig,
        paper="Qin et al., LangSplat: 3D Language Gaussian Splatting, CVPR 2024",
        tracks=("oracle", "real"),
        queries=("agnostic", "sensitive"),
        answer_rule="relevance",
        sensitive_rule="relevance",
    ),
    MethodSpec(
        name="langsplat+",
        description="langsplat with the benchmark's extension: pixels no mask covers supervised as background",
        entry_point="methods.langsplat:LangSplat",
        config=LangSplatPlusConfig,
        tracks=("oracle", "real"),
        queries=("agnostic", "sensitive"),
        variant_of="langsplat",
        answer_rule="relevance",
        sensitive_rule="relevance",
    ),
]
