"""Configuration of 3D-GS / 4D-GS reconstruction: every recipe constant is a named, documented field.

Paper values are the defaults (3D-GS: Kerbl et al., SIGGRAPH 2023; 4D-GS: Wu et al., CVPR 2024, as used
by 4D LangSplat). Where the public release differs, the release value is named in the field's docstring.

Schedule scaling
----------------
The recipes are defined on long GPU runs (3D-GS: 30 000 iterations; 4D LangSplat: 3 000 static +
10 000 deformation iterations). Small CPU scenes are trained for far fewer iterations, so every
*interval* of the recipe (densification window and period, opacity-reset period, SH-degree period,
learning-rate decay length) is written here in **paper iterations** and multiplied by the stage's
``schedule_scale`` (:class:`Schedule`):

* static 3D-GS reference of n iterations: ``n / 30 000``;
* 4D-GS static stage: ``static_iterations / 3 000``; deformation stage:
  ``deformation_iterations / 10 000``.

So a 3 000-iteration 3D-GS run densifies from iteration 50 to 1 500 every 10 iterations and resets
opacity every 300 iterations: the *shape* of the paper's schedule over the run is preserved. A scaled
interval is at least one iteration. ``ReconConfig.schedule_scale`` overrides the derived scales.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional


@dataclass
class GaussianConfig:
    """3D-GS model and optimisation recipe (the static reconstruction, and the static stage of 4D-GS)."""

    # --- model ---------------------------------------------------------------------------------
    sh_degree: int = 3
    """Maximum spherical-harmonics degree of the view-dependent colour (paper: 3)."""
    init_opacity: float = 0.1
    """Opacity of every Gaussian at initialisation (paper: 0.1)."""
    random_init_points: int = 100_000
    """Random initial Gaussians when the scene has no point cloud (paper: 100 000 inside the scene
    bounds for synthetic scenes). Always capped by ``random_init_cap_fraction`` of the Gaussian cap."""
    random_init_cap_fraction: float = 0.1
    """Random initialisation uses at most this fraction of the scene's Gaussian cap, leaving room for
    densification to put Gaussians where the images need them (a CPU-scale choice; the paper has no cap).
    Measured on split-cookie at 128 px, 1 000 iterations: 0.1 gives +1 dB test PSNR over 0.5 at equal
    CPU time, and a much cheaper start (fewer overlapping random blobs). On a tiny object toy scene 0.5
    fits faster: the best value depends on the scene; this one suits the benchmark's scenes."""
    init_knn: int = 3
    """Initial scale = RMS distance to this many nearest neighbours (paper release: 3)."""

    # --- model size (scene-adaptive cap) ---------------------------------------------------------
    gaussians_per_foreground_pixel: float = 1.0
    """Gaussian cap = this x mean number of foreground pixels per training view, so the model grows with
    what the images can constrain (128x170 room scene: 21 760; D-NeRF lego at 200 px: 10 259; jumping
    jacks: 3 195), never a constant. One per pixel is a CPU-scale choice (2 per pixel roughly doubles the
    per-step rasterisation cost of the room scenes). Foreground comes from the scene's
    alpha masks, else from pixels that differ from the known background, else the whole image."""
    foreground_threshold: float = 0.02
    """A pixel is foreground when some channel differs from the known background by more than this."""
    min_gaussians: int = 500
    """Lower bound of the cap (tiny images still need enough Gaussians to cover a shape)."""
    max_gaussians: int = 360_000
    """Upper bound of the cap: 4D LangSplat densifies up to 360k Gaussians (protocol)."""
    gradual_cap: bool = True
    """Let the allowed count grow linearly from the stage's start count to the cap over the
    densification window (a budget schedule in the spirit of Taming 3DGS, Mallick et al. 2024), rather
    than allowing the whole cap at once. Densification grows the count exponentially, so an immediate cap
    is reached within a few events, by the first coarse Gaussians, and nothing can be refined later;
    with the schedule every event refines the highest-gradient Gaussians of the moment."""

    # --- learning rates (paper) ----------------------------------------------------------------
    position_lr_init: float = 1.6e-4
    """Initial position learning rate, multiplied by the scene extent (paper: 1.6e-4)."""
    position_lr_final: float = 1.6e-6
    """Final position learning rate x extent after exponential decay (paper: 1.6e-6)."""
    position_lr_delay_mult: float = 0.01
    """Delay multiplier of the position schedule (paper: 0.01; with zero delay steps it has no effect)."""
    position_lr_max_steps: int = 30_000
    """Length of the position learning-rate decay, paper iterations (paper: 30 000)."""
    feature_lr: float = 2.5e-3
    """Learning rate of the SH degree-0 (base colour) coefficients (paper: 2.5e-3)."""
    feature_rest_lr_divisor: float = 20.0
    """Higher SH bands use ``feature_lr / feature_rest_lr_divisor`` (paper release: 20)."""
    opacity_lr: float = 5e-2
    """Learning rate of opacity logits (paper: 0.05; later 3D-GS releases use 0.025)."""
    scaling_lr: float = 5e-3
    """Learning rate of log-scales (paper: 5e-3)."""
    rotation_lr: float = 1e-3
    """Learning rate of the quaternions (paper: 1e-3)."""
    adam_eps: float = 1e-15
    """Adam epsilon of the Gaussian parameters (paper release: 1e-15)."""

    # --- loss ----------------------------------------------------------------------------------
    lambda_dssim: float = 0.2
    """Loss = (1 - lambda) L1 + lambda (1 - SSIM) (paper: 0.2)."""
    ssim_window: int = 11
    """Gaussian window of the training SSIM (paper release: 11, sigma 1.5)."""
    ssim_sigma: float = 1.5
    """Standard deviation of the SSIM window in pixels."""

    # --- schedule (paper iterations, scaled by the run's schedule_scale) -------------------------
    paper_iterations: int = 30_000
    """Length of the paper's 3D-GS run; a run of n iterations has schedule_scale n / 30 000."""
    sh_degree_interval: int = 1000
    """Raise the active SH degree by one every this many paper iterations (paper: 1000)."""
    densify_from_iter: int = 500
    """First densification, paper iterations (paper: 500)."""
    densify_until_iter: int = 15_000
    """No densification after this, paper iterations (paper: 15 000)."""
    densification_interval: int = 100
    """Densify and prune every this many paper iterations (paper: 100)."""
    opacity_reset_interval: int = 3000
    """Reset all opacities to ``opacity_reset_value`` every this many paper iterations (paper: 3000)."""
    min_opacity_reset_gap: int = 500
    """Iterations (of this run, not scaled) at least between two opacity resets. Recovering from a reset
    takes an absolute number of Adam steps (|logit(0.01)| / opacity_lr ~ 90 at best), which a scaled
    interval of a short run (100 iterations in a 1 000-iteration run) does not leave; the paper leaves
    3 000. Short runs therefore get fewer resets, never denser ones."""

    # --- densification and pruning (paper) -----------------------------------------------------
    densify_grad_threshold: float = 2e-4
    """Densify Gaussians whose mean view-space positional gradient (NDC units) exceeds this (paper: 0.0002)."""
    percent_dense: float = 0.01
    """Gaussians larger than this fraction of the scene extent are split, smaller ones cloned (paper: 0.01)."""
    split_count: int = 2
    """A split replaces one Gaussian with this many samples drawn from it (paper: 2)."""
    split_scale_divisor: float = 1.6
    """Split children get scale / this (paper: 0.8 x split_count = 1.6)."""
    min_opacity: float = 0.005
    """Prune Gaussians less opaque than this (paper: 0.005)."""
    opacity_reset_value: float = 0.01
    """Opacities are clamped to at most this at an opacity reset (paper: 0.01)."""
    max_screen_px: Optional[float] = 20.0
    """Prune Gaussians whose screen radius exceeded this many pixels since the last densification, once
    the first opacity reset has happened (paper: 20 px, absolute). The 3D-GS release compares against
    radii it has just reset to zero, so there the check never fires; ``None`` reproduces that."""
    max_world_fraction: float = 0.1
    """Prune Gaussians whose largest scale exceeds this fraction of the scene extent (paper: 0.1)."""
    extent_margin: float = 1.1
    """Scene extent = this x largest camera distance from the cameras' centroid (paper: 1.1)."""

    # --- misc ----------------------------------------------------------------------------------
    near: float = 0.01
    """Near plane passed to the rasterizer (camera-space depth)."""


