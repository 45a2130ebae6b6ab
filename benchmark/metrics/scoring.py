"""Scoring predictions against ground truth: per-query array functions, then whole scenes.

Layers (per-scene scoring is separate from combining, as in TrackEval):

* :func:`score_agnostic` / :func:`score_sensitive`: one query's arrays -> its metric values.
* :func:`score_scene`: one :class:`~benchmark.core.annotation.AnnotationSet` + one
  :class:`~benchmark.predictions.ScenePredictions` -> :class:`SceneScore` (records + query rows),
  with every mismatch between the two reported as an :class:`~benchmark.core.errors.InputError`.
* :func:`aggregate_scenes`: scene scores -> :class:`DatasetScore` (means as in
  :mod:`benchmark.metrics.aggregate`).

Which frames are scored: for a query, every frame where it (a time-sensitive query: its base) has
a GT mask, optionally restricted to :attr:`ScoreConfig.eval_frames`, in time order
``(time_index, camera_id)``. A query with no such frame is not scored (listed in
:attr:`SceneScore.skipped`). mIoU / mAcc average time-agnostic queries only; Acc / vIoU (and the
diagnostics AUC / nearTau, which need per-frame scores) average time-sensitive queries only.

Unanswered queries: a method may decline a query kind it cannot answer (a time-sensitive query on a
scene it has no state captions for, say). The predictions then list those query texts in
``info["unanswered_queries"]`` (``bench4d eval`` writes it) and hold no answer for them. **A declared
unanswered query is not scored, and is listed** (:attr:`SceneScore.unanswered`, ``"unanswered"`` in
the results document): it enters no mean, so a method that answers only time-agnostic queries has no
Acc / vIoU (NaN: absent from a time-sensitive table, whose readers are told it answered none) rather
than a made-up failure score. Scoring it as a failure instead (an empty mask on every frame, every
time-sensitive frame decided negative) would give such a method the share of negative frames as its Acc
and rank it in a table of a task it never attempted. ``bench4d eval`` and ``bench4d score`` of the
folder it wrote apply this one rule, so they give the same numbers. A GT query that has no prediction
and is *not* declared unanswered stays an :class:`~benchmark.core.errors.InputError` (usually a misspelt
query text or an incomplete conversion); so does a query declared unanswered that has an answer.

Units: array functions, records and query rows hold fractions in [0, 1]; summaries and the results
document are in percent.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, fields
from typing import Iterable, Optional, Sequence

import numpy as np
import pandas as pd

from benchmark.core.annotation import AnnotatedFrame, AnnotationSet, Query

from benchmark.core.errors import InputError
from ..predictions import QueryPrediction, ScenePredictions, field_name, query_slug
from .aggregate import FrameRecord, aggregate, records_table
from .masks import accuracy_from_confusion, confusion, iou, iou_from_confusion, pixel_accuracy
from .temporal import (TemporalDecision, TemporalRule, apply_temporal_rule, near_threshold_fraction, score_auc,
                       temporal_accuracy, video_iou)

REPORT_METRICS = {"mIoU": "miou", "mAcc": "macc", "Acc": "acc", "vIoU": "viou", "AUC": "auc",
                  "nearTau": "near_threshold"}
"""Reported name (percent) -> query-row column (fraction). ``AUC`` and ``nearTau`` are diagnostics of
the time-sensitive decisions (:mod:`benchmark.metrics.temporal`), not paper metrics."""


@dataclass(frozen=True)
class ScoreConfig:
    """How predictions are scored."""

    temporal: TemporalRule = field(default_factory=TemporalRule)
    """The temporal decision rule for time-sensitive queries."""
    eval_frames: Optional[tuple[str, ...]] = None
    """Frame names to score; ``None`` = every annotated frame (the split is chosen by whoever
    builds the GT / calls this, e.g. held-out frames in ``bench4d eval``)."""
    allow_extra: bool = False
    """Whether predictions may hold queries that are not in the GT (ignored then); by default an
    unknown query is an error, since it usually means a misspelt query text."""

    def to_dict(self) -> dict:
        return {"temporal": self.temporal.to_dict(),
                "eval_frames": None if self.eval_frames is None else list(self.eval_frames),
                "allow_extra": self.allow_extra}


# -- one query, arrays -----------------------------------------------------------------------------
@dataclass(frozen=True)
class AgnosticScore:
    iou: np.ndarray
    """(T,) IoU per frame."""
    acc: np.ndarray
    """(T,) pixel accuracy per frame."""

    @property
    def miou(self) -> float:
        return float(self.iou.mean()) if self.iou.size else float("nan")

    @property
    def macc(self) -> float:
        return float(self.acc.mean()) if self.acc.size else float("nan")


def score_agnostic(pred_masks: Sequence[np.ndarray] | np.ndarray,
                   gt_masks: Sequence[np.ndarray] | np.ndarray) -> AgnosticScore:
    """Per-frame IoU and pixel accuracy of ``pred_masks`` vs ``gt_masks``: (T, H, W) arrays or
    length-T sequences of (H, W) masks (sequences are processed frame by frame to bound memory)."""
    if isinstance(pred_masks, np.ndarray) and isinstance(gt_masks, np.ndarray):
        if pred_masks.ndim != 3:
            raise ValueError(f"expected (T, H, W) masks, got shape {pred_masks.shape}")
        return AgnosticScore(np.atleast_1d(iou(pred_masks, gt_masks)),
                             np.atleast_1d(pixel_accuracy(pred_masks, gt_masks)))
    pairs = list(zip(pred_masks, gt_masks, strict=True))
    return AgnosticScore(np.array([float(iou(p, g)) for p, g in pairs], dtype=np.float64),
                         np.array([float(pixel_accuracy(p, g)) for p, g in pairs], dtype=np.float64))


@dataclass(frozen=True)
class SensitiveScore:
    decisions: np.ndarray
    """(T,) bool ``pred_t``."""
    labels: np.ndarray
    """(T,) bool ``label_t``."""
    accuracy: float
    """Temporal Acc (fraction)."""
    viou: float
    """vIoU (fraction)."""
    rule: Optional[TemporalDecision]
    """The rule's intermediate values, or ``None`` when the method gave decisions."""
    auc: float = float("nan")
    """ROC AUC (fraction) of the smoothed scores against the labels; NaN without scores or
    without both a positive and a negative frame."""
    near_threshold: float = float("nan")
    """Fraction of the frames decided within :data:`~benchmark.metrics.temporal.NEAR_THRESHOLD_FRACTION`
    of the score range of ``tau``; NaN without scores."""

    @property
    def decision_source(self) -> str:
        return "decisions" if self.rule is None else "rule"


