"""``bench4d slim``: results files as the committed tree keeps them.

    bench4d slim results/synthetic/americano [more files or folders ...] [--dry-run]

A results file as ``eval`` writes it holds, besides its metrics and per-query scores, one record per
(query, frame) and a predictions folder beside it (the answered masks). The leaderboard, the paper tables,
the Pareto charts and the studies' tables read only the former; the timeline chart, ``ablate decisions``,
``ablate rescore`` and ``score`` on the run's folder need the latter. ``slim`` keeps the former and drops the
latter (the per-frame records become their count, ``scores.frames_dropped``), so a finished sweep can be
committed at a fraction of its size while the full files stay where the run wrote them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from benchmark.core.errors import InputError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("paths", nargs="+", type=Path, help="results files, or folders searched for seed*.json")
    parser.add_argument("--dry-run", action="store_true", help="list the files that would change, change nothing")


def results_files(paths: list[Path]) -> list[Path]:
    """The results files named by ``paths`` (folders searched, prediction folders skipped), in order."""
    found: list[Path] = []
    for path in paths:
        if path.is_file():
            found.append(path)
        elif path.is_dir():
            found.extend(p for p in sorted(path.rglob("seed*.json"))
                         if not any(part.endswith(".predictions") for part in p.parts))
        else:
            raise InputError(path, None, "no such file or folder")
    return found


def run(args: argparse.Namespace) -> int:
    from benchmark.results import needs_slimming, read_results, slim_results

    files = results_files(args.paths)
    freed = 0
    for path in files:
        if args.dry_run:
            if needs_slimming(path, read_results(path)):
                print(f"would slim {path}")
            continue
        freed += slim_results(path)
    if not args.dry_run:
        print(f"slim: {len(files)} results file(s), {freed / 2 ** 20:.1f} MiB freed")
    return 0
