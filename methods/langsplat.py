"""``langsplat``: LangSplat (Qin et al., CVPR 2024) on a dynamic scene -- a static 3D-GS, time ignored.

The three-level language field of :mod:`methods.language_methods` on a static 3D Gaussian model
fitted to all training frames at once: moving content is smeared over its positions. Time-sensitive
answers use the relevance score (mean relevance inside the spatial mask), which cannot change with
time except through the camera.
"""

from __future__ import annotations

from .language_methods import LanguageFieldMethod
from .specs.langsplat import LangSplatConfig


class LangSplat(LanguageFieldMethod):
    name = "langsplat"
    geometry_kind = "3dgs"
    sensitive = "relevance"
    supports = frozenset({"agnostic", "sensitive"})
    config_class = LangSplatConfig
