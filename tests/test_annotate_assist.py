"""Assisted segmentation: GrabCut box-to-mask and corrective clicks; the SAM backend's embedding cache."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from annotations.assist import GrabCutSegmenter, PromptedSamConfig, PromptedSamSegmenter, make_segmenter
from conftest import BoxSamPredictor
from annotations.propagate import iou
from annotations.tool.synthetic import rigid_sequence
from benchmark.core.errors import InputError


@pytest.fixture(scope="module")
def seq():
    return rigid_sequence(3, 320, 180, seed=5)


def loose_box(box, pad, shape):
    x0, y0, x1, y1 = box
    h, w = shape
    return (max(0, x0 - pad), max(0, y0 - pad), min(w, x1 + pad), min(h, y1 + pad))


def test_box_to_mask_finds_the_object(seq):
    seg = GrabCutSegmenter()
    img, truth = seq.images[0], seq.masks[0]
    mask = seg.segment("f0", img, loose_box(seq.boxes[0], 12, truth.shape))
    assert mask.dtype == bool and mask.shape == truth.shape
    assert iou(mask, truth) > 0.9
    # nothing outside the crop around the box
    x0, y0, x1, y1 = loose_box(seq.boxes[0], 12 + 40, truth.shape)
    outside = np.ones_like(mask)
    outside[y0:y1, x0:x1] = False
    assert not mask[outside].any()


def test_corrective_clicks_add_and_remove(seq):
    seg = GrabCutSegmenter()
    img, truth = seq.images[0], seq.masks[0]
    # a wrong current mask: the object minus a chunk, plus a blob of background
    current = truth.copy()
    ys, xs = np.nonzero(truth)
    cy, cx = int(ys.mean()), int(xs.mean())
    current[cy - 6:cy + 6, cx - 6:cx + 6] = False
    bx, by = seq.boxes[0][2] + 15, seq.boxes[0][3] - 5
    current[by - 4:by + 4, bx - 4:bx + 4] = True
    clicks = [(cx + 0.5, cy + 0.5, 1), (bx + 0.5, by + 0.5, 0)]
    out = seg.segment("f0", img, None, clicks, current)
    assert out[cy, cx] and not out[by, bx]
    assert iou(out, truth) > iou(current, truth)
    assert iou(out, truth) > 0.9


def test_clicks_alone_make_a_mask(seq):
    seg = GrabCutSegmenter()
    truth = seq.masks[0]
    ys, xs = np.nonzero(truth)
    out = seg.segment("f0", seq.images[0], None, [(float(xs.mean()), float(ys.mean()), 1)])
    assert out[int(ys.mean()), int(xs.mean())]
    assert iou(out, truth) > 0.5


def test_bad_boxes_are_input_errors(seq):
    seg = GrabCutSegmenter()
    with pytest.raises(InputError, match="box"):
        seg.segment("f0", seq.images[0], (10, 10, 11, 11))
    with pytest.raises(InputError, match="box"):
        seg.segment("f0", seq.images[0], (0, 0, "x", 3))
    with pytest.raises(InputError, match="segmenter"):
        make_segmenter("magic")


def test_sam_without_weights_is_a_clear_error(tmp_path):
    with pytest.raises(InputError, match="sam-checkpoint"):
        make_segmenter("sam", sam_checkpoint=tmp_path / "missing.pth")
    with pytest.raises(InputError, match="sam-checkpoint"):
        make_segmenter("sam")


def test_sam_model_comes_from_the_sam_segmenters_loader(tmp_path, monkeypatch):
    """The tool's SAM is the ``sam`` segmenter's: one loader of the official package's models."""
    from methods.supervision import sam

    weights = tmp_path / "sam_vit_b.pth"
    weights.write_bytes(b"not a checkpoint")
    calls = []

    def fake_loader(checkpoint, model_type, device):
        calls.append((Path(checkpoint), model_type, device))
        return BoxSamPredictor()

    monkeypatch.setattr(sam, "load_segment_anything", fake_loader)
    seg = make_segmenter("sam", sam_checkpoint=weights, sam_model="vit_b", device="cpu")
    assert isinstance(seg, PromptedSamSegmenter) and calls == [(weights, "vit_b", "cpu")]
    monkeypatch.undo()
    # the real loader: the optional package missing, or the file not a checkpoint, is a clear error
    with pytest.raises(InputError, match="segment_anything|cannot load as SAM"):
        make_segmenter("sam", sam_checkpoint=weights)


