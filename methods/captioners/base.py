"""Object-wise video captioning (4D LangSplat, Sec. 3.3): the interface, the driver and its cache.

4D LangSplat supervises its time-varying field with *captions*: every tracked object of the video
is singled out with a visual prompt (:mod:`.visual_prompt`) and a multimodal LLM describes it in two
steps,

1. a **video-level description** of the object (what it is and how it changes over the video), then
2. a **caption per frame** of the object's state in that frame, with the video-level description
   (and, in the release, the neighbouring frames as extra images) as context.

Pieces here:

* :class:`ObjectTracks`: objects tracked through the training frames, one ``(H, W)`` id map per
  frame (the paper gets them from DEVA; the oracle track from the generator's truth,
  :func:`methods.captioners.tracks.truth_tracks`; any track from a file).
* :class:`Captioner`: one interface for every captioner (``template`` oracle, ``qwen2-vl``, ``file``):
  :meth:`Captioner.describe_video` (step 1) and :meth:`Captioner.caption_frame` (step 2).
* :class:`CaptionPromptConfig`: the prompt ablations of the paper's Table 3 (visual prompt ``blur``
  / ``blur+gray`` / ``blur+gray+contour``; text prompt ``none`` / ``video`` / ``video+image``).
* :func:`caption_objects`: runs both steps over all objects and training frames through the on-disk
  :class:`CaptionCache`, keyed by (scene, captioner, config) per file and by (frame, object) per
  entry, so an interrupted MLLM run resumes where it stopped.

Text-prompt modes (our reading of the paper's ablation, which has no code in the release):

* ``none``: each frame is captioned on its own (no video-level description is made).
* ``video``: the frame caption sees the video-level description.
* ``video+image``: it also sees the object's neighbouring frames (``context_offset`` of the object's
  frames before and after, as the release does with frames ``idx - 3, idx, idx + 3``; at the ends of
  the video the frame is shown alone, as in the release).
"""

from __future__ import annotations

import abc
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar, Iterable, Optional, Sequence

import numpy as np

from benchmark.core.atomic import read_json, write_json
from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from .visual_prompt import VisualPromptConfig, visual_prompt

TEXT_PROMPTS: tuple[str, ...] = ("none", "video", "video+image")
"""Text-prompt modes of the ablation (see the module docstring)."""
VISUAL_PROMPTS: tuple[str, ...] = ("none", "blur", "blur+gray", "blur+gray+contour")
"""Visual-prompt rows of the ablation (:meth:`VisualPromptConfig.ablation`)."""

CACHE_FORMAT = "bench4d-caption-cache"
CACHE_VERSION = 1
CACHE_SUBDIR = "captions"

ProgressFn = Callable[..., Iterable]


def _no_progress(iterable: Iterable, **_: Any) -> Iterable:
    return iterable


# ---------------------------------------------------------------------------------------------------
# Configuration
# ---------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CaptionPromptConfig:
    """How objects are shown to the captioner and what text context it gets (paper defaults)."""

    visual_prompt: str = "blur+gray+contour"
    """Visual prompt: ``"none"``, ``"blur"``, ``"blur+gray"`` or ``"blur+gray+contour"`` (paper: all
    three cues, the last row of its Table 3)."""
    text_prompt: str = "video+image"
    """Text prompt: ``"none"``, ``"video"`` or ``"video+image"`` (module docstring; the release
    captions with the video description and the neighbouring frames)."""
    context_offset: int = 3
    """Context frames are this many of the object's frames before and after (release: 3)."""
    video_frames: int = 8
    """Frames sampled evenly from the object's frames for the video-level description (the release
    samples ``min(round(frames / fps), 18)`` frames of the object's video)."""
    min_object_pixels: int = 4
    """An object counts as visible in a frame (and is captioned there) from this many pixels on."""

    def __post_init__(self) -> None:
        if self.visual_prompt not in VISUAL_PROMPTS:
            raise InputError(None, "visual prompt", f"unknown visual prompt {self.visual_prompt!r}; "
                             f"choose from {', '.join(VISUAL_PROMPTS)}")
        if self.text_prompt not in TEXT_PROMPTS:
            raise InputError(None, "text prompt", f"unknown text prompt {self.text_prompt!r}; "
                             f"choose from {', '.join(TEXT_PROMPTS)}")
        if self.context_offset < 1 or self.video_frames < 1 or self.min_object_pixels < 1:
            raise InputError(None, "caption prompt", "context_offset, video_frames and min_object_pixels must be >= 1")

    def visual(self) -> VisualPromptConfig:
        return VisualPromptConfig.ablation(self.visual_prompt)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


