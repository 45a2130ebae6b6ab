"""Where two fits that differ only in torch's CPU kernels part ways.

One short 4D-GS fit per kernel setting (``ATEN_CPU_CAPABILITY``, as :mod:`.kernel_spread` sets it), each in a
fresh single-threaded process, records its loss and Gaussian count at every iteration and its densification
steps. Two settings' records are then compared step by step (:func:`parting`): the first iteration whose loss
differs at all, the largest relative difference before the fits part, the first iteration where the relative
difference exceeds :attr:`TraceConfig.jump`, the last densification at or before it, and the first iteration
whose Gaussian count differs.

What it shows: torch's vectorised operators round differently at each vector width (reductions summed in
another order, another polynomial for exp), so the losses differ in their last bits within a few iterations
and drift slowly; a densification step compares each Gaussian's accumulated gradient with a threshold and,
under the gradual budget, keeps the highest ones: where a Gaussian's value lies between the two fits' values of
the threshold or of the budget's last pick, the fits densify different Gaussians (their counts, set by the
budget, can agree for a while). From there they differ as two seeds do. No rule of this kind removes that:
any comparison has values arbitrarily close to its boundary. The compiled kernels of :mod:`methods.gaussians.backends.native_cpu` give the same
numbers at any vector width; the rest of a fit is torch's.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

TRACE_FILE_VERSION = 1


@dataclass
class TraceConfig:
    """The short fit each kernel setting runs."""

    preset: str = "smoke"
    """Synthetic preset fitted (generated with scene seed ``seed``)."""
    size: int = 64
    """Its image width."""
    static_iterations: int = 300
    """Static stage length (its densification schedule scaled to it, as every short fit's is)."""
    deformation_iterations: int = 600
    """Deformation stage length."""
    seed: int = 0
    """Scene seed and fit seed."""
    jump: float = 1e-4
    """Relative loss difference from which two fits count as parted."""
    timeout: float = 1800.0
    """Seconds one fit may take before it counts as failed."""


def trace_fit(scene_dir: Path, static_iterations: int, deformation_iterations: int, seed: int) -> dict:
    """Fit 4D-GS on ``scene_dir`` in this process and return its per-iteration record: ``steps`` as
    ``[stage, iteration, loss, gaussians]`` and ``densify`` as ``[stage, iteration]``."""
    import contextlib
    import io

    import torch

    from benchmark.loaders import load_scene
    from methods.gaussians.config import ReconConfig
    from methods.gaussians.train import Trainer

    torch.set_num_threads(1)
    scene = load_scene(scene_dir)
    cfg = ReconConfig(static_iterations=static_iterations, deformation_iterations=deformation_iterations, seed=seed)
    cfg.log_every = 1
    with contextlib.redirect_stdout(io.StringIO()):  # a progress line per iteration
        result = Trainer(scene, cfg).fit_4dgs()
    steps = [[h["stage"], int(h["iteration"]), float(h["loss"]), int(h["gaussians"])] for h in result.history]
    densify = [[stage["stage"], int(e["iteration"])] for stage in result.stages for e in stage["events"]
               if e.get("event") == "densify"]
    return {"version": TRACE_FILE_VERSION, "capability": torch.backends.cpu.get_cpu_capability(), "steps": steps,
            "densify": densify}


def _matches(doc: dict, config: TraceConfig, capability: str) -> bool:
    kept = doc.get("config") if isinstance(doc.get("config"), dict) else {}
    mine = {k: v for k, v in asdict(config).items() if k not in ("jump", "timeout")}
    return (doc.get("version") == TRACE_FILE_VERSION and doc.get("setting") == capability
            and {k: kept.get(k) for k in mine} == mine and isinstance(doc.get("steps"), list))


def run_trace(config: TraceConfig, capability: str, scene_dir: Path, kept: Path,
              log: Callable[[str], None]) -> dict:
    """The trace of ``capability`` (an ``ATEN_CPU_CAPABILITY`` value, or ``native``): read from ``kept`` when
    it is this configuration's, else fitted in a subprocess and written there atomically."""
    from benchmark.core.atomic import write_json

    from .kernel_spread import REPO, run_env

    if kept.is_file():
        try:
            doc = json.loads(kept.read_text())
        except (OSError, ValueError):
            doc = None  # damaged: traced again
        if isinstance(doc, dict) and _matches(doc, config, capability):
            return doc
    log(f"trace: {config.preset} at {config.size} px, {capability} kernels")
    with tempfile.TemporaryDirectory(prefix="bench4d-kernel-trace-") as tmp:
        out = Path(tmp) / "trace.json"
        cmd = [sys.executable, "-m", "benchmark.studies.kernel_trace", str(scene_dir), str(config.static_iterations),
               str(config.deformation_iterations), str(config.seed), str(out)]
        done = subprocess.run(cmd, cwd=str(REPO), env=run_env(capability), capture_output=True, text=True,
                              timeout=config.timeout)
        if done.returncode != 0 or not out.is_file():
            raise RuntimeError(f"the {capability} trace fit of {scene_dir} failed (exit {done.returncode}): "
                               f"{done.stderr.strip()[-3000:]}")
        doc = json.loads(out.read_text())
    doc.update({"setting": capability, "config": asdict(config)})
    write_json(kept, doc, indent=None)
    return doc


def _relative(a: float, b: float) -> float:
    scale = max(abs(a), abs(b))
    return abs(a - b) / scale if scale > 0 else 0.0


def parting(a: dict, b: dict, jump: float = TraceConfig.jump) -> dict:
    """How the traces ``a`` and ``b`` (of :func:`trace_fit`, the same fit under two kernel settings) part:

    ``first_difference`` -- the first step whose loss differs at all, ``[stage, iteration]`` (None: never);
    ``before_jump`` -- the largest relative loss difference before the first jump;
    ``first_jump`` -- the first step whose relative loss difference exceeds ``jump`` (None: never);
    ``densify_before_jump`` -- the last densification (of ``a``) at or before that step, in its stage;
    ``growth`` -- how many times larger the relative difference is at the first jump than one step before;
    ``first_count_difference`` -- ``[stage, iteration, count a, count b]`` of the first differing count;
    ``final_relative`` and ``final_counts`` -- at the last step."""
    sa, sb = a["steps"], b["steps"]
    if [s[:2] for s in sa] != [s[:2] for s in sb]:
        raise ValueError("the two traces do not record the same iterations")
    rel = [_relative(x[2], y[2]) for x, y in zip(sa, sb)]
    first_diff = next((i for i, (x, y) in enumerate(zip(sa, sb)) if x[2] != y[2]), None)
    first_jump = next((i for i, r in enumerate(rel) if r > jump), None)
    densify_before = None
    if first_jump is not None:
        stage, it = sa[first_jump][:2]
        earlier = [d for d in a["densify"] if d[0] == stage and d[1] <= it]
        densify_before = earlier[-1] if earlier else None
    count = next(([x[0], x[1], x[3], y[3]] for x, y in zip(sa, sb) if x[3] != y[3]), None)
    growth = None
    if first_jump is not None and first_jump > 0:
        growth = rel[first_jump] / max(rel[first_jump - 1], 1e-12)
    return {"first_difference": None if first_diff is None else sa[first_diff][:2],
            "before_jump": max(rel[:first_jump], default=0.0) if first_jump is not None else max(rel, default=0.0),
            "first_jump": None if first_jump is None else sa[first_jump][:2],
            "densify_before_jump": densify_before, "growth": growth, "first_count_difference": count,
            "final_relative": rel[-1] if rel else None,
            "final_counts": [sa[-1][3], sb[-1][3]] if sa else None, "steps": len(sa)}


def _step(step: Optional[Sequence]) -> str:
    return "never" if step is None else f"{step[0]} {step[1]}"


def pairings(traces: dict[str, dict], jump: float = TraceConfig.jump) -> dict[str, dict]:
    """``"x / y"`` -> :func:`parting` of every pair of the settings' traces, in their order."""
    names = list(traces)
    return {f"{x} / {y}": parting(traces[x], traces[y], jump) for i, x in enumerate(names) for y in names[i + 1:]}


def trace_markdown(config: TraceConfig, traces: dict[str, dict], pairs: dict[str, dict]) -> str:
    """The report section: every pair's :func:`parting` (``pairs``, from :func:`pairings`), and a reading
    generated from them."""
    from ._report import markdown_table

    rows, gaps, growths = [], [], []
    for label, p in pairs.items():
        gap = None
        if p["first_jump"] is not None and p["densify_before_jump"] is not None:
            gap = p["first_jump"][1] - p["densify_before_jump"][1]
            gaps.append(gap)
        if p["growth"] is not None:
            growths.append(p["growth"])
        count = p["first_count_difference"]
        rows.append([label, _step(p["first_difference"]), f"{p['before_jump']:.1e}", _step(p["first_jump"]),
                     _step(p["densify_before_jump"]) + ("" if gap is None else f" ({gap} before)"),
                     "-" if p["growth"] is None else f"{p['growth']:.0f}x",
                     "never" if count is None else f"{count[0]} {count[1]} ({count[2]} / {count[3]})",
                     f"{p['final_relative']:.1e}", f"{p['final_counts'][0]} / {p['final_counts'][1]}"])
    recorded = ", ".join(f"{n} -> {trace.get('capability')}" for n, trace in traces.items())
    head = (f"## Where the fits part\n\nOne 4D-GS fit of preset `{config.preset}` at {config.size} px "
            f"({config.static_iterations} + {config.deformation_iterations} iterations, seed {config.seed}) per kernel "
            f"setting, each in a fresh single-threaded process; loss and Gaussian count at every iteration "
            f"(kernels recorded: {recorded}). Parted: relative loss difference above {config.jump:g}.\n\n")
    table = markdown_table(["settings", "first differing loss", "largest relative difference before parting",
                            "parted at", "last densification before", "growth in that iteration",
                            "first differing Gaussian count",
                            "relative difference at the end", "Gaussians at the end"], rows)
    if gaps and len(gaps) == len(rows) and set(gaps) == {1} and growths:
        reading = (f"\n\nEvery pair parted on the iteration right after a densification step, the difference "
                   f"growing {min(growths):.0f}- to {max(growths):.0f}-fold in that one iteration: the losses drift "
                   "apart slowly in their last bits, then a densification step's threshold or its budget's last "
                   "pick falls between the two fits' values of one Gaussian's gradient, and the fits densify "
                   "different Gaussians. From there they differ as two seeds do.\n")
    elif rows and not gaps and all(p["first_jump"] is None for p in pairs.values()):
        reading = f"\n\nNo pair parted: the relative loss difference stayed at or below {config.jump:g}.\n"
    elif rows:
        reading = ("\n\nNot every pair parted right after a densification step: see the table for where the "
                   "difference grew.\n")
    else:
        reading = "\n"
    return head + table + reading


def main(argv: Optional[list[str]] = None) -> int:
    """``python -m benchmark.studies.kernel_trace SCENE STATIC DEFORMATION SEED OUT``: one trace, written to OUT."""
    from benchmark.core.atomic import write_json

    args = sys.argv[1:] if argv is None else argv
    if len(args) != 5:
        print(main.__doc__, file=sys.stderr)
        return 2
    scene, static, deformation, seed, out = args
    write_json(out, trace_fit(Path(scene), int(static), int(deformation), int(seed)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
