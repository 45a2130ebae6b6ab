"""The evaluation splits of a generated scene, and how much multi-view signal its training frames carry.

Every generated scene records, per evaluation split (:data:`benchmark.core.scene.EVAL_SPLITS`), the frames
it scores and two numbers (``bench4d_meta.json`` ``splits``; the annotations' ``info.splits`` keep the frame
names alone):

* the **effective multi-view factor** of the training frames, after DyCheck (Gao et al., "Monocular Dynamic
  View Synthesis: A Reality Check", NeurIPS 2022): how fast the camera moves around the scene compared with
  how fast the scene moves. A capture whose camera sweeps round the scene between frames while the scene
  barely moves is close to a multi-view capture of a static scene; a large factor makes a monocular video
  easier than it looks. Computed here exactly from the generator:

  - camera speed: for consecutive training frames ``k, k + 1`` (time order), the angle between their camera
    centres seen from the scene's focus point, in radians, times the mean distance of the two centres from
    the focus (the arc the camera sweeps), divided by the time steps between them; averaged over the pairs;
  - scene speed: every object pixel of training frame ``k`` is lifted to 3D from the truth depth and moved
    with its part's rigid motion (the poses of the part and the nodes above it) to the time of frame
    ``k + 1``; the mean distance moved by the pixels that move, per time step, averaged over the pairs in
    which something moves. Shape and colour changes (a liquid rising, chocolate melting) are not motion here:
    where no part moves rigidly (espresso: its coffee rises and its stream appears in place) the scene speed
    and the factor are null;
  - ``multi_view_factor`` = camera speed / scene speed (DyCheck's full EMF, in time steps rather than
    seconds: the ratio has no unit). ``camera_deg_per_step`` is the angular speed alone (DyCheck's angular
    EMF, per time step instead of per second). A rig sees a time step from several cameras at once: its
    factor is unbounded (null, ``multi_camera: true``), as DyCheck counts multi-camera captures.

  Both splits train on the same frames, so the factor is the same for both;
* ``eval_angle_deg``: for each scored frame, the angle (seen from the focus) to the nearest training camera;
  its minimum and mean. This is what makes ``novel-view`` harder than ``paper``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from benchmark.core.scene import Camera, eval_splits_of
from benchmark.core.errors import InputError
from benchmark.core.strict import load_npz
from benchmark.core.truth import LEVELS, LEVELS_DIR
from .model import Catalogue, FrameContext, SceneDef, resolve


def _directions(cameras: Sequence[Camera], focus) -> np.ndarray:
    """(N, 3) unit vectors from the focus to each camera centre."""
    v = np.stack([c.center for c in cameras]) - np.asarray(focus, dtype=np.float64)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def angles_deg(a: Sequence[Camera], b: Sequence[Camera], focus) -> np.ndarray:
    """(len(a), len(b)) angles in degrees between camera centres, seen from ``focus``."""
    cos = np.clip(_directions(a, focus) @ _directions(b, focus).T, -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def nearest_angles_deg(cameras: Sequence[Camera], training: Sequence[Camera], focus) -> np.ndarray:
    """(len(cameras),) angle in degrees from each camera to the nearest of ``training``, seen from ``focus``."""
    return angles_deg(cameras, training, focus).min(axis=1)


def _leaf_poses(scene: SceneDef, catalogue: Catalogue, time_index: int) -> dict[int, np.ndarray]:
    """Subpart id -> 4x4 world pose of its part chain (whole, part, subpart poses composed) at a time."""
    ctx = FrameContext(time_index, scene.num_frames)
    out = {}
    for leaf in catalogue.leaves:
        pose = np.eye(4)
        for node in leaf.chain:
            pose = pose @ np.asarray(resolve(node.pose, ctx), dtype=np.float64)
        out[leaf.ids[0]] = pose
    return out


def _object_points(truth_dir: Path, name: str, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """((M, 3) world points, (M,) subpart ids) of the object pixels of frame ``name`` (its truth maps)."""
    path = Path(truth_dir) / LEVELS_DIR / f"{name}.npz"
    arrays = load_npz(path)
    missing = [key for key in (LEVELS[0], "depth") if key not in arrays]
    if missing:
        raise InputError(path, missing[0], "missing array; regenerate the scene")
    ids, depth = arrays[LEVELS[0]], arrays["depth"]
    i, j = np.nonzero((ids > 0) & np.isfinite(depth))
    z = depth[i, j].astype(np.float64)
    cam = np.stack([(j + 0.5 - camera.cx) / camera.fx * z, (i + 0.5 - camera.cy) / camera.fy * z, z], axis=1)
    return (cam - camera.t) @ camera.R, ids[i, j].astype(np.int64)


def multi_view_factor(train, scene: SceneDef, catalogue: Catalogue, truth_dir: Path) -> dict[str, Any]:
    """The training frames' effective multi-view factor (module docstring). ``train``: the training frames'
    records (``name``, ``time_index``, ``camera``); ``truth_dir``: the scene's rendered truth."""
    train = sorted(train, key=lambda r: (r.time_index, r.name))
    times = [r.time_index for r in train]
    if len(set(times)) != len(times):
        return {"multi_view_factor": None, "multi_camera": True, "camera_deg_per_step": None,
                "camera_speed_per_step": None, "scene_speed_per_step": None, "training_frames": len(train)}
    focus = np.asarray(scene.focus_center, dtype=np.float64)
    arcs, turns, speeds = [], [], []
    poses = {}
    for a, b in zip(train, train[1:]):
        steps = b.time_index - a.time_index
        angle = float(np.radians(angles_deg([a.camera], [b.camera], focus)[0, 0]))
        radius = 0.5 * (np.linalg.norm(a.camera.center - focus) + np.linalg.norm(b.camera.center - focus))
        arcs.append(angle * radius / steps)
        turns.append(np.degrees(angle) / steps)
        for t in (a.time_index, b.time_index):
            if t not in poses:
                poses[t] = _leaf_poses(scene, catalogue, t)
        points, ids = _object_points(truth_dir, a.name, a.camera)
        moved = np.zeros(len(points))
        for leaf_id in np.unique(ids):
            change = poses[b.time_index][leaf_id] @ np.linalg.inv(poses[a.time_index][leaf_id])
            sel = ids == leaf_id
            moved[sel] = np.linalg.norm(points[sel] @ change[:3, :3].T + change[:3, 3] - points[sel], axis=1)
        moving = moved > 1e-9
        if moving.any():
            speeds.append(float(moved[moving].mean()) / steps)
    camera_speed = float(np.mean(arcs)) if arcs else None
    scene_speed = float(np.mean(speeds)) if speeds else None
    factor = camera_speed / scene_speed if camera_speed is not None and scene_speed else None
    return {"multi_view_factor": factor, "multi_camera": False,
            "camera_deg_per_step": float(np.mean(turns)) if turns else None,
            "camera_speed_per_step": camera_speed, "scene_speed_per_step": scene_speed,
            "training_frames": len(train)}


