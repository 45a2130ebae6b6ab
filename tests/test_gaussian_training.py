"""3D-GS / 4D-GS training: densification, pruning, regularisers, static detection, tiny fits, recon CLI.

Toy scenes are rendered from known Gaussians with the project's rasterizer (torch backend), so a fit
has an exact target. Budget: well under 120 s on one core.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmark.commands import recon
from benchmark.core.scene import Camera, Frame, Scene
from methods.gaussians.config import (DeformationConfig, GaussianConfig, HexPlaneConfig, ReconConfig, Schedule)
from methods.gaussians.hexplane import DeformationField, HexPlane, axis_warp
from methods.gaussians.model import DeformableGaussians, GaussianModel, deformation_field_from_state
from methods.gaussians.rasterize import rasterize
from methods.gaussians.checkpoint import Checkpointing
from methods.gaussians.optimizer import GaussianOptimizer
from methods.gaussians.strategy import DensifyStats, densify_and_prune, reset_opacity
from methods.gaussians.train import Trainer, evaluate, gaussian_cap, gaussian_window, inside_box, make_views, ssim

RAST = functools.partial(rasterize, backend="torch")


# ---------------------------------------------------------------------------------------------------
# toy scenes
# ---------------------------------------------------------------------------------------------------
def look_at(eye: np.ndarray, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(4, 4) OpenCV world-to-camera of a camera at ``eye`` looking at ``target``."""
    f = np.asarray(target, float) - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    y = np.cross(f, r)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([r, y, f])
    w2c[:3, 3] = -w2c[:3, :3] @ eye
    return w2c


def truth_gaussians(t: float, motion: float, moving: int = 4, darken: float = 0.0):
    """24 coloured blobs in a 1.2-unit cube; the first ``moving`` slide along x by ``motion`` over t in [0, 1]
    and lose the fraction ``darken`` x t of their colour (appearance that changes)."""
    g = torch.Generator().manual_seed(1)
    n = 24
    means = (torch.rand(n, 3, generator=g) - 0.5) * 1.2
    colors = torch.rand(n, 3, generator=g)
    means[:moving, 0] += motion * (t - 0.5)
    colors[:moving] *= 1.0 - darken * t
    return (means, torch.tensor([1.0, 0, 0, 0]).repeat(n, 1), torch.full((n, 3), 0.14),
            torch.full((n,), 0.9), colors)


def toy_scene(size: int = 16, times: int = 6, views_per_time: int = 6, motion: float = 0.0,
              moving: int = 4, test_every: int = 3, darken: float = 0.0) -> Scene:
    """Cameras on a jittered ring around the blobs; every ``test_every``-th view of a time is a test view."""
    bg = np.ones(3, np.float32)
    frames = []
    k = 0
    for ti in range(times):
        t = ti / (times - 1)
        for v in range(views_per_time):
            ang = 2 * np.pi * ((k * 0.618034) % 1.0)
            elev = 0.35 * np.sin(3.0 * ang)
            k += 1
            eye = 3.0 * np.array([np.cos(ang) * np.cos(elev), np.sin(ang) * np.cos(elev), np.sin(elev)])
            cam = Camera(size, size, 1.2 * size, 1.2 * size, size / 2, size / 2, look_at(eye))
            m, q, s, o, c = truth_gaussians(t, motion, moving, darken)
            with torch.no_grad():
                img = RAST(m, q, s, o, c, torch.tensor(cam.world_to_camera, dtype=torch.float32),
                           torch.tensor(cam.K, dtype=torch.float32), size, size,
                           background=torch.tensor(bg)).image.numpy()
            split = "test" if v % test_every == test_every - 1 else "train"
            frames.append(Frame(f"{ti:02d}_{v:02d}", cam, t, ti, split, load_image=(lambda im=img: im)))
    return Scene("toy", "synthetic", frames, np.array([[-1.0] * 3, [1.0] * 3]), background=bg)


def small_recon_config(static: int, deform: int, **deformation) -> ReconConfig:
    """CPU-test sized config: SH degree 1, a small HexPlane."""
    hp = HexPlaneConfig(spatial_resolution=12, output_dim=8, multires=(1, 2))
    return ReconConfig(gaussians=GaussianConfig(sh_degree=1), static_iterations=static,
                       deformation_iterations=deform,
                       deformation=DeformationConfig(hexplane=hp, net_width=32, **deformation))


def model_from(means, log_scales, opacities, sh_degree=0) -> GaussianModel:
    n = means.shape[0]
    k = (sh_degree + 1) ** 2 - 1
    return GaussianModel({"means": means, "sh_dc": torch.zeros(n, 1, 3), "sh_rest": torch.zeros(n, k, 3),
                          "opacity_logits": torch.logit(opacities), "log_scales": log_scales,
                          "quats": torch.tensor([1.0, 0, 0, 0]).repeat(n, 1)}, sh_degree)


# ---------------------------------------------------------------------------------------------------
# densification and pruning
# ---------------------------------------------------------------------------------------------------
def test_densify_clones_small_splits_large_prunes_transparent():
    cfg = GaussianConfig()
    extent = 1.0  # clone/split boundary at percent_dense * extent = 0.01
    means = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]])
    log_scales = torch.log(torch.tensor([[0.005] * 3, [0.2, 0.1, 0.1], [0.005] * 3, [0.005] * 3]))
    opac = torch.tensor([0.5, 0.5, 0.001, 0.5])  # #2 is below min_opacity 0.005
    model = model_from(means, log_scales, opac)
    opt = GaussianOptimizer(model, cfg, extent)
    # give Adam some state to check it follows the rows
    for p in model.params.values():
        p.grad = torch.ones_like(p)
    opt.step()
    before_moment = opt.optim.state[model.params["means"]]["exp_avg"].clone()
    parent_scale = model.scales[1].detach().clone()
    parent_mean = model.means[1].detach().clone()
    stats = DensifyStats.zeros(4)
    stats.grad_sum[:] = torch.tensor([1e-3, 1e-3, 0.0, 1e-5])  # #0 and #1 above the 2e-4 threshold
    stats.count[:] = 1.0
    source, counts = densify_and_prune(model, opt, stats, cfg, extent, cap=100, size_pruning=False,
                                       max_screen_px=None, generator=torch.Generator().manual_seed(0))
    assert counts["cloned"] == 1 and counts["split"] == 1 and counts["pruned"] == 1
    # 4 + 1 clone + 2 split children - 1 split parent - 1 pruned
    assert model.num_gaussians == 5
    src = source.tolist()
    assert sorted(src) == [0, 0, 1, 1, 3]
    children = [i for i, s in enumerate(src) if s == 1]
    child_scales = model.scales[children]
    assert torch.allclose(child_scales, parent_scale.expand(2, 3) / cfg.split_scale_divisor)
    # split children are sampled around the parent, within a few of its standard deviations
    offsets = model.means[children] - parent_mean
    assert (offsets.abs() < 4 * parent_scale).all() and float(offsets.detach().abs().sum()) > 0
    # the clone is a copy of #0
    clones = [i for i, s in enumerate(src) if s == 0]
    assert torch.equal(model.means[clones[0]], model.means[clones[1]])
    # Adam moments: kept rows carry theirs, new rows start at zero; tensors are the optimiser's
    moment = opt.optim.state[model.params["means"]]["exp_avg"]
    assert moment.shape == (5, 3)
    assert torch.equal(moment[src.index(3)], before_moment[3])
    assert (moment[3:] == 0).all()
    assert opt.groups["means"]["params"][0] is model.params["means"]


