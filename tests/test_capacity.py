"""``bench4d ablate capacity`` (:mod:`benchmark.studies.capacity`): the plan of runs, the knob checks, the
model-size count, and a tiny study on ``smoke`` that runs, reports, resumes and reads its table from its CSV."""

from __future__ import annotations

import dataclasses
import json
import math

import pandas as pd
import pytest
import torch

from benchmark.core.errors import InputError
from benchmark.studies import capacity
from benchmark.studies.capacity import AUTO, RELEASE, CapacityConfig, Knob

TINY = {"geometry.static_iterations": "20", "geometry.deformation_iterations": "20", "field.iterations": "30",
        "autoencoder.min_steps": "40", "autoencoder.max_steps": "60", "geometry.render_backend": "torch",
        "status.static_iterations": "20", "status.iterations": "30", "caption_autoencoder.min_steps": "40",
        "caption_autoencoder.max_steps": "60"}
"""Schedules short enough for a study of a few runs to take seconds."""


def test_hexplane_resolution_is_a_geometry_option_of_the_language_methods():
    from methods import registry

    spec = registry.get("4d-langsplat")
    assert spec.make_config({}).geometry.hexplane_resolution == 32
    assert spec.make_config({"geometry.hexplane_resolution": "64"}).geometry.hexplane_resolution == 64
    with pytest.raises(InputError, match="hexplane_resolution"):
        spec.make_config({"geometry.hexplane_resolution": "1"})


def test_plan_shares_runs_whose_configs_are_equal_and_adds_auto_and_release():
    config = CapacityConfig(presets=("smoke",), seeds=(0, 1), knobs=("latent", "states"),
                            values={"latent": ("2", "3")}, overrides=TINY)
    cells = capacity.plan(config, pixels={"smoke": 1000})
    runs = capacity.distinct_runs(cells)
    labels = sorted({r.label for r in runs})
    # latent 3 is the default: the auto run; K = 3 with the choice off is a run of its own
    assert labels == sorted([AUTO, "latent-2", "states-2", "states-3", "states-4", "states-6", RELEASE])
    assert len(runs) == 2 * len(labels)
    latent3 = [c for c in cells if c.knob == "latent" and c.value == "3" and c.run.seed == 0]
    assert len(latent3) == 1 and latent3[0].run.label == AUTO
    states = next(c.run for c in cells if c.knob == "states" and c.value == "4")
    assert dict(states.options) == {"status.num_states": "4", "extensions.choose_states": "false"}
    release = next(c.run for c in cells if c.knob == RELEASE)
    assert dict(release.options)["extensions.skip_static_semantics"] == "false"
    # runs of one preset and seed with equal geometry options make one group (one geometry fit)
    groups = capacity.geometry_groups(runs)
    assert len(groups) == 4 and all(len({r.geometry_options for r in g}) == 1 for g in groups)


def test_the_gaussian_bound_is_raised_only_where_it_would_cap_first():
    config = CapacityConfig()
    assert capacity.knob_options(config, "gaussians", "2", 5_000) == {"geometry.gaussians_per_foreground_pixel": "2"}
    raised = capacity.knob_options(config, "gaussians", "8", 100_000)
    assert raised["geometry.max_gaussians"] == "800000"


def test_a_knob_that_does_not_reach_the_geometry_or_the_method_is_refused(monkeypatch):
    monkeypatch.setitem(capacity.KNOBS, "backend", Knob("geometry.render_backend", ("torch", "auto"), "rasterizer"))
    with pytest.raises(InputError, match="does not change the geometry"):
        capacity.check_knobs(CapacityConfig(knobs=("backend",)))
    with pytest.raises(InputError, match="no knob"):
        capacity.check_knobs(CapacityConfig(knobs=("colour",)))
    with pytest.raises(InputError):  # langsplat has no states
        capacity.check_knobs(CapacityConfig(method="langsplat", knobs=("states",)))


