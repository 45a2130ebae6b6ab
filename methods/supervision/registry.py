"""Registry of supervision sources (segmenters, image-text encoders).

Each source is described by a small spec module in :mod:`methods.supervision.specs` (one file per
source, defining ``SPEC``); its code is imported only when the source is created, so a missing
optional backend breaks only the runs that use it. Text encoders and captioners have their own
registries (:mod:`methods.text_encoders`, :mod:`methods.captioners`).

A *track* fixes the default sources: ``oracle`` = ``gt`` segments + ``oracle-text`` features;
``real`` = SAM segments + CLIP features. A source labelled with one track cannot be used on the
other, so results of the two tracks never mix.
"""

from __future__ import annotations

import difflib
import functools
import importlib
import pkgutil
from dataclasses import dataclass, field
from typing import Any, Iterator, Literal, Optional

from benchmark.core.errors import InputError

from .._registry import Registry, import_entry_point

SourceKind = Literal["segmenter", "image_text"]
SOURCE_KINDS: tuple[str, ...] = ("segmenter", "image_text")

TRACK_DEFAULTS: dict[str, dict[str, str]] = {
    "oracle": {"segmenter": "gt", "image_text": "oracle-text"},
    "real": {"segmenter": "sam", "image_text": "clip"},
}
"""Default sources per track (kind -> source name)."""

TRACK_DESCRIPTIONS: dict[str, str] = {
    "oracle": "generator truth of TRAINING frames + oracle-text (isolates the 3D/4D method)",
    "real": "real 2D models: segmenter + image-text encoder (+ captioner)",
}


@dataclass(frozen=True)
class SourceSpec:
    """How to find and build one supervision source."""

    name: str
    """Registry name, e.g. ``"gt"``, ``"oracle-text"``, ``"sam"``."""
    kind: str
    """``"segmenter"`` or ``"image_text"``."""
    track: str
    """``"oracle"`` or ``"real"``: the only track it may supervise."""
    description: str
    entry_point: str
    """``"module:factory"``; ``factory(scene, *, text_encoder, device, **options)`` returns the source."""
    requires: tuple[str, ...] = ()
    """Python packages the source needs beyond the core (shown by ``bench4d methods``)."""
    options: dict[str, Any] = field(default_factory=dict)
    """Default options passed to the factory."""

    def __post_init__(self) -> None:
        if self.kind not in SOURCE_KINDS:
            raise ValueError(f"source {self.name!r}: unknown kind {self.kind!r}")
        if self.track not in TRACK_DEFAULTS:
            raise ValueError(f"source {self.name!r}: unknown track {self.track!r}")

    def create(self, scene, *, text_encoder, device: str = "cpu", **options: Any):
        factory = import_entry_point(self.entry_point, f"supervision source {self.name}", ", ".join(self.requires))
        merged = {**self.options, **options}
        return factory(scene, text_encoder=text_encoder, device=device, **merged)


def _discover(kind: str) -> Iterator[SourceSpec]:
    """The specs of ``kind`` in :mod:`methods.supervision.specs` (``SPEC`` / ``SPECS`` of each module)."""
    from . import specs

    for info in sorted(pkgutil.iter_modules(specs.__path__), key=lambda i: i.name):
        module = importlib.import_module(f"{specs.__name__}.{info.name}")
        found = getattr(module, "SPECS", ()) or ((module.SPEC,) if hasattr(module, "SPEC") else ())
        yield from (spec for spec in found if spec.kind == kind)


SOURCES: dict[str, Registry[SourceSpec]] = {
    kind: Registry(f"{kind} source", functools.partial(_discover, kind)) for kind in SOURCE_KINDS}
"""The registered sources of each kind, by name."""


def register_source(spec: SourceSpec, *, replace: bool = False) -> SourceSpec:
    """Add a source (spec modules call nothing: discovery reads their ``SPEC``; tests may call this)."""
    return SOURCES[spec.kind].register(spec, replace=replace)


def sources(kind: Optional[str] = None) -> list[SourceSpec]:
    """All registered sources (of ``kind``), sorted by kind then name."""
    return [spec for k in SOURCE_KINDS if kind is None or k == kind
            for spec in sorted(SOURCES[k].entries(), key=lambda s: s.name)]


def _of_kind(kind: str) -> Registry[SourceSpec]:
    if kind not in SOURCES:
        close = difflib.get_close_matches(kind, SOURCE_KINDS, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise InputError(None, "source kind", f"unknown source kind {kind!r}{hint}; kinds: {', '.join(SOURCE_KINDS)}")
    return SOURCES[kind]


def get_source(kind: str, name: str) -> SourceSpec:
    return _of_kind(kind).get(name)


def track_sources(track: str, overrides: Optional[dict[str, str]] = None) -> dict[str, SourceSpec]:
    """The sources a track uses (kind -> spec), checking every one belongs to that track."""
    if track not in TRACK_DEFAULTS:
        close = difflib.get_close_matches(track, list(TRACK_DEFAULTS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise InputError(None, "track", f"unknown track {track!r}{hint}; tracks: {', '.join(TRACK_DEFAULTS)}")
    chosen = {**TRACK_DEFAULTS[track], **(overrides or {})}
    out: dict[str, SourceSpec] = {}
    for kind, name in chosen.items():
        if name not in _of_kind(kind):
            if overrides and kind in overrides:
                get_source(kind, name)  # raises with a "did you mean"
            raise InputError(None, f"track {track}",
                             f"needs {kind} {name!r}, which is not registered in this install "
                             f"(registered {kind} sources: {', '.join(s.name for s in sources(kind)) or 'none'})")
        spec = SOURCES[kind].get(name)
        if spec.track != track:
            raise InputError(None, f"track {track}",
                             f"{kind} {name!r} belongs to the {spec.track!r} track and cannot supervise {track!r} runs")
        out[kind] = spec
    return out