def test_sam_embeddings_are_prefetched_and_cached(seq, tmp_path):
    fake = BoxSamPredictor()
    sam = PromptedSamSegmenter(PromptedSamConfig(memory_cache=2, cache_dir=tmp_path / "cache"), predictor=fake)
    sam.prefetch("a", lambda: seq.images[0])
    sam.prefetch("a", lambda: seq.images[0])  # asked twice, computed once
    assert sam.wait_idle(10)
    assert sam.cached("a") and len(fake.calls) == 1
    out = sam.segment("a", seq.images[0], (10, 20, 50, 60), [(70.5, 80.5, 1)])
    assert len(fake.calls) == 1  # the cached embedding served the prediction
    assert out[20:60, 10:50].all() and out[80, 70] and out.sum() == 40 * 40 + 1
    # the memory cache is bounded; an evicted embedding comes back from disk, not from the model
    for key, k in (("b", 1), ("c", 2)):
        sam.prefetch(key, lambda k=k: seq.images[k])
    assert sam.wait_idle(10)
    assert not sam.cached("a") and len(fake.calls) == 3
    sam.segment("a", seq.images[0], (0, 0, 5, 5))
    assert len(fake.calls) == 3
    assert len(list((tmp_path / "cache").glob("*.pt"))) == 3


@pytest.mark.shared
def test_box_to_mask_on_real_dnerf_frames(dnerf_dir):
    """A loose box around the person on real D-NeRF frames, against the alpha channel."""
    from benchmark.loaders import load_scene

    scene = load_scene(dnerf_dir / "jumpingjacks")
    seg = GrabCutSegmenter()
    scores = []
    for frame in scene.split("test")[::4]:
        img = (np.clip(frame.image(), 0, 1) * 255 + 0.5).astype(np.uint8)
        alpha = frame.alpha()
        ys, xs = np.nonzero(alpha)
        scores.append(iou(seg.segment(frame.name, img, (xs.min() - 8, ys.min() - 8, xs.max() + 9, ys.max() + 9)),
                          alpha))
    # without the background-colour prior GrabCut keeps the white between the limbs (about 0.78)
    assert np.mean(scores) > 0.9 and min(scores) > 0.85


def test_a_right_click_removes_the_uniform_region_around_it():
    import cv2

    img = np.full((160, 160, 3), 250, np.uint8)
    rng = np.random.default_rng(1)
    sweater = np.zeros((160, 160), bool)
    sweater[60:130, 40:120] = True
    head = np.zeros((160, 160), bool)
    cv2.circle(head.view(np.uint8), (80, 38), 22, 1, -1)
    head &= ~sweater
    img[sweater] = np.clip(rng.normal((230, 120, 30), 8, (sweater.sum(), 3)), 0, 255).astype(np.uint8)
    img[head] = np.clip(rng.normal((225, 180, 150), 8, (head.sum(), 3)), 0, 255).astype(np.uint8)
    seg = GrabCutSegmenter()
    box = (35, 12, 125, 135)
    first = seg.segment("s", img, box)
    assert first[head].mean() > 0.5  # the box alone takes the head too
    fixed = seg.segment("s", img, box, [(80.5, 95.5, 1), (80.5, 30.5, 0)], first)
    assert fixed[head].mean() < 0.1 and fixed[sweater].mean() > 0.95
