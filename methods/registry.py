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

A config's fields may themselves be dataclasses (option groups: ``autoencoder.latent_dim``); each field's
docstring is its help. :mod:`benchmark.core.config` derives from the class the option list
(``bench4d methods --options NAME``), dotted overrides (:meth:`MethodSpec.make_config`, ``--set``) and the
command-line flags of ``bench4d eval --method NAME``.

Spec files import nothing heavy (no torch): ``bench4d methods`` lists every method without loading
any of them. Specs from outside the package can be added with ``$BENCH4D_METHOD_SPECS`` (comma-
separated module names or ``.py`` paths) or :func:`register`. :data:`METHODS` holds them (a lazy
:class:`methods._registry.Registry`, as every registry of the package).

The paper's own numbers of methods not (yet) implemented here live in
:mod:`methods.specs.paper_numbers`; they are shown beside ours, never ranked with ours.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import os
import pkgutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping, Optional

from benchmark.core.cache_keys import code_digest
from benchmark.core.config import ConfigOption, config_options, with_overrides
from benchmark.core.errors import InputError
from benchmark.core.protocol import TIME_SCORES

from ._registry import Registry, entry_point_modules, import_entry_point

DEFAULT_METHOD = "nearest-frame"
"""The method ``bench4d demo`` runs: the best runnable method registered (switch it when a better
one lands)."""

SPECS_ENV = "BENCH4D_METHOD_SPECS"

ANSWER_RULES = ("relevance", "mask-selection", "caption")
"""How a method answers (:attr:`MethodSpec.answer_rule`, :attr:`MethodSpec.sensitive_rule`): a floor and a
ranked method of the same rule are compared in the tables."""

