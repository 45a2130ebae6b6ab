"""``nearest-frame``: answer every query with the 2D supervision of the nearest training frame.

No 3D, no learning: for a query frame it takes the training frame nearest in time (and camera, for
multi-view scenes), compares the query text with the feature of every mask of that frame at each of
the three levels, and answers with the best-matching mask. Relevance is the LERF relevance of each
mask painted over its pixels; the time-sensitive score is the cosine between the query embedding and
the chosen mask's feature. It is the floor every 3D/4D method must clear: a method that does not beat
copying its own supervision has learnt nothing from geometry or time.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from benchmark.core.scene import Frame, Scene

from .api import AgnosticAnswer, Method, Model, Progress, SensitiveAnswer
from .specs._recorded import config_from_record
from .specs.nearest_frame import NearestFrameConfig
from .supervision.base import LEVELS, Supervision, TextEncoder

STATE_FILE = "nearest_frame.npz"
META_FILE = "nearest_frame.json"


def _view_direction(frame: Frame) -> np.ndarray:
    """(3,) unit viewing direction (camera +z) in world coordinates."""
    d = frame.camera.R.T @ np.array([0.0, 0.0, 1.0])
    return d / np.linalg.norm(d)


def _resize_nearest(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Nearest-neighbour resize of an (h, w) map to (height, width), pixel centres aligned."""
    h, w = image.shape
    if (h, w) == (height, width):
        return image
    rows = np.minimum(((np.arange(height) + 0.5) * h / height).astype(int), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w / width).astype(int), w - 1)
    return image[rows[:, None], cols[None, :]]


