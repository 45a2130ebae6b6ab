"""Named levels of how far the oracle track's captions fall short of the truth's state names.

On generated scenes the ``template`` captioner (:mod:`methods.captioners.template`) stands in for the
paper's MLLM (Qwen2-VL): one caption per tracked object and training frame, written from the generator's
states of the TRAINING frames only. A level says what goes wrong with those captions:

* every level draws one of the state's paraphrases per frame (the truth lists five per state), as an MLLM
  words one state differently from frame to frame;
* ``wrong_state_rate``: the share of captions that describe another state of the object, drawn
  independently per caption, among the states the object shows in the training frames (a state the
  training frames never show is never described);
* ``lag_fraction``: captions lag the change: the caption at training time ``t`` describes the state at the
  latest training time at or before ``t - lag`` (the first training time when there is none), with
  ``lag = round(lag_fraction * video length)`` time steps.

Lag first, then the wrong state, then the paraphrase. Draws are seeded by (captioner seed, frame name,
object), so the same level and seed give the same captions on any machine.

Levels:

=========  ================  ======================  ==========================================================
level      wrong-state rate  lag                     what it stands for
=========  ================  ======================  ==========================================================
``clean``  0                 0                       the state's own paraphrases (the captions before levels)
``mllm``   0.15              5 % of the video        an MLLM: one caption in about seven names another state,
                                                     and a change is described some frames after it shows
=========  ================  ======================  ==========================================================

The ``mllm`` rates are stated assumptions, not measured Qwen2-VL error rates. A scene declares the level
its captions default to (``caption_noise`` in its truth; the synthetic presets with time queries declare
``mllm``); a method's ``captions.noise`` option names another.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

from .errors import InputError


@dataclass(frozen=True)
class CaptionNoise:
    """One named level of caption noise (module docstring)."""

    name: str
    """Level name (``"clean"``, ``"mllm"``)."""
    wrong_state_rate: float
    """Share of captions describing another state the object shows in the training frames (per caption)."""
    lag_fraction: float
    """Captions describe the state ``round(lag_fraction * video length)`` time steps earlier (the latest
    training time at or before it)."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.wrong_state_rate <= 1.0:
            raise ValueError(f"caption noise {self.name!r}: wrong_state_rate must be in [0, 1]")
        if not 0.0 <= self.lag_fraction < 1.0:
            raise ValueError(f"caption noise {self.name!r}: lag_fraction must be in [0, 1)")

    @property
    def is_clean(self) -> bool:
        return self.wrong_state_rate == 0.0 and self.lag_fraction == 0.0

    def lag_steps(self, num_frames: int) -> int:
        """The lag in time steps for a video of ``num_frames`` frames."""
        return int(round(self.lag_fraction * int(num_frames)))

    def describe(self) -> dict:
        """What a captioner's config records (its caption cache key)."""
        return asdict(self)


CAPTION_NOISE: dict[str, CaptionNoise] = {level.name: level for level in (
    CaptionNoise("clean", wrong_state_rate=0.0, lag_fraction=0.0),
    CaptionNoise("mllm", wrong_state_rate=0.15, lag_fraction=0.05),
)}
"""Every caption noise level, by name."""

DEFAULT_CAPTION_NOISE = "clean"
"""The level of a scene that declares none (scenes generated before levels existed)."""


LAG_SUFFIX = "+lag:"
"""A level name followed by ``+lag:X`` (``mllm+lag:0.1``): that level with its captions lagging ``X`` of the
video more (:func:`with_extra_lag`)."""


def with_extra_lag(level: CaptionNoise, extra: float, *, where=None, field: str = "caption_noise") -> CaptionNoise:
    """``level`` with its lag grown by ``extra`` of the video (the stress suite's ``caption-lag``); 0 returns it
    as it is. An :class:`InputError` where ``extra`` is not finite and >= 0 or the lag reaches the video."""
    extra = float(extra)
    if not math.isfinite(extra) or extra < 0:
        raise InputError(where, field, f"extra caption lag must be a finite share of the video >= 0, got {extra!r}")
    if extra == 0:
        return level
    try:
        return replace(level, name=f"{level.name}{LAG_SUFFIX}{extra:g}", lag_fraction=level.lag_fraction + extra)
    except ValueError as exc:
        raise InputError(where, field, str(exc)) from None


def split_lag(name: str, *, where=None, field: str = "caption_noise") -> tuple[str, float]:
    """(level name, extra lag) of ``name`` (``"mllm+lag:0.1"`` -> ``("mllm", 0.1)``; no suffix: 0)."""
    base, sep, extra = str(name).partition(LAG_SUFFIX)
    if not sep:
        return base, 0.0
    try:
        return base, float(extra)
    except ValueError:
        raise InputError(where, field, f"expected a number after {LAG_SUFFIX!r} in {name!r}") from None


def caption_noise(name: str, *, where=None, field: str = "caption_noise") -> CaptionNoise:
    """The level called ``name``, with an optional extra lag (:data:`LAG_SUFFIX`); an :class:`InputError` naming
    ``where`` and ``field`` and the valid levels otherwise."""
    base, extra = split_lag(name, where=where, field=field)
    if base not in CAPTION_NOISE:
        raise InputError(where, field, f"unknown caption noise level {base!r} (valid: {', '.join(CAPTION_NOISE)})")
    return with_extra_lag(CAPTION_NOISE[base], extra, where=where, field=field)