# ---------------------------------------------------------------------------------------------------
# Object tracks
# ---------------------------------------------------------------------------------------------------
@dataclass
class ObjectTracks:
    """Objects tracked through a scene's training frames.

    ``ids[i]`` is the (H, W) int32 map of frame ``frame_names[i]``: the object id of every pixel,
    -1 where no object is. Ids are non-negative integers, consistent across frames (object ``3`` is
    the same object in every frame). Frames are in time order.
    """

    source: str
    """Where the tracks come from (``"truth"``, ``"file:<name>"``)."""
    frame_names: list[str]
    """Training frame names, in time order."""
    ids: list[np.ndarray]
    """Per frame, (H, W) int32 object ids (-1 = none)."""
    labels: dict[int, str] = field(default_factory=dict)
    """Optional human-readable name per object id (reports only; never used by a method)."""

    def __post_init__(self) -> None:
        if len(self.frame_names) != len(self.ids):
            raise ValueError(f"{len(self.frame_names)} frame names for {len(self.ids)} id maps")
        self.ids = [np.asarray(m, dtype=np.int32) for m in self.ids]
        for name, m in zip(self.frame_names, self.ids):
            if m.ndim != 2:
                raise ValueError(f"id map of frame {name!r} must be (H, W), got {m.shape}")
        self._index = {n: i for i, n in enumerate(self.frame_names)}
        self._counts: Optional[list[dict[int, int]]] = None

    def pixel_counts(self) -> list[dict[int, int]]:
        """Per frame, object id -> its pixels there (counted once: segment tracks have many objects)."""
        if self._counts is None:
            self._counts = [dict(zip(*(v.tolist() for v in np.unique(m[m >= 0], return_counts=True))))
                            for m in self.ids]
        return self._counts

    def index(self, frame_name: str) -> int:
        try:
            return self._index[frame_name]
        except KeyError:
            raise KeyError(f"no tracks for frame {frame_name!r}") from None

    def objects(self) -> list[int]:
        """Every object id that appears in some frame, sorted."""
        return sorted(set().union(*self.pixel_counts()))

    def mask(self, frame_index: int, obj: int) -> np.ndarray:
        """(H, W) bool pixels of ``obj`` in frame ``frame_index``."""
        return self.ids[frame_index] == obj

    def frames_of(self, obj: int, min_pixels: int = 1) -> list[int]:
        """Indices of the frames where ``obj`` covers at least ``min_pixels`` pixels."""
        return [i for i, counts in enumerate(self.pixel_counts()) if counts.get(obj, 0) >= min_pixels]

    def fingerprint(self) -> str:
        """Hash of the frames and id maps (part of caption cache keys)."""
        import hashlib

        digest = hashlib.sha256(self.source.encode())
        for name, m in zip(self.frame_names, self.ids):
            digest.update(name.encode())
            digest.update(np.ascontiguousarray(m, dtype=np.int32).tobytes())
            digest.update(str(m.shape).encode())
        return digest.hexdigest()[:16]


# ---------------------------------------------------------------------------------------------------
# The captioner interface
# ---------------------------------------------------------------------------------------------------
class Captioner(abc.ABC):
    """Describes one tracked object: first over the video (step 1), then per frame (step 2)."""

    name: ClassVar[str] = "captioner"
    track: ClassVar[str] = "real"
    """``"oracle"`` (reads the generator's truth of training frames) or ``"real"``."""
    uses_images: ClassVar[bool] = True
    """Whether the captioner looks at the (visually prompted) images; when False the driver does not
    build them and the prompt ablations change nothing but the cache key."""

    def config(self) -> dict[str, Any]:
        """What identifies this captioner's outputs (goes into cache keys)."""
        return {"name": self.name}

    def describe_video(self, obj: int, frames: Sequence[Frame], images: Sequence[np.ndarray]) -> str:
        """Step 1: a video-level description of object ``obj``.

        Args:
            frames: the sampled frames showing the object, in time order.
            images: per frame, (H, W, 3) float32 RGB in [0, 1] with the object visually prompted
                (empty when :attr:`uses_images` is False).
        """
        return ""

    @abc.abstractmethod
    def caption_frame(self, obj: int, frame: Frame, images: Sequence[np.ndarray], *,
                      description: Optional[str]) -> str:
        """Step 2: the state of object ``obj`` in ``frame``.

        Args:
            images: (H, W, 3) float32 RGB in [0, 1], visually prompted: the frame alone, or
                ``[previous, frame, next]`` context frames (text prompt ``video+image``); empty when
                :attr:`uses_images` is False.
            description: the video-level description (None for text prompt ``none``).
        """


