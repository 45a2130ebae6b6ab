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
``(time_index, camera_id)``, except, under :attr:`ScoreConfig.absent_frames` ``"skip"`` (the release's
rule, the default), the frames where that GT mask is empty (the object is annotated absent there). A
query with no such frame is not scored (listed in :attr:`SceneScore.skipped`). mIoU / mAcc average
time-agnostic queries only; Acc / vIoU (and the diagnostics AUC / nearTau, which need per-frame scores)
average time-sensitive queries only.

Absent frames: the release queries a label only on the frames where it is annotated, so a frame where
the object is absent is never scored for it (``shared/docs/protocol.md``). Scoring such frames against
the empty mask (``"score-empty"``) is a stricter rule of the benchmark's own. Either way false positives
there are reported as their own figure, ``absentFP``: the share (percent) of the absent (time-agnostic
query, evaluated frame) pairs of a scene on which the predicted mask is non-empty; the dataset value is
the mean over the scenes that have absent frames. A prediction therefore needs a mask on those frames
too.

Unanswered queries and coverage: a method may decline a query kind it cannot answer (a time-sensitive
query on a scene it has no state captions for, say). The predictions then list those query texts in
``info["unanswered_queries"]`` (``bench4d eval`` writes it) and hold no answer for them. A declared
unanswered query is *asked* (it has a scored frame) but not answered: it has no query row and no frame
records, it is listed (:attr:`SceneScore.unanswered`, ``"unanswered"`` in the results document), and it
**scores 0 in the full mean**: ``mIoU``, ``mAcc``, ``Acc`` and ``vIoU`` average every asked query of
their kind, an unanswered one counting 0, so declining a query never raises a mean. A kind declined on
every scene (a method built for time-agnostic queries only) has no full mean (null): the method is not in
that kind's table; declined on some scenes only, those scenes count 0 in the dataset mean. The means over the
answered queries alone are reported beside them (``mIoU_answered`` ...), with the counts
``answered_<kind>_queries`` / ``asked_<kind>_queries``. (An unanswered query is not scored as if it had
answered with empty masks and negative decisions: that would give a method that attempted no
time-sensitive query the share of negative frames as its Acc.) The diagnostics AUC / nearTau describe
answered queries only. ``bench4d eval`` and ``bench4d score`` of the folder it wrote apply these rules,
so they give the same numbers. A GT query that has no prediction and is *not* declared unanswered stays
an :class:`~benchmark.core.errors.InputError` (usually a misspelt query text or an incomplete
conversion); so does a query declared unanswered that has an answer.

The time-sensitive threshold ``tau`` depends on how the method made its scores
(:data:`~benchmark.core.protocol.TIME_SCORES`): :attr:`ScoreConfig.time_score`, else the predictions'
``info["time_score"]``, else ``"feature"``.

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
from benchmark.core.protocol import TIME_SCORES, AbsentFrames, Protocol
from ..predictions import QueryPrediction, ScenePredictions, field_name, query_slug
from .aggregate import FrameRecord, records_table
from .masks import accuracy_from_confusion, confusion, iou, iou_from_confusion, pixel_accuracy
from .temporal import (TemporalDecision, TemporalRule, apply_temporal_rule, near_threshold_fraction, score_auc,
                       temporal_accuracy, video_iou)

