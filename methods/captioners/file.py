"""The ``file`` captioner: captions made elsewhere (another machine, another MLLM), read from JSON.

File format (``format`` and ``version`` are checked; everything is validated with errors that name
the file and the field)::

    {
      "format": "bench4d-captions",
      "version": 1,
      "scene": "split-cookie",                      # optional; checked against the scene's name
      "captioner": "Qwen2-VL-7B-Instruct, ...",     # optional free text
      "objects": {
        "3": {                                      # object id (a non-negative integer, as a string)
          "name": "cookie",                         # optional (reports only)
          "video_description": "a cookie that ...", # optional (step 1 of the two-step prompting)
          "frames": {
            "000004": "the cookie is whole",        # frame name -> caption ...
            "000005": {"caption": "...",            # ... or an object with the caption and,
                       "mask": {"size": [H, W], "counts": "..."}}   # optionally, the object's mask
          }                                         # (COCO RLE, as benchmark.core.annotation.encode_mask)
        }
      }
    }

Masks, when every entry has one, also give the object tracks (:func:`tracks_from_file`), so a real
video segmenter's output can be brought in with its captions. :func:`write_captions_file` writes
this format from any :class:`~methods.captioners.base.Captions` (e.g. to move MLLM captions made on
a GPU machine to a CPU one).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from benchmark.core.atomic import read_json, write_json
from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from .base import Captioner, Captions, ObjectTracks

FILE_FORMAT = "bench4d-captions"
FILE_VERSION = 1


class CaptionsFile:
    """A validated captions file."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(self.path, None, "captions file not found")
        try:
            doc = read_json(self.path)
        except InputError:
            raise
        except Exception as err:  # malformed JSON
            raise InputError(self.path, None, f"not a readable JSON file: {err}") from None
        if not isinstance(doc, dict):
            raise InputError(self.path, None, "top level must be a JSON object")
        if doc.get("format") != FILE_FORMAT:
            raise InputError(self.path, "format", f"expected {FILE_FORMAT!r}, got {doc.get('format')!r}")
        if doc.get("version") != FILE_VERSION:
            raise InputError(self.path, "version", f"unsupported version {doc.get('version')!r} (expected {FILE_VERSION})")
        scene = doc.get("scene")
        if scene is not None and not isinstance(scene, str):
            raise InputError(self.path, "scene", "must be a string")
        self.scene: Optional[str] = scene
        self.captioner = str(doc.get("captioner", ""))
        objects = doc.get("objects")
        if not isinstance(objects, dict) or not objects:
            raise InputError(self.path, "objects", "must be a non-empty object mapping object ids to entries")
        self.names: dict[int, str] = {}
        self.video: dict[int, str] = {}
        self.captions: dict[tuple[str, int], str] = {}
        self.masks: dict[tuple[str, int], dict] = {}
        for key, entry in objects.items():
            where = f"objects.{key}"
            try:
                obj = int(key)
            except (TypeError, ValueError):
                raise InputError(self.path, where, "object ids must be non-negative integers") from None
            if obj < 0 or str(obj) != str(key).strip():
                raise InputError(self.path, where, "object ids must be non-negative integers")
            if not isinstance(entry, dict):
                raise InputError(self.path, where, "must be an object with 'frames'")
            if "name" in entry:
                if not isinstance(entry["name"], str):
                    raise InputError(self.path, f"{where}.name", "must be a string")
                self.names[obj] = entry["name"]
            if "video_description" in entry:
                if not isinstance(entry["video_description"], str):
                    raise InputError(self.path, f"{where}.video_description", "must be a string")
                self.video[obj] = entry["video_description"]
            frames = entry.get("frames")
            if not isinstance(frames, dict) or not frames:
                raise InputError(self.path, f"{where}.frames", "must be a non-empty object mapping frame names to captions")
            for frame, value in frames.items():
                fwhere = f"{where}.frames.{frame}"
                if isinstance(value, str):
                    caption, mask = value, None
                elif isinstance(value, dict):
                    caption, mask = value.get("caption"), value.get("mask")
                    if not isinstance(caption, str):
                        raise InputError(self.path, f"{fwhere}.caption", "missing or not a string")
                    if mask is not None and not (isinstance(mask, dict) and "size" in mask and "counts" in mask):
                        raise InputError(self.path, f"{fwhere}.mask", "must be a COCO RLE object with 'size' and 'counts'")
                else:
                    raise InputError(self.path, fwhere, "must be a caption string or an object with 'caption'")
                if not caption.strip():
                    raise InputError(self.path, fwhere, "empty caption")
                self.captions[(str(frame), obj)] = caption
                if mask is not None:
                    self.masks[(str(frame), obj)] = mask

    def check_scene(self, scene: Scene) -> None:
        """Raise if the file names another scene or frames the scene does not have."""
        if self.scene is not None and self.scene != scene.name:
            raise InputError(self.path, "scene", f"captions are for scene {self.scene!r}, not {scene.name!r}")
        known = {f.name for f in scene.frames}
        unknown = sorted({f for f, _ in self.captions if f not in known})
        if unknown:
            raise InputError(self.path, "objects.*.frames",
                             f"frames not in scene {scene.name!r}: {', '.join(unknown[:5])}"
                             + (" ..." if len(unknown) > 5 else ""))


