"""The strict input layer, one test per class of defect: sizes before allocation (a compressed-RLE string
longer than its mask can need), polygons through one checked path (an import that would crash
pycocotools), typed provenance fields, bounded revisions, canonical keys (no duplicates, no case,
whitespace or Unicode-digit variants) and names that are not paths.

A document that could take the process down is parsed in a child process under a memory cap
(``RLIMIT_AS``), so that the old behaviour fails the test instead of the test run.
"""

from __future__ import annotations

import base64
import gzip
import json
import os
import resource
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from annotations.format import annotation_set_from_dict, load_annotations, save_annotations
from benchmark.cli import main
from benchmark.core.annotation import AnnotatedFrame, AnnotationSet, Query, encode_mask
from benchmark.core.errors import InputError
from benchmark.predictions import QueryPrediction, ScenePredictions, read_predictions, write_predictions

ROOT = Path(__file__).resolve().parents[1]
MEMORY_CAP = 1 << 30
"""Address space of a child that parses one hostile document (bench4d's imports need about 0.5 GiB)."""
H, W = 4, 5


def _gt_and_preds(tmp_path: Path, *, text: str = "cookie", scene: str = "kitchen") -> tuple[Path, Path]:
    mask = np.zeros((H, W), bool)
    mask[:2, :2] = True
    aset = AnnotationSet(scene=scene, frames=[AnnotatedFrame(id=10 + t, name=f"f{t}", time_index=t, width=W,
                                                             height=H) for t in range(2)],
                         num_time_steps=2, queries=[Query(1, text)])
    for t in range(2):
        aset.set_mask(1, 10 + t, mask)
    gt = Path(save_annotations(aset, tmp_path / "gt.json"))
    preds = ScenePredictions(scene=scene, method="oracle")
    preds.add(QueryPrediction(text, kind="agnostic", masks={f"f{t}": mask for t in range(2)}))
    write_predictions(tmp_path / "pred", preds)
    return gt, tmp_path / "pred"


def run_capped(code: str, cap: int = MEMORY_CAP, timeout: float = 120.0) -> subprocess.CompletedProcess:
    """``code`` in a child Python with its address space capped at ``cap`` bytes."""
    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))

    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          timeout=timeout, preexec_fn=limit, env=env, cwd=str(ROOT))


def one_error_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr[-2000:]
    return lines[0]


# -- 1. a compressed-RLE string far longer than its mask can need ------------------------------------------
def test_an_rle_string_longer_than_its_mask_needs_is_refused_before_decoding(tmp_path):
    """A frame of H x W pixels never needs more than about 6 (H W + 1) characters of compressed RLE: a
    longer string is refused from its length, before any array as long as the string is built. 40 MB of
    zeros (40 kB gzip-compressed) must not take a child capped at 1 GiB down."""
    gt, pred = _gt_and_preds(tmp_path)
    doc = json.loads((pred / "predictions.json").read_text())
    doc["queries"]["cookie"]["masks"]["f0"]["counts"] = "0" * 40_000_000
    (pred / "predictions.json").unlink()
    (pred / "predictions.json.gz").write_bytes(gzip.compress(json.dumps(doc).encode(), 1))
    before = (pred / "predictions.json.gz").read_bytes()
    proc = run_capped(f"""
        import sys
        from benchmark.cli import main
        sys.exit(main(["score", "--gt", {str(gt)!r}, "--pred", {str(pred)!r}, "--quiet"]))
    """)
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    line = one_error_line(proc.stderr)
    assert "counts" in line and "f0" in line
    assert (pred / "predictions.json.gz").read_bytes() == before


def test_the_rle_length_bound_keeps_every_valid_mask():
    """The bound is no tighter than the worst valid mask: a checkerboard, whose every pixel is a run."""
    from benchmark.core.annotation import decode_mask

    for h, w in ((1, 1), (3, 7), (16, 16), (33, 65)):
        board = (np.indices((h, w)).sum(0) % 2).astype(bool)
        for mask in (board, ~board, np.ones((h, w), bool), np.zeros((h, w), bool)):
            assert np.array_equal(decode_mask(encode_mask(mask), size=(h, w)), mask)


