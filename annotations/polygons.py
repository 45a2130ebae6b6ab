"""Polygons <-> masks, with one stated pixel convention.

Convention
----------
Polygon vertices are continuous pixel coordinates ``(x, y)`` with the image's top-left *corner* at
``(0, 0)`` (the project convention of :mod:`benchmark.core.scene`: the centre of pixel row ``i``, column
``j`` is ``(j + 0.5, i + 0.5)``). A pixel belongs to a polygon when its **centre** lies inside it
(even-odd rule). Rasterisation is pycocotools' ``frPyObjects``, which implements this rule on its
1/5-pixel grid; the polygons of one label are OR-ed (``merge``). A polygon whose vertices lie on
integer coordinates (pixel edges) therefore covers exactly the pixels it encloses.

:func:`mask_to_polygons` writes exactly such polygons: the pixel-edge boundary of each 8-connected
component, its holes joined to the outer loop by zero-width "keyhole" bridges (each bridge is
walked there and back, so it changes no pixel's parity). One polygon per component means holes
survive the OR of several polygons, and ``polygons_to_mask(mask_to_polygons(m)) == m`` exactly
(checked by the tests; :func:`annotations.release.export_release` also checks every mask and falls
back to RLE if it ever did not hold). ``cv2.findContours`` is not used for export because its
contours run through boundary pixel *centres*, so a centre-rule fill of them loses about half of
every boundary pixel: lossy.

The release's evaluation instead truncates vertices to int32 and calls ``cv2.fillPoly`` per polygon
(pixel centres at integer coordinates, boundary pixels included: a slightly larger mask). It is
available as ``rasterizer="release_cv2"`` for reproducing the release's numbers.

Hostile polygons
----------------
Every polygon reaches a rasteriser through one checked path: :func:`check_polygon` (a flat list of
finite numbers, every vertex within one image size of the image it was drawn on), the polygons of one
mask within :func:`polygon_budget` (edge lengths in pixels, max(|dx|, |dy|), plus one per vertex; about
0.2-3 x height x width for even noisy hand-drawn masks), then :func:`polygons_to_mask`, which checks again
that the (scaled) vertices are finite and near the target image whoever calls it.
pycocotools walks every edge point by point: a NaN vertex crashes it and a vertex at 4e8 makes it grow
without bound, so nothing unchecked may reach it. :func:`checked_polygons_mask` is the whole path for a
list of polygons from a file.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal, Sequence

import cv2
import numpy as np
from pycocotools import mask as mask_utils

from benchmark.core.annotation import MAX_MASK_PIXELS
from benchmark.core.errors import InputError

Rasterizer = Literal["coco", "release_cv2"]

__all__ = ["Rasterizer", "mask_to_polygons", "polygons_to_mask", "check_polygon", "checked_polygons_mask",
           "polygon_budget", "polygon_cost"]

MAX_COORDINATE = 1e9
"""Largest absolute vertex coordinate a file may give (checked exactly before anything converts it)."""


def polygon_budget(height: int, width: int) -> int:
    """Largest :func:`polygon_cost` of the polygons of one mask of a (height x width) image:
    ``2 * (height * width + height + width)``, twice the length of every pixel edge of the image."""
    return 2 * (height * width + height + width)


def polygon_cost(polygons: Sequence[Sequence[float]], scale: tuple[float, float] = (1.0, 1.0)) -> float:
    """Boundary length of ``polygons`` in (scaled) pixels, each edge counted as max(|dx|, |dy|),
    plus one per vertex: proportional to the points pycocotools walks and allocates to fill them."""
    total = 0.0
    for poly in polygons:
        pts = np.asarray(poly, dtype=np.float64).reshape(-1, 2) * np.asarray(scale, dtype=np.float64)
        if len(pts):
            total += float(np.abs(pts - np.roll(pts, -1, axis=0)).max(axis=1).sum()) + len(pts)
    return total


def check_polygon(poly: Any, w_img: int, h_img: int, file: str | Path | None, field: str) -> list:
    """``poly`` checked as a flat ``[x0, y0, ...]`` of finite numbers, every vertex within one image
    size of the ``w_img`` x ``h_img`` image it was drawn on (:class:`InputError` naming ``field``)."""
    if not isinstance(poly, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in poly):
        raise InputError(file, field, "expected a flat list of numbers [x0, y0, x1, y1, ...]")
    if len(poly) % 2:
        raise InputError(file, field, f"odd number of coordinates ({len(poly)})")
    if len(poly) > 2 * (polygon_budget(h_img, w_img) + 1):  # every vertex costs at least one
        raise InputError(file, field, f"{len(poly) // 2} vertices; a {w_img}x{h_img} image never needs that many")
    # ints are compared exactly first: float() of a huge int raises OverflowError
    if not all(abs(v) <= MAX_COORDINATE if isinstance(v, int) else math.isfinite(v) for v in poly):
        raise InputError(file, field, f"contains NaN, inf or a number beyond {MAX_COORDINATE:g}")
    if poly:
        pts = np.asarray(poly, dtype=np.float64).reshape(-1, 2)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        # the rasteriser walks every edge point by point: a vertex far outside costs memory and time
        if lo[0] < -w_img or lo[1] < -h_img or hi[0] > 2 * w_img or hi[1] > 2 * h_img:
            raise InputError(file, field, f"vertices reach ({lo[0]:g}, {lo[1]:g})..({hi[0]:g}, {hi[1]:g}), more than "
                                          f"one image size outside the {w_img}x{h_img} image")
    return poly


def checked_polygons_mask(polygons: Any, source_size: tuple[int, int], height: int, width: int, *,
                          file: str | Path | None, field: str, rasterizer: "Rasterizer" = "coco") -> np.ndarray:
    """The (height, width) bool mask of a file's list of polygons drawn on an image of ``source_size`` =
    ``(width, height)``: each polygon through :func:`check_polygon`, their cost within the budget, then
    rasterised (scaled to the target size). The one path from a file's polygons to a mask."""
    w_img, h_img = int(source_size[0]), int(source_size[1])
    if not isinstance(polygons, list):
        raise InputError(file, field, f"expected a list of polygons, got {type(polygons).__name__}")
    clean = [check_polygon(poly, w_img, h_img, file, f"{field}[{j}]") for j, poly in enumerate(polygons)]
    scale = (width / w_img, height / h_img)
    cost = polygon_cost(clean, scale)
    if cost > polygon_budget(height, width):
        raise InputError(file, field, f"the polygons are {cost:.0f} pixels long, more than "
                                      f"{polygon_budget(height, width)} for a {width}x{height} image")
    return polygons_to_mask(clean, height, width, scale=scale, rasterizer=rasterizer)


