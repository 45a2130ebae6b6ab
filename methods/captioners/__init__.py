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

import difflib
import importlib
import inspect
from dataclasses import dataclass
from typing import Any

from benchmark.core.errors import InputError


@dataclass(frozen=True)
class CaptionerSpec:
    name: str
    track: str
    """``"oracle"`` or ``"real"``."""
    description: str
    entry_point: str
    """``"module:factory"``; ``factory(scene, **options)`` returns the captioner."""


CAPTIONERS: dict[str, CaptionerSpec] = {s.name: s for s in (
    CaptionerSpec("template", "oracle", "captions from the synthetic scene's states (oracle; paraphrases per frame)",
                  "methods.captioners.template:TemplateCaptioner"),
    CaptionerSpec("qwen2-vl", "real", "Qwen2-VL, video description then per-frame captions (paper)",
                  "methods.captioners.qwen2vl:Qwen2VLCaptioner"),
    CaptionerSpec("file", "real", "captions made elsewhere, read from a JSON file (option path=...)",
                  "methods.captioners.file:FileCaptioner"),
)}


def captioner_spec(name: str) -> CaptionerSpec:
    if name not in CAPTIONERS:
        close = difflib.get_close_matches(name, list(CAPTIONERS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise InputError(None, "captioner", f"unknown captioner {name!r}{hint}; known: {', '.join(CAPTIONERS)}")
    return CAPTIONERS[name]


def get_captioner(name: str, scene, **options: Any):
    """Create captioner ``name`` for ``scene`` with ``options`` (keyword arguments of its factory)."""
    spec = captioner_spec(name)
    module_name, _, attr = spec.entry_point.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise InputError(None, f"captioner {name}", f"cannot import {module_name}: {err}") from err
    factory = getattr(module, attr)
    try:
        inspect.signature(factory).bind(scene, **options)
    except TypeError as err:
        raise InputError(None, f"captioner {name}", f"bad options {sorted(options)}: {err}") from None
    return factory(scene, **options)
