"""Language-field building blocks: relevance query steps, autoencoder, status network."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from methods.fields.autoencoder import AutoencoderConfig, train_autoencoder
from methods.fields.relevance import (AgnosticQuery, majority_filter, query_levels, relevance,
                                      smooth, threshold_mask)
from methods.fields.status import NonStatusField, StatusField, StatusFieldConfig


def test_relevance_matches_lerf_formula():
    torch.manual_seed(0)
    f = F.normalize(torch.randn(5, 8), dim=-1)
    q = F.normalize(torch.randn(8), dim=-1)
    c = F.normalize(torch.randn(4, 8), dim=-1)
    got = relevance(f, q, c, temperature=10.0)
    # Direct formula: min over phrases of exp(10 q.f) / (exp(10 q.f) + exp(10 c.f)).
    eq = torch.exp(10 * (f @ q))[:, None]
    ec = torch.exp(10 * (f @ c.T))
    want = (eq / (eq + ec)).min(dim=1).values
    assert torch.allclose(got, want, atol=1e-6)


def test_smoothing_excludes_padding_from_mean():
    v = torch.ones(1, 9, 9)
    out = smooth(v, 5)
    # With padding counted, corners would be pulled towards 0; excluded, a constant map stays constant.
    assert torch.allclose(out, v)
    spike = torch.zeros(9, 9)
    spike[4, 4] = 1.0
    out = smooth(spike, 3)
    assert out[4, 4].item() == pytest.approx(0.5 * (1 + 1 / 9))
    assert out[0, 0].item() == 0.0


@pytest.mark.parametrize("rule,cut", [("rescaled", 0.4), ("stretched", 0.7)])
def test_threshold_rules(rule, cut):
    ramp = torch.linspace(0, 1, 101).reshape(1, 101).repeat(3, 1)
    query = AgnosticQuery(threshold_rule=rule)
    assert query.rescaled_cut == pytest.approx(cut)
    mask = threshold_mask(ramp, query)
    first_on = int(torch.nonzero(mask[0])[0])
    assert ramp[0, first_on].item() > cut
    assert ramp[0, first_on - 1].item() <= cut + 1e-6


def test_majority_filter_removes_speckle_keeps_blob():
    m = torch.zeros(20, 20, dtype=torch.bool)
    m[5:15, 5:15] = True
    m[1, 18] = True  # isolated speckle
    out = majority_filter(m, 7)
    assert not out[1, 18]
    assert out[8:12, 8:12].all()
    assert not out[0:3, 0:3].any()


def test_query_levels_picks_level_with_highest_peak():
    torch.manual_seed(0)
    d = 16
    q = F.normalize(torch.randn(d), dim=0)
    canon = F.normalize(torch.randn(4, d), dim=-1)
    other = F.normalize(torch.randn(d), dim=0)
    feats = other.expand(3, 32, 32, d).clone()
    feats[1, 10:20, 10:20] = q  # the query object appears at level 1 only
    res = query_levels(feats, q, canon, AgnosticQuery(smoothing_kernel=5))
    assert res.level == 1
    inside = res.mask[12:18, 12:18].float().mean().item()
    outside = res.mask[:8].float().mean().item()
    assert inside == 1.0 and outside == 0.0


@pytest.mark.parametrize("size,smoothing,majority", [((536, 960), 29, 7), ((1072, 1920), 59, 15),
                                                     ((170, 128), 5, 1), ((400, 400), 17, 3), ((8, 8), 1, 1)])
def test_windows_scale_with_resolution(size, smoothing, majority):
    assert AgnosticQuery().kernels_for(*size) == (smoothing, majority)
    assert AgnosticQuery(kernel_scaling="fixed").kernels_for(*size) == (29, 7)


def test_fixed_windows_erase_a_thin_part_that_scaled_windows_keep():
    """At 128 px the paper's 7x7 majority filter erases a 3-px-wide part (a spoon handle, a rim)."""
    torch.manual_seed(1)
    d = 16
    q = F.normalize(torch.randn(d), dim=0)
    canon = F.normalize(torch.randn(4, d), dim=-1)
    other = F.normalize(torch.randn(d), dim=0)
    feats = other.expand(3, 128, 128, d).clone()
    feats[:, 40:80, 60:63] = q
    truth = torch.zeros(128, 128, dtype=torch.bool)
    truth[40:80, 60:63] = True

    def iou(cfg):
        m = query_levels(feats, q, canon, cfg).mask
        return float((m & truth).sum()) / max(float((m | truth).sum()), 1.0)

    assert iou(AgnosticQuery()) > 0.9
    assert iou(AgnosticQuery(kernel_scaling="fixed")) < 0.1
    # at the paper's resolution the two agree
    assert AgnosticQuery().kernels_for(536, 960) == AgnosticQuery(kernel_scaling="fixed").kernels_for(536, 960)


