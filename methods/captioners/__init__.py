"""Captioners (MLLM, template, file) behind one interface, and the object-wise visual prompts they see.

==============  ======  ============================================================================
name            track   what it is
==============  ======  ============================================================================
``template``    oracle  captions from the generated scene's semantic states (training frames only)
``qwen2-vl``    real    Qwen2-VL with 4D LangSplat's two-step prompting (transformers; weights local)
``file``        real    captions made elsewhere, read from JSON (:mod:`.file`)
``states``      oracle  the annotation's time segments at the training frames, for scenes without
                        generator truth (D-NeRF; :mod:`.states`)
==============  ======  ============================================================================

Code is imported only when a captioner is created (:func:`get_captioner`).
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass
from typing import Any

from benchmark.core.errors import InputError

from .._registry import Registry


@dataclass(frozen=True)
class CaptionerSpec:
    """How to find and build one captioner."""

    name: str
    """Registry name, e.g. ``"template"``."""
    track: str
    """``"oracle"`` or ``"real"``."""
    description: str
    """One line for listings."""
    entry_point: str
    """``"module:factory"``; ``factory(scene, **options)`` returns the captioner."""


BUILT_IN: tuple[CaptionerSpec, ...] = (
    CaptionerSpec("template", "oracle", "captions from the synthetic scene's states (oracle; paraphrases per frame)",
                  "methods.captioners.template:TemplateCaptioner"),
    CaptionerSpec("qwen2-vl", "real", "Qwen2-VL, video description then per-frame captions (paper)",
                  "methods.captioners.qwen2vl:Qwen2VLCaptioner"),
    CaptionerSpec("file", "real", "captions made elsewhere, read from a JSON file (option path=...)",
                  "methods.captioners.file:FileCaptioner"),
    CaptionerSpec("states", "oracle", "the annotation's states at the training frames (oracle, no generator "
                  "truth: D-NeRF)", "methods.captioners.states:StatesCaptioner"),
)

CAPTIONERS: Registry[CaptionerSpec] = Registry("captioner", lambda: BUILT_IN)
"""Every captioner, by name (the built-in ones, and any registered by hand)."""


def captioner_spec(name: str) -> CaptionerSpec:
    return CAPTIONERS.get(name)


def get_captioner(name: str, scene, **options: Any):
    """Create captioner ``name`` for ``scene`` with ``options`` (keyword arguments of its factory)."""
    factory = CAPTIONERS.load(name)
    try:
        inspect.signature(factory).bind(scene, **options)
    except TypeError as err:
        raise InputError(None, f"captioner {name}", f"bad options {sorted(options)}: {err}") from None
    return factory(scene, **options)


def resolve_captioning(captions, track: str, states: bool = False) -> tuple[str, str]:
    """(captioner name, object-track source) of the ``captions`` group
    (:class:`methods.specs._time_varying.CaptionConfig`) on ``track`` (``"auto"`` resolved). ``states``: the
    run's supervision carries training states (:attr:`methods.supervision.base.Supervision.states`), which
    "auto" captions on the oracle track (``states`` captioner, ``alpha`` tracks) instead of generator truth."""
    captioner = captions.captioner
    if captioner == "auto":
        if track == "oracle":
            captioner = "states" if states else "template"
        else:
            captioner = "file" if captions.file else "qwen2-vl"
    spec = captioner_spec(captioner)
    if spec.track == "oracle" and track != "oracle":
        raise InputError(None, "captioner", f"captioner {captioner!r} reads the oracle's truth: oracle track only")
    tracks = captions.object_tracks
    if tracks == "auto":
        if track == "oracle":
            tracks = "alpha" if captioner == "states" else "truth"
        else:
            tracks = "file" if captions.file else "segments"
    if tracks in ("truth", "alpha") and track != "oracle":
        raise InputError(None, "captions.object_tracks", f"{tracks} tracks read the oracle's truth: oracle track "
                         "only (on the real track use the segments or give the masks in captions.file)")
    if tracks == "file" and not captions.file:
        raise InputError(None, "captions.file", "object_tracks='file' needs captions.file=<JSON with masks>")
    return captioner, tracks


def captioning_unavailable(captions, scene, supervision) -> str:
    """Why the ``captions`` group cannot caption ``scene`` with ``supervision`` (a
    :class:`~methods.supervision.base.Supervision`), or ``""`` when it can: the oracle captioners need
    generator truth (``template``, ``truth`` tracks) or training states (``states``, ``alpha`` tracks)."""
    captioner, tracks = resolve_captioning(captions, supervision.track, bool(supervision.states))
    if captioner == "states" and not supervision.states:
        return f"scene {scene.name!r} has no training states to caption on the {supervision.track} track"
    if captioner == "template" or tracks == "truth":
        from methods.supervision.truth_access import open_truth

        try:
            open_truth(scene)
        except InputError:
            return f"scene {scene.name!r} has no generator truth to caption on the {supervision.track} track"
    return ""