def test_a_knob_runs_only_for_the_methods_whose_config_has_its_option():
    config = CapacityConfig(methods=("4d-langsplat", "deformable-clip"), presets=("smoke",), knobs=("states", "latent"),
                            values={"states": ("2", "4"), "latent": ("2",)},
                            overrides={k: v for k, v in TINY.items() if not k.startswith(("status.", "caption_"))})
    capacity.check_knobs(config)  # deformable-clip has no status field: the states knob passes it by
    cells = capacity.plan(config, pixels={"smoke": 1000})
    knobs_of = {m: {c.knob for c in cells if c.run.method == m} for m in config.methods}
    assert knobs_of == {"4d-langsplat": {AUTO, "states", "latent", RELEASE},
                        "deformable-clip": {AUTO, "latent", RELEASE}}
    release = next(c.run for c in cells if c.knob == RELEASE and c.run.method == "deformable-clip")
    assert dict(release.options) == {"geometry.max_gaussians": "360000",
                                     "geometry.gaussians_per_foreground_pixel": "1e9"}
    with pytest.raises(InputError, match="none of the methods"):
        capacity.check_knobs(CapacityConfig(methods=("deformable-clip", "langsplat"), knobs=("states",)))


def test_the_selection_score_is_the_mean_of_miou_and_acc_or_miou_alone():
    assert capacity.selection_score({"mIoU": 50.0, "Acc": 80.0}) == 65.0
    assert capacity.selection_score({"mIoU": 50.0, "Acc": math.nan}) == 50.0  # no time queries: mIoU alone
    assert math.isnan(capacity.selection_score({"mIoU": math.nan, "Acc": 80.0}))


def test_parameters_are_gaussians_times_their_floats_plus_the_networks(tmp_path):
    model = tmp_path / "model"
    (model / "time_varying").mkdir(parents=True)
    torch.save({"geometry": {"shape": {"means": torch.zeros(10, 3), "quats": torch.zeros(10, 4)},
                             "dynamic_mask": torch.zeros(10, dtype=torch.bool)},
                "features": torch.zeros(10, 6), "autoencoder": {"w": torch.zeros(5, 4)}}, model / "language_model.pt")
    torch.save({"module": {"states": torch.zeros(4, 2, 6), "fixed": torch.zeros(6, 6), "mlp": torch.zeros(7)}},
               model / "time_varying" / "time_varying.pt")
    counts = capacity.parameter_counts(model)
    assert counts == {"gaussians": 10, "per_gaussian_floats": (30 + 40 + 60 + 48 + 36) / 10,
                      "network_parameters": 27, "parameters": 30 + 40 + 60 + 48 + 36 + 27}
    assert capacity.parameter_counts(tmp_path / "gone") == {}


def _readme_row(readme: str, section: str, value: str) -> list[str]:
    part = readme.split(section)[1].split("\n## ")[0]
    line = next(line for line in part.splitlines() if line.startswith(f"| {value} |"))
    return [cell.strip() for cell in line.strip("|").split("|")]


