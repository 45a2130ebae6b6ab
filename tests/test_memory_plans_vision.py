"""Memory plans of the real track's vision models (CLIP's image tower, SAM's point decoder): precision and
batch size from the device and its free memory. The GPU's memory query is stubbed: no GPU here."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from conftest import tiny_clip_model, tiny_sam_model
import torch

from benchmark.core.errors import InputError


@pytest.fixture
def gpu_with(monkeypatch):
    """Set the free memory a CUDA device reports, in GiB."""
    from methods import backends

    def set_free(gib):
        monkeypatch.setattr(backends, "gpu_free_bytes", lambda device: int(gib * backends.GIB))
        monkeypatch.setattr(backends, "half_dtype", lambda device: "bfloat16")
        monkeypatch.setattr(backends, "module_available", lambda name: True)
    return set_free


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("models")
    return {"clip": tiny_clip_model(root / "clip"), "sam": tiny_sam_model(root / "sam")}


def scene_of(height, width):
    """What the factories read of a scene: its training frames' sizes."""
    return SimpleNamespace(train_frames=[SimpleNamespace(camera=SimpleNamespace(height=height, width=width))])


# -- CLIP ---------------------------------------------------------------------------------------------
def test_clip_plan_on_the_cpu_is_full_precision_and_a_fixed_batch():
    from methods.supervision.clip import CLIP_CPU_BATCH, plan_clip

    plan = plan_clip("cpu")
    assert (plan.dtype, plan.batch_size, plan.offload) == (None, CLIP_CPU_BATCH, False)


def test_clip_plan_on_cuda_batches_what_the_free_memory_holds(gpu_with):
    from methods.backends import GIB, WEIGHT_MARGIN, backend
    from methods.supervision.clip import CLIP_GB_PER_CROP, CLIP_MAX_BATCH, plan_clip

    weights = backend("clip").gpu_memory_gb * WEIGHT_MARGIN
    gpu_with(80)
    plan = plan_clip("cuda")
    assert (plan.dtype, plan.batch_size, plan.offload) == ("bfloat16", CLIP_MAX_BATCH, False)
    gpu_with(weights + 10.5 * CLIP_GB_PER_CROP)  # room for ten crops beside the weights
    assert plan_clip("cuda:1").batch_size == 10
    assert plan_clip("cuda", free_bytes=int((weights + 3.5 * CLIP_GB_PER_CROP) * GIB)).batch_size == 3
    assert plan_clip("cuda", dtype="float16").dtype == "float16"


def test_clip_on_a_gpu_without_room_for_its_weights_says_so_in_one_line(gpu_with):
    from methods.supervision.clip import plan_clip

    gpu_with(0.5)
    with pytest.raises(InputError, match=r"needs about .* GB of GPU memory and 0.5 GB is free") as err:
        plan_clip("cuda")
    assert "--device cpu" in str(err.value) and "\n" not in str(err.value)
    assert "accelerate" not in str(err.value)  # a small model is never offloaded


def test_clip_factory_loads_by_the_plan(gpu_with, monkeypatch, tiny):
    from methods.supervision import clip

    loaded = {}

    class Recorded(clip.CLIPBackend):
        def __init__(self, model, *, device, dtype, local_files_only):
            loaded.update(device=device, dtype=dtype)

        def encode_images(self, pixels):
            return torch.ones(pixels.shape[0], 4)

        def encode_texts(self, texts):
            return torch.ones(len(texts), 4)

        def config(self):
            return {}

    on_cpu = clip.create(None, model=str(tiny["clip"]))
    assert on_cpu.batch_size == clip.CLIP_CPU_BATCH and on_cpu.config()["dtype"] == "float32"
    assert clip.create(None, model=str(tiny["clip"]), batch_size=5).batch_size == 5

    monkeypatch.setattr(clip, "HFCLIPBackend", Recorded)
    gpu_with(80)
    on_gpu = clip.create(None, device="cuda", model="any")
    assert loaded == {"device": "cuda", "dtype": "bfloat16"} and on_gpu.batch_size == clip.CLIP_MAX_BATCH
    clip.create(None, device="cuda", model="any", dtype="float32", batch_size=7)
    assert loaded["dtype"] == "float32"


def test_clip_runs_in_half_precision_and_rejects_an_unknown_dtype(tiny):
    from methods.supervision.clip import create

    masks = np.zeros((2, 48, 64), dtype=bool)
    masks[0, :20], masks[1, 20:] = True, True
    image = np.random.default_rng(0).random((48, 64, 3)).astype(np.float32)
    frame = SimpleNamespace(image_path=None)
    full = create(None, model=str(tiny["clip"])).encode_masks(image, masks, frame=frame)
    half_encoder = create(None, model=str(tiny["clip"]), dtype="bfloat16")
    half = half_encoder.encode_masks(image, masks, frame=frame)
    assert half_encoder.config()["dtype"] == "bfloat16" and half.dtype == np.float32
    assert np.allclose(half, full, atol=0.05)  # the same features, to bfloat16's precision
    with pytest.raises(InputError, match="unknown dtype 'half'"):
        create(None, model=str(tiny["clip"]), dtype="half")


