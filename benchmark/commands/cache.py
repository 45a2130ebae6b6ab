"""``bench4d cache``: what the cache folder holds, and pruning it.

    bench4d cache [--cache-dir cache]                     # size per kind, leftovers of interrupted runs
    bench4d cache --prune leftovers [--older-than 24]     # delete those leftovers
    bench4d cache --prune unreferenced [--results-dir results]
                                                          # delete fitted models no results file names
    ... --dry-run                                         # list what would go, delete nothing

The cache holds generated presets, 2D supervision, captions, fitted geometries and language fields
(``language/``, shared between methods) and each method's fit (``fits/``). Nothing in it is lost
work except two kinds of file, which pruning never touches unless asked:

* **leftovers** of interrupted runs: a geometry fit's checkpoint (``*.partial.pt``, from which the
  same command resumes), a fit's working folder (``*.work``), a half-written fit (``.*.partial-*``), a
  half-generated scene (``.*.staging-*``) and a scene being checked or replaced against the generator's
  code (``.*.check-*``, ``.*.replaced-*``, ``.*.damaged-*``).
  Only those older than ``--older-than`` hours go: a running geometry fit rewrites its checkpoint
  every two minutes, so an old one belongs to no live process (it is still resumable: keep it if you
  mean to rerun that command).
* **unreferenced** fits: entries of ``fits/`` and the geometries and fields of ``language/`` whose key
  no results file under ``--results-dir`` names (archived and ablation results included, and the
  demo's). Presets, supervision and captions are never pruned (captions from a real captioner are
  the costliest thing here); delete those by hand.
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import re
import shutil
import time
from pathlib import Path
from typing import Iterable, Optional

LEFTOVER_PATTERNS = ("*.partial.pt", "*.work", ".*.partial-*", ".*.staging-*", ".*.check-*", ".*.replaced-*",
                     ".*.damaged-*")
"""Glob patterns of what interrupted runs leave behind (see the module docstring)."""
_MODEL_FILE = re.compile(r"^(geometry|field)-(3dgs|4dgs)-([0-9a-f]+)\.pt$")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cache-dir", type=Path, default=Path("cache"), help="the cache folder (default: cache)")
    parser.add_argument("--results-dir", type=Path, default=Path("results"),
                        help="results whose fits count as referenced (--prune unreferenced)")
    parser.add_argument("--prune", choices=("leftovers", "unreferenced"), default=None,
                        help="leftovers: checkpoints and working folders of interrupted runs; unreferenced: "
                             "fitted models no results file names (default: only report)")
    parser.add_argument("--older-than", type=float, default=24.0,
                        help="hours: prune only what was last written longer ago than this")
    parser.add_argument("--dry-run", action="store_true", help="list what would be deleted, delete nothing")


def _size(path: Path) -> int:
    if path.is_file() or path.is_symlink():
        return path.lstat().st_size
    return sum(p.lstat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())


def _mtime(path: Path) -> float:
    """Last write under ``path``: a folder counts its newest file (its own time if it has none)."""
    times = [p.lstat().st_mtime for p in path.rglob("*") if p.is_file()] if path.is_dir() else []
    return max(times) if times else path.lstat().st_mtime


def leftovers(cache_dir: Path) -> list[Path]:
    """Leftovers of interrupted runs under ``cache_dir`` (:data:`LEFTOVER_PATTERNS`), outermost only."""
    found: set[Path] = set()
    for pattern in LEFTOVER_PATTERNS:
        found.update(cache_dir.rglob(pattern))
    return sorted(p for p in found if not any(q in found for q in p.parents))


def fitted_models(cache_dir: Path) -> list[tuple[Path, str]]:
    """``(path, key)`` of every fitted model: ``fits/<method>/<scene>/<key>/`` and
    ``language/<scene>/{geometry,field}-<kind>-<key>.pt``."""
    models = []
    fits = cache_dir / "fits"
    if fits.is_dir():
        for entry in fits.glob("*/*/*"):
            if entry.is_dir() and (entry / "fit.json").is_file() and not entry.name.startswith("."):
                models.append((entry, entry.name))
    language = cache_dir / "language"
    if language.is_dir():
        for entry in language.glob("*/*.pt"):
            match = _MODEL_FILE.match(entry.name)
            if match:
                models.append((entry, match.group(3)))
    return sorted(models)


def referenced_keys(results_dirs: Iterable[Path]) -> set[str]:
    """Fit, geometry and field keys that results files name (every ``seed*.json`` below the folders,
    archive and ablations included). A results file that cannot be read stops the command: pruning
    on a partial view could delete what it names."""
    from benchmark.core.errors import InputError

    keys: set[str] = set()
    for root in results_dirs:
        if not root.is_dir():
            continue
        for path in root.rglob("seed*.json"):
            try:
                doc = json.loads(path.read_text())
            except (OSError, ValueError) as err:
                raise InputError(path, None, f"unreadable results file ({err}); nothing pruned") from err
            fit = doc.get("fit") if isinstance(doc, dict) else None
            if not isinstance(fit, dict):
                continue
            info = fit.get("info") if isinstance(fit.get("info"), dict) else {}
            geometry = info.get("geometry") if isinstance(info.get("geometry"), dict) else {}
            for key in (fit.get("key"), fit.get("head_refit_of"), info.get("key"), geometry.get("key")):
                if isinstance(key, str) and key:
                    keys.add(key)
    return keys


def _kind(cache_dir: Path, path: Path) -> str:
    parts = path.relative_to(cache_dir).parts
    if any(fnmatch.fnmatch(part, pattern) for part in parts for pattern in LEFTOVER_PATTERNS):
        return "leftovers"
    if parts[0] == "language" and len(parts) > 2:
        match = _MODEL_FILE.match(parts[-1])
        return f"language/{match.group(1)}" if match else "language/other"
    return parts[0]


def _mib(n: int) -> str:
    return f"{n / 2 ** 20:,.1f}"


def _report(cache_dir: Path) -> None:
    totals: dict[str, list[int]] = {}
    for path in sorted(cache_dir.rglob("*")):
        if path.is_file() and not path.is_symlink():
            entry = totals.setdefault(_kind(cache_dir, path), [0, 0])
            entry[0] += 1
            entry[1] += path.lstat().st_size
    print(f"{cache_dir}: {_mib(sum(v[1] for v in totals.values()))} MiB in {sum(v[0] for v in totals.values())} files")
    for kind, (count, size) in sorted(totals.items()):
        print(f"  {kind:<22} {count:>6} files  {_mib(size):>10} MiB")
    left = leftovers(cache_dir)
    if left:
        now = time.time()
        print(f"leftovers of interrupted runs ({len(left)}; `--prune leftovers` deletes those older than --older-than):")
        for path in left:
            print(f"  {path}  {_mib(_size(path))} MiB, last written {(now - _mtime(path)) / 3600:.1f} h ago")


def _delete(paths: list[Path], dry_run: bool) -> int:
    freed = 0
    for path in paths:
        size = _size(path)
        print(f"{'would delete' if dry_run else 'deleted'} {path} ({_mib(size)} MiB)")
        if not dry_run:
            if path.is_dir():
                shutil.rmtree(path)
            else:
                path.unlink()
        freed += size
    return freed


def prune(cache_dir: Path, what: str, *, older_than_hours: float, results_dirs: Optional[list[Path]] = None,
          dry_run: bool = False) -> list[Path]:
    """Delete (or with ``dry_run`` only list) ``what`` (``"leftovers"`` or ``"unreferenced"``) last written
    more than ``older_than_hours`` ago; returns the paths."""
    cutoff = time.time() - older_than_hours * 3600.0
    if what == "leftovers":
        candidates = leftovers(cache_dir)
    elif what == "unreferenced":
        keys = referenced_keys(results_dirs or [])
        candidates = [path for path, key in fitted_models(cache_dir) if key not in keys]
    else:
        raise ValueError(f"prune what: 'leftovers' or 'unreferenced', not {what!r}")
    chosen = [p for p in candidates if _mtime(p) < cutoff]
    freed = _delete(chosen, dry_run)
    print(f"{'would free' if dry_run else 'freed'} {_mib(freed)} MiB ({len(chosen)} of {len(candidates)} {what}; "
          f"{len(candidates) - len(chosen)} written in the last {older_than_hours:g} h kept)")
    return chosen


def run(args: argparse.Namespace) -> int:
    from benchmark.core.errors import InputError

    cache_dir = Path(args.cache_dir)
    if not cache_dir.is_dir():
        raise InputError(cache_dir, None, "no such cache folder")
    if args.older_than < 0:
        raise InputError(None, "--older-than", f"hours must be >= 0, got {args.older_than}")
    if args.prune is None:
        _report(cache_dir)
        return 0
    results_dirs = [Path(args.results_dir), cache_dir / "demo-results"]
    if args.prune == "unreferenced" and not Path(args.results_dir).is_dir():
        raise InputError(args.results_dir, None, "no such results folder: every fit would count as unreferenced")
    prune(cache_dir, args.prune, older_than_hours=args.older_than, results_dirs=results_dirs, dry_run=args.dry_run)
    return 0
