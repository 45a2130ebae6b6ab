"""HyperNeRF / Nerfies scenes (monocular video, ``camera/<id>.json`` per frame).

Layout::

    scene.json      {"scale", "center", "near", "far"}
    dataset.json    {"ids", "train_ids", "val_ids"}
    metadata.json   {id: {"warp_id", "camera_id", "time_id", "appearance_id"}}   (optional, see below)
    camera/<id>.json
    rgb/{1x,2x,4x}/<id>.png
    points.npy      (optional, (N, 3) initial point cloud in the same coordinates as the cameras)

Conventions applied (all checked against the Nerfies/HyperNeRF ``camera.py``):

* ``orientation`` is the **world-to-camera rotation** (its rows are the camera x/y/z axes in world
  coordinates) and ``position`` the camera centre, so ``x_cam = orientation @ (p - position)``.
  Camera axes are already OpenCV (x right, y down, looking along +z).
* ``image_size`` is ``[width, height]`` (Nerfies reads ``image_size_x = image_size[0]``); the
  protocol note that says ``[H, W]`` is wrong. ``principal_point`` is ``[x, y]``. Nerfies pixel
  centres are at ``index + 0.5``, the same as ours, so no half-pixel shift is applied.
* ``fx = focal_length``, ``fy = focal_length * pixel_aspect_ratio``; distortion is
  ``radial_distortion = [k1, k2, k3]``, ``tangential_distortion = [p1, p2]`` (older files:
  ``tangential``) with exactly OpenCV's model, stored as OpenCV ``(k1, k2, p1, p2, k3)``.
  Non-zero ``skew`` has no place in the pinhole model: it is an error unless ``ignore_skew=True``.
* **Normalisation** (``normalize=True``, the default, as the 4D-GS/4D LangSplat loaders do):
  world = ``(position - scene.center) * scene.scale`` for camera centres and ``points.npy``.
  ``scene.json``'s near/far are in these normalised units; with ``normalize=False`` they are divided
  by ``scale`` to stay consistent with the raw coordinates.
* **Resolution**: ``scale`` is a resolution multiplier relative to the 1x images (``0.5`` = the
  ``rgb/2x`` folder, which is what the release renders and the default when it exists; else 1x).
  Strings ``"1x"``/``"2x"``/``"4x"`` are accepted too. Intrinsics are scaled by the ratio of the
  actual image size (read from the first image's header) to the 1x size. A multiplier with no
  folder of its own is resized (area averaging) from the closest finer folder.
* **Time**: ``time_index = warp_id`` and ``time = warp_id / max(warp_id)``. Without
  ``metadata.json`` (e.g. a bare camera export) the id order gives the time: ``time_index = i``,
  ``time = i / (N - 1)``, with a warning.
* **Splits** (``split_rule``): ``"auto"`` uses ``train_ids``/``val_ids`` when ``val_ids`` is non-empty
  (``val_ids`` become the **test** split), else ``"every4"``: frame ``i`` (position in ``ids``) trains
  when ``i % 4 == 0`` and is a test view when ``i % 4 == 2``. ``"every4-release"`` additionally drops
  the last test frame, as the release's ``i_test[:-1]`` does. Frames that are neither train nor test
  stay in the scene with split ``"val"``: methods never train on them, but their cameras let
  annotations on any video frame be evaluated.
* **Evaluation splits** (``metadata["eval_splits"]``, :mod:`benchmark.core.scene`): ``paper`` is the test
  frames of the camera(s) that train, ``novel-view`` the test frames of a ``camera_id`` that never trains
  (a second camera path; HyperNeRF's ``vrig`` captures hold out their second camera the same way).
* **Bounds** (without ``points.npy``): the box of the *training* frames' view frustums between near and far.
"""

from __future__ import annotations

import re
import warnings
from collections import Counter
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Optional, Union

import numpy as np

from benchmark.core.atomic import read_json
from benchmark.core.errors import InputError
from benchmark.core.scene import Camera, Frame, Scene, eval_splits_of
from benchmark.core.strict import MAX_COUNT, check_finite, check_int, check_npy
from . import _common as C