def test_densify_respects_cap_best_gradient_first():
    cfg = GaussianConfig()
    n = 6
    model = model_from(torch.arange(n, dtype=torch.float32)[:, None].repeat(1, 3),
                       torch.full((n, 3), float(np.log(0.001))), torch.full((n,), 0.5))
    opt = GaussianOptimizer(model, cfg, 1.0)
    stats = DensifyStats.zeros(n)
    stats.grad_sum[:] = torch.tensor([1e-3, 5e-3, 2e-3, 4e-3, 1e-6, 3e-3])
    stats.count[:] = 1.0
    source, counts = densify_and_prune(model, opt, stats, cfg, 1.0, cap=8, size_pruning=False,
                                       max_screen_px=None, generator=torch.Generator())
    assert model.num_gaussians == 8 and counts["cloned"] == 2
    assert sorted(source.tolist()[n:]) == [1, 3]  # the two largest gradients


def test_size_pruning_and_opacity_reset():
    cfg = GaussianConfig()
    model = model_from(torch.zeros(3, 3), torch.log(torch.tensor([[0.01] * 3, [0.5] * 3, [0.01] * 3])),
                       torch.tensor([0.9, 0.9, 0.9]))
    opt = GaussianOptimizer(model, cfg, 1.0)
    stats = DensifyStats.zeros(3)
    stats.max_radius[:] = torch.tensor([3.0, 3.0, 50.0])  # #2 exceeded 20 px on screen; #1 > 0.1 extent
    _, counts = densify_and_prune(model, opt, stats, cfg, 1.0, cap=10, size_pruning=False, max_screen_px=20.0,
                                  generator=torch.Generator())
    assert model.num_gaussians == 3  # size pruning only after the first opacity reset
    _, counts = densify_and_prune(model, opt, stats, cfg, 1.0, cap=10, size_pruning=True, max_screen_px=20.0,
                                  generator=torch.Generator())
    assert model.num_gaussians == 1 and counts["pruned"] == 2
    reset_opacity(model, opt, cfg.opacity_reset_value)
    assert float(model.opacities[0].detach()) == pytest.approx(cfg.opacity_reset_value, rel=1e-4)


def test_schedule_scaling_keeps_the_paper_shape():
    s = Schedule(GaussianConfig(), 3000 / 30000)
    assert s.at(500) == 50 and s.at(100) == 10 and s.at(3000) == 300
    assert not s.densify_now(50) and s.densify_now(60) and not s.densify_now(65) and not s.densify_now(1510)
    # resets are never closer than min_opacity_reset_gap (500): the scaled 300 is raised to 500
    assert s.reset_opacity_now(500, 3000) and not s.reset_opacity_now(300, 3000)
    assert not s.reset_opacity_now(1500, 1500)  # never at a stage's last iteration
    dense = Schedule(GaussianConfig(min_opacity_reset_gap=0), 0.1)
    assert dense.reset_opacity_now(300, 3000) and not dense.reset_opacity_now(1800, 3000)  # window ends at 1500
    assert [s.sh_degree(i) for i in (0, 99, 100, 250, 5000)] == [0, 0, 1, 2, 3]
    assert s.position_lr(0, 2.0) == pytest.approx(2 * 1.6e-4)
    assert s.position_lr(3000, 2.0) == pytest.approx(2 * 1.6e-6)


def test_gaussian_cap_follows_foreground():
    cfg = GaussianConfig(min_gaussians=1)
    cam = Camera(20, 10, 20.0, 20.0, 10.0, 5.0, np.eye(4))
    small = np.ones((10, 20, 3), np.float32)
    small[:2, :5] = 0.0  # 10 foreground pixels on a white background
    big = np.zeros((10, 20, 3), np.float32)  # all 200 pixels foreground
    frames = [Frame("a", cam, 0.0, 0, "train", load_image=lambda: small)]
    frames_big = [Frame("a", cam, 0.0, 0, "train", load_image=lambda: big)]
    bg = np.ones(3)
    assert gaussian_cap(make_views(frames), bg, cfg) == round(cfg.gaussians_per_foreground_pixel * 10)
    assert gaussian_cap(make_views(frames_big), bg, cfg) == round(cfg.gaussians_per_foreground_pixel * 200)
    assert gaussian_cap(make_views(frames), None, cfg) == round(cfg.gaussians_per_foreground_pixel * 200)


def test_ssim_matches_convolution_and_scikit_image():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(0)
    a = rng.random((24, 20, 3)).astype(np.float32)
    b = np.clip(a + 0.2 * rng.standard_normal(a.shape), 0, 1).astype(np.float32)
    ours = float(ssim(torch.from_numpy(a), torch.from_numpy(b), gaussian_window(11, 1.5)))
    # reference: 2-D convolution with the outer-product window and zero padding (3D-GS release)
    g = gaussian_window(11, 1.5)
    w2 = (g[:, None] * g[None, :]).expand(3, 1, 11, 11)
    x, y = (torch.from_numpy(v).permute(2, 0, 1)[None] for v in (a, b))
    blur = lambda t: torch.nn.functional.conv2d(t, w2, padding=5, groups=3)  # noqa: E731
    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx ** 2, blur(y * y) - my ** 2, blur(x * y) - mx * my
    conv = ((2 * mx * my + 1e-4) * (2 * cxy + 9e-4)) / ((mx ** 2 + my ** 2 + 1e-4) * (vx + vy + 9e-4))
    assert ours == pytest.approx(float(conv.mean()), abs=1e-5)
    ref = structural_similarity(a, b, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                use_sample_covariance=False)
    # scikit-image crops the border instead of zero-padding: close, not equal
    assert ours == pytest.approx(ref, abs=0.05)
    assert float(ssim(torch.from_numpy(a), torch.from_numpy(a), gaussian_window(11, 1.5))) == pytest.approx(1.0)


