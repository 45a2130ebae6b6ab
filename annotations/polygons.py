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
"""

from __future__ import annotations

from typing import Literal, Sequence

import cv2
import numpy as np
from pycocotools import mask as mask_utils

Rasterizer = Literal["coco", "release_cv2"]

__all__ = ["Rasterizer", "mask_to_polygons", "polygons_to_mask"]


def polygons_to_mask(polygons: Sequence[Sequence[float]], height: int, width: int, *,
                     scale: tuple[float, float] = (1.0, 1.0), rasterizer: Rasterizer = "coco") -> np.ndarray:
    """OR of the polygons' fills as an (H, W) bool mask.

    ``polygons``: COCO flat lists ``[x0, y0, x1, y1, ...]`` (already validated: even length, finite).
    ``scale``: ``(sx, sy)`` applied to the vertices first (a polygon drawn on a resized image is
    mapped back by ``x * sx``, ``y * sy``; scaling about the top-left corner is exact in the corner
    convention). A polygon with fewer than 3 vertices encloses no area and adds nothing.
    """
    mask = np.zeros((height, width), dtype=bool)
    sx, sy = scale
    for poly in polygons:
        pts = np.asarray(poly, dtype=np.float64).reshape(-1, 2)
        if pts.shape[0] < 3:
            continue
        pts = pts * np.array([sx, sy])
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
