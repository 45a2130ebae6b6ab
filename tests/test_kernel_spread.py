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
    mine = {s["score"]: s for s in summarize(runs, config, kernel_spread.read_folder(config))}
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
    assert "paper split, oracle track" in report.table.splitlines()[0]

    def refit(*args, **kwargs):
        raise AssertionError("a kept run was fitted again")

    monkeypatch.setattr(kernel_spread, "run_one", refit)
    again = kernel_spread.kernel_spread_report(config, log=lambda m: None)
    assert again.table == report.table
    # a kept file of other options is not this configuration's run: it is fitted again
    changed = KernelSpreadConfig(**{**config.__dict__, "overrides": {**TINY, "field.iterations": "4"}})
    with pytest.raises(AssertionError, match="fitted again"):
        kernel_spread.kernel_spread_report(changed, log=lambda m: None)


# --- kernels against seeds ------------------------------------------------------------------------

def test_the_prediction_interval_of_one_fit_is_the_t_interval_widened_by_one_draw():
    from benchmark.stats import prediction_interval

    lo, hi = prediction_interval([1.0, 2.0, 3.0])
    # mean 2, s = 1, n = 3: t(0.975, 2) = 4.3027 (tables), sqrt(1 + 1/3) = 1.1547
    assert lo == pytest.approx(2.0 - 4.3027 * 1.1547, abs=1e-3) and hi == pytest.approx(2.0 + 4.3027 * 1.1547, abs=1e-3)
    assert all(np.isnan(v) for v in prediction_interval([5.0]))
    assert prediction_interval([4.0, 4.0, None]) == (4.0, 4.0)


def test_each_seeds_spread_over_kernels_is_set_beside_the_folders_spread_over_seeds(monkeypatch):
    runs = [_run("a", 0, "default", 44.0), _run("a", 0, "avx2", 52.0)]
    monkeypatch.setattr(kernel_spread, "folder_values",
                        lambda *a, **k: {"a": {0: 50.0, 1: 52.0, 2: 48.0}} if a[4] == "mIoU" else {})
    config = KernelSpreadConfig(scenes=("a",), capabilities=("default", "avx2"))
    rows = {r["score"]: r for r in kernel_spread.noise_rows(runs, config, folder_runs=object())}
    miou = rows["mIoU"]
    # the study did not refit native: the folder's own fit of seed 0 joins the kernel settings
    assert miou["kernels"] == {"default": 44.0, "avx2": 52.0, "folder": 50.0}
    assert miou["kernel_range"] == pytest.approx(8.0) and miou["seed_range"] == pytest.approx(4.0)
    assert miou["kernel_std"] == pytest.approx(np.std([44.0, 52.0, 50.0], ddof=1))
    assert miou["seed_std"] == pytest.approx(2.0)
    lo, hi = miou["prediction_interval"]  # 50 -+ 4.3027 * 2 * 1.1547 = [40.06, 59.94]
    assert lo == pytest.approx(40.063, abs=1e-2) and hi == pytest.approx(59.937, abs=1e-2)
    assert miou["inside_prediction"] == {"default": True, "avx2": True}
    assert rows["Acc"]["prediction_interval"] is None and rows["Acc"]["inside_prediction"] is None
    assert "## Kernels against seeds" in kernel_spread.noise_markdown(list(rows.values()))
    # a refitted native run stands for the seed itself: the folder's is not added
    native = kernel_spread.noise_rows(runs + [_run("a", 0, "native", 70.0)], config, folder_runs=object())
    assert set(native[0]["kernels"]) == {"default", "avx2", "native"}
    assert native[0]["inside_prediction"]["native"] is False


# --- where fits part ------------------------------------------------------------------------------

def _trace(losses, counts, densify):
    steps = [["static", i + 1, loss, n] for i, (loss, n) in enumerate(zip(losses, counts))]
    return {"steps": steps, "densify": [["static", it] for it in densify], "capability": "X"}


