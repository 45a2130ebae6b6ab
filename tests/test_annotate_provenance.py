"""How a mask was made, draft queries, which frames a session offers, and the review's coverage checks (no HTTP)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from annotations.format import load_annotations, save_annotations
from annotations.tool.review import review
from annotations.tool.session import AnnotationSession, SessionConfig, mask_to_runs
from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene
from benchmark.core.annotation import AnnotatedFrame, AnnotationSet, Query
from benchmark.core.errors import InputError
from benchmark.loaders import load_scene

W, H = 96, 64


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The same motion in a test and a train split, interleaved in time."""
    seq = rigid_sequence(5, W, H, seed=1, travel_frac=0.2, radius_frac=0.2)
    out = write_dnerf_scene(seq, tmp_path_factory.mktemp("two") / "two", split="test")
    return load_scene(write_dnerf_scene(seq, out, split="train"))


def _mask(x0=10, x1=40):
    m = np.zeros((H, W), bool)
    m[10:40, x0:x1] = True
    return m


def test_the_default_session_offers_the_scored_frames(scene, tmp_path):
    s = AnnotationSession(scene, tmp_path / "a.json")
    try:
        assert [f.split for f in s.frames] == ["test"] * 5
        assert "scored" in s.state()["frames_offered"]
    finally:
        s.close()


def test_propagation_walks_the_offered_frames_across_splits(scene, tmp_path):
    s = AnnotationSession(scene, tmp_path / "a.json", config=SessionConfig(split="all"))
    try:
        qid, rev = s.add_query(s.revision, "blob")
        s.apply(rev, [{"type": "mask", "query": qid, "frame": 0, "mask": {"counts": mask_to_runs(_mask())}}])
        out = s.propagate(qid, 0, 1, 3)
        assert [p["frame"] for p in out["proposals"]] == [1, 2, 3]
        assert [s.frames[i].split for i in (1, 2)] == ["train", "test"]
    finally:
        s.close()


def test_made_by_is_kept_per_mask_forgotten_on_an_unsaid_edit_and_checked(scene, tmp_path):
    path = tmp_path / "a.json"
    s = AnnotationSession(scene, path, config=SessionConfig(annotator="simulated",
                                                            protocol={"target_iou": 0.9}))
    try:
        qid, rev = s.add_query(s.revision, "blob")
        change = {"type": "mask", "query": qid, "mask": {"counts": mask_to_runs(_mask())}}
        rev = s.apply(rev, [{**change, "frame": 0, "made_by": "box"}, {**change, "frame": 1, "made_by": "propagated"}])
        saved = load_annotations(path)
        fid = {f.name: f.id for f in saved.frames}
        first, second = (fid[s.frames[k].name] for k in (0, 1))
        assert saved.made_by == {(qid, first): "box", (qid, second): "propagated"}
        assert "made_by" not in saved.info
        assert saved.info["annotator"] == "simulated" and saved.info["protocol"] == {"target_iou": 0.9}
        assert s.masks_of_frame(1)["masks"][str(qid)]["made_by"] == "propagated"
        rev = s.apply(rev, [{**change, "frame": 1}])  # edited by hand: no longer "propagated"
        assert load_annotations(path).made_by == {(qid, first): "box"}
        assert "made_by" not in s.masks_of_frame(1)["masks"][str(qid)]
        with pytest.raises(InputError, match="made_by"):
            s.apply(rev, [{**change, "frame": 2, "made_by": "magic"}])
        rev = s.apply(rev, [{**change, "frame": 2, "made_by": "scripted"}, {**change, "frame": 0, "mask": None}])
        saved = load_annotations(path)  # a removed mask takes its note along
        assert saved.made_by == {(qid, saved.frame(s.frames[2].name).id): "scripted"}
        s.delete_query(rev, qid)
        assert load_annotations(path).made_by == {}
    finally:
        s.close()


