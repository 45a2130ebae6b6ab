"""What evaluating the 4D-GS deformation only on dynamic Gaussians saves, measured on a trained model.

:func:`measure_static_skip` times one training step with the deformation field on the dynamic
Gaussians only and on all of them (``DeformationConfig.static_skip``), and counts the activation
memory each keeps for backward (:func:`saved_tensor_bytes`).
"""

from __future__ import annotations

import time
from typing import Callable, Sequence

import numpy as np
import torch

from methods.gaussians.model import DeformableGaussians
from methods.gaussians.train import RasterizeFn, RGBView, gaussian_window, photometric_loss


def measure_static_skip(deformable: DeformableGaussians, views: Sequence[RGBView], background: torch.Tensor,
                        rasterize_fn: RasterizeFn, lambda_dssim: float = 0.2, repeats: int = 8) -> dict:
    """What evaluating the deformation only on dynamic Gaussians saves, on a trained model.

    For each mode (``skip``: field on ``dynamic_mask`` only; ``full``: on every Gaussian) and the same
    ``repeats`` views: CPU milliseconds of the deformation forward + backward alone and of a whole
    training step (deformation, rasterisation, loss, backward; no optimiser step), and the bytes autograd
    saves for backward (activation memory) for each. Gradients are cleared afterwards.
    """
    gm = deformable.gaussians
    window = gaussian_window(11, 1.5).to(gm.params["means"].device)
    params = list(gm.params.values()) + list(deformable.field.parameters())
    picks = [views[i % len(views)] for i in range(repeats + 1)]

    def deform_only(view: RGBView, skip: bool) -> torch.Tensor:
        means, quats, scales = deformable.deform(view.time, skip_static=skip)
        return means.sum() + quats.sum() + scales.sum()

    def full_step(view: RGBView, skip: bool) -> torch.Tensor:
        means, quats, scales, colors = deformable.deform_with_colors(view.time, view.center, skip_static=skip)
        out = rasterize_fn(means, quats, scales, gm.opacities, colors, view.viewmat,
                           view.K, view.width, view.height, background=background)
        return photometric_loss(out.image, view.image, lambda_dssim, window)

    result: dict = {"gaussians": deformable.num_gaussians, "dynamic": deformable.num_dynamic()}
    result["dynamic_fraction"] = result["dynamic"] / max(1, result["gaussians"])
    for label, fn in (("deform", deform_only), ("step", full_step)):
        for skip in (True, False):
            mode = "skip" if skip else "full"
            cpu = []
            saved = 0
            for k, view in enumerate(picks):
                c0 = time.process_time()
                loss, nbytes = saved_tensor_bytes(lambda: fn(view, skip))
                loss.backward()
                if k > 0:  # the first call warms caches up
                    cpu.append(time.process_time() - c0)
                saved = max(saved, nbytes)
                for p in params:
                    p.grad = None
            result[f"{label}_cpu_ms_{mode}"] = 1000 * float(np.mean(cpu))
            result[f"{label}_saved_mib_{mode}"] = saved / 2 ** 20
    return result


def saved_tensor_bytes(fn: Callable[[], object]) -> tuple[object, int]:
    """Run ``fn`` and return (its result, bytes of the tensors autograd saved for backward during it).

    This is the activation memory a step pays for the computation; RSS cannot see it reliably on CPU.
    """
    total = 0
    seen: set[int] = set()

    def pack(t: torch.Tensor):
        nonlocal total
        key = t.untyped_storage().data_ptr() if t.device.type != "meta" else id(t)
        if key not in seen:
            seen.add(key)
            total += t.untyped_storage().nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        result = fn()
    return result, total
