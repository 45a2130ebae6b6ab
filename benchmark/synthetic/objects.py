"""Reusable object builders (cups, plates, rings, the room) shared by the presets.

Every builder returns pieces or nodes in a local frame with the object standing on z = 0, so a
preset only places them. Dimensions are in scene units (roughly metres).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from . import textures as tx
from .csg import Box, Cylinder, Difference, HalfSpace, Moved, Solid
from .model import Piece
from .transforms import rotation, translation

# Cutters stick out of the solid they carve by this much, so no two operands share a surface.
CUT_MARGIN = 0.05


def moved(solid: Solid, *, rot: Optional[np.ndarray] = None, at=(0.0, 0.0, 0.0)) -> Solid:
    """``solid`` rotated by the 4x4 ``rot`` (default none) then moved to ``at``, as one local solid."""
    r = np.eye(3) if rot is None else np.asarray(rot)[:3, :3]
    return Moved(solid, r, np.asarray(at, dtype=np.float64))


def hollow_cylinder(radius: float, height: float, wall: float, bottom: float) -> Solid:
    """An open-topped container standing on z = 0: outer radius, height, wall and bottom thickness."""
    return Difference(Cylinder(radius, 0.0, height), Cylinder(radius - wall, bottom, height + CUT_MARGIN))


def ring(r_out: float, r_in: float, half_width: float) -> Solid:
    """A flat ring (washer) about local z, ``2 * half_width`` thick."""
    return Difference(Cylinder(r_out, -half_width, half_width),
                      Cylinder(r_in, -half_width - CUT_MARGIN, half_width + CUT_MARGIN))


@dataclass(frozen=True)
class CupGeometry:
    """Shape of a mug or glass standing on z = 0."""

    radius: float = 0.07
    """Outer radius."""
    height: float = 0.11
    """Height of the rim above the base."""
    wall: float = 0.008
    """Wall thickness."""
    bottom: float = 0.012
    """Base thickness (height of the inner floor)."""
    rim_band: float = 0.012
    """Height of the band painted as the rim subpart."""
    handle_radius: float = 0.035
    """Outer radius of the handle ring."""
    handle_thickness: float = 0.011
    """Radial thickness of the handle ring."""
    handle_width: float = 0.008
    """Half width of the handle ring along its axis."""

    @property
    def inner_radius(self) -> float:
        return self.radius - self.wall

    def wall_solid(self) -> Solid:
        """The cup body below the rim band."""
        body = hollow_cylinder(self.radius, self.height, self.wall, self.bottom)
        return body & HalfSpace((0.0, 0.0, 1.0), self.height - self.rim_band)

    def rim_solid(self) -> Solid:
        body = hollow_cylinder(self.radius, self.height, self.wall, self.bottom)
        return body & HalfSpace((0.0, 0.0, -1.0), -(self.height - self.rim_band))

    def handle_solid(self) -> Solid:
        """A half ring on the +x side, its ends buried in the wall."""
        r_in = self.handle_radius - self.handle_thickness
        loop = moved(ring(self.handle_radius, r_in, self.handle_width), rot=rotation((1, 0, 0), np.pi / 2),
                     at=(self.radius, 0.0, 0.55 * self.height))
        return loop & HalfSpace((-1.0, 0.0, 0.0), -(self.radius - 0.5 * self.wall))

    def liquid_solid(self, level: float) -> Solid:
        """Liquid filling ``level`` in [0, 1] of the inner height (keep ``level`` > 0)."""
        z0 = self.bottom + 1e-3  # just above the inner floor: no shared surface with the cup
        z1 = z0 + max(level, 1e-3) * (self.height - self.bottom - 0.01)
        return Cylinder(self.inner_radius - 1e-3, z0, z1)


def dish(radius: float, height: float, inner_radius: float, base: float) -> Solid:
    """A plate or saucer: a low disc with a shallow well."""
    return Difference(Cylinder(radius, 0.0, height), Cylinder(inner_radius, base, height + CUT_MARGIN))


def room(half_size: float = 2.5, height: float = 2.2, seed: int = 0,
         floor: Optional[tx.Texture] = None, walls: Optional[tx.Texture] = None) -> list[Piece]:
    """Static textured surroundings seen from inside: a floor (table top) and four walls."""
    floor_tex = floor or tx.Layered(
        tx.Stripes((0.55, 0.38, 0.24), (0.62, 0.45, 0.29), axis=(1.0, 0.15, 0.0), period=0.09, duty=0.45),
        tx.Noise((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), scale=0.12, seed=seed, octaves=3), strength=0.35)
    wall_tex = walls or tx.Layered(
        tx.Checker((0.80, 0.80, 0.74), (0.64, 0.70, 0.76), cell=0.35),
        tx.Noise((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), scale=0.25, seed=seed + 1, octaves=2), strength=0.3)
    box = Box((half_size, half_size, height / 2))
    # Local z runs from -height/2 (the floor) upwards; the floor band is the bottom millimetre.
    tex = tx.ByHeight(floor_tex, wall_tex, z_split=-height / 2 + 1e-3)
    return [Piece(box, tex, translation((0.0, 0.0, height / 2)))]
