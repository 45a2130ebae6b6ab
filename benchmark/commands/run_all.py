"""``bench4d run-all``: evaluate methods x scenes x seeds, then report mean and spread over seeds.

    bench4d run-all [--methods M ...] [--scenes S ...] [--seeds 0 1 2] [--force] [--jobs N]

Defaults: every registered method, every synthetic preset (except the tiny test preset ``smoke``),
seeds 0 1 2. Runs whose results file exists are skipped (so an interrupted sweep resumes) unless
``--force``; a rerun moves the file it replaces to ``results/archive/`` (never overwritten).

``--jobs N`` runs N (scene, seed) groups at once, each in a worker process with
``--threads-per-job`` torch threads (default: cores / N); the methods of a group run in order in
one worker, so the 4D methods share one geometry and field fit as they do sequentially. (The
committed sweeps ran as two single-threaded processes on 2 CPU cores.) Every results file records
``concurrent_runs`` and ``torch_threads`` beside its timings, which sharing the machine inflates.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ._common import add_run_arguments, check_device, check_run_folders, parse_overrides, splits

TEST_PRESETS = ("smoke",)
"""Presets made for tests, left out of the default sweep."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--methods", nargs="+", default=None, help="methods (default: all registered)")
    parser.add_argument("--scenes", nargs="+", default=None,
                        help="scene folders or synthetic presets (default: every synthetic preset but smoke)")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--force", action="store_true", help="rerun even where a results file exists")
    parser.add_argument("--keep-going", action="store_true", help="report a failing run and continue")
    parser.add_argument("--jobs", type=int, default=1,
                        help="runs at the same time, each (scene, seed) in its own worker process running its "
                             "methods in order, so methods that share a fit reuse it (default 1: this process)")
    parser.add_argument("--threads-per-job", type=int, default=None,
                        help="torch threads of each worker (default: CPU cores / jobs, at least 1)")
    add_run_arguments(parser)


def default_scenes() -> list[str]:
    from ..runner import _presets

    return [p for p in sorted(_presets()) if p not in TEST_PRESETS]


def _summary_line(item: dict) -> str:
    from ._common import fmt

    m = item["metrics"]
    return (f"{item['method']} {item['scene']} seed {item['seed']}: mIoU {fmt(m.get('mIoU'))} Acc {fmt(m.get('Acc'))} "
            f"vIoU {fmt(m.get('vIoU'))} (fit {item['fit_seconds']:.2f} s)")


def _run_group(group: list, keep_going: bool) -> list[dict]:
    """Evaluate the runs of one (scene, seed) in order; one dict per run attempted: ``path`` and
    ``metrics``, or ``error`` (the exception). Stops at the first failure unless ``keep_going``."""
    from ..runner import evaluate

    items = []
    for options in group:
        item = {"method": options.method, "scene": Path(options.scene).name, "seed": options.seed}
        try:
            outcome = evaluate(options)
        except Exception as err:  # noqa: BLE001 - reported by the caller
            items.append({**item, "error": _portable(err)})
            if not keep_going:
                break
            continue
        items.append({**item, "scene": outcome.results["scene"], "path": outcome.path,
                      "metrics": outcome.results["metrics"], "fit_seconds": outcome.results["timing"]["fit_seconds"]})
    return items


def _portable(err: Exception) -> Exception:
    """``err`` itself if it survives pickling (a worker returns it to the parent), else a RuntimeError
    with its type and message."""
    import pickle

    try:
        pickle.loads(pickle.dumps(err))
        return err
    except Exception:  # noqa: BLE001 - any failure to round-trip
        return RuntimeError(f"{type(err).__name__}: {err}")


def _start_worker(threads: int, git: dict) -> None:
    """A ``--jobs`` worker: its torch threads, and the commit it records: the parent command's (read as
    ``bench4d`` started, with its code fingerprint, so a run can tell that the code changed since),
    not the checkout's when the worker happens to start."""
    import os

    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[name] = str(threads)
    import torch

    torch.set_num_threads(threads)
    from ..runner import adopt_git_state

    adopt_git_state(git)


