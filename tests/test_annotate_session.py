"""The annotation tool's session (no HTTP): saving, revisions, lock, intervals, review, propagation,
import and export."""

from __future__ import annotations

import base64
import io
import json
import zipfile

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from annotations.format import load_annotations
from benchmark.core.annotation import decode_mask
from annotations.propagate import iou
from annotations.tool import exchange
from annotations.tool.session import (AnnotationSession, Conflict, Locked, SessionConfig, mask_to_runs,
                                      runs_to_mask)
from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene
from benchmark.core.errors import InputError
from benchmark.loaders import load_scene

W, H = 192, 112


@pytest.fixture(scope="module")
def seq():
    return rigid_sequence(8, W, H, seed=4, travel_frac=0.2, radius_frac=0.22)


@pytest.fixture(scope="module")
def scene(seq, tmp_path_factory):
    return load_scene(write_dnerf_scene(seq, tmp_path_factory.mktemp("scene") / "blob"))


@pytest.fixture
def session(scene, tmp_path):
    s = AnnotationSession(scene, tmp_path / "ann" / "blob.json")
    yield s
    s.close()


def runs(mask):
    return {"counts": mask_to_runs(mask)}


def with_query(session, text="blob"):
    qid, _ = session.add_query(session.revision, text)
    return qid


# -- the page's RLE -----------------------------------------------------------------------------
@settings(max_examples=40, deadline=None)
@given(st.integers(1, 9), st.integers(1, 9), st.data())
def test_runs_round_trip_and_match_coco(h, w, data):
    bits = data.draw(st.lists(st.booleans(), min_size=h * w, max_size=h * w))
    mask = np.array(bits, bool).reshape(h, w)
    counts = mask_to_runs(mask)
    assert counts[0] >= 0 and sum(counts) == h * w
    assert np.array_equal(runs_to_mask(counts, h, w), mask)
    assert np.array_equal(decode_mask({"size": [h, w], "counts": counts}), mask)  # COCO's own reading


def test_runs_are_validated():
    with pytest.raises(InputError, match="counts"):
        runs_to_mask([3, 2], 2, 2)
    with pytest.raises(InputError, match="counts"):
        runs_to_mask([5, -1], 2, 2)
    with pytest.raises(InputError, match="counts"):
        runs_to_mask("abc", 2, 2)


# -- saving, revisions, lock --------------------------------------------------------------------
def test_edits_are_saved_at_once_with_a_new_revision(session, seq):
    qid = with_query(session)
    rev = session.revision
    new = session.apply(rev, [
        {"type": "mask", "query": qid, "frame": 0, "mask": runs(seq.masks[0])},
        {"type": "mask", "query": qid, "frame": 3, "mask": {"absent": True}},
    ], timing={"0": 12.5})
    assert new == rev + 1
    back = load_annotations(session.path)
    assert back.info["revision"] == new and back.info["annotator"] == "human"
    assert back.info["annotation_seconds"] == {"train_r_000": 12.5}
    assert np.array_equal(back.get_mask(qid, back.frame("train_r_000").id), seq.masks[0])
    absent = back.get_mask(qid, back.frame("train_r_003").id)
    assert absent is not None and not absent.any()
    # back to "not annotated"
    session.apply(new, [{"type": "mask", "query": qid, "frame": 3, "mask": None}])
    back = load_annotations(session.path)
    assert back.get_mask(qid, back.frame("train_r_003").id) is None


def test_stale_revision_is_refused_and_changes_nothing(session, seq):
    qid = with_query(session)
    rev = session.revision
    session.apply(rev, [{"type": "mask", "query": qid, "frame": 0, "mask": runs(seq.masks[0])}])
    before = session.path.read_bytes()
    with pytest.raises(Conflict) as err:
        session.apply(rev, [{"type": "mask", "query": qid, "frame": 0, "mask": {"absent": True}}])
    assert err.value.current == rev + 1
    assert session.path.read_bytes() == before


def test_bad_batches_are_refused_whole(session, seq):
    qid = with_query(session)
    rev = session.revision
    good = {"type": "mask", "query": qid, "frame": 0, "mask": runs(seq.masks[0])}
    for bad in ({"type": "mask", "query": qid, "frame": 99, "mask": None},
                {"type": "mask", "query": 777, "frame": 0, "mask": None},
                {"type": "mask", "query": qid, "frame": 0, "mask": {"counts": [1, 2]}},
                {"type": "intervals", "query": qid, "intervals": [[0, 2]]},
                {"type": "paint"}):
        with pytest.raises(InputError):
            session.apply(rev, [good, bad])
        assert session.revision == rev
    assert session.mask(qid, 0) is None


def test_lock_file_keeps_a_second_session_out(scene, tmp_path):
    path = tmp_path / "a.json"
    first = AnnotationSession(scene, path)
    try:
        with pytest.raises(Locked, match="another session"):
            AnnotationSession(scene, path)
    finally:
        first.close()
    second = AnnotationSession(scene, path)  # released: opens
    second.close()


