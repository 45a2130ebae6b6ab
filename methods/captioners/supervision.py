"""Captions as supervision: object tracks of the training frames, their captions (:mod:`methods.captioners`)
and the captions' embeddings, for the time-varying heads (:mod:`methods.fields.time_varying`) and the
caption-replay floor (``nearest-frame``). Imports nothing heavy (no torch)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from benchmark.core.errors import InputError
from benchmark.core.scene import Scene

from . import resolve_captioning


@dataclass
class CaptionSupervision:
    """Object tracks, their captions and caption embeddings on the training frames."""

    tracks: Any
    """:class:`methods.captioners.base.ObjectTracks`."""
    captions: Any
    """:class:`methods.captioners.base.Captions`."""
    texts: list[str]
    """Distinct caption texts."""
    embeddings: np.ndarray
    """(T, D) float32 unit passage embeddings of :attr:`texts`."""
    text_index: dict[tuple[str, int], int]
    """(frame name, object id) -> row of :attr:`embeddings`."""

    @property
    def dim(self) -> int:
        return int(self.embeddings.shape[1])

    def object_rows(self, obj: int) -> list[int]:
        """Embedding rows of ``obj`` over the frames it was captioned in (tracking order)."""
        return [self.text_index[(f, obj)] for f in self.tracks.frame_names if (f, obj) in self.text_index]

    def areas(self) -> np.ndarray:
        """(T,) pixels covered by each distinct caption over all frames (autoencoder weights)."""
        out = np.zeros(len(self.texts))
        for i, name in enumerate(self.tracks.frame_names):
            ids = self.tracks.ids[i]
            counts = np.bincount(ids[ids >= 0].ravel())
            for obj, n in enumerate(counts):
                row = self.text_index.get((name, obj))
                if n and row is not None:
                    out[row] += n
        return out


def build_captions(scene: Scene, track: str, captions, *, supervision=None, cache_root: Optional[Path] = None,
                   device: str = "cpu", progress: Optional[Callable] = None):
    """(Captions, ObjectTracks) of ``scene``'s training frames per the ``captions`` group
    (:class:`methods.specs._time_varying.CaptionConfig`); ``supervision``: the run's
    :class:`~methods.supervision.base.Supervision`, whose segments are the object tracks of
    ``object_tracks="segments"``."""
    from methods.captioners import get_captioner
    from methods.captioners.base import CaptionPromptConfig, caption_objects

    captioner_name, tracks_kind = resolve_captioning(captions, track, bool(getattr(supervision, "states", None)))
    tracks = object_tracks(scene, tracks_kind, captions, supervision)
    if captioner_name == "template":
        captioner = get_captioner("template", scene, seed=captions.seed, noise=captions.noise)
    elif captioner_name == "states":
        captioner = get_captioner("states", scene, states=getattr(supervision, "states", None) or {},
                                  object_name=supervised_object_name(supervision))
    elif captioner_name == "file":
        if not captions.file:
            raise InputError(None, "captions.file", "captioner 'file' needs captions.file=<JSON>")
        captioner = get_captioner("file", scene, path=captions.file)
    else:
        captioner = get_captioner("qwen2-vl", scene, model=captions.qwen_model, device=device)
    prompt = CaptionPromptConfig(visual_prompt=captions.visual_prompt, text_prompt=captions.text_prompt)
    made = caption_objects(captioner, scene, tracks, prompt, cache_root=cache_root, progress=progress)
    return made, tracks


def object_tracks(scene: Scene, kind: str, captions, supervision=None):
    """The :class:`~methods.captioners.base.ObjectTracks` of ``kind`` (``"truth"``, ``"segments"`` or ``"file"``,
    as :func:`resolve_captioning` gives it) on ``scene``'s training frames."""
    from methods.captioners.file import tracks_from_file
    from methods.captioners.states import alpha_tracks
    from methods.captioners.tracks import segment_tracks, truth_tracks

    if kind == "truth":
        return truth_tracks(scene)
    if kind == "alpha":
        return alpha_tracks(scene, supervised_object_name(supervision))
    if kind == "file":
        return tracks_from_file(scene, captions.file)
    if supervision is None:
        raise InputError(None, "captions.object_tracks", "object_tracks='segments' needs the run's supervision "
                         "(its segments are the tracks); give the tracks in captions.file instead")
    return segment_tracks(scene, supervision, min_frames=captions.min_track_frames,
                          min_area=captions.min_track_area)


def supervised_object_name(supervision) -> str:
    """The object name of a supervision by the ``object-name`` source (D-NeRF's oracle track: the scene's
    whole-object query), for the ``states`` captioner and ``alpha`` tracks."""
    name = ((getattr(supervision, "source_configs", None) or {}).get("image_text") or {}).get("object_name")
    if not name:
        raise InputError(None, "captions", "the states captioner and alpha tracks need the object-name source's "
                         "object name (the oracle track of a D-NeRF scene)")
    return str(name)


def embed_captions(captions, tracks, text_encoder) -> CaptionSupervision:
    """Embed every distinct caption once (as a passage)."""
    texts = captions.texts()
    if not texts:
        raise InputError(None, "captions", "no object was captioned in any training frame")
    emb = np.asarray(text_encoder.encode(texts, kind="passage"), dtype=np.float32)
    row = {t: i for i, t in enumerate(texts)}
    index = {key: row[text] for key, text in captions.frames.items()}
    return CaptionSupervision(tracks, captions, texts, emb, index)


def caption_text_encoder(captions, run_encoder, device: str):
    """The text encoder of captions and time-sensitive queries: ``captions.text_encoder`` when set (e.g. the
    paper's e5-mistral), else the run's."""
    if captions.text_encoder is None:
        return run_encoder
    import inspect

    from methods.text_encoders import TEXT_ENCODERS, get_text_encoder

    takes_device = "device" in inspect.signature(TEXT_ENCODERS.load(captions.text_encoder)).parameters
    return get_text_encoder(captions.text_encoder, **({"device": str(device)} if takes_device else {}))
