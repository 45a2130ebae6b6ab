"""``bench4d demo``: the main job, end to end on a small synthetic scene.

Generates the default synthetic preset at :data:`DEMO_SIZE` px (once, into the cache), fits the 4D
language method :data:`DEMO_METHOD` with demo-sized schedules (:data:`DEMO_OVERRIDES`) and the 2D floors
beside it (``nearest-frame``, which answers through the same query rule, and ``nearest-frame-masks``) on the
oracle track, answers and scores every annotated query, and prints how both stand
against the perfect-feature ceiling under the same protocol (:mod:`benchmark.studies.protocol_ceiling`).
``--method`` runs one chosen method only. Results go under the cache folder, never into ``results/``.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Any, Optional

from benchmark.core.errors import InputError

DEMO_METHOD = "4d-langsplat"
"""The 4D language method the demo fits, in its paper config (the floors run beside it)."""

DEMO_SIZE = 64
"""Image width of the demo's generated preset (the leaderboard's runs use 128 px)."""

DEMO_OVERRIDES: dict[str, Any] = {
    "geometry.static_iterations": 300, "geometry.deformation_iterations": 600,
    "autoencoder.min_steps": 1500, "autoencoder.max_steps": 1500, "field.iterations": 400,
    "caption_autoencoder.min_steps": 1500, "caption_autoencoder.max_steps": 1500,
    "status.static_iterations": 100, "status.iterations": 400,
}
"""Demo-sized schedules: config overrides (dotted option path -> value) of :data:`DEMO_METHOD`, given to
every demo method whose config has the option; the methods' own defaults are the leaderboard's."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ._common import add_protocol_argument, add_threads_argument, parse_seed

    parser.add_argument("--scene", default=None, help="preset or folder (default: the generator's default preset)")
    parser.add_argument("--method", default=None,
                        help=f"run this method only (default: {DEMO_METHOD} and the 2D floors beside it)")
    parser.add_argument("--seed", type=parse_seed, default=0)
    parser.add_argument("--size", type=int, default=DEMO_SIZE, help="image size of the generated preset")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a method config field on top of the demo's schedules (repeatable; applied "
                             "to each method whose config has the field)")
    parser.add_argument("--results-dir", type=Path, default=None,
                        help="where the demo's results files go (default: CACHE_DIR/demo-results, so that a demo "
                             "in a fresh clone leaves the committed results/ untouched)")
    parser.add_argument("--cache-dir", type=Path, default=Path("cache"))
    parser.add_argument("--device", default="cpu")
    add_protocol_argument(parser)
    add_threads_argument(parser)
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


def demo_methods(chosen: Optional[str]) -> list[str]:
    """``[chosen]``, else :data:`DEMO_METHOD` followed by the registered floors."""
    from methods import registry

    if chosen:
        return [chosen]
    return [DEMO_METHOD] + [name for name in registry.names() if registry.get(name).floor and name != DEMO_METHOD]


def method_overrides(methods: list[str], extra: dict[str, str]) -> dict[str, dict[str, Any]]:
    """Method -> its config overrides: :data:`DEMO_OVERRIDES`, then ``extra`` (``--set``), each kept only
    for the methods whose config has that option. A ``--set`` option no method has is an error."""
    from benchmark.core.config import config_options
    from methods import registry

    fields = {m: {o.path for o in config_options(registry.get(m).config)} for m in methods}
    unknown = sorted(k for k in extra if not any(k in names for names in fields.values()))
    if unknown:
        raise InputError(None, "--set", f"no demo method ({', '.join(methods)}) has option(s) {unknown}")
    wanted = {**DEMO_OVERRIDES, **extra}
    return {m: {k: v for k, v in wanted.items() if k in fields[m]} for m in methods}


def protocol_ceiling_of(root: Path, protocol: str, text_encoder: str,
                        split: str = "paper") -> tuple[Optional[dict[str, float]], str]:
    """``({"mIoU": %, "vIoU": %}, "")`` of perfect features on evaluation split ``split`` of the scene at ``root``
    under ``protocol``, or ``(None, why)`` where it cannot be measured (a scene without generator truth)."""
    from benchmark.core.protocol import get_protocol
    from benchmark.studies.protocol_ceiling import protocol_ceiling
    from methods.text_encoders import get_text_encoder

    from ..loaders import load_scene
    from ..runner import find_annotations

    scene = load_scene(root)
    try:
        measured = protocol_ceiling(scene, find_annotations(scene), get_text_encoder(text_encoder),
                                    {protocol: get_protocol(protocol).agnostic}, split=split)
    except InputError as err:
        return None, str(err)
    variant = measured["variants"][protocol]
    return {"mIoU": 100.0 * variant["mIoU"], "vIoU": 100.0 * variant["vIoU"]}, ""


def demo_splits(root: Path) -> list[str]:
    """The evaluation splits the demo scores on the scene at ``root``: the paper's, then the novel views where
    the scene has them (a preset's scored times seen from off the training path: the question a 2D floor
    cannot answer by copying the nearest training frame)."""
    from benchmark.core.scene import scene_split_frames

    from ..loaders import load_scene

    scene = load_scene(root)
    try:
        novel = scene_split_frames(scene, "novel-view")
    except InputError:
        novel = []
    return ["paper"] + (["novel-view"] if novel else [])