# -- 2. polygons of a COCO import, through one checked path ------------------------------------------------
def _coco_import(tmp_path: Path, polygon: list, *, width: object = W, height: object = H) -> subprocess.CompletedProcess:
    """The annotation tool's COCO import of one polygon, in a capped child (old code: pycocotools
    crashes on a NaN vertex and grows without bound on a far one)."""
    doc = {"images": [{"id": 1, "file_name": "f0.png", "width": width, "height": height}],
           "categories": [{"id": 1, "name": "cookie"}],
           "annotations": [{"id": 1, "image_id": 1, "category_id": 1, "segmentation": [polygon]}]}
    data = json.dumps(doc, allow_nan=True).encode()
    return run_capped(f"""
        import base64, sys
        from types import SimpleNamespace
        from annotations.tool.exchange import import_set
        from annotations.tool.session import SessionConfig
        from benchmark.core.annotation import AnnotationSet
        from benchmark.core.errors import InputError
        cam = SimpleNamespace(width={W}, height={H})
        frames = [SimpleNamespace(name="f0", time_index=0, camera=cam, camera_id="0", split="test")]
        scene = SimpleNamespace(name="kitchen", dataset="dnerf", frames=frames)
        current = AnnotationSet(scene="kitchen", num_time_steps=1)
        data = base64.b64decode({base64.b64encode(data).decode()!r})
        try:
            out = import_set("coco-rle", "up.json", data, scene, current, SessionConfig())
        except InputError as err:
            print("InputError:", err)
            sys.exit(2)
        print("imported", len(out.masks))
    """, timeout=60)


@pytest.mark.parametrize("polygon", [[0, 0, 4, 0, float("nan"), 3], [0, 0, 4e8, 0, 4, 3], [0, 0, 4, 0, 4, -4e8],
                                     [0, 0, float("inf"), 0, 4, 3], [0, 0, 1e300, 1e300, 4, 3]],
                         ids=["nan", "4e8", "minus-4e8", "inf", "1e300"])
def test_a_coco_import_with_a_hostile_vertex_is_an_input_error(tmp_path, polygon):
    proc = _coco_import(tmp_path, polygon)
    assert proc.returncode == 2 and proc.stdout.startswith("InputError:"), (proc.returncode, proc.stdout,
                                                                             proc.stderr[-1500:])
    assert "segmentation" in proc.stdout


@pytest.mark.parametrize("width,height", [(0, H), (W, 0), (-5, H), (W, 2.5), (True, H), (10 ** 12, H)])
def test_a_coco_import_with_a_bad_image_size_is_an_input_error(tmp_path, width, height):
    proc = _coco_import(tmp_path, [0, 0, 2, 0, 2, 2], width=width, height=height)
    assert proc.returncode == 2 and proc.stdout.startswith("InputError:"), (proc.returncode, proc.stdout,
                                                                             proc.stderr[-1500:])
    assert "images[0]" in proc.stdout


def test_a_sane_coco_polygon_still_imports(tmp_path):
    proc = _coco_import(tmp_path, [0, 0, 3, 0, 3, 2, 0, 2])
    assert proc.returncode == 0 and "imported 1" in proc.stdout, proc.stderr[-1500:]


# -- 3. provenance fields of the wrong type; revisions that are not counts ---------------------------------
def _doc(tmp_path: Path, **info) -> dict:
    gt, _ = _gt_and_preds(tmp_path)
    doc = json.loads(gt.read_text())
    doc["info"] = {**doc.get("info", {}), **info}
    return doc


@pytest.mark.parametrize("field,value", [("annotators", "alice"), ("annotators", 7), ("annotators", [1, 2]),
                                         ("annotation_seconds", [1, 2]), ("annotation_seconds", {"f0": "long"}),
                                         ("annotation_seconds", "x"), ("annotator", ["a"]),
                                         ("revision", "seven"), ("revision", -1), ("revision", 2.5),
                                         ("revision", True), ("revision", 2 ** 80), ("imported", "x")])
def test_provenance_fields_of_the_wrong_type_are_refused_naming_the_field(tmp_path, field, value):
    with pytest.raises(InputError, match=rf"info\.{field}"):
        annotation_set_from_dict(_doc(tmp_path, **{field: value}), "gt.json")


@pytest.mark.parametrize("token", ["Infinity", "-Infinity", "NaN"])
def test_a_non_finite_revision_is_refused(tmp_path, token):
    text = json.dumps(_doc(tmp_path)).replace('"info": {', f'"info": {{"revision": {token}, ', 1)
    path = tmp_path / "nonfinite.json"
    path.write_text(text)
    with pytest.raises(InputError) as err:
        load_annotations(path)
    assert str(path) in str(err.value)


