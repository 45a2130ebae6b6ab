"""The 2D floors: answer every query from the supervision of the nearest training view, with no 3D or 4D model.

A method that does not beat copying its own supervision has learnt nothing from geometry or time. Both
floors pick the training view at the least distance ``angle + time_weight * steps`` from the queried frame
(:class:`NearestView`; :class:`methods.specs.nearest_frame.NearestViewConfig`) and paint its 2D
supervision at the queried camera, pixel for pixel (no warping: a view far from the queried one pays for it).

* ``nearest-frame`` (:class:`NearestFrame`) answers as the language fields do. Time-agnostic: each level's
  mask features give their masks' LERF relevance (against the protocol's canonical phrases, at its
  temperature), painted over their pixels (0 where no mask is), and the protocol's query rule
  (:func:`methods.fields.relevance.answer_from_relevance`: smoothing, min-max threshold, majority filter,
  level choice) makes the mask, as it does for a field's decoded features. Time-sensitive: the view's
  captions replayed (the time-varying heads' captions, :mod:`methods.captioners.supervision`): the score is
  the mean cosine, over the time-agnostic answer's spatial mask (the protocol's
  :attr:`~benchmark.core.protocol.SensitiveQuery.mask`), between the query and the caption embedding of the
  tracked object under each pixel, through the same caption text encoder as the heads and the harness's
  temporal rule; NaN where the mask covers no captioned object.
* ``nearest-frame-masks`` (:class:`NearestFrameMasks`) selects a mask: the view's mask, over the three levels,
  whose LERF relevance peaks highest answers (``"canonical"`` matching: only where it beats every canonical
  phrase), with no smoothing, threshold or majority filter; its time-sensitive score is that mask feature's
  cosine to the query.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch

from benchmark.core.scene import Camera, Frame, Scene

from .api import AgnosticAnswer, Method, Model, Progress, SensitiveAnswer
from .fields.relevance import AgnosticResult, answer_from_relevance, encode_canonical, relevance, spatial_mask
from .specs._recorded import config_from_record
from .specs.nearest_frame import NearestFrameConfig, NearestFrameMasksConfig, NearestViewConfig
from .supervision.base import LEVELS, Supervision, TextEncoder

STATE_FILE = "nearest_frame.npz"
META_FILE = "nearest_frame.json"


def view_direction(camera: Camera) -> np.ndarray:
    """(3,) unit viewing direction (camera +z) in world coordinates."""
    d = camera.R.T @ np.array([0.0, 0.0, 1.0])
    return d / np.linalg.norm(d)


def _resize_nearest(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Nearest-neighbour resize of an (h, w) map to (height, width), pixel centres aligned."""
    h, w = image.shape
    if (h, w) == (height, width):
        return image
    rows = np.minimum(((np.arange(height) + 0.5) * h / height).astype(int), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w / width).astype(int), w - 1)
    return image[rows[:, None], cols[None, :]]


class NearestView:
    """Which training view a floor answers from (:class:`~methods.specs.nearest_frame.NearestViewConfig`)."""

    def __init__(self, times: np.ndarray, directions: np.ndarray, time_step: float, time_weight: float) -> None:
        self.times = np.asarray(times, dtype=np.float64)            # (N,)
        self.directions = np.asarray(directions, dtype=np.float64)  # (N, 3) unit
        self.time_step = float(time_step)
        self.time_weight = float(time_weight)

    @staticmethod
    def time_step_of(times: np.ndarray) -> float:
        """One training-frame step of time: the median gap between distinct training times (1 without gaps)."""
        gaps = np.diff(np.unique(np.asarray(times, dtype=np.float64)))
        return float(np.median(gaps)) if gaps.size else 1.0

    def distances(self, frame: Frame) -> np.ndarray:
        """(N,) ``angle + time_weight * steps`` of every training view from ``frame``."""
        cos = np.clip(self.directions @ view_direction(frame.camera), -1.0, 1.0)
        steps = np.abs(self.times - float(frame.time)) / self.time_step
        return np.arccos(cos) + self.time_weight * steps

    def nearest(self, frame: Frame) -> int:
        """Index of the training view nearest to ``frame`` (the first of equally near ones)."""
        return int(np.argmin(self.distances(frame)))