def test_parting_finds_the_first_difference_the_jump_and_the_densification_before_it():
    from benchmark.studies.kernel_trace import parting

    base = [1.0] * 12
    a = _trace(base, [10] * 11 + [11], densify=[5, 10])
    other = list(base)
    other[3:10] = [1.0 + 1e-7] * 7  # last bits from iteration 4
    other[10:] = [1.02, 1.03]  # parted at iteration 11, right after the densification at 10
    b = _trace(other, [10] * 12, densify=[5, 10])
    p = parting(a, b, jump=1e-4)
    assert p["first_difference"] == ["static", 4]
    assert p["first_jump"] == ["static", 11]
    assert p["densify_before_jump"] == ["static", 10]
    assert p["before_jump"] == pytest.approx(1e-7, rel=1e-3)
    assert p["growth"] == pytest.approx((0.02 / 1.02) / (1e-7 / (1 + 1e-7)), rel=1e-3)
    assert p["first_count_difference"] == ["static", 12, 11, 10]
    assert p["final_counts"] == [11, 10]
    same = parting(a, a)
    assert same["first_difference"] is None and same["first_jump"] is None and same["final_relative"] == 0.0
    with pytest.raises(ValueError):
        parting(a, _trace(base[:5], [10] * 5, densify=[]))


def test_the_reading_says_densification_only_when_every_pair_parted_right_after_one():
    from benchmark.studies.kernel_trace import TraceConfig, pairings, trace_markdown

    def text(traces):
        return trace_markdown(TraceConfig(), traces, pairings(traces))

    a = _trace([1.0] * 6, [3] * 6, densify=[3])
    after = _trace([1.0, 1.0, 1.0, 1.1, 1.1, 1.1], [3] * 6, densify=[3])
    later = _trace([1.0, 1.0, 1.0, 1.0, 1.0, 1.2], [3] * 6, densify=[3])
    assert "right after a densification step" in text({"x": a, "y": after})
    mixed = text({"x": a, "y": later})
    assert "right after a densification step, the difference" not in mixed and "Not every pair" in mixed
    assert "No pair parted" in text({"x": a, "y": a})  # nothing to explain: said so, not "not every pair"
    assert list(pairings({"x": a, "y": after, "z": later})) == ["x / y", "x / z", "y / z"]


def test_a_trace_runs_per_setting_in_its_own_process_and_is_read_back(tmp_path, monkeypatch):
    from benchmark.runner import resolve_scene
    from benchmark.studies import kernel_trace
    from benchmark.studies.kernel_trace import TraceConfig, parting, run_trace

    config = TraceConfig(size=24, static_iterations=8, deformation_iterations=6)
    scene = resolve_scene("smoke", tmp_path / "cache", size=24, seed=0)
    traces = {cap: run_trace(config, cap, scene, tmp_path / f"{cap}.json", log=lambda m: None)
              for cap in ("default", "native")}
    assert traces["default"]["capability"] == "DEFAULT"
    assert [s[:2] for s in traces["default"]["steps"]] == [["static", i] for i in range(1, 9)] + \
        [["deformation", i] for i in range(1, 7)]
    p = parting(traces["default"], traces["native"])
    assert p["steps"] == 14 and p["final_counts"][0] > 0

    def refit(*args, **kwargs):
        raise AssertionError("a kept trace was fitted again")

    monkeypatch.setattr(kernel_trace.subprocess, "run", refit)
    assert run_trace(config, "default", scene, tmp_path / "default.json", log=lambda m: None) == traces["default"]
    (tmp_path / "native.json").write_text("{broken")
    with pytest.raises(AssertionError, match="fitted again"):  # a damaged kept trace is traced again
        run_trace(config, "native", scene, tmp_path / "native.json", log=lambda m: None)


def test_the_folders_runs_are_read_on_the_studys_track_only():
    import pandas as pd

    table = pd.DataFrame([
        {"method": "4d-langsplat", "split": "paper", "scene": "a", "seed": s, "dirty": False, "code_changed": False,
         "machine_kind": "cpu (x)", "track": track, "mIoU": value}
        for s, track, value in ((0, "oracle", 50.0), (1, "oracle", 52.0), (0, "real", 10.0), (1, "real", 12.0))])
    got = kernel_spread.folder_values(None, "4d-langsplat", "paper", ["a"], "mIoU", runs=table, track="oracle")
    assert got == {"a": {0: 50.0, 1: 52.0}}
    assert kernel_spread.study_track([{"track": "oracle"}, {"track": "oracle"}]) == "oracle"
    assert kernel_spread.study_track([{"track": "oracle"}, {"track": "real"}]) is None