def test_reopening_continues_the_revision(scene, tmp_path, seq):
    path = tmp_path / "a.json"
    s = AnnotationSession(scene, path, config=SessionConfig(annotator="scripted", method="unit test",
                                                             record_timing=False))
    qid = with_query(s)
    s.apply(s.revision, [{"type": "mask", "query": qid, "frame": 1, "mask": runs(seq.masks[1])}], timing={"1": 3.0})
    rev = s.revision
    s.close()
    s = AnnotationSession(scene, path)
    try:
        assert s.revision == rev
        assert np.array_equal(s.mask(qid, 1), seq.masks[1])
        s.apply(s.revision, [{"type": "mask", "query": qid, "frame": 2, "mask": {"absent": True}}])
        info = load_annotations(path).info
        assert info["annotator"] == "scripted" and info["method"] == "unit test"
        assert info["annotators"] == ["scripted", "human"]  # a person edited the scripted file after
        assert "annotation_seconds" not in info
    finally:
        s.close()


# -- queries and intervals ----------------------------------------------------------------------
def test_time_sensitive_queries_use_their_base_masks_and_own_intervals(session, seq):
    base = with_query(session)
    sid, rev = session.add_query(session.revision, "blob moving right", "sensitive", base)
    rev = session.apply(rev, [
        {"type": "mask", "query": sid, "frame": 2, "mask": runs(seq.masks[2])},  # written to the base
        {"type": "intervals", "query": sid, "intervals": [[5, 7], [0, 2], [3, 4]]},
    ])
    back = load_annotations(session.path)
    assert back.query(sid).intervals == [(0, 7)]
    assert np.array_equal(back.get_mask(base, back.frame("train_r_002").id), seq.masks[2])
    with pytest.raises(InputError, match="outside"):
        session.apply(rev, [{"type": "intervals", "query": sid, "intervals": [[0, 8]]}])
    with pytest.raises(InputError, match="base"):
        session.delete_query(session.revision, base)
    with pytest.raises(InputError, match="exists"):
        session.add_query(session.revision, "blob")
    session.delete_query(session.revision, sid)
    session.delete_query(session.revision, base)
    assert load_annotations(session.path).queries == []


def test_review_flags_what_a_reviewer_should_look_at(session, seq):
    base = with_query(session)
    sid, rev = session.add_query(session.revision, "blob early", "sensitive", base)
    tiny = np.zeros((H, W), bool)
    tiny[5:8, 5:8] = True
    pieces = np.zeros((H, W), bool)
    for k in range(5):
        pieces[10:20, 10 + 20 * k:15 + 20 * k] = True
    session.apply(rev, [
        {"type": "mask", "query": base, "frame": 0, "mask": runs(seq.masks[0])},
        {"type": "mask", "query": base, "frame": 1, "mask": runs(tiny)},
        {"type": "mask", "query": base, "frame": 2, "mask": {"absent": True}},
        {"type": "mask", "query": base, "frame": 3, "mask": runs(pieces)},
        {"type": "mask", "query": base, "frame": 5, "mask": runs(seq.masks[5])},
        {"type": "intervals", "query": sid, "intervals": [[0, 2], [4, 4]]},
    ])
    found = {(f["kind"], f["frame"]) for f in session.review()}
    assert ("tiny", 1) in found
    assert ("empty", 2) in found
    assert ("absent-in-interval", 2) in found
    assert ("fragmented", 3) in found
    assert ("mask-outside-interval", 3) in found or ("mask-outside-interval", 5) in found
    assert ("no-mask-in-interval", 4) in found
    assert not any(k == "tiny" and f == 0 for k, f in found)


# -- assistance ---------------------------------------------------------------------------------
def test_segment_and_propagate_through_the_session(session, seq):
    qid = with_query(session)
    out = session.segment(0, list(map(float, seq.boxes[0])), [], None)
    mask = runs_to_mask(out["counts"], H, W)
    assert iou(mask, seq.masks[0]) > 0.85
    rev = session.apply(session.revision, [{"type": "mask", "query": qid, "frame": 0, "mask": runs(seq.masks[0])}])
    res = session.propagate(qid, 0, 1, 3)
    assert [p["frame"] for p in res["proposals"]] == [1, 2, 3]
    for p in res["proposals"]:
        assert iou(runs_to_mask(p["counts"], H, W), seq.masks[p["frame"]]) > 0.85
    # a keyframe ahead: the frames between are filled from both ends
    session.apply(rev, [{"type": "mask", "query": qid, "frame": 4, "mask": runs(seq.masks[4])}])
    res = session.propagate(qid, 0, 1, 10)
    assert [p["frame"] for p in res["proposals"]] == [1, 2, 3]
    assert {p["method"] for p in res["proposals"]} == {"between"}
    back = session.propagate(qid, 4, -1, 10)  # stops at frame 0, annotated
    assert [p["frame"] for p in back["proposals"]] == [3, 2, 1]
    with pytest.raises(InputError, match="no mask"):
        session.propagate(qid, 6, 1, 2)


