"""Exact ray casting of analytic solids and their boolean combinations (numpy, all rays at once).

Every solid answers two questions, both vectorised over N rays / points in its *local* frame:

* :meth:`Solid.crossings` - every place a ray crosses the solid's surface, as a list of
  :class:`Crossing` (``t`` per ray, ``inf`` where that surface is missed, plus the outward normal);
* :meth:`Solid.contains` - whether points lie inside.

The first visible point of a closed solid seen from outside is simply its nearest crossing with
``t > 0``, and boolean combinations follow from set algebra on boundaries: the boundary of ``A - B``
lies in (boundary of A outside B) + (boundary of B inside A), and so on. This makes every shape
here - cups, rings, half cookies, hinged shells - exact, with no meshing and no marching.

Rule for scene authors: boolean operands must not share a surface (make the subtracted cylinder
stick out above the cup's rim, not end exactly at it); points on two coincident surfaces are
ambiguous.

Rays are ``(o, d)`` with ``o`` (N, 3) origins and ``d`` (N, 3) directions (unit length in world;
rigid transforms keep that). Parameters are in scene units.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

INF = np.inf
# Smallest |denominator| treated as non-zero when a ray is parallel to a face or axis.
_PARALLEL_EPS = 1e-12


@dataclass
class Crossing:
    """Where N rays cross one surface patch."""

    t: np.ndarray
    """(N,) ray parameter of the crossing; ``inf`` where this patch is not crossed."""
    normal: np.ndarray
    """(N, 3) outward unit normal of the solid at the crossing (garbage where ``t`` is ``inf``)."""


def _points(o: np.ndarray, d: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 3) points ``o + t d``; rays with no crossing (t = inf) give the origin (never used)."""
    return o + np.where(np.isfinite(t), t, 0.0)[:, None] * d


def _normalise(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-300)


