"""3D-GS and 4D-GS training on a :class:`~benchmark.core.scene.Scene` (one training view per iteration).

* :meth:`Trainer.fit_3dgs`: the 3D-GS recipe (static reference).
* :meth:`Trainer.fit_4dgs`: 4D-GS = a 3D-GS static stage, then a deformation stage that trains the
  HexPlane deformation field together with the canonical Gaussians, with the temporal regularisers
  added to the loss (the release never adds them) and, optionally, the deformation evaluated only on
  Gaussians that move (:meth:`~methods.gaussians.model.DeformableGaussians.update_static_mask`).

Each stage is a loop of named steps (:meth:`Trainer._run_stage`); densification is the stage's
:class:`~methods.gaussians.strategy.DensificationStrategy` (the total never exceeds the scene's cap,
:func:`gaussian_cap`), checkpoints and the fit's clock are :mod:`methods.gaussians.checkpoint`'s.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable, Optional, Sequence

import numpy as np
import torch

from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from .backends import native_cpu
from .checkpoint import Checkpointing, FitCheckpoints
from .config import DeformationConfig, GaussianConfig, ReconConfig, Schedule, exponential_lr
from .hexplane import DeformationField
from .model import DeformableGaussians, GaussianModel
from .optimizer import GaussianOptimizer, fast_adam
from .rasterize import RenderOutput, camera_tensors
from .strategy import DensificationStrategy

RasterizeFn = Callable[..., object]


def default_rasterize() -> RasterizeFn:
    from .rasterize import rasterize

    return rasterize


# ---------------------------------------------------------------------------------------------------
# Views, scene size, model size
# ---------------------------------------------------------------------------------------------------
@dataclass
class RGBView:
    """One frame's RGB image and camera as tensors, ready to render and compare."""

    name: str
    image: torch.Tensor
    """(H, W, 3) float32 target RGB."""
    viewmat: torch.Tensor
    """(4, 4) world-to-camera, OpenCV axes."""
    K: torch.Tensor
    """(3, 3) intrinsics."""
    width: int
    height: int
    time: float
    """Normalised time in [0, 1]."""
    center: torch.Tensor
    """(3,) camera centre in world coordinates."""
    foreground: Optional[np.ndarray] = None
    """(H, W) bool foreground mask when the scene has one."""


QUANTILE_INPUT_LIMIT = 1_000_000
"""Most points ``torch.quantile`` takes (its input limit is 2^24 elements: 1M points of 3 coordinates fit)."""


