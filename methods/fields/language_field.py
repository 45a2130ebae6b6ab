"""The time-agnostic language field: per-Gaussian latent features on ONE frozen geometry.

4D LangSplat (and LangSplat before it) attaches a low-dimensional latent feature to every Gaussian
for each of the three SAM levels (small / middle / large) and renders it like a colour; the
autoencoder of :mod:`methods.fields.autoencoder` maps rendered latents back to the language space.
The release trains a separate Gaussian model per level, each relearning the RGB geometry; here the
three levels are three groups of channels of ONE model, rendered together in one rasterizer call
(``levels x latent`` channels, 9 by default), on a geometry that is fitted once and then frozen.

* :class:`FrozenGeometry`: a fitted static 3D-GS or deformable 4D-GS reduced to what shapes the
  Gaussians (means, rotations, scales, opacities, deformation field); colours are dropped.
  :meth:`FrozenGeometry.at` gives the Gaussians at time ``t`` (a static geometry ignores ``t``).
  Features do not deform, as in the paper: only positions, scales and rotations move.
* :class:`LanguageField`: the ``[N, levels * latent]`` feature table and its rendering.
* :func:`train_language_field`: L1 between rendered and target latents inside the valid masks of
  every level (pixels covered by a mask of that level), geometry frozen, Adam.
* :func:`render_levels` / :func:`decode_for_relevance`: the query side (render the latent maps at a
  frame's camera and time, decode each level, and reduce the decoded features to the few
  coordinates the LERF relevance needs, exactly, so the protocol's :func:`query_levels` runs on
  small tensors at any image size).

Everything takes a ``device`` and stays on it; numpy appears only where supervision comes in.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable, Iterator, Optional, Sequence

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from benchmark.core.scene import Camera
from methods.gaussians.optimizer import fast_adam
from methods.gaussians.rasterize import camera_tensors

from .configs import LanguageFieldConfig


# ---------------------------------------------------------------------------------------------------
# Frozen geometry
# ---------------------------------------------------------------------------------------------------
@dataclass
class GaussianState:
    """Activated Gaussians at one time (all detached)."""

    means: torch.Tensor
    """[N, 3] world positions."""
    quats: torch.Tensor
    """[N, 4] unit quaternions (w, x, y, z)."""
    scales: torch.Tensor
    """[N, 3] activated scales."""
    opacities: torch.Tensor
    """[N] activated opacities."""

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.means, self.quats, self.scales, self.opacities))


class FrozenGeometry:
    """A fitted Gaussian geometry (static 3D-GS or deformable 4D-GS), colours dropped, nothing trainable.

    Wraps the Gaussian core's own classes so deformation is exactly what training used
    (:meth:`methods.gaussians.model.DeformableGaussians.deform`).
    """

    def __init__(self, model) -> None:
        """``model``: a :class:`~methods.gaussians.model.GaussianModel` or
        :class:`~methods.gaussians.model.DeformableGaussians`."""
        from methods.gaussians.model import DeformableGaussians, GaussianModel

        if isinstance(model, DeformableGaussians):
            self.kind = "4dgs"
            gaussians = model.gaussians
        elif isinstance(model, GaussianModel):
            self.kind = "3dgs"
            gaussians = model
        else:
            raise TypeError(f"expected GaussianModel or DeformableGaussians, got {type(model).__name__}")
        p = gaussians.params
        n = p["means"].shape[0]
        dev = p["means"].device
        # Shape only: SH colour is irrelevant to the language field (degree 0, zero coefficients).
        shape_params = {"means": p["means"].detach(), "quats": p["quats"].detach(),
                        "log_scales": p["log_scales"].detach(), "opacity_logits": p["opacity_logits"].detach(),
                        "sh_dc": torch.zeros(n, 1, 3, device=dev), "sh_rest": torch.zeros(n, 0, 3, device=dev)}
        self.gaussians = GaussianModel(shape_params, sh_degree=0)
        for t in self.gaussians.params.values():
            t.requires_grad_(False)
        self.deformable = None
        if self.kind == "4dgs":
            model.field.requires_grad_(False)
            self.deformable = DeformableGaussians(self.gaussians, model.field)
            self.deformable.dynamic_mask = None if model.dynamic_mask is None else model.dynamic_mask.detach().clone()

    @property
    def num_gaussians(self) -> int:
        return self.gaussians.num_gaussians

    @property
    def device(self) -> torch.device:
        return self.gaussians.params["means"].device

    @property
    def is_dynamic(self) -> bool:
        return self.deformable is not None

    @torch.no_grad()
    def at(self, t: float) -> GaussianState:
        """The Gaussians at time ``t`` in [0, 1] (a static geometry ignores ``t``). The latest time's state is
        kept: a time-sensitive answer deforms to its frame's time twice (the mask, then the status field)."""
        key = 0.0 if self.deformable is None else float(t)
        last = getattr(self, "_last_state", None)
        if last is not None and last[0] == key:
            return last[1]
        g = self.gaussians
        if self.deformable is None:
            means, quats, scales = g.means, g.quats, g.scales
        else:
            means, quats, scales = self.deformable.deform(key, skip_static=True)
        state = GaussianState(means, quats, scales, g.opacities)
        self._last_state = (key, state)
        return state

    @torch.no_grad()
    def hexplane_features(self, t: float, means: Optional[torch.Tensor] = None) -> torch.Tensor:
        """[N, F] frozen HexPlane features at time ``t`` (the status field's input); 4D-GS only."""
        if self.deformable is None:
            raise ValueError("a static 3D-GS geometry has no HexPlane features")
        return self.deformable.hexplane_features(float(t), means)

    # -- persistence ---------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        p = self.gaussians.params
        state = {"kind": self.kind,
                 "shape": {k: p[k].detach().cpu() for k in ("means", "quats", "log_scales", "opacity_logits")}}
        if self.deformable is not None:
            fld = self.deformable.field
            state["deformation"] = {
                "config": dataclasses.asdict(fld.cfg),
                "time_resolution": int(fld.hexplane.time_resolution),
                "state": {k: v.detach().cpu() for k, v in fld.state_dict().items()},
                "dynamic_mask": None if self.deformable.dynamic_mask is None else self.deformable.dynamic_mask.cpu(),
            }
        return state

    @staticmethod
    def from_state_dict(state: dict, device: torch.device | str = "cpu") -> "FrozenGeometry":
        from methods.gaussians.model import DeformableGaussians, GaussianModel, deformation_field_from_state

        shape = {k: v.to(device) for k, v in state["shape"].items()}
        n = shape["means"].shape[0]
        params = {**shape, "sh_dc": torch.zeros(n, 1, 3, device=device), "sh_rest": torch.zeros(n, 0, 3, device=device)}
        gm = GaussianModel(params, sh_degree=0)
        if state["kind"] == "3dgs":
            return FrozenGeometry(gm)
        d = state["deformation"]
        fld = deformation_field_from_state(d["config"], d["state"], d["time_resolution"])
        deformable = DeformableGaussians(gm, fld.to(device))
        deformable.dynamic_mask = None if d["dynamic_mask"] is None else d["dynamic_mask"].to(device)
        return FrozenGeometry(deformable)


