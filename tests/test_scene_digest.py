"""Scene versions: a generated preset is identified by its content digest; the committed generator
must reproduce the committed digests; the runner never reuses a cached scene of another version; the
leaderboard never mixes versions."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import pytest

from benchmark.leaderboard import render_markdown
from benchmark.results import comparable_runs, find_results, results_path, runs_table, write_results
from benchmark.synthetic.digest import expected_digest, load_digests, scene_digest, scene_version
from benchmark.synthetic.generate import generate


@pytest.fixture(scope="module")
def smoke48(tmp_path_factory) -> Path:
    return Path(generate("smoke", tmp_path_factory.mktemp("digest") / "smoke", size=48))


def test_committed_generator_reproduces_the_committed_digests(tmp_path, smoke48):
    # a generator change that alters a preset must come with `bench4d data digests --write`
    assert scene_digest(smoke48) == expected_digest("smoke", 48)
    americano = generate("americano", tmp_path / "americano", size=128)
    assert scene_digest(americano) == expected_digest("americano", 128)
    # every preset the runner uses has a committed version
    from benchmark.synthetic import PRESETS

    assert set(PRESETS) <= set(load_digests())


def test_digest_ignores_last_bits_and_folder_name_but_not_pixels(tmp_path, smoke48):
    copy = tmp_path / "renamed"
    shutil.copytree(smoke48, copy)
    doc = json.loads((copy / "annotations.json").read_text())
    doc["scene"] = "renamed"
    (copy / "annotations.json").write_text(json.dumps(doc))
    cam = sorted((copy / "camera").glob("*.json"))[0]
    c = json.loads(cam.read_text())
    c["position"] = [v * (1 + 2e-16) + 1e-17 for v in c["position"]]  # another CPU's trigonometry
    cam.write_text(json.dumps(c))
    assert scene_digest(copy) == scene_digest(smoke48)
    c["position"][0] += 1e-6  # a camera that really moved
    cam.write_text(json.dumps(c))
    assert scene_digest(copy) != scene_digest(smoke48)
    shutil.copy(smoke48 / "camera" / cam.name, cam)
    image = sorted((copy / "rgb").rglob("*.png"))[0]
    pixels = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    pixels[0, 0, 0] ^= 1
    cv2.imwrite(str(image), pixels)
    assert scene_digest(copy) != scene_digest(smoke48)
    version = scene_version(copy)
    assert version["preset"] == "smoke" and version["current"] is False
    assert scene_version(smoke48)["current"] is True
    assert scene_version(tmp_path) is None  # not a generated folder


def test_runner_regenerates_a_cached_preset_of_another_version(tmp_path, smoke48):
    from benchmark.runner import resolve_scene

    cache = tmp_path / "cache"
    target = cache / "scenes" / "48px" / "smoke"
    shutil.copytree(smoke48, target)
    image = sorted((target / "rgb").rglob("*.png"))[0]
    pixels = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    pixels[:4, :4] = 0
    cv2.imwrite(str(image), pixels)
    logs: list[str] = []
    out = resolve_scene("smoke", cache, size=48, log=logs.append)
    assert out == target and scene_digest(out) == expected_digest("smoke", 48)
    assert any("not the committed scene version" in m for m in logs)
    logs.clear()
    assert resolve_scene("smoke", cache, size=48, log=logs.append) == target and not logs  # now reused


def _doc(scene: str, miou: float, generated) -> dict:
    return {"method": "m", "dataset": "synthetic", "scene": scene, "track": "oracle", "seed": 0, "splits": ["test"],
            "metrics": {"mIoU": miou, "mAcc": 90.0, "Acc": None, "vIoU": None},
            "timing": {"fit_seconds": 1.0, "query_agnostic": {"fps": 1.0}},
            "memory": {"peak_cpu_mib": 1.0}, "environment": {"device": "cpu", "git": {"commit": "abc", "dirty": False}},
            "scene_info": {"generated": generated}, "scores": {"queries": [], "frames": [], "skipped": []}}


def test_leaderboard_leaves_out_runs_on_another_scene_version(tmp_path):
    root = tmp_path / "results"
    good = {"preset": "smoke", "size": 48, "seed": 0, "digest": expected_digest("smoke", 48)}
    old = dict(good, digest="0" * 24)
    write_results(results_path(root, "synthetic", "smoke", "m", "oracle", 0), _doc("smoke", 40.0, good))
    write_results(results_path(root, "synthetic", "americano", "m", "oracle", 0), _doc("americano", 91.23, None))
    write_results(results_path(root, "synthetic", "chickchicken", "m", "oracle", 0),
                  _doc("chickchicken", 81.23, dict(old, preset="chickchicken", size=128)))
    write_results(results_path(root / "archive" / "x", "synthetic", "smoke", "m", "oracle", 0), _doc("smoke", 1.0, old))
    runs = runs_table(find_results(root), relative_to=root)
    assert len(runs) == 3  # the archive is never read
    kept, stale = comparable_runs(runs)
    assert list(kept["scene"]) == ["smoke"] and sorted(stale["scene"]) == ["americano", "chickchicken"]
    md = render_markdown(runs, "results")
    assert "2 result file(s) left out" in md and "synthetic/americano/m/oracle/seed0.json" in md
    assert "| m | 40.00 |" in md and "91.23" not in md and "81.23" not in md


def test_data_digests_command_compares_with_the_committed_versions(capsys, monkeypatch, tmp_path):
    from benchmark.cli import main
    from benchmark.synthetic import digest

    assert main(["data", "digests", "--presets", "smoke", "--sizes", "48"]) == 0
    assert "same" in capsys.readouterr().out
    # against a manifest that records another version, the command reports the change and fails
    other = tmp_path / "digests.json"
    other.write_text(json.dumps({"presets": {"smoke": {"48px-seed0": "0" * 24}}}))
    monkeypatch.setattr(digest, "DIGESTS_FILE", other)
    assert main(["data", "digests", "--presets", "smoke", "--sizes", "48"]) == 1
    assert "CHANGED" in capsys.readouterr().out
    assert main(["data", "digests", "--presets", "nope"]) == 2
