"""The time-agnostic language field: frozen geometry, 9-channel rendering, masked L1 training, exact
reduced decoding for the relevance query. Scenes are built by hand (Gaussians placed on known
objects) so that what the field must learn is known exactly and no RGB fit is needed."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from benchmark.core.scene import Camera
from methods.fields.autoencoder import AutoencoderConfig, FeatureAutoencoder, train_autoencoder
from methods.fields.language_field import (FrozenGeometry, GaussianState, LanguageField, LanguageFieldConfig,
                                           decode_for_relevance, make_target, masked_l1, project_phrases,
                                           relevance_basis, train_language_field)
from benchmark.core.protocol import AgnosticQuery
from methods.fields.relevance import query_levels, relevance
from methods.gaussians.config import DeformationConfig, GaussianConfig
from methods.gaussians.hexplane import DeformationField
from methods.gaussians.model import DeformableGaussians, GaussianModel

H, W = 24, 32


def camera() -> Camera:
    """Looks down +z at the plane z = 3 (OpenCV axes)."""
    return Camera(W, H, 80.0, 80.0, W / 2, H / 2, np.eye(4))


def blob(center, n_side=4, spacing=0.07, scale=0.06):
    """A small square patch of isotropic Gaussians facing the camera."""
    g = (np.arange(n_side) - (n_side - 1) / 2) * spacing
    xx, yy = np.meshgrid(g, g)
    pts = np.stack([xx.ravel() + center[0], yy.ravel() + center[1], np.full(xx.size, center[2])], -1)
    return pts, np.full(len(pts), scale)


@dataclass
class ToyScene:
    """Two objects ('ball', 'box') as Gaussian patches in front of a backdrop ('table') that fills the
    view, as real scenes do; ``velocity`` moves the ball."""

    means: torch.Tensor
    scales: torch.Tensor
    owner: torch.Tensor  # [N] 0 = ball, 1 = box, 2 = backdrop
    velocity: torch.Tensor  # [3] world units per unit time (ball only)

    def state(self, t: float) -> GaussianState:
        means = self.means + (self.owner == 0).float()[:, None] * self.velocity * t
        n = means.shape[0]
        quats = torch.tensor([1.0, 0, 0, 0]).repeat(n, 1)
        return GaussianState(means, quats, self.scales[:, None].repeat(1, 3), torch.full((n,), 0.95))


def toy_scene(velocity=(0.0, 0.0, 0.0)) -> ToyScene:
    p0, s0 = blob((-0.3, -0.15, 3.0))  # ball: upper left (u ~ 8, v ~ 8 px)
    p1, s1 = blob((0.15, 0.25, 3.0), n_side=5)  # box: lower middle
    p2, s2 = blob((0.0, 0.0, 4.0), n_side=14, spacing=0.13, scale=0.12)  # backdrop behind both
    means = torch.as_tensor(np.concatenate([p0, p1, p2]), dtype=torch.float32)
    scales = torch.as_tensor(np.concatenate([s0, s1, s2]), dtype=torch.float32)
    owner = torch.cat([torch.full((len(p),), k, dtype=torch.long) for k, p in enumerate((p0, p1, p2))])
    return ToyScene(means, scales, owner, torch.tensor(velocity, dtype=torch.float32))


class ToyGeometry:
    """Duck-typed :class:`FrozenGeometry` over a :class:`ToyScene` (``at(t)`` moves the ball)."""

    def __init__(self, toy: ToyScene, frozen_time: Optional[float] = None):
        self.toy, self.frozen_time = toy, frozen_time

    num_gaussians = property(lambda self: self.toy.means.shape[0])
    device = torch.device("cpu")
    is_dynamic = property(lambda self: self.frozen_time is None)

    def at(self, t: float) -> GaussianState:
        return self.toy.state(self.frozen_time if self.frozen_time is not None else t)


def object_masks(toy: ToyScene, t: float) -> np.ndarray:
    """(H, W) int: 0 ball, 1 box, -1 background, from rendering one-hot ownership."""
    from methods.gaussians.rasterize import rasterize

    st = toy.state(t)
    onehot = F.one_hot(toy.owner, 3).float()
    viewmat, K = torch.eye(4), torch.as_tensor(camera().K, dtype=torch.float32)
    out = rasterize(st.means, st.quats, st.scales, st.opacities, onehot, viewmat, K, W, H, backend="torch")
    ids = out.image.argmax(-1).numpy()
    ids[out.alpha.numpy() < 0.5] = -1
    return ids


def fake_embedding(text: str, dim: int = 24) -> np.ndarray:
    """Deterministic unit vector: a direction shared by all texts plus a text-specific one, as real
    text/image embeddings share a common component (canonical phrases lean more on it)."""
    import zlib

    common = np.random.default_rng(7).standard_normal(dim)
    own = np.random.default_rng(zlib.crc32(text.encode())).standard_normal(dim)
    w = 0.9 if text in ("object", "things", "stuff", "texture") else 0.5
    v = w * common / np.linalg.norm(common) + np.sqrt(1 - w * w) * own / np.linalg.norm(own)
    return (v / np.linalg.norm(v)).astype(np.float32)


# -- geometry ------------------------------------------------------------------------------------------
def _gaussian_model(n=20, seed=0):
    rng = np.random.default_rng(seed)
    pts = rng.uniform([-1, -1, 2], [1, 1, 4], size=(n, 3))
    return GaussianModel.from_points(pts, rng.uniform(size=(n, 3)), GaussianConfig(sh_degree=1))


def test_frozen_geometry_round_trip_static_and_deformable():
    gm = _gaussian_model()
    static = FrozenGeometry(gm)
    assert static.kind == "3dgs" and not static.is_dynamic
    back = FrozenGeometry.from_state_dict(static.state_dict())
    for a, b in zip(vars(static.at(0.3)).values(), vars(back.at(0.9)).values()):
        assert torch.allclose(a, b)

    cfg = DeformationConfig(zero_init_heads=False)
    torch.manual_seed(1)
    fld = DeformationField(cfg, torch.tensor([[-1.0, -1, 2], [1, 1, 4]]), time_resolution=4)
    with torch.no_grad():  # make the time planes vary so that the deformation depends on t
        for tp in fld.hexplane.temporal:
            tp.add_(0.5 * torch.randn_like(tp))
    dyn = FrozenGeometry(DeformableGaussians(gm, fld))
    assert dyn.kind == "4dgs" and dyn.is_dynamic
    a0, a1 = dyn.at(0.0), dyn.at(1.0)
    assert not torch.allclose(a0.means, a1.means)  # it moves with time
    assert torch.equal(a0.opacities, a1.opacities)
    back = FrozenGeometry.from_state_dict(dyn.state_dict())
    b1 = back.at(1.0)
    assert torch.allclose(a1.means, b1.means, atol=1e-6) and torch.allclose(a1.quats, b1.quats, atol=1e-6)
    assert back.hexplane_features(0.5).shape == (20, cfg.hexplane.feature_dim)
    assert not any(t.requires_grad for t in dyn.gaussians.params.values())
    with pytest.raises(ValueError):
        static.hexplane_features(0.5)


# -- rendering and training ----------------------------------------------------------------------------
def test_nine_channels_in_one_call_equal_per_level_renders():
    toy = toy_scene()
    fld = LanguageField(toy.means.shape[0], LanguageFieldConfig(init_std=1.0, render_backend="torch"),
                        generator=torch.Generator().manual_seed(0))
    st = toy.state(0.0)
    maps = fld.render(st, camera())
    assert maps.shape == (3, H, W, 3)
    from methods.gaussians.rasterize import rasterize

    viewmat, K = torch.eye(4), torch.as_tensor(camera().K, dtype=torch.float32)
    for level in range(3):
        feats = fld.features[:, 3 * level:3 * level + 3].detach()
        single = rasterize(st.means, st.quats, st.scales, st.opacities, feats, viewmat, K, W, H, backend="torch")
        assert torch.allclose(maps[level].detach(), single.image, atol=1e-5)


def test_masked_l1_counts_only_supervised_pixels():
    levels = np.full((3, 2, 2), -1)
    levels[0, 0, 0] = 0
    levels[0, 1, 1] = 1
    lat = [torch.tensor([[1.0, 0, 0], [0, 1.0, 0]]), torch.zeros(0, 3), torch.zeros(0, 3)]
    tgt = make_target(Camera(2, 2, 1, 1, 1, 1, np.eye(4)), 0.0, levels, lat, "cpu")
    pred = torch.zeros(3, 2, 2, 3)
    pred[1:] = 100.0  # unsupervised levels: ignored
    pred[0, 0, 1] = 100.0  # unsupervised pixel: ignored
    # level 0: two pixels, each |error| sums to 1 over 3 channels -> mean 1/3
    assert masked_l1(pred, tgt).item() == pytest.approx(1.0 / 3.0)
    levels[1, 0, 0] = 0
    lat[1] = torch.tensor([[0.0, 0, 1.0]])
    tgt = make_target(Camera(2, 2, 1, 1, 1, 1, np.eye(4)), 0.0, levels, lat, "cpu")
    assert tgt.index[1, 0, 0].item() == 2  # offset past level 0's two rows
    pred = torch.zeros(3, 2, 2, 3)
    assert masked_l1(pred, tgt).item() == pytest.approx(1.0 / 3.0)


def _targets(toy: ToyScene, times, latents_by_object, levels_with_masks=(0, 2)):
    """Targets where the listed levels carry the object masks (other levels unsupervised)."""
    out = []
    for t in times:
        ids = object_masks(toy, t)
        levels = np.full((3, H, W), -1)
        lat = [torch.zeros(0, 3)] * 3
        for level in levels_with_masks:
            levels[level] = ids
            lat[level] = latents_by_object
        out.append(make_target(camera(), t, levels, list(lat), "cpu"))
    return out


def test_field_learns_per_level_targets_and_leaves_unsupervised_levels_alone():
    toy = toy_scene()
    latents = F.normalize(torch.tensor([[1.0, 0.2, 0.0], [-0.3, 1.0, 0.5], [0.1, -0.4, 1.0]]), dim=-1)
    targets = _targets(toy, [0.0, 0.5, 1.0], latents)
    cfg = LanguageFieldConfig(iterations=150, learning_rate=0.05, render_backend="torch", log_every=10)
    fld, report = train_language_field(ToyGeometry(toy, frozen_time=0.0), targets, cfg, seed=0)
    assert report.losses[-1] < 0.25 * report.losses[0]
    ids = object_masks(toy, 0.0)
    maps = fld.render(toy.state(0.0), camera()).detach()
    for obj in (0, 1):
        inside = torch.as_tensor(ids == obj)
        inner = torch.as_tensor(ids == obj) & torch.roll(inside, 1, 0) & torch.roll(inside, -1, 0) \
            & torch.roll(inside, 1, 1) & torch.roll(inside, -1, 1)
        got = maps[0][inner].mean(0)
        assert F.cosine_similarity(got, latents[obj], dim=0) > 0.95
    assert torch.count_nonzero(fld.features[:, 3:6]) == 0  # level 1 never supervised: still zero


# -- reduced decoding ----------------------------------------------------------------------------------
def test_reduced_decoding_gives_the_same_relevance_and_query_answer():
    torch.manual_seed(0)
    ae = FeatureAutoencoder(24, AutoencoderConfig(hidden_dims=(16, 8)))
    latents = torch.randn(3, 12, 14, 3)
    q = torch.randn(24)
    canon = torch.randn(4, 24)
    full = ae.decode(latents).detach()
    basis = relevance_basis(q, canon)
    assert basis.shape == (24, 5)
    reduced = decode_for_relevance(latents, ae.decode, basis, chunk=50)
    assert reduced.shape == (3, 12, 14, 6)
    fast = decode_for_relevance(latents, ae.decoder, basis, chunk=50)  # last layer folded (Gram matrix)
    assert torch.allclose(fast, reduced, atol=1e-4)
    zq, zc = project_phrases(basis, q, canon)
    assert torch.allclose(relevance(full, q, canon), relevance(reduced, zq, zc), atol=1e-5)
    cfg = AgnosticQuery(smoothing_kernel=5, majority_kernel=3)
    a, b = query_levels(full, q, canon, cfg), query_levels(reduced, zq, zc, cfg)
    assert a.level == b.level and torch.equal(a.mask, b.mask)
    assert torch.allclose(a.relevance, b.relevance, atol=1e-5)


def test_query_finds_each_object_and_follows_motion_with_a_deforming_geometry():
    """Autoencoder + field + protocol query on a scene whose ball moves: the dynamic geometry finds the
    ball where it is at a held-out time; the same field on a time-frozen geometry cannot."""
    toy = toy_scene(velocity=(0.4, 0.0, 0.0))
    names = ["ball", "box", "table"]
    feats = np.stack([fake_embedding(n) for n in names])
    ae, rep = train_autoencoder(feats, AutoencoderConfig(hidden_dims=(16, 8), max_steps=400), seed=0)
    assert rep.reconstruction_cosine > 0.95
    with torch.no_grad():
        lat = ae.encode(torch.as_tensor(feats))
    times = [0.0, 0.25, 0.5, 0.75, 1.0]
    cfg = LanguageFieldConfig(iterations=150, learning_rate=0.05, render_backend="torch")
    dynamic = ToyGeometry(toy)
    fld, _ = train_language_field(dynamic, _targets(toy, times, lat, (0, 1, 2)), cfg, seed=0)
    canon = torch.as_tensor(np.stack([fake_embedding(c) for c in ("object", "things", "stuff", "texture")]))
    rcfg = AgnosticQuery(smoothing_kernel=5, majority_kernel=3)

    def answer(geometry, text, t):
        q = torch.as_tensor(fake_embedding(text))
        basis = relevance_basis(q, canon)
        zq, zc = project_phrases(basis, q, canon)
        with torch.no_grad():
            lat_maps = fld.render(geometry.at(t), camera())
        return query_levels(decode_for_relevance(lat_maps, ae.decoder, basis), zq, zc, rcfg).mask.numpy()

    def iou(a, b):
        return (a & b).sum() / max((a | b).sum(), 1)

    t_test = 0.6
    truth = object_masks(toy, t_test)
    for obj, name in enumerate(names[:2]):
        assert iou(answer(dynamic, name, t_test), truth == obj) > 0.6
    frozen = ToyGeometry(toy, frozen_time=0.0)  # what a static model sees at every time
    assert iou(answer(frozen, "ball", t_test), truth == 0) < iou(answer(dynamic, "ball", t_test), truth == 0) - 0.2


# -- blending matrices ---------------------------------------------------------------------------------
def test_a_views_blend_matrix_renders_and_differentiates_as_the_rasterizer():
    from methods.fields.language_field import BlendMatrixView

    toy = toy_scene()
    fld = LanguageField(toy.means.shape[0], LanguageFieldConfig(init_std=1.0, render_backend="torch"),
                        generator=torch.Generator().manual_seed(0))
    frozen = fld.prepare(toy.state(0.0), camera())
    if frozen is None:
        pytest.skip("the compiled CPU kernels do not run here: no frozen view to compare with")
    matrix = BlendMatrixView.from_frozen(frozen)
    colors = fld.features.detach().clone().requires_grad_(True)
    want, want_alpha = frozen.render(colors)
    grad_out = torch.randn_like(want)
    (want * grad_out).sum().backward()
    want_grad, colors.grad = colors.grad.clone(), None
    got, got_alpha = matrix.render(colors)
    (got * grad_out).sum().backward()
    assert got.shape == want.shape and float(want.detach().abs().max()) > 0.1
    assert torch.allclose(got, want, atol=1e-5) and torch.allclose(got_alpha, want_alpha, atol=1e-6)
    assert torch.allclose(colors.grad, want_grad, atol=1e-4)
    assert matrix.nbytes() > 0


def test_training_on_blend_matrices_fits_the_same_field_as_the_rasterizer():
    toy = toy_scene()
    latents = F.normalize(torch.tensor([[1.0, 0.2, 0.0], [-0.3, 1.0, 0.5], [0.1, -0.4, 1.0]]), dim=-1)
    targets = _targets(toy, [0.0, 0.5, 1.0], latents)
    fits = {}
    for budget in (0.0, 64.0):
        cfg = LanguageFieldConfig(iterations=60, learning_rate=0.05, render_backend="torch", log_every=10,
                                  blend_matrix_mib=budget)
        fits[budget] = train_language_field(ToyGeometry(toy, frozen_time=0.0), targets, cfg, seed=0)
    (slow, slow_report), (fast, fast_report) = fits[0.0], fits[64.0]
    assert slow_report.views == "kept layouts"
    if fast_report.views != "blend matrices":
        pytest.skip("the compiled CPU kernels do not run here")
    assert np.allclose(fast_report.losses, slow_report.losses, rtol=1e-3, atol=1e-5)
    assert torch.allclose(fast.features, slow.features, atol=1e-3)
    tiny = LanguageFieldConfig(iterations=5, render_backend="torch", blend_matrix_mib=1e-6)
    assert train_language_field(ToyGeometry(toy, frozen_time=0.0), targets, tiny, seed=0)[1].views == "kept layouts"


def test_the_view_cycle_keeps_each_views_rendering_as_the_rasterizer_renders_it():
    """Feature-3DGS and Gaussian Grouping render their training views through :meth:`ViewCycle.prepared`: a
    blending matrix where all fit the budget, else the kept projection and layout; the rasterizer's image
    either way, and a view is prepared once."""
    from methods.fields.views import ViewCycle
    from methods.gaussians.rasterize import rasterize

    toy = toy_scene(velocity=(0.4, 0.0, 0.0))
    geometry, times = ToyGeometry(toy), [0.0, 0.5, 1.0]
    colors = torch.randn(toy.means.shape[0], 5, generator=torch.Generator().manual_seed(1))
    viewmat, K = torch.eye(4), torch.as_tensor(camera().K, dtype=torch.float32)
    for matrix_mib, expected in ((64.0, "blend matrices"), (0.0, "kept layouts")):
        cycle = ViewCycle(geometry, times, 0, 64 * 2 ** 20, cameras=[camera()] * 3, render_backend="torch",
                          matrix_budget_bytes=matrix_mib * 2 ** 20)
        for v, t in enumerate(times):
            state = geometry.at(t)
            view = cycle.prepared(v, state)
            assert view is not None and cycle.prepared(v, state) is view
            got, got_alpha = view.render(colors)
            want = rasterize(state.means, state.quats, state.scales, state.opacities, colors, viewmat, K, W, H,
                             backend="torch")
            assert float(want.image.abs().max()) > 0.1
            assert torch.allclose(got.reshape(H, W, -1), want.image.reshape(H, W, -1), atol=1e-5)
            assert torch.allclose(got_alpha.reshape(H, W), want.alpha.reshape(H, W), atol=1e-6)
        assert cycle.rendered_by == expected
    assert ViewCycle(geometry, times, 0, 64 * 2 ** 20).prepared(0, geometry.at(0.0)) is None  # no cameras given
    with pytest.raises(ValueError, match="2 cameras for 3 views"):
        ViewCycle(geometry, times, 0, 0.0, cameras=[camera()] * 2)


@pytest.mark.parametrize("method", ["feature-3dgs", "gaussian-grouping"])
def test_feature_and_identity_fields_train_on_blend_matrices_as_on_the_rasterizer(method, monkeypatch):
    """The same 40 steps with the views' blending matrices and with the rasterizer: the same losses."""
    from methods import feature_3dgs, gaussian_grouping
    from methods.specs.feature_3dgs import Feature3DGSConfig
    from methods.specs.gaussian_grouping import GaussianGroupingConfig

    toy = toy_scene(velocity=(0.4, 0.0, 0.0))
    geometry, times = ToyGeometry(toy), [0.0, 0.5, 1.0]
    truth = [torch.as_tensor(object_masks(toy, t)) for t in times]
    runs = {}
    for matrix_mib in (1024.0, 0.0):
        budget = LanguageFieldConfig(blend_matrix_mib=matrix_mib)
        module = feature_3dgs if method == "feature-3dgs" else gaussian_grouping
        monkeypatch.setattr(module, "LanguageFieldConfig", lambda **kw: dataclasses_replace(budget, **kw))
        if method == "feature-3dgs":
            config = Feature3DGSConfig()
            config.feature.iterations, config.geometry.render_backend = 40, "torch"
            table = torch.randn(3, 12, generator=torch.Generator().manual_seed(2))
            targets = [feature_3dgs.FeatureTarget(camera(), t, ids.long(), table) for t, ids in zip(times, truth)]
            _, report = feature_3dgs.train_feature_field(geometry, targets, config, output_dim=12, seed=0,
                                                         log_every=5)
        else:
            config = GaussianGroupingConfig()
            config.identity.iterations, config.geometry.render_backend = 40, "torch"
            config.identity.reg_weight = 0.0
            targets = [gaussian_grouping.IdentityTarget(camera(), t, ids.long()) for t, ids in zip(times, truth)]
            _, report = gaussian_grouping.train_identity_field(geometry, targets, 3, config, seed=0)
        runs[matrix_mib] = report
    fast, slow = runs[1024.0], runs[0.0]
    assert (fast.rendered_by, slow.rendered_by) == ("blend matrices", "kept layouts")
    assert len(fast.losses) == len(slow.losses) >= 2 and fast.losses[-1] < fast.losses[0]
    assert np.allclose(fast.losses, slow.losses, rtol=1e-3, atol=1e-5)


def dataclasses_replace(config, **changes):
    import dataclasses

    return dataclasses.replace(config, **changes)