def score_sensitive(labels: np.ndarray, frame_iou: np.ndarray, *, scores: Optional[np.ndarray] = None,
                    decisions: Optional[np.ndarray] = None,
                    config: TemporalRule = TemporalRule()) -> SensitiveScore:
    """Temporal Acc and vIoU of one time-sensitive query over its T evaluated frames in time order.

    ``labels`` (T,) bool; ``frame_iou`` (T,) IoU of the query's predicted mask vs the base
    object's GT mask; either ``scores`` (T,) (NaN = undefined; the temporal rule decides) or
    ``decisions`` (T,) bool (used as given). ``scores`` wins when both are given.
    """
    y = np.asarray(labels, dtype=bool)
    if scores is not None:
        rule = apply_temporal_rule(np.asarray(scores, dtype=np.float64), config)
        d = rule.decisions
    elif decisions is not None:
        rule, d = None, np.asarray(decisions, dtype=bool)
    else:
        raise ValueError("score_sensitive needs scores or decisions")
    diagnostics = {} if rule is None else {
        "auc": score_auc(rule.smoothed, y), "near_threshold": near_threshold_fraction(rule.smoothed, rule.threshold)}
    return SensitiveScore(decisions=d, labels=y, accuracy=temporal_accuracy(d, y),
                          viou=video_iou(d, y, frame_iou), rule=rule, **diagnostics)