def test_autoencoder_reconstructs_distinct_vectors():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(12, 32)).astype(np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    cfg = AutoencoderConfig(hidden_dims=(32, 16), latent_dim=3, max_steps=800, epochs=1000)
    model, report = train_autoencoder(x, cfg, seed=0)
    assert report.reconstruction_cosine > 0.9
    # An untrained model of the same shape does far worse: the test can fail.
    from methods.fields.autoencoder import FeatureAutoencoder
    untrained = FeatureAutoencoder(32, cfg)
    with torch.no_grad():
        cos0 = F.cosine_similarity(untrained(torch.as_tensor(x)), torch.as_tensor(x)).mean().item()
    assert cos0 < 0.5


def test_autoencoder_epochs_are_raised_to_its_minimum_steps_within_its_cap():
    cfg = AutoencoderConfig(batch_size=64, epochs=100, min_steps=8000, max_steps=10000)
    # 13 distinct vectors: one step an epoch, so 8 000 epochs; 200 vectors: 4 steps an epoch, 2 000 epochs
    assert cfg.for_features(13).epochs == 8000 and cfg.for_features(200).epochs == 2000
    assert AutoencoderConfig(min_steps=8000, max_steps=300).for_features(13).epochs == 300  # the cap wins
    assert AutoencoderConfig().for_features(13).epochs == 100  # no minimum: the epochs as given
    x = np.random.default_rng(0).normal(size=(5, 8)).astype(np.float32)
    _, report = train_autoencoder(x, AutoencoderConfig(hidden_dims=(4,), min_steps=700, max_steps=900), seed=0)
    assert report.steps == 700
    with pytest.raises(ValueError, match="min_steps"):
        AutoencoderConfig(min_steps=-1)


def test_the_status_head_config_shapes_the_status_field():
    from methods.fields.configs import StatusHeadConfig

    head = StatusHeadConfig(num_states=5, hidden_dim=16, weight_mode="linear", iterations=7)
    assert head.shape(2) == StatusFieldConfig(num_states=2, hidden_dim=16, weight_mode="linear", init_noise=0.1)
    assert type(head.shape(2)) is StatusFieldConfig  # what a saved field records, without the training options
    with pytest.raises(ValueError, match="fit must be one of"):
        StatusHeadConfig(fit="sometimes")


def test_status_field_layout_weights_and_static_gaussians():
    n, d, fdim = 10, 6, 8
    base = torch.arange(n * d, dtype=torch.float32).reshape(n, d)
    dyn = torch.zeros(n, dtype=torch.bool)
    dyn[[1, 4, 7]] = True
    field = StatusField(base, fdim, dyn, StatusFieldConfig(num_states=3, init_noise=0.01))
    # Layout: each state of Gaussian n starts near base[n] (not another Gaussian's feature).
    assert torch.allclose(field.states.mean(1), base[dyn], atol=0.05)
    h = torch.randn(3, fdim)
    w = field.weights(h)
    assert torch.allclose(w.sum(-1), torch.ones(3), atol=1e-6)
    out = field(h)
    assert out.shape == (n, d)
    assert torch.equal(out[~dyn], base[~dyn])
    # Static Gaussians carry one vector, not K: parameters shrink accordingly.
    full = StatusField(base, fdim, None, StatusFieldConfig(num_states=3))
    per_gauss_saved = (full.states.numel() - field.states.numel() - field.fixed.numel()) * 4
    assert per_gauss_saved == (7 * 3 * d - 7 * d) * 4
    linear = StatusField(base, fdim, dyn, StatusFieldConfig(weight_mode="linear"))
    assert not torch.allclose(linear.weights(h).sum(-1), torch.ones(3))


def test_non_status_field_starts_at_static_and_learns_a_delta():
    base = torch.randn(5, 6)
    field = NonStatusField(base, 4)
    h = torch.randn(5, 4)
    assert torch.allclose(field(h), base)
    target = base + 1.0
    opt = torch.optim.Adam(field.parameters(), lr=0.05)
    for _ in range(200):
        loss = (field(h) - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.1


def test_status_weights_are_each_rows_softmax_over_its_states():
    from methods.fields.status import StatusField, StatusFieldConfig

    torch.manual_seed(0)
    field = StatusField(torch.randn(50, 3), hexplane_dim=8, cfg=StatusFieldConfig(num_states=3), seed=0)
    feats = torch.randn(50, 8, requires_grad=True)
    got = field.weights(feats)
    want = torch.softmax(field.weight_mlp(feats), dim=-1)
    assert got.shape == (50, 3) and torch.allclose(got, want, atol=1e-6)
    assert torch.allclose(got.sum(-1), torch.ones(50), atol=1e-6)
    grad_got, = torch.autograd.grad((got * torch.arange(3.0)).sum(), feats)
    grad_want, = torch.autograd.grad((want * torch.arange(3.0)).sum(), feats)
    assert torch.allclose(grad_got, grad_want, atol=1e-6)