LAYOUT = "hypernerf"
SPLIT_RULES = ("auto", "every4", "every4-release", "dataset")
MAX_POINTS_BYTES = 1 << 30
"""Largest ``points.npy`` read (44 M float64 points; a capture's sparse cloud is well under a million)."""
FOCAL_RANGE = (1e-3, 1e7)
"""Focal lengths (pixels) a camera file may give: below a thousandth of a pixel or above ten million (a field of
view under 0.01 degree on a 64 K-pixel image) no real camera is meant, and the frustum arithmetic overflows."""
ASPECT_RANGE = (1e-3, 1e3)
"""Pixel aspect ratios a camera file may give (real ones are within a few percent of 1)."""
MAX_PIXEL_VALUE = 1e7
"""Largest ``|principal_point|``, ``|skew|`` or distortion coefficient a camera file may give."""
MAX_IMAGE_SIDE = 65535
"""Largest ``image_size`` side (PNG and most decoders stop well below; the frames' own check is in pixels)."""
METADATA_IDS = ("warp_id", "appearance_id", "camera_id", "time_id")
"""Integer ids of a ``metadata.json`` entry; the time key (``warp_id`` by default) is required, the others are
checked where present."""


@dataclass
class HyperNeRFOptions:
    """Options of :func:`load` (pass them as keywords to :func:`benchmark.loaders.load_scene`)."""

    scale: Union[float, str, None] = None
    """Resolution multiplier relative to 1x (0.5 = ``rgb/2x``) or ``"2x"``-style folder name;
    ``None``: ``rgb/2x`` when it exists (the release's choice), else ``rgb/1x``, else the finest
    folder present, else 1x cameras without images."""
    split_rule: Optional[str] = None
    """One of :data:`SPLIT_RULES`; ``None`` = ``"auto"``."""
    train_every: int = 4
    """The release trains on every ``train_every``-th frame when ``val_ids`` is empty."""
    test_offset: int = 2
    """... and tests on the frame ``test_offset`` after each training frame."""
    normalize: bool = True
    """Apply ``scene.json``: world = (position - center) * scale (the 4D-GS convention)."""
    time_key: str = "warp_id"
    """``metadata.json`` field giving the frame's time step (some forks use ``time_id``)."""
    ignore_skew: bool = False
    """Drop a non-zero camera skew instead of raising (pixel error up to ``|skew * y_normalised|``)."""
    check_images: bool = True
    """When the image folder exists, check at load time that every frame's file is there."""


def detect(root: Path) -> bool:
    return (root / "dataset.json").is_file() and (root / "scene.json").is_file()


@dataclass
class NerfiesCamera:
    """One ``camera/<id>.json`` as read (1x resolution, file world coordinates)."""

    orientation: np.ndarray
    """(3, 3) world-to-camera rotation."""
    position: np.ndarray
    """(3,) camera centre."""
    focal_length: float
    principal_point: np.ndarray
    """(2,) ``[x, y]`` pixels."""
    skew: float
    pixel_aspect_ratio: float
    radial: np.ndarray
    """(3,) ``k1, k2, k3``."""
    tangential: np.ndarray
    """(2,) ``p1, p2``."""
    width: int
    height: int


