"""Scene definitions as data: objects with part trees, motion, and semantic state timelines.

A synthetic scene is a list of **wholes** (objects). A whole has **parts**, a part has **subparts**
(the three levels SAM calls large / middle / small). Geometry (:class:`Piece`) hangs on the finest
node that is declared; a node declared with pieces and no children stands for itself one level
down as well ("implicit" entries in the catalogue: same name, same pixels), so every object pixel
carries an id at every level.

Anything that changes over time - a pose, a solid's size, a colour, visibility - may be given as a
function of :class:`FrameContext` instead of a constant (:data:`Animated`). Semantic states are
:class:`Timeline` objects; the visual variables that show a state (liquid level, lid angle, gap
between halves) are derived from the *same* timeline with :meth:`Timeline.value`, so the labels and
the pixels cannot disagree about when a state changes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence, TypeVar, Union

import numpy as np

from benchmark.core.truth import LEVELS, Level

from .csg import Solid
from .textures import Texture
from .transforms import smoothstep

"""Finest first, the order of the id maps (SAM small / middle / large)."""

T = TypeVar("T")


@dataclass(frozen=True)
class FrameContext:
    """What a time-varying quantity may depend on."""

    time_index: int
    """0-based video frame number."""
    num_frames: int
    """Length of the video."""

    @property
    def u(self) -> float:
        """Normalised time in [0, 1] (frame / (num_frames - 1))."""
        return self.time_index / max(1, self.num_frames - 1)


Animated = Union[T, Callable[[FrameContext], T]]


def resolve(value: "Animated[T]", ctx: FrameContext) -> T:
    """The value of a constant-or-function-of-time at ``ctx``."""
    return value(ctx) if callable(value) else value


@dataclass
class Piece:
    """One solid with one texture, placed in its node's frame."""

    solid: Animated[Solid]
    texture: Animated[Texture]
    pose: Animated[np.ndarray] = field(default_factory=lambda: np.eye(4))
    """4x4 transform of the solid in its node's frame."""
    visible: Animated[bool] = True
    """A piece that is hidden at a frame covers no pixels (a coffee stream that starts and stops)."""


@dataclass
class Node:
    """A whole, part or subpart: a name a person would use, and what it is made of."""

    name: str
    """Noun phrase used as the query text (``"cup handle"``)."""
    synonyms: tuple[str, ...] = ()
    """Other phrases for the same thing (for captions and open-vocabulary checks)."""
    pieces: list[Piece] = field(default_factory=list)
    """Geometry of this node (only for nodes without children)."""
    children: list["Node"] = field(default_factory=list)
    """Parts of a whole / subparts of a part."""
    pose: Animated[np.ndarray] = field(default_factory=lambda: np.eye(4))
    """4x4 transform of this node in its parent's frame (world for wholes)."""
    timeline: Optional["Timeline"] = None
    """Semantic states of this node over time, if any."""
    queried: bool = True
    """Whether its name becomes a query of the annotations. A distractor (the stress suite's occluder) is
    in the scene, its truth and its supervision, but no query asks about it."""

    def __post_init__(self) -> None:
        if self.pieces and self.children:
            raise ValueError(f"node {self.name!r}: give either pieces or children, not both")
        if not self.pieces and not self.children:
            raise ValueError(f"node {self.name!r} has no geometry")


def whole(name: str, *, parts: Sequence[Node] = (), pieces: Sequence[Piece] = (), synonyms: Sequence[str] = (),
          pose: Animated[np.ndarray] = None, timeline: Optional["Timeline"] = None, queried: bool = True) -> Node:
    """An object (large level); ``parts`` are its parts, or ``pieces`` its geometry if it has none."""
    return Node(name, tuple(synonyms), list(pieces), list(parts), np.eye(4) if pose is None else pose, timeline,
                queried)


def part(name: str, *, parts: Sequence[Node] = (), pieces: Sequence[Piece] = (), synonyms: Sequence[str] = (),
         pose: Animated[np.ndarray] = None, timeline: Optional["Timeline"] = None) -> Node:
    """A part of a whole (middle level); ``parts`` are then its subparts."""
    return whole(name, parts=parts, pieces=pieces, synonyms=synonyms, pose=pose, timeline=timeline)


def subpart(name: str, *, pieces: Sequence[Piece], synonyms: Sequence[str] = (),
            pose: Animated[np.ndarray] = None, timeline: Optional["Timeline"] = None) -> Node:
    """A subpart of a part (small level): geometry only."""
    return whole(name, pieces=pieces, synonyms=synonyms, pose=pose, timeline=timeline)


@dataclass(frozen=True)
class State:
    """One semantic state of an object ("cracked")."""

    key: str
    """Short identifier (``"cracked"``)."""
    phrase: str
    """Time-sensitive query text (``"cracked cookie"``)."""
    captions: tuple[str, ...]
    """Several paraphrased captions describing the object in this state."""
    query: bool = True
    """Whether the state becomes a time-sensitive query in the annotations."""


