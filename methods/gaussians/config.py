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
    densification (a CPU-scale choice; the paper has no cap)."""
    init_knn: int = 3
    """Initial scale = RMS distance to this many nearest neighbours (paper release: 3)."""

    # --- model size (scene-adaptive cap) ---------------------------------------------------------
    gaussians_per_foreground_pixel: float = 1.0
    """Gaussian cap = this x mean foreground pixels per training view (alpha masks, else pixels unlike
    the known background, else the whole image); one per pixel is a CPU-scale choice."""
    foreground_threshold: float = 0.02
    """A pixel is foreground when some channel differs from the known background by more than this."""
    min_gaussians: int = 500
    """Lower bound of the cap (tiny images still need enough Gaussians to cover a shape)."""
    max_gaussians: int = 360_000
    """Upper bound of the cap: 4D LangSplat densifies up to 360k Gaussians (protocol)."""
    gradual_cap: bool = True
    """Let the allowed count grow linearly from the stage's start count to the cap over the
    densification window (as Taming 3DGS, Mallick et al. 2024), rather than allowing the whole cap at once."""

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
    """Iterations of this run (not scaled) at least between two opacity resets: short runs get fewer
    resets, never denser ones."""

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
    """Prune Gaussians whose screen radius exceeded this many pixels since the last densification, after the
    first opacity reset (paper: 20 px; ``None``: never, as the 3D-GS release in effect)."""
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
    """Share of each spatial axis's cells given to the motion box (where the static stage leaves the
    training images unexplained), the rest to the remainder of the plane box (0: even cells, as the release)."""
    motion_residual: float = 0.1
    """A rendered pixel of the static stage counts as unexplained when its mean absolute RGB error exceeds
    this."""
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
    """Also predict an RGB offset of each Gaussian's base colour over time (its head zero-initialised; not in
    4D-GS, off = the recipe)."""
    zero_init_heads: bool = False
    """Initialise the heads' last layers to zero, so the deformation stage starts exactly at the static
    stage's result (off: Xavier init, as the release)."""

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
    """Learning rate of the colour head's output layer at the start (``deform_color``; RGB units, not scaled
    by the extent; not in the release)."""
    color_lr_final: float = 1.6e-3
    """... and at the end (exponential decay over the deformation stage, as the MLP's)."""

    densify_until_iter: int = 7000
    """Densification stops after this many paper iterations of the deformation stage (4D-GS HyperNeRF
    config: 10 000 of its 14 000 fine iterations, i.e. the first ~70%)."""
    opacity_reset_interval: Optional[int] = None
    """Opacity-reset period of the deformation stage, paper iterations; ``None``: no reset, and so no
    screen/world-size pruning (4D-GS HyperNeRF config, 4D LangSplat's)."""
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
    """Weight of an L1 prior on the deformation, each offset in units of its static tolerance (not in the
    4D-GS recipe; 0 = the recipe)."""

    # --- schedule (paper iterations of the deformation stage) -----------------------------------
    paper_iterations: int = 10_000
    """Deformation-stage length of 4D LangSplat's recipe (protocol: 10 000)."""

    # --- static-Gaussian detection (skip the deformation where nothing moves) --------------------
    static_skip: bool = True
    """Detect Gaussians whose deformation does not vary over time and evaluate the HexPlane/MLP only on
    the dynamic ones (not in the release)."""
    static_outside_motion_box: bool = True
    """Start the deformation stage with the Gaussians outside the motion box marked static instead of
    all dynamic; the regular checks can still mark them dynamic (not in the release)."""
    recheck_outside_motion_box: bool = True
    """With ``static_outside_motion_box``: the regular checks may mark Gaussians outside the motion box
    dynamic (True), or keep them static for the whole stage (False)."""
    static_warmup_fraction: float = 0.5
    """First static-Gaussian detection after this fraction of the deformation stage, once the field has
    learned the motion."""
    static_check_interval_fraction: float = 0.1
    """Re-check (both ways: the field, trained by the dynamic neighbours, may start to move a static
    Gaussian's region) every this fraction of the stage, and once more at its end."""
    static_time_samples: int = 16
    """Times in [0, 1] at which the deformation is sampled for the check."""
    static_pixel_tol: float = 1.0
    """Static when the position offset varies over time by less than this many pixels in the training view
    where it looks largest (``static_position_tol`` in world units when no cameras are given)."""
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
