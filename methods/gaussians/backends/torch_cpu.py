"""Pure-PyTorch Gaussian-splatting rasterizer with sparse compositing (the CPU default).

What it computes (the rendering function of 3D-GS, Kerbl et al. 2023, made exact)
-------------------------------------------------------------------------------------
1. **Projection (EWA).** ``Sigma = R S S^T R^T``; 2D covariance ``J W Sigma W^T J^T + eps2d I`` with the
   perspective Jacobian ``J`` evaluated at the camera-space mean, its lateral coordinates clamped to 1.3x
   the field of view as in 3D-GS / gsplat (only matters for Gaussians far off-screen). The conic is the
   inverse 2D covariance.
2. **Culling.** A Gaussian is dropped when its depth is outside ``(near, far)``, its 2D covariance is
   degenerate, its opacity is below ``alpha_min`` or the box that holds every pixel where its alpha can
   reach ``alpha_min`` contains no pixel centre. That box is *opacity-aware*: ``alpha >= alpha_min``
   exactly on the ellipse ``d^T conic d <= 2 ln(opacity / alpha_min)``, so no contributing pixel is ever
   outside it and the image does not depend on the tiling (3D-GS' 3-sigma circle drops the rim of opaque
   Gaussians, whose alpha there is about 0.011 > 1/255).
3. **Compositing.** Per pixel, front to back by camera depth (ties by index): alpha
   ``= min(alpha_max, opacity * exp(-d^T conic d / 2))``; pairs with ``alpha < alpha_min`` are skipped;
   compositing stops *before* the first Gaussian that would bring the transmittance below
   ``transmittance_min``. Pixel ``(i, j)`` has centre ``(j + 0.5, i + 0.5)``.

How (sparse, tiled compositing)
-------------------------------
* **Layout (no gradient).** The image is cut into 4x4-pixel tiles. Every visible Gaussian yields one row
  per tile that its box overlaps and its ellipse actually meets (exact test, per band of tiles); rows
  are ordered by (tile, depth) with one stable sort of small integer keys, and each tile's list is cut
  into chunks of 32 depth slots (the last one padded). Nothing is capped, so no Gaussian is ever
  dropped (``n_overflow_tiles`` is always 0).
* **Compositing** (:class:`_RasterizeTiles`, a custom autograd Function) works on
  ``[chunks, 16 pixels, 32 slots]`` arrays, block by block: alpha for every candidate pair, the
  transmittance by ``cumprod`` along the slots with the transmittance entering a chunk carried from the
  earlier chunks of its tile (a segmented sum of logs in float64), early termination by clamping, and
  colours by batched matmul. Its backward is analytic -- the front-to-back compositing gradient from the
  saved weights and ``alpha / (1 - alpha)`` plus a reverse cumulative sum -- and reduces to per-Gaussian
  gradients of the 2D mean, conic and opacity through pixel moments, instead of autograd through
  ``cumprod``. Pairs that do not composite (skipped, terminated, padding) carry zero weight and get zero
  gradient.
* **Projection** is plain autograd on [N] tensors.

On CPU the cost is dominated by passes over the candidate arrays, so they are laid out with the slot
axis innermost (inner broadcasts over 4-wide axes are an order of magnitude slower), and temporaries are
kept below glibc's mmap threshold (see :func:`tune_cpu_allocator`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from torch import Tensor

from . import native_cpu


@dataclass(frozen=True)
class CompositingRule:
    """Thresholds of front-to-back compositing (3D-GS rasterizer constants)."""

    alpha_min: float = 1.0 / 255.0
    """Pixel-Gaussian pairs with alpha below this are skipped (3D-GS: 1/255)."""
    alpha_max: float = 0.99
    """Alpha is clamped to at most this, keeping ``1 - alpha`` invertible (3D-GS: 0.99; gsplat: 0.999)."""
    transmittance_min: float = 1e-4
    """Compositing of a pixel stops before the Gaussian that would bring its transmittance below this
    (3D-GS: 0.0001)."""
    jacobian_fov_margin: float = 0.3
    """Lateral clamp of the projection Jacobian: ``x/z`` limited to the image edge plus this fraction of
    ``tan(fov/2)`` (3D-GS / gsplat: 0.3, i.e. 1.3x the half field of view for a centred camera)."""


DEFAULT_RULE = CompositingRule()


@dataclass
class TorchRasterConfig:
    """Knobs of the PyTorch backend that change speed and memory, never the image."""

    tile_size: int = 4
    """Side of the square pixel tiles that group candidate pairs. 4 measured fastest on CPU at 128x128
    (smaller tiles: more rows; larger tiles: more pixels evaluated outside the footprint)."""
    slots: int = 32
    """Depth slots per chunk: each tile's front-to-back list is cut into chunks of this many Gaussians
    (the last chunk of a tile is padded), composited as one batch with the transmittance carried
    between consecutive chunks of a tile."""
    cull_corners: bool = True
    """Drop (tile, Gaussian) rows whose tile misses the Gaussian's alpha >= alpha_min ellipse (exact
    test), not just its bounding box."""
    block_entries: int = 1 << 21
    """At most about this many pixel-Gaussian candidates are processed by one autograd call (whole
    tiles per block; a tile with more candidates is a block of its own). Bounds the size of every
    temporary (8 MiB per float32 tensor at the default), keeping it in the allocator's reusable heap."""
    native: bool = True
    """On the CPU, lay out tiles and composite with the compiled kernels of :mod:`.native_cpu` where they
    build (same function, several times faster); off, or without a C compiler: the PyTorch passes below."""
    native_tile_size: int = 8
    """Side of the pixel tiles of the compiled kernels (they walk each pixel's list, so larger tiles than
    the PyTorch passes' pay: fewer rows to lay out, few candidates wasted)."""


