"""Every parser of annotation and prediction data under hostile and faulty input.

Property: any mutation of a valid file (values swapped for hostile ones, keys deleted, lists grown,
bytes flipped or cut, PNG headers rewritten) gives either a valid object or an
:class:`~benchmark.core.errors.InputError` naming the file in one line: never another exception, never a
crash, and never an allocation beyond a fixed multiple of the frame size the file declares
(measured with ``tracemalloc``). Then one targeted test per class of fault: RLE run lengths that
wrap around, sizes checked before decoding, mask PNG formats, non-finite and huge numbers, and
malformed JSON.
"""

from __future__ import annotations

import contextlib
import copy
import gzip
import io
import json
import math
import struct
import tempfile
import tracemalloc
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from PIL import Image

from annotations.davis import import_davis
from annotations.format import annotation_set_to_dict, load_annotations, save_annotations
from benchmark.core.annotation import (MAX_MASK_PIXELS, AnnotatedFrame, AnnotationSet, Query, decode_mask, encode_mask,
                               rle_runs, runs_to_string, string_to_runs)
from annotations.release import ReleaseImportOptions, export_release, import_release
from benchmark.core.atomic import read_json, write_json
from benchmark.core.errors import InputError
from benchmark.core.imageio import read_mask
from benchmark.metrics import score_scene
from benchmark.predictions import QueryPrediction, ScenePredictions, read_predictions, write_predictions

FUZZ = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
H, W = 6, 8

# -- hostile values ---------------------------------------------------------------------------------
HOSTILE = [None, True, False, 0, -1, 1, 3, 2 ** 31, 2 ** 63, 2 ** 64 + 7, -(2 ** 63) - 1, 10 ** 30, 60000,
           0.5, -0.0, 1e308, 1.7e308, -1.7e308, math.nan, math.inf, -math.inf, "", "x", "\x00", "é", "0`", "~~~",
           "../x", "a/b", [], {}, [0], [1, 2], [60000, 60000], [H, W], [W, H], {"a": 1}, [[[[]]]],
           {"size": [H, W], "counts": [H * W]}, [2 ** 62] * 4 + [2 ** 62 + H * W]]
DEEP = "__deep__"  # replaced in the JSON text by lists nested far deeper than any parser accepts


def overflow_runs(pixels: int) -> list[int]:
    """Non-negative runs whose int64 sum wraps around to exactly ``pixels``."""
    return [2 ** 62] * 4 + [pixels]


def wrapping_string(pixels: int) -> str:
    """A compressed RLE string whose runs (2**59 each, 12-character numbers) wrap an int64 sum
    around to exactly ``pixels``."""
    return runs_to_string([0] + [2 ** 59] * 32 + [pixels])


def _paths(node, prefix=()):
    """Every (container, key) in a JSON tree."""
    out = []
    if isinstance(node, dict):
        for k, v in node.items():
            out.append((node, k))
            out += _paths(v)
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out.append((node, i))
            out += _paths(v)
    return out


def mutate_doc(doc, data) -> None:
    """One to three structural mutations of a parsed JSON document, in place."""
    for _ in range(data.draw(st.integers(1, 3), label="mutations")):
        paths = _paths(doc)
        if not paths:
            return
        container, key = data.draw(st.sampled_from(paths), label="where")
        value = container[key]
        op = data.draw(st.sampled_from(["replace", "replace", "delete", "tweak", "grow", "wrap", "rle"]), label="op")
        if op == "replace":
            container[key] = copy.deepcopy(data.draw(st.sampled_from(HOSTILE + [DEEP]), label="value"))
        elif op == "delete":
            del container[key]
        elif op == "tweak" and isinstance(value, int) and not isinstance(value, bool):
            container[key] = data.draw(st.sampled_from([value + 1, value - 1, -value, value * 2 ** 40, 0]))
        elif op == "grow" and isinstance(value, list):
            value.extend(copy.deepcopy(value[:2]) or [0])
        elif op == "wrap":
            container[key] = data.draw(st.sampled_from([[value], {"x": value}, str(value)[:20]]))
        elif op == "rle":
            pixels = H * W
            container[key] = data.draw(st.sampled_from([
                {"size": [H, W], "counts": overflow_runs(pixels)},
                {"size": [H, W], "counts": wrapping_string(pixels)},
                {"size": [60000, 60000], "counts": [60000 * 60000]},
                {"size": [H, W], "counts": [pixels, 0, -5, 5]},
                {"size": [H, W], "counts": "0" * 13},
                {"size": [H, W], "counts": [pixels + 0.0]},
            ]), label="rle")


def dump_text(doc) -> str:
    text = json.dumps(doc)  # NaN / Infinity tokens included: Python's reader accepts them
    return text.replace(json.dumps(DEEP), "[" * 3000 + "]" * 3000)


