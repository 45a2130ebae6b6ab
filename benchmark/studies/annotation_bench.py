"""The annotation tool measured by a simulated annotator against exact ground truth.

The annotator talks to the tool's own HTTP API, as the page does (token header, JSON bodies, this
server's origin), never to its internals:

* **interactive masks, clicks only** (the protocol of the interactive segmentation literature, e.g.
  RITM, Sofiiuk et al. 2022, and Xu et al. 2016 before it): the first click at the interior point of the
  truth mask farthest from its boundary, each next click at the centre of the largest error region (the
  maximum of the distance transform of that region's mask, the image border counting as an edge):
  positive inside a missed region, negative inside a false one; at most
  :attr:`BenchConfig.max_interactions` clicks. Its NoC@85 / NoC@90 compare with the literature's.
* **interactive masks, box first** (how the tool is meant to be used): a box around the truth mask with
  stated noise (:func:`noisy_box`: each edge off by a normal draw of :attr:`BenchConfig.box_jitter` of the
  object's size), then the same corrective clicks until the target IoU or the cap; the box counts as one
  interaction. A frame where the object is absent is marked absent (the ``A`` key: one interaction).
* **propagation** (``/api/propagate``): from an annotated frame to the next frames of the session; a
  proposal at or above the target IoU is accepted (``Enter``), a poorer one is corrected with clicks
  starting from the proposal, and propagation resumes from the corrected frame.
* **time segments**: stepping through the video as the page shows it (``/api/frame``), the annotator
  finds where the base object's pixels change (:func:`change_times`: a step detector on the frames'
  pixels inside the object's region, not the truth's intervals) and presses ``[`` / ``]`` there, each saved
  as the page saves them (an ``intervals`` change). Which side of a change the state holds on is what a
  person reads from the query; the simulation takes it from the truth's majority between two changes.

Which frames: the frames the benchmark scores (the ground truth's annotated frames) for masks; every
frame of the video for time segments and for the propagation-versus-distance curve.

The tool is started by the caller (:data:`ToolLauncher`): this module is only the client.
"""

from __future__ import annotations

import json
import time
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ContextManager, Optional

import cv2
import numpy as np

from benchmark.core.annotation import AnnotationSet, normalise_intervals
from benchmark.core.errors import InputError

from ._report import markdown_table, number_cell, write_report

TOKEN_HEADER = "X-Bench4d-Token"

BOX_SECONDS = 7.0
"""Human time to draw one box: extreme clicking, Papadopoulos et al., "Extreme clicking for efficient
object annotation", ICCV 2017 (7.0 s per box, against 34.5 s for drawing a box the usual way)."""
CLICK_SECONDS = 2.4
"""Human time for one corrective click: one point on an object, Bearman et al., "What's the point:
semantic segmentation with point supervision", ECCV 2016 (2.4 s per point)."""
KEY_SECONDS = 1.0
"""Human time to look at a proposal and press one key (accept, absent, ``[`` / ``]``): an assumption
of this benchmark, no published source."""


@dataclass
class BenchConfig:
    """Settings of the simulated annotator."""

    target_iou: float = 0.90
    """IoU at which the annotator stops correcting a mask (and accepts a propagated proposal)."""
    max_interactions: int = 20
    """Interactions (box + clicks) after which a frame counts as failed (NoC cap)."""
    propagation_frames: int = 30
    """Frames propagated without correction for the IoU-versus-distance curve."""
    box_margin: int = 2
    """Pixels added on each side of the truth mask's bounding box (a person's box is not tight)."""
    box_jitter: float = 0.05
    """Standard deviation of each box edge's offset (:func:`noisy_box`), as a share of the object's width (left
    and right edges) or height (top and bottom): a person's box is not exact either. An assumption of this
    benchmark (5 % of the object's size), stated in the report; 0 gives the truth's box plus the margin."""
    seed: int = 0
    """Seed of the box noise (one draw per query, frame and seed)."""
    change_window: int = 3
    """Time steps on each side of a candidate change that the interval marker compares (:func:`change_times`)."""
    change_threshold: float = 3.0
    """A change is marked where the step between the two windows exceeds this many times the median step
    over the video (camera and object motion make the median; a state change stands out of it)."""
    restart_below_iou: float = 0.5
    """A propagated proposal below this IoU is redrawn from a box instead of corrected with clicks."""
    images: str = "rendered"
    """``rendered``: the scenes' own images; ``truth-colours``: every frame repainted with one flat colour per
    truth region (:func:`paint_truth_regions`), the ceiling of a colour-driven assistant."""


# ---------------------------------------------------------------------------------------------
# the page's mask format (COCO uncompressed runs, column-major, first run = zeros)
# ---------------------------------------------------------------------------------------------
def mask_to_runs(mask: np.ndarray) -> list[int]:
    """(H, W) bool -> the page's run lengths."""
    flat = np.asarray(mask, dtype=bool).ravel(order="F")
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    runs = np.diff(np.concatenate([[0], change, [flat.size]])).tolist()
    return [0] + runs if flat.size and flat[0] else runs


