"""Spec of ``non-status-field``: the paper's Non-Status Field baseline (Table 5 / Sec. 4.3)."""

from __future__ import annotations

from dataclasses import dataclass

from methods.registry import MethodSpec
from methods.specs._time_varying import TimeVaryingMethodConfig


@dataclass
class NonStatusFieldConfig(TimeVaryingMethodConfig):
    """Options of :class:`methods.non_status_field.NonStatusFieldMethod`: the time-agnostic half shared
    with ``deformable-clip`` / ``4d-langsplat`` (one cached 4D-GS and field per scene and seed), and
    the time-varying head's (the states' options - ``status.num_states``, ``status.weight_mode``,
    ``status.init_noise``, ``extensions.choose_states``, ``extensions.skip_static_semantics`` ... - are
    unused: every Gaussian's latent is deformed directly)."""


SPEC = MethodSpec(
    name="non-status-field",
    description="Non-Status Field baseline: 4D-GS + time-agnostic field; time-sensitive score from a "
                "caption field deformed directly, f + MLP(hexplane(x, t))",
    entry_point="methods.non_status_field:NonStatusFieldMethod",
    config=NonStatusFieldConfig,
    paper="baseline defined in Li et al., 4D LangSplat, CVPR 2025",
    tracks=("oracle", "real"),
    queries=("agnostic", "sensitive"),
)
