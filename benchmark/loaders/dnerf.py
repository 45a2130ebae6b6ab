"""D-NeRF synthetic scenes (Blender renders of one object, RGBA, a time per frame).

Layout::

    transforms_train.json   {"camera_angle_x", "frames": [{"file_path", "time", "transform_matrix"}]}
    transforms_val.json     (optional)
    transforms_test.json    (optional)
    train/r_000.png ...     RGBA

Conventions applied:

* ``transform_matrix`` is a 4x4 camera-to-world in the OpenGL/Blender convention (x right, y up,
  the camera looks along -z); it is converted to OpenCV with :meth:`Camera.from_opengl_c2w`.
* ``fx = fy = 0.5 W / tan(0.5 camera_angle_x)``, ``cx = W/2``, ``cy = H/2`` (pixel corners at 0),
  with ``W, H`` read from the image header. ``scale`` is a resolution multiplier (0.5: 400 -> 200 px);
  the RGBA image is area-resized first, then composited, as D-NeRF does.
* ``file_path`` usually has no extension: ``.png`` is appended when the path as given is no file.
* Images are composited on :attr:`DNeRFOptions.background` (white, D-NeRF's default); the alpha
  channel above :attr:`DNeRFOptions.alpha_threshold` is the whole-object mask (``Frame.load_alpha``).
* Time: ``time`` from the file (must lie in [0, 1]). ``time_index`` is the **rank of the frame's time
  among all distinct times of every loaded split** (times rounded to ``time_decimals`` decimals), so
  frames at equal times share an index and indices follow time order.
* Frames are named ``<split>_<file stem>`` (``train_r_000``) to stay unique across splits; the
  ``val`` file becomes the ``"val"`` split.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Optional

import numpy as np

from benchmark.core.atomic import read_json
from benchmark.core.errors import InputError
from benchmark.core.imageio import read_image
from benchmark.core.scene import Camera, Frame, Scene, eval_splits_of
from . import _common as C

LAYOUT = "dnerf"
SPLITS = ("train", "val", "test")
SPLIT_RULES = ("dataset",)

@dataclass
class DNeRFOptions:
    """Options of :func:`load` (pass them as keywords to :func:`benchmark.loaders.load_scene`)."""

    scale: Optional[float] = None
    """Resolution multiplier relative to the PNGs (0.5: 400 -> 200 px); ``None`` = as stored."""
    split_rule: Optional[str] = None
    """Only ``"dataset"`` (the default): the three transforms files are the splits."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """RGB in [0, 1] the RGBA renders are composited on (D-NeRF's white background)."""
    alpha_threshold: float = 0.5
    """Alpha above this is foreground in the whole-object mask."""
    time_decimals: int = 9
    """Times equal after rounding to this many decimals share a ``time_index``."""
    near: float = 2.0
    """Depth range of D-NeRF's Blender renders (its ray sampling near bound); a ``near_far`` pair
    in ``bench4d_meta.json`` (written by the synthetic generator) takes precedence."""
    far: float = 6.0
    """... and far bound; used for ``Scene.near_far`` and as a fallback for the bounds."""


def _near_far(root: Path, opts: "DNeRFOptions") -> tuple[float, float]:
    """Depth range: ``bench4d_meta.json``'s ``near_far`` when present, else the options."""
    meta_path = root / "bench4d_meta.json"
    if not meta_path.is_file():
        return float(opts.near), float(opts.far)
    value = read_json(meta_path).get("near_far")
    if value is None:
        return float(opts.near), float(opts.far)
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in value)
            or not 0 < value[0] < value[1]):
        raise InputError(meta_path, "near_far", f"expected [near, far] with 0 < near < far, got {value!r}")
    return float(value[0]), float(value[1])


def detect(root: Path) -> bool:
    return (root / "transforms_train.json").is_file()


def _resolve_image(root: Path, file_path: str, file: Path, field: str) -> Path:
    given = root / file_path
    if given.is_file():
        return given
    with_png = given.parent / (given.name + ".png")
    if with_png.is_file():
        return with_png
    from benchmark.core.strict import file_problem

    for candidate in (given, with_png):  # there, but not a regular file: say what it is
        problem = file_problem(candidate)
        if problem not in (None, "missing"):
            raise InputError(candidate, field, f"is {problem}, expected an image file")
    raise InputError(file, field, f"image not found: {given}" + ("" if given.suffix else " (nor .png)"))


def load_composited(path: Path, width: Optional[int], height: Optional[int],
                    background: tuple[float, float, float]) -> np.ndarray:
    """(H, W, 3) float32: the RGBA file resized (unless ``width`` is None), then composited on ``background``."""
    rgba = C.resize(read_image(path, keep_alpha=True), width, height)
    alpha = rgba[:, :, 3:4]
    return rgba[:, :, :3] * alpha + np.asarray(background, dtype=np.float32) * (1.0 - alpha)


def load_alpha_mask(path: Path, width: Optional[int], height: Optional[int], threshold: float) -> np.ndarray:
    """(H, W) bool: resized alpha above ``threshold``."""
    return C.resize(read_image(path, keep_alpha=True)[:, :, 3], width, height) > threshold


