"""The one output guard every command that writes calls first: nothing a command read is replaced by
what it writes.

:func:`guard_output` refuses a target (a file to write, or a folder to write into) that is, once links
are resolved, an input file or a hard link of one, or that lies in an input folder: given as such,
reached through a symbolic link inside one (``masks/<query> -> elsewhere/``), or written through a
symlinked folder. Scene folders, prediction folders, release run folders and annotation folders are
input folders; each is walked once (links followed, each real folder once), so a file a command reads
through a link is known by its real place and its inode.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable

from .errors import InputError

MAX_WALK_ENTRIES = 500_000
"""Entries walked per input folder at most (a scene has a few thousand); beyond, the folder itself (and
every folder reached so far) still guards its subtree."""


def _real(path: Path) -> Path:
    try:
        return Path(os.path.realpath(path))
    except (OSError, RuntimeError, ValueError):
        return Path(os.path.abspath(path))


def _identity(path: Path):
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


def _within(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


class InputSet:
    """The files and folders a command reads, resolved once (see the module docstring)."""

    def __init__(self, inputs: Iterable[str | Path]):
        self.given_folders: list[Path] = []
        self.real_folders: list[Path] = []
        self.real_files: set[Path] = set()
        self.inodes: set[tuple[int, int]] = set()
        for item in inputs:
            if item is None:
                continue
            path = Path(item)
            if path.is_dir():
                self._add_folder(path)
            else:
                self.real_files.add(_real(path))
                ident = _identity(path)
                if ident is not None:
                    self.inodes.add(ident)

    def _add_folder(self, folder: Path) -> None:
        self.given_folders.append(Path(os.path.abspath(folder)))
        seen: set[Path] = set()
        entries = 0
        for dirpath, dirnames, filenames in os.walk(folder, followlinks=True):
            real = _real(Path(dirpath))
            if real in seen:  # a link loop, or one folder reached twice: walk it once
                dirnames[:] = []
                continue
            seen.add(real)
            self.real_folders.append(real)
            for name in filenames:
                entries += 1
                ident = _identity(Path(dirpath) / name)
                if ident is not None:
                    self.inodes.add(ident)
            entries += len(dirnames)
            if entries > MAX_WALK_ENTRIES:
                break

    def holds(self, target: Path) -> bool:
        """Whether writing ``target`` could replace (or land among) what was read."""
        lexical = Path(os.path.abspath(target))
        real = _real(target)
        if real in self.real_files:
            return True
        ident = _identity(target)
        if ident is not None and ident in self.inodes:
            return True
        if any(_within(lexical, f) for f in self.given_folders):
            return True
        return any(_within(real, f) for f in self.real_folders)


def guard_output(target: str | Path, inputs: "Iterable[str | Path] | InputSet", *, option: str = "--out") -> None:
    """Refuse (:class:`InputError` naming ``option``) a ``target`` that resolves, through symbolic or hard
    links, to any of ``inputs``' files or into any of ``inputs``' folders (module docstring). ``inputs``
    are files and folders a command reads (``None`` entries are skipped), or an :class:`InputSet` of them
    made once for several targets (each folder walked once). Call it before anything is read or computed,
    so that a refused path costs nothing."""
    target = Path(target)
    inputs = inputs if isinstance(inputs, InputSet) else InputSet(inputs)
    if inputs.holds(target):
        raise InputError(target, option, "is an input of this command or lies among its inputs (an input file, "
                                         "a hard or symbolic link of one, or a place inside an input folder); "
                                         "give a path outside them")