def mutate_bytes(raw: bytes, data) -> bytes:
    op = data.draw(st.sampled_from(["none", "none", "none", "cut", "flip", "insert", "nonutf8", "deep"]), label="bytes")
    if op == "none" or not raw:
        return raw
    pos = data.draw(st.integers(0, len(raw) - 1), label="pos")
    if op == "cut":
        return raw[:pos]
    if op == "flip":
        return raw[:pos] + bytes([raw[pos] ^ data.draw(st.integers(1, 255))]) + raw[pos + 1:]
    if op == "insert":
        return raw[:pos] + data.draw(st.binary(min_size=1, max_size=4)) + raw[pos:]
    if op == "nonutf8":
        return raw[:pos] + b"\xff\xfe" + raw[pos:]
    return b"[" * 100000 + b"]" * 100000


# -- the property ---------------------------------------------------------------------------------------
@contextlib.contextmanager
def bounded(pixels: int):
    """Fail if the block allocates more than a fixed multiple of ``pixels`` (plus 8 MB)."""
    tracemalloc.start()
    try:
        yield
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        limit = 8 * 2 ** 20 + 48 * pixels
        assert peak <= limit, f"allocated {peak} bytes for a frame of {pixels} pixels"


def valid_or_input_error(fn, pixels: int):
    """``fn()`` or ``None`` when it raised an InputError (one line, naming a file)."""
    try:
        with bounded(pixels):
            result = fn()
    except InputError as err:
        assert "\n" not in str(err), str(err)
        assert err.file, str(err)
        event("InputError")
        return None
    event("valid")
    return result


def declared_pixels(doc) -> int:
    """Largest width x height (within MAX_MASK_PIXELS) a COCO-shaped document declares."""
    best = H * W
    images = doc.get("images") if isinstance(doc, dict) else None
    for im in images if isinstance(images, list) else []:
        if isinstance(im, dict):
            w, h = im.get("width"), im.get("height")
            if all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (w, h)):
                if w * h <= MAX_MASK_PIXELS:
                    best = max(best, w * h)
    return best


def check_annotation_set(aset: AnnotationSet) -> None:
    """A valid result: every mask decodes at its frame's size, and it serialises by the file rules."""
    frames = {f.id: f for f in aset.frames}
    for (qid, fid), rle in aset.masks.items():
        f = frames[fid]
        assert decode_mask(rle, size=(f.height, f.width)).shape == (f.height, f.width)
    annotation_set_to_dict(aset)


# -- valid inputs -------------------------------------------------------------------------------------
def small_set() -> AnnotationSet:
    rng = np.random.default_rng(1)
    aset = AnnotationSet(scene="toy", num_time_steps=5, info={"annotator": "test"})
    aset.frames = [AnnotatedFrame(id=10 + k, name=f"{k + 1:06d}", time_index=k, width=W, height=H) for k in range(3)]
    aset.queries = [Query(1, "cup"), Query(2, "plate"), Query(3, "full cup", "sensitive", base=1, intervals=[(0, 1)])]
    for f in aset.frames:
        aset.set_mask(1, f.id, rng.random((H, W)) < 0.3)
        if f.id != 11:
            aset.set_mask(2, f.id, np.zeros((H, W), bool) if f.id == 12 else rng.random((H, W)) < 0.5)
    return aset


@pytest.fixture(scope="module")
def valid_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("valid")
    aset = small_set()
    ann = json.loads(Path(save_annotations(aset, root / "toy.json")).read_text())
    ann["annotations"][0]["segmentation"]["counts"] = rle_runs(ann["annotations"][0]["segmentation"])[2].tolist()
    next(a for a in ann["annotations"] if a["absent"]).pop("segmentation")  # "absent": true alone
    written = export_release(aset, root / "release", frame_base=1)
    coco = json.loads(written["coco"].read_text())
    coco["annotations"].append({"id": 99, "image_id": 10, "category_id": 2, "iscrowd": 1,
                                "segmentation": encode_mask(np.eye(H, W, dtype=bool))})
    video = json.loads(written["video"].read_text())
    preds = ScenePredictions(scene="toy", method="oracle")
    for q in aset.queries:
        frames = aset.annotated_frames(q.id)
        p = QueryPrediction(q.text, kind=q.kind, masks={f.name: aset.get_mask(q.id, f.id) for f in frames})
        if q.kind == "sensitive":
            p.scores = {f.name: float(q.holds_at(f.time_index)) for f in frames}
        preds.add(p)
    pred_json = json.loads(write_predictions(root / "pj", preds).read_text())
    pred_json["queries"]["cup"]["masks"]["000001"]["counts"] = rle_runs(
        pred_json["queries"]["cup"]["masks"]["000001"])[2].tolist()
    write_predictions(root / "pp", preds, layout="png")
    pngs = {p.relative_to(root / "pp").as_posix(): p.read_bytes() for p in (root / "pp" / "masks").rglob("*.png")}
    scores_png = json.loads((root / "pp" / "scores.json").read_text())
    davis = {}
    for t in range(2):
        arr = np.zeros((H, W), np.uint8)
        arr[1:3, 1:4] = 1
        arr[4:, 5:] = 2 if t else 0
        buf = io.BytesIO()
        Image.fromarray(arr, mode="P" if t else "L").save(buf, "PNG")
        davis[f"{t:05d}.png"] = buf.getvalue()
    return {"aset": aset, "ann": ann, "coco": coco, "video": video, "pred_json": pred_json, "pngs": pngs,
            "scores_png": scores_png, "davis": davis}