RANKED_METRICS = {"mIoU": "miou", "mAcc": "macc", "Acc": "acc", "vIoU": "viou"}
"""The paper's metrics: reported name (percent, the full mean: every asked query, an unanswered one
counting 0) -> query-row column (fraction)."""
ANSWERED_SUFFIX = "_answered"
"""``<metric>_answered`` (e.g. ``mIoU_answered``): the same mean over the answered queries only."""
DIAGNOSTIC_METRICS = {"AUC": "auc", "nearTau": "near_threshold"}
"""Diagnostics of the time-sensitive decisions (:mod:`benchmark.metrics.temporal`), not paper metrics;
over answered queries."""
REPORT_METRICS = {**RANKED_METRICS, **DIAGNOSTIC_METRICS}
"""Reported name (percent) -> query-row column (fraction)."""
ANSWERED_METRICS = {f"{name}{ANSWERED_SUFFIX}": col for name, col in RANKED_METRICS.items()}
"""``<metric>_answered`` -> query-row column."""
ABSENT_FP = "absentFP"
"""Reported name of the share (percent) of absent frames with a non-empty predicted mask (module docstring)."""
KIND_METRICS = {"agnostic": ("miou", "macc"), "sensitive": ("acc", "viou")}
"""Query kind -> the query-row columns of its paper metrics (what an unanswered query scores 0 in)."""
QUERY_KINDS = ("agnostic", "sensitive")


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
    absent_frames: AbsentFrames = "skip"
    """Frames where the query's GT mask is empty: ``"skip"`` (release) not scored for it; ``"score-empty"``
    scored against the empty mask (:class:`~benchmark.core.protocol.ScoringRule`)."""
    time_score: Optional[str] = None
    """How the method made its time-sensitive scores (:data:`~benchmark.core.protocol.TIME_SCORES`), which
    picks ``tau``'s source; ``None``: as the predictions declare (``info["time_score"]``; absent: ``"feature"``)."""

    def __post_init__(self) -> None:
        if self.absent_frames not in ("skip", "score-empty"):
            raise ValueError(f"absent_frames must be 'skip' or 'score-empty', got {self.absent_frames!r}")
        if self.time_score is not None and self.time_score not in TIME_SCORES:
            raise ValueError(f"time_score must be one of {TIME_SCORES} or None, got {self.time_score!r}")

    @classmethod
    def from_protocol(cls, protocol: Protocol, **options) -> "ScoreConfig":
        """The scoring rules of ``protocol`` (its temporal rule and absent-frame rule), with ``options``
        (``eval_frames``, ``allow_extra``, ``time_score``)."""
        return cls(temporal=protocol.temporal, absent_frames=protocol.scoring.absent_frames, **options)

    def to_dict(self) -> dict:
        return {"temporal": self.temporal.to_dict(),
                "eval_frames": None if self.eval_frames is None else list(self.eval_frames),
                "allow_extra": self.allow_extra, "absent_frames": self.absent_frames, "time_score": self.time_score}


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
                    config: TemporalRule = TemporalRule(), time_score: str = "feature") -> SensitiveScore:
    """Temporal Acc and vIoU of one time-sensitive query over its T evaluated frames in time order.

    ``labels`` (T,) bool; ``frame_iou`` (T,) IoU of the query's predicted mask vs the base
    object's GT mask; either ``scores`` (T,) (NaN = undefined; the temporal rule decides, ``tau`` as
    ``config`` says for ``time_score``) or ``decisions`` (T,) bool (used as given). ``scores`` wins when
    both are given.
    """
    y = np.asarray(labels, dtype=bool)
    if scores is not None:
        rule = apply_temporal_rule(np.asarray(scores, dtype=np.float64), config, time_score)
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


def _defined_mean(values: pd.Series) -> float:
    """The mean of the defined values (NaN when none is)."""
    v = values.to_numpy(dtype=np.float64)
    v = v[~np.isnan(v)]
    return float(v.mean()) if v.size else float("nan")


def _percent_mean(values: pd.Series) -> float:
    """100 x the mean of the defined fractions (NaN when none is)."""
    return 100.0 * _defined_mean(values)


