"""Class fuzzers: hypothesis makes hostile documents for each parser a command runs (predictions, annotation
files, the release's COCO and video files, scene files and images, results files read beside predictions),
and every one runs through the real command line in a child process whose address space is capped
(``RLIMIT_AS``). The property, per document: the command ends with exit 0 (the document was still valid)
or exit 2 with exactly one line on stderr (never a traceback, a crash or a memory error), and every input
file is byte-identical afterwards.

Hostile values come by class, not by payload: sizes and counts far beyond the frame (compressed-RLE strings
longer than any mask needs, headers declaring billions of pixels), non-finite and unbounded numbers,
wrong types, keys repeated or varied (case, spaces, fullwidth, non-ASCII digits), control characters,
names that are paths, deep nesting, and truncated or flipped bytes. A batch of documents shares one child,
so a class costs one interpreter start per example.
"""

from __future__ import annotations

import copy
import gzip
import hashlib
import json
import math
import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parents[1]
MEMORY_CAP = 1 << 30
"""Address space of the child: bench4d's imports take about half of it."""
BATCH = 10
FUZZ = settings(max_examples=2, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                      HealthCheck.function_scoped_fixture,
                                                                      HealthCheck.data_too_large])

DRIVER = r"""
import contextlib, io, json, sys
from benchmark.cli import main
out = []
for argv in json.load(open(sys.argv[1])):
    err = io.StringIO()
    rc, exc = None, None
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            rc = main(argv)
    except BaseException as e:  # noqa: BLE001 - reported to the parent: any escape fails the property
        exc = f"{type(e).__name__}: {str(e)[:300]}"
    out.append({"rc": rc, "stderr": err.getvalue()[-3000:], "exc": exc})
sys.__stdout__.write(json.dumps(out))
"""


# -- hostile documents ----------------------------------------------------------------------------------------
class Raw:
    """A JSON token written as given (``NaN``, ``1e999``, a deep nest, a 40-digit integer)."""

    def __init__(self, text: str):
        self.text = text


class Dup:
    """An object whose (key, value) pairs are written as listed: a key may come twice."""

    def __init__(self, pairs: list):
        self.pairs = pairs


def dump(obj) -> str:
    if isinstance(obj, Raw):
        return obj.text
    if isinstance(obj, Dup):
        return "{" + ", ".join(f"{json.dumps(str(k))}: {dump(v)}" for k, v in obj.pairs) + "}"
    if isinstance(obj, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))}: {dump(v)}" for k, v in obj.items()) + "}"
    if isinstance(obj, (list, tuple)):
        return "[" + ", ".join(dump(v) for v in obj) + "]"
    if isinstance(obj, float) and not math.isfinite(obj):
        return "NaN" if obj != obj else ("Infinity" if obj > 0 else "-Infinity")
    return json.dumps(obj)


def hostile_values(h: int, w: int) -> list:
    """Values of every class the parsers must refuse (or survive), sized for an h x w frame."""
    return [None, True, False, -1, 0, 1, 2 ** 31, 2 ** 63, -(2 ** 63) - 1, Raw("1" * 40), Raw("1e999"),
            Raw("NaN"), Raw("-Infinity"), 0.5, 1e308, "", "\x1b[2J\r", "../victim", "a/b", "\u0669", " 9 ",
            "\uff42ox", "x" * 3000, [], {}, [[[[[]]]]], Raw("[" * 5000 + "]" * 5000),
            [60000, 60000], [h, w], [w, h], [0, w],
            {"size": [h, w], "counts": "0" * (6 * (h * w + 1) + 7)},           # longer than any mask needs
            {"size": [h, w], "counts": "0" * 200_000},
            {"size": [60000, 60000], "counts": "0"}, {"size": [h, w], "counts": [2 ** 62] * 4 + [h * w]},
            {"size": [h, w], "counts": [h * w, -1, 1]}, {"size": [h, w], "counts": "\x00\xff"},
            [[0, 0, float("nan"), 1, 2, 2]], [[0, 0, 4e8, 0, 4, 3]], [[0, 0] * 5000],
            [[1e300, 1e300, 0, 0, 2, 2]], [[0, 0, 1, "a", 2, 2]]]