def polygons_to_mask(polygons: Sequence[Sequence[float]], height: int, width: int, *,
                     scale: tuple[float, float] = (1.0, 1.0), rasterizer: Rasterizer = "coco") -> np.ndarray:
    """OR of the polygons' fills as an (H, W) bool mask.

    ``polygons``: COCO flat lists ``[x0, y0, x1, y1, ...]`` (already validated: even length, finite).
    ``scale``: ``(sx, sy)`` applied to the vertices first (a polygon drawn on a resized image is
    mapped back by ``x * sx``, ``y * sy``; scaling about the top-left corner is exact in the corner
    convention). A polygon with fewer than 3 vertices encloses no area and adds nothing.
    """
    if not (0 < height and 0 < width and height * width <= MAX_MASK_PIXELS):
        raise InputError(None, "polygon", f"a {width}x{height} mask is outside 1..{MAX_MASK_PIXELS} pixels")
    sx, sy = scale
    scaled = []
    for poly in polygons:
        pts = np.asarray(poly, dtype=np.float64).reshape(-1, 2) * np.array([sx, sy])
        # the last line of defence before pycocotools: finite, near the image (module docstring)
        if pts.size and (not np.isfinite(pts).all() or pts[:, 0].min() < -width or pts[:, 1].min() < -height
                         or pts[:, 0].max() > 2 * width or pts[:, 1].max() > 2 * height):
            raise InputError(None, "polygon", f"vertices outside the {width}x{height} image by more than its size, "
                                              "or not finite")
        scaled.append(pts)
    mask = np.zeros((height, width), dtype=bool)
    for pts in scaled:
        if pts.shape[0] < 3:
            continue
        if rasterizer == "coco":
            rle = mask_utils.frPyObjects([pts.ravel().tolist()], height, width)
            mask |= mask_utils.decode(rle)[:, :, 0].astype(bool)
        elif rasterizer == "release_cv2":
            canvas = np.zeros((height, width), dtype=np.uint8)
            cv2.fillPoly(canvas, [pts.astype(np.int32)], 1)
            mask |= canvas.astype(bool)
        else:
            raise ValueError(f"unknown rasterizer {rasterizer!r}")
    return mask


