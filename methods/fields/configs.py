"""Configs of the fields' parts: feature autoencoder, time-agnostic language field, status field.

Plain dataclasses that import nothing heavy, so the method specs (:mod:`methods.specs`) use them as
option groups without loading torch; the code that reads them is :mod:`.autoencoder`,
:mod:`.language_field` and :mod:`.status`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal, Optional

AE_SAMPLE_WEIGHTINGS = ("pixels", "masks", "uniform")
"""Values of :attr:`MaskAutoencoderConfig.sample_weighting`."""


@dataclass
class AutoencoderConfig:
    """Architecture and training of a feature autoencoder (D -> a few latent channels -> D)."""

    hidden_dims: tuple[int, ...] = (256, 128, 64, 32)
    """Encoder widths between the input and the latent; the decoder mirrors them (release: 256-128-64-32)."""
    latent_dim: int = 3
    """Latent channels carried by each Gaussian (paper: 3 for CLIP, 6 for captions)."""
    cosine_weight: float = 1.0
    """Weight of the ``1 - cos`` term added to the MSE (release: 1)."""
    learning_rate: float = 1e-3
    """Adam learning rate."""
    batch_size: int = 64
    """Minibatch size (release: 64)."""
    epochs: int = 100
    """Passes over the distinct feature vectors (release: 100)."""
    min_steps: int = 0
    """At least this many optimiser steps, however few distinct vectors there are (raises the epochs)."""
    max_steps: Optional[int] = 3000
    """Cap on optimiser steps (``None``: the epochs alone)."""
    normalize_latent: bool = True
    """L2-normalise the latent (release)."""

    def __post_init__(self) -> None:
        self.hidden_dims = tuple(int(x) for x in self.hidden_dims)
        if self.min_steps < 0 or (self.max_steps is not None and self.max_steps < 0):
            raise ValueError("min_steps and max_steps must be >= 0")

    def for_features(self, num_features: int) -> "AutoencoderConfig":
        """This config with :attr:`epochs` raised so that training on ``num_features`` distinct vectors runs
        at least :attr:`min_steps` steps (at most :attr:`max_steps`)."""
        steps_per_epoch = max(1, -(-int(num_features) // self.batch_size))
        wanted = self.min_steps if self.max_steps is None else min(self.min_steps, self.max_steps)
        return dataclasses.replace(self, epochs=max(self.epochs, -(-wanted // steps_per_epoch)))


@dataclass
class MaskAutoencoderConfig(AutoencoderConfig):
    """The time-agnostic field's autoencoder, trained on the distinct mask features of all levels."""

    latent_dim: int = 3
    """Latent channels per level (paper: 3 for CLIP)."""
    learning_rate: float = 3e-4
    """Adam learning rate (release: 1e-4 over its per-mask features)."""
    min_steps: int = 8000
    """At least this many steps: the oracle track's few distinct features need many more than 100 epochs."""
    max_steps: Optional[int] = 10000
    """Cap on steps (bounds the cost with many distinct features, e.g. CLIP on SAM masks)."""
    sample_weighting: str = "masks"
    """How often each distinct feature is drawn: ``"masks"`` (once per mask and training image, the
    release's data), ``"pixels"`` (by pixel area) or ``"uniform"``."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.sample_weighting not in AE_SAMPLE_WEIGHTINGS:
            raise ValueError(f"sample_weighting must be one of {AE_SAMPLE_WEIGHTINGS}, got {self.sample_weighting!r}")


@dataclass
class CaptionAutoencoderConfig(AutoencoderConfig):
    """The time-varying field's autoencoder, trained on the distinct caption embeddings (area-weighted)."""

    latent_dim: int = 6
    """Latent channels (paper: 4096 -> 6)."""
    min_steps: int = 8000
    """At least this many steps: captions of two states differ by a few hundredths of cosine."""
    max_steps: Optional[int] = 10000
    """Cap on steps (batch 64, 100 epochs, release)."""


