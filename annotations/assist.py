"""Assisted segmentation for the annotation tool: a box (and corrective clicks) to a binary mask.

Two backends share one call, :meth:`Segmenter.segment`:

* :class:`GrabCutSegmenter` (default, offline, no weights): OpenCV GrabCut on a crop around the
  box, downscaled to a bounded size so one call stays well under a second at 960x540. A corrective
  click (left = "this is the object", right = "this is not") on a mask edits it locally: GrabCut
  runs in a disk around the click sized by the click's distance to the mask's edge, with the mask
  beyond it fixed, and only the connected change that holds the click is kept, so a click never
  undoes what earlier clicks fixed elsewhere.
* :class:`PromptedSamSegmenter` (optional): Segment Anything prompted with the box and clicks, the model
  loaded from a path the user gives by the ``sam`` segmenter's loader
  (:func:`methods.supervision.sam.load_segment_anything`). Image embeddings are computed per frame in a
  background thread (the tool asks for the frames around the one on screen) and cached in memory and,
  optionally, on disk.

Coordinates follow :mod:`benchmark.core.scene`: ``(x, y)`` are continuous pixel coordinates with the
image's top-left corner at ``(0, 0)``; pixel ``(row i, column j)`` covers ``[j, j+1) x [i, i+1)``.
Masks are ``(H, W)`` bool, images ``(H, W, 3)`` uint8 RGB.
"""

from __future__ import annotations

import collections
import hashlib
import queue
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Protocol, Sequence

import cv2
import numpy as np

from benchmark.core.errors import InputError

Box = tuple[float, float, float, float]
"""``(x0, y0, x1, y1)`` in pixel coordinates (corners, any order)."""
Click = tuple[float, float, int]
"""``(x, y, label)``: label 1 = part of the object (left click), 0 = not (right click)."""


class Segmenter(Protocol):
    """What the annotation server needs from an assisted segmenter."""

    name: str

    def segment(self, frame_key: str, image: np.ndarray, box: Optional[Box], clicks: Sequence[Click] = (),
                current: Optional[np.ndarray] = None) -> np.ndarray:
        """(H, W, 3) uint8 image -> (H, W) bool mask for the box and clicks.

        ``current`` is the (H, W) bool mask on screen; corrective clicks refine it.
        """

    def prefetch(self, frame_key: str, load_image: Callable[[], np.ndarray]) -> None:
        """Hint that ``frame_key`` may be segmented soon (precompute what can be)."""


# ---------------------------------------------------------------------------------------------
# GrabCut
# ---------------------------------------------------------------------------------------------
@dataclass
class GrabCutConfig:
    """Settings of the GrabCut backend."""

    margin: float = 0.25
    """Context added around the box on each side, as a fraction of the box's larger side: GrabCut
    learns the background colours from this ring."""
    min_margin_px: int = 16
    """At least this much context (pixels) on each side of the box."""
    max_side: int = 256
    """A crop whose larger side exceeds this is downscaled before GrabCut (its cost grows with
    the pixel count); the result is upscaled back to full resolution."""
    iterations: int = 4
    """GrabCut iterations for a new box."""
    refine_iterations: int = 3
    """GrabCut iterations after corrective clicks."""
    click_radius_px: float = 0.5
    """Radius of the hard-labelled disk around a click, in full-resolution pixels (0.5: the clicked
    pixel alone; a wider disk crosses the edges of thin parts and small objects)."""
    click_box_px: float = 48.0
    """Without a box or a mask, positive clicks are segmented in a box this many pixels around them."""
    click_reach: float = 8.0
    """A click on an existing mask may change it only within this many times the click's distance to
    the nearest pixel of the other label (the click sits inside an error region about that wide)."""
    click_min_reach_px: float = 4.0
    """That disk is at least this wide (pixels), so a click on a one-pixel error still has room."""
    click_tolerance: float = 15.0
    """Around a click on an existing mask, the connected region whose CIELAB channels stay within this
    of the clicked colour starts on the click's side ("probably")."""
    flood_tolerance: float = 8.0
    """A click also claims the connected region around it whose CIELAB channels stay within this
    of the clicked colour (as "probably" labels); 0 disables."""
    flood_reach: float = 0.2
    """That region is cut to a disk of this fraction of the crop's larger side around the click."""
    background_prior: bool = True
    """Start box pixels whose colour matches the context ring as "probably background"."""
    ring_colours: int = 6
    """Colour clusters (k-means) summarising the context ring for :attr:`background_prior`."""
    ring_distance: float = 10.0
    """A box pixel within this CIELAB distance of a ring cluster counts as background-coloured."""


