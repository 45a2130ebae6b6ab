"""2D supervision: segmenters, image-text encoders, and the cached bundle methods fit on.

* :mod:`.base`: the interfaces and :class:`Supervision` / :class:`FrameSupervision`.
* :mod:`.registry`: sources by name and track (spec files in :mod:`.specs`).
* :mod:`.cache`: :func:`build_supervision` (on-disk npz cache per scene, source and config).
* Oracle track sources: :mod:`.gt` (segmenter), :mod:`.oracle_text` (image-text).
"""

from .base import LEVELS, FrameSupervision, ImageTextEncoder, Segmenter, Supervision, TextEncoder, relabel_levels

__all__ = ["LEVELS", "FrameSupervision", "ImageTextEncoder", "Segmenter", "Supervision", "TextEncoder",
           "relabel_levels"]
