"""Spec of ``gaussian-grouping``: identity encodings on the shared 4D-GS, one open-vocabulary feature per identity."""

from __future__ import annotations

from dataclasses import dataclass

from methods.registry import MethodSpec
from methods.specs._language import LanguageMethodConfig

OVERLAP_ASSOCIATION = ("auto", "on", "off")
"""Values of :attr:`GaussianGroupingConfig.overlap_association`."""


@dataclass
class GaussianGroupingConfig(LanguageMethodConfig):
    """Options of :class:`methods.gaussian_grouping.GaussianGrouping`. The geometry options are the
    other language methods' (one cached 4D-GS per scene and seed serves them all); the autoencoder and
    language-field options are unused. Original values (Ye et al., ECCV 2024, release) in docstrings."""

    identity_level: int = 2
    """SAM level whose masks are the identities: 0 small, 1 middle, 2 large (default: whole objects, as
    the original's SAM "everything" masks)."""
    identity_dim: int = 16
    """Channels of each Gaussian's identity encoding (original: 16)."""
    identity_iterations: int = 1500
    """Optimisation steps, one training view each (original: 30 000, jointly with RGB)."""
    identity_learning_rate: float = 5e-2
    """Adam learning rate of the identity encodings (original: 2.5e-3 over 30 000 steps; 20x for the
    20x shorter schedule)."""
    classifier_learning_rate: float = 1e-2
    """Adam learning rate of the linear identity classifier (original: 5e-4; 20x, as the encodings')."""
    identity_reg_weight: float = 2.0
    """Weight of the 3D regulariser, whose KL is divided by the number of identities as in the original
    (original: 2)."""
    identity_reg_k: int = 5
    """Nearest Gaussians each sampled Gaussian's identity distribution is compared to, itself included
    as in the original (original: 5)."""
    identity_reg_sample_size: int = 1000
    """Gaussians sampled per regulariser step (original: 1 000)."""
    identity_reg_interval: int = 2
    """The regulariser is added every this many steps (original: 2)."""
    overlap_association: str = "auto"
    """Link masks of consecutive training frames of one camera by overlap
    (:class:`methods.supervision.association.TemporalAssociator`): ``"auto"`` = on the real track only
    (the cached supervision's per-frame mask indices are not associated over time; the oracle track's
    features already name each object), ``"on"`` or ``"off"``."""
    association_min_iou: float = 0.3
    """IoU above which a mask continues an identity of the previous frame (the segmenters' 0.3)."""

    def __post_init__(self) -> None:
        LanguageMethodConfig.__post_init__(self)
        if self.identity_level not in (0, 1, 2):
            raise ValueError(f"identity_level must be 0, 1 or 2, got {self.identity_level!r}")
        for name in ("identity_dim", "identity_reg_k", "identity_reg_sample_size", "identity_reg_interval"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        if self.identity_iterations < 0:
            raise ValueError(f"identity_iterations must be >= 0, got {self.identity_iterations!r}")
        for name in ("identity_learning_rate", "classifier_learning_rate", "identity_reg_weight"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if self.overlap_association not in OVERLAP_ASSOCIATION:
            raise ValueError(f"overlap_association must be one of {OVERLAP_ASSOCIATION}, "
                             f"got {self.overlap_association!r}")
        if not 0.0 <= self.association_min_iou < 1.0:
            raise ValueError(f"association_min_iou must be in [0, 1), got {self.association_min_iou!r}")


SPEC = MethodSpec(
    name="gaussian-grouping",
    description="Gaussian Grouping on 4D-GS: identity encodings of temporally associated large masks, "
                "each identity answering with its mean mask feature (time-agnostic only)",
    entry_point="methods.gaussian_grouping:GaussianGrouping",
    config=GaussianGroupingConfig,
    paper="Ye et al., Gaussian Grouping: Segment and Edit Anything in 3D Scenes, ECCV 2024 "
          "(4D adaptation as in Li et al., 4D LangSplat, CVPR 2025)",
    tracks=("oracle", "real"),
    queries=("agnostic",),
    code=("methods.language_methods", "methods.fields.language_field", "methods.fields.relevance",
          "methods.supervision.association", "methods.gaussians"),
)
