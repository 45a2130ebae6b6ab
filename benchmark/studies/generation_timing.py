"""Generation time of every preset (``bench4d data timing``), written as a markdown table."""

from __future__ import annotations

import os
import platform
import shutil
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Optional, Sequence

from benchmark.core.atomic import write_text
from benchmark.synthetic.generate import GENERATOR_VERSION, generate, resolve_settings
from benchmark.synthetic.presets import PRESETS


def measure_generation(presets: Optional[Sequence[str]] = None, *, size: int = 128, seed: int = 0,
                       log: Callable[[str], None] = lambda m: None) -> list[dict]:
    """Generate each preset at its defaults (width ``size``) into a temporary folder and time it.

    Returns one row per preset: preset, layout, size, frames, views, images, wall and CPU seconds.
    CPU time is the process's own; wall time also counts waiting for a busy machine.
    """
    rows = []
    for name in presets or list(PRESETS):
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
        spec, width, frames, views, layout = resolve_settings(name, size, None, None, None)
        tmp = Path(tempfile.mkdtemp(prefix=f"bench4d-timing-{name}-"))
        try:
            wall, cpu = time.perf_counter(), time.process_time()
            generate(name, tmp / name, size=width, seed=seed)
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        rows.append({"preset": name, "layout": layout, "size": width, "frames": frames, "views": views,
                     "images": frames * views, "wall_s": wall, "cpu_s": cpu, "load": load})
        log(f"{name}: {wall:.1f} s wall, {cpu:.1f} s CPU ({frames * views} images at {width} px)")
    return rows


def write_report(rows: list[dict], path: str | Path) -> Path:
    """Markdown table of :func:`measure_generation` rows, written atomically."""
    lines = [
        "# Synthetic scene generation time",
        "",
        f"Generator {GENERATOR_VERSION}; {platform.processor() or platform.machine()}, Python "
        f"{platform.python_version()}; {datetime.now(timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}. "
        "One process, one core (numpy ray casting). Regenerate with `bench4d data timing`. "
        "CPU time is this process's own; wall time also counts waiting for a shared machine "
        "(`load` = 1-minute load average when the preset started).",
        "",
        "| preset | layout | width px | frames | views | images | wall s | CPU s | CPU ms / image | load |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r['preset']} | {r['layout']} | {r['size']} | {r['frames']} | {r['views']} | {r['images']} "
                     f"| {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {1000 * r['cpu_s'] / r['images']:.0f} | {r.get('load', float('nan')):.1f} |")
    lines.append("")
    path = Path(path)
    write_text(path, "\n".join(lines))
    return path
