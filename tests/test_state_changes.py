"""State changes of the time-sensitive presets (gradual, back and forth) and the noise of the oracle captions
(:mod:`benchmark.synthetic.state_changes`, :mod:`benchmark.core.caption_noise`, the ``template`` captioner)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from annotations.format import load_annotations
from benchmark.core.caption_noise import CAPTION_NOISE, CaptionNoise
from benchmark.core.errors import InputError
from benchmark.synthetic import PRESETS, generate, load_truth
from benchmark.synthetic.generate import preset_rng
from benchmark.synthetic.model import Catalogue, FrameContext
from benchmark.synthetic.state_changes import STATE_CHANGES, alternating_boundaries


def _timelines(preset: str, frames: int, seed: int = 0, level=None):
    scene = PRESETS[preset].build(preset_rng(preset, seed), frames, level)
    return [tl for _, tl in Catalogue.build(scene.wholes).timelines()]


def _query_timelines(spec) -> bool:
    return any(st.query for tl in _timelines(spec.name, spec.default_frames) for st in tl.states)


def _changing(tl, n: int) -> list[int]:
    """Frames whose visual variable is strictly between its two states (a transition under way)."""
    first, second = tl.states[tl.sequence[0]].key, next(tl.states[s].key for s in tl.sequence if s != tl.sequence[0])
    values = [tl.value(FrameContext(t, n), {first: 0.0, second: 1.0}) for t in range(n)]
    return [t for t, v in enumerate(values) if 0.02 < v < 0.98]


@pytest.fixture(scope="module")
def generated(tmp_path_factory):
    """(preset, frames) -> a tiny generated scene at its default levels, made on first use."""
    root = tmp_path_factory.mktemp("state-changes")
    made: dict[tuple, Path] = {}

    def get(preset: str, frames: int) -> Path:
        if (preset, frames) not in made:
            made[(preset, frames)] = generate(preset, root / f"{preset}-{frames}", size=16, frames=frames)
        return made[(preset, frames)]

    return get


# -- levels of the presets ------------------------------------------------------------------------------
def test_the_paper_presets_with_time_queries_change_gradually_or_back_and_forth_with_mllm_captions():
    paper = [spec for spec in PRESETS.values() if spec.time_sensitive and spec.analogue.startswith("hypernerf/")]
    assert len(paper) == 4 and all(_query_timelines(spec) for spec in paper)
    assert {spec.state_changes for spec in paper} == {"gradual", "back-and-forth"}
    assert all(spec.caption_noise == "mllm" for spec in paper)
    # the other presets keep their own schedule and clean captions
    for spec in PRESETS.values():
        if spec not in paper:
            assert spec.state_changes is None and spec.caption_noise == "clean"
    with pytest.raises(InputError, match="fixed schedule"):
        PRESETS["torchocolate"].build(preset_rng("torchocolate", 0), 20, "gradual")
    with pytest.raises(InputError, match="valid: switch"):
        PRESETS["americano"].build(preset_rng("americano", 0), 20, "sudden")


@pytest.mark.parametrize("level", list(STATE_CHANGES))
def test_a_state_holds_from_the_first_frame_past_the_midpoint_of_its_transition(level):
    """The ground truth's rule (the annotations' intervals are the timeline's segments): the visual variable is
    past half of the change exactly on the frames labelled with the new state, for any length and seed."""
    for spec in (s for s in PRESETS.values() if s.state_changes is not None):
        for frames in (4, 7, 10, 33, 60, 150):
            for seed in range(4):
                for tl in _timelines(spec.name, frames, seed, level):
                    keys = {tl.states[tl.sequence[0]].key: 0.0}
                    keys.update({s.key: 1.0 for s in tl.states if s.key not in keys})
                    later = [tl.value(FrameContext(t, frames), keys) > 0.5 for t in range(frames)]
                    labels = [keys[tl.state_at(t).key] == 1.0 for t in range(frames)]
                    assert later == labels, (spec.name, level, frames, seed)


def test_gradual_changes_take_many_frames_and_back_and_forth_returns_to_the_first_state():
    n = 60
    for spec in (s for s in PRESETS.values() if s.state_changes is not None):
        switch = _timelines(spec.name, n, 0, "switch")[0]
        gradual = _timelines(spec.name, n, 0, "gradual")[0]
        back = _timelines(spec.name, n, 0, "back-and-forth")[0]
        assert len(gradual.boundaries) == 1 and len(_changing(gradual, n)) >= 0.2 * n
        assert len(_changing(gradual, n)) > 1.5 * len(_changing(switch, n)) / len(switch.boundaries)
        # there, back, and there again: the first state holds twice, each state once per stay
        assert len(back.boundaries) == 3 and back.sequence[0] == back.sequence[2] != back.sequence[1] == back.sequence[3]
        assert len(_changing(back, n)) >= 3 * 0.08 * n
        for tl in (gradual, back):  # every state is held fully at both ends of the video
            keys = {tl.states[tl.sequence[0]].key: 0.0, tl.states[tl.sequence[1]].key: 1.0}
            assert tl.value(FrameContext(0, n), keys) == 0.0
            assert tl.value(FrameContext(n - 1, n), keys) in (0.0, 1.0)
    # the default levels: gradual on two presets, back and forth on two
    defaults = [_timelines(s.name, n)[0] for s in PRESETS.values() if s.state_changes is not None]
    assert sorted(len(tl.boundaries) for tl in defaults) == [1, 1, 3, 3]


def test_levels_change_the_states_only():
    """The same preset and seed at two levels: the same objects, placements and camera path (the random
    stream after the scene is built is where the switch level leaves it)."""
    for spec in (s for s in PRESETS.values() if s.state_changes is not None):
        scenes = {}
        for level in STATE_CHANGES:
            rng = preset_rng(spec.name, 3)
            scene = spec.build(rng, 40, level)
            scenes[level] = (scene, rng.random(4))
        names = {lv: [e.name for e in Catalogue.build(s.wholes).entries["subpart"]] for lv, (s, _) in scenes.items()}
        assert len({tuple(v) for v in names.values()}) == 1
        after = [draws for _, draws in scenes.values()]
        assert all(np.array_equal(after[0], a) for a in after[1:])
        boundaries = {lv: _timelines(spec.name, 40, 3, lv)[0].boundaries for lv in STATE_CHANGES}
        assert len(set(boundaries.values())) == len(STATE_CHANGES)


def test_alternating_boundaries_keep_ramps_apart_and_fit_short_videos():
    rng = np.random.default_rng(0)
    for n in range(2, 80):
        for changes in (1, 3, 6):
            bounds, ramp = alternating_boundaries(rng, n, changes, 0.2 * n, 0.05 * n)
            assert len(bounds) == min(changes, n - 1) and all(0 < b < n for b in bounds)
            assert all(b - a >= ramp for a, b in zip(bounds, bounds[1:]))  # no two ramps overlap
            assert bounds[0] - 0.5 - ramp / 2 >= -1e-9 or ramp == 1.0
    draws = {alternating_boundaries(np.random.default_rng(s), 60, 3, 7.2, 3.6)[0] for s in range(10)}
    assert len(draws) > 5  # changes at varied times across seeds


def test_generated_scene_records_its_levels_and_annotates_the_midpoint_rule(generated):
    root = generated("espresso", 24)
    truth = load_truth(root)
    assert truth.doc["state_changes"] == "gradual" and truth.doc["caption_noise"] == "mllm"
    assert json.loads((root / "bench4d_meta.json").read_text())["state_changes"] == "gradual"
    (tl,) = _timelines("espresso", 24)
    ann = load_annotations(root / "annotations.json")
    sensitive = {q.text: [tuple(iv) for iv in q.intervals] for q in ann.queries if q.kind == "sensitive"}
    assert sensitive == {s.phrase: tl.intervals()[s.key] for s in tl.states}
    # a preset without levels records none, and clean captions are not written at all (older scenes read the same)
    smoke = load_truth(generate("smoke", root.parent / "smoke", size=16, frames=6))
    assert "state_changes" not in smoke.doc and "caption_noise" not in smoke.doc


# -- caption noise -----------------------------------------------------------------------------------------
def _captioner(root: Path, **options):
    from benchmark.loaders import load_scene
    from methods.captioners import get_captioner

    scene = load_scene(root)
    return scene, get_captioner("template", scene, **options)


def _state_of_caption(truth, node: str) -> dict[str, str]:
    return {c: st["state"] for s in truth.timelines(allow_eval=True) if s["object"] == node
            for st in s["states"] for c in st["captions"]}


def test_mllm_captions_lag_the_change_and_name_another_state_at_the_stated_rate(generated):
    from methods.captioners.base import caption_objects
    from methods.captioners.tracks import truth_tracks

    root = generated("chickchicken", 60)
    scene, cap = _captioner(root)  # the level the scene declares: mllm
    assert cap.noise == CAPTION_NOISE["mllm"] and cap.config()["noise"]["wrong_state_rate"] == 0.15
    lag = cap.noise.lag_steps(60)
    assert lag == 3
    train = sorted({f.time_index for f in scene.train_frames})
    for t in train:
        assert cap.lagged_time(t) == max([u for u in train if u <= t - lag] or [train[0]])
    # the wrong-state rate, over many draws at one training time
    rng = np.random.default_rng(1)
    states = [cap.described_state("toy egg", train[10], rng)["state"] for _ in range(4000)]
    lagged = cap.truth.state_at("toy egg", cap.lagged_time(train[10]))["state"]
    assert abs(np.mean([s != lagged for s in states]) - 0.15) < 0.02
    # the captions of the scene: each describes a state its training frames show; right on most frames, and
    # wrong on the frames just after a change more often than elsewhere (the lag)
    tracks = truth_tracks(scene)
    egg = next(o for o, name in tracks.labels.items() if name == "toy egg")
    made = caption_objects(cap, scene, tracks)
    state_of = _state_of_caption(cap.truth, "toy egg")
    (timeline,) = [s for s in cap.truth.timelines(allow_eval=True) if s["object"] == "toy egg"]
    changes = sorted(a for st in timeline["states"] for a, _ in st["intervals"] if a > 0)
    right, just_after = [], []
    for f in scene.train_frames:
        if (f.name, egg) not in made.frames:
            continue
        said = state_of[made.frames[(f.name, egg)]]
        ok = said == cap.truth.state_at("toy egg", f.time_index)["state"]
        (just_after if any(0 <= f.time_index - b < lag for b in changes) else right).append(ok)
    assert 0.7 < np.mean(right) < 1.0 and just_after and np.mean(just_after) < 0.5
    # seeded: the same captions again, other captions for another seed
    assert caption_objects(_captioner(root)[1], scene, tracks).frames == made.frames
    assert caption_objects(_captioner(root, seed=4)[1], scene, tracks).frames != made.frames


def test_clean_captions_are_a_named_option_and_describe_the_frame_s_own_state(generated):
    from methods.captioners.base import caption_objects
    from methods.captioners.tracks import truth_tracks

    root = generated("chickchicken", 60)
    scene, cap = _captioner(root, noise="clean")
    assert "noise" not in cap.config()  # clean captions keep the cache keys they had before levels existed
    tracks = truth_tracks(scene)
    made = caption_objects(cap, scene, tracks)
    state_of = _state_of_caption(cap.truth, "toy egg")
    egg = next(o for o, name in tracks.labels.items() if name == "toy egg")
    frames = {f.name: f for f in scene.train_frames}
    said = [(state_of[text], cap.truth.state_at("toy egg", frames[name].time_index)["state"])
            for (name, obj), text in made.frames.items() if obj == egg]
    assert said and all(a == b for a, b in said)
    assert len({text for (name, obj), text in made.frames.items() if obj == egg}) >= 8  # paraphrases vary
    with pytest.raises(InputError, match="valid: clean, mllm"):
        _captioner(root, noise="noisy")


def test_caption_noise_levels_and_the_method_option():
    from methods import registry

    assert CAPTION_NOISE["clean"].is_clean and not CAPTION_NOISE["mllm"].is_clean
    with pytest.raises(ValueError):
        CaptionNoise("bad", wrong_state_rate=1.5, lag_fraction=0.0)
    spec = registry.get("4d-langsplat")
    assert spec.make_config({}).captions.noise == "scene"
    assert spec.make_config({"captions.noise": "clean"}).captions.noise == "clean"
    with pytest.raises(InputError, match="noise"):
        spec.make_config({"captions.noise": "loud"})
