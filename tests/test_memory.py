"""Peak memory of runs and of the stages inside them (``benchmark/memory.py``), and how the tables
charge a run with the stages it reused."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest

from benchmark.core import memory
from benchmark.leaderboard import UNMEASURED_MARK, render_markdown
from benchmark.results import peak_memory_with_shared, run_row, runs_table, seed_summary

LINUX = sys.platform == "linux"
MIB = 2 ** 20


def _touch(mib: int) -> np.ndarray:
    block = np.ones(mib * MIB // 8, dtype=np.float64)  # written, so resident
    return block


@pytest.mark.skipif(not LINUX, reason="needs a resettable high-water mark (Linux VmHWM)")
def test_a_stage_reports_its_own_peak_and_the_run_keeps_every_stage_peak():
    memory.reset_peak()
    with memory.StagePeak() as large:
        block = _touch(200)
        del block
    with memory.StagePeak() as small:
        block = _touch(8)
        del block
    assert memory.window() == "run"
    # the second stage starts after the first one's memory went back: it is not charged for it
    assert large.cpu_mib - small.cpu_mib > 150, (large.cpu_mib, small.cpu_mib)
    # restarting the mark for the second stage does not lose the first stage's peak for the run
    assert memory.peak_cpu_mib() >= large.cpu_mib - 1e-6
    assert large.record() == {"peak_cpu_mib": large.cpu_mib, "peak_gpu_mib": None, "peak_window": "run",
                              "baseline_cpu_mib": large.baseline_cpu_mib}
    # the stage began at what the process held, and grew by the block it wrote
    assert 0 < large.baseline_cpu_mib < large.cpu_mib - 150, (large.baseline_cpu_mib, large.cpu_mib)


@pytest.mark.skipif(not LINUX, reason="needs a resettable high-water mark (Linux VmHWM)")
def test_an_enclosing_stage_keeps_the_peak_of_a_stage_inside_it():
    memory.reset_peak()
    with memory.StagePeak() as outer:
        with memory.StagePeak() as inner:
            block = _touch(160)
            del block
        with memory.StagePeak() as after:
            pass
    assert inner.cpu_mib - after.cpu_mib > 120
    assert outer.cpu_mib >= inner.cpu_mib - 1e-6


@pytest.mark.skipif(not LINUX, reason="needs a resettable high-water mark (Linux VmHWM)")
def test_a_new_run_is_not_charged_for_the_previous_one():
    memory.reset_peak()
    block = _touch(200)
    del block
    before = memory.peak_cpu_mib()
    memory.reset_peak()
    assert before - memory.peak_cpu_mib() > 150


def _doc(window="run", stages=None, run_peak=500.0, fit_peak=300.0):
    info = {}
    for stage, peak in (stages or {}).items():
        info[stage] = {"seconds": 10.0}
        if peak is not None:
            info[stage].update({"peak_cpu_mib": peak, "peak_gpu_mib": None, "peak_window": "run"})
    return {"dataset": "dnerf", "track": "oracle", "method": "m", "scene": "s", "seed": 0,
            "memory": {"peak_cpu_mib": run_peak, "peak_cpu_fit_mib": fit_peak, "peak_gpu_mib": None,
                       "peak_window": window},
            "timing": {}, "fit": {"key": "k", "info": info}}


def test_a_run_is_charged_the_peak_of_every_stage_it_reused():
    # the geometry was fitted by another run (cached): this run's own peak is only its queries'
    cpu, gpu, measured = peak_memory_with_shared(_doc(stages={"geometry": 900.0, "field": 300.0}))
    assert (cpu, measured) == (900.0, True) and math.isnan(gpu)
    cpu, _, measured = peak_memory_with_shared(_doc(stages={"geometry": 100.0}))
    assert (cpu, measured) == (500.0, True)


def test_peaks_that_may_not_be_the_runs_own_are_flagged():
    # the process's mark (results made before per-run peaks)
    assert peak_memory_with_shared(_doc(window="process"))[2] is False
    assert peak_memory_with_shared({"memory": {"peak_cpu_mib": 5.0}})[2] is False
    # a reused stage that recorded its seconds but no peak: the run would be charged too little
    cpu, _, measured = peak_memory_with_shared(_doc(stages={"geometry": None, "field": 300.0}))
    assert (cpu, measured) == (500.0, False)


def test_the_leaderboard_marks_and_never_ranks_unmeasured_peaks():
    def table(docs):
        # an official scene: only those are ranked
        rows = [run_row({**d, "scene": "lego", "metrics": {"mIoU": 50.0 + i}}) for i, d in enumerate(docs)]
        import pandas as pd

        from benchmark.results import RUN_COLUMNS
        return render_markdown(pd.DataFrame(rows, columns=RUN_COLUMNS), "results")

    measured = [{**_doc(run_peak=400.0), "method": "a"}, {**_doc(run_peak=800.0), "method": "b"}]
    text = table(measured)
    assert "peak RAM (MiB)" in text and "**400**" in text and UNMEASURED_MARK + " |" not in text
    assert "peak GPU (MiB)" not in text  # no CUDA run in the table
    mixed = [{**_doc(run_peak=400.0, window="process"), "method": "a"}, {**_doc(run_peak=800.0), "method": "b"}]
    text = table(mixed)
    assert f"400 {UNMEASURED_MARK}" in text and "**400" not in text and "**800" not in text
    gpu = {**_doc(run_peak=400.0), "method": "c"}
    gpu["memory"] = {**gpu["memory"], "peak_gpu_mib": 2048.0}
    assert "peak GPU (MiB)" in table([gpu, measured[1]])


def test_seed_summary_says_whether_every_run_behind_a_number_was_measured(tmp_path):
    from benchmark.results import results_path, write_results

    root = tmp_path / "results"
    for seed, window in enumerate(("run", "process")):
        doc = {**_doc(window=window), "seed": seed, "metrics": {"mIoU": 50.0}}
        write_results(results_path(root, "dnerf", "s", "m", "oracle", seed), doc)
    write_results(results_path(root, "dnerf", "t", "m", "oracle", 0), {**_doc(), "scene": "t", "metrics": {"mIoU": 1.0}})
    from benchmark.results import find_results

    summary = seed_summary(runs_table(find_results(root)))
    flags = {r["scene"]: r["peak_measured"] for r in summary.to_dict(orient="records")}
    # s: seed 1 is the process's; t: one measured seed; mean: only seed 0 is complete, and it is measured
    assert flags == {"s": False, "t": True, "mean": True}


@pytest.mark.cuda
def test_stage_and_run_gpu_peaks_on_cuda():
    torch = pytest.importorskip("torch")
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    device = "cuda:0"
    torch.zeros(1, device=device)  # initialise CUDA before the run starts
    memory.reset_peak()
    with memory.StagePeak(device) as large:
        block = torch.ones(64 * MIB, device=device)  # 256 MiB
        del block
    with memory.StagePeak(device) as small:
        block = torch.ones(MIB, device=device)
        del block
    assert large.gpu_mib - small.gpu_mib > 200, (large.gpu_mib, small.gpu_mib)
    assert memory.peak_gpu_mib(device) >= large.gpu_mib - 1e-6
    assert memory.peak_gpu_mib("cpu") is None and memory.StagePeak("cpu").gpu_mib is None


def test_eval_output_names_the_memory_of_reused_stages(capsys):
    from benchmark.commands._common import print_run

    doc = {**_doc(stages={"geometry": 900.0}), "metrics": {"mIoU": 1.0},
           "timing": {"fit_seconds": 1.0, "fit_cached": True}}
    print_run(doc, "out.json")
    assert "peak CPU memory 500 MiB (with the cached stages it reused: 900 MiB)" in capsys.readouterr().out
    print_run({**_doc(stages={"geometry": 100.0}), "metrics": {}, "timing": {"fit_seconds": 1.0}}, "out.json")
    assert "reused" not in capsys.readouterr().out
