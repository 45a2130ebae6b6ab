"""The method API: what the harness fits, queries, times and ranks, the same way for every method.

A method is a class with two class methods::

    model = MyMethod.fit(scene, supervision, config, seed=0, device="cpu", progress=progress,
                         work_dir=path)       # train on the scene's training frames + 2D supervision
    model.save(directory)                     # the fit cache
    model = MyMethod.load(directory, supervision=supervision, device="cpu")

and the :class:`Model` answers queries on any frames of the scene (usually held-out test frames):

* time-agnostic: ``model.query_agnostic(text, frames) -> [AgnosticAnswer(mask, relevance)]``
* time-sensitive: ``model.query_sensitive(text, frames) -> [SensitiveAnswer(mask, score)]``

A method answers with per-frame *scores*; the harness turns them into yes/no decisions with the
shared temporal rule (:func:`benchmark.metrics.temporal.decide_temporal`), so no method can tune its
own threshold. A method never sees ground-truth annotations: only the scene (images, cameras, times)
and the :class:`~methods.supervision.base.Supervision` of its training frames.

Registering a method takes one spec file in :mod:`methods.specs` (see :mod:`methods.registry`).
"""

from __future__ import annotations

import abc
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Iterable, Literal, Optional, Sequence, TextIO

import numpy as np

from benchmark.core.protocol import Protocol, default_protocol
from benchmark.core.scene import Frame, Scene

from .supervision.base import Supervision

QueryKind = Literal["agnostic", "sensitive"]
QUERY_KINDS: tuple[str, str] = ("agnostic", "sensitive")


@dataclass
class AgnosticAnswer:
    """Answer to a time-agnostic query on one frame."""

    mask: np.ndarray
    """(H, W) bool: where the queried thing is."""
    relevance: np.ndarray
    """(H, W) float32: the method's per-pixel relevance (any monotone scale; for inspection)."""


@dataclass
class SensitiveAnswer:
    """Answer to a time-sensitive query on one frame."""

    mask: np.ndarray
    """(H, W) bool: where the queried thing would be (scored for vIoU on positive frames)."""
    score: float
    """How much the query holds at this frame (higher = more); NaN = undefined (nothing matched)."""


LOG_FILE_PROGRESS_SECONDS = 30.0
"""Seconds between progress-bar updates when stderr is not a terminal (a log file, a batch job, CI): a
bar redrawn ten times a second made a 40-minute ``run-all`` log 290 kB of carriage returns."""


def progress_bar(iterable: Optional[Iterable] = None, *, stream: Optional[TextIO] = None, **kwargs: Any):
    """A tqdm bar on ``stream`` (default stderr) that updates every :data:`LOG_FILE_PROGRESS_SECONDS`
    where ``stream`` is not a terminal; tqdm's arguments pass through."""
    from tqdm.auto import tqdm

    stream = sys.stderr if stream is None else stream
    is_terminal = bool(getattr(stream, "isatty", lambda: False)())
    if not is_terminal:
        kwargs.setdefault("mininterval", LOG_FILE_PROGRESS_SECONDS)
    return tqdm(iterable, file=stream, dynamic_ncols=is_terminal, **kwargs)


class Progress:
    """tqdm bars that honour ``--quiet``; a method calls ``progress(iterable, desc=..., total=...)``."""

    def __init__(self, quiet: bool = False, *, leave: bool = False) -> None:
        self.quiet = quiet
        self.leave = leave

    def __call__(self, iterable: Optional[Iterable] = None, *, desc: Optional[str] = None,
                 total: Optional[int] = None, **kwargs: Any):
        return progress_bar(iterable, desc=desc, total=total, disable=self.quiet, leave=self.leave, **kwargs)

    def log(self, message: str) -> None:
        """A line for the user (suppressed by ``--quiet``), written without breaking open bars."""
        if not self.quiet:
            from tqdm.auto import tqdm

            tqdm.write(message, file=sys.stderr)


class Model(abc.ABC):
    """A fitted method on one scene."""

    supports: ClassVar[frozenset[str]] = frozenset(QUERY_KINDS)
    """Query kinds this model answers."""

    @property
    def protocol(self) -> Protocol:
        """The evaluation protocol the model answers under (:mod:`benchmark.core.protocol`; the default preset
        until the harness hands it one with :meth:`use_protocol`)."""
        return getattr(self, "_protocol", None) or default_protocol()

    def use_protocol(self, protocol: Protocol) -> None:
        """Answer with ``protocol``'s query rules from now on. The harness calls this before asking
        anything; answers may change, the fitted state must not. A model whose answers read no protocol
        constant needs nothing more; one that memoises query state drops it here."""
        self._protocol = protocol

    def prepare(self, texts: Sequence[str]) -> None:
        """Told the texts an evaluation is about to ask (or, with the texts of one timed call, that the
        next call must do all its work). A model may keep per-frame work shared by these texts between
        calls, and must drop anything kept for earlier texts; answers must not change. Default: nothing."""

    def query_agnostic(self, text: str, frames: Sequence[Frame]) -> list[AgnosticAnswer]:
        """One :class:`AgnosticAnswer` per frame, in order, each at that frame's camera size."""
        raise NotImplementedError(f"{type(self).__name__} does not answer time-agnostic queries")

    def query_sensitive(self, text: str, frames: Sequence[Frame]) -> list[SensitiveAnswer]:
        """One :class:`SensitiveAnswer` per frame, in order, each at that frame's camera size."""
        raise NotImplementedError(f"{type(self).__name__} does not answer time-sensitive queries")

    @abc.abstractmethod
    def save(self, directory: Path) -> None:
        """Write everything :meth:`Method.load` needs into the (existing, empty) ``directory``."""