class NearestFrameModel(Model):
    supports = frozenset({"agnostic", "sensitive"})

    def __init__(self, config: NearestFrameConfig, text_encoder: TextEncoder, *, names: list[str],
                 times: np.ndarray, centers: np.ndarray, directions: np.ndarray, time_step: float,
                 extent: float, levels: list[np.ndarray], features: list[tuple[np.ndarray, ...]]) -> None:
        self.config = config
        self.text_encoder = text_encoder
        self.names = names
        self.times = np.asarray(times, dtype=np.float64)            # (N,)
        self.centers = np.asarray(centers, dtype=np.float64)        # (N, 3)
        self.directions = np.asarray(directions, dtype=np.float64)  # (N, 3)
        self.time_step = float(time_step)
        self.extent = float(extent)
        self.levels = levels        # N x (3, H, W) int16
        self.features = features    # N x 3 x (M_l, D) float32
        self._canon: Optional[np.ndarray] = None

    # -- which training frame ------------------------------------------------------------------
    def nearest(self, frame: Frame) -> int:
        """Index of the training frame nearest to ``frame`` in time and camera."""
        cost = np.abs(self.times - float(frame.time)) / self.time_step
        if self.config.camera_weight > 0:
            centre_dist = np.linalg.norm(self.centers - frame.camera.center, axis=1) / self.extent
            angle_cost = 1.0 - self.directions @ _view_direction(frame)
            cost = cost + self.config.camera_weight * (centre_dist + angle_cost)
        return int(np.argmin(cost))

    def use_protocol(self, protocol) -> None:
        super().use_protocol(protocol)
        self._canon = None  # the canonical phrases are the protocol's

    # -- matching ------------------------------------------------------------------------------
    def _canonical(self) -> np.ndarray:
        if self._canon is None:
            self._canon = self.text_encoder.encode(list(self.protocol.agnostic.canonical_phrases), kind="query")
        return self._canon

    def _match(self, query: np.ndarray, index: int) -> tuple[int, int, np.ndarray, np.ndarray, bool]:
        """Best mask of training frame ``index`` for ``query`` (D,).

        Returns (level, mask index, (M,) relevance of that level's masks, (M,) cosine of that
        level's masks, matched?). Level choice as the paper's: the level whose relevance peaks highest.
        """
        best: Optional[tuple] = None
        canon = self._canonical()  # (P, D)
        for level in range(len(LEVELS)):
            feats = self.features[index][level]  # (M, D)
            if feats.shape[0] == 0:
                continue
            cos = feats @ query  # (M,)
            canon_cos = feats @ canon.T  # (M, P)
            # LERF: min over canonical phrases of sigmoid(s (q.f - c.f))
            rel = 1.0 / (1.0 + np.exp(-self.protocol.agnostic.temperature * (cos[:, None] - canon_cos)))
            rel = rel.min(axis=1)
            m = int(np.argmax(rel))
            key = (rel[m], cos[m])
            if best is None or key > best[0]:
                best = (key, level, m, rel, cos)
        if best is None:
            return -1, -1, np.zeros(0), np.zeros(0), False
        (peak, _), level, m, rel, cos = best
        matched = self.config.match_rule == "best" or peak > 0.5
        return level, m, rel.astype(np.float32), cos.astype(np.float32), matched

    def _answer(self, text: str, frame: Frame) -> tuple[np.ndarray, np.ndarray, float]:
        query = self.text_encoder.encode([text], kind="query")[0]
        index = self.nearest(frame)
        level, m, rel, cos, matched = self._match(query, index)
        h, w = frame.camera.height, frame.camera.width
        if level < 0:
            return np.zeros((h, w), bool), np.zeros((h, w), np.float32), float("nan")
        ids = _resize_nearest(self.levels[index][level], h, w)
        painted = np.where(ids >= 0, rel[np.maximum(ids, 0)], 0.0).astype(np.float32)
        mask = (ids == m) if matched else np.zeros((h, w), bool)
        return mask, painted, float(cos[m]) if matched else float("nan")

    # -- the API -------------------------------------------------------------------------------
    def query_agnostic(self, text: str, frames: Sequence[Frame]) -> list[AgnosticAnswer]:
        out = []
        for frame in frames:
            mask, rel, _ = self._answer(text, frame)
            out.append(AgnosticAnswer(mask=mask, relevance=rel))
        return out

    def query_sensitive(self, text: str, frames: Sequence[Frame]) -> list[SensitiveAnswer]:
        out = []
        for frame in frames:
            mask, _, score = self._answer(text, frame)
            out.append(SensitiveAnswer(mask=mask, score=score))
        return out

    def save(self, directory: Path) -> None:
        directory = Path(directory)
        arrays = {"times": self.times, "centers": self.centers, "directions": self.directions}
        for i, (lv, feats) in enumerate(zip(self.levels, self.features)):
            arrays[f"levels/{i}"] = lv
            for level, f in enumerate(feats):
                arrays[f"features/{i}/{level}"] = f
        np.savez_compressed(directory / STATE_FILE, **arrays)
        meta = {"names": self.names, "time_step": self.time_step, "extent": self.extent,
                "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(self.config).items()}}
        (directory / META_FILE).write_text(json.dumps(meta, indent=1))


class NearestFrame(Method):
    """See the module docstring."""

    supports = frozenset({"agnostic", "sensitive"})

    @classmethod
    def fit(cls, scene: Scene, supervision: Supervision, config: NearestFrameConfig, *, seed: int,
            device: str, progress: Progress, work_dir: Optional[Path] = None) -> NearestFrameModel:
        frames = [scene.frame(s.name) for s in supervision.frames]
        if not frames:
            raise ValueError("nearest-frame needs at least one supervised training frame")
        times = np.array([f.time for f in frames])
        gaps = np.diff(np.unique(times))
        time_step = float(np.median(gaps)) if gaps.size else 1.0
        extent = float(np.linalg.norm(scene.bounds[1] - scene.bounds[0]) / 2.0) or 1.0
        return NearestFrameModel(
            config, supervision.text_encoder, names=[f.name for f in frames], times=times,
            centers=np.stack([f.camera.center for f in frames]),
            directions=np.stack([_view_direction(f) for f in frames]), time_step=time_step, extent=extent,
            levels=[s.levels for s in supervision.frames], features=[s.features for s in supervision.frames])

    @classmethod
    def load(cls, directory: Path, *, supervision: Supervision, device: str) -> NearestFrameModel:
        directory = Path(directory)
        meta = json.loads((directory / META_FILE).read_text())
        config = config_from_record(NearestFrameConfig, meta["config"], what=f"{directory / META_FILE}: config")
        with np.load(directory / STATE_FILE, allow_pickle=False) as data:
            n = len(meta["names"])
            levels = [data[f"levels/{i}"] for i in range(n)]
            features = [tuple(data[f"features/{i}/{level}"] for level in range(len(LEVELS))) for i in range(n)]
            return NearestFrameModel(config, supervision.text_encoder, names=meta["names"], times=data["times"],
                                     centers=data["centers"], directions=data["directions"],
                                     time_step=meta["time_step"], extent=meta["extent"], levels=levels,
                                     features=features)