# -- one scene ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class QueryScore:
    """One query's row (fractions; NaN where a metric does not apply to its kind)."""

    scene: str
    query: str
    kind: str
    frames: int
    """Evaluated frames."""
    miou: float = float("nan")
    """Agnostic: mean IoU over frames."""
    macc: float = float("nan")
    """Agnostic: mean pixel accuracy over frames."""
    acc: float = float("nan")
    """Sensitive: temporal accuracy."""
    viou: float = float("nan")
    """Sensitive: vIoU."""
    threshold: float = float("nan")
    """Sensitive: ``tau`` of the temporal rule (NaN if decisions were given)."""
    positives: int = 0
    """Sensitive: frames labelled positive."""
    predicted: int = 0
    """Sensitive: frames predicted positive."""
    decision_source: str = ""
    """Sensitive: ``"rule"`` (from scores) or ``"decisions"`` (given by the method)."""
    auc: float = float("nan")
    """Sensitive diagnostic: ROC AUC of the smoothed scores against the labels (threshold-free)."""
    near_threshold: float = float("nan")
    """Sensitive diagnostic: fraction of decisions near ``tau`` (see :mod:`benchmark.metrics.temporal`)."""


QUERY_COLUMNS = [f.name for f in fields(QueryScore)]


def _summary(query_rows: pd.DataFrame, level: str) -> pd.DataFrame:
    cols = list(REPORT_METRICS.values())
    table = aggregate(query_rows, cols, start="query", to=level)
    for name, col in REPORT_METRICS.items():
        table[name] = 100.0 * table.pop(col)
    return table


def _counts(query_rows: pd.DataFrame) -> dict:
    return {"agnostic_queries": int((query_rows["kind"] == "agnostic").sum()),
            "sensitive_queries": int((query_rows["kind"] == "sensitive").sum()),
            "frames_scored": int(query_rows["frames"].sum())}


def _nan_to_none(value):
    if isinstance(value, (float, np.floating)) and math.isnan(value):
        return None
    if isinstance(value, np.generic):
        return value.item()
    return value


def _table_json(table: pd.DataFrame) -> list[dict]:
    return [{k: _nan_to_none(v) for k, v in row.items()} for row in table.to_dict(orient="records")]


@dataclass
class SceneScore:
    """All scores of one method on one scene."""

    scene: str
    method: Optional[str]
    config: ScoreConfig
    records: list[FrameRecord]
    """One per evaluated (query, frame)."""
    queries: list[QueryScore]
    """One per scored query."""
    skipped: list[str] = field(default_factory=list)
    """Queries not scored: no evaluated frame."""
    unanswered: list[str] = field(default_factory=list)
    """Queries not scored: the method declared them unanswered (module docstring), with evaluated frames."""
    unanswered_kinds: dict[str, str] = field(default_factory=dict)
    """Kind of each of :attr:`unanswered` (from the ground truth)."""

    def records_table(self) -> pd.DataFrame:
        return records_table(self.records)

    def query_table(self) -> pd.DataFrame:
        return pd.DataFrame([q.__dict__ for q in self.queries], columns=QUERY_COLUMNS)

    def summary(self) -> dict:
        """``{"mIoU", "mAcc", "Acc", "vIoU"}`` in percent (NaN if no query of that kind) + counts."""
        rows = self.query_table()
        out = {name: float("nan") for name in REPORT_METRICS}
        if len(rows):
            out.update({k: float(v) for k, v in _summary(rows, "scene").iloc[0][list(REPORT_METRICS)].items()})
        out.update(_counts(rows))
        return out