# ---------------------------------------------------------------------------------------------------
# HexPlane, regularisers, static detection
# ---------------------------------------------------------------------------------------------------
def test_the_motion_box_gets_its_share_of_the_cells_and_nothing_outside_is_lost():
    lo, hi = torch.tensor([-4.0, -1.0, 0.0]), torch.tensor([4.0, 1.0, 2.0])
    focus = torch.tensor([[-0.5, -0.9, 1.9], [0.5, 0.9, 2.5]])  # x: 1/8 of the axis; y: 90 %; z: past the top
    knots, knots_n = axis_warp(lo, hi, focus, 0.75)
    inner_share = (knots_n[:, 2] - knots_n[:, 1]) / 2.0
    assert inner_share[0] == pytest.approx(0.75)  # x: widened to the share
    assert inner_share[1] == pytest.approx(0.9)  # y: already wider than the share: uniform
    assert knots[2, 2] == pytest.approx(2.0) and inner_share[2] == pytest.approx(0.75)  # clipped to the box
    # x: the outer cells are split in proportion to the outer lengths (3.5 m each side)
    assert knots_n[0, 1] + 1.0 == pytest.approx(1.0 - knots_n[0, 2])
    cfg = HexPlaneConfig(spatial_resolution=8, output_dim=2, multires=(1,), motion_cell_share=0.75)
    box = torch.stack([lo, hi])
    uniform, focused = HexPlane(cfg, box, 4), HexPlane(cfg, box, 4, focus)
    pts = torch.stack([torch.linspace(-5, 5, 101), torch.linspace(-1.5, 1.5, 101), torch.linspace(-1, 3, 101)], 1)
    assert not uniform.warped and focused.warped
    assert torch.equal(uniform.normalise(pts), (pts - lo) * (2.0 / (hi - lo)) - 1.0)  # the old map, bit for bit
    n = focused.normalise(pts)
    within = (pts >= lo) & (pts <= hi)
    rising = n[1:] > n[:-1]
    assert torch.all(rising[within[1:] & within[:-1]])  # strictly monotone in the box: no two places share a cell
    assert torch.all(n[~within].abs() >= 1.0 - 1e-6)  # outside: at or beyond the border, as before
    assert torch.allclose(focused.normalise(box), torch.tensor([[-1.0] * 3, [1.0] * 3]), atol=1e-6)  # box ends kept
    assert torch.allclose(focused.normalise(focus[:, :1].expand(2, 3))[:, 0], torch.tensor([-0.75, 0.75]), atol=1e-6)
    assert focused.cell_size()[0] == pytest.approx(1.0 / (0.75 * 7), rel=1e-5)  # 1 m over 3/4 of 7 cells
    assert uniform.cell_size()[0] == pytest.approx(8.0 / 7, rel=1e-5)
    assert HexPlane(dataclasses.replace(cfg, motion_cell_share=0.0), box, 4, focus).normalise(pts).allclose(
        uniform.normalise(pts))  # share 0: off


def _blob_model(t: float, motion: float, moving: int = 4) -> GaussianModel:
    """The toy scene's blobs at time ``t`` as a static model (degree-0 colours equal to theirs)."""
    m, q, s, o, c = truth_gaussians(t, motion, moving)
    return GaussianModel({
        "means": m, "sh_dc": ((c - 0.5) / 0.28209479177387814).unsqueeze(1), "sh_rest": torch.zeros(m.shape[0], 0, 3),
        "opacity_logits": torch.logit(o), "log_scales": torch.log(s), "quats": q}, 0)


def test_the_motion_box_is_where_a_static_model_leaves_the_images_unexplained():
    # the first blob slides 0.8 along x; a model of all blobs at mid-time explains everything else exactly
    motion = 0.8
    scene = toy_scene(size=24, times=6, views_per_time=8, motion=motion, moving=1)
    cfg = small_recon_config(0, 0)
    cfg.deformation.hexplane.motion_min_pixels = 16  # one blob in 24-px views
    cfg.deformation.hexplane.motion_cell_share = 0.75  # the default, stated: the test is about the box
    trainer = Trainer(scene, cfg, rasterize_fn=RAST)
    model = _blob_model(0.5, motion, moving=1)
    box, pixels = trainer.motion_box(model)
    assert box is not None and pixels >= 16, pixels
    moving, still = model.means[:1].detach(), model.means[1:].detach()
    assert torch.all((moving >= box[0]) & (moving <= box[1]))  # the moving blob's mid position is inside
    inside = torch.all((still >= box[0]) & (still <= box[1]), dim=1)
    assert int(inside.sum()) < still.shape[0] // 2, inside  # most of the static blobs are not
    # nothing moves: nothing is unexplained, no motion box (uniform cells)
    still_scene = toy_scene(size=24, times=6, views_per_time=8, motion=0.0, moving=4)
    assert Trainer(still_scene, cfg, rasterize_fn=RAST).motion_box(_blob_model(0.5, 0.0)) == (None, 0)
    off = small_recon_config(0, 0)
    off.deformation.hexplane.motion_cell_share = 0.0
    assert Trainer(scene, off, rasterize_fn=RAST).motion_box(model) == (None, 0)


def test_the_deformation_stage_starts_with_what_lies_outside_the_motion_box_static(monkeypatch):
    """One blob slides, the static stage explains the rest: the field starts on the Gaussians in the motion
    box only (on all of them with the option off), and the fit is no worse for it: it keeps what the field
    learns of the motion, which a start box that holds nothing loses."""
    box = torch.tensor([[-1.0, -1.0, 0.0], [1.0, 2.0, 0.5]])
    points = torch.tensor([[0.0, 0.0, 0.2], [1.0, 2.0, 0.5], [1.01, 0.0, 0.2], [0.0, 0.0, -0.1]])
    assert inside_box(points, box).tolist() == [True, True, False, False]  # faces belong to the box
    scene = toy_scene(size=24, times=6, views_per_time=8, motion=0.8, moving=1)
    checks: list = []  # (may_move, which Gaussians lie in motion_box) at every static check of a fit
    motion_box = None
    check = DeformableGaussians.update_static_mask

    def spy(self, cfg, extent, times=None, px_per_unit=None, may_move=None):
        inside = None if motion_box is None else inside_box(self.gaussians.means.detach(), motion_box)
        checks.append((may_move, inside))
        return check(self, cfg, extent, times, px_per_unit, may_move)

    monkeypatch.setattr(DeformableGaussians, "update_static_mask", spy)

    def fit(**deformation):
        cfg = small_recon_config(300, 300, **deformation)
        cfg.deformation.hexplane.motion_min_pixels = 16  # one blob in 24-px views
        checks.clear()
        result = Trainer(scene, cfg, rasterize_fn=RAST).fit_4dgs()
        assert result.field_box["motion_box"] is not None
        return result, evaluate(result.model, scene.test_frames, scene.background, RAST)["psnr"]

    on, psnr_on = fit()  # the default: static outside the box at the start, rechecked, nothing confined
    assert checks and all(may is None for may, _ in checks)
    off, psnr_off = fit(static_outside_motion_box=False)
    started = on.field_box.get("static_at_start", 0)
    assert "static_at_start" not in off.field_box and 0 < started < on.model.num_gaussians, started
    # the reference that deforms nothing: a start box that holds no Gaussian leaves every one static
    static_outside_box = Trainer._static_outside_box
    monkeypatch.setattr(Trainer, "_static_outside_box", lambda self: torch.tensor([[50.0] * 3, [51.0] * 3]))
    frozen, psnr_frozen = fit()
    monkeypatch.setattr(Trainer, "_static_outside_box", static_outside_box)
    assert frozen.model.num_dynamic() == 0
    psnr = {"on": psnr_on, "off": psnr_off, "frozen": psnr_frozen}
    # Short fits are chaotic: the CPU's kernels (ATEN_CPU_CAPABILITY, MKL) move each by about a dB and
    # the frozen reference lies only 1-2 dB below the others, so the margins are set from their spread
    # over kernels; a start box that misses the moving blob makes "on" the frozen fit, and fails.
    assert psnr_on > psnr_frozen + 0.25, psnr
    assert psnr_on > psnr_off - 1.5, psnr
    # recheck_outside_motion_box off: every check is told that only the Gaussians in the box may move
    motion_box = torch.tensor(on.field_box["motion_box"])  # the same static stage: the same box
    fit(recheck_outside_motion_box=False)
    assert checks and all(may is not None and torch.equal(may, inside) for may, inside in checks)