def _paths(node, out=None):
    out = [] if out is None else out
    if isinstance(node, dict):
        for k, v in node.items():
            out.append((node, k))
            _paths(v, out)
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out.append((node, i))
            _paths(v, out)
    return out


def _variant(key: str, draw) -> str:
    return draw(st.sampled_from([key.upper(), key.capitalize(), f" {key}", f"{key} ", key + "\u200b",
                                 "".join(chr(ord(c) + 0xFEE0) if "a" <= c <= "z" else c for c in key)]))


@st.composite
def hostile_doc(draw, base, h: int, w: int):
    """``base`` (a parsed document) with one to three mutations of a class; returns the JSON text."""
    doc = copy.deepcopy(base)
    values = hostile_values(h, w)
    for _ in range(draw(st.integers(1, 3))):
        spots = _paths(doc)
        if not spots:
            break
        parent, key = spots[draw(st.integers(0, len(spots) - 1))]
        op = draw(st.sampled_from(["value", "value", "value", "delete", "variant", "duplicate", "nest"]))
        if op == "value":  # a copy: a value drawn twice must not become its own element
            parent[key] = copy.deepcopy(draw(st.sampled_from(values)))
        elif op == "delete":
            del parent[key]
        elif op == "variant" and isinstance(parent, dict) and isinstance(key, str):
            parent[_variant(key, draw)] = parent[key]
        elif op == "duplicate" and isinstance(parent, dict):
            pairs = list(parent.items()) + [(key, copy.deepcopy(draw(st.sampled_from(values))))]
            replacement = Dup(pairs)
            holder = next(((p, k) for p, k in _paths(doc) if p[k] is parent), None)
            if holder is None:
                doc = replacement
            else:
                holder[0][holder[1]] = replacement
            break  # a Dup is written, not walked again
        elif op == "nest":
            parent[key] = [[[parent[key]]]]
    return dump(doc)


def mutate_bytes(raw: bytes, draw) -> bytes:
    op = draw(st.sampled_from(["keep", "keep", "keep", "cut", "flip"]))
    if op == "cut" and raw:
        return raw[: draw(st.integers(0, len(raw) - 1))]
    if op == "flip" and raw:
        i = draw(st.integers(0, len(raw) - 1))
        return raw[:i] + bytes([raw[i] ^ draw(st.integers(1, 255))]) + raw[i + 1:]
    return raw


# -- running a batch --------------------------------------------------------------------------------------------
def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and not p.is_symlink()}


def run_batch(workdir: Path, cases: list[tuple[list[str], Path]]) -> None:
    """Run every ``(argv, input folder)`` in one capped child and check the property for each."""
    before = [_digest(folder) for _, folder in cases]
    manifest = workdir / "cases.json"
    manifest.write_text(json.dumps([argv for argv, _ in cases]))

    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP, MEMORY_CAP))

    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", DRIVER, str(manifest)], capture_output=True, text=True, timeout=300,
                          preexec_fn=cap, env=env, cwd=str(workdir))
    assert proc.returncode == 0, f"the child died ({proc.returncode}): {proc.stderr[-3000:]}"
    results = json.loads(proc.stdout)
    for (argv, folder), got, digest in zip(cases, results, before):
        case = f"{' '.join(argv)[:300]}"
        assert got["exc"] is None, (case, got)
        assert got["rc"] in (0, 2), (case, got)
        if got["rc"] == 2:
            lines = [line for line in got["stderr"].splitlines() if line.strip()]
            errors = [line for line in lines if not line.startswith(("warning:", "note:"))]
            assert len(errors) == 1 and errors[0].startswith("bench4d "), (case, got["stderr"][-1500:])
            assert "Traceback" not in got["stderr"] and "\x1b" not in got["stderr"], (case, got["stderr"][-1500:])
        assert _digest(folder) == digest, f"{case}: an input changed"


# -- valid inputs -------------------------------------------------------------------------------------------------
H, W = 6, 8


