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
