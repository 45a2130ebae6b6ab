"""The Gaussian rasterizer: exactness against a dense brute-force compositor, gradients, edge cases.

The reference below is deliberately plain: every pixel against every Gaussian, sorted by depth,
written from the 3D-GS definitions (EWA projection with the 1.3x-FOV Jacobian clamp, eps2d dilation,
alpha = min(0.99, o exp(-d^T conic d / 2)), skip alpha < 1/255, stop before T < 1e-4).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from benchmark.core.errors import InputError
from benchmark.core.scene import Camera
from methods.gaussians import camera_tensors, rasterize
from methods.gaussians.backends import native_cpu, torch_cpu
from methods.gaussians.backends.gsplat_cuda import gsplat_available
from methods.gaussians.sh import eval_sh, num_sh_bases, rgb_to_sh0, sh0_to_rgb, sh_basis

F64 = torch.float64


@pytest.fixture(params=["native", "torch"])
def compositor(request, monkeypatch):
    """Runs a test with the compiled kernels (``native``, where a C compiler builds them) and with the
    PyTorch passes (``torch``, as without a compiler)."""
    if request.param == "torch":
        monkeypatch.setenv("BENCH4D_NATIVE", "0")
    else:
        monkeypatch.delenv("BENCH4D_NATIVE", raising=False)
        if native_cpu.kernels() is None:
            pytest.skip(f"the compiled kernels do not build here: {native_cpu.unavailable_reason()}")
    return request.param


def _uses_native(scene) -> bool:
    """Whether torch_cpu.render composites ``scene`` with the compiled kernels right now."""
    means, quats, scales, opac, colors, viewmat, K, W, H, bg = scene
    r = torch_cpu.render(means, quats, scales, opac, colors, viewmat, K, W, H, bg, 0.01, 50.0, 64, 0.3)
    return isinstance(r.layout, native_cpu.NativeLayout)


# --------------------------------------------------------------------------------------------
# reference
# --------------------------------------------------------------------------------------------
def reference_render(means, quats, scales, opac, colors, viewmat, K, W, H, bg=None, near=0.01, far=1e10,
                     eps2d=0.3):
    """Dense [pixels x Gaussians] front-to-back compositing. Returns (image, alpha, depth)."""
    dt = means.dtype
    q = quats / quats.norm(dim=1, keepdim=True)
    w, x, y, z = q.T
    R = torch.stack([torch.stack([w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     torch.stack([2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)], -1),
                     torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z], -1)], 1)
    sigma3 = R @ torch.diag_embed(scales ** 2) @ R.transpose(1, 2)
    rv, tv = viewmat[:3, :3], viewmat[:3, 3]
    pc = means @ rv.T + tv
    zc = pc[:, 2]
    ok = (zc > near) & (zc < far)
    zs = torch.where(ok, zc, torch.ones_like(zc))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    mean2d = torch.stack([fx * pc[:, 0] / zs + cx, fy * pc[:, 1] / zs + cy], -1)
    xl = torch.clamp(pc[:, 0] / zs, -(cx / fx + 0.15 * W / fx), (W - cx) / fx + 0.15 * W / fx) * zs
    yl = torch.clamp(pc[:, 1] / zs, -(cy / fy + 0.15 * H / fy), (H - cy) / fy + 0.15 * H / fy) * zs
    J = torch.zeros(len(means), 2, 3, dtype=dt)
    J[:, 0, 0] = fx / zs
    J[:, 0, 2] = -fx * xl / zs ** 2
    J[:, 1, 1] = fy / zs
    J[:, 1, 2] = -fy * yl / zs ** 2
    cov = J @ rv @ sigma3 @ rv.T @ J.transpose(1, 2) + eps2d * torch.eye(2, dtype=dt)
    ok = ok & (torch.linalg.det(cov) > 0)
    conic = torch.linalg.inv(torch.where(ok[:, None, None], cov, torch.eye(2, dtype=dt)))
    jj, ii = torch.meshgrid(torch.arange(W, dtype=dt) + 0.5, torch.arange(H, dtype=dt) + 0.5, indexing="xy")
    pix = torch.stack([jj, ii], -1).reshape(-1, 2)
    d = pix[:, None, :] - mean2d[None]
    power = 0.5 * torch.einsum("pni,nij,pnj->pn", d, conic, d)
    alpha = torch.clamp(opac[None] * torch.exp(-power), max=0.99)
    alpha = torch.where(ok[None] & (alpha >= 1 / 255), alpha, torch.zeros_like(alpha))
    order = torch.sort(zc, stable=True).indices
    alpha = alpha[:, order]
    t_after = torch.cumprod(1 - alpha, 1)
    alpha = alpha * (t_after >= 1e-4)  # stop before the pair that brings T below 1e-4
    t_after = torch.cumprod(1 - alpha, 1)
    t_before = torch.cat([torch.ones_like(t_after[:, :1]), t_after[:, :-1]], 1)
    wts = alpha * t_before
    acc = wts.sum(1)
    if bg is None:
        bg = torch.zeros(colors.shape[1], dtype=dt)
    img = wts @ colors[order] + (1 - acc)[:, None] * bg
    depth = (wts @ zc[order]) / acc.clamp_min(1e-10)
    return img.reshape(H, W, -1), acc.reshape(H, W), depth.reshape(H, W)


# --------------------------------------------------------------------------------------------
# scenes
# --------------------------------------------------------------------------------------------
def _random_rotation(g: torch.Generator, angle: float) -> torch.Tensor:
    axis = torch.randn(3, generator=g, dtype=F64)
    axis = axis / axis.norm()
    kx = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=F64)
    return torch.eye(3, dtype=F64) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def random_scene(seed: int, channels: int, width: int = 30, height: int = 22, n_overlap: int = 60):
    """A camera plus a hard mix: a dense overlapping cluster, Gaussians straddling the camera plane and
    behind it, off-screen ones whose footprint reaches into the image, huge ones, near-opaque ones
    (alpha clamp), and one beyond ``far = 50``."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=F64)  # noqa: E731
    fx, fy = 0.9 * width, 0.85 * width
    K = torch.tensor([[fx, 0, 0.45 * width], [0, fy, 0.55 * height], [0, 0, 1]], dtype=F64)
    rot = _random_rotation(g, 0.4)
    viewmat = torch.eye(4, dtype=F64)
    viewmat[:3, :3] = rot
    viewmat[:3, 3] = torch.randn(3, generator=g, dtype=F64) * 0.5
    groups = []

    def add(n, z_lo, z_hi, lateral, s_lo, s_hi, o_lo, o_hi):
        z = z_lo + (z_hi - z_lo) * r(n)
        xy = (r(n, 2) * 2 - 1) * lateral * z[:, None]
        groups.append((torch.cat([xy, z[:, None]], 1), s_lo + (s_hi - s_lo) * r(n, 3), o_lo + (o_hi - o_lo) * r(n)))

    add(n_overlap, 2.0, 4.0, 0.35, 0.03, 0.25, 0.05, 0.95)  # dense overlapping cluster
    add(4, 0.02, 0.6, 0.3, 0.2, 0.8, 0.02, 0.06)  # centre in front, footprint straddles the camera plane
    add(4, -2.0, -0.05, 0.3, 0.2, 1.0, 0.5, 0.9)  # behind the camera: culled
    add(8, 1.5, 3.0, 0.9, 0.1, 0.5, 0.3, 0.9)  # off-screen centres, footprints reaching in (lateral 0.9 > fov)
    add(3, 3.0, 5.0, 0.2, 1.0, 2.5, 0.03, 0.15)  # huge
    add(1, 60.0, 61.0, 0.1, 1.0, 2.0, 0.9, 0.9)  # beyond far = 50
    cam_pts = torch.cat([p for p, _, _ in groups])
    scales = torch.cat([s for _, s, _ in groups])
    opac = torch.cat([o for _, _, o in groups])
    opac[:n_overlap:9] = 0.995  # clamped at 0.99 near their centres
    n = cam_pts.shape[0]
    means = (cam_pts - viewmat[:3, 3]) @ rot  # world = R^T (cam - t)
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    colors = torch.randn(n, channels, generator=g, dtype=F64)
    bg = torch.randn(channels, generator=g, dtype=F64)
    return means, quats, scales, opac, colors, viewmat, K, width, height, bg