@dataclass
class DatasetScore:
    """Scene scores combined: dataset value = mean over scenes of per-scene means."""

    scenes: list[SceneScore]

    def query_table(self) -> pd.DataFrame:
        tables = [s.query_table() for s in self.scenes]
        return pd.concat(tables, ignore_index=True) if tables else pd.DataFrame(columns=QUERY_COLUMNS)

    def scene_table(self) -> pd.DataFrame:
        """One row per scene: scene, metrics in percent, count (queries)."""
        rows = self.query_table()
        if not len(rows):
            return pd.DataFrame(columns=["scene", *REPORT_METRICS, "count"])
        return _summary(rows, "scene")

    def summary(self) -> dict:
        rows = self.query_table()
        out = {name: float("nan") for name in REPORT_METRICS}
        if len(rows):
            out.update({k: float(v) for k, v in _summary(rows, "dataset").iloc[0][list(REPORT_METRICS)].items()})
        out.update(_counts(rows))
        out["scenes"] = len(self.scenes)
        return out

    def to_json(self, provenance: Optional[dict] = None, include_frames: bool = True) -> dict:
        """The results document (percent in ``metrics`` and ``queries``; fractions in ``frames``)."""
        queries = self.query_table()
        for name, col in REPORT_METRICS.items():
            queries[name] = 100.0 * queries.pop(col)
        configs = {json_key(s.config.to_dict()) for s in self.scenes}
        doc = {
            "format": "bench4d-results", "version": 1,
            "units": "metrics and queries in percent; frames in fractions [0, 1]",
            "provenance": provenance or {},
            "config": (self.scenes[0].config.to_dict() if len(configs) == 1
                       else [s.config.to_dict() for s in self.scenes] or None),
            "metrics": {"dataset": {k: _nan_to_none(v) for k, v in self.summary().items()},
                        "scenes": {r["scene"]: {k: _nan_to_none(v) for k, v in r.items() if k != "scene"}
                                   for r in self.scene_table().to_dict(orient="records")}},
            "methods": sorted({s.method for s in self.scenes if s.method}),
            "queries": _table_json(queries),
            "skipped": [{"scene": s.scene, "query": q} for s in self.scenes for q in s.skipped],
            "unanswered": [{"scene": s.scene, "query": q, "kind": s.unanswered_kinds.get(q)}
                           for s in self.scenes for q in s.unanswered],
        }
        if include_frames:
            doc["frames"] = [r for s in self.scenes for r in _table_json(s.records_table())]
        return doc


def json_key(obj: dict) -> str:
    """Canonical JSON text of ``obj`` (to compare configs)."""
    return json.dumps(obj, sort_keys=True)


def aggregate_scenes(scenes: Iterable[SceneScore]) -> DatasetScore:
    """Combine scene scores (one method); scene names must be distinct."""
    scenes = list(scenes)
    names = [s.scene for s in scenes]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise InputError(None, "scene", f"scored more than once: {dupes}")
    return DatasetScore(scenes)


def _frame_order(f: AnnotatedFrame) -> tuple:
    return (f.time_index, f.camera_id, f.name)


def _evaluated_frames(aset: AnnotationSet, query: Query, wanted: Optional[set[str]]) -> list[AnnotatedFrame]:
    owner = aset.mask_owner(query)
    ids = {fid for (qid, fid) in aset.masks if qid == owner.id}
    frames = [f for f in aset.frames if f.id in ids and (wanted is None or f.name in wanted)]
    return sorted(frames, key=_frame_order)


def _check_pred_keys(pred: QueryPrediction, known: set[str], scene: str, src) -> None:
    for part, mapping in (("masks", pred.masks), ("scores", pred.scores), ("decisions", pred.decisions)):
        for frame in mapping:
            if frame not in known:
                raise InputError(pred.source or src, field_name(pred.text, part, frame),
                                 f"frame is not in the ground truth of scene {scene!r}")


