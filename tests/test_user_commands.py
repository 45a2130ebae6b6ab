"""Commands as a user meets them: `doctor` per track, `data presets` / `make-synthetic` / `show` wording and
where they write, the demo's dataset line."""

from __future__ import annotations

import os

import pytest

from benchmark.cli import main

SMALL_SCENE = ["--width", "96", "--height", "64", "--frames", "10"]


def _doctor(monkeypatch, capsys, tmp_path, *, present_modules, present_weights, track="real") -> list[str]:
    import methods.backends as backends
    from benchmark.commands import doctor

    monkeypatch.setattr(backends, "module_available", lambda name: name in present_modules)
    monkeypatch.setattr(backends, "locate", lambda b: backends.Located(b, None, b.name in present_weights, "test"))
    monkeypatch.setattr(doctor, "available_memory_gb", lambda: 1000.0)
    assert main(["doctor", "--cache-dir", str(tmp_path / "cache"), "--track", track, *SMALL_SCENE]) == 0
    return capsys.readouterr().out.splitlines()


def test_doctor_says_per_track_what_is_ready_and_what_is_missing(tmp_path, monkeypatch, capsys):
    from methods.backends import BACKENDS

    # nothing of the real track here, no CUDA, no gsplat: the oracle track is still ready
    out = _doctor(monkeypatch, capsys, tmp_path, present_modules=set(), present_weights=set())
    assert out[-2] == "oracle track: ready"
    required = [b for b in BACKENDS if b.name != "sam-checkpoint"]  # the default SAM is the transformers one
    modules = sorted({b.module for b in required})
    assert out[-1].startswith(f"real track: {len(required) + len(modules)} missing (")
    assert "weights sam-checkpoint" not in out[-1] and "gsplat" not in out[-1] and "CUDA" not in out[-1]
    # everything the real track needs
    out = _doctor(monkeypatch, capsys, tmp_path, present_modules=set(modules),
                  present_weights={b.name for b in required})
    assert out[-2:] == ["oracle track: ready", "real track: ready"]
    # the weights are looked for only on request: the real track is then never called ready
    out = _doctor(monkeypatch, capsys, tmp_path, present_modules=set(modules), present_weights=set(), track="oracle")
    assert out[-2:] == ["oracle track: ready", "real track: weights not checked (bench4d doctor --track real)"]


def test_doctor_counts_a_shortage_of_memory_against_both_tracks(tmp_path, monkeypatch, capsys):
    from benchmark.commands import doctor

    monkeypatch.setattr(doctor, "available_memory_gb", lambda: 0.01)
    assert main(["doctor", "--cache-dir", str(tmp_path / "cache"), "--track", "oracle", *SMALL_SCENE]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[-2] == "oracle track: 1 missing (memory)"


def test_presets_list_each_default_frame_size_in_one_pair_of_brackets(capsys):
    from benchmark.synthetic import PRESETS

    assert main(["data", "presets"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == len(PRESETS)
    assert not any("((" in line or "))" in line for line in lines)
    smoke = next(line for line in lines if line.startswith("smoke "))
    assert " 48x64 " in smoke and "(tests)" in smoke


def test_make_synthetic_help_states_each_default_size_and_the_made_scene_has_it(tmp_path, capsys):
    from benchmark.commands.data import default_frame_size
    from benchmark.loaders import load_scene
    from benchmark.synthetic import PRESETS

    with pytest.raises(SystemExit):
        main(["data", "make-synthetic", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "the preset's: 128, smoke 48" in help_text
    assert default_frame_size(PRESETS["smoke"]) == (48, 64)
    assert main(["data", "make-synthetic", "smoke", "--out", str(tmp_path / "smoke")]) == 0
    camera = load_scene(tmp_path / "smoke").frames[0].camera
    assert (camera.width, camera.height) == (48, 64)
    # onto the folder again: the command's own words
    capsys.readouterr()
    assert main(["data", "make-synthetic", "smoke", "--out", str(tmp_path / "smoke")]) == 2
    err = capsys.readouterr().err
    assert "--overwrite" in err and "overwrite=True" not in err


def test_data_show_writes_beside_the_scene_not_into_the_current_folder(tmp_path, monkeypatch, capsys):
    from benchmark.synthetic import generate

    scene = generate("smoke", tmp_path / "scenes" / "nc-smoke", size=32, frames=6)
    work = tmp_path / "checkout"
    work.mkdir()
    monkeypatch.chdir(work)
    assert main(["data", "show", str(scene), "--frames", "1"]) == 0
    assert os.listdir(work) == []
    sheet = tmp_path / "scenes" / "nc-smoke_sheet.png"
    assert sheet.is_file() and f"wrote {sheet}" in capsys.readouterr().out
    assert main(["data", "show", str(scene), "--frames", "1", "--out", str(tmp_path / "elsewhere.png")]) == 0
    assert (tmp_path / "elsewhere.png").is_file()


def test_the_run_log_names_a_generated_scene_under_the_dataset_its_results_go_to(tmp_path):
    from benchmark.loaders import load_scene
    from benchmark.runner import scene_line
    from benchmark.synthetic import generate

    scene = load_scene(generate("smoke", tmp_path / "nc-smoke", size=32, frames=6))
    line = scene_line(scene)
    assert line.startswith("synthetic/nc-smoke (hypernerf layout): ") and "hypernerf/" not in line
    assert line.partition(": ")[2] == scene.summary().partition(": ")[2]