def random_geometry(num_gaussians: int, width: int, height: int, *, seed: int = 0,
                    device: torch.device | str = "cpu") -> tuple[FrozenGeometry, Camera]:
    """A deformable geometry of random Gaussians filling the view of a ``width x height`` camera, and
    that camera: what the speed measurements time the query and status stages on at a chosen scale.

    The Gaussians lie in a slab 2 units in front of the camera, sized so that together they cover the
    image a few times over (like a fitted scene), with random orientations and opacities; the
    deformation field is a freshly initialised HexPlane (protocol sizes) over the slab.
    """
    from methods.gaussians.config import DeformationConfig, HexPlaneConfig
    from methods.gaussians.hexplane import DeformationField
    from methods.gaussians.model import DeformableGaussians, GaussianModel

    dev = torch.device(device)
    gen = torch.Generator().manual_seed(seed)
    n = int(num_gaussians)
    focal = float(max(width, height))
    depth = 2.0
    half_w, half_h = 0.5 * width / focal * depth, 0.5 * height / focal * depth
    means = torch.stack([(torch.rand(n, generator=gen) * 2 - 1) * half_w, (torch.rand(n, generator=gen) * 2 - 1) * half_h,
                         (torch.rand(n, generator=gen) - 0.5) * 0.5], 1)
    scale = float(np.sqrt(4 * half_w * half_h / n)) * 0.8  # footprints tile the image a few times over
    params = {"means": means, "sh_dc": torch.zeros(n, 1, 3), "sh_rest": torch.zeros(n, 0, 3),
              "opacity_logits": torch.randn(n, generator=gen), "log_scales": torch.log(
                  torch.full((n, 3), scale) * torch.exp(0.3 * torch.randn(n, 3, generator=gen))),
              "quats": torch.randn(n, 4, generator=gen)}
    box = torch.tensor([[-half_w, -half_h, -0.5], [half_w, half_h, 0.5]])
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        fld = DeformationField(DeformationConfig(hexplane=HexPlaneConfig()), box, time_resolution=50)
    geometry = FrozenGeometry(DeformableGaussians(GaussianModel({k: v.to(dev) for k, v in params.items()}, 0),
                                                  fld.to(dev)))
    w2c = np.eye(4)
    w2c[2, 3] = depth
    return geometry, Camera(width, height, focal, focal, width / 2, height / 2, w2c)


