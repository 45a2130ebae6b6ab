"""Automatic checks of an annotation set, shown in the tool's review mode.

Each finding names a query, a frame and a kind; the reviewer jumps there and decides. Checks:

* ``no-mask-in-interval``: a frame inside a time-sensitive query's interval where its base query
  has no mask ("not annotated" where the state is said to hold: the frame cannot be scored).
* ``absent-in-interval``: inside an interval, the base is marked absent (the state cannot hold on
  an object that is not there).
* ``mask-outside-interval``: a non-empty base mask just outside an interval (within
  :attr:`ReviewConfig.edge_frames` of its edge): confirm the edge, the state must not hold there.
* ``empty``: a mask with no pixel ("absent in this frame"): confirm the object is really gone.
* ``tiny``: fewer than :attr:`ReviewConfig.tiny_pixels` pixels.
* ``fragmented``: more than :attr:`ReviewConfig.max_components` connected pieces of meaningful size.
* ``not-annotated``: a run of frames of the evaluated split where a query that is annotated
  elsewhere has no annotation (one finding per run: those frames cannot be scored).
* ``area-jump``: a mask whose area differs from the previous annotated frame's (same camera) by
  more than :attr:`ReviewConfig.area_jump` times (a proposal that filled a gap, a lost part).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Optional, Sequence

import cv2
import numpy as np

from benchmark.core.annotation import AnnotationSet, decode_mask


@dataclass
class ReviewConfig:
    """Thresholds of the automatic review checks."""

    tiny_pixels: int = 64
    """A non-empty mask with fewer pixels than this is flagged ``tiny``."""
    max_components: int = 3
    """More connected pieces than this (8-connectivity) is flagged ``fragmented``."""
    min_component_pixels: int = 4
    """Pieces smaller than this are counted as specks (always flagged, see ``specks``)."""
    edge_frames: int = 2
    """``mask-outside-interval`` looks this many time steps beyond each interval edge."""
    area_jump: float = 1.5
    """``area-jump``: consecutive non-empty masks whose areas differ by more than this factor."""


class _FrameRef(NamedTuple):
    name: str
    time_index: int


def review(aset: AnnotationSet, tool_frames: Sequence[tuple[int, str, int, str]],
           config: Optional[ReviewConfig] = None) -> list[dict]:
    """Findings for ``aset``; ``tool_frames`` lists the tool's frames as (index, name, time_index, split).

    The interval checks look at every tool frame of a split that has annotated frames (the
    evaluated split: annotating test frames does not make every training frame a finding).

    Returns dicts ``{"kind", "query", "frame" (tool index or None), "frame_name", "time_index", "message"}``
    sorted by query then time.
    """
    config = config or ReviewConfig()
    findings: list[dict] = []
    frames_by_id = {f.id: f for f in aset.frames}
    frame_index = {name: i for i, name, _, _ in tool_frames}
    id_by_name = {f.name: f.id for f in aset.frames}
    evaluated = {split for _, name, _, split in tool_frames if name in id_by_name}

    def add(kind: str, qid: int, frame, message: str) -> None:
        findings.append({"kind": kind, "query": qid, "frame": frame_index.get(frame.name),
                         "frame_name": frame.name, "time_index": frame.time_index, "message": message})

    # per-mask checks
    for (qid, fid), rle in aset.masks.items():
        frame = frames_by_id.get(fid)
        if frame is None:
            continue
        mask = decode_mask(rle)
        area = int(mask.sum())
        if area == 0:
            add("empty", qid, frame, "marked absent (empty mask): confirm the object is not visible")
            continue
        if area < config.tiny_pixels:
            add("tiny", qid, frame, f"only {area} pixels")
        n, _, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
        sizes = stats[1:, cv2.CC_STAT_AREA]
        pieces = int((sizes >= config.min_component_pixels).sum())
        specks = int((sizes < config.min_component_pixels).sum())
        if pieces > config.max_components:
            add("fragmented", qid, frame, f"{pieces} separate pieces")
        elif specks:
            add("fragmented", qid, frame, f"{specks} speck(s) under {config.min_component_pixels} pixels")

    _coverage_checks(aset, tool_frames, evaluated, config, add)

    # interval checks for time-sensitive queries (their masks are their base's)
    for q in aset.sensitive_queries:
        if q.base is None:
            continue
        for index, name, t, split in tool_frames:
            if split not in evaluated:
                continue
            frame = _FrameRef(name, t)
            fid = id_by_name.get(name)
            rle = None if fid is None else aset.masks.get((q.base, fid))
            inside = q.holds_at(t)
            if inside and rle is None:
                add("no-mask-in-interval", q.id, frame,
                    f"t={t} is inside an interval of {q.text!r} but its base has no mask here")
            elif inside and decode_mask(rle).sum() == 0:
                add("absent-in-interval", q.id, frame,
                    f"t={t} is inside an interval of {q.text!r} but its base is marked absent")
            elif not inside and rle is not None and q.intervals:
                near = [(a, b) for a, b in q.intervals
                        if a - config.edge_frames <= t < a or b < t <= b + config.edge_frames]
                if near and decode_mask(rle).any():
                    a, b = near[0]
                    add("mask-outside-interval", q.id, frame,
                        f"t={t} is just outside [{a}, {b}] of {q.text!r} and the object is visible: "
                        "confirm the state does not hold here")
    findings.sort(key=lambda f: (f["query"], f["time_index"], f["frame_name"], f["kind"]))
    return findings


def _coverage_checks(aset: AnnotationSet, tool_frames: Sequence[tuple[int, str, int, str]], evaluated: set,
                     config: ReviewConfig, add) -> None:
    """``not-annotated`` runs and ``area-jump`` masks of each annotated time-agnostic query, walking
    the tool's frames of the evaluated split in order."""
    id_by_name = {f.name: f.id for f in aset.frames}
    walk = [(name, t) for _, name, t, split in tool_frames if split in evaluated]
    for q in aset.agnostic_queries:
        if not any(k[0] == q.id for k in aset.masks):
            continue
        run: list[_FrameRef] = []
        previous = None
        for name, t in walk + [(None, None)]:  # a sentinel closes the last run
            rle = None if name is None else aset.masks.get((q.id, id_by_name.get(name, -1)))
            if name is not None and rle is None:
                run.append(_FrameRef(name, t))
                continue
            if run:
                span = f"t={run[0].time_index}..{run[-1].time_index}" if len(run) > 1 else f"t={run[0].time_index}"
                add("not-annotated", q.id, run[0], f"{len(run)} frame(s) ({span}) have no annotation of {q.text!r}")
                run = []
            if rle is None:
                continue
            area = int(decode_mask(rle).sum())
            if previous and area and max(area, previous) > config.area_jump * min(area, previous):
                add("area-jump", q.id, _FrameRef(name, t),
                    f"{area} pixels against {previous} on the previous annotated frame (x{area / previous:.2f})")
            previous = area or previous