def _read_split(root: Path, split: str) -> Optional[tuple[Path, float, list[dict]]]:
    """(file, camera_angle_x, validated frame records) of one transforms file, or None if absent."""
    file = root / f"transforms_{split}.json"
    if not file.is_file():
        if split == "train":
            raise InputError(file, None, "file not found (a D-NeRF scene needs transforms_train.json)")
        return None
    data = read_json(file)
    angle = C.as_float(C.get_key(data, "camera_angle_x", file), file, "camera_angle_x", positive=True)
    if angle >= math.pi:
        raise InputError(file, "camera_angle_x", f"must be below pi radians, got {angle}")
    frames = C.get_key(data, "frames", file)
    if not isinstance(frames, list) or not frames:
        raise InputError(file, "frames", "expected a non-empty list of frames (empty split)")
    records = []
    for i, fr in enumerate(frames):
        parent = f"frames[{i}]"
        fp = C.get_key(fr, "file_path", file, parent)
        if not isinstance(fp, str) or not fp:
            raise InputError(file, f"{parent}.file_path", f"expected a path string, got {fp!r:.80}")
        t = C.as_float(C.get_key(fr, "time", file, parent), file, f"{parent}.time")
        if not 0.0 <= t <= 1.0:
            raise InputError(file, f"{parent}.time", f"must lie in [0, 1], got {t}")
        c2w = C.as_array(C.get_key(fr, "transform_matrix", file, parent), (4, 4), file, f"{parent}.transform_matrix")
        if np.abs(c2w[3] - [0, 0, 0, 1]).max() > 1e-6:
            raise InputError(file, f"{parent}.transform_matrix", f"last row must be [0, 0, 0, 1], got {c2w[3].tolist()}")
        C.check_rotation(c2w[:3, :3], file, f"{parent}.transform_matrix")
        image = _resolve_image(root, fp, file, f"{parent}.file_path")
        records.append({"image": image, "time": t, "c2w": c2w})
    return file, angle, records


def load(path: str | Path, options: Optional[DNeRFOptions] = None) -> Scene:
    """Load a D-NeRF scene folder (conventions in the module docstring)."""
    opts = options or DNeRFOptions()
    root = Path(path)
    if (opts.split_rule or "dataset") not in SPLIT_RULES:
        raise InputError(None, "split_rule", f"unknown rule {opts.split_rule!r} for {LAYOUT} "
                                             f"(valid: {', '.join(SPLIT_RULES)})")
    background = C.as_array(opts.background, (3,), None, "background")
    if np.any(background < 0) or np.any(background > 1):
        raise InputError(None, "background", f"RGB must lie in [0, 1], got {background.tolist()}")
    bg = tuple(float(v) for v in background)
    splits = {s: r for s in SPLITS if (r := _read_split(root, s)) is not None}

    all_times = sorted({round(rec["time"], opts.time_decimals) for _, _, recs in splits.values() for rec in recs})
    rank = {t: i for i, t in enumerate(all_times)}
    frames = []
    for split, (file, angle, recs) in splits.items():
        width, height = C.image_size(recs[0]["image"])
        focal = 0.5 * width / math.tan(0.5 * angle)
        out_w, out_h = C.target_size(width, height, opts.scale)
        # without scale the files are read as they are, so a wrongly sized one fails Frame.image()
        load_w, load_h = (None, None) if opts.scale is None else (out_w, out_h)
        for rec in recs:
            camera = Camera.from_opengl_c2w(rec["c2w"], width, height, focal, focal,
                                            width / 2.0, height / 2.0).resized(out_w, out_h)
            image = rec["image"]
            frames.append(Frame(
                name=f"{split}_{image.stem}", camera=camera, time=rec["time"],
                time_index=rank[round(rec["time"], opts.time_decimals)], split=split,
                camera_id="0", image_path=image,
                load_image=partial(load_composited, image, load_w, load_h, bg),
                load_alpha=partial(load_alpha_mask, image, load_w, load_h, opts.alpha_threshold)))
    near, far = _near_far(root, opts)
    cameras = [f.camera for f in frames]
    bounds = C.lookat_bounds(cameras)
    if bounds is None:
        bounds = C.frustum_bounds(cameras, [near] * len(cameras), [far] * len(cameras))
    return Scene(name=root.resolve().name, dataset=LAYOUT, frames=frames, bounds=bounds, root=root,
                 background=np.asarray(bg), near_far=(near, far),
                 metadata={"layout": LAYOUT, "splits": {s: str(f) for s, (f, _, _) in splits.items()},
                           "num_distinct_times": len(all_times),
                           # one camera per frame: every test frame is already a novel view
                           "eval_splits": eval_splits_of(frames, held_out_cameras=True)})


def object_annotations(scene: Scene, query_text: str, split: str = "test"):
    """One time-agnostic whole-object query ``query_text`` (what the object is: the scene's folder name
    says nothing a query may rely on) with the alpha masks as ground truth on every frame of ``split``
    (the real-data check for methods). Reads every frame's alpha channel."""
    from benchmark.core.annotation import AnnotatedFrame, AnnotationSet, Query

    if not query_text or not str(query_text).strip():
        raise InputError(scene.root, "object query", "name the object the alpha masks show (e.g. 'person')")
    frames = scene.split(split)  # type: ignore[arg-type]
    if not frames:
        raise InputError(scene.root, "split", f"scene {scene.name!r} has no {split!r} frames")
    query = Query(id=1, text=str(query_text).strip(), kind="agnostic", level="whole")
    aset = AnnotationSet(scene=scene.name, queries=[query], num_time_steps=scene.num_time_steps,
                         info={"source": "D-NeRF alpha channel (whole-object mask)", "split": split})
    for image_id, frame in enumerate(frames, start=1):
        alpha = frame.alpha()
        if alpha is None:
            raise InputError(frame.image_path, "alpha", f"frame {frame.name!r} has no alpha mask")
        aset.frames.append(AnnotatedFrame(id=image_id, name=frame.name, time_index=frame.time_index,
                                          width=frame.camera.width, height=frame.camera.height,
                                          camera_id=frame.camera_id))
        aset.set_mask(query.id, image_id, alpha, made_by="scripted")
    return aset
