"""One differentiable Gaussian-splatting rasterizer entry point: :func:`rasterize`.

Conventions are the project's (:mod:`benchmark.core.scene`): OpenCV camera axes, ``viewmat`` maps world to
camera, pixel ``(i, j)`` has centre ``(j + 0.5, i + 0.5)``. Quaternions are ``(w, x, y, z)``.

Backends (same inputs, same :class:`RenderOutput`):

* ``"torch"`` -- pure PyTorch with sparse compositing (:mod:`.backends.torch_cpu`); any device, the CPU
  default. Exact 3D-GS compositing rule (alpha >= 1/255, alpha <= 0.99, stop before transmittance
  < 1e-4) with an opacity-aware footprint, so the image does not depend on tiling.
* ``"gsplat"`` -- ``gsplat.rasterization`` on CUDA tensors (:mod:`.backends.gsplat_cuda`). gsplat uses
  a 3-sigma footprint and clamps alpha at 0.999, so images agree with ``"torch"`` to about 1e-2 at
  the rims of opaque Gaussians, not bit for bit.
* ``"auto"`` -- ``"gsplat"`` for CUDA tensors when gsplat imports, else ``"torch"``.

Densification gradients
-----------------------
``RenderOutput.means2d`` is an [N, 2] tensor of the graph. After ``loss.backward()``,
``out.means2d.grad`` is the gradient of the loss with respect to the projected 2D means (pixel units),
zero for culled Gaussians -- what 3D-GS accumulates to decide densification. Both backends fill it
(the torch backend by ``retain_grad``, the gsplat backend by a hook on gsplat's own means2d).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import torch
from torch import Tensor

from benchmark.core.errors import InputError

if TYPE_CHECKING:  # pragma: no cover
    from benchmark.core.scene import Camera

BACKENDS = ("auto", "torch", "gsplat")


@dataclass
class RenderOutput:
    """What one rasterization returns (both backends)."""

    image: Tensor
    """[H, W, C] composited ``colors`` over ``background``."""
    alpha: Tensor
    """[H, W] accumulated opacity ``1 - prod(1 - alpha_i)`` of the composited Gaussians."""
    depth: Tensor
    """[H, W] *normalised* expected depth ``sum_i w_i z_i / alpha`` (camera z of the Gaussian means;
    0 where ``alpha`` is 0). The accumulated depth is ``depth * alpha``."""
    means2d: Tensor
    """[N, 2] projected means in pixels; part of the graph: after backward, ``means2d.grad`` holds the
    view-space positional gradients used for densification."""
    radii: Tensor
    """[N] int32 screen-space radius in pixels, 0 for culled Gaussians (torch: half-size of the box where
    alpha can reach 1/255, capped at the image size; gsplat: its own 3-sigma / opacity-aware radius)."""
    visible: Tensor
    """[N] bool: the Gaussian survived culling (``radii > 0``)."""
    n_pairs: int
    """torch: pixel-Gaussian pairs that were composited; gsplat: Gaussian-tile intersections."""
    n_candidates: int
    """torch: pixel-Gaussian pairs evaluated by the no-gradient pass; gsplat: same as ``n_pairs``."""
    n_overflow_tiles: int
    """Tiles whose Gaussian list was truncated (always 0: neither backend caps tile lists)."""
    backend: str
    """``"torch"`` or ``"gsplat"``: the backend that actually ran."""


_FLUSH_DENORMAL_SET = False


def _ensure_flush_denormal() -> None:
    # Transmittance products underflow into denormals, which slow CPU compositing several-fold.
    global _FLUSH_DENORMAL_SET
    if not _FLUSH_DENORMAL_SET:
        torch.set_flush_denormal(True)
        _FLUSH_DENORMAL_SET = True


def _check(cond: bool, field: str, message: str) -> None:
    if not cond:
        raise InputError(None, field, message)


def _check_inputs(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, viewmat: Tensor,
                  K: Tensor, width: int, height: int, background: Optional[Tensor], backend: str, channel_chunk: int,
                  near: float, far: float) -> Tensor:
    """Raise :class:`InputError` naming the first bad input of :func:`rasterize`; returns the background
    ([C], zeros by default) on the inputs' device and dtype."""
    _check(isinstance(means, Tensor) and means.dim() == 2 and means.shape[1] == 3, "means",
           f"expected a [N, 3] tensor, got {tuple(getattr(means, 'shape', ()))}")
    n = means.shape[0]
    _check(quats.shape == (n, 4), "quats", f"expected [{n}, 4], got {tuple(quats.shape)}")
    _check(scales.shape == (n, 3), "scales", f"expected [{n}, 3], got {tuple(scales.shape)}")
    _check(opacities.shape == (n,), "opacities", f"expected [{n}], got {tuple(opacities.shape)}")
    _check(colors.dim() == 2 and colors.shape[0] == n and colors.shape[1] >= 1, "colors",
           f"expected [{n}, C] with C >= 1, got {tuple(colors.shape)}")
    _check(viewmat.shape == (4, 4), "viewmat", f"expected [4, 4], got {tuple(viewmat.shape)}")
    _check(K.shape == (3, 3), "K", f"expected [3, 3], got {tuple(K.shape)}")
    _check(int(width) > 0 and int(height) > 0, "width/height", f"must be positive, got {width}x{height}")
    _check(backend in BACKENDS, "backend", f"expected one of {BACKENDS}, got {backend!r}")
    _check(int(channel_chunk) >= 1, "channel_chunk", f"must be >= 1, got {channel_chunk}")
    _check(0 < near < far, "near/far", f"need 0 < near < far, got {near}, {far}")
    _check(means.is_floating_point(), "means", f"must be floating point, got {means.dtype}")
    c = colors.shape[1]
    device, dtype = means.device, means.dtype
    for name, t in (("quats", quats), ("scales", scales), ("opacities", opacities), ("colors", colors),
                    ("viewmat", viewmat), ("K", K)):
        _check(t.device == device, name, f"on {t.device}, but means are on {device}")
        _check(t.dtype == dtype, name, f"dtype {t.dtype}, but means are {dtype}")
    if background is None:
        background = torch.zeros(c, device=device, dtype=dtype)
    _check(background.shape == (c,), "background", f"expected [{c}], got {tuple(background.shape)}")
    background = background.to(device=device, dtype=dtype)
    return background


