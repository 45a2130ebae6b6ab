"""The real track end to end on tiny random models of the real classes, on a scene in the release's layout.

The scene is the ``smoke`` preset (HyperNeRF folders) with its ground truth written only as the 4D LangSplat
release ships it (Roboflow COCO + ``video_annotations.json``) and its generator truth removed, so nothing
but the real models can supervise it. The models are randomly initialised: what they say is noise, and the
run checks the flow (every stage runs, caches, resumes), never a score.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from conftest import tiny_clip_model, tiny_sam_model, keep_paper_split
import torch

from benchmark.core.annotation import decode_mask
from benchmark.core.errors import InputError

TINY_SCHEDULE = {
    "geometry.static_iterations": "20", "geometry.deformation_iterations": "20",
    "autoencoder.min_steps": "20", "autoencoder.max_steps": "20", "autoencoder.epochs": "1",
    "field.iterations": "20", "field.log_every": "10",
    "caption_autoencoder.min_steps": "20", "caption_autoencoder.max_steps": "20",
    "caption_autoencoder.epochs": "1",
    "status.static_iterations": "10", "status.iterations": "20", "status.fit": "on",
}
"""4d-langsplat at a few steps per stage: enough to run every stage, far too few to learn anything."""

RANDOM_SAM_FILTERS = {"points_per_side": 3, "pred_iou_thresh": -1e9, "stability_score_thresh": 0.0,
                      "min_mask_region_area": 0, "nms_score_thresh": -1.0, "nms_iou_thresh": 1.0}
"""SAM's mask filters opened wide: a random SAM's masks would otherwise all be dropped."""


# ---------------------------------------------------------------------------------------------
# the scene in the release's layout
# ---------------------------------------------------------------------------------------------
def release_layout_scene(folder):
    """The smoke preset at ``folder``: HyperNeRF folders, the release's annotation files in
    ``annotations/``, no bench4d annotation file and no generator truth. Returns the bench4d
    annotation set the release files were written from."""
    from annotations.format import load_annotations
    from annotations.release import export_release
    from benchmark.synthetic.generate import generate

    generate("smoke", folder, size=48)
    aset = load_annotations(folder / "annotations.json")
    keep_paper_split(aset)  # the release annotates one camera: the video's, not the novel-view path
    export_release(aset, folder / "annotations", frame_base=1)
    (folder / "annotations.json").unlink()
    shutil.rmtree(folder / "truth")
    return aset


@pytest.fixture(scope="module")
def release_scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("release") / "smoke"
    return folder, release_layout_scene(folder)


def test_release_annotations_beside_a_scene_are_found_and_read_as_shipped(release_scene):
    from benchmark.loaders import load_scene
    from benchmark.runner import find_annotations

    folder, written = release_scene
    assert not (folder / "annotations.json").exists()
    scene = load_scene(folder)
    found = find_annotations(scene)
    assert found.info["path"].endswith("_annotations.coco.json")
    assert sorted(q.text for q in found.queries) == sorted(q.text for q in written.queries)
    assert {f.name for f in found.frames} == {f.name for f in written.frames}
    by_text = {q.text: q for q in written.queries}
    for q in found.sensitive_queries:
        assert q.intervals == by_text[q.text].intervals
    for (qid, fid), rle in written.masks.items():
        text = written.query(qid).text
        frame = next(f.name for f in written.frames if f.id == fid)
        other_q = next(q.id for q in found.queries if q.text == text)
        other_f = next(f.id for f in found.frames if f.name == frame)
        assert np.array_equal(decode_mask(found.masks[(other_q, other_f)]), decode_mask(rle))
    # the folder, or its COCO file, given explicitly
    assert len(find_annotations(scene, folder / "annotations").queries) == len(found.queries)
    coco = folder / "annotations" / "train" / "_annotations.coco.json"
    assert len(find_annotations(scene, coco).queries) == len(found.queries)
    with pytest.raises(InputError, match="not a release annotation folder"):
        find_annotations(scene, folder / "camera")


# ---------------------------------------------------------------------------------------------
# tiny random models of the real classes
# ---------------------------------------------------------------------------------------------

def tiny_qwen2vl(folder):
    from methods.captioners.qwen2vl import tiny_random_components

    model, tokenizer, processor = tiny_random_components(0)
    model.save_pretrained(folder)
    tokenizer.save_pretrained(folder)
    processor.save_pretrained(folder)
    return folder


def tiny_e5_mistral(folder):
    """A sentence-transformers folder of a tiny random MistralModel, laid out as e5-mistral-7b-instruct's
    (last-token pooling, normalised, its named query prompt)."""
    from sentence_transformers import SentenceTransformer
    from sentence_transformers.sentence_transformer.modules import Normalize, Pooling, Transformer
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import MistralConfig, MistralModel, PreTrainedTokenizerFast

    from methods.text_encoders import E5_MISTRAL_QUERY_PROMPT, E5_MISTRAL_QUERY_PROMPT_NAME

    words = "instruct given a news summary retrieve other similar summaries query the lid is open closed box".split()
    vocab = {w: i for i, w in enumerate(["<unk>", "<s>", "</s>", *words])}
    backend = Tokenizer(models.WordLevel(vocab=vocab, unk_token="<unk>"))
    backend.pre_tokenizer = pre_tokenizers.Whitespace()
    PreTrainedTokenizerFast(tokenizer_object=backend, unk_token="<unk>", bos_token="<s>", eos_token="</s>",
                            pad_token="</s>").save_pretrained(folder / "hf")
    torch.manual_seed(0)
    MistralModel(MistralConfig(vocab_size=len(vocab), hidden_size=16, intermediate_size=32, num_hidden_layers=1,
                               num_attention_heads=2, num_key_value_heads=1, max_position_embeddings=64,
                               pad_token_id=2)).save_pretrained(folder / "hf")
    modules = [Transformer(str(folder / "hf"), max_seq_length=64), Pooling(16, pooling_mode="lasttoken"), Normalize()]
    SentenceTransformer(modules=modules, prompts={E5_MISTRAL_QUERY_PROMPT_NAME: E5_MISTRAL_QUERY_PROMPT}).save(
        str(folder / "st"))
    return folder / "st"


def test_e5_mistral_encoder_on_a_tiny_random_mistral(tmp_path):
    from methods.text_encoders import E5_MISTRAL_QUERY_PROMPT, e5_mistral

    encoder = e5_mistral(str(tiny_e5_mistral(tmp_path)))
    assert encoder.dim == 16 and encoder.config()["query_prompt"] == E5_MISTRAL_QUERY_PROMPT
    passages = encoder.encode(["the lid is open", "closed box"], kind="passage")
    assert passages.shape == (2, 16) and np.allclose(np.linalg.norm(passages, axis=1), 1.0, atol=1e-5)
    query = encoder.encode(["the lid is open"], kind="query")
    assert not np.allclose(query[0], passages[0]), "queries carry the instruction prompt, passages do not"


@pytest.fixture(scope="module")
def tiny_models(tmp_path_factory):
    root = tmp_path_factory.mktemp("models")
    return {"BENCH4D_CLIP": tiny_clip_model(root / "clip"), "BENCH4D_SAM": tiny_sam_model(root / "sam"),
            "BENCH4D_QWEN2VL": tiny_qwen2vl(root / "qwen2vl")}


def test_real_track_runs_every_stage_on_tiny_models_and_resumes_from_the_caches(release_scene, tiny_models,
                                                                               tmp_path, monkeypatch):
    from benchmark.runner import EvalOptions, evaluate

    folder, written = release_scene
    for name, path in tiny_models.items():
        monkeypatch.setenv(name, str(path))
    # no tracks file: the captioned objects are the segmenter's ids followed over time
    options = dict(TINY_SCHEDULE, **{"captions.captioner": "qwen2-vl", "captions.min_track_frames": "1"})

    def run():
        return evaluate(EvalOptions(method="4d-langsplat", scene=str(folder), track="real",
                                    results_dir=tmp_path / "results", cache_dir=tmp_path / "cache",
                                    text_encoder="minilm", method_options=options,
                                    source_options={"segmenter": RANDOM_SAM_FILTERS}, quiet=True))

    first = run()
    record = first.results
    assert record["track"] == "real"
    assert record["supervision"]["sources"] == {"segmenter": "sam", "image_text": "clip", "text_encoder": "clip-text"}
    configs = record["supervision"]["source_configs"]
    assert configs["segmenter"]["backend"] == configs["image_text"]["backend"] == "transformers"
    stages = record["fit"]["info"]
    assert stages["time_varying"]["captioner"] == "qwen2-vl"
    assert stages["time_varying"]["object_tracks"] == "segments:sam"
    assert stages["time_varying"]["objects"] >= 1 and stages["time_varying"]["distinct_captions"] >= 1
    assert stages["autoencoder"]["distinct_features"] > 0 and stages["field"]["iterations"] == 20
    assert record["metrics"]["agnostic_queries"] > 0 and record["metrics"]["sensitive_queries"] > 0
    assert record["fit"]["cached"] is False
    # every stage says what it cost: the supervision's two stages and the captions (outside the head's field)
    built = record["supervision"]["stages"]
    assert built["segment"]["cached"] is False and built["encode"]["cached"] is False
    assert built["segment"]["seconds"] > 0 and built["segment"]["masks_per_frame"] > 0
    captioning = stages["time_varying"]["captioning"]
    assert captioning["captioner"] == "qwen2-vl" and captioning["captions"] >= stages["time_varying"]["objects"]
    assert 0 < captioning["caption_seconds"] <= captioning["seconds"]
    assert 0 <= stages["field"]["targets_seconds"] < stages["field"]["seconds"] + 60
    cache_files = {p: p.stat().st_mtime_ns for p in (tmp_path / "cache").rglob("*") if p.is_file()}
    assert cache_files

    second = run().results
    assert second["fit"]["cached"] is True
    assert second["metrics"] == record["metrics"]
    assert all(stage["cached"] for stage in second["supervision"]["stages"].values())
    changed = [p for p, t in cache_files.items() if p.exists() and p.stat().st_mtime_ns != t]
    assert not changed, f"a second run redid a finished stage: {changed[:3]}"


# ---------------------------------------------------------------------------------------------
# object tracks from the run's segments
# ---------------------------------------------------------------------------------------------
def frame_named(name, camera_id="0", time_index=0, size=(8, 8)):
    from types import SimpleNamespace

    camera = SimpleNamespace(height=size[0], width=size[1])
    return SimpleNamespace(name=name, camera_id=camera_id, time_index=time_index, camera=camera, image_path=None)


def supervision_of(large_ids, segment_ids=True):
    """A real-track supervision whose large level holds ``large_ids`` (per frame, (H, W) segmenter ids, -1 =
    none), relabelled per frame as the cache stores them."""
    from methods.supervision.base import FrameSupervision, Supervision, relabel_levels

    frames = []
    for t, ids in enumerate(large_ids):
        levels, originals = relabel_levels(np.stack([np.full_like(ids, -1), np.full_like(ids, -1), ids]))
        features = tuple(np.zeros((len(o), 4), dtype=np.float32) for o in originals)
        frames.append(FrameSupervision(name=f"{t:06d}", time=t / 10, time_index=t, camera_id="0", levels=levels,
                                       features=features, segment_ids=tuple(originals) if segment_ids else None))
    return Supervision(track="real", sources={"segmenter": "sam", "image_text": "clip", "text_encoder": "clip-text"},
                       frames=frames, text_encoder=None, fingerprint="test")


def test_segment_tracks_follow_the_segmenters_ids_and_drop_short_lived_or_tiny_ones():
    from methods.captioners.tracks import segment_tracks

    maps = [np.full((8, 8), -1) for _ in range(3)]
    for t, m in enumerate(maps):
        m[:, :3] = 70             # an object the segmenter follows through all three frames
        m[0, 7] = 110             # a one-pixel sliver in every frame
        if t == 0:
            m[4:, 4:] = 90        # seen in one frame only
        else:
            m[4:, 4:] = 130       # seen in the two later frames
        if t == 2:
            m[:2, 3:5] = 5        # a new, small-numbered id: the per-frame mask indices shift
    frames = [frame_named(f"{t:06d}", time_index=t) for t in range(3)]
    tracks = segment_tracks(None, supervision_of(maps), min_frames=2, min_area=2 / 64, frames=frames)
    assert tracks.source == "segments:sam" and tracks.frame_names == ["000000", "000001", "000002"]
    assert tracks.labels == {0: "sam segment 70", 1: "sam segment 130"}
    for t, m in enumerate(maps):
        expected = np.where(m == 70, 0, np.where(m == 130, 1, -1))
        assert np.array_equal(tracks.ids[t], expected), t
    assert tracks.frames_of(1) == [1, 2] and tracks.objects() == [0, 1]
    # one frame is enough when asked: the one-frame id and the later id 5 are tracks too, the sliver is not
    loose = segment_tracks(None, supervision_of(maps), min_frames=1, min_area=2 / 64, frames=frames)
    assert sorted(loose.labels.values()) == ["sam segment 130", "sam segment 5", "sam segment 70", "sam segment 90"]
    with pytest.raises(InputError, match="carry no segmenter ids"):
        segment_tracks(None, supervision_of(maps, segment_ids=False), frames=frames)
    with pytest.raises(InputError, match="no segments of training frame 'elsewhere'"):
        segment_tracks(None, supervision_of(maps), frames=[frame_named("elsewhere")])


def test_object_tracks_are_truth_on_the_oracle_track_the_file_when_given_else_the_segments(tmp_path):
    from methods.fields.time_varying import object_tracks, resolve_captioning
    from methods.specs._time_varying import CaptionConfig

    assert resolve_captioning(CaptionConfig(), "real") == ("qwen2-vl", "segments")
    assert resolve_captioning(CaptionConfig(file="captions.json"), "real") == ("file", "file")
    assert resolve_captioning(CaptionConfig(), "oracle") == ("template", "truth")
    assert resolve_captioning(CaptionConfig(object_tracks="segments"), "oracle") == ("template", "segments")
    with pytest.raises(InputError, match="oracle track only"):
        resolve_captioning(CaptionConfig(object_tracks="truth"), "real")
    with pytest.raises(InputError, match="needs the run's supervision"):
        object_tracks(None, "segments", CaptionConfig())
    with pytest.raises(ValueError, match="min_track_frames"):
        CaptionConfig(min_track_frames=0)


def test_the_supervision_cache_keeps_the_segmenters_ids_and_rebuilds_a_file_without_them(tmp_path):
    from methods.supervision.cache import _load_npz, _save_npz, cached_segments

    class Counting:
        calls = 0

        def segment(self, frame):
            Counting.calls += 1
            ids = np.full((3, 8, 8), -1)
            ids[2, :, :4] = 1000 + frame.time_index   # a large-level id the segmenter chose
            ids[0, :2, :2] = 7
            return ids

    frames = [frame_named(f"{t:06d}", time_index=t) for t in range(2)]
    path = tmp_path / "segments.npz"
    levels, ids = cached_segments(path, frames, Counting(), "counting", lambda it, **_: it)
    assert Counting.calls == 2
    assert [i[2].tolist() for i in ids] == [[1000], [1001]] and [i[0].tolist() for i in ids] == [[7], [7]]
    assert [i[1].size for i in ids] == [0, 0] and all(lv[2, 0, 0] == 0 for lv in levels)
    again_levels, again_ids = cached_segments(path, frames, Counting(), "counting", lambda it, **_: it)
    assert Counting.calls == 2  # read back, not segmented again
    assert all(np.array_equal(a, b) for a, b in zip(again_levels, levels))
    assert [[x.tolist() for x in i] for i in again_ids] == [[x.tolist() for x in i] for i in ids]
    # a file written without the ids is not trusted: segmented again
    _save_npz(path, {k: v for k, v in _load_npz(path).items() if not k.startswith("ids/")})
    cached_segments(path, frames, Counting(), "counting", lambda it, **_: it)
    assert Counting.calls == 4 and any(k.startswith("ids/") for k in _load_npz(path))


def test_the_real_track_captions_the_segmenters_tracks_on_tiny_models_without_a_tracks_file(release_scene,
                                                                                             tiny_models, tmp_path,
                                                                                             monkeypatch):
    from benchmark.loaders import load_scene
    from methods.api import build_supervision
    from methods.fields.time_varying import build_captions
    from methods.specs._time_varying import CaptionConfig

    folder, _ = release_scene
    for name, path in tiny_models.items():
        monkeypatch.setenv(name, str(path))
    scene = load_scene(folder)
    supervision = build_supervision(scene, "real", cache_dir=tmp_path / "cache", text_encoder="minilm",
                                    source_options={"segmenter": RANDOM_SAM_FILTERS})
    assert all(f.segment_ids is not None for f in supervision.frames)
    config = CaptionConfig(min_track_frames=1)  # a random SAM's masks need not last
    captions, tracks = build_captions(scene, "real", config, supervision=supervision, cache_root=tmp_path / "cache")
    assert tracks.source == "segments:sam" and captions.captioner == "qwen2-vl"
    assert tracks.objects() and captions.objects() and set(captions.objects()) <= set(tracks.objects())
    for name, ids in zip(tracks.frame_names, tracks.ids):
        large = supervision.frame(name).levels[2]
        segment = supervision.frame(name).segment_ids[2]
        for obj in np.unique(ids[ids >= 0]).tolist():  # each track is one large-level SAM mask, named by its id
            masks = np.unique(large[ids == obj])
            assert masks.size == 1 and np.array_equal(large == masks[0], ids == obj)
            assert tracks.labels[obj] == f"sam segment {segment[masks[0]]}"
    with pytest.raises(InputError, match="needs the run's supervision"):
        build_captions(scene, "real", config)


# ---------------------------------------------------------------------------------------------
# memory plans of the large models (the GPU's memory query stubbed: no GPU here)
# ---------------------------------------------------------------------------------------------
@pytest.fixture
def gpu_with(monkeypatch):
    """Set the free memory a CUDA device reports, in GiB."""
    from methods import backends

    def set_free(gib, *, accelerate=True):
        monkeypatch.setattr(backends, "gpu_free_bytes", lambda device: int(gib * backends.GIB))
        monkeypatch.setattr(backends, "half_dtype", lambda device: "bfloat16")
        monkeypatch.setattr(backends, "module_available", lambda name: accelerate if name == "accelerate" else True)
    return set_free


def test_memory_plan_on_the_cpu_keeps_full_precision():
    from methods.backends import backend, plan_memory

    plan = plan_memory(backend("qwen2-vl"), "cpu", per_item_gb=2.0, max_batch=4)
    assert (plan.device, plan.dtype, plan.batch_size, plan.offload, plan.message) == ("cpu", None, 4, False, None)


def test_memory_plan_batches_what_the_free_gpu_memory_holds(gpu_with):
    from methods.backends import GIB, WEIGHT_MARGIN, backend, plan_memory

    e5 = backend("e5-mistral")
    gpu_with(80)
    plan = plan_memory(e5, "cuda", per_item_gb=0.05, max_batch=256)
    assert plan.dtype == "bfloat16" and not plan.offload and plan.message is None
    expected = int((80 * GIB - e5.gpu_memory_gb * WEIGHT_MARGIN * GIB) // (0.05 * GIB))
    assert plan.batch_size == min(256, expected)
    gpu_with(e5.gpu_memory_gb * WEIGHT_MARGIN + 0.12)  # room for two texts beside the weights
    assert plan_memory(e5, "cuda", per_item_gb=0.05, max_batch=256).batch_size == 2


def test_memory_plan_offloads_a_model_that_does_not_fit_or_says_how_to_in_one_line(gpu_with):
    from methods.backends import backend, plan_memory

    qwen = backend("qwen2-vl")
    gpu_with(12)
    plan = plan_memory(qwen, "cuda:0", per_item_gb=2.0, max_batch=1)
    assert plan.offload and plan.batch_size == 1 and plan.dtype == "bfloat16"
    assert "device_map='auto'" in plan.message and "12.0 GB is free" in plan.message and "\n" not in plan.message
    gpu_with(12, accelerate=False)
    with pytest.raises(InputError, match="install accelerate") as err:
        plan_memory(qwen, "cuda:0", per_item_gb=2.0, max_batch=1)
    assert "\n" not in str(err.value) and "captions.file" in str(err.value)


def test_e5_mistral_on_a_gpu_too_small_and_without_accelerate_says_what_to_do(gpu_with, tmp_path):
    from methods.text_encoders import e5_mistral

    gpu_with(4, accelerate=False)
    with pytest.raises(InputError, match=r"e5-mistral-7b-instruct needs about .* GB of GPU memory and 4.0 GB is free"):
        e5_mistral(str(tiny_e5_mistral(tmp_path)), device="cuda")


def test_qwen2vl_on_a_gpu_too_small_and_without_accelerate_says_what_to_do(gpu_with, tiny_models):
    from methods.captioners.qwen2vl import load_components

    gpu_with(80, accelerate=False)
    with pytest.raises(InputError, match="Qwen2-VL-7B-Instruct needs about .* and 6.0 GB is free: install accelerate"):
        load_components(str(tiny_models["BENCH4D_QWEN2VL"]), device="cuda", free_bytes=6 * 1024 ** 3)
