"""``bench4d ablate real-cost``: the real backends' architectures, their units of work, and the projection."""

from __future__ import annotations

import json

import pytest

from benchmark.core.errors import InputError
from benchmark.studies import real_cost
from benchmark.studies.real_cost import PAPER_SCENES, RealCostConfig, project

PUBLISHED_PARAMETERS = {"sam": 641e6, "clip": 86e6, "qwen2vl": 8.29e9, "e5": 7.11e9}
"""SAM ViT-H (2.56 GB of float32 weights), CLIP ViT-B/16's image tower, Qwen2-VL-7B, e5-mistral-7b-instruct."""


@pytest.mark.parametrize("backend", sorted(PUBLISHED_PARAMETERS))
def test_the_full_architectures_have_the_published_sizes(backend):
    import torch

    with torch.device("meta"):  # shapes only: no memory, no time
        model = real_cost.model_classes()[backend](real_cost._configs("full")[backend])
    count = sum(p.numel() for p in model.parameters())
    assert count == pytest.approx(PUBLISHED_PARAMETERS[backend], rel=0.02)


def test_build_makes_the_model_in_its_run_dtype_and_restores_the_default(monkeypatch):
    import torch

    seen = []
    real_classes = real_cost.model_classes

    def recording_classes():
        classes = dict(real_classes())
        original = classes["clip"]

        def make(config):
            seen.append(torch.get_default_dtype())  # the dtype the weights are created in
            return original(config)
        classes["clip"] = make
        return classes

    monkeypatch.setattr(real_cost, "model_classes", recording_classes)
    before = torch.get_default_dtype()
    model = real_cost.build("clip", "tiny", "cpu", dtype=torch.bfloat16)  # as on CUDA
    assert seen == [torch.bfloat16] and {p.dtype for p in model.parameters()} == {torch.bfloat16}
    assert torch.get_default_dtype() == before
    assert {p.dtype for p in real_cost.build("clip", "tiny", "cpu").parameters()} == {torch.float32}
    assert seen[-1] == torch.float32
    row = real_cost._measure_backend("clip", RealCostConfig(size="tiny", repeats=1, crops_per_batch=2), 56, 84)
    assert row["weights_gpu_gib"] is None and row["peak_gpu_gib"] is None and row["crop_seconds"] > 0


def _units(sam=2.0, crop=0.01, video=30.0, frame=12.0, text=0.05):
    return {"sam": {"frame_seconds": sam}, "clip": {"crop_seconds": crop},
            "qwen2vl": {"video_request_seconds": video, "frame_request_seconds": frame}, "e5": {"text_seconds": text}}


def test_the_projection_counts_each_stage_and_captions_only_time_sensitive_scenes():
    cfg = RealCostConfig(masks_per_frame=100, objects=2, hypernerf_frames=10)
    rows = {r["scene"]: r for r in project(_units(), cfg)}
    assert len(rows) == 12
    cookie = rows["split-cookie"]
    assert cookie["frames"] == 10 and cookie["captions"] == 2 * 11
    assert cookie["sam_seconds"] == pytest.approx(10 * 2.0) and cookie["clip_seconds"] == pytest.approx(10 * 100 * 0.01)
    assert cookie["qwen2vl_seconds"] == pytest.approx(2 * (30.0 + 10 * 12.0))
    assert cookie["e5_seconds"] == pytest.approx(22 * 0.05)
    assert cookie["total_seconds"] == pytest.approx(20 + 10 + 300 + 1.1)
    keyboard, salmon = rows["keyboard"], rows["flame_salmon"]  # time-agnostic only: no captions
    assert keyboard["captions"] == salmon["captions"] == 0 and keyboard["qwen2vl_seconds"] == 0.0
    assert salmon["frames"] == 20 * 300 and salmon["sam_seconds"] == pytest.approx(6000 * 2.0)
    assert sum(s.time_sensitive for s in PAPER_SCENES) == 4


def test_bad_settings_are_refused_by_name():
    with pytest.raises(InputError, match="size"):
        RealCostConfig(size="huge")
    with pytest.raises(InputError, match="objects"):
        RealCostConfig(objects=0)


def test_the_tiny_run_times_every_backend_and_writes_its_report(tmp_path):
    from benchmark.cli import main

    assert main(["ablate", "real-cost", "--size", "tiny", "--repeats", "1", "--points-per-side", "2",
                 "--caption-tokens", "2", "--out", str(tmp_path), "--quiet"]) == 0
    raw = (tmp_path / "real-cost-tiny-cpu.json").read_text()
    doc = json.loads(raw)
    # a study record: one value a line, unindented (half the size of an indented one)
    assert len(raw.splitlines()) > 50 and not [line for line in raw.splitlines() if line.startswith(" ")]
    units = doc["units"]
    assert units["sam"]["frame_seconds"] > 0 and units["clip"]["crop_seconds"] > 0 and units["e5"]["text_seconds"] > 0
    qwen = units["qwen2vl"]
    # a video request reads 8 images, a frame request 3: more input tokens, more vision work
    assert qwen["video_input_tokens"] > qwen["frame_input_tokens"] and qwen["frame_request_seconds"] > 0
    assert len(doc["projection"]) == 12 and doc["config"]["size"] == "tiny" and "git" in doc
    text = (tmp_path / "real-cost-tiny-cpu.md").read_text()
    assert "| Qwen2-VL-7B |" in text and "All 12 scenes:" in text and "test size" in text