# ---------------------------------------------------------------------------------------------------
# The field
# ---------------------------------------------------------------------------------------------------
class LanguageField(nn.Module):
    """Per-Gaussian latent features of every level: ``features`` [N, levels * latent_dim].

    Channel ``l * latent_dim + k`` is latent coordinate ``k`` of level ``l``.
    """

    def __init__(self, num_gaussians: int, cfg: Optional[LanguageFieldConfig] = None, *,
                 generator: Optional[torch.Generator] = None, device: torch.device | str = "cpu") -> None:
        super().__init__()
        self.cfg = cfg or LanguageFieldConfig()
        init = torch.zeros(num_gaussians, self.cfg.channels)
        if self.cfg.init_std > 0:
            init = self.cfg.init_std * torch.randn(num_gaussians, self.cfg.channels, generator=generator)
        self.features = nn.Parameter(init.to(device))

    def render(self, state: GaussianState, camera: Camera) -> torch.Tensor:
        """[L, H, W, d] rendered latent maps of every level at ``camera`` (one rasterizer call).

        Differentiable in :attr:`features` only (``state`` is frozen); background 0.
        """
        return self.render_with_alpha(state, camera)[0]

    def render_with_alpha(self, state: GaussianState, camera: Camera,
                          prepared=None) -> tuple[torch.Tensor, torch.Tensor]:
        """(:meth:`render`'s [L, H, W, d] latent maps, [H, W] accumulated opacity) from one rasterizer call;
        ``prepared``: the view's :meth:`prepare` (the same numbers, without projecting and laying out the
        Gaussians again)."""
        from methods.gaussians.rasterize import rasterize

        viewmat, K, w, h = camera_tensors(camera, self.features.device)
        if prepared is not None:
            image, alpha = prepared.render(self.features)
        else:
            out = rasterize(state.means, state.quats, state.scales, state.opacities, self.features, viewmat, K, w, h,
                            near=self.cfg.near, backend=self.cfg.render_backend, channel_chunk=self.cfg.channels)
            image, alpha = out.image, out.alpha
        latents = image.view(h, w, self.cfg.num_levels, self.cfg.latent_dim).permute(2, 0, 1, 3)
        return latents, alpha.reshape(h, w)

    def prepare(self, state: GaussianState, camera: Camera):
        """What rendering ``state`` at ``camera`` needs besides the features (projection and tile layout), or
        ``None`` where the rasterizer has no such split (:func:`methods.gaussians.rasterize.prepare_view`)."""
        from methods.gaussians.rasterize import prepare_view

        viewmat, K, w, h = camera_tensors(camera, self.features.device)
        return prepare_view(state.means, state.quats, state.scales, state.opacities, viewmat, K, w, h,
                            near=self.cfg.near, backend=self.cfg.render_backend)


