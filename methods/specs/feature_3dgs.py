"""Spec of ``feature-3dgs``: Feature 3DGS's distilled feature field on the shared 4D-GS (time-agnostic only)."""

from __future__ import annotations

from dataclasses import dataclass

from methods.registry import MethodSpec
from methods.specs._language import LanguageMethodConfig

FEATURE_LEVEL_NAMES: tuple[str, str, str] = ("small", "middle", "large")
"""Names of the values 0, 1, 2 of :attr:`Feature3DGSConfig.feature_level` (the SAM levels, in the
order of :data:`methods.supervision.base.LEVELS`; repeated here so the spec imports nothing heavy)."""


@dataclass
class Feature3DGSConfig(LanguageMethodConfig):
    """Options of :class:`methods.feature_3dgs.Feature3DGS`: geometry and query options shared with the
    language fields (so the 4D-GS is the cached one of ``deformable-clip`` / ``4d-langsplat``), plus
    the feature field's. The autoencoder and ``field_*`` options are unused."""

    feature_dim: int = 16
    """Channels of the per-Gaussian feature, decoded to the encoder's dimension by a learned 1x1
    convolution (the original's speed-up module renders D / 4: 128 channels for 512-d LSeg)."""
    feature_level: int = 1
    """SAM level whose mask features form the dense target: 0 small, 1 middle (default), 2 large. One
    level, as the original distils one feature map per image; the middle lies between parts and wholes."""
    feature_iterations: int = 1200
    """Optimisation steps, one training view each (original: 30 000, jointly with RGB, on a GPU)."""
    feature_learning_rate: float = 1e-2
    """Adam learning rate of the per-Gaussian features (original: 1e-3 over its 25x longer schedule)."""
    decoder_learning_rate: float = 1e-3
    """Adam learning rate of the 1x1 decoder (original: 1e-4 over its 25x longer schedule)."""

    def __post_init__(self) -> None:
        LanguageMethodConfig.__post_init__(self)
        if self.feature_dim < 1:
            raise ValueError(f"feature_dim must be >= 1, got {self.feature_dim}")
        if self.feature_level not in range(len(FEATURE_LEVEL_NAMES)):
            raise ValueError(f"feature_level must be 0 (small), 1 (middle) or 2 (large), got {self.feature_level!r}")
        if self.feature_iterations < 0:
            raise ValueError(f"feature_iterations must be >= 0, got {self.feature_iterations}")
        for name in ("feature_learning_rate", "decoder_learning_rate"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")


SPEC = MethodSpec(
    name="feature-3dgs",
    description="Feature 3DGS: per-Gaussian features on the shared frozen 4D-GS + 1x1 decoder, distilled "
                "from one SAM level's mask features; time-agnostic queries only",
    entry_point="methods.feature_3dgs:Feature3DGS",
    config=Feature3DGSConfig,
    paper="Zhou et al., Feature 3DGS: Supercharging 3D Gaussian Splatting to Enable Distilled Feature Fields, "
          "CVPR 2024 (time-agnostic baseline of Li et al., 4D LangSplat, CVPR 2025)",
    tracks=("oracle", "real"),
    queries=("agnostic",),
    code=("methods.language_methods", "methods.fields.language_field", "methods.fields.relevance",
          "methods.gaussians"),
)