def test_a_tiny_study_runs_reports_resumes_and_its_table_reads_the_csv(tmp_path, monkeypatch):
    import benchmark.runner as runner
    from benchmark.cli import main

    evaluated = []
    real_evaluate = runner.evaluate

    def counting(options):
        evaluated.append(options.results_dir)
        return real_evaluate(options)

    monkeypatch.setattr(runner, "evaluate", counting)
    config = CapacityConfig(presets=("smoke",), size=32, knobs=("latent",), values={"latent": ("2", "3")},
                            overrides=TINY, release=False, cache_dir=tmp_path / "cache", out_dir=tmp_path / "report",
                            timing_frames=1, timing_repeats=1)
    report = capacity.capacity_report(config, log=lambda message: None)
    assert len(evaluated) == 2  # latent 3 is the auto run
    out = tmp_path / "report"
    assert {p.name for p in report.paths} >= {"capacity.csv", "README.md", "latent.png", "latent.pdf"}
    assert (out / "charts" / "latent.png").stat().st_size > 0
    table = pd.read_csv(out / "capacity.csv", dtype={"value": str})
    assert sorted(zip(table["knob"], table["value"].fillna(""))) == [(AUTO, ""), ("latent", "2"), ("latent", "3")]
    assert table["parameters"].gt(table["gaussians"]).all() and table["fit_seconds"].gt(0).all()
    assert table["psnr"].gt(5).all()  # every run's geometry recorded its held-out PSNR
    files = {p: p.stat().st_mtime_ns for p in (tmp_path / "cache" / "capacity").rglob("seed0.json")}
    assert len(files) == 2

    readme = (out / "README.md").read_text()
    row = _readme_row(readme, "## 4d-langsplat+: latent dimension", "2")
    csv_row = table[(table["knob"] == "latent") & (table["value"] == "2")].iloc[0]
    score = (csv_row["mIoU"] + csv_row["Acc"]) / 2
    # one seed of one preset: the interval is the point itself
    assert row[1] == f"{score:.2f} [{score:.2f}, {score:.2f}]"
    assert row[2] == f"{csv_row['mIoU']:.2f} [{csv_row['mIoU']:.2f}, {csv_row['mIoU']:.2f}]"
    assert row[3] == f"{csv_row['Acc']:.2f}" and row[5] == f"{csv_row['psnr']:.2f}"
    assert row[11] == f"{csv_row['parameters']:,.0f}"
    # memory: the model's bytes, and what the fit added above the process's baseline
    assert table["model_mib"].to_numpy() == pytest.approx(table["parameters"].to_numpy() * 4 / 2 ** 20, rel=1e-4)
    assert table["peak_cpu_above_baseline_mib"].between(0, 1e5).all()
    assert (table["peak_cpu_above_baseline_mib"] < table["peak_cpu_needed_mib"]).all()
    assert "Plateau (highest mean score): **" in readme and "Knee (the cheapest value" in readme
    assert "## The automatic setting against the plateau, per preset" in readme
    assert "Best fixed value" not in readme and "ties: lower fit time" not in readme
    assert (table["track"] == "oracle").all() and table["machine_kind"].str.len().gt(0).all()
    assert f"Made under: supervision track oracle; split {table['split'][0]}; protocol {table['protocol'][0]}; " \
        f"machine {table['machine_kind'][0]}; code {table['git_commit'][0]}." in readme
    # the charts redraw from the written table alone
    assert main(["plot", "capacity", "--table", str(out / "capacity.csv"), "--out", str(tmp_path / "redrawn")]) == 0
    assert (tmp_path / "redrawn" / "charts" / "latent.png").stat().st_size > 0

    # a second study resumes: nothing is evaluated again, no results file rewritten
    capacity.capacity_report(config, log=lambda message: None)
    assert len(evaluated) == 2
    assert {p: p.stat().st_mtime_ns for p in files} == files

    # the command reports the same runs
    args = ["ablate", "capacity", "--presets", "smoke", "--size", "32", "--knobs", "latent", "--values", "latent=2,3",
            "--no-release", "--report-only", "--cache-dir", str(tmp_path / "cache"), "--out", str(tmp_path / "cli"),
            "--quiet"] + [a for k, v in TINY.items() for a in ("--set", f"{k}={v}")]
    assert main(args) == 0
    assert (tmp_path / "cli" / "capacity.csv").read_text() == (out / "capacity.csv").read_text()
    assert len(evaluated) == 2
    # runs made under another method config (a default that moved since) are stale: not reported, redone
    moved = dataclasses.replace(config, overrides={**TINY, "field.learning_rate": "0.02"})
    assert all(capacity.results_file(moved, run) is None for run in capacity.distinct_runs(capacity.plan(moved)))
    assert all(capacity.results_file(config, run) is not None for run in capacity.distinct_runs(capacity.plan(config)))
    # a report written from an emptied cache keeps the table it replaces beside it: no measurement is lost
    table_text = (out / "capacity.csv").read_text()
    emptied = dataclasses.replace(config, cache_dir=tmp_path / "empty-cache")
    capacity.capacity_report(emptied, report_only=True, log=lambda message: None)
    assert [p.read_text() for p in out.glob("capacity-replaced-*.csv")] == [table_text]
    capacity.capacity_report(config, report_only=True, log=lambda message: None)  # adds rows, drops none
    assert len(list(out.glob("capacity-replaced-*.csv"))) == 1


def _hand_table(scores: dict[str, list[list[float]]], seconds: dict[str, float]) -> pd.DataFrame:
    """A capacity table of one method and knob: ``scores[value][preset][seed]`` is the run's mIoU (no Acc: the
    score is mIoU alone), ``seconds[value]`` every run's fit time."""
    rows = []
    for value, presets in scores.items():
        for p, per_seed in enumerate(presets):
            for seed, miou in enumerate(per_seed):
                rows.append({"method": "m", "preset": f"p{p}", "seed": seed, "knob": "gaussians", "value": value,
                             "mIoU": miou, "Acc": math.nan, "fit_seconds": seconds[value]})
    return pd.DataFrame(rows)


