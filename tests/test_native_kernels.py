"""The compiled CPU kernels beyond the rasterizer: each against the PyTorch code it replaces (same
values and gradients up to rounding), so that switching them on (the default where a C compiler is)
changes no fit beyond float noise. ``BENCH4D_NATIVE=0`` runs the PyTorch code."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from methods.gaussians.backends import native_cpu
from methods.gaussians.config import DeformationConfig, GaussianConfig, HexPlaneConfig
from methods.gaussians.hexplane import DeformationField, HexPlane
from methods.gaussians.model import GaussianModel

F64 = torch.float64


@pytest.fixture(autouse=True)
def kernels_built():
    if native_cpu.kernels() is None:
        pytest.skip(f"the compiled kernels do not build here: {native_cpu.unavailable_reason()}")


def both(monkeypatch, run):
    """``run()`` with the kernels, then with the PyTorch code."""
    monkeypatch.delenv("BENCH4D_NATIVE", raising=False)
    native = run()
    monkeypatch.setenv("BENCH4D_NATIVE", "0")
    plain = run()
    monkeypatch.delenv("BENCH4D_NATIVE", raising=False)
    return native, plain


def _close(a, b, atol, rtol=0.0):
    for x, y in zip(a, b):
        assert torch.allclose(x, y, atol=atol, rtol=rtol), float((x - y).abs().max())


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_hexplane_features_and_gradients(monkeypatch, dtype):
    """Points inside, on the border and outside the plane box (clipped: no gradient), a per-point time."""
    torch.manual_seed(0)
    field = DeformationField(DeformationConfig(hexplane=HexPlaneConfig(spatial_resolution=8, multires=(1, 2))),
                             torch.tensor([[-1.0, -1, -1], [1, 1, 1]]), 5).to(dtype)
    with torch.no_grad():
        for plane in field.hexplane.temporal:
            plane.add_(0.3 * torch.randn_like(plane))
    xyz = torch.rand(400, 3, dtype=dtype) * 2.6 - 1.3
    xyz[0] = torch.tensor([1.0, -1.0, 0.0])  # exactly on the box's faces
    times = torch.rand(400, dtype=dtype)

    def run():
        for p in field.parameters():
            p.grad = None
        x, t = xyz.clone().requires_grad_(True), times.clone().requires_grad_(True)
        feat = field.hexplane(x, t)
        weights = torch.randn(feat.shape, generator=torch.Generator().manual_seed(1), dtype=dtype)
        (feat * weights).sum().backward()
        return [feat.detach(), x.grad, t.grad] + [p.grad.clone() for p in field.hexplane.parameters()]

    native, plain = both(monkeypatch, run)
    # on the box's faces the clipped coordinates pass no gradient, the third one does
    for grads in (native[1], plain[1]):
        assert grads[0, 0] == 0 and grads[0, 1] == 0 and grads[0, 2] != 0 and grads[1:].abs().sum() > 0
    _close(native, plain, atol=1e-12 if dtype == F64 else 2e-4, rtol=1e-10 if dtype == F64 else 1e-4)


def test_hexplane_regularisers_each_term(monkeypatch):
    torch.manual_seed(1)
    plane = HexPlane(HexPlaneConfig(spatial_resolution=8, output_dim=4, multires=(1, 2)),
                     torch.tensor([[-1.0] * 3, [1.0] * 3]), 6).double()
    with torch.no_grad():
        for tp in plane.temporal:
            tp.add_(0.2 * torch.randn_like(tp))
            tp.view(-1)[:3] = 1.0  # |1 - P| at its kink

    def run():
        out = []
        regs = plane.regularisers()
        for name in ("plane_tv", "time_smoothness", "l1_time_planes"):
            params = list(plane.parameters())
            grads = torch.autograd.grad(regs[name], params, retain_graph=True, allow_unused=True)
            out += [regs[name].detach()] + [torch.zeros_like(p) if g is None else g for g, p in zip(grads, params)]
        return out

    native, plain = both(monkeypatch, run)
    _close(native, plain, atol=1e-12, rtol=1e-10)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_sh_colours_and_gradients(monkeypatch, degree):
    rng = np.random.default_rng(degree)
    model = GaussianModel.from_points(rng.random((300, 3)).astype(np.float32), rng.random((300, 3)).astype(np.float32),
                                      GaussianConfig())
    model.params = {k: v.double().detach() for k, v in model.params.items()}
    with torch.no_grad():
        model.params["sh_rest"].normal_(0, 0.3)
        model.params["sh_dc"].normal_(0, 1.0)  # some colours clamp at 0
    for name in ("sh_dc", "sh_rest"):
        model.params[name].requires_grad_(True)
    model.active_sh_degree = degree
    centre = torch.tensor([0.1, -0.2, -3.0], dtype=F64)

    def run():
        means = model.params["means"].clone().requires_grad_(True)
        for name in ("sh_dc", "sh_rest"):
            model.params[name].grad = None
        colours = model.colors(centre, means)
        weights = torch.randn(colours.shape, generator=torch.Generator().manual_seed(3), dtype=F64)
        (colours * weights).sum().backward()
        return [colours.detach(), means.grad, model.params["sh_dc"].grad.clone(), model.params["sh_rest"].grad.clone()]

    native, plain = both(monkeypatch, run)
    assert (plain[0] == 0).any()
    _close(native, plain, atol=1e-12, rtol=1e-10)


def test_blend_operator_from_the_kernels_equals_the_pytorch_one(monkeypatch):
    """The recorded blending operator of the time-varying field: the kernels list the same weights."""
    from benchmark.core.scene import Camera
    from methods.fields.language_field import GaussianState
    from methods.fields.time_varying import blend_operator

    gen = torch.Generator().manual_seed(4)
    n = 600
    means = torch.cat([(torch.rand(n, 2, generator=gen) - 0.5) * 2.4, 3 + torch.rand(n, 1, generator=gen)], 1)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=-1)
    state = GaussianState(means, quats, 0.05 + 0.2 * torch.rand(n, 3, generator=gen),
                          0.2 + 0.7 * torch.rand(n, generator=gen))
    camera = Camera(40, 30, 36.0, 36.0, 20.0, 15.0, np.eye(4))
    pixels = torch.arange(0, 40 * 30, 3)

    def run():
        op = blend_operator(state, camera, pixels)
        assert op is not None
        return [op.w.to_dense(), op.outside]

    native, plain = both(monkeypatch, run)
    assert native[0].count_nonzero() == plain[0].count_nonzero() > 1000
    _close(native, plain, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_ssim_and_its_gradient(monkeypatch, dtype):
    """The training loss's SSIM (zero-padded separable window): value and gradient in the rendered image."""
    from methods.gaussians.train import gaussian_window, ssim

    gen = torch.Generator().manual_seed(6)
    img = torch.rand(37, 26, 3, generator=gen, dtype=dtype)
    ref = (img + 0.2 * torch.randn(img.shape, generator=gen, dtype=dtype)).clamp(0, 1)

    def run():
        x = img.clone().requires_grad_(True)
        value = ssim(x, ref, gaussian_window(11, 1.5))
        (2.5 * value).backward()
        return [value.detach(), x.grad]

    native, plain = both(monkeypatch, run)
    _close(native, plain, atol=1e-12 if dtype == F64 else 1e-6, rtol=1e-10 if dtype == F64 else 1e-4)


def test_a_damaged_cached_library_is_built_again(tmp_path):
    """A truncated library in the cache (an interrupted copy, a full disk) is rebuilt, not a silent fallback."""
    if native_cpu._compiler() is None:
        pytest.skip("needs a C compiler")
    built = native_cpu._build(tmp_path)
    good = built.read_bytes()
    built.write_bytes(good[:200])  # damaged: not a loadable library any more
    lib = native_cpu._load(tmp_path)
    assert lib is not None and built.read_bytes() == good


def test_results_record_whether_the_compiled_kernels_ran(monkeypatch):
    from benchmark.runner import device_description

    monkeypatch.setattr(native_cpu, "_STATE", {})
    monkeypatch.setenv("BENCH4D_NATIVE", "0")
    assert device_description("cpu")["native_kernels"] == "not used: switched off by BENCH4D_NATIVE=0"
    monkeypatch.setenv("BENCH4D_NATIVE", "1")
    if native_cpu._compiler() is not None:
        assert device_description("cpu")["native_kernels"] == "loaded"
