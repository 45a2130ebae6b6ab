"""Procedural solid textures: albedo as a function of the *local* surface point.

Textures are evaluated in the coordinates of the piece they paint, so they move with the object
and give a reconstruction method consistent features to track. All are vectorised over points.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Sequence

import numpy as np

Color = tuple[float, float, float]


class Texture:
    """Albedo in [0, 1] at surface points."""

    def albedo(self, p: np.ndarray, n: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        """(M, 3) albedo at (M, 3) local points ``p`` with (M, 3) local normals ``n``."""
        raise NotImplementedError


def _mix(c1: Color, c2: Color, w: np.ndarray) -> np.ndarray:
    """(M, 3): ``c1`` where ``w`` = 0, ``c2`` where ``w`` = 1."""
    a, b = np.asarray(c1, dtype=np.float64), np.asarray(c2, dtype=np.float64)
    return a + (b - a) * w[:, None]


@dataclass(frozen=True)
class Solid(Texture):
    """One colour."""

    color: Color

    def albedo(self, p, n):
        return np.broadcast_to(np.asarray(self.color, dtype=np.float64), p.shape).copy()


@dataclass(frozen=True)
class Checker(Texture):
    """3D checkerboard of two colours."""

    color_a: Color
    color_b: Color
    cell: float
    """Edge length of one cell, in scene units."""

    def albedo(self, p, n):
        parity = np.floor(p / self.cell).astype(np.int64).sum(axis=1) & 1
        return _mix(self.color_a, self.color_b, parity.astype(np.float64))


@dataclass(frozen=True)
class Stripes(Texture):
    """Parallel bands across ``axis``."""

    color_a: Color
    color_b: Color
    axis: tuple[float, float, float]
    """Direction across the stripes (local)."""
    period: float
    """Distance between two stripes of the same colour."""
    duty: float = 0.5
    """Fraction of each period painted ``color_b``."""

    def albedo(self, p, n):
        ax = np.asarray(self.axis, dtype=np.float64)
        phase = np.mod(p @ (ax / np.linalg.norm(ax)) / self.period, 1.0)
        return _mix(self.color_a, self.color_b, (phase < self.duty).astype(np.float64))


@dataclass(frozen=True)
class Noise(Texture):
    """Smooth fractal value noise blending two colours (wood, dough, leaves, plaster)."""

    color_a: Color
    color_b: Color
    scale: float
    """Feature size of the coarsest octave, in scene units."""
    seed: int = 0
    """Selects the random lattice."""
    octaves: int = 3
    """Number of octaves, each half the size and half the weight of the previous one."""
    contrast: float = 1.0
    """Gain applied around 0.5 before clipping (> 1 gives blotchier patterns)."""

    def albedo(self, p, n):
        w = fractal_noise(p / self.scale, self.seed, self.octaves)
        w = np.clip(0.5 + (w - 0.5) * self.contrast, 0.0, 1.0)
        return _mix(self.color_a, self.color_b, w)


@dataclass(frozen=True)
class Layered(Texture):
    """``base`` modulated by a multiplicative ``detail`` texture (its luminance, centred on 1)."""

    base: Texture
    detail: Texture
    strength: float = 0.3
    """How strongly the detail darkens/brightens the base (0 = none)."""

    def albedo(self, p, n):
        lum = self.detail.albedo(p, n).mean(axis=1, keepdims=True)
        return np.clip(self.base.albedo(p, n) * (1.0 + self.strength * (2.0 * lum - 1.0)), 0.0, 1.0)


@dataclass(frozen=True)
class ByNormal(Texture):
    """``up`` on faces whose local normal points along +z (within ``cos_limit``), else ``side``."""

    up: Texture
    side: Texture
    cos_limit: float = 0.7
    """Faces with ``n_z > cos_limit`` use ``up``."""

    def albedo(self, p, n):
        top = n[:, 2] > self.cos_limit
        out = self.side.albedo(p, n)
        if np.any(top):
            out[top] = self.up.albedo(p[top], n[top])
        return out


@dataclass(frozen=True)
class ByHeight(Texture):
    """``below`` under local height ``z_split``, ``above`` over it (a label band, a floor and walls)."""

    below: Texture
    above: Texture
    z_split: float

    def albedo(self, p, n):
        low = p[:, 2] < self.z_split
        out = self.above.albedo(p, n)
        if np.any(low):
            out[low] = self.below.albedo(p[low], n[low])
        return out


LATTICE_SIZE = 32
"""Period of the noise lattice in cells along each axis (a power of two: indices wrap with a mask).
Each octave uses its own lattice, so the repetition is not visible in the sum."""


@functools.lru_cache(maxsize=32)
def _lattice(seed: int) -> np.ndarray:
    """(L**3,) float32 random values of ``seed``'s noise lattice, flattened x-major, L = :data:`LATTICE_SIZE`."""
    return np.random.default_rng(seed).random(LATTICE_SIZE ** 3).astype(np.float32)


def value_noise(x: np.ndarray, seed: int) -> np.ndarray:
    """(M,) smooth noise in [0, 1] at (M, 3) points: trilinear interpolation of a periodic random lattice."""
    values = _lattice(seed)
    size, mask = LATTICE_SIZE, LATTICE_SIZE - 1
    i0 = np.floor(x)
    f = (x - i0).astype(np.float32)  # single precision is plenty for a blend weight, and faster
    f = f * f * (3.0 - 2.0 * f)  # smoothstep fade: continuous derivative across cells
    i0 = i0.astype(np.int64)
    i1 = (i0 + 1) & mask
    i0 &= mask
    # (2, M) flat-index contributions of the cell's two faces along each axis
    ax = np.stack([i0[:, 0], i1[:, 0]]).astype(np.int32) * (size * size)
    ay = np.stack([i0[:, 1], i1[:, 1]]).astype(np.int32) * size
    az = np.stack([i0[:, 2], i1[:, 2]]).astype(np.int32)
    v = values[ax[:, None, None, :] + ay[None, :, None, :] + az[None, None, :, :]]  # (2, 2, 2, M) corners
    v = v[:, :, 0] + (v[:, :, 1] - v[:, :, 0]) * f[:, 2]  # blend along z, then y, then x
    v = v[:, 0] + (v[:, 1] - v[:, 0]) * f[:, 1]
    return (v[0] + (v[1] - v[0]) * f[:, 0]).astype(np.float64)


def fractal_noise(x: np.ndarray, seed: int, octaves: int) -> np.ndarray:
    """(M,) sum of ``octaves`` value-noise layers (each twice the frequency, half the weight), in [0, 1]."""
    total, weight, norm = np.zeros(len(x)), 1.0, 0.0
    for k in range(max(1, octaves)):
        total += weight * value_noise(x * (2.0 ** k), seed + 101 * k)
        norm += weight
        weight *= 0.5
    return total / norm


def darken(color: Sequence[float], amount: float) -> Color:
    """``color`` scaled towards black by ``amount`` in [0, 1]."""
    c = np.asarray(color, dtype=np.float64) * (1.0 - amount)
    return (float(c[0]), float(c[1]), float(c[2]))


def lerp_color(a: Sequence[float], b: Sequence[float], w: float) -> Color:
    """Linear blend of two colours; ``w`` = 0 gives ``a``."""
    c = np.asarray(a, dtype=np.float64) + (np.asarray(b, dtype=np.float64) - np.asarray(a)) * w
    return (float(c[0]), float(c[1]), float(c[2]))
