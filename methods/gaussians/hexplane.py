"""4D-GS deformation field: a multi-resolution HexPlane over (x, y, z, t) and small MLP heads.

HexPlane (Cao & Johnson 2023; as used by 4D-GS, Wu et al. 2024): six 2-D feature planes, one per pair of
the four axes (xy, xz, yz spatial; xt, yt, zt spatio-temporal). A point's feature is the *product* over
the six planes of the bilinearly sampled plane features; features of all resolutions (``multires``) are
concatenated. An MLP trunk maps the feature to a hidden vector, and one head per deformed attribute maps
that to an offset of position, log-scale and (raw) quaternion.

The planes of one resolution are stored stacked, spatial ``[3, C, R, R]`` and temporal ``[3, C, T, R]``,
so each level costs two batched ``grid_sample`` calls instead of six.

Temporal regularisers (K-Planes / 4D-GS): total variation of the spatial planes, second-order smoothness
along t of the time planes, and L1 pulling the time planes towards 1 (no motion). The release computes
them but never adds them (a stage-name check); :meth:`HexPlane.regularisers` returns them for the
trainer to add.
"""

from __future__ import annotations

from typing import Optional, Union

import torch
import torch.nn.functional as F
from torch import nn

from .backends import native_cpu
from .config import DeformationConfig, HexPlaneConfig

# Axis pairs of the planes, (horizontal axis, vertical axis) in grid_sample's (x, y) order.
SPATIAL_PAIRS = ((0, 1), (0, 2), (1, 2))  # xy, xz, yz
TIME_PAIRS = ((0, 3), (1, 3), (2, 3))  # xt, yt, zt (t along the plane's rows)

TimeLike = Union[float, torch.Tensor]


