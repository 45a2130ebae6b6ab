"""The one data model: :class:`Camera`, :class:`Frame`, :class:`Scene`.

Every loader produces a :class:`Scene`; every method consumes one. Loaders never leak their file
format past themselves.

Conventions (one for the whole project)
---------------------------------------
* **Camera axes**: OpenCV. x right, y down, z forward (the camera looks along +z).
* **Extrinsics**: ``world_to_camera`` is a 4x4 matrix mapping homogeneous world points to camera
  coordinates: ``X_cam = R @ X_world + t``.
* **Pixels**: continuous pixel coordinates with the *top-left corner* of the image at (0, 0); the
  centre of the pixel in row ``i``, column ``j`` is ``(u, v) = (j + 0.5, i + 0.5)``.
  ``u = fx * x / z + cx``, ``v = fy * y / z + cy``.
* **Distortion**: OpenCV coefficients ``(k1, k2, p1, p2, k3)`` kept where the source has them
  (HyperNeRF); ``None`` for ideal pinholes. :meth:`Camera.project` applies them.
* **Time**: every frame has ``time`` in [0, 1] and an integer ``time_index`` (the video frame number,
  0-based). Annotations and time intervals refer to ``time_index``.
* **Images**: float32 RGB in [0, 1], shape ``(H, W, 3)``; masks are bool ``(H, W)``.

Evaluation splits
-----------------
Every frame has a *frame split* (``train``, ``test``, ``val``: what a method may fit on). Which held-out
frames a run scores is the *evaluation split* (:data:`EVAL_SPLITS`); one fit answers every evaluation split,
since all of them share the training frames:

* ``paper``: the dataset's own held-out frames (HyperNeRF layout: frames ``i % 4 == 2`` of the video,
  training on ``i % 4 == 0``, as the paper and the release's loader do; Neu3D: the held-out camera
  ``cam00``; D-NeRF: its ``test`` frames);
* ``novel-view``: held-out frames seen from cameras no training frame uses (a generated HyperNeRF-layout
  scene renders the scored times a second time from a camera path off the training path; Neu3D: the
  held-out camera; D-NeRF: every frame has its own camera, so its ``test`` frames).

Loaders record the frames of each evaluation split in ``Scene.metadata["eval_splits"]`` (split -> frame
names); a generated scene's annotations record them in ``info["splits"]``. :func:`split_frame_names`
selects a split's frames from either record.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Literal, Mapping, Optional, Sequence

import numpy as np

from .errors import InputError

Split = Literal["train", "test", "val"]
EvalSplit = Literal["paper", "novel-view"]
EVAL_SPLITS: tuple[EvalSplit, ...] = ("paper", "novel-view")
"""Evaluation splits a run can score (module docstring), the default first."""
DEFAULT_EVAL_SPLIT: EvalSplit = "paper"
"""The evaluation split of a run that names none."""
LEGACY_EVAL_SPLIT = "legacy-dense"
"""What results written before evaluation splits existed scored: the synthetic presets then trained on three
frames of every four (``i % 4`` in 0, 1, 3) and scored the fourth; read back under this name."""
EVAL_SPLITS_KEY = "eval_splits"
"""Key of :attr:`Scene.metadata` under which loaders record each evaluation split's frame names."""