# ---------------------------------------------------------------------------------------------------
# Captions
# ---------------------------------------------------------------------------------------------------
@dataclass
class Captions:
    """Every caption of a scene's tracked objects."""

    scene: str
    captioner: str
    track: str
    """Supervision track of the captioner (``"oracle"`` or ``"real"``)."""
    config: dict[str, Any]
    """The captioner's and the prompt's configuration."""
    video: dict[int, str] = field(default_factory=dict)
    """Object id -> video-level description (absent for text prompt ``none``)."""
    frames: dict[tuple[str, int], str] = field(default_factory=dict)
    """(frame name, object id) -> caption."""

    def objects(self) -> list[int]:
        return sorted({o for _, o in self.frames})

    def of_object(self, obj: int) -> dict[str, str]:
        """Frame name -> caption of ``obj``."""
        return {f: c for (f, o), c in self.frames.items() if o == obj}

    def texts(self) -> list[str]:
        """Distinct captions, sorted (what the text encoder has to embed)."""
        return sorted(set(self.frames.values()))


# ---------------------------------------------------------------------------------------------------
# Cache
# ---------------------------------------------------------------------------------------------------
class CaptionCache:
    """One JSON file per (scene, captioner, config): video descriptions and (frame, object) captions.

    Written atomically, every ``flush_every`` new entries and at the end, so an interrupted run
    resumes. A file that cannot be read or whose key differs is ignored (and later replaced): a cache
    is never trusted over recomputing.
    """

    def __init__(self, path: Optional[Path], key: str, meta: dict[str, Any], flush_every: int = 16) -> None:
        self.path = None if path is None else Path(path)
        self.key = key
        self.meta = meta
        self.flush_every = max(1, int(flush_every))
        self.video: dict[str, str] = {}
        self.frames: dict[str, dict[str, str]] = {}
        self._pending = 0
        self.loaded_entries = 0
        if self.path is not None and self.path.is_file():
            try:
                doc = read_json(self.path)
            except Exception:  # unreadable cache: recompute
                doc = None
            if (isinstance(doc, dict) and doc.get("format") == CACHE_FORMAT and doc.get("version") == CACHE_VERSION
                    and doc.get("key") == key and isinstance(doc.get("video"), dict)
                    and isinstance(doc.get("frames"), dict)):
                self.video = {str(k): str(v) for k, v in doc["video"].items()}
                self.frames = {str(f): {str(o): str(c) for o, c in objs.items()}
                               for f, objs in doc["frames"].items() if isinstance(objs, dict)}
                self.loaded_entries = sum(len(v) for v in self.frames.values())

    def get_video(self, obj: int) -> Optional[str]:
        return self.video.get(str(obj))

    def put_video(self, obj: int, text: str) -> None:
        self.video[str(obj)] = text
        self._touch()

    def get(self, frame: str, obj: int) -> Optional[str]:
        return self.frames.get(frame, {}).get(str(obj))

    def put(self, frame: str, obj: int, text: str) -> None:
        self.frames.setdefault(frame, {})[str(obj)] = text
        self._touch()

    def _touch(self) -> None:
        self._pending += 1
        if self._pending >= self.flush_every:
            self.flush()

    def flush(self) -> None:
        if self.path is None or self._pending == 0:
            self._pending = 0
            return
        write_json(self.path, {"format": CACHE_FORMAT, "version": CACHE_VERSION, "key": self.key, **self.meta,
                               "video": self.video, "frames": self.frames})
        self._pending = 0


def caption_cache_path(cache_root: Path, scene: Scene, captioner: Captioner, key: str) -> Path:
    """``<cache_root>/captions/<dataset>-<scene>/<captioner>-<key>.json``."""
    return Path(cache_root) / CACHE_SUBDIR / f"{scene.dataset}-{scene.name}" / f"{captioner.name}-{key}.json"


def caption_key(scene: Scene, captioner: Captioner, prompt: CaptionPromptConfig, tracks: ObjectTracks) -> str:
    """Hash of what the captions depend on: the scene's training frames, captioner, prompt, tracks."""
    from benchmark.core.cache_keys import scene_fingerprint, stable_hash

    frames = [scene.frame(n) for n in tracks.frame_names]
    return stable_hash({"scene": scene_fingerprint(scene, frames), "captioner": captioner.config(),
                        "prompt": prompt.to_dict(), "tracks": tracks.fingerprint()}, 16)


