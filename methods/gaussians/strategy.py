"""Adaptive density control of 3D-GS as a strategy object, after gsplat's ``strategy`` design.

A :class:`DensificationStrategy` serves one training stage and owns what densification carries from
one iteration to the next: the per-Gaussian statistics (:class:`DensifyStats`), the stage's Gaussian
budget (``GaussianConfig.gradual_cap``) and the schedule of growing, pruning and opacity resets. The
training loop calls :meth:`~DensificationStrategy.step_pre_backward` on each render before the
backward pass and :meth:`~DensificationStrategy.step_post_backward` once the optimisers have stepped.

Densification follows 3D-GS: Gaussians whose mean view-space positional gradient (NDC units) exceeds
the threshold are cloned when small and split when large; transparent or huge ones are pruned; the total
never exceeds the scene's cap, highest-gradient candidates first.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from .backends.torch_cpu import quat_to_rotmat
from .config import GaussianConfig, Schedule
from .model import PARAM_NAMES, GaussianModel, inverse_sigmoid
from .optimizer import GaussianOptimizer
from .rasterize import RenderOutput


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


class DensificationStrategy:
    """When and how one training stage grows, prunes and resets the Gaussians (3D-GS schedule)."""

    def __init__(self, cfg: GaussianConfig, schedule: Schedule, iterations: int, extent: float, cap: int,
                 num_gaussians: int, generator: torch.Generator, device: torch.device | str = "cpu"):
        """``iterations``: the stage's length; ``extent``: the scene extent (size thresholds);
        ``cap``: the most Gaussians the scene gets; ``num_gaussians``: the count the stage starts with;
        ``generator``: draws the positions of split children."""
        self.cfg = cfg
        self.schedule = schedule
        self.iterations = iterations
        self.extent = extent
        self.cap = cap
        self.generator = generator
        self.device = device
        self.stats = DensifyStats.zeros(num_gaussians, device)
        self.start_count = num_gaussians
        """Gaussians at the stage's start: the gradual budget grows from there to the cap."""

    def budget(self, iteration: int) -> int:
        """Gaussians allowed after ``iteration`` (see ``GaussianConfig.gradual_cap``)."""
        if not self.cfg.gradual_cap or self.start_count >= self.cap:
            return self.cap
        window = self.schedule.densify_until_iteration()
        return int(self.start_count + (self.cap - self.start_count) * min(1.0, iteration / window))

    def step_pre_backward(self, render: RenderOutput) -> None:
        """Keep the gradient of the projected means of ``render`` (the densification statistic)."""
        means2d = render.means2d
        if means2d.requires_grad and not means2d.is_leaf:
            means2d.retain_grad()

    @torch.no_grad()
    def step_post_backward(self, iteration: int, model: GaussianModel, opt: GaussianOptimizer,
                           render: RenderOutput, width: int, height: int) -> tuple[Optional[torch.Tensor], list[dict]]:
        """Account for ``render`` (a ``width`` x ``height`` view) after ``iteration``, then densify and prune
        and reset opacities where the schedule says so.

        Returns ``(source, events)``: ``source`` as :func:`densify_and_prune` gives it where the Gaussians
        were rebuilt (per-Gaussian buffers follow it), else None; ``events`` the stage log's entries.
        """
        if render.means2d.grad is not None:
            self.stats.update(render.means2d.grad, render.radii, render.visible, width, height)
        source, events = None, []
        if self.schedule.densify_now(iteration):
            source, counts = densify_and_prune(model, opt, self.stats, self.cfg, self.extent, self.budget(iteration),
                                               self.schedule.screen_pruning_active(iteration), self.cfg.max_screen_px,
                                               self.generator)
            self.stats = DensifyStats.zeros(model.num_gaussians, self.device)
            events.append({"iteration": iteration, "event": "densify", **counts})
        if self.schedule.reset_opacity_now(iteration, self.iterations):
            reset_opacity(model, opt, self.cfg.opacity_reset_value)
            events.append({"iteration": iteration, "event": "opacity_reset"})
        return source, events

    def state_dict(self) -> dict:
        """What a resumed stage needs to go on exactly as an uninterrupted one."""
        return {"grad_sum": self.stats.grad_sum, "count": self.stats.count, "max_radius": self.stats.max_radius,
                "start_count": self.start_count}

    def load_state_dict(self, state: dict) -> None:
        self.stats = DensifyStats(*(state[k].to(self.device) for k in ("grad_sum", "count", "max_radius")))
        self.start_count = int(state["start_count"])


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
    rot = quat_to_rotmat(p["quats"][rep])  # normalises the quaternions itself
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
