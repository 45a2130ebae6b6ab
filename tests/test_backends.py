"""``bench4d models`` and ``bench4d doctor``: where the real track's weights are looked for, and what a
machine lacks before a long run."""

from __future__ import annotations

import json

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
    assert all(line.startswith(("[ok] ", "[--] ")) for line in out[:-1])
    assert sum(line.startswith("[--] weights") for line in out) == len(BACKENDS)
    assert any(line.startswith("[ok] disk:") for line in out)
    assert out[-1].endswith("thing(s) missing")
