"""``bench4d recon``: reconstruct a scene with 4D-GS and the static 3D-GS reference; report quality and cost.

SCENE is a scene folder (any layout :func:`benchmark.loaders.load_scene` reads) or a synthetic preset
name (generated once into ``--cache-dir``). Each model is trained in its own child process, so that its
peak memory (the process's high-water resident size; ``torch.cuda.max_memory_allocated`` on CUDA) is its own, and is then
scored on the test frames of evaluation split ``--split`` (:data:`benchmark.core.scene.EVAL_SPLITS`; default
``paper``, the dataset's held-out frames; ``report.json`` records it as ``split``): PSNR and SSIM (scikit-image, data range 1), fit time (wall and CPU),
render FPS, Gaussian count. A few renders are saved as PNG beside ``report.json`` (written atomically).

The static 3D-GS reference gets the same iteration budget as 4D-GS; on scenes with motion 4D-GS must
beat it. For 4D-GS the report also measures what skipping the deformation of static Gaussians saves
(per-step CPU time and autograd activation memory, and test PSNR with and without skipping);
``--compare-static-skip`` additionally trains a 4D-GS with skipping off.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, Optional

from benchmark.core.atomic import json_ready

from ._common import add_threads_argument, parse_seed, set_threads
from .eval import add_split_argument
from benchmark.core.config import with_overrides
from benchmark.core.errors import InputError
from benchmark.core.scene import DEFAULT_EVAL_SPLIT, scene_split_frames

MODELS = ("3dgs", "4dgs")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scene", help="scene folder or synthetic preset name")
    parser.add_argument("--summarize", type=Path, metavar="DIR", default=None,
                        help="instead of training: tabulate every DIR/*/report.json into DIR/summary.md")
    parser.add_argument("--model", choices=("3dgs", "4dgs", "both"), default="both",
                        help="which reconstruction(s) to run (default both: 4D-GS and its 3D-GS reference)")
    parser.add_argument("--size", type=int, default=128, help="image width of a generated synthetic preset")
    parser.add_argument("--scale", type=float, default=None,
                        help="resolution multiplier for a scene folder (e.g. 0.5: D-NeRF 400 -> 200 px)")
    parser.add_argument("--iters", type=int, default=None,
                        help="total 4D-GS iterations, split static:deformation as the recipe's 3000:10000 "
                             "(default 3000); the 3D-GS reference gets the same total")
    parser.add_argument("--static-iters", type=int, default=None, help="override the 4D-GS static stage length")
    parser.add_argument("--deform-iters", type=int, default=None, help="override the deformation stage length")
    parser.add_argument("--reference-iters", type=int, default=None,
                        help="3D-GS reference iterations (default: the 4D-GS total)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a ReconConfig option by its dotted path, e.g. gaussians.sh_degree=1 or "
                             "deformation.hexplane.multires=1,2 (repeatable)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default reports/recon/<scene>)")
    parser.add_argument("--cache-dir", type=Path, default=Path("cache"), help="where presets are generated")
    parser.add_argument("--seed", type=parse_seed, default=0)
    add_split_argument(parser)
    add_threads_argument(parser)
    parser.add_argument("--device", default="cpu", help="cpu or cuda[:N]")
    parser.add_argument("--renders", type=int, default=3, help="test renders saved per model as PNG")
    parser.add_argument("--compare-static-skip", action="store_true",
                        help="also train 4D-GS with static-Gaussian skipping off and compare")
    parser.add_argument("--save-models", action="store_true",
                        help="also save each trained model as <out>/<model>.pt (torch.save of its tensors)")
    parser.add_argument("--no-isolate", action="store_true",
                        help="train in this process (peak memory then covers everything before it)")
    parser.add_argument("--log-every", type=int, default=0, help="print training progress every N iterations")
    parser.add_argument("--time-range", default=None, metavar="FIRST:LAST",
                        help="train and score only the frames whose video frame number is in FIRST..LAST "
                             "(inclusive), e.g. the frames before a change: what the same recipe reaches on "
                             "a stretch where nothing moves")


# ---------------------------------------------------------------------------------------------------
# Configuration
# ---------------------------------------------------------------------------------------------------
def build_config(args: argparse.Namespace):
    """The :class:`ReconConfig` of this run (iterations, seed, ``--set`` overrides by dotted path)."""
    from methods.gaussians.config import ReconConfig

    from ._common import parse_overrides

    cfg = ReconConfig(seed=args.seed, log_every=args.log_every)
    total = args.iters if args.iters is not None else 3000
    if total < 2:
        raise InputError(None, "--iters", f"must be at least 2, got {total}")
    ratio = cfg.paper_static_iterations / (cfg.paper_static_iterations + cfg.deformation.paper_iterations)
    cfg.static_iterations = max(1, int(round(total * ratio)))
    cfg.deformation_iterations = max(1, total - cfg.static_iterations)
    if args.static_iters is not None:
        cfg.static_iterations = args.static_iters
    if args.deform_iters is not None:
        cfg.deformation_iterations = args.deform_iters
    if cfg.static_iterations < 0 or cfg.deformation_iterations < 0:
        raise InputError(None, "--static-iters/--deform-iters", "iteration counts must be >= 0")
    cfg.reference_iterations = args.reference_iters
    return with_overrides(cfg, parse_overrides(args.set), what="--set")


# ---------------------------------------------------------------------------------------------------
# One model: train, evaluate, save renders (runs in a child process by default)
# ---------------------------------------------------------------------------------------------------
def load_for_recon(scene_dir: str, scale: Optional[float]):
    from ..loaders import load_scene

    return load_scene(scene_dir, scale=scale) if scale is not None else load_scene(scene_dir)


def parse_time_range(text: Optional[str]) -> Optional[tuple[int, int]]:
    """``"FIRST:LAST"`` -> (first, last) inclusive video frame numbers, or ``None`` for no restriction."""
    if text is None:
        return None
    first, sep, last = str(text).partition(":")
    try:
        if not sep:
            raise ValueError
        lo, hi = int(first), int(last)
    except ValueError:
        raise InputError(None, "--time-range", f"expected FIRST:LAST frame numbers, e.g. 0:38, got {text!r}") from None
    if lo < 0 or hi < lo:
        raise InputError(None, "--time-range", f"needs 0 <= FIRST <= LAST, got {text!r}")
    return lo, hi


def frames_in_range(frames, time_range: Optional[tuple[int, int]]) -> list:
    """The frames whose ``time_index`` lies in the inclusive ``time_range`` (all of them for ``None``)."""
    if time_range is None:
        return list(frames)
    lo, hi = time_range
    return [f for f in frames if lo <= f.time_index <= hi]


def evaluation_frames(scene, split: str = DEFAULT_EVAL_SPLIT) -> list:
    """The frames a reconstruction is scored on: the test frames of evaluation split ``split``
    (:func:`benchmark.core.scene.scene_split_frames`: a generated scene's test frames hold the ``paper`` and the
    ``novel-view`` split's frames, scored apart), else (a scene without test frames) the val split."""
    if scene.test_frames:
        return scene_split_frames(scene, split)
    return list(scene.split("val"))


def moving_regions(scene, frames) -> Optional[tuple[dict[int, str], dict[str, Any]]]:
    """(dynamic part id -> name, frame name -> (H, W) bool pixels of moving parts) of a generated scene at
    the frames' resolution, or ``None`` for a scene without generator truth (D-NeRF, HyperNeRF...)."""
    from ..synthetic.dynamic import META_FILE, dynamic_masks, dynamic_parts
    from ..runner import to_size

    if scene.root is None or not (Path(scene.root) / META_FILE).is_file():
        return None
    parts = dynamic_parts(scene.root)
    masks = dynamic_masks(scene.root, frames, parts)
    return parts, {f.name: to_size(masks[f.name], (f.camera.height, f.camera.width)) for f in frames}


def fit_and_evaluate(job: dict) -> dict:
    """Train one model as ``job`` says and return its report entry (also used in-process by tests)."""
    import functools

    import torch

    from benchmark.studies.static_skip import measure_static_skip
    from methods.gaussians.rasterize import rasterize
    from methods.gaussians.train import Trainer, evaluate

    from ..core import memory
    from benchmark.core.imageio import write_image

    set_threads(job["threads"])
    torch.set_flush_denormal(True)  # transmittance products underflow into slow denormals on CPU
    device = job["device"]
    cuda = device.startswith("cuda")
    scene = job.get("scene_object") or load_for_recon(job["scene_dir"], job["scale"])
    cfg = job["config"]
    rast = functools.partial(rasterize, backend="auto")
    rss_before = memory.peak_cpu_mib()
    time_range = job.get("time_range")
    trainer = Trainer(scene, cfg, device=device, rasterize_fn=rast,
                      train_frames=frames_in_range(scene.train_frames, time_range),
                      checkpoint=_checkpointing(job, scene))
    rss_loaded = memory.peak_cpu_mib()
    if cuda:
        torch.cuda.reset_peak_memory_stats(torch.device(device))
    kind = job["model"]
    result = trainer.fit_3dgs() if kind == "3dgs" else trainer.fit_4dgs()
    rss_trained = memory.peak_cpu_mib()
    test_frames = frames_in_range(evaluation_frames(scene, job.get("split", DEFAULT_EVAL_SPLIT)), time_range)
    if not test_frames:
        raise InputError(scene.root, "frames", "the scene has no test or val frames to evaluate on"
                         + ("" if time_range is None else f" in frames {time_range[0]}..{time_range[1]}"))
    moving = moving_regions(scene, test_frames)
    ev = evaluate(result.model, test_frames, scene.background, rast, device=device, keep_renders=job["renders"],
                  region_masks=None if moving is None else moving[1])
    entry: dict[str, Any] = {
        "model": kind, "label": job.get("label", kind),
        "psnr": ev["psnr"], "ssim": ev["ssim"], "test_frames": len(test_frames),
        "fit_seconds": result.fit_seconds, "fit_cpu_seconds": result.fit_cpu_seconds,
        "iterations": sum(s["iterations"] for s in result.stages),
        "render_fps": ev["render_fps"],
        "gaussians": result.model.num_gaussians, "cap": result.cap, "extent": result.extent,
        "peak_rss_mib": rss_trained, "rss_after_loading_mib": rss_loaded, "rss_at_start_mib": rss_before,
        "stages": result.stages, "per_frame": ev["per_frame"], "resumed_at": result.resumed_at,
    }
    if moving is not None:
        entry["moving"] = {"parts": sorted(set(moving[0].values())), "pixel_fraction": ev["region_fraction"],
                           "psnr": ev["region_psnr"], "static_psnr": ev["rest_psnr"]}
    if cuda:
        entry["cuda_max_memory_allocated_mib"] = torch.cuda.max_memory_allocated(torch.device(device)) / 2 ** 20
    if kind == "4dgs":
        entry["dynamic_gaussians"] = result.model.num_dynamic()
        entry["field_box"] = result.field_box
        if cfg.deformation.static_skip and result.model.dynamic_mask is not None:
            train_views = trainer.views
            # cost of one step with the field on dynamic Gaussians only vs on all (same model, same views);
            # the quality effect needs a model trained without skipping: --compare-static-skip
            entry["static_skip"] = measure_static_skip(result.model, train_views, trainer.background, rast,
                                                       cfg.deformation.lambda_dssim)
    out_dir = Path(job["out_dir"])
    if job.get("save_model"):
        from methods.gaussians.model import save_model

        save_model(out_dir / f"{job.get('label', kind)}.pt", result.model)
        entry["model_file"] = str(out_dir / f"{job.get('label', kind)}.pt")
    saved = []
    for name, pred, gt in ev["renders"]:
        pred_path = out_dir / "renders" / f"{job.get('label', kind)}_{name}.png"
        gt_path = out_dir / "renders" / f"gt_{name}.png"
        write_image(pred_path, pred)
        if not gt_path.exists():
            write_image(gt_path, gt)
        saved.append(str(pred_path))
    entry["renders"] = saved
    del ev, result, trainer
    return json_ready(entry)


def _checkpointing(job: dict, scene):
    """An interrupted fit of this job resumes from ``.<label>.partial.pt`` in the output folder; the key
    names the scene, frames, model, config and the code digest of the Gaussian core's trainer, so another
    job's file is ignored."""
    import hashlib

    from benchmark.core.cache_keys import code_digest
    from methods.gaussians.train import Checkpointing

    what = {"scene": scene.summary(), "folder": job.get("scene_dir"), "scale": job.get("scale"),
            "time_range": job.get("time_range"), "model": job["model"],
            "device": str(job.get("device", "cpu")).split(":")[0], "config": dataclasses.asdict(job["config"]),
            "code": code_digest("methods.gaussians.train")}
    key = hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()[:24]
    return Checkpointing(Path(job["out_dir"]) / f".{job.get('label', job['model'])}.partial.pt", key)


def _child(job: dict, result_path: str) -> None:
    """Child-process entry: train, evaluate, write the entry (or the error) as JSON."""
    from benchmark.core.atomic import write_json

    try:
        write_json(result_path, {"ok": True, "entry": fit_and_evaluate(job)})
    except InputError as err:
        write_json(result_path, {"ok": False, "error": str(err), "input_error": True})
    except Exception as err:  # noqa: BLE001 - reported to the parent, which re-raises
        import traceback

        write_json(result_path, {"ok": False, "error": f"{type(err).__name__}: {err}",
                                 "traceback": traceback.format_exc()})


def run_job(job: dict, isolate: bool) -> dict:
    """Run one model job, in a fresh ``spawn`` child process unless ``isolate`` is false."""
    if not isolate:
        return fit_and_evaluate(job)
    import multiprocessing as mp
    import tempfile

    from benchmark.core.atomic import read_json

    with tempfile.TemporaryDirectory(prefix="bench4d-recon-") as tmp:
        result_path = str(Path(tmp) / "result.json")
        proc = mp.get_context("spawn").Process(target=_child, args=(job, result_path))
        proc.start()
        proc.join()
        if not Path(result_path).is_file():
            raise RuntimeError(f"training process for {job['model']} died (exit code {proc.exitcode})")
        payload = read_json(result_path)
    if not payload["ok"]:
        if payload.get("input_error"):
            raise InputError(None, None, payload["error"])
        raise RuntimeError(f"{job['model']} failed: {payload['error']}\n{payload.get('traceback', '')}")
    return payload["entry"]


# ---------------------------------------------------------------------------------------------------
# Command
# ---------------------------------------------------------------------------------------------------
def run(args: argparse.Namespace) -> int:
    from benchmark.core.atomic import write_json
    from benchmark.core.outputs import guard_output
    from ..runner import resolve_scene

    if args.summarize is not None:
        path = summarize(args.summarize)
        print(path.read_text(encoding="utf-8"))
        return 0
    _check_arguments(args)
    cfg = build_config(args)
    time_range = parse_time_range(args.time_range)
    scene_dir = resolve_scene(args.scene, args.cache_dir, size=args.size, log=print)
    scene = load_for_recon(str(scene_dir), args.scale)  # validate early, and for the summary
    print(f"bench4d recon: {scene.summary()}")
    kept = (len(frames_in_range(scene.train_frames, time_range)),
            len(frames_in_range(evaluation_frames(scene, args.split), time_range)))  # (training, scored) frames
    if time_range is not None:
        if not all(kept):
            raise InputError(scene_dir, "--time-range", f"frames {time_range[0]}..{time_range[1]} keep {kept[0]} "
                             f"training and {kept[1]} test frames; both must be at least 1")
        print(f"  frames {time_range[0]}..{time_range[1]} only: {kept[0]} training, {kept[1]} test")
    suffix = "" if time_range is None else f"-frames-{time_range[0]}-{time_range[1]}"
    out_dir = args.out or Path("reports") / "recon" / (scene.name + suffix)
    guard_output(out_dir, [scene_dir], option="--out")  # never into the scene it reads (its digest would move)
    out_dir.mkdir(parents=True, exist_ok=True)

    report = _report_header(args, cfg, scene, scene_dir, kept, time_range)
    started = time.perf_counter()
    for job in _jobs(args, cfg):
        job.update({"scene_dir": str(scene_dir), "scale": args.scale, "time_range": time_range, "split": args.split,
                    "device": args.device, "threads": args.threads,
                    "renders": args.renders, "out_dir": str(out_dir), "save_model": args.save_models})
        print(f"  training {job['label']} ...", flush=True)
        entry = run_job(job, isolate=not args.no_isolate)
        report["models"][job["label"]] = entry
        _print_entry(job["label"], entry)
        write_json(out_dir / "report.json", report, indent=0)  # partial report survives an interruption
    _compare_models(report)
    report["total_seconds"] = time.perf_counter() - started
    write_json(out_dir / "report.json", report, indent=0)  # unindented: half the size, diffs still by line
    print(f"  report: {out_dir / 'report.json'}")
    return 0


def _check_arguments(args: argparse.Namespace) -> None:
    """Raise :class:`InputError` on arguments a training run cannot start with."""
    from ._common import check_device

    if not args.scene:
        raise InputError(None, "--scene", "required (a scene folder or a synthetic preset name)")
    check_device(args.device)
    if args.size <= 0:
        raise InputError(None, "--size", f"must be positive, got {args.size}")
    if args.scale is not None and args.scale <= 0:
        raise InputError(None, "--scale", f"must be positive, got {args.scale}")
    args.threads = set_threads(args.threads)


def _jobs(args: argparse.Namespace, cfg) -> list[dict]:
    """The models to train (model kind, label, config), 4D-GS first."""
    wanted = ["4dgs", "3dgs"] if args.model == "both" else [args.model]
    jobs = [{"model": kind, "label": kind, "config": cfg} for kind in wanted]
    if args.compare_static_skip and "4dgs" in wanted:
        no_skip = dataclasses.replace(cfg, deformation=dataclasses.replace(cfg.deformation, static_skip=False))
        jobs.append({"model": "4dgs", "label": "4dgs-no-static-skip", "config": no_skip})
    return jobs


def _report_header(args: argparse.Namespace, cfg, scene, scene_dir: Path, kept: tuple[int, int],
                   time_range) -> dict[str, Any]:
    """The report before any model is trained: command, scene, config, machine (``models`` empty)."""
    from ..runner import device_description, git_state, package_versions

    return {
        "command": "bench4d " + " ".join(getattr(args, "_argv", None) or sys.argv[1:]),
        "overrides": list(args.set),
        "split": args.split,  # the evaluation split whose test frames were scored
        "scene": {"name": scene.name, "dataset": scene.dataset, "folder": str(scene_dir), "scale": args.scale,
                  "train_frames": kept[0], "test_frames": kept[1],
                  "time_range": None if time_range is None else list(time_range),
                  "time_steps": scene.num_time_steps,
                  "image_size": None if not scene.frames else [scene.frames[0].camera.width,
                                                               scene.frames[0].camera.height]},
        "config": dataclasses.asdict(cfg), "threads": args.threads, "environment": device_description(args.device),
        "packages": package_versions(("numpy", "torch", "scikit-image")), "git": git_state(),
        "models": {},
    }


def _print_entry(label: str, entry: dict) -> None:
    print(f"  {label:<22} PSNR {entry['psnr']:.2f} dB  SSIM {entry['ssim']:.4f}  "
          f"fit {entry['fit_seconds']:.0f} s wall / {entry['fit_cpu_seconds']:.0f} s CPU  "
          f"{entry['render_fps']:.1f} FPS  {entry['gaussians']} Gaussians  peak {entry['peak_rss_mib']:.0f} MiB"
          + (f"  moving parts ({100 * entry['moving']['pixel_fraction']:.1f} % of pixels) PSNR "
             f"{entry['moving']['psnr']:.2f} dB" if "moving" in entry else ""), flush=True)


def _compare_models(report: dict[str, Any]) -> None:
    """Add the 4D-GS vs 3D-GS and with vs without static skip comparisons to ``report`` and print them."""
    models = report["models"]
    if "4dgs" in models and "3dgs" in models:
        gain = models["4dgs"]["psnr"] - models["3dgs"]["psnr"]
        report["comparison"] = {"psnr_gain_4dgs_over_3dgs": gain, "ssim_gain_4dgs_over_3dgs":
                                models["4dgs"]["ssim"] - models["3dgs"]["ssim"], "4dgs_beats_3dgs": gain > 0}
        print(f"  4D-GS - 3D-GS: {gain:+.2f} dB PSNR")
    if "4dgs" in models and "static_skip" in models["4dgs"]:
        s = models["4dgs"]["static_skip"]
        print(f"  static skip: {s['dynamic']}/{s['gaussians']} dynamic; step {s['step_cpu_ms_skip']:.0f} vs "
              f"{s['step_cpu_ms_full']:.0f} ms CPU (field on dynamic only vs on all); deformation activations "
              f"{s['deform_saved_mib_skip']:.1f} vs {s['deform_saved_mib_full']:.1f} MiB")
    if "4dgs" in models and "4dgs-no-static-skip" in models:
        a, b = models["4dgs"], models["4dgs-no-static-skip"]
        report["static_skip_comparison"] = {
            "psnr_with": a["psnr"], "psnr_without": b["psnr"], "fit_cpu_seconds_with": a["fit_cpu_seconds"],
            "fit_cpu_seconds_without": b["fit_cpu_seconds"], "render_fps_with": a["render_fps"],
            "render_fps_without": b["render_fps"], "peak_rss_mib_with": a["peak_rss_mib"],
            "peak_rss_mib_without": b["peak_rss_mib"]}
        print(f"  trained with / without static skip: PSNR {a['psnr']:.2f} / {b['psnr']:.2f} dB, "
              f"CPU {a['fit_cpu_seconds']:.0f} / {b['fit_cpu_seconds']:.0f} s, "
              f"{a['render_fps']:.1f} / {b['render_fps']:.1f} FPS")


def summarize(folder: Path) -> Path:
    """Tabulate ``folder/*/report.json`` (one per scene) into ``folder/summary.md``, atomically."""
    from benchmark.core.atomic import read_json, write_text

    reports = sorted(Path(folder).glob("*/report.json"))
    if not reports:
        raise InputError(folder, None, "no */report.json under this folder")

    def num(value, digits=2):
        return "-" if value is None else f"{value:.{digits}f}"

    lines = ["# Reconstruction: 4D-GS vs the static 3D-GS reference", "",
             "Generated by `bench4d recon --summarize` from the `report.json` files beside this file. "
             "PSNR / SSIM on the scenes' test frames (scikit-image, data range 1); device = where it trained "
             "(`[...]`: the run's `--set` overrides); CPU = training CPU "
             "seconds of the process (what a shared machine does not inflate; on a GPU, the launching thread's "
             "time, about the wall time); wall = elapsed seconds; "
             "peak = the training process' maxrss. Moving parts (generated scenes): PSNR pooled over the pixels "
             "of parts the preset animates (`benchmark/synthetic/dynamic.py`), what static 3D-GS cannot fit, "
             "and over all other pixels (elsewhere). *Gain if moving parts perfect*: the pooled PSNR gain over "
             "3D-GS of a model that renders the moving parts exactly and everything else as 3D-GS does, "
             "10 log10(MSE_3D / ((1 - f) MSE_3D,elsewhere)) with f the moving pixel fraction: how much of a gain "
             "the motion alone can explain (more needs a better fit of what does not move). "
             "HexPlane cell: the deformation field's base cell in the motion box, and in a uniform grid over its "
             "whole box, in units of the scene (largest axis; `HexPlaneConfig.motion_cell_share`; - = a run "
             "recorded before the motion box). "
             "git = the commit that ran (+: with uncommitted changes); runs of different commits can differ "
             "by float-order changes alone (seeds of one commit: see the README).", "",
             "| scene | device | size | iterations | 4D-GS PSNR | 3D-GS PSNR | gain dB | 4D-GS SSIM | 3D-GS SSIM "
             "| 4D-GS CPU s (wall) | 3D-GS CPU s (wall) | Gaussians 4D / 3D (cap) | render FPS 4D / 3D "
             "| peak MiB 4D / 3D | dynamic Gaussians | moving parts: pixels %, PSNR 4D / 3D "
             "| elsewhere PSNR 4D / 3D | gain if moving parts perfect dB | HexPlane cell: motion box (uniform) | git |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---|---|---|---|---:|---|---|"]
    for path in reports:
        r = read_json(path)
        m = r.get("models", {})
        g4, g3 = m.get("4dgs", {}), m.get("3dgs", {})
        size = r.get("scene", {}).get("image_size") or ["?", "?"]
        gain = (g4["psnr"] - g3["psnr"]) if ("psnr" in g4 and "psnr" in g3) else None
        dyn = g4.get("dynamic_gaussians")
        span = r.get("scene", {}).get("time_range")
        overrides = r["overrides"] if "overrides" in r else _overrides(r.get("command", ""))
        seed = r.get("config", {}).get("seed", 0)
        split = r.get("split") or DEFAULT_EVAL_SPLIT  # a report written before --split names none
        parts = (([f"frames {span[0]}-{span[1]}"] if span else []) + ([f"seed {seed}"] if seed else [])
                 + ([f"split {split}"] if split != DEFAULT_EVAL_SPLIT else []))
        name = (r["scene"]["name"] + ("" if not parts else f" ({', '.join(parts)})")
                + ("" if not overrides else f" [{', '.join(overrides)}]"))
        env = r.get("environment", {})
        device = (env.get("gpu") or env.get("device", "?")) if str(env.get("device", "")).startswith("cuda") else "cpu"
        lines.append(
            f"| {name} | {device} | {size[0]}x{size[1]} | {g4.get('iterations', g3.get('iterations', '-'))} "
            f"| {num(g4.get('psnr'))} | {num(g3.get('psnr'))} | {num(gain)} | {num(g4.get('ssim'), 4)} "
            f"| {num(g3.get('ssim'), 4)} | {num(g4.get('fit_cpu_seconds'), 0)} ({num(g4.get('fit_seconds'), 0)}) "
            f"| {num(g3.get('fit_cpu_seconds'), 0)} ({num(g3.get('fit_seconds'), 0)}) "
            f"| {g4.get('gaussians', '-')} / {g3.get('gaussians', '-')} ({g4.get('cap', g3.get('cap', '-'))}) "
            f"| {num(g4.get('render_fps'), 1)} / {num(g3.get('render_fps'), 1)} "
            f"| {num(g4.get('peak_rss_mib'), 0)} / {num(g3.get('peak_rss_mib'), 0)} "
            f"| {'-' if dyn is None else dyn} | {_moving_cell(g4, g3)} | {_scores_cell(g4, g3, 'static_psnr')} "
            f"| {num(moving_gain_bound(g3.get('moving')))} | {_hexplane_cell(g4, r.get('config', {}))} "
            f"| {_commit_cell(r.get('git'))} |")
    lines += ["", "Commands:", ""]
    for path in reports:
        lines.append(f"- `{read_json(path).get('command', '?')}`")
    out = Path(folder) / "summary.md"
    write_text(out, "\n".join(lines) + "\n")
    return out


def _hexplane_cell(g4: dict, config: dict) -> str:
    """The 4D-GS HexPlane's base cell inside its motion box and over its whole box (largest axis), or -."""
    box = g4.get("field_box")
    resolution = config.get("deformation", {}).get("hexplane", {}).get("spatial_resolution")
    if not box or not box.get("cell_size") or not resolution:
        return "-"
    lo, hi = box["bounds"]
    uniform = max(h - l for l, h in zip(lo, hi)) / max(1, int(resolution) - 1)
    return f"{max(box['cell_size']):.3g} ({uniform:.3g})"


def _commit_cell(git: Optional[dict]) -> str:
    """Short commit of a report's ``git`` record, ``+`` when the tree had uncommitted changes."""
    if not git or not git.get("commit"):
        return "-"
    return str(git["commit"])[:7] + ("+" if git.get("dirty") else "")


def _overrides(command: str) -> list[str]:
    """The ``--set KEY=VALUE`` overrides of a recorded ``bench4d recon`` command line, in order (reports
    written before ``overrides`` was recorded)."""
    words = command.split()
    return [words[i + 1] for i, w in enumerate(words[:-1]) if w == "--set"]


def moving_gain_bound(moving: Optional[dict]) -> Optional[float]:
    """PSNR gain over a model with these ``moving`` scores (3D-GS: pooled ``psnr`` over the moving pixels,
    ``static_psnr`` elsewhere, ``pixel_fraction`` f) of one that renders the moving pixels exactly and the
    rest as that model: 10 log10(MSE / ((1 - f) MSE_elsewhere)). ``None`` without scores."""
    if not moving or any(moving.get(k) is None for k in ("psnr", "static_psnr", "pixel_fraction")):
        return None
    f = float(moving["pixel_fraction"])
    mse_moving, mse_rest = 10 ** (-moving["psnr"] / 10), 10 ** (-moving["static_psnr"] / 10)
    if f >= 1.0:
        return float("inf")
    return 10 * math.log10((f * mse_moving + (1 - f) * mse_rest) / ((1 - f) * mse_rest))


def _db(value: Optional[float]) -> str:
    """A PSNR cell: two decimals, ``-`` when the model was not run or has no such score."""
    return "-" if value is None or not math.isfinite(value) else f"{value:.2f}"


def _scores_cell(g4: dict, g3: dict, key: str) -> str:
    """``PSNR 4D / 3D`` of the ``moving`` score ``key`` (``psnr``: the moving parts, ``static_psnr``: the
    other pixels), ``-`` for a scene without generator truth."""
    m4, m3 = g4.get("moving") or {}, g3.get("moving") or {}
    if not m4 and not m3:
        return "-"
    return f"{_db(m4.get(key))} / {_db(m3.get(key))}"


def _moving_cell(g4: dict, g3: dict) -> str:
    """``pixels %, PSNR 4D / 3D`` of the moving parts, ``-`` for a scene without generator truth."""
    frac = ((g4.get("moving") or g3.get("moving")) or {}).get("pixel_fraction")
    return (f"{100 * frac:.1f} %, " if frac is not None else "") + _scores_cell(g4, g3, "psnr")
