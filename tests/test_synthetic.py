"""The synthetic 4D scene generator: exact ray casting, presets, layouts read back by the loaders,
exact ground truth, the training-frames-only guard, and the ``bench4d data`` commands."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmark.core.errors import InputError
from benchmark.core.scene import Camera
from benchmark.synthetic import PRESETS, TruthAccessError, generate, list_presets, load_truth
from benchmark.synthetic import csg
from benchmark.synthetic.generate import preset_rng
from benchmark.synthetic.layouts import LAYOUTS, NEU3D_RIG_CAMERAS
from benchmark.synthetic.model import Catalogue, FrameContext, Piece, State, Timeline, part, subpart, whole
from benchmark.synthetic.objects import CupGeometry, ring
from benchmark.synthetic.render import background_instances, instances, render, surfaces
from benchmark.synthetic.transforms import look_at_opencv, rotation
from benchmark.synthetic import textures as tx

TINY = {"size": 24, "frames": 5, "views": 2}
"""Small enough that all presets x layouts render in seconds."""
REPROJECTION_TOLERANCE_PX = 1e-3


# -- fixtures ---------------------------------------------------------------------------------------
@pytest.fixture(scope="session")
def scene_dirs(tmp_path_factory):
    """(preset, layout) -> folder of a tiny generated scene, generated on first use."""
    root = tmp_path_factory.mktemp("synthetic")
    cache: dict[tuple[str, str], Path] = {}

    def get(preset: str, layout: str, **kw) -> Path:
        settings = {**TINY, **kw}
        key = (preset, layout, tuple(sorted(settings.items())))
        if key not in cache:
            cache[key] = generate(preset, root / f"{preset}-{layout}-{len(cache)}", layout=layout, **settings)
        return cache[key]

    return get


def _unproject(cam: Camera, depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(M, 3) world points of the masked pixels from camera-space depth."""
    i, j = np.nonzero(mask)
    z = depth[i, j].astype(np.float64)
    xc = np.stack([(j + 0.5 - cam.cx) / cam.fx * z, (i + 0.5 - cam.cy) / cam.fy * z, z], axis=1)
    return (xc - cam.t) @ cam.R


def _scene_def(preset: str, frames: int, seed: int = 0):
    """Rebuild the generator's scene definition (same seeding as generate())."""
    scene = PRESETS[preset].build(preset_rng(preset, seed), frames)
    return scene, Catalogue.build(scene.wholes)


# -- exact ray casting ------------------------------------------------------------------------------
def _cast(solid: csg.Solid, o: np.ndarray, d: np.ndarray):
    return csg.nearest(solid.crossings(o, d), 1e-9)


def test_sphere_box_cylinder_cone_hits_are_analytic():
    o = np.array([[0.0, 0.0, -5.0], [0.3, 0.0, -5.0], [2.0, 2.0, -5.0]])
    d = np.tile([0.0, 0.0, 1.0], (3, 1))
    t, n = _cast(csg.Sphere(1.0), o, d)
    assert t[0] == pytest.approx(4.0) and t[1] == pytest.approx(5.0 - np.sqrt(1 - 0.09))
    assert np.isinf(t[2])
    np.testing.assert_allclose(n[0], [0, 0, -1], atol=1e-12)

    t, n = _cast(csg.Box((1.0, 2.0, 0.5)), o, d)
    assert t[0] == pytest.approx(4.5) and t[1] == pytest.approx(4.5) and np.isinf(t[2])
    np.testing.assert_allclose(n[:2], [[0, 0, -1], [0, 0, -1]])

    side = np.array([[-5.0, 0.0, 0.5]])
    t, n = _cast(csg.Cylinder(0.5, 0.0, 1.0), side, np.array([[1.0, 0.0, 0.0]]))
    assert t[0] == pytest.approx(4.5)
    np.testing.assert_allclose(n[0], [-1, 0, 0], atol=1e-12)

    # cone with its apex at z = 1: a ray along the axis from above meets the apex, one from below the base
    cone = csg.Frustum(0.5, 0.0, 0.0, 1.0)
    t, _ = _cast(cone, np.array([[0.0, 0.0, 3.0], [0.1, 0.0, -2.0]]), np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]))
    assert t[0] == pytest.approx(2.0, abs=1e-9) and t[1] == pytest.approx(2.0)
    # at height z the cone's radius is 0.5 (1 - z): a horizontal ray at z = 0.5 enters at |x| = 0.25
    t, n = _cast(cone, np.array([[-3.0, 0.0, 0.5]]), np.array([[1.0, 0.0, 0.0]]))
    assert t[0] == pytest.approx(3.0 - 0.25)
    np.testing.assert_allclose(n[0], np.array([-1.0, 0.0, 0.5]) / np.linalg.norm([-1.0, 0.0, 0.5]), atol=1e-12)


