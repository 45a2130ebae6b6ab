"""Ground-truth annotations of a generated scene, built exactly from the id maps.

* One **time-agnostic** query per declared name (wholes, parts, subparts: "cookie", "cup handle",
  "chocolate chip"), with a mask on every evaluated frame (empty where it is hidden or absent).
  Several nodes with one name ("chocolate chip" x 5) share one query whose mask is their union.
* One **time-sensitive** query per state of every timeline whose state is marked ``query``
  ("cracked cookie" and its complement "whole cookie"), based on the query of the node that owns
  the timeline, with the state's inclusive time-index intervals. A change that develops over many frames
  (:mod:`benchmark.synthetic.state_changes`) counts as the new state from the first frame past the
  midpoint of its visual transition (:class:`~benchmark.synthetic.model.Timeline`: frames from the
  boundary ``b`` on show more than half of the change, frames before it less), so the intervals are the
  timeline's segments exactly; a state that comes back gets one interval per time it holds.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from benchmark.core.annotation import AnnotatedFrame, AnnotationSet, Query

from .model import LEVELS, Catalogue

LEVEL_INDEX = {lv: k for k, lv in enumerate(LEVELS)}


def build_annotations(scene_name: str, catalogue: Catalogue, evaluated: Iterable[tuple], num_frames: int, *,
                      time_sensitive: bool, info: dict) -> AnnotationSet:
    """``evaluated`` yields (frame name, time_index, camera_id, (3, H, W) id maps) per evaluated frame."""
    aset = AnnotationSet(scene=scene_name, num_time_steps=num_frames, info=dict(info))
    query_of: dict[str, Query] = {}
    selectors: dict[int, tuple[int, np.ndarray]] = {}
    for name in catalogue.names(queried_only=True):
        level, ids = catalogue.ids_named(name)
        q = Query(id=len(aset.queries) + 1, text=name, kind="agnostic", level=level)
        aset.queries.append(q)
        query_of[name] = q
        selectors[q.id] = (LEVEL_INDEX[level], np.asarray(ids, dtype=np.uint16))
    if time_sensitive:
        for entry, timeline in catalogue.timelines():
            base = query_of[entry.name]
            intervals = timeline.intervals()
            for state in timeline.states:
                if not state.query:
                    continue
                if state.phrase in query_of:
                    raise ValueError(f"state phrase {state.phrase!r} repeats a query text")
                q = Query(id=len(aset.queries) + 1, text=state.phrase, kind="sensitive", base=base.id,
                          intervals=list(intervals[state.key]), level=entry.level)
                aset.queries.append(q)
                query_of[state.phrase] = q
    for frame_id, (name, time_index, camera_id, ids) in enumerate(evaluated, start=1):
        h, w = ids.shape[1:]
        aset.frames.append(AnnotatedFrame(id=frame_id, name=name, time_index=time_index, width=w, height=h,
                                          camera_id=camera_id))
        for qid, (level, wanted) in selectors.items():
            aset.set_mask(qid, frame_id, np.isin(ids[level], wanted))
    return aset