def csr32(rows: torch.Tensor, cols: torch.Tensor, vals: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """Sparse CSR matrix with int32 indices (half the index memory of the default int64)."""
    order = torch.argsort(rows * shape[1] + cols)
    rows, cols, vals = rows[order], cols[order], vals[order]
    crow = torch.zeros(shape[0] + 1, dtype=torch.int64, device=vals.device)
    crow[1:] = torch.bincount(rows, minlength=shape[0]).cumsum(0)
    with warnings.catch_warnings():  # "sparse CSR support is in beta": the products used here are stable
        warnings.simplefilter("ignore")
        return torch.sparse_csr_tensor(crow.to(torch.int32), cols.to(torch.int32), vals, shape)


class _SparseBlend(torch.autograd.Function):
    """``matrix @ colors`` with the transposed matrix for the gradient (both CSR: no transpose per step)."""

    @staticmethod
    def forward(ctx, colors: torch.Tensor, matrix: torch.Tensor, transposed: torch.Tensor):  # type: ignore[override]
        ctx.transposed = transposed
        return matrix @ colors

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        return ctx.transposed @ grad.contiguous(), None, None


class BlendMatrixView:
    """A frozen view's rendering as the sparse linear map it is: with the Gaussians fixed, every composited
    pixel is a fixed weighted sum (alpha x transmittance) of the Gaussians' colours, so the weights listed once
    by the compiled kernels (:func:`methods.gaussians.backends.native_cpu.blend_weights`) render any colours
    as a sparse matrix product: the rasterizer's numbers up to float rounding, without testing every tile's
    Gaussians against every pixel again each step. Same interface as the rasterizer's frozen view."""

    def __init__(self, matrix: torch.Tensor, transposed: torch.Tensor, alpha: torch.Tensor, width: int,
                 height: int) -> None:
        self.matrix, self.transposed, self.alpha = matrix, transposed, alpha
        self.width, self.height = width, height

    @classmethod
    @torch.no_grad()
    def from_frozen(cls, view) -> "BlendMatrixView":
        """From a :func:`methods.gaussians.rasterize.prepare_view` of the compiled kernels."""
        from methods.gaussians.backends import native_cpu

        n, w, h = view.params.shape[0], view.width, view.height
        stats: dict = {}
        _, alpha = native_cpu.Composite.apply(view.params, view.params.new_zeros(n, 1), view.layout, w, h, view.rule,
                                              stats)
        pix, gid, weight = native_cpu.blend_weights(view.params, view.layout, w, h, view.rule, stats["pairs"])
        values = weight.to(torch.float32)
        return cls(csr32(pix, gid, values, (h * w, n)), csr32(gid, pix, values, (n, h * w)),
                   alpha.detach().reshape(h, w), w, h)

    def render(self, colors: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """([H, W, C] composited ``colors`` [N, C] over a zero background, [H, W] accumulated alpha)."""
        out = _SparseBlend.apply(colors.to(torch.float32), self.matrix, self.transposed)  # [H * W, C]
        return out.reshape(self.height, self.width, -1).to(colors.dtype), self.alpha

    def nbytes(self) -> int:
        def size(m: torch.Tensor) -> int:
            return sum(t.numel() * t.element_size() for t in (m.crow_indices(), m.col_indices(), m.values()))

        return size(self.matrix) + size(self.transposed) + self.alpha.numel() * self.alpha.element_size()


# ---------------------------------------------------------------------------------------------------
# Training
# ---------------------------------------------------------------------------------------------------
@dataclass
class FieldTarget:
    """Supervision of one training view, as indices into a latent table (compact at any size)."""

    camera: Camera
    time: float
    index: torch.Tensor
    """[L, H, W] int64 row of :attr:`latents` per pixel and level; -1 = no mask (pixel not supervised)."""
    latents: torch.Tensor
    """[M, d] latent vectors of this view's masks (all levels, rows referenced by :attr:`index`)."""


def make_target(camera: Camera, time_value: float, levels: np.ndarray, level_latents: Sequence[torch.Tensor],
                device: torch.device | str) -> FieldTarget:
    """Build a :class:`FieldTarget` from a frame's mask-index maps and per-level mask latents.

    Args:
        levels:        (L, H, W) int mask index per level, -1 = none.
        level_latents: per level, [M_l, d] latent of mask ``i`` in row ``i``.
    """
    idx = torch.as_tensor(np.asarray(levels, dtype=np.int64), device=device).clone()
    offsets = np.cumsum([0] + [int(t.shape[0]) for t in level_latents])
    for level in range(idx.shape[0]):
        plane = idx[level]
        plane[plane >= 0] += int(offsets[level])
    d = level_latents[0].shape[1] if level_latents else 0
    table = (torch.cat([t.to(device) for t in level_latents], 0) if offsets[-1] > 0
             else torch.zeros(0, d, device=device))
    return FieldTarget(camera, float(time_value), idx, table)


@dataclass
class FieldReport:
    """How training the field went."""

    iterations: int
    seconds: float
    final_loss: float
    losses: list[float] = field(default_factory=list)
    supervised_fraction: float = 0.0
    """Mean fraction of (pixel, level) pairs inside a mask over the training views."""
    views: str = ""
    """How each step rendered its view (:attr:`methods.fields.views.ViewCycle.rendered_by`): ``blend matrices``
    (:class:`BlendMatrixView`), ``kept layouts`` (the compiled compositing on each view's kept layout), or
    ``rasterizer`` (a full render each step)."""


def masked_l1(pred: torch.Tensor, target: FieldTarget) -> torch.Tensor:
    """Mean over levels of the mean L1 over the supervised pixels of that level.

    Args:
        pred: [L, H, W, d] rendered latents.
    """
    valid = target.index >= 0  # [L, H, W]
    gathered = target.latents[target.index.clamp_min(0)]  # [L, H, W, d]
    err = (pred - gathered).abs().sum(-1) * valid  # [L, H, W]
    counts = valid.flatten(1).sum(1)  # [L]
    per_level = err.flatten(1).sum(1) / (counts.clamp_min(1) * pred.shape[-1])
    has = counts > 0
    return per_level[has].mean() if bool(has.any()) else pred.sum() * 0.0


def train_language_field(geometry: FrozenGeometry, targets: Sequence[FieldTarget],
                         cfg: Optional[LanguageFieldConfig] = None, *, seed: int = 0,
                         progress: Optional[Callable] = None) -> tuple[LanguageField, FieldReport]:
    """Fit a :class:`LanguageField` on ``geometry`` (frozen) to ``targets``, one random view per step."""
    cfg = cfg or LanguageFieldConfig()
    if not targets:
        raise ValueError("the language field needs at least one training view")
    gen = torch.Generator().manual_seed(seed)
    fld = LanguageField(geometry.num_gaussians, cfg, generator=gen, device=geometry.device)
    opt = fast_adam([fld.features], lr=cfg.learning_rate)
    from .views import ViewCycle

    # the geometry is frozen: each view's blending matrix, or its projection and tile layout, and its deformed
    # Gaussians are kept between steps, within the memory budgets (ViewCycle.prepared)
    views = ViewCycle(geometry, [t.time for t in targets], seed, cfg.cache_view_geometry_mib * 2 ** 20,
                      cameras=[t.camera for t in targets], near=cfg.near, render_backend=cfg.render_backend,
                      matrix_budget_bytes=cfg.blend_matrix_mib * 2 ** 20)
    losses: list[float] = []
    loss_value = float("nan")
    steps = range(cfg.iterations)
    if progress is not None:
        steps = progress(steps, desc="language field", total=cfg.iterations)
    start = time.perf_counter()
    for step in steps:
        v, state = views.next()
        target = targets[v]
        pred = fld.render_with_alpha(state, target.camera, views.prepared(v, state))[0]
        loss = cfg.loss_weight * masked_l1(pred, target)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % max(1, cfg.log_every) == 0 or step == cfg.iterations - 1:
            loss_value = float(loss.detach())
            losses.append(loss_value)
    seconds = time.perf_counter() - start
    frac = float(np.mean([float((t.index >= 0).float().mean()) for t in targets]))
    how = views.rendered_by
    return fld, FieldReport(cfg.iterations, seconds, loss_value, losses, frac, how)


# ---------------------------------------------------------------------------------------------------
# Query side
# ---------------------------------------------------------------------------------------------------
def relevance_basis(query: torch.Tensor, canon: torch.Tensor) -> torch.Tensor:
    """[D, k] orthonormal basis of the span of the query (or queries) and canonical phrase embeddings.

    Args:
        query: [D] or [N, D] (several queries: one basis serves them all, exactly); canon: [P, D].
    """
    stacked = torch.cat([query.reshape(-1, query.shape[-1]), canon], 0).T  # [D, N + P]
    q, r = torch.linalg.qr(stacked)
    keep = r.diagonal().abs() > 1e-6 * r.diagonal().abs().max().clamp_min(1e-12)
    return q[:, keep]


@contextlib.contextmanager
def matmul_precision(precision: Optional[str]) -> Iterator[None]:
    """Run the block with ``torch.set_float32_matmul_precision(precision)`` (``"highest"``: float32,
    ``"high"``: TensorFloat-32 on GPUs that have it), restoring the previous setting; ``None``: unchanged."""
    if precision is None:
        yield
        return
    before = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision(precision)
    try:
        yield
    finally:
        torch.set_float32_matmul_precision(before)


class DecodeTable:
    """:func:`decode_for_relevance` of 3-d latents through a lookup table: the reduced features decoded
    once at ``resolution``^3 points spanning the box ``[lo, hi]`` and interpolated trilinearly per pixel.

    A rendered latent is an alpha blend of the Gaussians' latents with a zero background, so it lies in
    the convex hull of 0 and those latents: a box from their per-channel extremes and 0 holds every
    pixel. The decoder is piecewise linear (ReLU), so the interpolation is exact inside the cells no
    ReLU kink crosses; the norm channel is smooth. Latents outside the box are decoded exactly.

    ``lazy``: decode a grid point only when a latent first falls into a cell it corners, and keep it
    (the same table values and interpolation, without decoding the cells no latent visits: what the
    CPU can afford at fine resolutions; the eager table suits a GPU, which decodes all at once).
    """

    def __init__(self, decoder: Callable[[torch.Tensor], torch.Tensor], basis: torch.Tensor, lo: torch.Tensor,
                 hi: torch.Tensor, resolution: int, chunk: int = 65536, lazy: bool = False) -> None:
        if lo.numel() != 3 or hi.numel() != 3:
            raise ValueError(f"a decode table needs 3-d latents, got {lo.numel()}")
        if resolution < 2:
            raise ValueError(f"decode table resolution must be >= 2, got {resolution}")
        self.decoder, self.basis, self.chunk, self.resolution, self.lazy = decoder, basis, chunk, resolution, lazy
        self.lo = lo.to(basis.dtype)
        self.hi = torch.maximum(hi.to(basis.dtype), self.lo + 1e-6)
        self.axes = [torch.linspace(float(self.lo[i]), float(self.hi[i]), resolution, device=basis.device,
                                    dtype=basis.dtype) for i in range(3)]
        if lazy:
            self.table = None
            self._ids = torch.empty(0, dtype=torch.long, device=basis.device)  # sorted flat grid indices decoded
            self._values = basis.new_empty(0, basis.shape[1] + 1)
            return
        points = torch.stack(torch.meshgrid(*self.axes, indexing="ij"), -1).reshape(-1, 3)  # [n^3, 3]
        values = decode_for_relevance(points, decoder, basis, chunk)  # [n^3, C]
        n, c = resolution, values.shape[-1]
        self.table = values.reshape(n, n, n, c).permute(3, 0, 1, 2).unsqueeze(0).contiguous()  # [1, C, n, n, n]

    @property
    def decoded_points(self) -> int:
        """Grid points decoded so far."""
        return self.resolution ** 3 if self.table is not None else int(self._ids.numel())

    @torch.no_grad()
    def __call__(self, latents: torch.Tensor) -> torch.Tensor:
        """[..., 3] latents -> [..., C] reduced features."""
        shape = latents.shape[:-1]
        flat = latents.reshape(-1, 3).to(self.basis.dtype)
        unit = 2.0 * (flat - self.lo) / (self.hi - self.lo) - 1.0
        if self.table is None:
            out = self._interpolate(unit)
        else:
            # grid_sample reads (x, y, z) as (last, middle, first) table axis
            grid = unit.flip(-1).reshape(1, 1, 1, -1, 3)
            out = F.grid_sample(self.table, grid, mode="bilinear", padding_mode="border", align_corners=True)
            out = out.reshape(self.table.shape[1], -1).T.contiguous()  # [P, C]
        outside = ((flat < self.lo) | (flat > self.hi)).any(-1)
        if bool(outside.any()):
            out[outside] = decode_for_relevance(flat[outside], self.decoder, self.basis, self.chunk)
        return out.reshape(*shape, out.shape[-1])

    def _interpolate(self, unit: torch.Tensor) -> torch.Tensor:
        """The eager table's trilinear interpolation (grid_sample's, align_corners, border), on grid
        points decoded on demand."""
        n = self.resolution
        pos = ((unit + 1.0) / 2.0 * (n - 1)).clamp(0, n - 1)  # [P, 3] grid coordinates
        base = pos.floor().clamp(max=n - 2).long()  # the cell's first corner (its last cell for pos = n - 1)
        frac = pos - base.to(pos.dtype)
        steps = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], device=unit.device)
        corners = base[:, None, :] + steps[None]  # [P, 8, 3]
        flat_ids = (corners[..., 0] * n + corners[..., 1]) * n + corners[..., 2]  # [P, 8]
        self._fill(flat_ids.unique())
        values = self._values[torch.searchsorted(self._ids, flat_ids)]  # [P, 8, C]
        w = torch.where(steps[None].bool(), frac[:, None, :], 1.0 - frac[:, None, :]).prod(-1)  # [P, 8]
        return (w[..., None] * values).sum(1)

    def _fill(self, wanted: torch.Tensor) -> None:
        """Decode the grid points of the sorted ``wanted`` flat indices not decoded yet."""
        if self._ids.numel():
            at = torch.searchsorted(self._ids, wanted).clamp(max=self._ids.numel() - 1)
            wanted = wanted[self._ids[at] != wanted]
        if not wanted.numel():
            return
        n = self.resolution
        i, j, k = wanted // (n * n), (wanted // n) % n, wanted % n
        points = torch.stack([self.axes[0][i], self.axes[1][j], self.axes[2][k]], -1)
        values = decode_for_relevance(points, self.decoder, self.basis, self.chunk)
        ids, order = torch.cat([self._ids, wanted]).sort()
        self._ids, self._values = ids, torch.cat([self._values, values])[order]