def _choice(table: pd.DataFrame) -> capacity.Choice:
    table = capacity.with_scores(table)
    values = capacity._values_in_order(table)
    presets = capacity.complete_presets(table, values)
    score = capacity.estimates(table, capacity.SCORE, values, presets, seed=3)
    seconds = {v: table[table["value"] == v]["fit_seconds"].mean() for v in values}
    return capacity.plateau_and_knee(score, seconds)


def test_the_knee_is_the_cheapest_value_whose_interval_overlaps_the_plateau_s():
    # 8 is the plateau; 4's seeds overlap 8's, 2's lie far below: the knee is 4, whatever 2 costs
    table = _hand_table({"2": [[40, 42, 41], [45, 47, 46]], "4": [[60, 66, 63], [70, 76, 73]],
                         "8": [[62, 68, 65], [72, 78, 75]]}, {"2": 10.0, "4": 20.0, "8": 40.0})
    choice = _choice(table)
    assert choice.plateau == ("8",) and choice.knee == ("4",) and choice.overlapping == ("4", "8")
    # every interval overlaps: the knee is the cheapest value
    close = _hand_table({"2": [[55, 75, 65], [60, 80, 70]], "4": [[58, 76, 67], [61, 79, 70]],
                         "8": [[60, 78, 69], [62, 80, 71]]}, {"2": 10.0, "4": 20.0, "8": 40.0})
    choice = _choice(close)
    assert choice.plateau == ("8",) and choice.knee == ("2",) and choice.overlapping == ("2", "4", "8")
    # equal means are a tied plateau, equal costs a tied knee: no secondary order picks one
    tied = _hand_table({"2": [[40, 40], [40, 40]], "4": [[70, 71], [72, 73]], "8": [[70, 71], [72, 73]]},
                       {"2": 10.0, "4": 20.0, "8": 20.0})
    choice = _choice(tied)
    assert choice.plateau == ("4", "8") and choice.knee == ("4", "8")
    assert capacity.plateau_and_knee({"2": capacity.Estimate(math.nan, math.nan, math.nan)}, {"2": 1.0}) is None


def test_the_interval_of_a_constant_table_is_a_point_and_the_mean_weights_presets_equally():
    table = _hand_table({"2": [[50, 50, 50], [50, 50]], "4": [[60], [80, 80, 80]]}, {"2": 1.0, "4": 2.0})
    table = capacity.with_scores(table)
    est = capacity.estimates(table, capacity.SCORE, ["2", "4"], ["p0", "p1"], seed=0)
    assert (est["2"].mean, est["2"].low, est["2"].high) == (50.0, 50.0, 50.0)
    assert (est["4"].mean, est["4"].low, est["4"].high) == (70.0, 70.0, 70.0)  # (60 + 80) / 2, not (60 + 240) / 4
    varied = capacity.estimates(_hand_table({"2": [[40, 60]]}, {"2": 1.0}), "mIoU", ["2"], ["p0"], seed=0)["2"]
    assert varied.mean == 50.0 and 40.0 <= varied.low < 50.0 < varied.high <= 60.0


def test_the_report_states_plateau_knee_and_whether_auto_sits_at_the_plateau():
    table = _hand_table({"2": [[40, 42, 41], [45, 47, 46]], "4": [[60, 66, 63], [70, 76, 73]],
                         "8": [[62, 68, 65], [72, 78, 75]]}, {"2": 10.0, "4": 20.0, "8": 40.0})
    auto = table[table["value"] == "4"].assign(knob=AUTO, value="")
    full = pd.concat([table, auto], ignore_index=True)
    for column in capacity.CSV_COLUMNS:
        if column not in full:
            full[column] = math.nan
    readme = capacity.render_readme(full, CapacityConfig(methods=("m",), knobs=("gaussians",), seeds=(0, 1, 2)))
    assert "Plateau (highest mean score): **8** (8: 70.00 [" in readme
    assert "Knee (the cheapest value by mean fit time whose interval overlaps the plateau's): **4** (4: 68.00" in readme
    assert "Automatic setting (`auto`): 68.00 [" in readme and "its mean is inside the plateau's interval, at no more " \
        "than the plateau's fit time" in readme
    per_preset = [line for line in readme.splitlines() if line.startswith("| m | p")]
    assert len(per_preset) == 2 and all(line.rstrip(" |").endswith("**yes**") for line in per_preset)
    assert "seed s fits the preset generated with generator seed s" in readme