def mask_to_polygons(mask: np.ndarray) -> list[list[int]]:
    """(H, W) bool -> one pixel-edge polygon (flat ``[x0, y0, ...]`` ints) per 8-connected component.

    Exact inverse of :func:`polygons_to_mask` with the default rasteriser (module docstring).
    An empty mask gives ``[]``.
    """
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        return []
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    polygons = []
    for k in range(1, count):
        x, y, w, h = (int(v) for v in stats[k, :4])
        comp = labels[y:y + h, x:x + w] == k
        loops = _boundary_loops(comp)
        poly = _keyhole(loops)
        poly[:, 0] += x
        poly[:, 1] += y
        polygons.append(poly.ravel().tolist())
    return polygons


def _boundary_loops(comp: np.ndarray) -> list[np.ndarray]:
    """Closed pixel-edge loops (each (N, 2) int corner vertices) bounding the bool region ``comp``.

    Directed unit edges keep the region on their right (y down): top edges go +x, right edges +y,
    bottom edges -x, left edges -y. Every vertex then has equal in- and out-degree, so the edges
    split into closed loops; the first loop starts at the top-left-most vertex, i.e. is the outer one.
    """
    h, w = comp.shape
    pad = np.zeros((h + 2, w + 2), dtype=bool)
    pad[1:-1, 1:-1] = comp
    inner = pad[1:-1, 1:-1]
    i, j = np.nonzero(inner & ~pad[:-2, 1:-1])      # top edges: (j, i) -> (j+1, i)
    top = np.stack([j, i, j + 1, i], 1)
    i, j = np.nonzero(inner & ~pad[1:-1, 2:])       # right edges: (j+1, i) -> (j+1, i+1)
    right = np.stack([j + 1, i, j + 1, i + 1], 1)
    i, j = np.nonzero(inner & ~pad[2:, 1:-1])       # bottom edges: (j+1, i+1) -> (j, i+1)
    bottom = np.stack([j + 1, i + 1, j, i + 1], 1)
    i, j = np.nonzero(inner & ~pad[1:-1, :-2])      # left edges: (j, i+1) -> (j, i)
    left = np.stack([j, i + 1, j, i], 1)
    edges = np.concatenate([top, right, bottom, left]).astype(np.int64)  # (E, 4) x0 y0 x1 y1

    stride = w + 1
    start = edges[:, 1] * stride + edges[:, 0]
    end = edges[:, 3] * stride + edges[:, 2]
    order = np.argsort(start, kind="stable")
    out_of: dict[int, list[int]] = {}
    for e in order.tolist():
        out_of.setdefault(int(start[e]), []).append(e)
    used = np.zeros(len(edges), dtype=bool)
    dirs = edges[:, 2:] - edges[:, :2]

    loops = []
    # raster order of start vertices: the first unused top edge begins the outer loop
    for first in order.tolist():
        if used[first]:
            continue
        verts = []
        e = first
        while not used[e]:
            used[e] = True
            verts.append(edges[e, :2])
            cands = [c for c in out_of[int(end[e])] if not used[c]]
            if not cands:
                break
            if len(cands) > 1:
                # a pinch vertex (two diagonal pixels): turn right, i.e. stay with this pixel
                dx, dy = dirs[e]
                right_turn = (-dy, dx)
                cands.sort(key=lambda c: 0 if tuple(dirs[c]) == right_turn else 1)
            e = cands[0]
        loops.append(_corners(np.array(verts)))
    return loops


def _corners(verts: np.ndarray) -> np.ndarray:
    """Drop vertices where the loop goes straight on; keeps the first vertex if it is a corner."""
    prev = np.roll(verts, 1, axis=0)
    nxt = np.roll(verts, -1, axis=0)
    d_in = verts - prev
    d_out = nxt - verts
    turn = (d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0]) != 0
    return verts[turn]


def _keyhole(loops: list[np.ndarray]) -> np.ndarray:
    """Join loops into one vertex ring: outer loop, then for each other loop a bridge from the
    outer start vertex, the loop, and the bridge back (walked twice, so it adds no area)."""
    outer = loops[0]
    ring = [outer, outer[:1]]
    for loop in loops[1:]:
        ring += [loop, loop[:1], outer[:1]]
    return np.concatenate(ring).astype(np.int64)
