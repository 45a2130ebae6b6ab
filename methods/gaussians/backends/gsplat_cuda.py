"""gsplat backend: ``gsplat.rasterization`` on CUDA tensors behind the project's signature.

gsplat's PyPI wheel compiles its CUDA kernels on first use. On a machine with ``nvcc`` but no GPU a
compile attempt fails and leaves a broken extension cache, so :func:`gsplat_available` checks
``torch.cuda.is_available()`` *before* importing gsplat, and nothing here imports gsplat at module
level.

Mapping (gsplat >= 1.0 API): one camera (``viewmats[None]``, ``Ks[None]``), ``packed=False`` (so the
projected means are a dense [1, N, 2] tensor that maps one-to-one onto the Gaussians),
``render_mode="RGB+ED"`` (colour channels plus gsplat's normalised expected depth, the same quantity
as the torch backend's ``depth``), ``backgrounds`` [1, C], ``rasterize_mode="classic"``.

Differences from the torch backend (documented, covered by the CUDA parity test's tolerance): gsplat
clamps alpha at 0.999 instead of 0.99, and older releases bound each Gaussian by 3 sigma instead of
the opacity-aware footprint, which drops alpha < ~0.011 at the rim of opaque Gaussians.
"""

from __future__ import annotations

import importlib.util
from typing import Optional

import torch
from torch import Tensor

_AVAILABLE: Optional[bool] = None


def gsplat_available() -> bool:
    """True when a CUDA device is present *and* ``import gsplat`` works (cached)."""
    global _AVAILABLE
    if _AVAILABLE is None:
        _AVAILABLE = False
        if torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None:
            try:
                import gsplat

                _AVAILABLE = hasattr(gsplat, "rasterization")
            except Exception:  # noqa: BLE001 - a broken install must not break the torch backend
                _AVAILABLE = False
    return _AVAILABLE


def render(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] (w, x, y, z)
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, C]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    *,
    background: Tensor,  # [C]
    near: float,
    far: float,
    channel_chunk: int,
    eps2d: float,
):
    """Render with gsplat; returns :class:`methods.gaussians.rasterize.RenderOutput`."""
    from gsplat import rasterization

    from ..rasterize import RenderOutput

    n, c = colors.shape
    render_colors, render_alphas, meta = rasterization(
        means, quats, scales, opacities, colors, viewmat[None], K[None], width, height,
        near_plane=near, far_plane=far, eps2d=eps2d, packed=False, backgrounds=background[None],
        render_mode="RGB+ED", rasterize_mode="classic", channel_chunk=channel_chunk,
    )
    image = render_colors[0, ..., :c]  # [H, W, C]
    depth = render_colors[0, ..., c]  # [H, W] normalised expected depth
    alpha = render_alphas[0, ..., 0]  # [H, W]

    radii = meta["radii"][0]  # [N] (gsplat < 1.5) or [N, 2] per-axis (gsplat >= 1.5)
    if radii.dim() == 2:
        radii = radii.max(dim=-1).values
    radii = radii.to(torch.int32)

    # gsplat's means2d is [1, N, 2]; a slice of it would not be on the backward path, so hand out a
    # detached [N, 2] tensor and fill its .grad from a hook on gsplat's tensor.
    full = meta["means2d"]
    means2d = full.detach()[0]
    if full.requires_grad:
        def _hook(grad: Tensor) -> None:
            g = grad[0].detach()
            means2d.grad = g.clone() if means2d.grad is None else means2d.grad + g

        full.register_hook(_hook)
    isect = meta.get("isect_ids")
    n_isect = int(isect.numel()) if isect is not None else -1
    return RenderOutput(
        image=image, alpha=alpha, depth=depth, means2d=means2d, radii=radii, visible=radii > 0,
        n_pairs=n_isect, n_candidates=n_isect, n_overflow_tiles=0, backend="gsplat",
    )