ANSWER_GROUP = "answer"
"""The option group of a method config read only when answering, never when fitting: fit cache keys leave
it out, a cached fit answers with the run's values, and ``bench4d ablate rescore`` changes it on recorded fits."""


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
    """A floor, not a competitor: it answers from the nearest training view's 2D supervision (and captions),
    with no 3D or 4D model; the leaderboard shows it in its own labelled row and never ranks it."""
    variant_of: Optional[str] = None
    """The registered paper method this is a variant of: the same method with some of the benchmark's
    extensions on (its config differs from the base's only in the ``extensions`` group), in a row of its own;
    the paper's numbers attach to the base only. ``None`` for a paper method, a baseline or a floor."""
    answer_rule: str = "relevance"
    """How it answers time-agnostic queries (one of :data:`ANSWER_RULES`): ``"relevance"``, a per-pixel
    relevance map through the protocol's query rule (smoothing, min-max threshold, majority filter, level
    choice); ``"mask-selection"``, a chosen mask or identity. A ranked method is compared with the floor of
    the same rule (:func:`floor_for`)."""
    sensitive_rule: Optional[str] = None
    """How it scores time-sensitive queries (one of :data:`ANSWER_RULES`): ``"relevance"``, read from the
    relevance map (the CLIP baselines); ``"caption"``, the cosine to training frames' caption embeddings
    (learnt by a time-varying field, or replayed by the floor); ``"mask-selection"``, the chosen mask's
    feature. ``None``: none (a method that answers no time-sensitive query) or, where it answers them,
    :attr:`answer_rule`."""

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
        for what, rule in (("answer_rule", self.answer_rule), ("sensitive_rule", self.sensitive_rule)):
            if rule is not None and rule not in ANSWER_RULES:
                raise ValueError(f"method {self.name!r}: {what} must be one of {ANSWER_RULES}, got {rule!r}")
        if self.variant_of is not None and (self.variant_of == self.name or self.floor):
            raise ValueError(f"method {self.name!r}: a variant names another method and is no floor")

    @property
    def time_score(self) -> str:
        """How its time-sensitive score is made, which picks the protocol's ``tau`` rule
        (:data:`benchmark.core.protocol.TIME_SCORES`): ``"relevance-peak"`` for a score read from the
        relevance map (``sensitive_rule == "relevance"``, the release's CLIP-only baselines), else
        ``"feature"`` (a time-varying or replayed feature's similarity to the query)."""
        score = "relevance-peak" if self.sensitive_rule == "relevance" else "feature"
        assert score in TIME_SCORES
        return score

    def rule_for(self, kind: str) -> Optional[str]:
        """The rule of its answers to ``kind`` queries (``"agnostic"`` or ``"sensitive"``); ``None`` where it
        answers none of them."""
        if kind not in ("agnostic", "sensitive"):
            raise ValueError(f"query kind must be 'agnostic' or 'sensitive', got {kind!r}")
        if kind not in self.queries:
            return None
        return self.answer_rule if kind == "agnostic" else (self.sensitive_rule or self.answer_rule)

    # -- code ----------------------------------------------------------------------------------
    @property
    def module(self) -> str:
        """The module of :attr:`entry_point`."""
        return self.entry_point.partition(":")[0]

    def load(self):
        """Import and return the method class (``entry_point``)."""
        cls = import_entry_point(self.entry_point, f"method {self.name}")
        declared = set(getattr(cls, "supports", self.queries))
        if set(self.queries) - declared:
            raise TypeError(f"method {self.name!r}: spec promises {sorted(self.queries)} but "
                            f"{cls.__name__}.supports is {sorted(declared)}")
        return cls

    def code_digest(self) -> str:
        """Hash of the method's code, for fit cache keys: the entry point's module, every project module it
        imports (transitively, function-local imports included) and the modules of the registry entries
        that code names (e.g. the captioners a time-varying head loads by name)."""
        try:
            found = importlib.util.find_spec(self.module) is not None
        except (ImportError, ValueError):
            found = False
        if not found:
            raise InputError(None, f"method {self.name}", f"code module {self.module!r} not found")
        return code_digest(self.module, *entry_point_modules(self.module))

    # -- configuration -------------------------------------------------------------------------
    def default_config(self):
        return self.config()

    def make_config(self, overrides: Optional[Mapping[str, Any]] = None):
        """The default config with ``overrides`` (dotted option path -> value, e.g.
        ``{"autoencoder.latent_dim": "4"}``; strings are read by the option's type). An unknown path or a
        value the config refuses is an :class:`InputError`."""
        what = f"{self.name} config"
        try:
            return with_overrides(self.config(), overrides, what=what)
        except InputError:
            raise
        except (TypeError, ValueError) as err:
            raise InputError(None, what, str(err)) from None

    def options(self) -> list[ConfigOption]:
        """Every option of the method's config: dotted path, type, default and help."""
        return config_options(self.config)

    def answer_options(self) -> frozenset[str]:
        """The options read only when answering (those of the config's :data:`ANSWER_GROUP` group)."""
        return frozenset(o.path for o in self.options() if o.path.startswith(ANSWER_GROUP + "."))

    def recorded_options(self, recorded: Optional[Mapping[str, Any]]) -> dict[str, Any]:
        """Dotted path -> value of this method's options in a recorded config (a results file's
        ``method_config``, nested or in the flat form of older records); other keys are left out. An option
        of :data:`BEFORE_THE_OPTION` that a (non-empty) record lacks gets the value it had before it existed."""
        from .specs._recorded import recorded_options

        out = recorded_options(self.config, recorded)
        if recorded:
            known = {o.path for o in self.options()}
            out.update({path: value for path, value in BEFORE_THE_OPTION.items() if path in known and path not in out})
        return out

    def config_from_record(self, recorded: Optional[Mapping[str, Any]]):
        """The config a recorded ``method_config`` (nested or flat) describes, other options default."""
        return self.make_config(self.recorded_options(recorded))

    def recorded_as(self, recorded: Optional[Mapping[str, Any]], overrides: Optional[Mapping[str, Any]] = None) -> bool:
        """Whether a recorded ``method_config`` is the config these ``overrides`` give today (False when a
        default has moved since, the record holds a value this version refuses or an option it retired, or
        there is no record): a study's cached run is current only then."""
        from .specs._recorded import holds_retired_options

        if not isinstance(recorded, Mapping) or holds_retired_options(recorded):
            return False
        try:
            return self.config_from_record(recorded) == self.make_config(overrides)
        except InputError:
            return False

    def differences_from_defaults(self, recorded: Optional[Mapping[str, Any]]) -> Optional[dict[str, tuple[Any, Any]]]:
        """Dotted path -> (recorded value, today's default) of every option where a recorded ``method_config``
        differs from this method's defaults today (empty: made at today's defaults); None when the record
        cannot be read as this method's config (missing, refused or retired options)."""
        from benchmark.core.config import option_values

        from .specs._recorded import holds_retired_options

        if not isinstance(recorded, Mapping) or holds_retired_options(recorded):
            return None
        try:
            made, now = option_values(self.config_from_record(recorded)), option_values(self.make_config())
        except InputError:
            return None
        return {path: (made.get(path), value) for path, value in now.items() if made.get(path) != value}

    def results_made_as(self, path: Path, overrides: Optional[Mapping[str, Any]] = None) -> bool:
        """:meth:`recorded_as` of the ``method_config`` of the results file at ``path`` (False when the
        file cannot be read: the run is made anew)."""
        from benchmark.core.atomic import read_json

        try:
            doc = read_json(path)
        except InputError:
            return False
        return self.recorded_as(doc.get("method_config") if isinstance(doc, dict) else None, overrides)


BEFORE_THE_OPTION: dict[str, Any] = {
    "extensions.caption_segments": False,
}
"""Dotted path -> what a record that predates the option did, where a config's default may differ today
(every frame's caption was its own target before caption segments existed; ``4d-langsplat+`` turns them on)."""


