"""Time-sensitive heads of the language-field methods: 4D LangSplat's status field and the Non-Status
baseline, plugged into :class:`methods.language_methods.LanguageFieldModel` as
:class:`~methods.language_methods.TimeVaryingHead` subclasses.

Both fit :func:`methods.fields.time_varying.fit_time_varying_field` on the method's frozen 4D-GS
(shared with the time-agnostic half) and score a time-sensitive query on a frame as the protocol
says: the spatial mask is the time-agnostic answer of the same text (after the 7x7 majority filter,
or before it as the release does: the protocol's :attr:`~benchmark.core.protocol.SensitiveQuery.mask`), and
``s_t`` = mean cosine, over that mask, between the decoded time-varying feature and the query's
text embedding (NaN on an empty mask).

Captions are cached under ``<cache>/captions/`` (the runner's cache folder, or the config's
``shared_cache_dir``), so every method and seed on a scene reuses one captioning run.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch

from benchmark.core.atomic import atomic_path, write_json
from benchmark.core.memory import StagePeak
from benchmark.core.scene import Frame

from .captioners.supervision import caption_text_encoder
from .fields.relevance import AgnosticResult
from .fields.time_varying import build_captions, embed_captions, fit_time_varying_field, load_time_varying_field
from .language_methods import FitContext, LanguageFieldModel, TimeVaryingHead, spatial_mask

STATE_FILE = "time_varying.pt"
INFO_FILE = "time_varying.json"


class _FieldHead(TimeVaryingHead):
    kind: ClassVar[str] = "status"

    def __init__(self, field, text_encoder) -> None:
        self.field = field
        self.text_encoder = text_encoder
        self._queries: dict[str, np.ndarray] = {}

    @classmethod
    def fit(cls, context: FitContext) -> "_FieldHead":
        cfg = context.config
        start = time.perf_counter()
        with StagePeak(context.device) as caption_peak:
            captions, tracks = build_captions(context.scene, context.supervision.track, cfg.captions,
                                              supervision=context.supervision, cache_root=context.cache_root,
                                              device=context.device, progress=context.progress)
            captioned = time.perf_counter()
            encoder = caption_text_encoder(cfg.captions, context.supervision.text_encoder, context.device)
            sup = embed_captions(captions, tracks, encoder)
        embedded = time.perf_counter()
        # captioning is outside fit_time_varying_field (it is cached per scene and shared by the heads),
        # so its time is recorded here, where a run that captions pays it
        captioning = {"seconds": embedded - start, "caption_seconds": captioned - start,
                      "embed_seconds": embedded - captioned, "captioner": captions.captioner,
                      "object_tracks": tracks.source, "captions": len(captions.frames),
                      "video_descriptions": len(captions.video), **caption_peak.record()}
        with StagePeak(context.device) as peak:
            field = fit_time_varying_field(context.shared.geometry, context.scene, sup, cfg, kind=cls.kind,
                                           seed=context.seed, device=context.device, progress=context.progress,
                                           log=context.progress.log, backend=cfg.geometry.render_backend,
                                           cache_dir=None if context.cache_root is None
                                           else Path(context.cache_root) / "captions")
        field.info.update(peak.record())
        field.info["captioning"] = captioning
        mem = field.memory()
        context.progress.log(f"{cls.name}: K = {field.info['num_states']}, {field.info['dynamic_gaussians']} of "
                             f"{mem['gaussians']} Gaussians carry states, {mem['bytes_per_gaussian']:.1f} B/Gaussian, "
                             f"{field.info['train']['seconds']:.1f} s")
        return cls(field, encoder)

    def query_embedding(self, text: str) -> np.ndarray:
        if text not in self._queries:
            self._queries[text] = self.text_encoder.encode([text], kind="query")[0]
        return self._queries[text]

    def score(self, text: str, frame: Frame, spatial: AgnosticResult, model: LanguageFieldModel) -> float:
        return self.field.score(frame, spatial_mask(spatial, model.protocol.sensitive), self.query_embedding(text),
                                tf32=model.config.answer.decode_tf32)

    def save(self, directory: Path) -> None:
        directory = Path(directory)
        with atomic_path(directory / STATE_FILE) as tmp:
            torch.save(self.field.state(), tmp)
        write_json(directory / INFO_FILE, {"head": self.name, "info": self.field.info})

    @classmethod
    def load(cls, directory: Path, *, model: LanguageFieldModel, device: str) -> "_FieldHead":
        state = torch.load(Path(directory) / STATE_FILE, map_location=device, weights_only=True)
        encoder = caption_text_encoder(model.config.captions, model.text_encoder, device)
        return cls(load_time_varying_field(state, model.geometry, device), encoder)


class StatusHead(_FieldHead):
    """4D LangSplat's status deformable network."""

    name = "status-field"
    kind = "status"


class NonStatusHead(_FieldHead):
    """The Non-Status Field baseline: a direct deformation of the feature, ``f + MLP(hexplane(x, t))``."""

    name = "non-status-field"
    kind = "non-status"
