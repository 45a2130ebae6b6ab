"""Where object tracks come from: the generator's truth (oracle track), the run's segments, or a file.

The paper tracks objects through the video with DEVA (SAM inside a video segmenter); here:

* :func:`truth_tracks`: on generated scenes, the truth's ``whole``-level ids of the **training**
  frames (through the guarded accessor of :mod:`methods.supervision.truth_access`, so no evaluated
  frame is ever read). Oracle track only.
* :func:`segment_tracks`: the run's own segmenter (SAM on the real track): its ``large``-level masks,
  named by the ids it carries from frame to frame (:mod:`methods.supervision.association`), one track
  per id.
* :func:`methods.captioners.file.tracks_from_file`: masks stored beside the captions in a captions file
  (:mod:`.file`), e.g. from a video segmenter run elsewhere.
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from .base import ObjectTracks

TRUTH_OBJECT_LEVEL = 2
"""Index of the truth level whose ids are the tracked objects (``whole``; DEVA tracks whole objects)."""
SEGMENT_OBJECT_LEVEL = 2
"""Index into :data:`methods.supervision.base.LEVELS` of the segments whose ids are the tracked objects
(``large``: SAM's whole objects)."""


def tracked_frames(scene: Scene) -> list[Frame]:
    """The training frames in tracking order: per camera, in time order (so that the neighbours of
    a frame in the list are the same camera's neighbouring times)."""
    return sorted(scene.train_frames, key=lambda f: (f.camera_id, f.time_index, f.name))


def truth_tracks(scene: Scene, frames: Optional[list[Frame]] = None) -> ObjectTracks:
    """Whole-object tracks of a generated scene's training frames (oracle track)."""
    from methods.supervision.truth_access import open_truth, training_id_maps

    truth = open_truth(scene)
    frames = tracked_frames(scene) if frames is None else frames
    ids = [training_id_maps(truth, f)[TRUTH_OBJECT_LEVEL] for f in frames]
    labels = {}
    present = set()
    for m in ids:
        present.update(int(v) for v in np.unique(m) if v >= 0)
    for obj in sorted(present):
        labels[obj] = truth.name("whole", obj) or f"object {obj}"
    return ObjectTracks(source="truth", frame_names=[f.name for f in frames], ids=ids, labels=labels)


def segment_id_maps(supervision, frames: Sequence[Frame]) -> list[np.ndarray]:
    """Per frame, the (H, W) int64 map of ``supervision``'s ``large``-level masks in the ids the segmenter
    gave them (-1 = no mask)."""
    segmenter = supervision.sources.get("segmenter", "segments")
    maps = []
    for frame in frames:
        try:
            sup = supervision.frame(frame.name)
        except KeyError:
            raise InputError(frame.image_path, "captions.object_tracks",
                             f"no segments of training frame {frame.name!r} in the run's supervision") from None
        if sup.segment_ids is None:
            raise InputError(None, "captions.object_tracks", f"the {segmenter!r} segments of frame {frame.name!r} "
                             "carry no segmenter ids to track objects by (give the tracks in captions.file)")
        index = sup.levels[SEGMENT_OBJECT_LEVEL].astype(np.int64)
        named = sup.segment_ids[SEGMENT_OBJECT_LEVEL]
        masked = (index >= 0) & (index < named.size)  # a mask added after segmenting has no segmenter id
        ids = np.full(index.shape, -1, dtype=np.int64)
        ids[masked] = named[index[masked]]
        maps.append(ids)
    return maps


def segment_tracks(scene: Scene, supervision, *, min_frames: int = 3, min_area: float = 0.001,
                   frames: Optional[list[Frame]] = None) -> ObjectTracks:
    """Whole-object tracks of the training frames from the run's segments (``supervision``, a
    :class:`~methods.supervision.base.Supervision` whose frames carry their ``segment_ids``).

    Each ``large``-level mask is named by the id the segmenter gave it; one track per id. An id is visible
    in a frame where it covers at least ``min_area`` of the frame's pixels; ids visible in fewer than
    ``min_frames`` training frames (one-frame ids, slivers) are dropped, their pixels belong to no object.
    The kept ids are numbered 0, 1, ... in the order of the segmenter's ids, and labelled with them.
    """
    frames = tracked_frames(scene) if frames is None else frames
    maps = segment_id_maps(supervision, frames)
    visible: dict[int, int] = {}
    for ids in maps:
        found, counts = np.unique(ids[ids >= 0], return_counts=True)
        for sid in found[counts >= min_area * ids.size].tolist():
            visible[sid] = visible.get(sid, 0) + 1
    kept = np.array(sorted(sid for sid, n in visible.items() if n >= min_frames), dtype=np.int64)
    out = []
    for ids in maps:
        tracked = np.full(ids.shape, -1, dtype=np.int32)
        if kept.size:
            pos = np.searchsorted(kept, ids)
            hit = (ids >= 0) & (kept[np.minimum(pos, kept.size - 1)] == ids)
            tracked[hit] = pos[hit]
        out.append(tracked)
    segmenter = supervision.sources.get("segmenter", "segments")
    labels = {obj: f"{segmenter} segment {sid}" for obj, sid in enumerate(kept.tolist())}
    return ObjectTracks(source=f"segments:{segmenter}", frame_names=[f.name for f in frames], ids=out, labels=labels)


def whole_of(truth, level: str, id_: int) -> int:
    """The ``whole``-level id that truth node (``level``, ``id_``) belongs to (parents walked up)."""
    while level != "whole":
        parent = truth.catalogue[level][int(id_)]["parent"]
        level = "part" if level == "subpart" else "whole"
        id_ = int(parent)
    return int(id_)


def objects_named(tracks: ObjectTracks, name: str, truth=None) -> list[int]:
    """Tracked objects that ``name`` (a query's base object, e.g. ``"liquid"``) lies in.

    Truth tracks: the wholes containing the nodes declared with that name (a part's whole). Other
    tracks: objects whose label is ``name``. Empty when none matches.
    """
    if tracks.source == "truth" and truth is not None:
        level, ids = truth.ids_named(name)
        wholes = sorted({whole_of(truth, level, i) for i in ids})
        return [w for w in wholes if w in set(tracks.objects())]
    return sorted(o for o, label in tracks.labels.items() if label == name)


def caption_embeddings_by_base(aset, captions, tracks, encoder, time_of: dict, truth=None) -> dict:
    """(base object's query text, time_index) -> caption embedding, for every sensitive query's base.

    Captions belong to tracked objects; a query's base (``"liquid"``) is mapped to the tracked object
    it lies in (:func:`objects_named`). With several cameras at one time
    index the first frame's caption (by name) is used.
    """
    emb_of = dict(zip(captions.texts(), encoder.encode(captions.texts(), kind="passage")))
    out = {}
    for q in aset.sensitive_queries:
        base = aset.mask_owner(q).text
        try:
            objs = objects_named(tracks, base, truth)
        except KeyError:
            objs = []
        if not objs:
            raise InputError(None, "tracks", f"no tracked object for {base!r} (base of query {q.text!r})")
        for (frame, obj), text in sorted(captions.frames.items()):
            if obj == objs[0]:
                out.setdefault((base, int(time_of[frame])), emb_of[text])
    return out
