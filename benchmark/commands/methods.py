"""``bench4d methods``: registered methods, supervision sources and text encoders."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--paper", action="store_true", help="also list methods known only by their paper numbers")


def run(args: argparse.Namespace) -> int:
    from methods import registry
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
    for name, t in TEXT_ENCODERS.items():
        mark = " [default]" if name == DEFAULT_TEXT_ENCODER else ""
        print(f"  {name}{mark}: {t.description} (weights: {t.weights})")
    return 0