@dataclass
class HexPlaneConfig:
    """4D-GS HexPlane: six multi-resolution feature planes over (x, y, z, t)."""

    spatial_resolution: int = 64
    """Base resolution of the spatial axes (protocol: HexPlane 64^3 x T)."""
    time_resolution: Optional[int] = None
    """Resolution of the time axis (the 'timebase'); ``None`` = half the scene's number of time steps,
    at least 2 (the 4D-GS release's advice: 'half length of dynamic frames'; D-NeRF config: 25)."""
    output_dim: int = 16
    """Features per plane and resolution (protocol / 4D LangSplat: 16; 4D-GS D-NeRF config: 32)."""
    multires: tuple[int, ...] = (1, 2)
    """Spatial resolution multipliers; features of all levels are concatenated (4D-GS D-NeRF: [1, 2])."""
    spatial_init_low: float = 0.1
    """Spatial planes start uniform in [low, high] (release: 0.1)."""
    spatial_init_high: float = 0.5
    """Upper end of the spatial planes' initial values (release: 0.5)."""
    time_init_value: float = 1.0
    """Time planes start at this constant, so the product over planes is time-independent (release: 1)."""
    bounds_margin: float = 0.1
    """The plane box is the static Gaussians' bounding box (robust percentiles) widened by this fraction
    of its size on each side (the release uses the initial point cloud's box)."""
    bounds_percentile: float = 0.5
    """Percentile (and 100 - it) of the static Gaussians' positions used for the plane box."""
    motion_cell_share: float = 0.75
    """Share of each spatial axis's cells given to the *motion box* (0 = off: cells spread evenly over the
    plane box, as the release). Not in the release. The plane box spans every static Gaussian, and in a
    scene with surroundings that is the room: 6-9 m on the synthetic presets against a subject of 0.3-0.5 m,
    so a 64-cell plane had cells of about 10 cm and could not tell a spinach leaf from the pan under it.
    The motion box is where the static stage leaves the training images unexplained (see
    ``motion_residual``); each axis is mapped piecewise-linearly so that at least this share of its cells
    covers the motion box and the rest the remainder of the plane box, so nothing the box held before is
    lost, only coarser. When the motion box already spans that share of an axis the mapping is uniform
    (D-NeRF: the object is the scene). Measured on cook-spinach, 128 px, 3000 iterations, seed 0: a hard
    box from the 25th-75th percentiles gave 30.23 vs 29.18 dB (moving parts 18.66 vs 16.33 dB)."""
    motion_residual: float = 0.1
    """A rendered pixel of the static stage counts as unexplained when its mean absolute RGB error exceeds
    this (about 25 of 255 levels; the static stage's median pixel error on the presets is 0.02-0.03, its
    moving parts are ghosts at 0.2-0.6)."""
    motion_views: int = 64
    """Training views (evenly spaced over the training frames) rendered to find the motion box."""
    motion_percentile: float = 2.0
    """Percentile (and 100 - it) of the unexplained pixels' back-projected points taken as the motion box,
    which is then widened by ``bounds_margin`` as the plane box is."""
    motion_min_pixels: int = 64
    """Fewer unexplained pixels (with a rendered surface, alpha > 0.5) than this: no motion box, uniform cells."""

    @property
    def feature_dim(self) -> int:
        """Length of the concatenated multi-resolution feature."""
        return self.output_dim * len(self.multires)