def run(args: argparse.Namespace) -> int:

    from methods import registry

    from benchmark.core.errors import InputError
    from ..loaders import load_scene
    from ..results import (archive_results, load_results, results_lock, results_path, runs_table, scene_status,
                           seed_summary)
    from ..runner import EvalOptions, checkout_at_start, dataset_label, resolve_scene

    check_device(args.device)
    check_run_folders(args)
    if args.jobs < 1:
        raise InputError(None, "--jobs", f"must be >= 1, got {args.jobs}")
    if args.threads_per_job is not None and args.threads_per_job < 1:
        raise InputError(None, "--threads-per-job", f"must be >= 1, got {args.threads_per_job}")
    methods = args.methods or registry.names()
    for m in methods:
        registry.get(m)  # unknown names fail before any work, with a "did you mean"
    runnable = []
    for method in methods:
        if args.track not in registry.get(method).tracks:
            print(f"skip {method}: does not run on the {args.track} track", file=sys.stderr)
        else:
            runnable.append(method)
    scenes = args.scenes or default_scenes()
    if not scenes:
        raise InputError(None, "--scenes", "no scenes given and no synthetic presets available")
    overrides = parse_overrides(args.set)
    done, failed, skipped = [], [], 0
    start = time.perf_counter()
    # one group per (scene, seed): its methods run in order in one process, so a method sharing
    # another's geometry and field (the 4D methods) finds them cached
    groups: list[list] = []
    for scene_spec in scenes:
        root = resolve_scene(scene_spec, args.cache_dir, size=args.size,
                             log=lambda m: None if args.quiet else print(m, file=sys.stderr))
        scene = load_scene(root)
        for seed in args.seeds:
            group = []
            for method in runnable:
                path = results_path(args.results_dir, dataset_label(scene), scene.name, method, args.track, seed)
                if path.is_file() and not args.force:
                    digest, current = scene_status(load_results(path))
                    if current is not False:
                        done.append(path)
                        skipped += 1
                        continue
                    # measured on another version of this preset: rerun, keeping the old file in the archive
                    with results_lock(path):  # a run writing this file meanwhile finishes first
                        moved = archive_results(path, args.results_dir, f"scene-{digest or 'unversioned'}") \
                            if path.is_file() else None
                    if moved is not None:
                        print(f"{path}: measured on another scene version; moved to {moved}, rerunning",
                              file=sys.stderr)
                group.append(EvalOptions(
                    method=method, scene=str(root), seed=seed, track=args.track, results_dir=args.results_dir,
                    cache_dir=args.cache_dir, splits=splits(args), device=args.device, text_encoder=args.text_encoder,
                    method_options=overrides, preset_size=args.size, scale=args.scale,
                    protocol=args.protocol, object_query=args.object_query, quiet=args.quiet or args.jobs > 1))
            if group:
                groups.append(group)
    jobs = min(args.jobs, len(groups)) or 1
    for group in groups:
        for options in group:
            options.concurrent_runs = jobs  # timings are taken beside this many other runs at most

    def report(items: list[dict]) -> None:
        for item in items:
            if "error" in item:
                failed.append((item["method"], item["scene"], item["seed"], item["error"]))
                if args.keep_going:
                    print(f"FAILED {item['method']} on {item['scene']} seed {item['seed']}: {item['error']}",
                          file=sys.stderr)
                continue
            done.append(item["path"])
            if not args.quiet:
                print(_summary_line(item), file=sys.stderr)

    if jobs == 1:
        for group in groups:
            report(_run_group(group, args.keep_going))
            if failed and not args.keep_going:
                raise failed[0][3]
    else:
        import concurrent.futures as cf
        import multiprocessing as mp
        import os

        threads = args.threads_per_job or max(1, (os.cpu_count() or 1) // jobs)
        if not args.quiet:
            print(f"run-all: {sum(len(g) for g in groups)} run(s) in {len(groups)} (scene, seed) group(s), "
                  f"{jobs} at a time, {threads} torch thread(s) each", file=sys.stderr)
        with cf.ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"),
                                    initializer=_start_worker, initargs=(threads, checkout_at_start())) as pool:
            futures = {pool.submit(_run_group, group, args.keep_going): group for group in groups}
            for future in cf.as_completed(futures):
                try:
                    items = future.result()
                except cf.process.BrokenProcessPool:
                    # a worker was killed (out of memory, a signal): the pool cannot go on; what finished is
                    # kept, and a rerun resumes the rest (results, cached fits, geometry checkpoints)
                    group = futures[future]
                    err = RuntimeError("a run-all worker process died (killed: out of memory?); rerun the same "
                                       "command to resume")
                    items = [{"method": o.method, "scene": Path(o.scene).name, "seed": o.seed, "error": err}
                             for o in group]
                    report(items)
                    pool.shutdown(wait=False, cancel_futures=True)
                    print(f"run-all: {err}", file=sys.stderr)
                    break
                report(items)
                if failed and not args.keep_going:
                    pool.shutdown(wait=True, cancel_futures=True)
                    raise failed[0][3]
    summary = seed_summary(runs_table(done))
    print(f"\n{len(done)} run(s) ({skipped} reused), {len(failed)} failed, {time.perf_counter() - start:.1f} s")
    _print_summary(summary)
    return 1 if failed else 0


def _print_summary(summary) -> None:
    from ..results import MEAN_SCENE
    from ._common import fmt

    def cell(row, col, digits=2):
        mean, std = row[f"{col}_mean"], row[f"{col}_std"]
        return fmt(mean, digits) + ("" if std != std else f"±{fmt(std, digits)}")

    header = f"{'dataset/track':24} {'method':16} {'scene':16} {'mIoU':>13} {'mAcc':>13} {'Acc':>13} {'vIoU':>13} " \
             f"{'FPS':>11} {'fit s':>11} seeds"
    print(header)
    print("-" * len(header))
    for row in summary.to_dict(orient="records"):
        scene = "MEAN" if row["scene"] == MEAN_SCENE else row["scene"]
        print(f"{row['dataset'] + '/' + row['track']:24} {row['method']:16} {scene:16} {cell(row, 'mIoU'):>13} "
              f"{cell(row, 'mAcc'):>13} {cell(row, 'Acc'):>13} {cell(row, 'vIoU'):>13} "
              f"{cell(row, 'fps_agnostic', 1):>11} {cell(row, 'fit_seconds'):>11} {row['seeds']}")
