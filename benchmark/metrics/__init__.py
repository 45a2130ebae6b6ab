"""The metrics core: pure metric functions, the temporal decision rule, aggregation, scoring.

* :mod:`.masks`: :func:`iou`, :func:`pixel_accuracy` (empty-mask rules in their docstrings).
* :mod:`.temporal`: :class:`TemporalRule`, :func:`smooth_scores`, :func:`decide_temporal`,
  :func:`apply_temporal_rule`, :func:`temporal_accuracy`, :func:`video_iou`; diagnostics
  :func:`score_auc`, :func:`threshold_margins`, :func:`near_threshold_fraction`,
  :func:`accuracy_at_threshold`, :func:`best_cut_accuracy`.
* :mod:`.captions`: :func:`delta_sim` and its scene/dataset forms.
* :mod:`.aggregate`: :class:`FrameRecord`, :func:`aggregate` (frame -> query -> scene -> dataset).
* :mod:`.scoring`: :class:`ScoreConfig`, :func:`score_agnostic`, :func:`score_sensitive`,
  :func:`score_scene` -> :class:`SceneScore`, :func:`aggregate_scenes` -> :class:`DatasetScore`; the
  reported names: :data:`RANKED_METRICS` (full means, an unanswered query counting 0),
  :data:`ANSWERED_METRICS` (answered queries only), :data:`ABSENT_FP`.
"""

from .aggregate import LEVELS, FrameRecord, aggregate, records_table
from .captions import (caption_auc, caption_replay_accuracy, caption_replay_scores, cosine_similarity, delta_sim,
                       delta_sim_scene, mean_delta_sim)
from .masks import EMPTY_IOU, accuracy_from_confusion, confusion, iou, iou_from_confusion, pixel_accuracy
from .scoring import (ABSENT_FP, ANSWERED_METRICS, ANSWERED_SUFFIX, RANKED_METRICS, REPORT_METRICS, AgnosticScore,
                      DatasetScore, QueryScore, SceneScore, ScoreConfig, SensitiveScore, aggregate_scenes,
                      score_agnostic, score_scene, score_sensitive)
from .temporal import (EMPTY_UNION_VIOU, NEAR_THRESHOLD_FRACTION, TemporalDecision, TemporalRule,
                       accuracy_at_threshold, apply_temporal_rule, best_cut_accuracy, decide_temporal,
                       near_threshold_fraction, score_auc, smooth_scores, temporal_accuracy, temporal_threshold,
                       threshold_margins, video_iou)

__all__ = [
    "LEVELS", "FrameRecord", "aggregate", "records_table",
    "caption_auc", "caption_replay_accuracy", "caption_replay_scores", "cosine_similarity", "delta_sim",
    "delta_sim_scene", "mean_delta_sim",
    "EMPTY_IOU", "accuracy_from_confusion", "confusion", "iou", "iou_from_confusion", "pixel_accuracy",
    "ABSENT_FP", "ANSWERED_METRICS", "ANSWERED_SUFFIX", "RANKED_METRICS", "REPORT_METRICS", "AgnosticScore", "DatasetScore", "QueryScore", "SceneScore", "ScoreConfig",
    "SensitiveScore", "aggregate_scenes", "score_agnostic", "score_scene", "score_sensitive",
    "EMPTY_UNION_VIOU", "NEAR_THRESHOLD_FRACTION", "TemporalDecision", "TemporalRule",
    "accuracy_at_threshold", "apply_temporal_rule", "best_cut_accuracy",
    "decide_temporal", "near_threshold_fraction", "score_auc", "smooth_scores", "temporal_accuracy",
    "temporal_threshold", "threshold_margins", "video_iou",
]