UNANSWERED_FIELD = "unanswered_queries"
"""Key of a prediction folder's ``info`` that lists the query texts the method declined (module docstring)."""


def declared_unanswered(predictions: ScenePredictions) -> list[str]:
    """The query texts ``predictions`` declare unanswered (``info["unanswered_queries"]``; none if absent)."""
    listed = (predictions.info or {}).get(UNANSWERED_FIELD)
    if listed is None:
        return []
    if not isinstance(listed, list) or not all(isinstance(t, str) for t in listed):
        raise InputError(predictions.source, f"info.{UNANSWERED_FIELD}", "expected a list of query texts")
    return list(dict.fromkeys(listed))


def score_scene(aset: AnnotationSet, predictions: ScenePredictions,
                config: ScoreConfig = ScoreConfig()) -> SceneScore:
    """Score one method's predictions on one scene (see the module docstring for the rules).

    Raises :class:`InputError` (naming the prediction file and field) for: a GT query without a
    prediction that the predictions do not declare unanswered, a query declared unanswered that has a
    prediction (or, unless ``allow_extra``, is unknown to the GT), a kind that contradicts the GT, a
    missing mask / score on an evaluated frame, a mask of the wrong size, a frame or (unless
    ``allow_extra``) a query unknown to the GT, and predictions made for another scene.
    """
    src = predictions.source
    wanted = _check_scene(aset, predictions, config)
    slug_counts: dict[str, int] = {}
    for t in {q.text for q in aset.queries}:
        slug_counts[query_slug(t)] = slug_counts.get(query_slug(t), 0) + 1
    declined = _check_prediction_queries(aset, predictions, config, slug_counts)
    known = {f.name for f in aset.frames}
    gt_cache: dict[tuple[int, int], np.ndarray] = {}
    records: list[FrameRecord] = []
    rows: list[QueryScore] = []
    skipped: list[str] = []
    unanswered: list[str] = []
    for query in sorted(aset.queries, key=lambda q: (q.kind, q.text)):
        try:
            owner = aset.mask_owner(query)
        except KeyError:
            raise InputError(None, f"queries[{query.text!r}].base", f"base query {query.base!r} does not exist") from None
        frames = _evaluated_frames(aset, query, wanted)
        # matching by slug (PNG folder names) only where the slug names one GT query
        pred = predictions.find(query.text, by_slug=slug_counts[query_slug(query.text)] == 1)
        if pred is None:
            if not frames:
                skipped.append(query.text)
            elif query.text in declined:
                unanswered.append(query.text)
            else:
                raise InputError(src, field_name(query.text), "missing: the ground truth has this query (a method "
                                 f"that declines it lists it in info.{UNANSWERED_FIELD})")
            continue
        _check_pred_keys(pred, known, aset.scene, src)
        if pred.kind is not None and pred.kind != query.kind:
            raise InputError(pred.source or src, field_name(pred.text, "kind"),
                             f"is {pred.kind!r} but the ground truth says {query.kind!r}")
        if not frames:
            skipped.append(query.text)
            continue
        overlap = _overlaps(aset, owner, pred, frames, gt_cache, src)
        if query.kind == "agnostic":
            row, query_records = _score_agnostic_query(aset.scene, query, frames, overlap)
        else:
            row, query_records = _score_sensitive_query(aset.scene, query, pred, frames, overlap, config.temporal, src)
        rows.append(row)
        records.extend(query_records)
    kinds = {q.text: q.kind for q in aset.queries}
    return SceneScore(scene=aset.scene, method=predictions.method, config=config, records=records,
                      queries=rows, skipped=skipped, unanswered=unanswered,
                      unanswered_kinds={t: kinds[t] for t in unanswered})


