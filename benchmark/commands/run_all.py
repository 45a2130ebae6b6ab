"""``bench4d run-all``: evaluate methods x scenes x seeds, then report mean and spread over seeds.

    bench4d run-all [--methods M ...] [--scenes S ...] [--seeds 0 1 2] [--split paper|novel-view] [--force]
                    [--jobs N] [--threads 1] [--engine local|ray] [--address HOST:PORT]
                    [--source-option KIND.KEY=VALUE ...]

Defaults: every registered method, every synthetic preset (except the tiny test preset ``smoke``),
seeds 0 1 2, the ``paper`` evaluation split. Seed ``s`` of a preset measures the scene generated with
generator seed ``s`` (seeds sample scenes as well as fits). Runs whose results file exists are skipped (so
an interrupted sweep resumes) unless ``--force``, or the file measured another version of its preset, or its
method config is not the sweep's (a default moved since, other ``--set`` options); a rerun moves the file it
replaces to ``results/archive/`` (never overwritten). A sweep of the other split reuses the first sweep's fits.

``--jobs N`` runs N (scene, seed) groups at once, each in a worker process with ``--threads`` torch
threads (default 1, :func:`~benchmark.commands._common.set_threads`); the methods of a group run in
order in one worker, so the 4D methods share one geometry and field fit as they do sequentially. (The
committed sweeps ran as two single-threaded processes on 2 CPU cores.) Every results file records
``concurrent_runs`` and ``torch_threads`` beside its timings, which sharing the machine inflates.

``--engine ray`` runs each group as a task of a Ray cluster instead (:mod:`benchmark.commands.ray_engine`):
a local instance, or the cluster at ``--address``.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from ._common import (add_run_arguments, check_device, check_run_folders, parse_overrides, parse_seed, set_threads,
                      splits)
from .eval import add_source_option_argument, add_split_argument, parse_source_options

TEST_PRESETS = ("smoke",)
"""Presets made for tests, left out of the default sweep."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--methods", nargs="+", default=None, help="methods (default: all registered)")
    parser.add_argument("--scenes", nargs="+", default=None,
                        help="scene folders or synthetic presets (default: every synthetic preset but smoke)")
    parser.add_argument("--seeds", nargs="+", type=parse_seed, default=[0, 1, 2],
                        help="seeds of the fits and, on a synthetic preset, of the generated scene")
    add_split_argument(parser)
    parser.add_argument("--force", action="store_true", help="rerun even where a results file exists")
    parser.add_argument("--keep-going", action="store_true", help="report a failing run and continue")
    parser.add_argument("--jobs", type=int, default=1,
                        help="runs at the same time, each (scene, seed) in its own worker process running its "
                             "methods in order, so methods that share a fit reuse it (default 1: this process)")
    parser.add_argument("--engine", choices=("local", "ray"), default="local",
                        help="local: this machine's processes (--jobs); ray: each (scene, seed) group a task of a "
                             "Ray cluster (needs pip install 'bench4d[ray]')")
    parser.add_argument("--address", default=None,
                        help="with --engine ray: the cluster to join (HOST:PORT, or auto); default: start a local "
                             "Ray instance")
    add_run_arguments(parser)
    add_source_option_argument(parser)
    # a hidden second name of --threads, which sweep scripts spell
    parser.add_argument("--threads-per-job", dest="threads", type=int, default=argparse.SUPPRESS, help=argparse.SUPPRESS)


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


def run(args: argparse.Namespace) -> int:
    from ..results import runs_table, seed_summary

    check_device(args.device)
    check_run_folders(args)
    threads = _check_counts(args)
    runnable = _runnable_methods(args)
    start = time.perf_counter()
    tally = _Tally(args.keep_going, args.quiet)
    groups = _plan_groups(args, runnable, tally)
    jobs = min(args.jobs, len(groups)) or 1
    if args.engine == "ray":
        _run_on_ray(args, groups, threads, tally)
    elif jobs == 1:
        _set_concurrency(groups, 1)
        _run_here(groups, tally)
    else:
        _set_concurrency(groups, jobs)
        _run_in_workers(groups, jobs, threads, tally, args.quiet)
    summary = seed_summary(runs_table(tally.done))
    print(f"\n{len(tally.done)} run(s) ({tally.skipped} reused), {len(tally.failed)} failed, "
          f"{time.perf_counter() - start:.1f} s")
    _print_summary(summary)
    return 1 if tally.failed else 0


def _check_counts(args: argparse.Namespace) -> int:
    """``--jobs`` checked, and the thread rule applied to this process (its workers get the same);
    returns the threads of each fitting process."""
    from benchmark.core.errors import InputError

    if args.jobs < 1:
        raise InputError(None, "--jobs", f"must be >= 1, got {args.jobs}")
    return set_threads(args.threads)