def read_camera(path: Path) -> NerfiesCamera:
    """Parse and validate a Nerfies camera JSON."""
    data = read_json(path)
    if not isinstance(data, dict):
        raise InputError(path, None, "expected a JSON object")
    orientation = C.as_array(C.get_key(data, "orientation", path), (3, 3), path, "orientation")
    C.check_rotation(orientation, path, "orientation")
    position = C.as_array(C.get_key(data, "position", path), (3,), path, "position")
    # every intrinsic bounded where it is read: a value beyond any camera would otherwise overflow later, in
    # arithmetic that no longer knows which file it came from
    focal = check_finite(C.get_key(data, "focal_length", path), path, "focal_length", *FOCAL_RANGE)
    pp = C.as_array(C.get_key(data, "principal_point", path), (2,), path, "principal_point", limit=MAX_PIXEL_VALUE)
    width, height = _image_size(C.get_key(data, "image_size", path), path)
    skew = check_finite(data.get("skew", 0.0), path, "skew", -MAX_PIXEL_VALUE, MAX_PIXEL_VALUE)
    aspect = check_finite(data.get("pixel_aspect_ratio", 1.0), path, "pixel_aspect_ratio", *ASPECT_RANGE)
    radial = C.as_array(data.get("radial_distortion", [0.0, 0.0, 0.0]), (-1,), path, "radial_distortion",
                        limit=MAX_PIXEL_VALUE)
    if radial.size > 3:
        raise InputError(path, "radial_distortion", f"expected at most 3 values [k1, k2, k3], got {radial.size}")
    tan_key = "tangential_distortion" if "tangential_distortion" in data else "tangential"
    tangential = C.as_array(data.get(tan_key, [0.0, 0.0]), (2,), path, tan_key, limit=MAX_PIXEL_VALUE)
    return NerfiesCamera(orientation, position, focal, pp, skew, aspect,
                         np.pad(radial, (0, 3 - radial.size)), tangential, width, height)


def _image_size(value, path: Path) -> tuple[int, int]:
    """``image_size`` ``[width, height]``: two integers in 1..:data:`MAX_IMAGE_SIDE` (``640.0`` is 640)."""
    if not isinstance(value, list) or len(value) != 2:
        raise InputError(path, "image_size", f"expected [width, height], got {value!r:.80}")
    sides = []
    for side in value:
        if isinstance(side, float) and side.is_integer() and abs(side) <= MAX_IMAGE_SIDE:
            side = int(side)  # some exporters write sizes as floats
        if isinstance(side, bool) or not isinstance(side, int) or not 1 <= side <= MAX_IMAGE_SIDE:
            raise InputError(path, "image_size", f"expected two integers in 1..{MAX_IMAGE_SIDE} [width, height], "
                                                 f"got {value!r:.80}")
        sides.append(side)
    return sides[0], sides[1]


def to_opencv(cam: NerfiesCamera, center: np.ndarray, world_scale: float, *, path: Path,
              ignore_skew: bool = False) -> Camera:
    """The 1x :class:`Camera` of a Nerfies camera; world = (position - center) * world_scale."""
    if cam.skew != 0.0 and not ignore_skew:
        raise InputError(path, "skew", f"non-zero skew {cam.skew} is not supported by the pinhole model "
                                       "(pass ignore_skew=True to drop it)")
    w2c = np.eye(4)
    w2c[:3, :3] = cam.orientation
    with np.errstate(over="ignore", invalid="ignore"):  # checked below, as one error naming the field
        w2c[:3, 3] = -cam.orientation @ ((cam.position - center) * world_scale)
    if not np.isfinite(w2c).all():
        raise InputError(path, "position", f"camera position {cam.position.tolist()} is not finite once centred "
                                           f"and scaled (scene centre {np.asarray(center).tolist()}, scale {world_scale})")
    k1, k2, k3 = cam.radial
    p1, p2 = cam.tangential
    return Camera(cam.width, cam.height, cam.focal_length, cam.focal_length * cam.pixel_aspect_ratio,
                  float(cam.principal_point[0]), float(cam.principal_point[1]), w2c,
                  np.array([k1, k2, p1, p2, k3]))


def _image_folders(root: Path) -> dict[int, Path]:
    """Downsampling factor -> ``rgb/<k>x`` folder, for the folders present."""
    rgb = root / "rgb"
    found = {}
    if rgb.is_dir():
        for sub in rgb.iterdir():
            m = re.fullmatch(r"(\d+)x", sub.name)
            if m and sub.is_dir() and int(m.group(1)) > 0:
                found[int(m.group(1))] = sub
    return found


