"""``bench4d demo``: the main job, end to end on a small synthetic scene.

Generates the default synthetic preset at 128 px (once, into the cache), runs the best registered
method (:data:`methods.registry.DEFAULT_METHOD`) on the oracle track, prints metrics and timings.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", default=None, help="preset or folder (default: the generator's default preset)")
    parser.add_argument("--method", default=None, help="method (default: the registry's default method)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--results-dir", type=Path, default=None,
                        help="where the demo's results file goes (default: CACHE_DIR/demo-results, so that a demo "
                             "in a fresh clone leaves the committed results/ untouched)")
    parser.add_argument("--cache-dir", type=Path, default=Path("cache"))
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--quiet", action="store_true")


def default_preset() -> str:
    import importlib

    synthetic = importlib.import_module("benchmark.synthetic")
    name = getattr(synthetic, "DEFAULT_PRESET", None)
    if name:
        return name
    from ..synthetic.presets import PRESETS

    presets = [p for p in PRESETS if p != "smoke"]  # declaration order: the generator's own first choice
    return presets[0] if presets else "smoke"


def run(args: argparse.Namespace) -> int:
    from methods import registry

    from ..runner import EvalOptions, evaluate
    from ._common import check_device, print_run

    check_device(args.device)
    method = args.method or registry.default_method()
    scene = args.scene or default_preset()
    start = time.perf_counter()
    print(f"bench4d demo: {method} on synthetic preset {scene!r} at {args.size}px (oracle track, seed {args.seed})")
    results_dir = args.results_dir or Path(args.cache_dir) / "demo-results"
    outcome = evaluate(EvalOptions(method=method, scene=scene, seed=args.seed, track="oracle", results_dir=results_dir,
                                   cache_dir=args.cache_dir, device=args.device, preset_size=args.size,
                                   quiet=args.quiet))
    print_run(outcome.results, outcome.path)
    sup = outcome.results["supervision"]
    print(f"  supervision: {sup['track']} track, sources {sup['sources']}")
    print(f"  total wall time {time.perf_counter() - start:.1f} s")
    print("Next: bench4d run-all, bench4d leaderboard, bench4d plot pareto")
    return 0
