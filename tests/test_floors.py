"""The 2D floors: the view they answer from (viewing angle and time), ``nearest-frame`` answering through the
protocol's query rule and replaying captions, ``nearest-frame-masks`` selecting a mask."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmark.core.protocol import PROTOCOLS
from benchmark.core.scene import Camera, Frame


def _camera_looking(azimuth_deg: float) -> Camera:
    """A camera on the unit circle of the xz-plane looking at the origin along ``(sin a, 0, cos a)``."""
    a = math.radians(azimuth_deg)
    forward = np.array([math.sin(a), 0.0, math.cos(a)])
    down = np.array([0.0, 1.0, 0.0])
    right = np.cross(down, forward)
    rotation = np.stack([right, down, forward])  # rows: the camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = rotation
    w2c[:3, 3] = -rotation @ (-forward)  # centre one unit behind the origin along the viewing direction
    return Camera(width=8, height=6, fx=8.0, fy=8.0, cx=4.0, cy=3.0, world_to_camera=w2c)


def _frame(name: str, azimuth_deg: float, time: float, split: str = "test") -> Frame:
    return Frame(name=name, camera=_camera_looking(azimuth_deg), time=time, time_index=int(round(time * 10)),
                 split=split)


def test_the_nearest_view_weighs_viewing_angle_against_time_steps():
    from methods.nearest_frame import NearestView, view_direction

    views = [_frame("a", 0.0, 0.0, "train"), _frame("b", 30.0, 0.1, "train"), _frame("c", 60.0, 0.2, "train")]
    times = np.array([f.time for f in views])
    directions = np.stack([view_direction(f.camera) for f in views])
    assert np.allclose(directions[1], [math.sin(math.radians(30)), 0.0, math.cos(math.radians(30))])
    step = NearestView.time_step_of(times)
    assert step == pytest.approx(0.1)
    query = _frame("q", 35.0, 0.0)  # 35 degrees from a at its time; 5 degrees from b one step later
    default = NearestView(times, directions, step, time_weight=0.1)
    assert default.distances(query) == pytest.approx([math.radians(35), math.radians(5) + 0.1,
                                                      math.radians(25) + 0.2])
    assert default.nearest(query) == 1  # the angle decides: one step costs 0.1 rad
    assert NearestView(times, directions, step, time_weight=1.0).nearest(query) == 0  # time decides
    assert NearestView(times, directions, step, time_weight=0.0).nearest(_frame("r", 58.0, 0.0)) == 2
    # every training view is nearest to itself
    assert [default.nearest(f) for f in views] == [0, 1, 2]


def _numpy_relevance(features: np.ndarray, query: np.ndarray, canon: np.ndarray, temperature: float) -> np.ndarray:
    """LERF relevance of unit rows ``features`` (M, D): min over phrases of the pairwise softmax."""
    sim_q = features @ query
    sim_c = features @ canon.T
    pairwise = np.exp(temperature * sim_q[:, None]) / (np.exp(temperature * sim_q[:, None])
                                                       + np.exp(temperature * sim_c))
    return pairwise.min(axis=1)


@pytest.fixture(scope="module")
def fitted(smoke_base):
    from benchmark.loaders import load_scene
    from methods.api import Progress
    from methods.nearest_frame import NearestFrame, NearestFrameMasks
    from methods.specs.nearest_frame import NearestFrameConfig, NearestFrameMasksConfig
    from methods.supervision.cache import build_supervision

    scene = load_scene(smoke_base["scene"])
    sup = build_supervision(scene, "oracle", cache_dir=smoke_base["cache"])
    quiet = Progress(True)
    floor = NearestFrame.fit(scene, sup, NearestFrameConfig(), seed=0, device="cpu", progress=quiet)
    masks = NearestFrameMasks.fit(scene, sup, NearestFrameMasksConfig(), seed=0, device="cpu", progress=quiet)
    return scene, sup, floor, masks


@pytest.mark.parametrize("protocol", ["release", "paper-text"])
def test_the_floor_answers_through_the_protocols_rule_on_its_painted_relevance(fitted, protocol):
    from methods.fields.relevance import answer_from_relevance
    from methods.supervision.base import LEVELS

    scene, sup, floor, _ = fitted
    rules = PROTOCOLS[protocol]
    floor.use_protocol(rules)
    encoder = sup.text_encoder
    canon = encoder.encode(list(rules.agnostic.canonical_phrases), kind="query")
    checked = 0
    for frame in scene.test_frames[:2]:
        index = floor.nearest(frame)
        view = sup.frame(floor.names[index])
        for text in ("box", "ball", "bar"):
            query = encoder.encode([text], kind="query")[0]
            painted = np.zeros((len(LEVELS), frame.camera.height, frame.camera.width), np.float32)
            for level in range(len(LEVELS)):
                ids = view.levels[level]  # the smoke preset's supervision is at the frames' size
                rel = _numpy_relevance(np.asarray(view.features[level]), query, canon, rules.agnostic.temperature)
                painted[level][ids >= 0] = rel[ids[ids >= 0]]
            # what the floor paints is the view's masks' relevance (to float rounding) ...
            assert np.allclose(floor.painted_relevance(text, frame).numpy(), painted, atol=1e-5), (frame.name, text)
            # ... and what it answers is the protocol's rule on that map (levels whose peaks tie to float
            # rounding - one object's feature at several levels - are chosen as the rule chooses on its map)
            expected = answer_from_relevance(floor.painted_relevance(text, frame), rules.agnostic)
            answer = floor.query_agnostic(text, [frame])[0]
            assert np.array_equal(answer.mask, expected.mask.numpy()), (frame.name, text)
            assert np.allclose(answer.relevance, expected.relevance.numpy(), atol=1e-5)
            checked += int(expected.mask.any())
    assert checked >= 3  # the rule found something to answer


def test_the_mask_selection_floor_answers_with_one_mask_of_its_view(fitted):
    scene, sup, floor, masks = fitted
    masks.use_protocol(PROTOCOLS["release"])
    frame = scene.test_frames[0]
    view = sup.frame(masks.names[masks.nearest(frame)])
    answer = masks.query_agnostic("ball", [frame])[0]
    assert answer.mask.any()
    assert any(np.array_equal(answer.mask, view.levels[level] == m)
               for level in range(3) for m in range(view.num_masks(level)))  # exactly one supervised mask
    # the relevance floor's answer is a thresholded, filtered map: not always one mask of the view
    assert floor.query_agnostic("ball", [frame])[0].mask.shape == answer.mask.shape


def test_the_floor_replays_the_nearest_views_captions_for_time_sensitive_queries(fitted, tmp_path):
    from methods.captioners.supervision import build_captions, embed_captions
    from methods.fields.relevance import spatial_mask
    from methods.nearest_frame import NearestFrame
    from methods.specs._time_varying import CaptionConfig

    scene, sup, floor, _ = fitted
    floor.use_protocol(PROTOCOLS["release"])
    assert floor.supports == {"agnostic", "sensitive"} and floor.describe()["caption_replay"]
    captions, tracks = build_captions(scene, "oracle", CaptionConfig(), supervision=sup)
    embedded = embed_captions(captions, tracks, sup.text_encoder)
    scores = []
    for frame in scene.test_frames:
        spatial = floor.agnostic("open box", frame)  # the protocol's spatial mask: the query text's own answer
        view = floor.names[floor.nearest(frame)]
        ids = tracks.ids[tracks.index(view)][spatial_mask(spatial, floor.protocol.sensitive).numpy()]
        rows = [embedded.text_index[(view, int(obj))] for obj in ids[ids >= 0]]
        query = sup.text_encoder.encode(["open box"], kind="query")[0]
        expected = float(np.mean(embedded.embeddings[rows] @ query)) if rows else float("nan")
        score = floor.query_sensitive("open box", [frame])[0].score
        assert score == pytest.approx(expected, abs=1e-5) or (math.isnan(score) and math.isnan(expected))
        scores.append(score)
    assert len({round(s, 4) for s in scores if not math.isnan(s)}) >= 2  # the captions change over time
    # saved and loaded, it answers the same
    floor.save(tmp_path)
    again = NearestFrame.load(tmp_path, supervision=sup, device="cpu")
    again.use_protocol(PROTOCOLS["release"])
    frame = scene.test_frames[-1]
    assert again.query_sensitive("open box", [frame])[0].score == pytest.approx(
        floor.query_sensitive("open box", [frame])[0].score, nan_ok=True)


def test_without_captions_the_floor_answers_time_agnostic_queries_only(fitted):
    from methods.api import Progress
    from methods.nearest_frame import NearestFrame
    from methods.specs.nearest_frame import NearestFrameConfig

    scene, sup, _, _ = fitted
    off = NearestFrame.fit(scene, sup, NearestFrameConfig(replay="off"), seed=0, device="cpu", progress=Progress(True))
    assert off.supports == {"agnostic"} and not off.describe()["caption_replay"]
    with pytest.raises(NotImplementedError):
        off.query_sensitive("open box", scene.test_frames[:1])
