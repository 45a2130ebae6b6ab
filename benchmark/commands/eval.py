"""``bench4d eval``: fit one method on one scene, answer every annotated query, score, record.

    bench4d eval --method nearest-frame --scene smoke [--seed 0] [--track oracle] [--split paper|novel-view]
                 [--results-dir results] [--cache-dir cache] [--threads 1] [--quiet]
                 [--<group>.<option> VALUE ...] [--set <group>.<option>=VALUE ...]
                 [--source-option KIND.KEY=VALUE ...]

``--scene`` is a scene folder or a synthetic preset name (generated into the cache once per seed: seed ``s``
generates the preset with generator seed ``s``). ``--split`` is the evaluation split scored: ``paper`` (the
dataset's held-out frames, default) or ``novel-view`` (held-out frames from cameras no training frame uses);
one cached fit answers both. The method's
options are flags derived from its config (``--autoencoder.latent-dim 4``; ``bench4d eval --method M --help``
lists them with their help and default); ``--set autoencoder.latent_dim=4`` is the same for scripts.
``--source-option segmenter.points_per_side=16`` is an option of a supervision source's factory
(:func:`parse_source_options`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from ._common import (add_run_arguments, check_device, check_run_folders, parse_overrides, print_run, parse_seed,
                      set_threads, splits)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--method", required=True, help="registered method (see bench4d methods); its options "
                        "are listed by bench4d eval --method M --help")
    parser.add_argument("--scene", required=True, help="scene folder or synthetic preset name")
    parser.add_argument("--seed", type=parse_seed, default=0)
    parser.add_argument("--annotations", type=Path, default=None, help="ground-truth file, or the 4D LangSplat release's annotations/ folder (default: found beside the scene)")
    parser.add_argument("--refit", action="store_true", help="ignore a cached fit")
    add_split_argument(parser)
    add_run_arguments(parser)
    add_source_option_argument(parser)
    _add_method_options_on_parse(parser)


def add_split_argument(parser: argparse.ArgumentParser) -> None:
    """``--split``: the evaluation split a run scores (:data:`benchmark.core.scene.EVAL_SPLITS`)."""
    from benchmark.core.scene import DEFAULT_EVAL_SPLIT, EVAL_SPLITS

    parser.add_argument("--split", choices=EVAL_SPLITS, default=DEFAULT_EVAL_SPLIT,
                        help="evaluation split: paper (the dataset's held-out frames: HyperNeRF frames i %% 4 == 2, "
                             "training on i %% 4 == 0; the Neu3D held-out camera; default) or novel-view (the scored "
                             "times seen from cameras no training frame uses); one cached fit answers both")


def add_source_option_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--source-option", action="append", default=[], metavar="KIND.KEY=VALUE",
                        help="an option of the track's supervision source of KIND (segmenter or image_text), e.g. "
                             "segmenter.points_per_side=16 or image_text.model=/weights/clip; VALUE is read as "
                             "JSON when it parses, else as text (repeatable)")


def parse_source_options(items: list[str]) -> dict[str, dict[str, Any]]:
    """``--source-option KIND.KEY=VALUE`` items as :attr:`benchmark.runner.EvalOptions.source_options`
    (kind -> key -> value). A value that parses as JSON (numbers, booleans, null, lists) is that; any other
    is the text. A malformed item or an unknown kind is a one-line :class:`InputError`."""
    from benchmark.core.errors import InputError
    from methods.supervision.registry import SOURCE_KINDS

    out: dict[str, dict[str, Any]] = {}
    for item in items:
        target, sep, text = item.partition("=")
        kind, dot, key = target.strip().partition(".")
        if not sep or not dot or not kind or not key.strip():
            raise InputError(None, "--source-option", f"expected KIND.KEY=VALUE, got {item!r}")
        if kind not in SOURCE_KINDS:
            raise InputError(None, "--source-option", f"unknown source kind {kind!r} in {item!r}; "
                             f"kinds: {', '.join(SOURCE_KINDS)}")
        try:
            value = json.loads(text)
        except ValueError:
            value = text.strip()
        out.setdefault(kind, {})[key.strip()] = value
    return out


def _add_method_options_on_parse(parser: argparse.ArgumentParser) -> None:
    """Parse in two phases: read ``--method`` first, then add that method's config options (one flag per
    option, :func:`benchmark.core.config.add_config_arguments`) and parse everything. An unknown method adds
    none (the run then says so)."""
    parse_known_args = parser.parse_known_args

    def two_phase(args=None, namespace=None):
        probe = argparse.ArgumentParser(add_help=False)
        probe.add_argument("--method")
        method = probe.parse_known_args(args)[0].method
        if method and not getattr(parser, "_method_options_of", None):
            from benchmark.core.config import add_config_arguments
            from benchmark.core.errors import InputError
            from methods import registry

            try:
                spec = registry.get(method)
            except InputError:
                spec = None
            if spec is not None:
                add_config_arguments(parser, spec.config, title=f"{spec.name} options")
                parser._method_options_of = spec.name
        return parse_known_args(args, namespace)

    parser.parse_known_args = two_phase


def method_options(args: argparse.Namespace) -> dict[str, str]:
    """The method's options given on the command line: ``--set KEY=VALUE`` items, then the derived flags
    (a flag given both ways takes the flag's value)."""
    from benchmark.core.config import overrides_from_arguments

    return {**parse_overrides(args.set), **overrides_from_arguments(args)}


def run(args: argparse.Namespace) -> int:
    from ..runner import EvalOptions, evaluate

    check_device(args.device)
    check_run_folders(args)
    source_options = parse_source_options(args.source_option)
    set_threads(args.threads)
    outcome = evaluate(EvalOptions(
        method=args.method, scene=args.scene, seed=args.seed, split=args.split, track=args.track,
        results_dir=args.results_dir,
        cache_dir=args.cache_dir, splits=splits(args), device=args.device, text_encoder=args.text_encoder,
        source_options=source_options, method_options=method_options(args), annotations=args.annotations,
        preset_size=args.size,
        scale=args.scale, protocol=args.protocol, object_query=args.object_query, refit=args.refit,
        quiet=args.quiet))
    print_run(outcome.results, outcome.path)
    _say_if_unranked(outcome.results, outcome.path)
    return 0


def _say_if_unranked(doc: dict, path) -> None:
    """A run on a scene that is not one of the benchmark's official scenes: say where its results went and
    that the leaderboard never ranks them."""
    from benchmark.core.official import is_official, official_note

    generated = (doc.get("scene_info") or {}).get("generated") or {}
    dataset, scene = str(doc.get("dataset")), str(doc.get("scene"))
    if not is_official(dataset, scene, generated.get("preset") if isinstance(generated, dict) else None):
        print(f"results: {path}; {official_note(dataset, scene)}")
