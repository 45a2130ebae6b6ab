"""``bench4d leaderboard``: regenerate ``leaderboard.md`` and ``reports/*.csv`` from results files.

    bench4d leaderboard [--results-dir results] [--out leaderboard.md] [--reports-dir reports] [--csv-dir DIR]

A second leaderboard (another results folder, ``--out`` elsewhere) takes ``--csv-dir`` so that its CSVs do not
replace the main leaderboard's ``reports/runs.csv``.

Deterministic: the same results files give byte-identical outputs.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--results-dir", type=Path, default=Path("results"))
    parser.add_argument("--out", type=Path, default=Path("leaderboard.md"), help="the Markdown leaderboard")
    parser.add_argument("--reports-dir", type=Path, default=Path("reports"),
                        help="the reports the leaderboard links to and reads the ceiling from; its CSVs go here too "
                             "unless --csv-dir says elsewhere")
    parser.add_argument("--csv-dir", type=Path, default=None,
                        help="where the CSVs go (runs.csv, one per table, paper_numbers.csv; default: --reports-dir)")
    parser.add_argument("--ceiling", type=Path, default=None,
                        help="the protocol ceiling's JSON (default: <reports-dir>/ablations/protocol-ceiling.json)")


def run(args: argparse.Namespace) -> int:
    from ..leaderboard import build_leaderboard

    written = build_leaderboard(args.results_dir, markdown=args.out, reports_dir=args.reports_dir,
                                ceiling=args.ceiling, csv_dir=args.csv_dir)
    for path in written.values():
        print(path)
    return 0
