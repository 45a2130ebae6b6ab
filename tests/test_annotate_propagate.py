"""Mask propagation: affine motion from DIS flow + RANSAC, per-pixel fallback, two-keyframe blending."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from annotations.propagate import (PropagationConfig, blend_masks, dis_flow, iou, propagate_between,
                                   propagate_chain, propagate_step, warp_by_flow)
from annotations.tool.synthetic import rigid_sequence


@pytest.fixture(scope="module")
def seq():
    return rigid_sequence(20, 320, 180, seed=2, palette="scene")


def per_pixel_chain(images, start):
    mask = start
    out = []
    for i in range(1, len(images)):
        back = dis_flow(cv2.cvtColor(images[i], cv2.COLOR_RGB2GRAY), cv2.cvtColor(images[i - 1], cv2.COLOR_RGB2GRAY))
        mask = warp_by_flow(mask, back)
        out.append(mask)
    return out


def test_affine_chain_keeps_the_shape_where_per_pixel_warping_drifts(seq):
    steps = propagate_chain(seq.images, len(seq.images) - 1, seq.masks[0])
    assert sum(s.method == "affine" for s in steps) >= 0.8 * len(steps)
    final = iou(steps[-1].mask, seq.masks[-1])
    warped = per_pixel_chain(seq.images, seq.masks[0])
    baseline = iou(warped[-1], seq.masks[-1])
    assert final > 0.9
    assert final > baseline + 0.05


def test_one_step_matches_the_true_motion(seq):
    step = propagate_step(seq.images[0], seq.images[1], seq.masks[0], PropagationConfig(refine=False))
    assert step.method == "affine" and step.matrix.shape == (2, 3)
    assert iou(step.mask, seq.masks[1]) > 0.95


def test_non_rigid_motion_falls_back_to_per_pixel_flow():
    rng = np.random.default_rng(0)
    h, w = 160, 240
    tex = (cv2.resize(rng.random((h // 4, w // 4, 3)).astype(np.float32), (w, h)) * 255).astype(np.uint8)
    src = tex.copy()
    dst = tex.copy()
    # the left half of the masked region moves left and the right half moves right: no affine fits
    mask = np.zeros((h, w), bool)
    mask[50:110, 60:180] = True
    dst[:, :120] = np.roll(tex[:, :120], -6, axis=1)
    dst[:, 120:] = np.roll(tex[:, 120:], 6, axis=1)
    step = propagate_step(src, dst, mask, PropagationConfig(refine=False, min_inlier_ratio=0.8))
    assert step.method == "flow"
    assert step.inlier_ratio < 0.8


def test_empty_mask_propagates_to_empty(seq):
    step = propagate_step(seq.images[0], seq.images[1], np.zeros(seq.masks[0].shape, bool))
    assert step.method == "empty" and not step.mask.any()


def test_blend_follows_the_nearer_keyframe_and_is_exact_at_the_ends():
    a = np.zeros((50, 80), bool)
    a[10:30, 5:25] = True
    b = np.zeros((50, 80), bool)
    b[10:30, 45:65] = True
    assert np.array_equal(blend_masks(a, b, 0.0), a)
    assert np.array_equal(blend_masks(a, b, 1.0), b)
    mid = blend_masks(a, b, 0.5)
    assert not mid[:, 5:15].any() and not mid[:, 55:65].any()
    assert blend_masks(a, np.zeros_like(a), 0.2).sum() < a.sum()


def test_between_two_keyframes_uses_both_ends(seq):
    n = 10
    masks = propagate_between(seq.images[: n + 1], n, seq.masks[0], seq.masks[n])
    assert len(masks) == n - 1
    scores = [iou(m, seq.masks[k + 1]) for k, m in enumerate(masks)]
    assert min(scores) > 0.9
