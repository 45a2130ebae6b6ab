"""Seconds per training step of the 4D LangSplat status field, on random Gaussians in front of a camera.

:func:`measure_status_speed` times the step the release runs per iteration (HexPlane features, the
weight MLP, the K-state mixture, rendering the latents, L1, backward and Adam), by rasterization and,
on the CPU, by the recorded blending operator (:func:`methods.fields.time_varying.blend_operator`).
"""

from __future__ import annotations

import time
from typing import Any, Callable

import torch

from methods.fields.language_field import random_geometry
from methods.fields.status import StatusField, StatusFieldConfig
from methods.fields.time_varying import blend_operator, render_channels


def measure_status_speed(num_gaussians: int, width: int, height: int, *, num_states: int = 3,
                         dynamic_fraction: float = 1.0, iterations: int = 20, warmup: int = 3,
                         latent_dim: int = 6, device: str | torch.device = "cpu", operator: bool = False,
                         seed: int = 0) -> dict[str, Any]:
    """Seconds per training step of the status field on random Gaussians in front of a camera.

    One step = HexPlane features of the dynamic Gaussians (frozen; protocol HexPlane 64^3, 16 x 2
    features), the weight MLP, the K-state mixture, rendering ``latent_dim`` channels at
    ``width x height``, L1 and the backward + Adam step: what the release does per iteration (with
    its 4096 -> 6 latents). With ``operator`` also the recorded-blending-operator step (CPU).
    """
    dev = torch.device(device)
    geometry, camera = random_geometry(num_gaussians, width, height, seed=seed, device=dev)
    gen = torch.Generator().manual_seed(seed + 1)
    n = geometry.num_gaussians
    dynamic = torch.rand(n, generator=gen) < dynamic_fraction
    feature_dim = geometry.deformable.field.hexplane.feature_dim
    field_ = StatusField(torch.zeros(n, latent_dim), feature_dim, semantic_dynamic=dynamic,
                         cfg=StatusFieldConfig(num_states=num_states), seed=seed).to(dev)
    opt = torch.optim.Adam(field_.parameters(), lr=1e-3)
    target = torch.rand(height * width, latent_dim, generator=gen).to(dev)
    pixels = torch.arange(height * width, device=dev)
    state = geometry.at(0.5)
    rows = field_.dynamic_index
    out: dict[str, Any] = {"gaussians": n, "dynamic_gaussians": int(rows.numel()), "num_states": num_states,
                           "width": width, "height": height, "device": str(dev),
                           "parameter_bytes_per_gaussian": field_.parameter_bytes() / n}

    def sync() -> None:
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    def step(predict: Callable[[torch.Tensor], torch.Tensor], t: float) -> None:
        with torch.no_grad():
            h = geometry.hexplane_features(t, geometry.gaussians.means[rows])
        pred = predict(field_(h))
        loss = (pred - target).abs().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    def render(lat: torch.Tensor) -> torch.Tensor:
        return render_channels(state, lat, camera).reshape(-1, latent_dim)

    for name, predict in [("rasterize", render)] + ([("operator", None)] if operator and dev.type == "cpu" else []):
        if name == "operator":
            t0 = time.perf_counter()
            op = blend_operator(state, camera, pixels)
            out["operator_record_seconds"] = time.perf_counter() - t0
            if op is None:
                out["operator_seconds_per_iteration"] = float("nan")
                continue
            out["operator_mib"] = op.nbytes() / 2 ** 20
            predict = op
        for i in range(warmup):
            step(predict, (i + 0.5) / warmup)
        sync()
        t0 = time.perf_counter()
        for i in range(iterations):
            step(predict, (i + 0.5) / iterations)
        sync()
        out[f"{name}_seconds_per_iteration"] = (time.perf_counter() - t0) / max(1, iterations)
    if dev.type == "cuda":
        out["peak_gpu_mib"] = torch.cuda.max_memory_allocated(dev) / 2 ** 20
    return out
