"""``4d-langsplat``: 4D LangSplat (Li et al., CVPR 2025).

Time-agnostic half: the three-level language field of :mod:`methods.language_methods` on a 4D-GS
(the same fit as ``deformable-clip``: one shared geometry and field per scene and seed).

Time-sensitive half: the status deformable network comes in its own issue. It plugs in by setting
:attr:`FourDLangSplat.time_varying_head` to a :class:`methods.language_methods.TimeVaryingHead`
subclass (fitted on ``FitContext.shared``: frozen 4D-GS with ``geometry.hexplane_features(t)``, the
field, the autoencoder) and adding ``"sensitive"`` to :attr:`supports` and to the spec's ``queries``.
Until then the method answers time-agnostic queries only (it never falls back to the relevance
score, which would pass the baseline's answers off as the method's).
"""

from __future__ import annotations

from typing import ClassVar, Optional

from .language_methods import LanguageFieldMethod, TimeVaryingHead
from .specs.four_d_langsplat import FourDLangSplatConfig


class FourDLangSplat(LanguageFieldMethod):
    name = "4d-langsplat"
    geometry_kind = "4dgs"
    sensitive = None
    time_varying_head: ClassVar[Optional[type[TimeVaryingHead]]] = None
    supports = frozenset({"agnostic"})
    config_class = FourDLangSplatConfig