def _unanswered_rows(scene: str, kinds: dict[str, str]) -> pd.DataFrame:
    """One query row per unanswered query: 0 in its kind's paper metrics (:data:`KIND_METRICS`), NaN elsewhere."""
    rows = []
    for text, kind in kinds.items():
        row = QueryScore(scene=scene, query=text, kind=kind, frames=0).__dict__
        row.update({col: 0.0 for col in KIND_METRICS.get(kind, ())})
        rows.append(row)
    return pd.DataFrame(rows, columns=QUERY_COLUMNS)


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
    """Queries asked (with a scored frame) that the method declared unanswered (module docstring): 0 in the
    full means."""
    unanswered_kinds: dict[str, str] = field(default_factory=dict)
    """Kind of each of :attr:`unanswered` (from the ground truth)."""
    absent: dict[str, tuple[int, int]] = field(default_factory=dict)
    """Time-agnostic query text -> (its evaluated frames where the object is absent, of those the frames
    with a non-empty predicted mask); answered queries with at least one absent frame."""

    def records_table(self) -> pd.DataFrame:
        return records_table(self.records)

    def query_table(self) -> pd.DataFrame:
        return pd.DataFrame([q.__dict__ for q in self.queries], columns=QUERY_COLUMNS)

    def asked_table(self) -> pd.DataFrame:
        """:meth:`query_table` plus one row per unanswered query, 0 in its kind's paper metrics: what the
        full means average."""
        rows, missing = self.query_table(), _unanswered_rows(self.scene, self.unanswered_kinds)
        return pd.concat([rows, missing], ignore_index=True) if len(missing) else rows

    def summary(self) -> dict:
        """In percent (NaN where no query of that kind was asked or answered): the full means
        (:data:`RANKED_METRICS`), the answered-only means (:data:`ANSWERED_METRICS`), the diagnostics,
        ``absentFP``; and counts: queries answered and asked per kind, (query, frame) pairs scored,
        absent (query, frame) pairs looked at, queries answered (``count``)."""
        rows, asked = self.query_table(), self.asked_table()
        # A kind declined as a whole (no query of it answered) is not this method's kind: NaN, so a method
        # built for time-agnostic queries gets no time-sensitive row. The dataset mean then counts such a
        # scene 0 if the method answers that kind on another scene (DatasetScore.summary).
        out: dict = {name: (_percent_mean(asked.loc[asked["kind"] == kind, col])
                            if (rows["kind"] == kind).any() else float("nan"))
                     for kind, cols in KIND_METRICS.items() for name, col in RANKED_METRICS.items() if col in cols}
        out.update({name: _percent_mean(rows.loc[rows["kind"] == kind, col])
                    for kind, cols in KIND_METRICS.items() for name, col in ANSWERED_METRICS.items() if col in cols})
        out.update({name: _percent_mean(rows[col]) for name, col in DIAGNOSTIC_METRICS.items()})
        absent = sum(n for n, _ in self.absent.values())
        out[ABSENT_FP] = 100.0 * sum(p for _, p in self.absent.values()) / absent if absent else float("nan")
        for kind in QUERY_KINDS:
            answered = int((rows["kind"] == kind).sum())
            out[f"{kind}_queries"] = answered  # the name results files had before coverage was recorded
            out[f"answered_{kind}_queries"] = answered
            out[f"asked_{kind}_queries"] = answered + sum(1 for k in self.unanswered_kinds.values() if k == kind)
        out["frames_scored"] = int(rows["frames"].sum())
        out["absent_frames"] = absent
        out["count"] = len(rows)
        return out


SUMMED_COUNTS = ("agnostic_queries", "sensitive_queries", "answered_agnostic_queries", "asked_agnostic_queries",
                 "answered_sensitive_queries", "asked_sensitive_queries", "frames_scored", "absent_frames")
"""Counts of :meth:`SceneScore.summary` that a dataset sums over its scenes."""
MEAN_VALUES = (*RANKED_METRICS, *ANSWERED_METRICS, *DIAGNOSTIC_METRICS, ABSENT_FP)
"""Values of :meth:`SceneScore.summary` that a dataset averages over its scenes (NaN skipped)."""


