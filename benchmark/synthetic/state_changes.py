"""How a preset's semantic states change over time: named levels.

A preset with a state timeline says how its states change by naming a level (``PresetSpec.state_changes``):

* ``switch``: the preset's own schedule: its sequence of states, its boundaries drawn in its own ranges of
  the video, and its own (short) visual ramps: a clean switch a few frames long;
* ``gradual``: one change that develops over :data:`GRADUAL` ``.ramp_fraction`` of the video (30 %: 18 of 60
  frames), the liquid darkening or the cup filling frame by frame;
* ``back-and-forth``: the states alternate: three changes (first, second, first, second state), each over
  12 % of the video (7 of 60 frames), as an egg that is opened, shut and opened again.

Ground truth of a gradual change
--------------------------------
The visual variables of a state (a colour, a lid angle, a fill level) follow :meth:`Timeline.value`: a
smoothstep ramp of ``ramp_frames`` frames per change, centred half a frame before the change's boundary
``b``. **A state holds from the first frame past the midpoint of its transition**: frames up to ``b - 1``
show less than half of the change, frames from ``b`` on more than half, and the time-sensitive
annotations (:mod:`benchmark.synthetic.gt`) give the new state from ``b`` on. The levels place the changes
so that their ramps never overlap (consecutive boundaries at least ``ramp_frames + hold_frames`` apart) and
lie inside the video with ``hold_frames`` of held state before the first and after the last, so the
visible fraction of the change at a frame is that ramp's progress alone, and the rule holds exactly.

The boundaries are drawn from a stream spawned from the preset's random stream after the preset's own
schedule has been drawn from it, so every other draw (placements, colours, the camera path) is the one the
``switch`` level makes: the levels differ in the state changes only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from benchmark.core.errors import InputError

from .model import State, Timeline


@dataclass(frozen=True)
class StateChanges:
    """One named level of state changes (module docstring)."""

    name: str
    """Level name (``"switch"``, ``"gradual"``, ``"back-and-forth"``)."""
    description: str
    """One line for listings."""
    changes: Optional[int] = None
    """How many times the state changes, alternating between the preset's first two states of its
    sequence (``None``: the preset's own sequence and boundary ranges)."""
    ramp_fraction: Optional[float] = None
    """Length of each visual transition, as a share of the video (``None``: the preset's own)."""
    hold_fraction: float = 0.0
    """Frames each state is held fully between transitions (and before the first, after the last), as a
    share of the video."""

    @property
    def is_preset_schedule(self) -> bool:
        return self.changes is None

    def timeline(self, rng: np.random.Generator, num_frames: int, states: Sequence[State], sequence: Sequence[int],
                 fraction_ranges: Sequence[tuple[float, float]], ramp_fraction: float) -> Timeline:
        """The timeline of ``states`` under this level. ``sequence``, ``fraction_ranges`` and ``ramp_fraction``
        are the preset's own schedule (:meth:`Timeline.sample`), always drawn from ``rng`` first; another level
        then draws its boundaries from a stream spawned from ``rng`` (module docstring)."""
        own = Timeline.sample(rng, num_frames, states, sequence, fraction_ranges, ramp_fraction)
        if self.is_preset_schedule:
            return own
        first, second = sequence[0], next(s for s in sequence if s != sequence[0])
        stream = rng.spawn(1)[0]
        boundaries, ramp = alternating_boundaries(stream, num_frames, self.changes, self.ramp_fraction * num_frames,
                                                  self.hold_fraction * num_frames)
        seq = tuple(first if j % 2 == 0 else second for j in range(len(boundaries) + 1))
        return Timeline(tuple(states), seq, boundaries, num_frames, ramp_frames=ramp)


def alternating_boundaries(rng: np.random.Generator, num_frames: int, changes: int, ramp_frames: float,
                           hold_frames: float) -> tuple[tuple[int, ...], float]:
    """(boundaries, ramp frames) of ``changes`` state changes in a video of ``num_frames`` frames whose ramps
    (``ramp_frames`` wide, centred at ``b - 0.5``) never overlap and leave ``hold_frames`` of held state between
    them and at both ends. A video too short for that gets narrower ramps and holds (scaled down together
    until they fit), and a video too short for ``changes`` changes gets as many as it has room for (one
    frame per segment). Boundaries are uniform among the placements that keep those gaps."""
    n = int(num_frames)
    if n < 2:
        raise ValueError(f"a state change needs at least 2 frames, got {n}")
    m = max(1, min(int(changes), n - 1))
    ramp, hold = float(ramp_frames), float(hold_frames)
    for _ in range(200):
        gap = max(1, int(np.ceil(ramp + hold - 1e-9)))
        lo = max(1, int(np.ceil(ramp / 2 + 0.5 + hold - 1e-9)))
        hi = min(n - 1, int(np.floor(n - 0.5 - ramp / 2 - hold + 1e-9)))
        if hi - lo >= (m - 1) * gap:
            break
        ramp, hold = 0.9 * ramp, 0.9 * hold
    else:  # vanishing ramps: one frame per segment always fits (m <= n - 1)
        ramp, hold, gap, lo, hi = 1.0, 0.0, 1, 1, n - 1
    slack = hi - lo - (m - 1) * gap
    offsets = np.sort(rng.integers(0, slack + 1, size=m))
    bounds = tuple(int(lo + j * gap + offsets[j]) for j in range(m))
    return bounds, max(ramp, 1.0)  # a ramp under a frame is a switch either way (as Timeline.sample keeps)


STATE_CHANGES: dict[str, StateChanges] = {level.name: level for level in (
    StateChanges("switch", "the preset's own schedule: each change a clean switch a few frames long"),
    StateChanges("gradual", "one change developing over 30 % of the video", changes=1, ramp_fraction=0.3,
                 hold_fraction=0.1),
    StateChanges("back-and-forth", "three changes there and back and there again, each over 12 % of the video",
                 changes=3, ramp_fraction=0.12, hold_fraction=0.06),
)}
"""Every level of state changes, by name."""


def state_changes(name: str) -> StateChanges:
    """The level called ``name`` (an :class:`InputError` naming the valid ones otherwise)."""
    if name not in STATE_CHANGES:
        raise InputError(None, "state_changes", f"unknown level of state changes {name!r} "
                         f"(valid: {', '.join(STATE_CHANGES)})")
    return STATE_CHANGES[name]
