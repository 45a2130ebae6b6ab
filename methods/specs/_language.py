"""Options shared by the language-field methods (``langsplat``, ``deformable-clip``, ``4d-langsplat``).

A private module (leading underscore): the registry does not look for a ``SPEC`` here. Imports
nothing heavy, so ``bench4d methods`` lists the methods without loading torch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

AE_SAMPLE_WEIGHTINGS = ("pixels", "masks", "uniform")
"""Values of :attr:`LanguageMethodConfig.ae_sample_weighting`."""


@dataclass
class LanguageMethodConfig:
    """Every constant of geometry, autoencoder, field and query (paper values by default where the
    recipe fixes one; CPU-scale iteration counts, with the paper's in the docstring)."""

    ANSWER_OPTIONS: ClassVar[frozenset[str]] = frozenset({"uncovered_alpha", "decode_chunk", "decode_chunk_cuda"})
    """Fields read only when answering, never when fitting: the runner's fit cache key ignores them
    (they hash as their defaults) and a cached fit answers with the run's values. The query rules
    (threshold, windows, canonical phrases, temporal rule) are not method options at all: they are the
    evaluation protocol's (:mod:`benchmark.core.protocol`), handed to the fitted model when it answers."""

    # --- geometry (fitted once per scene, geometry options and seed; then frozen) ----------------
    static_iterations: int = 1000
    """4D-GS static (3D-GS) stage (protocol: 3 000). The recipe's schedule intervals are scaled to
    the run length (:mod:`methods.gaussians.config`)."""
    deformation_iterations: int = 2000
    """4D-GS deformation stage (protocol: 10 000)."""
    static_model_iterations: Optional[int] = None
    """Iterations of the static 3D-GS of ``langsplat``; ``None`` = static + deformation iterations
    (the same optimisation budget as the 4D-GS)."""
    max_gaussians: int = 360_000
    """Upper bound of the scene-adaptive Gaussian cap (protocol: densification up to 360k)."""
    gaussians_per_foreground_pixel: float = 2.0
    """Gaussian cap = this x mean foreground pixels of a training view (see
    :class:`methods.gaussians.config.GaussianConfig`)."""

    # --- autoencoder D -> latent (one per scene, on the distinct mask features) -------------------
    latent_dim: int = 3
    """Latent channels per level (paper: 3 for CLIP)."""
    ae_hidden_dims: tuple[int, ...] = (256, 128, 64, 32)
    """Encoder widths between D and the latent; the decoder mirrors them (release: 256-128-64-32)."""
    ae_cosine_weight: float = 1.0
    """Weight of the ``1 - cos`` term added to the MSE (release: 1)."""
    ae_learning_rate: float = 3e-4
    """Adam learning rate (release: 1e-4 over its per-mask features)."""
    ae_batch_size: int = 64
    """Minibatch size (release: 64)."""
    ae_epochs: int = 100
    """Epochs over the distinct features (release: 100 epochs over its per-mask features)."""
    ae_min_steps: int = 8000
    """At least this many steps: 100 epochs over a few distinct mask features (the oracle track has
    one per object name) are a few hundred steps, far from the release's millions of pixel samples;
    text embeddings of names differ by a few hundredths of cosine, so the decoder must be precise
    (the reconstruction cosine is reported in the fit's info)."""
    ae_max_steps: int = 10000
    """Cap on autoencoder steps (bounds the cost with many distinct features, e.g. CLIP on SAM masks)."""
    ae_sample_weighting: str = "masks"
    """How often each distinct mask feature is drawn into an autoencoder batch: ``"masks"`` (default: once
    per mask and training image, the release's autoencoder data, LangSplat's ``Autoencoder_dataset`` over
    its per-mask ``*_f.npy`` features), ``"pixels"`` (by the pixel area carrying it) or ``"uniform"``.
    Area weighting under-fits small parts: the protocol ceiling's query on perfect latents through the
    autoencoder loses 84.7 -> 77.8 mIoU on the 7 presets under the release rule with ``"pixels"`` and
    nothing with ``"masks"`` (``reports/ablations/autoencoder-ceiling.md``)."""

    unmasked_text: Optional[str] = "background"
    """Pixels that no mask of a level covers are supervised at that level as one more mask whose
    feature is this text's passage embedding (the run's text encoder / the image-text source's text
    tower). The paper's SAM masks cover (nearly) every pixel, background included; the oracle
    segmenter leaves the surroundings unmasked, and unsupervised Gaussians decode to arbitrary
    features that the min-max threshold then selects. ``None`` = leave them unsupervised (release)."""
    uncovered_alpha: float = 0.5
    """At query time a pixel whose accumulated opacity is below this shows no Gaussian: its feature is
    the ``unmasked_text`` embedding (the feature-space analogue of compositing RGB over a known
    background). Object-centric scenes (D-NeRF) leave most pixels uncovered, and the decoder's output
    for an empty (zero) latent is arbitrary; scenes covered wall to wall are unaffected."""

    # --- language field (per-Gaussian latents of the three levels, geometry frozen) ---------------
    field_iterations: int = 1200
    """Field optimisation steps, one training view each (release: 10 000 on a GPU)."""
    field_learning_rate: float = 1e-2
    """Adam learning rate of the features (release: 2.5e-3 over a 10x longer schedule)."""
    field_loss_weight: float = 0.2
    """Weight of the L1 language loss inside valid masks (protocol: 0.2)."""
    field_init_std: float = 0.0
    """Standard deviation of the initial features (release: zeros)."""

    # --- answering (the query rules themselves are the evaluation protocol's: benchmark.core.protocol) ------
    decode_chunk: int = 2048
    """Pixels decoded at once on the CPU (bounds query memory at any image size; no effect on results).
    Small enough that the decoder's [chunk, 256] temporaries (2 MiB) stay near the cache: decoding the
    3 levels of a 128x170 frame (384-d features; best / median of 4 on an idle 2-core machine) took
    399 / 429 ms at 65 536 pixels a chunk, 287 / 293 at 8 192 and 241 / 256 at 2 048 on one thread,
    250 / 341, 169 / 240 and 152 / 158 ms on two; 1 024 and 512 gained nothing more."""
    decode_chunk_cuda: int = 1 << 20
    """Pixels decoded at once on a CUDA device: fewer, larger matrix products. Measured on an H100 at
    536x960 with 200k Gaussians (``bench4d ablate query-speed --device cuda``): 65 536 gives 46.7 FPS
    with a 1.4 GiB peak, 1 048 576 gives 52.5 FPS with a 4.4 GiB peak; no effect on results."""

    def decode_chunk_for(self, device: "str | object") -> int:
        """:attr:`decode_chunk_cuda` on a CUDA device, else :attr:`decode_chunk`."""
        return self.decode_chunk_cuda if str(device).startswith("cuda") else self.decode_chunk

    # --- engineering ------------------------------------------------------------------------------
    render_backend: str = "auto"
    """Rasterizer backend: ``"auto"`` (gsplat on CUDA when importable, else PyTorch), ``"torch"``, ``"gsplat"``."""
    shared_cache_dir: Optional[str] = None
    """Where fitted geometries and fields are shared between methods and runs; ``None`` = the
    runner's cache folder (the parent of its ``fits`` folder), or no sharing outside the runner."""

    def __post_init__(self) -> None:
        self.ae_hidden_dims = tuple(int(x) for x in self.ae_hidden_dims)
        if self.ae_sample_weighting not in AE_SAMPLE_WEIGHTINGS:
            raise ValueError(f"ae_sample_weighting must be one of {AE_SAMPLE_WEIGHTINGS}, "
                             f"got {self.ae_sample_weighting!r}")
        if self.render_backend not in ("auto", "torch", "gsplat"):
            raise ValueError(f"render_backend must be 'auto', 'torch' or 'gsplat', got {self.render_backend!r}")
        for name in ("static_iterations", "deformation_iterations", "field_iterations", "ae_max_steps", "ae_min_steps"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")