def test_seeds_sample_scenes_and_methods_share_one_geometry(tmp_path, monkeypatch):
    from benchmark.cli import main
    from benchmark.runner import preset_folder
    from methods.gaussians.train import Trainer

    fits = []
    real_fit = Trainer.fit_4dgs

    def counting(self, *args, **kwargs):
        fits.append(1)
        return real_fit(self, *args, **kwargs)

    monkeypatch.setattr(Trainer, "fit_4dgs", counting)
    from methods import registry

    tiny = {**TINY, "geometry.static_iterations": "6", "geometry.deformation_iterations": "6"}
    # the default budget: the knob's one value is the auto run, so each method has one run
    budget = f"{registry.get('4d-langsplat').make_config().geometry.gaussians_per_foreground_pixel:g}"
    config = CapacityConfig(methods=("4d-langsplat", "non-status-field"), presets=("smoke",), size=24, seeds=(1,),
                            knobs=("gaussians",), values={"gaussians": (budget,)}, overrides=tiny, release=False,
                            cache_dir=tmp_path / "cache", out_dir=tmp_path / "report", timing_frames=1,
                            timing_repeats=1)
    runs = capacity.distinct_runs(capacity.plan(config))
    assert sorted(r.method for r in runs) == ["4d-langsplat", "non-status-field"]
    assert len(capacity.geometry_groups(runs)) == 1  # both methods' runs in one group: one geometry
    capacity.capacity_report(config, log=lambda message: None)
    assert len(fits) == 1  # the second method reused the first one's geometry
    results = sorted((tmp_path / "cache" / "capacity").rglob("seed1.json"))
    assert len(results) == 2 and {p.parts[-3] for p in results} == {"4d-langsplat", "non-status-field"}
    # seed 1 fits the scene generated with seed 1; no scene of seed 0 was made, not even to count pixels
    assert all(json.loads(p.read_text())["scene_seed"] == 1 for p in results)
    assert preset_folder(tmp_path / "cache", "smoke", 24, 1).is_dir()
    assert not preset_folder(tmp_path / "cache", "smoke", 24, 0).exists()
    table = pd.read_csv(tmp_path / "report" / "capacity.csv")
    assert sorted(table["method"].unique()) == ["4d-langsplat", "non-status-field"]
    assert (table["scene_seed"] == 1).all()
    readme = (tmp_path / "report" / "README.md").read_text()
    assert "## 4d-langsplat: Gaussians per foreground pixel" in readme
    assert "## non-status-field: Gaussians per foreground pixel" in readme

    # the command: --methods reports the same runs; --method is a one-method --methods; not both
    args = ["ablate", "capacity", "--presets", "smoke", "--size", "24", "--seeds", "1", "--knobs", "gaussians",
            "--values", f"gaussians={budget}", "--no-release", "--report-only", "--cache-dir", str(tmp_path / "cache"),
            "--quiet"] + [a for k, v in tiny.items() for a in ("--set", f"{k}={v}")]
    assert main(args + ["--methods", "4d-langsplat", "non-status-field", "--out", str(tmp_path / "cli")]) == 0
    assert (tmp_path / "cli" / "capacity.csv").read_text() == (tmp_path / "report" / "capacity.csv").read_text()
    assert main(args + ["--method", "non-status-field", "--out", str(tmp_path / "one")]) == 0
    assert set(pd.read_csv(tmp_path / "one" / "capacity.csv")["method"]) == {"non-status-field"}
    assert main(args + ["--method", "x", "--methods", "y", "--out", str(tmp_path / "both")]) == 2
    assert len(fits) == 1