def _resolve_resolution(root: Path, scale) -> tuple[float, Optional[Path], bool]:
    """(resolution multiplier, image folder or None, whether the folder is at exactly that multiplier)."""
    folders = _image_folders(root)
    if scale is None:
        for k in (2, 1):
            if k in folders:
                return 1.0 / k, folders[k], True
        if folders:
            k = min(folders)
            return 1.0 / k, folders[k], True
        return 1.0, None, False
    if isinstance(scale, str):
        m = re.fullmatch(r"\s*(\d+)\s*x\s*", scale)
        if not m or int(m.group(1)) < 1:
            raise InputError(None, "scale", f"expected a multiplier like 0.5 or a folder name like '2x', got {scale!r}")
        multiplier = 1.0 / int(m.group(1))
    else:
        multiplier = C.check_scale(scale)
    need = 1.0 / multiplier
    for k, folder in folders.items():
        if abs(k - need) < 1e-9:
            return multiplier, folder, True
    finer = [k for k in folders if k < need]
    if finer:
        return multiplier, folders[max(finer)], False
    if folders:
        raise InputError(root / "rgb", "scale", f"no image folder fine enough for scale {multiplier} "
                                               f"(have {', '.join(f'{k}x' for k in sorted(folders))})")
    return multiplier, None, False


def _frame_times(root: Path, ids: list[str], time_key: str) -> tuple[list[int], list[float], list[str], str]:
    """(time_index, time, camera_id) per id, and a note saying where times came from."""
    meta_path = root / "metadata.json"
    if not meta_path.is_file():
        warnings.warn(f"{meta_path} is absent: frame times follow the order of dataset.json ids",
                      stacklevel=4)  # the caller of load_scene
        n = len(ids)
        return list(range(n)), [i / (n - 1) if n > 1 else 0.0 for i in range(n)], ["0"] * n, "dataset.json id order"
    meta = read_json(meta_path)
    if not isinstance(meta, dict):
        raise InputError(meta_path, None, "expected a JSON object {id: {...}}")
    steps, cams = [], []
    for fid in ids:
        entry = C.get_key(meta, fid, meta_path)
        C.get_key(entry, time_key, meta_path, fid)  # the time key is required, the other ids optional
        found = {key: check_int(entry[key], meta_path, f"{fid}.{key}", 0, MAX_COUNT)
                 for key in dict.fromkeys((time_key, *METADATA_IDS)) if key in entry}
        steps.append(found[time_key])
        cams.append(str(found.get("camera_id", 0)))
    top = max(steps)
    return steps, [s / top if top > 0 else 0.0 for s in steps], cams, f"metadata.json {time_key}"


def _assign_splits(ids: list[str], train_ids: list[str], val_ids: list[str], rule: str,
                   every: int, offset: int, path: Path) -> list[str]:
    n = len(ids)
    if rule == "auto":
        rule = "dataset" if val_ids else "every4"
    if rule == "dataset":
        if not val_ids:
            raise InputError(path, "val_ids", "is empty: split_rule='dataset' needs it (use 'every4')")
        train, test = set(train_ids), set(val_ids)
        both = sorted(train & test)
        if both:
            raise InputError(path, "val_ids", f"ids both in train_ids and val_ids: {both[:5]}")
        return ["train" if i in train else "test" if i in test else "val" for i in ids]
    if every < 1 or not 0 <= offset < every:
        raise InputError(None, "train_every/test_offset", f"need train_every >= 1 and 0 <= test_offset < "
                                                          f"train_every, got {every}, {offset}")
    splits = ["val"] * n
    train_idx = list(range(0, n, every))
    test_idx = [i + offset for i in train_idx if offset and i + offset < n]
    if rule == "every4-release" and test_idx:
        test_idx = test_idx[:-1]
    for i in train_idx:
        splits[i] = "train"
    for i in test_idx:
        splits[i] = "test"
    return splits


def _load_points(path: Path, center: np.ndarray, world_scale: float) -> np.ndarray:
    """The (N, 3) initial point cloud of ``points.npy``, centred and scaled like the cameras."""
    check_npy(path, max_bytes=MAX_POINTS_BYTES, kinds="iuf")  # before np.load allocates what the header claims
    try:
        pts = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise InputError(path, "points", f"cannot read a numpy array ({err})") from None
    pts = C.as_array(pts, (-1, 3), path, "points")
    if len(pts) == 0:
        raise InputError(path, "points", "is empty")
    return (pts - center) * world_scale