class _NearestViewModel(Model):
    """What both floors keep: the training views' times, viewing directions and supervision."""

    def __init__(self, config: NearestViewConfig, text_encoder: TextEncoder, *, names: list[str], times: np.ndarray,
                 directions: np.ndarray, time_step: float, levels: list[np.ndarray],
                 features: list[tuple[np.ndarray, ...]]) -> None:
        self.config = config
        self.text_encoder = text_encoder
        self.names = list(names)
        self.view = NearestView(times, directions, time_step, config.time_weight)
        self.levels = levels        # N x (3, H, W) int16
        self.features = features    # N x 3 x (M_l, D) float32
        self._canon: Optional[torch.Tensor] = None

    @property
    def times(self) -> np.ndarray:
        return self.view.times

    def nearest(self, frame: Frame) -> int:
        """Index of the training view the floor answers ``frame`` from."""
        return self.view.nearest(frame)

    def use_protocol(self, protocol) -> None:
        super().use_protocol(protocol)
        self._canon = None  # the canonical phrases are the protocol's

    def canonical(self) -> torch.Tensor:
        """[P, D] embeddings of the protocol's canonical phrases."""
        if self._canon is None:
            self._canon = encode_canonical(self.text_encoder, self.protocol.agnostic.canonical_phrases)
        return self._canon

    def query_vector(self, text: str) -> torch.Tensor:
        return torch.as_tensor(self.text_encoder.encode([text], kind="query")[0], dtype=torch.float32)

    def mask_relevance(self, query: torch.Tensor, index: int, level: int) -> torch.Tensor:
        """[M] LERF relevance of each mask of ``level`` of training view ``index`` (protocol's temperature)."""
        feats = torch.as_tensor(np.asarray(self.features[index][level], dtype=np.float32))
        if feats.shape[0] == 0:
            return feats.new_zeros(0)
        return relevance(feats, query, self.canonical(), self.protocol.agnostic.temperature)

    def mask_ids(self, index: int, level: int, frame: Frame) -> np.ndarray:
        """(H, W) mask index of each pixel of ``frame`` at ``level`` of training view ``index`` (-1: none)."""
        return _resize_nearest(self.levels[index][level], frame.camera.height, frame.camera.width)

    def _arrays(self) -> dict[str, np.ndarray]:
        arrays = {"times": self.view.times, "directions": self.view.directions}
        for i, (lv, feats) in enumerate(zip(self.levels, self.features)):
            arrays[f"levels/{i}"] = lv
            for level, f in enumerate(feats):
                arrays[f"features/{i}/{level}"] = f
        return arrays

    def _meta(self) -> dict[str, Any]:
        return {"names": self.names, "time_step": self.view.time_step,
                "config": json.loads(json.dumps(dataclasses.asdict(self.config), default=str))}

    def save(self, directory: Path) -> None:
        directory = Path(directory)
        np.savez_compressed(directory / STATE_FILE, **self._arrays())
        (directory / META_FILE).write_text(json.dumps(self._meta(), indent=1))


class NearestFrameModel(_NearestViewModel):
    """``nearest-frame``: the protocol's query rule on the nearest view's painted relevance; its captions
    replayed for time-sensitive queries (see the module docstring)."""

    supports = frozenset({"agnostic", "sensitive"})

    def __init__(self, config: NearestFrameConfig, text_encoder: TextEncoder, *, caption_encoder=None,
                 caption_rows: Optional[list[np.ndarray]] = None, caption_embeddings: Optional[np.ndarray] = None,
                 caption_info: Optional[dict] = None, **views: Any) -> None:
        super().__init__(config, text_encoder, **views)
        self.caption_encoder = caption_encoder
        self.caption_rows = caption_rows              # N x (H, W) int32: row of caption_embeddings, -1 = none
        self.caption_embeddings = caption_embeddings  # (T, D) float32 unit passage embeddings
        self.caption_info = dict(caption_info or {})
        if caption_rows is None:  # no captions to replay: time-agnostic answers only
            self.supports = frozenset({"agnostic"})

    def painted_relevance(self, text: str, frame: Frame) -> torch.Tensor:
        """[L, H, W] relevance at ``frame``'s camera: each level's masks of the nearest training view painted
        with their LERF relevance to ``text``, 0 where no mask is (what the protocol's rule reads)."""
        index = self.nearest(frame)
        query = self.query_vector(text)
        out = torch.zeros((len(LEVELS), frame.camera.height, frame.camera.width), dtype=torch.float32)
        for level in range(len(LEVELS)):
            rel = self.mask_relevance(query, index, level)
            if rel.numel() == 0:
                continue
            ids = torch.as_tensor(self.mask_ids(index, level, frame).astype(np.int64))
            covered = ids >= 0
            out[level][covered] = rel[ids[covered]]
        return out

    def agnostic(self, text: str, frame: Frame) -> AgnosticResult:
        """The protocol's time-agnostic query on the painted relevance of ``frame``."""
        return answer_from_relevance(self.painted_relevance(text, frame), self.protocol.agnostic)

    def caption_score(self, text: str, frame: Frame, spatial: AgnosticResult) -> float:
        """Mean cosine between ``text`` and the nearest view's caption embeddings over the spatial mask of the
        time-agnostic answer ``spatial`` (NaN where it covers no captioned object)."""
        index = self.nearest(frame)
        mask = spatial_mask(spatial, self.protocol.sensitive).cpu().numpy()
        rows = _resize_nearest(self.caption_rows[index], frame.camera.height, frame.camera.width)[mask]
        rows = rows[rows >= 0]
        if rows.size == 0:
            return float("nan")
        query = self.caption_encoder.encode([text], kind="query")[0]
        return float(np.mean((self.caption_embeddings @ query)[rows]))

    def query_agnostic(self, text: str, frames: Sequence[Frame]) -> list[AgnosticAnswer]:
        out = []
        for frame in frames:
            res = self.agnostic(text, frame)
            out.append(AgnosticAnswer(mask=res.mask.numpy(), relevance=res.relevance.numpy()))
        return out

    def query_sensitive(self, text: str, frames: Sequence[Frame]) -> list[SensitiveAnswer]:
        if self.caption_rows is None:
            raise NotImplementedError("nearest-frame replays no captions on this scene (replay is off)")
        out = []
        for frame in frames:
            res = self.agnostic(text, frame)
            out.append(SensitiveAnswer(mask=res.mask.numpy(), score=self.caption_score(text, frame, res)))
        return out

    def describe(self) -> dict:
        """What the fit did, for the results file: whether captions are replayed, and whose."""
        return {"caption_replay": self.caption_rows is not None, **self.caption_info}

    def _arrays(self) -> dict[str, np.ndarray]:
        arrays = super()._arrays()
        if self.caption_rows is not None:
            arrays["caption_embeddings"] = self.caption_embeddings
            arrays.update({f"caption_rows/{i}": rows for i, rows in enumerate(self.caption_rows)})
        return arrays

    def _meta(self) -> dict[str, Any]:
        return {**super()._meta(), "caption_info": self.caption_info}