def _check_scene(aset: AnnotationSet, predictions: ScenePredictions, config: ScoreConfig) -> Optional[set[str]]:
    """The frame names to score (None: every annotated frame), after checking that the predictions are
    for this scene, that its frame names are unique and that ``config.eval_frames`` names its frames."""
    if predictions.scene and predictions.scene != aset.scene:
        raise InputError(predictions.source, "scene",
                         f"predictions are for scene {predictions.scene!r}, ground truth is {aset.scene!r}")
    names = [f.name for f in aset.frames]
    known = set(names)
    if len(known) != len(names):
        dupes = sorted({n for n in names if names.count(n) > 1})
        raise InputError(None, "images", f"scene {aset.scene!r}: frame names are not unique: {dupes[:5]}")
    if config.eval_frames is None:
        return None
    wanted = set(config.eval_frames)
    unknown = sorted(wanted - known)
    if unknown:
        raise InputError(None, "eval_frames", f"not frames of scene {aset.scene!r}: {unknown[:5]}")
    return wanted


def _check_prediction_queries(aset: AnnotationSet, predictions: ScenePredictions, config: ScoreConfig,
                              slug_counts: dict[str, int]) -> set[str]:
    """The query texts the predictions declare unanswered, after checking that every predicted query is a
    GT query (unless ``allow_extra``) and that every declared one is unanswered and (unless
    ``allow_extra``) a GT query."""
    src = predictions.source
    gt_texts = {q.text for q in aset.queries}
    if not config.allow_extra:
        for text, pred in predictions.queries.items():
            if text not in gt_texts and slug_counts.get(query_slug(text), 0) != 1:
                raise InputError(pred.source or src, field_name(text),
                                 f"not a query of scene {aset.scene!r} (GT queries: {sorted(gt_texts)})")
    declined = declared_unanswered(predictions)
    for text in declined:
        if predictions.find(text, by_slug=False) is not None:
            raise InputError(src, f"info.{UNANSWERED_FIELD}", f"lists {text!r}, which the predictions answer")
        if text not in gt_texts and not config.allow_extra:
            raise InputError(src, f"info.{UNANSWERED_FIELD}",
                             f"lists {text!r}, not a query of scene {aset.scene!r} (GT queries: {sorted(gt_texts)})")
    return set(declined)


@dataclass(frozen=True)
class _Overlap:
    """A query's predicted masks against the GT masks on its T evaluated frames, in time order."""

    iou: np.ndarray
    """(T,) IoU per frame."""
    acc: np.ndarray
    """(T,) pixel accuracy per frame."""
    pred_pixels: np.ndarray
    """(T,) positive pixels of the prediction."""
    gt_pixels: np.ndarray
    """(T,) positive pixels of the GT."""

    def records(self, base: dict, frames: Sequence[AnnotatedFrame], **per_frame) -> list[FrameRecord]:
        """One :class:`FrameRecord` per frame; ``per_frame``: further fields, one value per frame each."""
        return [FrameRecord(**base, frame=f.name, time_index=f.time_index, camera_id=f.camera_id,
                            iou=float(self.iou[i]), acc=float(self.acc[i]), pred_pixels=int(self.pred_pixels[i]),
                            gt_pixels=int(self.gt_pixels[i]), **{k: v[i] for k, v in per_frame.items()})
                for i, f in enumerate(frames)]