def test_a_saved_field_keeps_its_motion_box_and_one_saved_before_it_loads_uniform():
    cfg = DeformationConfig(hexplane=HexPlaneConfig(spatial_resolution=8, output_dim=4, multires=(1, 2),
                                                    motion_cell_share=0.75), net_width=16)
    box, focus = torch.tensor([[-2.0] * 3, [2.0] * 3]), torch.tensor([[-0.2] * 3, [0.3] * 3])
    field_ = DeformationField(cfg, box, 5, focus)
    state = {k: v.clone() for k, v in field_.state_dict().items()}
    back = deformation_field_from_state(dataclasses.asdict(cfg), state, 5)
    pts = torch.rand(50, 3) * 4 - 2
    assert torch.equal(back.hexplane.normalise(pts), field_.hexplane.normalise(pts))
    assert back.hexplane.warped  # the flag follows the loaded knots, not the uniform ones it was built with
    old = {k: v for k, v in state.items() if "warp" not in k}  # written before the motion box existed
    legacy = deformation_field_from_state(dataclasses.asdict(cfg), old, 5)
    assert not legacy.hexplane.warped
    assert torch.allclose(legacy.hexplane.normalise(pts), (pts + 2.0) / 2.0 - 1.0, atol=1e-6)


def test_hexplane_regularisers_nonzero_with_gradients():
    hp = HexPlane(HexPlaneConfig(spatial_resolution=8, output_dim=4, multires=(1, 2)), torch.tensor([[-1.0] * 3, [1.0] * 3]), 6)
    regs = hp.regularisers()
    assert float(regs["plane_tv"].detach()) > 0  # spatial planes start random
    assert float(regs["time_smoothness"].detach()) == 0 and float(regs["l1_time_planes"].detach()) == 0  # time planes start at 1
    with torch.no_grad():
        for tp in hp.temporal:
            tp.add_(0.1 * torch.randn(tp.shape))
    regs = hp.regularisers()
    for name, value in regs.items():
        assert float(value.detach()) > 0, name
        grads = torch.autograd.grad(value, list(hp.parameters()), allow_unused=True)
        assert any(g is not None and float(g.abs().sum()) > 0 for g in grads), name
    feats = hp(torch.zeros(5, 3), 0.5)
    assert feats.shape == (5, 8)


def test_trainer_applies_temporal_regularisers(monkeypatch):
    """The regularisers reach the backward pass of the deformation stage (the release never adds them).

    1. Each term is scaled by a probe leaf tensor: after training, every probe has a nonzero gradient,
       so every term was part of the loss that was backpropagated.
    2. Two identical runs (same seed) differ only in the weights: spatial-plane cells that no Gaussian
       samples (unchanged without regularisers) move with them.
    """
    scene = toy_scene(size=12, times=3, views_per_time=3, motion=0.3)

    def cfg_with(weight: float) -> ReconConfig:
        return small_recon_config(0, 3, plane_tv_weight=weight, time_smoothness_weight=weight,
                                  l1_time_planes_weight=weight, static_skip=False)

    probes = {k: torch.ones((), requires_grad=True) for k in ("plane_tv", "time_smoothness", "l1_time_planes")}
    original = HexPlane.regularisers

    def probed(self):
        regs = original(self)
        # value unchanged; d/d probe = term + 1, nonzero even where a term is 0 (flat time planes)
        return {k: v * probes[k] + (probes[k] - probes[k].detach()) for k, v in regs.items()}

    monkeypatch.setattr(HexPlane, "regularisers", probed)
    Trainer(scene, cfg_with(1e-3), rasterize_fn=RAST).fit_4dgs()
    for name, probe in probes.items():
        assert probe.grad is not None and float(probe.grad) != 0.0, name
    monkeypatch.setattr(HexPlane, "regularisers", original)

    def spatial_change(weight: float) -> torch.Tensor:
        torch.manual_seed(0)
        hp = Trainer(scene, cfg_with(weight), rasterize_fn=RAST).fit_4dgs().model.field.hexplane
        torch.manual_seed(0)
        init = Trainer(scene, dataclasses.replace(cfg_with(weight), deformation_iterations=0),
                       rasterize_fn=RAST).fit_4dgs().model.field.hexplane
        return torch.cat([(a - b).abs().flatten() for a, b in zip(hp.spatial, init.spatial)]).detach()

    without, with_reg = spatial_change(0.0), spatial_change(1.0)
    assert (without > 0).any()  # the data term trains the planes
    unsampled = without == 0
    assert unsampled.any() and (with_reg[unsampled] > 0).any()


def _two_region_field() -> DeformationField:
    """A field whose time planes vary only near x = +0.75: deformation there depends on t."""
    cfg = DeformationConfig(hexplane=HexPlaneConfig(spatial_resolution=8, output_dim=4, multires=(1,)),
                            net_width=16, zero_init_heads=False)
    torch.manual_seed(0)
    fld = DeformationField(cfg, torch.tensor([[-1.0] * 3, [1.0] * 3]), time_resolution=5)
    with torch.no_grad():
        xt = fld.hexplane.temporal[0][0]  # (C, T, R): x along columns
        xt[:, :, 6:] = 1.0 + torch.linspace(-0.8, 0.8, 5)[None, :, None]
    return fld


def test_static_detection_marks_static_and_dynamic():
    fld = _two_region_field()
    means = torch.tensor([[-0.75, 0.1, 0.0], [0.8, 0.1, 0.0]])  # static region, moving region
    gm = model_from(means, torch.full((2, 3), float(np.log(0.05))), torch.full((2,), 0.5))
    dg = DeformableGaussians(gm, fld)
    before = [x.detach().clone() for x in dg.deform(0.3, skip_static=False)]
    counts = dg.update_static_mask(DeformationConfig(), extent=1.0)
    assert dg.dynamic_mask.tolist() == [False, True]
    assert counts["static"] == 1 and counts["newly_static"] == 1
    # the static Gaussian's constant offset was folded in: rendering does not jump
    after = dg.deform(0.3, skip_static=True)
    for a, b in zip(before, after):
        assert torch.allclose(a, b, atol=1e-4)
    # the field runs on the dynamic Gaussian only
    rows = []
    hook = fld.trunk.register_forward_hook(lambda m, i, o: rows.append(i[0].shape[0]))
    dg.deform(0.7, skip_static=True)
    hook.remove()
    assert rows == [1]
    # and the moving one really moves
    m0, m1 = dg.deform(0.0)[0], dg.deform(1.0)[0]
    assert float((m0[1] - m1[1]).detach().norm()) > 1e-3 and float((m0[0] - m1[0]).detach().norm()) == 0.0
    # a Gaussian that may not move (outside the motion box, recheck_outside_motion_box off) is static
    # whatever its offsets, and gets its time-mean offset folded in as any newly static one
    counts = dg.update_static_mask(DeformationConfig(), extent=1.0, may_move=torch.tensor([True, False]))
    assert dg.dynamic_mask.tolist() == [False, False] and counts["newly_static"] == 1