@dataclass(frozen=True)
class _SceneFrame:
    """What ``scene.json`` says about the world frame, as the loader uses it."""

    near: float
    far: float
    world_scale: float
    """Scale applied to camera positions and points (1 when not normalising)."""
    center: np.ndarray
    """Subtracted from camera positions and points before scaling (zeros when not normalising)."""
    file_scale: float
    """The file's own ``scale``, recorded in the scene's metadata either way."""
    file_center: np.ndarray
    """The file's own ``center``, recorded in the scene's metadata either way."""


def _read_scene_frame(root: Path, normalize: bool) -> _SceneFrame:
    scene_path = root / "scene.json"
    scene_json = read_json(scene_path)
    world_scale = C.as_float(C.get_key(scene_json, "scale", scene_path), scene_path, "scale", positive=True)
    center = C.as_array(C.get_key(scene_json, "center", scene_path), (3,), scene_path, "center")
    near = C.as_float(C.get_key(scene_json, "near", scene_path), scene_path, "near", positive=True)
    far = C.as_float(C.get_key(scene_json, "far", scene_path), scene_path, "far", positive=True)
    if far <= near:
        raise InputError(scene_path, "far", f"must exceed near ({far} <= {near})")
    file_scale, file_center = world_scale, center
    if not normalize:  # near/far are stored in normalised units
        near, far, world_scale, center = near / world_scale, far / world_scale, 1.0, np.zeros(3)
    return _SceneFrame(near, far, world_scale, center, file_scale, file_center)


def _read_dataset_ids(ds_path: Path) -> tuple[list[str], list[str], list[str]]:
    """``ids``, ``train_ids`` and ``val_ids`` of ``dataset.json``, checked."""
    dataset = read_json(ds_path)
    ids = C.get_key(dataset, "ids", ds_path)
    if not isinstance(ids, list) or not ids or not all(isinstance(i, str) for i in ids):
        raise InputError(ds_path, "ids", "expected a non-empty list of id strings")
    if len(set(ids)) != len(ids):
        raise InputError(ds_path, "ids", "contains duplicate ids")
    train_ids = dataset.get("train_ids", [])
    val_ids = dataset.get("val_ids", [])
    for key, lst in (("train_ids", train_ids), ("val_ids", val_ids)):
        if not isinstance(lst, list) or not all(isinstance(i, str) for i in lst):
            raise InputError(ds_path, key, "expected a list of id strings")
        unknown = sorted(set(lst) - set(ids))
        if unknown:
            raise InputError(ds_path, key, f"ids not in 'ids': {unknown[:5]}")
        if len(set(lst)) != len(lst):
            repeated = sorted(i for i, n in Counter(lst).items() if n > 1)
            raise InputError(ds_path, key, f"ids given twice: {repeated[:5]}")
    # whatever split rule is used: a frame both trained on and held out would score its own training view
    both = sorted(set(train_ids) & set(val_ids))
    if both:
        raise InputError(ds_path, "val_ids", f"ids both in train_ids and val_ids: {both[:5]}")
    for key in ("count", "num_exemplars"):  # optional (a bare export lacks them); never used, but never absurd
        if key in dataset:
            check_int(dataset[key], ds_path, key, 0, MAX_COUNT)
    return ids, train_ids, val_ids


def _output_sizes(ids: list[str], raw: list[NerfiesCamera], multiplier: float, folder: Optional[Path],
                  exact: bool) -> dict[tuple[int, int], tuple[int, int]]:
    """Output size per distinct 1x size: the actual files' size when the folder matches exactly
    (intrinsics follow the real ratio), else the rounded product."""
    out_size: dict[tuple[int, int], tuple[int, int]] = {}
    for fid, cam in zip(ids, raw):
        key = (cam.width, cam.height)
        if key not in out_size:
            if folder is not None and exact:
                out_size[key] = C.image_size(folder / f"{fid}.png")
            else:
                out_size[key] = C.target_size(cam.width, cam.height, multiplier)
    return out_size