def _assert_matches_reference(scene, far=50.0, atol=1e-9, **kw):
    means, quats, scales, opac, colors, viewmat, K, W, H, bg = scene
    out = rasterize(means, quats, scales, opac, colors, viewmat, K, W, H, background=bg, far=far,
                    backend="torch", **kw)
    img, acc, depth = reference_render(means, quats, scales, opac, colors, viewmat, K, W, H, bg, far=far)
    assert out.n_overflow_tiles == 0
    assert out.image.shape == (H, W, colors.shape[1])
    assert (out.image - img).abs().max().item() < atol
    assert (out.alpha - acc).abs().max().item() < atol
    assert (out.depth - depth).abs().max().item() < atol * 100  # depths are O(10)
    return out, acc


# --------------------------------------------------------------------------------------------
# exactness
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("channels,seed", [(3, 0), (6, 1), (16, 2), (512, 3)])
def test_matches_brute_force(channels, seed, compositor):
    scene = random_scene(seed, channels)
    assert _uses_native(scene) == (compositor == "native")
    out, acc = _assert_matches_reference(scene)
    # the scene exercises what it claims: opaque regions, empty regions, culled and visible Gaussians
    assert acc.max() > 0.999 and acc.min() < 0.5
    vis = out.visible
    assert vis.any() and not vis.all()
    assert torch.equal(vis, out.radii > 0)
    assert out.n_pairs > 0 and out.n_candidates >= out.n_pairs