def test_deformation_field_matches_its_definition():
    """The fused forward (written-out plane product, block-diagonal head outputs, in-place ReLU) computes
    the definition: the product of six separately sampled planes per resolution, then three independent
    heads on their own third of the hidden layer; gradients reach every plane and weight alike."""
    torch.manual_seed(0)
    cfg = DeformationConfig(hexplane=HexPlaneConfig(spatial_resolution=6, output_dim=4, multires=(1, 2)),
                            net_width=8, zero_init_heads=False, deform_color=True)
    fld = DeformationField(cfg, torch.tensor([[-1.0] * 3, [1.0] * 3]), 5)
    with torch.no_grad():
        for plane in fld.hexplane.temporal:
            plane.add_(0.3 * torch.randn(plane.shape))
    xyz = torch.rand(40, 3) * 2.4 - 1.2  # some outside the box: border padding
    t = 0.37

    def reference(xyz):
        hp = fld.hexplane
        p = hp.normalise(xyz)
        feats = []
        for sp, tp in zip(hp.spatial, hp.temporal):
            value = torch.ones(xyz.shape[0], sp.shape[1])
            for k, (a, b) in enumerate(((0, 1), (0, 2), (1, 2))):
                grid = p[:, [a, b]][None, None]
                value = value * torch.nn.functional.grid_sample(sp[k:k + 1], grid, align_corners=True,
                                                                padding_mode="border")[0, :, 0].t()
            for k, a in enumerate((0, 1, 2)):
                grid = torch.stack([p[:, a], torch.full_like(p[:, a], 2 * t - 1)], -1)[None, None]
                value = value * torch.nn.functional.grid_sample(tp[k:k + 1], grid, align_corners=True,
                                                                padding_mode="border")[0, :, 0].t()
            feats.append(value)
        hidden = torch.relu(fld.heads_hidden(torch.relu(fld.trunk(torch.cat(feats, 1)))))
        chunks = hidden.chunk(len(fld.head_names), dim=1)
        return [fld.heads_out[name](chunk) for name, chunk in zip(fld.head_names, chunks)]

    got = list(fld.forward_all(xyz, t))
    want = reference(xyz)
    assert fld.head_names == ["position", "scale", "rotation", "color"]
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w, rtol=1e-5, atol=1e-6)
    weights = [torch.randn_like(w) for w in want]
    params = list(fld.parameters())
    g_got = torch.autograd.grad(sum((g * w).sum() for g, w in zip(got, weights)), params)
    g_want = torch.autograd.grad(sum((g * w).sum() for g, w in zip(reference(xyz), weights)), params)
    for a, b in zip(g_got, g_want):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


def test_hexplane_features_exposed():
    fld = _two_region_field()
    gm = model_from(torch.zeros(3, 3), torch.zeros(3, 3), torch.full((3,), 0.5))
    dg = DeformableGaussians(gm, fld)
    f = dg.hexplane_features(0.5)
    assert f.shape == (3, fld.cfg.hexplane.feature_dim)
    assert dg.hexplane_features(0.5, torch.ones(2, 3)).shape == (2, fld.cfg.hexplane.feature_dim)


def test_deformable_state_dict_round_trip():
    fld = _two_region_field()
    gm = model_from(torch.tensor([[-0.75, 0.1, 0.0], [0.8, 0.1, 0.0]]), torch.full((2, 3), -3.0),
                    torch.full((2,), 0.5), sh_degree=1)
    dg = DeformableGaussians(gm, fld)
    dg.update_static_mask(DeformationConfig(), extent=1.0)
    back = DeformableGaussians.from_state_dict(dg.state_dict())
    assert torch.equal(back.dynamic_mask, dg.dynamic_mask)
    for a, b in zip(dg.deform(0.4), back.deform(0.4)):
        assert torch.allclose(a, b)
    assert torch.allclose(dg.hexplane_features(0.4), back.hexplane_features(0.4))


# ---------------------------------------------------------------------------------------------------
# tiny fits
# ---------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def moving_scene() -> Scene:
    """Half the blobs slide by 0.4 units over 8 time steps; 6 training views per time step."""
    return toy_scene(size=16, times=8, views_per_time=8, motion=0.4, moving=12, test_every=4)


def _initial_psnr(scene: Scene, cfg: ReconConfig) -> float:
    trainer = Trainer(scene, dataclasses.replace(cfg, static_iterations=0, deformation_iterations=0), rasterize_fn=RAST)
    return evaluate(trainer.fit_3dgs(1).model, scene.test_frames, scene.background, RAST)["psnr"]


def test_tiny_3dgs_fit_static_scene():
    scene = toy_scene(size=16, times=2, views_per_time=9, motion=0.0)
    cfg = small_recon_config(0, 0)
    trainer = Trainer(scene, cfg, rasterize_fn=RAST)
    result = trainer.fit_3dgs(600)
    ev = evaluate(result.model, scene.test_frames, scene.background, RAST)
    assert result.stages[0]["final_loss"] < 0.5 * result.stages[0]["first_loss"]
    baseline = _initial_psnr(scene, cfg)
    assert ev["psnr"] > 24.0, (ev["psnr"], baseline)
    assert ev["psnr"] > baseline + 8.0
    assert result.model.num_gaussians <= result.cap
    assert np.isnan(ev["region_psnr"]) and np.isnan(ev["region_fraction"])  # no masks asked for
    # region PSNR pools squared errors: the whole image as the region gives the PSNR of the mean MSE
    # (frames of one size), and any split of it gives back the same total squared error
    mse = np.array([10 ** (-f["psnr"] / 10) for f in ev["per_frame"]])
    everything = {f.name: np.ones((f.camera.height, f.camera.width), bool) for f in scene.test_frames}
    whole = evaluate(result.model, scene.test_frames, scene.background, RAST, region_masks=everything)
    assert whole["region_psnr"] == pytest.approx(-10 * np.log10(mse.mean()), abs=1e-6)
    assert np.isnan(whole["rest_psnr"]) and whole["region_fraction"] == 1.0
    rng = np.random.default_rng(0)
    half = {k: rng.random(v.shape) < 0.5 for k, v in everything.items()}
    split = evaluate(result.model, scene.test_frames, scene.background, RAST, region_masks=half)
    frac = split["region_fraction"]
    assert frac == pytest.approx(np.mean([m.mean() for m in half.values()]))
    total = frac * 10 ** (-split["region_psnr"] / 10) + (1 - frac) * 10 ** (-split["rest_psnr"] / 10)
    assert total == pytest.approx(mse.mean(), rel=1e-6)
    with pytest.raises(ValueError, match="region mask"):
        evaluate(result.model, scene.test_frames[:1], scene.background, RAST,
                 region_masks={scene.test_frames[0].name: np.ones((3, 3), bool)})