# -- the registry ----------------------------------------------------------------------------------
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


def _discover() -> Iterator[MethodSpec]:
    """The specs of :mod:`methods.specs` (``SPEC`` / ``SPECS`` of each public module), then those of the
    modules and files named by ``$BENCH4D_METHOD_SPECS``."""
    from . import specs

    for info in sorted(pkgutil.iter_modules(specs.__path__), key=lambda i: i.name):
        if info.name.startswith("_") or info.name == "paper_numbers":
            continue
        yield from _specs_of(importlib.import_module(f"{specs.__name__}.{info.name}"))
    for item in filter(None, (s.strip() for s in os.environ.get(SPECS_ENV, "").split(","))):
        yield from _specs_of(_import_path(Path(item)) if item.endswith(".py") else importlib.import_module(item))


METHODS: Registry[MethodSpec] = Registry("method", _discover)
"""Every runnable method, by name."""


def register(spec: MethodSpec, *, replace: bool = False) -> MethodSpec:
    """Add ``spec`` (spec files are discovered; tests and plug-ins may call this directly)."""
    return METHODS.register(spec, replace=replace)


def unregister(name: str) -> None:
    METHODS.unregister(name)


def refresh() -> None:
    """Forget every spec (those registered by hand too) and discover again on next use."""
    METHODS.refresh()


def names() -> list[str]:
    """Names of all registered (runnable) methods, sorted."""
    return sorted(METHODS.names())


def all_specs() -> list[MethodSpec]:
    return sorted(METHODS.entries(), key=lambda s: s.name)


def get(name: str) -> MethodSpec:
    """The spec of ``name``; unknown names raise :class:`InputError` with a "did you mean"."""
    if name not in METHODS:
        from .specs.paper_numbers import PAPER_NUMBERS

        if name in PAPER_NUMBERS:
            raise InputError(None, "method", f"{name!r} is not implemented here yet (only its paper numbers are "
                             f"known); runnable methods: {', '.join(names())}")
    return METHODS.get(name)


def default_method() -> str:
    """:data:`DEFAULT_METHOD` when registered, else the first registered method."""
    registered = names()
    if DEFAULT_METHOD in registered:
        return DEFAULT_METHOD
    if not registered:
        raise InputError(None, "method", "no method is registered")
    return registered[0]


def paper_numbers(name: str) -> dict[str, Any]:
    """The paper's numbers for method ``name``: from its spec if registered, else the data file; none for a
    variant (:attr:`MethodSpec.variant_of`): they are its base's, whose row shows them."""
    from .specs.paper_numbers import PAPER_NUMBERS

    if name in METHODS:
        spec = METHODS.get(name)
        if spec.variant_of is not None:
            return {}
        if spec.paper_numbers:
            return dict(spec.paper_numbers)
    return dict(PAPER_NUMBERS.get(name, {}))


def variants_of(name: str) -> list[str]:
    """Names of the registered variants of method ``name`` (:attr:`MethodSpec.variant_of`), sorted."""
    return sorted(s.name for s in METHODS.entries() if s.variant_of == name)


def recorded_method(name: str, recorded: Optional[Mapping[str, Any]]) -> str:
    """The registered name a run of ``name`` made with the config ``recorded`` stands for today: ``name``
    when that is its default config (or no variant's default matches either: the leaderboard marks such a
    run), else the variant whose default config it is. A run made before the paper configs became the
    defaults, with the benchmark's extensions on, is thereby shown as the variant it was (``4d-langsplat+``),
    never as the paper's method."""
    from .specs._recorded import RETIRED_AS

    try:
        spec = get(name)
    except InputError:
        return name
    retired = [RETIRED_AS[key] for key in (recorded or {}) if key in RETIRED_AS]
    if retired and retired[0] in METHODS:
        return retired[0]
    if spec.recorded_as(recorded):
        return name
    for variant in variants_of(name):
        if get(variant).recorded_as(recorded):
            return variant
    return name


def paper_base(name: str) -> str:
    """The paper method whose row a method's results belong beside: its :attr:`~MethodSpec.variant_of`, else
    ``name`` itself."""
    return get(name).variant_of or name


def floor_for(name: str, kind: str) -> Optional[str]:
    """The floor a method's answers to ``kind`` queries are compared with: the registered floor whose rule
    for ``kind`` (:meth:`MethodSpec.rule_for`) is the method's, preferring one whose rules agree on both
    kinds, then by name; ``None`` where no floor shares the rule (or the method answers no such query)."""
    spec = get(name)
    rule = spec.rule_for(kind)
    if rule is None:
        return None
    kinds = ("agnostic", "sensitive")
    same = [s for s in all_specs() if s.floor and s.rule_for(kind) == rule]
    same.sort(key=lambda s: (sum(s.rule_for(k) != spec.rule_for(k) for k in kinds), s.name))
    return same[0].name if same else None


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
