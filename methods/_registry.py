"""One lazy registry for every kind of pluggable part: methods, supervision sources, captioners, text
encoders.

An entry is a small, import-free description (a spec) whose ``entry_point`` names its code as
``"module:attr"``; the module is imported only when the entry is used (:func:`import_entry_point`), so
listing what is registered loads nothing heavy and a missing optional backend breaks only the runs that
use it. Unknown names raise :class:`~benchmark.core.errors.InputError` with a "did you mean".

Entries can come from a discovery function (spec files, read on first use) or be registered by hand.
An entry point is a string, not an import, so a code digest of the code that uses a registry does not
reach the entries' modules: :func:`entry_point_modules` lists them (a method's fit key includes the
captioners its time-varying head loads by name).
"""

from __future__ import annotations

import ast
import difflib
import functools
import importlib
import importlib.util
import re
import threading
from typing import Callable, Generic, Iterable, Optional, Protocol, TypeVar

from benchmark.core.cache_keys import PROJECT_PACKAGES, code_modules
from benchmark.core.errors import InputError


class Entry(Protocol):
    """What a registry holds: a name and the ``"module:attr"`` of its code."""

    name: str
    entry_point: str


T = TypeVar("T", bound=Entry)

ENTRY_POINT = re.compile(r"^([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*):([A-Za-z_]\w*)$")
"""A ``"module:attr"`` entry point."""


def import_entry_point(entry_point: str, where: str, needs: str = "") -> object:
    """The object ``entry_point`` (``"module:attr"``) names, its module imported now. ``where`` names the
    entry in errors; ``needs`` says what an import failure may lack (e.g. an optional package)."""
    match = ENTRY_POINT.match(entry_point)
    if match is None:
        raise ValueError(f"{where}: entry point must be 'module:attr', got {entry_point!r}")
    module_name, attr = match.groups()
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        hint = f"; it needs {needs}" if needs else ""
        raise InputError(None, where, f"cannot import {module_name}: {err}{hint}") from err
    try:
        return getattr(module, attr)
    except AttributeError:
        raise InputError(None, where, f"{module_name} has no attribute {attr!r}") from None


class Registry(Generic[T]):
    """Entries of one kind by name, in the order registered; a discovery function (when given) adds its
    entries on first use."""

    def __init__(self, what: str, discover: Optional[Callable[[], Iterable[T]]] = None) -> None:
        self.what = what
        """What an entry is, in messages: ``"method"``, ``"captioner"``, ``"segmenter source"``..."""
        self._discover = discover
        self._discovered = discover is None
        self._entries: dict[str, T] = {}
        # discovery registers through register(), which comes back here: reentrant, and other threads wait for it
        self._lock = threading.RLock()
        self._discovering = False

    def _ensure_discovered(self) -> None:
        if self._discovered:
            return
        with self._lock:  # another thread waits here until the entries are in
            if self._discovered or self._discovering:  # done meanwhile, or this thread's discovery registering
                return
            self._discovering = True
            try:
                for entry in self._discover():
                    self.register(entry)
                self._discovered = True
            finally:
                self._discovering = False

    def register(self, entry: T, *, replace: bool = False) -> T:
        """Add ``entry``; a different entry of the same name raises ``ValueError`` unless ``replace``."""
        self._ensure_discovered()
        if not ENTRY_POINT.match(entry.entry_point):
            raise ValueError(f"{self.what} {entry.name!r}: entry point must be 'module:attr', "
                             f"got {entry.entry_point!r}")
        known = self._entries.get(entry.name)
        if known is not None and known != entry and not replace:
            raise ValueError(f"{self.what} {entry.name!r} is already registered")
        self._entries[entry.name] = entry
        return entry

    def unregister(self, name: str) -> None:
        self._entries.pop(name, None)

    def refresh(self) -> None:
        """Forget every entry (those registered by hand too); discovery runs again on next use."""
        self._entries.clear()
        self._discovered = self._discover is None

    def names(self) -> list[str]:
        """Registered names, in the order registered."""
        self._ensure_discovered()
        return list(self._entries)

    def entries(self) -> list[T]:
        """Registered entries, in the order registered."""
        self._ensure_discovered()
        return list(self._entries.values())

    def __contains__(self, name: object) -> bool:
        self._ensure_discovered()
        return name in self._entries

    def get(self, name: str) -> T:
        """The entry ``name``; an unknown name raises :class:`InputError` with a "did you mean"."""
        self._ensure_discovered()
        if name in self._entries:
            return self._entries[name]
        close = difflib.get_close_matches(name, list(self._entries), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise InputError(None, self.what, f"unknown {self.what} {name!r}{hint}; "
                         f"registered: {', '.join(sorted(self._entries)) or 'none'}")

    def load(self, name: str) -> object:
        """The code of entry ``name`` (its ``entry_point``), imported now."""
        return import_entry_point(self.get(name).entry_point, f"{self.what} {name}")


def entry_point_modules(*modules: str) -> list[str]:
    """Project modules named by ``"module:attr"`` strings in the code of ``modules`` and of every project
    module it reaches, transitively: the lazily imported code of the registry entries that code
    declares (a code digest of ``modules`` alone does not see them: they are strings, not imports)."""
    found: set[str] = set()
    todo = list(modules)
    seen: set[str] = set()
    while todo:
        reached = [m for m in code_modules(*todo) if m not in seen]
        seen.update(reached)
        todo = []
        for name in reached:
            for target in _named_entry_modules(name):
                if target not in found:
                    found.add(target)
                    todo.append(target)
    return sorted(found)


@functools.lru_cache(maxsize=None)
def _named_entry_modules(module: str) -> frozenset[str]:
    """Project modules that a whole string constant of ``module``'s source names as ``"module:attr"``
    (read once per process, as the code digest reads each file once)."""
    spec = importlib.util.find_spec(module)
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        return frozenset()
    with open(spec.origin, encoding="utf-8") as handle:
        tree = ast.parse(handle.read(), filename=spec.origin)
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            match = ENTRY_POINT.match(node.value)
            if match and match.group(1).split(".")[0] in PROJECT_PACKAGES \
                    and importlib.util.find_spec(match.group(1)) is not None:
                out.add(match.group(1))
    return frozenset(out)
