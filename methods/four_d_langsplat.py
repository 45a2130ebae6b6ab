"""``4d-langsplat``: 4D LangSplat (Li et al., CVPR 2025).

Time-agnostic half: the three-level language field of :mod:`methods.language_methods` on a 4D-GS
(the same fit as ``deformable-clip``: one shared geometry and field per scene and seed).

Time-sensitive half: the status deformable network (:class:`methods.time_sensitive.StatusHead`,
:mod:`methods.fields.time_varying`), fitted on the same frozen 4D-GS from object-wise captions:
K states per semantically changing Gaussian mixed by an MLP on the frozen HexPlane feature at (x, t).
A time-sensitive score is the mean cosine, inside the time-agnostic answer's mask, between the
decoded time-varying feature and the query embedding (NaN on an empty mask).
"""

from __future__ import annotations

from typing import ClassVar, Optional

from .language_methods import LanguageFieldMethod, TimeVaryingHead
from .specs.four_d_langsplat import FourDLangSplatConfig
from .time_sensitive import StatusHead


class FourDLangSplat(LanguageFieldMethod):
    name = "4d-langsplat"
    geometry_kind = "4dgs"
    sensitive = None
    time_varying_head: ClassVar[Optional[type[TimeVaryingHead]]] = StatusHead
    supports = frozenset({"agnostic", "sensitive"})
    config_class = FourDLangSplatConfig
