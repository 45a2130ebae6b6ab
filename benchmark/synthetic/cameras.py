"""Camera setups: a smooth handheld-like arc (monocular), a fixed rig on an arc (multi-view),
and one random viewpoint per frame on a hemisphere (D-NeRF style).

Every camera keeps the scene's focus sphere inside its view: the distance is chosen from the
narrower field of view so that the sphere fits with :attr:`CameraSetup.margin` to spare.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from benchmark.core.scene import Camera
from .transforms import look_at_opencv, spherical


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics relative to the image size (so they hold at any resolution)."""

    fov_x_deg: float
    """Horizontal field of view in degrees."""
    height_over_width: float = 1.0
    """Image aspect: height = round(width * this), made even."""
    principal_offset: tuple[float, float] = (0.0, 0.0)
    """Principal point offset from the image centre, as fractions of (width, height)."""
    pixel_aspect_ratio: float = 1.0
    """fy / fx (Nerfies ``pixel_aspect_ratio``)."""

    def image_size(self, width: int) -> tuple[int, int]:
        """(width, height); both even so a half-resolution copy has exact integer size."""
        if width < 8 or width % 2:
            raise ValueError(f"image width must be an even number >= 8, got {width}")
        height = 2 * int(round(width * self.height_over_width / 2))
        return width, height

    def camera(self, width: int, world_to_camera: np.ndarray) -> Camera:
        w, h = self.image_size(width)
        fx = 0.5 * w / np.tan(np.radians(self.fov_x_deg) / 2)
        return Camera(w, h, fx, fx * self.pixel_aspect_ratio,
                      w / 2 + self.principal_offset[0] * w, h / 2 + self.principal_offset[1] * h,
                      world_to_camera)


@dataclass(frozen=True)
class CameraSetup:
    """Placement knobs shared by the three setups."""

    intrinsics: Intrinsics
    elevation_deg: float = 35.0
    """Mean camera elevation above the floor plane, seen from the focus point."""
    margin: float = 1.0
    """Distance multiplier over the tightest fit of the focus sphere (> 1 leaves a border)."""
    sweep_deg: float = 55.0
    """Monocular: total azimuth travelled; rig: total azimuth spanned by the cameras."""
    elevation_wobble_deg: float = 5.0
    """Monocular: amplitude of the up-down wobble of a hand-held camera."""
    distance_wobble: float = 0.05
    """Monocular: relative amplitude of the in-out wobble."""
    elevation_range_deg: tuple[float, float] = (18.0, 60.0)
    """Hemisphere: range of random elevations."""


def fit_distance(radius: float, cam: Camera, margin: float) -> float:
    """Distance at which a sphere of ``radius`` fits in the narrower half field of view."""
    half = 0.5 * min(cam.fov_x, cam.fov_y)
    return margin * radius / np.sin(half)


def _probe(setup: CameraSetup, width: int) -> Camera:
    return setup.intrinsics.camera(width, np.eye(4))


@dataclass(frozen=True)
class MonocularPath:
    """A hand-held camera's arc around the focus, drawn once from the scene's random stream; it gives the
    camera of any frame, and of the same path turned about the focus (a second, novel-view path)."""

    setup: CameraSetup
    center: tuple[float, float, float]
    radius: float
    num_frames: int
    width: int
    distance: float
    """Mean distance from the focus."""
    azimuth0: float
    """Azimuth (radians) at the middle of the video."""
    phase: tuple[float, float, float]
    """Phases of the elevation, distance and aim wobbles."""
    direction: float
    """+1 or -1: the way the camera travels."""

    def camera(self, i: int, azimuth_offset_deg: float = 0.0, elevation_offset_deg: float = 0.0) -> Camera:
        """Camera of frame ``i``; the offsets turn it about the focus (azimuth in the direction of travel)."""
        setup, u = self.setup, i / max(1, self.num_frames - 1)
        az = self.azimuth0 + self.direction * (np.radians(setup.sweep_deg) * (u - 0.5)
                                               + np.radians(azimuth_offset_deg))
        el = np.radians(setup.elevation_deg + elevation_offset_deg
                        + setup.elevation_wobble_deg * np.sin(2 * np.pi * 1.3 * u + self.phase[0]))
        d = self.distance * (1 + setup.distance_wobble * np.sin(2 * np.pi * 0.8 * u + self.phase[1]))
        center = np.asarray(self.center)
        target = center + 0.04 * self.radius * np.array([np.sin(2 * np.pi * u + self.phase[2]),
                                                          np.cos(2 * np.pi * u + self.phase[2]), 0.0])
        eye = spherical(center, d, az, el)
        return setup.intrinsics.camera(self.width, look_at_opencv(eye, target))


def monocular_path(setup: CameraSetup, center, radius: float, num_frames: int, width: int,
                   rng: np.random.Generator) -> MonocularPath:
    """A smooth arc (with hand-held wobble) around the focus, its randomness drawn from ``rng``."""
    dist = fit_distance(radius, _probe(setup, width), setup.margin * (1 + setup.distance_wobble))
    az0 = rng.uniform(-np.pi, np.pi)
    phase = rng.uniform(0, 2 * np.pi, size=3)
    direction = rng.choice([-1.0, 1.0])
    return MonocularPath(setup, tuple(float(v) for v in center), float(radius), int(num_frames), int(width),
                         float(dist), float(az0), tuple(float(v) for v in phase), float(direction))


def monocular(setup: CameraSetup, center, radius: float, num_frames: int, width: int,
              rng: np.random.Generator) -> list[Camera]:
    """One camera per frame moving smoothly along an arc (with hand-held wobble) around the focus."""
    path = monocular_path(setup, center, radius, num_frames, width, rng)
    return [path.camera(i) for i in range(num_frames)]


def rig(setup: CameraSetup, center, radius: float, num_views: int, width: int,
        rng: np.random.Generator) -> list[Camera]:
    """Fixed cameras on an arc facing the focus; index 0 (``cam00``, the test view) is the middle one."""
    dist = fit_distance(radius, _probe(setup, width), setup.margin)
    az0 = rng.uniform(-np.pi, np.pi)
    sweep = np.radians(setup.sweep_deg)
    offsets = np.linspace(-0.5, 0.5, num_views) if num_views > 1 else np.zeros(1)
    order = [num_views // 2] + [k for k in range(num_views) if k != num_views // 2]
    cams = []
    for k in order:
        el = np.radians(setup.elevation_deg + (4.0 if k % 2 else -4.0))
        eye = spherical(center, dist, az0 + sweep * offsets[k], el)
        cams.append(setup.intrinsics.camera(width, look_at_opencv(eye, center)))
    return cams


def hemisphere(setup: CameraSetup, center, radius: float, num_frames: int, width: int,
               rng: np.random.Generator) -> list[Camera]:
    """A random viewpoint on the upper hemisphere for every frame (the D-NeRF capture)."""
    dist = fit_distance(radius, _probe(setup, width), setup.margin)
    lo, hi = np.radians(setup.elevation_range_deg)
    cams = []
    for _ in range(num_frames):
        az = rng.uniform(-np.pi, np.pi)
        el = np.arcsin(rng.uniform(np.sin(lo), np.sin(hi)))  # uniform over the spherical band
        cams.append(setup.intrinsics.camera(width, look_at_opencv(spherical(center, dist, az, el), center)))
    return cams