DEFAULT_CONFIG = TorchRasterConfig()


_ALLOCATOR_TUNED = False


def tune_cpu_allocator() -> bool:
    """Let glibc keep freed blocks of up to 32 MiB in its heap instead of unmapping them.

    Every temporary of the compositing pass is several MiB; by default glibc serves such blocks with a
    fresh ``mmap`` and unmaps them on free, so each one costs a page fault per 4 KiB when first written
    -- measured here as more than half of the CPU time of a training step. Raising glibc's mmap and
    trim thresholds (``mallopt``) makes the blocks reusable. Process-wide, done once; returns whether
    it applied (not on non-glibc systems, or when ``BENCH4D_NO_MALLOC_TUNING`` is set).
    """
    global _ALLOCATOR_TUNED
    if _ALLOCATOR_TUNED:
        return True
    import os

    if os.environ.get("BENCH4D_NO_MALLOC_TUNING"):
        return False
    try:
        import ctypes
        import platform

        if platform.libc_ver()[0] != "glibc":
            return False
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        ok = libc.mallopt(m_mmap_threshold, 32 << 20) == 1 and libc.mallopt(m_trim_threshold, 256 << 20) == 1
    except (OSError, AttributeError):
        return False
    _ALLOCATOR_TUNED = ok
    return ok


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities (differentiable where marked)."""

    means2d: Tensor
    """[N, 2] pixel coordinates ``(u, v)`` of the projected means (differentiable)."""
    conics: Tensor
    """[N, 3] ``(a, b, c)`` of the inverse 2D covariance ``[[a, b], [b, c]]`` (differentiable)."""
    depths: Tensor
    """[N] camera-space z of the means (differentiable)."""
    visible: Tensor
    """[N] bool: survives culling."""
    radii: Tensor
    """[N] int32: half-size in pixels of the alpha >= alpha_min box (rounded up, capped at
    ``max(width, height) + 1``), 0 when culled."""
    pixel_box: Tensor
    """[N, 4] int64 ``(j0, j1, i0, i1)``: inclusive pixel column / row range of the box, clipped to the
    image (meaningful where ``visible``)."""
    cull_q: Tensor
    """[N] no-grad bound of ``d^T conic d`` inside which alpha can reach alpha_min (with a margin)."""


@dataclass
class TileLayout:
    """Candidate (tile, Gaussian) rows, cut into fixed-length depth chunks (the no-gradient part).

    Every tile's rows, front to back, fill ``ceil(rows / slots)`` consecutive chunks of ``slots`` slots;
    the last chunk of a tile is padded with the empty Gaussian index ``N``.
    """

    gid: Tensor
    """[K, S] int64 Gaussian of each slot (``N`` for an empty slot)."""
    chunk_tile: Tensor
    """[K] int64 tile (``ty * tiles_x + tx``) of each chunk; chunks of a tile are consecutive."""
    last_chunk: Tensor
    """[K] int64 index of the last chunk of the same tile."""
    first_chunk: Tensor
    """[K] int64 index of the first chunk of the same tile."""
    n_rows: int
    """(tile, Gaussian) rows, i.e. candidates / tile_size**2."""
    tiles_x: int
    tiles_y: int
    tile_size: int


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """[N, 4] quaternions ``(w, x, y, z)``, any norm -> [N, 3, 3] rotation matrices."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def project_gaussians(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    near: float,
    far: float,
    eps2d: float,
    rule: CompositingRule = DEFAULT_RULE,
) -> Projection:
    """EWA projection and culling of 3D Gaussians (see the module docstring)."""
    rot = viewmat[:3, :3]
    p_cam = means @ rot.T + viewmat[:3, 3]  # [N, 3]
    x, y, z = p_cam.unbind(-1)
    in_depth = (z > near) & (z < far)
    # Culled Gaussians get a harmless depth so that no inf/NaN reaches the backward pass.
    z_safe = torch.where(in_depth, z, torch.ones_like(z))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = fx * x / z_safe + cx
    v = fy * y / z_safe + cy
    means2d = torch.stack([u, v], -1)

    margin = rule.jacobian_fov_margin
    lim_x_pos = (width - cx) / fx + margin * (0.5 * width / fx)
    lim_x_neg = cx / fx + margin * (0.5 * width / fx)
    lim_y_pos = (height - cy) / fy + margin * (0.5 * height / fy)
    lim_y_neg = cy / fy + margin * (0.5 * height / fy)
    tx = z_safe * torch.minimum(torch.maximum(x / z_safe, -lim_x_neg), lim_x_pos)
    ty = z_safe * torch.minimum(torch.maximum(y / z_safe, -lim_y_neg), lim_y_pos)
    zero = torch.zeros_like(z)
    jac = torch.stack(
        [fx / z_safe, zero, -fx * tx / (z_safe * z_safe), zero, fy / z_safe, -fy * ty / (z_safe * z_safe)],
        -1,
    ).reshape(-1, 2, 3)
    # J W R_g S: the 2x3 factor whose outer product is the 2D covariance.
    jw = (jac.reshape(-1, 3) @ rot).view(-1, 2, 3)
    factor = torch.bmm(jw, quat_to_rotmat(quats) * scales[:, None, :])  # [N, 2, 3]
    cov_a = (factor[:, 0] * factor[:, 0]).sum(-1) + eps2d
    cov_b = (factor[:, 0] * factor[:, 1]).sum(-1)
    cov_c = (factor[:, 1] * factor[:, 1]).sum(-1) + eps2d
    det = cov_a * cov_c - cov_b * cov_b
    ok = in_depth & (det > 0) & (opacities >= rule.alpha_min)
    det_safe = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([cov_c / det_safe, -cov_b / det_safe, cov_a / det_safe], -1)

    with torch.no_grad():
        # alpha >= alpha_min  <=>  d^T conic d <= k with k = 2 ln(opacity / alpha_min); the ellipse's
        # bounding box has half-widths sqrt(k * cov_xx), sqrt(k * cov_yy). A relative and an absolute
        # margin make rounding never exclude a pixel that the exact alpha test keeps.
        k = 2.0 * torch.log(opacities.detach().clamp_min(rule.alpha_min) / rule.alpha_min)
        half_w = torch.sqrt(k * cov_a.detach().clamp_min(0)) * (1 + 1e-5) + 1e-4
        half_h = torch.sqrt(k * cov_c.detach().clamp_min(0)) * (1 + 1e-5) + 1e-4
        ud, vd = u.detach(), v.detach()
        j0 = torch.ceil(ud - half_w - 0.5)
        j1 = torch.floor(ud + half_w - 0.5)
        i0 = torch.ceil(vd - half_h - 0.5)
        i1 = torch.floor(vd + half_h - 0.5)
        finite = torch.isfinite(j0) & torch.isfinite(j1) & torch.isfinite(i0) & torch.isfinite(i1)
        visible = ok & finite & (j1 >= 0) & (j0 <= width - 1) & (i1 >= 0) & (i0 <= height - 1) & (j0 <= j1) & (i0 <= i1)
        big = float(max(width, height) + 1)
        box = torch.stack(
            [j0.clamp(0, width - 1), j1.clamp(0, width - 1), i0.clamp(0, height - 1), i1.clamp(0, height - 1)], -1
        )
        box = torch.where(visible[:, None], box, torch.zeros_like(box)).nan_to_num(0.0).long()
        radii = torch.where(visible, torch.ceil(torch.maximum(half_w, half_h)).clamp(max=big), torch.zeros_like(half_w))
    return Projection(means2d, conics, z, visible, radii.to(torch.int32), box, k * (1 + 1e-4) + 1e-6)


