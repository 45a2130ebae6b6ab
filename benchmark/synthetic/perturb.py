"""Perturbation families: knobs that make a preset harder in one respect and leave the rest as it was.

A perturbation is a (family, strength) pair given to :func:`benchmark.synthetic.generate.generate`. It
changes the scene definition and the planned frames after the preset has drawn them from its random
stream, with a random stream of its own, so strength 0 gives the clean scene file for file (the same
digest) and a larger strength changes only what its family names. A perturbed scene records the pair
in its truth and metadata (``perturbation``), so its digest names the knob and the strength.

Families on the scene's side (strength units in :data:`FAMILIES`):

* ``motion-speed``: free-moving objects (no state timeline above or below them) play their motion
  faster, back and forth over the same path;
* ``motion-amplitude``: their displacement from where they start is scaled up;
* ``frames-dropped``: a share of the training frames is left out, spread uniformly;
* ``state-gap``: the training frames of a window centred on the first state change are left out;
* ``camera-slow``: the monocular camera covers a shrinking part of its path (1: a still camera);
* ``camera-teleport``: a share of the frames takes the camera of another, random frame;
* ``camera-rig``: every training time step is also seen by extra cameras, placed where the monocular
  camera is at evenly spaced other times (a rig moving along the path; the scored views stay monocular);
* ``occluder``: a ball of growing radius crosses between the camera and the queried object
  (the first object with states) in the middle third of the video, coming from beyond one edge of the
  image and leaving beyond the other;
* ``appearance``: every object's colour drifts towards a warm dark tint and back, twice (lighting
  and colour change with no change of state);
* ``semantic-subtle``: states change when they did, but their visible change shrinks (1: none);
* ``state-ramp``: states change when they did, but each visible change develops gradually over a share of
  the video (a liquid darkening frame by frame); the labels keep the truth's rule (a state holds from the
  first frame past the midpoint of its transition), exact because a ramp is never wider than the gap
  between two changes of the same timeline (:func:`widened_ramp`);
* ``topology``: the parts of every object of several parts move apart and back together, twice.

A family with nothing to act on in a preset (no freely moving part for the motion families, no object of
several parts for ``topology``, no state for the state families) is refused: its scene would be the clean one
under another name (:meth:`Perturbation.changes_nothing`).

The supervision-side families (noise of the oracle track's masks, captions and query wording) act on
what a method is given, not on the scene: :mod:`benchmark.studies.stress`.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, replace
from typing import Callable, Optional, Sequence

import numpy as np

from benchmark.core.errors import InputError
from . import textures as tx
from .csg import Sphere
from .layouts import FrameRecord
from .model import FrameContext, Node, Piece, SceneDef, Timeline, resolve, whole
from .transforms import translation


@dataclass(frozen=True)
class Family:
    """One knob of the stress suite."""

    name: str
    """Name on the command line and in the reports."""
    unit: str
    """What a strength means, in words (the x axis of its chart)."""
    strengths: tuple[float, ...]
    """The suite's strengths, the clean end (0) first, up to clearly broken."""
    side: str
    """``"scene"`` (this module) or ``"supervision"`` (:mod:`benchmark.studies.stress`)."""


