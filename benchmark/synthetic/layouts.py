"""Writers for the three on-disk layouts the loaders read (HyperNeRF, Neu3D, D-NeRF).

Each layout plans its frames (:class:`FrameRecord`: the name the loader will give the frame, split,
time, camera) and writes images and metadata files. The conventions are those of
:mod:`benchmark.loaders` (see each loader's docstring); the generator's own tests read every layout
back through :func:`benchmark.loaders.load_scene`.

Frame names, splits and times per layout
----------------------------------------
* ``hypernerf``: one moving camera; ids ``000000 ...``; ``train_ids`` are frames ``i % 4 == 0`` and
  ``val_ids`` (the test split) frames ``i % 4 == 2``, as the paper and the release's loader split them
  (the loader calls the rest ``val``: neither trained on nor scored); ``time = i / (N - 1)``
  (``warp_id / max(warp_id)``). Each scored time is rendered a second time from the novel-view path
  (:class:`NovelViewPath`): ids ``novel_<i>``, ``camera_id`` :data:`NOVEL_CAMERA_ID`, in ``val_ids`` too.
  Only ``rgb/1x`` is written (the loader falls back to 1x when ``rgb/2x`` is absent, so the images
  it returns by default have the size the truth and annotations are drawn at; ``scale=0.5`` gives
  area-downsampled 2x images).
* ``neu3d``: a fixed rig, ``camXX/images/NNNN.png``; frames ``camXX_NNNN``; ``cam00`` is the test
  view; ``time = k / N`` with ``N`` in ``bench4d_meta.json``.
* ``dnerf``: one random hemisphere camera per frame, RGBA on a transparent background (objects
  only); files ``<split>/r_<i>`` numbered by the *video* frame so stems are unique, frames
  ``<split>_r_<i>``; test = ``i % 4 == 2``, val = ``i % 12 == 0``; ``time = i / (N - 1)``.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import cv2
import numpy as np

from benchmark.core.atomic import write_json
from benchmark.core.imageio import write_image as write_image_file
from benchmark.core.scene import Camera
from . import cameras as cams
from .model import SceneDef
from .render import RenderResult

Layout = Literal["hypernerf", "neu3d", "dnerf"]
LAYOUTS: tuple[Layout, ...] = ("hypernerf", "neu3d", "dnerf")
META_FILE = "bench4d_meta.json"
NEU3D_RIG_CAMERAS = 21
"""Cameras of the real Neu3D / DyNeRF rig (``../shared/docs/protocol.md``: 21 synced cameras); cam00 is
held out, so 20 train. The Neu3D-like presets use the real count: a rig of a few cameras turns the
held-out view into a sparse-view problem that neither 3D-GS nor 4D-GS solves (cook-spinach, 3D-GS test PSNR at 6 / 12 /
18 / 21 cameras: 20.4 / 26.4 / 27.7 / 27.1 dB; 4D-GS at 6 / 21: 21.1 / 29.2 dB)."""


@dataclass(frozen=True)
class SplitRule:
    """How video frames are split (monocular and D-NeRF layouts)."""

    test_every: int = 4
    """Every ``test_every``-th frame is held out ..."""
    test_offset: int = 2
    """... starting at this frame (the release's "train index + 2")."""
    train_offset: Optional[int] = 0
    """Frames ``i % test_every == train_offset`` train (the paper: "one frame every four frames as the training
    set"); the others are neither trained on nor scored (split ``val``). None: every frame that is not held
    out trains."""
    val_every: int = 12
    """D-NeRF only: frames ``i % val_every == 0`` form the (small) validation split."""

    def split(self, i: int, with_val: bool) -> str:
        if i % self.test_every == self.test_offset:
            return "test"
        if with_val and i % self.val_every == 0:
            return "val"
        if self.train_offset is None or i % self.test_every == self.train_offset:
            return "train"
        return "val"


PAPER_SPLIT = SplitRule()
"""The HyperNeRF layout's split: train on ``i % 4 == 0``, score ``i % 4 == 2`` (the paper, and the release's
loader; :mod:`benchmark.loaders.hypernerf`'s ``every4`` rule)."""
DNERF_SPLIT = SplitRule(train_offset=None)
"""The D-NeRF layout's split: test ``i % 4 == 2``, validation ``i % 12 == 0``, every other frame trains."""


@dataclass(frozen=True)
class NovelViewPath:
    """The second camera path of the HyperNeRF layout: every scored time is rendered again from the training
    camera of that time turned about the focus, off the training path (the ``novel-view`` evaluation split).

    The azimuth offset keeps the novel camera inside the azimuths the training path sweeps (55 degrees): it
    sees each scored time from where the training camera stood at another time, the question of monocular
    dynamic view synthesis. The elevation offset takes it off the path: the training path's elevation wobbles
    by +-``elevation_wobble_deg`` (5), so a novel camera is at least 15 - 2 x 5 = 5 degrees above every
    training camera. Measured at demo schedules (split-cookie, 64 px, 60 frames, one seed), the floor and
    4D LangSplat both lose mIoU with the offset: (20, 20) left both near 30, the scale of their noise."""

    azimuth_deg: float = 10.0
    """Added to the training camera's azimuth about the focus, in the direction the camera travels."""
    elevation_deg: float = 15.0
    """Added to its elevation: the novel camera looks down more steeply."""
    min_angle_deg: float = 5.0
    """Every novel-view camera is at least this far from every training camera, as the angle between their
    centres seen from the focus; :func:`plan` checks it."""


NOVEL_VIEW = NovelViewPath()
"""The novel-view path of the presets."""
NOVEL_CAMERA_ID = "100"
"""``camera_id`` of the novel-view frames (HyperNeRF's ``metadata.json`` numbers cameras; the stress suite's
``camera-rig`` family numbers its extra training cameras 1, 2, ...)."""
NOVEL_PREFIX = "novel_"
"""Frame names of the novel-view path: ``novel_<frame number>``."""


@dataclass(frozen=True)
class LayoutSpec:
    """Per-layout camera setup."""

    setup: cams.CameraSetup
    background: bool
    """Whether the static surroundings are rendered (not in D-NeRF: transparent background)."""


LAYOUT_SPECS: dict[str, LayoutSpec] = {
    # Portrait phone video with a slightly off-centre principal point and non-square pixels,
    # like the real HyperNeRF captures (the loader must honour both).
    "hypernerf": LayoutSpec(cams.CameraSetup(cams.Intrinsics(52.0, 4 / 3, (0.012, -0.009), 1.004)), True),
    # Landscape 4:3 rig (Neu3D is 1352x1014); LLFF poses have no principal point: centred. The fit
    # uses the narrow vertical field of view, where table-top content is short: a tighter margin.
    "neu3d": LayoutSpec(cams.CameraSetup(cams.Intrinsics(55.0, 0.75), sweep_deg=80.0, elevation_deg=28.0,
                                         margin=0.85), True),
    # Square renders, D-NeRF's camera_angle_x = 0.6911 rad (39.6 degrees).
    "dnerf": LayoutSpec(cams.CameraSetup(cams.Intrinsics(np.degrees(0.6911112070083618), 1.0)), False),
}


@dataclass
class FrameRecord:
    """One image to render and write."""

    name: str
    """The frame name the loader gives it (``Frame.name``)."""
    split: str
    time_index: int
    time: float
    """Normalised time as the layout's loader computes it."""
    camera_id: str
    camera: Camera
    """Camera at the written (1x) resolution."""
    image_file: str
    """Path of the image relative to the scene folder."""


def plan(layout: Layout, scene: SceneDef, width: int, num_frames: int, num_views: int,
         rng: np.random.Generator, rule: Optional[SplitRule] = None, height: Optional[int] = None,
         novel_view: Optional[NovelViewPath] = NOVEL_VIEW) -> list[FrameRecord]:
    """Cameras, names, splits and times of every image of the layout; ``height`` replaces the layout's image
    aspect (the horizontal field of view stays the layout's). ``rule``: the layout's split (default
    :data:`PAPER_SPLIT` for HyperNeRF, :data:`DNERF_SPLIT` for D-NeRF). ``novel_view``: the HyperNeRF layout's
    second path, one frame per scored time (None: none)."""
    spec = LAYOUT_SPECS[layout]
    if height is not None:
        intrinsics = dataclasses.replace(spec.setup.intrinsics, height_over_width=height / width)
        spec = dataclasses.replace(spec, setup=dataclasses.replace(spec.setup, intrinsics=intrinsics))
    c, r = scene.focus_center, scene.focus_radius
    n = num_frames
    if layout == "hypernerf":
        rule = PAPER_SPLIT if rule is None else rule
        path = cams.monocular_path(spec.setup, c, r, n, width, rng)
        records = [FrameRecord(f"{i:06d}", rule.split(i, False), i, i / max(1, n - 1), "0", path.camera(i),
                               f"rgb/1x/{i:06d}.png") for i in range(n)]
        if novel_view is not None:
            records += [FrameRecord(f"{NOVEL_PREFIX}{i:06d}", "test", i, i / max(1, n - 1), NOVEL_CAMERA_ID,
                                    path.camera(i, novel_view.azimuth_deg, novel_view.elevation_deg),
                                    f"rgb/1x/{NOVEL_PREFIX}{i:06d}.png")
                        for i in range(n) if rule.split(i, False) == "test"]
            _check_novel_views(records, c, novel_view)
        return sorted(records, key=lambda rec: rec.time_index)  # video order; a time's novel view after its frame
    if layout == "neu3d":
        rig = cams.rig(spec.setup, c, r, num_views, width, rng)
        return [FrameRecord(f"cam{v:02d}_{k:04d}", "test" if v == 0 else "train", k, k / n, f"cam{v:02d}",
                            rig[v], f"cam{v:02d}/images/{k:04d}.png") for k in range(n) for v in range(num_views)]
    if layout == "dnerf":
        rule = DNERF_SPLIT if rule is None else rule
        views = cams.hemisphere(spec.setup, c, r, n, width, rng)
        out = []
        for i in range(n):
            split = rule.split(i, True)
            out.append(FrameRecord(f"{split}_r_{i:03d}", split, i, i / max(1, n - 1), "0", views[i],
                                   f"{split}/r_{i:03d}.png"))
        return out
    raise ValueError(f"unknown layout {layout!r} (valid: {', '.join(LAYOUTS)})")


def _check_novel_views(records: list[FrameRecord], focus, novel_view: NovelViewPath) -> None:
    """A ``ValueError`` unless every novel-view camera is :attr:`NovelViewPath.min_angle_deg` or more from every
    training camera (a camera setup whose wobble outgrew the offset)."""
    from .splits import nearest_angles_deg

    novel = [r.camera for r in records if r.camera_id == NOVEL_CAMERA_ID]
    train = [r.camera for r in records if r.split == "train"]
    if novel and train:
        closest = float(nearest_angles_deg(novel, train, focus).min())
        if closest < novel_view.min_angle_deg:
            raise ValueError(f"a novel-view camera is {closest:.2f} degrees from a training camera, under the "
                             f"{novel_view.min_angle_deg} degrees the novel-view path promises")


def as_layout_records(layout: Layout, records: list[FrameRecord]) -> list[FrameRecord]:
    """``records`` with the camera ids the layout's files can say: D-NeRF's ``transforms_*.json`` have no
    camera ids (its loader calls every frame camera ``"0"``), so a rig's extra views are ``"0"`` there too."""
    if layout != "dnerf":
        return records
    return [r if r.camera_id == "0" else dataclasses.replace(r, camera_id="0") for r in records]


def write_image(root: Path, layout: Layout, record: FrameRecord, result: RenderResult) -> None:
    """Write the frame's image file (RGBA with alpha = objects for D-NeRF)."""
    path = root / record.image_file
    path.parent.mkdir(parents=True, exist_ok=True)
    if layout == "dnerf":
        rgb = np.where(result.alpha[..., None], result.rgb, 0.0)
        rgba = np.concatenate([rgb, result.alpha[..., None].astype(np.float32)], axis=-1)
        _imwrite_fast(path, rgba)
    else:
        _imwrite_fast(path, result.rgb)


def _imwrite_fast(path: Path, image: np.ndarray) -> None:
    """PNG with light compression (speed over size; the files are regenerated at will)."""
    img = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    code = cv2.COLOR_RGBA2BGRA if img.shape[2] == 4 else cv2.COLOR_RGB2BGR
    ok, buf = cv2.imencode(".png", cv2.cvtColor(img, code), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:  # pragma: no cover - cv2 encodes any uint8 image
        write_image_file(path, image)
        return
    path.write_bytes(buf.tobytes())  # inside the generator's staging folder: published atomically


def write_metadata(root: Path, layout: Layout, records: list[FrameRecord], near_far: dict[str, tuple[float, float]],
                   num_frames: int, meta: dict) -> None:
    """The layout's camera and index files, plus ``bench4d_meta.json``.

    ``near_far`` maps camera id -> (near, far) depth of the content it sees.
    """
    if layout == "hypernerf":
        _write_hypernerf(root, records, near_far)
    elif layout == "neu3d":
        _write_neu3d(root, records, near_far)
    elif layout == "dnerf":
        _write_dnerf(root, records)
    write_json(root / META_FILE, {**meta, "layout": layout, "num_frames": num_frames})


def _camera_number(camera_id: str) -> int:
    """HyperNeRF's integer ``camera_id`` (0: the monocular camera; a rig's extra cameras count up)."""
    return int(camera_id) if camera_id.isdigit() else 0


def _write_hypernerf(root: Path, records: list[FrameRecord], near_far: dict[str, tuple[float, float]]) -> None:
    # the training cameras' depth range: where the held-out cameras see from is not for a method to know
    training = {r.camera_id for r in records if r.split == "train"} & set(near_far) or set(near_far)
    near = min(near_far[cam][0] for cam in training)
    far = max(near_far[cam][1] for cam in training)
    # Identity normalisation: the loader's world = (position - center) * scale is our world.
    write_json(root / "scene.json", {"scale": 1.0, "center": [0.0, 0.0, 0.0], "near": near, "far": far})
    ids = [r.name for r in records]
    write_json(root / "dataset.json", {
        "count": len(ids), "num_exemplars": len(ids), "ids": ids,
        "train_ids": [r.name for r in records if r.split == "train"],
        "val_ids": [r.name for r in records if r.split == "test"],
    })
    write_json(root / "metadata.json", {r.name: {"warp_id": r.time_index, "camera_id": _camera_number(r.camera_id),
                                                 "time_id": r.time_index, "appearance_id": r.time_index}
                                        for r in records})
    for r in records:
        cam = r.camera
        write_json(root / "camera" / f"{r.name}.json", {
            "orientation": cam.R.tolist(),  # world-to-camera rotation, rows = camera axes
            "position": cam.center.tolist(),
            "focal_length": cam.fx,
            "principal_point": [cam.cx, cam.cy],
            "skew": 0.0,
            "pixel_aspect_ratio": cam.fy / cam.fx,
            "radial_distortion": [0.0, 0.0, 0.0],
            "tangential_distortion": [0.0, 0.0],
            "image_size": [cam.width, cam.height],  # Nerfies order: width first
        })


def _write_neu3d(root: Path, records: list[FrameRecord], near_far: dict[str, tuple[float, float]]) -> None:
    by_cam: dict[str, Camera] = {}
    for r in records:
        by_cam.setdefault(r.camera_id, r.camera)
    rows = []
    for cam_id in sorted(by_cam, key=lambda s: int(s[3:])):
        cam = by_cam[cam_id]
        if abs(cam.cx - cam.width / 2) > 1e-9 or abs(cam.cy - cam.height / 2) > 1e-9 or cam.fx != cam.fy:
            raise ValueError("LLFF poses need a centred principal point and square pixels")
        c2w = cam.camera_to_world
        llff = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2]], axis=1)  # columns: down, right, backwards
        pose = np.concatenate([llff, c2w[:3, 3:4], np.array([[cam.height], [cam.width], [cam.fx]])], axis=1)
        near, far = near_far[cam_id]
        rows.append(np.concatenate([pose.reshape(-1), [near, far]]))
    np.save(root / "poses_bounds.npy", np.asarray(rows, dtype=np.float64))


def _write_dnerf(root: Path, records: list[FrameRecord]) -> None:
    for split in ("train", "val", "test"):
        recs = [r for r in records if r.split == split]
        if not recs:
            continue  # the loader rejects an empty split file; an absent one is fine
        cam0 = recs[0].camera
        frames = []
        for r in recs:
            cam = r.camera
            if abs(cam.cx - cam.width / 2) > 1e-9 or abs(cam.cy - cam.height / 2) > 1e-9 or cam.fx != cam.fy:
                raise ValueError("D-NeRF cameras need a centred principal point and square pixels")
            c2w = cam.camera_to_world.copy()
            c2w[:3, 1:3] *= -1.0  # OpenCV (y down, z forward) -> OpenGL (y up, looks along -z)
            frames.append({"file_path": "./" + r.image_file[: -len(".png")], "time": r.time,
                           "transform_matrix": c2w.tolist()})
        write_json(root / f"transforms_{split}.json", {"camera_angle_x": cam0.fov_x, "frames": frames})


def read_meta(root: Path) -> dict:
    """``bench4d_meta.json`` of a generated scene, or ``{}``."""
    path = Path(root) / META_FILE
    if not path.is_file():
        return {}
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError):
        return {}