def test_matches_brute_force_float32(compositor):
    scene = random_scene(4, 6)
    scene32 = tuple(t.float() if torch.is_tensor(t) else t for t in scene)
    assert _uses_native(scene32) == (compositor == "native")
    means, quats, scales, opac, colors, viewmat, K, W, H, bg = scene32
    out = rasterize(means, quats, scales, opac, colors, viewmat, K, W, H, background=bg, far=50.0)
    img, acc, depth = reference_render(*[t.double() if torch.is_tensor(t) else t for t in scene32], far=50.0)
    assert (out.image.double() - img).abs().max() < 1e-5
    assert (out.alpha.double() - acc).abs().max() < 1e-5
    assert ((out.depth.double() - depth).abs() / depth.abs().clamp_min(1)).max() < 1e-5


def test_many_layers_terminate_early(compositor):
    """A deep stack of opaque Gaussians: transmittance hits 1e-4 inside the stack, across chunks."""
    g = torch.Generator().manual_seed(7)
    n = 150
    means = torch.cat([(torch.rand(n, 2, generator=g, dtype=F64) - 0.5) * 0.8,
                       2 + torch.rand(n, 1, generator=g, dtype=F64) * 3], 1)
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    scales = 0.2 + 0.2 * torch.rand(n, 3, generator=g, dtype=F64)
    opac = 0.7 + 0.25 * torch.rand(n, generator=g, dtype=F64)
    colors = torch.rand(n, 4, generator=g, dtype=F64)
    K = torch.tensor([[20.0, 0, 10], [0, 20, 9], [0, 0, 1]], dtype=F64)
    scene = (means, quats, scales, opac, colors, torch.eye(4, dtype=F64), K, 20, 18, torch.zeros(4, dtype=F64))
    out, acc = _assert_matches_reference(scene)
    assert (acc > 1 - 1e-3).float().mean() > 0.25  # a quarter of the pixels is opaque
    # many pairs with alpha >= 1/255 lie behind the opaque front and are never composited
    no_stop = torch_cpu.CompositingRule(transmittance_min=0.0)
    all_pairs = torch_cpu.render(*scene[:7], 20, 18, scene[9], 0.01, 1e10, 64, 0.3, rule=no_stop).n_pairs
    assert out.n_pairs < 0.75 * all_pairs


