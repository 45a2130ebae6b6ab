"""``bench4d doctor``: before a long run, what this machine has and lacks, one line each: Python and
torch, CUDA and its free memory, the gsplat build, the optional libraries, the real track's weights,
free disk under the cache folder and free memory against what a scene of the given size needs. It ends
with one line per supervision track: ``oracle track: ready`` or what it lacks, likewise the real track
(what only speeds a run up, CUDA and gsplat, counts for neither)."""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path
from typing import NamedTuple

from benchmark.core.memory import available_memory_gb

GB = 1 << 30


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cache-dir", type=Path, default=Path("cache"), help="where fits and supervision go")
    parser.add_argument("--width", type=int, default=960, help="image width of the scene to run (default: 960)")
    parser.add_argument("--height", type=int, default=536, help="image height (default: 536)")
    parser.add_argument("--frames", type=int, default=200, help="training frames of the scene (default: 200)")
    parser.add_argument("--track", choices=("oracle", "real"), default="real",
                        help="real: check the model weights too (default)")


TORCH_RASTER_BYTES_PER_PIXEL = 40 * 1024
"""Working set of the PyTorch rasterizer's training step per pixel of the rendered view (its candidates and
what autograd keeps of them). Measured 18-38 KB: 128x170 CPU fits (about 0.9 GB peak, 0.5 GB of it the
process), the tiny real track at 536x714 on CUDA (8.8-14.5 GB of GPU memory); at 536x960 a CPU run was killed
past 23 GB, so the upper end is what a check should assume. gsplat's CUDA kernels need a small fraction."""


def scene_needs(width: int, height: int, frames: int, torch_rasterizer: bool = False) -> dict[str, float]:
    """Rough GB a scene needs: on disk (images, three mask levels, latent features, fits) and in memory
    (its images and training views loaded at once; with ``torch_rasterizer``, where gsplat cannot run, the
    PyTorch rasterizer's working set as well, in host memory on a CPU and in GPU memory on CUDA)."""
    pixels = width * height * frames
    disk = pixels * (3 + 3 * 2 + 3 * 3 * 4) / GB + 2.0  # RGB, int16 masks, 3x3 float latents; fits and features
    memory = pixels * (3 * 4 + 3 * 2) / GB + 4.0  # float images and masks, plus models and working set
    raster = width * height * TORCH_RASTER_BYTES_PER_PIXEL / GB if torch_rasterizer else 0.0
    return {"disk_gb": round(disk, 1), "memory_gb": round(memory + raster, 1), "rasterizer_gb": round(raster, 1)}


TRACKS = ("oracle", "real")
BOTH = frozenset(TRACKS)
REAL = frozenset({"real"})
NEITHER = frozenset()
REAL_TRACK_ALTERNATIVES = frozenset({"sam-checkpoint"})
"""Backends of the real track that only an alternative setting uses (SAM from the official package's
checkpoint, ``backend=segment-anything``, instead of the default transformers one): not required."""


class Check(NamedTuple):
    """One line of the report."""

    ok: bool
    line: str
    needed_by: frozenset = NEITHER
    """The tracks that cannot run without it (empty: it helps, e.g. speed, but no track needs it)."""
    name: str = ""
    """Short name for the track summary."""


