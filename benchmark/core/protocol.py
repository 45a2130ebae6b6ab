"""The evaluation protocol: every constant of the time-agnostic query, the time-sensitive query and the
temporal rule in one object, with named presets (in the spirit of pycocotools' ``Params``).

* ``release`` (the default): the rules of the code that produced the published numbers of LangSplat
  and 4D LangSplat (their ``evaluate_iou_loc.py`` / ``eval.py``).
* ``paper-text``: the reading of the paper's wording (threshold 0.4 on the min-max rescaled relevance,
  ``tau`` = mean of the smoothed scores for every method).

Choices of the benchmark's own that both presets share, stated here because tables call ``release`` "the
rules of the code" (README's protocol table says the same):

* window sizes scale with the resolution (:attr:`AgnosticQuery.kernel_scaling`): the release's 29x29 and
  7x7 windows are defined at its 960x536 frames; at 170x128 they become 5 and 1, and the majority filter
  does nothing. Perfect features score mIoU 84.7 with scaled windows and 59.8 with the fixed ones
  (synthetic presets, ``reports/ablations/protocol-ceiling.md``);
* mAcc is read as per-pixel accuracy ``(TP + TN) / (H W)`` averaged like mIoU: an assumption, the release
  has no mAcc code (:func:`benchmark.metrics.masks.pixel_accuracy`);
* the frames scored are the annotated held-out frames of the named split (:data:`SCORED_FRAMES_NOTE`).

A method answers with the protocol the harness hands it (:meth:`methods.api.Model.use_protocol`); the
harness scores with the same object, and every results file records its name and all of its constants.
``shared/docs/protocol.md`` states the facts behind each constant. This module imports nothing of the
harness or the methods: every layer may read it.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from dataclasses import dataclass, field
from typing import Any, Literal, Mapping

CANONICAL_PHRASES: tuple[str, ...] = ("object", "things", "stuff", "texture")
"""LERF's canonical negative phrases, as used by LangSplat and 4D LangSplat."""

ThresholdRule = Literal["stretched", "rescaled"]
TauFrom = Literal["raw", "smoothed"]
EndMode = Literal["renormalise", "keep", "replicate"]
SensitiveMask = Literal["unfiltered", "filtered"]
RelevanceScore = Literal["peak", "mask-mean"]
TimeScore = Literal["feature", "relevance-peak"]
AbsentFrames = Literal["skip", "score-empty"]

TIME_SCORES: tuple[str, ...] = ("feature", "relevance-peak")
"""How a method makes its per-frame time-sensitive score, which picks its ``tau`` rule
(:meth:`TemporalRule.tau_source`): ``"feature"``: a similarity of decoded time-varying features to the
query (4D LangSplat-style heads); ``"relevance-peak"``: the method's time-agnostic relevance alone (the
release's CLIP-only baselines, deformable CLIP and LangSplat: the chosen level's peak smoothed relevance
under ``release``, :attr:`SensitiveQuery.relevance_score`)."""


def _choice(value: Any, allowed: tuple, name: str) -> None:
    if value not in allowed:
        raise ValueError(f"{name} must be one of {', '.join(repr(a) for a in allowed)}, got {value!r}")


