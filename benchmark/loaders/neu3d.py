"""Neu3D / DyNeRF multi-view video scenes (``poses_bounds.npy`` + one video per camera).

Layout::

    poses_bounds.npy         (N, 17) per camera, cameras in sorted name order (cam00, cam01, ...)
    camXX.mp4                one synchronised video per camera, or extracted frames:
    camXX/images/NNNN.png    (also accepted: camXX/NNNN.png; extracted frames win over a video)
    bench4d_meta.json        optional {"num_frames": N} (written by the synthetic generator)

Conventions applied:

* Each row of ``poses_bounds.npy`` is a row-major 3x5 matrix ``[c2w rotation | centre | (H, W, f)]``
  followed by ``near, far``. The rotation columns are LLFF's (down, right, backwards); the OpenCV
  camera-to-world columns are ``(x right, y down, z forward) = (col1, col0, -col2)``.
* ``fx = fy = f`` at the ``(H, W)`` of the file; the principal point is the image centre
  ``(W/2, H/2)`` (pixel corners at 0). Intrinsics follow the **actual** frame size on disk
  (frames extracted at half resolution get half the focal length), then ``scale`` (a resolution
  multiplier, area-resized) on top. The released DyNeRF videos are 2704x2028: the protocol's
  1352x1014 is ``scale=0.5``.
* Time: frame ``k`` (0-based, first ``num_frames`` frames of each video) has ``time_index = k`` and
  ``time = k / num_frames``; ``num_frames`` is the option, else ``bench4d_meta.json``, else
  :attr:`Neu3DOptions.default_num_frames` (300, the protocol's divisor for the real data).
* Frames are named ``camXX_NNNN`` (``camera_id = "camXX"``). ``cam00`` is the test view, every other
  camera trains (:attr:`Neu3DOptions.test_cameras`).
* Videos are decoded lazily, once per camera and output size, on the first pixel access: into PNGs
  under a cache folder (default ``$BENCH4D_CACHE`` or ``~/.cache/bench4d``, keyed by the video's path,
  size and mtime) or, with ``video_cache="memory"``, into RAM.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import tempfile
import threading
import warnings
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from benchmark.core.atomic import read_json
from benchmark.core.errors import InputError
from benchmark.core.imageio import native_decoder_messages, read_image, refuse_if_said
from benchmark.core.scene import Camera, Frame, Scene, eval_splits_of
from benchmark.core.strict import check_npy
from . import _common as C

LAYOUT = "neu3d"
VIDEO_REFUSED = "damaged video"
"""How a video FFmpeg (inside OpenCV) complained about while opening or reading it is refused: it printed
because the file is damaged (a cut container, a broken frame header)."""
SPLIT_RULES = ("test-cameras",)
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
META_FILE = "bench4d_meta.json"
MAX_POSES_BYTES = 16 << 20
"""Largest ``poses_bounds.npy`` read: 123 K cameras of 17 float64 (a capture has a few dozen)."""


@dataclass
class Neu3DOptions:
    """Options of :func:`load` (pass them as keywords to :func:`benchmark.loaders.load_scene`)."""

    scale: Optional[float] = None
    """Resolution multiplier relative to the frames on disk (0.5 = half); ``None`` = as stored."""
    split_rule: Optional[str] = None
    """Only ``"test-cameras"`` (the default): :attr:`test_cameras` test, the others train."""
    test_cameras: tuple[str, ...] = ("cam00",)
    """Held-out views (the protocol's cam00)."""
    num_frames: Optional[int] = None
    """Frames used per camera and the time divisor; ``None``: ``bench4d_meta.json`` or the default."""
    default_num_frames: int = 300
    """The protocol uses the first 300 frames and t = frame / 300 for the real data."""
    video_cache: str = "disk"
    """Where decoded video frames go: ``"disk"`` (PNG cache folder) or ``"memory"`` (all frames of
    every accessed camera stay in RAM: small scenes and tests only)."""
    cache_dir: Optional[Path] = None
    """Root of the disk cache; ``None``: ``$BENCH4D_CACHE`` or ``~/.cache/bench4d``."""


def detect(root: Path) -> bool:
    return (root / "poses_bounds.npy").is_file()


def llff_to_opencv_c2w(pose: np.ndarray) -> np.ndarray:
    """(3, 4) LLFF ``[down, right, backwards | centre]`` -> (4, 4) OpenCV camera-to-world."""
    c2w = np.eye(4)
    c2w[:3, 0] = pose[:, 1]
    c2w[:3, 1] = pose[:, 0]
    c2w[:3, 2] = -pose[:, 2]
    c2w[:3, 3] = pose[:, 3]
    return c2w


def default_cache_dir() -> Path:
    env = os.environ.get("BENCH4D_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "bench4d"


class VideoFrames:
    """Frames ``0 .. count-1`` of one video at a fixed output size, decoded once on first access."""

    def __init__(self, path: Path, count: int, width: int, height: int, mode: str, cache_root: Path):
        self.path, self.count, self.width, self.height = Path(path), count, width, height
        self.mode, self.cache_root = mode, Path(cache_root)
        self._frames: Optional[list[np.ndarray]] = None  # (H, W, 3) uint8 RGB each, memory mode
        self._lock = threading.Lock()

    def __getstate__(self) -> dict:  # picklable for worker processes: no lock, no decoded pixels
        state = dict(self.__dict__)
        state["_lock"], state["_frames"] = None, None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    @property
    def cache_folder(self) -> Path:
        st = self.path.stat()
        key = hashlib.sha1(f"{self.path.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode()).hexdigest()[:12]
        return self.cache_root / "neu3d" / f"{self.path.stem}-{key}-{self.width}x{self.height}-{self.count}"

    def _decode(self):
        """Yield (H, W, 3) uint8 BGR frames at the output size."""
        with native_decoder_messages() as said:  # FFmpeg prints on fd 2: an open it complains about is refused
            cap = cv2.VideoCapture(str(self.path))
        try:
            refuse_if_said(self.path, said, VIDEO_REFUSED, "video")
            if not cap.isOpened():
                raise InputError(self.path, "video", "cannot open the video")
            for k in range(self.count):
                with native_decoder_messages() as said:
                    ok, frame = cap.read()
                refuse_if_said(self.path, said, VIDEO_REFUSED, f"frame {k}")
                if not ok or frame is None:
                    raise InputError(self.path, f"frame {k}", f"video ends after {k} frames, expected {self.count}")
                yield C.resize(frame, self.width, self.height)
        finally:
            cap.release()

    def _fill_disk_cache(self, folder: Path) -> None:
        folder.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
        try:
            for k, frame in enumerate(self._decode()):
                if not cv2.imwrite(str(tmp / f"{k:04d}.png"), frame, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
                    raise InputError(tmp, "cache", "cannot write decoded frames (disk full or read-only?)")
            try:
                os.rename(tmp, folder)  # atomic: readers see the whole folder or none
            except OSError:
                if not folder.is_dir():  # not a lost race with another process
                    raise
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)

    def rgb(self, index: int) -> np.ndarray:
        """(H, W, 3) float32 RGB in [0, 1] of frame ``index``."""
        if not 0 <= index < self.count:
            raise InputError(self.path, "frame", f"frame {index} out of range 0..{self.count - 1}")
        if self.mode == "memory":
            with self._lock:
                if self._frames is None:
                    self._frames = [cv2.cvtColor(f, cv2.COLOR_BGR2RGB) for f in self._decode()]
            return self._frames[index].astype(np.float32) / 255.0
        folder = self.cache_folder
        with self._lock:
            if not folder.is_dir():
                self._fill_disk_cache(folder)
        return read_image(folder / f"{index:04d}.png")


def _frame_files(folder: Path) -> list[Path]:
    """Numbered image files of an extracted-frames folder, in order; gaps are errors."""
    files = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()]
    numbered = []
    for p in files:
        if not re.fullmatch(r"\d+", p.stem):
            raise InputError(p, "file name", "extracted frames must be named by their number (e.g. 0000.png)")
        numbered.append((int(p.stem), p))
    numbered.sort()
    if not numbered:
        raise InputError(folder, "frames", "no frame images")
    first = numbered[0][0]
    for k, (num, p) in enumerate(numbered):
        if num != first + k:
            raise InputError(folder, "frames", f"frame {first + k} is missing (next is {p.name})")
    return [p for _, p in numbered]


def _camera_sources(root: Path) -> dict[str, tuple[str, object]]:
    """camera name -> ("frames", [paths]) or ("video", path); extracted frames take precedence."""
    sources: dict[str, tuple[str, object]] = {}
    for p in sorted(root.iterdir()):
        m = re.fullmatch(r"(cam\d+)(\.mp4)?", p.name, flags=re.IGNORECASE)
        if not m:
            continue
        name = m.group(1)
        if p.is_dir():
            sub = p / "images" if (p / "images").is_dir() else p
            if any(q.suffix.lower() in IMAGE_SUFFIXES for q in sub.iterdir()):
                sources[name] = ("frames", _frame_files(sub))
        elif p.is_file() and m.group(2) and name not in sources:
            sources[name] = ("video", p)
    return dict(sorted(sources.items(), key=lambda kv: (int(kv[0][3:]), kv[0])))


def _video_info(path: Path) -> tuple[int, int, int]:
    """(width, height, frame count) from the container metadata."""
    with native_decoder_messages() as said:  # FFmpeg prints on fd 2 (a missing index, a damaged header)
        cap = cv2.VideoCapture(str(path))
    try:
        refuse_if_said(path, said, VIDEO_REFUSED, "video")
        if not cap.isOpened():
            raise InputError(path, "video", "cannot open the video (missing codec or not a video)")
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    finally:
        cap.release()
    if w <= 0 or h <= 0 or n <= 0:
        raise InputError(path, "video", f"no frames or no size (width {w}, height {h}, frames {n})")
    return w, h, n


def _read_poses(path: Path) -> np.ndarray:
    """The (N, 17) rows of ``poses_bounds.npy`` as float64, checked finite."""
    check_npy(path, max_bytes=MAX_POSES_BYTES, kinds="iuf")  # before np.load allocates what the header claims
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise InputError(path, None, f"cannot read a numpy array ({err})") from None
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] < 1:
        raise InputError(path, "shape", f"expected (num_cameras, 17), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise InputError(path, "dtype", f"expected numbers, got {arr.dtype}")
    arr = arr.astype(np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(arr), axis=1))
    if bad.size:
        raise InputError(path, f"row {bad[0]}", "contains NaN or inf")
    return arr


def _num_frames(root: Path, opts: Neu3DOptions) -> tuple[int, str]:
    if opts.num_frames is not None:
        return C.as_int(opts.num_frames, None, "num_frames", minimum=1), "option num_frames"
    meta_path = root / META_FILE
    if meta_path.is_file():
        meta = read_json(meta_path)
        return C.as_int(C.get_key(meta, "num_frames", meta_path), meta_path, "num_frames", minimum=1), META_FILE
    return C.as_int(opts.default_num_frames, None, "default_num_frames", minimum=1), "default"


def load(path: str | Path, options: Optional[Neu3DOptions] = None) -> Scene:
    """Load a Neu3D/DyNeRF scene folder (conventions in the module docstring)."""
    opts = options or Neu3DOptions()
    root = Path(path)
    if (opts.split_rule or "test-cameras") not in SPLIT_RULES:
        raise InputError(None, "split_rule", f"unknown rule {opts.split_rule!r} for {LAYOUT} "
                                             f"(valid: {', '.join(SPLIT_RULES)})")
    if opts.video_cache not in ("disk", "memory"):
        raise InputError(None, "video_cache", f"expected 'disk' or 'memory', got {opts.video_cache!r}")
    poses_path = root / "poses_bounds.npy"
    arr = _read_poses(poses_path)
    sources = _camera_sources(root)
    if len(sources) != len(arr):
        raise InputError(poses_path, "shape", f"{len(arr)} poses for {len(sources)} cameras found in {root} "
                                              f"({', '.join(sources) or 'no camXX.mp4 or camXX/ folders'})")
    test_cameras = (opts.test_cameras,) if isinstance(opts.test_cameras, str) else tuple(opts.test_cameras)
    unknown = sorted(set(test_cameras) - set(sources))
    if unknown:
        raise InputError(None, "test_cameras", f"no camera {unknown[0]!r} in {root}")
    if not set(sources) - set(test_cameras):
        raise InputError(root, "cameras", "no training camera (every camera is a test camera)")
    num_frames, frames_source = _num_frames(root, opts)
    cache_root = Path(opts.cache_dir) if opts.cache_dir is not None else default_cache_dir()

    frames, cameras, nears, fars, short = [], [], [], [], []
    for row, (name, (kind, src)) in zip(arr, sources.items()):
        pose = row[:15].reshape(3, 5)
        field = f"row {len(cameras)} ({name})"
        height, width, focal = pose[:, 4]
        near, far = row[15], row[16]
        if height <= 0 or width <= 0 or focal <= 0:
            raise InputError(poses_path, field, f"H, W, focal must be positive, got {height}, {width}, {focal}")
        if not 0 < near < far:
            raise InputError(poses_path, field, f"need 0 < near < far, got {near}, {far}")
        C.check_rotation(pose[:, :3], poses_path, field)
        if kind == "frames":
            files: list[Path] = src  # type: ignore[assignment]
            disk_w, disk_h = C.image_size(files[0])
            available = len(files)
        else:
            disk_w, disk_h, available = _video_info(src)  # type: ignore[arg-type]
        count = min(num_frames, available)
        if count < num_frames:
            short.append(f"{name}: {available}")
        out_w, out_h = C.target_size(disk_w, disk_h, opts.scale)
        sx, sy = disk_w / width, disk_h / height  # the frames on disk may be downsampled
        camera = Camera(disk_w, disk_h, focal * sx, focal * sy, disk_w / 2.0, disk_h / 2.0,
                        np.linalg.inv(llff_to_opencv_c2w(pose[:, :4]))).resized(out_w, out_h)
        cameras.append(camera)
        nears.append(near)
        fars.append(far)
        split = "test" if name in test_cameras else "train"
        video = None if kind == "frames" else VideoFrames(src, count, out_w, out_h, opts.video_cache, cache_root)
        for k in range(count):
            if video is None:
                image_path = files[k]
                loader = (partial(C.load_rgb, image_path) if opts.scale is None
                          else partial(C.load_rgb, image_path, out_w, out_h))
            else:
                image_path = src  # type: ignore[assignment]
                loader = partial(video.rgb, k)
            frames.append(Frame(name=f"{name}_{k:04d}", camera=camera, time=k / num_frames, time_index=k,
                                split=split, camera_id=name, image_path=image_path, load_image=loader))
    if short:
        warnings.warn(f"{root}: fewer than {num_frames} frames in {', '.join(short)}; times stay k / {num_frames}",
                      stacklevel=3)  # the caller of load_scene
    return Scene(
        name=root.resolve().name, dataset=LAYOUT, frames=frames,
        bounds=C.frustum_bounds(cameras, nears, fars), root=root,
        near_far=(float(min(nears)), float(max(fars))),
        metadata={"layout": LAYOUT, "num_frames": num_frames, "num_frames_source": frames_source,
                  "test_cameras": list(test_cameras),
                  # the held-out camera is the novel view: both evaluation splits score it
                  "eval_splits": eval_splits_of(frames, held_out_cameras=True),
                  "sources": {n: k for n, (k, _) in sources.items()}},
    )