def _quadratic_roots(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Real roots of ``a t^2 + b t + c = 0`` per ray, (N,) each, ``inf`` where none.

    Uses the cancellation-free form; where ``a`` is ~0 the single linear root goes to the first slot.
    """
    disc = b * b - 4.0 * a * c
    ok = disc >= 0.0
    sq = np.sqrt(np.where(ok, disc, 0.0))
    q = -0.5 * (b + np.where(b >= 0.0, sq, -sq))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = q / a
        r2 = c / q
        linear = np.abs(a) < _PARALLEL_EPS
        lin_root = np.where(np.abs(b) > _PARALLEL_EPS, -c / b, INF)
    r1 = np.where(linear, lin_root, r1)
    r2 = np.where(linear, INF, r2)
    r1 = np.where(ok | linear, r1, INF)
    r2 = np.where(ok & ~linear, r2, INF)
    r1 = np.where(np.isfinite(r1), r1, INF)
    r2 = np.where(np.isfinite(r2), r2, INF)
    return r1, r2


def _plane_t(o_axis: np.ndarray, d_axis: np.ndarray, value: float) -> np.ndarray:
    """(N,) parameter where ``o + t d`` reaches ``value`` along one axis; ``inf`` when parallel."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (value - o_axis) / d_axis
    return np.where(np.abs(d_axis) > _PARALLEL_EPS, t, INF)


class Solid:
    """A closed region of space in local coordinates."""

    def crossings(self, o: np.ndarray, d: np.ndarray) -> list[Crossing]:  # pragma: no cover - abstract
        raise NotImplementedError

    def contains(self, p: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        """(N,) bool: ``p`` (N, 3) inside the solid."""
        raise NotImplementedError

    def bounding_sphere(self) -> tuple[np.ndarray, float]:  # pragma: no cover - abstract
        """(centre (3,), radius) of a sphere containing the solid; radius ``inf`` if unbounded."""
        raise NotImplementedError

    # operators read like set algebra: a | b, a & b, a - b
    def __or__(self, other: "Solid") -> "Solid":
        return Union(self, other)

    def __and__(self, other: "Solid") -> "Solid":
        return Intersection(self, other)

    def __sub__(self, other: "Solid") -> "Solid":
        return Difference(self, other)


# -- primitives ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Ellipsoid(Solid):
    """Axis-aligned ellipsoid centred at the origin; a sphere when the radii are equal."""

    radii: tuple[float, float, float]
    """Semi-axes along local x, y, z."""

    def crossings(self, o, d):
        r = np.asarray(self.radii, dtype=np.float64)
        os_, ds = o / r, d / r  # unit-sphere space; t is unchanged by the scaling
        a = np.einsum("ij,ij->i", ds, ds)
        b = 2.0 * np.einsum("ij,ij->i", os_, ds)
        c = np.einsum("ij,ij->i", os_, os_) - 1.0
        out = []
        for t in _quadratic_roots(a, b, c):
            p = _points(o, d, t)
            out.append(Crossing(t, _normalise(p / (r * r))))
        return out

    def contains(self, p):
        r = np.asarray(self.radii, dtype=np.float64)
        return np.einsum("ij,ij->i", p / r, p / r) <= 1.0

    def bounding_sphere(self):
        return np.zeros(3), float(max(self.radii))


def Sphere(radius: float) -> Ellipsoid:
    """A sphere of ``radius`` at the origin."""
    return Ellipsoid((radius, radius, radius))


@dataclass(frozen=True)
class Box(Solid):
    """Axis-aligned box centred at the origin."""

    half_extents: tuple[float, float, float]
    """Half sizes along local x, y, z."""

    def crossings(self, o, d):
        h = np.asarray(self.half_extents, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            ta = (-h - o) * inv
            tb = (h - o) * inv
        # A ray parallel to a slab: inside it -> no constraint, outside -> empty.
        parallel = np.abs(d) < _PARALLEL_EPS
        inside_slab = np.abs(o) <= h
        lo = np.where(parallel, np.where(inside_slab, -INF, INF), np.minimum(ta, tb))
        hi = np.where(parallel, np.where(inside_slab, INF, -INF), np.maximum(ta, tb))
        ax_in = np.argmax(lo, axis=1)
        ax_out = np.argmin(hi, axis=1)
        rows = np.arange(len(o))
        t_in = lo[rows, ax_in]
        t_out = hi[rows, ax_out]
        hit = (t_in <= t_out) & np.isfinite(t_in) & np.isfinite(t_out)
        n_in = np.zeros_like(o)
        n_in[rows, ax_in] = -np.sign(d[rows, ax_in])
        n_out = np.zeros_like(o)
        n_out[rows, ax_out] = np.sign(d[rows, ax_out])
        return [Crossing(np.where(hit, t_in, INF), n_in), Crossing(np.where(hit, t_out, INF), n_out)]

    def contains(self, p):
        return np.all(np.abs(p) <= np.asarray(self.half_extents), axis=1)

    def bounding_sphere(self):
        return np.zeros(3), float(np.linalg.norm(self.half_extents))


@dataclass(frozen=True)
class Frustum(Solid):
    """Solid of revolution about local z between ``z0`` and ``z1`` whose radius varies linearly.

    Equal radii give a capped cylinder; a zero radius gives a cone with its apex on that cap.
    """

    r0: float
    """Radius at ``z0``."""
    r1: float
    """Radius at ``z1``."""
    z0: float
    """Bottom cap height."""
    z1: float
    """Top cap height (> ``z0``)."""

    def _radius_line(self) -> tuple[float, float]:
        slope = (self.r1 - self.r0) / (self.z1 - self.z0)
        return self.r0 - slope * self.z0, slope  # r(z) = k + s z

    def crossings(self, o, d):
        k, s = self._radius_line()
        kz_o = k + s * o[:, 2]
        a = d[:, 0] ** 2 + d[:, 1] ** 2 - (s * d[:, 2]) ** 2
        b = 2.0 * (o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1] - s * d[:, 2] * kz_o)
        c = o[:, 0] ** 2 + o[:, 1] ** 2 - kz_o ** 2
        out = []
        for t in _quadratic_roots(a, b, c):
            p = _points(o, d, t)
            on_side = (p[:, 2] >= self.z0) & (p[:, 2] <= self.z1) & (k + s * p[:, 2] >= 0.0)
            n = np.stack([p[:, 0], p[:, 1], -s * (k + s * p[:, 2])], axis=1)
            out.append(Crossing(np.where(on_side, t, INF), _normalise(n)))
        for z, r, sign in ((self.z0, self.r0, -1.0), (self.z1, self.r1, 1.0)):
            if r <= 0.0:
                continue
            t = _plane_t(o[:, 2], d[:, 2], z)
            p = _points(o, d, t)
            on_cap = p[:, 0] ** 2 + p[:, 1] ** 2 <= r * r
            n = np.zeros_like(o)
            n[:, 2] = sign
            out.append(Crossing(np.where(on_cap, t, INF), n))
        return out

    def contains(self, p):
        k, s = self._radius_line()
        r = k + s * p[:, 2]
        return (p[:, 2] >= self.z0) & (p[:, 2] <= self.z1) & (p[:, 0] ** 2 + p[:, 1] ** 2 <= r * np.abs(r))

    def bounding_sphere(self):
        zc = 0.5 * (self.z0 + self.z1)
        half = 0.5 * (self.z1 - self.z0)
        return np.array([0.0, 0.0, zc]), float(np.hypot(half, max(self.r0, self.r1)))


def Cylinder(radius: float, z0: float, z1: float) -> Frustum:
    """Capped cylinder about local z from ``z0`` to ``z1``."""
    return Frustum(radius, radius, z0, z1)


@dataclass(frozen=True)
class HalfSpace(Solid):
    """The points ``p`` with ``normal . p <= offset`` (unbounded; use it to cut other solids)."""

    normal: tuple[float, float, float]
    """Outward normal (need not be unit length; it is normalised)."""
    offset: float = 0.0
    """Signed distance of the plane from the origin along the unit normal."""

    def _unit(self) -> np.ndarray:
        n = np.asarray(self.normal, dtype=np.float64)
        return n / np.linalg.norm(n)

    def crossings(self, o, d):
        n = self._unit()
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.offset - o @ n) / denom
        t = np.where(np.abs(denom) > _PARALLEL_EPS, t, INF)
        return [Crossing(t, np.broadcast_to(n, o.shape))]

    def contains(self, p):
        return p @ self._unit() <= self.offset

    def bounding_sphere(self):
        return np.zeros(3), INF


# -- boolean combinations -----------------------------------------------------------------------
def _filter(o, d, crossings: list[Crossing], keep_fn, flip: bool = False) -> list[Crossing]:
    out = []
    for c in crossings:
        keep = keep_fn(_points(o, d, c.t)) & np.isfinite(c.t)
        out.append(Crossing(np.where(keep, c.t, INF), -c.normal if flip else c.normal))
    return out


@dataclass(frozen=True)
class Union(Solid):
    a: Solid
    b: Solid

    def crossings(self, o, d):
        return (_filter(o, d, self.a.crossings(o, d), lambda p: ~self.b.contains(p))
                + _filter(o, d, self.b.crossings(o, d), lambda p: ~self.a.contains(p)))

    def contains(self, p):
        return self.a.contains(p) | self.b.contains(p)

    def bounding_sphere(self):
        (ca, ra), (cb, rb) = self.a.bounding_sphere(), self.b.bounding_sphere()
        if not (np.isfinite(ra) and np.isfinite(rb)):
            return np.zeros(3), INF
        dist = float(np.linalg.norm(cb - ca))
        if dist + rb <= ra:
            return ca, ra
        if dist + ra <= rb:
            return cb, rb
        r = 0.5 * (dist + ra + rb)
        return ca + (cb - ca) * ((r - ra) / dist), r


@dataclass(frozen=True)
class Intersection(Solid):
    a: Solid
    b: Solid

    def crossings(self, o, d):
        return (_filter(o, d, self.a.crossings(o, d), self.b.contains)
                + _filter(o, d, self.b.crossings(o, d), self.a.contains))

    def contains(self, p):
        return self.a.contains(p) & self.b.contains(p)

    def bounding_sphere(self):
        (ca, ra), (cb, rb) = self.a.bounding_sphere(), self.b.bounding_sphere()
        return (ca, ra) if ra <= rb else (cb, rb)


@dataclass(frozen=True)
class Difference(Solid):
    """``a`` with ``b`` carved out."""

    a: Solid
    b: Solid

    def crossings(self, o, d):
        return (_filter(o, d, self.a.crossings(o, d), lambda p: ~self.b.contains(p))
                + _filter(o, d, self.b.crossings(o, d), self.a.contains, flip=True))

    def contains(self, p):
        return self.a.contains(p) & ~self.b.contains(p)

    def bounding_sphere(self):
        return self.a.bounding_sphere()


@dataclass(frozen=True)
class Moved(Solid):
    """``solid`` placed by a rigid transform (for building compound shapes in one local frame)."""

    solid: Solid
    rotation: np.ndarray
    """(3, 3) rotation taking the solid's frame to this frame."""
    translation: np.ndarray
    """(3,) position of the solid's origin in this frame."""

    def _to_solid(self, p: np.ndarray) -> np.ndarray:
        return (p - self.translation) @ self.rotation  # R^T (p - t) for row vectors

    def crossings(self, o, d):
        out = self.solid.crossings(self._to_solid(o), d @ self.rotation)
        return [Crossing(c.t, c.normal @ self.rotation.T) for c in out]

    def contains(self, p):
        return self.solid.contains(self._to_solid(p))

    def bounding_sphere(self):
        c, r = self.solid.bounding_sphere()
        return self.rotation @ c + self.translation, r

    def __hash__(self) -> int:  # numpy fields are unhashable; identity is enough here
        return id(self)

    def __eq__(self, other) -> bool:
        return self is other


def nearest(crossings: Sequence[Crossing], t_min: float) -> tuple[np.ndarray, np.ndarray]:
    """Nearest crossing beyond ``t_min`` per ray: ((N,) t with inf = miss, (N, 3) normal)."""
    ts = np.stack([c.t for c in crossings])  # (K, N)
    ts = np.where(ts > t_min, ts, INF)
    k = np.argmin(ts, axis=0)
    rows = np.arange(ts.shape[1])
    normals = np.stack([np.broadcast_to(c.normal, (ts.shape[1], 3)) for c in crossings])  # (K, N, 3)
    return ts[k, rows], normals[k, rows]


def ray_sphere_hits(o: np.ndarray, d: np.ndarray, center: np.ndarray, radius: float, t_min: float) -> np.ndarray:
    """(N,) bool: the ray meets the sphere somewhere beyond ``t_min`` (used to cull rays cheaply).

    ``o`` is (N, 3), or (3,) when every ray starts at one point (a pinhole camera: much cheaper).
    """
    if not np.isfinite(radius):
        return np.ones(len(d), dtype=bool)
    oc = o - center
    if oc.ndim == 1:
        b = d @ oc
        c = float(oc @ oc) - radius * radius
    else:
        b = np.einsum("ij,ij->i", oc, d)
        c = np.einsum("ij,ij->i", oc, oc) - radius * radius
    disc = b * b - c  # d is unit length
    far = -b + np.sqrt(np.maximum(disc, 0.0))
    return (disc >= 0.0) & (far > t_min)
