"""Generate a preset scene: render every frame, write the layout, the truth and the annotations.

The scene is built in a staging folder beside ``out_dir`` and moved into place only when complete,
so an interrupted run never leaves a half-written scene, and an existing folder is replaced only
when asked to and only if it is itself a generated scene.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import zlib
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ..core import openblas
from benchmark.core.caption_noise import DEFAULT_CAPTION_NOISE
from benchmark.core.errors import InputError
from benchmark.core.memory import available_memory_gb
from . import layouts
from .gt import build_annotations
from .model import Catalogue, FrameContext
from .perturb import parse as parse_perturbation
from .presets import PRESETS, PresetSpec
from .render import SurfaceLayer, background_instances, instances, render, surfaces
from .splits import split_records
from benchmark.core.truth import TRUTH_DIR, TruthFrame, save_levels, write_truth

GENERATOR = "bench4d.synthetic"
GENERATOR_VERSION = "1.1"
"""1.1: the HyperNeRF layout trains on frames i % 4 == 0 (the paper's split) and renders a novel-view path."""
MIN_FRAMES = 4
"""Fewest frames a scene may have (a held-out frame and state changes need room)."""
NEAR_FAR_MARGIN = (0.9, 1.1)
"""near/far written to the layout = (min depth * first, max depth * second) over what was rendered."""
RENDER_BYTES_PER_PIXEL = 2048
"""Memory the renderer holds per pixel of a frame, measured: 0.5 KB (smoke, 512 px) to 1.8 KB (cook-spinach,
384 px). Checked against the memory available before anything is rendered."""


def _spec(preset: str) -> PresetSpec:
    if preset not in PRESETS:
        import difflib

        close = difflib.get_close_matches(preset, PRESETS, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise InputError(None, "preset", f"unknown preset {preset!r}{hint}; available: {', '.join(PRESETS)}")
    return PRESETS[preset]


def _check_target(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise InputError(out, None, "exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise InputError(out, None, "folder exists and is not empty; pass overwrite=True (--overwrite) to "
                                        "replace a previously generated scene")
        if layouts.read_meta(out).get("generator") != GENERATOR:
            raise InputError(out, None, f"folder is not empty and has no {layouts.META_FILE} from the generator: "
                                        "refusing to replace it")


def _publish(staging: Path, out: Path) -> None:
    """Move the finished staging folder to ``out`` (replacing an empty or generated folder)."""
    trash = None
    if out.exists():
        trash = out.parent / f".{out.name}.old-{os.getpid()}-{time.time_ns()}"
        os.replace(out, trash)
    os.replace(staging, out)
    if trash is not None:
        shutil.rmtree(trash, ignore_errors=True)


def resolve_settings(preset: str, size: Optional[int], frames: Optional[int], views: Optional[int],
                     layout: Optional[str], height: Optional[int] = None) -> tuple[PresetSpec, int, int, int, str]:
    """(spec, size, frames, views, layout) with defaults filled in and values checked (``height`` checked only)."""
    spec = _spec(preset)
    layout = layout or spec.default_layout
    if layout not in layouts.LAYOUTS:
        raise InputError(None, "layout", f"unknown layout {layout!r} (valid: {', '.join(layouts.LAYOUTS)})")
    size = spec.default_size if size is None else int(size)
    if size < 8 or size % 2:
        raise InputError(None, "size", f"image width must be an even number >= 8, got {size}")
    if height is not None and (int(height) < 8 or int(height) % 2 or not 0.25 <= int(height) / size <= 4):
        raise InputError(None, "height", f"image height must be an even number >= 8 within 1/4 to 4 times the "
                                         f"width ({size}), got {height}")
    frames = spec.default_frames if frames is None else int(frames)
    if frames < MIN_FRAMES:
        raise InputError(None, "frames", f"need at least {MIN_FRAMES} frames, got {frames}")
    views = spec.default_views if views is None else int(views)
    if layout == "neu3d" and views < 2:
        raise InputError(None, "views", f"a rig needs a test camera and a training camera (>= 2 views), got {views}")
    if layout != "neu3d":
        views = 1
    return spec, size, frames, views, layout


def _check_memory(size: int, height: Optional[int], layout: str, jobs: int) -> None:
    """An :class:`InputError` naming ``size`` when ``jobs`` processes, each rendering one frame, need more
    memory than is available (nothing is checked where that is unknown)."""
    aspect = height / size if height is not None else layouts.LAYOUT_SPECS[layout].setup.intrinsics.height_over_width
    need_gb = jobs * size * size * aspect * RENDER_BYTES_PER_PIXEL / (1 << 30)
    have_gb = available_memory_gb()
    if need_gb > have_gb:  # False for NaN
        per = "" if jobs == 1 else f" in each of {jobs} processes"
        raise InputError(None, "size", f"rendering a {size}x{2 * int(round(size * aspect / 2))} frame{per} needs "
                                       f"about {need_gb:.1f} GB; {have_gb:.1f} GB of memory is available")


def preset_rng(preset: str, seed: int) -> np.random.Generator:
    """The generator's random stream for ``preset`` and ``seed``: ``PRESETS[preset].build(rng, frames)`` on
    it rebuilds the scene definition a generated folder was made from (the layout plan draws from it next)."""
    return np.random.default_rng([int(seed), zlib.crc32(preset.encode())])


def generate(preset: str, out_dir: str | Path, *, size: Optional[int] = None, frames: Optional[int] = None,
             views: Optional[int] = None, layout: Optional[str] = None, seed: int = 0, overwrite: bool = False,
             shadows: bool = True, perturbation=None, height: Optional[int] = None, jobs: int = 1) -> Path:
    """Render preset ``preset`` into ``out_dir`` and return the folder.

    ``size`` is the image width in pixels (default: the preset's, 128); ``frames`` the video length;
    ``views`` the rig size in the Neu3D layout; ``layout`` one of ``hypernerf``, ``neu3d``, ``dnerf``
    (default: the preset's); ``height`` the image height in pixels (default: the layout's aspect, e.g. 536 wide
    in the HyperNeRF layout is 714 high; 960 gives the real HyperNeRF captures' 536x960). The same arguments
    and ``seed`` give identical files, on any x86-64 CPU with AVX2: where numpy's BLAS runs other kernels than
    the committed scene versions were made with, the scene is rendered in a child process that runs theirs
    (:mod:`benchmark.core.openblas`).
    ``perturbation``: a stress-suite knob ``(family, strength)`` applied to the preset
    (:mod:`benchmark.synthetic.perturb`; strength 0 is the clean scene). ``jobs``: processes that render
    the frames (contiguous runs of time steps each); the files are the same for any count.
    """
    perturbation = parse_perturbation(perturbation)
    spec, size, frames, views, layout = resolve_settings(preset, size, frames, views, layout, height)
    height = None if height is None else int(height)
    if int(jobs) < 1:
        raise InputError(None, "jobs", f"must be at least 1, got {jobs}")
    jobs = min(int(jobs), frames)
    _check_memory(size, height, layout, jobs)
    out = Path(out_dir)
    _check_target(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    if openblas.generation_needs_pinned_process():
        _generate_in_pinned_process(dict(preset=preset, out_dir=str(out), size=size, frames=frames, views=views,
                                         layout=layout, seed=int(seed), overwrite=overwrite, shadows=shadows,
                                         height=height, jobs=jobs,
                                         perturbation=None if perturbation is None else
                                         [perturbation.family, perturbation.strength]))
        return out

    plan = _Plan(preset, seed, frames, size, views, layout, height, perturbation)
    scene, catalogue, records = plan.build()

    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
    try:
        truth_dir = staging / TRUTH_DIR
        if jobs == 1:
            depth_range, evaluated = _render_frames(plan, staging, range(frames), shadows, built=(scene, catalogue,
                                                                                                 records))
        else:
            depth_range, evaluated = _render_in_processes(plan, staging, jobs, shadows)
        near_far = {cam: (lo * NEAR_FAR_MARGIN[0], hi * NEAR_FAR_MARGIN[1]) for cam, (lo, hi) in depth_range.items()}
        info = {"generator": GENERATOR, "generator_version": GENERATOR_VERSION, "preset": preset, "seed": int(seed),
                "size": size, "num_views": views, "time_sensitive": spec.time_sensitive}
        if spec.state_changes is not None:  # in the truth too: how its states change, and its captions' noise
            info["state_changes"] = spec.state_changes
        if spec.caption_noise != DEFAULT_CAPTION_NOISE:
            info["caption_noise"] = spec.caption_noise
        if height is not None:
            info["height"] = height  # in the truth too: the digest names it (absent: the layout's aspect)
        if perturbation is not None and not perturbation.is_clean:
            info["perturbation"] = perturbation.describe()  # in the truth too: the digest names it
        all_near = min(v[0] for v in near_far.values())
        all_far = max(v[1] for v in near_far.values())
        write_truth(truth_dir, frames=[TruthFrame(r.name, r.split, r.time_index, r.time, r.camera_id, r.camera,
                                                  r.image_file) for r in records],
                    catalogue=catalogue, info={**info, "layout": layout, "num_frames": frames})
        # the evaluation splits, with the multi-view factor read from the truth just written
        split_info = split_records(records, scene, catalogue, truth_dir, layout=layout,
                                   novel_view=layouts.NOVEL_VIEW if layout == "hypernerf" else None)
        layouts.write_metadata(staging, layout, records, near_far, frames,
                               {**info, "truth": TRUTH_DIR, "annotations": "annotations.json",
                                "near_far": [all_near, all_far], "analogue": spec.analogue, "splits": split_info})
        from annotations.format import save_annotations

        aset = build_annotations(out.name, catalogue, evaluated, frames, time_sensitive=spec.time_sensitive,
                                 info={"source": f"{GENERATOR} {GENERATOR_VERSION} (exact, from the id maps)",
                                       "preset": preset, "seed": int(seed), "layout": layout,
                                       # which annotated frames each evaluation split scores (in the digest)
                                       "splits": {name: entry["frames"] for name, entry in split_info.items()}})
        save_annotations(aset, staging / "annotations.json")
        _publish(staging, out)
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return out


def perturbation_changes_nothing(preset: str, perturbation, *, seed: int = 0,
                                 frames: Optional[int] = None) -> Optional[str]:
    """Why ``perturbation`` would leave preset ``preset`` (scene seed ``seed``) as it is, else None: read from
    the scene definition alone, before anything is rendered (:meth:`Perturbation.changes_nothing`)."""
    perturbation = parse_perturbation(perturbation)
    if perturbation is None:
        return None
    _, _, frames, _, _ = resolve_settings(preset, None, frames, None, None, None)
    return perturbation.changes_nothing(_spec(preset).build(preset_rng(preset, seed), frames))


@dataclass(frozen=True)
class _Plan:
    """What a scene is built from: every process that renders its frames rebuilds the same scene from it."""

    preset: str
    seed: int
    frames: int
    size: int
    views: int
    layout: str
    height: Optional[int]
    perturbation: Any

    def build(self):
        """(scene, catalogue, frame records): the preset's random stream, its layout's plan, the knob."""
        rng = preset_rng(self.preset, self.seed)
        scene = _spec(self.preset).build(rng, self.frames)
        records = layouts.plan(self.layout, scene, self.size, self.frames, self.views, rng, height=self.height)
        if self.perturbation is not None:
            # a knob acts on the captured video; the novel-view path keeps seeing the scored times as planned
            novel = [r for r in records if r.camera_id == layouts.NOVEL_CAMERA_ID]
            video = [r for r in records if r.camera_id != layouts.NOVEL_CAMERA_ID]
            scene, records = self.perturbation.apply(scene, video, self.seed)
            records = layouts.as_layout_records(self.layout, records)
            if novel:  # back in video order, a time's novel view after its frames (strength 0: the clean plan)
                records = sorted(records + novel, key=lambda rec: rec.time_index)
        return scene, Catalogue.build(scene.wholes), records


def _render_frames(plan: _Plan, staging: Path, times, shadows: bool, built=None):
    """Render the frames of the time steps ``times`` into ``staging`` (images and truth levels): their depth
    range per camera and the evaluated frames' ``(name, time index, camera, ids)``, in time order."""
    scene, catalogue, records = plan.build() if built is None else built
    by_time: dict[int, list[layouts.FrameRecord]] = defaultdict(list)
    for rec in records:
        by_time[rec.time_index].append(rec)
    truth_dir = staging / TRUTH_DIR
    depth_range: dict[str, list[float]] = {}
    evaluated = []
    # The surroundings are static: a fixed camera (a rig) sees the same background every frame.
    bg = background_instances(scene, FrameContext(0, plan.frames)) if layouts.LAYOUT_SPECS[plan.layout].background \
        else []
    static_layers: dict[int, SurfaceLayer] = {}
    for ti in times:
        insts = instances(scene, catalogue, FrameContext(ti, plan.frames), background=False)
        for rec in by_time[ti]:
            static = None
            if bg:
                key = id(rec.camera)  # rig frames share their camera object
                if key not in static_layers:
                    if plan.layout != "neu3d":
                        static_layers.clear()  # a moving camera never sees the same layer twice
                    static_layers[key] = surfaces(bg, rec.camera)
                static = static_layers[key]
            res = render(insts, rec.camera, scene.light, shadows=shadows, static=static)
            layouts.write_image(staging, plan.layout, rec, res)
            save_levels(truth_dir, rec.name, res.ids, res.depth)
            finite = res.depth[np.isfinite(res.depth)]
            if finite.size:
                _widen(depth_range, rec.camera_id, float(finite.min()), float(finite.max()))
            if rec.split == "test":
                evaluated.append((rec.name, ti, rec.camera_id, res.ids))
    return depth_range, evaluated


def _render_in_processes(plan: _Plan, staging: Path, jobs: int, shadows: bool):
    """:func:`_render_frames` over ``jobs`` processes, each a contiguous run of time steps; merged in order."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    bounds = np.linspace(0, plan.frames, jobs + 1).round().astype(int)
    chunks = [range(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    # spawn: a fresh interpreter per worker (no forked BLAS threads), with this process's environment
    with ProcessPoolExecutor(len(chunks), mp_context=multiprocessing.get_context("spawn")) as pool:
        parts = list(pool.map(_render_frames, [plan] * len(chunks), [staging] * len(chunks), chunks,
                              [shadows] * len(chunks)))
    depth_range: dict[str, list[float]] = {}
    evaluated = []
    for part_range, part_evaluated in parts:
        for cam, (lo, hi) in part_range.items():
            _widen(depth_range, cam, lo, hi)
        evaluated += part_evaluated
    return depth_range, evaluated


def _widen(depth_range: dict[str, list[float]], camera_id: str, lo: float, hi: float) -> None:
    """Grow the camera's [near, far] depth range to take in [lo, hi]."""
    old_lo, old_hi = depth_range.get(camera_id, [np.inf, 0.0])
    depth_range[camera_id] = [min(old_lo, lo), max(old_hi, hi)]


def _generate_in_pinned_process(arguments: dict) -> None:
    """``generate(**arguments)`` in a child process on the pinned BLAS kernels (its errors re-raised here)."""
    env = openblas.pinned_environment()
    package_root = str(Path(__file__).resolve().parents[2])  # importable without an install too
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH", "")) if p)
    code = "import json, sys; from benchmark.synthetic.generate import generate; generate(**json.loads(sys.argv[1]))"
    done = subprocess.run([sys.executable, "-c", code, json.dumps(arguments)], env=env, capture_output=True, text=True)
    if done.returncode != 0:
        tail = "\n".join(done.stderr.strip().splitlines()[-20:])
        raise RuntimeError(f"generating preset {arguments['preset']!r} into {arguments['out_dir']} in a child process "
                           f"on the pinned BLAS kernels failed (exit status {done.returncode}):\n{tail}")