def even_subsample(n: int, k: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """(k,) int64 indices spread evenly over ``range(n)``, first 0 and last ``n - 1`` (``k <= n``, ``k >= 2``).

    Integer arithmetic: ``torch.linspace(0, n - 1, k)`` is float32, whose spacing above 2^24 is 2 or more,
    so its last index can round up to ``n`` (n = 20 000 000 does) and overrun the array (a CUDA device-side
    assert at 536x960, where 36 training views give up to 18.5M candidate pixels)."""
    return torch.arange(k, device=device, dtype=torch.int64) * (n - 1) // (k - 1)


def make_views(frames: Sequence[Frame], device: torch.device | str = "cpu", with_images: bool = True) -> list[RGBView]:
    """Load ``frames`` as :class:`RGBView` objects (images decoded once; 128-px scenes hold easily in memory)."""
    views = []
    for fr in frames:
        # The rasterizer is a pinhole: distortion coefficients (HyperNeRF) are ignored, as in 4D-GS.
        viewmat, K, width, height = camera_tensors(fr.camera, device)
        img = torch.as_tensor(np.ascontiguousarray(fr.image(), dtype=np.float32), device=device) if with_images \
            else torch.empty(0)
        fg = fr.alpha() if with_images else None
        views.append(RGBView(fr.name, img, viewmat, K, width, height, float(fr.time),
                             torch.as_tensor(fr.camera.center, dtype=torch.float32, device=device),
                             None if fg is None else np.asarray(fg, dtype=bool)))
    return views


def scene_extent(centers: np.ndarray, bounds: np.ndarray, margin: float) -> float:
    """Scene extent for learning rates and size thresholds (3D-GS: ``margin`` x camera spread radius).

    ``centers``: (V, 3) camera centres; ``bounds``: (2, 3) scene box. When the cameras barely move (a
    monocular fixed camera), their spread says nothing about the scene, so the box's half-diagonal is
    used instead whenever it is more than 10x larger.
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    radius = float(np.linalg.norm(centers - centers.mean(0), axis=1).max()) * margin if len(centers) else 0.0
    half_diag = 0.5 * float(np.linalg.norm(np.asarray(bounds)[1] - np.asarray(bounds)[0]))
    if radius < 0.1 * half_diag:
        return max(half_diag, 1e-6)
    return radius


def foreground_fraction(views: Sequence[RGBView], background: Optional[np.ndarray], threshold: float) -> float:
    """Mean fraction of foreground pixels over ``views``: alpha masks, else pixels unlike the background,
    else 1 (real backgrounds: everything must be modelled)."""
    fractions = []
    for v in views:
        if v.foreground is not None:
            fractions.append(float(v.foreground.mean()))
        elif background is not None:
            bg = torch.as_tensor(np.asarray(background, dtype=np.float32), device=v.image.device)
            fractions.append(float(((v.image - bg).abs().amax(-1) > threshold).float().mean()))
        else:
            fractions.append(1.0)
    return float(np.mean(fractions)) if fractions else 1.0


def gaussian_cap(views: Sequence[RGBView], background: Optional[np.ndarray], cfg: GaussianConfig) -> int:
    """Most Gaussians this scene gets: ``gaussians_per_foreground_pixel`` x mean foreground pixels of a
    training view, within [min_gaussians, max_gaussians]."""
    if not views:
        return cfg.min_gaussians
    pixels = float(np.mean([v.width * v.height for v in views]))
    fg = foreground_fraction(views, background, cfg.foreground_threshold)
    cap = int(round(cfg.gaussians_per_foreground_pixel * fg * pixels))
    return int(min(max(cap, cfg.min_gaussians), cfg.max_gaussians))


def initial_gaussians(scene: Scene, cfg: GaussianConfig, cap: int, generator: torch.Generator,
                      device: torch.device | str = "cpu", views: Optional[Sequence[RGBView]] = None) -> GaussianModel:
    """From the scene's point cloud (random subset if larger than the cap), else random in its bounds.

    Random points are kept only where some training camera ``views`` sees them (in front of it, inside
    its image): loaders of real layouts give loose boxes (a room around a tabletop), and Gaussians
    that no view sees would never receive a gradient.
    """
    if scene.points is not None and len(scene.points) > 0:
        pts = np.asarray(scene.points, dtype=np.float32).reshape(-1, 3)
        cols = None if scene.point_colors is None else np.asarray(scene.point_colors, dtype=np.float32).reshape(-1, 3)
        if cols is not None and len(cols) != len(pts):
            raise InputError(scene.root, "point_colors", f"{len(cols)} colours for {len(pts)} points")
        if len(pts) > cap:
            keep = torch.randperm(len(pts), generator=generator)[:cap].numpy()
            pts = pts[keep]
            cols = None if cols is None else cols[keep]
        return GaussianModel.from_points(pts, cols, cfg, device)
    count = max(1, min(cfg.random_init_points, int(cfg.random_init_cap_fraction * cap)))
    b = torch.as_tensor(np.asarray(scene.bounds, dtype=np.float32))
    kept: list[torch.Tensor] = []
    total = 0
    for _ in range(64):  # rejection sampling; a few rounds unless views see a sliver of the box
        cand = b[0] + torch.rand(4 * count, 3, generator=generator) * (b[1] - b[0])
        if views:
            cand = cand[seen_by_any(cand, views, cfg.near)]
        kept.append(cand)
        total += cand.shape[0]
        if total >= count:
            break
    pts = torch.cat(kept)[:count]
    if pts.shape[0] == 0:
        raise InputError(scene.root, "bounds", "no training camera sees any point of the scene bounds")
    rgb = torch.rand(pts.shape[0], 3, generator=generator)
    return GaussianModel.from_points(pts.numpy(), rgb.numpy(), cfg, device)


def seen_by_any(points: torch.Tensor, views: Sequence[RGBView], near: float) -> torch.Tensor:
    """(M,) bool: the (M, 3) ``points`` project inside the image of at least one of ``views``."""
    seen = torch.zeros(points.shape[0], dtype=torch.bool)
    for v in views:
        cam = points @ v.viewmat[:3, :3].T.cpu() + v.viewmat[:3, 3].cpu()
        z = cam[:, 2]
        uv = (cam @ v.K.T.cpu())[:, :2] / z.clamp_min(1e-9)[:, None]
        seen |= (z > near) & (uv[:, 0] >= 0) & (uv[:, 0] < v.width) & (uv[:, 1] >= 0) & (uv[:, 1] < v.height)
    return seen


# ---------------------------------------------------------------------------------------------------
# Loss
# ---------------------------------------------------------------------------------------------------
def gaussian_window(size: int, sigma: float) -> torch.Tensor:
    """(size,) normalised 1-D Gaussian kernel (the SSIM window is its outer product with itself)."""
    x = torch.arange(size, dtype=torch.float32) - (size - 1) / 2.0
    g = torch.exp(-(x ** 2) / (2 * sigma ** 2))
    return g / g.sum()


_BAND_CACHE: dict[tuple, torch.Tensor] = {}


def _band_matrix(kernel: torch.Tensor, n: int) -> torch.Tensor:
    """(n, n) matrix B with ``B @ x`` = ``x`` filtered by the 1-D ``kernel`` with zero padding."""
    key = (n, kernel.device, kernel.dtype, tuple(kernel.tolist()))
    band = _BAND_CACHE.get(key)
    if band is None:
        half = kernel.numel() // 2
        i = torch.arange(n, device=kernel.device)
        d = i[None, :] - i[:, None] + half  # column - row + half: index into the kernel
        valid = (d >= 0) & (d < kernel.numel())
        band = torch.where(valid, kernel[d.clamp(0, kernel.numel() - 1)], kernel.new_zeros(()))
        if len(_BAND_CACHE) > 16:
            _BAND_CACHE.clear()
        _BAND_CACHE[key] = band
    return band


def ssim(img: torch.Tensor, ref: torch.Tensor, window: torch.Tensor) -> torch.Tensor:
    """Differentiable mean SSIM of two (H, W, C) images in [0, 1]; ``window`` is the (size,) 1-D kernel.

    Gaussian-weighted local moments with zero padding, as the 3D-GS release (K1 = 0.01, K2 = 0.03 for
    data range 1). The separable blur is two matrix products with banded matrices: several times
    faster on CPU than a grouped 2-D convolution at these image sizes, and the same numbers.
    """
    h, w, c = img.shape
    if (native_cpu.supports(img) and window.numel() % 2 == 1 and not ref.requires_grad
            and native_cpu.kernels() is not None):
        # the compiled kernel: the same blurs (11 taps per pixel instead of a full band-matrix product), the
        # backward as three more blurs
        return native_cpu.Ssim.apply(img, ref, window)
    kernel = window.to(device=img.device, dtype=img.dtype)
    bh, bw = _band_matrix(kernel, h), _band_matrix(kernel, w)
    x = img.permute(2, 0, 1)
    y = ref.permute(2, 0, 1)
    stacked = torch.cat([x, y, x * x, y * y, x * y], dim=0)  # (5C, H, W): all five moments at once
    moments = bh @ stacked @ bw.T
    mu_x, mu_y, e_xx, e_yy, e_xy = moments.split(c, dim=0)
    var_x = e_xx - mu_x ** 2
    var_y = e_yy - mu_y ** 2
    cov = e_xy - mu_x * mu_y
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    s = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (var_x + var_y + c2))
    return s.mean()


def photometric_loss(render: torch.Tensor, target: torch.Tensor, lambda_dssim: float,
                     window: torch.Tensor) -> torch.Tensor:
    """(1 - lambda) L1 + lambda (1 - SSIM) of (H, W, 3) images (3D-GS)."""
    l1 = (render - target).abs().mean()
    if lambda_dssim <= 0:
        return l1
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(render, target, window))


# ---------------------------------------------------------------------------------------------------
# Trainer
# ---------------------------------------------------------------------------------------------------
@dataclass
class FitResult:
    """A trained model and how the training went."""

    kind: str
    """``"3dgs"`` or ``"4dgs"``."""
    model: object
    """:class:`GaussianModel` (3dgs) or :class:`DeformableGaussians` (4dgs)."""
    fit_seconds: float
    """Wall time of the training loop (images already loaded)."""
    fit_cpu_seconds: float = 0.0
    """CPU time of this process during training, all threads (what a shared machine does not inflate)."""
    stages: list[dict] = field(default_factory=list)
    """Per stage: name, iterations, seconds, ms per iteration, final Gaussian count, events."""
    history: list[dict] = field(default_factory=list)
    """Sparse log: iteration, stage, loss, Gaussian count."""
    extent: float = 0.0
    cap: int = 0
    resumed_at: Optional[dict] = None
    """``{"stage", "iteration"}`` of the checkpoint this fit resumed from (None: it ran in one go)."""
    field_box: Optional[dict] = None
    """4D-GS: the HexPlane's ``bounds`` and ``motion_box`` ((2, 3) lists; the latter ``None`` when off or
    not found), ``unexplained_pixels`` it came from, base ``cell_size`` (3,) inside it, ``cpu_seconds``."""


@dataclass
class StageRun:
    """One training stage as it goes: what it trains, and the bookkeeping it reports and checkpoints."""

    name: str
    """``"static"`` or ``"deformation"``."""
    iterations: int
    """The stage's length."""
    model: GaussianModel
    """The Gaussians (the canonical ones in the deformation stage)."""
    opt: GaussianOptimizer
    """The Gaussians' optimiser."""
    deformable: Optional[DeformableGaussians]
    """The Gaussians with their deformation field (deformation stage), else None."""
    net_opt: Optional[torch.optim.Optimizer]
    """The deformation field's optimiser (deformation stage), else None."""
    schedule: Schedule
    """The stage's learning rates, SH degree and densification intervals."""
    strategy: DensificationStrategy
    """When and how the stage densifies, prunes and resets opacities."""
    iter_seconds: np.ndarray
    """(iterations,) wall seconds of each iteration."""
    deform_seconds: np.ndarray
    """(iterations,) wall seconds of each iteration's deformation (0 in a static stage)."""
    events: list[dict] = field(default_factory=list)
    """Densifications, opacity resets and static checks, in order."""
    first_loss: float = float("nan")
    """Loss of the stage's first iteration."""
    last_loss: float = float("nan")
    """Loss of the latest iteration."""
    px_per_unit: Optional[torch.Tensor] = None
    """(N,) pixels per world unit of the Gaussians for the motion prior; dropped at each densification."""
    first_iteration: int = 1
    """The iteration the loop starts at (after the checkpoint's, when resumed)."""
    cpu_start: float = 0.0
    """``time.process_time()`` at the stage's start, less the time spent before an interruption."""
    wall_start: float = 0.0
    """``time.perf_counter()`` at the stage's start, less the time spent before an interruption."""

    def start_clock(self, loop: Optional[dict] = None) -> None:
        """The stage's time counts from now, plus that of a resumed ``loop`` (see :meth:`state_dict`)."""
        cpu_before = 0.0 if loop is None else float(loop["cpu_seconds"])
        wall_before = 0.0 if loop is None else float(loop["wall_seconds"])
        self.cpu_start, self.wall_start = time.process_time() - cpu_before, time.perf_counter() - wall_before

    def record(self, iteration: int, loss: float, started: float) -> None:
        """``iteration`` ended with ``loss``; it began at ``time.perf_counter()`` = ``started``."""
        self.last_loss = loss
        if iteration == 1:
            self.first_loss = loss
        self.iter_seconds[iteration - 1] = time.perf_counter() - started

    def state_dict(self) -> dict:
        """The loop's bookkeeping and the densification state, for a checkpoint."""
        return {**self.strategy.state_dict(), "events": self.events,
                "iter_seconds": torch.from_numpy(self.iter_seconds.copy()),
                "deform_seconds": torch.from_numpy(self.deform_seconds.copy()),
                "last_loss": self.last_loss, "first_loss": self.first_loss, "px_per_unit": self.px_per_unit,
                "cpu_seconds": time.process_time() - self.cpu_start,
                "wall_seconds": time.perf_counter() - self.wall_start}

    def load_state_dict(self, loop: dict, device: torch.device | str) -> None:
        self.strategy.load_state_dict(loop)
        self.events = list(loop["events"])
        self.iter_seconds = loop["iter_seconds"].cpu().numpy().astype(np.float64)
        self.deform_seconds = loop["deform_seconds"].cpu().numpy().astype(np.float64)
        self.last_loss, self.first_loss = float(loop["last_loss"]), float(loop["first_loss"])
        self.px_per_unit = None if loop["px_per_unit"] is None else loop["px_per_unit"].to(device)

    def summary(self) -> dict:
        """The stage's entry of :attr:`FitResult.stages`."""
        n = self.iterations
        tail = self.iter_seconds[n // 2:] if n > 1 else self.iter_seconds
        out = {"stage": self.name, "iterations": n, "seconds": float(self.iter_seconds.sum()),
               "cpu_seconds": time.process_time() - self.cpu_start,
               "ms_per_iteration": 1000 * float(self.iter_seconds.mean()) if n else 0.0,
               "ms_per_iteration_second_half": 1000 * float(tail.mean()) if len(tail) else 0.0,
               "first_loss": self.first_loss, "final_loss": self.last_loss, "gaussians": self.model.num_gaussians,
               "schedule_scale": self.schedule.scale, "events": self.events}
        if self.deformable is not None:
            out["deform_ms_per_iteration_second_half"] = 1000 * float(self.deform_seconds[n // 2:].mean()) \
                if n > 1 else 1000 * float(self.deform_seconds.mean())
            out["dynamic_gaussians"] = self.deformable.num_dynamic()
        return out


class Trainer:
    """Trains 3D-GS / 4D-GS on a scene's training frames, one random training view per iteration."""

    def __init__(self, scene: Scene, cfg: Optional[ReconConfig] = None, device: torch.device | str = "cpu",
                 rasterize_fn: Optional[RasterizeFn] = None, train_frames: Optional[Sequence[Frame]] = None,
                 progress: Optional[Callable[..., Iterable]] = None, checkpoint: Optional[Checkpointing] = None):
        """``progress``: ``progress(iterable, desc=..., total=...)`` wrapper (tqdm-like) over each stage's
        iterations, or ``None``: a geometry fit is the longest silent stretch of a run. ``checkpoint``:
        save the training state as it goes and resume from it (:class:`Checkpointing`)."""
        self.scene = scene
        self.progress = progress
        self.checkpoint = checkpoint
        self.cfg = cfg or ReconConfig()
        self.device = torch.device(device)
        self.rasterize = rasterize_fn or default_rasterize()
        frames = list(train_frames) if train_frames is not None else scene.train_frames
        if not frames:
            raise InputError(scene.root, "frames", f"scene {scene.name!r} has no training frames")
        self.views = make_views(frames, self.device)
        bg = scene.background
        self.background = torch.as_tensor(np.zeros(3) if bg is None else np.asarray(bg), dtype=torch.float32,
                                          device=self.device)
        g = self.cfg.gaussians
        self.extent = scene_extent(np.stack([v.center.cpu().numpy() for v in self.views]), scene.bounds,
                                   g.extent_margin)
        self.cap = gaussian_cap(self.views, bg, g)
        self.window = gaussian_window(g.ssim_window, g.ssim_sigma).to(self.device)
        self._reset_random()

    def _reset_random(self) -> None:
        """Every fit starts from the run's seed, whatever ran before it on this trainer."""
        self.generator = torch.Generator().manual_seed(self.cfg.seed)
        self.rng = np.random.default_rng(self.cfg.seed)
        self._order: list[int] = []

    # -- public -------------------------------------------------------------------------------------
    def fit_3dgs(self, iterations: Optional[int] = None) -> FitResult:
        """Static 3D-GS for ``iterations`` (default: the 4D-GS total, the same budget)."""
        c = self.cfg
        iterations = iterations or c.reference_iterations or (c.static_iterations + c.deformation_iterations)
        self._reset_random()
        model = initial_gaussians(self.scene, c.gaussians, self.cap, self.generator, self.device, self.views)
        self._checkpoints = FitCheckpoints(self.checkpoint, "3dgs", iterations, self.device)
        resume = self._checkpoints.resume
        opt = self._gaussians_from(resume, model)
        self._checkpoints.start_clock()
        result = FitResult("3dgs", model, 0.0, extent=self.extent, cap=self.cap)
        sched = Schedule(c.gaussians, c.reference_scale(iterations))
        self._run_stage("static", model, opt, None, None, sched, iterations, result, resume)
        self._checkpoints.finish(result)
        return result

    def fit_4dgs(self) -> FitResult:
        """4D-GS: static stage, then deformation stage (canonical Gaussians + deformation field)."""
        c = self.cfg
        self._reset_random()
        model = initial_gaussians(self.scene, c.gaussians, self.cap, self.generator, self.device, self.views)
        self._checkpoints = FitCheckpoints(self.checkpoint, "4dgs", c.static_iterations + c.deformation_iterations,
                                           self.device)
        resume = self._checkpoints.resume
        opt = self._gaussians_from(resume, model)
        result = FitResult("4dgs", model, 0.0, extent=self.extent, cap=self.cap)
        self._checkpoints.start_clock()
        in_deformation = resume is not None and resume["stage"] == "deformation"
        if c.static_iterations > 0 and not in_deformation:
            self._run_stage("static", model, opt, None, None, Schedule(c.gaussians, c.static_stage_scale()),
                            c.static_iterations, result, resume, stage_follows=c.deformation_iterations > 0)
        deformable, net_opt = self._deformation_model(model, result, resume if in_deformation else None)
        result.model = deformable
        if c.deformation_iterations > 0:
            d = c.deformation
            sched = Schedule(c.gaussians, c.deformation_stage_scale(), densify_until=d.densify_until_iter,
                             opacity_resets=d.opacity_reset_interval is not None,
                             reset_interval=d.opacity_reset_interval)
            self._run_stage("deformation", model, opt, deformable, net_opt, sched, c.deformation_iterations,
                            result, resume if in_deformation else None)
        self._checkpoints.finish(result)
        return result

    def _deformation_model(self, model: GaussianModel, result: FitResult,
                           resume: Optional[dict]) -> tuple[DeformableGaussians, torch.optim.Optimizer]:
        """The deformation stage's model on the static stage's Gaussians, and the field's optimiser.

        The HexPlane box (and motion box) are read from the Gaussians as the static stage ends, into
        ``result.field_box``; ``resume``: a checkpoint taken inside the deformation stage (the Gaussians
        have moved since: its box, field, optimiser and dynamic mask are the saved ones).
        """
        c = self.cfg
        d = c.deformation
        bounds = resume["field_bounds"] if resume is not None else self.hexplane_bounds(model)
        if resume is not None:
            focus = resume.get("field_focus")
        else:
            clock = time.process_time()
            focus, focus_pixels = self.motion_box(model)
            result.field_box = {"bounds": bounds.tolist(), "motion_box": None if focus is None else focus.tolist(),
                                "unexplained_pixels": focus_pixels,
                                "cpu_seconds": time.process_time() - clock}
        with torch.random.fork_rng(devices=[]):  # the field's random init follows the run's seed only
            torch.manual_seed(c.seed)
            field_ = DeformationField(d, bounds, self.time_resolution(), focus).to(self.device)
        if result.field_box is not None:
            result.field_box["cell_size"] = field_.hexplane.cell_size().tolist()
        self._field_bounds, self._field_focus = bounds, focus
        deformable = DeformableGaussians(model, field_)
        start_box = self._static_outside_box()
        if resume is None and start_box is not None:
            deformable.dynamic_mask = inside_box(model.params["means"].detach(), start_box)
            result.field_box["static_at_start"] = int((~deformable.dynamic_mask).sum())
        groups = [{"params": field_.mlp_parameters(), "lr": d.deformation_lr_init * self.extent, "name": "mlp"},
                  {"params": field_.grid_parameters(), "lr": d.grid_lr_init * self.extent, "name": "grid"}]
        if field_.color_parameters():
            groups.append({"params": field_.color_parameters(), "lr": d.color_lr_init, "name": "color"})
        net_opt = fast_adam(groups, lr=0.0, eps=c.gaussians.adam_eps)
        if resume is not None:
            field_.load_state_dict(resume["field"])
            net_opt.load_state_dict(resume["net_opt"])
            mask = resume["dynamic_mask"]
            deformable.dynamic_mask = None if mask is None else mask.to(self.device)
        return deformable, net_opt

    # -- checkpoints --------------------------------------------------------------------------------
    def _gaussians_from(self, resume: Optional[dict], model: GaussianModel) -> GaussianOptimizer:
        """The Gaussians' optimiser; with a checkpoint, the Gaussians, their moments and every random
        generator as saved."""
        if resume is not None:
            model.params = {k: v.detach().to(self.device).requires_grad_(True) for k, v in resume["params"].items()}
            model.active_sh_degree = int(resume["active_sh_degree"])
        opt = GaussianOptimizer(model, self.cfg.gaussians, self.extent)
        if resume is not None:
            opt.load_state_dict(resume["opt"])
            self.generator.set_state(resume["generator"])
            self.rng.bit_generator.state = resume["numpy_rng"]
            self._order = list(resume["view_order"])
            torch.set_rng_state(resume["torch_rng"])
        return opt

    def _training_state(self, run: StageRun, result: FitResult) -> dict:
        """The whole training state as the stage ``run`` stands (see :class:`Checkpointing`)."""
        model = run.model
        state: dict = {
            "params": {k: v.detach() for k, v in model.params.items()},
            "active_sh_degree": model.active_sh_degree, "opt": run.opt.optim.state_dict(),
            "generator": self.generator.get_state(), "numpy_rng": self.rng.bit_generator.state,
            "view_order": list(self._order), "torch_rng": torch.get_rng_state(),
            "stages": list(result.stages), "history": list(result.history), "loop": run.state_dict()}
        if run.deformable is not None:
            mask = run.deformable.dynamic_mask
            state.update({"field": run.deformable.field.state_dict(), "net_opt": run.net_opt.state_dict(),
                          "dynamic_mask": None if mask is None else mask.detach(),
                          "field_bounds": self._field_bounds, "field_focus": self._field_focus})
        return state

    def hexplane_bounds(self, model: GaussianModel) -> torch.Tensor:
        """(2, 3) HexPlane box: robust box of the static Gaussians, widened by ``bounds_margin``."""
        h = self.cfg.deformation.hexplane
        means = model.params["means"].detach()
        if means.shape[0] < 2:
            return torch.as_tensor(self.scene.bounds, dtype=torch.float32)
        return self._robust_box(means, h.bounds_percentile)

    def _robust_box(self, points: torch.Tensor, percentile: float) -> torch.Tensor:
        """(2, 3) box of the (N, 3) ``points`` between their ``percentile`` and ``100 - percentile``
        percentiles, widened by ``bounds_margin`` of its size on each side (the plane box and the motion box)."""
        if points.shape[0] > QUANTILE_INPUT_LIMIT:  # an even subsample keeps the percentiles
            points = points[even_subsample(points.shape[0], QUANTILE_INPUT_LIMIT, points.device)]
        q = torch.tensor([percentile / 100.0, 1.0 - percentile / 100.0], device=points.device)
        lo, hi = torch.quantile(points, q, dim=0)
        pad = (hi - lo).clamp_min(1e-3 * self.extent) * self.cfg.deformation.hexplane.bounds_margin
        return torch.stack([lo - pad, hi + pad]).cpu()

    @torch.no_grad()
    def motion_box(self, model: GaussianModel) -> tuple[Optional[torch.Tensor], int]:
        """((2, 3) box of what the static stage leaves unexplained, or ``None``; the pixel count it came from).

        Renders ``motion_views`` training views evenly spaced over the training frames with the static
        Gaussians, back-projects (along the rendered expected depth) every pixel whose mean absolute RGB
        error exceeds ``motion_residual`` where a surface is rendered (alpha > 0.5), and takes the
        ``motion_percentile`` box of those points widened by ``bounds_margin``. A deterministic pass: no
        random draw, so the seeded training stream is the same with it on or off.
        """
        h = self.cfg.deformation.hexplane
        if h.motion_cell_share <= 0 or not self.views:
            return None, 0
        count = min(max(1, h.motion_views), len(self.views))
        picks = np.unique(np.linspace(0, len(self.views) - 1, count).round().astype(int))
        means, quats, scales = model.means.detach(), model.quats.detach(), model.scales.detach()
        opacities = model.opacities.detach()
        points = []
        for i in picks:
            view = self.views[int(i)]
            out = self.rasterize(means, quats, scales, opacities, model.colors(view.center, means).detach(),
                                 view.viewmat, view.K, view.width, view.height, background=self.background,
                                 near=self.cfg.gaussians.near)
            error = (out.image.clamp(0.0, 1.0) - view.image).abs().mean(-1)  # (H, W)
            rows, cols = torch.nonzero((error > h.motion_residual) & (out.alpha > 0.5), as_tuple=True)
            if rows.numel() == 0:
                continue
            z = out.depth[rows, cols]
            K = view.K
            cam = torch.stack([((cols.float() + 0.5) - K[0, 2]) / K[0, 0] * z,
                               ((rows.float() + 0.5) - K[1, 2]) / K[1, 1] * z, z], dim=1)  # (M, 3) camera frame
            R, t = view.viewmat[:3, :3], view.viewmat[:3, 3]
            points.append((cam - t) @ R)  # world = R^T (x - t), row-vector form
        n = int(sum(p.shape[0] for p in points))
        if n < max(1, h.motion_min_pixels):
            return None, n
        return self._robust_box(torch.cat(points), h.motion_percentile), n

    def _static_outside_box(self) -> Optional[torch.Tensor]:
        """(2, 3) motion box outside which the deformation stage starts static
        (``DeformationConfig.static_outside_motion_box``), or None where that does not apply."""
        d = self.cfg.deformation
        return self._field_focus if d.static_skip and d.static_outside_motion_box else None

    def pixels_per_unit(self, points: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
        """(N,) largest pixels-per-world-unit of the (N, 3) ``points`` over the training views: focal / depth
        at the nearest camera that has them in front (0 where none does)."""
        viewmats = torch.stack([v.viewmat for v in self.views])  # (V, 4, 4)
        focal = torch.stack([v.K[:2, :2].diagonal().max() for v in self.views])  # (V,)
        near = self.cfg.gaussians.near
        out = torch.zeros(points.shape[0], device=points.device)
        for start in range(0, points.shape[0], chunk):
            p = points[start:start + chunk]
            z = p @ viewmats[:, 2, :3].T + viewmats[:, 2, 3]  # (n, V) camera depths
            scale = torch.where(z > near, focal / z.clamp_min(near), torch.zeros_like(z))
            out[start:start + chunk] = scale.amax(dim=1)
        return out

    def time_resolution(self) -> int:
        h = self.cfg.deformation.hexplane
        if h.time_resolution is not None:
            return max(2, int(h.time_resolution))
        return max(2, math.ceil(self.scene.num_time_steps / 2))

    # -- the loop -----------------------------------------------------------------------------------
    def _next_view(self) -> RGBView:
        """Views in a fresh random order every epoch (3D-GS)."""
        if not self._order:
            self._order = self.rng.permutation(len(self.views)).tolist()
        return self.views[self._order.pop()]

    def _run_stage(self, stage: str, model: GaussianModel, opt: GaussianOptimizer,
                   deformable: Optional[DeformableGaussians], net_opt: Optional[torch.optim.Optimizer],
                   sched: Schedule, iterations: int, result: FitResult, resume: Optional[dict] = None,
                   stage_follows: bool = False) -> None:
        """One training stage. ``resume``: a checkpoint taken inside this stage to go on from;
        ``stage_follows``: another stage comes after this one, so its end is checkpointed (the end of a
        fit's last stage is not: the fit completes and removes its checkpoint right after)."""
        strategy = DensificationStrategy(self.cfg.gaussians, sched, iterations, self.extent, self.cap,
                                         model.num_gaussians, self.generator, self.device)
        run = StageRun(stage, iterations, model, opt, deformable, net_opt, sched, strategy,
                       iter_seconds=np.zeros(iterations), deform_seconds=np.zeros(iterations))
        loop = resume["loop"] if resume is not None and resume["stage"] == stage else None
        if loop is not None:
            run.load_state_dict(loop, self.device)
            result.stages, result.history = list(resume["stages"]), list(resume["history"])
            run.first_iteration = int(resume["iteration"]) + 1
        run.start_clock(loop)
        self._checkpoints.begin_stage()
        for it in self._iterations(run):
            started = time.perf_counter()
            self._follow_schedule(run, it)
            loss, render, view = self.train_step(run, it)
            with torch.no_grad():
                self._refine(run, it, render, view)
            run.record(it, float(loss.detach()), started)
            self._log(run, it, result)
            if self._checkpoints.due(it, iterations, stage_follows):
                self._checkpoints.save(stage, it, self._training_state(run, result))
        result.stages.append(run.summary())

    def train_step(self, run: StageRun, it: int) -> tuple[torch.Tensor, RenderOutput, RGBView]:
        """Iteration ``it`` of ``run`` once its schedule is set: the epoch's next view rendered, the loss and its
        backward, the Gaussians' and the field's optimisers stepped; (loss, render, view). Densification is the
        stage loop's (:meth:`_refine`), which reads the render's gradients."""
        view = self._next_view()
        render, offsets = self._render(run, view, it)
        run.strategy.step_pre_backward(render)
        loss = self._loss(run, render, view, offsets)
        loss.backward()
        with torch.no_grad():
            run.opt.step()
            if run.net_opt is not None:
                run.net_opt.step()
                run.net_opt.zero_grad(set_to_none=True)
        return loss, render, view

    def _iterations(self, run: StageRun) -> Iterable[int]:
        """The stage's iterations still to run, through the progress wrapper where there is one."""
        steps: Iterable[int] = range(run.first_iteration, run.iterations + 1)
        if self.progress is not None:
            steps = self.progress(steps, desc=f"geometry ({run.name})", total=len(steps))
        return steps

    def _follow_schedule(self, run: StageRun, it: int) -> None:
        """SH degree and learning rates of iteration ``it``."""
        g, d = self.cfg.gaussians, self.cfg.deformation
        # one band more every scaled interval; never lowered (the deformation stage keeps the static
        # stage's degree, as the release's oneupSHdegree does)
        run.model.active_sh_degree = max(run.model.active_sh_degree, run.schedule.sh_degree(it - 1))
        if run.deformable is None:
            run.opt.set_lr("means", run.schedule.position_lr(it - 1, self.extent))
            return
        decay_steps = run.schedule.at(d.lr_decay_steps)
        run.opt.set_lr("means", self.extent * exponential_lr(it - 1, g.position_lr_init, g.position_lr_final,
                                                               decay_steps))
        for group in run.net_opt.param_groups:
            lo, hi, unit = {"mlp": (d.deformation_lr_final, d.deformation_lr_init, self.extent),
                            "grid": (d.grid_lr_final, d.grid_lr_init, self.extent),
                            "color": (d.color_lr_final, d.color_lr_init, 1.0)}[group["name"]]
            group["lr"] = unit * exponential_lr(it - 1, hi, lo, decay_steps, 0, d.deformation_lr_delay_mult)

    def _render(self, run: StageRun, view: RGBView, it: int) -> tuple[RenderOutput, Optional[tuple]]:
        """(the render of ``view``, the deformation offsets it used: None in a static stage)."""
        model, deformable = run.model, run.deformable
        offsets = None
        if deformable is None:
            means, quats, scales = model.means, model.quats, model.scales
            colors = model.colors(view.center, means)
        else:
            t_def = time.perf_counter()
            offsets = deformable.offsets(view.time, skip_static=self.cfg.deformation.static_skip)
            means, quats, scales = deformable.apply_offsets(offsets)
            run.deform_seconds[it - 1] = time.perf_counter() - t_def
            colors = deformable.colors(view.center, means, offsets)
        render = self.rasterize(means, quats, scales, model.opacities, colors, view.viewmat, view.K,
                                view.width, view.height, background=self.background, near=self.cfg.gaussians.near)
        return render, offsets

    def _loss(self, run: StageRun, render: RenderOutput, view: RGBView, offsets: Optional[tuple]) -> torch.Tensor:
        """Photometric loss; in the deformation stage plus the HexPlane regularisers and the motion prior."""
        g, d = self.cfg.gaussians, self.cfg.deformation
        if run.deformable is None:
            return photometric_loss(render.image, view.image, g.lambda_dssim, self.window)
        loss = photometric_loss(render.image, view.image, d.lambda_dssim, self.window)
        reg_weights = {"plane_tv": d.plane_tv_weight, "time_smoothness": d.time_smoothness_weight,
                       "l1_time_planes": d.l1_time_planes_weight}
        regs = run.deformable.field.hexplane.regularisers()
        loss = loss + sum(reg_weights[k] * v for k, v in regs.items())
        if d.motion_l1_weight > 0 and offsets is not None:
            if run.px_per_unit is None:
                run.px_per_unit = self.pixels_per_unit(run.model.means.detach())
            loss = loss + d.motion_l1_weight * motion_l1(offsets, run.px_per_unit, run.model.params["quats"], d)
        return loss

    def _refine(self, run: StageRun, it: int, render: RenderOutput, view: RGBView) -> None:
        """After the optimiser steps: the densification strategy, then the static check where one is due."""
        source, events = run.strategy.step_post_backward(it, run.model, run.opt, render, view.width, view.height)
        deformable = run.deformable
        if source is not None:
            run.px_per_unit = None
            if deformable is not None and deformable.dynamic_mask is not None:
                deformable.dynamic_mask = deformable.dynamic_mask[source]
        run.events.extend(events)
        if deformable is None or not self._static_check_due(run, it):
            return
        d = self.cfg.deformation
        means = run.model.means.detach()
        confine = None if d.recheck_outside_motion_box else self._static_outside_box()
        counts = deformable.update_static_mask(d, self.extent, px_per_unit=self.pixels_per_unit(means),
                                               may_move=None if confine is None else inside_box(means, confine))
        run.events.append({"iteration": it, "event": "static_check", **counts})

    def _static_check_due(self, run: StageRun, it: int) -> bool:
        """Whether the deformation stage looks for static Gaussians after ``it``: from the warm-up on,
        every check interval and at the stage's end (``static_skip`` only)."""
        d = self.cfg.deformation
        if not d.static_skip:
            return False
        warmup = max(1, int(round(d.static_warmup_fraction * run.iterations)))
        check_every = max(1, int(round(d.static_check_interval_fraction * run.iterations)))
        return it >= warmup and ((it - warmup) % check_every == 0 or it == run.iterations)

    def _log(self, run: StageRun, it: int, result: FitResult) -> None:
        """Every ``log_every`` iterations and at the stage's end: a history entry and a progress line."""
        log_every = self.cfg.log_every
        if not log_every or not (it % log_every == 0 or it == run.iterations):
            return
        deformable = run.deformable
        result.history.append({"stage": run.name, "iteration": it, "loss": run.last_loss,
                               "gaussians": run.model.num_gaussians,
                               "dynamic": None if deformable is None else deformable.num_dynamic()})
        print(f"[{run.name}] it {it}/{run.iterations} loss {run.last_loss:.4f} N {run.model.num_gaussians} "
              f"cpu {time.process_time() - run.cpu_start:.0f}s wall {time.perf_counter() - run.wall_start:.0f}s"
              + ("" if deformable is None else f" dynamic {deformable.num_dynamic()}"), flush=True)


def inside_box(points: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """(N,) bool: which of the (N, 3) ``points`` lie in the (2, 3) ``box`` [min; max] (faces included)."""
    box = box.to(points.device)
    return ((points >= box[0]) & (points <= box[1])).all(dim=1)


def motion_l1(offsets: tuple, px_per_unit: torch.Tensor, quats: torch.Tensor, d: DeformationConfig) -> torch.Tensor:
    """Mean L1 size, over all N Gaussians, of the motion in ``offsets`` (:class:`~methods.gaussians.model.DeformationOffsets`, or any
    sequence starting ``(rows, dx, ds, dq)``) in units of the static tolerances: position offsets in pixels
    (``px_per_unit``: (N,) pixels per world unit) over ``static_pixel_tol``, log-scale offsets over
    ``static_scale_tol``, quaternion offsets over ``static_rotation_tol`` x the (N, 4) ``quats``' norm."""
    rows, dx, ds, dq = offsets[:4]  # the colour offset is not motion
    ppu = px_per_unit if rows is None else px_per_unit[rows]
    qnorm = (quats if rows is None else quats[rows]).detach().norm(dim=1).clamp_min(1e-8)
    per_gaussian = (dx.abs().sum(1) * ppu / d.static_pixel_tol + ds.abs().sum(1) / d.static_scale_tol
                    + dq.abs().sum(1) / (d.static_rotation_tol * qnorm))
    # summed over the deformed Gaussians and divided by all of them: a Gaussian found static (skipped)
    # counts as zero, so the prior's weight does not grow as the dynamic set shrinks
    return per_gaussian.sum() / quats.shape[0]


# ---------------------------------------------------------------------------------------------------
# Rendering and evaluation
# ---------------------------------------------------------------------------------------------------
@torch.no_grad()
def render_view(model: object, view: RGBView, background: torch.Tensor, rasterize_fn: RasterizeFn,
                skip_static: bool = True, near: float = 0.01) -> torch.Tensor:
    """(H, W, 3) render of ``model`` (:class:`GaussianModel` or :class:`DeformableGaussians`) at ``view``."""
    if isinstance(model, DeformableGaussians):
        gm = model.gaussians
        means, quats, scales, colors = model.deform_with_colors(view.time, view.center, skip_static=skip_static)
    else:
        gm = model
        means, quats, scales = gm.means, gm.quats, gm.scales
        colors = gm.colors(view.center, means)
    out = rasterize_fn(means, quats, scales, gm.opacities, colors, view.viewmat, view.K, view.width,
                       view.height, background=background, near=near)
    return out.image.clamp(0.0, 1.0)


def evaluate(model: object, frames: Sequence[Frame], background: Optional[np.ndarray],
             rasterize_fn: Optional[RasterizeFn] = None, device: torch.device | str = "cpu",
             keep_renders: int = 0, skip_static: bool = True,
             region_masks: Optional[dict[str, np.ndarray]] = None) -> dict:
    """PSNR / SSIM (scikit-image, data range 1) of renders of ``frames`` against their images.

    Returns mean ``psnr``, ``ssim``, per-frame values, ``render_fps`` (deformation + rasterisation,
    images already in memory) and the first ``keep_renders`` (name, render, ground truth) triples as
    (H, W, 3) float arrays. ``skip_static=False`` deforms every Gaussian (4D-GS), for comparison.

    ``region_masks`` (frame name -> (H, W) bool, e.g. the pixels of moving parts) adds ``region_psnr``
    and ``rest_psnr``: the PSNR of the squared errors pooled over the masked pixels of all frames, and
    over all the other pixels (pooled, not averaged per frame: a region of a few pixels in one frame
    would otherwise swing the mean), with ``region_fraction`` of the pixels masked (NaN without masks).
    """
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    rasterize_fn = rasterize_fn or default_rasterize()
    views = make_views(frames, device)
    bg = torch.as_tensor(np.zeros(3) if background is None else np.asarray(background), dtype=torch.float32,
                         device=device)
    psnrs, ssims, renders = [], [], []
    region = np.zeros(2)  # (sum of squared errors, channel values) inside the masks
    rest = np.zeros(2)  # ... outside them
    render_seconds = 0.0
    for v in views:
        t0 = time.perf_counter()
        img = render_view(model, v, bg, rasterize_fn, skip_static=skip_static)
        render_seconds += time.perf_counter() - t0
        pred = img.cpu().numpy().astype(np.float64)
        gt = v.image.cpu().numpy().astype(np.float64)
        if region_masks is not None:
            mask = np.asarray(region_masks[v.name], dtype=bool)
            if mask.shape != gt.shape[:2]:
                raise ValueError(f"region mask of {v.name!r} is {mask.shape}, the frame is {gt.shape[:2]}")
            sq = ((pred - gt) ** 2).sum(axis=-1)  # (H, W) over channels
            region += (sq[mask].sum(), mask.sum() * gt.shape[-1])
            rest += (sq[~mask].sum(), (~mask).sum() * gt.shape[-1])
        psnrs.append(float(peak_signal_noise_ratio(gt, pred, data_range=1.0)))
        ssims.append(float(structural_similarity(gt, pred, channel_axis=-1, data_range=1.0)))
        if len(renders) < keep_renders:
            renders.append((v.name, pred.astype(np.float32), gt.astype(np.float32)))
    def pooled_psnr(acc: np.ndarray) -> float:
        if acc[1] == 0:
            return float("nan")
        return float("inf") if acc[0] == 0 else float(-10.0 * np.log10(acc[0] / acc[1]))

    return {"psnr": float(np.mean(psnrs)) if psnrs else float("nan"),
            "ssim": float(np.mean(ssims)) if ssims else float("nan"),
            "region_psnr": pooled_psnr(region), "rest_psnr": pooled_psnr(rest),
            "region_fraction": float(region[1] / (region[1] + rest[1])) if region_masks is not None and
            (region[1] + rest[1]) else float("nan"),
            "per_frame": [{"frame": v.name, "psnr": p, "ssim": s} for v, p, s in zip(views, psnrs, ssims)],
            "render_fps": len(views) / render_seconds if render_seconds > 0 else float("nan"),
            "renders": renders}