def axis_warp(lo: torch.Tensor, hi: torch.Tensor, focus: Optional[torch.Tensor],
              share: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Knots of the per-axis piecewise-linear map from the box [``lo``, ``hi``] (each (3,)) to [-1, 1].

    Returns ((3, 4) world knots ``[lo, a, b, hi]``, (3, 4) normalised knots ``[-1, n_a, n_b, 1]``) where
    [a, b] is the motion box ``focus`` ((2, 3), clipped to the box) on that axis. The interval [a, b] gets
    ``max(share, (b - a) / (hi - lo))`` of the normalised range, the two outer intervals the rest in
    proportion to their lengths; ``focus=None`` or ``share <= 0``: uniform (knots at thirds).
    """
    lo, hi = lo.float(), hi.float()
    length = (hi - lo).clamp_min(1e-9)
    if focus is None or share <= 0:
        a, b = lo + length / 3.0, lo + 2.0 * length / 3.0
        inner = torch.full_like(lo, 1.0 / 3.0)
        before = torch.full_like(lo, 0.5)
    else:
        f = torch.as_tensor(focus, dtype=torch.float32).reshape(2, 3)
        a = torch.minimum(torch.maximum(f[0], lo), hi)
        b = torch.minimum(torch.maximum(f[1], a), hi)
        tiny = 1e-6 * length  # a motion box thinner than this on an axis is widened to it
        b = torch.minimum(torch.maximum(b, a + tiny), hi)
        a = torch.minimum(a, b - tiny)
        outer = (a - lo) + (hi - b)
        inner = torch.where(outer > 1e-9 * length, torch.clamp((b - a) / length, min=min(share, 1.0)),
                            torch.ones_like(lo))
        before = torch.where(outer > 1e-9 * length, (a - lo) / outer.clamp_min(1e-12), torch.full_like(lo, 0.5))
    n_a = -1.0 + 2.0 * (1.0 - inner) * before
    n_b = n_a + 2.0 * inner
    knots = torch.stack([lo, a, b, hi], dim=1)
    knots_n = torch.stack([torch.full_like(lo, -1.0), n_a, n_b, torch.ones_like(lo)], dim=1)
    return knots, knots_n


class HexPlane(nn.Module):
    """Six multi-resolution feature planes over the box ``bounds`` x [0, 1] (time)."""

    def __init__(self, cfg: HexPlaneConfig, bounds: torch.Tensor, time_resolution: int,
                 focus: Optional[torch.Tensor] = None):
        """``bounds``: (2, 3) [min, max] world box the spatial axes span; ``time_resolution``: T >= 2;
        ``focus``: (2, 3) [min, max] motion box that gets at least ``cfg.motion_cell_share`` of each axis's
        cells (``None``: cells spread evenly over ``bounds``)."""
        super().__init__()
        self.cfg = cfg
        bounds = torch.as_tensor(bounds, dtype=torch.float32).reshape(2, 3)
        size = (bounds[1] - bounds[0]).clamp_min(1e-6)
        self.register_buffer("box_min", bounds[0].clone())
        self.register_buffer("box_size", size.clone())
        knots, knots_n = axis_warp(bounds[0], bounds[0] + size, focus, cfg.motion_cell_share)
        self.register_buffer("warp_knots", knots)
        self.register_buffer("warp_knots_n", knots_n)
        self._note_warp()
        # a loaded state brings its own knots: whether they warp is read again from them
        self.register_load_state_dict_post_hook(lambda module, _keys: module._note_warp())
        self.time_resolution = max(2, int(time_resolution))
        self.spatial = nn.ParameterList()
        self.temporal = nn.ParameterList()
        c = cfg.output_dim
        for mult in cfg.multires:
            r = cfg.spatial_resolution * mult
            sp = torch.empty(3, c, r, r).uniform_(cfg.spatial_init_low, cfg.spatial_init_high)
            tp = torch.full((3, c, self.time_resolution, r), float(cfg.time_init_value))
            self.spatial.append(nn.Parameter(sp))
            self.temporal.append(nn.Parameter(tp))

    @property
    def feature_dim(self) -> int:
        return self.cfg.feature_dim

    def _note_warp(self) -> None:
        """Whether the knots differ from the uniform map (host-side flag, so the hot path need not check)."""
        uniform = torch.tensor([-1.0, -1.0 / 3.0, 1.0 / 3.0, 1.0], device=self.warp_knots_n.device)
        self.warped = not torch.allclose(self.warp_knots_n, uniform.expand_as(self.warp_knots_n), atol=1e-6)

    def normalise(self, xyz: torch.Tensor) -> torch.Tensor:
        """(N, 3) world points -> (N, 3) in [-1, 1] over the plane box (outside: clamped by sampling).

        With a motion box, per axis piecewise linear through the (3, 4) knots of :func:`axis_warp`; without
        one, the affine map of the release (the same numbers as before the motion box existed)."""
        if not self.warped:
            return (xyz - self.box_min) * (2.0 / self.box_size) - 1.0
        k, kn = self.warp_knots, self.warp_knots_n  # (3, 4) world, (3, 4) normalised
        slope = (kn[:, 1:] - kn[:, :-1]) / (k[:, 1:] - k[:, :-1]).clamp_min(1e-9)  # (3, 3)
        lower = kn[:, 0] + (xyz - k[:, 0]) * slope[:, 0]
        inner = kn[:, 1] + (xyz - k[:, 1]) * slope[:, 1]
        upper = kn[:, 2] + (xyz - k[:, 2]) * slope[:, 2]
        return torch.where(xyz < k[:, 1], lower, torch.where(xyz < k[:, 2], inner, upper))

    def cell_size(self) -> torch.Tensor:
        """(3,) world size of a base-resolution cell inside the motion box (the whole box when uniform)."""
        k, kn = self.warp_knots, self.warp_knots_n
        cells_per_unit = (kn[:, 2] - kn[:, 1]) / 2.0 * (self.cfg.spatial_resolution - 1)
        return (k[:, 2] - k[:, 1]) / cells_per_unit.clamp_min(1e-9)

    def forward(self, xyz: torch.Tensor, t: TimeLike) -> torch.Tensor:
        """Features at (N, 3) world points ``xyz`` and time ``t`` (scalar or (N,) in [0, 1]) -> (N, F).

        Time is mapped to [-1, 1] so the whole time axis is used (the release feeds t in [0, 1] to a
        [-1, 1] grid, i.e. uses only half of its time planes).
        """
        n = xyz.shape[0]
        p = self.normalise(xyz)
        tt = torch.as_tensor(t, dtype=p.dtype, device=p.device)
        tt = (tt * 2.0 - 1.0).expand(n) if tt.dim() == 0 else tt.reshape(n) * 2.0 - 1.0
        if native_cpu.supports(p) and native_cpu.kernels() is not None:
            # the compiled kernels: the same samples and products, several times faster on the CPU (above
            # all the backward, grid_sample's scatter)
            planes = [plane for level in zip(self.spatial, self.temporal) for plane in level]
            return native_cpu.HexPlaneSample.apply(p, tt, *planes)
        # (3, 1, N, 2) sample coordinates for the three spatial and the three time planes
        sp_coords = torch.stack([p[:, [a, b]] for a, b in SPATIAL_PAIRS], 0).unsqueeze(1)
        tp_coords = torch.stack([torch.stack([p[:, a], tt], -1) for a, _ in TIME_PAIRS], 0).unsqueeze(1)
        feats = []
        for sp, tp in zip(self.spatial, self.temporal):
            fs = F.grid_sample(sp, sp_coords, mode="bilinear", padding_mode="border", align_corners=True)
            ft = F.grid_sample(tp, tp_coords, mode="bilinear", padding_mode="border", align_corners=True)
            # (3, C, 1, N) each -> product over the six planes -> (N, C). Written out rather than prod(0):
            # prod's backward checks for zeros and divides, twice the time of these five products.
            prod = (fs[0] * fs[1]) * (fs[2] * ft[0]) * (ft[1] * ft[2])
            feats.append(prod.reshape(fs.shape[1], n).t())
        return torch.cat(feats, dim=1)

    def regularisers(self) -> dict[str, torch.Tensor]:
        """Unweighted temporal regularisers (scalars with gradients), summed over planes and levels.

        ``plane_tv``: mean squared first differences of each spatial plane along both axes (x2, K-Planes);
        ``time_smoothness``: mean squared second difference along t of each time plane;
        ``l1_time_planes``: mean |1 - value| of each time plane.
        """
        if native_cpu.supports(self.box_min) and native_cpu.kernels() is not None:
            # the compiled kernels: one pass per plane forward and one backward, in place of a dozen
            # full-size temporaries per level
            tv, smooth, l1 = native_cpu.PlaneRegularisers.apply(len(self.spatial), *self.spatial, *self.temporal)
            return {"plane_tv": tv, "time_smoothness": smooth, "l1_time_planes": l1}
        tv = smooth = l1 = self.box_min.new_zeros(())
        for sp, tp in zip(self.spatial, self.temporal):
            dh = (sp[:, :, 1:, :] - sp[:, :, :-1, :]).square().mean(dim=(1, 2, 3))
            dw = (sp[:, :, :, 1:] - sp[:, :, :, :-1]).square().mean(dim=(1, 2, 3))
            tv = tv + 2.0 * (dh + dw).sum()
            first = tp[:, :, 1:, :] - tp[:, :, :-1, :]
            if first.shape[2] >= 2:
                second = first[:, :, 1:, :] - first[:, :, :-1, :]
                smooth = smooth + second.square().mean(dim=(1, 2, 3)).sum()
            l1 = l1 + (1.0 - tp).abs().mean(dim=(1, 2, 3)).sum()
        return {"plane_tv": tv, "time_smoothness": smooth, "l1_time_planes": l1}


class DeformationField(nn.Module):
    """HexPlane + MLP trunk + heads: (x, t) -> offsets of position, log-scale and raw quaternion (and, with
    ``deform_color``, of the RGB colour)."""

    def __init__(self, cfg: DeformationConfig, bounds: torch.Tensor, time_resolution: int,
                 focus: Optional[torch.Tensor] = None):
        """``bounds``: (2, 3) world box of the HexPlane; ``time_resolution``: rows of the time planes;
        ``focus``: (2, 3) motion box given finer cells (:class:`HexPlane`)."""
        super().__init__()
        self.cfg = cfg
        self.hexplane = HexPlane(cfg.hexplane, bounds, time_resolution, focus)
        w = cfg.net_width
        layers: list[nn.Module] = [nn.Linear(self.hexplane.feature_dim, w)]
        for _ in range(cfg.net_depth):
            layers += [nn.ReLU(), nn.Linear(w, w)]
        self.trunk = nn.Sequential(*layers)
        # The heads' hidden layers (ReLU, Linear(W, W), ReLU) of all heads as one Linear(W, 3W):
        # mathematically three independent heads, one matmul instead of three.
        self.head_names = [name for name, on in (("position", cfg.deform_position), ("scale", cfg.deform_scale),
                                                 ("rotation", cfg.deform_rotation),
                                                 ("color", cfg.deform_color)) if on]
        self.head_dims = {"position": 3, "scale": 3, "rotation": 4, "color": 3}
        self.heads_hidden = nn.Linear(w, w * max(1, len(self.head_names)))
        self.heads_out = nn.ModuleDict({name: nn.Linear(w, self.head_dims[name]) for name in self.head_names})
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.xavier_uniform_(m.weight)
                nn.init.zeros_(m.bias)
        if cfg.zero_init_heads:
            for head in self.heads_out.values():
                nn.init.zeros_(head.weight)
        if "color" in self.heads_out:  # start the deformation stage from the static stage's colours
            nn.init.zeros_(self.heads_out["color"].weight)

    def features(self, xyz: torch.Tensor, t: TimeLike) -> torch.Tensor:
        """(N, 3) points at time t -> (N, F) HexPlane features."""
        return self.hexplane(xyz, t)

    def forward(self, xyz: torch.Tensor, t: TimeLike) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(N, 3) canonical points at time t -> offsets ((N, 3) position, (N, 3) log-scale, (N, 4) quat).

        Disabled heads return zeros.
        """
        return self.forward_all(xyz, t)[:3]

    def forward_all(self, xyz: torch.Tensor, t: TimeLike) -> tuple:
        """:meth:`forward`'s three offsets and the (N, 3) RGB offset of the colour head (``None`` when
        ``deform_color`` is off), from one evaluation."""
        n = xyz.shape[0]
        h = self.trunk(self.hexplane(xyz, t))
        # ReLU in place on the heads' hidden layer: a Linear's backward does not need its output, and each
        # (N, heads x W) temporary costs milliseconds on the CPU.
        hidden = torch.relu_(self.heads_hidden(torch.relu(h)))
        if not self.head_names:
            out = {}
        else:
            # The heads' output layers as one block-diagonal Linear(heads x W -> sum of head dims): the same
            # independent maps, one matmul, and no split and re-join of the hidden tensor.
            heads = [self.heads_out[name] for name in self.head_names]
            joined = F.linear(hidden, torch.block_diag(*(head.weight for head in heads)),
                              torch.cat([head.bias for head in heads]))
            out = dict(zip(self.head_names, joined.split([self.head_dims[name] for name in self.head_names], 1)))
        return (*(out[name] if name in out else xyz.new_zeros(n, self.head_dims[name])
                  for name in ("position", "scale", "rotation")), out.get("color"))

    def mlp_parameters(self) -> list[nn.Parameter]:
        """The trunk's and heads' weights, the colour head's output layer excepted."""
        return [p for name, p in self.named_parameters()
                if not name.startswith("hexplane.") and not name.startswith("heads_out.color.")]

    def color_parameters(self) -> list[nn.Parameter]:
        """The colour head's output layer (its own learning rate: RGB units, not scene units); [] without."""
        return list(self.heads_out["color"].parameters()) if "color" in self.heads_out else []

    def grid_parameters(self) -> list[nn.Parameter]:
        return list(self.hexplane.parameters())