@torch.no_grad()
def tile_layout(proj: Projection, width: int, height: int, config: TorchRasterConfig = DEFAULT_CONFIG) -> TileLayout:
    """One row per (tile, Gaussian) whose alpha >= alpha_min box overlaps the tile, ordered by
    (tile, depth), cut into chunks of ``config.slots`` rows."""
    device = proj.depths.device
    ts, slots = config.tile_size, config.slots
    tiles_x, tiles_y = (width + ts - 1) // ts, (height + ts - 1) // ts
    n_tiles = tiles_x * tiles_y
    n = proj.depths.shape[0]
    vis = proj.visible.nonzero().squeeze(1)
    # Front to back; a stable sort breaks depth ties by index.
    gids = vis.index_select(0, torch.sort(proj.depths.detach().index_select(0, vis), stable=True).indices)
    box = proj.pixel_box.index_select(0, gids) // ts  # [Nv, 4] tile range (tx0, tx1, ty0, ty1)
    ntx = box[:, 1] - box[:, 0] + 1
    counts = ntx * (box[:, 3] - box[:, 2] + 1)
    n_rows = int(counts.sum())
    src = torch.repeat_interleave(torch.arange(gids.numel(), device=device), counts)  # [R]
    within = torch.arange(n_rows, device=device) - (torch.cumsum(counts, 0) - counts).index_select(0, src)
    # within // ntx and within % ntx through float32 (exact for these small integers, and vectorised)
    ntx_r = ntx.index_select(0, src)
    row = torch.floor((within.float() + 0.5) / ntx_r.float()).long()
    tile = (box[:, 2] * tiles_x + box[:, 0]).index_select(0, src) + row * (tiles_x - ntx_r) + within
    if config.cull_corners and n_rows:
        keep = _ellipse_meets_tile(proj, gids, box, src, row, within - row * ntx_r, ts).nonzero().squeeze(1)
        tile, src = tile.index_select(0, keep), src.index_select(0, keep)
        n_rows = int(keep.numel())
    del within, ntx_r, row
    # Rows are generated front to back, so a stable sort by tile gives (tile, depth) order.
    key = tile.int() if n_tiles < 2 ** 31 else tile
    tile, perm = torch.sort(key, stable=True)
    tile = tile.long()
    row_g = gids.index_select(0, src.index_select(0, perm))
    del src, perm, key

    per_tile = torch.bincount(tile, minlength=n_tiles)
    chunks_per_tile = (per_tile + slots - 1) // slots
    chunk_start = torch.cumsum(chunks_per_tile, 0) - chunks_per_tile
    # slot of row r = chunk_start[tile] * slots + (r - first row of its tile)
    shift = chunk_start * slots - (torch.cumsum(per_tile, 0) - per_tile)
    slot = torch.arange(n_rows, device=device) + shift.index_select(0, tile)
    n_chunks = int(chunks_per_tile.sum())
    gid = torch.full((n_chunks * slots,), n, dtype=torch.long, device=device).index_copy_(0, slot, row_g)
    chunk_tile = torch.repeat_interleave(torch.arange(n_tiles, device=device), chunks_per_tile)
    first = chunk_start.index_select(0, chunk_tile)
    return TileLayout(gid.view(n_chunks, slots), chunk_tile, first + chunks_per_tile.index_select(0, chunk_tile) - 1,
                      first, n_rows, tiles_x, tiles_y, ts)