def test_motion_l1_counts_offsets_in_units_of_the_static_tolerances():
    from methods.gaussians.train import motion_l1

    d = DeformationConfig(static_pixel_tol=2.0, static_scale_tol=0.1, static_rotation_tol=0.05)
    quats = torch.tensor([[2.0, 0, 0, 0], [1.0, 0, 0, 0], [1.0, 0, 0, 0]])
    ppu = torch.tensor([10.0, 100.0, 1.0])
    dx = torch.tensor([[0.1, 0.0, -0.1], [0.0, 0.0, 0.0]], requires_grad=True)
    ds = torch.tensor([[0.0, 0.05, 0.0], [0.0, 0.0, 0.0]])
    dq = torch.tensor([[0.0, 0.0, 0.0, 0.0], [0.0, 0.1, 0.0, 0.0]])
    rows = torch.tensor([0, 2])  # the second Gaussian is static (skipped): it counts as zero
    value = motion_l1((rows, dx, ds, dq), ppu, quats, d)
    # Gaussian 0: 0.2 units x 10 px / 2 px + 0.05 / 0.1; Gaussian 2: 0.1 / (0.05 x 1); mean over all 3
    assert float(value.detach()) == pytest.approx((1.0 + 0.5 + 2.0) / 3)
    value.backward()
    assert torch.allclose(dx.grad[0], torch.tensor([1.0, 0.0, -1.0]) * 10 / 2 / 3)


def test_motion_prior_keeps_a_static_monocular_scene_still():
    """One view per time (monocular): without the prior the field moves static blobs to fit each view."""
    scene = toy_scene(size=16, times=30, views_per_time=1, motion=0.0, test_every=4)
    times = torch.linspace(0, 1, 16)
    spread = {}
    for weight in (0.0, 0.01):
        cfg = small_recon_config(100, 300, static_skip=False, motion_l1_weight=weight)
        trainer = Trainer(scene, cfg, rasterize_fn=RAST)
        model = trainer.fit_4dgs().model
        px = model.deformation_variation(times)["position"] * trainer.pixels_per_unit(model.gaussians.means.detach())
        spread[weight] = float(px.median())
    assert spread[0.01] < 0.5 * spread[0.0], spread


def test_tiny_4dgs_beats_3dgs_on_motion(moving_scene):
    """Same budget (900 iterations): 3D-GS cannot represent the motion, 4D-GS must."""
    cfg = small_recon_config(150, 750)
    r3 = Trainer(moving_scene, cfg, rasterize_fn=RAST).fit_3dgs()
    r4 = Trainer(moving_scene, cfg, rasterize_fn=RAST).fit_4dgs()
    assert r3.stages[0]["iterations"] == 900
    p3 = evaluate(r3.model, moving_scene.test_frames, moving_scene.background, RAST)["psnr"]
    p4 = evaluate(r4.model, moving_scene.test_frames, moving_scene.background, RAST)["psnr"]
    assert p4 > 32.0, (p3, p4)  # ~36-37 dB over seeds 0-2; 3D-GS ~27.4
    assert p4 > p3 + 4.0, (p3, p4)
    assert [s["stage"] for s in r4.stages] == ["static", "deformation"]
    assert r4.stages[1]["final_loss"] < 0.5 * r4.stages[1]["first_loss"]
    checks = [e for e in r4.stages[1]["events"] if e["event"] == "static_check"]
    assert checks and checks[-1]["iteration"] == 750  # detection ran, last at the stage's end
    assert r4.model.dynamic_mask is not None and r4.model.num_dynamic() > 0


def test_color_head_fits_appearance_that_changes():
    """Half the blobs darken over time and nothing moves: a position / scale / rotation deformation cannot
    follow, the colour head can (measured 28.2 vs 36.5 dB)."""
    scene = toy_scene(size=16, times=8, views_per_time=8, motion=0.0, moving=12, test_every=4, darken=0.8)
    psnr, models = {}, {}
    for on in (False, True):
        cfg = small_recon_config(150, 750, deform_color=on)
        models[on] = Trainer(scene, cfg, rasterize_fn=RAST).fit_4dgs().model
        psnr[on] = evaluate(models[on], scene.test_frames, scene.background, RAST)["psnr"]
    assert psnr[True] > psnr[False] + 3.0, psnr
    with_head = models[True]
    var = with_head.deformation_variation(torch.linspace(0, 1, 8))
    assert float(var["color"].max()) > 0.2  # the head does carry the darkening
    assert float(models[False].deformation_variation(torch.linspace(0, 1, 8))["color"].max()) == 0.0
    back = DeformableGaussians.from_state_dict(with_head.state_dict())
    view = make_views(scene.test_frames[:1])[0]
    for a, b in zip(with_head.deform_with_colors(0.7, view.center), back.deform_with_colors(0.7, view.center)):
        assert torch.allclose(a, b)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_tiny_4dgs_on_cuda_reaches_the_cpu_quality(moving_scene):
    """The same fits on CUDA with the default rasterizer (gsplat where importable): the training loop,
    densification (gsplat's screen-space gradients) and deformation run on the GPU to the CPU's quality."""
    cfg = small_recon_config(150, 750)
    r3 = Trainer(moving_scene, cfg, device="cuda").fit_3dgs()
    r4 = Trainer(moving_scene, cfg, device="cuda").fit_4dgs()
    assert r4.model.gaussians.means.is_cuda
    p3 = evaluate(r3.model, moving_scene.test_frames, moving_scene.background, device="cuda")["psnr"]
    p4 = evaluate(r4.model, moving_scene.test_frames, moving_scene.background, device="cuda")["psnr"]
    assert p4 > 32.0 and p4 > p3 + 4.0, (p3, p4)
    assert r4.model.num_dynamic() > 0


# ---------------------------------------------------------------------------------------------------
# bench4d recon
# ---------------------------------------------------------------------------------------------------
def write_dnerf_folder(root: Path, size: int = 12) -> Path:
    """A tiny D-NeRF-layout scene (RGBA PNGs, OpenGL camera-to-world) rendered from the toy blobs."""
    from benchmark.core.imageio import write_image

    focal = 1.2 * size
    splits = {"train": 10, "test": 3}
    k = 0
    for split, count in splits.items():
        frames = []
        (root / split).mkdir(parents=True, exist_ok=True)
        for i in range(count):
            t = i / max(1, count - 1)
            ang = 2 * np.pi * ((k * 0.618034) % 1.0)
            k += 1
            eye = 3.0 * np.array([np.cos(ang), np.sin(ang), 0.3])
            w2c = look_at(eye)
            cam = Camera(size, size, focal, focal, size / 2, size / 2, w2c)
            m, q, s, o, c = truth_gaussians(t, 0.3, 4)
            with torch.no_grad():
                out = RAST(m, q, s, o, c, torch.tensor(w2c, dtype=torch.float32),
                           torch.tensor(cam.K, dtype=torch.float32), size, size)
            rgba = np.concatenate([out.image.numpy() / np.maximum(out.alpha.numpy()[..., None], 1e-6),
                                   out.alpha.numpy()[..., None]], -1).clip(0, 1)
            write_image(root / split / f"r_{i:03d}.png", rgba)
            c2w = np.linalg.inv(w2c)
            c2w[:3, 1:3] *= -1.0  # OpenCV -> OpenGL axes
            frames.append({"file_path": f"./{split}/r_{i:03d}", "time": t, "transform_matrix": c2w.tolist()})
        angle = 2 * np.arctan(size / (2 * focal))
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    return root