class NearestFrameMasksModel(_NearestViewModel):
    """``nearest-frame-masks``: the nearest view's best-matching mask (see the module docstring)."""

    supports = frozenset({"agnostic", "sensitive"})

    def _match(self, query: torch.Tensor, index: int) -> tuple[int, int, np.ndarray, np.ndarray, bool]:
        """Best mask of training view ``index`` for ``query`` (D,).

        Returns (level, mask index, (M,) relevance of that level's masks, (M,) cosine of that level's masks,
        matched?). The level is the one whose best mask's relevance (then cosine) is highest.
        """
        best: Optional[tuple] = None
        q = query.numpy()
        for level in range(len(LEVELS)):
            feats = np.asarray(self.features[index][level], dtype=np.float32)  # (M, D)
            if feats.shape[0] == 0:
                continue
            cos = feats @ q
            rel = self.mask_relevance(query, index, level).numpy()
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
        index = self.nearest(frame)
        level, m, rel, cos, matched = self._match(self.query_vector(text), index)
        h, w = frame.camera.height, frame.camera.width
        if level < 0:
            return np.zeros((h, w), bool), np.zeros((h, w), np.float32), float("nan")
        ids = self.mask_ids(index, level, frame)
        painted = np.where(ids >= 0, rel[np.maximum(ids, 0)], 0.0).astype(np.float32)
        mask = (ids == m) if matched else np.zeros((h, w), bool)
        return mask, painted, float(cos[m]) if matched else float("nan")

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


def _views(scene: Scene, supervision: Supervision) -> dict[str, Any]:
    """The training views of ``supervision``: names, times, viewing directions, time step, supervision."""
    frames = [scene.frame(s.name) for s in supervision.frames]
    if not frames:
        raise ValueError("a nearest-view floor needs at least one supervised training frame")
    times = np.array([f.time for f in frames], dtype=np.float64)
    return {"names": [f.name for f in frames], "times": times,
            "directions": np.stack([view_direction(f.camera) for f in frames]),
            "time_step": NearestView.time_step_of(times),
            "levels": [s.levels for s in supervision.frames], "features": [s.features for s in supervision.frames]}