@pytest.fixture(scope="module")
def valid(tmp_path_factory):
    from annotations.format import save_annotations
    from annotations.release import export_release
    from benchmark.core.annotation import AnnotatedFrame, AnnotationSet, Query
    from benchmark.predictions import QueryPrediction, ScenePredictions, write_predictions

    root = tmp_path_factory.mktemp("fuzz_valid")
    rng = np.random.default_rng(5)
    aset = AnnotationSet(scene="toy", num_time_steps=5, info={"annotator": "test"})
    aset.frames = [AnnotatedFrame(id=10 + k, name=f"{k + 1:06d}", time_index=k, width=W, height=H) for k in range(3)]
    aset.queries = [Query(1, "cup"), Query(2, "plate"), Query(3, "full cup", "sensitive", base=1, intervals=[(0, 1)])]
    for f in aset.frames:
        aset.set_mask(1, f.id, rng.random((H, W)) < 0.3)
        aset.set_mask(2, f.id, rng.random((H, W)) < 0.5)
    gt = save_annotations(aset, root / "gt.json")
    preds = ScenePredictions(scene="toy", method="oracle")
    for q in aset.queries:
        frames = aset.annotated_frames(q.id)
        p = QueryPrediction(q.text, kind=q.kind, masks={f.name: aset.get_mask(q.id, f.id) for f in frames})
        if q.kind == "sensitive":
            p.scores = {f.name: float(q.holds_at(f.time_index)) for f in frames}
        preds.add(p)
    pred_main = write_predictions(root / "pred", preds)
    written = export_release(aset, root / "release", frame_base=1)
    return {"root": root, "gt": gt, "pred": root / "pred", "gt_doc": json.loads(Path(gt).read_text()),
            "pred_doc": json.loads(pred_main.read_text()), "coco": json.loads(written["coco"].read_text()),
            "video": json.loads(written["video"].read_text())}


def _case_dir(base: Path, i: int) -> Path:
    folder = base / f"case{i}"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    return folder


# -- the classes ------------------------------------------------------------------------------------------------
@FUZZ
@given(data=st.data())
def test_fuzz_predictions_through_score(valid, tmp_path_factory, data):
    work = tmp_path_factory.mktemp("fz_pred")
    cases = []
    for i in range(BATCH):
        folder = _case_dir(work, i)
        text = data.draw(hostile_doc(valid["pred_doc"], H, W)) if i else dump(valid["pred_doc"])
        raw = mutate_bytes(text.encode("utf-8", "surrogatepass"), data.draw) if i else text.encode()
        name = "predictions.json.gz" if data.draw(st.booleans()) else "predictions.json"
        (folder / "pred").mkdir()
        (folder / "pred" / name).write_bytes(gzip.compress(raw, 1) if name.endswith(".gz") else raw)
        shutil.copy(valid["gt"], folder / "gt.json")
        # the results file eval writes beside its predictions is read too: fuzz it in the same go
        if data.draw(st.booleans()):
            (folder / "pred").rename(folder / "seed0.predictions")
            results = {"format": "bench4d-run", "predictions": "seed0.predictions/predictions.json",
                       "unanswered_queries": ["cup"]}
            (folder / "seed0.json").write_text(data.draw(hostile_doc(results, H, W)))
            pred = folder / "seed0.predictions"
        else:
            pred = folder / "pred"
        cases.append((["score", "--gt", str(folder / "gt.json"), "--pred", str(pred)], folder))
    run_batch(work, cases)


@FUZZ
@given(data=st.data())
def test_fuzz_annotation_files_through_score(valid, tmp_path_factory, data):
    work = tmp_path_factory.mktemp("fz_gt")
    cases = []
    for i in range(BATCH):
        folder = _case_dir(work, i)
        text = data.draw(hostile_doc(valid["gt_doc"], H, W)) if i else dump(valid["gt_doc"])
        (folder / "gt.json").write_bytes(mutate_bytes(text.encode("utf-8", "surrogatepass"), data.draw) if i
                                         else text.encode())
        shutil.copytree(valid["pred"], folder / "pred")
        cases.append((["score", "--gt", str(folder / "gt.json"), "--pred", str(folder / "pred")], folder))
    run_batch(work, cases)


