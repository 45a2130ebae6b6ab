"""Real spherical harmonics up to degree 3, in the 3D-GS basis order and sign convention.

View-dependent colour of a Gaussian = ``sum_k coeffs[k] * Y_k(d)`` over the ``(degree + 1)**2`` basis
functions, ``d`` the unit direction from the camera centre to the Gaussian. 3D-GS stores the colour
offset by 0.5 (``rgb = SH + 0.5``, clamped at 0): see :func:`sh_to_color`.
"""

from __future__ import annotations

import torch
from torch import Tensor

SH_C0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
SH_C1 = 0.4886025119029199  # sqrt(3 / (4 pi))
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
MAX_DEGREE = 3


def num_sh_bases(degree: int) -> int:
    """Number of basis functions up to ``degree``: ``(degree + 1)**2``."""
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """[..., 3] unit directions -> [..., (degree + 1)**2] basis values (3D-GS order and signs)."""
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"SH degree must be in [0, {MAX_DEGREE}], got {degree}")
    x, y, z = dirs.unbind(-1)
    cols = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        cols += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        cols += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        cols += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(cols, -1)


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate SH.

    coeffs: [N, K, C] with ``K >= (degree + 1)**2`` (only the first bases are used);
    dirs: [N, 3] unit directions. Returns [N, C].
    """
    nb = num_sh_bases(degree)
    if coeffs.shape[-2] < nb:
        raise ValueError(f"degree {degree} needs {nb} SH coefficients, got {coeffs.shape[-2]}")
    return torch.einsum("nk,nkc->nc", sh_basis(degree, dirs), coeffs[:, :nb])


def view_directions(means: Tensor, viewmat: Tensor) -> Tensor:
    """[N, 3] unit directions from the camera centre of ``viewmat`` [4, 4] (world-to-camera) to ``means``."""
    center = -viewmat[:3, :3].T @ viewmat[:3, 3]
    d = means - center
    return d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def sh_to_color(degree: int, coeffs: Tensor, means: Tensor, viewmat: Tensor) -> Tensor:
    """3D-GS colour: ``max(SH(d) + 0.5, 0)`` with ``d`` the viewing direction. coeffs [N, K, 3] -> [N, 3]."""
    return (eval_sh(degree, coeffs, view_directions(means, viewmat)) + 0.5).clamp_min(0.0)


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """Degree-0 coefficient whose colour is ``rgb`` (inverse of the 0.5 offset): [..., 3] -> [..., 3]."""
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: Tensor) -> Tensor:
    """Colour of a degree-0 coefficient: [..., 3] -> [..., 3]."""
    return sh0 * SH_C0 + 0.5
