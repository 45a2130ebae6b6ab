"""Specs of ``feature-3dgs``: Feature 3DGS's distilled feature field on the shared 4D-GS (time-agnostic only)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

from methods.registry import MethodSpec
from methods.specs._language import AnswerConfig, GeometryConfig, LanguageExtensions, benchmark_extensions

FEATURE_LEVEL_NAMES: tuple[str, str, str] = ("small", "middle", "large")
"""Names of the values 0, 1, 2 of :attr:`FeatureFieldConfig.level` (the SAM levels, in the order of
:data:`methods.supervision.base.LEVELS`; repeated here so the spec imports nothing heavy)."""


@dataclass
class FeatureFieldConfig:
    """The distilled per-Gaussian feature field and its 1x1 decoder (original values: Zhou et al., CVPR 2024)."""

    dim: int = 16
    """Channels of the per-Gaussian feature, decoded to the encoder's dimension by a learned 1x1 convolution
    (original's speed-up module: D / 4)."""
    level: int = 1
    """SAM level whose mask features form the dense target: 0 small, 1 middle, 2 large (one level, as the
    original distils one feature map per image)."""
    iterations: int = 1200
    """Optimisation steps, one training view each (original: 30 000, jointly with RGB, on a GPU)."""
    learning_rate: float = 1e-2
    """Adam learning rate of the per-Gaussian features (original: 1e-3 over a 25x longer schedule)."""
    decoder_learning_rate: float = 1e-3
    """Adam learning rate of the 1x1 decoder (original: 1e-4 over a 25x longer schedule)."""

    def __post_init__(self) -> None:
        if self.dim < 1:
            raise ValueError(f"dim must be >= 1, got {self.dim}")
        if self.level not in range(len(FEATURE_LEVEL_NAMES)):
            raise ValueError(f"level must be 0 (small), 1 (middle) or 2 (large), got {self.level!r}")
        if self.iterations < 0:
            raise ValueError(f"iterations must be >= 0, got {self.iterations}")
        for name in ("learning_rate", "decoder_learning_rate"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")


@dataclass
class Feature3DGSConfig:
    """Options of :class:`methods.feature_3dgs.Feature3DGS`: the geometry of the language fields (so the
    4D-GS is the cached one of ``deformable-clip`` / ``4d-langsplat``) and the feature field's."""

    geometry: GeometryConfig = dataclasses.field(default_factory=GeometryConfig)
    """The Gaussian geometry (shared with the language fields)."""
    feature: FeatureFieldConfig = dataclasses.field(default_factory=FeatureFieldConfig)
    """The distilled feature field."""
    answer: AnswerConfig = dataclasses.field(default_factory=AnswerConfig)
    """Options read only when answering."""
    extensions: LanguageExtensions = dataclasses.field(default_factory=LanguageExtensions)
    """Departures from the paper."""
    shared_cache_dir: Optional[str] = None
    """Where fitted geometries and fields are shared between methods and runs (``None``: the runner's
    cache folder)."""


@dataclass
class Feature3DGSPlusConfig(Feature3DGSConfig):
    """``feature-3dgs`` with the benchmark's extension on."""

    extensions: LanguageExtensions = dataclasses.field(default_factory=benchmark_extensions)
    """Departures from the paper: uncovered pixels supervised as "background"."""


SPECS = [
    MethodSpec(
        name="feature-3dgs",
        description="Feature 3DGS: per-Gaussian features on the shared frozen 4D-GS + 1x1 decoder, distilled "
                    "from one SAM level's mask features; time-agnostic queries only",
        entry_point="methods.feature_3dgs:Feature3DGS",
        config=Feature3DGSConfig,
        paper="Zhou et al., Feature 3DGS: Supercharging 3D Gaussian Splatting to Enable Distilled Feature Fields, "
              "CVPR 2024 (time-agnostic baseline of Li et al., 4D LangSplat, CVPR 2025)",
        tracks=("oracle", "real"),
        queries=("agnostic",),
        answer_rule="relevance",
    ),
    MethodSpec(
        name="feature-3dgs+",
        description="feature-3dgs with the benchmark's extension: pixels no mask covers supervised as background",
        entry_point="methods.feature_3dgs:Feature3DGS",
        config=Feature3DGSPlusConfig,
        tracks=("oracle", "real"),
        queries=("agnostic",),
        variant_of="feature-3dgs",
        answer_rule="relevance",
    ),
]