def write_mutated(path: Path, doc, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(mutate_bytes(dump_text(doc).encode("utf-8"), data))


# -- fuzz: annotation JSON ------------------------------------------------------------------------------
@FUZZ
@given(data=st.data())
def test_fuzz_annotation_json(valid_files, data):
    doc = copy.deepcopy(valid_files["ann"])
    mutate_doc(doc, data)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "toy.json"
        write_mutated(path, doc, data)
        aset = valid_or_input_error(lambda: load_annotations(path), declared_pixels(doc))
    if aset is not None:
        check_annotation_set(aset)


# -- fuzz: the release's Roboflow COCO and video_annotations.json ------------------------------------------
@FUZZ
@given(data=st.data(), which=st.sampled_from(["coco", "coco", "video"]))
def test_fuzz_release_import(valid_files, data, which):
    coco, video = copy.deepcopy(valid_files["coco"]), copy.deepcopy(valid_files["video"])
    mutate_doc(coco if which == "coco" else video, data)
    with tempfile.TemporaryDirectory() as tmp:
        cpath, vpath = Path(tmp) / "coco.json", Path(tmp) / "video.json"
        for path, doc, mutated in ((cpath, coco, which == "coco"), (vpath, video, which == "video")):
            if mutated:
                write_mutated(path, doc, data)
            else:
                path.write_text(json.dumps(doc))
        rasterizer = data.draw(st.sampled_from(["coco", "release_cv2"]))
        aset = valid_or_input_error(lambda: import_release(cpath, vpath, scene_name="toy", frame_base=1,
                                                           options=ReleaseImportOptions(rasterizer=rasterizer)),
                                    declared_pixels(coco))
    if aset is not None:
        check_annotation_set(aset)


# -- fuzz: DAVIS PNG folders ------------------------------------------------------------------------------
def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def png_bytes(width: int, height: int, colour: int = 0, depth: int = 8, rows: bytes | None = None) -> bytes:
    """A PNG with any header (CRC right) and ``rows`` (default: all zero) as its image data."""
    channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(colour, 1)
    if rows is None:
        rows = b"".join(b"\0" + b"\0" * (width * channels * depth // 8) for _ in range(height))
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    extra = _chunk(b"PLTE", b"\0\0\0" * 256) if colour == 3 else b""
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + extra + _chunk(b"IDAT", zlib.compress(rows))
            + _chunk(b"IEND", b""))


def mutate_png(raw: bytes, data) -> bytes:
    op = data.draw(st.sampled_from(["none", "header", "header", "cut", "flip", "jpeg", "empty", "text"]), label="png")
    if op == "none":
        return raw
    if op == "header":  # rewrite the IHDR (with a right CRC) so the decoder sees the new header
        width, height, depth, colour = struct.unpack(">IIBB", raw[16:26])
        width = data.draw(st.sampled_from([width, 0, 1, W + 1, 60000, 2 ** 31 - 1, 2 ** 32 - 1]), label="w")
        height = data.draw(st.sampled_from([height, 0, 1, H - 1, 60000, 2 ** 31 - 1]), label="h")
        depth = data.draw(st.sampled_from([depth, 1, 16, 3]), label="depth")
        colour = data.draw(st.sampled_from([colour, 0, 2, 3, 4, 6, 5]), label="colour")
        body = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
        return raw[:8] + _chunk(b"IHDR", body) + raw[33:]
    if op == "cut":
        return raw[:data.draw(st.integers(0, len(raw) - 1))]
    if op == "flip":
        pos = data.draw(st.integers(0, len(raw) - 1))
        return raw[:pos] + bytes([raw[pos] ^ 0x5A]) + raw[pos + 1:]
    if op == "jpeg":
        return cv2.imencode(".jpg", np.full((H, W), 3, np.uint8))[1].tobytes()
    if op == "empty":
        return b""
    return b"not an image at all"


def png_pixels(raw: bytes) -> int:
    if raw[:8] != b"\x89PNG\r\n\x1a\n" or len(raw) < 24:
        return H * W
    width, height = struct.unpack(">II", raw[16:24])
    return width * height if 0 < width * height <= MAX_MASK_PIXELS else H * W


@FUZZ
@given(data=st.data())
def test_fuzz_davis_folder(valid_files, data):
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        pixels = H * W
        target = data.draw(st.sampled_from(sorted(valid_files["davis"])), label="png")
        for name, raw in valid_files["davis"].items():
            raw = mutate_png(raw, data) if name == target else raw
            pixels = max(pixels, png_pixels(raw))
            (folder / name).write_bytes(raw)
        if data.draw(st.booleans(), label="folder named .png"):
            (folder / "00002.png").mkdir()
        aset = valid_or_input_error(lambda: import_davis(folder, {1: "cup", 2: "plate"}, scene_name="toy"), pixels)
    if aset is not None:
        check_annotation_set(aset)


# -- fuzz: predictions (JSON and PNG layouts) -------------------------------------------------------------------
def declared_mask_pixels(preds: ScenePredictions) -> int:
    """Largest size (within MAX_MASK_PIXELS) any mask of ``preds`` declares: RLE ``size`` or PNG header."""
    best = H * W
    for pred in preds.queries.values():
        for value in pred.masks.values():
            if isinstance(value, Path):
                best = max(best, png_pixels(value.read_bytes()[:24]) if value.is_file() else 0)
            elif isinstance(value, dict) and isinstance(value.get("size"), list) and len(value["size"]) == 2:
                h, w = value["size"]
                if all(isinstance(v, int) and v > 0 for v in (h, w)) and h * w <= MAX_MASK_PIXELS:
                    best = max(best, h * w)
    return best


def check_predictions(valid_files, preds: ScenePredictions) -> None:
    """Masks decode at the frame's size or raise InputError, allocating only for the frame;
    scoring gives numbers or InputError."""
    with bounded(H * W):
        for pred in preds.queries.values():
            for frame in pred.masks:
                try:
                    m = pred.mask(frame, (H, W))
                except InputError as err:
                    assert "\n" not in str(err)
                    continue
                assert m.shape == (H, W) and m.dtype == bool
            assert all(math.isnan(s) or abs(s) <= 1e30 for s in pred.scores.values())
    # score_scene asks for each mask without the frame's size, so it is bounded by what the masks
    # declare (each within MAX_MASK_PIXELS) until it passes the frame's size to QueryPrediction.mask
    try:
        with bounded(declared_mask_pixels(preds)):
            result = score_scene(valid_files["aset"], preds)
    except InputError as err:
        assert "\n" not in str(err)
        return
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "r.json"
        write_json(out, {"summary": result.summary()})
        json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"non-standard JSON token {c}"))


