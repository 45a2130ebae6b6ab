"""Captioners (MLLM, template, file) behind one interface, and the object-wise visual prompts they see.

==============  ======  ============================================================================
name            track   what it is
==============  ======  ============================================================================
``template``    oracle  captions from the generated scene's semantic states (training frames only)
``qwen2-vl``    real    Qwen2-VL with 4D LangSplat's two-step prompting (transformers; weights local)
``file``        real    captions made elsewhere, read from JSON (:mod:`.file`)
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