FAMILIES: dict[str, Family] = {f.name: f for f in (
    Family("motion-speed", "extra motion speed (x clean speed)", (0.0, 1.0, 2.0, 4.0, 8.0), "scene"),
    Family("motion-amplitude", "extra motion amplitude (x clean displacement)", (0.0, 0.5, 1.0, 2.0, 4.0), "scene"),
    Family("frames-dropped", "share of training frames dropped", (0.0, 0.25, 0.5, 0.75, 0.9), "scene"),
    Family("state-gap", "training frames dropped around the state change (share of the video)",
           (0.0, 0.1, 0.2, 0.35, 0.5), "scene"),
    Family("camera-slow", "share of the camera path removed (1: still camera)", (0.0, 0.5, 0.75, 0.9, 1.0), "scene"),
    Family("camera-teleport", "share of frames with another frame's camera", (0.0, 0.25, 0.5, 0.75, 1.0), "scene"),
    Family("camera-rig", "extra rig cameras per training time step (0: monocular)", (0.0, 1.0, 2.0, 4.0, 8.0),
           "scene"),
    Family("occluder", "occluder radius (share of the scene radius)", (0.0, 0.1, 0.2, 0.3, 0.45), "scene"),
    Family("appearance", "colour shift without a state change (blend weight)", (0.0, 0.15, 0.3, 0.45, 0.6),
           "scene"),
    Family("semantic-subtle", "share of the states' visible change removed", (0.0, 0.5, 0.75, 0.9, 1.0), "scene"),
    Family("state-ramp", "length of each visible state change (share of the video)", (0.0, 0.1, 0.2, 0.35, 0.5),
           "scene"),
    Family("topology", "parts split apart and merge back (distance, share of the scene radius)",
           (0.0, 0.1, 0.2, 0.35, 0.5), "scene"),
    Family("mask-erode", "mask boundary eroded (pixels at 48 px)", (0.0, 1.0, 2.0, 3.0, 4.0), "supervision"),
    Family("mask-dilate", "mask boundary dilated (pixels at 48 px)", (0.0, 1.0, 2.0, 3.0, 4.0), "supervision"),
    Family("mask-id-swap", "share of training frames with their masks' features shuffled",
           (0.0, 0.1, 0.25, 0.5, 1.0), "supervision"),
    Family("mask-drop", "share of masks dropped", (0.0, 0.1, 0.25, 0.5, 0.9), "supervision"),
    Family("caption-swap", "share of captions of another state", (0.0, 0.1, 0.25, 0.5, 1.0), "supervision"),
    Family("caption-lag", "extra lag of the captions behind each change (share of the video)",
           (0.0, 0.05, 0.1, 0.2, 0.3), "supervision"),
    Family("query-paraphrase", "share of queries asked in other words", (0.0, 0.25, 0.5, 0.75, 1.0), "supervision"),
)}

SCENE_FAMILIES = tuple(name for name, f in FAMILIES.items() if f.side == "scene")
OCCLUDER_NAME = "occluder"
"""Name of the occluding ball in the scene's truth and supervision (no query asks about it)."""
OCCLUDER_DEPTH = 0.4
"""Where the occluder stands on the line from the queried object to the camera (0: at the object)."""
OCCLUDER_MARGIN = 1.5
"""How far beyond the image edge the occluder waits before and after its crossing, in its radii."""
CYCLES = 2
"""Back-and-forth cycles of the ``appearance`` and ``topology`` changes over the video."""


def family(name: str) -> Family:
    """The family called ``name`` (an :class:`InputError` naming the valid ones otherwise)."""
    if name not in FAMILIES:
        raise InputError(None, "family", f"unknown perturbation family {name!r} (valid: {', '.join(FAMILIES)})")
    return FAMILIES[name]


@dataclass(frozen=True)
class Perturbation:
    """A family at a strength, applied to a preset's scene definition and planned frames."""

    family: str
    strength: float

    def __post_init__(self) -> None:
        fam = family(self.family)
        if fam.side != "scene":
            raise InputError(None, "family", f"{self.family!r} acts on the supervision, not on the scene "
                             "(benchmark.studies.stress applies it)")
        if not np.isfinite(self.strength) or self.strength < 0:
            raise InputError(None, "strength", f"expected a finite strength >= 0, got {self.strength!r}")

    @property
    def is_clean(self) -> bool:
        return self.strength == 0

    def describe(self) -> dict:
        """What the scene's truth and metadata record (so its digest names knob and strength)."""
        return {"family": self.family, "strength": float(self.strength)}

    def rng(self, seed: int) -> np.random.Generator:
        """The perturbation's own random stream (the preset's is left as the clean scene drew it)."""
        return np.random.default_rng([int(seed), zlib.crc32(self.family.encode()), int(round(self.strength * 1e6))])

    def changes_nothing(self, scene: SceneDef) -> Optional[str]:
        """Why the family would leave ``scene`` as it is (it has nothing the family acts on), else None."""
        if self.is_clean or self.family not in _NOTHING_TO_ACT_ON:
            return None
        test, reason = _NOTHING_TO_ACT_ON[self.family]
        return reason if test(scene) else None

    def apply(self, scene: SceneDef, records: list[FrameRecord], seed: int) -> tuple[SceneDef, list[FrameRecord]]:
        """The perturbed (scene, frames); strength 0 returns both as given. A family with nothing to act on
        in ``scene`` (:meth:`changes_nothing`) is an error: its scene would be the clean one under another name."""
        if self.is_clean:
            return scene, records
        reason = self.changes_nothing(scene)
        if reason is not None:
            raise InputError(None, "perturbation", f"{self.family} changes nothing on this scene: {reason}")
        return _APPLY[self.family](scene, records, self.strength, self.rng(seed))


