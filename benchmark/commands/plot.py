"""``bench4d plot``: charts into ``reports/`` (PNG and PDF).

    bench4d plot pareto   [--results-dir results] [--reports-dir reports] [--ceiling FILE]
    bench4d plot timeline --method M [M ...] --scene S --query Q [--track oracle] [--seed 0]
    bench4d plot capacity  [--table reports/capacity/capacity.csv] [--out reports/capacity]
    bench4d plot stability [--table reports/stability/scores.csv] [--out reports/stability]

``capacity`` and ``stability`` redraw the charts of ``bench4d ablate capacity`` and ``bench4d stress`` from
their written tables, without running anything.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ._common import parse_seed


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="chart", metavar="CHART", required=True)
    p = sub.add_parser("pareto", help="accuracy vs query FPS and vs fit time, Pareto front drawn; one chart "
                                      "per kind of machine, floors and the perfect-feature ceiling as lines")
    _common(p)
    p.add_argument("--ceiling", type=Path, default=None,
                   help="the protocol ceiling's JSON (bench4d ablate ceiling; default: "
                        "<reports-dir>/ablations/protocol-ceiling.json); no ceiling line without it")
    t = sub.add_parser("timeline", help="one time-sensitive query's similarity over time (paper Fig. 4 analogue)")
    _common(t)
    t.add_argument("--method", required=True, nargs="+",
                   help="one or more methods: one panel each (e.g. deformable-clip 4d-langsplat)")
    t.add_argument("--scene", required=True, help="scene name (as in the results folder)")
    t.add_argument("--query", required=True, help="time-sensitive query text")
    t.add_argument("--track", default="oracle")
    t.add_argument("--seed", type=parse_seed, default=0)
    t.add_argument("--dataset", default=None, help="dataset folder, when a scene name exists in several")
    c = sub.add_parser("capacity", help="capacity curves (accuracy and cost against each knob) from capacity.csv")
    c.add_argument("--table", type=Path, default=Path("reports/capacity/capacity.csv"))
    c.add_argument("--out", type=Path, default=Path("reports/capacity"), help="charts go to <out>/charts/")
    st = sub.add_parser("stability", help="stress-suite charts (each metric against strength) from scores.csv")
    st.add_argument("--table", type=Path, default=Path("reports/stability/scores.csv"))
    st.add_argument("--out", type=Path, default=Path("reports/stability"), help="charts go to <out>/charts/")


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--results-dir", type=Path, default=Path("results"))
    p.add_argument("--reports-dir", type=Path, default=Path("reports"))


def run(args: argparse.Namespace) -> int:
    from .. import plots

    if args.chart == "pareto":
        written = plots.pareto(args.results_dir, args.reports_dir, ceiling=args.ceiling)
    elif args.chart == "capacity":
        from benchmark.studies.capacity import charts_from_csv

        written = charts_from_csv(args.table, args.out)
    elif args.chart == "stability":
        from benchmark.studies.stress_plots import charts_from_csv

        written = charts_from_csv(args.table, args.out)
    else:
        written = plots.timeline(args.method, args.scene, args.query, results_dir=args.results_dir,
                                 reports_dir=args.reports_dir, track=args.track, seed=args.seed, dataset=args.dataset)
    for path in written:
        print(path)
    return 0