def test_recon_command_end_to_end(tmp_path):
    from benchmark.cli import main

    scene_dir = write_dnerf_folder(tmp_path / "toy-dnerf")
    out = tmp_path / "out"
    code = main(["recon", "--scene", str(scene_dir), "--iters", "24", "--no-isolate", "--threads", "1",
                 "--renders", "1", "--out", str(out), "--set", "gaussians.sh_degree=1",
                 "--set", "deformation.hexplane.spatial_resolution=8"])
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    assert set(report["models"]) == {"3dgs", "4dgs"}
    for entry in report["models"].values():
        assert 5.0 < entry["psnr"] < 60.0 and 0.0 < entry["ssim"] <= 1.0
        assert entry["fit_cpu_seconds"] > 0 and entry["render_fps"] > 0 and entry["peak_rss_mib"] > 0
        assert 0 < entry["gaussians"] <= entry["cap"]
        assert all(Path(p).is_file() for p in entry["renders"])
    assert report["models"]["3dgs"]["iterations"] == report["models"]["4dgs"]["iterations"] == 24
    # each fit checkpointed into the output folder and removed its checkpoint when it completed
    assert all(e["resumed_at"] is None for e in report["models"].values()) and not list(out.glob(".*.partial.pt"))
    assert report["config"]["gaussians"]["sh_degree"] == 1
    assert "psnr_gain_4dgs_over_3dgs" in report["comparison"]
    skip = report["models"]["4dgs"]["static_skip"]
    for key in ("step_cpu_ms_skip", "step_cpu_ms_full", "deform_saved_mib_skip", "deform_saved_mib_full"):
        assert key in skip
    assert all("moving" not in e for e in report["models"].values())  # no generator truth: no moving parts
    assert main(["recon", "--summarize", str(tmp_path)]) == 0
    summary = (tmp_path / "summary.md").read_text()
    # the row names the run's --set overrides and where it trained
    (row,) = [line for line in summary.splitlines() if line.startswith(
        "| toy-dnerf [gaussians.sh_degree=1, deformation.hexplane.spatial_resolution=8] | cpu | 12x12 | 24 |")]
    cells = [c.strip() for c in row.split("|")]
    assert cells[-4] == "-"  # no generator truth: no gain bound
    assert cells[-2] == recon._commit_cell(report["git"])  # the commit that ran
    box = report["models"]["4dgs"]["field_box"]  # the HexPlane's box and, where found, its motion box
    lo, hi = box["bounds"]
    assert cells[-3].endswith(f"({max(h - l for l, h in zip(lo, hi)) / 7:.3g})")  # uniform: 8 cells per axis
    assert float(cells[-3].split()[0]) <= max(h - l for l, h in zip(lo, hi)) / 7 + 1e-9
    # another seed is its own row, named by its seed
    report["config"]["seed"] = 3
    report["git"] = {"commit": "0123456789abcdef", "dirty": True}
    (tmp_path / "seed3").mkdir()
    (tmp_path / "seed3" / "report.json").write_text(json.dumps(report))
    assert main(["recon", "--summarize", str(tmp_path)]) == 0
    (row,) = [line for line in (tmp_path / "summary.md").read_text().splitlines()
              if line.startswith("| toy-dnerf (seed 3) [gaussians.sh_degree=1")]
    assert row.endswith(f"| - | {cells[-3]} | 0123456+ |")


def test_recon_scores_the_moving_parts_of_a_generated_scene(tmp_path):
    from benchmark.cli import main
    from benchmark.synthetic.generate import generate

    scene_dir = generate("smoke", tmp_path / "smoke", size=32)
    out = tmp_path / "reports" / "smoke"
    assert main(["recon", "--scene", str(scene_dir), "--iters", "12", "--no-isolate", "--renders", "0",
                 "--out", str(out), "--set", "deformation.hexplane.spatial_resolution=8"]) == 0
    report = json.loads((out / "report.json").read_text())
    for entry in report["models"].values():
        moving = entry["moving"]
        assert moving["parts"] == ["ball", "bar half", "lid knob", "lid panel"]
        assert 0.0 < moving["pixel_fraction"] < 0.5
        assert np.isfinite(moving["psnr"]) and np.isfinite(moving["static_psnr"])
    assert main(["recon", "--summarize", str(tmp_path / "reports")]) == 0
    (row,) = [line for line in (tmp_path / "reports" / "summary.md").read_text().splitlines()
              if line.startswith("| smoke [")]  # the label names the run's --set overrides
    cells = [c.strip() for c in row.split("|")]
    assert " %, " in cells[-6] and " / " in cells[-5]  # moving parts; elsewhere
    m3 = report["models"]["3dgs"]["moving"]
    assert float(cells[-4]) == pytest.approx(recon.moving_gain_bound(m3), abs=0.006)


def test_moving_gain_bound_counts_what_perfect_moving_parts_would_gain():
    # half the pixels move, rendered as badly as the rest: perfect moving pixels halve the error (+3.01 dB)
    assert recon.moving_gain_bound({"psnr": 20.0, "static_psnr": 20.0, "pixel_fraction": 0.5}) == \
        pytest.approx(10 * np.log10(2.0))
    # a moving part 10x worse on 1 % of the pixels: (0.01 * 10 + 0.99) / 0.99
    assert recon.moving_gain_bound({"psnr": 20.0, "static_psnr": 30.0, "pixel_fraction": 0.01}) == \
        pytest.approx(10 * np.log10(1.09 / 0.99))
    assert recon.moving_gain_bound(None) is None
    assert recon.moving_gain_bound({"psnr": None, "static_psnr": 30.0, "pixel_fraction": 0.1}) is None


def test_recon_time_range_trains_and_scores_only_those_frames(tmp_path, capsys):
    from benchmark.cli import main
    from benchmark.loaders import load_scene
    from benchmark.synthetic.generate import generate

    from benchmark.core.scene import scene_split_frames

    scene_dir = generate("smoke", tmp_path / "smoke", size=24)
    scene = load_scene(scene_dir)
    last = scene.num_time_steps // 2
    want_train = sum(f.time_index <= last for f in scene.train_frames)
    # the paper split's frames by default: the novel views among the test frames are another split's
    want_test = [f.name for f in scene_split_frames(scene, "paper") if f.time_index <= last]
    assert 0 < want_train < len(scene.train_frames) and 0 < len(want_test) < len(scene.test_frames) // 2
    for split, want in (("paper", want_test),
                        ("novel-view", [f.name for f in scene_split_frames(scene, "novel-view") if f.time_index <= last])):
        out = tmp_path / "reports" / f"smoke-start-{split}"
        assert main(["recon", "--scene", str(scene_dir), "--iters", "6", "--no-isolate", "--renders", "0",
                     "--model", "3dgs", "--time-range", f"0:{last}", "--out", str(out),
                     "--set", "deformation.hexplane.spatial_resolution=8"]
                    + ([] if split == "paper" else ["--split", split])) == 0
        report = json.loads((out / "report.json").read_text())
        assert [p["frame"] for p in report["models"]["3dgs"]["per_frame"]] == want and want
        assert (report["scene"]["train_frames"], report["scene"]["test_frames"]) == (want_train, len(want))
        assert report["scene"]["time_range"] == [0, last] and report["split"] == split
    assert main(["recon", "--summarize", str(tmp_path / "reports")]) == 0
    summary = (tmp_path / "reports" / "summary.md").read_text()
    assert f"| smoke (frames 0-{last}) [" in summary and f"| smoke (frames 0-{last}, split novel-view) [" in summary
    capsys.readouterr()
    for bad in ("5:2", "a:b", "7", f"{scene.num_time_steps + 5}:{scene.num_time_steps + 9}"):
        assert main(["recon", "--scene", str(scene_dir), "--time-range", bad, "--out", str(tmp_path / "o")]) == 2
        assert "--time-range" in capsys.readouterr().err


