"""CPU timing of the PyTorch rasterizer: ``python -m benchmark.studies.rasterizer_bench``.

Measures forward + backward milliseconds per iteration (median over repeats) on a realistic surface
scene -- Gaussians lying on a back wall, a floor and three spheres in front of the camera, with
in-surface scales of about 1-4 pixels of footprint and opacities 0.5-0.9 -- at 1 and 2 threads, for
C = 6 and C = 3 + 6 channels, plus a size sweep (Gaussians x pixels grow together) with peak memory.
Writes ``reports/rasterizer_cpu.md`` atomically.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from benchmark.core.atomic import write_text
from methods.gaussians.rasterize import rasterize

REPORT = Path(__file__).resolve().parents[2] / "reports" / "rasterizer_cpu.md"


@dataclass
class SurfaceScene:
    """Gaussians on surfaces, plus the camera that sees them."""

    means: torch.Tensor  # [N, 3]
    quats: torch.Tensor  # [N, 4]
    scales: torch.Tensor  # [N, 3]
    opacities: torch.Tensor  # [N]
    colors: torch.Tensor  # [N, C]
    viewmat: torch.Tensor  # [4, 4]
    K: torch.Tensor  # [3, 3]
    width: int
    height: int


def _rotmat_to_quat(rot: np.ndarray) -> np.ndarray:
    """[N, 3, 3] rotation matrices -> [N, 4] quaternions (w, x, y, z)."""
    m = rot
    w = np.sqrt(np.clip(1.0 + m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2], 0, None)) / 2
    x = np.sqrt(np.clip(1.0 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], 0, None)) / 2
    y = np.sqrt(np.clip(1.0 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2], 0, None)) / 2
    z = np.sqrt(np.clip(1.0 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2], 0, None)) / 2
    x = np.copysign(x, m[:, 2, 1] - m[:, 1, 2])
    y = np.copysign(y, m[:, 0, 2] - m[:, 2, 0])
    z = np.copysign(z, m[:, 1, 0] - m[:, 0, 1])
    return np.stack([w, x, y, z], -1)


def surface_scene(n: int, width: int = 128, height: int = 128, channels: int = 6, seed: int = 0,
                  dtype: torch.dtype = torch.float32) -> SurfaceScene:
    """``n`` Gaussians spread by area over a wall (z = 7), a floor (y = 1.5) and three spheres.

    Camera at the origin looking along +z (OpenCV axes), field of view about 49 degrees.
    Each Gaussian is flat (normal scale 1/10 of the in-surface scales); in-surface scales are 0.6x the
    mean spacing of the Gaussians on their surface times a factor in [0.7, 1.4], which is 1-4 pixels of
    footprint at these depths for n = 10 000 at 128 x 128 (scales follow ``n`` and the image size, so
    the coverage stays alike across the size sweep).
    """
    rng = np.random.default_rng(seed)
    f = 1.1 * width
    half_x, half_y = 0.5 * width / f, 0.5 * height / f
    wall_z = 7.0
    spheres = [((-0.8, 0.2, 4.0), 0.8), ((0.9, -0.3, 5.0), 1.0), ((0.1, 0.6, 3.0), 0.5)]
    wall = (2 * half_x * wall_z * 1.1) * (2 * half_y * wall_z * 1.1)
    floor_y, floor_z = 1.5, (2.0, wall_z)
    floor = (2 * half_x * wall_z) * (floor_z[1] - floor_z[0])
    areas = np.array([wall, floor] + [4 * math.pi * r * r for _, r in spheres])
    # Same screen density everywhere: weight each surface by its area seen at a typical depth.
    depth = np.array([wall_z, 4.5, 4.0, 5.0, 3.0])
    weights = areas / depth ** 2
    counts = np.floor(n * weights / weights.sum()).astype(int)
    counts[0] += n - counts.sum()
    pts, normals, spacing = [], [], []

    def add(p: np.ndarray, normal: np.ndarray, area: float) -> None:
        pts.append(p)
        normals.append(np.broadcast_to(normal, p.shape))
        spacing.append(np.full(len(p), math.sqrt(area / max(len(p), 1))))

    k = counts[0]
    add(np.stack([rng.uniform(-1.1, 1.1, k) * half_x * wall_z, rng.uniform(-1.1, 1.1, k) * half_y * wall_z,
                  np.full(k, wall_z)], -1), np.array([0.0, 0.0, -1.0]), wall)
    k = counts[1]
    add(np.stack([rng.uniform(-1, 1, k) * half_x * wall_z, np.full(k, floor_y), rng.uniform(*floor_z, k)], -1),
        np.array([0.0, -1.0, 0.0]), floor)
    for (centre, r), k in zip(spheres, counts[2:]):
        d = rng.normal(size=(k, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        add(np.asarray(centre) + r * d, d, 4 * math.pi * r * r)
    pts, normals, spacing = np.concatenate(pts), np.concatenate(normals), np.concatenate(spacing)
    # Orthonormal frame (t1, t2, normal) per Gaussian, randomly spun about the normal.
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    ang = rng.uniform(0, 2 * math.pi, n)[:, None]
    t1, t2 = np.cos(ang) * t1 + np.sin(ang) * t2, -np.sin(ang) * t1 + np.cos(ang) * t2
    rot = np.stack([t1, t2, normals], -1)  # columns
    rot[np.linalg.det(rot) < 0, :, 1] *= -1
    s = 0.6 * spacing[:, None] * rng.uniform(0.7, 1.4, (n, 2))
    scales = np.concatenate([s, 0.1 * s.mean(1, keepdims=True)], 1)
    to = lambda a: torch.as_tensor(np.asarray(a), dtype=dtype)  # noqa: E731
    K = to([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    return SurfaceScene(
        means=to(pts), quats=to(_rotmat_to_quat(rot)), scales=to(scales),
        opacities=to(rng.uniform(0.5, 0.9, n)), colors=to(rng.uniform(0, 1, (n, channels))),
        viewmat=torch.eye(4, dtype=dtype), K=K, width=width, height=height,
    )


def time_forward_backward(scene: SurfaceScene, iters: int = 8, warmup: int = 2, threads: int = 1,
                          native: bool = True) -> dict:
    """Forward+backward of :func:`rasterize` (torch backend) on ``scene``: median wall-clock ms, median
    CPU ms (this thread's CPU time with 1 thread, the process' with more), forward-only (no grad) CPU ms.
    ``native``: with the compiled kernels where they build (else the PyTorch passes, ``BENCH4D_NATIVE=0``)."""
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    cpu_clock = time.thread_time if threads == 1 else time.process_time
    switch = os.environ.get("BENCH4D_NATIVE")
    os.environ["BENCH4D_NATIVE"] = "1" if native else "0"
    try:
        params = [t.clone().requires_grad_(True) for t in
                  (scene.means, scene.quats, scene.scales, scene.opacities, scene.colors)]
        gen = torch.Generator().manual_seed(0)
        target = torch.rand(scene.height, scene.width, scene.colors.shape[1], generator=gen, dtype=scene.means.dtype)

        def step():
            for p in params:
                p.grad = None
            out = rasterize(*params, scene.viewmat, scene.K, scene.width, scene.height, backend="torch")
            loss = ((out.image - target) ** 2).mean() + out.depth.mean() * 1e-3
            loss.backward()
            return out

        for _ in range(warmup):
            step()
        wall, cpu, fwd = [], [], []
        for _ in range(iters):
            t0, c0 = time.perf_counter(), cpu_clock()
            out = step()
            wall.append(time.perf_counter() - t0)
            cpu.append(cpu_clock() - c0)
        for _ in range(max(3, iters // 2)):
            with torch.no_grad():
                c0 = cpu_clock()
                rasterize(*[p.detach() for p in params], scene.viewmat, scene.K, scene.width, scene.height,
                          backend="torch")
                fwd.append(cpu_clock() - c0)
        return {
            "ms": 1e3 * statistics.median(wall), "cpu_ms": 1e3 * statistics.median(cpu),
            "forward_cpu_ms": 1e3 * statistics.median(fwd), "pairs": out.n_pairs, "candidates": out.n_candidates,
            "visible": int(out.visible.sum()), "coverage": float((out.alpha > 0.5).float().mean()),
        }
    finally:
        torch.set_num_threads(old)
        if switch is None:
            os.environ.pop("BENCH4D_NATIVE", None)
        else:
            os.environ["BENCH4D_NATIVE"] = switch


def _status_kib(field: str) -> int:
    with open("/proc/self/status") as fh:
        return next(int(line.split()[1]) for line in fh if line.startswith(field + ":"))


def measure_step_memory(n: int, side: int, channels: int = 6) -> float:
    """In this process: MiB by which one forward+backward raises the peak resident memory above the
    resident memory just before it (Linux: the peak is reset through ``/proc/self/clear_refs``)."""
    time_forward_backward(surface_scene(200, 16, 16, channels=2), iters=1, warmup=1)  # one-time allocations
    scene = surface_scene(n, side, side, channels=channels)
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")  # reset VmHWM to the current RSS
    base = _status_kib("VmRSS")
    time_forward_backward(scene, iters=1, warmup=0)
    return (_status_kib("VmHWM") - base) / 1024


def memory_of_one_step(n: int, side: int, channels: int = 6) -> float:
    """:func:`measure_step_memory` in a fresh single-threaded process (MiB)."""
    code = ("import torch; torch.set_num_threads(1); from benchmark.studies.rasterizer_bench import measure_step_memory; "
            f"print(measure_step_memory({n}, {side}, {channels}))")
    root = Path(__file__).resolve().parents[2]
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root, check=True)
    return float(res.stdout.strip().splitlines()[-1])


def run_benchmark(iters: int = 8, report: Path = REPORT, sizes: bool = True) -> str:
    """Measure and write ``report`` (Markdown); returns the text."""
    torch.set_flush_denormal(True)
    load = os.getloadavg()
    from methods.gaussians.backends import native_cpu

    compiled = native_cpu.kernels() is not None
    lines = [
        "# CPU rasterizer timing (PyTorch backend)",
        "",
        f"Command: `python -m benchmark.studies.rasterizer_bench --iters {iters}`. Forward + backward of "
        "`rasterize(..., backend=\"torch\")` with an L2 image loss plus a depth term; median of "
        f"{iters} iterations after 2 warm-up iterations. *wall* = elapsed time; *CPU* = CPU time of the "
        "iteration (the thread's with 1 thread, the whole process' with 2), which is what the "
        "iteration costs when the machine is shared. Forward-only (no grad) CPU time in brackets. "
        "*kernels*: the compiled kernels (`native`, the default where a C compiler builds them) or the "
        "PyTorch passes (`pytorch`, `BENCH4D_NATIVE=0`)"
        + ("." if compiled else f" (the kernels did not build here: {native_cpu.unavailable_reason()})."),
        f"torch {torch.__version__}, Python {platform.python_version()}, {os.cpu_count()} CPUs, "
        f"load average at start {load[0]:.1f} (1 min) -- other jobs were running: wall times above the "
        "CPU times are waiting for a core.",
        "Scene: `surface_scene` (Gaussians on a wall, a floor and three spheres; 1-4 px footprints; "
        "opacity 0.5-0.9); 128x128 covers the image with about 31 composited Gaussians per pixel.",
        "",
        "| kernels | Gaussians | image | channels | threads | wall ms | CPU ms | (fwd CPU ms) | composited pairs "
        "| candidates |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    kinds = (("native", True), ("pytorch", False)) if compiled else (("pytorch", False),)
    for channels, label in ((6, "6"), (9, "3+6")):
        scene = surface_scene(10_000, 128, 128, channels=channels)
        for threads in (1, 2):
            for kind, native in kinds:
                r = time_forward_backward(scene, iters=iters, threads=threads, native=native)
                lines.append(f"| {kind} | 10000 | 128x128 | {label} | {threads} | {r['ms']:.1f} | {r['cpu_ms']:.1f} | "
                             f"({r['forward_cpu_ms']:.1f}) | {r['pairs']} | {r['candidates']} |")
                print(lines[-1], flush=True)
    if sizes:
        lines += [
            "",
            "## Size sweep (1 thread, C = 6, the default kernels): Gaussians and pixels grow together",
            "",
            "Extra memory = peak resident memory during one forward+backward minus the resident memory "
            "just before it (fresh process, peak reset through /proc/self/clear_refs).",
            "",
            "| Gaussians | image | wall ms | CPU ms | CPU us per 1k pixels | extra MiB | composited pairs |",
            "|---:|---|---:|---:|---:|---:|---:|",
        ]
        for n, side in ((2_500, 64), (10_000, 128), (40_000, 256)):
            scene = surface_scene(n, side, side, channels=6)
            r = time_forward_backward(scene, iters=iters if n <= 10_000 else max(3, iters // 2), threads=1)
            mem = memory_of_one_step(n, side)
            lines.append(f"| {n} | {side}x{side} | {r['ms']:.1f} | {r['cpu_ms']:.1f} | "
                         f"{r['cpu_ms'] * 1e3 / (side * side / 1e3):.0f} | {mem:.0f} | {r['pairs']} |")
            print(lines[-1], flush=True)
    lines.append("")
    lines.append(f"Load average at end: {os.getloadavg()[0]:.1f}.")
    text = "\n".join(lines) + "\n"
    write_text(report, text)
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmark.studies.rasterizer_bench", description=__doc__.split("\n")[0])
    parser.add_argument("--iters", type=int, default=8, help="timed iterations per setting (median reported)")
    parser.add_argument("--no-sizes", action="store_true", help="skip the size sweep")
    parser.add_argument("--report", type=Path, default=REPORT, help="Markdown file to write")
    args = parser.parse_args(argv)
    run_benchmark(iters=args.iters, report=args.report, sizes=not args.no_sizes)
    print(f"wrote {args.report}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
