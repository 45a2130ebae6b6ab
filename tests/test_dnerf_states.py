"""D-NeRF on the oracle track: captions from the annotation's time segments at the TRAINING frames only, so the
time-varying heads and the caption-replay floor answer its time-sensitive queries."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from benchmark.core.annotation import AnnotatedFrame, AnnotationSet, Query
from benchmark.core.errors import InputError

OBJECT = "ball"


def _write_rgba_split(root, split: str, frames: int) -> None:
    """A D-NeRF split of a ball moving left to right: RGBA frames whose alpha is the ball (one static camera,
    ``time = t / (frames - 1)``)."""
    from annotations.tool.synthetic import rigid_sequence
    from benchmark.core.atomic import write_json
    from benchmark.core.imageio import write_image

    seq = rigid_sequence(frames, 40, 32, seed=3, travel_frac=0.3, radius_frac=0.2)
    (root / split).mkdir(parents=True, exist_ok=True)
    records = []
    for t, (image, mask) in enumerate(zip(seq.images, seq.masks)):
        write_image(root / split / f"r_{t:03d}.png", np.dstack([image, np.where(mask, 255, 0).astype(np.uint8)]))
        c2w = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0], [0.0, 0.0, 0.0, 1.0]]
        records.append({"file_path": f"./{split}/r_{t:03d}", "time": t / (frames - 1), "transform_matrix": c2w})
    write_json(root / f"transforms_{split}.json", {"camera_angle_x": 0.69, "frames": records})


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A D-NeRF-layout scene: 9 training frames and 6 test frames, some at times no training frame has."""
    from benchmark.loaders import load_scene

    root = tmp_path_factory.mktemp("dnerf") / "ball"
    _write_rgba_split(root, "test", 6)
    _write_rgba_split(root, "train", 9)
    return load_scene(root)


@dataclasses.dataclass
class _AskedQuery(Query):
    """A query that notes every time index its segments are asked about."""

    asked: list = dataclasses.field(default_factory=list)

    def holds_at(self, time_index: int) -> bool:
        self.asked.append(int(time_index))
        return super().holds_at(time_index)