class FileCaptioner(Captioner):
    """Answers both captioning steps from a :class:`CaptionsFile`."""

    name = "file"
    track = "real"
    uses_images = False

    def __init__(self, scene: Scene, path: str | Path) -> None:
        self.file = CaptionsFile(path)
        self.file.check_scene(scene)

    def config(self) -> dict[str, Any]:
        st = self.file.path.stat()
        return {"name": self.name, "path": self.file.path.name, "size": st.st_size, "mtime_ns": st.st_mtime_ns,
                "captioner": self.file.captioner}

    def describe_video(self, obj: int, frames: Sequence[Frame], images: Sequence[np.ndarray]) -> str:
        return self.file.video.get(int(obj), "")

    def caption_frame(self, obj: int, frame: Frame, images: Sequence[np.ndarray], *,
                      description: Optional[str]) -> str:
        try:
            return self.file.captions[(frame.name, int(obj))]
        except KeyError:
            raise InputError(self.file.path, f"objects.{obj}.frames.{frame.name}",
                             "no caption for this object in this frame (the tracks show it there)") from None


def tracks_from_file(scene: Scene, path: str | Path, frames: Optional[Sequence[Frame]] = None) -> ObjectTracks:
    """Object tracks from the masks of a captions file (every caption must carry its mask)."""
    from benchmark.core.annotation import decode_mask

    from .tracks import tracked_frames

    cf = CaptionsFile(path)
    cf.check_scene(scene)
    if not cf.masks:
        raise InputError(cf.path, "objects.*.frames.*.mask", "the file has no masks, so it gives no object tracks")
    missing = sorted(set(cf.captions) - set(cf.masks))
    if missing:
        f, o = missing[0]
        raise InputError(cf.path, f"objects.{o}.frames.{f}.mask", "a caption without a mask: give every entry its mask")
    frames = list(tracked_frames(scene) if frames is None else frames)
    ids = []
    for frame in frames:
        h, w = frame.camera.height, frame.camera.width
        m = np.full((h, w), -1, dtype=np.int32)
        for (fname, obj), rle in cf.masks.items():
            if fname != frame.name:
                continue
            try:
                mask = decode_mask(rle)
            except Exception as err:
                raise InputError(cf.path, f"objects.{obj}.frames.{fname}.mask", f"cannot decode RLE: {err}") from None
            if mask.shape != (h, w):
                raise InputError(cf.path, f"objects.{obj}.frames.{fname}.mask",
                                 f"mask is {mask.shape[1]}x{mask.shape[0]} but the frame is {w}x{h}")
            if (mask & (m >= 0)).any():
                raise InputError(cf.path, f"objects.{obj}.frames.{fname}.mask", "overlaps another object's mask")
            m[mask] = obj
        ids.append(m)
    return ObjectTracks(source=f"file:{cf.path.name}", frame_names=[f.name for f in frames], ids=ids,
                        labels=dict(cf.names))


def write_captions_file(path: str | Path, captions: Captions, tracks: Optional[ObjectTracks] = None, *,
                        overwrite: bool = False) -> Path:
    """Write ``captions`` (and the masks of ``tracks``) in the file format above, atomically.

    An existing file is replaced only with ``overwrite=True``.
    """
    from benchmark.core.annotation import encode_mask

    path = Path(path)
    if path.exists() and not overwrite:
        raise InputError(path, None, "file exists (pass overwrite=True to replace it)")
    objects: dict[str, Any] = {}
    for (frame, obj), caption in sorted(captions.frames.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        entry = objects.setdefault(str(obj), {"frames": {}})
        if tracks is not None:
            if tracks.labels.get(obj):
                entry["name"] = tracks.labels[obj]
            mask = tracks.mask(tracks.index(frame), obj)
            entry["frames"][frame] = {"caption": caption, "mask": encode_mask(mask)}
        else:
            entry["frames"][frame] = caption
        if obj in captions.video:
            entry["video_description"] = captions.video[obj]
    write_json(path, {"format": FILE_FORMAT, "version": FILE_VERSION, "scene": captions.scene,
                      "captioner": f"{captions.captioner} ({captions.track} track)", "objects": objects})
    return path