@FUZZ
@given(data=st.data())
def test_fuzz_release_coco_and_video_through_score(valid, release_scene, tmp_path_factory, data):
    """The release's layout, read against its scene folder: COCO polygons and RLE, video intervals."""
    work = tmp_path_factory.mktemp("fz_rel")
    cases = []
    scene, coco, video, pred = release_scene
    for i in range(BATCH // 2):
        folder = _case_dir(work, i)
        ann = folder / "annotations"
        (ann / "train").mkdir(parents=True)
        which = data.draw(st.sampled_from(["coco", "coco", "video"])) if i else "none"
        h, w = 48, 64
        (ann / "train" / "_annotations.coco.json").write_text(
            data.draw(hostile_doc(coco, h, w)) if which == "coco" else dump(coco))
        (ann / "video_annotations.json").write_text(data.draw(hostile_doc(video, h, w)) if which == "video"
                                                    else dump(video))
        shutil.copytree(pred, folder / "pred")
        cases.append((["score", "--gt", str(ann), "--scene", str(scene), "--pred", str(folder / "pred")], folder))
    run_batch(work, cases)


@FUZZ
@given(data=st.data())
def test_fuzz_scene_files_and_images_through_data_validate(dnerf_scene, tmp_path_factory, data):
    work = tmp_path_factory.mktemp("fz_scene")
    transforms = json.loads((dnerf_scene / "transforms_train.json").read_text())
    cases = []
    for i in range(BATCH // 2):
        folder = _case_dir(work, i)
        scene = Path(shutil.copytree(dnerf_scene, folder / "scene"))
        what = data.draw(st.sampled_from(["json", "json", "image"])) if i else "none"
        if what == "json":
            (scene / "transforms_train.json").write_text(data.draw(hostile_doc(transforms, 24, 32)))
        elif what == "image":
            victim = sorted((scene / "train").glob("*.png"))[data.draw(st.integers(0, 2))]
            raw = victim.read_bytes()
            if data.draw(st.booleans()):  # a header declaring another size (CRC kept valid)
                import struct
                import zlib

                w_, h_ = data.draw(st.sampled_from([(60000, 60000), (1, 1), (2 ** 31 - 1, 1), (0, 5)]))
                ihdr = b"IHDR" + struct.pack(">II", w_, h_) + raw[24:29]
                raw = raw[:12] + ihdr + struct.pack(">I", zlib.crc32(ihdr)) + raw[33:]
            else:
                raw = mutate_bytes(raw, data.draw) or raw[:8]
            victim.write_bytes(raw)
        cases.append((["data", "validate", str(scene)], folder))
    run_batch(work, cases)


@pytest.fixture(scope="module")
def dnerf_scene(tmp_path_factory):
    from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene

    return write_dnerf_scene(rigid_sequence(3, 32, 24, seed=6), tmp_path_factory.mktemp("fz_dnerf") / "scene")


@pytest.fixture(scope="module")
def release_scene(tmp_path_factory):
    """A D-NeRF scene (frames 0..2, 64 x 48), its annotations in the release's layout and predictions of them."""
    from annotations.release import export_release
    from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene
    from benchmark.core.annotation import AnnotatedFrame, AnnotationSet, Query
    from benchmark.loaders import load_scene
    from benchmark.predictions import QueryPrediction, ScenePredictions, write_predictions

    base = tmp_path_factory.mktemp("fz_release")
    seq = rigid_sequence(3, 64, 48, seed=7)
    folder = write_dnerf_scene(seq, base / "scene")
    scene = load_scene(folder)
    aset = AnnotationSet(scene=scene.name, num_time_steps=3)
    aset.frames = [AnnotatedFrame(id=k + 1, name=f.name, time_index=f.time_index, width=64, height=48)
                   for k, f in enumerate(scene.frames)]
    aset.queries = [Query(1, "blob"), Query(2, "moving blob", "sensitive", base=1, intervals=[(1, 2)])]
    for af, mask in zip(aset.frames, seq.masks):
        aset.set_mask(1, af.id, mask)
    written = export_release(aset, base / "export", frame_base=0)
    preds = ScenePredictions(scene=scene.name)
    preds.add(QueryPrediction("blob", masks={f.name: aset.get_mask(1, f.id) for f in aset.frames}))
    preds.add(QueryPrediction("moving blob", masks={f.name: aset.get_mask(1, f.id) for f in aset.frames},
                              scores={f.name: float(f.time_index >= 1) for f in aset.frames}))
    write_predictions(base / "pred", preds)
    return (folder, json.loads(written["coco"].read_text()), json.loads(written["video"].read_text()),
            base / "pred")
