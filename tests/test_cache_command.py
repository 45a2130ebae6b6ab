"""``bench4d cache``: the report, and pruning leftovers and unreferenced fits without touching the rest."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from benchmark.cli import main

OLD = time.time() - 48 * 3600


def _file(path: Path, data: bytes = b"x" * 1000, old: bool = True) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    if old:
        os.utime(path, (OLD, OLD))
    return path


def _cache(tmp_path: Path) -> tuple[Path, Path]:
    cache, results = tmp_path / "cache", tmp_path / "results"
    _file(cache / "scenes" / "128px" / "smoke" / "rgb.png")
    _file(cache / "captions" / "hypernerf-smoke" / "qwen2-vl-abc.json")
    _file(cache / "supervision" / "hypernerf" / "smoke" / "gt.npz")
    for key in ("fitused", "fitunused"):
        _file(cache / "fits" / "4d-langsplat" / "hypernerf-smoke" / key / "fit.json", b"{}")
        _file(cache / "fits" / "4d-langsplat" / "hypernerf-smoke" / key / "model" / "m.pt")
    lang = cache / "language" / "hypernerf-smoke"
    for name in ("geometry-4dgs-aaa1.pt", "field-4dgs-bbb2.pt", "geometry-3dgs-ccc3.pt", "field-3dgs-ddd4.pt"):
        _file(lang / name)
    _file(lang / "geometry-4dgs-eee5.partial.pt")  # an interrupted geometry fit, two days old
    _file(lang / "geometry-4dgs-fff6.partial.pt", old=False)  # a fit running now
    _file(cache / "fits" / "4d-langsplat" / "hypernerf-smoke" / "fitgone.work" / "tmp.pt")
    # a generator killed while it wrote a scene, and a stress scene killed while it was checked
    _file(cache / "scenes" / "128px" / ".smoke.staging-abc" / "rgb.png")
    _file(cache / "stress" / "smoke-48px-16f" / "scenes" / ".smoke-occluder-0.2.check-123" / "rgb.png")
    doc = {"method": "4d-langsplat", "fit": {"key": "fitused", "info": {"key": "bbb2", "geometry": {"key": "aaa1"}}}}
    _file(results / "synthetic" / "smoke" / "4d-langsplat" / "oracle" / "seed0.json", json.dumps(doc).encode())
    # an archived run still names its fit
    archived = {"fit": {"key": "x", "info": {"key": "ddd4", "geometry": {"key": "ccc3"}}}}
    _file(results / "archive" / "replaced-1" / "synthetic" / "smoke" / "langsplat" / "oracle" / "seed0.json",
          json.dumps(archived).encode())
    return cache, results


def _tree(root: Path) -> set[str]:
    return {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()}


def test_report_lists_kinds_and_leftovers(tmp_path, capsys):
    cache, _ = _cache(tmp_path)
    assert main(["cache", "--cache-dir", str(cache)]) == 0
    out = capsys.readouterr().out
    for kind in ("scenes", "captions", "fits", "language/geometry", "language/field", "supervision", "leftovers"):
        assert kind in out
    assert "language/other" not in out  # a geometry checkpoint is a leftover, not a model
    assert "geometry-4dgs-eee5.partial.pt" in out and "fitgone.work" in out and "fff6" in out


def test_prune_leftovers_deletes_only_old_leftovers(tmp_path):
    cache, _ = _cache(tmp_path)
    before = _tree(cache)
    assert main(["cache", "--cache-dir", str(cache), "--prune", "leftovers", "--dry-run"]) == 0
    assert _tree(cache) == before
    assert main(["cache", "--cache-dir", str(cache), "--prune", "leftovers"]) == 0
    gone = before - _tree(cache)
    assert gone == {"language/hypernerf-smoke/geometry-4dgs-eee5.partial.pt",
                    "fits/4d-langsplat/hypernerf-smoke/fitgone.work/tmp.pt",
                    "scenes/128px/.smoke.staging-abc/rgb.png",
                    "stress/smoke-48px-16f/scenes/.smoke-occluder-0.2.check-123/rgb.png"}
    assert not (cache / "fits" / "4d-langsplat" / "hypernerf-smoke" / "fitgone.work").exists()


def test_prune_unreferenced_keeps_every_fit_a_results_file_names(tmp_path, capsys):
    cache, results = _cache(tmp_path)
    before = _tree(cache)
    assert main(["cache", "--cache-dir", str(cache), "--results-dir", str(results), "--prune", "unreferenced"]) == 0
    gone = before - _tree(cache)
    assert gone == {"fits/4d-langsplat/hypernerf-smoke/fitunused/fit.json",
                    "fits/4d-langsplat/hypernerf-smoke/fitunused/model/m.pt"}
    # the same with the archived run gone: its 3D-GS geometry and field go too; presets, supervision,
    # captions and leftovers never do
    for p in (results / "archive").rglob("seed0.json"):
        p.unlink()
    assert main(["cache", "--cache-dir", str(cache), "--results-dir", str(results), "--prune", "unreferenced"]) == 0
    left = _tree(cache)
    assert "language/hypernerf-smoke/geometry-3dgs-ccc3.pt" not in left and "language/hypernerf-smoke/field-3dgs-ddd4.pt" not in left
    assert {"scenes/128px/smoke/rgb.png", "captions/hypernerf-smoke/qwen2-vl-abc.json",
            "supervision/hypernerf/smoke/gt.npz", "language/hypernerf-smoke/geometry-4dgs-aaa1.pt",
            "language/hypernerf-smoke/field-4dgs-bbb2.pt", "language/hypernerf-smoke/geometry-4dgs-eee5.partial.pt",
            "fits/4d-langsplat/hypernerf-smoke/fitused/fit.json"} <= left


def test_prune_refuses_on_unreadable_results_or_a_missing_folder(tmp_path, capsys):
    cache, results = _cache(tmp_path)
    before = _tree(cache)
    bad = _file(results / "synthetic" / "x" / "m" / "oracle" / "seed1.json", b"{not json")
    assert main(["cache", "--cache-dir", str(cache), "--results-dir", str(results), "--prune", "unreferenced"]) == 2
    assert str(bad) in capsys.readouterr().err and _tree(cache) == before
    assert main(["cache", "--cache-dir", str(cache), "--results-dir", str(tmp_path / "nope"),
                 "--prune", "unreferenced"]) == 2
    assert "no such results folder" in capsys.readouterr().err and _tree(cache) == before
    assert main(["cache", "--cache-dir", str(tmp_path / "nocache")]) == 2