def runs_to_mask(runs: list[int], height: int, width: int) -> np.ndarray:
    """The page's run lengths -> (H, W) bool."""
    values = (np.arange(len(runs)) % 2).astype(bool)
    return np.repeat(values, np.asarray(runs, dtype=np.int64)).reshape(width, height).T.copy()


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union; two empty masks agree fully (1.0)."""
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


def corrective_click(pred: np.ndarray, truth: np.ndarray) -> Optional[tuple[float, float, int]]:
    """The next click: ``(x, y, label)`` at the centre of the largest error region (label 1 in a
    missed region, 0 in a false one); ``None`` when the masks agree."""
    best = None
    for label, error in ((1, truth & ~pred), (0, pred & ~truth)):
        if not error.any():
            continue
        # the image border counts as the region's edge: pad with background before the transform
        padded = np.pad(error.astype(np.uint8), 1)
        dist = cv2.distanceTransform(padded, cv2.DIST_L2, 5)[1:-1, 1:-1]
        y, x = np.unravel_index(int(np.argmax(dist)), dist.shape)
        if best is None or dist[y, x] > best[0]:
            best = (float(dist[y, x]), (float(x) + 0.5, float(y) + 0.5, label))
    return None if best is None else best[1]


def one_pixel_iou(truth: np.ndarray) -> Optional[float]:
    """The IoU a one-pixel boundary error leaves: the lower of ``truth`` against itself eroded and dilated by
    one pixel (3x3). Below the target IoU, reaching the target needs every boundary pixel right. ``None`` for
    an empty mask."""
    mask = np.asarray(truth, dtype=np.uint8)
    area = int(mask.sum())
    if area == 0:
        return None
    kernel = np.ones((3, 3), np.uint8)
    eroded = int(cv2.erode(mask, kernel, borderType=cv2.BORDER_REPLICATE).sum())
    dilated = int(cv2.dilate(mask, kernel, borderType=cv2.BORDER_REPLICATE).sum())
    return min(eroded / area, area / dilated)


def truth_box(truth: np.ndarray, margin: int) -> list[float]:
    """``[x0, y0, x1, y1]`` around the truth mask, ``margin`` pixels wider on each side, in the frame."""
    return noisy_box(truth, margin, 0.0, np.random.default_rng(0))


def noisy_box(truth: np.ndarray, margin: int, jitter: float, rng: np.random.Generator) -> list[float]:
    """``[x0, y0, x1, y1]``: the truth mask's bounding box, ``margin`` pixels wider on each side, each edge
    then moved by a normal draw of standard deviation ``jitter`` times the object's width (x edges) or height
    (y edges); inside the frame and at least one pixel wide and tall. A negative draw may cut the object."""
    ys, xs = np.nonzero(truth)
    h, w = truth.shape
    x0, y0, x1, y1 = float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1)
    dx0, dy0, dx1, dy1 = rng.normal(0.0, jitter, 4) * [x1 - x0, y1 - y0, x1 - x0, y1 - y0] if jitter > 0 else (0,) * 4
    x0, x1 = min(max(0.0, x0 - margin + dx0), w - 1.0), max(min(float(w), x1 + margin + dx1), 1.0)
    y0, y1 = min(max(0.0, y0 - margin + dy0), h - 1.0), max(min(float(h), y1 + margin + dy1), 1.0)
    x1, y1 = max(x1, x0 + 1.0), max(y1, y0 + 1.0)
    return [round(x0, 2), round(y0, 2), round(x1, 2), round(y1, 2)]


def box_rng(seed: int, query: str, frame: str) -> np.random.Generator:
    """The box noise's generator of one (query, frame): the same box for the same mask in every run."""
    import zlib

    return np.random.default_rng([seed, zlib.crc32(f"{query}\x00{frame}".encode())])


def first_click(truth: np.ndarray) -> Optional[tuple[float, float, int]]:
    """The standard first click: ``(x, y, 1)`` at the interior point of ``truth`` farthest from its boundary
    (the image border counting as boundary); ``None`` for an empty mask."""
    return corrective_click(np.zeros_like(truth, dtype=bool), np.asarray(truth, bool))


# ---------------------------------------------------------------------------------------------
# the tool's HTTP API
# ---------------------------------------------------------------------------------------------
class ToolRefused(RuntimeError):
    """The tool answered a request with an error status."""

    def __init__(self, status: int, body: str, path: str):
        super().__init__(f"{path}: HTTP {status}: {body}")
        self.status = status