@pytest.mark.parametrize("tile_size,slots,block_entries,cull", [(2, 3, 64, True), (8, 5, 4096, True),
                                                                (4, 2, 1 << 22, False)])
def test_layout_does_not_change_the_result(tile_size, slots, block_entries, cull):
    """Tiles, chunk length, block splitting and the ellipse-tile cull only change speed: image and
    gradients are identical."""
    means, quats, scales, opac, colors, viewmat, K, W, H, bg = random_scene(5, 5, n_overlap=40)
    params = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
    results = []
    for cfg in (torch_cpu.TorchRasterConfig(native=False),
                torch_cpu.TorchRasterConfig(tile_size=tile_size, slots=slots, cull_corners=cull,
                                            block_entries=block_entries, native=False)):
        for p in params:
            p.grad = None
        r = torch_cpu.render(*params, viewmat, K, W, H, bg, 0.01, 50.0, 64, 0.3, config=cfg)
        ((r.image ** 2).sum() + r.alpha.sum() + r.depth.sum()).backward()
        results.append((r.image.detach(), r.alpha.detach(), r.depth.detach(), [p.grad.clone() for p in params],
                        r.n_candidates))
    (i0, a0, d0, g0, n0), (i1, a1, d1, g1, n1) = results
    if not cull:
        assert n0 < 0.95 * n1  # the ellipse test does drop candidates
    assert torch.allclose(i0, i1, atol=1e-12) and torch.allclose(a0, a1, atol=1e-12)
    assert torch.allclose(d0, d1, atol=1e-10)
    for x, y in zip(g0, g1):
        assert torch.allclose(x, y, atol=1e-8, rtol=1e-8)


def test_channel_chunks_equal_one_pass(compositor):
    means, quats, scales, opac, colors, viewmat, K, W, H, bg = random_scene(6, 512, n_overlap=30)
    outs = []
    for chunk in (64, 1024):
        cols = colors.clone().requires_grad_(True)
        mu = means.clone().requires_grad_(True)
        out = rasterize(mu, quats, scales, opac, cols, viewmat, K, W, H, background=bg, far=50.0,
                        channel_chunk=chunk)
        (out.image.sin().sum() + out.depth.sum()).backward()
        outs.append((out.image.detach(), cols.grad, mu.grad))
    for x, y in zip(*outs):
        assert torch.allclose(x, y, atol=1e-10)


# --------------------------------------------------------------------------------------------
# gradients
# --------------------------------------------------------------------------------------------
def _gradcheck_scene(channels: int, opaque_stack: bool):
    g = torch.Generator().manual_seed(11 if opaque_stack else 12)
    n = 7
    xy = (torch.rand(n, 2, generator=g, dtype=F64) - 0.5) * 0.8
    z = 3 + torch.rand(n, 1, generator=g, dtype=F64)
    means = torch.cat([xy * z, z], 1)
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    scales = 0.25 + 0.35 * torch.rand(n, 3, generator=g, dtype=F64)
    if opaque_stack:  # transmittance falls below 1e-4 inside the stack: gradients through termination
        means[:4, :2] = 0.0
        opac = torch.tensor([0.98, 0.97, 0.985, 0.96, 0.5, 0.6, 0.7], dtype=F64)
    else:
        opac = 0.3 + 0.5 * torch.rand(n, generator=g, dtype=F64)
    colors = torch.rand(n, channels, generator=g, dtype=F64)
    K = torch.tensor([[7.0, 0, 4.2], [0, 7.5, 3.9], [0, 0, 1]], dtype=F64)
    return means, quats, scales, opac, colors, K


