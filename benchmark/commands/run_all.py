"""``bench4d run-all``: evaluate methods x scenes x seeds, then report mean and spread over seeds.

    bench4d run-all [--methods M ...] [--scenes S ...] [--seeds 0 1 2] [--force]

Defaults: every registered method, every synthetic preset (except the tiny test preset ``smoke``),
seeds 0 1 2. Runs whose results file exists are skipped (so an interrupted sweep resumes) unless
``--force``; a rerun moves the file it replaces to ``results/archive/`` (never overwritten).
"""

from __future__ import annotations

import argparse
import sys
import time

from ._common import add_run_arguments, check_device, parse_overrides, splits

TEST_PRESETS = ("smoke",)
"""Presets made for tests, left out of the default sweep."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--methods", nargs="+", default=None, help="methods (default: all registered)")
    parser.add_argument("--scenes", nargs="+", default=None,
                        help="scene folders or synthetic presets (default: every synthetic preset but smoke)")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--force", action="store_true", help="rerun even where a results file exists")
    parser.add_argument("--keep-going", action="store_true", help="report a failing run and continue")
    add_run_arguments(parser)


def default_scenes() -> list[str]:
    from ..runner import _presets

    return [p for p in sorted(_presets()) if p not in TEST_PRESETS]


def run(args: argparse.Namespace) -> int:

    from methods import registry

    from ..errors import InputError
    from ..loaders import load_scene
    from ..results import archive_results, load_results, results_path, runs_table, scene_status, seed_summary
    from ..runner import EvalOptions, dataset_label, evaluate, resolve_scene
    from ._common import fmt

    check_device(args.device)
    methods = args.methods or registry.names()
    for m in methods:
        registry.get(m)  # unknown names fail before any work, with a "did you mean"
    scenes = args.scenes or default_scenes()
    if not scenes:
        raise InputError(None, "--scenes", "no scenes given and no synthetic presets available")
    overrides = parse_overrides(args.set)
    done, failed, skipped = [], [], 0
    start = time.perf_counter()
    for scene_spec in scenes:
        root = resolve_scene(scene_spec, args.cache_dir, size=args.size,
                             log=lambda m: None if args.quiet else print(m, file=sys.stderr))
        scene = load_scene(root)
        for method in methods:
            spec = registry.get(method)
            if args.track not in spec.tracks:
                print(f"skip {method}: does not run on the {args.track} track", file=sys.stderr)
                continue
            for seed in args.seeds:
                path = results_path(args.results_dir, dataset_label(scene), scene.name, method, args.track, seed)
                if path.is_file() and not args.force:
                    digest, current = scene_status(load_results(path))
                    if current is not False:
                        done.append(path)
                        skipped += 1
                        continue
                    # measured on another version of this preset: rerun, keeping the old file in the archive
                    moved = archive_results(path, args.results_dir, f"scene-{digest or 'unversioned'}")
                    print(f"{path}: measured on another scene version; moved to {moved}, rerunning",
                          file=sys.stderr)
                options = EvalOptions(method=method, scene=str(root), seed=seed, track=args.track,
                                      results_dir=args.results_dir, cache_dir=args.cache_dir, splits=splits(args),
                                      device=args.device, text_encoder=args.text_encoder,
                                      method_options=overrides, preset_size=args.size, scale=args.scale,
                                      temporal_rule=args.temporal_rule, quiet=args.quiet)
                try:
                    outcome = evaluate(options)
                except Exception as err:  # noqa: BLE001 - reported, then re-raised unless --keep-going
                    failed.append((method, scene.name, seed, err))
                    if not args.keep_going:
                        raise
                    print(f"FAILED {method} on {scene.name} seed {seed}: {err}", file=sys.stderr)
                    continue
                done.append(outcome.path)
                if not args.quiet:
                    m = outcome.results["metrics"]
                    print(f"{method} {scene.name} seed {seed}: mIoU {fmt(m.get('mIoU'))} Acc {fmt(m.get('Acc'))} "
                          f"vIoU {fmt(m.get('vIoU'))} (fit {outcome.results['timing']['fit_seconds']:.2f} s)",
                          file=sys.stderr)
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