@torch.no_grad()
def _ellipse_meets_tile(proj: Projection, gids: Tensor, box: Tensor, src: Tensor, row: Tensor, col: Tensor,
                        ts: int) -> Tensor:
    """[R] bool: the row's tile holds a pixel-centre rectangle point inside its Gaussian's
    alpha >= alpha_min ellipse ``q(d) = a dx^2 + 2 b dx dy + c dy^2 <= q_max`` (the box test alone keeps
    the box corners; elongated, tilted Gaussians have many such empty rows).

    Exact, per horizontal band of tiles: over ``dy`` in the band the ellipse's chord spans
    ``dx = (-b dy -+ sqrt(a q_max - D dy^2)) / a`` (``D = ac - b^2``); its right end is concave in ``dy``
    and peaks at the ellipse's rightmost point ``dy* = -b sqrt(q_max / (c D))``, so the band's largest
    ``dx`` is at ``dy*`` clamped into the band (the smallest, by symmetry, at ``-dy*``). A tile meets the
    ellipse iff its ``dx`` range overlaps the band's. ``row``, ``col``: [R] tile offsets in the box.
    """
    dtype = proj.means2d.dtype
    u, v = proj.means2d.detach().index_select(0, gids).unbind(1)
    a, b, c = proj.conics.detach().index_select(0, gids).unbind(1)
    q_max = proj.cull_q.index_select(0, gids)
    det = (a * c - b * b).clamp_min(1e-30)
    nty = box[:, 3] - box[:, 2] + 1
    band_g = torch.repeat_interleave(torch.arange(gids.numel(), device=u.device), nty)  # [B]
    band_start = torch.cumsum(nty, 0) - nty
    band_row = torch.arange(band_g.numel(), device=u.device) - band_start.index_select(0, band_g)
    per_g = torch.stack([
        (box[:, 2] * ts).to(dtype) + 0.5 - v,  # dy of the box's first pixel-centre row
        torch.sqrt(q_max * a / det),  # |dy| reach of the ellipse
        -b * torch.sqrt(q_max / (c * det)),  # dy of the rightmost point
        a, b, a * q_max, det,
    ]).index_select(1, band_g)  # [7, B], rows contiguous
    dy0, reach, dy_star, ba, bb, aq, bdet = per_g
    dy1 = dy0 + band_row.to(dtype) * ts
    lo = torch.maximum(dy1, -reach)
    hi = torch.minimum(dy1 + (ts - 1), reach)
    y_r = torch.minimum(torch.maximum(dy_star, lo), hi)
    y_l = torch.minimum(torch.maximum(-dy_star, lo), hi)
    x_max = (torch.sqrt((aq - bdet * y_r * y_r).clamp_min(0)) - bb * y_r) / ba
    x_min = (-torch.sqrt((aq - bdet * y_l * y_l).clamp_min(0)) - bb * y_l) / ba
    x_max = torch.where(lo <= hi, x_max, torch.full_like(x_max, -float("inf")))  # band misses the ellipse
    band = band_start.index_select(0, src) + row
    dxl = ((box[:, 0] * ts).to(dtype) + 0.5 - u).index_select(0, src) + col.to(dtype) * ts
    return (dxl <= x_max.index_select(0, band)) & (dxl + (ts - 1) >= x_min.index_select(0, band))


