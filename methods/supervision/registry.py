"""Registry of supervision sources (segmenters, image-text encoders, captioners).

Each source is described by a small spec module in :mod:`methods.supervision.specs` (one file per
source, defining ``SPEC``); its code is imported only when the source is created, so a missing
optional backend breaks only the runs that use it. Text encoders have their own registry
(:mod:`methods.text_encoders`).

A *track* fixes the default sources: ``oracle`` = ``gt`` segments + ``oracle-text`` features;
``real`` = SAM segments + CLIP features. A source labelled with one track cannot be used on the
other, so results of the two tracks never mix.
"""

from __future__ import annotations

import difflib
import importlib
import pkgutil
from dataclasses import dataclass, field
from typing import Any, Literal, Optional

from benchmark.core.errors import InputError

SourceKind = Literal["segmenter", "image_text", "captioner"]
SOURCE_KINDS: tuple[str, ...] = ("segmenter", "image_text", "captioner")

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
    """``"segmenter"``, ``"image_text"`` or ``"captioner"``."""
    track: str
    """``"oracle"`` or ``"real"``: the only track it may supervise."""
    description: str
    entry_point: str
    """``"module:factory"``; ``factory(scene, *, text_encoder, device, **options)`` returns the source."""
    requires: tuple[str, ...] = ()
    """Python packages the source needs beyond the core (shown by ``bench4d methods``)."""
    options: dict[str, Any] = field(default_factory=dict)
    """Default options passed to the factory."""

    def create(self, scene, *, text_encoder, device: str = "cpu", **options: Any):
        module_name, _, attr = self.entry_point.partition(":")
        try:
            module = importlib.import_module(module_name)
        except ImportError as err:
            raise InputError(None, f"supervision source {self.name}",
                             f"cannot import {module_name} ({err}); it needs {', '.join(self.requires) or 'nothing extra'}") from err
        factory = getattr(module, attr)
        merged = {**self.options, **options}
        return factory(scene, text_encoder=text_encoder, device=device, **merged)


_SOURCES: dict[tuple[str, str], SourceSpec] = {}
_DISCOVERED = False


def register_source(spec: SourceSpec, *, replace: bool = False) -> SourceSpec:
    """Add a source (spec modules call nothing: discovery reads their ``SPEC``; tests may call this)."""
    if spec.kind not in SOURCE_KINDS:
        raise ValueError(f"source {spec.name!r}: unknown kind {spec.kind!r}")
    if spec.track not in TRACK_DEFAULTS:
        raise ValueError(f"source {spec.name!r}: unknown track {spec.track!r}")
    key = (spec.kind, spec.name)
    if key in _SOURCES and not replace and _SOURCES[key] != spec:
        raise ValueError(f"{spec.kind} {spec.name!r} is already registered")
    _SOURCES[key] = spec
    return spec


def _discover() -> None:
    global _DISCOVERED
    if _DISCOVERED:
        return
    _DISCOVERED = True
    from . import specs

    for info in sorted(pkgutil.iter_modules(specs.__path__), key=lambda i: i.name):
        module = importlib.import_module(f"{specs.__name__}.{info.name}")
        for spec in getattr(module, "SPECS", ()) or ((module.SPEC,) if hasattr(module, "SPEC") else ()):
            register_source(spec)


def sources(kind: Optional[str] = None) -> list[SourceSpec]:
    """All registered sources (of ``kind``), sorted by kind then name."""
    _discover()
    return sorted((s for s in _SOURCES.values() if kind is None or s.kind == kind),
                  key=lambda s: (SOURCE_KINDS.index(s.kind), s.name))


def get_source(kind: str, name: str) -> SourceSpec:
    _discover()
    if (kind, name) in _SOURCES:
        return _SOURCES[(kind, name)]
    known = [s.name for s in sources(kind)]
    close = difflib.get_close_matches(name, known, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    raise InputError(None, kind, f"unknown {kind} source {name!r}{hint}; registered: {', '.join(known) or 'none'}")


def track_sources(track: str, overrides: Optional[dict[str, str]] = None) -> dict[str, SourceSpec]:
    """The sources a track uses (kind -> spec), checking every one belongs to that track."""
    if track not in TRACK_DEFAULTS:
        close = difflib.get_close_matches(track, list(TRACK_DEFAULTS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise InputError(None, "track", f"unknown track {track!r}{hint}; tracks: {', '.join(TRACK_DEFAULTS)}")
    chosen = {**TRACK_DEFAULTS[track], **(overrides or {})}
    out: dict[str, SourceSpec] = {}
    for kind, name in chosen.items():
        _discover()
        if (kind, name) not in _SOURCES:
            if overrides and kind in overrides:
                get_source(kind, name)  # raises with a "did you mean"
            raise InputError(None, f"track {track}",
                             f"needs {kind} {name!r}, which is not registered in this install "
                             f"(registered {kind} sources: {', '.join(s.name for s in sources(kind)) or 'none'})")
        spec = _SOURCES[(kind, name)]
        if spec.track != track:
            raise InputError(None, f"track {track}",
                             f"{kind} {name!r} belongs to the {spec.track!r} track and cannot supervise {track!r} runs")
        out[kind] = spec
    return out