def split_records(records, scene: SceneDef, catalogue: Catalogue, truth_dir: Path, *, layout: str,
                  novel_view: Optional[Any] = None) -> dict[str, dict[str, Any]]:
    """Per evaluation split: its scored frames, what they are, the training frames' multi-view factor and the
    scored cameras' angles from the training cameras (module docstring). ``records``: every planned frame
    (:class:`~benchmark.synthetic.layouts.FrameRecord`); ``novel_view``: the novel-view path, if rendered."""
    named = eval_splits_of(records, held_out_cameras=layout != "hypernerf")
    by_name = {r.name: r for r in records}
    train = [r for r in records if r.split == "train"]
    factor = multi_view_factor(train, scene, catalogue, truth_dir)
    focus = scene.focus_center
    out = {}
    for split, names in named.items():
        angles = nearest_angles_deg([by_name[n].camera for n in names], [r.camera for r in train], focus) \
            if names and train else np.zeros(0)
        entry: dict[str, Any] = {
            "frames": list(names),
            "scored": _scored_words(layout, split),
            "training": "frames i % 4 == 0 of the video" if layout == "hypernerf" else
                        "every camera but cam00" if layout == "neu3d" else "frames not in test or val",
            **factor,
            "eval_angle_deg": {"min": float(angles.min()) if angles.size else None,
                               "mean": float(angles.mean()) if angles.size else None},
            "focus": [float(v) for v in focus],
        }
        if split == "novel-view" and layout == "hypernerf" and novel_view is not None:
            entry["camera_offset_deg"] = {"azimuth": novel_view.azimuth_deg, "elevation": novel_view.elevation_deg,
                                          "min_angle": novel_view.min_angle_deg}
        out[split] = entry
    return out


def _scored_words(layout: str, split: str) -> str:
    if layout == "hypernerf":
        return ("frames i % 4 == 2 from the training camera path" if split == "paper" else
                "the times of frames i % 4 == 2 from the novel-view camera path, off the training path")
    if layout == "neu3d":
        return "the held-out camera cam00 at every time"
    return "the test frames (each from its own camera on the hemisphere)"