@dataclass
class DatasetScore:
    """Scene scores combined: dataset value = mean over scenes of per-scene means."""

    scenes: list[SceneScore]

    def query_table(self) -> pd.DataFrame:
        tables = [s.query_table() for s in self.scenes]
        return pd.concat(tables, ignore_index=True) if tables else pd.DataFrame(columns=QUERY_COLUMNS)

    def scene_table(self) -> pd.DataFrame:
        """One row per scene (sorted by name): scene, every value of :meth:`SceneScore.summary`."""
        rows = [{"scene": s.scene, **s.summary()} for s in sorted(self.scenes, key=lambda s: s.scene)]
        columns = ["scene", *MEAN_VALUES, *SUMMED_COUNTS, "count"]
        return pd.DataFrame(rows, columns=columns)

    def summary(self) -> dict:
        """Each value the mean over scenes of the scenes' values (those defined), counts summed, ``scenes``."""
        table = self.scene_table()
        out: dict = {name: _defined_mean(table[name]) for name in MEAN_VALUES}
        for kind, cols in KIND_METRICS.items():
            # a scene whose asked queries of this kind were all declined counts 0 once the method answers the
            # kind elsewhere: declining a hard scene never raises the dataset mean
            declined = (table[f"answered_{kind}_queries"] == 0) & (table[f"asked_{kind}_queries"] > 0)
            for name, col in RANKED_METRICS.items():
                if col in cols and declined.any() and table[name].notna().any():
                    out[name] = _defined_mean(table[name].where(~declined, 0.0))
        out.update({name: int(table[name].sum()) for name in SUMMED_COUNTS})
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
            "absent": [{"scene": s.scene, "query": q, "frames": n, "predicted": p}
                       for s in self.scenes for q, (n, p) in s.absent.items()],
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


TIME_SCORE_FIELD = "time_score"
"""Key of a prediction folder's ``info`` that says how the method made its time-sensitive scores (one of
:data:`~benchmark.core.protocol.TIME_SCORES`; absent: ``"feature"``)."""


def declared_time_score(predictions: ScenePredictions) -> str:
    """How ``predictions`` say their time-sensitive scores were made (``info["time_score"]``; ``"feature"``
    if absent)."""
    declared = (predictions.info or {}).get(TIME_SCORE_FIELD, "feature")
    if declared not in TIME_SCORES:
        raise InputError(predictions.source, f"info.{TIME_SCORE_FIELD}",
                         f"expected one of {', '.join(TIME_SCORES)}, got {declared!r}")
    return declared


def score_scene(aset: AnnotationSet, predictions: ScenePredictions,
                config: ScoreConfig = ScoreConfig()) -> SceneScore:
    """Score one method's predictions on one scene (see the module docstring for the rules).

    Raises :class:`InputError` (naming the prediction file and field) for: a GT query without a
    prediction that the predictions do not declare unanswered, a query declared unanswered that has a
    prediction (or, unless ``allow_extra``, is unknown to the GT), a kind that contradicts the GT, a
    missing mask / score on an evaluated frame (a time-agnostic query's mask on a frame where its object
    is absent included: it gives ``absentFP``), a mask of the wrong size, a frame or (unless
    ``allow_extra``) a query unknown to the GT, an unknown ``info.time_score``, and predictions made for
    another scene.
    """
    src = predictions.source
    wanted = _check_scene(aset, predictions, config)
    slug_counts: dict[str, int] = {}
    for t in {q.text for q in aset.queries}:
        slug_counts[query_slug(t)] = slug_counts.get(query_slug(t), 0) + 1
    declined = _check_prediction_queries(aset, predictions, config, slug_counts)
    time_score = config.time_score or declared_time_score(predictions)
    known = {f.name for f in aset.frames}
    gt_cache: dict[tuple[int, int], np.ndarray] = {}
    records: list[FrameRecord] = []
    rows: list[QueryScore] = []
    skipped: list[str] = []
    unanswered: list[str] = []
    absent_counts: dict[str, tuple[int, int]] = {}
    for query in sorted(aset.queries, key=lambda q: (q.kind, q.text)):
        try:
            owner = aset.mask_owner(query)
        except KeyError:
            raise InputError(None, f"queries[{query.text!r}].base", f"base query {query.base!r} does not exist") from None
        frames = _evaluated_frames(aset, query, wanted)
        absent = [f for f in frames if not _gt_mask(aset, owner, f, gt_cache).any()]
        if config.absent_frames == "skip":
            absent_ids = {f.id for f in absent}
            frames = [f for f in frames if f.id not in absent_ids]
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
        if query.kind == "agnostic" and absent:
            predicted = sum(bool(_pred_mask(pred, f, gt_cache[(owner.id, f.id)].shape, src).any()) for f in absent)
            absent_counts[query.text] = (len(absent), int(predicted))
        if not frames:
            skipped.append(query.text)
            continue
        overlap = _overlaps(aset, owner, pred, frames, gt_cache, src)
        if query.kind == "agnostic":
            row, query_records = _score_agnostic_query(aset.scene, query, frames, overlap)
        else:
            row, query_records = _score_sensitive_query(aset.scene, query, pred, frames, overlap, config.temporal,
                                                        time_score, src)
        rows.append(row)
        records.extend(query_records)
    kinds = {q.text: q.kind for q in aset.queries}
    return SceneScore(scene=aset.scene, method=predictions.method, config=config, records=records,
                      queries=rows, skipped=skipped, unanswered=unanswered,
                      unanswered_kinds={t: kinds[t] for t in unanswered}, absent=absent_counts)


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