@FUZZ
@given(data=st.data())
def test_fuzz_prediction_json(valid_files, data):
    doc = copy.deepcopy(valid_files["pred_json"])
    mutate_doc(doc, data)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "predictions.json"
        write_mutated(path, doc, data)
        preds = valid_or_input_error(lambda: read_predictions(tmp), H * W)
    if preds is not None:
        check_predictions(valid_files, preds)


@FUZZ
@given(data=st.data())
def test_fuzz_prediction_png_folder(valid_files, data):
    scores = copy.deepcopy(valid_files["scores_png"])
    if data.draw(st.booleans(), label="mutate scores.json"):
        mutate_doc(scores, data)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        write_mutated(root / "scores.json", scores, data)
        names = sorted(valid_files["pngs"])
        target = data.draw(st.sampled_from(names), label="png")
        for name, raw in valid_files["pngs"].items():
            (root / name).parent.mkdir(parents=True, exist_ok=True)
            (root / name).write_bytes(mutate_png(raw, data) if name == target else raw)
        preds = valid_or_input_error(lambda: read_predictions(root), H * W)
        if preds is not None:
            check_predictions(valid_files, preds)


# =============================================================================================
# one targeted test per class of fault
# =============================================================================================
def _gt_file(tmp_path: Path) -> tuple[AnnotationSet, Path]:
    aset = small_set()
    return aset, save_annotations(aset, tmp_path / "gt.json")


def _pred_doc(tmp_path: Path) -> dict:
    aset = small_set()
    preds = ScenePredictions(scene="toy")
    for q in aset.queries:
        frames = aset.annotated_frames(q.id)
        p = QueryPrediction(q.text, masks={f.name: aset.get_mask(q.id, f.id) for f in frames})
        if q.kind == "sensitive":
            p.scores = {f.name: 1.0 for f in frames}
        preds.add(p)
    return json.loads(write_predictions(tmp_path / "pred", preds).read_text())


