"""The decode table: an interpolated stand-in for decoding every pixel, and the float32 matmul switch."""

from __future__ import annotations

import pytest
import torch
import torch.nn as nn

from benchmark.studies.query_speed import measure_query_speed
from methods.fields.language_field import DecodeTable, decode_for_relevance, matmul_precision, relevance_basis
from methods.specs._language import LanguageMethodConfig


def small_decoder(seed: int = 0) -> nn.Sequential:
    torch.manual_seed(seed)
    return nn.Sequential(nn.Linear(3, 16), nn.ReLU(), nn.Linear(16, 32), nn.ReLU(), nn.Linear(32, 64)).eval()


def basis_of(dim: int = 64, texts: int = 4, seed: int = 1) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    vectors = torch.nn.functional.normalize(torch.randn(texts, dim, generator=gen), dim=-1)
    return relevance_basis(vectors[0], vectors[1:])


def test_the_table_matches_the_exact_decode_inside_its_box_and_decodes_outside_exactly():
    decoder, basis = small_decoder(), basis_of()
    lo, hi = torch.tensor([-1.0, -1.0, -1.0]), torch.tensor([1.0, 1.0, 1.0])
    table = DecodeTable(decoder, basis, lo, hi, resolution=129)
    gen = torch.Generator().manual_seed(2)
    inside = torch.rand(4000, 3, generator=gen) * 2 - 1
    exact = decode_for_relevance(inside, decoder, basis)
    approx = table(inside)
    assert approx.shape == exact.shape
    scale = exact.abs().max()
    assert float((approx - exact).abs().max()) < 0.02 * float(scale)
    coarse = DecodeTable(decoder, basis, lo, hi, resolution=5)(inside)
    assert float((coarse - exact).abs().max()) > float((approx - exact).abs().max())  # resolution matters
    # on the table's own grid the interpolation returns the decoded values
    grid = torch.tensor([[-1.0, 0.0, 1.0], [0.5, -0.5, 0.25]])
    assert torch.allclose(table(grid), decode_for_relevance(grid, decoder, basis), atol=1e-5)
    # a latent outside the box is decoded, not clamped to the border
    outside = torch.tensor([[1.5, 0.0, 0.0], [0.0, -3.0, 0.2]])
    assert torch.allclose(table(outside), decode_for_relevance(outside, decoder, basis), atol=1e-6)


def test_the_table_refuses_latents_that_are_not_3_d_and_tiny_resolutions():
    decoder, basis = small_decoder(), basis_of()
    with pytest.raises(ValueError, match="3-d"):
        DecodeTable(decoder, basis, torch.zeros(2), torch.ones(2), resolution=9)
    with pytest.raises(ValueError, match=">= 2"):
        DecodeTable(decoder, basis, torch.zeros(3), torch.ones(3), resolution=1)


def test_a_model_answering_through_the_table_agrees_with_the_exact_decode():
    agreement = {}
    for resolution in (17, 257):
        config = LanguageMethodConfig()
        config.answer.decode_table = resolution
        out = measure_query_speed(3000, 48, 40, frames=2, warmup=1, feature_dim=64, config=config)
        assert config.answer.decode_table == resolution  # the exact comparison restores the option
        agreement[resolution] = out["mask_agreement_with_exact"]
    # random latents far from unit length at 48x40 px: a fine table is near exact, a coarse one is not
    assert agreement[257] > 0.99 and agreement[17] < agreement[257]
    plain = measure_query_speed(3000, 48, 40, frames=2, warmup=1, feature_dim=64, config=LanguageMethodConfig())
    assert "mask_agreement_with_exact" not in plain  # exact on the CPU: nothing to compare


def test_matmul_precision_is_restored_after_the_block():
    before = torch.get_float32_matmul_precision()
    other = "high" if before != "high" else "medium"
    with matmul_precision(other):
        assert torch.get_float32_matmul_precision() == other
    assert torch.get_float32_matmul_precision() == before
    with pytest.raises(RuntimeError):
        with matmul_precision(other):
            raise RuntimeError("inside")
    assert torch.get_float32_matmul_precision() == before
    with matmul_precision(None):
        assert torch.get_float32_matmul_precision() == before