@dataclass
class DeformationConfig:
    """4D-GS deformation stage: HexPlane + MLP heads, learning rates, temporal regularisers."""

    hexplane: HexPlaneConfig = field(default_factory=HexPlaneConfig)
    """The spatio-temporal feature planes."""
    net_width: int = 64
    """Hidden width of the deformation MLP (4D-GS D-NeRF config: 64, kept here for CPU cost; HyperNeRF: 128)."""
    net_depth: int = 0
    """Extra hidden layers of the shared trunk after its input layer (4D-GS D-NeRF: 0, kept for CPU cost;
    HyperNeRF: 1)."""
    deform_position: bool = True
    """Predict position offsets (release: on)."""
    deform_scale: bool = True
    """Predict log-scale offsets (release: on)."""
    deform_rotation: bool = True
    """Predict quaternion offsets, added to the raw quaternion (release: on)."""
    deform_color: bool = False
    """Also predict an RGB offset of each Gaussian's base colour (added to the view-dependent colour, its
    head's last layer zero-initialised so the deformation stage starts from the static colours). Not in
    4D-GS (off by default = the recipe): appearance that changes over time -- a liquid darkening,
    chocolate melting, content appearing -- is outside a position / scale / rotation deformation, which
    fits it with floaters or not at all. On the tests' darkening toy (8 views per time) it gains 8 dB; on
    the monocular presets it does not help (128 px, 3000 iterations, seed 0, with / without: americano 27.32
    / 27.24 dB, torchocolate 28.00 / 28.48, espresso 30.72 / 30.61, split-cookie 27.46 / 27.43;
    reports/recon/*-deform-color; with a 10x lower colour learning rate americano 27.19, torchocolate 28.39):
    with one view per time a colour offset also fits each view's residual."""
    zero_init_heads: bool = False
    """Initialise the heads' last layers to zero, so the deformation stage starts exactly at the static
    stage's result. Off by default, as the release (Xavier init: a small random initial deformation):
    zero heads pass no gradient to the HexPlane until they have grown, and learn motion markedly slower
    in short runs."""

    # --- learning rates (4D-GS release defaults, used by its HyperNeRF config; all x scene extent) --
    deformation_lr_init: float = 1.6e-4
    """MLP learning rate x extent at the start of the deformation stage (release: 1.6e-4)."""
    deformation_lr_final: float = 1.6e-5
    """MLP learning rate x extent at the end (release default / HyperNeRF: 1.6e-5; D-NeRF config: 1.6e-6,
    which in short runs decays before the motion is learned)."""
    deformation_lr_delay_mult: float = 0.01
    """Delay multiplier of the MLP schedule (release: 0.01)."""
    grid_lr_init: float = 1.6e-3
    """HexPlane learning rate x extent at the start (release: 1.6e-3)."""
    grid_lr_final: float = 1.6e-4
    """HexPlane learning rate x extent at the end (release default / HyperNeRF: 1.6e-4; D-NeRF: 1.6e-5)."""
    color_lr_init: float = 1.6e-2
    """Learning rate of the colour head's output layer at the start (``deform_color``; RGB units, so not
    scaled by the extent). Not in the release. On the darkening toy of the tests the MLP's 1.6e-4 x extent
    leaves the colour offsets at a fifth of the change after 750 iterations."""
    color_lr_final: float = 1.6e-3
    """... and at the end (exponential decay over the deformation stage, as the MLP's)."""

    densify_until_iter: int = 7000
    """Densification stops after this many paper iterations of the deformation stage (4D-GS HyperNeRF
    config: 10 000 of its 14 000 fine iterations, i.e. the first ~70%)."""
    opacity_reset_interval: Optional[int] = None
    """Opacity-reset period in the deformation stage, paper iterations; ``None`` = no reset (4D-GS
    HyperNeRF config, which 4D LangSplat uses: 300 000, beyond the stage; D-NeRF config: 3000). Without
    resets the screen/world-size pruning stays off too, as in the release (it starts after a reset)."""
    lr_decay_steps: int = 10_000
    """Paper iterations over which every rate of the deformation stage (MLP, grid and the Gaussians'
    positions) decays to its final value; = the stage length, as the release's 20 000-step decay spans
    its D-NeRF fine stage."""
    lambda_dssim: float = 0.2
    """D-SSIM weight of the deformation stage (4D-GS release: 0, L1 only; 0.2 keeps the 3D-GS loss)."""

    # --- temporal regularisers (applied for real: the release's stage-name check disabled them) --
    plane_tv_weight: float = 2e-4
    """Total variation of the spatial planes (release HyperNeRF config, 4D LangSplat's: 2e-4; D-NeRF: 1e-4)."""
    time_smoothness_weight: float = 1e-3
    """Second-order smoothness along t of the time planes (release HyperNeRF: 1e-3; D-NeRF: 1e-2)."""
    l1_time_planes_weight: float = 1e-4
    """L1 of (1 - time plane), pulling the field towards no motion (release: 1e-4)."""
    motion_l1_weight: float = 0.0
    """Weight of an L1 prior on the deformation itself (not in the 4D-GS recipe; 0 = the recipe, the
    default): the mean over the Gaussians of their offsets at the rendered time, each in units of its
    static tolerance (position in pixels of the nearest training view / ``static_pixel_tol``, log-scale /
    ``static_scale_tol``, quaternion / (``static_rotation_tol`` x norm)). On monocular video every time has
    one view, so without it the field moves static content a few pixels to fit each view's residual
    (split-cookie frames 0-38, where only the cookie moves, in the last four: median 3 px, 83 % of the
    Gaussians flagged dynamic; frames 0-34, where nothing moves: 17 332 of 21 693 flagged, and the cookie
    3 dB below a static 3D-GS, 22.79 vs 25.85 dB). At 0.01 (with ``static_warmup_fraction`` 0.25)
    split-cookie 128 px ends with 3 077 of 21 691 Gaussians dynamic instead of 15 786, at 27.64 instead of
    27.43 dB and 14 % less CPU; 0.003 left 6 758 dynamic. It is off by default because its cost grows with
    the size of the motion while what the motion earns does not: on D-NeRF at 200 px, 0.01 (warm-up 0.25)
    froze every Gaussian (standup 30.58 -> 19.22 dB, the static 3D-GS level; lego 25.00 -> 23.64 dB), and
    on the test suite's toy scene (blobs sliding ~2 px) it stops the field learning the motion (27.4 vs
    34.3 dB; 0.001: 33.8 dB). A scene-independent weight would need a penalty that saturates with the
    offset."""

    # --- schedule (paper iterations of the deformation stage) -----------------------------------
    paper_iterations: int = 10_000
    """Deformation-stage length of 4D LangSplat's recipe (protocol: 10 000)."""

    # --- static-Gaussian detection (skip the deformation where nothing moves) --------------------
    static_skip: bool = True
    """Detect Gaussians whose deformation does not vary over time and evaluate the HexPlane/MLP only on
    the dynamic ones (not in the release)."""
    static_outside_motion_box: bool = True
    """Start the deformation stage with the Gaussians outside the motion box (``HexPlaneConfig.motion_cell_share``:
    where the static stage explains the training images) marked static, instead of all dynamic; the
    regular checks from ``static_warmup_fraction`` on can still mark any of them dynamic. Not in the release.
    Without it, every Gaussian pays for the field until the first check, and on monocular video the field
    moves static content by about a pixel to fit each view's residual, so most of a room is still dynamic
    at the end (keyboard: 16 153 of 21 699 Gaussians, where 0.3 % of the pixels move). No effect where the
    motion box spans the scene (D-NeRF standup: 16 of 3 401 start static) or none was found. Measured at
    128 px, 3000 iterations, seed 0, off / on (``reports/recon/*-outside-box-*``): keyboard 27.63 / 27.68 dB,
    538 / 453 CPU s (two processes on two cores; 4 327 of the 6 067 Gaussians start static, 13 930 instead of
    16 153 are dynamic at the end), americano 27.57 / 27.63, split-cookie 27.22 / 27.31, D-NeRF standup at
    200 px 30.10 / 30.06."""
    recheck_outside_motion_box: bool = True
    """With ``static_outside_motion_box``: the regular checks may mark Gaussians outside the motion box dynamic
    (True), or keep them static for the whole stage, so that only the motion box deforms (False: keyboard
    27.70 dB, 433 CPU s, 7 492 dynamic at the end; americano 27.69 dB, 10 607 dynamic instead of 17 662).
    True by default: a box that misses some motion is then corrected by the checks."""
    static_warmup_fraction: float = 0.5
    """First detection after this fraction of the deformation stage, once the field has learned the
    motion (a Gaussian marked static gets no deformation gradient, so marking it early could freeze
    motion the field has not learned yet). With the motion prior the jitter is gone early and a quarter
    suffices (split-cookie, prior 0.01: 0.5 -> 0.25 cut the fit's CPU time from 537 to 494 s)."""
    static_check_interval_fraction: float = 0.1
    """Re-check (both ways: the field, trained by the dynamic neighbours, may start to move a static
    Gaussian's region) every this fraction of the stage, and once more at its end."""
    static_time_samples: int = 16
    """Times in [0, 1] at which the deformation is sampled for the check."""
    static_pixel_tol: float = 1.0
    """Static when the position offset varies over time by less than this many pixels in the training
    view where it looks largest (nearest camera). Trained on monocular video, the field jitters static
    content by about a pixel (lego at 200 px: median 1.1 px over the sequence; split-cookie: 2 px), so
    sub-pixel tolerances find nothing; at 1 px, half of lego is static, the remaining training absorbs
    the change, and test PSNR is unchanged (see reports/recon). A world-space tolerance
    (``static_position_tol``) is used when no cameras are given."""
    static_position_tol: float = 1e-3
    """Fallback without cameras: static when the position offset varies by less than this fraction of
    the scene extent."""
    static_scale_tol: float = 0.1
    """... and the log-scale offset by less than this (10% size change: the same jitter shows in scales)."""
    static_rotation_tol: float = 0.05
    """... and the quaternion offset by less than this fraction of the quaternion's norm."""
    static_color_tol: float = 0.02
    """... and (``deform_color``) the RGB offset by less than this (about 5 of 255 levels)."""