def _segment_exclusive_cumsum(x: Tensor, first: Tensor) -> Tensor:
    """Exclusive cumulative sum of [K, ...] ``x`` along dim 0 restarting at each segment's ``first``
    index (float64 accumulation; segments are runs of consecutive chunks of one tile)."""
    cs = torch.cumsum(x.double(), 0)
    excl = cs - x.double()
    return (excl - excl[first]).to(x.dtype)


def _segment_suffix_sum(x: Tensor, last: Tensor) -> Tensor:
    """Sum of [K, ...] ``x`` over the later chunks of the same segment (exclusive), float64 accumulation."""
    cs = torch.cumsum(x.double(), 0)
    return (cs[last] - cs).to(x.dtype)


class _RasterizeTiles(torch.autograd.Function):
    """Alpha evaluation + front-to-back compositing of all tiles, with an analytic backward.

    Works block by block (runs of whole tiles, see :func:`_blocks`) on the layout ``[K chunks,
    P pixels of the chunk's tile, S depth slots]`` -- slots innermost, so every full-size operation is
    a contiguous or outer-broadcast pass (inner broadcasts over 4-wide pixel axes are an order of
    magnitude slower on CPU).

    Inputs: ``params_t`` [6, N] = ``(u, v, a, b, c, opacity)`` rows (2D mean, conic, opacity),
    ``feat`` [N, C]. Outputs: composited features [tiles, C, P] (no background) and accumulated alpha
    [tiles, P], ``P = tile_size**2`` pixels row-major inside each tile.
    """

    @staticmethod
    def forward(ctx, params_t: Tensor, feat: Tensor, lay: "TileLayout", blocks: list, chunk: int,
                rule: CompositingRule, stats: dict):  # type: ignore[override]
        n, c = feat.shape
        ts, tiles_x = lay.tile_size, lay.tiles_x
        n_tiles, npix = lay.tiles_x * lay.tiles_y, lay.tile_size ** 2
        dtype, device = params_t.dtype, params_t.device
        empty = params_t.new_tensor([0.0, 0.0, 1.0, 0.0, 1.0, 0.0])[:, None]  # opacity 0: never composited
        params_ext = torch.cat([params_t, empty], 1)  # [6, N + 1]; column N serves empty slots
        local = torch.arange(ts, dtype=dtype, device=device) + 0.5
        px = local.repeat(ts)  # [P] pixel-centre x inside the tile (row-major pixels)
        py = local.repeat_interleave(ts)
        a_below = torch.nextafter(torch.tensor(rule.alpha_min, dtype=dtype), torch.tensor(0.0, dtype=dtype)).item()
        t_below = torch.nextafter(torch.tensor(rule.transmittance_min, dtype=dtype),
                                  torch.tensor(0.0, dtype=dtype)).item()
        out = feat.new_zeros(n_tiles, c, npix)  # channels before pixels: the faster bmm orientation
        t_end = params_t.new_ones(n_tiles, npix)  # final transmittance
        states = []
        for k0, k1 in blocks:
            gid = lay.gid[k0:k1]
            chunk_tile = lay.chunk_tile[k0:k1]
            k, s = gid.shape
            flat_gid = gid.reshape(-1)
            pt = params_ext.index_select(1, flat_gid).view(6, k, s)
            # 2D means relative to the chunk's tile origin keep the backward's moment sums well scaled.
            pt[0] -= ((chunk_tile % tiles_x) * ts).to(dtype)[:, None]
            pt[1] -= ((chunk_tile // tiles_x) * ts).to(dtype)[:, None]
            u, v, a, b, cc, o = pt
            dx = px[None, :, None] - u[:, None, :]  # [K, P, S]
            dy = py[None, :, None] - v[:, None, :]
            # sigma = a dx^2 / 2 + b dx dy + c dy^2 / 2; alpha = opacity * exp(-sigma)
            sig = (0.5 * a)[:, None, :] * dx
            sig.addcmul_(b[:, None, :], dy).mul_(dx)
            sig.addcmul_(torch.mul(dy, (0.5 * cc)[:, None, :], out=dx), dy)
            del dx, dy
            alpha = torch.sub(torch.log(o.clamp_min(1e-38))[:, None, :], sig, out=sig).exp_()
            # alpha < alpha_min -> 0 (skipped); threshold keeps x > t, t = the float just below alpha_min
            torch.nn.functional.threshold_(alpha, a_below, 0.0)
            clamped = None
            if k and float(alpha.max()) > rule.alpha_max:  # only where opacity exceeds alpha_max
                clamped = (alpha.view(-1) > rule.alpha_max).nonzero().squeeze(1)
                alpha.clamp_(max=rule.alpha_max)
            # trans[..., j] = transmittance before slot j; trans[..., j + 1] = after it.
            trans = alpha.new_empty(k, npix, s + 1)
            torch.sub(1.0, alpha, out=trans[..., 1:])
            del alpha
            log_total = torch.log(trans[..., 1:].prod(-1).clamp_min(1e-30))  # [K, P]
            trans[..., 0] = torch.exp(_segment_exclusive_cumsum(log_total, lay.first_chunk[k0:k1] - k0))
            trans.cumprod_(-1)
            # Compositing stops before the pair that would bring T below transmittance_min, so a pixel's
            # final transmittance is its smallest T >= transmittance_min. Clamping each chunk's T from
            # below at the chunk's smallest T >= transmittance_min (2 where none: the tile stopped in an
            # earlier chunk) zeroes the weights T_j - T_{j+1} of the stopped pairs. Per chunk, so that
            # the clamp value comes from the same product chain as the values it clamps.
            t_stop = torch.nn.functional.threshold(trans, t_below, 2.0).amin(-1)  # [K, P]
            trans.clamp_min_(t_stop[..., None])
            t_end.scatter_reduce_(0, chunk_tile[:, None].expand(-1, npix), t_stop, "amin")
            weights = trans[..., :-1] - trans[..., 1:]  # alpha_j T_j of composited pairs, else 0
            # alpha / (1 - alpha) of composited pairs (0 elsewhere), for the backward
            ratio = torch.div(weights, trans[..., 1:], out=trans[..., 1:])
            # weights >= 0, so sign() counts the composited pairs (count_nonzero is slow on sparse
            # data); a float32 sum of 0/1 is exact below 2**24 entries
            signs = weights.sign()
            stats["pairs"] += int(signs.sum(dtype=torch.float64 if signs.numel() >= 1 << 24 else None))
            del signs
            # Empty slots have zero weight, so any valid row serves them in the feature gather.
            feat_gid = flat_gid.clamp(max=max(n - 1, 0))
            ft_saved = None
            for c0 in range(0, c, chunk):
                ft = feat[:, c0:c0 + chunk].index_select(0, feat_gid).view(k, s, -1)  # [K, S, c']
                out[:, c0:c0 + chunk].index_add_(0, chunk_tile, torch.bmm(ft.transpose(1, 2), weights.transpose(1, 2)))
                if c <= chunk:
                    ft_saved = ft
            states.append((pt, weights, ratio, flat_gid, feat_gid, chunk_tile, lay.last_chunk[k0:k1] - k0,
                           clamped, ft_saved))
        ctx.states = states  # intermediates of this call only, released with the graph
        ctx.save_for_backward(feat, t_end)
        ctx.meta = (n, c, ts, chunk)
        return out, 1.0 - t_end

    @staticmethod
    def backward(ctx, g_out: Optional[Tensor], g_acc: Optional[Tensor]):  # type: ignore[override]
        n, c, ts, chunk = ctx.meta
        feat, t_end = ctx.saved_tensors
        need_params, need_feat = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        dtype, device = feat.dtype, feat.device
        grad_params = torch.zeros(6, n + 1, dtype=dtype, device=device) if need_params else None
        grad_feat = torch.zeros(c, n, dtype=dtype, device=device) if need_feat else None
        local = torch.arange(ts, dtype=dtype, device=device) + 0.5
        px, py = local.repeat(ts), local.repeat_interleave(ts)
        basis = torch.stack([torch.ones_like(px), px, py, px * px, py * py, px * py])  # [6, P]
        acc_term = None if g_acc is None else g_acc * t_end  # [tiles, P]
        for pt, weights, ratio, flat_gid, feat_gid, chunk_tile, last_chunk, clamped, ft_saved in ctx.states:
            k, npix, s = weights.shape
            wq = None  # becomes w_i q_i with q_i = f_i . G_p
            if g_out is not None:
                for c0 in range(0, c, chunk):
                    g = g_out[:, c0:c0 + chunk].index_select(0, chunk_tile)  # [K, c', P]
                    if need_params:
                        ft = ft_saved if ft_saved is not None else \
                            feat[:, c0:c0 + chunk].index_select(0, feat_gid).view(k, s, -1)
                        q = torch.bmm(g.transpose(1, 2), ft.transpose(1, 2))  # [K, P, S]
                        wq = q if wq is None else wq.add_(q)
                    if need_feat:
                        gf = torch.bmm(g, weights)  # [K, c', S]
                        cw = gf.shape[1]
                        grad_feat[c0:c0 + cw].scatter_add_(1, feat_gid[None].expand(cw, -1),
                                                           gf.permute(1, 0, 2).reshape(cw, -1))
            if not need_params:
                continue
            if wq is None:
                wq = weights.new_zeros(k, npix, s)
            wq.mul_(weights)
            # out_p = sum_i w_i f_i with w_i = alpha_i T_i; d out_p / d alpha_i = T_i f_i - R_i / (1 - alpha_i),
            # R_i = sum_{j>i} w_j f_j. With d alpha / d sigma = -alpha (unclamped), contracted with G_p:
            # dL/dsigma_i = r_i S_i - w_i q_i, r_i = alpha_i / (1 - alpha_i), S_i = sum_{j>i} w_j q_j.
            g_sigma = torch.cumsum(wq, -1)
            total = g_sigma[..., -1]
            tail = total + _segment_suffix_sum(total, last_chunk)  # [K, P]: this and later chunks
            if acc_term is not None:
                # accumulated alpha 1 - prod(1 - alpha_j): d/d alpha_i = T_end / (1 - alpha_i), i.e. it
                # enters like a suffix sum of -g_acc * T_end.
                tail = tail - acc_term.index_select(0, chunk_tile)
            torch.sub(tail[..., None], g_sigma, out=g_sigma).mul_(ratio).sub_(wq)
            del wq
            if clamped is not None:
                g_sigma.view(-1)[clamped] = 0.0  # alpha clamped at alpha_max: no gradient
            # Moments over the tile pixels: [sum g, sum g x, sum g y, sum g x^2, sum g y^2, sum g x y].
            m0, mx, my, mxx, myy, mxy = torch.matmul(basis, g_sigma).unbind(1)  # [K, S] each
            del g_sigma
            u, v, a, b, cc, o = pt
            sdx = mx - u * m0  # sum g dx with dx = x - u
            sdy = my - v * m0
            sdxx = mxx - 2 * u * mx + u * u * m0
            sdyy = myy - 2 * v * my + v * v * m0
            sdxy = mxy - u * my - v * mx + u * v * m0
            grad = torch.stack([
                -(a * sdx + b * sdy),  # d sigma / d u = -(a dx + b dy)
                -(b * sdx + cc * sdy),
                0.5 * sdxx,
                sdxy,
                0.5 * sdyy,
                -m0 / o.clamp_min(1e-30),  # d alpha / d opacity = alpha / opacity
            ]).view(6, -1)
            grad_params.scatter_add_(1, flat_gid[None].expand(6, -1), grad)
        return (None if grad_params is None else grad_params[:, :n],
                None if grad_feat is None else grad_feat.T, None, None, None, None, None)


@dataclass
class TorchRender:
    """Raw result of :func:`render` (the public wrapper builds ``RenderOutput`` from it)."""

    image: Tensor
    """[H, W, C] composited features over the background."""
    alpha: Tensor
    """[H, W] accumulated alpha."""
    depth: Tensor
    """[H, W] expected depth ``sum_i w_i z_i / alpha`` (0 where alpha is 0)."""
    proj: Projection
    layout: "TileLayout | native_cpu.NativeLayout"
    """The PyTorch passes' chunked layout, or the compiled kernels' tile lists."""
    n_pairs: int
    """Pixel-Gaussian pairs composited."""
    n_candidates: int
    """Pixel-Gaussian pairs evaluated (tile rows x tile pixels)."""


def render(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, C]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    background: Tensor,  # [C]
    near: float,
    far: float,
    channel_chunk: int,
    eps2d: float,
    config: TorchRasterConfig = DEFAULT_CONFIG,
    rule: CompositingRule = DEFAULT_RULE,
) -> TorchRender:
    """Render one view (inputs already validated by the public wrapper)."""
    n, c = colors.shape
    lib = native_cpu.kernels() if config.native and native_cpu.supports(means) else None
    if lib is not None:
        if viewmat.requires_grad or K.requires_grad:  # the kernels' projection has no camera gradients
            proj = project_gaussians(means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d,
                                     rule)
        else:
            proj = _project_native(means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d,
                                   rule)
        return _render_native(lib, proj, opacities, colors, width, height, background, config, rule)
    proj = project_gaussians(means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d, rule)
    lay = tile_layout(proj, width, height, config)
    ts, npix = lay.tile_size, lay.tile_size ** 2
    params_t = torch.stack([proj.means2d[:, 0], proj.means2d[:, 1], *proj.conics.unbind(1), opacities])  # [6, N]
    feat = torch.cat([colors, proj.depths[:, None]], 1)  # [N, C + 1]: depth rides as a last channel
    stats: dict = {"pairs": 0}
    blocks = _blocks(lay, max(1, config.block_entries // (npix * config.slots)))
    out, acc = _RasterizeTiles.apply(params_t, feat, lay, blocks, max(1, channel_chunk), rule, stats)
    full = torch.cat([out, acc[:, None]], 1)  # [tiles, C + 2, P]
    img = full.view(lay.tiles_y, lay.tiles_x, c + 2, ts, ts).permute(0, 3, 1, 4, 2)
    img = img.reshape(lay.tiles_y * ts, lay.tiles_x * ts, c + 2)[:height, :width]
    alpha = img[..., c + 1]
    image = img[..., :c] + (1.0 - alpha)[..., None] * background
    depth = img[..., c] / alpha.clamp_min(1e-10)
    return TorchRender(image, alpha, depth, proj, lay, stats["pairs"], lay.n_rows * npix)


def _project_native(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, K: Tensor,
                    width: int, height: int, near: float, far: float, eps2d: float,
                    rule: CompositingRule) -> Projection:
    """:func:`project_gaussians` by the compiled kernels (the same quantities, computed in double)."""
    view, intr, lim = native_cpu.camera_constants(viewmat, K, width, height, rule.jacobian_fov_margin)
    means2d, conics, depths, visible, radii, box, cull_q = native_cpu.Project.apply(
        means, quats, scales, opacities, view, intr, lim, width, height, float(near), float(far), float(eps2d),
        rule.alpha_min)
    return Projection(means2d, conics, depths, visible, radii, box, cull_q)


def _render_native(lib, proj: Projection, opacities: Tensor, colors: Tensor, width: int, height: int,
                   background: Tensor, config: TorchRasterConfig, rule: CompositingRule) -> TorchRender:
    """:func:`render`'s layout and compositing by the compiled kernels (:mod:`.native_cpu`)."""
    c = colors.shape[1]
    params = torch.cat([proj.means2d, proj.conics, opacities[:, None]], 1)  # [N, 6]: one cache line per Gaussian
    with torch.no_grad():
        vis = proj.visible.nonzero().squeeze(1)
        # front to back; a stable sort breaks depth ties by index
        order = vis.index_select(0, torch.sort(proj.depths.detach().index_select(0, vis), stable=True).indices)
    lay = native_cpu.layout(lib, params, proj.cull_q, proj.pixel_box, order, width, height, config.native_tile_size)
    feat = torch.cat([colors, proj.depths[:, None]], 1)  # [N, C + 1]: depth rides as a last channel
    stats: dict = {"pairs": 0}
    composited, alpha = native_cpu.Composite.apply(params, feat, lay, width, height, rule, stats)
    image = composited[..., :c] + (1.0 - alpha)[..., None] * background
    depth = composited[..., c] / alpha.clamp_min(1e-10)
    return TorchRender(image, alpha, depth, proj, lay, stats["pairs"], lay.n_rows * lay.tile_size ** 2)


def _blocks(lay: TileLayout, max_chunks: int) -> list[tuple[int, int]]:
    """Split the chunk sequence into runs of whole tiles with at most ``max_chunks`` chunks each (a tile
    with more chunks than that forms a run of its own)."""
    k = lay.gid.shape[0]
    if k <= max_chunks:
        return [(0, k)] if k else []
    starts = torch.unique_consecutive(lay.first_chunk).tolist() + [k]
    out, k0, prev = [], 0, 0
    for st in starts[1:]:
        if st - k0 > max_chunks and prev > k0:
            out.append((k0, prev))
            k0 = prev
        prev = st
    out.append((k0, k))
    return out


@dataclass
class FrozenView:
    """Projection and tile layout of fixed Gaussians at one camera (see
    :func:`methods.gaussians.rasterize.prepare_view`): renders any number of channel sets."""

    params: Tensor
    """[N, 6] (u, v, a, b, c, opacity) of the projected Gaussians."""
    layout: native_cpu.NativeLayout
    width: int
    height: int
    rule: CompositingRule

    def render(self, colors: Tensor) -> tuple[Tensor, Tensor]:
        """([H, W, C] composited ``colors`` over a zero background, [H, W] accumulated alpha)."""
        return native_cpu.Composite.apply(self.params, colors, self.layout, self.width, self.height, self.rule, {})

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.params, self.layout.rows, self.layout.tile_start))


@torch.no_grad()
def prepare_frozen(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, K: Tensor,
                   width: int, height: int, near: float, far: float, eps2d: float,
                   config: TorchRasterConfig = DEFAULT_CONFIG,
                   rule: CompositingRule = DEFAULT_RULE) -> Optional[FrozenView]:
    """A :class:`FrozenView`, or ``None`` where the compiled kernels do not run."""
    lib = native_cpu.kernels() if config.native and native_cpu.supports(means) else None
    if lib is None:
        return None
    proj = _project_native(means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d, rule)
    params = torch.cat([proj.means2d, proj.conics, opacities[:, None]], 1)
    vis = proj.visible.nonzero().squeeze(1)
    order = vis.index_select(0, torch.sort(proj.depths.index_select(0, vis), stable=True).indices)
    lay = native_cpu.layout(lib, params, proj.cull_q, proj.pixel_box, order, width, height, config.native_tile_size)
    return FrozenView(params, lay, width, height, rule)
