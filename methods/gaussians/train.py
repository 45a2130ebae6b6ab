"""3D-GS and 4D-GS training on a :class:`~benchmark.core.scene.Scene` (one training view per iteration).

* :meth:`Trainer.fit_3dgs`: the 3D-GS recipe (static reference).
* :meth:`Trainer.fit_4dgs`: 4D-GS = a 3D-GS static stage, then a deformation stage that trains the
  HexPlane deformation field together with the canonical Gaussians, with the temporal regularisers
  added to the loss (the release never adds them) and, optionally, the deformation evaluated only on
  Gaussians that move (:meth:`~methods.gaussians.model.DeformableGaussians.update_static_mask`).

Densification follows 3D-GS: Gaussians whose mean view-space positional gradient (NDC units) exceeds
the threshold are cloned when small and split when large; transparent or huge ones are pruned; the total
never exceeds the scene's cap (:func:`gaussian_cap`), highest-gradient candidates first.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from benchmark.core.atomic import atomic_path
from benchmark.core.errors import InputError
from benchmark.core.scene import Camera, Frame, Scene

from .config import DeformationConfig, GaussianConfig, ReconConfig, Schedule, exponential_lr
from .hexplane import DeformationField
from .model import PARAM_NAMES, DeformableGaussians, GaussianModel, inverse_sigmoid

RasterizeFn = Callable[..., object]


def default_rasterize() -> RasterizeFn:
    from .rasterize import rasterize

    return rasterize


# ---------------------------------------------------------------------------------------------------
# Views, scene size, model size
# ---------------------------------------------------------------------------------------------------
@dataclass
class View:
    """One frame as tensors, ready to render and compare."""

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


def camera_tensors(camera: Camera, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """((4, 4) world-to-camera, (3, 3) K) float32 tensors of ``camera``."""
    viewmat = torch.as_tensor(camera.world_to_camera, dtype=torch.float32, device=device)
    K = torch.as_tensor(camera.K, dtype=torch.float32, device=device)
    return viewmat, K


def make_views(frames: Sequence[Frame], device: torch.device | str = "cpu", with_images: bool = True) -> list[View]:
    """Load ``frames`` as :class:`View`s (images decoded once; 128-px scenes hold easily in memory)."""
    views = []
    for fr in frames:
        # The rasterizer is a pinhole: distortion coefficients (HyperNeRF) are ignored, as in 4D-GS.
        viewmat, K = camera_tensors(fr.camera, device)
        img = torch.as_tensor(np.ascontiguousarray(fr.image(), dtype=np.float32), device=device) if with_images \
            else torch.empty(0)
        fg = fr.alpha() if with_images else None
        views.append(View(fr.name, img, viewmat, K, fr.camera.width, fr.camera.height, float(fr.time),
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


def foreground_fraction(views: Sequence[View], background: Optional[np.ndarray], threshold: float) -> float:
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


def gaussian_cap(views: Sequence[View], background: Optional[np.ndarray], cfg: GaussianConfig) -> int:
    """Most Gaussians this scene gets: ``gaussians_per_foreground_pixel`` x mean foreground pixels of a
    training view, within [min_gaussians, max_gaussians]."""
    if not views:
        return cfg.min_gaussians
    pixels = float(np.mean([v.width * v.height for v in views]))
    fg = foreground_fraction(views, background, cfg.foreground_threshold)
    cap = int(round(cfg.gaussians_per_foreground_pixel * fg * pixels))
    return int(min(max(cap, cfg.min_gaussians), cfg.max_gaussians))


def initial_gaussians(scene: Scene, cfg: GaussianConfig, cap: int, generator: torch.Generator,
                      device: torch.device | str = "cpu", views: Optional[Sequence[View]] = None) -> GaussianModel:
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


def seen_by_any(points: torch.Tensor, views: Sequence[View], near: float) -> torch.Tensor:
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
# Optimiser that follows densification
# ---------------------------------------------------------------------------------------------------
class GaussianOptimizer:
    """Adam over the Gaussian tensors, one group per tensor, whose moments follow densification."""

    def __init__(self, model: GaussianModel, cfg: GaussianConfig, extent: float):
        self.model = model
        lrs = {"means": cfg.position_lr_init * extent, "sh_dc": cfg.feature_lr,
               "sh_rest": cfg.feature_lr / cfg.feature_rest_lr_divisor, "opacity_logits": cfg.opacity_lr,
               "log_scales": cfg.scaling_lr, "quats": cfg.rotation_lr}
        self.optim = torch.optim.Adam([{"params": [model.params[k]], "lr": lrs[k], "name": k} for k in PARAM_NAMES],
                                      lr=0.0, eps=cfg.adam_eps)
        self.groups = {g["name"]: g for g in self.optim.param_groups}

    def set_lr(self, name: str, lr: float) -> None:
        self.groups[name]["lr"] = lr

    def load_state_dict(self, state: dict) -> None:
        """Moments and learning rates as saved (torch replaces the group dicts: ``groups`` follows)."""
        self.optim.load_state_dict(state)
        self.groups = {g["name"]: g for g in self.optim.param_groups}

    def step(self) -> None:
        self.optim.step()
        self.optim.zero_grad(set_to_none=True)

    def rebuild(self, new_values: dict[str, torch.Tensor], keep_rows: torch.Tensor, n_added: int) -> None:
        """Replace every tensor by ``new_values[name]`` whose rows are ``old[keep_rows]`` followed by
        ``n_added`` new rows; Adam moments follow the kept rows and start at zero for new ones."""
        for name in PARAM_NAMES:
            group = self.groups[name]
            old = group["params"][0]
            new = new_values[name].detach().contiguous().requires_grad_(True)
            state = self.optim.state.pop(old, None)
            if state:
                for key in ("exp_avg", "exp_avg_sq"):
                    moment = state[key][keep_rows]
                    pad = moment.new_zeros((n_added,) + moment.shape[1:])
                    state[key] = torch.cat([moment, pad], 0)
                self.optim.state[new] = state
            group["params"][0] = new
            self.model.params[name] = new

    def reset_moments(self, name: str) -> None:
        state = self.optim.state.get(self.groups[name]["params"][0])
        if state:
            state["exp_avg"].zero_()
            state["exp_avg_sq"].zero_()


@dataclass
class DensifyStats:
    """Per-Gaussian accumulators between two densifications."""

    grad_sum: torch.Tensor
    """(N,) sum of view-space positional gradient norms (NDC units) over the views that saw it."""
    count: torch.Tensor
    """(N,) number of views that saw it."""
    max_radius: torch.Tensor
    """(N,) largest screen radius (pixels) over those views."""

    @staticmethod
    def zeros(n: int, device: torch.device | str = "cpu") -> "DensifyStats":
        return DensifyStats(torch.zeros(n, device=device), torch.zeros(n, device=device),
                            torch.zeros(n, device=device))

    def update(self, means2d_grad: torch.Tensor, radii: torch.Tensor, visible: torch.Tensor,
               width: int, height: int) -> None:
        """Add one view: ``means2d_grad`` (N, 2) d loss / d pixel position, ``radii`` (N,), ``visible`` (N,)."""
        # Pixel -> NDC gradient (NDC spans 2 over the image): the threshold 0.0002 is in NDC units.
        scale = means2d_grad.new_tensor([width * 0.5, height * 0.5])
        norm = (means2d_grad * scale).norm(dim=-1)
        vis = visible.float()
        self.grad_sum += norm * vis
        self.count += vis
        self.max_radius = torch.where(visible, torch.maximum(self.max_radius, radii.float()), self.max_radius)


@torch.no_grad()
def densify_and_prune(model: GaussianModel, opt: GaussianOptimizer, stats: DensifyStats, cfg: GaussianConfig,
                      extent: float, cap: int, size_pruning: bool, max_screen_px: Optional[float],
                      generator: torch.Generator, prune_only: bool = False) -> tuple[torch.Tensor, dict[str, int]]:
    """One 3D-GS densification + pruning step, within the cap.

    Returns ``(source, counts)``: ``source`` (N_new,) gives, for every Gaussian after the step, the index
    of the Gaussian it came from (itself, or the parent of a clone / split child), so callers can carry
    per-Gaussian buffers along; ``counts`` = cloned, split, pruned, total.
    """
    p = model.params
    n = model.num_gaussians
    device = p["means"].device
    grads = torch.nan_to_num(stats.grad_sum / stats.count, nan=0.0)
    scales = torch.exp(p["log_scales"])
    big = scales.amax(1) > cfg.percent_dense * extent
    candidates = (grads >= cfg.densify_grad_threshold) if not prune_only else torch.zeros(n, dtype=torch.bool,
                                                                                             device=device)
    # Budget: a clone adds one Gaussian, a split adds split_count - 1; best gradients first.
    room = cap - n
    cand_idx = candidates.nonzero().squeeze(1)
    if cand_idx.numel():
        order = cand_idx[grads[cand_idx].argsort(descending=True)]
        cost = torch.where(big[order], cfg.split_count - 1, 1)
        order = order[cost.cumsum(0) <= max(room, 0)]
        candidates = torch.zeros_like(candidates)
        candidates[order] = True
    clone = candidates & ~big
    split = candidates & big
    clone_idx = clone.nonzero().squeeze(1)
    split_idx = split.nonzero().squeeze(1)

    # Children: clones are copies; split children are sampled from the parent Gaussian and shrunk.
    k = cfg.split_count
    rep = split_idx.repeat(k)
    std = scales[rep]
    local = torch.randn(std.shape, generator=generator).to(device) * std
    rot = quat_to_rotmat(F.normalize(p["quats"][rep], dim=-1))
    split_means = p["means"][rep] + torch.einsum("nij,nj->ni", rot, local)
    children = {name: torch.cat([p[name][clone_idx], p[name][rep]], 0) for name in PARAM_NAMES}
    children["means"] = torch.cat([p["means"][clone_idx], split_means], 0)
    children["log_scales"] = torch.cat([p["log_scales"][clone_idx],
                                        torch.log(scales[rep] / cfg.split_scale_divisor)], 0)
    child_source = torch.cat([clone_idx, rep])

    ext = {name: torch.cat([p[name], children[name]], 0) for name in PARAM_NAMES}
    source = torch.cat([torch.arange(n, device=device), child_source])
    radius = torch.cat([stats.max_radius, torch.zeros(child_source.numel(), device=device)])
    keep = torch.ones(source.numel(), dtype=torch.bool, device=device)
    keep[split_idx] = False  # split parents are replaced by their children
    prune = torch.sigmoid(ext["opacity_logits"]) < cfg.min_opacity
    if size_pruning:
        if max_screen_px is not None:
            prune |= radius > max_screen_px
        prune |= torch.exp(ext["log_scales"]).amax(1) > cfg.max_world_fraction * extent
    if bool((keep & ~prune).any()):
        keep &= ~prune
    keep_old = keep[:n].nonzero().squeeze(1)
    keep_new = keep[n:].nonzero().squeeze(1)
    new_values = {name: torch.cat([ext[name][keep_old], ext[name][n + keep_new]], 0) for name in PARAM_NAMES}
    opt.rebuild(new_values, keep_old, int(keep_new.numel()))
    final_source = torch.cat([source[keep_old], source[n + keep_new]])
    counts = {"cloned": int(clone_idx.numel()), "split": int(split_idx.numel()),
              "pruned": int((~keep).sum()) - int(split_idx.numel()), "total": model.num_gaussians}
    return final_source, counts


@torch.no_grad()
def reset_opacity(model: GaussianModel, opt: GaussianOptimizer, value: float) -> None:
    """Clamp every opacity to at most ``value`` and forget its Adam moments (3D-GS opacity reset)."""
    logits = model.params["opacity_logits"]
    logits.copy_(torch.minimum(logits, inverse_sigmoid(torch.tensor(value))))
    opt.reset_moments("opacity_logits")


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """(N, 4) unit quaternions (w, x, y, z) -> (N, 3, 3) rotation matrices."""
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(-1, 3, 3)


def saved_tensor_bytes(fn: Callable[[], object]) -> tuple[object, int]:
    """Run ``fn`` and return (its result, bytes of the tensors autograd saved for backward during it).

    This is the activation memory a step pays for the computation; RSS cannot see it reliably on CPU.
    """
    total = 0
    seen: set[int] = set()

    def pack(t: torch.Tensor):
        nonlocal total
        key = t.untyped_storage().data_ptr() if t.device.type != "meta" else id(t)
        if key not in seen:
            seen.add(key)
            total += t.untyped_storage().nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        result = fn()
    return result, total


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
class Checkpointing:
    """Where and how often a fit saves its whole training state, so that an interrupted fit resumes.

    A resumed fit ends exactly as an uninterrupted one on the CPU (the state includes every random
    generator, the Adam moments, the densification statistics and the loop's bookkeeping; on CUDA the
    rasterizer's atomic adds make any two runs differ in the last bits); its ``fit_seconds`` add the
    time spent before the interruption. The file is removed when the fit completes."""

    path: Path
    """The checkpoint file (written atomically: temp file + rename)."""
    key: str
    """What the fit is (e.g. the geometry cache key): a checkpoint of another fit is ignored."""
    every_seconds: float = 120.0
    """Wall seconds between saves, plus a save where one stage ends and another begins; saving reads
    the state and never changes it."""


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
        self._total_iterations = iterations
        resume = self._load_checkpoint("3dgs", iterations)
        opt = self._gaussians_from(resume, model)
        self._start_clock(resume)
        result = FitResult("3dgs", model, 0.0, extent=self.extent, cap=self.cap)
        sched = Schedule(c.gaussians, c.reference_scale(iterations))
        self._run_stage("static", model, opt, None, None, sched, iterations, result, resume)
        self._finish(result, resume)
        return result

    def fit_4dgs(self) -> FitResult:
        """4D-GS: static stage, then deformation stage (canonical Gaussians + deformation field)."""
        c = self.cfg
        self._reset_random()
        model = initial_gaussians(self.scene, c.gaussians, self.cap, self.generator, self.device, self.views)
        self._total_iterations = c.static_iterations + c.deformation_iterations
        resume = self._load_checkpoint("4dgs", self._total_iterations)
        opt = self._gaussians_from(resume, model)
        result = FitResult("4dgs", model, 0.0, extent=self.extent, cap=self.cap)
        self._start_clock(resume)
        in_deformation = resume is not None and resume["stage"] == "deformation"
        if c.static_iterations > 0 and not in_deformation:
            self._run_stage("static", model, opt, None, None, Schedule(c.gaussians, c.static_stage_scale()),
                            c.static_iterations, result, resume, stage_follows=c.deformation_iterations > 0)
        d = c.deformation
        # the box is read from the Gaussians as the static stage ends (a resumed fit has moved them since)
        bounds = resume["field_bounds"] if in_deformation else self.hexplane_bounds(model)
        if in_deformation:
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
        if not in_deformation and start_box is not None:
            deformable.dynamic_mask = inside_box(model.params["means"].detach(), start_box)
            result.field_box["static_at_start"] = int((~deformable.dynamic_mask).sum())
        result.model = deformable
        groups = [{"params": field_.mlp_parameters(), "lr": d.deformation_lr_init * self.extent, "name": "mlp"},
                  {"params": field_.grid_parameters(), "lr": d.grid_lr_init * self.extent, "name": "grid"}]
        if field_.color_parameters():
            groups.append({"params": field_.color_parameters(), "lr": d.color_lr_init, "name": "color"})
        net_opt = torch.optim.Adam(groups, lr=0.0, eps=c.gaussians.adam_eps)
        if in_deformation:
            field_.load_state_dict(resume["field"])
            net_opt.load_state_dict(resume["net_opt"])
            mask = resume["dynamic_mask"]
            deformable.dynamic_mask = None if mask is None else mask.to(self.device)
        if c.deformation_iterations > 0:
            sched = Schedule(c.gaussians, c.deformation_stage_scale(), densify_until=d.densify_until_iter,
                             opacity_resets=d.opacity_reset_interval is not None,
                             reset_interval=d.opacity_reset_interval)
            self._run_stage("deformation", model, opt, deformable, net_opt, sched, c.deformation_iterations,
                            result, resume if in_deformation else None)
        self._finish(result, resume)
        return result

    # -- checkpoints --------------------------------------------------------------------------------
    def _load_checkpoint(self, kind: str, total_iterations: int) -> Optional[dict]:
        """The saved state of this very fit, or None (no checkpointing, no file, another fit's, unreadable)."""
        ck = self.checkpoint
        if ck is None or not Path(ck.path).is_file():
            return None
        try:
            state = torch.load(ck.path, map_location=self.device, weights_only=True)
        except Exception:  # a corrupt or incompatible checkpoint is never trusted: the fit starts over
            return None
        if (not isinstance(state, dict) or state.get("key") != ck.key or state.get("kind") != kind
                or state.get("total_iterations") != total_iterations):
            return None
        return state

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

    def _start_clock(self, resume: Optional[dict]) -> None:
        """Fit time counts from the fit's start, the time spent before an interruption included."""
        before_wall = 0.0 if resume is None else float(resume["fit_seconds"])
        before_cpu = 0.0 if resume is None else float(resume["fit_cpu_seconds"])
        self._fit_start = (time.perf_counter() - before_wall, time.process_time() - before_cpu)

    def _finish(self, result: FitResult, resume: Optional[dict]) -> None:
        result.fit_seconds = time.perf_counter() - self._fit_start[0]
        result.fit_cpu_seconds = time.process_time() - self._fit_start[1]
        if resume is not None:
            result.resumed_at = {"stage": resume["stage"], "iteration": int(resume["iteration"])}
        if self.checkpoint is not None:
            Path(self.checkpoint.path).unlink(missing_ok=True)  # the caller keeps the fitted model

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
        if points.shape[0] > 1_000_000:  # quantile's input limit; an even subsample keeps the percentiles
            points = points[torch.linspace(0, points.shape[0] - 1, 1_000_000, device=points.device).long()]
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
    def _next_view(self) -> View:
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
        c = self.cfg
        g = c.gaussians
        d: DeformationConfig = c.deformation
        stats = DensifyStats.zeros(model.num_gaussians, self.device)
        events: list[dict] = []
        iter_seconds = np.zeros(iterations)
        deform_seconds = np.zeros(iterations)
        lambda_dssim = g.lambda_dssim if deformable is None else d.lambda_dssim
        reg_weights = {"plane_tv": d.plane_tv_weight, "time_smoothness": d.time_smoothness_weight,
                       "l1_time_planes": d.l1_time_planes_weight}
        warmup = max(1, int(round(d.static_warmup_fraction * iterations)))
        check_every = max(1, int(round(d.static_check_interval_fraction * iterations)))
        decay_steps = sched.at(d.lr_decay_steps)
        log_every = c.log_every
        start_count = model.num_gaussians
        window = sched.densify_until_iteration()

        def budget(it: int) -> int:
            """Gaussians allowed after iteration ``it`` (see GaussianConfig.gradual_cap)."""
            if not g.gradual_cap or start_count >= self.cap:
                return self.cap
            return int(start_count + (self.cap - start_count) * min(1.0, it / window))

        last_loss = first_loss = float("nan")
        px_per_unit: Optional[torch.Tensor] = None  # (N,) for the motion prior; dropped at each densification
        first_iteration, cpu_before, wall_before = 1, 0.0, 0.0
        if resume is not None and resume["stage"] == stage:
            loop = resume["loop"]
            stats = DensifyStats(*(loop[k].to(self.device) for k in ("grad_sum", "count", "max_radius")))
            events = list(loop["events"])
            iter_seconds = loop["iter_seconds"].cpu().numpy().astype(np.float64)
            deform_seconds = loop["deform_seconds"].cpu().numpy().astype(np.float64)
            start_count = int(loop["start_count"])
            last_loss, first_loss = float(loop["last_loss"]), float(loop["first_loss"])
            px_per_unit = None if loop["px_per_unit"] is None else loop["px_per_unit"].to(self.device)
            cpu_before, wall_before = float(loop["cpu_seconds"]), float(loop["wall_seconds"])
            result.stages, result.history = list(resume["stages"]), list(resume["history"])
            first_iteration = int(resume["iteration"]) + 1
        cpu_start, wall_start = time.process_time() - cpu_before, time.perf_counter() - wall_before
        last_save = time.perf_counter()

        def save(it: int) -> None:
            """The whole training state after iteration ``it`` (see :class:`Checkpointing`)."""
            ck = self.checkpoint
            state: dict = {
                "key": ck.key, "kind": result.kind, "total_iterations": self._total_iterations,
                "stage": stage, "iteration": it,
                "params": {k: v.detach() for k, v in model.params.items()},
                "active_sh_degree": model.active_sh_degree, "opt": opt.optim.state_dict(),
                "generator": self.generator.get_state(), "numpy_rng": self.rng.bit_generator.state,
                "view_order": list(self._order), "torch_rng": torch.get_rng_state(),
                "fit_seconds": time.perf_counter() - self._fit_start[0],
                "fit_cpu_seconds": time.process_time() - self._fit_start[1],
                "stages": list(result.stages), "history": list(result.history),
                "loop": {"grad_sum": stats.grad_sum, "count": stats.count, "max_radius": stats.max_radius,
                         "events": events, "iter_seconds": torch.from_numpy(iter_seconds.copy()),
                         "deform_seconds": torch.from_numpy(deform_seconds.copy()), "start_count": start_count,
                         "last_loss": last_loss, "first_loss": first_loss, "px_per_unit": px_per_unit,
                         "cpu_seconds": time.process_time() - cpu_start,
                         "wall_seconds": time.perf_counter() - wall_start}}
            if deformable is not None:
                mask = deformable.dynamic_mask
                state.update({"field": deformable.field.state_dict(), "net_opt": net_opt.state_dict(),
                              "dynamic_mask": None if mask is None else mask.detach(),
                              "field_bounds": self._field_bounds, "field_focus": self._field_focus})
            with atomic_path(ck.path) as tmp:
                torch.save(state, tmp)

        steps: Iterable[int] = range(first_iteration, iterations + 1)
        if self.progress is not None:
            steps = self.progress(steps, desc=f"geometry ({stage})", total=len(steps))
        for it in steps:
            t_start = time.perf_counter()
            # one band more every scaled interval; never lowered (the deformation stage keeps the static
            # stage's degree, as the release's oneupSHdegree does)
            model.active_sh_degree = max(model.active_sh_degree, sched.sh_degree(it - 1))
            if deformable is None:
                opt.set_lr("means", sched.position_lr(it - 1, self.extent))
            else:
                opt.set_lr("means", self.extent * exponential_lr(it - 1, g.position_lr_init, g.position_lr_final,
                                                                   decay_steps))
                for group in net_opt.param_groups:
                    lo, hi, unit = {"mlp": (d.deformation_lr_final, d.deformation_lr_init, self.extent),
                                    "grid": (d.grid_lr_final, d.grid_lr_init, self.extent),
                                    "color": (d.color_lr_final, d.color_lr_init, 1.0)}[group["name"]]
                    group["lr"] = unit * exponential_lr(it - 1, hi, lo, decay_steps, 0, d.deformation_lr_delay_mult)
            view = self._next_view()
            if deformable is None:
                means, quats, scales = model.means, model.quats, model.scales
            else:
                t_def = time.perf_counter()
                offsets = deformable.offsets(view.time, skip_static=d.static_skip)
                means, quats, scales = deformable.apply_offsets(offsets)
                deform_seconds[it - 1] = time.perf_counter() - t_def
            colors = (model.colors(view.center, means) if deformable is None
                      else deformable.colors(view.center, means, offsets))
            out = self.rasterize(means, quats, scales, model.opacities, colors, view.viewmat, view.K,
                                 view.width, view.height, background=self.background, near=g.near)
            means2d = out.means2d
            if means2d.requires_grad and not means2d.is_leaf:
                means2d.retain_grad()
            loss = photometric_loss(out.image, view.image, lambda_dssim, self.window)
            if deformable is not None:
                regs = deformable.field.hexplane.regularisers()
                loss = loss + sum(reg_weights[k] * v for k, v in regs.items())
                if d.motion_l1_weight > 0 and offsets is not None:
                    if px_per_unit is None:
                        px_per_unit = self.pixels_per_unit(model.means.detach())
                    loss = loss + d.motion_l1_weight * motion_l1(offsets, px_per_unit, model.params["quats"], d)
            loss.backward()
            with torch.no_grad():
                if means2d.grad is not None:
                    stats.update(means2d.grad, out.radii, out.visible, view.width, view.height)
                opt.step()
                if net_opt is not None:
                    net_opt.step()
                    net_opt.zero_grad(set_to_none=True)
                if sched.densify_now(it):
                    px_per_unit = None
                    source, counts = densify_and_prune(model, opt, stats, g, self.extent, budget(it),
                                                       sched.screen_pruning_active(it), g.max_screen_px,
                                                       self.generator)
                    if deformable is not None and deformable.dynamic_mask is not None:
                        deformable.dynamic_mask = deformable.dynamic_mask[source]
                    stats = DensifyStats.zeros(model.num_gaussians, self.device)
                    events.append({"iteration": it, "event": "densify", **counts})
                if sched.reset_opacity_now(it, iterations):
                    reset_opacity(model, opt, g.opacity_reset_value)
                    events.append({"iteration": it, "event": "opacity_reset"})
                if (deformable is not None and d.static_skip and it >= warmup
                        and ((it - warmup) % check_every == 0 or it == iterations)):
                    means = model.means.detach()
                    confine = None if d.recheck_outside_motion_box else self._static_outside_box()
                    counts = deformable.update_static_mask(
                        d, self.extent, px_per_unit=self.pixels_per_unit(means),
                        may_move=None if confine is None else inside_box(means, confine))
                    events.append({"iteration": it, "event": "static_check", **counts})
            last_loss = float(loss.detach())
            if it == 1:
                first_loss = last_loss
            iter_seconds[it - 1] = time.perf_counter() - t_start
            if log_every and (it % log_every == 0 or it == iterations):
                result.history.append({"stage": stage, "iteration": it, "loss": last_loss,
                                       "gaussians": model.num_gaussians,
                                       "dynamic": None if deformable is None else deformable.num_dynamic()})
                print(f"[{stage}] it {it}/{iterations} loss {last_loss:.4f} N {model.num_gaussians} "
                      f"cpu {time.process_time() - cpu_start:.0f}s wall {time.perf_counter() - wall_start:.0f}s"
                      + ("" if deformable is None else f" dynamic {deformable.num_dynamic()}"), flush=True)
            if self.checkpoint is not None:
                due = time.perf_counter() - last_save >= self.checkpoint.every_seconds
                if (due and it < iterations) or (it == iterations and stage_follows):
                    save(it)
                    last_save = time.perf_counter()
        tail = iter_seconds[iterations // 2:] if iterations > 1 else iter_seconds
        summary = {"stage": stage, "iterations": iterations, "seconds": float(iter_seconds.sum()),
                   "cpu_seconds": time.process_time() - cpu_start,
                   "ms_per_iteration": 1000 * float(iter_seconds.mean()) if iterations else 0.0,
                   "ms_per_iteration_second_half": 1000 * float(tail.mean()) if len(tail) else 0.0,
                   "first_loss": first_loss, "final_loss": last_loss, "gaussians": model.num_gaussians,
                   "schedule_scale": sched.scale, "events": events}
        if deformable is not None:
            summary["deform_ms_per_iteration_second_half"] = 1000 * float(deform_seconds[iterations // 2:].mean()) \
                if iterations > 1 else 1000 * float(deform_seconds.mean())
            summary["dynamic_gaussians"] = deformable.num_dynamic()
        result.stages.append(summary)


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
def render_view(model: object, view: View, background: torch.Tensor, rasterize_fn: RasterizeFn,
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


def measure_static_skip(deformable: DeformableGaussians, views: Sequence[View], background: torch.Tensor,
                        rasterize_fn: RasterizeFn, lambda_dssim: float = 0.2, repeats: int = 8) -> dict:
    """What evaluating the deformation only on dynamic Gaussians saves, on a trained model.

    For each mode (``skip``: field on ``dynamic_mask`` only; ``full``: on every Gaussian) and the same
    ``repeats`` views: CPU milliseconds of the deformation forward + backward alone and of a whole
    training step (deformation, rasterisation, loss, backward; no optimiser step), and the bytes autograd
    saves for backward (activation memory) for each. Gradients are cleared afterwards.
    """
    gm = deformable.gaussians
    window = gaussian_window(11, 1.5).to(gm.params["means"].device)
    params = list(gm.params.values()) + list(deformable.field.parameters())
    picks = [views[i % len(views)] for i in range(repeats + 1)]

    def deform_only(view: View, skip: bool) -> torch.Tensor:
        means, quats, scales = deformable.deform(view.time, skip_static=skip)
        return means.sum() + quats.sum() + scales.sum()

    def full_step(view: View, skip: bool) -> torch.Tensor:
        means, quats, scales, colors = deformable.deform_with_colors(view.time, view.center, skip_static=skip)
        out = rasterize_fn(means, quats, scales, gm.opacities, colors, view.viewmat,
                           view.K, view.width, view.height, background=background)
        return photometric_loss(out.image, view.image, lambda_dssim, window)

    result: dict = {"gaussians": deformable.num_gaussians, "dynamic": deformable.num_dynamic()}
    result["dynamic_fraction"] = result["dynamic"] / max(1, result["gaussians"])
    for label, fn in (("deform", deform_only), ("step", full_step)):
        for skip in (True, False):
            mode = "skip" if skip else "full"
            cpu = []
            saved = 0
            for k, view in enumerate(picks):
                c0 = time.process_time()
                loss, nbytes = saved_tensor_bytes(lambda: fn(view, skip))
                loss.backward()
                if k > 0:  # the first call warms caches up
                    cpu.append(time.process_time() - c0)
                saved = max(saved, nbytes)
                for p in params:
                    p.grad = None
            result[f"{label}_cpu_ms_{mode}"] = 1000 * float(np.mean(cpu))
            result[f"{label}_saved_mib_{mode}"] = saved / 2 ** 20
    return result