def parse(value: Optional[Sequence]) -> Optional[Perturbation]:
    """A :class:`Perturbation` from ``(family, strength)`` (or None / a Perturbation as it is)."""
    if value is None or isinstance(value, Perturbation):
        return value
    if len(value) != 2:
        raise InputError(None, "perturbation", f"expected (family, strength), got {value!r}")
    return Perturbation(str(value[0]), float(value[1]))


# -- which nodes move freely, which object is queried ---------------------------------------------
def _has_timeline(node: Node) -> bool:
    return node.timeline is not None or any(_has_timeline(c) for c in node.children)


def _free_movers(scene: SceneDef) -> list[Node]:
    """Nodes with an animated pose and no state timeline on them, above or below (their motion shows
    no state, so changing it leaves every label true)."""
    out: list[Node] = []

    def walk(node: Node, stateful_above: bool) -> None:
        stateful = stateful_above or node.timeline is not None
        if callable(node.pose) and not stateful and not _has_timeline(node):
            out.append(node)
        for child in node.children:
            walk(child, stateful)

    for w in scene.wholes:
        walk(w, False)
    return out


def _queried_object(scene: SceneDef) -> Node:
    """The first object with a state timeline (else the first object)."""
    return next((w for w in scene.wholes if _has_timeline(w)), scene.wholes[0])


def _first_timeline(scene: SceneDef) -> Optional[Timeline]:
    def walk(node: Node) -> Optional[Timeline]:
        if node.timeline is not None:
            return node.timeline
        return next((t for t in map(walk, node.children) if t is not None), None)

    return next((t for t in map(walk, scene.wholes) if t is not None), None)


def _all_nodes(scene: SceneDef) -> list[Node]:
    out: list[Node] = []

    def walk(node: Node) -> None:
        out.append(node)
        for child in node.children:
            walk(child)

    for w in scene.wholes:
        walk(w)
    return out


def _ping_pong(x: float) -> float:
    """Triangle wave of period 2 in [0, 1]: 0 -> 1 -> 0 ..."""
    x = x % 2.0
    return x if x <= 1.0 else 2.0 - x


# -- scene-side families ------------------------------------------------------------------------------
def _motion_speed(scene: SceneDef, records: list, strength: float, rng) -> tuple:
    factor = 1.0 + strength
    for node in _free_movers(scene):
        pose = node.pose

        def faster(ctx: FrameContext, pose=pose) -> np.ndarray:
            u = _ping_pong(ctx.u * factor)
            last = max(1, ctx.num_frames - 1)
            return pose(FrameContext(int(round(u * last)), ctx.num_frames))

        node.pose = faster
    return scene, records


def _motion_amplitude(scene: SceneDef, records: list, strength: float, rng) -> tuple:
    factor = 1.0 + strength
    for node in _free_movers(scene):
        pose = node.pose

        def wider(ctx: FrameContext, pose=pose) -> np.ndarray:
            start, now = pose(FrameContext(0, ctx.num_frames)), np.array(pose(ctx), dtype=np.float64)
            now[:3, 3] = start[:3, 3] + factor * (now[:3, 3] - start[:3, 3])
            return now

        node.pose = wider
    return scene, records


def _keep_frames(records: list[FrameRecord], dropped: set[int]) -> list[FrameRecord]:
    """``records`` without the training frames of the time indices in ``dropped`` (the first and last
    time index stay: the layouts' normalised time is read from them)."""
    last = max(r.time_index for r in records)
    return [r for r in records if r.split != "train" or r.time_index in (0, last) or r.time_index not in dropped]


def _frames_dropped(scene: SceneDef, records: list, strength: float, rng) -> tuple:
    train_times = sorted({r.time_index for r in records if r.split == "train"})
    count = int(round(strength * len(train_times)))
    # evenly spread over the training times: every k-th, starting half a step in
    picks = np.linspace(0, len(train_times) - 1, count + 2)[1:-1] if count else []
    dropped = {train_times[int(round(p))] for p in picks}
    return scene, _keep_frames(records, dropped)


def _state_gap(scene: SceneDef, records: list, strength: float, rng) -> tuple:
    timeline = _first_timeline(scene)
    n = scene.num_frames
    centre = timeline.boundaries[0] - 0.5 if timeline is not None else (n - 1) / 2
    half = strength * n / 2
    dropped = {t for t in range(n) if abs(t - centre) <= half}
    return scene, _keep_frames(records, dropped)


