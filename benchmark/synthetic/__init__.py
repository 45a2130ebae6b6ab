"""Seeded procedural 4D scenes with exact ground truth.

Analytic solids (spheres, ellipsoids, boxes, cylinders, cones, half-spaces and their boolean
combinations) are ray-cast exactly on the CPU with numpy, textured procedurally and Lambert-shaded.
Objects have a three-level part tree (subpart / part / whole), move rigidly, on hinges, or split,
and carry semantic states that change at a chosen time and show in the pixels. Each preset is
written in one of the layouts the loaders read (HyperNeRF, Neu3D, D-NeRF) with exact per-pixel ids
and depth in ``truth/`` and ground-truth annotations in ``annotations.json``.

>>> from benchmark.synthetic import generate, list_presets, load_truth
>>> scene_dir = generate("split-cookie", "/tmp/split-cookie", size=128, seed=0)
>>> truth = load_truth(scene_dir)
>>> truth.levels(truth.training_frames[0])["part"]      # (H, W) uint16 part ids

See :mod:`.truth` for the training-frames-only guard that oracle supervision must respect.
"""

from .generate import GENERATOR_VERSION, generate
from .presets import PRESETS, PresetSpec, list_presets
from benchmark.core.truth import SceneTruth, TruthAccessError, load_truth

DEFAULT_PRESET = "split-cookie"
"""The preset ``bench4d demo`` runs: time-sensitive, clear visual change, quick to render."""

__all__ = ["DEFAULT_PRESET", "GENERATOR_VERSION", "PRESETS", "PresetSpec", "SceneTruth", "TruthAccessError", "generate",
           "list_presets", "load_truth"]
