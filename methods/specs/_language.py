"""Options shared by the language-field methods (``langsplat``, ``deformable-clip``, ``4d-langsplat``).

A private module (leading underscore): the registry does not look for a ``SPEC`` here. Imports
nothing heavy, so ``bench4d methods`` lists the methods without loading torch.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

CANONICAL_PHRASES: tuple[str, ...] = ("object", "things", "stuff", "texture")
"""LERF's canonical negative phrases, as used by LangSplat and 4D LangSplat."""


AE_SAMPLE_WEIGHTINGS = ("pixels", "masks", "uniform")
"""Values of :attr:`LanguageMethodConfig.ae_sample_weighting`."""


@dataclass
class LanguageMethodConfig:
    """Every constant of geometry, autoencoder, field and query (paper values by default where the
    recipe fixes one; CPU-scale iteration counts, with the paper's in the docstring)."""

    ANSWER_OPTIONS: ClassVar[frozenset[str]] = frozenset({
        "uncovered_alpha", "canonical_phrases", "temperature", "smoothing_kernel", "threshold",
        "threshold_variant", "majority_kernel", "majority_fraction", "kernel_scaling", "decode_chunk",
        "decode_chunk_cuda",
        "sensitive_mask"})
    """Fields read only when answering, never when fitting: the runner's fit cache key ignores them
    (they hash as their defaults) and a cached fit answers with the run's values, so comparing query
    rules (``--set threshold_variant=release``) reuses the fit."""

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
    ae_sample_weighting: str = "pixels"
    """How often each distinct mask feature is drawn into an autoencoder batch: ``"pixels"`` (default: by
    the pixel area carrying it), ``"masks"`` (once per mask and training image: the release's autoencoder
    data, LangSplat's ``Autoencoder_dataset`` over the per-mask ``*_f.npy`` features) or ``"uniform"``.
    A trade measured in session 20. Area weighting under-fits small parts: on the 7 presets (oracle track,
    seeds 0-1, ``bench4d ablate autoencoder``) its reconstruction cosine is 0.989-0.997 (cook-spinach
    1.0000) and the query on perfect latents through it scores 56.5 / 77.8 mIoU (paper / release
    threshold) against 58.6 / 84.7 on perfect features; drawn per mask every name comes back (cosine
    1.0000, 58.6 / 84.7). The fitted field does not follow under the paper threshold: on americano the
    large parts' codes lie closer together (area-weighted distance to the nearest other code 0.558 vs
    0.599), so the rendered field's errors move more pixels across names (with noise of 0.2 on the codes,
    0.77 vs 0.89 of the pixels still decode nearest their own name). 4d-langsplat, seed 0, the same
    geometry bit for bit (``results/ablations/ae-masks/``): americano 46.8 -> 43.8, chickchicken
    26.5 -> 26.8, espresso 50.6 -> 51.0, keyboard 53.1 -> 51.5 mIoU (mean -0.9); under the release
    threshold 60.6 -> 59.7, 51.1 -> 58.6, 59.1 -> 68.6, 63.4 -> 71.3 (mean +6.0). So ``"masks"`` goes with
    ``threshold_variant="release"``; the default stays with the default threshold."""

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

    # --- time-agnostic query (shared/docs/protocol.md) -------------------------------------------
    canonical_phrases: tuple[str, ...] = CANONICAL_PHRASES
    """Negative phrases of the LERF relevance (paper and release: object, things, stuff, texture)."""
    temperature: float = 10.0
    """Scale ``s`` of ``exp(s q.f)`` in the relevance (paper and release: 10)."""
    smoothing_kernel: int = 29
    """Average-pooling window mixed into the relevance map (paper and release: 29)."""
    threshold: float = 0.4
    """Threshold on the min-max rescaled smoothed relevance (paper and release: 0.4)."""
    threshold_variant: str = "paper"
    """``"paper"``: rescaled > threshold; ``"release"``: ``clip(2 x - 1, 0, 1) > threshold``."""
    majority_kernel: int = 7
    """Majority filter window on the binary mask (release: 7)."""
    majority_fraction: float = 0.5
    """A pixel stays when more than this fraction of its window is set (release: 0.5)."""
    kernel_scaling: str = "resolution"
    """``"resolution"`` (default): the smoothing and majority windows scale with the rendered image from
    their sizes at the paper's 960x536 (:attr:`methods.fields.relevance.RelevanceConfig.kernel_scaling`);
    ``"fixed"``: the pixel sizes as given (the release's code)."""
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

    # --- time-sensitive answers of the relevance-score baselines ----------------------------------
    sensitive_mask: str = "unfiltered"
    """Mask inside which the relevance is averaged for a time-sensitive score: ``"unfiltered"`` (the
    release uses the mask before the majority filter) or ``"filtered"``."""

    # --- engineering ------------------------------------------------------------------------------
    render_backend: str = "auto"
    """Rasterizer backend: ``"auto"`` (gsplat on CUDA when importable, else PyTorch), ``"torch"``, ``"gsplat"``."""
    shared_cache_dir: Optional[str] = None
    """Where fitted geometries and fields are shared between methods and runs; ``None`` = the
    runner's cache folder (the parent of its ``fits`` folder), or no sharing outside the runner."""

    def __post_init__(self) -> None:
        self.canonical_phrases = tuple(self.canonical_phrases)
        self.ae_hidden_dims = tuple(int(x) for x in self.ae_hidden_dims)
        if self.threshold_variant not in ("paper", "release"):
            raise ValueError(f"threshold_variant must be 'paper' or 'release', got {self.threshold_variant!r}")
        if self.sensitive_mask not in ("unfiltered", "filtered"):
            raise ValueError(f"sensitive_mask must be 'unfiltered' or 'filtered', got {self.sensitive_mask!r}")
        if self.ae_sample_weighting not in AE_SAMPLE_WEIGHTINGS:
            raise ValueError(f"ae_sample_weighting must be one of {AE_SAMPLE_WEIGHTINGS}, "
                             f"got {self.ae_sample_weighting!r}")
        if self.render_backend not in ("auto", "torch", "gsplat"):
            raise ValueError(f"render_backend must be 'auto', 'torch' or 'gsplat', got {self.render_backend!r}")
        for name in ("static_iterations", "deformation_iterations", "field_iterations", "ae_max_steps", "ae_min_steps"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")
        if self.smoothing_kernel % 2 == 0 or self.majority_kernel % 2 == 0:
            raise ValueError("smoothing_kernel and majority_kernel must be odd (centred windows)")
        if self.kernel_scaling not in ("resolution", "fixed"):
            raise ValueError(f"kernel_scaling must be 'resolution' or 'fixed', got {self.kernel_scaling!r}")