def _share(value: Optional[float], bound: Optional[float]) -> str:
    if value is None or bound is None or not math.isfinite(value) or not math.isfinite(bound) or bound <= 0:
        return "–"
    return f"{100.0 * value / bound:.0f}"


def _milliseconds(seconds: float) -> str:
    ms = 1000.0 * seconds
    return f"{ms:.1f}" if ms < 10 else f"{ms:.0f}"


def demo_table(runs: list[dict], ceiling: Optional[dict[str, float]], floors: set[str], *,
               split_ceilings: Optional[dict[str, Optional[dict[str, float]]]] = None) -> list[str]:
    """The demo's summary table: one row per results document in ``runs``, then the ceiling's row (one per
    split with ``split_ceilings``: split -> its ceiling, each run's share taken of its own split's ceiling;
    ``ceiling`` is then unused). Acc and vIoU columns appear when some run scored time-sensitive queries."""
    from ._common import fmt

    timed = any((r["metrics"].get("sensitive_queries") or 0) > 0 for r in runs)
    splits = len({r.get("split") for r in runs}) > 1
    if split_ceilings is not None:
        ceilings = [(split, value) for split, value in split_ceilings.items() if value is not None]
    else:
        ceilings = [("", ceiling)] if ceiling is not None else []
    header = (["split"] if splits else []) + ["method", "mIoU"] + (["Acc", "vIoU"] if timed else []) + [
        "% of ceiling (mIoU" + (" / vIoU)" if timed else ")"), "fit s", "query ms/frame"]
    rows = []
    for r in runs:
        m, t = r["metrics"], r["timing"]
        bound = (split_ceilings.get(r.get("split")) if split_ceilings is not None else ceiling) or {}
        share = _share(m.get("mIoU"), bound.get("mIoU"))
        if timed:
            share += " / " + _share(m.get("vIoU"), bound.get("vIoU"))
        query = t.get("query_agnostic") or t.get("query_sensitive")
        rows.append(([str(r.get("split"))] if splits else [])
                    + [r["method"] + (" (2D floor)" if r["method"] in floors else ""), fmt(m.get("mIoU"), 1)]
                    + ([fmt(m.get("Acc"), 1), fmt(m.get("vIoU"), 1)] if timed else [])
                    + [share, fmt(t.get("fit_seconds"), 1) + (" (cached)" if t.get("fit_cached") else ""),
                       "–" if not query else _milliseconds(query["seconds_per_frame"])])
    for split, value in ceilings:
        share = _share(value["mIoU"], value["mIoU"]) + (
            " / " + _share(value["vIoU"], value["vIoU"]) if timed else "")
        rows.append(([split] if splits else []) + ["perfect features (ceiling)", fmt(value["mIoU"], 1)]
                    + (["–", fmt(value["vIoU"], 1)] if timed else []) + [share, "–", "–"])
    widths = [max(len(str(row[i])) for row in [header] + rows) for i in range(len(header))]
    left = 2 if splits else 1  # the text columns
    return ["  ".join(str(cell).ljust(w) if i < left else str(cell).rjust(w) for i, (cell, w) in
                      enumerate(zip(row, widths))).rstrip() for row in [header] + rows]


def run(args: argparse.Namespace) -> int:
    from methods import registry

    from ..runner import EvalOptions, evaluate, resolve_scene
    from ._common import check_device, parse_overrides, print_run, set_threads

    check_device(args.device)
    set_threads(args.threads)
    methods = demo_methods(args.method)
    overrides = method_overrides(methods, parse_overrides(args.set))
    spec = args.scene or default_preset()
    start = time.perf_counter()
    print(f"bench4d demo: {', '.join(methods)} on {spec!r} at {args.size}px "
          f"(oracle track, seed {args.seed}, protocol {args.protocol})")
    root = resolve_scene(spec, args.cache_dir, size=args.size, log=(lambda m: None) if args.quiet else print)
    results_dir = args.results_dir or Path(args.cache_dir) / "demo-results"
    runs = []
    for split in demo_splits(root):  # one fit per method answers both splits
        for method in methods:
            options = EvalOptions(method=method, scene=str(root), seed=args.seed, track="oracle",
                                  results_dir=results_dir, cache_dir=args.cache_dir, device=args.device,
                                  method_options=overrides[method], preset_size=args.size, protocol=args.protocol,
                                  quiet=args.quiet, split=split)
            outcome = evaluate(options)
            print_run(outcome.results, outcome.path)
            runs.append(outcome.results)
    measured = {split: protocol_ceiling_of(root, args.protocol, options.text_encoder, split)
                for split in demo_splits(root)}  # each split's runs against its own frames' ceiling
    ceiling = next((value for value, _ in measured.values() if value is not None), None)
    why = next((reason for _, reason in measured.values() if reason), "")
    floors = {m for m in methods if registry.get(m).floor}
    print()
    print("\n".join(demo_table(runs, None, floors, split_ceilings={s: v for s, (v, _) in measured.items()})))
    print(f"\nDemo-sized fits ({args.size} px, short schedules), not the leaderboard's: the leaderboard fits "
          "each method with its default config at 128 px (bench4d eval / run-all).")
    print("% of ceiling: the score's share of what perfect features score under the same protocol on the same "
          "frames" + ("" if ceiling is not None else f" (not measured here: {why})") + ".")
    print(f"Total wall time {time.perf_counter() - start:.1f} s. "
          "Next: bench4d run-all, bench4d leaderboard, bench4d plot pareto")
    return 0
