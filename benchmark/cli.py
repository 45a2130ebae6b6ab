"""``bench4d``: one entry point, subcommands loaded lazily.

Each subcommand lives in its own module under :mod:`benchmark.commands` and exposes
``add_arguments(parser)`` and ``run(args) -> int``. Modules are imported only when their command runs,
so ``bench4d --help`` stays fast and an optional backend missing breaks only the command that needs it.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from benchmark.core.errors import InputError
from benchmark.core.strict import terminal_text

# command name -> (module under benchmark.commands, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "data": ("data", "make, validate and show scenes (make-synthetic, validate, show)"),
    "score": ("score", "score prediction files against ground-truth annotations"),
    "convert": ("convert", "another release's outputs (4D LangSplat's rendered masks, time decisions) as bench4d predictions"),
    "recon": ("recon", "reconstruct a scene with 3D-GS / 4D-GS and report PSNR, SSIM, time, memory"),
    "methods": ("methods", "list registered methods and supervision sources"),
    "eval": ("eval", "fit a method on a scene, answer every annotated query, score and record"),
    "run-all": ("run_all", "evaluate methods x scenes x seeds; mean and spread over seeds"),
    "leaderboard": ("leaderboard", "regenerate leaderboard.md and reports/*.csv from results"),
    "paper-tables": ("paper_tables", "every table of the paper with the published numbers beside ours"),
    "plot": ("plot", "charts: pareto (accuracy vs speed), timeline (similarity over time), capacity, stability"),
    "annotate": ("annotate", "local web app to annotate query masks and time segments"),
    "annotate-bench": ("annotate_bench", "the annotation tool measured by a simulated annotator against exact truth"),
    "models": ("models", "the real track's model backends: hub ids, sizes, where weights are looked for, present or not"),
    "doctor": ("doctor", "before a long run: CUDA, gsplat, libraries, weights, free disk and memory, one line each"),
    "demo": ("demo", "the main job: a synthetic scene end to end, printing metrics and timings"),
    "cache": ("cache", "what the cache folder holds; prune leftovers of interrupted runs or unreferenced fits"),
    "slim": ("slim", "results files as the committed tree keeps them: per-frame records and predictions dropped"),
    "ablate": ("ablate", "analyses: protocol ceiling, rescore under another protocol, gap, autoencoder, states (K), "
                         "delta-sim (caption prompts), decisions, speed, query-speed"),
    "stress": ("stress", "the stress suite: perturbation families x strengths x methods x seeds, breaking points"),
}

RECORDING_COMMANDS = frozenset({"eval", "run-all", "recon", "ablate", "demo", "stress"})
"""Commands whose outputs record the git state of the code that produced them."""


def os_error_line(err: OSError) -> str:
    """An ``OSError`` as one line: the file(s) it names, then what went wrong."""
    what = err.strerror or " ".join(str(err).split()) or type(err).__name__
    names = [str(n) for n in (err.filename, err.filename2) if n is not None]
    return f"{' -> '.join(names)}: {what}" if names else what


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="bench4d", description="bench4d: open-vocabulary 4D language field benchmark")
    from . import __version__

    parser.add_argument("--version", action="version", version=f"bench4d {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    wanted = next((a for a in argv if not a.startswith("-")), None)
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == wanted:
            mod = importlib.import_module(f"benchmark.commands.{module}")
            mod.add_arguments(p)
            p.set_defaults(_run=mod.run)
    if wanted is not None and wanted not in COMMANDS:
        import difflib

        close = difflib.get_close_matches(wanted, COMMANDS, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        parser.error(f"unknown command {wanted!r}{hint}")
    args = parser.parse_args(argv)
    args._argv = argv  # the command line as given (``main([...])`` from Python included), for records
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    if args.command in RECORDING_COMMANDS:
        from .runner import git_state

        git_state()  # records name the commit a command started on, however long it runs
    try:
        return int(args._run(args) or 0)
    except InputError as err:
        print(f"bench4d {args.command}: error: {terminal_text(err)}", file=sys.stderr)
        return 2
    except OSError as err:  # a full disk, a read-only folder, a vanished file: one line, never a traceback
        print(f"bench4d {args.command}: error: {terminal_text(os_error_line(err))}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
