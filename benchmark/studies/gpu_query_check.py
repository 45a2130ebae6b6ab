"""The GPU query's speed and answers with default settings, in one command for a machine with a GPU.

    python -m benchmark.studies.gpu_query_check [--device cuda] [--out reports/gpu-query]

Measures, through the method's own query code on random Gaussians, features and decoder (the work does
not depend on what they mean; :func:`benchmark.studies.query_speed.measure_query_speed`):

* the time-agnostic query at 536 x 960 with 200 000 Gaussians with the default answer options, and with
  every pixel decoded (``answer.decode_table=0``) for comparison, each with the share of mask pixels
  equal to the float32 decode's;
* the time-agnostic and the time-sensitive query (the status field, K = 3, on every Gaussian) at
  536 x 714 with 360 000 Gaussians, the scale of the fitted model the issue's figures come from.

Writes ``<out>/gpu-query.json`` and ``<out>/gpu-query.md`` atomically. On a CPU (``--device cpu``) the
same runs at the ``--scale`` given, for a dry run of the script.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Any, Optional, Sequence

import torch

from benchmark.core.scene import Frame

from ._report import Report, markdown_table, write_report

AGNOSTIC = {"gaussians": 200_000, "width": 536, "height": 960}
"""The time-agnostic target: at least 100 FPS here with default settings."""
SENSITIVE = {"gaussians": 360_000, "width": 536, "height": 714}
"""The time-sensitive target: at least 60 FPS here."""
AGREEMENT_TARGET = 0.9999
"""Share of mask pixels that must equal the float32 decode's."""


def table_agreement(model, texts: Sequence[str], frames: Sequence[Frame], resolution: int = 257) -> dict[str, Any]:
    """How the time-agnostic answers of a fitted ``model`` (a :class:`methods.language_methods.LanguageFieldModel`)
    through a decode table of ``resolution`` compare with decoding every pixel in float32, on ``frames`` and
    ``texts``: the share of all pixels, and of mask pixels (those either answer marks), on which the masks
    agree, and the worst frame's. On a CPU the model fills its tables lazily
    (:class:`methods.fields.language_field.DecodeTable`): the same values as a GPU's eager table."""
    answer = model.config.answer
    saved = answer.decode_table
    equal = total = mask_equal = mask_total = 0
    worst = 1.0
    try:
        answers = {}
        for resolution_used in (0, resolution):
            answer.decode_table = resolution_used
            model._decode_tables.clear()
            model._reduced_cache.clear()
            for text in texts:
                for frame in frames:
                    answers[(resolution_used, text, frame.name)] = model.agnostic(text, frame).mask.cpu().numpy()
    finally:
        answer.decode_table = saved
        model._decode_tables.clear()
        model._reduced_cache.clear()
    for text in texts:
        for frame in frames:
            exact, table = answers[(0, text, frame.name)], answers[(resolution, text, frame.name)]
            same = exact == table
            union = exact | table
            equal += int(same.sum())
            total += same.size
            mask_equal += int((same & union).sum())
            mask_total += int(union.sum())
            worst = min(worst, float(same.mean()))
    return {"resolution": resolution, "texts": len(texts), "frames": len(frames), "pixels": total,
            "pixel_agreement": equal / total if total else float("nan"),
            "mask_pixels": mask_total, "mask_pixel_agreement": mask_equal / mask_total if mask_total else float("nan"),
            "worst_frame_pixel_agreement": worst}


def sensitive_speed(num_gaussians: int, width: int, height: int, *, device: str, frames: int = 10, warmup: int = 2,
                    num_states: int = 3, caption_dim: int = 384, feature_dim: int = 512,
                    seed: int = 0) -> dict[str, Any]:
    """Frames per second of the time-sensitive query (the agnostic answer for the mask, then the status
    field's score inside it) and of the agnostic one alone, on random Gaussians with a random status field
    on every Gaussian."""
    from methods.fields.autoencoder import FeatureAutoencoder
    from methods.fields.status import StatusField, StatusFieldConfig
    from methods.fields.time_varying import HexplaneStandardiser, TimeVaryingField
    from methods.language_methods import autoencoder_config
    from methods.specs._language import LanguageMethodConfig
    from methods.text_encoders import SeededTextEncoder
    from methods.time_sensitive import StatusHead

    from .query_speed import random_model

    dev = torch.device(device)
    config = LanguageMethodConfig()
    model, camera = random_model(num_gaussians, width, height, feature_dim=feature_dim, device=dev, config=config,
                                 seed=seed)
    geometry = model.geometry
    n = geometry.num_gaussians
    hex_dim = geometry.deformable.field.hexplane.feature_dim
    latent = 6
    gen = torch.Generator().manual_seed(seed + 5)
    status = StatusField(torch.randn(n, latent, generator=gen), hex_dim, cfg=StatusFieldConfig(num_states=num_states),
                         seed=seed)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed + 6)
        caption_ae = FeatureAutoencoder(caption_dim, dataclasses.replace(autoencoder_config(config),
                                                                         latent_dim=latent))
    field = TimeVaryingField("status", geometry, status.to(dev), HexplaneStandardiser(hex_dim).to(dev),
                             caption_ae.to(dev), backend=config.geometry.render_backend)
    model.head = StatusHead(field, SeededTextEncoder(caption_dim))
    model.supports = frozenset(model.supports | {"sensitive"})
    frame_list = [Frame(name=f"t{i:04d}", camera=camera, time=(i + 0.5) / (frames + warmup), time_index=i,
                        split="test") for i in range(frames + warmup)]

    def sync() -> None:
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    out: dict[str, Any] = {"gaussians": n, "width": width, "height": height, "device": str(dev),
                           "num_states": num_states, "frames": frames}
    for kind, call in (("agnostic", model.query_agnostic), ("sensitive", model.query_sensitive)):
        for frame in frame_list[:warmup]:
            call("query 0", [frame])
        sync()
        t0 = time.perf_counter()
        for frame in frame_list[warmup:]:
            call("query 0", [frame])
        sync()
        seconds = (time.perf_counter() - t0) / frames
        out[kind] = {"seconds_per_frame": seconds, "fps": 1.0 / seconds}
    return out