@dataclass
class ReconConfig:
    """A whole reconstruction run: the 3D-GS recipe, the 4D-GS deformation recipe and stage lengths."""

    gaussians: GaussianConfig = field(default_factory=GaussianConfig)
    """3D-GS recipe (static reference, and the static stage of 4D-GS)."""
    deformation: DeformationConfig = field(default_factory=DeformationConfig)
    """4D-GS deformation recipe."""
    static_iterations: int = 3000
    """4D-GS static (3D-GS) stage length (protocol: 3 000)."""
    deformation_iterations: int = 10_000
    """4D-GS deformation stage length (protocol: 10 000)."""
    paper_static_iterations: int = 3000
    """Static-stage length of the recipe (protocol: 3 000); static_iterations / this scales the static
    stage's schedule, and deformation_iterations / DeformationConfig.paper_iterations the other's."""
    reference_iterations: Optional[int] = None
    """Iterations of the static 3D-GS reference; ``None`` = the 4D-GS total (same budget)."""
    schedule_scale: Optional[float] = None
    """Override of the schedule scale (``None`` = derived from the stage lengths as documented above)."""
    seed: int = 0
    """Seed of initialisation and view sampling."""
    log_every: int = 0
    """Print progress every this many iterations (0 = silent)."""

    def static_stage_scale(self) -> float:
        """Schedule scale of the 4D-GS static stage: static_iterations / paper_static_iterations."""
        if self.schedule_scale is not None:
            return float(self.schedule_scale)
        return self.static_iterations / self.paper_static_iterations

    def deformation_stage_scale(self) -> float:
        """Schedule scale of the deformation stage: deformation_iterations / its paper length."""
        if self.schedule_scale is not None:
            return float(self.schedule_scale)
        return self.deformation_iterations / self.deformation.paper_iterations

    def reference_scale(self, iterations: int) -> float:
        """Schedule scale of a static 3D-GS run of ``iterations`` (relative to the paper's 30 000)."""
        if self.schedule_scale is not None:
            return float(self.schedule_scale)
        return iterations / self.gaussians.paper_iterations