@dataclass(frozen=True)
class AgnosticQuery:
    """Constants of the time-agnostic query (relevance, smoothing, threshold, majority filter, level)."""

    canonical_phrases: tuple[str, ...] = CANONICAL_PHRASES
    """Negative phrases the query competes against in the LERF relevance."""
    temperature: float = 10.0
    """Scale ``s`` inside ``exp(s q.f)`` of the LERF relevance (paper and release: 10)."""
    smoothing_kernel: int = 29
    """Side of the average-pooling window mixed into the relevance map (29x29)."""
    threshold: float = 0.4
    """Threshold on the relevance after :attr:`threshold_rule`'s rescaling (paper and release: 0.4)."""
    threshold_rule: ThresholdRule = "stretched"
    """``"stretched"`` (release): ``clip(2 x - 1, 0, 1) > threshold`` of the min-max rescaled ``x``, i.e.
    ``x > (1 + threshold) / 2`` = 0.7. ``"rescaled"`` (paper text): ``x > threshold``."""
    majority_kernel: int = 7
    """Side of the majority filter applied to the binary mask (7x7)."""
    majority_fraction: float = 0.5
    """A pixel stays in the mask when more than this fraction of its window is in the mask."""
    kernel_scaling: Literal["resolution", "fixed"] = "resolution"
    """``"resolution"``: both windows are the release's sizes scaled by ``sqrt(H W / (H_ref W_ref))`` to the
    rendered image, rounded to the nearest odd size (at least 1), so they cover the same fraction of the
    image as at 960x536, where they equal the release's. ``"fixed"``: the pixel sizes as given, whatever
    the resolution (the release's code, literally). With perfect features on split-cookie at 128 px,
    release threshold: mIoU 77.2 fixed vs 90.8 scaled (a 29x29 window at 128 px spreads every small
    part's relevance over its neighbours)."""
    reference_size: tuple[int, int] = (536, 960)
    """(height, width) at which the window sizes are defined: the release renders HyperNeRF's ``rgb/2x``."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "canonical_phrases", tuple(self.canonical_phrases))
        object.__setattr__(self, "reference_size", tuple(int(x) for x in self.reference_size))
        _choice(self.threshold_rule, ("stretched", "rescaled"), "threshold_rule")
        _choice(self.kernel_scaling, ("resolution", "fixed"), "kernel_scaling")
        if self.smoothing_kernel < 1 or self.majority_kernel < 1 or self.smoothing_kernel % 2 == 0 \
                or self.majority_kernel % 2 == 0:
            raise ValueError("smoothing_kernel and majority_kernel must be odd and positive (centred windows)")
        if not self.canonical_phrases:
            raise ValueError("canonical_phrases must name at least one phrase")

    @property
    def rescaled_cut(self) -> float:
        """The cut on the min-max rescaled relevance the rule amounts to (0.7 stretched, 0.4 rescaled)."""
        return (1.0 + self.threshold) / 2.0 if self.threshold_rule == "stretched" else self.threshold

    def kernels_for(self, height: int, width: int) -> tuple[int, int]:
        """(smoothing, majority) window sides for an image of ``height x width`` (see ``kernel_scaling``)."""
        if self.kernel_scaling == "fixed":
            return self.smoothing_kernel, self.majority_kernel
        scale = math.sqrt(height * width / float(self.reference_size[0] * self.reference_size[1]))
        return _nearest_odd(self.smoothing_kernel * scale), _nearest_odd(self.majority_kernel * scale)


def _nearest_odd(size: float) -> int:
    """The odd integer nearest to ``size``, at least 1 (a centred window needs an odd side)."""
    return max(1, 2 * int(math.floor((size - 1.0) / 2.0 + 0.5)) + 1)


@dataclass(frozen=True)
class SensitiveQuery:
    """Constants of the time-sensitive query's per-frame answer (before the temporal rule)."""

    mask: SensitiveMask = "unfiltered"
    """Spatial mask of the query on a frame: the time-agnostic answer before the majority filter
    (``"unfiltered"``: the release) or after it (``"filtered"``)."""
    relevance_score: RelevanceScore = "peak"
    """Per-frame score of methods that answer time by relevance alone (the CLIP baselines):
    ``"peak"`` (release): the chosen level's maximum smoothed relevance; ``"mask-mean"``: the mean
    smoothed relevance inside the spatial mask (undefined on an empty mask)."""

    def __post_init__(self) -> None:
        _choice(self.mask, ("unfiltered", "filtered"), "mask")
        _choice(self.relevance_score, ("peak", "mask-mean"), "relevance_score")


