"""Specs of ``gaussian-grouping``: identity encodings on the shared 4D-GS, one open-vocabulary feature per identity."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

from methods.registry import MethodSpec
from methods.specs._language import AnswerConfig, GeometryConfig, LanguageExtensions, benchmark_extensions

OVERLAP_ASSOCIATION = ("auto", "on", "off")
"""Values of :attr:`OverlapAssociationConfig.overlap`."""


@dataclass
class IdentityConfig:
    """Identity encodings, their classifier and the 3D regulariser (original values: Ye et al., ECCV 2024,
    release)."""

    level: int = 2
    """SAM level whose masks are the identities: 0 small, 1 middle, 2 large (whole objects, as the
    original's SAM "everything" masks)."""
    dim: int = 16
    """Channels of each Gaussian's identity encoding (original: 16)."""
    iterations: int = 1500
    """Optimisation steps, one training view each (original: 30 000, jointly with RGB)."""
    learning_rate: float = 5e-2
    """Adam learning rate of the identity encodings (original: 2.5e-3 over a 20x longer schedule)."""
    classifier_learning_rate: float = 1e-2
    """Adam learning rate of the linear identity classifier (original: 5e-4 over a 20x longer schedule)."""
    reg_weight: float = 2.0
    """Weight of the 3D regulariser, its KL divided by the number of identities (original: 2)."""
    reg_k: int = 5
    """Nearest Gaussians each sampled Gaussian is compared to, itself included (original: 5)."""
    reg_sample_size: int = 1000
    """Gaussians sampled per regulariser step (original: 1 000)."""
    reg_interval: int = 2
    """The regulariser is added every this many steps (original: 2)."""

    def __post_init__(self) -> None:
        if self.level not in (0, 1, 2):
            raise ValueError(f"level must be 0, 1 or 2, got {self.level!r}")
        for name in ("dim", "reg_k", "reg_sample_size", "reg_interval"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        if self.iterations < 0:
            raise ValueError(f"iterations must be >= 0, got {self.iterations!r}")
        for name in ("learning_rate", "classifier_learning_rate", "reg_weight"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")


@dataclass
class OverlapAssociationConfig:
    """How masks of consecutive training frames become one identity
    (:class:`methods.supervision.association.TemporalAssociator`)."""

    overlap: str = "auto"
    """Link masks of consecutive frames of one camera by overlap: ``"on"``, ``"off"`` or ``"auto"`` (on the
    real track only: the oracle track's features already name each object)."""
    min_iou: float = 0.3
    """IoU above which a mask continues an identity of the previous frame (the segmenters' 0.3)."""

    def __post_init__(self) -> None:
        if self.overlap not in OVERLAP_ASSOCIATION:
            raise ValueError(f"overlap must be one of {OVERLAP_ASSOCIATION}, got {self.overlap!r}")
        if not 0.0 <= self.min_iou < 1.0:
            raise ValueError(f"min_iou must be in [0, 1), got {self.min_iou!r}")


@dataclass
class GaussianGroupingConfig:
    """Options of :class:`methods.gaussian_grouping.GaussianGrouping`. The geometry is the language methods'
    (one cached 4D-GS per scene and seed serves them all); its answers decode nothing, so
    ``answer.decode_chunk*`` are unused."""

    geometry: GeometryConfig = dataclasses.field(default_factory=GeometryConfig)
    """The Gaussian geometry (shared with the language fields)."""
    identity: IdentityConfig = dataclasses.field(default_factory=IdentityConfig)
    """Identity encodings and their training."""
    association: OverlapAssociationConfig = dataclasses.field(default_factory=OverlapAssociationConfig)
    """Temporal association of the masks."""
    answer: AnswerConfig = dataclasses.field(default_factory=AnswerConfig)
    """Options read only when answering."""
    extensions: LanguageExtensions = dataclasses.field(default_factory=LanguageExtensions)
    """Departures from the paper."""
    shared_cache_dir: Optional[str] = None
    """Where fitted geometries and fields are shared between methods and runs (``None``: the runner's
    cache folder)."""


@dataclass
class GaussianGroupingPlusConfig(GaussianGroupingConfig):
    """``gaussian-grouping`` with the benchmark's extension on."""

    extensions: LanguageExtensions = dataclasses.field(default_factory=benchmark_extensions)
    """Departures from the paper: uncovered pixels supervised as "background"."""


SPECS = [
    MethodSpec(
        name="gaussian-grouping",
        description="Gaussian Grouping on 4D-GS: identity encodings of temporally associated large masks, "
                    "each identity answering with its mean mask feature (time-agnostic only)",
        entry_point="methods.gaussian_grouping:GaussianGrouping",
        config=GaussianGroupingConfig,
        paper="Ye et al., Gaussian Grouping: Segment and Edit Anything in 3D Scenes, ECCV 2024 "
              "(4D adaptation as in Li et al., 4D LangSplat, CVPR 2025)",
        tracks=("oracle", "real"),
        queries=("agnostic",),
        answer_rule="relevance",
    ),
    MethodSpec(
        name="gaussian-grouping+",
        description="gaussian-grouping with the benchmark's extension: pixels no mask covers supervised as background",
        entry_point="methods.gaussian_grouping:GaussianGrouping",
        config=GaussianGroupingPlusConfig,
        tracks=("oracle", "real"),
        queries=("agnostic",),
        variant_of="gaussian-grouping",
        answer_rule="relevance",
    ),
]
