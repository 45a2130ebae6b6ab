"""Specs of ``non-status-field`` (the paper's Non-Status Field baseline, Table 5 / Sec. 4.3) and its variant
``non-status-field+`` (the benchmark's extensions on)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from methods.registry import MethodSpec
from methods.specs._time_varying import (TimeVaryingExtensions, TimeVaryingMethodConfig,
                                         benchmark_time_varying_extensions)


@dataclass
class NonStatusFieldConfig(TimeVaryingMethodConfig):
    """Options of :class:`methods.non_status_field.NonStatusFieldMethod`: the time-agnostic half shared
    with ``deformable-clip`` / ``4d-langsplat`` (one cached 4D-GS and field per scene and seed), and
    the time-varying head's (the states' options - ``status.num_states``, ``status.weight_mode``,
    ``status.init_noise``, ``extensions.choose_states``, ``extensions.skip_static_semantics`` ... - are
    unused: every Gaussian's latent is deformed directly)."""


@dataclass
class NonStatusFieldPlusConfig(NonStatusFieldConfig):
    """``non-status-field`` with the extensions of ``4d-langsplat+`` (its caption targets and time-agnostic
    half are ``4d-langsplat+``'s)."""

    extensions: TimeVaryingExtensions = dataclasses.field(default_factory=benchmark_time_varying_extensions)
    """Departures from the paper: caption targets averaged per state, uncovered pixels supervised as
    "background" (the states' extensions are unused here)."""


SPECS = [
    MethodSpec(
        name="non-status-field",
        description="Non-Status Field baseline: 4D-GS + time-agnostic field; time-sensitive score from a "
                    "caption field deformed directly, f + MLP(hexplane(x, t))",
        entry_point="methods.non_status_field:NonStatusFieldMethod",
        config=NonStatusFieldConfig,
        paper="baseline defined in Li et al., 4D LangSplat, CVPR 2025",
        tracks=("oracle", "real"),
        queries=("agnostic", "sensitive"),
        answer_rule="relevance",
        sensitive_rule="caption",
    ),
    MethodSpec(
        name="non-status-field+",
        description="non-status-field with the extensions of 4d-langsplat+: caption targets averaged per "
                    "state, uncovered pixels as background",
        entry_point="methods.non_status_field:NonStatusFieldMethod",
        config=NonStatusFieldPlusConfig,
        tracks=("oracle", "real"),
        queries=("agnostic", "sensitive"),
        variant_of="non-status-field",
        answer_rule="relevance",
        sensitive_rule="caption",
    ),
]