@dataclass(frozen=True)
class TemporalRule:
    """Constants of the temporal decision rule (:mod:`benchmark.metrics.temporal`)."""

    weights: tuple[float, ...] = (0.1, 0.8, 0.1)
    """Smoothing kernel over neighbouring evaluated frames, centred, odd length, summing to 1.
    Paper and release: ``(0.1, 0.8, 0.1)``; ``(1.0,)`` disables smoothing."""
    ends: EndMode = "keep"
    """What a missing neighbour (outside the sequence, or an undefined score) does: ``"keep"``
    (release): the frame keeps its unsmoothed score; ``"renormalise"``: the remaining weights are
    rescaled to sum to 1, e.g. the first frame gets ``(0.8 s_0 + 0.1 s_1) / 0.9``; ``"replicate"``: the
    missing neighbour takes the frame's own score, e.g. ``0.9 s_0 + 0.1 s_1``."""
    tau_from: TauFrom = "raw"
    """``tau`` of methods whose time score is a ``"feature"`` similarity (:data:`TIME_SCORES`): the mean of
    the ``"raw"`` scores (release; the smoothed scores are compared with it) or of the ``"smoothed"`` ones
    (paper text). The release's ``eval/eval.py`` takes ``video_thresh`` as the mean of ``video_similarity``,
    the list it never overwrites with the smoothed values."""
    relevance_peak_tau_from: TauFrom = "smoothed"
    """``tau`` of methods whose time score is a ``"relevance-peak"`` (the CLIP-only baselines). Release:
    ``"smoothed"``: its ``eval/eval.py`` overwrites ``sorted_clip_similarity`` with the smoothed values and
    then takes ``clip_thresh`` as their mean. The rule differs per method kind in the release's code."""
    inclusive: bool = True
    """``pred_t = s~_t >= tau`` (paper and release); ``False`` uses ``>``."""
    undefined_decision: bool = False
    """Decision for a frame whose score is undefined (NaN, e.g. an empty spatial mask)."""
    tie_tolerance: float = 1e-9
    """Relative tolerance (times the largest ``|s~_t|``) within which ``s~_t`` counts as equal to ``tau``,
    so float rounding cannot split ties. Not a paper constant; 0 compares exactly."""

    def __post_init__(self) -> None:
        try:
            w = tuple(float(x) for x in self.weights)
        except (TypeError, ValueError):
            raise ValueError(f"weights must be numbers, got {self.weights!r}") from None
        object.__setattr__(self, "weights", w)
        if len(w) % 2 == 0 or not all(math.isfinite(x) and x >= 0 for x in w):
            raise ValueError(f"weights must be a finite, non-negative kernel of odd length, got {w}")
        if abs(sum(w) - 1.0) > 1e-6:
            raise ValueError(f"weights must sum to 1, got sum {sum(w):.6g}")
        if w[len(w) // 2] <= 0:
            raise ValueError("the centre weight must be positive")
        if not (self.tie_tolerance >= 0):
            raise ValueError(f"tie_tolerance must be >= 0, got {self.tie_tolerance}")
        _choice(self.ends, ("renormalise", "keep", "replicate"), "ends")
        _choice(self.tau_from, ("raw", "smoothed"), "tau_from")
        _choice(self.relevance_peak_tau_from, ("raw", "smoothed"), "relevance_peak_tau_from")

    def tau_source(self, time_score: str = "feature") -> str:
        """``"raw"`` or ``"smoothed"``: the scores whose mean is ``tau`` for a method whose time score is
        ``time_score`` (one of :data:`TIME_SCORES`)."""
        _choice(time_score, TIME_SCORES, "time_score")
        return self.relevance_peak_tau_from if time_score == "relevance-peak" else self.tau_from

    def to_dict(self) -> dict:
        return {**dataclasses.asdict(self), "weights": list(self.weights)}


@dataclass(frozen=True)
class ScoringRule:
    """Which annotated frames a query is scored on."""

    absent_frames: AbsentFrames = "skip"
    """A frame whose ground-truth mask for the query (a time-sensitive query: its base's) is empty, i.e.
    the object is annotated absent there. ``"skip"`` (release): not scored for that query: the release
    queries a label only on the frames where it is annotated (``eval/eval.py``:
    ``clip_model.set_positives(list(img_ann.keys()))`` per frame, a time query's label added only where
    its base label is). ``"score-empty"``: scored against the empty mask, a stricter rule of the
    benchmark's own (a min-max thresholded relevance is never empty, so every field method scores IoU 0
    there). Either way the share of absent frames with a non-empty predicted mask is reported apart
    (``absentFP``, :mod:`benchmark.metrics.scoring`)."""

    def __post_init__(self) -> None:
        _choice(self.absent_frames, ("skip", "score-empty"), "absent_frames")


@dataclass(frozen=True)
class Protocol:
    """One named set of query and scoring rules."""

    name: str = "release"
    """Preset name (``release``, ``paper-text``), or ``custom`` when a constant was changed."""
    agnostic: AgnosticQuery = field(default_factory=AgnosticQuery)
    """The time-agnostic query's constants."""
    sensitive: SensitiveQuery = field(default_factory=SensitiveQuery)
    """The time-sensitive query's per-frame answer."""
    temporal: TemporalRule = field(default_factory=TemporalRule)
    """The temporal decision rule, ``tau`` per method kind included."""
    scoring: ScoringRule = field(default_factory=ScoringRule)
    """Which annotated frames are scored (absent objects)."""

    def to_dict(self) -> dict:
        """Every constant, as plain JSON values (what results files record)."""
        out = dataclasses.asdict(self)
        out["temporal"]["weights"] = list(self.temporal.weights)
        out["agnostic"]["canonical_phrases"] = list(self.agnostic.canonical_phrases)
        out["agnostic"]["reference_size"] = list(self.agnostic.reference_size)
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "Protocol":
        """Rebuild a protocol from :meth:`to_dict` (unknown keys are an error naming them).

        A constant the record lacks was added after it was written: it takes the value the code applied
        then (:data:`CONSTANTS_BEFORE_RECORDED`), else the default. A record named after a preset whose
        constants are no longer that preset's is named ``custom``, so runs scored under a preset's earlier
        rules never sit in one table with runs under its current ones."""
        parts: dict[str, Any] = {}
        for group, kind in _GROUPS:
            values = dict(data.get(group) or {})
            known = {f.name for f in dataclasses.fields(kind)}
            unknown = sorted(set(values) - known)
            if unknown:
                raise ValueError(f"protocol.{group}: unknown constant(s) {unknown}; known: {sorted(known)}")
            for key, earlier in CONSTANTS_BEFORE_RECORDED.items():
                key_group, _, constant = key.partition(".")
                if key_group == group and constant not in values:
                    values[constant] = earlier(values)
            parts[group] = kind(**values)
        name = str(data.get("name", "custom"))
        rebuilt = cls(name=name, **parts)
        if name in PROTOCOLS and rebuilt != PROTOCOLS[name]:
            return dataclasses.replace(rebuilt, name="custom")
        return rebuilt

    def with_changes(self, changes: Mapping[str, Any]) -> "Protocol":
        """A copy with ``{"group.constant": value}`` changed; named ``custom`` unless nothing changed."""
        groups = {group: getattr(self, group) for group, _ in _GROUPS}
        edits: dict[str, dict] = {}
        for key, value in changes.items():
            group, _, constant = key.partition(".")
            if group not in groups or not constant:
                raise ValueError(f"protocol constant {key!r} must be <group>.<constant> with group one of "
                                 f"{sorted(groups)}")
            known = [f.name for f in dataclasses.fields(groups[group])]
            if constant not in known:
                close = difflib.get_close_matches(constant, known, n=1)
                hint = f" (did you mean {group}.{close[0]}?)" if close else ""
                raise ValueError(f"protocol has no constant {key!r}{hint}")
            edits.setdefault(group, {})[constant] = value
        new = {g: dataclasses.replace(groups[g], **edits.get(g, {})) for g in groups}
        changed = any(new[g] != groups[g] for g in groups)
        return Protocol(name="custom" if changed else self.name, **new)


_GROUPS: tuple[tuple[str, type], ...] = (("agnostic", AgnosticQuery), ("sensitive", SensitiveQuery),
                                         ("temporal", TemporalRule), ("scoring", ScoringRule))
"""The protocol's groups of constants, as results files record them."""

CONSTANTS_BEFORE_RECORDED: dict[str, Any] = {
    # one tau rule for every method kind: the feature rule's
    "temporal.relevance_peak_tau_from": lambda group: group.get("tau_from", "raw"),
    # absent frames were scored against the empty mask
    "scoring.absent_frames": lambda group: "score-empty",
}
"""``"group.constant"`` -> the value (a function of the record's other constants of that group) a
constant had in code written before results recorded it: what :meth:`Protocol.from_dict` gives a record
that lacks it, so an earlier run is read as it was scored."""

PROTOCOLS: dict[str, Protocol] = {
    "release": Protocol(name="release"),
    "paper-text": Protocol(
        name="paper-text",
        agnostic=AgnosticQuery(threshold_rule="rescaled"),
        sensitive=SensitiveQuery(relevance_score="mask-mean"),
        temporal=TemporalRule(ends="renormalise", tau_from="smoothed"),
    ),
}
"""The named presets. ``release`` is every default of the dataclasses above."""

DEFAULT_PROTOCOL = "release"
"""The protocol runs and scores use unless told otherwise: the rules behind the published numbers."""

RELEASE_DEFECTS_NOT_COPIED: tuple[str, ...] = (
    "annotation files: the release reads only the first polygon of an annotation; every polygon of a "
    "label in an image is OR-ed here",
    "vIoU with no frame predicted or labelled positive: the release returns 0; here it is "
    "1 (the method correctly says 'never'; never arises with the release's annotations)",
)
"""Release behaviours that change what a query means or crash; both presets keep them fixed."""

SCORED_FRAMES_NOTE = ("the annotated held-out frames of the named split (`--score-train` adds the annotated "
                      "training frames)")
"""Which frames the benchmark scores by default, as tables state it. (The release scores the annotated
frames of its evaluation split; its code does not show whether training views are among them, and the
paper's appendix says the annotated test frames do not overlap the training frames.)"""


WINDOW_SCALING_NOTE = ("29x29 smoothing and 7x7 majority windows are the release's sizes at its 960x536 frames, "
                       "scaled with the resolution here (at 170x128 they become 5 and 1: no majority filter); "
                       "perfect features score mIoU 84.7 scaled vs 59.8 fixed (reports/ablations/protocol-ceiling.md)")
"""The benchmark's window scaling (:attr:`AgnosticQuery.kernel_scaling`), as tables state it."""

MACC_NOTE = "mAcc = per-pixel accuracy (TP + TN) / (H W) averaged like mIoU: an assumption (the release has no mAcc code)"
"""How mAcc is read (:func:`benchmark.metrics.masks.pixel_accuracy`), as tables state it."""

SHARED_CHOICES: tuple[str, ...] = (WINDOW_SCALING_NOTE, MACC_NOTE, f"scored frames: {SCORED_FRAMES_NOTE}")
"""The benchmark's own choices both presets share (module docstring), one line each, for table headers
that call ``release`` the rules of the code."""


def get_protocol(name: str) -> Protocol:
    """The preset called ``name``; an unknown name is a ``ValueError`` with the closest preset."""
    if isinstance(name, Protocol):
        return name
    if name in PROTOCOLS:
        return PROTOCOLS[name]
    close = difflib.get_close_matches(str(name), list(PROTOCOLS), n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    raise ValueError(f"unknown protocol {name!r}{hint}; presets: {', '.join(PROTOCOLS)}")


def default_protocol() -> Protocol:
    return PROTOCOLS[DEFAULT_PROTOCOL]