@dataclass(frozen=True)
class Schedule:
    """Iteration-dependent quantities of one training stage, with paper intervals scaled.

    ``scale`` multiplies every interval written in paper iterations; a scaled interval is at least 1.
    """

    cfg: GaussianConfig
    """The 3D-GS recipe whose intervals are scaled."""
    scale: float
    """The run's schedule scale."""
    densify_until: Optional[int] = None
    """Paper iteration after which densification stops (``None``: ``cfg.densify_until_iter``)."""
    opacity_resets: bool = True
    """Whether opacities are reset every ``reset_interval`` (and size pruning starts after the first)."""
    reset_interval: Optional[int] = None
    """Opacity-reset period, paper iterations (``None``: ``cfg.opacity_reset_interval``)."""

    def at(self, paper_iterations: int) -> int:
        """A paper-iteration count scaled to this run (at least 1)."""
        return max(1, int(round(paper_iterations * self.scale)))

    def sh_degree(self, iteration: int) -> int:
        """Active SH degree at ``iteration`` (0-based): one band more every scaled interval."""
        return min(self.cfg.sh_degree, iteration // self.at(self.cfg.sh_degree_interval))

    def densify_until_iteration(self) -> int:
        """Last iteration of the densification window, scaled."""
        return self.at(self.cfg.densify_until_iter if self.densify_until is None else self.densify_until)

    def _reset_interval(self) -> int:
        scaled = self.at(self.cfg.opacity_reset_interval if self.reset_interval is None else self.reset_interval)
        return max(scaled, self.cfg.min_opacity_reset_gap)

    def densify_now(self, iteration: int) -> bool:
        """Whether to densify and prune after ``iteration`` (1-based count of completed steps)."""
        return (self.at(self.cfg.densify_from_iter) < iteration <= self.densify_until_iteration()
                and iteration % self.at(self.cfg.densification_interval) == 0)

    def reset_opacity_now(self, iteration: int, stage_end: int) -> bool:
        """Whether to reset opacities after ``iteration`` (inside the densification window only).

        Never at the stage's last iteration: nothing would be left to recover the opacities (the
        release resets at the end of its 3 000-iteration static stage).
        """
        return (self.opacity_resets and iteration <= self.densify_until_iteration() and iteration < stage_end
                and iteration % self._reset_interval() == 0)

    def screen_pruning_active(self, iteration: int) -> bool:
        """The paper prunes by screen and world size only after the first opacity reset."""
        return self.opacity_resets and iteration > self._reset_interval()

    def position_lr(self, iteration: int, extent: float) -> float:
        """Exponentially decayed position learning rate (paper), x scene extent."""
        return extent * exponential_lr(iteration, self.cfg.position_lr_init, self.cfg.position_lr_final,
                                       self.at(self.cfg.position_lr_max_steps))


def exponential_lr(step: int, lr_init: float, lr_final: float, max_steps: int,
                   delay_steps: int = 0, delay_mult: float = 1.0) -> float:
    """Log-linear interpolation from ``lr_init`` to ``lr_final`` over ``max_steps`` (3D-GS schedule).

    With ``delay_steps > 0`` the rate is further damped by a cosine ramp starting at ``delay_mult``.
    """
    if lr_init == lr_final or max_steps <= 0:
        return lr_init
    if step < 0 or (lr_init == 0.0 and lr_final == 0.0):
        return 0.0
    if delay_steps > 0:
        delay = delay_mult + (1 - delay_mult) * math.sin(0.5 * math.pi * min(max(step / delay_steps, 0.0), 1.0))
    else:
        delay = 1.0
    frac = min(max(step / max_steps, 0.0), 1.0)
    return delay * math.exp(math.log(lr_init) * (1 - frac) + math.log(lr_final) * frac)