def _load_views(directory: Path, config_class: type) -> tuple[Any, dict[str, Any], dict[str, np.ndarray], dict]:
    """(config, the views' keyword arguments, the other arrays, the meta record) saved in ``directory``."""
    meta = json.loads((directory / META_FILE).read_text())
    config = config_from_record(config_class, meta["config"], what=f"{directory / META_FILE}: config")
    with np.load(directory / STATE_FILE, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    n = len(meta["names"])
    views = {"names": meta["names"], "times": arrays["times"], "directions": arrays["directions"],
             "time_step": meta["time_step"], "levels": [arrays[f"levels/{i}"] for i in range(n)],
             "features": [tuple(arrays[f"features/{i}/{level}"] for level in range(len(LEVELS))) for i in range(n)]}
    return config, views, arrays, meta


def _cache_root(work_dir: Optional[Path]) -> Optional[Path]:
    """The runner's cache folder (its ``work_dir`` is ``<cache>/fits/<method>/<scene>/<key>.work``), where the
    captions of a scene are cached once for every method; ``None`` outside the runner."""
    if work_dir is None:
        return None
    for parent in Path(work_dir).resolve().parents:
        if parent.name == "fits":
            return parent.parent
    return None


def _caption_replay(scene: Scene, supervision: Supervision, config: NearestFrameConfig, *, device: str,
                    progress: Progress, work_dir: Optional[Path]) -> dict[str, Any]:
    """The keyword arguments of :class:`NearestFrameModel` that replay captions (none when replay is off):
    per training view the caption row of the tracked object under each pixel, the caption embeddings, and
    their text encoder."""
    from .captioners import captioning_unavailable

    if config.replay == "off":
        return {}
    if config.replay == "auto":
        why = captioning_unavailable(config.captions, scene, supervision)
        if why:
            progress.log(f"nearest-frame: caption replay off ({why}); time-sensitive queries stay unanswered")
            return {}
    from .captioners.supervision import build_captions, caption_text_encoder, embed_captions

    captions, tracks = build_captions(scene, supervision.track, config.captions, supervision=supervision,
                                      cache_root=_cache_root(work_dir), device=device, progress=progress)
    encoder = caption_text_encoder(config.captions, supervision.text_encoder, device)
    sup = embed_captions(captions, tracks, encoder)
    rows = []
    for fs in supervision.frames:
        try:
            ids = tracks.ids[tracks.index(fs.name)]
        except KeyError:
            rows.append(np.full(fs.levels.shape[1:], -1, dtype=np.int32))
            continue
        lookup = {obj: sup.text_index.get((fs.name, obj), -1) for obj in np.unique(ids[ids >= 0]).tolist()}
        out = np.full(ids.shape, -1, dtype=np.int32)
        for obj, row in lookup.items():
            out[ids == obj] = row
        rows.append(out)
    info = {"captioner": captions.captioner, "object_tracks": tracks.source, "captions": len(captions.frames),
            "distinct_captions": len(sup.texts)}
    return {"caption_encoder": encoder, "caption_rows": rows, "caption_embeddings": sup.embeddings,
            "caption_info": info}


class NearestFrame(Method):
    """See the module docstring."""

    supports = frozenset({"agnostic", "sensitive"})

    @classmethod
    def fit(cls, scene: Scene, supervision: Supervision, config: NearestFrameConfig, *, seed: int,
            device: str, progress: Progress, work_dir: Optional[Path] = None) -> NearestFrameModel:
        replay = _caption_replay(scene, supervision, config, device=device, progress=progress, work_dir=work_dir)
        return NearestFrameModel(config, supervision.text_encoder, **replay, **_views(scene, supervision))

    @classmethod
    def load(cls, directory: Path, *, supervision: Supervision, device: str) -> NearestFrameModel:
        config, views, arrays, meta = _load_views(Path(directory), NearestFrameConfig)
        replay: dict[str, Any] = {}
        if "caption_embeddings" in arrays:
            from .captioners.supervision import caption_text_encoder

            replay = {"caption_encoder": caption_text_encoder(config.captions, supervision.text_encoder, device),
                      "caption_embeddings": arrays["caption_embeddings"],
                      "caption_rows": [arrays[f"caption_rows/{i}"] for i in range(len(views["names"]))],
                      "caption_info": meta.get("caption_info", {})}
        return NearestFrameModel(config, supervision.text_encoder, **replay, **views)


class NearestFrameMasks(Method):
    """See the module docstring."""

    supports = frozenset({"agnostic", "sensitive"})

    @classmethod
    def fit(cls, scene: Scene, supervision: Supervision, config: NearestFrameMasksConfig, *, seed: int,
            device: str, progress: Progress, work_dir: Optional[Path] = None) -> NearestFrameMasksModel:
        return NearestFrameMasksModel(config, supervision.text_encoder, **_views(scene, supervision))

    @classmethod
    def load(cls, directory: Path, *, supervision: Supervision, device: str) -> NearestFrameMasksModel:
        config, views, _, _ = _load_views(Path(directory), NearestFrameMasksConfig)
        return NearestFrameMasksModel(config, supervision.text_encoder, **views)