@dataclass(frozen=True)
class Timeline:
    """Which state holds when: segments separated by boundaries, with short visual ramps.

    Segment ``j`` covers time indices ``[boundaries[j-1], boundaries[j] - 1]`` (inclusive; the first
    starts at 0, the last ends at ``num_frames - 1``). The visual change for boundary ``b`` is a
    smoothstep ramp of ``ramp_frames`` frames centred on ``b - 0.5``: frames up to ``b - 1`` are less
    than half way, frames from ``b`` on are more than half way. That is the ground truth's rule for a
    gradual change: a state holds from the first frame past the midpoint of its transition (exact while
    ramps do not overlap, as :mod:`benchmark.synthetic.state_changes` places them).
    """

    states: tuple[State, ...]
    """Distinct states."""
    sequence: tuple[int, ...]
    """Index into ``states`` of each segment, in time order (states may recur: closed-open-closed)."""
    boundaries: tuple[int, ...]
    """First time index of each segment after the first (strictly increasing, len = segments - 1)."""
    num_frames: int
    """Video length the boundaries refer to."""
    ramp_frames: float = 4.0
    """Width of each visual transition, in frames."""

    def __post_init__(self) -> None:
        if len(self.boundaries) != len(self.sequence) - 1:
            raise ValueError("timeline: need one boundary between consecutive segments")
        edges = (0,) + tuple(self.boundaries) + (self.num_frames,)
        if any(b <= a for a, b in zip(edges, edges[1:])):
            raise ValueError(f"timeline boundaries {self.boundaries} not strictly inside (0, {self.num_frames})")

    @staticmethod
    def sample(rng: np.random.Generator, num_frames: int, states: Sequence[State], sequence: Sequence[int],
               fraction_ranges: Sequence[tuple[float, float]], ramp_fraction: float = 0.06) -> "Timeline":
        """Draw each boundary uniformly inside its range of normalised time (varied segment lengths)."""
        bounds = []
        lo_allowed = 1
        for k, (lo, hi) in enumerate(fraction_ranges):
            b = int(round(rng.uniform(lo, hi) * (num_frames - 1)))
            remaining = len(fraction_ranges) - k - 1
            b = int(np.clip(b, lo_allowed, num_frames - 1 - remaining))
            bounds.append(b)
            lo_allowed = b + 1
        return Timeline(tuple(states), tuple(sequence), tuple(bounds), num_frames,
                        ramp_frames=max(1.0, ramp_fraction * num_frames))

    def segments(self) -> list[tuple[State, int, int]]:
        """(state, first, last) per segment, inclusive time indices."""
        edges = (0,) + tuple(self.boundaries) + (self.num_frames,)
        return [(self.states[s], edges[j], edges[j + 1] - 1) for j, s in enumerate(self.sequence)]

    def intervals(self) -> dict[str, list[tuple[int, int]]]:
        """State key -> inclusive time-index intervals where it holds."""
        out: dict[str, list[tuple[int, int]]] = {s.key: [] for s in self.states}
        for state, a, b in self.segments():
            out[state.key].append((a, b))
        return out

    def state_at(self, time_index: int) -> State:
        for state, a, b in self.segments():
            if a <= time_index <= b:
                return state
        raise IndexError(f"time index {time_index} outside the video (0..{self.num_frames - 1})")

    def progress(self, ctx: FrameContext, boundary: int) -> float:
        """Visual progress in [0, 1] of transition number ``boundary`` at this frame."""
        centre = self.boundaries[boundary] - 0.5
        return float(smoothstep((ctx.time_index - centre) / self.ramp_frames + 0.5))

    def value(self, ctx: FrameContext, per_state: dict[str, float]) -> float:
        """A visual variable that takes ``per_state[key]`` in each state, ramping at the boundaries."""
        seq = [self.states[s].key for s in self.sequence]
        v = per_state[seq[0]]
        for j in range(len(self.boundaries)):
            v += (per_state[seq[j + 1]] - per_state[seq[j]]) * self.progress(ctx, j)
        return float(v)

    def to_dict(self) -> list[dict]:
        """JSON form: one entry per state with its phrase, captions and intervals."""
        iv = self.intervals()
        return [{"state": s.key, "phrase": s.phrase, "captions": list(s.captions), "query": s.query,
                 "intervals": [list(x) for x in iv[s.key]]} for s in self.states]


@dataclass(frozen=True)
class Light:
    """A directional light plus ambient light (Lambert shading)."""

    direction: tuple[float, float, float] = (0.4, -0.5, 1.0)
    """Direction *towards* the light, world coordinates."""
    ambient: float = 0.35
    """Ambient fraction: unlit faces keep this much of their albedo."""
    intensity: float = 0.75
    """Diffuse strength for a face that points straight at the light."""