def test_the_runs_can_live_beside_the_report_so_a_study_resumes_without_its_cache(tmp_path):
    from benchmark.studies.capacity import CapacityConfig

    default = CapacityConfig(cache_dir=tmp_path / "cache", size=128, methods=("4d-langsplat",))
    assert default.runs_dir_of("4d-langsplat") == tmp_path / "cache" / "capacity" / "4d-langsplat-128px" / "runs"
    kept = CapacityConfig(cache_dir=tmp_path / "cache", size=128, methods=("4d-langsplat",),
                          runs_root=tmp_path / "reports" / "runs")
    assert kept.runs_dir_of("non-status-field") == tmp_path / "reports" / "runs" / "non-status-field-128px" / "runs"


def test_the_header_names_what_the_runs_were_made_under_and_shows_a_mix_with_its_counts():
    table = _hand_table({"2": [[40, 42], [45, 47]], "4": [[60, 66], [70, 76]]}, {"2": 10.0, "4": 20.0})
    table = table.assign(run=table["value"], track="oracle", split="paper", protocol="release",
                         machine_kind="CPU A (avx2)", git_commit="abc123")
    assert capacity.provenance_line(table) == ("Made under: supervision track oracle; split paper; protocol release; "
                                               "machine CPU A (avx2); code abc123.")
    table.loc[table["seed"] == 1, "machine_kind"] = "CPU B (avx512)"
    assert "machine mixed: CPU A (avx2) (4 runs), CPU B (avx512) (4 runs);" in capacity.provenance_line(table)
    assert "supervision track not recorded" in capacity.provenance_line(table.drop(columns=["track"]))


def test_the_pooled_curve_carries_the_readme_s_interval_and_the_chart_shades_it(tmp_path, monkeypatch):
    from benchmark import plots

    table = _hand_table({"2": [[40, 42, 41], [45, 47, 46]], "8": [[62, 68, 65], [72, 78, 75]]}, {"2": 10.0, "8": 40.0})
    table = table.reindex(columns=list(capacity.CSV_COLUMNS))  # the CSV's columns, those not measured empty
    curve = capacity.pooled_curve(table, "gaussians", "m")
    assert list(curve["value"]) == ["2", "8"]
    scored = capacity.with_scores(table)
    readme = capacity.estimates(scored, capacity.SCORE, ["2", "8"], ["p0", "p1"],
                                seed=capacity.stats.stable_seed("capacity", "m", "gaussians"))
    for _, row in curve.iterrows():
        est = readme[row["value"]]
        assert (row["score"], row["score_low"], row["score_high"]) == (est.mean, est.low, est.high)
        assert row["score_low"] < row["score"] < row["score_high"]
    assert curve["fit_seconds"].tolist() == [10.0, 40.0]

    figures = []
    monkeypatch.setattr(plots, "_save", lambda fig, stem: figures.append(fig) or [stem.with_suffix(".png")])
    plots.metric_curves(tmp_path / "c", {"m": curve.assign(x=[2.0, 8.0])}, x="x", x_label="x",
                        panels=[("score", "score"), ("fit_seconds", "fit")])
    score_ax, fit_ax = figures[0].axes[:2]
    assert len(score_ax.collections) == 1 and len(fit_ax.collections) == 0  # a band where the table has one


def test_the_cheapest_value_at_every_preset_s_plateau_is_named_and_a_value_failing_one_preset_is_not():
    # 8 is each preset's plateau; 4 sits inside its interval on both presets; 2 on p0 only
    table = _hand_table({"2": [[63, 64, 65], [40, 42, 41]], "4": [[63, 65, 64], [73, 75, 74]],
                         "8": [[60, 70, 65], [70, 80, 75]]}, {"2": 10.0, "4": 20.0, "8": 40.0})
    table = table.assign(run=table["value"]).reindex(columns=list(capacity.CSV_COLUMNS))
    assert capacity.at_every_plateau(table, "gaussians", "m") == {"2": ["p0"], "4": ["p0", "p1"], "8": ["p0", "p1"]}
    section = "\n".join(capacity.every_preset_section(table, ["gaussians"], ["m"]))
    assert "| m | gaussians | 2: 1/2; 4: 2/2; 8: 2/2 | 4 |" in section
    # no value at the plateau everywhere but the plateau itself costs most: still named, never 'none' then
    lone = table[table["value"] != "4"]
    assert "| m | gaussians | 2: 1/2; 8: 2/2 | 8 |" in "\n".join(capacity.every_preset_section(lone, ["gaussians"], ["m"]))


