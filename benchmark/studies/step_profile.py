"""Where one deformation-stage step of a 4D-GS fit spends its CPU time, at a fitted model's size.

``bench4d ablate step-profile --geometry FILE --scene SCENE`` takes a cached 4D-GS geometry (the
``geometry-4dgs-*.pt`` a language method's fit writes under ``<cache>/language/<dataset>-<scene>/``: its
Gaussians and deformation field), gives its Gaussians random degree-3 SH colours (a fitted geometry keeps
shape only; a step's cost does not depend on the colours' values), and runs deformation-stage training steps
on the scene's training views -- render, loss with the HexPlane regularisers, backward, both optimisers -- on
one thread under :mod:`torch.profiler`. The operators' self CPU time is summed into the step's parts
(:data:`PARTS`): what a faster fit would have to shrink, and how much each could give at most.

Writes ``<out>/<name>.json`` and ``.md`` (default ``reports/fit-timing/step-profile``).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

from benchmark.core.errors import InputError

from ._report import Report, markdown_table, write_report

PARTS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("compositing (compiled, forward and backward)", ("Composite", "CompositeBackward")),
    ("HexPlane sampling and regularisers (compiled)", ("HexPlaneSample", "HexPlaneSampleBackward", "PlaneRegularisers",
                                                       "PlaneRegularisersBackward")),
    ("projection, SH colour, SSIM (compiled)", ("Project", "ProjectBackward", "ShColor", "ShColorBackward", "Ssim",
                                                "SsimBackward")),
    ("deformation MLP: matrix products (BLAS)", ("aten::mm", "aten::addmm")),
    ("deformation MLP: ReLU forward and backward", ("aten::threshold_backward", "aten::clamp_min", "aten::clamp_min_",
                                                    "aten::relu", "aten::relu_")),
    ("optimisers (fused Adam)", ("aten::_fused_adam_",)),
)
"""The step's parts and the profiler's event names summed into each; every other operator is "other"."""


@dataclass
class StepProfileConfig:
    """What to profile."""

    geometry: Path
    """A cached 4D-GS geometry file (``geometry-4dgs-<key>.pt``)."""
    scene: str
    """The scene it was fitted on: a synthetic preset or a folder."""
    size: int = 128
    """Image width of a generated preset."""
    seed: int = 0
    """Scene seed of a generated preset (the fit's seed)."""
    steps: int = 10
    """Profiled steps (after :attr:`warmup` unprofiled ones)."""
    warmup: int = 3
    """Steps run before profiling."""
    all_dynamic: bool = True
    """Deform every Gaussian, as at the start of the stage and on scenes where everything moves (else the
    geometry's recorded dynamic mask)."""
    cache_dir: Path = Path("cache")
    """Where a generated preset is kept."""
    name: str = "step-profile"
    """Output file stem."""
    out: Path = Path("reports/fit-timing")
    """Output folder."""


def part_of(event: str) -> str:
    """The :data:`PARTS` name an operator's profiler event belongs to ("other" when none)."""
    for part, names in PARTS:
        if event in names:
            return part
    return "other"


def split_parts(events: dict[str, float]) -> dict[str, float]:
    """Event name -> self CPU ms summed into part -> ms, in :data:`PARTS` order, "other" last."""
    out = {part: 0.0 for part, _ in PARTS}
    out["other"] = 0.0
    for event, ms in events.items():
        out[part_of(event)] += ms
    return out


def _load(config: StepProfileConfig):
    import torch

    from benchmark.runner import resolve_scene
    from benchmark.loaders import load_scene
    from methods.fields.language_field import FrozenGeometry

    path = Path(config.geometry)
    if not path.is_file():
        raise InputError(path, "--geometry", "no such file (a cached geometry-4dgs-*.pt)")
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
        geometry = FrozenGeometry.from_state_dict(saved["geometry"], "cpu")
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the user's input, named
        raise InputError(path, "--geometry", f"not a cached geometry file ({type(exc).__name__})") from None
    if geometry.deformable is None:
        raise InputError(path, "--geometry", "a 3D-GS geometry: the deformation stage needs a 4D-GS one")
    scene = load_scene(resolve_scene(config.scene, Path(config.cache_dir), size=config.size, seed=config.seed))
    return geometry, scene


def profile_steps(config: StepProfileConfig, log: Callable[[str], None] = lambda m: None) -> dict:
    """Run and profile the steps; returns the per-event and per-part self CPU ms per step and the step's
    measured CPU ms without the profiler."""
    import numpy as np
    import torch
    from torch.profiler import ProfilerActivity, profile

    from methods.gaussians.config import ReconConfig
    from methods.gaussians.model import DeformableGaussians, GaussianModel
    from methods.gaussians.optimizer import GaussianOptimizer, fast_adam
    from methods.gaussians.strategy import DensificationStrategy
    from methods.gaussians.train import Schedule, StageRun, Trainer

    torch.set_num_threads(1)
    geometry, scene = _load(config)
    p = geometry.gaussians.params
    n = p["means"].shape[0]
    generator = torch.Generator().manual_seed(config.seed)
    params = {k: p[k].detach().clone() for k in ("means", "quats", "log_scales", "opacity_logits")}
    params["sh_dc"] = torch.rand(n, 1, 3, generator=generator) * 0.5
    params["sh_rest"] = torch.randn(n, 15, 3, generator=generator) * 0.01
    model = GaussianModel({k: v.requires_grad_(True) for k, v in params.items()}, sh_degree=3)
    model.active_sh_degree = 3
    field = geometry.deformable.field
    field.requires_grad_(True)
    cfg = ReconConfig(seed=config.seed)
    trainer = Trainer(scene, cfg)
    deformable = DeformableGaussians(model, field)
    deformable.dynamic_mask = None if config.all_dynamic else geometry.deformable.dynamic_mask
    opt = GaussianOptimizer(model, cfg.gaussians, trainer.extent)
    d = cfg.deformation
    net_opt = fast_adam([{"params": field.mlp_parameters(), "lr": d.deformation_lr_init * trainer.extent, "name": "mlp"},
                         {"params": field.grid_parameters(), "lr": d.grid_lr_init * trainer.extent, "name": "grid"}],
                        lr=0.0, eps=cfg.gaussians.adam_eps)
    sched = Schedule(cfg.gaussians, cfg.deformation_stage_scale(), densify_until=d.densify_until_iter,
                     opacity_resets=False, reset_interval=None)
    iterations = cfg.deformation_iterations
    strategy = DensificationStrategy(cfg.gaussians, sched, iterations, trainer.extent, trainer.cap, n,
                                     trainer.generator, "cpu")
    run = StageRun("deformation", iterations, model, opt, deformable, net_opt, sched, strategy,
                   iter_seconds=np.zeros(iterations), deform_seconds=np.zeros(iterations))

    def step() -> None:
        # the stage's last iteration: past densification, as every step of a fitted model's size
        trainer.train_step(run, iterations)

    log(f"step profile: {n} Gaussians, {len(trainer.views)} training views, {config.warmup} + {config.steps} steps")
    for _ in range(config.warmup):
        step()
    start = time.process_time()
    for _ in range(config.steps):
        step()
    plain_ms = 1000.0 * (time.process_time() - start) / config.steps
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(config.steps):
            step()
    events: dict[str, float] = {}
    for e in prof.key_averages():
        events[e.key] = events.get(e.key, 0.0) + e.self_cpu_time_total / 1000.0 / config.steps
    total = sum(events.values())
    return {"gaussians": n, "dynamic": deformable.num_dynamic(), "views": len(trainer.views),
            "width": trainer.views[0].width, "height": trainer.views[0].height, "step_cpu_ms": plain_ms,
            "profiled_ms": total, "parts": split_parts(events),
            "events": dict(sorted(events.items(), key=lambda kv: -kv[1])[:40])}


def step_profile_markdown(config: StepProfileConfig, result: dict) -> str:
    total = result["profiled_ms"] or 1.0
    rows = [[part, f"{ms:.1f}", f"{100.0 * ms / total:.0f} %"] for part, ms in result["parts"].items()]
    rows.append(["whole step (profiled)", f"{result['profiled_ms']:.1f}", "100 %"])
    top = [[name, f"{ms:.2f}"] for name, ms in list(result["events"].items())[:15]]
    return (f"# One deformation-stage step, part by part\n\nMade by `bench4d ablate step-profile`: the cached 4D-GS "
            f"geometry `{Path(config.geometry).name}` on `{config.scene}` ({result['gaussians']} Gaussians, "
            f"{result['dynamic']} deformed, {result['width']}x{result['height']} training views), random SH colours, "
            f"one thread, {config.steps} profiled steps after {config.warmup}. Self CPU ms per step of the "
            f"profiler's operators, summed into the step's parts; without the profiler a step took "
            f"{result['step_cpu_ms']:.1f} CPU ms. A part's share is the most that making it free could save.\n\n"
            + markdown_table(["part", "CPU ms per step", "share"], rows)
            + "\n## The costliest operators\n\n" + markdown_table(["operator", "self CPU ms per step"], top))


def step_profile_report(config: StepProfileConfig, log: Callable[[str], None] = lambda m: None) -> Report:
    """Profile, then write ``<out>/<name>.json`` and ``.md``."""
    if config.steps < 1:
        raise InputError(None, "--steps", f"need at least one profiled step, got {config.steps}")
    if config.warmup < 0:
        raise InputError(None, "warmup", f"must be >= 0, got {config.warmup}")
    result = profile_steps(config, log)
    table = step_profile_markdown(config, result)
    doc = {"config": {**asdict(config), "geometry": str(config.geometry), "cache_dir": str(config.cache_dir),
                      "out": str(config.out)}, **result}
    return Report(table, write_report(Path(config.out), config.name, doc, table))
