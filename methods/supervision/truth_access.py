"""Shared by the oracle sources: open a generated scene's truth, training frames only."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

EVAL_TRUTH_MESSAGE = "ground truth of evaluated frames is for scoring"


class EvaluatedFrameTruthError(PermissionError):
    """An oracle source was asked for the truth of a frame that is not a training frame."""


def open_truth(scene: Scene):
    """The :class:`benchmark.core.truth.SceneTruth` of ``scene`` (InputError if it has none)."""
    from benchmark.core.truth import has_truth, load_truth

    root = None if scene.root is None else Path(scene.root)
    if not has_truth(root):
        raise InputError(root, "truth", f"scene {scene.name!r} has no generator truth: the oracle track runs on "
                                        "generated (synthetic) scenes only; use --track real for other scenes")
    return load_truth(root)


def training_id_maps(truth, frame: Frame) -> np.ndarray:
    """(3, H, W) int32 truth ids of a TRAINING frame (small, middle, large), -1 = none, resized
    (nearest) to the frame's camera size. Any other frame raises :class:`EvaluatedFrameTruthError`."""
    if frame.split != "train":
        raise EvaluatedFrameTruthError(f"frame {frame.name!r} is a {frame.split} frame: {EVAL_TRUTH_MESSAGE}")
    ids = truth.id_maps(frame).astype(np.int32)  # the truth's own guard also refuses non-training frames
    ids[ids == 0] = -1  # 0 = background / surroundings: in no mask
    h, w = frame.camera.height, frame.camera.width
    if ids.shape[1:] != (h, w):
        rows = np.minimum(((np.arange(h) + 0.5) * ids.shape[1] / h).astype(int), ids.shape[1] - 1)
        cols = np.minimum(((np.arange(w) + 0.5) * ids.shape[2] / w).astype(int), ids.shape[2] - 1)
        ids = ids[:, rows[:, None], cols[None, :]]
    return ids
