"""Shared fixtures: paths to ../shared (real data; skipped cleanly where absent, never in CI)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import benchmark  # noqa: F401  (first: pins numpy's BLAS kernels before torch loads numpy; benchmark.core.openblas)

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("BENCH4D_SHARED", ROOT.parent / "shared"))

# Denormals from transmittance products slow CPU compositing several-fold.
try:  # pragma: no cover - torch always present in the test env
    import torch

    torch.set_flush_denormal(True)
    torch.set_num_threads(1)  # xdist already runs one worker per core
except ImportError:  # pragma: no cover
    pass


SMOKE_SIZE = 48
"""Image width of the runner tests' smoke scene."""


@pytest.fixture(scope="session")
def smoke_base(tmp_path_factory) -> dict:
    """The smoke preset at :data:`SMOKE_SIZE`, generated once, and a cache holding its oracle supervision."""
    from benchmark.loaders import load_scene
    from benchmark.synthetic.generate import generate
    from methods.supervision.cache import build_supervision

    base = tmp_path_factory.mktemp("smoke")
    scene_dir = Path(generate("smoke", base / "scenes" / "smoke", size=SMOKE_SIZE))
    build_supervision(load_scene(scene_dir), "oracle", cache_dir=base / "cache")
    return {"scene": scene_dir, "cache": base / "cache"}


@pytest.fixture
def env(smoke_base, tmp_path) -> dict:
    """A test's own copy of the smoke cache's supervision, and its own results folder."""
    import shutil

    cache = tmp_path / "cache"
    shutil.copytree(smoke_base["cache"] / "supervision", cache / "supervision")
    return {"scene": smoke_base["scene"], "cache": cache, "results": tmp_path / "results"}


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"{SHARED} is absent (real-data checks need ../shared)")
    return SHARED


@pytest.fixture(scope="session")
def dnerf_dir(shared_dir: Path) -> Path:
    path = shared_dir / "data" / "dnerf"
    if not path.is_dir():
        pytest.skip(f"{path} is absent")
    return path


@pytest.fixture(scope="session")
def hypernerf_json_dir(shared_dir: Path) -> Path:
    path = shared_dir / "formats" / "hypernerf-chickchicken"
    if not path.is_dir():
        pytest.skip(f"{path} is absent")
    return path


def keep_paper_split(aset):
    """``aset`` narrowed, in place, to the frames of its paper split: the release format annotates one camera
    (the video's), not a generated scene's novel-view path. Returns ``aset``."""
    kept = {f.id for f in aset.frames if f.name in set(aset.info["splits"]["paper"])}
    aset.frames = [f for f in aset.frames if f.id in kept]
    aset.masks = {key: rle for key, rle in aset.masks.items() if key[1] in kept}
    aset.made_by = {key: how for key, how in aset.made_by.items() if key[1] in kept}
    return aset


def tiny_clip_model(folder: Path, max_positions: int = 77) -> Path:
    """A randomly initialised transformers CLIP (16-wide, one layer, a 54-token letter vocabulary) with its
    tokenizer, saved in ``folder``: the real class at a size a test can run."""
    import json
    import string

    import torch
    from transformers import CLIPConfig, CLIPModel, CLIPTokenizer

    folder.mkdir(parents=True, exist_ok=True)
    vocab = {c: i for i, c in enumerate(string.ascii_lowercase)}
    vocab.update({c + "</w>": 26 + i for i, c in enumerate(string.ascii_lowercase)})
    vocab["<|startoftext|>"], vocab["<|endoftext|>"] = 52, 53
    (folder / "vocab.json").write_text(json.dumps(vocab))
    (folder / "merges.txt").write_text("#version: 0.2\n")
    CLIPTokenizer(str(folder / "vocab.json"), str(folder / "merges.txt")).save_pretrained(folder)
    torch.manual_seed(0)
    cfg = CLIPConfig(
        text_config=dict(vocab_size=54, hidden_size=16, intermediate_size=32, num_hidden_layers=1,
                         num_attention_heads=2, max_position_embeddings=max_positions, bos_token_id=52,
                         eos_token_id=53, pad_token_id=53),
        vision_config=dict(image_size=32, patch_size=8, hidden_size=16, intermediate_size=32, num_hidden_layers=1,
                           num_attention_heads=2),
        projection_dim=8)
    CLIPModel(cfg).save_pretrained(folder)
    return folder


def tiny_sam_model(folder: Path) -> Path:
    """A randomly initialised transformers SAM (16-wide, one layer, 32 px input) saved in ``folder``."""
    import torch
    from transformers import SamConfig, SamModel

    torch.manual_seed(0)
    cfg = SamConfig(
        vision_config=dict(hidden_size=16, output_channels=16, num_hidden_layers=1, num_attention_heads=2,
                           image_size=32, patch_size=8, window_size=2, global_attn_indexes=[0], num_pos_feats=8,
                           mlp_dim=32),
        prompt_encoder_config=dict(hidden_size=16, image_size=32, patch_size=8, mask_input_channels=4),
        mask_decoder_config=dict(hidden_size=16, mlp_dim=32, num_hidden_layers=1, num_attention_heads=2,
                                 iou_head_hidden_dim=16))
    SamModel(cfg).save_pretrained(folder)
    return folder


class BoxSamPredictor:
    """Stands in for ``segment_anything.SamPredictor``: the attributes ``PromptedSamSegmenter`` reads and
    writes. ``set_image`` "embeds" an image as its mean colour (and records the call); ``predict`` returns
    the box region at the embedded image's size with each point's pixel set to its label, so a test can
    tell which embedding a prediction used. Random weights would measure nothing more."""

    def __init__(self):
        import threading

        self.calls = []
        self.lock = threading.Lock()
        self.features = self.original_size = self.input_size = None
        self.is_image_set = False

    def set_image(self, image):
        import torch

        with self.lock:
            self.calls.append(image.shape)
        self.features = torch.tensor(image.reshape(-1, 3).mean(0))
        self.original_size = self.input_size = image.shape[:2]
        self.is_image_set = True

    def predict(self, point_coords=None, point_labels=None, box=None, multimask_output=False):
        import numpy as np

        assert self.is_image_set
        h, w = self.original_size
        m = np.zeros((1, h, w), bool)
        if box is not None:
            x0, y0, x1, y1 = (int(v) for v in box)
            m[0, y0:y1, x0:x1] = True
        if point_coords is not None:
            for (x, y), lbl in zip(point_coords, point_labels):
                m[0, int(y), int(x)] = bool(lbl)
        return m, np.ones(1), np.zeros((1, 256, 256))
