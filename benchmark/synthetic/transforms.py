"""Rigid transforms (4x4, local -> parent) and small easing helpers for motion schedules."""

from __future__ import annotations

from typing import Sequence

import numpy as np

WORLD_UP = np.array([0.0, 0.0, 1.0])
"""The synthetic world is z-up with the floor at z = 0."""


def identity() -> np.ndarray:
    return np.eye(4)


def translation(v: Sequence[float]) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = np.asarray(v, dtype=np.float64)
    return m


def rotation(axis: Sequence[float], angle: float) -> np.ndarray:
    """4x4 rotation by ``angle`` radians about ``axis`` through the origin (right-hand rule)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)
    return m


def about(pivot: Sequence[float], transform: np.ndarray) -> np.ndarray:
    """``transform`` applied about ``pivot`` instead of the origin (a hinge)."""
    return translation(pivot) @ transform @ translation(-np.asarray(pivot, dtype=np.float64))


def compose(*transforms: np.ndarray) -> np.ndarray:
    """Left-to-right product: ``compose(A, B)`` applies B first, then A."""
    out = np.eye(4)
    for m in transforms:
        out = out @ m
    return out


def look_at_opencv(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = WORLD_UP) -> np.ndarray:
    """4x4 world-to-camera matrix (OpenCV axes: x right, y down, z forward) looking from ``eye`` at ``target``."""
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to the up vector")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rot = np.stack([right, down, forward])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ eye
    return w2c


def spherical(center: Sequence[float], radius: float, azimuth: float, elevation: float) -> np.ndarray:
    """(3,) point at ``radius`` from ``center``; azimuth about +z from +x, elevation above the floor plane."""
    c = np.asarray(center, dtype=np.float64)
    return c + radius * np.array([np.cos(elevation) * np.cos(azimuth),
                                  np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])


def smoothstep(x: float | np.ndarray) -> float | np.ndarray:
    """0 below 0, 1 above 1, cubic ease in between (zero slope at both ends)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)