# -- import / export ----------------------------------------------------------------------------
def _annotated(session, seq):
    base = with_query(session)
    sid, rev = session.add_query(session.revision, "blob late", "sensitive", base)
    session.apply(rev, [
        {"type": "mask", "query": base, "frame": 0, "mask": runs(seq.masks[0])},
        {"type": "mask", "query": base, "frame": 4, "mask": runs(seq.masks[4])},
        {"type": "mask", "query": base, "frame": 6, "mask": {"absent": True}},
        {"type": "intervals", "query": sid, "intervals": [[4, 5]]},
    ])
    return load_annotations(session.path)


@pytest.mark.parametrize("fmt", ["project", "coco-rle", "release"])
def test_export_then_import_gives_identical_masks_and_intervals(session, seq, fmt):
    original = _annotated(session, seq)
    out = session.export(fmt)
    files = [session.root / f for f in out["files"]]
    assert files and all(f.is_file() for f in files)
    assert not list((session.root / "exports").glob(".*"))  # no temporary left behind
    if fmt == "release":
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as zf:
            for f in files:
                zf.write(f, f"annotations/{f.relative_to(session.root / 'exports' / 'blob.release')}")
        data, name = buf.getvalue(), "release.zip"
    else:
        data, name = files[0].read_bytes(), files[0].name
    # wipe the working set, then import the export
    session.apply(session.revision, [{"type": "mask", "query": q.id, "frame": i, "mask": None}
                                     for q in original.agnostic_queries for i in range(len(session.frames))])
    res = session.import_data(session.revision, fmt, name, base64.b64encode(data).decode())
    assert res["backup"] and (session.root / res["backup"]).is_file()
    back = load_annotations(session.path)
    assert exchange.same_content(original, back) is None
    assert back.info["imported"][-1]["format"] == fmt


def test_failed_export_check_keeps_the_previous_export(session, seq, monkeypatch):
    _annotated(session, seq)
    first = session.root / session.export("coco-rle")["files"][0]
    before = first.read_bytes()
    session.apply(session.revision, [{"type": "mask", "query": 1, "frame": 0, "mask": {"absent": True}}])

    def broken(path, aset):
        raise InputError(path, None, "export check failed: simulated")

    monkeypatch.setattr(exchange, "_check_coco_file", broken)
    with pytest.raises(InputError, match="simulated"):
        session.export("coco-rle")
    assert first.read_bytes() == before
    assert not list(first.parent.glob(".*"))


def test_video_annotations_import_merges_intervals(session, seq):
    _annotated(session, seq)
    doc = {"blob": {"blob late": [[5, 7], [1, 2], [3, 3]], "blob early": [[0, 0]]}}
    session.import_data(session.revision, "video-annotations", "video_annotations.json",
                        base64.b64encode(json.dumps(doc).encode()).decode())
    back = load_annotations(session.path)
    assert back.query("blob late").intervals == [(1, 3), (5, 7)]
    assert back.query("blob early").intervals == [(0, 0)] and back.query("blob early").base == back.query("blob").id
    with pytest.raises(InputError, match="not a time-agnostic"):
        session.import_data(session.revision, "video-annotations", "v.json",
                            base64.b64encode(json.dumps({"nothing": {"x": [[0, 1]]}}).encode()).decode())


@pytest.mark.parametrize("name", ["\x1b[2J\x9b31m.json", "a\rb.json", "\u202ename.json"])
def test_an_import_whose_file_name_holds_control_characters_is_refused_before_anything_changes(session, seq, name):
    _annotated(session, seq)
    before = session.path.read_bytes()
    doc = {"blob": {"blob late": [[5, 7]]}}
    with pytest.raises(InputError, match="filename"):
        session.import_data(session.revision, "video-annotations", name,
                            base64.b64encode(json.dumps(doc).encode()).decode())
    assert session.path.read_bytes() == before


def _zip(entries):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in entries:
            zf.writestr(name, data)
    return base64.b64encode(buf.getvalue()).decode()


def test_archives_with_escaping_paths_or_too_much_data_are_refused(scene, tmp_path):
    s = AnnotationSession(scene, tmp_path / "a.json", config=SessionConfig(max_unpacked_bytes=1000))
    try:
        for bad in ("../evil/_annotations.coco.json", "/abs/_annotations.coco.json"):
            with pytest.raises(InputError, match="escapes"):
                s.import_data(s.revision, "release", "x.zip", _zip([(bad, "{}")]))
        with pytest.raises(InputError, match="unpack"):
            s.import_data(s.revision, "release", "x.zip", _zip([("train/_annotations.coco.json", " " * 5000)]))
        with pytest.raises(InputError, match="zip"):
            s.import_data(s.revision, "release", "x.zip", base64.b64encode(b"PK\x03\x04broken").decode())
        assert s.revision == 0 and not s.path.exists()
    finally:
        s.close()