# -- SAM ----------------------------------------------------------------------------------------------
def test_sam_plan_on_the_cpu_decodes_a_fixed_number_of_points():
    from methods.supervision.sam import SAM_CPU_POINTS, plan_sam

    plan = plan_sam("cpu", height=536, width=960)
    assert (plan.dtype, plan.batch_size, plan.offload) == (None, SAM_CPU_POINTS, False)


def test_sam_plan_on_cuda_decodes_the_points_the_free_memory_holds(gpu_with):
    from methods.backends import GIB, WEIGHT_MARGIN, backend
    from methods.supervision.sam import SAM_MAX_POINTS, plan_sam, sam_point_gb

    assert sam_point_gb(1080, 1920) > sam_point_gb(536, 960) > 0  # larger frames, larger decoded masks
    weights = backend("sam").gpu_memory_gb * WEIGHT_MARGIN
    point = sam_point_gb(536, 960)
    gpu_with(80)
    plan = plan_sam("cuda", height=536, width=960)
    assert (plan.dtype, plan.batch_size, plan.offload) == ("bfloat16", SAM_MAX_POINTS, False)
    gpu_with(weights + 20.5 * point)
    assert plan_sam("cuda", height=536, width=960).batch_size == 20
    free = int((weights + 20.5 * point) * GIB)
    assert plan_sam("cuda", height=1080, width=1920, free_bytes=free).batch_size < 20
    gpu_with(weights / 2)
    with pytest.raises(InputError, match=r"SAM ViT-H needs about .* GB of GPU memory") as err:
        plan_sam("cuda", height=536, width=960)
    assert "--device cpu" in str(err.value) and "\n" not in str(err.value)


def test_sam_factory_plans_points_per_batch_and_precision(gpu_with, monkeypatch, tiny):
    from methods.supervision import sam

    segmenter = sam.create(None, model=str(tiny["sam"]), points_per_side=3)
    assert segmenter.cfg.points_per_batch == sam.SAM_CPU_POINTS
    assert "points_per_batch" not in segmenter.config()  # memory only: not part of the cache key
    assert segmenter.config()["dtype"] == "float32"
    assert sam.create(None, model=str(tiny["sam"]), points_per_batch=5).cfg.points_per_batch == 5

    loaded = {}

    class Recorded(sam.MultimaskPredictor):
        def __init__(self, model, *, device, dtype, local_files_only):
            loaded.update(device=device, dtype=dtype)

        def set_image(self, image):
            pass

        def predict(self, points):
            raise NotImplementedError

    monkeypatch.setattr(sam, "HFSamPredictor", Recorded)
    point = sam.sam_point_gb(536, 960)
    from methods.backends import WEIGHT_MARGIN, backend

    gpu_with(backend("sam").gpu_memory_gb * WEIGHT_MARGIN + 30.5 * point)
    on_gpu = sam.create(scene_of(536, 960), device="cuda", model="any")
    assert loaded == {"device": "cuda", "dtype": "bfloat16"} and on_gpu.cfg.points_per_batch == 30
    bigger = sam.create(scene_of(1080, 1920), device="cuda", model="any")
    assert bigger.cfg.points_per_batch < 30  # planned for the scene's largest frame


def test_sam_points_per_batch_changes_memory_not_masks(tiny):
    from methods.supervision.sam import create

    wide_open = dict(points_per_side=3, pred_iou_thresh=-1e9, stability_score_thresh=0.0, min_mask_region_area=0,
                     nms_score_thresh=-1.0, nms_iou_thresh=1.0)
    image = (np.random.default_rng(1).random((48, 64, 3)) * 255).astype(np.uint8)
    one = create(None, model=str(tiny["sam"]), points_per_batch=1, **wide_open)
    all_at_once = create(None, model=str(tiny["sam"]), points_per_batch=9, **wide_open)
    assert one.config() == all_at_once.config()
    for a, b in zip(one.level_masks(image), all_at_once.level_masks(image)):
        assert a.shape == b.shape and torch.equal(a, b)


def test_sam_runs_in_half_precision_and_rejects_an_unknown_dtype(tiny):
    from methods.supervision.sam import create

    segmenter = create(None, model=str(tiny["sam"]), dtype="bfloat16", points_per_side=3, pred_iou_thresh=-1e9,
                       stability_score_thresh=0.0, min_mask_region_area=0, nms_score_thresh=-1.0, nms_iou_thresh=1.0)
    assert segmenter.config()["dtype"] == "bfloat16"
    image = (np.random.default_rng(2).random((48, 64, 3)) * 255).astype(np.uint8)
    masks = segmenter.level_masks(image)
    assert len(masks) == 3 and all(m.dtype == torch.bool and m.shape[1:] == (48, 64) for m in masks)
    assert sum(m.shape[0] for m in masks) > 0
    with pytest.raises(InputError, match="unknown dtype 'fp16'"):
        create(None, model=str(tiny["sam"]), dtype="fp16")