def test_hollow_cup_is_seen_from_inside_and_outside():
    geo = CupGeometry(radius=0.07, height=0.11, wall=0.008, bottom=0.012)
    body = geo.wall_solid() | geo.rim_solid()
    down = np.array([[0.0, 0.0, 1.0], [0.066, 0.0, 1.0]])  # down the middle; onto the rim's top face
    t, n = _cast(body, down, np.tile([0.0, 0.0, -1.0], (2, 1)))
    assert t[0] == pytest.approx(1.0 - geo.bottom)  # the inner floor
    assert t[1] == pytest.approx(1.0 - geo.height)  # the rim
    t, n = _cast(body, np.array([[0.0, 0.0, 0.05]]), np.array([[1.0, 0.0, 0.0]]))  # from inside the cup
    assert t[0] == pytest.approx(geo.inner_radius)
    np.testing.assert_allclose(n[0], [-1, 0, 0], atol=1e-12)  # inner wall faces the axis


def _random_rays(rng, n, radius):
    """Rays from a shell outside the solid aimed at random points near it."""
    start = rng.normal(size=(n, 3))
    start = 3 * radius * start / np.linalg.norm(start, axis=1, keepdims=True)
    aim = rng.uniform(-radius, radius, (n, 3))
    d = aim - start
    return start, d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("name", ["cup", "ring", "cookie-half", "egg-lid", "box-minus-box", "union", "moved-cone"])
def test_first_crossing_is_where_the_ray_enters_the_solid(name):
    """Property: just before the reported hit the ray is outside, just after it is inside; a miss
    stays outside along its whole length. Holds for primitives and boolean combinations alike."""
    geo = CupGeometry()
    shell = csg.Ellipsoid((0.07, 0.07, 0.085)) - csg.Ellipsoid((0.065, 0.065, 0.08))
    solids = {
        "cup": geo.wall_solid() | geo.rim_solid() | geo.handle_solid(),
        "ring": ring(0.05, 0.03, 0.01),
        "cookie-half": csg.Cylinder(0.085, 0.0, 0.02) & csg.HalfSpace((0.6, 0.8, 0.0), 0.0),
        "egg-lid": shell & csg.HalfSpace((0.0, 0.0, -1.0), -0.01),
        "box-minus-box": csg.Box((0.08, 0.06, 0.04)) - csg.Moved(csg.Box((0.07, 0.05, 0.04)), np.eye(3), np.array([0, 0, 0.01])),
        "union": csg.Sphere(0.05) | csg.Box((0.08, 0.02, 0.02)),
        "moved-cone": csg.Moved(csg.Frustum(0.03, 0.0, 0.0, 0.09), rotation((1, 1, 0), 0.7)[:3, :3], np.array([0.01, 0, 0])),
    }
    solid = solids[name]
    rng = np.random.default_rng(7)
    o, d = _random_rays(rng, 4000, 0.12)
    t, _ = _cast(solid, o, d)
    hit = np.isfinite(t)
    assert 0.05 < hit.mean() < 0.98
    eps = 1e-7
    before = solid.contains(o[hit] + (t[hit] - eps)[:, None] * d[hit])
    after = solid.contains(o[hit] + (t[hit] + eps)[:, None] * d[hit])
    # a ray that only grazes a silhouette can touch the surface without entering: allow a handful
    assert np.mean(before) < 2e-3 and np.mean(after) > 0.998
    steps = np.linspace(0.0, 6 * 0.12, 400)
    miss_points = o[~hit][:, None, :] + steps[None, :, None] * d[~hit][:, None, :]
    assert not solid.contains(miss_points.reshape(-1, 3)).any()