def _cameras_by_time(records: list[FrameRecord]) -> dict[int, list[FrameRecord]]:
    out: dict[int, list[FrameRecord]] = {}
    for r in records:
        out.setdefault(r.time_index, []).append(r)
    return out


def _monocular_path(records: list[FrameRecord]) -> dict:
    """Time index -> camera of a monocular video (an :class:`InputError` for a rig)."""
    if len({r.time_index for r in records}) != len(records):
        raise InputError(None, "perturbation", "the camera families change a monocular camera path: use a "
                         "monocular layout (hypernerf or dnerf)")
    return {r.time_index: r.camera for r in records}


def _camera_slow(scene: SceneDef, records: list, strength: float, rng) -> tuple:
    path = _monocular_path(records)
    times = sorted(path)
    middle = (len(times) - 1) / 2
    out = []
    for r in records:
        k = times.index(r.time_index)
        source = times[int(round(middle + (k - middle) * (1.0 - strength)))]
        out.append(replace(r, camera=path[source]))
    return scene, out


def _camera_teleport(scene: SceneDef, records: list, strength: float, rng) -> tuple:
    path = _monocular_path(records)
    times = sorted(path)
    draws = rng.random(len(times))
    sources = rng.integers(0, len(times), len(times))
    out = []
    for r in records:
        k = times.index(r.time_index)
        source = times[int(sources[k])] if draws[k] < strength else r.time_index
        out.append(replace(r, camera=path[source]))
    return scene, out


def _camera_rig(scene: SceneDef, records: list, strength: float, rng) -> tuple:
    path = _monocular_path(records)
    times = sorted(path)
    n, extra = len(times), int(round(strength))
    position = {t: k for k, t in enumerate(times)}
    out = list(records)
    for r in records:
        if r.split != "train":
            continue
        k = position[r.time_index]
        for m in range(1, extra + 1):
            source = times[(k + int(round(m * n / (extra + 1)))) % n]
            stem, dot, ext = r.image_file.rpartition(".")
            out.append(replace(r, name=f"{r.name}_rig{m}", camera_id=str(m), camera=path[source],
                               image_file=f"{stem}_rig{m}{dot}{ext}"))
    return scene, out


def _occluder(scene: SceneDef, records: list, strength: float, rng) -> tuple:
    target = _queried_object(scene)
    radius = strength * scene.focus_radius
    cameras = {t: rs[0].camera for t, rs in _cameras_by_time(records).items()}
    lift = np.array([0.0, 0.0, 0.5 * radius])

    def place(ctx: FrameContext) -> np.ndarray:
        anchor = np.asarray(resolve(target.pose, ctx), dtype=np.float64)[:3, 3] + lift
        cam = cameras[ctx.time_index]
        eye = np.asarray(cam.center, dtype=np.float64)
        ahead = anchor + OCCLUDER_DEPTH * (eye - anchor)
        # slide along the image's x axis at the occluder's depth, from beyond the left edge to beyond the
        # right one: the scene is unoccluded before and after the crossing, so the family hides the queried
        # object alone (parked in view, the ball hid another object for a third of the video)
        uv, z = cam.project(ahead)
        right, column, depth = cam.R[0], float(uv[0, 0]), float(z[0])
        margin = OCCLUDER_MARGIN * max(radius, 1e-3)
        left_end = -(column / cam.fx * depth + margin)
        right_end = (cam.width - column) / cam.fx * depth + margin
        # crosses the object during the middle third of the video, out of view before and after
        sweep = float(np.clip((ctx.u - 1 / 3) * 3.0, 0.0, 1.0))
        return translation(ahead + right * (left_end + sweep * (right_end - left_end)))

    # no query asks about the ball: the family's scores are those of the clean scene's queries, comparable
    # with its clean scores (a query of the ball would score 0 wherever it is out of view, for every method)
    ball = whole(OCCLUDER_NAME, pose=place, pieces=[Piece(Sphere(radius), tx.Solid((0.35, 0.55, 0.35)))],
                 queried=False)
    return replace(scene, wholes=list(scene.wholes) + [ball]), records


@dataclass(frozen=True)
class Tinted(tx.Texture):
    """``base`` blended towards one colour."""

    base: tx.Texture
    tint: tx.Color
    amount: float
    """Blend weight of the tint in [0, 1]."""

    def albedo(self, p: np.ndarray, n: np.ndarray) -> np.ndarray:
        a = self.base.albedo(p, n)
        return a + (np.asarray(self.tint, dtype=np.float64) - a) * self.amount


