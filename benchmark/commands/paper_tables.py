"""``bench4d paper-tables``: every table of the paper with the published numbers beside ours.

    bench4d paper-tables [--results-dir results] [--reports-dir reports] [--protocol release] [--track oracle]
                         [--split SPLIT] [--allow-dirty] [--out reports/paper-tables.md]

Reads results files only (no fit): see :mod:`benchmark.paper_tables`. Results from a checkout with
uncommitted code changes, or whose code changed during the run, are refused unless ``--allow-dirty``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import add_protocol_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--results-dir", type=Path, default=Path("results"))
    parser.add_argument("--reports-dir", type=Path, default=Path("reports"),
                        help="where the query-speed reports are read from")
    add_protocol_argument(parser)
    parser.add_argument("--track", choices=("oracle", "real"), default="oracle")
    parser.add_argument("--split", default=None,
                        help="the split of our runs (default: the paper's where results have it, else the first "
                             "of novel-view, legacy-dense with results)")
    parser.add_argument("--allow-dirty", action="store_true",
                        help="read results from a checkout with uncommitted code changes or whose code changed during "
                             "the run (the header counts them) instead of refusing them")
    parser.add_argument("--out", type=Path, default=Path("reports/paper-tables.md"))


def run(args: argparse.Namespace) -> int:
    from benchmark.core.atomic import write_text
    from benchmark.core.outputs import guard_output
    from ..paper_tables import render, speed_report_files

    # never over a results file or a speed report it reads (nor a link of one)
    guard_output(args.out, [args.results_dir, *speed_report_files(args.reports_dir)], option="--out")
    text = render(args.results_dir, args.reports_dir, protocol=args.protocol, track=args.track, split=args.split,
                  allow_dirty=args.allow_dirty)
    write_text(args.out, text)
    print(text)
    print(f"wrote {args.out}")
    return 0