class Method(abc.ABC):
    """A registered method: fits a :class:`Model` on a scene."""

    supports: ClassVar[frozenset[str]] = frozenset(QUERY_KINDS)
    """Query kinds the fitted models answer."""
    resumable: ClassVar[bool] = False
    """True when :meth:`fit` writes intermediate checkpoints into ``work_dir`` and resumes from them."""

    @classmethod
    @abc.abstractmethod
    def fit(cls, scene: Scene, supervision: Supervision, config: Any, *, seed: int, device: str,
            progress: Progress, work_dir: Optional[Path] = None) -> Model:
        """Fit on ``scene``'s training frames and ``supervision``.

        ``work_dir`` (when given) persists across interrupted runs of the same fit: a resumable
        method writes checkpoints there atomically and continues from the last one.
        """

    @classmethod
    @abc.abstractmethod
    def load(cls, directory: Path, *, supervision: Supervision, device: str) -> Model:
        """Rebuild the model that :meth:`Model.save` wrote into ``directory``."""


def check_agnostic(answers: Sequence[AgnosticAnswer], frames: Sequence[Frame], who: str) -> None:
    """Raise a clear error if ``answers`` do not match ``frames`` (count, shapes, dtypes)."""
    if len(answers) != len(frames):
        raise ValueError(f"{who}: {len(answers)} answers for {len(frames)} frames")
    for answer, frame in zip(answers, frames):
        size = (frame.camera.height, frame.camera.width)
        mask = np.asarray(answer.mask)
        rel = np.asarray(answer.relevance)
        if mask.shape != size or mask.dtype != bool:
            raise ValueError(f"{who}: mask for frame {frame.name!r} must be bool {size}, got {mask.dtype} {mask.shape}")
        if rel.shape != size:
            raise ValueError(f"{who}: relevance for frame {frame.name!r} must be {size}, got {rel.shape}")


def check_sensitive(answers: Sequence[SensitiveAnswer], frames: Sequence[Frame], who: str) -> None:
    if len(answers) != len(frames):
        raise ValueError(f"{who}: {len(answers)} answers for {len(frames)} frames")
    for answer, frame in zip(answers, frames):
        size = (frame.camera.height, frame.camera.width)
        mask = np.asarray(answer.mask)
        if mask.shape != size or mask.dtype != bool:
            raise ValueError(f"{who}: mask for frame {frame.name!r} must be bool {size}, got {mask.dtype} {mask.shape}")
        score = float(answer.score)
        if math.isinf(score):
            raise ValueError(f"{who}: score for frame {frame.name!r} is inf (use NaN for undefined)")


def training_states(scene: Scene, annotations: Any) -> dict[str, list[str]]:
    """Per training frame of ``scene``, the texts of the time-sensitive queries of ``annotations`` (a
    :class:`benchmark.core.annotation.AnnotationSet`) whose time segments hold at the frame's time index:
    the states of the oracle captions of a scene without generator truth (D-NeRF; ``states`` of
    :func:`build_supervision`). Only training frames are asked about, so nothing of an evaluated frame's
    ground truth is passed on; empty where the annotations have no time-sensitive query."""
    sensitive = [q for q in annotations.queries if q.kind == "sensitive" and q.intervals]
    if not sensitive:
        return {}
    return {frame.name: [q.text for q in sensitive if q.holds_at(int(frame.time_index))]
            for frame in scene.train_frames}


def native_kernels_state() -> str:
    """``"loaded"`` where the Gaussian core's compiled CPU kernels run
    (:mod:`methods.gaussians.backends.native_cpu`), else ``"not used: <why>"`` (no compiler,
    ``BENCH4D_NATIVE=0``, a build that failed): every CPU fit of the process takes the PyTorch passes then."""
    from .gaussians.backends import native_cpu

    if native_cpu.kernels() is not None:
        return "loaded"
    return f"not used: {native_cpu.unavailable_reason() or 'unknown'}"


def build_supervision(scene: Scene, track: str = "oracle", **options: Any) -> Supervision:
    """The 2D supervision of ``scene``'s training frames on ``track`` (``"oracle"`` or ``"real"``), built
    once per scene and cached: :func:`methods.supervision.cache.build_supervision` (its options)."""
    from .supervision.cache import build_supervision as build

    return build(scene, track, **options)