def test_render_depth_and_ids_are_exact_for_a_sphere():
    center = np.array([0.1, -0.05, 0.2])
    ball = whole("ball", pieces=[Piece(csg.Sphere(0.15), tx.Solid((0.8, 0.2, 0.2)))],
                 pose=np.block([[np.eye(3), center[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]))
    from benchmark.synthetic.model import SceneDef

    scene = SceneDef("t", [ball], [], tuple(center), 0.2, 2)
    cat = Catalogue.build(scene.wholes)
    cam = Camera(40, 30, 35.0, 36.0, 20.5, 14.2, look_at_opencv([1.0, -0.8, 0.7], center))
    res = render(instances(scene, cat, FrameContext(0, 2)), cam, scene.light)
    assert res.ids.shape == (3, 30, 40) and res.alpha.sum() > 50
    pts = _unproject(cam, res.depth, res.alpha)
    np.testing.assert_allclose(np.linalg.norm(pts - center, axis=1), 0.15, atol=1e-5)  # float32 depth
    uv, _ = cam.project(center[None])  # the centre pixel sees the ball
    assert res.ids[2, int(uv[0, 1]), int(uv[0, 0])] == 1
    assert np.all(res.ids[:, ~res.alpha] == 0) and np.all(np.isinf(res.depth[~res.alpha]))


def test_cached_static_layer_renders_the_same_image():
    scene, cat = _scene_def("split-cookie", 10)
    ctx = FrameContext(7, 10)
    cam = Camera(40, 30, 30.0, 30.0, 20.0, 15.0, look_at_opencv([0.5, -0.6, 0.5], scene.focus_center))
    full = render(instances(scene, cat, ctx), cam, scene.light)
    bg = background_instances(scene, ctx)
    layered = render(instances(scene, cat, ctx, background=False), cam, scene.light, static=surfaces(bg, cam))
    np.testing.assert_array_equal(full.ids, layered.ids)
    np.testing.assert_array_equal(full.depth, layered.depth)
    np.testing.assert_allclose(full.rgb, layered.rgb, atol=1e-6)
    assert full.alpha.any() and (~full.alpha).any()


# -- model: hierarchy and timelines ------------------------------------------------------------------
def test_catalogue_assigns_ids_per_level_and_implicit_entries():
    leaf = Piece(csg.Sphere(0.1), tx.Solid((1, 1, 1)))
    cup = whole("cup", parts=[part("cup body", parts=[subpart("cup wall", pieces=[leaf]),
                                                     subpart("cup rim", pieces=[leaf])]),
                              part("cup handle", pieces=[leaf])])
    ball = whole("ball", pieces=[leaf])
    cat = Catalogue.build([cup, ball])
    assert [e.name for e in cat.entries["whole"]] == ["cup", "ball"]
    assert [e.name for e in cat.entries["part"]] == ["cup body", "cup handle", "ball"]
    assert [e.name for e in cat.entries["subpart"]] == ["cup wall", "cup rim", "cup handle", "ball"]
    assert [leaf.ids for leaf in cat.leaves] == [(1, 1, 1), (2, 1, 1), (3, 2, 1), (4, 3, 2)]
    assert cat.ids_named("cup handle") == ("part", [2])
    assert cat.names() == ["cup", "ball", "cup body", "cup handle", "cup wall", "cup rim"]
    with pytest.raises(ValueError, match="both"):
        Catalogue.build([whole("lid", parts=[part("lid", parts=[subpart("x", pieces=[leaf])]),
                                             part("y", pieces=[leaf])])])


def test_timeline_intervals_partition_and_visuals_switch_at_the_boundary():
    a, b = State("closed", "closed box", ("c",) * 5), State("open", "open box", ("o",) * 5)
    tl = Timeline((a, b), (0, 1, 0), (7, 15), 30, ramp_frames=4.0)
    assert tl.intervals() == {"closed": [(0, 6), (15, 29)], "open": [(7, 14)]}
    values = [tl.value(FrameContext(i, 30), {"closed": 0.0, "open": 1.0}) for i in range(30)]
    assert all(v < 0.5 for v in values[:7]) and all(v > 0.5 for v in values[7:15])
    assert all(v < 0.5 for v in values[15:]) and values[0] == 0.0 and values[11] == 1.0
    assert tl.state_at(7).key == "open" and tl.state_at(29).key == "closed"
    with pytest.raises(ValueError):
        Timeline((a, b), (0, 1), (0,), 30)
    draws = {Timeline.sample(np.random.default_rng(s), 60, (a, b), (0, 1), [(0.3, 0.7)]).boundaries for s in range(8)}
    assert len(draws) > 3  # state changes at varied times across seeds


# -- presets -----------------------------------------------------------------------------------------
def test_presets_cover_the_paper_scenes():
    names = list_presets()
    assert {"americano", "chickchicken", "split-cookie", "espresso", "keyboard", "torchocolate", "smoke"} <= set(names)
    real = [p for p in PRESETS.values() if p.name != "smoke"]
    assert len(real) >= 6
    assert sum(p.time_sensitive for p in real) >= 4
    assert any(p.default_layout == "neu3d" for p in real)
    # a Neu3D-like preset has the real rig's cameras: a few cameras make its held-out view a sparse-view problem
    assert all(p.default_views == NEU3D_RIG_CAMERAS for p in real if p.default_layout == "neu3d")
    for spec in PRESETS.values():
        scene, cat = _scene_def(spec.name, spec.default_frames)
        assert len(scene.wholes) >= 2
        for entry, tl in cat.timelines():
            lengths = [b - a + 1 for _, a, b in tl.segments()]
            assert sum(lengths) == spec.default_frames
            for state in tl.states:
                assert len(state.captions) >= 5 and len(set(state.captions)) == len(state.captions)
        if spec.time_sensitive:
            assert any(st.query for _, tl in cat.timelines() for st in tl.states)


@pytest.mark.parametrize("preset", list(PRESETS))
@pytest.mark.parametrize("layout", LAYOUTS)
def test_loaders_read_back_cameras_times_and_splits(scene_dirs, preset, layout):
    from benchmark.loaders import load_scene

    root = scene_dirs(preset, layout)
    scene = load_scene(root)
    truth = load_truth(root)
    loaded = {f.name: f for f in scene.frames}
    assert set(loaded) == set(truth.frames)
    views = TINY["views"] if layout == "neu3d" else 1
    novel = len(range(2, TINY["frames"], 4)) if layout == "hypernerf" else 0  # the novel-view path's frames
    assert len(loaded) == TINY["frames"] * views + novel and scene.num_time_steps == TINY["frames"]
    rng = np.random.default_rng(0)
    worst = 0.0
    for name, tf in truth.frames.items():
        f = loaded[name]
        assert (f.time, f.time_index, f.split, str(f.camera_id)) == (tf.time, tf.time_index, tf.split, tf.camera_id)
        assert (f.camera.width, f.camera.height) == (tf.camera.width, tf.camera.height)
        # points at random pixels and depths, and the rendered surface itself, reproject onto the same pixels
        depth = truth.depth(name, allow_eval=True)
        surface = np.isfinite(depth)
        pix = np.stack(np.nonzero(surface), axis=1)[:, ::-1] + 0.5
        uv, _ = f.camera.project(_unproject(tf.camera, depth, surface))
        worst = max(worst, float(np.abs(uv - pix).max()) if len(pix) else 0.0)
        rand = rng.uniform(0, 1, (32, 2)) * [tf.camera.width, tf.camera.height]
        z = rng.uniform(0.3, 3.0, 32)
        cam_pts = np.stack([(rand[:, 0] - tf.camera.cx) / tf.camera.fx, (rand[:, 1] - tf.camera.cy) / tf.camera.fy,
                            np.ones(32)], axis=1) * z[:, None]
        uv, _ = f.camera.project((cam_pts - tf.camera.t) @ tf.camera.R)
        worst = max(worst, float(np.abs(uv - rand).max()))
        assert f.image().shape == (tf.camera.height, tf.camera.width, 3)
    assert worst < REPROJECTION_TOLERANCE_PX
    splits = {f.split for f in scene.frames}
    assert "train" in splits and "test" in splits
    if layout == "dnerf":
        f = scene.test_frames[0]
        np.testing.assert_array_equal(f.alpha(), truth.levels(f.name, allow_eval=True)["whole"] > 0)


@pytest.mark.parametrize("preset", list(PRESETS))
def test_cameras_keep_every_object_in_view(scene_dirs, preset):
    spec = PRESETS[preset]
    truth = load_truth(scene_dirs(preset, spec.default_layout))
    seen: set[int] = set()
    border = []
    for name in truth.frames:
        whole_ids = truth.levels(name, allow_eval=True)["whole"]
        seen |= set(np.unique(whole_ids).tolist())
        edge = np.concatenate([whole_ids[0], whole_ids[-1], whole_ids[:, 0], whole_ids[:, -1]])
        border.append(np.mean(edge > 0))
    assert seen - {0} == set(truth.names("whole"))  # every object appears
    assert np.mean(border) < 0.1  # and the framing does not crop the content


@pytest.mark.parametrize("layout", LAYOUTS)
def test_annotations_are_exact_and_validate_against_the_scene(scene_dirs, layout):
    from annotations.format import load_annotations
    from benchmark.loaders import load_scene

    root = scene_dirs("smoke", layout, frames=8)
    scene = load_scene(root)
    truth = load_truth(root)
    aset = load_annotations(root / "annotations.json", scene=scene)
    assert [f.name for f in aset.frames] == truth.evaluated_frames
    agn = {q.text: q for q in aset.agnostic_queries}
    assert set(agn) == set(truth.query_names())
    for af in aset.frames:
        ids = truth.levels(af.name, allow_eval=True)
        for text, q in agn.items():
            level, wanted = truth.ids_named(text)
            np.testing.assert_array_equal(aset.get_mask(q.id, af.id), np.isin(ids[level], wanted))
    sens = {q.text: q for q in aset.sensitive_queries}
    assert {"open box", "closed box", "broken bar", "intact bar"} == set(sens)
    assert aset.query(sens["open box"].base).text == "box"
    covered = sorted(t for q in ("open box", "closed box") for a, b in sens[q].intervals for t in range(a, b + 1))
    assert covered == list(range(8))  # complementary states partition the video


def test_hierarchy_is_nested_and_consistent(scene_dirs):
    root = scene_dirs("chickchicken", "hypernerf", size=48, frames=6)
    truth = load_truth(root)
    parent = {lv: np.zeros(1 + max(truth.catalogue[lv]), dtype=np.int64) for lv in ("subpart", "part")}
    for lv in parent:
        for i, e in truth.catalogue[lv].items():
            parent[lv][i] = e["parent"]
    for name in truth.frames:
        lv = truth.levels(name, allow_eval=True)
        assert all(a.dtype == np.uint16 for a in lv.values())
        np.testing.assert_array_equal(parent["subpart"][lv["subpart"]], lv["part"])
        np.testing.assert_array_equal(parent["part"][lv["part"]], lv["whole"])
    assert truth.name("part", 0) is None and truth.names("whole")[1] == "toy chicken"
    assert "chicken beak" in truth.query_names() and "toy egg" in truth.stateful_objects


def test_truth_guard_allows_training_frames_only(scene_dirs):
    truth = load_truth(scene_dirs("smoke", "hypernerf", frames=8))
    train, test = truth.training_frames[0], truth.evaluated_frames[0]
    assert truth.levels(train)["whole"].shape == truth.depth(train).shape
    for call in (lambda: truth.levels(test), lambda: truth.depth(test), lambda: truth.mask("box", test),
                 lambda: truth.state_at("box", truth.frames[test].time_index), lambda: truth.timelines()):
        with pytest.raises(TruthAccessError):
            call()
    assert truth.levels(test, allow_eval=True)["part"].shape == truth.depth(test, allow_eval=True).shape
    assert truth.state_at("box", truth.frames[train].time_index)["phrase"] in ("open box", "closed box")
    assert len(truth.timelines(allow_eval=True)) == 2


# -- the states show in the pixels -------------------------------------------------------------------
def _per_frame(truth, text):
    out = []
    for name, tf in sorted(truth.frames.items(), key=lambda kv: kv[1].time_index):
        mask = truth.mask(text, name, allow_eval=True)
        out.append((tf, mask))
    return out


def test_states_change_the_appearance(scene_dirs):
    from benchmark.core.imageio import read_image

    # americano: the liquid darkens
    root = scene_dirs("americano", "hypernerf", size=64, frames=10)
    truth = load_truth(root)
    (state_of,) = [s for s in truth.timelines(allow_eval=True) if s["object"] == "liquid"]
    clear = dict((st["state"], st["intervals"]) for st in state_of["states"])["clear"]
    lum = {"clear": [], "dark": []}
    for tf, mask in _per_frame(truth, "liquid"):
        if mask.sum() >= 4:
            key = "clear" if any(a <= tf.time_index <= b for a, b in clear) else "dark"
            lum[key].append(read_image(root / tf.image_file)[mask].mean())
    assert lum["clear"] and lum["dark"] and np.mean(lum["clear"]) - np.mean(lum["dark"]) > 0.2

    # split-cookie: the halves move apart (3D distance between their centroids)
    root = scene_dirs("split-cookie", "hypernerf", size=64, frames=10)
    truth = load_truth(root)
    _, halves = truth.ids_named("cookie half")
    gaps = []
    for name, tf in sorted(truth.frames.items(), key=lambda kv: kv[1].time_index):
        ids, depth = truth.levels(name, allow_eval=True)["part"], truth.depth(name, allow_eval=True)
        c = [_unproject(tf.camera, depth, ids == h).mean(axis=0) for h in halves]
        gaps.append(np.linalg.norm(c[0] - c[1]))
    assert gaps[-1] - gaps[0] > 0.03

    # espresso: no coffee in the cup at first, coffee at the end
    truth = load_truth(scene_dirs("espresso", "hypernerf", size=64, frames=10))
    seen = [mask.sum() for _, mask in _per_frame(truth, "espresso")]
    assert seen[0] == 0 and seen[-1] > 0


def test_rendered_surface_matches_the_scene_geometry(scene_dirs):
    """The ball of the smoke preset: every pixel labelled 'ball' unprojects onto its sphere."""
    from benchmark.loaders import load_scene

    root = scene_dirs("smoke", "neu3d", size=48, frames=5, views=3)
    scene, cat = _scene_def("smoke", 5)
    (ball,) = [w for w in scene.wholes if w.name == "ball"]
    truth = load_truth(root)
    loaded = {f.name: f for f in load_scene(root).frames}
    for name, tf in truth.frames.items():
        mask = truth.mask("ball", name, allow_eval=True)
        centre = ball.pose(FrameContext(tf.time_index, 5))[:3, 3]
        pts = _unproject(loaded[name].camera, truth.depth(name, allow_eval=True), mask)
        np.testing.assert_allclose(np.linalg.norm(pts - centre, axis=1), 0.035, atol=2e-5)


def test_same_seed_same_scene_other_seed_other_scene(tmp_path):
    a = generate("smoke", tmp_path / "a", size=24, frames=5)
    b = generate("smoke", tmp_path / "b", size=24, frames=5)
    c = generate("smoke", tmp_path / "c", size=24, frames=5, seed=1)
    for rel in ("truth/scene_truth.json", "rgb/1x/000003.png", "camera/000003.json"):
        assert (a / rel).read_bytes() == (b / rel).read_bytes()
    ann_a, ann_b = (json.loads((x / "annotations.json").read_text()) for x in (a, b))
    assert ann_a.pop("scene") == "a" and ann_b.pop("scene") == "b"  # scenes are named after their folder
    assert ann_a == ann_b
    with np.load(a / "truth/levels/000003.npz") as x, np.load(b / "truth/levels/000003.npz") as y:
        assert all(np.array_equal(x[k], y[k]) for k in x.files)
    assert (a / "camera/000003.json").read_bytes() != (c / "camera/000003.json").read_bytes()


def test_generate_refuses_to_clobber_user_folders(tmp_path):
    user = tmp_path / "mine"
    user.mkdir()
    (user / "notes.txt").write_text("keep me")
    with pytest.raises(InputError, match="not empty"):
        generate("smoke", user, size=24, frames=5)
    with pytest.raises(InputError, match="refusing"):
        generate("smoke", user, size=24, frames=5, overwrite=True)
    assert (user / "notes.txt").read_text() == "keep me"
    out = generate("smoke", tmp_path / "gen", size=24, frames=5)
    with pytest.raises(InputError, match="not empty"):
        generate("smoke", out, size=24, frames=5)
    generate("smoke", out, size=24, frames=6, overwrite=True)
    assert load_truth(out).num_frames == 6
    for bad, field in (({"size": 25}, "size"), ({"frames": 2}, "frames"), ({"layout": "llff"}, "layout"),
                       ({"height": 27}, "height"), ({"size": 24, "height": 200}, "height")):
        with pytest.raises(InputError, match=field):
            generate("smoke", tmp_path / "x", **bad)
    with pytest.raises(InputError, match="did you mean 'split-cookie'"):
        generate("split-cookies", tmp_path / "y")


def test_a_frame_too_large_for_the_memory_is_refused_before_anything_is_rendered(tmp_path, monkeypatch):
    import importlib

    gen = importlib.import_module("benchmark.synthetic.generate")  # the package exports the function by that name
    monkeypatch.setattr(gen, "available_memory_gb", lambda: 1.0)
    # 1024 x 1366 (the HyperNeRF aspect) at 2 KB per pixel: about 2.7 GB
    with pytest.raises(InputError, match=r"size: rendering a 1024x1366 frame needs about 2\.7 GB; 1\.0 GB"):
        generate("smoke", tmp_path / "big", size=1024, frames=4)
    assert not (tmp_path / "big").exists()
    # each rendering process holds a frame: 256 x 342 is 0.17 GB, fits alone, 16 at once need 2.7 GB
    gen._check_memory(256, None, "hypernerf", jobs=1)
    with pytest.raises(InputError, match=r"256x342 frame in each of 16 processes needs about 2\.7 GB"):
        generate("smoke", tmp_path / "many", size=256, frames=16, jobs=16)
    assert not (tmp_path / "many").exists()
    generate("smoke", tmp_path / "small", size=32, frames=4)  # 32 x 42: fits
    monkeypatch.setattr(gen, "available_memory_gb", lambda: float("nan"))  # unknown memory: tried
    generate("smoke", tmp_path / "unknown", size=32, frames=4)


def test_generate_takes_an_image_height_and_the_scene_says_so(tmp_path):
    from benchmark.loaders import load_scene

    default = load_scene(generate("smoke", tmp_path / "default", size=24, frames=5))
    tall = generate("smoke", tmp_path / "tall", size=24, height=44, frames=5)  # the HyperNeRF captures' 536:960
    scene = load_scene(tall)
    assert {(f.camera.width, f.camera.height) for f in scene.frames} == {(24, 44)}
    assert {(f.camera.width, f.camera.height) for f in default.frames} == {(24, 32)}  # the layout's 3:4
    assert json.loads((tall / "bench4d_meta.json").read_text())["height"] == 44
    assert "height" not in json.loads((tmp_path / "default" / "bench4d_meta.json").read_text())
    # the horizontal field of view stays the layout's: the same focal length in x
    assert np.allclose([f.camera.fx for f in scene.frames], default.frames[0].camera.fx)


@pytest.mark.parametrize("layout", ["hypernerf", "neu3d"])
def test_rendering_in_several_processes_writes_the_same_files(tmp_path, layout):
    one = generate("smoke", tmp_path / "one" / "scene", size=24, frames=5, layout=layout, views=3)
    three = generate("smoke", tmp_path / "three" / "scene", size=24, frames=5, layout=layout, views=3, jobs=3)
    files = sorted(p.relative_to(one) for p in one.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(three) for p in three.rglob("*") if p.is_file())
    assert len(files) > 10
    for rel in files:
        assert (one / rel).read_bytes() == (three / rel).read_bytes(), rel
    with pytest.raises(InputError, match="jobs"):
        generate("smoke", tmp_path / "none", size=24, frames=5, jobs=0)


# -- the bench4d data command ------------------------------------------------------------------------
def test_cli_make_validate_show(tmp_path, capsys):
    from benchmark.cli import main

    out = tmp_path / "scene"
    assert main(["data", "make-synthetic", "smoke", "--out", str(out), "--size", "24", "--frames", "6",
                 "--layout", "neu3d", "--views", "3"]) == 0
    text = capsys.readouterr().out
    assert "OK" in text and "max reprojection error" in text
    assert main(["data", "validate", str(out)]) == 0
    sheet = tmp_path / "sheet.png"
    assert main(["data", "show", str(out), "--out", str(sheet), "--frames", "2"]) == 0
    import cv2

    assert cv2.imread(str(sheet)) is not None
    assert main(["data", "presets"]) == 0
    assert "split-cookie" in capsys.readouterr().out

    # a frame name the scene does not have -> a clear error naming the file, exit 2
    doc = json.loads((out / "annotations.json").read_text())
    doc["images"][0]["file_name"] = "cam07_0000"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    assert main(["data", "validate", str(out), "--annotations", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.json" in err and "cam07_0000" in err
    # a time segment past the end of the video
    doc = json.loads((out / "annotations.json").read_text())
    key = next(iter(doc["time_segments"]))
    doc["time_segments"][key] = [[0, 99]]
    bad.write_text(json.dumps(doc))
    assert main(["data", "validate", str(out), "--annotations", str(bad)]) == 2
    assert "99" in capsys.readouterr().err


def test_dynamic_parts_are_the_ones_the_preset_animates(scene_dirs, tmp_path):
    from benchmark.core.errors import InputError
    from benchmark.synthetic.dynamic import dynamic_masks, dynamic_parts

    # smoke: the lid opens on its hinge (panel and knob), the ball rolls, the bar breaks; the box base stays
    root = scene_dirs("smoke", "neu3d")
    assert sorted(dynamic_parts(root).values()) == ["ball", "bar half", "bar half", "lid knob", "lid panel"]
    truth = load_truth(root)
    names = sorted(truth.frames)
    masks = dynamic_masks(root, names)
    for name in names:
        assert not (masks[name] & truth.mask("box base", name, allow_eval=True)).any()
        assert (masks[name] >= truth.mask("ball", name, allow_eval=True)).all()
    # a fixed rig camera sees the box base at the same pixels all video long wherever nothing moves over it
    by_cam = [n for n in names if truth.frames[n].camera_id == truth.frames[names[0]].camera_id]
    first, last = by_cam[0], by_cam[-1]
    base = [truth.mask("box base", n, allow_eval=True) for n in (first, last)]
    free = ~(masks[first] | masks[last])
    assert np.array_equal(base[0] & free, base[1] & free)
    # the moving parts do move: their pixels differ between the first and last frame of that camera
    assert not np.array_equal(masks[first], masks[last])
    # espresso: the coffee stream and the coffee appear; the machine around them does not move
    assert set(dynamic_parts(scene_dirs("espresso", "hypernerf")).values()) == {"coffee stream", "espresso"}
    with pytest.raises(InputError, match="not a generated scene"):
        dynamic_parts(tmp_path)
