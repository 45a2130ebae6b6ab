"""Option groups of the time-varying semantic field (``4d-langsplat``'s status field, ``non-status-field``).

A private module (leading underscore): the registry looks for no ``SPEC`` here. It imports nothing
heavy, so method specs use these groups without loading torch. The code that reads them is
:mod:`methods.fields.time_varying`. Measurements behind the defaults: ``reports/config-notes.md``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar, Optional

from benchmark.core.caption_noise import CAPTION_NOISE, split_lag, with_extra_lag
from methods.fields.configs import CaptionAutoencoderConfig, StatusHeadConfig

from ._language import BENCHMARK_UNMASKED_TEXT, LanguageExtensions, LanguageMethodConfig

__all__ = ["CAPTIONER_CHOICES", "TRACK_CHOICES", "CaptionConfig", "TimeVaryingExtensions", "TimeVaryingMethodConfig",
           "benchmark_time_varying_extensions"]

CAPTIONER_CHOICES = ("auto", "template", "qwen2-vl", "file", "states")
"""Values of :attr:`CaptionConfig.captioner`."""
TRACK_CHOICES = ("auto", "truth", "segments", "file", "alpha")
"""Values of :attr:`CaptionConfig.object_tracks`."""


@dataclass
class CaptionConfig:
    """Object tracks and their captions on the training frames."""

    captioner: str = "auto"
    """``"template"`` (oracle: a generated scene's states), ``"states"`` (oracle: the annotation's states
    at training frames), ``"qwen2-vl"`` or ``"file"``; ``"auto"``: states where given, else template
    (oracle), qwen2-vl (real)."""
    file: Optional[str] = None
    """JSON captions (and masks) for ``captioner="file"`` / ``object_tracks="file"``."""
    qwen_model: Optional[str] = None
    """Qwen2-VL folder or hub id (``None``: ``$BENCH4D_QWEN2VL`` or Qwen/Qwen2-VL-7B-Instruct)."""
    object_tracks: str = "auto"
    """``"truth"`` or ``"alpha"`` (oracle: the training alphas' object), ``"segments"`` (the segmenter's
    large-level ids) or ``"file"``; ``"auto"``: alpha for the states captioner, else truth (oracle); file or
    segments (real)."""
    min_track_frames: int = 3
    """``object_tracks="segments"``: keep segment ids visible in at least this many training frames."""
    min_track_area: float = 0.001
    """``object_tracks="segments"``: a segment id is visible in a frame where it covers this share of the frame."""
    visual_prompt: str = "blur+gray+contour"
    """Visual prompt of the captioner (paper: all three cues)."""
    text_prompt: str = "video+image"
    """Text prompt of the captioner: ``"none"``, ``"video"`` or ``"video+image"`` (release)."""
    seed: int = 0
    """Seed of the template captioner's paraphrase draw (fixed: every method and seed sees the same captions)."""
    noise: str = "scene"
    """Template captions' noise: a level of :mod:`benchmark.core.caption_noise` (``clean``, ``mllm``) or
    ``"scene"`` (the scene's own: ``mllm`` on presets with time queries), optionally lagging more
    (``scene+lag:0.1``)."""
    text_encoder: Optional[str] = None
    """Text encoder of the captions and the time-sensitive queries (paper: ``e5-mistral``); ``None``: the
    run's text encoder (the image-text source's text tower on the real track)."""

    def __post_init__(self) -> None:
        if self.captioner not in CAPTIONER_CHOICES:
            raise ValueError(f"captioner must be one of {CAPTIONER_CHOICES}, got {self.captioner!r}")
        if self.object_tracks not in TRACK_CHOICES:
            raise ValueError(f"object_tracks must be one of {TRACK_CHOICES}, got {self.object_tracks!r}")
        base, extra = split_lag(self.noise, field="captions.noise")
        if base != "scene" and base not in CAPTION_NOISE:
            raise ValueError(f"noise must be 'scene' or one of {tuple(CAPTION_NOISE)} (+lag:X optional), "
                             f"got {self.noise!r}")
        with_extra_lag(CAPTION_NOISE.get(base, CAPTION_NOISE["clean"]), extra, field="captions.noise")  # refused now
        if self.min_track_frames < 1 or not 0 <= self.min_track_area < 1:
            raise ValueError("min_track_frames must be >= 1 and min_track_area in [0, 1)")