def test_lazy_table_equals_the_eager_one():
    """Filled on demand (the CPU's way), the table gives the eager table's values, decoding only the grid
    points the latents reach."""
    decoder, basis = small_decoder(), basis_of()
    lo, hi = torch.tensor([-1.0, -0.5, -1.2]), torch.tensor([1.0, 1.3, 0.8])
    gen = torch.Generator().manual_seed(5)
    latents = torch.rand(2000, 3, generator=gen) * 0.5 * (hi - lo) + lo  # the lower part of the box only
    latents[0], latents[1], latents[2] = hi, lo, torch.tensor([1.5, 0.0, 0.0])  # corners; one outside
    eager = DecodeTable(decoder, basis, lo, hi, resolution=33)
    lazy = DecodeTable(decoder, basis, lo, hi, resolution=33, lazy=True)
    assert torch.allclose(lazy(latents), eager(latents), atol=1e-6)
    assert 0 < lazy.decoded_points < eager.decoded_points // 4
    before = lazy.decoded_points
    assert torch.allclose(lazy(latents[:50]), eager(latents[:50]), atol=1e-6)
    assert lazy.decoded_points == before  # nothing decoded twice


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A small fitted deformable-clip model on the smoke preset (autoencoder trained long enough to bend)."""
    from benchmark.loaders import load_scene
    from benchmark.runner import find_annotations
    from benchmark.synthetic.generate import generate
    from methods import registry
    from methods.api import Progress
    from methods.language_methods import LanguageFieldModel, fit_language_field
    from methods.supervision.cache import build_supervision

    base = tmp_path_factory.mktemp("table")
    scene = load_scene(generate("smoke", base / "smoke", size=48))
    supervision = build_supervision(scene, "oracle", cache_dir=base / "cache")
    cfg = registry.get("deformable-clip").make_config({
        "geometry.static_iterations": 100, "geometry.deformation_iterations": 100, "field.iterations": 400,
        "autoencoder.min_steps": 1500, "autoencoder.max_steps": 1500, "geometry.render_backend": "torch"})
    shared = fit_language_field(scene, supervision, cfg, kind="4dgs", seed=0, device="cpu", progress=Progress(True),
                                cache_root=base / "cache")
    model = LanguageFieldModel("deformable-clip", cfg, supervision.text_encoder, shared, sensitive="relevance")
    texts = [q.text for q in find_annotations(scene).queries if q.kind == "agnostic"]
    return model, texts, scene.test_frames


@pytest.mark.slow
def test_the_cuda_default_table_answers_as_decoding_every_pixel_on_a_fitted_model(fitted):
    """The decode table is the CUDA default (``answer.decode_table_cuda``): on a fitted model its relevance,
    on the 0-1 scale the threshold reads, stays within 2.5 % of decoding every pixel in float32, and it picks
    the same SAM level wherever the levels' peaks differ by more than 1e-3 (the CPU fills the same table
    lazily); a coarse table strays far. Its masks agree more often than the coarse table's.

    The 99.99 % share of mask pixels (``AGREEMENT_TARGET``) is measured at scale (reports/gpu-query), not
    here: this 48 px fit has flat relevance near the threshold, where 2e-4 of error flips a tenth of a frame,
    and how flat depends on the CPU's kernels."""
    from benchmark.studies.gpu_query_check import table_agreement

    model, texts, frames = fitted
    answer = model.config.answer
    assert answer.decode_table_for("cuda:0") == 257 and answer.decode_table_for("cpu") == 0
    fine = table_agreement(model, texts, frames, answer.decode_table_cuda)
    coarse = table_agreement(model, texts, frames, 3)
    assert fine["mask_pixels"] > 0 and fine["pixels"] == coarse["pixels"] > 0
    assert fine["max_rescaled_relevance_error"] < 0.025, fine
    assert fine["widest_peak_gap_at_level_change"] < 1e-3, fine  # only near-ties change level
    assert coarse["max_rescaled_relevance_error"] > 0.25 and coarse["level_changes"] > fine["level_changes"], coarse
    assert coarse["pixel_agreement"] < fine["pixel_agreement"] <= 1.0
    assert coarse["mask_pixel_agreement"] < fine["mask_pixel_agreement"] <= 1.0
    assert answer.decode_table == 0 and answer.decode_table_cuda == 257 and not model._decode_tables  # left as it was


def test_mask_agreement_counts_image_pixels_and_marked_pixels_apart():
    """Two 2x5 answers differing in one pixel: 9 of 10 image pixels agree, 3 of the 4 pixels either marks."""
    import types

    import numpy as np

    from benchmark.studies.query_speed import mask_agreement

    a = np.zeros((2, 5), bool)
    a[0, :3] = True
    b = a.copy()
    b[1, 4] = True
    out = mask_agreement([types.SimpleNamespace(mask=a)], [types.SimpleNamespace(mask=b)])
    assert out["mask_agreement_with_exact"] == 0.9 and out["min_mask_agreement_with_exact"] == 0.9
    assert out["mask_pixel_agreement_with_exact"] == 0.75 and out["mask_pixels"] == 4


def test_the_gpu_query_check_runs_its_rows_on_a_cpu_at_a_tiny_scale(tmp_path):
    """The one-command GPU check (``python -m benchmark.studies.gpu_query_check``) as a dry run on the CPU:
    every row measured, the report written with its machine and code, the time-sensitive parts timed."""
    import json

    from benchmark.studies.gpu_query_check import AGNOSTIC_VARIANTS, main

    assert main(["--device", "cpu", "--scale", "0.001", "--frames", "1", "--out", str(tmp_path)]) == 0
    doc = json.loads((tmp_path / "gpu-query.json").read_text())
    for key, _, options in AGNOSTIC_VARIANTS:
        assert doc[key]["fps"] > 0 and doc[key]["answer_options"] == options
    sensitive = doc["sensitive_default"]["sensitive"]
    assert sensitive["fps"] > 0 and set(sensitive["stage_seconds_per_frame"]) == {
        "agnostic", "status_render", "status_decode_score"}
    assert doc["environment"]["device"] == "cpu" and "commit" in doc["git"]
    text = (tmp_path / "gpu-query.md").read_text()
    assert "every pixel decoded, float32" in text and "Time-sensitive parts" in text
