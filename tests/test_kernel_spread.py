"""``bench4d ablate kernels``: one fit's scores under different torch CPU kernels."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmark.core.errors import InputError
from benchmark.studies import kernel_spread
from benchmark.studies.kernel_spread import (KernelSpreadConfig, check_config, reference_interval, run_env,
                                             setting_means, spread_rows, summarize)

TINY = {"geometry.static_iterations": "6", "geometry.deformation_iterations": "6", "autoencoder.min_steps": "5",
        "autoencoder.max_steps": "5", "field.iterations": "5", "caption_autoencoder.min_steps": "5",
        "caption_autoencoder.max_steps": "5", "status.static_iterations": "3", "status.iterations": "5"}


def _run(scene, seed, cap, miou, acc=None):
    return {"scene": scene, "seed": seed, "capability": cap, "recorded_capability": cap.upper(),
            "machine_kind": "cpu (x)", "scores": {"mIoU": miou, "Acc": acc, "vIoU": None}, "fit_seconds": 1.0,
            "results_file": "f.json"}


def test_spread_is_largest_minus_smallest_per_scene_seed_and_score():
    runs = [_run("a", 0, "default", 50.0), _run("a", 0, "avx2", 47.0), _run("a", 0, "native", 52.5),
            _run("b", 0, "default", 60.0), _run("b", 0, "avx2", 60.0), _run("b", 0, "native", 61.0)]
    rows = {(r["scene"], r["score"]): r for r in spread_rows(runs)}
    assert rows["a", "mIoU"]["spread"] == pytest.approx(5.5)
    assert rows["b", "mIoU"]["spread"] == pytest.approx(1.0)
    assert rows["a", "Acc"]["spread"] is None  # nothing scored it
    means = setting_means(runs, "mIoU")
    assert means == {"avx2": pytest.approx(53.5), "default": pytest.approx(55.0), "native": pytest.approx(56.75)}


def test_the_reference_interval_of_constant_runs_is_a_point_and_a_spread_outside_it_is_said():
    ref = reference_interval({"a": [50.0, 50.0, 50.0], "b": [60.0, 60.0]})
    assert ref["mean"] == pytest.approx(55.0) and ref["low"] == pytest.approx(55.0) and ref["high"] == pytest.approx(55.0)
    wide = reference_interval({"a": [40.0, 60.0, 50.0], "b": [55.0, 65.0, 60.0]})
    assert wide["low"] < 55.0 < wide["high"]
    assert reference_interval({"a": [1.0], "b": []}) is None


def test_a_setting_inside_the_results_folders_interval_is_marked_inside(tmp_path, monkeypatch):
    runs = [_run("a", 0, "default", 50.0), _run("a", 0, "native", 80.0)]
    monkeypatch.setattr(kernel_spread, "leaderboard_values",
                        lambda *a, **k: {"a": [48.0, 52.0, 50.0]} if a[4] == "mIoU" else {})
    config = KernelSpreadConfig(scenes=("a",), capabilities=("default", "native"), results_dir=tmp_path)
    mine = {s["score"]: s for s in summarize(runs, config)}
    assert mine["mIoU"]["inside"] == {"default": True, "native": False}
    assert mine["mIoU"]["spread_of_means"] == pytest.approx(30.0)
    assert mine["Acc"]["reference"] is None and mine["Acc"]["inside"] is None


def test_native_unsets_the_variable_and_the_others_set_it():
    base = {"ATEN_CPU_CAPABILITY": "avx512", "PATH": "/bin"}
    assert "ATEN_CPU_CAPABILITY" not in run_env("native", base)
    assert run_env("default", base)["ATEN_CPU_CAPABILITY"] == "default"
    assert run_env("avx2", base)["OMP_NUM_THREADS"] == "1"


@pytest.mark.parametrize("config", [KernelSpreadConfig(capabilities=("sse9",)), KernelSpreadConfig(scenes=()),
                                    KernelSpreadConfig(capabilities=("avx2", "avx2")),
                                    KernelSpreadConfig(split="nope")])
def test_a_bad_configuration_is_an_input_error_before_any_fit(config):
    with pytest.raises(InputError):
        check_config(config)


def test_two_settings_on_a_tiny_fit_then_resumed_without_refitting(tmp_path, monkeypatch):
    config = KernelSpreadConfig(scenes=("smoke",), seeds=(1,), size=24, capabilities=("default", "native"),
                                overrides=TINY, results_dir=None, cache_dir=tmp_path / "cache",
                                out=tmp_path / "out", name="tiny")
    report = kernel_spread.kernel_spread_report(config, log=lambda m: None)
    kept = sorted(p.name for p in (tmp_path / "out" / "tiny-runs").iterdir())
    assert kept == ["smoke-seed1-default.json", "smoke-seed1-native.json"]
    docs = {n: json.loads((tmp_path / "out" / "tiny-runs" / n).read_text()) for n in kept}
    assert docs["smoke-seed1-default.json"]["environment"]["cpu_capability"] == "DEFAULT"
    assert all(d["scene_seed"] == 1 for d in docs.values())  # seed 1 fits the scene generated with seed 1
    doc = json.loads((tmp_path / "out" / "tiny.json").read_text())
    assert {r["capability"] for r in doc["runs"]} == {"default", "native"}
    assert all(np.isfinite(r["scores"]["mIoU"]) for r in doc["runs"])
    assert "| smoke | 1 | mIoU |" in report.table

    def refit(*args, **kwargs):
        raise AssertionError("a kept run was fitted again")

    monkeypatch.setattr(kernel_spread, "run_one", refit)
    again = kernel_spread.kernel_spread_report(config, log=lambda m: None)
    assert again.table == report.table
    # a kept file of other options is not this configuration's run: it is fitted again
    changed = KernelSpreadConfig(**{**config.__dict__, "overrides": {**TINY, "field.iterations": "4"}})
    with pytest.raises(AssertionError, match="fitted again"):
        kernel_spread.kernel_spread_report(changed, log=lambda m: None)