def _score_cli(gt: Path, pred: Path, capsys) -> str:
    """``bench4d score``: the one-line error it prints (exit code 2: an input error, no traceback)."""
    from benchmark.cli import main

    assert main(["score", "--gt", str(gt), "--pred", str(pred), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    return err


# -- 1. integer overflow in RLE run lengths -----------------------------------------------------------------
@pytest.mark.parametrize("counts", [overflow_runs(H * W), [H * W, 2 ** 63 - 1, 2 ** 63 - 1, 2],
                                    wrapping_string(H * W), "0" * 7 + "1"],
                         ids=["list-wraps-int64", "list-past-int64", "string-wraps-int64", "string-13-chars"])
def test_rle_runs_that_wrap_around_are_refused_everywhere(tmp_path, capsys, counts):
    rle = {"size": [H, W], "counts": counts}
    # ground truth
    aset, gt = _gt_file(tmp_path)
    doc = json.loads(gt.read_text())
    doc["annotations"][0]["segmentation"] = rle
    for key in ("area", "absent", "bbox"):
        doc["annotations"][0].pop(key)
    bad_gt = tmp_path / "bad_gt.json"
    bad_gt.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"annotations\[0\]\.segmentation\.counts"):
        load_annotations(bad_gt)
    assert "annotations[0].segmentation.counts" in _score_cli(bad_gt, tmp_path / "any", capsys)  # GT is read first
    # predictions
    pdoc = _pred_doc(tmp_path / "p")
    pdoc["queries"]["cup"]["masks"]["000001"] = rle
    (tmp_path / "p2").mkdir()
    (tmp_path / "p2" / "predictions.json").write_text(json.dumps(pdoc))
    assert "masks['000001'].counts" in _score_cli(gt, tmp_path / "p2", capsys)
    # the decoder every reader goes through
    with pytest.raises(InputError, match="counts"):
        decode_mask(rle)
    with pytest.raises(InputError, match=r"f\.json: x\.counts"):
        decode_mask(rle, "f.json", "x")


def test_rle_checked_decoder_agrees_with_pycocotools():
    from pycocotools import mask as mask_utils

    rng = np.random.default_rng(3)
    for _ in range(40):
        h, w = (int(v) for v in rng.integers(1, 40, 2))
        m = rng.random((h, w)) < rng.random()
        rle = encode_mask(m)
        runs = rle_runs(rle)[2]
        assert string_to_runs(rle["counts"]).tolist() == runs.tolist()
        assert runs_to_string(runs) == rle["counts"]
        coco = mask_utils.frPyObjects({"size": [h, w], "counts": runs.tolist()}, h, w)
        assert coco["counts"].decode() == rle["counts"]
        assert np.array_equal(decode_mask({"size": [h, w], "counts": runs.tolist()}), m)


# -- 2. sizes checked before decoding -------------------------------------------------------------------------
def test_declared_size_refused_before_decoding(tmp_path, capsys):
    _, gt = _gt_file(tmp_path)
    pdoc = _pred_doc(tmp_path / "p")
    pdoc["queries"]["cup"]["masks"]["000001"] = {"size": [60000, 60000], "counts": [60000 * 60000]}
    (tmp_path / "big").mkdir()
    (tmp_path / "big" / "predictions.json").write_text(json.dumps(pdoc))
    assert (tmp_path / "big" / "predictions.json").stat().st_size < 4000
    with bounded(H * W):
        assert "masks['000001'].size" in _score_cli(gt, tmp_path / "big", capsys)
    # a size under the global bound but not the frame's is refused by the frame, still undecoded
    pred = QueryPrediction("cup", masks={"f": {"size": [4000, 4000], "counts": [16_000_000]}})
    with bounded(H * W), pytest.raises(InputError, match=r"masks\['f'\]\.size.*frame is 8x6"):
        pred.mask("f", (H, W))


def test_png_size_refused_from_its_header(tmp_path):
    path = tmp_path / "m.png"
    # declares 20000 x 20000 (400 M pixels) but carries almost no data: only the header is read
    path.write_bytes(png_bytes(20000, 20000, rows=b"\0" * 100))
    with bounded(H * W), pytest.raises(InputError, match=r"m\.png.*20000x20000"):
        read_mask(path)
    path.write_bytes(png_bytes(W + 1, H))
    with bounded(H * W), pytest.raises(InputError, match=r"m\.png.*9x6 \(WxH\), the frame is 8x6"):
        read_mask(path, (H, W))
    pred = QueryPrediction("cup", masks={"f": path}, source=tmp_path)
    with pytest.raises(InputError, match="the frame is 8x6"):
        pred.mask("f", (H, W))
    # a chunk length of 1.5 GB in a 100-byte file: a decoder would allocate it before finding it missing
    raw = bytearray(png_bytes(W, H))
    raw[33] ^= 0x5A
    path.write_bytes(bytes(raw))
    with bounded(H * W), pytest.raises(InputError, match=r"m\.png: truncated PNG: chunk b'IDAT'"):
        read_mask(path, (H, W))
    davis = tmp_path / "davis"
    davis.mkdir()
    (davis / "00000.png").write_bytes(bytes(raw))
    with bounded(H * W), pytest.raises(InputError, match=r"00000\.png: truncated PNG"):
        import_davis(davis, {1: "cup"}, scene_name="toy")


# -- 4. mask PNG formats ------------------------------------------------------------------------------------------
def _write(path: Path, image: np.ndarray) -> Path:
    assert cv2.imwrite(str(path), image)
    return path


def test_mask_png_any_channel_alpha_and_signature(tmp_path):
    want = np.zeros((H, W), bool)
    want[1:4, 2:6] = True
    for channel in range(3):  # red, green or blue on black (OpenCV writes BGR)
        img = np.zeros((H, W, 3), np.uint8)
        img[want, channel] = 255
        assert np.array_equal(read_mask(_write(tmp_path / f"c{channel}.png", img)) > 0, want), channel
    rgba = np.zeros((H, W, 4), np.uint8)
    rgba[..., 3] = 255
    rgba[want, 2] = 200  # opaque: colour decides
    assert np.array_equal(read_mask(_write(tmp_path / "opaque.png", rgba)) > 0, want)
    rgba = np.zeros((H, W, 4), np.uint8)
    rgba[want, 3] = 255  # alpha-only mask: black everywhere, alpha = mask
    assert np.array_equal(read_mask(_write(tmp_path / "alpha.png", rgba)) > 0, want)
    rgba = np.full((H, W, 4), 255, np.uint8)
    rgba[~want, 3] = 0  # white with transparent background
    assert np.array_equal(read_mask(_write(tmp_path / "white.png", rgba)) > 0, want)
    grey16 = want.astype(np.uint16) * 1000
    assert np.array_equal(read_mask(_write(tmp_path / "g16.png", grey16)) > 0, want)
    # JPEG bytes, a folder, text, empty: each refused in one line naming the file
    (tmp_path / "jpeg.png").write_bytes(cv2.imencode(".jpg", np.full((H, W), 3, np.uint8))[1].tobytes())
    (tmp_path / "dir.png").mkdir()
    (tmp_path / "text.png").write_text("hello")
    (tmp_path / "empty.png").write_bytes(b"")
    for name, match in [("jpeg.png", "JPEG"), ("dir.png", "is a folder"), ("text.png", "not a PNG"),
                        ("empty.png", "empty")]:
        with pytest.raises(InputError, match=match) as err:
            read_mask(tmp_path / name)
        assert name in str(err.value) and "\n" not in str(err.value)


def test_red_mask_scores_like_a_white_one(tmp_path):
    aset, gt = _gt_file(tmp_path)
    preds = ScenePredictions(scene="toy")
    for q in aset.queries:
        frames = aset.annotated_frames(q.id)
        p = QueryPrediction(q.text, masks={f.name: aset.get_mask(q.id, f.id) for f in frames})
        if q.kind == "sensitive":
            p.scores = {f.name: float(q.holds_at(f.time_index)) for f in frames}
        preds.add(p)
    write_predictions(tmp_path / "pp", preds, layout="png")
    for png in (tmp_path / "pp" / "masks").rglob("*.png"):
        grey = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        red = np.zeros(grey.shape + (3,), np.uint8)
        red[..., 2] = grey  # red in OpenCV's BGR order
        assert cv2.imwrite(str(png), red)
    assert score_scene(aset, read_predictions(tmp_path / "pp")).summary()["mIoU"] == 100.0


def test_davis_refuses_jpeg_and_rgb(tmp_path):
    (tmp_path / "00000.png").write_bytes(cv2.imencode(".jpg", np.full((H, W), 1, np.uint8))[1].tobytes())
    with pytest.raises(InputError, match=r"00000\.png.*JPEG"):
        import_davis(tmp_path, {1: "cup"}, scene_name="toy")
    (tmp_path / "00000.png").write_bytes(png_bytes(W, H, colour=2))
    with pytest.raises(InputError, match=r"00000\.png: mode.*RGB"):
        import_davis(tmp_path, {1: "cup"}, scene_name="toy")
    (tmp_path / "00000.png").write_bytes(png_bytes(60000, 60000, rows=b"\0"))
    with bounded(H * W), pytest.raises(InputError, match="60000x60000"):
        import_davis(tmp_path, {1: "cup"}, scene_name="toy")


# -- 8. non-finite and huge numbers ---------------------------------------------------------------------------------
@pytest.mark.parametrize("value", ["1.7e308", "-1e31", "Infinity", "NaN", "9" * 400, "true", "\"0.5\""])
def test_scores_beyond_the_bound_are_refused(tmp_path, capsys, value):
    _, gt = _gt_file(tmp_path)
    pdoc = _pred_doc(tmp_path / "p")
    (tmp_path / "s").mkdir()
    text = json.dumps(pdoc).replace('"000001": 1.0', f'"000001": {value}', 1)
    assert text != json.dumps(pdoc)
    (tmp_path / "s" / "predictions.json").write_text(text)
    with pytest.raises(InputError, match=r"predictions\.json: queries\['full cup'\]\.scores\['000001'\]"):
        read_predictions(tmp_path / "s")
    assert "scores['000001']" in _score_cli(gt, tmp_path / "s", capsys)


def test_largest_scores_keep_results_finite(tmp_path):
    aset, gt = _gt_file(tmp_path)
    pdoc = _pred_doc(tmp_path / "p")
    pdoc["queries"]["full cup"]["scores"] = {k: 1e30 for k in pdoc["queries"]["full cup"]["scores"]}
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "predictions.json").write_text(json.dumps(pdoc))
    from benchmark.cli import main

    assert main(["score", "--gt", str(gt), "--pred", str(tmp_path / "s"), "--quiet", "--out",
                 str(tmp_path / "r.json")]) == 0
    json.loads((tmp_path / "r.json").read_text(), parse_constant=lambda c: pytest.fail(f"wrote {c}"))