def test_annotate_with_a_bad_revision_or_annotators_fails_in_one_line(tmp_path):
    """Old: ``int("seven")`` and ``int(inf)`` were tracebacks at start, and ``info.annotators`` as text made
    every save an HTTP 500."""
    from annotations.tool.session import AnnotationSession
    from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene
    from benchmark.loaders import load_scene

    scene = load_scene(write_dnerf_scene(rigid_sequence(2, 32, 24, seed=3), tmp_path / "scene"))
    base = AnnotationSet(scene=scene.name, num_time_steps=2, queries=[Query(1, "ball")])
    for info in ({"revision": "seven"}, {"annotators": "alice"}, {"annotation_seconds": [1]}):
        path = tmp_path / "a.json"
        doc = json.loads(Path(save_annotations(base, tmp_path / "base.json", overwrite=True)).read_text())
        doc["info"] = info
        path.write_text(json.dumps(doc))
        with pytest.raises(InputError, match=r"info\."):
            AnnotationSession(scene, path).close()
    path.write_text(json.dumps(doc).replace('"info": {', '"info": {"revision": Infinity, ', 1))
    with pytest.raises(InputError):
        AnnotationSession(scene, path).close()


# -- 4. canonical keys ----------------------------------------------------------------------------------
def _sensitive_doc(tmp_path: Path) -> dict:
    aset = AnnotationSet(scene="kitchen", frames=[AnnotatedFrame(id=1, name="f0", time_index=0, width=W, height=H)],
                         num_time_steps=20, queries=[Query(1, "cookie"), Query(9, "cracked cookie", "sensitive",
                                                                                  base=1, intervals=[(2, 3)])])
    aset.set_mask(1, 1, np.ones((H, W), bool))
    return json.loads(Path(save_annotations(aset, tmp_path / "s.json", overwrite=True)).read_text())


@pytest.mark.parametrize("key", ["\u0669", " 9 ", "0_9", "+9", "09", "9 ", "\uff19", "9.0", "-0"])
def test_time_segment_keys_must_be_canonical_ids(tmp_path, key):
    doc = _sensitive_doc(tmp_path)
    doc["time_segments"] = {key: [[5, 6]]}
    with pytest.raises(InputError, match="time_segments"):
        annotation_set_from_dict(doc, "s.json")
    doc["time_segments"] = {"9": [[5, 6]]}
    assert annotation_set_from_dict(doc, "s.json").query(9).intervals == [(5, 6)]