def _runnable_methods(args: argparse.Namespace) -> list[str]:
    """The methods asked for (default: every registered one) that run on ``--track``; unknown names fail
    before any work, with a "did you mean"."""
    from methods import registry

    methods = args.methods or registry.names()
    for m in methods:
        registry.get(m)
    runnable = []
    for method in methods:
        if args.track not in registry.get(method).tracks:
            print(f"skip {method}: does not run on the {args.track} track", file=sys.stderr)
        else:
            runnable.append(method)
    return runnable


@dataclass
class _Tally:
    """What a sweep has done so far: results files (made or reused) and failures."""

    keep_going: bool
    """``--keep-going``: a failed run is reported and the sweep goes on."""
    quiet: bool
    """``--quiet``: no line per finished run."""
    done: list[Path] = field(default_factory=list)
    """Results files of the sweep, reused ones included."""
    failed: list[tuple] = field(default_factory=list)
    """``(method, scene, seed, error)`` of each failed run."""
    skipped: int = 0
    """Runs whose results file was reused."""

    def reused(self, path: Path) -> None:
        self.done.append(path)
        self.skipped += 1

    def report(self, items: list[dict]) -> None:
        """Record the outcomes :func:`_run_group` returned, printing a line each (a failure only under
        ``--keep-going``: otherwise it is raised)."""
        for item in items:
            if "error" in item:
                self.failed.append((item["method"], item["scene"], item["seed"], item["error"]))
                if self.keep_going:
                    print(f"FAILED {item['method']} on {item['scene']} seed {item['seed']}: {item['error']}",
                          file=sys.stderr)
                continue
            self.done.append(item["path"])
            if not self.quiet:
                print(_summary_line(item), file=sys.stderr)

    def stop(self) -> bool:
        """Whether the sweep stops here: a run failed and ``--keep-going`` was not given."""
        return bool(self.failed) and not self.keep_going


def _plan_groups(args: argparse.Namespace, runnable: list[str], tally: _Tally) -> list[list]:
    """The runs to make, one group per (scene, seed): its methods run in order in one process, so a
    method sharing another's geometry and field (the 4D methods) finds them cached. A run whose results
    file exists is reused (counted in ``tally``) unless ``--force`` or :func:`_reuse` finds it stale."""
    from benchmark.core.errors import InputError

    from ..loaders import load_scene
    from ..results import results_path
    from ..runner import EvalOptions, dataset_label, resolve_scene

    scenes = args.scenes or default_scenes()
    if not scenes:
        raise InputError(None, "--scenes", "no scenes given and no synthetic presets available")
    overrides = parse_overrides(args.set)
    source_options = parse_source_options(args.source_option)
    groups: list[list] = []
    for scene_spec in scenes:
        for seed in args.seeds:
            # seed s of a preset is the scene generated with seed s (a folder is the same for every seed)
            root = resolve_scene(scene_spec, args.cache_dir, size=args.size, seed=seed,
                                 log=lambda m: None if args.quiet else print(m, file=sys.stderr))
            scene = load_scene(root)
            group = []
            for method in runnable:
                path = results_path(args.results_dir, dataset_label(scene), scene.name, method, args.track, seed,
                                    args.split)
                if path.is_file() and not args.force and _reuse(path, args.results_dir, args.split, method, overrides):
                    tally.reused(path)
                    continue
                group.append(EvalOptions(
                    method=method, scene=str(root), seed=seed, split=args.split, track=args.track,
                    results_dir=args.results_dir,
                    cache_dir=args.cache_dir, splits=splits(args), device=args.device, text_encoder=args.text_encoder,
                    source_options=source_options, method_options=overrides, preset_size=args.size, scale=args.scale,
                    protocol=args.protocol, object_query=args.object_query, quiet=args.quiet or args.jobs > 1 or args.engine == "ray"))
            if group:
                groups.append(group)
    return groups


def _reuse(path: Path, results_dir: Path, split: str, method: str, overrides: dict) -> bool:
    """Whether the existing results file ``path`` stands; one measured on another version of its preset,
    written before evaluation splits were recorded (its split is not ``split``), or made with another method
    config than this sweep's (a default that moved since, or other ``--set`` options) is moved to the archive
    instead (and rerun)."""
    from methods import registry

    from ..results import archive_results, load_results, results_lock, run_split, scene_status

    doc = load_results(path)
    digest, current = scene_status(doc)
    made_as = registry.get(method).recorded_as(doc.get("method_config"), overrides)
    if current is not False and run_split(doc) == split and made_as:
        return True
    if current is False:
        label, why = f"scene-{digest or 'unversioned'}", "measured on another scene version"
    elif run_split(doc) != split:
        label, why = f"split-{run_split(doc)}", f"scored the {run_split(doc)} split"
    else:
        changed = registry.get(method).differences_from_defaults(doc.get("method_config")) if not overrides else None
        label = f"config-{str(doc.get('created') or 'undated').replace(':', '').replace(' ', '_')[:17]}"
        why = ("made with another method config than this sweep's"
               + (f" ({', '.join(f'{k}={a!r}, now {b!r}' for k, (a, b) in sorted(changed.items()))})"
                  if changed else ""))
    with results_lock(path):  # a run writing this file meanwhile finishes first
        moved = archive_results(path, results_dir, label) if path.is_file() else None
    if moved is not None:
        print(f"{path}: {why}; moved to {moved}, rerunning", file=sys.stderr)
    return False