@pytest.mark.parametrize("channels,opaque_stack", [(3, False), (5, True)])
def test_gradcheck(channels, opaque_stack, compositor):
    """float64 finite differences for means, rotations, scales, opacities, colours / features."""
    means, quats, scales, opac, colors, K = _gradcheck_scene(channels, opaque_stack)
    viewmat = torch.eye(4, dtype=F64)
    viewmat[:3, 3] = torch.tensor([0.05, -0.03, 0.1], dtype=F64)
    bg = torch.linspace(0.1, 0.9, channels, dtype=F64)

    def fn(m, q, s, o, c):
        out = rasterize(m, q, s, o, c, viewmat, K, 8, 8, background=bg, backend="torch")
        return out.image, out.alpha, out.depth

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors))
    out = rasterize(*inputs, viewmat, K, 8, 8, background=bg)
    assert out.visible.all() and out.n_pairs > 30
    if opaque_stack:
        assert out.alpha.max() > 1 - 1e-3  # the stack is opaque somewhere
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_gradients_match_dense_reference(compositor):
    """Analytic backward vs autograd through the dense reference on the hard random scene."""
    means, quats, scales, opac, colors, viewmat, K, W, H, bg = random_scene(8, 4, n_overlap=50)
    gen = torch.Generator().manual_seed(0)
    g_img, g_a, g_d = (torch.randn(H, W, 4, generator=gen, dtype=F64), torch.randn(H, W, generator=gen, dtype=F64),
                       torch.randn(H, W, generator=gen, dtype=F64))
    grads = []
    for which in ("torch", "reference"):
        ps = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors, bg)]
        if which == "torch":
            out = rasterize(*ps[:5], viewmat, K, W, H, background=ps[5], far=50.0)
            img, acc, depth = out.image, out.alpha, out.depth
        else:
            img, acc, depth = reference_render(*ps[:5], viewmat, K, W, H, ps[5], far=50.0)
        loss = (img * g_img).sum() + (acc * g_a).sum() + (depth * g_d).sum()
        grads.append(torch.autograd.grad(loss, ps))
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors", "background"), *grads):
        assert torch.allclose(a, b, atol=1e-8, rtol=1e-7), name


