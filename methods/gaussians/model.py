"""Gaussian models: static 3D-GS (:class:`GaussianModel`) and deformable 4D-GS (:class:`DeformableGaussians`).

Parameters are stored raw and activated on read, as in 3D-GS:

* ``means`` (N, 3) world positions;
* ``log_scales`` (N, 3), activated with ``exp``;
* ``quats`` (N, 4) raw ``(w, x, y, z)``, normalised on read;
* ``opacity_logits`` (N,), activated with ``sigmoid``;
* ``sh_dc`` (N, 1, 3) and ``sh_rest`` (N, (D+1)^2 - 1, 3) spherical-harmonics colour coefficients; colour
  = SH(view direction) + 0.5, clamped at 0 (3D-GS convention), evaluated up to the active degree.

All per-Gaussian state lives in ``params`` (leaf tensors the trainer optimises and resizes).
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple, Optional

import numpy as np
import torch
import torch.nn.functional as F

from .config import DeformationConfig, GaussianConfig
from .hexplane import DeformationField, TimeLike

SH_C0 = 0.28209479177387814
"""Degree-0 spherical-harmonics constant: colour = SH_C0 * dc + 0.5."""

PARAM_NAMES = ("means", "sh_dc", "sh_rest", "opacity_logits", "log_scales", "quats")


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """(N, 3) RGB in [0, 1] -> (N, 3) degree-0 coefficients that reproduce it."""
    return (rgb - 0.5) / SH_C0


def inverse_sigmoid(x: torch.Tensor) -> torch.Tensor:
    return torch.log(x / (1.0 - x))


class GaussianModel:
    """A set of 3-D Gaussians with SH colour (3D-GS)."""

    def __init__(self, params: dict[str, torch.Tensor], sh_degree: int):
        """``params``: the tensors of :data:`PARAM_NAMES`, shapes as in the module docstring."""
        missing = [k for k in PARAM_NAMES if k not in params]
        if missing:
            raise ValueError(f"missing Gaussian parameters {missing}")
        n = params["means"].shape[0]
        expected_rest = (sh_degree + 1) ** 2 - 1
        if params["sh_rest"].shape[1:] != (expected_rest, 3):
            raise ValueError(f"sh_rest must be (N, {expected_rest}, 3) for degree {sh_degree}")
        for name in PARAM_NAMES:
            if params[name].shape[0] != n:
                raise ValueError(f"{name} has {params[name].shape[0]} rows, means has {n}")
        self.params = {k: params[k].detach().float().requires_grad_(True) for k in PARAM_NAMES}
        self.max_sh_degree = int(sh_degree)
        self.active_sh_degree = 0

    # -- construction -----------------------------------------------------------------------------
    @staticmethod
    def from_points(points: np.ndarray, colors: Optional[np.ndarray], cfg: GaussianConfig,
                    device: torch.device | str = "cpu") -> "GaussianModel":
        """Gaussians centred on (N, 3) ``points`` with (N, 3) RGB ``colors`` (grey when ``None``).

        Initial scales are isotropic: the RMS distance to the ``cfg.init_knn`` nearest neighbours.
        """
        pts = torch.as_tensor(np.asarray(points, dtype=np.float32).reshape(-1, 3), device=device)
        n = pts.shape[0]
        if colors is None:
            rgb = torch.full((n, 3), 0.5, device=device)
        else:
            rgb = torch.as_tensor(np.asarray(colors, dtype=np.float32).reshape(-1, 3), device=device).clamp(0, 1)
        dist = knn_mean_distance(pts, cfg.init_knn)
        k_rest = (cfg.sh_degree + 1) ** 2 - 1
        params = {
            "means": pts,
            "sh_dc": rgb_to_sh_dc(rgb).unsqueeze(1),
            "sh_rest": torch.zeros(n, k_rest, 3, device=device),
            "opacity_logits": inverse_sigmoid(torch.full((n,), cfg.init_opacity, device=device)),
            "log_scales": torch.log(dist).unsqueeze(1).repeat(1, 3),
            "quats": torch.tensor([1.0, 0.0, 0.0, 0.0], device=device).repeat(n, 1),
        }
        return GaussianModel(params, cfg.sh_degree)

    # -- activated views ----------------------------------------------------------------------------
    @property
    def num_gaussians(self) -> int:
        return int(self.params["means"].shape[0])

    @property
    def means(self) -> torch.Tensor:
        return self.params["means"]

    @property
    def scales(self) -> torch.Tensor:
        """(N, 3) activated scales."""
        return torch.exp(self.params["log_scales"])

    @property
    def quats(self) -> torch.Tensor:
        """(N, 4) unit quaternions (w, x, y, z)."""
        return F.normalize(self.params["quats"], dim=-1)

    @property
    def opacities(self) -> torch.Tensor:
        """(N,) activated opacities."""
        return torch.sigmoid(self.params["opacity_logits"])

    def sh_coeffs(self) -> torch.Tensor:
        """(N, (D+1)^2, 3) coefficients up to the active degree D."""
        k = (self.active_sh_degree + 1) ** 2
        return torch.cat([self.params["sh_dc"], self.params["sh_rest"][:, : k - 1]], dim=1)

    def colors(self, camera_center: torch.Tensor, means: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(N, 3) RGB seen from the (3,) ``camera_center``; ``means`` (N, 3) overrides positions (4D-GS)."""
        means = self.params["means"] if means is None else means
        if self.active_sh_degree == 0:
            # Degree 0 is view-independent: skip the directions entirely.
            return (SH_C0 * self.params["sh_dc"][:, 0] + 0.5).clamp_min(0.0)
        from .backends import native_cpu

        if native_cpu.supports(means) and self.active_sh_degree <= 3 and native_cpu.kernels() is not None:
            # the compiled kernel: the same colours in one pass per Gaussian, forward and backward
            return native_cpu.ShColor.apply(means, camera_center, self.params["sh_dc"], self.params["sh_rest"],
                                            self.active_sh_degree)
        from .sh import eval_sh

        dirs = F.normalize(means - camera_center.reshape(1, 3), dim=-1)
        return (eval_sh(self.active_sh_degree, self.sh_coeffs(), dirs) + 0.5).clamp_min(0.0)

    # -- persistence ---------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"params": {k: v.detach().cpu() for k, v in self.params.items()},
                "max_sh_degree": self.max_sh_degree, "active_sh_degree": self.active_sh_degree}

    @staticmethod
    def from_state_dict(state: dict, device: torch.device | str = "cpu") -> "GaussianModel":
        model = GaussianModel({k: v.to(device) for k, v in state["params"].items()}, state["max_sh_degree"])
        model.active_sh_degree = int(state["active_sh_degree"])
        return model