class ToolClient:
    """The page's side of the tool's API: state, segment, propagate, save, queries."""

    def __init__(self, url: str, token: str, timeout: float = 120.0):
        parts = url.split("/", 3)
        self.origin = "/".join(parts[:3])
        self.token = token
        self.timeout = timeout
        self.revision = 0
        self.round_trips: list[float] = []
        """Client-side seconds of every segment and propagate request."""
        self.frames: list[dict] = []
        self.queries: dict[str, int] = {}
        self.refresh()

    def _call(self, path: str, body: Optional[dict] = None) -> Any:
        data = None if body is None else json.dumps(body).encode()
        headers = {TOKEN_HEADER: self.token, "Origin": self.origin}
        if data is not None:
            headers["Content-Type"] = "application/json"
        req = urllib.request.Request(self.origin + path, data=data, headers=headers,
                                     method="GET" if data is None else "POST")
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as resp:
                return json.loads(resp.read().decode())
        except urllib.error.HTTPError as err:
            raise ToolRefused(err.code, err.read().decode("utf-8", "replace")[:400], path) from None

    def frame_image(self, index: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB of frame ``index`` as the page shows it (``/api/frame/<index>.jpg``)."""
        req = urllib.request.Request(f"{self.origin}/api/frame/{int(index)}.jpg",
                                     headers={TOKEN_HEADER: self.token, "Origin": self.origin})
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as resp:
                data = np.frombuffer(resp.read(), np.uint8)
        except urllib.error.HTTPError as err:
            raise ToolRefused(err.code, err.read().decode("utf-8", "replace")[:400], f"/api/frame/{index}.jpg") from None
        image = cv2.imdecode(data, cv2.IMREAD_COLOR)
        if image is None:
            raise ToolRefused(200, "not a JPEG image", f"/api/frame/{index}.jpg")
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)

    def refresh(self) -> None:
        state = self._call("/api/state")
        self.revision = state["revision"]
        self.frames = state["frames"]
        self.queries = {q["text"]: q["id"] for q in state["queries"]}

    def add_query(self, text: str, kind: str = "agnostic", base: Optional[str] = None,
                  level: Optional[str] = None) -> int:
        out = self._call("/api/queries/add", {"revision": self.revision, "text": text, "kind": kind,
                                              "base": None if base is None else self.queries[base], "level": level})
        self.revision = out["revision"]
        self.queries[text] = out["id"]
        return out["id"]

    def segment(self, frame: int, box: Optional[list[float]], clicks: list, current: Optional[np.ndarray]) -> tuple:
        """(mask, server seconds) of one assisted segmentation request."""
        body = {"frame": frame, "box": box, "clicks": [list(c) for c in clicks],
                "current": None if current is None else {"counts": mask_to_runs(current)}}
        t0 = time.perf_counter()
        out = self._call("/api/segment", body)
        self.round_trips.append(time.perf_counter() - t0)
        h, w = out["size"]
        return runs_to_mask(out["counts"], h, w), float(out["seconds"])

    def propagate(self, query: str, frame: int, count: int) -> tuple[list[tuple[int, np.ndarray]], float]:
        """Forward proposals ``[(frame index, mask)]`` and the server's seconds."""
        t0 = time.perf_counter()
        out = self._call("/api/propagate", {"query": self.queries[query], "frame": frame, "direction": 1,
                                            "count": count})
        self.round_trips.append(time.perf_counter() - t0)
        return [(p["frame"], runs_to_mask(p["counts"], *p["size"])) for p in out["proposals"]], float(out["seconds"])

    def save_masks(self, query: str, masks: list[tuple[int, np.ndarray, str]]) -> None:
        """Store ``[(frame index, mask, made_by)]``; an empty mask is saved as "absent"."""
        changes = [{"type": "mask", "query": self.queries[query], "frame": f, "made_by": made_by,
                    "mask": {"absent": True} if not m.any() else {"counts": mask_to_runs(m)}} for f, m, made_by in masks]
        self._save(changes)

    def save_intervals(self, query: str, intervals: list[tuple[int, int]]) -> None:
        self._save([{"type": "intervals", "query": self.queries[query], "intervals": [list(iv) for iv in intervals]}])

    def _save(self, changes: list[dict]) -> None:
        self.revision = self._call("/api/save", {"revision": self.revision, "changes": changes})["revision"]


ToolLauncher = Callable[[Path, Path, str, str], ContextManager[ToolClient]]
"""``launch(scene_dir, annotation_file, split, backend)``: a context in which the tool runs on that
scene and file with that segmenter backend, yielding a connected :class:`ToolClient`."""


# ---------------------------------------------------------------------------------------------
# ground truth
# ---------------------------------------------------------------------------------------------
@dataclass
class TruthQuery:
    """One query the annotator reproduces."""

    text: str
    kind: str = "agnostic"
    """``agnostic`` (masks) or ``sensitive`` (time segments of its base's masks)."""
    base: Optional[str] = None
    """The base query's text (sensitive queries)."""
    level: Optional[str] = None
    """Part level, as in the annotation file."""
    intervals: list[tuple[int, int]] = field(default_factory=list)
    """True inclusive time intervals (sensitive queries)."""


@dataclass
class TruthScene:
    """A scene with exact masks for some queries."""

    name: str
    scene_dir: Path
    kind: str
    """``synthetic`` or ``dnerf``."""
    queries: list[TruthQuery]
    scored_frames: list[str]
    """Names of the frames the benchmark scores."""
    mask: Callable[[str, str], Optional[np.ndarray]]
    """``mask(query text, frame name)``: the exact mask, or ``None`` where no exact truth exists."""


def synthetic_truth(scene_dir: Path) -> TruthScene:
    """Exact truth of a generated synthetic scene: its ``annotations.json`` and its ``truth/`` ids."""
    from annotations.format import load_annotations
    from benchmark.core.truth import load_truth

    gt: AnnotationSet = load_annotations(scene_dir / "annotations.json")
    truth = load_truth(scene_dir)
    by_name = {f.name: f for f in gt.frames}

    def mask(text: str, frame: str) -> Optional[np.ndarray]:
        q = gt.query(text)
        if frame in by_name:
            return gt.get_mask(q.id, by_name[frame].id)
        try:
            return truth.mask(text, frame, allow_eval=True)
        except KeyError:  # a query the truth catalogue does not name: truth only on scored frames
            return None

    queries = [TruthQuery(q.text, q.kind, None if q.base is None else gt.query(q.base).text, q.level,
                          list(q.intervals)) for q in gt.queries]
    return TruthScene(gt.scene, scene_dir, "synthetic", queries, [f.name for f in gt.frames], mask)


def paint_truth_regions(scene_dir: Path) -> int:
    """Repaint every image of a generated scene with one flat colour per truth region (a distinct
    (subpart, part, whole) id triple), so that every boundary of every level is a colour edge; returns the
    number of regions. What a colour-driven assistant does on these images is its ceiling: whatever it
    still needs there is not for want of image evidence."""
    from benchmark.core.truth import load_truth

    truth = load_truth(scene_dir)
    keys = {}
    for name, frame in truth.frames.items():
        ids = truth.id_maps(name, allow_eval=True).astype(np.int64) + 1  # (3, H, W): subpart, part, whole
        keys[scene_dir / frame.image_file] = (ids[0] << 34) | (ids[1] << 17) | ids[2]  # ids + 1 < 2**17
    if not keys:
        raise InputError(scene_dir, None, "a generated scene without frames")
    regions, inverse = np.unique(np.concatenate([k.ravel() for k in keys.values()]), return_inverse=True)
    n = len(regions)
    hsv = np.stack([(np.arange(n) * 0.618034 % 1.0) * 179, np.full(n, 220), 255 - 60 * (np.arange(n) % 3)], 1)
    colours = cv2.cvtColor(hsv[None].astype(np.uint8), cv2.COLOR_HSV2BGR)[0]  # golden-ratio hues, 3 values
    start = 0
    for path, key in keys.items():
        index = inverse[start:start + key.size].reshape(key.shape)
        start += key.size
        if not cv2.imwrite(str(path), colours[index]):
            raise InputError(path, None, "could not write the repainted image")
    return n


def dnerf_truth(scene_dir: Path, annotations: Path) -> TruthScene:
    """A D-NeRF scene: its whole-object queries (from ``annotations``) have the alpha mask as exact truth."""
    from annotations.format import load_annotations
    from benchmark.loaders import load_scene

    scene = load_scene(scene_dir)
    aset = load_annotations(annotations)
    frames = {f.name: f for f in scene.frames}
    wholes = [TruthQuery(q.text, "agnostic", None, q.level) for q in aset.agnostic_queries if q.level == "whole"]

    def mask(text: str, frame: str) -> Optional[np.ndarray]:
        alpha = frames[frame].alpha()
        return None if alpha is None else np.asarray(alpha, bool)

    scored = [f.name for f in aset.frames]
    return TruthScene(scene.name, scene_dir, "dnerf", wholes, scored, mask)


# ---------------------------------------------------------------------------------------------
# the simulated annotator
# ---------------------------------------------------------------------------------------------
@dataclass
class FrameLog:
    """What annotating one mask took."""

    frame: str
    ious: list[float]
    """IoU with the truth after each interaction (box first, then clicks)."""
    seconds: list[float]
    """The tool's compute seconds of each interaction."""
    made_by: str
    """``box``, ``clicks`` (box first), ``clicks-only``, ``absent``, ``propagated`` or ``corrected``."""

    def noc(self, threshold: float, cap: int) -> int:
        """Interactions to reach ``threshold`` IoU (``cap`` if never)."""
        return next((k + 1 for k, v in enumerate(self.ious) if v >= threshold), cap)

    @property
    def interactions(self) -> int:
        return len(self.ious)


def annotate_mask(client: ToolClient, index: int, name: str, truth: np.ndarray, config: BenchConfig,
                  start: Optional[np.ndarray] = None, query: str = "") -> tuple[np.ndarray, FrameLog]:
    """A noisy box (:func:`noisy_box`; or the given starting mask), then corrective clicks until the target
    IoU or the cap."""
    if not truth.any():
        return truth.copy(), FrameLog(name, [1.0], [0.0], "absent")
    clicks: list[tuple[float, float, int]] = []
    ious, seconds = [], []
    if start is None:
        box = noisy_box(truth, config.box_margin, config.box_jitter, box_rng(config.seed, query, name))
        mask, sec = client.segment(index, box, [], None)
        ious.append(iou(mask, truth))
        seconds.append(sec)
    else:
        mask, box = start, None
    while (not ious or ious[-1] < config.target_iou) and len(ious) < config.max_interactions:
        click = corrective_click(mask, truth)
        if click is None:
            break
        clicks.append(click)
        mask, sec = client.segment(index, box, clicks, mask)
        ious.append(iou(mask, truth))
        seconds.append(sec)
    made_by = "corrected" if start is not None else ("clicks" if clicks else "box")
    return mask, FrameLog(name, ious, seconds, made_by)


CLICKS_ONLY_TARGET = 0.90
"""The clicks-only run goes on to at least this IoU (NoC@90 needs it), whatever the target."""


def annotate_clicks_only(client: ToolClient, index: int, name: str, truth: np.ndarray,
                         config: BenchConfig) -> tuple[np.ndarray, FrameLog]:
    """The literature's clicker, no box: :func:`first_click`, then :func:`corrective_click` after each answer,
    until :data:`CLICKS_ONLY_TARGET` (or the target IoU, if higher) or :attr:`BenchConfig.max_interactions`
    clicks."""
    if not truth.any():
        return truth.copy(), FrameLog(name, [1.0], [0.0], "absent")
    target = max(config.target_iou, CLICKS_ONLY_TARGET)
    clicks: list[tuple[float, float, int]] = []
    ious: list[float] = []
    seconds: list[float] = []
    mask = np.zeros_like(truth, dtype=bool)
    while (not ious or ious[-1] < target) and len(ious) < config.max_interactions:
        click = corrective_click(mask, truth)  # with no mask yet: first_click
        if click is None:
            break
        clicks.append(click)
        mask, sec = client.segment(index, None, clicks, mask if mask.any() else None)
        ious.append(iou(mask, truth))
        seconds.append(sec)
    return mask, FrameLog(name, ious, seconds, "clicks-only")


def _session_frames(client: ToolClient) -> dict[str, int]:
    return {f["name"]: f["index"] for f in client.frames}


def annotate_every_frame(client: ToolClient, scene: TruthScene, config: BenchConfig, *,
                         clicks_only: bool = False) -> dict[str, list[FrameLog]]:
    """Each scored frame of each query with exact truth annotated from scratch (a box first, or with
    ``clicks_only`` the literature's clicker: :func:`annotate_clicks_only`); saved through the tool."""
    index_of = _session_frames(client)
    logs: dict[str, list[FrameLog]] = {}
    for q in _mask_queries(scene):
        client.add_query(q.text, level=q.level)
        for name in scene.scored_frames:
            truth = scene.mask(q.text, name)
            if truth is None or name not in index_of:
                continue
            if clicks_only:
                mask, log = annotate_clicks_only(client, index_of[name], name, truth, config)
            else:
                mask, log = annotate_mask(client, index_of[name], name, truth, config, query=q.text)
            saved_as = "clicks" if log.made_by == "clicks-only" else log.made_by  # the file's word for it
            client.save_masks(q.text, [(index_of[name], mask, saved_as)])
            logs.setdefault(q.text, []).append(log)
    return logs


def _mask_queries(scene: TruthScene) -> list[TruthQuery]:
    return [q for q in scene.queries if q.kind == "agnostic"]


def annotate_by_propagation(client: ToolClient, scene: TruthScene, config: BenchConfig) -> dict[str, list[FrameLog]]:
    """Per query: the first scored frame by hand, then propagation forward over the session's frames,
    accepting proposals at the target IoU and correcting the first poorer one, from which it resumes."""
    index_of = _session_frames(client)
    name_of = {i: n for n, i in index_of.items()}
    logs: dict[str, list[FrameLog]] = {}
    for q in _mask_queries(scene):
        client.add_query(q.text, level=q.level)
        frames = [n for n in scene.scored_frames if n in index_of and scene.mask(q.text, n) is not None]
        if frames:
            logs[q.text] = _propagate_query(client, q.text, frames, index_of, name_of, scene, config)
    return logs


def _propagate_query(client, text, frames, index_of, name_of, scene, config) -> list[FrameLog]:
    first = index_of[frames[0]]
    mask, log = annotate_mask(client, first, frames[0], scene.mask(text, frames[0]), config, query=text)
    client.save_masks(text, [(first, mask, log.made_by)])
    logs, current, last = [log], first, index_of[frames[-1]]
    while current < last:
        proposals, sec = client.propagate(text, current, last - current)
        if not proposals:
            break
        accepted, current = _accept_until_poor(client, text, proposals, name_of, scene, config, sec, logs)
        client.save_masks(text, accepted)
    return logs


def _accept_until_poor(client, text, proposals, name_of, scene, config, sec, logs) -> tuple[list, int]:
    """Accept proposals in order; the first below the target IoU is corrected and ends the batch."""
    accepted = []
    share = sec / len(proposals)  # the request's compute, spread over the frames it proposed
    for index, proposal in proposals:
        name = name_of[index]
        truth = scene.mask(text, name)
        score = iou(proposal, truth)
        if score >= config.target_iou and proposal.any() == truth.any():
            accepted.append((index, proposal, "propagated"))
            logs.append(FrameLog(name, [score], [share], "propagated"))
            continue
        # a proposal that has lost the object is redone from a box, as a person would
        start = proposal if score >= config.restart_below_iou else None
        try:
            mask, log = annotate_mask(client, index, name, truth, config, start=start, query=text)
        except ToolRefused as err:
            if err.status != 400 or start is None:
                raise
            mask, log = annotate_mask(client, index, name, truth, config, query=text)  # a sliver it cannot refine
        log.ious.insert(0, score)  # looking at the proposal and rejecting it is the first interaction
        log.seconds.insert(0, share)
        accepted.append((index, mask, log.made_by if truth.any() else "absent"))
        logs.append(log)
        return accepted, index
    return accepted, proposals[-1][0]


def propagation_curve(client: ToolClient, scene: TruthScene, config: BenchConfig) -> list[dict]:
    """Per query: the exact mask set on the first frame where the object shows, then propagated over
    the next :attr:`BenchConfig.propagation_frames` frames uncorrected; IoU by distance."""
    index_of = _session_frames(client)
    name_of = {i: n for n, i in index_of.items()}
    rows = []
    for q in _mask_queries(scene):
        start = next((n for n in index_of if _shows(scene.mask(q.text, n))), None)
        if start is None:
            continue
        client.add_query(q.text, level=q.level)
        client.save_masks(q.text, [(index_of[start], scene.mask(q.text, start), "drawn")])
        proposals, _ = client.propagate(q.text, index_of[start], config.propagation_frames)
        truths = [scene.mask(q.text, name_of[i]) for i, _ in proposals]
        ious = [iou(m, t) for (_, m), t in zip(proposals, truths) if t is not None]
        parts = [_components(t) for t in truths if t is not None]
        rows.append({"query": q.text, "level": q.level, "ious": [round(v, 4) for v in ious],
                     "splits": bool(parts) and max(parts) > min(parts)})
    return rows


def _shows(mask: Optional[np.ndarray]) -> bool:
    return mask is not None and bool(mask.any())


def _components(mask: np.ndarray) -> int:
    """Connected pieces larger than 4 pixels (a change in their number marks splitting or occlusion)."""
    n, _, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    return int((stats[1:, cv2.CC_STAT_AREA] > 4).sum())


DESCRIPTOR_SIDE = 12
"""Side of the square an object's outline is resized to before frames are compared (coarse: camera and object
motion move a coarse outline less than they move its pixels)."""


def region_descriptor(image: np.ndarray, mask: Optional[np.ndarray]) -> Optional[dict[str, np.ndarray]]:
    """What the annotator compares between frames, in the region of ``mask`` (the object whose state is asked
    about): ``colour``, the mean and spread of its pixels' CIELAB values (a state that recolours it: coffee
    darkening, an egg opening on a yellow chick), and ``shape``, its outline cropped to its bounding box and
    resized to :data:`DESCRIPTOR_SIDE` squared (a state that reshapes it: a cookie cracking, a lid opening).
    ``None`` where the object is not in view."""
    if mask is None or not np.any(mask):
        return None
    mask = np.asarray(mask, bool)
    ys, xs = np.nonzero(mask)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    lab = cv2.cvtColor(np.ascontiguousarray(image[..., :3], dtype=np.uint8), cv2.COLOR_RGB2LAB).astype(np.float32)[mask]
    outline = cv2.resize(mask[y0:y1, x0:x1].astype(np.float32), (DESCRIPTOR_SIDE, DESCRIPTOR_SIDE),
                         interpolation=cv2.INTER_AREA)
    return {"colour": np.concatenate([lab.mean(0), lab.std(0)]), "shape": outline.ravel()}


def change_times(descriptors: list[Optional[dict[str, np.ndarray]]], window: int, threshold: float) -> list[int]:
    """Positions ``k`` of ``descriptors`` (one per time step) where the object changes between ``k - 1`` and
    ``k``. Per kind of descriptor, the step at ``k`` is the distance between the mean of up to ``window`` steps
    before and of up to ``window`` from ``k`` on, in units of its median over the video (the camera's and the
    object's motion make the median: a change of state stands out of it); a change is where the larger of the
    kinds' steps exceeds ``threshold`` and is the largest within ``window`` steps. Steps without a descriptor
    (the object not in view) are skipped."""
    present = [k for k, d in enumerate(descriptors) if d is not None]
    if len(present) < 3:
        return []
    n = len(present)
    score = np.zeros(n)
    for kind in descriptors[present[0]]:
        stack = np.stack([descriptors[k][kind] for k in present])
        steps = np.zeros(n)
        for j in range(1, n):
            steps[j] = float(np.linalg.norm(stack[max(0, j - window):j].mean(0) - stack[j:j + window].mean(0)))
        base = float(np.median(steps[1:]))
        if base > 0:
            score = np.maximum(score, steps / base)
    out: list[int] = []
    for j in range(1, n):
        if score[j] > threshold and score[j] >= score[max(1, j - window):j + window + 1].max():
            if not out or j - out[-1] > window:
                out.append(j)
    return [present[j] for j in out]


def intervals_from_changes(times: list[int], changes: list[int], holds: list[bool]) -> list[tuple[int, int]]:
    """Inclusive ``times`` intervals where the state holds: the video cut at ``changes`` (positions into
    ``times``), each piece labelled by the majority of ``holds`` over it (what the query says the state is
    there, as a person reading it would know), neighbouring pieces that hold joined."""
    cuts = [0, *sorted(c for c in changes if 0 < c < len(times)), len(times)]
    out: list[tuple[int, int]] = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        if b > a and 2 * sum(holds[a:b]) > b - a:
            out.append((times[a], times[b - 1]))
    return normalise_intervals(out)


def mark_intervals(client: ToolClient, scene: TruthScene, config: Optional[BenchConfig] = None) -> list[dict]:
    """Step through the video in time as the page shows it; where the base object's pixels change
    (:func:`change_times` over :func:`region_descriptor`), cut; ``[`` and ``]`` around each piece where the
    state holds (:func:`intervals_from_changes`), each ``]`` saved as the page saves it. Returns per query the
    marked and true intervals, the keys pressed and the worst boundary's distance in frames."""
    config = config or BenchConfig()
    first_at: dict[int, dict] = {}
    for f in client.frames:
        first_at.setdefault(f["time_index"], f)
    times = sorted(first_at)
    images: dict[int, np.ndarray] = {}
    rows = []
    for q in (q for q in scene.queries if q.kind == "sensitive"):
        if q.base not in client.queries:
            client.add_query(q.base)
        client.add_query(q.text, "sensitive", q.base)
        descriptors = []
        for t in times:
            frame = first_at[t]
            if frame["index"] not in images:
                images[frame["index"]] = client.frame_image(frame["index"])
            descriptors.append(region_descriptor(images[frame["index"]], scene.mask(q.base, frame["name"])))
        changes = change_times(descriptors, config.change_window, config.change_threshold)
        holds = [any(a <= t <= b for a, b in q.intervals) for t in times]
        marked: list[tuple[int, int]] = []
        for interval in intervals_from_changes(times, changes, holds):
            marked = normalise_intervals(marked + [interval])  # "[" at its start, "]" at its end: saved
            client.save_intervals(q.text, marked)
        rows.append({"query": q.text, "true": [list(iv) for iv in q.intervals], "marked": [list(iv) for iv in marked],
                     "keys": 2 * len(marked), "changes_found": [times[k] for k in changes],
                     "boundary_error": boundary_error(marked, q.intervals)})
    return rows


def boundary_error(marked: list[tuple[int, int]], true: list[tuple[int, int]]) -> Optional[int]:
    """Largest distance in frames between matching boundaries; ``None`` when the counts differ."""
    if len(marked) != len(true):
        return None
    return max((max(abs(a - c), abs(b - d)) for (a, b), (c, d) in zip(marked, true)), default=0)


# ---------------------------------------------------------------------------------------------
# a scene, end to end
# ---------------------------------------------------------------------------------------------
def bench_scene(scene: TruthScene, launch: ToolLauncher, work: Path, backends: list[str],
                config: BenchConfig) -> dict:
    """Every measurement of one scene; annotation files are written under ``work``."""
    out: dict[str, Any] = {"scene": scene.name, "kind": scene.kind, "backends": {},
                           "levels": {q.text: q.level for q in scene.queries}, "size": _image_size(scene),
                           "one_pixel_iou": _one_pixel_ious(scene)}
    work.mkdir(parents=True, exist_ok=True)
    for old in work.glob(f"{scene.name}.*.json"):  # each measurement starts from an empty file
        old.unlink()
    for backend in backends:
        with launch(scene.scene_dir, work / f"{scene.name}.every-frame.{backend}.json", "scored", backend) as c:
            every = annotate_every_frame(c, scene, config)
            trips = list(c.round_trips)
        with launch(scene.scene_dir, work / f"{scene.name}.clicks-only.{backend}.json", "scored", backend) as c:
            clicks_only = annotate_every_frame(c, scene, config, clicks_only=True)
        with launch(scene.scene_dir, work / f"{scene.name}.propagation.{backend}.json", "scored", backend) as c:
            prop = annotate_by_propagation(c, scene, config)
        out["backends"][backend] = {"every_frame": _logs_doc(every), "clicks_only": _logs_doc(clicks_only),
                                    "propagation": _logs_doc(prop), "round_trip_seconds": _mean(trips)}
    with launch(scene.scene_dir, work / f"{scene.name}.video.json", "all", backends[0]) as c:
        out["propagation_curve"] = propagation_curve(c, scene, config)
        out["intervals"] = mark_intervals(c, scene, config)
    return out


def _one_pixel_ious(scene: TruthScene) -> dict[str, float]:
    """Query -> :func:`one_pixel_iou` of its truth masks, mean over the scored frames that show it."""
    out = {}
    for q in _mask_queries(scene):
        values = [one_pixel_iou(m) for f in scene.scored_frames if (m := scene.mask(q.text, f)) is not None]
        values = [v for v in values if v is not None]
        if values:
            out[q.text] = float(np.mean(values))
    return out


def adopt_simulated_masks(shipped: Path, simulated: Path, scene: TruthScene, min_iou: float) -> dict[str, int]:
    """Put the simulated annotator's masks (``simulated``: a file the tool saved) into the annotation file
    ``shipped`` for the queries of ``scene`` that have exact truth, frame by frame where they agree with
    that truth at ``min_iou`` or better; the other masks stay as they were. Writes ``shipped`` atomically
    and returns how many masks were taken and kept."""
    from annotations.format import load_annotations, save_annotations

    target = load_annotations(shipped)
    made = load_annotations(simulated)
    made_frames = {f.name: f for f in made.frames}
    counts = {"adopted": 0, "kept": 0}
    for truth_query in scene.queries:
        if truth_query.kind != "agnostic":
            continue
        query, source = target.query(truth_query.text), made.query(truth_query.text)
        for frame in target.frames:
            other = made_frames.get(frame.name)
            mask = None if other is None else made.get_mask(source.id, other.id)
            truth = scene.mask(truth_query.text, frame.name)
            if mask is None or truth is None or iou(mask, truth) < min_iou:
                counts["kept"] += 1
                continue
            target.set_mask(query.id, frame.id, mask, made_by=made.made_by.get((source.id, other.id)))
            counts["adopted"] += 1
    if counts["adopted"]:
        who = target.info.setdefault("annotators", [target.info.get("annotator", "scripted")])
        if "simulated" not in who:
            who.append("simulated")
        target.info["simulated_protocol"] = dict(made.info.get("protocol") or {}, min_iou_against_truth=min_iou)
        target.info["adopted"] = (f"masks of the queries with exact truth are the simulated annotator's where they "
                                  f"reach IoU {min_iou:g} against that truth, else as before; each mask's made_by "
                                  "says which")
        save_annotations(target, shipped, overwrite=True)
    return counts


def _image_size(scene: TruthScene) -> Optional[list[int]]:
    """``[width, height]`` of the scene's annotated frames (from the first truth mask found)."""
    for q in scene.queries:
        for frame in scene.scored_frames:
            mask = scene.mask(q.text, frame) if q.kind == "agnostic" else None
            if mask is not None:
                return [int(mask.shape[1]), int(mask.shape[0])]
    return None


def _logs_doc(logs: dict[str, list[FrameLog]]) -> dict:
    return {q: [{"frame": x.frame, "ious": [round(v, 4) for v in x.ious], "seconds": [round(s, 4) for s in x.seconds],
                 "made_by": x.made_by} for x in items] for q, items in logs.items()}


def _mean(values) -> Optional[float]:
    values = list(values)
    return None if not values else float(np.mean(values))


# ---------------------------------------------------------------------------------------------
# summaries
# ---------------------------------------------------------------------------------------------
def noc_summary(frames: list[dict], config: BenchConfig) -> dict:
    """NoC@85, NoC@90, failures and seconds per interaction over frames where the object shows."""
    shown = [f for f in frames if f["made_by"] != "absent"]
    cap = config.max_interactions
    log = [FrameLog(f["frame"], f["ious"], f["seconds"], f["made_by"]) for f in shown]
    seconds = [s for f in shown for s in f["seconds"]]
    return {"frames": len(shown), "noc85": _mean(x.noc(0.85, cap) for x in log),
            "noc90": _mean(x.noc(0.90, cap) for x in log),
            "failed90": sum(x.noc(0.90, cap) >= cap and x.ious[-1] < 0.90 for x in log),
            "final_iou": _mean(x.ious[-1] for x in log), "min_final_iou": min((x.ious[-1] for x in log), default=None),
            "seconds_per_interaction": _mean(seconds)}


def human_seconds(frames: list[dict]) -> float:
    """Projected human time of a list of frame logs (box, clicks and keys at the stated times)."""
    total = 0.0
    for f in frames:
        n = len(f["ious"])
        if f["made_by"] in ("absent", "propagated"):
            total += KEY_SECONDS
        elif f["made_by"] == "clicks-only":
            total += n * CLICK_SECONDS
        elif f["made_by"] == "corrected":
            total += KEY_SECONDS + (n - 1) * CLICK_SECONDS
        else:
            total += BOX_SECONDS + (n - 1) * CLICK_SECONDS
    return total


def _all(logs_doc: dict) -> list[dict]:
    return [f for items in logs_doc.values() for f in items]


def summarise(results: list[dict], config: BenchConfig) -> dict:
    """Per scene and backend: NoC, human time per frame for both workflows, intervals, curve."""
    rows = []
    for r in results:
        for backend, b in r["backends"].items():
            every, prop = _all(b["every_frame"]), _all(b["propagation"])
            clicks = noc_summary(_all(b.get("clicks_only", {})), config)
            size = r.get("size")
            rows.append({"scene": r["scene"], "kind": r["kind"], "backend": backend,
                         "size": None if size is None else f"{size[0]}x{size[1]}", **noc_summary(every, config),
                         "clicks_frames": clicks["frames"], "clicks_noc85": clicks["noc85"],
                         "clicks_noc90": clicks["noc90"], "clicks_failed90": clicks["failed90"],
                         "human_s_per_frame_every": human_seconds(every) / max(1, len(every)),
                         "human_s_per_frame_propagation": human_seconds(prop) / max(1, len(prop)),
                         "interactions_per_frame_every": _mean(len(f["ious"]) for f in every),
                         "interactions_per_frame_propagation": _mean(len(f["ious"]) for f in prop),
                         "propagation_final_iou": _mean(f["ious"][-1] for f in prop if f["made_by"] != "absent"),
                         "round_trip_seconds": b["round_trip_seconds"]})
    return {"rows": rows}


def render_markdown(results: list[dict], summary: dict, config: BenchConfig) -> str:
    """The report: method, then one table per measurement."""
    parts = [_method_text(config), "## Interactive masks (every scored frame from scratch)\n",
             _noc_table(summary["rows"]), "\n### By part level (NoC@90)\n", _level_table(results, config),
             "\n### How exact the target asks a mask to be\n", _tolerance_text(results, config),
             "\n## Propagation against annotating every frame\n",
             _workflow_table(summary["rows"]), "\n## IoU after propagation by frames propagated (uncorrected)\n",
             _curve_table(results, config), "\n## Time segments\n", _interval_table(results)]
    return "\n".join(parts)


def _method_text(config: BenchConfig) -> str:
    return (
        "# The annotation tool, measured by a simulated annotator\n\n"
        "Written by `bench4d annotate-bench` (`benchmark/studies/annotation_bench.py`). The annotator drives the "
        "tool's HTTP API as the page does. Two ways to make a mask, each on every scored frame from scratch:\n\n"
        "* **clicks only**, the interactive-segmentation literature's protocol (Xu et al. 2016; RITM, Sofiiuk et al. "
        "2022): the first click at the interior point of the truth mask farthest from its boundary, each next one "
        "at the centre of the largest error region (distance transform, the image border an edge; positive in a "
        f"missed region, negative in a false one), at most {config.max_interactions} clicks: its NoC@85 / NoC@90 "
        "compare with published ones;\n"
        f"* **box first**, the tool's own workflow: a box around the exact truth mask ({config.box_margin} px margin, "
        f"each edge then moved by a normal draw of standard deviation {config.box_jitter:g} times the object's width "
        "or height: an assumed jitter of a person's box, seeded per query and frame), counted as one interaction, "
        f"then the same corrective clicks until IoU {config.target_iou:g} or {config.max_interactions} interactions.\n\n"
        "Frames where the object is absent are marked absent and left out of NoC. Time segments are marked where a "
        f"step detector finds the base object's pixels change ({config.change_window} time steps a side, "
        f"{config.change_threshold:g} times the video's median step), not at the truth's boundaries.\n\n"
        + ("**Images: truth colours.** Every frame was repainted with one flat colour per truth region (a distinct "
           "(subpart, part, whole) id triple), so every boundary of every level is a colour edge: what the assistant "
           "still needs here is not for want of image evidence.\n\n" if config.images == "truth-colours" else "")
        +
        f"Projected human time: box {BOX_SECONDS:g} s (Papadopoulos et al., ICCV 2017, extreme clicking), click "
        f"{CLICK_SECONDS:g} s (Bearman et al., ECCV 2016, point supervision), key (accept a proposal, absent, `[`/`]`) "
        f"{KEY_SECONDS:g} s (an assumption, no published source). Tool compute is the server's own seconds per "
        "segmentation request (the `seconds` of `/api/segment`), and per propagated frame its share of the "
        "`/api/propagate` request.\n")


def _noc_table(rows: list[dict]) -> str:
    header = ["scene", "size", "backend", "frames", "clicks only: NoC@85", "NoC@90", "failed@90",
              "box first: NoC@85", "NoC@90", "failed@90", "mean final IoU", "min final IoU", "compute s / interaction"]
    body = [[r["scene"], r.get("size") or "", r["backend"], str(r["frames"]), number_cell(r.get("clicks_noc85")),
             number_cell(r.get("clicks_noc90")), "" if r.get("clicks_failed90") is None else str(r["clicks_failed90"]),
             number_cell(r["noc85"]), number_cell(r["noc90"]), str(r["failed90"]), number_cell(r["final_iou"], 3),
             number_cell(r["min_final_iou"], 3), number_cell(r["seconds_per_interaction"], 3)] for r in rows]
    text = markdown_table(header, body)
    synthetic = [r for r in rows if r["kind"] == "synthetic"]
    for backend in sorted({r["backend"] for r in synthetic}):
        mine = [r for r in synthetic if r["backend"] == backend]
        parts = []
        for label, frames_key, keys in (("clicks only", "clicks_frames", ("clicks_noc85", "clicks_noc90")),
                                        ("box first", "frames", ("noc85", "noc90"))):
            counted = [r for r in mine if r.get(keys[1]) is not None]
            frames = sum(r[frames_key] for r in counted)
            if frames:
                means = [sum(r[k] * r[frames_key] for r in counted) / frames for k in keys]
                parts.append(f"{label} NoC@85 {means[0]:.2f}, NoC@90 {means[1]:.2f} over {frames} frames")
        if parts:
            text += f"\nOver the synthetic presets' annotated frames ({backend}): {'; '.join(parts)}.\n"
    return text


def _level_table(results: list[dict], config: BenchConfig) -> str:
    """NoC@90 per scene, backend and part level of the query (whole objects, parts, subparts)."""
    levels = ["whole", "part", "subpart"]
    body = []
    for r in results:
        for backend, b in r["backends"].items():
            cells = []
            for level in levels:
                frames = [f for q, items in b["every_frame"].items() if r["levels"].get(q) == level for f in items]
                s = noc_summary(frames, config)
                cells.append(f"{number_cell(s['noc90'])} ({s['frames']})" if s["frames"] else "")
            body.append([r["scene"], backend] + cells)
    return markdown_table(["scene", "backend"] + [f"{lv} (frames)" for lv in levels], body)


def _tolerance_text(results: list[dict], config: BenchConfig) -> str:
    """Per scene: how many queries' masks keep the target IoU after a one-pixel boundary error."""
    body = []
    for r in results:
        values = list((r.get("one_pixel_iou") or {}).values())
        if values:
            body.append([r["scene"], str(len(values)), str(sum(v >= config.target_iou for v in values)),
                         number_cell(float(np.median(values)), 3), number_cell(min(values), 3)])
    if not body:
        return "No query with a truth mask.\n"
    return ("IoU a one-pixel boundary error leaves (the truth mask against itself eroded and dilated by one pixel, "
            f"the lower; mean over the scored frames). A query below {config.target_iou:g} needs every boundary "
            "pixel right to reach the target.\n\n"
            + markdown_table(["scene", "queries", f"one-pixel IoU >= {config.target_iou:g}", "median one-pixel IoU",
                              "lowest"], body))


def _workflow_table(rows: list[dict]) -> str:
    header = ["scene", "backend", "interactions / frame: every frame", "propagation", "human s / frame: every frame",
              "propagation", "final IoU with propagation"]
    body = [[r["scene"], r["backend"], number_cell(r["interactions_per_frame_every"]),
             number_cell(r["interactions_per_frame_propagation"]), number_cell(r["human_s_per_frame_every"], 1),
             number_cell(r["human_s_per_frame_propagation"], 1), number_cell(r["propagation_final_iou"], 3)]
            for r in rows]
    return markdown_table(header, body)


def _curve_table(results: list[dict], config: BenchConfig) -> str:
    marks = [1, 5, 10, 20, config.propagation_frames]
    header = ["scene", "query", "level", "frames propagated"] + [f"IoU @{m}" for m in marks] + ["min IoU", "splits"]
    body = []
    for r in results:
        for c in r.get("propagation_curve", []):
            v = c["ious"]
            cells = [number_cell(v[m - 1], 3) if len(v) >= m else "" for m in marks]
            body.append([r["scene"], c["query"], str(c["level"]), str(len(v))] + cells +
                        [number_cell(min(v), 3) if v else "", "yes" if c["splits"] else ""])
    return markdown_table(header, body)


def _interval_table(results: list[dict]) -> str:
    header = ["scene", "query", "true", "marked", "keys", "boundary error (frames)"]
    body = [[r["scene"], i["query"], str(i["true"]), str(i["marked"]), str(i["keys"]),
             "count differs" if i["boundary_error"] is None else str(i["boundary_error"])]
            for r in results for i in r.get("intervals", [])]
    return markdown_table(header, body) if body else "No time-sensitive query with exact truth.\n"


def write(results: list[dict], config: BenchConfig, out: Path, name: str = "annotation_bench") -> list[Path]:
    """``<out>/<name>.json`` (summary, per-frame outcomes, curves, intervals) and ``.md`` (the tables).
    The per-interaction logs behind them are what :func:`bench_scene` returns."""
    summary = summarise(results, config)
    doc = {"config": vars(config), "human_seconds": {"box": BOX_SECONDS, "click": CLICK_SECONDS, "key": KEY_SECONDS},
           "summary": summary, "scenes": [_compact(r, config) for r in results]}
    return write_report(out, name, doc, render_markdown(results, summary, config))


def _compact(result: dict, config: BenchConfig) -> dict:
    """One scene's result with each query's frame logs cut to their summary (:func:`noc_summary`)."""
    def per_query(logs: dict) -> dict:
        return {q: {**noc_summary(items, config), "human_s": human_seconds(items)} for q, items in logs.items()}

    backends = {name: {"round_trip_seconds": b["round_trip_seconds"], "every_frame": per_query(b["every_frame"]),
                       "clicks_only": per_query(b.get("clicks_only", {})), "propagation": per_query(b["propagation"])}
                for name, b in result["backends"].items()}
    return {**result, "backends": backends}