def test_means2d_grad_for_densification(compositor):
    means, quats, scales, opac, colors, viewmat, K, W, H, bg = random_scene(9, 3, n_overlap=20)
    ps = [t.float().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
    out = rasterize(*ps, viewmat.float(), K.float(), W, H, far=50.0)
    out.image.square().sum().backward()
    g = out.means2d.grad
    assert g is not None and g.shape == (len(means), 2)
    assert torch.all(g[~out.visible] == 0)
    assert (g[out.visible].abs().sum(1) > 0).float().mean() > 0.8


# --------------------------------------------------------------------------------------------
# edge cases, conventions, validation
# --------------------------------------------------------------------------------------------
def test_empty_and_fully_culled_scenes_render_background(compositor):
    K = torch.tensor([[10.0, 0, 5], [0, 10, 4.5], [0, 0, 1]])
    bg = torch.tensor([0.1, 0.2, 0.3])
    for n, z in ((0, 1.0), (3, -1.0)):
        means = torch.zeros(n, 3)
        means[:, 2] = z
        ps = [means.requires_grad_(True), torch.tensor([[1.0, 0, 0, 0]] * n).reshape(n, 4),
              torch.full((n, 3), 0.1), torch.full((n,), 0.5), torch.ones(n, 3, requires_grad=True)]
        out = rasterize(*ps, torch.eye(4), K, 10, 9, background=bg)
        assert torch.equal(out.image, bg.expand(9, 10, 3))
        assert out.alpha.abs().max() == 0 and out.depth.abs().max() == 0
        assert out.n_pairs == 0 and out.n_overflow_tiles == 0 and not out.visible.any()
        out.image.sum().backward()  # still part of the graph (zero gradients), no error
        assert ps[0].grad is not None and ps[0].grad.abs().sum() == 0


def test_camera_conventions_pixel_centres(compositor):
    """A small Gaussian at a world point lands on the pixel whose centre Camera.project gives."""
    c2w = np.eye(4)
    c2w[:3, 3] = [0.3, -0.2, -4.0]
    cam = Camera(16, 12, 20.0, 20.0, 7.0, 6.5, np.linalg.inv(c2w))
    viewmat, K, W, H = camera_tensors(cam, dtype=F64)
    assert (W, H) == (16, 12) and viewmat.dtype == F64
    # choose the point that projects exactly to the centre of pixel (row 4, col 10): (u, v) = (10.5, 4.5)
    z = 4.0
    pt_cam = np.array([(10.5 - cam.cx) * z / cam.fx, (4.5 - cam.cy) * z / cam.fy, z])
    pt = (np.linalg.inv(cam.world_to_camera) @ np.append(pt_cam, 1))[:3]
    uv, _ = cam.project(pt[None])
    assert np.allclose(uv[0], [10.5, 4.5])
    out = rasterize(torch.tensor(pt[None], dtype=F64), torch.tensor([[1.0, 0, 0, 0]], dtype=F64),
                    torch.full((1, 3), 0.02, dtype=F64), torch.tensor([0.9], dtype=F64), torch.ones(1, 1, dtype=F64),
                    viewmat, K, W, H)
    a = out.alpha
    assert divmod(int(a.argmax()), W) == (4, 10)
    assert torch.isclose(a[4, 9], a[4, 11]) and torch.isclose(a[3, 10], a[5, 10])  # symmetric about the centre
    assert torch.allclose(out.means2d[0], torch.tensor([10.5, 4.5], dtype=F64))
    assert torch.isclose(out.depth[4, 10], torch.tensor(z, dtype=F64))


def test_invalid_inputs_raise_input_error():
    n = 2
    good = dict(means=torch.zeros(n, 3), quats=torch.ones(n, 4), scales=torch.ones(n, 3), opacities=torch.ones(n) * 0.5,
                colors=torch.ones(n, 3), viewmat=torch.eye(4), K=torch.eye(3), width=4, height=4)
    for field, bad in (("means", torch.zeros(n, 2)), ("quats", torch.ones(n, 3)), ("colors", torch.ones(n, 0)),
                       ("opacities", torch.ones(n, 1)), ("K", torch.eye(4)), ("width", 0)):
        with pytest.raises(InputError, match=field.split("/")[0]):
            rasterize(**{**good, field: bad})
    with pytest.raises(InputError, match="background"):
        rasterize(**good, background=torch.zeros(4))
    with pytest.raises(InputError, match="backend"):
        rasterize(**good, backend="cuda-magic")
    with pytest.raises(InputError, match="gsplat"):  # CPU tensors (or no gsplat at all)
        rasterize(**good, backend="gsplat")
    out = rasterize(**good)  # the good inputs do render
    assert out.image.shape == (4, 4, 3)


# --------------------------------------------------------------------------------------------
# the compiled kernels against the PyTorch passes
# --------------------------------------------------------------------------------------------
def _render_and_grads(scene, cfg, seed=0):
    means, quats, scales, opac, colors, viewmat, K, W, H, bg = scene
    params = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
    r = torch_cpu.render(*params, viewmat, K, W, H, bg, 0.01, 50.0, 64, 0.3, config=cfg)
    r.proj.means2d.retain_grad()
    gen = torch.Generator().manual_seed(seed)
    weights = [torch.randn(t.shape, generator=gen, dtype=t.dtype) for t in (r.image, r.alpha, r.depth)]
    sum(((t * w).sum() for t, w in zip((r.image, r.alpha, r.depth), weights))).backward()
    return r, [r.image.detach(), r.alpha.detach(), r.depth.detach()], [p.grad for p in params] + [r.proj.means2d.grad]


@pytest.mark.parametrize("tile_size", [3, 4, 8, 16])
def test_native_kernels_equal_the_pytorch_passes_in_float64(tile_size):
    """Image, alpha, depth and every gradient (the densification's means2d one too) agree to rounding,
    whatever the tile size (3: lanes padded; 16: many pixels per list)."""
    if native_cpu.kernels() is None:
        pytest.skip(f"the compiled kernels do not build here: {native_cpu.unavailable_reason()}")
    scene = random_scene(10 + tile_size, 5, n_overlap=60)
    r_torch, out_torch, grads_torch = _render_and_grads(scene, torch_cpu.TorchRasterConfig(native=False))
    r_nat, out_nat, grads_nat = _render_and_grads(scene, torch_cpu.TorchRasterConfig(native_tile_size=tile_size))
    assert isinstance(r_nat.layout, native_cpu.NativeLayout) and isinstance(r_torch.layout, torch_cpu.TileLayout)
    for a, b in zip(out_torch, out_nat):
        assert torch.allclose(a, b, atol=1e-12, rtol=1e-12)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors", "means2d"), grads_torch, grads_nat):
        assert torch.allclose(a, b, atol=1e-10, rtol=1e-9), name
    assert torch.equal(r_torch.proj.visible, r_nat.proj.visible) and torch.equal(r_torch.proj.radii, r_nat.proj.radii)
    assert r_nat.n_pairs > 0


def test_native_kernels_agree_with_the_pytorch_passes_in_float32():
    """A training-like float32 scene (10 000 surface Gaussians at 64 x 48): the kernels' float32 image and
    gradients are those of the PyTorch passes up to float32 rounding."""
    if native_cpu.kernels() is None:
        pytest.skip(f"the compiled kernels do not build here: {native_cpu.unavailable_reason()}")
    from benchmark.studies.rasterizer_bench import surface_scene

    sc = surface_scene(10_000, 64, 48, channels=4, seed=1)
    scene = (sc.means, sc.quats, sc.scales, sc.opacities, sc.colors, sc.viewmat, sc.K, sc.width, sc.height,
             torch.zeros(4))
    _, out_torch, grads_torch = _render_and_grads(scene, torch_cpu.TorchRasterConfig(native=False))
    _, out_nat, grads_nat = _render_and_grads(scene, torch_cpu.TorchRasterConfig())
    assert (out_torch[0] - out_nat[0]).abs().max() < 2e-5 and (out_torch[1] - out_nat[1]).abs().max() < 2e-5
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors", "means2d"), grads_torch, grads_nat):
        err = (a - b).norm() / a.norm()
        assert err < 1e-4, (name, float(err))


def test_the_pytorch_passes_serve_when_the_kernels_do_not_build(monkeypatch, tmp_path):
    """No working C compiler: rendering goes on with the PyTorch passes, and the reason is kept."""
    monkeypatch.setattr(native_cpu, "_STATE", {})
    monkeypatch.setenv("BENCH4D_NATIVE_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", "false")  # a "compiler" that fails on every input
    monkeypatch.setattr(native_cpu, "_compiler", lambda: shutil_which("false"))
    assert native_cpu.kernels() is None
    assert "failed" in native_cpu.unavailable_reason()
    scene = random_scene(3, 3)
    assert not _uses_native(scene)
    _assert_matches_reference(scene)
    monkeypatch.setenv("BENCH4D_NATIVE", "0")
    assert "BENCH4D_NATIVE=0" in native_cpu.unavailable_reason()


def shutil_which(name: str):
    import shutil

    return shutil.which(name)


# --------------------------------------------------------------------------------------------
# spherical harmonics
# --------------------------------------------------------------------------------------------
def test_sh_basis_is_orthonormal_and_colour_roundtrips():
    # Fibonacci sphere quadrature: integral of Y_i Y_j over the sphere = delta_ij
    m = 40_000
    i = torch.arange(m, dtype=F64) + 0.5
    zc = 1 - 2 * i / m
    phi = math.pi * (1 + 5 ** 0.5) * i
    rxy = torch.sqrt(1 - zc ** 2)
    dirs = torch.stack([rxy * torch.cos(phi), rxy * torch.sin(phi), zc], -1)
    basis = sh_basis(3, dirs)
    assert basis.shape == (m, num_sh_bases(3)) == (m, 16)
    gram = basis.T @ basis * (4 * math.pi / m)
    assert torch.allclose(gram, torch.eye(16, dtype=F64), atol=2e-3)
    rgb = torch.rand(5, 3, dtype=F64)
    assert torch.allclose(sh0_to_rgb(rgb_to_sh0(rgb)), rgb)
    coeffs = torch.zeros(5, 16, 3, dtype=F64)
    coeffs[:, 0] = rgb_to_sh0(rgb)
    assert torch.allclose(eval_sh(3, coeffs, dirs[:5]) + 0.5, rgb)  # degree 0 is view-independent


# --------------------------------------------------------------------------------------------
# CUDA parity (runs wherever a CUDA GPU and gsplat are present)
# --------------------------------------------------------------------------------------------
@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_gsplat_matches_torch_backend_on_cuda():
    if not gsplat_available():
        pytest.skip("gsplat is not importable")
    from benchmark.studies.rasterizer_bench import surface_scene

    sc = surface_scene(3000, 64, 64, channels=6, seed=3)
    dev = torch.device("cuda")
    ps_cpu = [t.clone().requires_grad_(True) for t in (sc.means, sc.quats, sc.scales, sc.opacities, sc.colors)]
    ps_gpu = [t.detach().to(dev).requires_grad_(True) for t in ps_cpu]
    bg = torch.linspace(0, 1, 6)
    outs = []
    for ps, d, backend in ((ps_cpu, "cpu", "torch"), (ps_gpu, dev, "gsplat")):
        out = rasterize(*ps, sc.viewmat.to(d), sc.K.to(d), sc.width, sc.height, background=bg.to(d), backend=backend)
        assert out.backend == backend
        (out.image.square().sum() + out.alpha.sum()).backward()
        outs.append(out)
    a, b = outs
    diff = (a.image - b.image.cpu()).abs()
    # opacities <= 0.9 keep both below their alpha clamps; remaining differences are gsplat's 3-sigma rims
    assert diff.mean() < 5e-3 and diff.quantile(0.99) < 3e-2
    assert (a.alpha - b.alpha.cpu()).abs().mean() < 5e-3
    m = (a.alpha > 0.5) & (b.alpha.cpu() > 0.5)
    assert ((a.depth - b.depth.cpu()).abs()[m] / a.depth[m]).median() < 1e-2
    assert (a.visible == b.visible.cpu()).float().mean() > 0.98
    assert b.means2d.grad is not None and b.means2d.grad.shape == (3000, 2)
    # densification reads the screen-space gradient: both backends must give it in the same (pixel) units
    g2a, g2b = a.means2d.grad.flatten(), b.means2d.grad.cpu().flatten()
    assert torch.nn.functional.cosine_similarity(g2a, g2b, dim=0) > 0.9
    assert 0.8 < float(g2b.norm() / g2a.norm()) < 1.25
    for p, q in zip(ps_cpu, ps_gpu):
        cos = torch.nn.functional.cosine_similarity(p.grad.flatten(), q.grad.cpu().flatten(), dim=0)
        assert cos > 0.9