def test_a_failed_commit_restores_the_notes(scene, tmp_path, monkeypatch):
    from annotations.tool import session as session_module

    s = AnnotationSession(scene, tmp_path / "a.json")
    try:
        qid, rev = s.add_query(s.revision, "blob")
        change = {"type": "mask", "query": qid, "frame": 0, "mask": {"counts": mask_to_runs(_mask())}}
        rev = s.apply(rev, [{**change, "made_by": "box"}])
        before = dict(s.aset.made_by)

        def fail(*args, **kwargs):
            raise OSError("disk full")

        monkeypatch.setattr(session_module, "save_annotations", fail)
        with pytest.raises(OSError):
            s.apply(rev, [{**change, "made_by": "clicks"}])
        assert s.aset.made_by == before
        with pytest.raises(OSError):
            s.delete_query(rev, qid)
        assert s.aset.made_by == before and s.revision == rev
    finally:
        s.close()


def test_an_older_file_keeps_its_notes_and_a_draft_query_can_be_marked_reviewed(scene, tmp_path):
    path = tmp_path / "a.json"
    aset = AnnotationSet(scene=scene.name, num_time_steps=scene.num_time_steps,
                         queries=[Query(id=1, text="blob", review="draft"), Query(id=2, text="dot")])
    frame = next(f for f in scene.frames if f.split == "test")
    aset.frames = [AnnotatedFrame(id=1, name=frame.name, time_index=frame.time_index, width=W, height=H)]
    aset.set_mask(1, 1, _mask())
    save_annotations(aset, path)
    doc = json.loads(path.read_text())
    doc["info"]["made_by"] = {"1": {frame.name: "drawn"}}  # where the notes were kept before
    path.write_text(json.dumps(doc))
    s = AnnotationSession(scene, path)
    try:
        index = s.index_of[frame.name]
        assert s.masks_of_frame(index)["masks"]["1"]["made_by"] == "drawn"
        assert [q["review"] for q in s.state()["queries"]] == ["draft", None]
        assert s.mark_reviewed(s.revision, 2) == s.revision  # not a draft: nothing to write
        with pytest.raises(InputError, match="query"):
            s.mark_reviewed(s.revision, 7)
        rev = s.mark_reviewed(s.revision, 1)
        back = load_annotations(path)
        assert back.draft_queries() == [] and rev == s.revision
        assert back.made_by == {(1, 1): "drawn"} and "made_by" not in back.info
        assert '"made_by": "drawn"' in path.read_text() and '"review"' not in path.read_text()
    finally:
        s.close()


@pytest.mark.parametrize("annotator, review", [("scripted", "draft"), ("human", None), ("simulated", None)])
def test_a_scripted_sessions_new_queries_are_drafts(scene, tmp_path, annotator, review):
    path = tmp_path / f"{annotator}.json"
    s = AnnotationSession(scene, path, config=SessionConfig(annotator=annotator))
    try:
        s.add_query(s.revision, "blob")
    finally:
        s.close()
    assert [q.review for q in load_annotations(path).queries] == [review]


def test_review_lists_unannotated_runs_and_area_jumps():
    frames = [AnnotatedFrame(id=k + 1, name=f"f{k}", time_index=k, width=W, height=H) for k in range(6)]
    aset = AnnotationSet(scene="s", frames=frames, queries=[Query(id=1, text="blob")], num_time_steps=6)
    for k, mask in ((0, _mask()), (1, _mask()), (4, _mask(10, 90))):
        aset.set_mask(1, k + 1, mask)
    tool = [(k, f"f{k}", k, "test") for k in range(6)]
    found = review(aset, tool)
    gaps = [f for f in found if f["kind"] == "not-annotated"]
    assert [(f["frame"], f["message"].split(" (")[0]) for f in gaps] == [(2, "2 frame(s)"), (5, "1 frame(s)")]
    jumps = [f for f in found if f["kind"] == "area-jump"]
    assert [f["frame"] for f in jumps] == [4]
