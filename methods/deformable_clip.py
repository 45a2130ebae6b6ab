"""``deformable-clip``: the paper's Deformable CLIP baseline -- 4D-GS geometry, time-agnostic field.

The three-level language field of :mod:`methods.language_methods` on a deformable 4D-GS (features
do not deform, positions do). Time-sensitive answers use the relevance score (mean relevance inside
the spatial mask), as the paper's baseline does: the field itself cannot express a change of state.
"""

from __future__ import annotations

from .language_methods import LanguageFieldMethod
from .specs.deformable_clip import DeformableCLIPConfig


class DeformableCLIP(LanguageFieldMethod):
    name = "deformable-clip"
    geometry_kind = "4dgs"
    sensitive = "relevance"
    supports = frozenset({"agnostic", "sensitive"})
    config_class = DeformableCLIPConfig
