"""Registry of methods: small spec files, code imported only when a method is used.

A method is added by **one spec file** in :mod:`methods.specs` plus its code::

    # methods/specs/my_method.py
    from dataclasses import dataclass
    from methods.registry import MethodSpec

    @dataclass
    class MyConfig:
        steps: int = 1000
        \"\"\"Optimisation steps.\"\"\"

    SPEC = MethodSpec(name="my-method", description="...", entry_point="methods.my_method:MyMethod",
                      config=MyConfig, paper="Author et al., Venue 2025", tracks=("oracle", "real"),
                      queries=("agnostic", "sensitive"))

Spec files import nothing heavy (no torch): ``bench4d methods`` lists every method without loading
any of them. Specs from outside the package can be added with ``$BENCH4D_METHOD_SPECS`` (comma-
separated module names or ``.py`` paths) or :func:`register`.

The paper's own numbers of methods not (yet) implemented here live in
:mod:`methods.specs.paper_numbers`; they are shown beside ours, never ranked with ours.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
import importlib.util
import os
import pkgutil
import sys
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional

from benchmark.core.errors import InputError

DEFAULT_METHOD = "nearest-frame"
"""The method ``bench4d demo`` runs: the best runnable method registered (switch it when a better
one lands)."""

SPECS_ENV = "BENCH4D_METHOD_SPECS"


@dataclass(frozen=True)
class MethodSpec:
    """Everything the harness needs to know about a method before importing its code."""

    name: str
    """Registry name (lower case, dashes), e.g. ``"nearest-frame"``."""
    description: str
    """One line for ``bench4d methods``."""
    entry_point: str
    """``"module:attr"`` of the :class:`methods.api.Method` subclass (imported only when used)."""
    config: type
    """Dataclass of the method's options; its defaults are the method's defaults."""
    paper: str = ""
    """Citation of the paper the method comes from (empty for the benchmark's own baselines)."""
    paper_numbers: Mapping[str, Any] = field(default_factory=dict)
    """The paper's reported numbers for this method (copied from the paper, percent), keyed by
    table name as in :mod:`methods.specs.paper_numbers`."""
    tracks: tuple[str, ...] = ("oracle", "real")
    """Supervision tracks it runs on."""
    queries: tuple[str, ...] = ("agnostic", "sensitive")
    """Query kinds it answers."""
    devices: tuple[str, ...] = ("cpu", "cuda")
    """Devices it runs on."""
    floor: bool = False
    """A floor, not a competitor: it answers from the training frames' 2D supervision without going
    through the protocol's query; the leaderboard shows it in its own labelled row and never ranks it."""
    code: tuple[str, ...] = ()
    """Further modules or packages (dotted names) whose source the fit depends on, e.g.
    ``("methods.gaussians", "methods.fields")``: their files are hashed into the fit cache key with
    the entry point's module, so editing them invalidates cached fits."""

    def __post_init__(self) -> None:
        if not dataclasses.is_dataclass(self.config):
            raise TypeError(f"method {self.name!r}: config must be a dataclass type")
        if ":" not in self.entry_point:
            raise ValueError(f"method {self.name!r}: entry_point must be 'module:attr', got {self.entry_point!r}")
        bad = set(self.queries) - {"agnostic", "sensitive"}
        if bad:
            raise ValueError(f"method {self.name!r}: unknown query kinds {sorted(bad)}")
        if "agnostic" not in self.queries:
            # a time-sensitive answer's mask is the time-agnostic answer of the same text
            raise ValueError(f"method {self.name!r}: every method answers time-agnostic queries")
        bad = set(self.tracks) - {"oracle", "real"}
        if bad:
            raise ValueError(f"method {self.name!r}: unknown tracks {sorted(bad)}")

    # -- code ----------------------------------------------------------------------------------
    def load(self):
        """Import and return the method class (``entry_point``)."""
        module_name, _, attr = self.entry_point.partition(":")
        try:
            module = importlib.import_module(module_name)
        except ImportError as err:
            raise InputError(None, f"method {self.name}", f"cannot import {module_name}: {err}") from err
        try:
            cls = getattr(module, attr)
        except AttributeError:
            raise InputError(None, f"method {self.name}", f"{module_name} has no attribute {attr!r}") from None
        declared = set(getattr(cls, "supports", self.queries))
        if set(self.queries) - declared:
            raise TypeError(f"method {self.name!r}: spec promises {sorted(self.queries)} but "
                            f"{cls.__name__}.supports is {sorted(declared)}")
        return cls

    def source_files(self) -> list[Path]:
        """Files whose content defines the method's behaviour (for fit cache keys): the entry
        point's module and every module of :attr:`code` (packages recursively), sorted."""
        files: set[Path] = set()
        for name in (self.entry_point.partition(":")[0], *self.code):
            try:
                spec = importlib.util.find_spec(name)
            except (ImportError, ValueError):
                spec = None
            if spec is None:
                raise InputError(None, f"method {self.name}", f"code module {name!r} not found")
            if spec.submodule_search_locations:  # a package: all its Python files
                for folder in spec.submodule_search_locations:
                    files.update(Path(folder).rglob("*.py"))
            elif spec.origin and spec.origin not in ("built-in", "frozen"):
                files.add(Path(spec.origin))
        return sorted(files)

    # -- configuration -------------------------------------------------------------------------
    def default_config(self):
        return self.config()

    def make_config(self, overrides: Optional[Mapping[str, Any]] = None):
        """The default config with ``overrides`` (``name -> value``; strings are parsed by field type)."""
        cfg = self.config()
        if not overrides:
            return cfg
        hints = typing.get_type_hints(self.config)
        names = [f.name for f in dataclasses.fields(self.config)]
        changes = {}
        for key, value in overrides.items():
            if key not in names:
                close = difflib.get_close_matches(key, names, n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise InputError(None, f"{self.name} config", f"unknown option {key!r}{hint}; options: {', '.join(names)}")
            changes[key] = _parse_value(value, hints.get(key), f"{self.name} config.{key}")
        return dataclasses.replace(cfg, **changes)


def _parse_value(value: Any, hint: Any, where: str) -> Any:
    if not isinstance(value, str) or hint is None or hint is str:
        return value
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin is typing.Union and type(None) in args:
        if value.lower() in ("none", "null"):
            return None
        hint = next(a for a in args if a is not type(None))
        origin = typing.get_origin(hint)
    try:
        if hint is bool:
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(value)
        if hint in (int, float):
            return hint(value)
        if origin is typing.Literal:
            if value not in typing.get_args(hint):
                raise ValueError(value)
            return value
        if origin in (tuple, list):
            item = typing.get_args(hint)[0] if typing.get_args(hint) else str
            parts = [p.strip() for p in value.split(",") if p.strip()]
            parsed = [item(p) if item in (int, float) else p for p in parts]
            return tuple(parsed) if origin is tuple else parsed
    except ValueError:
        raise InputError(None, where, f"cannot read {value!r} as {getattr(hint, '__name__', hint)}") from None
    return value


# -- the registry ----------------------------------------------------------------------------------
_REGISTRY: dict[str, MethodSpec] = {}
_DISCOVERED = False


def register(spec: MethodSpec, *, replace: bool = False) -> MethodSpec:
    """Add ``spec`` (spec files are discovered; tests and plug-ins may call this directly)."""
    if spec.name in _REGISTRY and not replace and _REGISTRY[spec.name] is not spec:
        raise ValueError(f"method {spec.name!r} is already registered")
    _REGISTRY[spec.name] = spec
    return spec


def unregister(name: str) -> None:
    _REGISTRY.pop(name, None)


def _specs_of(module) -> list[MethodSpec]:
    found = list(getattr(module, "SPECS", ()) or ())
    if hasattr(module, "SPEC"):
        found.append(module.SPEC)
    return [s for s in found if isinstance(s, MethodSpec)]


def _import_path(path: Path):
    name = f"bench4d_external_spec_{abs(hash(str(path.resolve())))}"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise InputError(path, None, "cannot import method spec file")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def _discover() -> None:
    global _DISCOVERED
    if _DISCOVERED:
        return
    _DISCOVERED = True
    from . import specs

    for info in sorted(pkgutil.iter_modules(specs.__path__), key=lambda i: i.name):
        if info.name.startswith("_") or info.name == "paper_numbers":
            continue
        for spec in _specs_of(importlib.import_module(f"{specs.__name__}.{info.name}")):
            _REGISTRY.setdefault(spec.name, spec)
    for item in filter(None, (s.strip() for s in os.environ.get(SPECS_ENV, "").split(","))):
        module = _import_path(Path(item)) if item.endswith(".py") else importlib.import_module(item)
        for spec in _specs_of(module):
            _REGISTRY.setdefault(spec.name, spec)


def refresh() -> None:
    """Forget discovered specs (keeps nothing registered by hand) and discover again on next use."""
    global _DISCOVERED
    _DISCOVERED = False
    _REGISTRY.clear()


def names() -> list[str]:
    """Names of all registered (runnable) methods, sorted."""
    _discover()
    return sorted(_REGISTRY)


def all_specs() -> list[MethodSpec]:
    _discover()
    return [_REGISTRY[n] for n in sorted(_REGISTRY)]


def get(name: str) -> MethodSpec:
    """The spec of ``name``; unknown names raise :class:`InputError` with a "did you mean"."""
    _discover()
    if name in _REGISTRY:
        return _REGISTRY[name]
    from .specs.paper_numbers import PAPER_NUMBERS

    close = difflib.get_close_matches(name, list(_REGISTRY) + list(PAPER_NUMBERS), n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    if name in PAPER_NUMBERS:
        raise InputError(None, "method", f"{name!r} is not implemented here yet (only its paper numbers are "
                         f"known); runnable methods: {', '.join(sorted(_REGISTRY))}")
    raise InputError(None, "method", f"unknown method {name!r}{hint}; registered: {', '.join(sorted(_REGISTRY))}")


def default_method() -> str:
    """:data:`DEFAULT_METHOD` when registered, else the first registered method."""
    registered = names()
    if DEFAULT_METHOD in registered:
        return DEFAULT_METHOD
    if not registered:
        raise InputError(None, "method", "no method is registered")
    return registered[0]


def paper_numbers(name: str) -> dict[str, Any]:
    """The paper's numbers for method ``name``: from its spec if registered, else the data file."""
    _discover()
    from .specs.paper_numbers import PAPER_NUMBERS

    if name in _REGISTRY and _REGISTRY[name].paper_numbers:
        return dict(_REGISTRY[name].paper_numbers)
    return dict(PAPER_NUMBERS.get(name, {}))


@dataclass(frozen=True)
class PaperReference:
    """The published numbers the leaderboard and the paper tables print beside ours."""

    numbers: Mapping[str, Any]
    """Method name -> its entry (display name, results per dataset and scene, query FPS)."""
    ablations: Mapping[str, Any]
    """The paper's ablation tables (number of states, prompt kinds)."""
    source: str
    """Where the numbers come from."""
    query_fps_device: str
    """The GPU the published query speeds were measured on."""


def paper_reference() -> PaperReference:
    """The published numbers of every method of the paper, registered here or not."""
    from .specs.paper_numbers import PAPER_ABLATIONS, PAPER_NUMBERS, PAPER_SOURCE, QUERY_FPS_DEVICE

    return PaperReference(PAPER_NUMBERS, PAPER_ABLATIONS, PAPER_SOURCE, QUERY_FPS_DEVICE)