def test_each_value_is_averaged_over_the_same_seeds_and_auto_over_them_too():
    # value 4 (and auto) ran seeds 0-2, value 8 seeds 0-1: seed 2 of 4 and of auto is left out of the comparison
    table = _hand_table({"4": [[60, 62, 10], [70, 72, 10]], "8": [[61, 63], [71, 73]]}, {"4": 20.0, "8": 40.0})
    auto = table[table["value"] == "4"].assign(knob=AUTO, value="")
    full = pd.concat([table, auto], ignore_index=True).reindex(columns=list(capacity.CSV_COLUMNS))
    full = full.assign(run=full["value"])
    matched = capacity.matched_runs(capacity.with_scores(table))
    assert sorted(set(matched["seed"])) == [0, 1] and len(matched) == 8
    readme = capacity.render_readme(full, CapacityConfig(methods=("m",), knobs=("gaussians",), seeds=(0, 1, 2)))
    assert "each the mean over its seeds (0 1)" in readme
    assert "Left out: 2 run(s) of a preset and seed that lack a run of another value." in readme
    assert _readme_row(readme, "m: Gaussians per foreground pixel", "4")[1].startswith("66.00 [")  # not 46.33
    assert "Automatic setting (`auto`): 66.00 [" in readme
    curve = capacity.pooled_curve(full, "gaussians", "m")
    assert list(curve["score"]) == [66.0, 67.0]
    assert capacity.at_every_plateau(full, "gaussians", "m") == {"4": ["p0", "p1"], "8": ["p0", "p1"]}


def test_a_knob_that_changes_neither_model_nor_scores_is_called_out():
    table = _hand_table({"2": [[60, 62], [70, 72]], "4": [[60, 62], [70, 72]]}, {"2": 20.0, "4": 21.0})
    table = table.assign(parameters=1000.0, Acc=50.0, vIoU=30.0).reindex(columns=list(capacity.CSV_COLUMNS))
    table = table.assign(run=table["value"])
    section = "\n".join(capacity.knob_section(table, "gaussians", "m"))
    assert "does not reach m's model" in section
    # a model that grows with the value is reached, whatever the scores
    grown = table.assign(parameters=table["value"].astype(float) * 1000.0)
    assert "does not reach" not in "\n".join(capacity.knob_section(grown, "gaussians", "m"))
    changed = table.copy()
    changed.loc[(changed["value"] == "4") & (changed["seed"] == 1), "mIoU"] += 1.0
    assert "does not reach" not in "\n".join(capacity.knob_section(changed, "gaussians", "m"))


def test_the_report_redraws_from_its_csv_alone_and_says_whether_the_runs_are_kept(tmp_path):
    from benchmark.cli import main
    from benchmark.studies.capacity import CapacityConfig

    table = _hand_table({"2": [[40, 42, 41], [45, 47, 46]], "8": [[62, 68, 65], [72, 78, 75]]}, {"2": 10.0, "8": 40.0})
    table = table.assign(run=table["value"]).reindex(columns=list(capacity.CSV_COLUMNS))
    out = tmp_path / "report"
    out.mkdir()
    csv = table.to_csv(index=False)
    (out / "capacity.csv").write_text(csv)
    config = CapacityConfig(methods=("m",), knobs=("gaussians",), seeds=(0, 1, 2), out_dir=out,
                            runs_root=tmp_path / "runs")
    report = capacity.capacity_report(config, from_csv=True)
    readme = (out / "README.md").read_text()
    assert readme == report.table and "Plateau (highest mean score): **8**" in readme
    assert "the runs' results files are not kept beside it" in readme
    assert (out / "capacity.csv").read_text() == csv  # read, never rewritten
    assert not list(out.glob("capacity-replaced-*.csv"))
    config.runs_dir_of("m").mkdir(parents=True)
    assert f"the runs' results files under `{config.runs_dir_of('m').as_posix()}/`" in \
        capacity.capacity_report(config, from_csv=True).table
    assert main(["ablate", "capacity", "--from-csv", "--out", str(tmp_path / "none"), "--quiet"]) == 2
    assert main(["ablate", "capacity", "--from-csv", "--report-only", "--out", str(out), "--quiet"]) == 2