def _overlaps(aset: AnnotationSet, owner: Query, pred: QueryPrediction, frames: Sequence[AnnotatedFrame],
              gt_cache: dict[tuple[int, int], np.ndarray], src) -> _Overlap:
    """IoU, pixel accuracy and pixel counts of ``pred``'s masks against ``owner``'s GT masks on ``frames``
    (GT masks kept in ``gt_cache``: a time-sensitive query shares its base's)."""
    ious = np.empty(len(frames))
    accs = np.empty(len(frames))
    pred_px = np.empty(len(frames), dtype=np.int64)
    gt_px = np.empty(len(frames), dtype=np.int64)
    for i, frame in enumerate(frames):
        key = (owner.id, frame.id)
        if key not in gt_cache:
            mask = aset.get_mask(owner.id, frame.id)
            if mask.shape != (frame.height, frame.width):
                raise InputError(None, f"annotations[{owner.text!r}][{frame.name!r}]",
                                 f"GT mask is {mask.shape[0]}x{mask.shape[1]}, frame is {frame.height}x{frame.width}")
            gt_cache[key] = mask
        g = gt_cache[key]
        p = pred.mask(frame.name, g.shape)  # the declared size is checked before decoding
        if p.shape != g.shape:
            raise InputError(pred.source or src, field_name(pred.text, "masks", frame.name),
                             f"mask is {p.shape[0]}x{p.shape[1]}, the frame is {g.shape[0]}x{g.shape[1]} (H x W)")
        c = confusion(p, g)  # one pass for both metrics
        ious[i] = iou_from_confusion(c)
        accs[i] = accuracy_from_confusion(c)
        pred_px[i] = int(c["tp"] + c["fp"])
        gt_px[i] = int(c["tp"] + c["fn"])
    return _Overlap(ious, accs, pred_px, gt_px)


def _score_agnostic_query(scene: str, query: Query, frames: Sequence[AnnotatedFrame],
                          overlap: _Overlap) -> tuple[QueryScore, list[FrameRecord]]:
    """A time-agnostic query's row (mean IoU and pixel accuracy over its frames) and frame records."""
    base = dict(scene=scene, query=query.text, kind=query.kind)
    row = QueryScore(**base, frames=len(frames), miou=float(overlap.iou.mean()), macc=float(overlap.acc.mean()))
    return row, overlap.records(base, frames)


def _score_sensitive_query(scene: str, query: Query, pred: QueryPrediction, frames: Sequence[AnnotatedFrame],
                           overlap: _Overlap, rule_config: TemporalRule, src) -> tuple[QueryScore, list[FrameRecord]]:
    """A time-sensitive query's row (temporal Acc and vIoU of its decisions: the temporal rule's on its
    scores, or the method's own) and frame records."""
    labels = np.array([query.holds_at(f.time_index) for f in frames])
    scores = decisions = None
    if pred.scores:
        missing = [f.name for f in frames if f.name not in pred.scores]
        if missing:
            raise InputError(pred.source or src, field_name(pred.text, "scores", missing[0]),
                             f"missing score for an evaluated frame ({len(missing)} missing)")
        scores = np.array([pred.scores[f.name] for f in frames], dtype=np.float64)
    elif pred.decisions:
        missing = [f.name for f in frames if f.name not in pred.decisions]
        if missing:
            raise InputError(pred.source or src, field_name(pred.text, "decisions", missing[0]),
                             f"missing decision for an evaluated frame ({len(missing)} missing)")
        decisions = np.array([pred.decisions[f.name] for f in frames], dtype=bool)
    else:
        raise InputError(pred.source or src, field_name(pred.text, "scores"),
                         "a time-sensitive query needs 'scores' (or 'decisions') for every evaluated frame")
    result = score_sensitive(labels, overlap.iou, scores=scores, decisions=decisions, config=rule_config)
    rule = result.rule
    base = dict(scene=scene, query=query.text, kind=query.kind)
    row = QueryScore(**base, frames=len(frames), acc=result.accuracy, viou=result.viou,
                     threshold=float("nan") if rule is None else rule.threshold,
                     positives=int(labels.sum()), predicted=int(result.decisions.sum()),
                     decision_source=result.decision_source, auc=result.auc, near_threshold=result.near_threshold)
    undefined = [float("nan")] * len(frames)
    records = overlap.records(base, frames,
                              score=undefined if rule is None else [float(v) for v in rule.scores],
                              smoothed=undefined if rule is None else [float(v) for v in rule.smoothed],
                              decision=[bool(d) for d in result.decisions], label=[bool(y) for y in labels])
    return row, records
