"""``bench4d ablate step-profile``: a deformation-stage step's CPU time by part, on a cached 4D-GS geometry."""

from __future__ import annotations

import json

import pytest
import torch

from benchmark.core.errors import InputError
from benchmark.studies.step_profile import PARTS, StepProfileConfig, part_of, split_parts, step_profile_report


def test_every_event_lands_in_one_part_and_the_rest_in_other():
    parts = split_parts({"Composite": 3.0, "CompositeBackward": 2.0, "aten::mm": 4.0, "aten::addmm": 1.0,
                         "aten::threshold_backward": 0.5, "aten::cat": 0.25})
    assert list(parts)[: len(PARTS)] == [p for p, _ in PARTS] and list(parts)[-1] == "other"
    assert parts["compositing (compiled, forward and backward)"] == 5.0
    assert parts["deformation MLP: matrix products (BLAS)"] == 5.0
    assert parts["deformation MLP: ReLU forward and backward"] == 0.5
    assert parts["other"] == 0.25 and sum(parts.values()) == pytest.approx(10.75)
    assert part_of("HexPlaneSampleBackward").startswith("HexPlane") and part_of("aten::sort") == "other"


def _cached_geometry(tmp_path, kind: str):
    from benchmark.runner import resolve_scene
    from benchmark.loaders import load_scene
    from methods.fields.language_field import FrozenGeometry
    from methods.gaussians.config import ReconConfig
    from methods.gaussians.train import Trainer

    scene_dir = resolve_scene("smoke", tmp_path / "cache", size=24, seed=0)
    trainer = Trainer(load_scene(scene_dir), ReconConfig(static_iterations=6, deformation_iterations=6, seed=0))
    fit = trainer.fit_4dgs() if kind == "4dgs" else trainer.fit_3dgs(12)
    path = tmp_path / f"geometry-{kind}.pt"
    torch.save({"key": "k", "geometry": FrozenGeometry(fit.model).state_dict(), "info": "{}"}, path)
    return path


def test_a_tiny_geometry_is_profiled_part_by_part(tmp_path):
    geometry = _cached_geometry(tmp_path, "4dgs")
    config = StepProfileConfig(geometry=geometry, scene="smoke", size=24, steps=2, warmup=1,
                               cache_dir=tmp_path / "cache", out=tmp_path / "out")
    report = step_profile_report(config)
    doc = json.loads((tmp_path / "out" / "step-profile.json").read_text())
    assert doc["gaussians"] > 0 and doc["step_cpu_ms"] > 0
    assert sum(doc["parts"].values()) == pytest.approx(doc["profiled_ms"], rel=1e-6)
    from methods.gaussians.backends import native_cpu

    if native_cpu.kernels() is not None:  # the compiled kernels ran: their parts are measured, not lumped
        assert doc["parts"]["compositing (compiled, forward and backward)"] > 0
        assert doc["parts"]["HexPlane sampling and regularisers (compiled)"] > 0
    else:  # the PyTorch passes: nothing is a compiled kernel's
        assert doc["parts"]["compositing (compiled, forward and backward)"] == 0
    assert "| whole step (profiled) |" in report.table


def test_a_missing_file_or_a_static_geometry_is_named(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        step_profile_report(StepProfileConfig(geometry=tmp_path / "nope.pt", scene="smoke", size=24,
                                              cache_dir=tmp_path / "cache", out=tmp_path / "out"))
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(InputError, match="not a cached geometry"):
        step_profile_report(StepProfileConfig(geometry=bad, scene="smoke", size=24, cache_dir=tmp_path / "cache",
                                              out=tmp_path / "out"))
    static = _cached_geometry(tmp_path, "3dgs")
    with pytest.raises(InputError, match="3D-GS geometry"):
        step_profile_report(StepProfileConfig(geometry=static, scene="smoke", size=24, cache_dir=tmp_path / "cache",
                                              out=tmp_path / "out"))
