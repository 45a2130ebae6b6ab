"""Visual prompts: each cue does what it says and nothing else."""

import numpy as np
import pytest

from methods.captioners.visual_prompt import VisualPromptConfig, visual_prompt


@pytest.fixture
def scene():
    rng = np.random.default_rng(0)
    img = rng.uniform(size=(40, 50, 3)).astype(np.float32)
    mask = np.zeros((40, 50), bool)
    mask[10:30, 15:35] = True
    return img, mask


def test_none_is_identity(scene):
    img, mask = scene
    assert np.allclose(visual_prompt(img, mask, VisualPromptConfig.ablation("none")), img)


def test_gray_background_only_outside(scene):
    img, mask = scene
    out = visual_prompt(img, mask, VisualPromptConfig(contour=False, blur_background=False))
    assert np.allclose(out[mask], img[mask])
    bg = out[~mask]
    assert np.allclose(bg[:, 0], bg[:, 1]) and np.allclose(bg[:, 1], bg[:, 2])


def test_blur_reduces_background_variance(scene):
    img, mask = scene
    out = visual_prompt(img, mask, VisualPromptConfig.ablation("blur"))
    assert out[~mask].std() < 0.5 * img[~mask].std()
    assert np.allclose(out[mask], img[mask])


def test_contour_is_red_on_the_boundary(scene):
    img, mask = scene
    out = visual_prompt(img, mask, VisualPromptConfig())
    # The boundary pixel at the mask's top edge is pure red; the mask's interior centre is untouched.
    assert np.allclose(out[10, 25], [1.0, 0.0, 0.0])
    assert np.allclose(out[20, 25], img[20, 25])


def test_shape_errors(scene):
    img, mask = scene
    with pytest.raises(ValueError, match="mask shape"):
        visual_prompt(img, mask[:-1])
    with pytest.raises(ValueError, match="unknown visual prompt"):
        VisualPromptConfig.ablation("sparkles")
