"""Checkpoints of a Gaussian fit: where and when it saves its training state, what it resumes from,
and the fit's clock, which counts the time spent before an interruption."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import torch

from benchmark.core.atomic import atomic_path
from benchmark.core.errors import warn
from benchmark.core.strict import file_problem, non_finite_entry

if TYPE_CHECKING:  # pragma: no cover
    from .train import FitResult


@dataclass
class Checkpointing:
    """Where and how often a fit saves its whole training state, so that an interrupted fit resumes.

    A resumed fit ends exactly as an uninterrupted one on the CPU (the state includes every random
    generator, the Adam moments, the densification statistics and the loop's bookkeeping; on CUDA the
    rasterizer's atomic adds make any two runs differ in the last bits); its ``fit_seconds`` add the
    time spent before the interruption. The file is removed when the fit completes."""

    path: Path
    """The checkpoint file (written atomically: temp file + rename)."""
    key: str
    """What the fit is (e.g. the geometry cache key): a checkpoint of another fit is ignored."""
    every_seconds: float = 120.0
    """Wall seconds between saves, plus a save where one stage ends and another begins; saving reads
    the state and never changes it."""


class FitCheckpoints:
    """One fit's checkpoints (none where ``checkpointing`` is None) and its clock."""

    def __init__(self, checkpointing: Optional[Checkpointing], kind: str, total_iterations: int,
                 device: torch.device | str = "cpu"):
        """``kind``: ``"3dgs"`` or ``"4dgs"``; a checkpoint of another kind or length is not resumed."""
        self.checkpointing = checkpointing
        self.kind = kind
        self.total_iterations = total_iterations
        self.resume = self._load(device)
        """The saved state this fit goes on from, or None (it starts over)."""
        self._fit_start = (time.perf_counter(), time.process_time())
        self._last_save = time.perf_counter()

    def _load(self, device: torch.device | str) -> Optional[dict]:
        """The saved state of this very fit, or None (no checkpointing, no file, another fit's, unreadable;
        with a warning, not a file or holding NaN or infinity)."""
        ck = self.checkpointing
        if ck is None:
            return None
        problem = file_problem(ck.path)
        if problem == "missing":
            return None
        if problem is not None:  # never opened: a FIFO would block the read
            warn(f"checkpoint {ck.path} is {problem}, not a file: the fit starts over")
            return None
        try:
            state = torch.load(ck.path, map_location=device, weights_only=True)
        except Exception:  # a corrupt or incompatible checkpoint is never trusted: the fit starts over
            return None
        if (not isinstance(state, dict) or state.get("key") != ck.key or state.get("kind") != self.kind
                or state.get("total_iterations") != self.total_iterations):
            return None
        bad = non_finite_entry(state)
        if bad is not None:  # a diverged or damaged state would be trained on, and cached as a fit
            warn(f"checkpoint {ck.path} holds non-finite values ({bad}): the fit starts over")
            return None
        return state

    def start_clock(self) -> None:
        """Fit time counts from the fit's start, the time spent before an interruption included."""
        before_wall = 0.0 if self.resume is None else float(self.resume["fit_seconds"])
        before_cpu = 0.0 if self.resume is None else float(self.resume["fit_cpu_seconds"])
        self._fit_start = (time.perf_counter() - before_wall, time.process_time() - before_cpu)

    def fit_seconds(self) -> tuple[float, float]:
        """(wall, CPU) seconds of the fit so far, the time before an interruption included."""
        return time.perf_counter() - self._fit_start[0], time.process_time() - self._fit_start[1]

    def begin_stage(self) -> None:
        """Timed saves count from the start of each stage."""
        self._last_save = time.perf_counter()

    def due(self, iteration: int, iterations: int, stage_follows: bool) -> bool:
        """Whether to save after ``iteration`` of a stage of ``iterations``: every ``every_seconds``, and
        at the stage's end where another stage follows (the end of a fit's last stage is not saved: the
        fit completes and removes its checkpoint right after)."""
        ck = self.checkpointing
        if ck is None:
            return False
        timed = time.perf_counter() - self._last_save >= ck.every_seconds
        return (timed and iteration < iterations) or (iteration == iterations and stage_follows)

    def save(self, stage: str, iteration: int, state: dict) -> None:
        """Write the training ``state`` after ``iteration`` of ``stage``, with what names the fit."""
        ck = self.checkpointing
        wall, cpu = self.fit_seconds()
        state = {"key": ck.key, "kind": self.kind, "total_iterations": self.total_iterations, "stage": stage,
                 "iteration": iteration, "fit_seconds": wall, "fit_cpu_seconds": cpu, **state}
        with atomic_path(ck.path) as tmp:
            torch.save(state, tmp)
        self._last_save = time.perf_counter()

    def finish(self, result: "FitResult") -> None:
        """Set the fit's times and where it resumed; remove the checkpoint (the caller keeps the model)."""
        result.fit_seconds, result.fit_cpu_seconds = self.fit_seconds()
        if self.resume is not None:
            result.resumed_at = {"stage": self.resume["stage"], "iteration": int(self.resume["iteration"])}
        if self.checkpointing is not None:
            Path(self.checkpointing.path).unlink(missing_ok=True)