def test_recon_command_rejects_bad_input(tmp_path, capsys):
    from benchmark.cli import main

    assert main(["recon", "--scene", str(tmp_path / "missing-folder")]) == 2
    scene_dir = write_dnerf_folder(tmp_path / "toy-dnerf", size=8)
    assert main(["recon", "--scene", str(scene_dir), "--set", "gaussians.no_such_field=1",
                 "--out", str(tmp_path / "o")]) == 2
    assert main(["recon", "--scene", str(scene_dir), "--set", "gaussians.sh_degree=abc",
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "no_such_field" in err and "sh_degree" in err


def test_each_stage_reports_its_iterations_through_the_progress_wrapper(moving_scene):
    bars: list[tuple[str, int, int]] = []

    def progress(iterable, desc=None, total=None):
        steps = list(iterable)
        bars.append((desc, total, len(steps)))
        return steps

    Trainer(moving_scene, small_recon_config(5, 7), rasterize_fn=RAST, progress=progress).fit_4dgs()
    assert bars == [("geometry (static)", 5, 5), ("geometry (deformation)", 7, 7)]


def _interrupting(after_calls: int):
    """The test rasterizer, raising KeyboardInterrupt on its ``after_calls + 1``-th call (one per iteration)."""
    calls = {"n": 0}

    def rast(*args, **kw):
        calls["n"] += 1
        if calls["n"] > after_calls:
            raise KeyboardInterrupt
        return RAST(*args, **kw)

    return rast


def test_an_interrupted_4dgs_fit_resumes_to_exactly_the_uninterrupted_model(moving_scene, tmp_path):
    # long enough for densification in both stages and for static checks before the deformation-stage stop
    cfg = small_recon_config(40, 60)
    cfg.deformation.hexplane.motion_cell_share = 0.75  # the default, stated: the motion box is resumed too
    reference = Trainer(moving_scene, cfg, rasterize_fn=RAST).fit_4dgs()
    ref_events = [[e for e in s["events"]] for s in reference.stages]
    assert any(e["event"] == "densify" for e in ref_events[0]) and any(e["event"] == "densify" for e in ref_events[1])
    # between the stages the motion box renders its views (one rasterizer call each, no iteration)
    box_renders = min(cfg.deformation.hexplane.motion_views, len(moving_scene.train_frames))
    for stop_after, resumed_at in ((23, {"stage": "static", "iteration": 23}),
                                   (40, {"stage": "static", "iteration": 40}),
                                   (40 + box_renders + 37, {"stage": "deformation", "iteration": 37})):
        ck = Checkpointing(tmp_path / f"fit-{stop_after}.pt", key="this fit", every_seconds=0.0)  # every iteration
        with pytest.raises(KeyboardInterrupt):
            Trainer(moving_scene, cfg, rasterize_fn=_interrupting(stop_after), checkpoint=ck).fit_4dgs()
        assert ck.path.is_file()
        resumed = Trainer(moving_scene, cfg, rasterize_fn=RAST, checkpoint=ck).fit_4dgs()
        assert resumed.resumed_at == resumed_at
        assert not ck.path.exists()  # a completed fit removes its checkpoint
        for name, value in reference.model.gaussians.params.items():
            assert torch.equal(resumed.model.gaussians.params[name], value), (stop_after, name)
        for name, value in reference.model.field.state_dict().items():
            assert torch.equal(resumed.model.field.state_dict()[name], value), (stop_after, name)
        assert torch.equal(resumed.model.dynamic_mask, reference.model.dynamic_mask)
        assert [s["events"] for s in resumed.stages] == ref_events
        assert [s["final_loss"] for s in resumed.stages] == [s["final_loss"] for s in reference.stages]
        assert resumed.fit_seconds > 0 and len(resumed.stages) == 2


def test_a_checkpoint_of_another_fit_is_not_resumed(moving_scene, tmp_path):
    cfg = small_recon_config(6, 0)
    ck = Checkpointing(tmp_path / "fit.pt", key="fit A", every_seconds=0.0)
    with pytest.raises(KeyboardInterrupt):
        Trainer(moving_scene, cfg, rasterize_fn=_interrupting(4), checkpoint=ck).fit_3dgs(6)
    other = Trainer(moving_scene, cfg, rasterize_fn=RAST,
                    checkpoint=Checkpointing(ck.path, key="fit B", every_seconds=1e9)).fit_3dgs(6)
    assert other.resumed_at is None and other.stages[0]["iterations"] == 6
    reference = Trainer(moving_scene, cfg, rasterize_fn=RAST).fit_3dgs(6)
    for name, value in reference.model.params.items():
        assert torch.equal(other.model.params[name], value)
    ck.path.write_bytes(b"not a checkpoint")  # unreadable: the fit starts over, never fails on it
    assert Trainer(moving_scene, cfg, rasterize_fn=RAST, checkpoint=ck).fit_3dgs(6).resumed_at is None


def test_a_fit_checkpoints_between_stages_but_not_as_it_completes(moving_scene, tmp_path, monkeypatch):
    saved = []
    real_save = torch.save
    monkeypatch.setattr(torch, "save", lambda obj, f, *a, **kw: (saved.append((obj["stage"], obj["iteration"])),
                                                                  real_save(obj, f, *a, **kw))[1])
    ck = Checkpointing(tmp_path / "fit.pt", key="k", every_seconds=1e9)  # no timed saves
    Trainer(moving_scene, small_recon_config(5, 6), rasterize_fn=RAST, checkpoint=ck).fit_4dgs()
    assert saved == [("static", 5)] and not ck.path.exists()  # the completed fit's last stage writes nothing
    saved.clear()
    Trainer(moving_scene, small_recon_config(5, 0), rasterize_fn=RAST, checkpoint=ck).fit_3dgs(5)
    assert saved == []


def test_even_subsample_stays_in_range_where_float32_spacing_exceeds_one():
    import torch

    from methods.gaussians.train import even_subsample

    n, k = 20_000_000, 1_000_000  # float32 spacing is 2 here: torch.linspace's last index rounds up to n
    idx = even_subsample(n, k)
    assert idx.dtype == torch.int64 and idx.shape == (k,)
    assert int(idx[0]) == 0 and int(idx[-1]) == n - 1 and bool((idx[1:] > idx[:-1]).all())
    gaps = idx[1:] - idx[:-1]
    assert int(gaps.min()) >= (n - 1) // (k - 1) and int(gaps.max()) <= (n - 1) // (k - 1) + 1
