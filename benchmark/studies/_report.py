"""What every study's report shares: Markdown tables, the JSON + Markdown pair written atomically, log lines
and progress bars that ``quiet`` turns off, and number cells."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from benchmark.core.atomic import write_json, write_text


@dataclass
class Report:
    """A study's written report."""

    table: str
    """The report's Markdown, as written to its ``.md`` file."""
    paths: list[Path] = field(default_factory=list)
    """The files written: the JSON document, then the Markdown."""


def keep_replaced_table(path: Path, before: set, after: set) -> Optional[Path]:
    """Before a study's table at ``path`` is rewritten: when the rows it holds (``before``, their keys) are
    not all among the new table's (``after``), copy it beside as ``<stem>-replaced-<UTC time><suffix>`` and
    return that path, so no measurement is lost by rewriting (a report made from an emptied cache, a run
    gone stale). None when nothing is dropped or there is no table."""
    import shutil
    import time

    path = Path(path)
    if not path.is_file() or before <= after:
        return None
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    kept = path.with_name(f"{path.stem}-replaced-{stamp}{path.suffix}")
    shutil.copy2(path, kept)
    return kept


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A Markdown table of string cells, one line per row, ending in a newline."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def write_report(out: Path, stem: str, doc: dict, table: str) -> list[Path]:
    """Write ``<out>/<stem>.json`` (``doc``; one value a line, unindented: half the size, diffs still by
    line) and ``<out>/<stem>.md`` (``table``) atomically, the folder made if missing; returns both paths."""
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / f"{stem}.json", doc, indent=0)
    write_text(out / f"{stem}.md", table)
    return [out / f"{stem}.json", out / f"{stem}.md"]


def stderr_log(quiet: bool) -> Callable[[str], None]:
    """A log that prints each line to stderr, or nothing when ``quiet``."""
    def log(message: str) -> None:
        if not quiet:
            print(message, file=sys.stderr)

    return log


def progress_bars(quiet: bool) -> Optional[Callable]:
    """The methods' progress bar (``progress_bar(iterable, **kwargs)``, bars cleared when done), or
    ``None`` when ``quiet``: the form the supervision and captioning code take as ``progress``."""
    if quiet:
        return None
    from methods.api import progress_bar  # here, not above: `bench4d ablate --help` imports this module


    def bar(iterable=None, **kwargs):
        return progress_bar(iterable, leave=False, **kwargs)

    return bar


def number_cell(value, digits: int = 2) -> str:
    """``value`` with ``digits`` decimals, or ``–`` when missing (``None`` or NaN)."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return f"{value:.{digits}f}"
