"""Where object tracks come from: the generator's truth (oracle track) or a file.

The paper tracks objects through the video with DEVA (SAM inside a video segmenter); here:

* :func:`truth_tracks`: on generated scenes, the truth's ``whole``-level ids of the **training**
  frames (through the guarded accessor of :mod:`methods.supervision.truth_access`, so no evaluated
  frame is ever read). Oracle track only.
* :func:`tracks_from_captions_file`: masks stored beside the captions in a captions file
  (:mod:`.file`), e.g. from a video segmenter run elsewhere.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from benchmark.core.errors import InputError
from benchmark.core.scene import Frame, Scene

from .base import ObjectTracks

TRUTH_OBJECT_LEVEL = 2
"""Index of the truth level whose ids are the tracked objects (``whole``; DEVA tracks whole objects)."""


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