def test_json_writers_write_standard_json(tmp_path):
    obj = {"nan": math.nan, "inf": math.inf, "ninf": -math.inf, "np": np.float32("nan"), "ok": 1.5,
           "arr": np.array([1.0, np.nan]), "nested": [{"x": np.float64("inf")}], "path": Path("a/b"), "n": None}
    write_json(tmp_path / "a.json", obj)
    back = json.loads((tmp_path / "a.json").read_text(), parse_constant=lambda c: pytest.fail(f"wrote {c}"))
    assert back == {"nan": None, "inf": None, "ninf": None, "np": None, "ok": 1.5, "arr": [1.0, None],
                    "nested": [{"x": None}], "path": "a/b", "n": None}
    aset = small_set()
    aset.info["weight"] = math.nan
    text = Path(save_annotations(aset, tmp_path / "ann.json")).read_text()
    assert json.loads(text, parse_constant=lambda c: pytest.fail(f"wrote {c}"))["info"]["weight"] is None
    preds = ScenePredictions(scene="toy")
    preds.add(QueryPrediction("q", masks={"f": np.zeros((H, W), bool)}, scores={"f": math.inf}))
    with pytest.raises(InputError, match=r"scores\['f'\]"):
        write_predictions(tmp_path / "p", preds)


# -- 9. malformed JSON: nesting, encodings, types, folders ---------------------------------------------------------
@pytest.mark.parametrize("text, match", [
    ("[" * 100000 + "]" * 100000, "nested deeper|lists and objects"),
    ('{"a": ' + "[" * 150 + "]" * 150 + "}", "nested deeper"),
    ('{"format": ' + "1" * 5000 + "}", "invalid JSON"),
    ("{bad", "invalid JSON"),
    (b'{"format": "\xff"}', "not UTF-8"),
    ("[]", "top level"),
    ("", "invalid JSON"),
])
def test_malformed_json_gives_input_error(tmp_path, capsys, text, match):
    _, gt = _gt_file(tmp_path)
    raw = text if isinstance(text, bytes) else text.encode()
    (tmp_path / "bad.json").write_bytes(raw)
    with pytest.raises(InputError, match=match) as err:
        load_annotations(tmp_path / "bad.json")
    assert str(tmp_path / "bad.json") in str(err.value) and "\n" not in str(err.value)
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "predictions.json").write_bytes(raw)
    with pytest.raises(InputError, match=match):
        read_predictions(tmp_path / "p")
    assert "predictions.json" in _score_cli(gt, tmp_path / "p", capsys)