APPEARANCE_TINT = (0.55, 0.32, 0.12)
"""Colour the ``appearance`` family drifts towards (a warm, dim light)."""


def _appearance(scene: SceneDef, records: list, strength: float, rng) -> tuple:
    def amount(ctx: FrameContext) -> float:
        return strength * 0.5 * (1.0 - np.cos(2.0 * np.pi * CYCLES * ctx.u))

    for node in _all_nodes(scene):
        for k, piece in enumerate(node.pieces):
            texture = piece.texture

            def drifting(ctx: FrameContext, texture=texture) -> tx.Texture:
                return Tinted(resolve(texture, ctx), APPEARANCE_TINT, float(amount(ctx)))

            node.pieces[k] = replace(piece, texture=drifting)
    return scene, records


def _semantic_subtle(scene: SceneDef, records: list, strength: float, rng) -> tuple:
    for node in _all_nodes(scene):
        timeline = node.timeline
        if timeline is None:
            continue
        clean_value = timeline.value

        def faint(ctx: FrameContext, per_state: dict[str, float], clean_value=clean_value,
                  timeline=timeline) -> float:
            first = per_state[timeline.states[timeline.sequence[0]].key]
            return first + (1.0 - strength) * (clean_value(ctx, per_state) - first)

        # the preset's closures hold the timeline object itself: its visual value is changed in place
        # (labels come from its intervals, which stay)
        object.__setattr__(timeline, "value", faint)
    return scene, records


def widened_ramp(timeline: Timeline, strength: float) -> float:
    """Ramp width (frames) of ``timeline`` under ``state-ramp`` at ``strength``: ``strength`` of the video, never
    narrower than the timeline's own ramp and never wider than the shortest gap between two of its boundaries
    (ramps that touch but never overlap, so a frame's visible change is one transition's progress alone)."""
    edges = tuple(timeline.boundaries)
    gap = min((b - a for a, b in zip(edges, edges[1:])), default=float(timeline.num_frames))
    return float(max(timeline.ramp_frames, min(strength * timeline.num_frames, gap)))


def _state_ramp(scene: SceneDef, records: list, strength: float, rng) -> tuple:
    for node in _all_nodes(scene):
        timeline = node.timeline
        if timeline is not None:
            # the preset's closures hold the timeline object itself: its ramp is widened in place (labels
            # come from its boundaries, which stay)
            object.__setattr__(timeline, "ramp_frames", widened_ramp(timeline, strength))
    return scene, records


def _topology(scene: SceneDef, records: list, strength: float, rng) -> tuple:
    distance = strength * scene.focus_radius

    for w in scene.wholes:
        if len(w.children) < 2:
            continue
        for k, child in enumerate(w.children):
            angle = 2.0 * np.pi * k / len(w.children)
            direction = np.array([np.cos(angle), np.sin(angle), 0.0])
            pose = child.pose

            def apart(ctx: FrameContext, pose=pose, direction=direction) -> np.ndarray:
                gap = distance * 0.5 * (1.0 - np.cos(2.0 * np.pi * CYCLES * ctx.u))
                return translation(direction * gap) @ np.asarray(resolve(pose, ctx), dtype=np.float64)

            child.pose = apart
    return scene, records


_NOTHING_TO_ACT_ON: dict[str, tuple[Callable[[SceneDef], bool], str]] = {
    "motion-speed": (lambda scene: not _free_movers(scene),
                     "no part moves without a state timeline above or below it"),
    "motion-amplitude": (lambda scene: not _free_movers(scene),
                         "no part moves without a state timeline above or below it"),
    "topology": (lambda scene: all(len(w.children) < 2 for w in scene.wholes), "no object has several parts"),
    "semantic-subtle": (lambda scene: _first_timeline(scene) is None, "no object changes state"),
    "state-ramp": (lambda scene: _first_timeline(scene) is None, "no object changes state"),
}
"""Families that act on one kind of part only, with the test that a scene has none, and what it lacks."""

_APPLY: dict[str, Callable] = {
    "motion-speed": _motion_speed, "motion-amplitude": _motion_amplitude, "frames-dropped": _frames_dropped,
    "state-gap": _state_gap, "camera-slow": _camera_slow, "camera-teleport": _camera_teleport,
    "camera-rig": _camera_rig,
    "occluder": _occluder, "appearance": _appearance, "semantic-subtle": _semantic_subtle, "state-ramp": _state_ramp,
    "topology": _topology,
}