def _annotations(scene) -> AnnotationSet:
    last = max(f.time_index for f in scene.frames)
    frames = [AnnotatedFrame(id=i + 1, name=f.name, time_index=f.time_index, width=f.camera.width,
                             height=f.camera.height) for i, f in enumerate(scene.test_frames)]
    queries = [Query(1, OBJECT, "agnostic", level="whole"),
               _AskedQuery(2, "ball on the left", "sensitive", base=1, intervals=[(0, last // 4)]),
               _AskedQuery(3, "ball on the right", "sensitive", base=1, intervals=[(2 * last // 3, last)])]
    return AnnotationSet(scene="blob", frames=frames, queries=queries, num_time_steps=last + 1)


def test_training_states_ask_the_time_segments_about_training_frames_only(scene):
    from methods.api import training_states

    aset = _annotations(scene)
    states = training_states(scene, aset)
    train = {f.name: f.time_index for f in scene.train_frames}
    assert set(states) == set(train)
    test_only = {f.time_index for f in scene.test_frames} - set(train.values())
    assert test_only  # the split has times no training frame has
    for query in aset.sensitive_queries:
        assert set(query.asked) == set(train.values()), query.text  # never an evaluated frame's time
        for name, index in train.items():
            assert (query.text in states[name]) == query.holds_at(index)
    assert any(held == [] for held in states.values())  # between the two segments: no state
    assert training_states(scene, AnnotationSet(scene="blob", queries=[Query(1, OBJECT)])) == {}


def test_supervision_refuses_states_of_an_evaluated_frame(scene, tmp_path):
    from methods.supervision.cache import build_supervision

    sources = {"segmenter": "alpha", "image_text": "object-name"}
    options = {"image_text": {"object_name": OBJECT}}
    with pytest.raises(InputError, match="not a training frame"):
        build_supervision(scene, "oracle", cache_dir=tmp_path, sources=sources, source_options=options,
                          states={scene.test_frames[0].name: ["ball on the left"]})
    plain = build_supervision(scene, "oracle", cache_dir=tmp_path, sources=sources, source_options=options)
    held = build_supervision(scene, "oracle", cache_dir=tmp_path, sources=sources, source_options=options,
                             states={scene.train_frames[0].name: ["ball on the left"]})
    assert plain.states == {} and held.states == {scene.train_frames[0].name: ("ball on the left",)}
    assert held.fingerprint != plain.fingerprint  # fits on other captions are other fits


def test_the_runner_hands_the_states_of_training_frames_to_the_supervision(scene, tmp_path, monkeypatch):
    from benchmark import runner
    from methods.api import Progress

    aset = _annotations(scene)
    options = runner.EvalOptions(method="nearest-frame", scene=str(scene.root), cache_dir=tmp_path,
                                 results_dir=tmp_path / "results")
    sup = runner._run_supervision(options, scene, aset, Progress(True))
    assert sup.sources["image_text"] == "object-name"
    assert set(sup.states) == {f.name for f in scene.train_frames}
    assert {t for held in sup.states.values() for t in held} == {"ball on the left", "ball on the right"}


def test_states_caption_the_alpha_object_and_the_heads_and_the_floor_answer_time_queries(scene, tmp_path):
    from benchmark.core.protocol import PROTOCOLS
    from methods.api import Progress, training_states
    from methods.captioners import captioning_unavailable
    from methods.captioners.states import StatesCaptioner
    from methods.captioners.supervision import build_captions
    from methods.nearest_frame import NearestFrame
    from methods.specs._time_varying import CaptionConfig
    from methods.specs.nearest_frame import NearestFrameConfig
    from methods.supervision.cache import build_supervision
    from methods.supervision.truth_access import EvaluatedFrameTruthError

    states = training_states(scene, _annotations(scene))
    sup = build_supervision(scene, "oracle", cache_dir=tmp_path, sources={"segmenter": "alpha",
                            "image_text": "object-name"}, source_options={"image_text": {"object_name": OBJECT}},
                            states=states)
    assert captioning_unavailable(CaptionConfig(), scene, sup) == ""
    without = build_supervision(scene, "oracle", cache_dir=tmp_path, sources={"segmenter": "alpha",
                                "image_text": "object-name"}, source_options={"image_text": {"object_name": OBJECT}})
    assert "no generator truth" in captioning_unavailable(CaptionConfig(), scene, without)

    captions, tracks = build_captions(scene, "oracle", CaptionConfig(), supervision=sup, cache_root=tmp_path)
    assert captions.captioner == "states" and tracks.source == "alpha" and tracks.objects() == [0]
    train = {f.name: f for f in scene.train_frames}
    assert {name for name, _ in captions.frames} <= set(train)
    for (name, obj), text in captions.frames.items():
        assert text == ("; ".join(states[name]) or OBJECT)
        assert np.array_equal(tracks.ids[tracks.index(name)] == 0, train[name].alpha().astype(bool))
    assert {"ball on the left", "ball on the right", OBJECT} <= set(captions.texts())
    with pytest.raises(EvaluatedFrameTruthError):
        StatesCaptioner(scene, states={**states, scene.test_frames[0].name: ["ball on the left"]}, object_name=OBJECT)
    with pytest.raises(EvaluatedFrameTruthError):
        StatesCaptioner(scene, states=states, object_name=OBJECT).caption_frame(0, scene.test_frames[0], [],
                                                                                description=None)

    floor = NearestFrame.fit(scene, sup, NearestFrameConfig(), seed=0, device="cpu", progress=Progress(True))
    floor.use_protocol(PROTOCOLS["release"])
    assert floor.supports == {"agnostic", "sensitive"} and floor.describe()["captioner"] == "states"
    early, late = scene.test_frames[0], scene.test_frames[-1]
    left = [floor.query_sensitive("ball on the left", [f])[0].score for f in (early, late)]
    right = [floor.query_sensitive("ball on the right", [f])[0].score for f in (early, late)]
    assert left[0] > left[1] and right[1] > right[0]  # the replayed state follows the time segments