@dataclass(frozen=True)
class Camera:
    """A pinhole camera with optional OpenCV distortion (conventions in the module docstring)."""

    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    fx: float
    """Focal length along x, in pixels."""
    fy: float
    """Focal length along y, in pixels."""
    cx: float
    """Principal point x, in pixels (top-left image corner at 0)."""
    cy: float
    """Principal point y, in pixels (top-left image corner at 0)."""
    world_to_camera: np.ndarray
    """(4, 4) float64 world-to-camera transform, OpenCV axes."""
    distortion: Optional[np.ndarray] = None
    """(5,) OpenCV ``k1, k2, p1, p2, k3`` or ``None`` for an ideal pinhole."""

    def __post_init__(self) -> None:
        w2c = np.asarray(self.world_to_camera, dtype=np.float64)
        if w2c.shape != (4, 4):
            raise InputError(None, "world_to_camera", f"expected shape (4, 4), got {w2c.shape}")
        if not np.all(np.isfinite(w2c)):
            raise InputError(None, "world_to_camera", "contains NaN or inf")
        object.__setattr__(self, "world_to_camera", w2c)
        for name in ("fx", "fy", "cx", "cy"):
            value = float(getattr(self, name))
            if not np.isfinite(value):
                raise InputError(None, name, "is NaN or inf")
            object.__setattr__(self, name, value)
        if self.fx <= 0 or self.fy <= 0:
            raise InputError(None, "fx/fy", f"focal lengths must be positive, got {self.fx}, {self.fy}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InputError(None, "width/height", f"must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        if self.distortion is not None:
            dist = np.zeros(5, dtype=np.float64)
            given = np.asarray(self.distortion, dtype=np.float64).ravel()
            dist[: min(5, given.size)] = given[:5]
            object.__setattr__(self, "distortion", None if not np.any(dist) else dist)

    # -- derived quantities -------------------------------------------------------------------
    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def R(self) -> np.ndarray:
        """(3, 3) world-to-camera rotation."""
        return self.world_to_camera[:3, :3]

    @property
    def t(self) -> np.ndarray:
        """(3,) world-to-camera translation."""
        return self.world_to_camera[:3, 3]

    @property
    def camera_to_world(self) -> np.ndarray:
        """(4, 4) inverse of :attr:`world_to_camera`."""
        return np.linalg.inv(self.world_to_camera)

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return -self.R.T @ self.t

    @property
    def fov_x(self) -> float:
        return 2.0 * np.arctan(self.width / (2.0 * self.fx))

    @property
    def fov_y(self) -> float:
        return 2.0 * np.arctan(self.height / (2.0 * self.fy))

    # -- operations -----------------------------------------------------------------------------
    def world_to_cam_points(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 3) camera-frame points."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return points @ self.R.T + self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project (N, 3) world points; returns ((N, 2) pixel coords ``(u, v)``, (N,) depth z).

        Distortion, when present, is applied with OpenCV's model.
        """
        cam = self.world_to_cam_points(points)
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = cam[:, 0] / z
            y = cam[:, 1] / z
        if self.distortion is not None:
            k1, k2, p1, p2, k3 = self.distortion
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
            xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x, y = xd, yd
        uv = np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=-1)
        return uv, z

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Rays through every pixel centre (ignoring distortion).

        Returns ((H, W, 3) origins, (H, W, 3) unit directions) in world coordinates.
        """
        j, i = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        dirs_cam = np.stack([(j - self.cx) / self.fx, (i - self.cy) / self.fy, np.ones_like(j)], -1)
        dirs = dirs_cam @ self.R  # R^T applied to row vectors
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        origins = np.broadcast_to(self.center, dirs.shape).copy()
        return origins, dirs

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by ``factor`` (e.g. 0.5 for half resolution)."""
        return dataclasses.replace(
            self,
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=self.cx * factor,
            cy=self.cy * factor,
        )

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera for an image resized to exactly ``width`` x ``height``."""
        sx, sy = width / self.width, height / self.height
        return dataclasses.replace(
            self, width=int(width), height=int(height), fx=self.fx * sx, fy=self.fy * sy,
            cx=self.cx * sx, cy=self.cy * sy,
        )

    @staticmethod
    def from_opengl_c2w(c2w: np.ndarray, width: int, height: int, fx: float, fy: float,
                        cx: float, cy: float) -> "Camera":
        """Build from an OpenGL/Blender camera-to-world matrix (x right, y up, camera looks -z)."""
        c2w = np.asarray(c2w, dtype=np.float64)
        c2w_cv = c2w.copy()
        c2w_cv[:3, 1:3] *= -1.0  # flip y and z axes: OpenGL -> OpenCV
        return Camera(width, height, fx, fy, cx, cy, np.linalg.inv(c2w_cv))

    def to_dict(self) -> dict:
        return {
            "width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
            "cx": self.cx, "cy": self.cy, "world_to_camera": self.world_to_camera.tolist(),
            "distortion": None if self.distortion is None else self.distortion.tolist(),
        }

    @staticmethod
    def from_dict(d: dict) -> "Camera":
        return Camera(d["width"], d["height"], d["fx"], d["fy"], d["cx"], d["cy"],
                      np.asarray(d["world_to_camera"]), d.get("distortion"))


ImageLoader = Callable[[], np.ndarray]


@dataclass
class Frame:
    """One image of the scene: a camera at a time, with its pixels loaded on demand."""

    name: str
    """Stable identifier inside the scene (usually the image file stem, e.g. ``"000123"``)."""
    camera: Camera
    """Camera of this image (intrinsics sized to the loaded image)."""
    time: float
    """Normalised time in [0, 1]."""
    time_index: int
    """0-based video frame number; annotations and time intervals refer to it."""
    split: Split
    """``"train"``, ``"test"`` or ``"val"``."""
    camera_id: str = "0"
    """Which physical camera took it (multi-camera rigs: ``"cam00"``...; monocular: ``"0"``)."""
    image_path: Optional[Path] = None
    """Where the pixels come from (for messages and caching); may be ``None`` for in-memory frames."""
    load_image: Optional[ImageLoader] = field(default=None, repr=False)
    """Returns (H, W, 3) float32 RGB in [0, 1]; called lazily."""
    load_alpha: Optional[ImageLoader] = field(default=None, repr=False)
    """Returns (H, W) bool foreground mask where the format has one (D-NeRF alpha)."""

    def __post_init__(self) -> None:
        if not np.isfinite(self.time) or not (-1e-9 <= self.time <= 1 + 1e-9):
            raise InputError(self.image_path, "time", f"frame {self.name!r}: time {self.time} not in [0, 1]")
        if self.split not in ("train", "test", "val"):
            raise InputError(self.image_path, "split", f"unknown split {self.split!r}")

    def image(self) -> np.ndarray:
        """(H, W, 3) float32 RGB in [0, 1]."""
        if self.load_image is None:
            raise InputError(self.image_path, "image", f"frame {self.name!r} has no image")
        img = self.load_image()
        if img.shape[:2] != (self.camera.height, self.camera.width):
            raise InputError(self.image_path, "image size",
                             f"image is {img.shape[1]}x{img.shape[0]} but the camera says "
                             f"{self.camera.width}x{self.camera.height}")
        return img

    def alpha(self) -> Optional[np.ndarray]:
        """(H, W) bool foreground mask, or ``None`` if the format has none."""
        return None if self.load_alpha is None else self.load_alpha()


@dataclass
class Scene:
    """A dynamic scene: frames (cameras at times) plus what a method may know a priori."""

    name: str
    """Scene name, e.g. ``"split-cookie"``."""
    dataset: str
    """Source dataset or layout: ``"hypernerf"``, ``"neu3d"``, ``"dnerf"`` (``"synthetic"`` adds truth)."""
    frames: list[Frame]
    """All frames, every split, sorted by (time_index, camera_id)."""
    bounds: np.ndarray
    """(2, 3) axis-aligned world box [min, max] that contains the scene content."""
    root: Optional[Path] = None
    """Folder the scene was loaded from."""
    background: Optional[np.ndarray] = None
    """(3,) RGB the images were composited on (D-NeRF white), or ``None`` for real backgrounds."""
    points: Optional[np.ndarray] = None
    """(N, 3) optional initial point cloud (world coordinates)."""
    point_colors: Optional[np.ndarray] = None
    """(N, 3) RGB in [0, 1] of :attr:`points`, when known."""
    near_far: Optional[tuple[float, float]] = None
    """Depth range of the content in camera space, when the format gives one."""
    metadata: dict = field(default_factory=dict)
    """Free-form, loader-specific facts (never needed by methods)."""

    def __post_init__(self) -> None:
        self.bounds = np.asarray(self.bounds, dtype=np.float64).reshape(2, 3)
        if not np.all(np.isfinite(self.bounds)):
            raise InputError(self.root, "bounds", "contains NaN or inf")
        self.frames = sorted(self.frames, key=lambda f: (f.time_index, f.camera_id, f.name))
        names = [f.name for f in self.frames]
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if names.count(n) > 1})[:5]
            raise InputError(self.root, "frames", f"duplicate frame names {dup}")

    def split(self, split: Split | Sequence[Split]) -> list[Frame]:
        wanted = {split} if isinstance(split, str) else set(split)
        return [f for f in self.frames if f.split in wanted]

    @property
    def train_frames(self) -> list[Frame]:
        return self.split("train")

    @property
    def test_frames(self) -> list[Frame]:
        return self.split("test")

    @property
    def num_time_steps(self) -> int:
        """Number of distinct time indices (video length)."""
        return len({f.time_index for f in self.frames})

    @property
    def camera_ids(self) -> list[str]:
        return sorted({f.camera_id for f in self.frames})

    def frame(self, name: str) -> Frame:
        for f in self.frames:
            if f.name == name:
                return f
        raise KeyError(f"scene {self.name!r} has no frame {name!r}")

    def frames_at(self, time_index: int, camera_id: Optional[str] = None) -> list[Frame]:
        return [f for f in self.frames
                if f.time_index == time_index and (camera_id is None or f.camera_id == camera_id)]

    def summary(self) -> str:
        counts = {s: len(self.split(s)) for s in ("train", "val", "test")}
        cam = self.frames[0].camera if self.frames else None
        size = f"{cam.width}x{cam.height}" if cam else "-"
        return (f"{self.dataset}/{self.name}: {len(self.frames)} frames ({counts['train']} train, "
                f"{counts['val']} val, {counts['test']} test), {self.num_time_steps} time steps, "
                f"{len(self.camera_ids)} camera(s), {size}")