def rasterize(
    means: Tensor,  # [N, 3] world positions
    quats: Tensor,  # [N, 4] rotations (w, x, y, z), not necessarily normalised
    scales: Tensor,  # [N, 3] scales (activated, > 0)
    opacities: Tensor,  # [N] opacities in (0, 1) (activated)
    colors: Tensor,  # [N, C] channels to composite, C >= 1
    viewmat: Tensor,  # [4, 4] world-to-camera (OpenCV axes)
    K: Tensor,  # [3, 3] intrinsics (pixel centres at +0.5)
    width: int,
    height: int,
    *,
    background: Optional[Tensor] = None,  # [C] composited behind (default zeros)
    near: float = 0.01,
    far: float = 1e10,
    backend: str = "auto",
    channel_chunk: int = 64,
    eps2d: float = 0.3,
) -> RenderOutput:
    """Render N Gaussians into one [height, width] view; differentiable in every Gaussian input.

    ``colors`` may hold any number of channels (RGB, features, or both concatenated); more than
    ``channel_chunk`` channels are composited in chunks of that size (bounding memory, same result).
    ``eps2d`` is the low-pass dilation added to the 2D covariance (3D-GS: 0.3).
    """
    background = _check_inputs(means, quats, scales, opacities, colors, viewmat, K, width, height, background,
                               backend, channel_chunk, near, far)
    width, height = int(width), int(height)

    use = backend
    if backend == "auto":
        from .backends.gsplat_cuda import gsplat_available

        use = "gsplat" if (means.is_cuda and gsplat_available()) else "torch"
    if use == "gsplat":
        from .backends.gsplat_cuda import gsplat_available, render as gsplat_render

        _check(means.is_cuda, "backend", "'gsplat' needs CUDA tensors")
        _check(gsplat_available(), "backend", "'gsplat' requested but gsplat is not importable (pip install gsplat)")
        return gsplat_render(means, quats, scales, opacities, colors, viewmat, K, width, height,
                             background=background, near=near, far=far, channel_chunk=int(channel_chunk),
                             eps2d=eps2d)

    from .backends import torch_cpu

    if means.device.type == "cpu":
        _ensure_flush_denormal()
        torch_cpu.tune_cpu_allocator()
    r = torch_cpu.render(means, quats, scales, opacities, colors, viewmat, K, width, height, background,
                         near, far, int(channel_chunk), eps2d)
    means2d = r.proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    return RenderOutput(
        image=r.image, alpha=r.alpha, depth=r.depth, means2d=means2d, radii=r.proj.radii,
        visible=r.proj.visible, n_pairs=r.n_pairs, n_candidates=r.n_candidates, n_overflow_tiles=0,
        backend="torch",
    )


def camera_tensors(
    camera: "Camera", device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32
) -> tuple[Tensor, Tensor, int, int]:
    """``benchmark.core.scene.Camera`` -> ``(viewmat [4, 4], K [3, 3], width, height)`` for :func:`rasterize`.

    The rasterizer is a pinhole: OpenCV distortion coefficients of the camera, if any, are not applied
    (undistort the images, or accept the error).
    """
    viewmat = torch.as_tensor(camera.world_to_camera, dtype=dtype, device=device)
    K = torch.as_tensor(camera.K, dtype=dtype, device=device)
    return viewmat, K, int(camera.width), int(camera.height)


def prepare_view(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, K: Tensor,
                 width: int, height: int, *, near: float = 0.01, far: float = 1e10, backend: str = "auto",
                 eps2d: float = 0.3):
    """The part of :func:`rasterize` that does not depend on the colours (projection, culling, tile
    layout) for Gaussians that stay fixed, so that several colour sets render on it:
    :meth:`~methods.gaussians.backends.torch_cpu.FrozenView.render` composites ``colors`` [N, C] as
    ``rasterize`` would with a zero background, differentiable in ``colors`` only (nothing flows to the
    Gaussians). ``None`` where the compiled CPU kernels do not run (a CUDA tensor, another backend, no C
    compiler): call :func:`rasterize` then."""
    probe = means.new_zeros(means.shape[0], 1)
    _check_inputs(means, quats, scales, opacities, probe, viewmat, K, width, height, None, backend, 1, near, far)
    if means.device.type != "cpu" or backend == "gsplat":
        return None
    from .backends import torch_cpu

    _ensure_flush_denormal()
    torch_cpu.tune_cpu_allocator()
    return torch_cpu.prepare_frozen(means.detach(), quats.detach(), scales.detach(), opacities.detach(), viewmat,
                                    K, int(width), int(height), near, far, eps2d)
