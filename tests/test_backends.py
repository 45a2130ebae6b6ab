"""``bench4d models`` and ``bench4d doctor``: where the real track's weights are looked for, and what a
machine lacks before a long run."""

from __future__ import annotations

import json

import pytest

from benchmark.cli import main
from methods.backends import BACKENDS, locate


def _backend(name: str):
    return next(b for b in BACKENDS if b.name == name)


def test_weights_are_found_in_the_hub_cache_or_where_the_environment_says(tmp_path, monkeypatch):
    for backend in BACKENDS:
        monkeypatch.delenv(backend.env, raising=False)
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub"))
    clip = _backend("clip")
    assert not locate(clip).present
    snapshot = tmp_path / "hub" / "models--laion--CLIP-ViT-B-16-laion2B-s34B-b88K" / "snapshots" / "abc123"
    snapshot.mkdir(parents=True)
    (snapshot / "config.json").write_text("{}")
    assert not locate(clip).present  # a config without weights is not a model
    (snapshot / "model.safetensors").write_bytes(b"weights")
    found = locate(clip)
    assert found.present and found.path == snapshot and found.source == "hub cache"

    e5 = _backend("e5-mistral")  # a local folder only: no hub id is looked up
    assert not locate(e5).present and locate(e5).path is None
    folder = tmp_path / "e5"
    folder.mkdir()
    (folder / "model-00001-of-00002.safetensors").write_bytes(b"w")
    monkeypatch.setenv("BENCH4D_E5_MISTRAL", str(folder))
    assert locate(e5).present and locate(e5).source == "$BENCH4D_E5_MISTRAL"


def test_models_lists_every_backend_and_doctor_says_what_is_missing(tmp_path, monkeypatch, capsys):
    for backend in BACKENDS:
        monkeypatch.delenv(backend.env, raising=False)
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "empty-hub"))
    assert main(["models", "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["name"] for r in rows] == [b.name for b in BACKENDS]
    assert not any(r["present"] for r in rows)

    assert main(["doctor", "--cache-dir", str(tmp_path / "cache"), "--width", "96", "--height", "64",
                 "--frames", "10"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert all(line.startswith(("[ok] ", "[--] ")) for line in out[:-2])
    assert sum(line.startswith("[--] weights") for line in out) == len(BACKENDS)
    assert any(line.startswith("[ok] disk:") for line in out)
    assert out[-2].startswith("oracle track: ") and out[-1].startswith("real track: ") and "missing" in out[-1]
    memory = [line for line in out if line[5:].startswith("memory:")]
    assert len(memory) == 1 and "PyTorch rasterizer" in memory[0]  # no gsplat on CUDA here


def test_doctor_counts_the_pytorch_rasterizers_working_set_where_gsplat_cannot_run():
    from benchmark.commands.doctor import GB, TORCH_RASTER_BYTES_PER_PIXEL, scene_needs

    with_gsplat = scene_needs(960, 536, 200)
    without = scene_needs(960, 536, 200, torch_rasterizer=True)
    assert with_gsplat["rasterizer_gb"] == 0 and with_gsplat["disk_gb"] == without["disk_gb"]
    raster = 960 * 536 * TORCH_RASTER_BYTES_PER_PIXEL / GB
    assert without["rasterizer_gb"] == round(raster, 1) and 10 < raster < 25  # a 536x960 view: over 10 GB
    assert without["memory_gb"] == pytest.approx(with_gsplat["memory_gb"] + raster, abs=0.11)