@dataclass
class TimeVaryingExtensions(LanguageExtensions):
    """Options that depart from the paper's method: the time-agnostic field's, the caption targets', the
    choice of K and of the Gaussians that carry states, extra loss terms. Their defaults are the paper's (every
    extension off); ``4d-langsplat+`` and ``non-status-field+`` turn the benchmark's on
    (:func:`benchmark_time_varying_extensions`). ``semantic_change_tolerance``, ``dynamic_weight_share`` and
    ``min_state_run`` are parameters of extensions (read only where one is on); ``blend_operators`` is a faster
    training path to the same loss, on in every config."""

    caption_window: int = 0
    """Average each object's caption embeddings over the training frames within this many time steps
    before they become targets (0: off, as the paper; needs ``caption_segments=false``)."""
    caption_segments: bool = False
    """Targets are each object's caption embeddings averaged per state (change points, segments of at least
    ``min_state_run`` steps); ``False``: each frame's own caption, as the paper."""
    choose_states: bool = False
    """Choose K per scene: the most caption states of any object, capped by ``status.num_states``
    (``False``: ``status.num_states`` as is, as the paper)."""
    skip_static_semantics: bool = False
    """Gaussians of objects whose captions never change carry one latent, not K states (``False``: all
    carry K, as the release)."""
    semantic_change_tolerance: float = 0.02
    """An object's semantics never change when every caption embedding lies within this cosine distance
    of their mean direction (read by ``choose_states`` and ``skip_static_semantics``; not used with
    ``caption_segments``)."""
    dynamic_weight_share: float = 0.2
    """A Gaussian carries states when at least this share of its blending weight over the training views
    falls on changing objects (read by ``skip_static_semantics``)."""
    min_state_run: float = 4.0
    """A caption state lasts at least this many consecutive frames on average (how ``choose_states`` counts
    states, and the shortest segment of ``caption_segments``)."""
    time_tv_weight: float = 0.0
    """Weight of a temporal total-variation term between the field at a view's time and an adjacent one
    (status and Non-Status fields; 0: off, as the paper)."""
    entropy_weight: float = 0.0
    """Weight of the mean entropy of the status weights (softmax mode; 0: off, as the paper)."""
    blend_operators: bool = True
    """Train by each view's recorded sparse blending operator instead of rasterizing every step (the same
    loss to float rounding: no departure from the method)."""

    PAPER: ClassVar[dict[str, Any]] = {**LanguageExtensions.PAPER, "caption_window": 0, "caption_segments": False,
                                       "choose_states": False, "skip_static_semantics": False,
                                       "time_tv_weight": 0.0, "entropy_weight": 0.0}
    """Extension -> its value in the paper's method."""

    def __post_init__(self) -> None:
        if self.time_tv_weight < 0 or self.entropy_weight < 0:
            raise ValueError("time_tv_weight and entropy_weight must be >= 0")
        if not 0 <= self.dynamic_weight_share <= 1:
            raise ValueError("dynamic_weight_share must be in [0, 1]")
        if self.semantic_change_tolerance < 0:
            raise ValueError("semantic_change_tolerance must be >= 0")
        if self.caption_window < 0:
            raise ValueError("caption_window must be >= 0 (time steps)")
        if self.caption_segments and self.caption_window:
            raise ValueError("caption_window and caption_segments are alternatives: set "
                             "extensions.caption_segments=false to average over a window")


@dataclass
class TimeVaryingMethodConfig(LanguageMethodConfig):
    """The time-agnostic half (shared with ``deformable-clip``: one cached 4D-GS and field per scene and
    seed) and the time-varying head fitted on it from object-wise captions."""

    extensions: TimeVaryingExtensions = dataclasses.field(default_factory=TimeVaryingExtensions)
    """Departures from the paper."""
    captions: CaptionConfig = dataclasses.field(default_factory=CaptionConfig)
    """Object tracks and captions."""
    caption_autoencoder: CaptionAutoencoderConfig = dataclasses.field(default_factory=CaptionAutoencoderConfig)
    """Autoencoder of the caption embeddings."""
    status: StatusHeadConfig = dataclasses.field(default_factory=StatusHeadConfig)
    """The time-varying head and its training."""


def benchmark_time_varying_extensions() -> TimeVaryingExtensions:
    """The extensions of ``4d-langsplat+`` and ``non-status-field+``: caption targets averaged per state, K
    chosen per scene, states only on Gaussians of changing objects, uncovered pixels supervised as
    ``"background"``."""
    return TimeVaryingExtensions(unmasked_text=BENCHMARK_UNMASKED_TEXT, caption_segments=True, choose_states=True,
                                 skip_static_semantics=True)