def knn_mean_distance(points: torch.Tensor, k: int) -> torch.Tensor:
    """(N, 3) points -> (N,) root-mean-square distance to the k nearest other points (3D-GS initial scale).

    A k-d tree (scipy): O(N log N), where brute force would be O(N^2) for 100k-point clouds.
    Coincident points get a small positive floor.
    """
    from scipy.spatial import cKDTree

    n = points.shape[0]
    if n <= 1:
        return torch.full((n,), 0.01, device=points.device)
    k = min(k, n - 1)
    pts = points.detach().cpu().double().numpy()
    dist, _ = cKDTree(pts).query(pts, k=k + 1)  # the first neighbour is the point itself
    mean = np.sqrt(np.square(np.asarray(dist, dtype=np.float64).reshape(n, k + 1)[:, 1:]).mean(axis=1))
    floor = float(np.linalg.norm(pts.max(0) - pts.min(0))) * 1e-4 + 1e-7
    return torch.as_tensor(np.maximum(mean, floor), dtype=torch.float32, device=points.device)


def deformation_field_from_state(config: dict, weights: dict, time_resolution: int) -> DeformationField:
    """Rebuild a saved :class:`DeformationField` from its config as a plain dict (``hexplane`` nested),
    its ``state_dict`` and its time resolution (the HexPlane bounds are read from the weights)."""
    from .config import HexPlaneConfig

    cfg_dict = dict(config)
    hp = dict(cfg_dict.pop("hexplane"))
    hp["multires"] = tuple(hp["multires"])
    cfg = DeformationConfig(hexplane=HexPlaneConfig(**hp), **cfg_dict)
    box_min = weights["hexplane.box_min"]
    field = DeformationField(cfg, torch.stack([box_min, box_min + weights["hexplane.box_size"]]), time_resolution)
    weights = dict(weights)
    for name in ("warp_knots", "warp_knots_n"):  # fields saved before the motion box: uniform cells
        weights.setdefault(f"hexplane.{name}", getattr(field.hexplane, name))
    field.load_state_dict(weights)
    return field


class DeformationOffsets(NamedTuple):
    """The deformation field's output for the Gaussians of ``rows`` at one time."""

    rows: Optional[torch.Tensor]
    """(M,) indices of the deformed Gaussians; ``None``: all N, in order."""
    position: torch.Tensor
    """(M, 3) position offsets."""
    scale: torch.Tensor
    """(M, 3) log-scale offsets."""
    rotation: torch.Tensor
    """(M, 4) raw quaternion offsets."""
    color: Optional[torch.Tensor]
    """(M, 3) RGB offsets; ``None`` without a colour head (``DeformationConfig.deform_color``)."""