def test_a_repeated_json_key_is_refused_in_every_document(tmp_path, capsys):
    gt, pred = _gt_and_preds(tmp_path)
    text = (pred / "predictions.json").read_text()
    # the query's entry given twice: the second (with no masks) used to win without a word
    dup = text.replace('"queries": {', '"queries": {"cookie": {"kind": "agnostic", "masks": {}}, ', 1)
    assert dup.count('"cookie"') == 2
    (pred / "predictions.json").write_text(dup)
    assert main(["score", "--gt", str(gt), "--pred", str(pred), "--quiet"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "cookie" in line and ("twice" in line or "duplicate" in line.lower()), line
    # an annotation file too
    gtext = gt.read_text().replace('"scene": "kitchen"', '"scene": "kitchen", "scene": "other"', 1)
    gt.write_text(gtext)
    with pytest.raises(InputError, match="scene"):
        load_annotations(gt)


@pytest.mark.parametrize("variant", ["Masks", "masks ", "MASKS", "\uff4dasks"])
def test_a_key_that_varies_a_known_key_is_refused(tmp_path, capsys, variant):
    """``Box`` beside ``box``: a key the schema knows, in another case, with spaces or in other Unicode
    forms, is refused instead of silently ignored."""
    gt, pred = _gt_and_preds(tmp_path)
    doc = json.loads((pred / "predictions.json").read_text())
    entry = doc["queries"]["cookie"]
    entry[variant] = {"f0": entry["masks"]["f0"]}
    (pred / "predictions.json").write_text(json.dumps(doc))
    assert main(["score", "--gt", str(gt), "--pred", str(pred), "--quiet"]) == 2
    line = one_error_line(capsys.readouterr().err)
    assert "masks" in line


def test_query_texts_that_differ_only_in_case_or_spaces_are_refused(tmp_path):
    doc = _sensitive_doc(tmp_path)
    doc["categories"].append({"id": 5, "name": "Cookie", "kind": "agnostic"})
    with pytest.raises(InputError, match="categories"):
        annotation_set_from_dict(doc, "s.json")
    doc["categories"][-1]["name"] = " cookie"
    with pytest.raises(InputError, match="categories"):
        annotation_set_from_dict(doc, "s.json")


def test_prediction_queries_that_differ_only_in_case_are_refused(tmp_path, capsys):
    gt, pred = _gt_and_preds(tmp_path)
    doc = json.loads((pred / "predictions.json").read_text())
    doc["queries"]["Cookie"] = doc["queries"]["cookie"]
    (pred / "predictions.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="Cookie"):
        read_predictions(pred)


# -- 5. names that are not paths ---------------------------------------------------------------------------
@pytest.mark.parametrize("scene", ["../victim", "a/b", "..", ".", "", "x\x00y", "/abs", "a\\b", "bad\x1b[2J"])
def test_a_scene_name_is_never_a_path(tmp_path, capsys, scene):
    """``score`` with several ``--gt`` and one folder of ``<scene>/`` predictions joins the scene name to the
    folder: a name that climbs out of it was read as a path."""
    gt, pred = _gt_and_preds(tmp_path)
    shutil.copytree(pred, tmp_path / "preds" / "kitchen")
    shutil.copytree(pred, tmp_path / "victim")  # old: "../victim" was read from here, outside --pred
    victim = json.loads((tmp_path / "victim" / "predictions.json").read_text())
    del victim["scene"]  # optional: predictions that do not name their scene
    (tmp_path / "victim" / "predictions.json").write_text(json.dumps(victim))
    doc = json.loads(gt.read_text())
    doc["scene"] = scene
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(doc))
    rc = main(["score", "--gt", str(gt), "--gt", str(bad), "--pred", str(tmp_path / "preds"), "--quiet"])
    assert rc == 2
    line = one_error_line(capsys.readouterr().err)
    assert "scene" in line


# -- 6. a query text with control characters is refused by the server and escaped on the terminal ---------
def test_the_server_refuses_control_characters_and_case_variants_in_query_texts(tmp_path):
    from annotations.tool.session import AnnotationSession
    from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene
    from benchmark.loaders import load_scene

    scene = load_scene(write_dnerf_scene(rigid_sequence(2, 32, 24, seed=3), tmp_path / "scene"))
    session = AnnotationSession(scene, tmp_path / "a.json")
    try:
        session.add_query(0, "ball")
        for text in ("Ball", " BALL", "ball\u200b", "\uff42all", "cup\x1b[2J", "cup\rplate", "cup\u202e"):
            with pytest.raises(InputError, match="text"):
                session.add_query(session.revision, text)
        assert [q.text for q in session.aset.queries] == ["ball"]
    finally:
        session.close()


def test_score_prints_no_raw_control_character(tmp_path, capfd):
    """Texts from files reach the terminal escaped (or the file is refused): never an ESC or CR that
    clears the screen or overwrites a row."""
    gt, pred = _gt_and_preds(tmp_path, text="cupX", scene="kitchen")
    hostile = "cup\x1b[2J\rX"
    for path in (gt, pred / "predictions.json"):  # written as another program would write them
        path.write_text(path.read_text().replace('"cupX"', json.dumps(hostile)))
    rc = main(["score", "--gt", str(gt), "--pred", str(pred)])
    out, err = capfd.readouterr()
    assert rc in (0, 2)
    for stream in (out, err):
        assert "\x1b" not in stream and "\r" not in stream, repr(stream[-400:])
    if rc == 2:
        one_error_line(err)


def test_terminal_text_escapes_every_control_character():
    from benchmark.core.strict import terminal_text

    assert terminal_text("plain text, é 日本") == "plain text, é 日本"
    for ch in ["\x1b", "\r", "\x07", "\x00", "\x7f", "\x9b", "\u202e", "\u2066", "\n", "\t"]:
        escaped = terminal_text(f"a{ch}b")
        assert ch not in escaped and escaped.startswith("a") and escaped.endswith("b"), repr(escaped)


@pytest.mark.parametrize("text", ['{"a": "\\ud800"}', '{"a": ["x", "y\\udfffz"]}', '{"\\udc00": 1}',
                                  '["\\ud83d"]', '{"a": "\\ude00\\ud83d"}'])
def test_a_lone_surrogate_is_refused_by_the_strict_reader_and_a_pair_is_one_character(text):
    from benchmark.core.strict import loads

    with pytest.raises(InputError, match="lone surrogate"):
        loads(text, "f.json")
    assert loads('{"a": "cup \\ud83d\\ude00"}', "f.json") == {"a": "cup \U0001F600"}


def test_a_query_level_with_a_control_character_is_refused_in_an_annotation_file(tmp_path):
    from annotations.format import FORMAT_NAME, FORMAT_VERSION, annotation_set_from_dict

    doc = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "scene": "s", "num_time_steps": 2, "images": [],
           "categories": [{"id": 1, "name": "cup", "level": "whole"}], "annotations": []}
    assert annotation_set_from_dict(doc, file="a.json").queries[0].level == "whole"
    doc["categories"][0]["level"] = "whole\u001b[2J"
    with pytest.raises(InputError, match="level"):
        annotation_set_from_dict(doc, file="a.json")
