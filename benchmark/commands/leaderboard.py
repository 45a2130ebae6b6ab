"""``bench4d leaderboard``: regenerate ``leaderboard.md`` (and ``reports/*.csv``) from results files.

    bench4d leaderboard [--results-dir results] [--out leaderboard.md] [--reports-dir reports] [--csv-dir DIR]
                        [--ceiling FILE] [--allow-dirty]

Without ``--out`` the command regenerates the repository's leaderboard: ``leaderboard.md`` and the CSVs in
``--reports-dir``. With ``--out`` it writes that file only, and CSVs only where ``--csv-dir`` says (a second
leaderboard never replaces the main one's ``reports/runs.csv``).

Results from a checkout with uncommitted code changes, or whose code changed during the run, are refused
unless ``--allow-dirty`` is given; then they are shown and marked.

Deterministic: the same results files give byte-identical outputs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

DEFAULT_OUT = Path("leaderboard.md")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--results-dir", type=Path, default=Path("results"))
    parser.add_argument("--out", type=Path, default=None,
                        help=f"the Markdown leaderboard (default: {DEFAULT_OUT}, with the CSVs in --reports-dir); "
                             "given, only this file is written unless --csv-dir is given too")
    parser.add_argument("--reports-dir", type=Path, default=Path("reports"),
                        help="the reports the leaderboard links to and reads the ceiling from; without --out its CSVs "
                             "go here too")
    parser.add_argument("--csv-dir", type=Path, default=None,
                        help="where the CSVs go (runs.csv, one per table, paper_numbers.csv)")
    parser.add_argument("--ceiling", type=Path, default=None,
                        help="the protocol ceiling's JSON (default: <reports-dir>/ablations/protocol-ceiling.json)")
    parser.add_argument("--allow-dirty", action="store_true",
                        help="show results from a checkout with uncommitted code changes or whose code changed during "
                             "the run (marked) instead of refusing them")


def run(args: argparse.Namespace) -> int:
    from ..leaderboard import build_leaderboard

    # no file written replaces one it reads (a results file, the ceiling; links of them; places inside the
    # results folder): build_leaderboard guards every output before it reads anything
    csv_dir = args.csv_dir if args.csv_dir is not None or args.out is not None else args.reports_dir
    written = build_leaderboard(args.results_dir, markdown=args.out or DEFAULT_OUT, reports_dir=args.reports_dir,
                                ceiling=args.ceiling, csv_dir=csv_dir, allow_dirty=args.allow_dirty)
    for path in written.values():
        print(path)
    return 0