def _set_concurrency(groups: list[list], runs: int) -> None:
    for group in groups:
        for options in group:
            options.concurrent_runs = runs  # timings are taken beside this many other runs at most


def _run_on_ray(args: argparse.Namespace, groups: list[list], threads: int, tally: _Tally) -> None:
    """Run the groups as tasks of a Ray cluster (:mod:`benchmark.commands.ray_engine`); the first failure
    is raised unless ``--keep-going``."""
    from ..runner import checkout_at_start
    from . import ray_engine

    if not groups:
        return
    cpus = ray_engine.connect(args.address, quiet=args.quiet).get("CPU", 1)
    try:
        _set_concurrency(groups, max(1, min(len(groups), int(cpus // threads))))
        ray_engine.run_groups(groups, address=args.address, threads=threads,
                              gpus=1 if args.device.startswith("cuda") else 0, git=checkout_at_start(),
                              keep_going=tally.keep_going, quiet=args.quiet, report=tally.report, stop=tally.stop)
    finally:
        ray_engine.disconnect()
    if tally.stop():
        raise tally.failed[0][3]


def _run_here(groups: list[list], tally: _Tally) -> None:
    """Run the groups one after the other in this process; the first failure is raised unless
    ``--keep-going``."""
    for group in groups:
        tally.report(_run_group(group, tally.keep_going))
        if tally.stop():
            raise tally.failed[0][3]


def _run_in_workers(groups: list[list], jobs: int, threads: int, tally: _Tally, quiet: bool) -> None:
    """Run the groups ``jobs`` at a time, each in a worker process with ``threads`` torch threads. A worker
    killed (out of memory, a signal) stops the pool: what finished is kept, and a rerun resumes the rest
    (results, cached fits, geometry checkpoints)."""
    import concurrent.futures as cf
    import multiprocessing as mp

    from ..runner import checkout_at_start, start_worker

    if not quiet:
        print(f"run-all: {sum(len(g) for g in groups)} run(s) in {len(groups)} (scene, seed) group(s), "
              f"{jobs} at a time, {threads} torch thread(s) each", file=sys.stderr)
    with cf.ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn"),
                                initializer=start_worker, initargs=(threads, checkout_at_start())) as pool:
        futures = {pool.submit(_run_group, group, tally.keep_going): group for group in groups}
        for future in cf.as_completed(futures):
            try:
                items = future.result()
            except cf.process.BrokenProcessPool:
                err = RuntimeError("a run-all worker process died (killed: out of memory?); rerun the same "
                                   "command to resume")
                tally.report([{"method": o.method, "scene": Path(o.scene).name, "seed": o.seed, "error": err}
                              for o in futures[future]])
                pool.shutdown(wait=False, cancel_futures=True)
                print(f"run-all: {err}", file=sys.stderr)
                break
            tally.report(items)
            if tally.stop():
                pool.shutdown(wait=True, cancel_futures=True)
                raise tally.failed[0][3]


def _print_summary(summary) -> None:
    from ..results import MEAN_SCENE
    from ._common import fmt

    def cell(row, col, digits=2):
        mean, std = row[f"{col}_mean"], row[f"{col}_std"]
        return fmt(mean, digits) + ("" if std != std else f"±{fmt(std, digits)}")

    header = f"{'dataset/track/split':32} {'method':16} {'scene':16} {'mIoU':>13} {'mAcc':>13} {'Acc':>13} {'vIoU':>13} " \
             f"{'FPS':>11} {'fit s':>11} seeds"
    print(header)
    print("-" * len(header))
    for row in summary.to_dict(orient="records"):
        scene = "MEAN" if row["scene"] == MEAN_SCENE else row["scene"]
        print(f"{row['dataset'] + '/' + row['track'] + '/' + row['split']:32} {row['method']:16} {scene:16} {cell(row, 'mIoU'):>13} "
              f"{cell(row, 'mAcc'):>13} {cell(row, 'Acc'):>13} {cell(row, 'vIoU'):>13} "
              f"{cell(row, 'fps_agnostic', 1):>11} {cell(row, 'fit_seconds'):>11} {row['seeds']}")