@dataclass
class SceneDef:
    """Everything needed to render a preset at any frame."""

    name: str
    """Preset name."""
    wholes: list[Node]
    """The objects (ids at every level are assigned in this order)."""
    background: list[Piece]
    """Static surroundings (floor, walls); id 0 at every level and not rendered in the D-NeRF layout."""
    focus_center: tuple[float, float, float]
    """Point the cameras look at."""
    focus_radius: float
    """Radius around :attr:`focus_center` that every camera must keep in view."""
    num_frames: int
    """Video length the timelines were sampled for."""
    light: Light = field(default_factory=Light)


# -- catalogue: ids per level -------------------------------------------------------------------
@dataclass(frozen=True)
class Entry:
    """One id at one level."""

    level: Level
    id: int
    name: str
    synonyms: tuple[str, ...]
    parent: Optional[int]
    """Id of the enclosing node one level up (``None`` for wholes)."""
    implicit: bool
    """True when the node was not declared at this level (it stands in for its parent)."""
    node: Node = field(compare=False, repr=False)


@dataclass(frozen=True)
class Leaf:
    """A node that carries pieces, with its ids at every level and the chain of nodes above it."""

    ids: tuple[int, int, int]
    """(subpart, part, whole) ids."""
    chain: tuple[Node, ...]
    """Nodes from the whole down to the leaf (poses compose in this order)."""


def _distinct(nodes: Sequence[Node]) -> tuple[Node, ...]:
    """``nodes`` without repeats (by identity), order kept."""
    out: list[Node] = []
    for n in nodes:
        if not any(n is m for m in out):
            out.append(n)
    return tuple(out)


@dataclass
class Catalogue:
    """Ids of every node at every level, assigned in declaration order starting at 1."""

    entries: dict[Level, list[Entry]]
    leaves: list[Leaf]

    @staticmethod
    def build(wholes: Sequence[Node]) -> "Catalogue":
        entries: dict[Level, list[Entry]] = {lv: [] for lv in LEVELS}
        leaves: list[Leaf] = []

        def add(level: Level, node: Node, parent: Optional[int], implicit: bool) -> int:
            eid = len(entries[level]) + 1
            entries[level].append(Entry(level, eid, node.name, node.synonyms, parent, implicit, node))
            return eid

        for w in wholes:
            wid = add("whole", w, None, False)
            parts = w.children or [w]
            for p in parts:
                pid = add("part", p, wid, p is w)
                subs = p.children or [p]
                for s in subs:
                    sid = add("subpart", s, pid, s is p)
                    chain = _distinct([w, p, s])  # implicit levels repeat their parent node
                    leaves.append(Leaf((sid, pid, wid), chain))
                    if not s.pieces:
                        raise ValueError(f"{w.name!r}: subpart {s.name!r} has children (only 3 levels exist)")
        cat = Catalogue(entries, leaves)
        cat._check_names()
        return cat

    def _check_names(self) -> None:
        """A name must mean one set of pixels: the same name may repeat within a level (every
        'chocolate chip'), or across levels only as an implicit stand-in of one node."""
        declared: dict[str, Level] = {}
        for level in ("whole", "part", "subpart"):
            for e in self.entries[level]:
                if e.implicit:
                    continue
                if e.name in declared and declared[e.name] != level:
                    raise ValueError(f"name {e.name!r} is declared at both the {declared[e.name]} and "
                                     f"{level} levels: queries would be ambiguous")
                declared[e.name] = level

    def declared_level(self, name: str) -> Level:
        for level in ("whole", "part", "subpart"):
            if any(e.name == name and not e.implicit for e in self.entries[level]):
                return level
        raise KeyError(name)

    def ids_named(self, name: str) -> tuple[Level, list[int]]:
        """(level where ``name`` is declared, ids there carrying it)."""
        level = self.declared_level(name)
        return level, [e.id for e in self.entries[level] if e.name == name]

    def names(self, queried_only: bool = False) -> list[str]:
        """Every declared name, whole first, in declaration order, without repeats (``queried_only``: of
        the nodes a query asks about, :attr:`Node.queried`)."""
        seen: dict[str, None] = {}
        for level in ("whole", "part", "subpart"):
            for e in self.entries[level]:
                if not e.implicit and (e.node.queried or not queried_only):
                    seen.setdefault(e.name, None)
        return list(seen)

    def timelines(self) -> list[tuple[Entry, Timeline]]:
        """(declared entry, timeline) for every node with semantic states."""
        out = []
        for level in ("whole", "part", "subpart"):
            for e in self.entries[level]:
                if not e.implicit and e.node.timeline is not None:
                    out.append((e, e.node.timeline))
        return out

    def to_dict(self) -> dict:
        return {level: {str(e.id): {"name": e.name, "synonyms": list(e.synonyms), "parent": e.parent,
                                    "implicit": e.implicit} for e in self.entries[level]}
                for level in LEVELS}