def checks(args: argparse.Namespace) -> list[Check]:
    """Everything a run needs or can use, with the tracks that need each."""
    from methods.backends import BACKENDS, locate, module_available

    out: list[Check] = [Check(sys.version_info >= (3, 10), f"python {sys.version.split()[0]}", BOTH, "python")]
    cuda_free = None  # GB free on the GPU, None without CUDA
    try:
        import torch
        out.append(Check(True, f"torch {torch.__version__}", BOTH, "torch"))
        if torch.cuda.is_available():
            free, total = torch.cuda.mem_get_info()
            cuda_free = free / GB
            out.append(Check(True, f"CUDA: {torch.cuda.get_device_name(0)}, {free / GB:.1f} of {total / GB:.1f} GB free"))
        else:
            out.append(Check(False, "CUDA: not available (runs use the CPU: fine for the oracle track at small sizes)"))
    except ImportError:
        out.append(Check(False, "torch: not installed (make setup)", BOTH, "torch"))
    gsplat = module_available("gsplat")
    out.append(Check(gsplat, "gsplat: installed (the CUDA rasterizer)" if gsplat else
                     "gsplat: not installed (pip install 'bench4d[gpu]'; the PyTorch rasterizer is used instead)"))
    required = {b.module for b in BACKENDS if b.name not in REAL_TRACK_ALTERNATIVES}
    for module, extra in (("transformers", "captioner"), ("sentence_transformers", "e5mistral"),
                          ("segment_anything", "sam"), ("open_clip", "clip"), ("ray", "ray")):
        ok = module_available(module)
        hint = "installed" if ok else f"not installed (pip install 'bench4d[{extra}]')"
        out.append(Check(ok, f"{module}: {hint}", REAL if module in required else NEITHER, module))
    if args.track == "real":
        for backend in BACKENDS:
            found = locate(backend)
            where = found.source if found.path is None else f"{found.source}: {found.path}"
            needed = NEITHER if backend.name in REAL_TRACK_ALTERNATIVES else REAL
            note = "" if needed else "; an alternative, not required"
            out.append(Check(found.present, f"weights {backend.name}: {'present' if found.present else 'missing'} "
                                            f"({where}{note})", needed, f"weights {backend.name}"))
    need = scene_needs(args.width, args.height, args.frames, torch_rasterizer=not (gsplat and cuda_free is not None))
    folder = args.cache_dir if args.cache_dir.exists() else args.cache_dir.resolve().parent
    while not folder.exists():
        folder = folder.parent
    free = shutil.disk_usage(folder).free / GB
    out.append(Check(free >= need["disk_gb"], f"disk: {free:.1f} GB free under {folder}, a {args.width}x{args.height} "
                                              f"scene of {args.frames} training frames needs about {need['disk_gb']} GB",
                     BOTH, "disk"))
    memory = available_memory_gb()
    raster = need["rasterizer_gb"]
    hint = "gsplat on a CUDA GPU needs a small fraction of it; or --scale 0.5 for a quarter"
    if raster and cuda_free is not None:  # the PyTorch rasterizer on CUDA: its working set is GPU memory
        out.append(Check(cuda_free >= raster, f"GPU memory: {cuda_free:.1f} GB free, the PyTorch rasterizer needs "
                                              f"about {raster} GB at {args.width}x{args.height} ({hint})",
                         BOTH, "GPU memory"))
        host, raster_note = need["memory_gb"] - raster, ""
    else:
        host = need["memory_gb"]
        raster_note = f", {raster} GB of it the PyTorch rasterizer's ({hint})" if raster else ""
    out.append(Check(memory >= host, f"memory: {memory:.1f} GB available, the scene needs about {host:.1f} GB"
                                     f"{raster_note}; {os.cpu_count()} CPU cores", BOTH, "memory"))
    return out


def track_summary(results: list[Check], track: str, *, weights_checked: bool = True) -> str:
    """``"<track> track: ready"`` or ``"<track> track: N missing (names)"`` from ``results`` (the real track's
    weights are only looked for with ``--track real``: without, it is never called ready)."""
    missing = [c.name or c.line for c in results if track in c.needed_by and not c.ok]
    unchecked = "; its weights were not checked (bench4d doctor --track real)" if track == "real" and not weights_checked else ""
    if missing:
        return f"{track} track: {len(missing)} missing ({', '.join(missing)}){unchecked}"
    return "real track: weights not checked (bench4d doctor --track real)" if unchecked else f"{track} track: ready"


def run(args: argparse.Namespace) -> int:
    results = checks(args)
    for check in results:
        print(f"[{'ok' if check.ok else '--'}] {check.line}")
    for track in TRACKS:
        print(track_summary(results, track, weights_checked=args.track == "real"))
    return 0
