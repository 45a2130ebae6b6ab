"""``bench4d methods``: registered methods, supervision sources and text encoders; ``--options NAME``:
every option of a method (dotted path, group, default, help), as ``bench4d eval --method NAME`` and
``--set`` take them."""

from __future__ import annotations

import argparse
import textwrap


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--paper", action="store_true", help="also list methods known only by their paper numbers")
    parser.add_argument("--options", metavar="NAME", default=None,
                        help="print every option of method NAME: dotted path, group, default and help")


def print_options(name: str) -> None:
    """Every option of method ``name``, group by group: dotted path, default, help."""
    from benchmark.core.config import field_docs
    from methods import registry

    spec = registry.get(name)
    groups = field_docs(spec.config)
    print(f"Options of {spec.name} (bench4d eval --method {spec.name} --<path> VALUE, or --set <path>=VALUE):")
    current = None
    for option in spec.options():
        group = option.path.partition(".")[0] if "." in option.path else ""
        if group != current:
            current = group
            print(f"\n{group or '(no group)'}" + (f": {groups[group]}" if groups.get(group) else ""))
        default = option.default
        shown = ",".join(map(str, default)) if isinstance(default, (tuple, list)) else default
        print(f"  {option.path} = {shown}")
        for line in textwrap.wrap(option.help, 100):
            print(f"      {line}")


def run(args: argparse.Namespace) -> int:
    from methods import registry

    if args.options:
        print_options(args.options)
        return 0
    from methods.specs.paper_numbers import PAPER_NUMBERS
    from methods.supervision.registry import TRACK_DEFAULTS, TRACK_DESCRIPTIONS, sources
    from methods.text_encoders import DEFAULT_TEXT_ENCODER, TEXT_ENCODERS

    default = registry.default_method()
    print("Methods (runnable):")
    for spec in registry.all_specs():
        mark = " [default]" if spec.name == default else ""
        print(f"  {spec.name}{mark}")
        print(f"      {spec.description}")
        print(f"      tracks: {', '.join(spec.tracks)}; queries: {', '.join(spec.queries)}; "
              f"devices: {', '.join(spec.devices)}")
        if spec.paper:
            print(f"      paper: {spec.paper}")
        if spec.variant_of:
            print(f"      variant of {spec.variant_of} (benchmark extensions on; the paper's numbers are its base's)")
    missing = [m for m in PAPER_NUMBERS if m not in registry.names()]
    if missing:
        print(f"\nKnown by paper numbers only (shown on the leaderboard, not runnable): {', '.join(missing)}")
        if args.paper:
            for m in missing:
                print(f"  {m}: {PAPER_NUMBERS[m]['citation']}")
    print("\nSupervision tracks:")
    for track, chosen in TRACK_DEFAULTS.items():
        print(f"  {track}: {TRACK_DESCRIPTIONS[track]} ({', '.join(f'{k}={v}' for k, v in chosen.items())})")
    print("\nSupervision sources:")
    for s in sources():
        req = f"; needs {', '.join(s.requires)}" if s.requires else ""
        print(f"  {s.kind:10} {s.name:14} track {s.track:6} {s.description}{req}")
    print("\nText encoders:")
    for t in TEXT_ENCODERS.entries():
        mark = " [default]" if t.name == DEFAULT_TEXT_ENCODER else ""
        print(f"  {t.name}{mark}: {t.description} (weights: {t.weights})")
    return 0
