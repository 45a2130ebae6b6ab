"""``bench4d eval``: fit one method on one scene, answer every annotated query, score, record.

    bench4d eval --method nearest-frame --scene smoke [--seed 0] [--track oracle]
                 [--results-dir results] [--cache-dir cache] [--quiet]

``--scene`` is a scene folder or a synthetic preset name (generated into the cache once).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import add_run_arguments, check_device, check_run_folders, parse_overrides, print_run, splits


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--method", required=True, help="registered method (see bench4d methods)")
    parser.add_argument("--scene", required=True, help="scene folder or synthetic preset name")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--annotations", type=Path, default=None, help="ground-truth file (default: found beside the scene)")
    parser.add_argument("--refit", action="store_true", help="ignore a cached fit")
    add_run_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from ..runner import EvalOptions, evaluate

    check_device(args.device)
    check_run_folders(args)
    outcome = evaluate(EvalOptions(
        method=args.method, scene=args.scene, seed=args.seed, track=args.track, results_dir=args.results_dir,
        cache_dir=args.cache_dir, splits=splits(args), device=args.device, text_encoder=args.text_encoder,
        method_options=parse_overrides(args.set), annotations=args.annotations, preset_size=args.size, scale=args.scale,
        protocol=args.protocol, object_query=args.object_query, refit=args.refit, quiet=args.quiet))
    print_run(outcome.results, outcome.path)
    return 0
