"""Dataset loaders: each source convention -> the one data model.

Every layout is checked the same way: the test converts known OpenCV cameras INTO the source format
with its own code (written from the format's documented math, independent of the loader), loads the
files, and projects known 3D points with the loaded camera against ``cv2.projectPoints`` on the known
parameters. Then times, splits, lazy images, and a table of malformed inputs whose error must name
the file and the field. Real data (../shared) is checked where present.
"""

from __future__ import annotations

import json
import math
import pickle
import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from benchmark.core.errors import InputError
from benchmark.core.imageio import write_image
from benchmark.loaders import detect_layout, load_scene
from benchmark.loaders.dnerf import object_annotations
from benchmark.loaders.hypernerf import read_camera, to_opencv
from benchmark.core.scene import Camera

REPROJ_TOL_PX = 1e-6


# ------------------------------------------------------------------------------------------------
# Known cameras and an independent projection
# ------------------------------------------------------------------------------------------------
def look_at_w2c(center, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(4, 4) OpenCV world-to-camera looking from ``center`` at ``target`` (image y = -up)."""
    center, target, up = (np.asarray(v, dtype=np.float64) for v in (center, target, up))
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([x, y, z])
    w2c[:3, 3] = -w2c[:3, :3] @ center
    return w2c


def known_cameras(n: int, width: int, height: int, *, square: bool = False, distortion: bool = False,
                  radius: float = 4.0) -> list[Camera]:
    """``n`` cameras on a ring around the origin (slightly perturbed, so none is special)."""
    rng = np.random.default_rng(n * 1000 + width)
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n + 0.1
        center = [radius * math.cos(a), radius * math.sin(a), 0.8 + 0.2 * i]
        target = rng.normal(scale=0.1, size=3)
        fx = 0.9 * width + 3 * i
        fy = fx if square else fx * 1.03
        cx, cy = (width / 2, height / 2) if square else (width / 2 + 1.7 * i - 2, height / 2 - 1.1 * i + 1)
        dist = np.array([0.05, -0.02, 0.003, -0.002, 0.01]) * (1 + 0.3 * i) if distortion else None
        cams.append(Camera(width, height, fx, fy, cx, cy, look_at_w2c(center, target), dist))
    return cams


def sample_points(n: int = 50) -> np.ndarray:
    return np.random.default_rng(7).uniform(-0.8, 0.8, size=(n, 3))


def cv2_project(points: np.ndarray, fx, fy, cx, cy, w2c, dist=None) -> np.ndarray:
    """(N, 2) pixels by OpenCV itself (the definition of the OpenCV model)."""
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    rvec, _ = cv2.Rodrigues(w2c[:3, :3])
    uv, _ = cv2.projectPoints(points.reshape(-1, 1, 3), rvec, w2c[:3, 3], K,
                              np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64))
    return uv.reshape(-1, 2)


def assert_projects_like(loaded: Camera, known: Camera, factor: float = 1.0) -> None:
    """The loaded camera projects known points where OpenCV puts them with the known camera
    resized by ``factor`` (pixel corners at 0, so coordinates scale by exactly ``factor``)."""
    pts = sample_points()
    got, z = loaded.project(pts)
    assert np.all(z > 0)
    want = cv2_project(pts, known.fx * factor, known.fy * factor, known.cx * factor, known.cy * factor,
                       known.world_to_camera, known.distortion)
    assert np.abs(got - want).max() < REPROJ_TOL_PX
    assert (loaded.width, loaded.height) == (round(known.width * factor), round(known.height * factor))


def tiny_rgb(width: int, height: int, value: int) -> np.ndarray:
    img = np.zeros((height, width, 3), dtype=np.uint8)
    img[..., 0] = value
    img[..., 1] = np.arange(width, dtype=np.uint8)[None, :] * 3
    img[..., 2] = 255 - value
    return img


# ------------------------------------------------------------------------------------------------
# HyperNeRF writer (Nerfies convention: orientation = w2c rotation, position = centre, [W, H])
# ------------------------------------------------------------------------------------------------
HN_W, HN_H = 64, 48
HN_SCALE, HN_CENTER = 0.25, np.array([1.0, -2.0, 0.5])


def write_hypernerf(root: Path, n: int = 10, *, folders=(2,), val_ids=(), metadata=True, points=None,
                    warp_step: int = 1, width: int = HN_W, height: int = HN_H) -> list[Camera]:
    """Write a HyperNeRF scene whose *normalised* world holds ``known_cameras``; return them (1x)."""
    cams = known_cameras(n, width, height, distortion=True)
    ids = [f"{i + 1:06d}" for i in range(n)]
    (root / "camera").mkdir(parents=True)
    for fid, cam in zip(ids, cams):
        k1, k2, p1, p2, k3 = cam.distortion
        doc = {
            "orientation": cam.R.tolist(),
            "position": (cam.center / HN_SCALE + HN_CENTER).tolist(),  # file coords: world / s + c
            "focal_length": cam.fx, "principal_point": [cam.cx, cam.cy], "skew": 0.0,
            "pixel_aspect_ratio": cam.fy / cam.fx, "radial_distortion": [k1, k2, k3],
            "tangential_distortion": [p1, p2], "image_size": [cam.width, cam.height],
        }
        (root / "camera" / f"{fid}.json").write_text(json.dumps(doc))
    (root / "scene.json").write_text(json.dumps({"scale": HN_SCALE, "center": HN_CENTER.tolist(),
                                                 "near": 0.5, "far": 3.0}))
    (root / "dataset.json").write_text(json.dumps({"count": n, "num_exemplars": n, "ids": ids,
                                                   "train_ids": [i for i in ids if i not in val_ids],
                                                   "val_ids": list(val_ids)}))
    if metadata:
        meta = {fid: {"warp_id": i * warp_step, "camera_id": 0, "time_id": i * warp_step, "appearance_id": i}
                for i, fid in enumerate(ids)}
        (root / "metadata.json").write_text(json.dumps(meta))
    for k in folders:
        for i, fid in enumerate(ids):
            write_image(root / "rgb" / f"{k}x" / f"{fid}.png", tiny_rgb(round(width / k), round(height / k), 10 * i))
    if points is not None:
        np.save(root / "points.npy", points / HN_SCALE + HN_CENTER)
    return cams


def test_hypernerf_cameras_times_splits(tmp_path):
    cams = write_hypernerf(tmp_path, n=10, folders=(1, 2), warp_step=3)
    assert detect_layout(tmp_path) == "hypernerf"
    scene = load_scene(tmp_path)  # default: rgb/2x
    assert scene.dataset == "hypernerf" and len(scene.frames) == 10
    assert scene.metadata["image_folder"] == str(Path("rgb") / "2x")
    for i, (frame, cam) in enumerate(zip(scene.frames, cams)):
        assert frame.name == f"{i + 1:06d}"
        assert_projects_like(frame.camera, cam, 0.5)
        assert frame.time_index == 3 * i and frame.time == (3 * i) / 27
    # every 4th trains, +2 tests, the rest are kept as "val"
    assert [f.split for f in scene.frames] == ["train", "val", "test", "val"] * 2 + ["train", "val"]
    img = scene.frames[4].image()
    assert img.shape == (HN_H // 2, HN_W // 2, 3) and img.dtype == np.float32
    assert img[0, 0, 0] == pytest.approx(40 / 255)
    full = load_scene(tmp_path, scale=1.0)
    for frame, cam in zip(full.frames, cams):
        assert_projects_like(frame.camera, cam, 1.0)
    assert full.frames[1].image().shape == (HN_H, HN_W, 3)
    release = load_scene(tmp_path, split_rule="every4-release")
    assert [f.name for f in release.test_frames] == ["000003"]  # the release drops the last test frame


def test_hypernerf_scale_variants_and_normalisation(tmp_path):
    cams = write_hypernerf(tmp_path, n=4, folders=(1,))
    # 4x has no folder: resized (area) from 1x, intrinsics by the exact factor
    quarter = load_scene(tmp_path, scale="4x")
    assert_projects_like(quarter.frames[0].camera, cams[0], 0.25)
    assert quarter.frames[0].image().shape == (HN_H // 4, HN_W // 4, 3)
    with pytest.raises(InputError, match="scale"):
        load_scene(tmp_path, scale="abc")
    raw = load_scene(tmp_path, normalize=False)
    for frame, cam in zip(raw.frames, cams):  # file coordinates: world / s + c
        np.testing.assert_allclose(frame.camera.center, cam.center / HN_SCALE + HN_CENTER, atol=1e-9)
    assert raw.near_far == pytest.approx((0.5 / HN_SCALE, 3.0 / HN_SCALE))


def test_hypernerf_intrinsics_follow_actual_image_size(tmp_path):
    # 1x is 65x49; the 2x files are 32x24 (rounded): intrinsics scale by 32/65 and 24/49, not 0.5.
    cams = write_hypernerf(tmp_path, n=2, folders=(2,), width=65, height=49)
    cam = load_scene(tmp_path).frames[0].camera
    assert (cam.width, cam.height) == (32, 24)
    assert cam.fx == pytest.approx(cams[0].fx * 32 / 65) and cam.cy == pytest.approx(cams[0].cy * 24 / 49)


def test_hypernerf_val_ids_points_bounds_and_no_metadata(tmp_path):
    pts = np.random.default_rng(1).uniform(-0.5, 0.5, size=(30, 3))
    write_hypernerf(tmp_path, n=6, val_ids=("000002", "000005"), points=pts, metadata=False)
    with pytest.warns(UserWarning, match="metadata.json"):
        scene = load_scene(tmp_path)
    assert [f.split for f in scene.frames] == ["train", "test", "train", "train", "test", "train"]
    assert [f.time_index for f in scene.frames] == list(range(6))
    assert scene.frames[-1].time == 1.0 and scene.frames[2].time == pytest.approx(0.4)
    np.testing.assert_allclose(scene.points, pts, atol=1e-12)  # (file - c) * s recovers the world
    np.testing.assert_allclose(scene.bounds, [pts.min(0), pts.max(0)], atol=1e-12)


def test_hypernerf_bounds_without_points_contain_the_training_frustums(tmp_path):
    from benchmark.loaders._common import frustum_bounds

    write_hypernerf(tmp_path, n=4)
    scene = load_scene(tmp_path)
    assert scene.test_frames and scene.train_frames
    for frame in scene.train_frames:  # a point at mid depth on the optical axis is inside the box
        cam = frame.camera
        p = cam.center + 1.5 * cam.R[2]
        assert np.all(p >= scene.bounds[0]) and np.all(p <= scene.bounds[1])
    # where the held-out cameras stand is not in it: the box is the training views' alone
    near, far = scene.near_far
    train = [f.camera for f in scene.train_frames]
    np.testing.assert_allclose(scene.bounds, frustum_bounds(train, [near] * len(train), [far] * len(train)))
    assert scene.metadata["eval_splits"] == {"paper": [f.name for f in scene.test_frames]}


def hn_edit(rel: str, fn):
    def mutate(root: Path) -> None:
        path = root / rel
        doc = json.loads(path.read_text())
        fn(doc)
        path.write_text(json.dumps(doc))
    return mutate


def _set(key, value):
    def fn(d):
        d[key] = value
    return fn


def _del(*keys):
    def fn(d):
        for k in keys[:-1]:
            d = d[k]
        del d[keys[-1]]
    return fn


HYPERNERF_BAD = [
    ("scene-missing-scale", hn_edit("scene.json", _del("scale")), "scene.json", "scale"),
    ("scene-far-below-near", hn_edit("scene.json", _set("far", 0.1)), "scene.json", "far"),
    ("dataset-missing-ids", hn_edit("dataset.json", _del("ids")), "dataset.json", "ids"),
    ("dataset-empty-ids", hn_edit("dataset.json", _set("ids", [])), "dataset.json", "ids"),
    ("dataset-unknown-val-id", hn_edit("dataset.json", _set("val_ids", ["999999"])), "dataset.json", "val_ids"),
    ("camera-missing-focal", hn_edit("camera/000002.json", _del("focal_length")), "000002.json", "focal_length"),
    ("camera-nan-orientation", hn_edit("camera/000001.json", lambda d: d["orientation"][0].__setitem__(1, float("nan"))),
     "000001.json", "orientation"),
    ("camera-not-rotation", hn_edit("camera/000001.json", _set("orientation", [[2, 0, 0], [0, 1, 0], [0, 0, 1]])),
     "000001.json", "orientation"),
    ("camera-bad-image-size", hn_edit("camera/000003.json", _set("image_size", [64])), "000003.json", "image_size"),
    ("camera-skew", hn_edit("camera/000003.json", _set("skew", 0.5)), "000003.json", "skew"),
    ("camera-file-missing", lambda r: (r / "camera" / "000004.json").unlink(), "000004.json", ""),
    ("metadata-missing-warp", hn_edit("metadata.json", _del("000002", "warp_id")), "metadata.json", "000002.warp_id"),
    ("metadata-missing-id", hn_edit("metadata.json", _del("000003")), "metadata.json", "000003"),
    ("metadata-negative-warp", hn_edit("metadata.json", lambda d: d["000002"].__setitem__("warp_id", -1)),
     "metadata.json", "warp_id"),
    ("image-missing", lambda r: (r / "rgb" / "2x" / "000003.png").unlink(), "000003.png", "image"),
    ("scene-json-invalid", lambda r: (r / "scene.json").write_text("{not json"), "scene.json", "line"),
    ("points-wrong-shape", lambda r: np.save(r / "points.npy", np.zeros((5, 2))), "points.npy", "points"),
]


@pytest.mark.parametrize("case,mutate,file,field", HYPERNERF_BAD, ids=[c[0] for c in HYPERNERF_BAD])
def test_hypernerf_bad_input(tmp_path, case, mutate, file, field):
    write_hypernerf(tmp_path, n=5)
    mutate(tmp_path)
    with pytest.raises(InputError) as err:
        load_scene(tmp_path)
    assert file in (err.value.file or "")
    assert field in (err.value.field or ""), str(err.value)


def test_hypernerf_truncated_image_raises_on_access(tmp_path):
    write_hypernerf(tmp_path, n=5)
    path = tmp_path / "rgb" / "2x" / "000003.png"
    path.write_bytes(path.read_bytes()[:40])
    scene = load_scene(tmp_path)  # metadata loads; the pixels fail when read, naming the file
    with pytest.raises(InputError, match="000003.png"):
        scene.frame("000003").image()
    # a file of the wrong size is an error, never silently resized to fit the camera
    write_image(tmp_path / "rgb" / "2x" / "000004.png", tiny_rgb(10, 10, 0))
    with pytest.raises(InputError, match="image size"):
        load_scene(tmp_path).frame("000004").image()


# ------------------------------------------------------------------------------------------------
# Real HyperNeRF JSON (../shared/formats/hypernerf-chickchicken: no images, no metadata.json)
# ------------------------------------------------------------------------------------------------
def nerfies_project(doc: dict, points: np.ndarray) -> np.ndarray:
    """The Nerfies projection, written from its documented math (image_size is not involved)."""
    R, pos = np.asarray(doc["orientation"]), np.asarray(doc["position"])
    local = (points - pos) @ R.T
    x, y = local[:, 0] / local[:, 2], local[:, 1] / local[:, 2]
    k1, k2, k3 = doc["radial_distortion"]
    p1, p2 = doc["tangential_distortion"]
    r2 = x * x + y * y
    d = 1 + r2 * (k1 + r2 * (k2 + k3 * r2))
    xd = x * d + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * d + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
    f, (ppx, ppy) = doc["focal_length"], doc["principal_point"]
    return np.stack([f * xd + doc["skew"] * yd + ppx, f * doc["pixel_aspect_ratio"] * yd + ppy], -1)


def test_real_hypernerf_camera(hypernerf_json_dir):
    path = hypernerf_json_dir / "camera" / "000001.json"
    doc = json.loads(path.read_text())
    scene_doc = json.loads((hypernerf_json_dir / "scene.json").read_text())
    cam = to_opencv(read_camera(path), np.zeros(3), 1.0, path=path)
    # image_size is [width, height] (Nerfies: image_size_x = image_size[0]): a portrait phone video
    assert (cam.width, cam.height) == tuple(doc["image_size"]) == (1072, 1920)
    assert 0 < cam.cx < cam.width and 0 < cam.cy < cam.height
    # Plausibility of that order: the scene centre projects inside the image as [W, H]; read as
    # [H, W] (1920 wide, 1072 tall) it would fall below the bottom edge.
    (u, v), z = (a[0] for a in cam.project(np.asarray(scene_doc["center"])[None]))
    assert z > 0 and 0 < u < 1072 and 0 < v < 1920 and v > 1072
    # Points in front of the camera project exactly as Nerfies does, and as OpenCV does.
    rng = np.random.default_rng(0)
    local = np.stack([rng.uniform(-0.3, 0.3, 40), rng.uniform(-0.5, 0.5, 40), rng.uniform(5, 30, 40)], -1)
    local[:, :2] *= local[:, 2:3]
    world = (local - cam.t) @ cam.R
    got, _ = cam.project(world)
    assert np.abs(got - nerfies_project(doc, world)).max() < 1e-6
    want = cv2_project(world, cam.fx, cam.fy, cam.cx, cam.cy, cam.world_to_camera, cam.distortion)
    # (cv2 goes through Rodrigues, which re-orthonormalises the float32 file rotation: ~1e-5 px)
    assert np.abs(got - want).max() < 1e-3


def test_real_hypernerf_scene_without_images_or_metadata(hypernerf_json_dir, tmp_path):
    # The sample ships one camera file; give every id a copy so the real scene/dataset JSON load.
    for name in ("scene.json", "dataset.json"):
        shutil.copy(hypernerf_json_dir / name, tmp_path / name)
    ids = json.loads((tmp_path / "dataset.json").read_text())["ids"]
    (tmp_path / "camera").mkdir()
    for fid in ids:
        shutil.copy(hypernerf_json_dir / "camera" / "000001.json", tmp_path / "camera" / f"{fid}.json")
    with pytest.warns(UserWarning, match="metadata.json"):
        scene = load_scene(tmp_path)
    n = len(ids)
    assert len(scene.frames) == n == 456
    assert len(scene.train_frames) == len(range(0, n, 4)) and len(scene.test_frames) == len(range(2, n, 4))
    assert scene.frames[-1].time == 1.0 and scene.frames[1].time == pytest.approx(1 / (n - 1))
    cam = scene.frames[0].camera
    assert (cam.width, cam.height) == (1072, 1920)  # no rgb/: 1x
    s = json.loads((tmp_path / "scene.json").read_text())
    np.testing.assert_allclose(cam.center, (read_camera(tmp_path / "camera" / "000001.json").position
                                            - s["center"]) * s["scale"], atol=1e-9)
    with pytest.raises(InputError, match="no images"):
        scene.frames[0].image()
    with pytest.warns(UserWarning, match="metadata.json"):
        half = load_scene(tmp_path, scale="2x")
    assert (half.frames[0].camera.width, half.frames[0].camera.height) == (536, 960)
    assert half.frames[0].camera.fx == pytest.approx(cam.fx / 2)


# ------------------------------------------------------------------------------------------------
# Neu3D writer (LLFF poses_bounds: [down, right, backwards | centre | (H, W, f)] + near, far)
# ------------------------------------------------------------------------------------------------
N3_HWF = (48, 64, 50.0)  # the poses' (H, W, f); the frames on disk are half that size


def write_neu3d(root: Path, n_cams: int = 4, n_frames: int = 4, *, videos=(2,), meta: bool = True) -> list[Camera]:
    """Cameras in ``videos`` are mp4s, the others extracted frames; returns full-size known cameras."""
    H, W, f = N3_HWF
    cams = known_cameras(n_cams, W, H, square=True)
    cams = [Camera(W, H, f + i, f + i, W / 2, H / 2, c.world_to_camera) for i, c in enumerate(cams)]
    rows = []
    for cam in cams:
        c2w = np.linalg.inv(cam.world_to_camera)
        llff = np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2], c2w[:3, 3], [H, W, cam.fx]], axis=1)  # (3, 5)
        rows.append(np.concatenate([llff.ravel(), [1.0, 8.0]]))
    root.mkdir(parents=True, exist_ok=True)
    np.save(root / "poses_bounds.npy", np.stack(rows))
    for c in range(n_cams):
        frames = [tiny_rgb(W // 2, H // 2, 40 * k + 5 * c) for k in range(n_frames)]
        if c in videos:
            writer = cv2.VideoWriter(str(root / f"cam{c:02d}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30, (W // 2, H // 2))
            for img in frames:
                writer.write(cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
            writer.release()
        else:
            for k, img in enumerate(frames):
                write_image(root / f"cam{c:02d}" / "images" / f"{k:04d}.png", img)
    if meta:
        (root / "bench4d_meta.json").write_text(json.dumps({"num_frames": n_frames}))
    return cams


def test_neu3d_cameras_times_splits_and_video(tmp_path):
    cams = write_neu3d(tmp_path / "s")
    assert detect_layout(tmp_path / "s") == "neu3d"
    scene = load_scene(tmp_path / "s", video_cache="memory")
    assert len(scene.frames) == 16 and scene.camera_ids == ["cam00", "cam01", "cam02", "cam03"]
    for frame in scene.frames:
        c = int(frame.camera_id[3:])
        assert frame.name == f"{frame.camera_id}_{frame.time_index:04d}"
        assert frame.time == frame.time_index / 4
        assert frame.split == ("test" if c == 0 else "train")
        assert_projects_like(frame.camera, cams[c], 0.5)  # intrinsics follow the half-size frames
    assert all(f.camera_id == "cam00" for f in scene.test_frames) and len(scene.test_frames) == 4
    for name, value in (("cam01_0002", 85), ("cam02_0003", 130)):  # extracted frame; mp4 frame (lossy)
        img = scene.frame(name).image()
        assert img.shape == (24, 32, 3)
        assert abs(float(img[..., 0].mean()) - value / 255) < 0.03
    half = load_scene(tmp_path / "s", scale=0.5, video_cache="memory")
    assert_projects_like(half.frame("cam03_0001").camera, cams[3], 0.25)
    assert half.frame("cam02_0001").image().shape == (12, 16, 3)


def test_neu3d_disk_cache_and_default_divisor(tmp_path):
    write_neu3d(tmp_path / "s", meta=False)
    with pytest.warns(UserWarning, match="fewer than 300"):
        scene = load_scene(tmp_path / "s", cache_dir=tmp_path / "cache")
    assert scene.frame("cam01_0003").time == 3 / 300  # the protocol's divisor when nothing says otherwise
    frame = scene.frame("cam02_0002")
    first = frame.image()
    cached = list((tmp_path / "cache").rglob("*.png"))
    assert len(cached) == 4  # the whole video decoded once
    again = pickle.loads(pickle.dumps(frame.load_image))()  # loaders survive pickling (worker processes)
    np.testing.assert_array_equal(first, again)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_scene(tmp_path / "s", num_frames=4).frame("cam01_0003").time == 0.75


def np_save_edit(fn):
    def mutate(root: Path) -> None:
        arr = np.load(root / "poses_bounds.npy")
        np.save(root / "poses_bounds.npy", fn(arr))
    return mutate


def _nan_row1(a):
    a = a.copy()
    a[1, 5] = np.nan
    return a


def _near_above_far(a):
    a = a.copy()
    a[2, 15] = 10.0
    return a


NEU3D_BAD = [
    ("poses-wrong-columns", np_save_edit(lambda a: a[:, :16]), "poses_bounds.npy", "shape"),
    ("poses-nan", np_save_edit(_nan_row1), "poses_bounds.npy", "row 1"),
    ("poses-near-above-far", np_save_edit(_near_above_far), "poses_bounds.npy", "row 2"),
    ("poses-count-mismatch", np_save_edit(lambda a: a[:3]), "poses_bounds.npy", "shape"),
    ("frames-gap", lambda r: (r / "cam01" / "images" / "0001.png").unlink(), "images", "frames"),
    ("meta-missing-key", lambda r: (r / "bench4d_meta.json").write_text("{}"), "bench4d_meta.json", "num_frames"),
    ("video-garbage", lambda r: (r / "cam02.mp4").write_bytes(b"not a video" * 10), "cam02.mp4", "video"),
]


@pytest.mark.parametrize("case,mutate,file,field", NEU3D_BAD, ids=[c[0] for c in NEU3D_BAD])
def test_neu3d_bad_input(tmp_path, case, mutate, file, field):
    write_neu3d(tmp_path)
    mutate(tmp_path)
    with pytest.raises(InputError) as err:
        load_scene(tmp_path)
    assert file in (err.value.file or "")
    assert field in (err.value.field or ""), str(err.value)


# ------------------------------------------------------------------------------------------------
# D-NeRF writer (transforms_*.json, OpenGL c2w, camera_angle_x, RGBA)
# ------------------------------------------------------------------------------------------------
DN_SIZE = 16
DN_TIMES = {"train": [0.0, 0.25, 0.5, 0.75, 1.0], "val": [0.125], "test": [0.25, 0.875]}


def write_dnerf(root: Path, times=DN_TIMES) -> dict[str, list[Camera]]:
    known = {}
    f = 20.0
    for s_i, (split, ts) in enumerate(times.items()):
        cams = known_cameras(len(ts) + 3 * s_i, DN_SIZE, DN_SIZE, square=True)[-len(ts):]
        cams = [Camera(DN_SIZE, DN_SIZE, f, f, DN_SIZE / 2, DN_SIZE / 2, c.world_to_camera) for c in cams]
        known[split] = cams
        frames = []
        for i, (t, cam) in enumerate(zip(ts, cams)):
            c2w = np.linalg.inv(cam.world_to_camera)
            c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL axes
            rgba = np.zeros((DN_SIZE, DN_SIZE, 4), dtype=np.uint8)
            rgba[..., 0] = 200
            rgba[4:12, 4:12, 3] = 255  # an opaque square, transparent elsewhere
            write_image(root / split / f"r_{i:03d}.png", rgba)
            frames.append({"file_path": f"./{split}/r_{i:03d}", "rotation": 0.1, "time": t,
                           "transform_matrix": c2w.tolist()})
        doc = {"camera_angle_x": 2 * math.atan(DN_SIZE / (2 * f)), "frames": frames}
        (root / f"transforms_{split}.json").write_text(json.dumps(doc))
    return known


def test_dnerf_cameras_times_splits_images(tmp_path):
    known = write_dnerf(tmp_path)
    assert detect_layout(tmp_path) == "dnerf"
    scene = load_scene(tmp_path)
    assert np.array_equal(scene.background, [1, 1, 1])
    distinct = sorted({t for ts in DN_TIMES.values() for t in ts})
    for split, ts in DN_TIMES.items():
        frames = sorted(scene.split(split), key=lambda f: f.name)
        assert [f.name for f in frames] == [f"{split}_r_{i:03d}" for i in range(len(ts))]
        for frame, t, cam in zip(frames, ts, known[split]):
            assert frame.time == t and frame.time_index == distinct.index(t)
            assert_projects_like(frame.camera, cam, 1.0)
    # equal times across splits share an index
    assert scene.frame("train_r_001").time_index == scene.frame("test_r_000").time_index == 2
    img, alpha = scene.frame("val_r_000").image(), scene.frame("val_r_000").alpha()
    assert alpha.sum() == 64 and alpha[4:12, 4:12].all()
    assert np.allclose(img[0, 0], 1.0) and np.allclose(img[8, 8], [200 / 255, 0, 0])  # composited on white
    black = load_scene(tmp_path, background=(0, 0, 0))
    assert np.allclose(black.frame("val_r_000").image()[0, 0], 0.0)
    half = load_scene(tmp_path, scale=0.5)
    assert_projects_like(half.frame("test_r_001").camera, known["test"][1], 0.5)
    assert half.frame("test_r_001").image().shape == (8, 8, 3) and half.frame("test_r_001").alpha().sum() == 16


def test_dnerf_object_annotations(tmp_path):
    write_dnerf(tmp_path / "lego")
    scene = load_scene(tmp_path / "lego")
    aset = object_annotations(scene, "yellow bulldozer")  # the query names the object, the folder does not
    assert [q.text for q in aset.queries] == ["yellow bulldozer"] and aset.queries[0].level == "whole"
    assert [f.name for f in aset.frames] == [f.name for f in scene.test_frames]
    for fr in aset.frames:
        np.testing.assert_array_equal(aset.get_mask(1, fr.id), scene.frame(fr.name).alpha())
    assert object_annotations(scene, "toy", split="val").queries[0].text == "toy"
    with pytest.raises(InputError, match="object query"):
        object_annotations(scene, " ")


def dn_edit(split: str, fn):
    return hn_edit(f"transforms_{split}.json", fn)


def _frame_set(i, key, value):
    def fn(d):
        d["frames"][i][key] = value
    return fn


DNERF_BAD = [
    ("missing-angle", dn_edit("train", _del("camera_angle_x")), "transforms_train.json", "camera_angle_x"),
    ("missing-time", dn_edit("train", _del("frames", 1, "time")), "transforms_train.json", "frames[1].time"),
    ("time-out-of-range", dn_edit("val", _frame_set(0, "time", 1.5)), "transforms_val.json", "frames[0].time"),
    ("time-not-number", dn_edit("test", _frame_set(1, "time", "late")), "transforms_test.json", "frames[1].time"),
    ("empty-split", dn_edit("test", _set("frames", [])), "transforms_test.json", "frames"),
    ("missing-image", lambda r: (r / "train" / "r_002.png").unlink(), "transforms_train.json", "frames[2].file_path"),
    ("nan-matrix", dn_edit("train", lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(3, float("nan"))),
     "transforms_train.json", "frames[0].transform_matrix"),
    ("matrix-shape", dn_edit("test", _frame_set(0, "transform_matrix", [[1, 0, 0], [0, 1, 0], [0, 0, 1]])),
     "transforms_test.json", "frames[0].transform_matrix"),
    ("no-train-file", lambda r: (r / "transforms_train.json").rename(r / "other.json"), "", "layout"),
    ("train-invalid-json", lambda r: (r / "transforms_train.json").write_text('{"frames": ['), "transforms_train.json", "line"),
]


@pytest.mark.parametrize("case,mutate,file,field", DNERF_BAD, ids=[c[0] for c in DNERF_BAD])
def test_dnerf_bad_input(tmp_path, case, mutate, file, field):
    write_dnerf(tmp_path)
    mutate(tmp_path)
    with pytest.raises(InputError) as err:
        load_scene(tmp_path)
    assert file in (err.value.file or "")
    assert field in (err.value.field or ""), str(err.value)


def test_generic_errors(tmp_path):
    with pytest.raises(InputError, match="layout"):
        detect_layout(tmp_path)
    with pytest.raises(InputError, match="not found"):
        load_scene(tmp_path / "nope")
    write_dnerf(tmp_path)
    with pytest.raises(InputError, match="num_frames"):
        load_scene(tmp_path, num_frames=3)  # a Neu3D option given to a D-NeRF scene
    with pytest.raises(InputError, match="split_rule"):
        load_scene(tmp_path, split_rule="every4")
    assert detect_layout(tmp_path / "transforms_train.json") == "dnerf"


# ------------------------------------------------------------------------------------------------
# Real D-NeRF scenes (../shared/data/dnerf)
# ------------------------------------------------------------------------------------------------
DNERF_SCENES = ("bouncingballs", "jumpingjacks", "lego", "standup")


@pytest.mark.parametrize("name", DNERF_SCENES)
def test_real_dnerf_scene(dnerf_dir, name):
    root = dnerf_dir / name
    scene = load_scene(root)
    for split in ("train", "val", "test"):
        doc = json.loads((root / f"transforms_{split}.json").read_text())
        frames = scene.split(split)
        assert len(frames) == len(doc["frames"]) > 0
        focal = 0.5 * 400 / math.tan(0.5 * doc["camera_angle_x"])
        assert all(f.camera.fx == pytest.approx(focal) and f.camera.cx == 200 for f in frames)
        for frame in (frames[0], frames[-1]):
            img, alpha = frame.image(), frame.alpha()
            assert img.shape == (400, 400, 3) and alpha.shape == (400, 400)
            assert 0 < alpha.mean() < 0.9
    assert scene.num_time_steps == len({f.time for f in scene.frames})
    # the object sits at the world origin: it projects inside every image, in front of the camera
    for frame in scene.frames:
        (u, v), z = (a[0] for a in frame.camera.project(np.zeros((1, 3))))
        assert z > 0 and 0 < u < 400 and 0 < v < 400
    assert np.all(scene.bounds[0] < 0) and np.all(scene.bounds[1] > 0)
    half = load_scene(root, scale=0.5)
    frame = half.test_frames[0]
    assert frame.image().shape == (200, 200, 3) and frame.alpha().shape == (200, 200)
    assert frame.camera.fx == pytest.approx(scene.test_frames[0].camera.fx / 2) and frame.camera.cx == 100


def test_real_dnerf_object_annotations(dnerf_dir):
    scene = load_scene(dnerf_dir / "lego", scale=0.5)
    aset = object_annotations(scene, "lego bulldozer")
    assert aset.queries[0].text == "lego bulldozer" and len(aset.frames) == len(scene.test_frames) == 20
    assert all(aset.get_mask(1, f.id).any() for f in aset.frames)
    # the benchmark's own file for the scene: the simulated annotator's masks where they reach IoU 0.95
    # against these alpha masks (made_by box / clicks), the alpha mask itself elsewhere (made_by scripted)
    from benchmark.runner import find_annotations

    shipped = find_annotations(load_scene(dnerf_dir / "lego"))
    full = object_annotations(load_scene(dnerf_dir / "lego"), "lego bulldozer")
    assert [q.text for q in shipped.queries] == ["lego bulldozer"]
    assert [a.name for a in shipped.frames] == [b.name for b in full.frames]
    for a, b in zip(shipped.frames, full.frames):
        mine, alpha = shipped.get_mask(1, a.id), full.get_mask(1, b.id)
        how = shipped.made_by[(1, a.id)]
        assert how in ("box", "clicks", "scripted")
        if how == "scripted":
            assert np.array_equal(mine, alpha)
        else:
            assert (mine & alpha).sum() / (mine | alpha).sum() >= 0.95


def test_dnerf_near_far_from_generator_meta(tmp_path):
    """The synthetic generator's D-NeRF layout carries its own depth range in bench4d_meta.json."""
    from benchmark.synthetic import generate

    root = generate("smoke", tmp_path / "smoke", layout="dnerf")
    scene = load_scene(root)
    meta = json.loads((root / "bench4d_meta.json").read_text())
    assert scene.near_far == tuple(meta["near_far"]) != (2.0, 6.0)
    meta["near_far"] = [3.0, 1.0]
    (root / "bench4d_meta.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="bench4d_meta.json: near_far"):
        load_scene(root)
