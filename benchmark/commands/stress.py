"""``bench4d stress``: the stress suite (where methods fail), written to ``reports/stability/``.

    bench4d stress [--preset split-cookie] [--size 96] [--frames 60] [--methods M ...] [--families F ...]
                   [--strengths S ...] [--seeds 0 1 2] [--split novel-view] [--schedule default]
                   [--set [METHOD:]KEY=VALUE ...]

The defaults are the suite's base: split-cookie at 96 px, 60 frames, the methods' own schedules, novel views.
That is the smallest image size, of 64, 96 and 128 px, at which every fitted method that clears both floors at
the leaderboard's 128 px clears them too (the shared CLIP field of the 4D heads, langsplat and Gaussian
Grouping; Feature-3DGS clears neither floor at any size measured, and no time head clears the floor's Acc).

Families x strengths x methods x seeds (:mod:`benchmark.studies.stress`); a run whose results file
exists is read, not redone (``--force`` redoes it), so an interrupted suite resumes. So is a run the
report's ``scores.csv`` keeps with today's scene and config digests: a suite split over machines, or run
again after the cache was cleared, adds to the table rather than starting over. Suites started side by
side on one cache (one per core) share the runs out: a run another one is making is left to it and read at
the end. ``--report-only`` writes
the charts, galleries and tables from the runs present (a gallery whose runs' results files are not here
is kept as drawn).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from benchmark.core.errors import InputError
from ._common import add_threads_argument, check_device, parse_overrides, parse_seed, set_threads

_SHORT_FIELD = {"autoencoder.min_steps": "1500", "autoencoder.max_steps": "2000", "field.iterations": "400"}
_SHORT_TIME_VARYING = {**_SHORT_FIELD, "caption_autoencoder.min_steps": "1500", "caption_autoencoder.max_steps": "2000",
                       "status.static_iterations": "100", "status.iterations": "800"}
SHORT_SCHEDULES: dict[str, dict[str, str]] = {
    "langsplat": _SHORT_FIELD,
    "deformable-clip": _SHORT_FIELD,
    "4d-langsplat": _SHORT_TIME_VARYING,
    "non-status-field": _SHORT_TIME_VARYING,
    "feature-3dgs": {"feature.iterations": "400"},
    "gaussian-grouping": {"identity.iterations": "500"},
}
SHORT_SCHEDULES.update({name + "+": schedule for name, schedule in list(SHORT_SCHEDULES.items())})  # the variants
"""``--schedule short``: option overrides per method that make a CPU suite cheaper: autoencoder, field and
head steps cut about fivefold, the geometry left at the methods' own schedule. The geometry is what a cut
breaks: measured on ``smoke`` (48 px, 16 frames, seed 0), ``4d-langsplat`` scores mIoU / Acc /
vIoU 53.8 / 100 / 59.7 with its own schedule, 51.3 / 100 / 58.4 with these cuts, 44.8 / 100 / 42.5 with the
geometry's 4D stage halved (500 + 1 000 iterations) and 10.1 / 68.8 / 9.3 with it at 300 + 300: a base that
is already broken has no breaking point to find. The 4D methods' geometry options are equal, so they share
one 4D-GS fit per scene and seed, and ``deformable-clip`` / ``non-status-field`` share ``4d-langsplat``'s
field."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from benchmark.core.scene import EVAL_SPLITS
    from benchmark.studies.stress import SUITE_METHODS
    from benchmark.synthetic.perturb import FAMILIES

    parser.add_argument("--preset", default="split-cookie", help="base preset every perturbation is applied to")
    parser.add_argument("--size", type=int, default=96, help="image width of the generated scenes")
    parser.add_argument("--frames", type=int, default=60, help="video length of the generated scenes")
    parser.add_argument("--methods", nargs="+", default=list(SUITE_METHODS),
                        help="methods run (default: both floors and the six paper methods)")
    parser.add_argument("--families", nargs="+", default=list(FAMILIES), metavar="FAMILY",
                        help=f"perturbation families (default: all: {', '.join(FAMILIES)})")
    parser.add_argument("--strengths", nargs="+", type=float, default=None,
                        help="strengths of every family (default: each family's own; 0 is always run)")
    parser.add_argument("--strongest-only", action="store_true",
                        help="each family's clean end and strongest strength only: a screen of which families "
                             "break a method or separate two (breaking points read '≤ s')")
    parser.add_argument("--seeds", nargs="+", type=parse_seed, default=[0, 1, 2],
                        help="seeds: seed s generates the scene with scene seed s and fits on it with seed s")
    parser.add_argument("--split", choices=EVAL_SPLITS, default="novel-view",
                        help="evaluation split the runs score (default novel-view: scored views off the "
                             "training path, a question the nearest training frame cannot answer)")
    parser.add_argument("--schedule", choices=("short", "default"), default="default",
                        help="short: the methods' step counts cut for a CPU suite (SHORT_SCHEDULES); default: "
                             "the methods' own")
    parser.add_argument("--set", action="append", default=[], metavar="[METHOD:]KEY=VALUE",
                        help="a method option by its dotted path, for METHOD only or every method (repeatable)")
    parser.add_argument("--out-dir", type=Path, default=Path("reports/stability"))
    parser.add_argument("--cache-dir", type=Path, default=Path("cache"),
                        help="generated scenes, fits and the suite's results files (<cache>/stress/...)")
    parser.add_argument("--device", default="cpu", help="cpu or cuda[:N]")
    parser.add_argument("--force", action="store_true", help="rerun even where a results file exists")
    parser.add_argument("--report-only", action="store_true", help="write the reports from the runs present")
    add_threads_argument(parser)


def method_options(methods: list[str], schedule: str, items: list[str]) -> dict[str, dict[str, str]]:
    """Method -> option overrides: the schedule's, then ``--set`` (``METHOD:KEY=VALUE`` for one method)."""
    out = {m: dict(SHORT_SCHEDULES.get(m, {})) if schedule == "short" else {} for m in methods}
    for item in items:
        scope, sep, rest = item.partition(":")
        if sep and "=" not in scope:
            if scope not in out:
                raise InputError(None, "--set", f"{scope!r} is not one of --methods {methods}")
            out[scope].update(parse_overrides([rest]))
        else:
            for m in methods:
                out[m].update(parse_overrides([item]))
    return {m: o for m, o in out.items() if o}


def run(args: argparse.Namespace) -> int:
    from benchmark.studies import stress, stress_plots
    from benchmark.synthetic.perturb import family

    for name in args.families:
        family(name)
    check_device(args.device)
    set_threads(args.threads)
    config = stress.SuiteConfig(
        preset=args.preset, size=args.size, frames=args.frames, methods=tuple(args.methods),
        families=tuple(args.families), strengths=None if args.strengths is None else tuple(args.strengths),
        strongest_only=args.strongest_only,
        seeds=tuple(args.seeds), split=args.split, method_options=method_options(args.methods, args.schedule, args.set),
        out_dir=args.out_dir, cache_dir=args.cache_dir, device=args.device, force=args.force)
    start = time.perf_counter()
    scores = stress.collect(config) if args.report_only else stress.run_suite(config)
    wall = None if args.report_only else time.perf_counter() - start
    for path in stress_plots.write_reports(config, scores, wall_seconds=wall):
        print(path)
    return 0
