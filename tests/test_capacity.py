"""``bench4d ablate capacity`` (:mod:`benchmark.studies.capacity`): the plan of runs, the knob checks, the
model-size count, and a tiny study on ``smoke`` that runs, reports, resumes and reads its table from its CSV."""

from __future__ import annotations

import dataclasses
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
    assert spec.make_config({}).geometry.hexplane_resolution == 64
    assert spec.make_config({"geometry.hexplane_resolution": "32"}).geometry.hexplane_resolution == 32
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


def test_best_value_has_the_highest_mean_of_miou_and_acc_ties_to_the_faster():
    means = pd.DataFrame({"value": ["2", "3", "4"], "mIoU": [50.0, 60.0, 55.0], "Acc": [80.0, 80.0, 85.0],
                          "fit_seconds": [10.0, 30.0, 20.0]})
    assert capacity.best_value(means) == "4"  # 3 and 4 both score 70: the faster
    means.loc[1, "fit_seconds"] = 5.0
    assert capacity.best_value(means) == "3"
    means.loc[2, "Acc"] = math.nan  # no time queries: mIoU alone
    assert capacity.best_value(means) == "3"
    assert capacity.best_value(means.assign(mIoU=math.nan, Acc=math.nan)) is None


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
    row = _readme_row(readme, "## latent dimension", "2")
    csv_row = table[(table["knob"] == "latent") & (table["value"] == "2")].iloc[0]
    assert row[1] == f"{csv_row['mIoU']:.2f}" and row[2] == f"{csv_row['Acc']:.2f}"
    assert row[4] == f"{csv_row['psnr']:.2f}" and row[8] == f"{csv_row['parameters']:,.0f}"
    assert "Best fixed value: **" in readme and "## The automatic choice against the best fixed value" in readme
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