# ---------------------------------------------------------------------------------------------------
# The driver
# ---------------------------------------------------------------------------------------------------
def _even_sample(indices: Sequence[int], count: int) -> list[int]:
    """``count`` items spread evenly over ``indices`` (all of them when there are fewer)."""
    if len(indices) <= count:
        return list(indices)
    picks = np.linspace(0, len(indices) - 1, count).round().astype(int)
    return [indices[int(p)] for p in picks]


def caption_objects(captioner: Captioner, scene: Scene, tracks: ObjectTracks,
                    prompt: Optional[CaptionPromptConfig] = None, *, cache_root: Optional[Path] = None,
                    progress: Optional[ProgressFn] = None, flush_every: int = 16) -> Captions:
    """Caption every tracked object in every training frame where it is visible (module docstring).

    Args:
        captioner: any :class:`Captioner`.
        scene: the scene ``tracks`` were made on (frames by name).
        tracks: the objects to caption.
        prompt: visual/text prompt settings (paper defaults).
        cache_root: root of the on-disk caption cache; ``None`` = no cache.
        progress: ``progress(iterable, desc=..., total=...)`` wrapper (tqdm-like) or ``None``.
    """
    prompt = prompt or CaptionPromptConfig()
    progress = progress or _no_progress
    key = caption_key(scene, captioner, prompt, tracks)
    path = None if cache_root is None else caption_cache_path(cache_root, scene, captioner, key)
    cache = CaptionCache(path, key, {"scene": scene.name, "captioner": captioner.name,
                                     "captioner_config": captioner.config(), "prompt": prompt.to_dict()},
                         flush_every)
    vp_cfg = prompt.visual()
    frames = [scene.frame(n) for n in tracks.frame_names]
    image_memo: dict[int, np.ndarray] = {}

    def raw_image(i: int) -> np.ndarray:
        if i not in image_memo:
            img = np.asarray(frames[i].image(), dtype=np.float32)
            if img.shape[:2] != tracks.ids[i].shape:
                raise InputError(frames[i].image_path, "tracks",
                                 f"object ids of frame {frames[i].name!r} are {tracks.ids[i].shape} "
                                 f"but its image is {img.shape[:2]}")
            image_memo[i] = img[..., :3]
        return image_memo[i]

    def prompted(i: int, obj: int) -> np.ndarray:
        return visual_prompt(raw_image(i), tracks.mask(i, obj), vp_cfg)

    out = Captions(scene=scene.name, captioner=captioner.name, track=captioner.track,
                   config={"captioner": captioner.config(), "prompt": prompt.to_dict()})
    objects = tracks.objects()
    work = [(obj, tracks.frames_of(obj, prompt.min_object_pixels)) for obj in objects]
    total = sum(len(idx) for _, idx in work)
    bar = progress(range(total), desc=f"captions ({captioner.name})", total=total)
    ticks = iter(bar)
    try:
        for obj, idxs in work:
            if not idxs:
                continue
            description = None
            if prompt.text_prompt != "none":
                description = cache.get_video(obj)
                if description is None:
                    sample = _even_sample(idxs, prompt.video_frames)
                    images = [prompted(i, obj) for i in sample] if captioner.uses_images else []
                    description = str(captioner.describe_video(obj, [frames[i] for i in sample], images))
                    cache.put_video(obj, description)
                out.video[obj] = description
            for pos, i in enumerate(idxs):
                next(ticks, None)
                name = frames[i].name
                text = cache.get(name, obj)
                if text is None:
                    if prompt.text_prompt == "video+image" and pos - prompt.context_offset >= 0 \
                            and pos + prompt.context_offset < len(idxs):
                        shown = [idxs[pos - prompt.context_offset], i, idxs[pos + prompt.context_offset]]
                    else:
                        shown = [i]
                    images = [prompted(j, obj) for j in shown] if captioner.uses_images else []
                    text = str(captioner.caption_frame(obj, frames[i], images, description=description))
                    cache.put(name, obj, text)
                out.frames[(name, obj)] = text
                # decoded images are only reused by the next few frames' context
                for stale in [k for k in image_memo if k < i - prompt.context_offset]:
                    del image_memo[stale]
    finally:
        cache.flush()
        close = getattr(bar, "close", None)
        if close is not None:
            close()
    return out