class GrabCutSegmenter:
    """Box (+ clicks) to mask with GrabCut on a bounded crop (see :class:`GrabCutConfig`)."""

    name = "grabcut"

    def __init__(self, config: Optional[GrabCutConfig] = None):
        self.config = config or GrabCutConfig()

    def prefetch(self, frame_key: str, load_image: Callable[[], np.ndarray]) -> None:
        """Nothing to precompute for GrabCut."""

    def segment(self, frame_key: str, image: np.ndarray, box: Optional[Box], clicks: Sequence[Click] = (),
                current: Optional[np.ndarray] = None) -> np.ndarray:
        image = _check_image(image)
        height, width = image.shape[:2]
        current = None if current is None else _check_mask(current, (height, width))
        clicks = [(float(x), float(y), int(lbl)) for x, y, lbl in clicks]
        if current is not None and current.any() and clicks:
            return self._edit(image, current, clicks)
        box = self._box_for(box, clicks, current)
        if box is None:  # no box, no mask to refine, no positive click: nothing to segment
            return np.zeros((height, width), bool) if current is None else current.copy()
        bx0, by0, bx1, by1 = _box_pixels(box, width, height)
        if bx1 - bx0 < 2 or by1 - by0 < 2:
            raise InputError(None, "box", f"box {box} covers less than 2x2 pixels of the {width}x{height} image")
        crop = self._crop(image, (bx0, by0, bx1, by1), clicks)
        labels = self._initial_labels(crop)
        self._label_clicks(labels, crop, clicks)
        fg_possible = np.isin(labels, (cv2.GC_FGD, cv2.GC_PR_FGD))
        if not fg_possible.any():
            return np.zeros((height, width), bool)
        _grabcut(crop.small, labels, self.config.refine_iterations if clicks else self.config.iterations)
        fg_small = np.isin(labels, (cv2.GC_FGD, cv2.GC_PR_FGD)).astype(np.float32)
        fg_crop = (cv2.resize(fg_small, (crop.width, crop.height), interpolation=cv2.INTER_LINEAR) >= 0.5) \
            if crop.scale < 1.0 else fg_small > 0.5
        out = np.zeros((height, width), bool)
        out[crop.rows, crop.cols] = fg_crop
        _stamp_clicks(out, clicks, self.config.click_radius_px)
        return out

    def _edit(self, image: np.ndarray, current: np.ndarray, clicks: Sequence[Click]) -> np.ndarray:
        """``current`` with each click applied in order; a click whose pixel already has its label was
        applied before (the page sends every click of the mask with the mask they made) and is skipped."""
        height, width = current.shape
        out = current.copy()
        lab = None
        for x, y, lbl in clicks:
            col, row = int(np.clip(x, 0, width - 1)), int(np.clip(y, 0, height - 1))
            if out[row, col] == bool(lbl == 1):
                continue
            if lab is None:
                lab = cv2.cvtColor(image, cv2.COLOR_RGB2LAB)
            out = self._edit_one(image, lab, out, (col, row), lbl == 1, clicks)
        _stamp_clicks(out, clicks, self.config.click_radius_px)
        return out

    def _edit_one(self, image: np.ndarray, lab: np.ndarray, mask: np.ndarray, at: tuple[int, int],
                  positive: bool, clicks: Sequence[Click]) -> np.ndarray:
        """One click at pixel ``at`` (column, row) on ``mask``: GrabCut in a disk around it whose radius
        follows the click's distance to the other label, the mask fixed outside the disk; the connected
        piece of change that holds the click is kept."""
        height, width = mask.shape
        col, row = at
        same = np.pad((mask == mask[row, col]).astype(np.uint8), 1, constant_values=1)
        edge_distance = float(cv2.distanceTransform(same, cv2.DIST_L2, 5)[row + 1, col + 1])
        reach = int(np.ceil(max(self.config.click_min_reach_px, self.config.click_reach * edge_distance)))
        x0, y0 = max(0, col - reach), max(0, row - reach)
        x1, y1 = min(width, col + reach + 1), min(height, row + reach + 1)
        window = mask[y0:y1, x0:x1]
        labels = np.where(window, cv2.GC_PR_FGD, cv2.GC_PR_BGD).astype(np.uint8)
        yy, xx = np.mgrid[y0:y1, x0:x1]
        beyond = (xx - col) ** 2 + (yy - row) ** 2 > reach ** 2
        labels[beyond] = np.where(window[beyond], cv2.GC_FGD, cv2.GC_BGD)
        if self.config.click_tolerance > 0:
            region = _flood(np.ascontiguousarray(lab[y0:y1, x0:x1]), (col - x0, row - y0),
                            self.config.click_tolerance, reach)
            labels[region & ~beyond] = cv2.GC_PR_FGD if positive else cv2.GC_PR_BGD
        labels[row - y0, col - x0] = cv2.GC_FGD if positive else cv2.GC_BGD
        # every click so far holds its label in the window (GrabCut may not trade one fix for another)
        radius = max(1, int(round(self.config.click_radius_px)))
        for x, y, lbl in clicks:
            cv2.circle(labels, (int(x) - x0, int(y) - y0), radius, int(cv2.GC_FGD if lbl == 1 else cv2.GC_BGD), -1)
        result = np.where(beyond, window, self._grabcut_window(image[y0:y1, x0:x1], labels))
        edited = mask.copy()
        edited[y0:y1, x0:x1] = result
        change = (edited != mask).astype(np.uint8)
        if change[row, col]:
            _, pieces = cv2.connectedComponents(change, connectivity=8)
            edited = np.where(pieces == pieces[row, col], edited, mask)
        return edited

    def _grabcut_window(self, image: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """(h, w) bool: GrabCut from ``labels`` on ``image``, downscaled to ``max_side`` when larger."""
        h, w = labels.shape
        scale = min(1.0, self.config.max_side / max(h, w))
        if scale < 1.0:
            size = (max(2, int(round(w * scale))), max(2, int(round(h * scale))))
            small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
            work = cv2.resize(labels, size, interpolation=cv2.INTER_NEAREST)
        else:
            small, work = np.ascontiguousarray(image), labels.copy()
        fg = np.isin(work, (cv2.GC_FGD, cv2.GC_PR_FGD))
        if fg.any() and not fg.all():
            _grabcut(small, work, self.config.refine_iterations)
        fg = np.isin(work, (cv2.GC_FGD, cv2.GC_PR_FGD))
        if scale < 1.0:
            fg = cv2.resize(fg.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR) >= 0.5
            fg[labels == cv2.GC_FGD] = True
            fg[labels == cv2.GC_BGD] = False
        return fg

    def _box_for(self, box: Optional[Box], clicks: Sequence[Click], current: Optional[np.ndarray]) -> Optional[Box]:
        """The box to segment in: ``box``, else the current mask's bounds, else a box around the positive
        clicks a few click radii wide; ``None`` when there is none of them."""
        if box is None and current is not None and current.any():
            ys, xs = np.nonzero(current)
            box = (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
        if box is None:
            if not any(lbl == 1 for _, _, lbl in clicks):
                return None
            pos = np.array([(x, y) for x, y, lbl in clicks if lbl == 1])
            pad = self.config.click_box_px
            box = (pos[:, 0].min() - pad, pos[:, 1].min() - pad, pos[:, 0].max() + pad, pos[:, 1].max() + pad)
        return box

    def _crop(self, image: np.ndarray, box: tuple[int, int, int, int], clicks: Sequence[Click]) -> "_Crop":
        """The box with context around it, grown to hold every click, and downscaled to ``max_side``."""
        height, width = image.shape[:2]
        bx0, by0, bx1, by1 = box
        side = max(bx1 - bx0, by1 - by0)
        pad = max(self.config.min_margin_px, int(round(self.config.margin * side)))
        cx0, cy0, cx1, cy1 = bx0 - pad, by0 - pad, bx1 + pad, by1 + pad
        for x, y, _ in clicks:
            cx0, cy0 = min(cx0, int(x) - pad), min(cy0, int(y) - pad)
            cx1, cy1 = max(cx1, int(x) + pad), max(cy1, int(y) + pad)
        cx0, cy0, cx1, cy1 = max(cx0, 0), max(cy0, 0), min(cx1, width), min(cy1, height)
        crop = image[cy0:cy1, cx0:cx1]
        ch, cw = crop.shape[:2]
        scale = min(1.0, self.config.max_side / max(ch, cw))
        sw, sh = max(2, int(round(cw * scale))), max(2, int(round(ch * scale)))
        sx, sy = sw / cw, sh / ch
        small = cv2.resize(crop, (sw, sh), interpolation=cv2.INTER_AREA) if scale < 1.0 else crop.copy()
        inner = (int(np.floor((by0 - cy0) * sy)), int(np.ceil((by1 - cy0) * sy)),
                 int(np.floor((bx0 - cx0) * sx)), int(np.ceil((bx1 - cx0) * sx)))
        return _Crop(cx0, cy0, cx1, cy1, small, scale, sx, sy, inner)

    def _initial_labels(self, crop: "_Crop") -> np.ndarray:
        """GrabCut's starting labels on the downscaled crop: outside the box background; inside "probably
        object", less the pixels coloured like the context ring."""
        sh, sw = crop.small.shape[:2]
        r0, r1, c0, c1 = crop.inner
        labels = np.full((sh, sw), cv2.GC_BGD, np.uint8)
        labels[r0:r1, c0:c1] = cv2.GC_PR_FGD
        if self.config.background_prior:
            # inside the box, pixels coloured like the context ring start as "probably background":
            # otherwise a box around a thin or spread-out object (limbs, a person with arms
            # out) teaches GrabCut's object model the background colour seen between the limbs
            like_bg = _like_ring(crop.small, labels == cv2.GC_BGD, self.config.ring_colours,
                                 self.config.ring_distance)
            inside = np.zeros((sh, sw), bool)
            inside[r0:r1, c0:c1] = True
            labels[inside & like_bg] = cv2.GC_PR_BGD
        if not (labels == cv2.GC_BGD).any():
            # the box fills the whole image: let the crop's border ring stand in for background
            ring = np.zeros((sh, sw), bool)
            ring[:2, :], ring[-2:, :], ring[:, :2], ring[:, -2:] = True, True, True, True
            labels[ring & (labels != cv2.GC_FGD)] = cv2.GC_PR_BGD
        return labels

    def _label_clicks(self, labels: np.ndarray, crop: "_Crop", clicks: Sequence[Click]) -> None:
        """Each click's disk becomes a hard label, and the uniform region around it a "probable" one."""
        sh, sw = labels.shape
        radius = max(1, int(round(self.config.click_radius_px * crop.scale)))
        if self.config.flood_tolerance > 0 and clicks:
            # a click speaks for the uniform region around it, not only its disk: that region starts
            # on the clicked side ("probably"), so one right click on a face removes the face
            lab = cv2.cvtColor(crop.small, cv2.COLOR_RGB2LAB)
            reach = max(radius, int(self.config.flood_reach * max(sh, sw)))
            for x, y, lbl in clicks:
                region = _flood(lab, crop.point(x, y), self.config.flood_tolerance, reach)
                if lbl == 1:
                    labels[region & (labels != cv2.GC_FGD) & (labels != cv2.GC_BGD)] = cv2.GC_PR_FGD
                else:
                    labels[region & (labels != cv2.GC_FGD)] = cv2.GC_PR_BGD
        for x, y, lbl in clicks:
            cv2.circle(labels, crop.point(x, y), radius, int(cv2.GC_FGD if lbl == 1 else cv2.GC_BGD), thickness=-1)


@dataclass
class _Crop:
    """The part of the image GrabCut sees: ``[x0, x1) x [y0, y1)``, downscaled by ``scale``."""

    x0: int
    y0: int
    x1: int
    y1: int
    small: np.ndarray
    """The crop at GrabCut's resolution (uint8 RGB)."""
    scale: float
    """Downscale factor (1 = full resolution)."""
    sx: float
    sy: float
    """Exact horizontal and vertical factors from crop to ``small`` pixels."""
    inner: tuple[int, int, int, int]
    """The box in ``small`` pixels: rows ``[r0, r1)``, columns ``[c0, c1)``."""

    @property
    def rows(self) -> slice:
        return slice(self.y0, self.y1)

    @property
    def cols(self) -> slice:
        return slice(self.x0, self.x1)

    @property
    def height(self) -> int:
        return self.y1 - self.y0

    @property
    def width(self) -> int:
        return self.x1 - self.x0

    def point(self, x: float, y: float) -> tuple[int, int]:
        """Image coordinates -> ``small`` pixel (column, row)."""
        return int((x - self.x0) * self.sx), int((y - self.y0) * self.sy)


def _grabcut(image: np.ndarray, labels: np.ndarray, iterations: int) -> None:
    """GrabCut from ``labels`` (updated in place) on ``image``, a contiguous uint8 RGB array."""
    bgd_model = np.zeros((1, 65), np.float64)
    fgd_model = np.zeros((1, 65), np.float64)
    try:
        cv2.grabCut(image, labels, None, bgd_model, fgd_model, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        pass  # degenerate colour statistics (e.g. a flat crop): keep the prior labelling


def _like_ring(image: np.ndarray, ring: np.ndarray, k: int, distance: float) -> np.ndarray:
    """(h, w) bool: pixels of ``image`` (uint8 RGB) within ``distance`` (CIELAB) of a ring colour cluster."""
    samples = cv2.cvtColor(image, cv2.COLOR_RGB2LAB).astype(np.float32)
    ring_px = samples[ring]
    if ring_px.shape[0] < 2 * k:
        return np.zeros(image.shape[:2], bool)
    rng = np.random.default_rng(0)
    if ring_px.shape[0] > 4000:
        ring_px = ring_px[rng.choice(ring_px.shape[0], 4000, replace=False)]
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.5)
    cv2.setRNGSeed(0)
    _, _, centres = cv2.kmeans(ring_px, k, None, criteria, 2, cv2.KMEANS_PP_CENTERS)
    flat = samples.reshape(-1, 3)
    d2 = ((flat[:, None, :] - centres[None, :, :]) ** 2).sum(-1).min(1)
    return (d2 <= distance ** 2).reshape(image.shape[:2])


def _flood(lab: np.ndarray, seed: tuple[int, int], tolerance: float, reach: int) -> np.ndarray:
    """(h, w) bool: pixels connected to ``seed`` (x, y) within ``tolerance`` of its colour, within ``reach``."""
    h, w = lab.shape[:2]
    x, y = seed
    if not (0 <= x < w and 0 <= y < h):
        return np.zeros((h, w), bool)
    x0, y0, x1, y1 = max(0, x - reach), max(0, y - reach), min(w, x + reach + 1), min(h, y + reach + 1)
    crop = np.ascontiguousarray(lab[y0:y1, x0:x1])
    mask = np.zeros((y1 - y0 + 2, x1 - x0 + 2), np.uint8)
    tol = (tolerance,) * 3
    cv2.floodFill(crop, mask, (x - x0, y - y0), (0, 0, 0), tol, tol,
                  4 | cv2.FLOODFILL_FIXED_RANGE | cv2.FLOODFILL_MASK_ONLY | (1 << 8))
    out = np.zeros((h, w), bool)
    region = mask[1:-1, 1:-1].astype(bool)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    out[y0:y1, x0:x1] = region & ((xx - x) ** 2 + (yy - y) ** 2 <= reach ** 2)
    return out


def _stamp_clicks(mask: np.ndarray, clicks: Sequence[Click], radius: float) -> None:
    """Force the click disks to their labels at full resolution (upscaling may have blurred them)."""
    h, w = mask.shape
    r = int(np.ceil(radius))
    for x, y, lbl in clicks:
        i0, i1 = max(0, int(y) - r), min(h, int(y) + r + 1)
        j0, j1 = max(0, int(x) - r), min(w, int(x) + r + 1)
        if i0 >= i1 or j0 >= j1:
            continue
        ii, jj = np.mgrid[i0:i1, j0:j1]
        disk = (jj + 0.5 - x) ** 2 + (ii + 0.5 - y) ** 2 <= radius ** 2
        mask[i0:i1, j0:j1][disk] = bool(lbl == 1)


def _box_pixels(box: Box, width: int, height: int) -> tuple[int, int, int, int]:
    """Corner box -> integer pixel bounds ``[x0, x1) x [y0, y1)`` clipped to the image."""
    try:
        x0, y0, x1, y1 = (float(v) for v in box)
    except (TypeError, ValueError):
        raise InputError(None, "box", f"expected four numbers (x0, y0, x1, y1), got {box!r}") from None
    if not all(np.isfinite([x0, y0, x1, y1])):
        raise InputError(None, "box", f"non-finite coordinates {box!r}")
    x0, x1 = sorted((x0, x1))
    y0, y1 = sorted((y0, y1))
    return (int(np.clip(np.floor(x0), 0, width)), int(np.clip(np.floor(y0), 0, height)),
            int(np.clip(np.ceil(x1), 0, width)), int(np.clip(np.ceil(y1), 0, height)))


def _check_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(None, "image", f"expected (H, W, 3) RGB, got shape {image.shape}")
    if image.dtype != np.uint8:
        image = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return np.ascontiguousarray(image)


def _check_mask(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    mask = np.asarray(mask).astype(bool)
    if mask.shape != shape:
        raise InputError(None, "mask", f"expected shape {shape}, got {mask.shape}")
    return mask


# ---------------------------------------------------------------------------------------------
# Segment Anything (optional)
# ---------------------------------------------------------------------------------------------
@dataclass
class PromptedSamConfig:
    """Settings of the optional SAM backend."""

    checkpoint: Optional[Path] = None
    """Path to the SAM weights on the user's machine (nothing is downloaded)."""
    model_type: str = "vit_b"
    """Registry name of the architecture matching the checkpoint (``vit_b``, ``vit_l``, ``vit_h``)."""
    device: str = "cpu"
    """Torch device for the image encoder and mask decoder."""
    memory_cache: int = 24
    """Image embeddings kept in memory (vit_b: 4 MiB each)."""
    cache_dir: Optional[Path] = None
    """Where embeddings are also cached on disk (``None``: memory only)."""


@dataclass
class _Embedding:
    features: object
    """(1, 256, 64, 64) torch tensor: the image encoder's output."""
    original_size: tuple[int, int]
    input_size: tuple[int, int]


class PromptedSamSegmenter:
    """Segment Anything prompted with a box and clicks, with per-frame embeddings computed in the
    background and cached.

    ``predictor`` is a ``segment_anything.SamPredictor`` (or anything with its ``set_image`` /
    ``predict`` interface and ``features``/``original_size``/``input_size`` attributes); by default the
    ``sam`` segmenter's loader builds one from :attr:`PromptedSamConfig.checkpoint`.
    """

    name = "sam"

    def __init__(self, config: PromptedSamConfig, predictor=None):
        self.config = config
        self._predictor = predictor if predictor is not None else _load_sam_predictor(config)
        self._cache: collections.OrderedDict[str, _Embedding] = collections.OrderedDict()
        self._lock = threading.Lock()          # guards the cache and the pending set
        self._model_lock = threading.Lock()    # one forward pass at a time (the predictor is stateful)
        self._pending: dict[str, Callable[[], np.ndarray]] = {}
        self._jobs: "queue.Queue[str]" = queue.Queue()
        self._worker = threading.Thread(target=self._run_worker, name="sam-embeddings", daemon=True)
        self._worker.start()
        if config.cache_dir is not None:
            Path(config.cache_dir).mkdir(parents=True, exist_ok=True)

    # -- embeddings -----------------------------------------------------------------------------
    def prefetch(self, frame_key: str, load_image: Callable[[], np.ndarray]) -> None:
        with self._lock:
            if frame_key in self._cache or frame_key in self._pending:
                return
            self._pending[frame_key] = load_image
        self._jobs.put(frame_key)

    def cached(self, frame_key: str) -> bool:
        with self._lock:
            return frame_key in self._cache

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Block until every prefetched embedding is computed (tests and benchmarks)."""
        import time

        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self._lock:
                if not self._pending and self._jobs.empty():
                    return True
            time.sleep(0.01)
        return False

    def _run_worker(self) -> None:
        while True:
            key = self._jobs.get()
            with self._lock:
                loader = self._pending.get(key)
            if loader is None:
                continue
            try:
                self._embedding(key, _check_image(loader()))
            except Exception:  # noqa: BLE001 - a failed prefetch is retried in the foreground
                pass
            finally:
                with self._lock:
                    self._pending.pop(key, None)

    def _disk_path(self, frame_key: str) -> Optional[Path]:
        if self.config.cache_dir is None:
            return None
        digest = hashlib.sha1(f"{self.config.model_type}:{frame_key}".encode()).hexdigest()[:20]
        return Path(self.config.cache_dir) / f"{digest}.pt"

    def _embedding(self, frame_key: str, image: np.ndarray) -> _Embedding:
        with self._lock:
            emb = self._cache.get(frame_key)
            if emb is not None:
                self._cache.move_to_end(frame_key)
                return emb
        path = self._disk_path(frame_key)
        emb = None
        if path is not None and path.is_file():
            import torch

            try:
                saved = torch.load(path, map_location=self.config.device, weights_only=True)
                emb = _Embedding(saved["features"], tuple(saved["original_size"]), tuple(saved["input_size"]))
            except Exception:  # noqa: BLE001 - a corrupt cache entry is recomputed
                emb = None
        if emb is None:
            with self._model_lock:
                self._predictor.set_image(image)
                emb = _Embedding(self._predictor.features, tuple(self._predictor.original_size),
                                 tuple(self._predictor.input_size))
            if path is not None:
                import torch

                from benchmark.core.atomic import atomic_path

                with atomic_path(path) as tmp:
                    torch.save({"features": emb.features, "original_size": list(emb.original_size),
                                "input_size": list(emb.input_size)}, tmp)
        with self._lock:
            self._cache[frame_key] = emb
            self._cache.move_to_end(frame_key)
            while len(self._cache) > self.config.memory_cache:
                self._cache.popitem(last=False)
        return emb

    # -- masks ----------------------------------------------------------------------------------
    def segment(self, frame_key: str, image: np.ndarray, box: Optional[Box], clicks: Sequence[Click] = (),
                current: Optional[np.ndarray] = None) -> np.ndarray:
        image = _check_image(image)
        height, width = image.shape[:2]
        if box is None and not clicks:
            return np.zeros((height, width), bool) if current is None else _check_mask(current, (height, width))
        emb = self._embedding(frame_key, image)
        coords = np.array([(x, y) for x, y, _ in clicks], np.float32) if clicks else None
        labels = np.array([lbl for _, _, lbl in clicks], np.int32) if clicks else None
        box_arr = None
        if box is not None:
            x0, y0, x1, y1 = _box_pixels(box, width, height)
            box_arr = np.array([x0, y0, x1, y1], np.float32)
        with self._model_lock:
            self._predictor.features = emb.features
            self._predictor.original_size = emb.original_size
            self._predictor.input_size = emb.input_size
            self._predictor.is_image_set = True
            masks, _, _ = self._predictor.predict(point_coords=coords, point_labels=labels, box=box_arr,
                                                  multimask_output=False)
        return np.asarray(masks[0]).astype(bool)


def _load_sam_predictor(config: PromptedSamConfig):
    """The ``sam`` segmenter's model (:func:`methods.supervision.sam.load_segment_anything`), once the
    tool's own options are checked."""
    if config.checkpoint is None:
        raise InputError(None, "--sam-checkpoint", "the SAM backend needs a path to its weights")
    path = Path(config.checkpoint)
    if not path.is_file():
        raise InputError(path, "--sam-checkpoint", "SAM weights not found")
    from methods.supervision.sam import load_segment_anything

    return load_segment_anything(path, config.model_type, config.device)


def make_segmenter(kind: str = "grabcut", *, sam_checkpoint: Optional[Path] = None, sam_model: str = "vit_b",
                   cache_dir: Optional[Path] = None, device: str = "cpu") -> Segmenter:
    """The backend named by ``kind`` (``"grabcut"`` or ``"sam"``)."""
    if kind == "grabcut":
        return GrabCutSegmenter()
    if kind == "sam":
        return PromptedSamSegmenter(PromptedSamConfig(checkpoint=sam_checkpoint, model_type=sam_model, device=device,
                                                      cache_dir=cache_dir))
    raise InputError(None, "--segmenter", f"unknown segmenter {kind!r} (grabcut or sam)")
