"""Option groups of the methods on the shared frozen 4D-GS (``langsplat``, ``deformable-clip``,
``4d-langsplat``, ``non-status-field``, ``feature-3dgs``, ``gaussian-grouping``).

A private module (leading underscore): the registry does not look for a ``SPEC`` here. Imports
nothing heavy, so ``bench4d methods`` lists the methods without loading torch. Measurements behind
the defaults: ``reports/config-notes.md``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar, Optional

from methods.fields.configs import (AE_SAMPLE_WEIGHTINGS, LanguageFieldOptions, MaskAutoencoderConfig)

__all__ = ["AE_SAMPLE_WEIGHTINGS", "BENCHMARK_UNMASKED_TEXT", "RENDER_BACKENDS", "GeometryConfig", "AnswerConfig",
           "LanguageExtensions", "LanguageMethodConfig", "benchmark_extensions"]

RENDER_BACKENDS = ("auto", "torch", "gsplat")
"""Values of :attr:`GeometryConfig.render_backend`."""


@dataclass
class GeometryConfig:
    """The Gaussian geometry, fitted once per scene, geometry options and seed, then frozen (the Gaussian
    core's recipe constants are :class:`methods.gaussians.config.ReconConfig`'s)."""

    static_iterations: int = 1000
    """4D-GS static (3D-GS) stage (protocol: 3 000)."""
    deformation_iterations: int = 2000
    """4D-GS deformation stage (protocol: 10 000)."""
    static_model_iterations: Optional[int] = None
    """Iterations of ``langsplat``'s static 3D-GS (``None``: static + deformation iterations)."""
    max_gaussians: int = 360_000
    """Upper bound of the scene-adaptive Gaussian cap (protocol: densification up to 360k)."""
    gaussians_per_foreground_pixel: float = 4.0
    """Gaussian cap = this x mean foreground pixels of a training view; 4: the cheapest budget at the plateau on
    every preset at 128 px (reports/capacity)."""
    hexplane_resolution: int = 32
    """Base resolution of the deformation HexPlane's spatial axes (each multi-resolution level multiplies it);
    32: the cheapest at the plateau on every preset at 128 px (reports/capacity; protocol: 64)."""
    render_backend: str = "auto"
    """Rasterizer: ``"auto"`` (gsplat on CUDA when importable, else PyTorch), ``"torch"`` or ``"gsplat"``."""

    def __post_init__(self) -> None:
        if self.render_backend not in RENDER_BACKENDS:
            raise ValueError(f"render_backend must be one of {RENDER_BACKENDS}, got {self.render_backend!r}")
        for name in ("static_iterations", "deformation_iterations"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")
        if self.hexplane_resolution < 2:
            raise ValueError(f"hexplane_resolution must be >= 2, got {self.hexplane_resolution}")


@dataclass
class AnswerConfig:
    """Options read only when answering, never when fitting: a fit is shared by runs that differ in them
    only, and a cached fit answers with the run's values. The query rules themselves are the evaluation
    protocol's (:mod:`benchmark.core.protocol`)."""

    uncovered_alpha: float = 0.5
    """A pixel whose accumulated opacity is below this shows no Gaussian and gets the
    ``extensions.unmasked_text`` feature (not in the paper; unused while that extension is off)."""
    decode_chunk: int = 2048
    """Pixels decoded at once on the CPU (bounds memory; no effect on results)."""
    decode_chunk_cuda: int = 1 << 20
    """Pixels decoded at once on a CUDA device (no effect on results)."""
    decode_table: int = 0
    """On the CPU, decode 3-d latents through a table of this many samples per axis, interpolated per
    pixel, its points decoded as latents reach them (0: decode every pixel;
    :class:`methods.fields.language_field.DecodeTable`)."""
    decode_table_cuda: int = 257
    """The same on a CUDA device, the whole table decoded once per query (about twice the FPS; on fitted models
    99.996 % of answer pixels as decoding every pixel in float32). 0: decode every pixel."""
    decode_tf32: bool = True
    """On a CUDA device, decode with TensorFloat-32 matrix products (inputs rounded to 10 mantissa bits,
    float32 sums), the status field's score too: relevance moves in its third digit; the CPU decodes in float32."""

    def decode_chunk_for(self, device: "str | object") -> int:
        """:attr:`decode_chunk_cuda` on a CUDA device, else :attr:`decode_chunk`."""
        return self.decode_chunk_cuda if str(device).startswith("cuda") else self.decode_chunk

    def decode_table_for(self, device: "str | object") -> int:
        """:attr:`decode_table_cuda` on a CUDA device, else :attr:`decode_table`."""
        return self.decode_table_cuda if str(device).startswith("cuda") else self.decode_table


@dataclass
class LanguageExtensions:
    """Options that depart from the papers' methods. Their defaults are the papers' (every extension off);
    the registered variants (``langsplat+``, ...) turn the benchmark's on (:func:`benchmark_extensions`)."""

    unmasked_text: Optional[str] = None
    """Pixels no mask of a level covers are supervised with this text's embedding (``None``: left
    unsupervised, as the release; the variants: ``"background"``)."""

    PAPER: ClassVar[dict[str, Any]] = {"unmasked_text": None}
    """Extension -> its value in the paper's method (an extension is on where the config's value differs)."""

    def enabled(self) -> dict[str, Any]:
        """The extensions this config turns on: option name -> value, where it is not the paper's."""
        return {name: getattr(self, name) for name, paper in self.PAPER.items() if getattr(self, name) != paper}


BENCHMARK_UNMASKED_TEXT = "background"
"""The text the benchmark's variants supervise uncovered pixels with: the oracle segmenter leaves the
background out of every mask, where the paper's SAM masks cover it."""


def benchmark_extensions() -> LanguageExtensions:
    """The extensions of the variants of the time-agnostic language methods (``langsplat+``,
    ``deformable-clip+``, ``feature-3dgs+``, ``gaussian-grouping+``)."""
    return LanguageExtensions(unmasked_text=BENCHMARK_UNMASKED_TEXT)


@dataclass
class LanguageMethodConfig:
    """The three-level language field on a frozen geometry (paper values by default where the recipe fixes
    one; CPU-scale iteration counts; no extension on)."""

    geometry: GeometryConfig = dataclasses.field(default_factory=GeometryConfig)
    """The Gaussian geometry."""
    autoencoder: MaskAutoencoderConfig = dataclasses.field(default_factory=MaskAutoencoderConfig)
    """Autoencoder D -> latent, one per scene, on the distinct mask features."""
    field: LanguageFieldOptions = dataclasses.field(default_factory=LanguageFieldOptions)
    """Per-Gaussian latents of the three levels, geometry frozen."""
    answer: AnswerConfig = dataclasses.field(default_factory=AnswerConfig)
    """Options read only when answering."""
    extensions: LanguageExtensions = dataclasses.field(default_factory=LanguageExtensions)
    """Departures from the paper."""
    shared_cache_dir: Optional[str] = None
    """Where fitted geometries and fields are shared between methods and runs (``None``: the runner's
    cache folder)."""