def test_folder_where_a_file_is_expected(tmp_path, capsys):
    (tmp_path / "gt.json").mkdir()
    with pytest.raises(InputError, match="gt.json: is a folder"):
        load_annotations(tmp_path / "gt.json")
    with pytest.raises(InputError, match="is a folder"):
        read_json(tmp_path / "gt.json")
    (tmp_path / "p" / "predictions.json").mkdir(parents=True)
    with pytest.raises(InputError, match="predictions.json: is a folder"):
        read_predictions(tmp_path / "p")
    (tmp_path / "file").write_text("{}")
    with pytest.raises(InputError, match="file: is a file; expected a prediction folder"):
        read_predictions(tmp_path / "file")


def test_compressed_predictions_read_as_the_plain_file_and_bad_gzip_is_an_input_error(tmp_path, capsys, monkeypatch):
    aset, gt = _gt_file(tmp_path)
    _pred_doc(tmp_path / "p")  # a valid plain folder, tmp_path/p/pred
    preds = read_predictions(write_predictions(tmp_path / "plain", read_predictions(tmp_path / "p" / "pred")))
    main = write_predictions(tmp_path / "gz", preds, compress=True)
    assert main.name == "predictions.json.gz" and main.read_bytes()[:2] == b"\x1f\x8b"
    assert read_json(main) == read_json(tmp_path / "plain" / "predictions.json")
    again = write_predictions(tmp_path / "gz2", preds, compress=True)
    assert again.read_bytes() == main.read_bytes()  # no timestamp inside: equal content, equal bytes
    for source in (tmp_path / "gz", main):  # the folder or its main file
        back = read_predictions(source)
        assert {t: (q.kind, sorted(q.masks), q.scores) for t, q in back.queries.items()} == \
            {t: (q.kind, sorted(q.masks), q.scores) for t, q in preds.queries.items()}
    # rewriting a folder in the other form leaves one main file; without overwrite it is refused
    with pytest.raises(InputError, match="predictions.json.gz: already exists"):
        write_predictions(tmp_path / "gz", preds)
    write_predictions(tmp_path / "gz", preds, overwrite=True)
    assert sorted(p.name for p in (tmp_path / "gz").iterdir()) == ["predictions.json"]
    write_predictions(tmp_path / "gz", preds, overwrite=True, compress=True)
    assert sorted(p.name for p in (tmp_path / "gz").iterdir()) == ["predictions.json.gz"]
    # both forms in one folder: which one counts is not guessed
    (tmp_path / "gz" / "predictions.json").write_text("{}")
    with pytest.raises(InputError, match="holds both predictions.json and predictions.json.gz"):
        read_predictions(tmp_path / "gz")
    (tmp_path / "gz" / "predictions.json").unlink()
    # truncated, not gzip at all, or expanding past the limit: one line naming the file
    whole = main.read_bytes()
    for name, raw in (("cut", whole[: len(whole) // 2]), ("plain-bytes", b'{"format": 1}')):
        (tmp_path / name).mkdir()
        (tmp_path / name / "predictions.json.gz").write_bytes(raw)
        with pytest.raises(InputError, match="predictions.json.gz: not valid gzip data"):
            read_predictions(tmp_path / name)
        assert "predictions.json.gz: not valid gzip data" in _score_cli(gt, tmp_path / name, capsys)
    import benchmark.core.atomic as atomic
    monkeypatch.setattr(atomic, "MAX_GZIP_JSON_BYTES", len(gzip.decompress(whole)) - 1)
    with pytest.raises(InputError, match="predictions.json.gz: decompresses to more than"):
        read_predictions(tmp_path / "gz")


def test_wrong_types_in_release_coco_name_the_field(tmp_path):
    aset = small_set()
    written = export_release(aset, tmp_path / "rel", frame_base=1)
    base = json.loads(written["coco"].read_text())
    cases = [
        (("annotations", 0, "category_id"), [1], r"annotations\[0\]\.category_id"),       # unhashable id
        (("annotations", 0, "image_id"), {"a": 1}, r"annotations\[0\]\.image_id"),
        (("annotations", 0, "segmentation"), [[0, 0, 10 ** 400, 0, 1, 1]], r"annotations\[0\]\.segmentation\[0\]"),
        (("annotations", 0, "segmentation"), [[0, 0, 1e12, 0, 1, 1]], r"annotations\[0\]\.segmentation\[0\]"),
        (("annotations", 0, "segmentation"), {"size": [H, W], "counts": overflow_runs(H * W)},
         r"annotations\[0\]\.segmentation\.counts"),
        (("images", 0, "width"), 2 ** 40, r"images\[0\]\.width"),
        (("info", "bench4d", "num_time_steps"), True, r"info\.bench4d\.num_time_steps"),
    ]
    for (a, b, c), value, match in cases:
        doc = copy.deepcopy(base)
        doc[a][b][c] = value
        path = tmp_path / "coco.json"
        path.write_text(json.dumps(doc))
        with pytest.raises(InputError, match=match):
            import_release(path, scene_name="toy", frame_base=1)