# -- evaluation splits --------------------------------------------------------------------------------
def check_eval_split(split: str) -> EvalSplit:
    """``split`` if it names an evaluation split (:data:`EVAL_SPLITS`), else an :class:`InputError`."""
    if split not in EVAL_SPLITS:
        raise InputError(None, "split", f"unknown evaluation split {split!r} (valid: {', '.join(EVAL_SPLITS)})")
    return split  # type: ignore[return-value]


def split_frame_names(split: str, names: Sequence[str], recorded=None, *, source=None) -> list[str]:
    """The names among ``names`` (held-out frames, e.g. an annotation file's frames) that evaluation split
    ``split`` scores, in the order given.

    ``recorded`` maps split -> frame names (a scene's ``metadata["eval_splits"]``, a generated scene's
    annotation ``info["splits"]``). Where nothing is recorded (``None``: real-data annotations, files made
    before splits were recorded), ``paper`` is every frame of ``names`` and any other split is an
    :class:`InputError` naming ``source``; so is a split the record lacks. Any other name is one too."""
    check_eval_split(split)
    if recorded is None:
        if split == DEFAULT_EVAL_SPLIT:
            return list(names)
        raise InputError(source, "splits", f"records no {split!r} evaluation split (only {DEFAULT_EVAL_SPLIT!r}: "
                                           "its held-out frames)")
    if not isinstance(recorded, Mapping):
        raise InputError(source, "splits", f"expected an object {{split: [frame names]}}, got "
                                           f"{type(recorded).__name__}")
    if split not in recorded:
        have = ", ".join(sorted(map(str, recorded))) or "none"
        raise InputError(source, "splits", f"records no {split!r} evaluation split (recorded: {have})")
    members = recorded[split]
    if not isinstance(members, (list, tuple)) or not all(isinstance(n, str) for n in members):
        raise InputError(source, f"splits.{split}", "expected a list of frame names")
    wanted = set(members)
    return [n for n in names if n in wanted]