@dataclass
class LanguageFieldOptions:
    """Training of the time-agnostic language field on the frozen geometry."""

    iterations: int = 1200
    """Optimisation steps, one training view each (release: 10 000 on a GPU)."""
    learning_rate: float = 1e-2
    """Adam learning rate of the features (release: 2.5e-3 over a longer schedule)."""
    loss_weight: float = 0.2
    """Weight of the L1 language loss inside valid masks (protocol: 0.2)."""
    init_std: float = 0.0
    """Standard deviation of the initial features (release: zeros)."""
    cache_view_geometry_mib: float = 512.0
    """Memory for the training views' deformed Gaussians, kept between steps (beyond it: recomputed)."""
    blend_matrix_mib: float = 1024.0
    """Memory (MiB) for every training view's blending matrix (its frozen compositing as a sparse map: the
    same renders, several times faster on the CPU); beyond it or at 0 the rasterizer composites each step."""
    log_every: int = 100
    """Record the loss every this many steps."""

    def __post_init__(self) -> None:
        if self.iterations < 0:
            raise ValueError("iterations must be >= 0")


@dataclass
class LanguageFieldConfig(LanguageFieldOptions):
    """:class:`LanguageFieldOptions` and the field's shape: what :class:`.language_field.LanguageField` reads."""

    num_levels: int = 3
    """Feature levels carried by every Gaussian (SAM small / middle / large: 3)."""
    latent_dim: int = 3
    """Latent channels per level (the autoencoder's)."""
    render_backend: str = "auto"
    """Rasterizer backend (``"auto"``: gsplat on CUDA when importable, else the PyTorch one)."""
    near: float = 0.01
    """Near plane passed to the rasterizer (camera-space depth)."""

    @property
    def channels(self) -> int:
        """Rendered channels: ``num_levels * latent_dim``."""
        return self.num_levels * self.latent_dim


@dataclass
class StatusFieldConfig:
    """Shape and initialisation of the status field (:class:`.status.StatusField`)."""

    num_states: int = 3
    """``K``, states per semantically dynamic Gaussian (paper: 3; Table 5 ablates 2-6)."""
    hidden_dim: int = 64
    """Width of the weight MLP (and of the Non-Status baseline's delta MLP)."""
    weight_mode: Literal["softmax", "linear"] = "softmax"
    """``"softmax"``: the K weights sum to one (paper); ``"linear"``: raw MLP outputs (release)."""
    init_noise: float = 0.1
    """Std of the noise added to the static latent to initialise each state."""

    def __post_init__(self) -> None:
        if self.weight_mode not in ("softmax", "linear"):
            raise ValueError(f"weight_mode must be 'softmax' or 'linear', got {self.weight_mode!r}")
        if self.num_states < 1:
            raise ValueError("num_states must be >= 1")

    def shape(self, num_states: int) -> "StatusFieldConfig":
        """The :class:`StatusFieldConfig` of a field with ``num_states`` states (the scene's K)."""
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(StatusFieldConfig)}
        return StatusFieldConfig(**{**values, "num_states": int(num_states)})


TIME_VARYING_CHOICES = ("auto", "on", "off")
"""Values of :attr:`StatusHeadConfig.fit`."""


@dataclass
class StatusHeadConfig(StatusFieldConfig):
    """The time-varying head: the status field's shape (``num_states`` is the cap of the per-scene K) and
    the training of the caption field and the status (or Non-Status) field."""

    fit: str = "auto"
    """``"on"``, ``"off"`` (time-agnostic answers only) or ``"auto"``: on wherever the track can caption the
    scene (off on the oracle track of a scene without generator truth)."""
    static_iterations: int = 300
    """Steps of the time-agnostic caption field the states start from (release: 1 000 + 10 000 on a GPU)."""
    learning_rate: float = 1e-2
    """Adam learning rate of the per-Gaussian latents (states, fixed vectors, caption field)."""
    iterations: int = 4000
    """Steps of the status stage, one training view each (release: 10 000 on a GPU)."""
    mlp_learning_rate: float = 1e-3
    """Adam learning rate of the weight MLP (and of the Non-Status delta MLP)."""
    loss_weight: float = 0.2
    """Weight of the L1 language loss inside the object masks (protocol: 0.2)."""
    cache_view_mib: float = 512.0
    """Memory for what is cached per training view (blending operators, then HexPlane inputs)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.fit not in TIME_VARYING_CHOICES:
            raise ValueError(f"fit must be one of {TIME_VARYING_CHOICES}, got {self.fit!r}")
        if self.static_iterations < 0 or self.iterations < 0:
            raise ValueError("static_iterations and iterations must be >= 0")
