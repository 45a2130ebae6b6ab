"""The annotation tool measured by a simulated annotator against exact ground truth.

The annotator talks to the tool's own HTTP API, as the page does (token header, JSON bodies, this
server's origin), never to its internals:

* **interactive masks** (the protocol of the interactive segmentation literature, e.g. RITM, Sofiiuk et
  al. 2022): a box around the truth mask (``/api/segment`` with a box), then corrective clicks, each at
  the centre of the largest error region (the maximum of the distance transform of that region's
  mask): positive inside a missed region, negative inside a false one; it stops at the target IoU or
  after :attr:`BenchConfig.max_interactions` interactions. A frame where the object is absent is
  marked absent (the ``A`` key: one interaction).
* **propagation** (``/api/propagate``): from an annotated frame to the next frames of the session; a
  proposal at or above the target IoU is accepted (``Enter``), a poorer one is corrected with clicks
  starting from the proposal, and propagation resumes from the corrected frame.
* **time segments**: stepping through the video, ``[`` at the first frame where the state holds and
  ``]`` at the last, each saved as the page saves them (an ``intervals`` change).

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
    ys, xs = np.nonzero(truth)
    h, w = truth.shape
    return [float(max(0, xs.min() - margin)), float(max(0, ys.min() - margin)),
            float(min(w, xs.max() + 1 + margin)), float(min(h, ys.max() + 1 + margin))]


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
    """``box``, ``clicks``, ``absent``, ``propagated`` or ``corrected``."""

    def noc(self, threshold: float, cap: int) -> int:
        """Interactions to reach ``threshold`` IoU (``cap`` if never)."""
        return next((k + 1 for k, v in enumerate(self.ious) if v >= threshold), cap)

    @property
    def interactions(self) -> int:
        return len(self.ious)


def annotate_mask(client: ToolClient, index: int, name: str, truth: np.ndarray, config: BenchConfig,
                  start: Optional[np.ndarray] = None) -> tuple[np.ndarray, FrameLog]:
    """Box (or the given starting mask), then corrective clicks until the target IoU or the cap."""
    if not truth.any():
        return truth.copy(), FrameLog(name, [1.0], [0.0], "absent")
    clicks: list[tuple[float, float, int]] = []
    ious, seconds = [], []
    if start is None:
        box = truth_box(truth, config.box_margin)
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


def _session_frames(client: ToolClient) -> dict[str, int]:
    return {f["name"]: f["index"] for f in client.frames}


def annotate_every_frame(client: ToolClient, scene: TruthScene, config: BenchConfig) -> dict[str, list[FrameLog]]:
    """Each scored frame of each query with exact truth annotated from scratch; saved through the tool."""
    index_of = _session_frames(client)
    logs: dict[str, list[FrameLog]] = {}
    for q in _mask_queries(scene):
        client.add_query(q.text, level=q.level)
        for name in scene.scored_frames:
            truth = scene.mask(q.text, name)
            if truth is None or name not in index_of:
                continue
            mask, log = annotate_mask(client, index_of[name], name, truth, config)
            client.save_masks(q.text, [(index_of[name], mask, log.made_by)])
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
    mask, log = annotate_mask(client, first, frames[0], scene.mask(text, frames[0]), config)
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
            mask, log = annotate_mask(client, index, name, truth, config, start=start)
        except ToolRefused as err:
            if err.status != 400 or start is None:
                raise
            mask, log = annotate_mask(client, index, name, truth, config)  # e.g. a sliver the tool cannot refine
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


def mark_intervals(client: ToolClient, scene: TruthScene) -> list[dict]:
    """Step through the video in time; ``[`` where the state starts to hold, ``]`` where it last holds,
    each key saved as the page saves it. Returns per query the marked and true intervals."""
    times = sorted({f["time_index"] for f in client.frames})
    rows = []
    for q in (q for q in scene.queries if q.kind == "sensitive"):
        if q.base not in client.queries:
            client.add_query(q.base)
        client.add_query(q.text, "sensitive", q.base)
        marked: list[tuple[int, int]] = []
        start, keys = None, 0
        for k, t in enumerate(times):
            holds = any(a <= t <= b for a, b in q.intervals)
            if holds and start is None:
                start, keys = t, keys + 1  # "[": a pending start, nothing saved yet
            if start is not None and (not holds or k == len(times) - 1):
                end = t if holds else times[k - 1]
                marked = normalise_intervals(marked + [(start, end)])  # "]": closes and saves
                client.save_intervals(q.text, marked)
                start, keys = None, keys + 1
        rows.append({"query": q.text, "true": [list(iv) for iv in q.intervals], "marked": [list(iv) for iv in marked],
                     "keys": keys, "boundary_error": boundary_error(marked, q.intervals)})
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
        with launch(scene.scene_dir, work / f"{scene.name}.propagation.{backend}.json", "scored", backend) as c:
            prop = annotate_by_propagation(c, scene, config)
        out["backends"][backend] = {"every_frame": _logs_doc(every), "propagation": _logs_doc(prop),
                                    "round_trip_seconds": _mean(trips)}
    with launch(scene.scene_dir, work / f"{scene.name}.video.json", "all", backends[0]) as c:
        out["propagation_curve"] = propagation_curve(c, scene, config)
        out["intervals"] = mark_intervals(c, scene)
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
            size = r.get("size")
            rows.append({"scene": r["scene"], "kind": r["kind"], "backend": backend,
                         "size": None if size is None else f"{size[0]}x{size[1]}", **noc_summary(every, config),
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
        "tool's HTTP API as the page does. Per mask: a box around the exact truth mask "
        f"({config.box_margin} px margin), then corrective clicks at the centre of the largest error region "
        "(distance transform; positive in a missed region, negative in a false one), until IoU "
        f"{config.target_iou:g} or {config.max_interactions} interactions (NoC cap). Frames where the object is absent "
        "are marked absent and left out of NoC.\n\n"
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
    header = ["scene", "size", "backend", "frames", "NoC@85", "NoC@90", "failed@90", "mean final IoU", "min final IoU",
              "compute s / interaction"]
    body = [[r["scene"], r.get("size") or "", r["backend"], str(r["frames"]), number_cell(r["noc85"]), number_cell(r["noc90"]),
             str(r["failed90"]), number_cell(r["final_iou"], 3), number_cell(r["min_final_iou"], 3),
             number_cell(r["seconds_per_interaction"], 3)] for r in rows]
    synthetic = [r for r in rows if r["kind"] == "synthetic" and r["noc90"] is not None]
    text = markdown_table(header, body)
    for backend in sorted({r["backend"] for r in synthetic}):
        mine = [r for r in synthetic if r["backend"] == backend]
        frames = sum(r["frames"] for r in mine)
        noc90 = sum(r["noc90"] * r["frames"] for r in mine) / max(1, frames)
        text += f"\nNoC@90 over the synthetic presets' {frames} annotated frames ({backend}): {noc90:.2f}\n"
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
                       "propagation": per_query(b["propagation"])}
                for name, b in result["backends"].items()}
    return {**result, "backends": backends}