def _image_loader(root: Path, fid: str, multiplier: float, folder: Optional[Path], exact: bool,
                  size: tuple[int, int], check_images: bool):
    """``(image path, loader)`` of frame ``fid``; without an image folder the loader raises."""
    if folder is None:
        image_path = root / "rgb" / f"{round(1 / multiplier)}x" / f"{fid}.png"
        return image_path, partial(C.missing_image, image_path,
                                   f"no images in this scene folder (no {root / 'rgb'}/<k>x/): cameras only")
    image_path = folder / f"{fid}.png"
    if check_images and not image_path.is_file():
        raise InputError(image_path, "image", f"image file of id {fid!r} not found")
    # an exact folder is read as is, so a wrongly sized file fails Frame.image()
    w, h = size
    return image_path, partial(C.load_rgb, image_path) if exact else partial(C.load_rgb, image_path, w, h)


def load(path: str | Path, options: Optional[HyperNeRFOptions] = None) -> Scene:
    """Load a HyperNeRF/Nerfies scene folder (conventions in the module docstring)."""
    opts = options or HyperNeRFOptions()
    root = Path(path)
    rule = opts.split_rule or "auto"
    if rule not in SPLIT_RULES:
        raise InputError(None, "split_rule", f"unknown rule {rule!r} for {LAYOUT} (valid: {', '.join(SPLIT_RULES)})")
    world = _read_scene_frame(root, opts.normalize)
    ds_path = root / "dataset.json"
    ids, train_ids, val_ids = _read_dataset_ids(ds_path)
    splits = _assign_splits(ids, train_ids, val_ids, rule, opts.train_every, opts.test_offset, ds_path)
    if "train" not in splits:
        raise InputError(ds_path, "train_ids", "the training split is empty")
    steps, times, cam_ids, time_source = _frame_times(root, ids, opts.time_key)

    multiplier, folder, exact = _resolve_resolution(root, opts.scale)
    raw = [read_camera(root / "camera" / f"{fid}.json") for fid in ids]
    out_size = _output_sizes(ids, raw, multiplier, folder, exact)
    frames = []
    for fid, cam, split, step, t, cam_id in zip(ids, raw, splits, steps, times, cam_ids):
        size = out_size[(cam.width, cam.height)]
        camera = to_opencv(cam, world.center, world.world_scale, path=root / "camera" / f"{fid}.json",
                           ignore_skew=opts.ignore_skew).resized(*size)
        image_path, loader = _image_loader(root, fid, multiplier, folder, exact, size, opts.check_images)
        frames.append(Frame(name=fid, camera=camera, time=t, time_index=step, split=split,
                            camera_id=cam_id, image_path=image_path, load_image=loader))

    points = None
    if (root / "points.npy").is_file():
        points = _load_points(root / "points.npy", world.center, world.world_scale)
        bounds = C.box(points)
    else:
        # the training frames' views only: where held-out cameras stand is not for a method to know
        train = [f for f in frames if f.split == "train"]
        bounds = C.frustum_bounds([f.camera for f in train], [world.near] * len(train), [world.far] * len(train))
    return Scene(
        name=root.resolve().name, dataset=LAYOUT, frames=frames, bounds=bounds, root=root,
        points=points, near_far=(world.near, world.far),
        metadata={
            "layout": LAYOUT,
            "image_folder": None if folder is None else str(folder.relative_to(root)),
            "resolution_scale": multiplier,
            "split_rule": rule if rule != "auto" else ("dataset" if val_ids else "every4"),
            "time_source": time_source,
            "normalized": opts.normalize,
            "scene_center": world.file_center.tolist(),
            "scene_scale": world.file_scale,
            "num_time_steps": max(steps) + 1,
            "eval_splits": eval_splits_of(frames, held_out_cameras=False),
        },
    )