def _gt_mask(aset: AnnotationSet, owner: Query, frame: AnnotatedFrame,
             gt_cache: dict[tuple[int, int], np.ndarray]) -> np.ndarray:
    """``owner``'s GT mask on ``frame``, checked against the frame's size, kept in ``gt_cache`` (a
    time-sensitive query shares its base's)."""
    key = (owner.id, frame.id)
    if key not in gt_cache:
        mask = aset.get_mask(owner.id, frame.id)
        if mask.shape != (frame.height, frame.width):
            raise InputError(None, f"annotations[{owner.text!r}][{frame.name!r}]",
                             f"GT mask is {mask.shape[0]}x{mask.shape[1]}, frame is {frame.height}x{frame.width}")
        gt_cache[key] = mask
    return gt_cache[key]


def _pred_mask(pred: QueryPrediction, frame: AnnotatedFrame, shape: tuple[int, ...], src) -> np.ndarray:
    """``pred``'s mask on ``frame``, which must be ``shape`` (the declared size is checked before decoding)."""
    p = pred.mask(frame.name, shape)
    if p.shape != shape:
        raise InputError(pred.source or src, field_name(pred.text, "masks", frame.name),
                         f"mask is {p.shape[0]}x{p.shape[1]}, the frame is {shape[0]}x{shape[1]} (H x W)")
    return p


def _overlaps(aset: AnnotationSet, owner: Query, pred: QueryPrediction, frames: Sequence[AnnotatedFrame],
              gt_cache: dict[tuple[int, int], np.ndarray], src) -> _Overlap:
    """IoU, pixel accuracy and pixel counts of ``pred``'s masks against ``owner``'s GT masks on ``frames``
    (GT masks kept in ``gt_cache``: a time-sensitive query shares its base's)."""
    ious = np.empty(len(frames))
    accs = np.empty(len(frames))
    pred_px = np.empty(len(frames), dtype=np.int64)
    gt_px = np.empty(len(frames), dtype=np.int64)
    for i, frame in enumerate(frames):
        g = _gt_mask(aset, owner, frame, gt_cache)
        p = _pred_mask(pred, frame, g.shape, src)
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
                           overlap: _Overlap, rule_config: TemporalRule, time_score: str,
                           src) -> tuple[QueryScore, list[FrameRecord]]:
    """A time-sensitive query's row (temporal Acc and vIoU of its decisions: the temporal rule's on its
    scores, ``tau`` as ``rule_config`` says for ``time_score``, or the method's own) and frame records."""
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
    result = score_sensitive(labels, overlap.iou, scores=scores, decisions=decisions, config=rule_config,
                             time_score=time_score)
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