def run_check(device: str, *, scale: float = 1.0, frames: int = 10) -> dict[str, Any]:
    """The measurements of the module docstring (sizes multiplied by ``scale``, for a dry run)."""
    from methods.specs._language import LanguageMethodConfig

    from .query_speed import measure_query_speed

    def scaled(spec: dict) -> dict:
        return {"num_gaussians": max(1000, int(spec["gaussians"] * scale)),
                "width": max(16, int(spec["width"] * scale ** 0.5)), "height": max(16, int(spec["height"] * scale ** 0.5))}

    a = scaled(AGNOSTIC)
    default = LanguageMethodConfig()
    plain = LanguageMethodConfig()
    plain.answer.decode_table = 0
    doc: dict[str, Any] = {"device": device, "scale": scale, "torch": torch.__version__,
                           "gpu": torch.cuda.get_device_name(0) if device.startswith("cuda") else None,
                           "default_answer_options": dataclasses.asdict(default.answer)}
    doc["agnostic_default"] = measure_query_speed(a["num_gaussians"], a["width"], a["height"], frames=frames,
                                                  device=device, config=default)
    doc["agnostic_every_pixel_decoded"] = measure_query_speed(a["num_gaussians"], a["width"], a["height"],
                                                              frames=frames, device=device, config=plain)
    s = scaled(SENSITIVE)
    doc["sensitive_default"] = sensitive_speed(s["num_gaussians"], s["width"], s["height"], device=device,
                                               frames=frames)
    return doc


def check_markdown(doc: dict) -> str:
    """The report's tables."""
    def agreement(run: dict) -> str:
        value = run.get("mask_agreement_with_exact")
        return "exact" if value is None else f"{100 * value:.4f} % (min {100 * run['min_mask_agreement_with_exact']:.4f} %)"

    rows = []
    for key, label in (("agnostic_default", "time-agnostic, default options"),
                       ("agnostic_every_pixel_decoded", "time-agnostic, every pixel decoded")):
        run = doc[key]
        rows.append([label, f"{run['width']}x{run['height']}", str(run["gaussians"]), f"{run['fps']:.1f}",
                     f"{1000 * run['seconds_per_frame']:.2f}", agreement(run)])
    sens = doc["sensitive_default"]
    for kind in ("agnostic", "sensitive"):
        rows.append([f"time-{kind}, status field K={sens['num_states']}", f"{sens['width']}x{sens['height']}",
                     str(sens["gaussians"]), f"{sens[kind]['fps']:.1f}",
                     f"{1000 * sens[kind]['seconds_per_frame']:.2f}", "–"])
    head = (f"# GPU query check ({doc.get('gpu') or doc['device']}, torch {doc['torch']})\n\n"
            f"Targets: time-agnostic >= 100 FPS at 536x960 with 200k Gaussians and >= "
            f"{100 * AGREEMENT_TARGET:.2f} % of mask pixels equal to the float32 decode; time-sensitive >= 60 FPS "
            f"at 536x714. Sizes scaled by {doc['scale']}.\n\n")
    stages = doc["agnostic_default"].get("stage_seconds_per_frame", {})
    stage_line = ", ".join(f"{k} {1000 * v:.2f} ms" for k, v in stages.items())
    return (head + markdown_table(["query", "size", "Gaussians", "FPS", "ms/frame", "mask pixels equal"], rows)
            + f"\nDefault time-agnostic stages: {stage_line}.\n")


def gpu_query_report(device: str, out: Path, *, scale: float = 1.0, frames: int = 10,
                     name: str = "gpu-query") -> Report:
    doc = run_check(device, scale=scale, frames=frames)
    table = check_markdown(doc)
    return Report(table, write_report(out, name, doc, table))


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--out", type=Path, default=Path("reports/gpu-query"))
    parser.add_argument("--scale", type=float, default=1.0, help="multiply the Gaussian counts (pixels: its root)")
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--name", default="gpu-query")
    args = parser.parse_args(argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        parser.error("no CUDA device here (use --device cpu --scale 0.01 for a dry run)")
    report = gpu_query_report(args.device, args.out, scale=args.scale, frames=args.frames, name=args.name)
    print(report.table)
    for path in report.paths:
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