@torch.no_grad()
def decode_for_relevance(latents: torch.Tensor, decoder: Callable[[torch.Tensor], torch.Tensor],
                         basis: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
    """Decode latent maps and keep only what the LERF relevance depends on, exactly.

    The relevance of a pixel depends on its decoded feature ``f`` only through ``f . x / |f|`` for
    ``x`` in span(query, canonical phrases). With ``B`` [D, k] an orthonormal basis of that span,
    ``g = [B^T f, |f - B B^T f|]`` has ``|g| = |f|`` and ``g . [B^T x, 0] = f . x``, so the
    relevance computed on ``g`` against the projected phrases equals the one on ``f``, while
    ``g`` has ``k + 1`` (<= 6) channels instead of D (512 for CLIP): the protocol's query runs
    unchanged at any image size.

    When ``decoder`` is an ``nn.Sequential`` ending in ``nn.Linear`` (``f = W h + b``), ``f`` is never
    formed: ``B^T f = (B^T W) h + B^T b`` and ``|f|^2 = h^T (W^T W) h + 2 (W^T b) . h + |b|^2``, which
    costs ``hidden^2`` instead of ``hidden x D`` per pixel (same values up to float rounding).

    Args:
        latents: [..., d] rendered latents.
        basis:   [D, k] orthonormal columns (:func:`relevance_basis`).
    Returns:
        [..., k + 1] reduced decoded features.
    """
    shape = latents.shape[:-1]
    flat = latents.reshape(-1, latents.shape[-1])
    k = basis.shape[1]
    out = latents.new_empty(flat.shape[0], k + 1)
    last = decoder[-1] if isinstance(decoder, nn.Sequential) and len(decoder) > 0 else None
    if isinstance(last, nn.Linear) and last.in_features < last.out_features:
        trunk = decoder[:-1]
        w = last.weight  # [D, hidden]
        b = last.bias if last.bias is not None else w.new_zeros(w.shape[0])
        proj = w.T @ basis  # [hidden, k]
        proj_b = b @ basis  # [k]
        gram = w.T @ w  # [hidden, hidden]
        wb = w.T @ b  # [hidden]
        bb = b @ b
        for s in range(0, flat.shape[0], chunk):
            h = trunk(flat[s:s + chunk])  # [c, hidden]
            par = h @ proj + proj_b
            norm2 = ((h @ gram) * h).sum(-1) + 2.0 * (h @ wb) + bb
            out[s:s + chunk, :-1] = par
            out[s:s + chunk, -1] = (norm2 - (par * par).sum(-1)).clamp_min(0.0).sqrt()
        return out.reshape(*shape, k + 1)
    for s in range(0, flat.shape[0], chunk):
        f = decoder(flat[s:s + chunk])  # [c, D]
        par = f @ basis  # [c, k]
        perp2 = (f * f).sum(-1) - (par * par).sum(-1)
        out[s:s + chunk, :-1] = par
        out[s:s + chunk, -1] = perp2.clamp_min(0.0).sqrt()
    return out.reshape(*shape, k + 1)


def project_phrases(basis: torch.Tensor, query: torch.Tensor, canon: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Query [D] and canonical phrases [P, D] in the reduced coordinates of :func:`decode_for_relevance`:
    ``([k + 1], [P, k + 1])`` (last coordinate 0: phrases lie in the span)."""
    q = F.normalize(query, dim=-1)
    c = F.normalize(canon, dim=-1)
    zq = torch.cat([q @ basis, q.new_zeros(1)])
    zc = torch.cat([c @ basis, c.new_zeros(c.shape[0], 1)], 1)
    return zq, zc


__all__ = ["LanguageFieldConfig", "GaussianState", "FrozenGeometry", "LanguageField", "FieldTarget", "make_target",
           "FieldReport", "masked_l1", "train_language_field", "relevance_basis", "decode_for_relevance",
           "project_phrases", "camera_tensors"]