def scene_split_frames(scene: "Scene", split: str) -> list[Frame]:
    """The ``test`` frames of ``scene`` that evaluation split ``split`` scores (its loader's record,
    :data:`EVAL_SPLITS_KEY`; a scene without one: ``paper`` is every test frame)."""
    names = split_frame_names(split, [f.name for f in scene.test_frames], scene.metadata.get(EVAL_SPLITS_KEY),
                              source=scene.root)
    wanted = set(names)
    return [f for f in scene.test_frames if f.name in wanted]


def paper_camera(scene: "Scene") -> Optional[str]:
    """The camera a single-camera annotation export (the release's COCO files, which number frames by video
    frame) refers to in a scene of several cameras: the one camera of the ``paper`` split's frames (Neu3D's
    held-out camera; a generated HyperNeRF-layout scene's video camera, not its novel-view path). None where
    the scene has one camera, or that split spans several."""
    if len(scene.camera_ids) < 2:
        return None
    cameras = {f.camera_id for f in scene_split_frames(scene, DEFAULT_EVAL_SPLIT)}
    return next(iter(cameras)) if len(cameras) == 1 else None


def eval_splits_of(frames: Sequence, *, held_out_cameras: bool) -> dict[str, list[str]]:
    """Frame names of each evaluation split (:data:`EVAL_SPLITS`) among the ``test``
    frames (:class:`Frame` or anything with ``name``, ``split`` and ``camera_id``), the record loaders keep in
    ``Scene.metadata["eval_splits"]`` and the generator writes.

    ``held_out_cameras``: every test frame is seen from a camera no training frame uses (a rig's held-out
    camera, D-NeRF's one camera per frame): both splits are all the test frames. Otherwise (a video whose
    cameras are identified by ``camera_id``): ``paper`` holds the test frames of cameras that also train (all
    test frames where none does), ``novel-view`` those of cameras that never train (absent when none)."""
    test = [f for f in frames if f.split == "test"]
    if held_out_cameras:
        names = [f.name for f in test]
        return {"paper": names, "novel-view": list(names)}
    training = {f.camera_id for f in frames if f.split == "train"}
    on_path = [f.name for f in test if f.camera_id in training]
    off_path = [f.name for f in test if f.camera_id not in training]
    out = {"paper": on_path or [f.name for f in test]}
    if off_path:
        out["novel-view"] = off_path
    return out
