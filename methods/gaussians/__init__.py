"""Gaussian core: rasterizer, 3D-GS / 4D-GS models and their trainer.

Rasterizer entry point: :func:`methods.gaussians.rasterize.rasterize` (re-exported here with
:class:`RenderOutput` and :func:`camera_tensors`); spherical harmonics in :mod:`.sh`.
"""

from .rasterize import RenderOutput, camera_tensors, rasterize

__all__ = ["RenderOutput", "camera_tensors", "rasterize"]
