"""``non-status-field``: the paper's Non-Status Field baseline.

Identical to ``4d-langsplat`` in everything but the time-varying field: the same 4D-GS and
time-agnostic three-level field (shared through the language-field cache), the same captions, caption
autoencoder and time-agnostic caption field, but instead of K states mixed by weights, the latent of
every Gaussian is deformed directly: ``f(x, t) = f_static + MLP(hexplane(x, t))``
(:class:`methods.fields.status.NonStatusField`, via :class:`methods.time_sensitive.NonStatusHead`).
Time-sensitive scores follow the protocol (mean cosine in the spatial mask, NaN when it is empty).
"""

from __future__ import annotations

from typing import ClassVar, Optional

from .language_methods import LanguageFieldMethod, TimeVaryingHead
from .specs.non_status_field import NonStatusFieldConfig
from .time_sensitive import NonStatusHead


class NonStatusFieldMethod(LanguageFieldMethod):
    name = "non-status-field"
    geometry_kind = "4dgs"
    sensitive = None
    time_varying_head: ClassVar[Optional[type[TimeVaryingHead]]] = NonStatusHead
    supports = frozenset({"agnostic", "sensitive"})
    config_class = NonStatusFieldConfig