class DeformableGaussians:
    """4D-GS: canonical :class:`GaussianModel` + :class:`DeformationField` evaluated at time t.

    ``dynamic_mask`` (N,) bool marks the Gaussians the deformation is evaluated on; the others are static
    (their constant offset has been folded into their canonical parameters, see :meth:`update_static_mask`).
    ``None`` means all are dynamic.
    """

    def __init__(self, gaussians: GaussianModel, field: DeformationField):
        self.gaussians = gaussians
        self.field = field
        self.dynamic_mask: Optional[torch.Tensor] = None

    @property
    def num_gaussians(self) -> int:
        return self.gaussians.num_gaussians

    def num_dynamic(self) -> int:
        return self.num_gaussians if self.dynamic_mask is None else int(self.dynamic_mask.sum())

    def deform(self, t: TimeLike, skip_static: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Gaussians at time ``t`` in [0, 1]: ((N, 3) means, (N, 4) unit quats, (N, 3) activated scales).

        With ``skip_static`` the field is evaluated only on ``dynamic_mask``; static Gaussians keep
        their canonical parameters.
        """
        return self.apply_offsets(self.offsets(t, skip_static))

    def offsets(self, t: TimeLike, skip_static: bool = True) -> Optional[DeformationOffsets]:
        """The field's :class:`DeformationOffsets` at time ``t`` (all Gaussians, or with ``skip_static`` those of
        ``dynamic_mask``); ``None`` when ``skip_static`` leaves no dynamic Gaussian."""
        mask = self.dynamic_mask if skip_static else None
        means = self.gaussians.params["means"]
        if mask is None:
            return DeformationOffsets(None, *self.field.forward_all(means, t))
        if not bool(mask.any()):
            return None
        rows = mask.nonzero().squeeze(1)
        return DeformationOffsets(rows, *self.field.forward_all(means[rows], t))

    def colors(self, camera_center: torch.Tensor, means: torch.Tensor,
               offsets: Optional[DeformationOffsets]) -> torch.Tensor:
        """(N, 3) RGB seen from ``camera_center`` with the Gaussians at ``means``, plus the colour offsets of
        :meth:`offsets` (when the field has a colour head)."""
        rgb = self.gaussians.colors(camera_center, means)
        if offsets is None or offsets.color is None:
            return rgb
        dc = offsets.color
        return (rgb + dc if offsets.rows is None else rgb.index_add(0, offsets.rows, dc)).clamp_min(0.0)

    def deform_with_colors(self, t: TimeLike, camera_center: torch.Tensor, skip_static: bool = True
                           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`deform` and the (N, 3) colours seen from ``camera_center`` at time ``t``."""
        offsets = self.offsets(t, skip_static)
        means, quats, scales = self.apply_offsets(offsets)
        return means, quats, scales, self.colors(camera_center, means, offsets)

    def apply_offsets(self, offsets: Optional[DeformationOffsets]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Canonical Gaussians plus :meth:`offsets` -> ((N, 3) means, (N, 4) unit quats, (N, 3) scales)."""
        p = self.gaussians.params
        means, log_scales, quats = p["means"], p["log_scales"], p["quats"]
        if offsets is not None:
            rows, dx, ds, dq, _ = offsets
            if rows is None:
                means, log_scales, quats = means + dx, log_scales + ds, quats + dq
            else:
                # Out-of-place index_add: canonical + offsets on the dynamic rows only; gradients reach the
                # canonical tensors everywhere and the field only through the dynamic rows.
                means = means.index_add(0, rows, dx)
                log_scales = log_scales.index_add(0, rows, ds)
                quats = quats.index_add(0, rows, dq)
        return means, F.normalize(quats, dim=-1), torch.exp(log_scales)

    def hexplane_features(self, t: TimeLike, means: Optional[torch.Tensor] = None) -> torch.Tensor:
        """(N, F) HexPlane features at time ``t`` at (N, 3) ``means`` (default: the canonical positions).

        F = output_dim x len(multires). The status network of 4D LangSplat reads these (frozen).
        """
        means = self.gaussians.params["means"] if means is None else means
        return self.field.features(means, t)

    @torch.no_grad()
    def deformation_variation(self, times: torch.Tensor, chunk: int = 65536) -> dict[str, torch.Tensor]:
        """Per Gaussian, over the (K,) ``times``: the range (max - min) and mean of each offset.

        Returns ``{"position", "scale", "rotation", "color"}`` -> (N,) largest per-component range, and
        ``{"mean_position", "mean_scale", "mean_rotation", "mean_color"}`` -> (N, 3|3|4|3) offsets averaged
        over times (colour: zeros without a colour head). The field is evaluated on every Gaussian (static
        ones included), in chunks.
        """
        p = self.gaussians.params
        n = self.num_gaussians
        dev = p["means"].device
        parts = {"position": slice(0, 3), "scale": slice(3, 6), "rotation": slice(6, 10), "color": slice(10, 13)}
        result = {k: torch.zeros(n, device=dev) for k in parts}
        means_out = {k: torch.zeros(n, s.stop - s.start, device=dev) for k, s in parts.items()}
        for start in range(0, n, chunk):
            xyz = p["means"][start:start + chunk]
            lo = hi = total = None
            for t in times.tolist():
                dx, ds, dq, dc = self.field.forward_all(xyz, t)
                off = torch.cat([dx, ds, dq, torch.zeros_like(dx) if dc is None else dc], dim=1)  # (n_chunk, 13)
                lo = off if lo is None else torch.minimum(lo, off)
                hi = off if hi is None else torch.maximum(hi, off)
                total = off if total is None else total + off
            rng, mean = hi - lo, total / len(times)
            for name, cols in parts.items():
                result[name][start:start + chunk] = rng[:, cols].amax(1)
                means_out[name][start:start + chunk] = mean[:, cols]
        result.update({f"mean_{k}": v for k, v in means_out.items()})
        return result

    @torch.no_grad()
    def update_static_mask(self, cfg: DeformationConfig, extent: float, times: Optional[torch.Tensor] = None,
                           px_per_unit: Optional[torch.Tensor] = None,
                           may_move: Optional[torch.Tensor] = None) -> dict[str, int]:
        """Mark Gaussians whose deformation does not vary over time as static (and back).

        A Gaussian is static when, over ``cfg.static_time_samples`` times, its position offset varies by
        less than ``static_pixel_tol`` pixels (``px_per_unit``: (N,) pixels per world unit at its nearest
        training camera; without it, less than ``static_position_tol x extent``), its log-scale offset by
        less than ``static_scale_tol``, its quaternion offset by less than ``static_rotation_tol x |q|`` and its
        RGB offset (colour head) by less than ``static_color_tol``. ``may_move`` (N,) bool: only these may be
        dynamic (the others are static whatever their offsets; None: all may).
        Newly static Gaussians get their time-mean offset folded into the canonical parameters, so what
        is rendered does not jump; Gaussians that became dynamic again get it taken back out.
        Returns counts: ``{"static", "dynamic", "newly_static", "newly_dynamic"}``.
        """
        if times is None:
            times = torch.linspace(0.0, 1.0, cfg.static_time_samples)
        p = self.gaussians.params
        var = self.deformation_variation(times)
        qnorm = p["quats"].norm(dim=1).clamp_min(1e-8)
        if px_per_unit is not None:
            still = var["position"] * px_per_unit < cfg.static_pixel_tol
        else:
            still = var["position"] < cfg.static_position_tol * extent
        static = (still
                  & (var["scale"] < cfg.static_scale_tol)
                  & (var["rotation"] < cfg.static_rotation_tol * qnorm)
                  & (var["color"] < cfg.static_color_tol))
        if may_move is not None:
            static = static | ~may_move
        was_dynamic = (torch.ones_like(static) if self.dynamic_mask is None else self.dynamic_mask)
        newly_static = static & was_dynamic
        newly_dynamic = ~static & ~was_dynamic
        sign = newly_static.float() - newly_dynamic.float()  # +1 fold in, -1 take out, 0 unchanged
        p["means"].add_(sign[:, None] * var["mean_position"])
        p["log_scales"].add_(sign[:, None] * var["mean_scale"])
        p["quats"].add_(sign[:, None] * var["mean_rotation"])
        p["sh_dc"][:, 0].add_(sign[:, None] * var["mean_color"] / SH_C0)  # RGB = SH_C0 x DC + ...
        self.dynamic_mask = ~static
        return {"static": int(static.sum()), "dynamic": int((~static).sum()),
                "newly_static": int(newly_static.sum()), "newly_dynamic": int(newly_dynamic.sum())}

    def state_dict(self) -> dict:
        import dataclasses

        return {"gaussians": self.gaussians.state_dict(),
                "field": {k: v.detach().cpu() for k, v in self.field.state_dict().items()},
                "field_config": dataclasses.asdict(self.field.cfg),
                "time_resolution": int(self.field.hexplane.time_resolution),
                "dynamic_mask": None if self.dynamic_mask is None else self.dynamic_mask.cpu()}

    @staticmethod
    def from_state_dict(state: dict, device: torch.device | str = "cpu") -> "DeformableGaussians":
        field = deformation_field_from_state(state["field_config"], state["field"], state["time_resolution"])
        model = DeformableGaussians(GaussianModel.from_state_dict(state["gaussians"], device), field.to(device))
        mask = state.get("dynamic_mask")
        model.dynamic_mask = None if mask is None else mask.to(device)
        return model


def save_model(path: str | Path, model: "GaussianModel | DeformableGaussians") -> None:
    """Save a model's tensors with ``torch.save``, atomically."""
    from benchmark.core.atomic import atomic_path

    with atomic_path(path) as tmp:
        torch.save({"kind": type(model).__name__, "state": model.state_dict()}, tmp)
