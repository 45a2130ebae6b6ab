"""The results file schema (:class:`benchmark.results.RunResults`): a complete document round-trips, each
field broken alone is an :class:`InputError` naming that field when read and when written, and every
committed results file reads."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any, Literal, Union, get_args, get_origin

import pytest

from benchmark.core.errors import InputError
from benchmark.core.protocol import PROTOCOLS
from benchmark.results import (RESULTS_FORMAT, RESULTS_VERSION, RunResults, _fields, _is_record, check_results,
                               read_results, results_path, write_results)

ROOT = Path(__file__).resolve().parents[1]


def _query_timing(text: str) -> dict:
    return {"query": text, "frames": 2, "repeats": 3, "seconds_per_frame": 0.01, "fps": 100.0,
            "min_seconds": 0.009, "max_seconds": 0.012}


def good_doc() -> dict:
    """A results document with every field of the schema."""
    frames = [{"scene": "s1", "query": "open box", "kind": "sensitive", "frame": f"f{t:03d}", "time_index": t,
               "camera_id": "0", "iou": 0.5, "acc": 0.9, "pred_pixels": 3, "gt_pixels": 4, "score": 0.1 * t,
               "smoothed": 0.1 * t, "decision": t >= 2, "label": t >= 2} for t in range(4)]
    return {
        "format": RESULTS_FORMAT, "version": RESULTS_VERSION,
        "method": "nearest-frame", "dataset": "synthetic", "scene": "s1", "layout": "hypernerf", "track": "oracle",
        "seed": 1, "split": "novel-view", "scene_seed": 1, "splits": ["test"],
        "metrics": {"mIoU": 60.0, "mAcc": 90.0, "Acc": 75.0, "vIoU": None, "AUC": 100.0, "nearTau": 25.0,
                    "mIoU_answered": 60.0, "mAcc_answered": 90.0, "Acc_answered": 75.0, "vIoU_answered": None,
                    "absentFP": 50.0, "absent_frames": 2, "answered_agnostic_queries": 1, "asked_agnostic_queries": 1,
                    "answered_sensitive_queries": 1, "asked_sensitive_queries": 2,
                    "agnostic_queries": 1, "sensitive_queries": 1, "frames_scored": 8, "scenes": 1},
        "unanswered_queries": ["closed box"],
        "timing": {"fit_seconds": 1.5, "fit_cached": False, "answer_all_seconds": 0.5, "note": "medians",
                   "query_agnostic": _query_timing("box"), "query_sensitive": _query_timing("open box")},
        "memory": {"peak_cpu_mib": 500.0, "peak_cpu_fit_mib": 300.0, "baseline_cpu_fit_mib": 200.0, "peak_gpu_mib": None,
                   "peak_gpu_fit_mib": None,
                   "peak_window": "run", "peak_fit_window": "process", "note": "peaks"},
        "method_config": {"match_rule": "canonical"},
        "fit": {"key": "a" * 24, "cached": False, "code_version": "2", "head_refit_of": "b" * 24,
                "info": {"geometry": {"seconds": 1.0}}},
        "supervision": {"track": "oracle", "sources": {"segmenter": "gt"}},
        "environment": {"packages": {"python": "3.11.7", "numpy": "2.0"}, "git": {"commit": "c" * 40, "dirty": False},
                        "code_changed_during_run": None, "device": "cuda:0", "platform": "Linux", "machine": "x86_64",
                        "cpu_count": 2, "processor": None, "cpu_capability": "AVX2", "numpy_blas_core": "haswell", "native_kernels": "loaded",
                        "gpu": "H100",
                        "torch_threads": 1, "concurrent_runs": 1},
        "scene_info": {"root": "cache/scenes/128px/s1", "summary": "8 frames", "annotations": "annotations.json",
                       "scale": None, "generated": {"preset": "s1", "size": 128, "seed": 1, "generator_version": "1.0",
                                                    "digest": "d" * 24, "committed_digest": None,
                                                    "perturbation": {"family": "occluder", "strength": 0.2},
                                                    "current": None},
                       "draft_queries": []},
        "protocol": PROTOCOLS["release"].to_dict(),
        "score_config": {"temporal": PROTOCOLS["release"].temporal.to_dict(), "eval_frames": ["f000"],
                         "allow_extra": False},
        "scores": {"queries": [{"scene": "s1", "query": "open box", "kind": "sensitive", "frames": 4, "Acc": 75.0}],
                   "skipped": [{"scene": "s1", "query": "ball"}], "frames": frames, "frames_dropped": 0},
        "predictions": "seed0.predictions/predictions.json",
        "wall_seconds": 3.0,
        "created": "2025-01-01T00:00:00+00:00",
    }


def _schema_fields(record: type = RunResults, prefix: str = "") -> list[tuple[str, Any, bool]]:
    """``(dotted path, type, required)`` of every field of ``record`` and of the records below it."""
    out = []
    for name, hint, required in _fields(record):
        path = f"{prefix}.{name}" if prefix else name
        out.append((path, hint, required))
        inner = [a for a in get_args(hint) if a is not type(None)] if get_origin(hint) is Union else [hint]
        if len(inner) == 1 and _is_record(inner[0]):
            out += _schema_fields(inner[0], path)
    return out


FIELDS = _schema_fields()


def _wrong_value(hint: Any) -> Any:
    """A value of another type than ``hint`` allows."""
    allowed = get_args(hint) if get_origin(hint) is Union else (hint,)
    takes_text = any(a is str or (get_origin(a) is Literal and "wrong" in get_args(a)) for a in allowed)
    return 12345 if takes_text else "wrong"


def _set(doc: dict, path: str, value: Any = None, *, delete: bool = False) -> None:
    *parents, last = path.split(".")
    for name in parents:
        doc = doc[name]
    if delete:
        del doc[last]
    else:
        doc[last] = value


def _expect_error(tmp_path: Path, doc: dict, field: str) -> None:
    """Reading ``doc`` from a file and writing it are both an InputError naming the file and ``field``."""
    path = tmp_path / "seed0.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as read:
        read_results(path)
    assert (read.value.field, read.value.file) == (field, str(path)), read.value
    target = results_path(tmp_path / "written", "synthetic", "s1", "m", "oracle", 0)
    written = {k: v for k, v in doc.items() if k not in ("format", "version")}
    with pytest.raises(InputError) as write:
        write_results(target, written)
    assert write.value.field == field, write.value
    assert not target.exists()


def test_a_complete_document_round_trips_and_names_every_field_of_the_schema(tmp_path):
    doc = good_doc()
    check_results(doc)
    for path, _, _ in FIELDS:  # the document below exercises every field
        node = doc
        for name in path.split("."):
            assert name in node, path
            node = node[name]
    target = results_path(tmp_path, "synthetic", "s1", "nearest-frame", "oracle", 0)
    write_results(target, {k: v for k, v in doc.items() if k not in ("format", "version")})
    assert read_results(target) == doc
    assert isinstance(json.loads(target.read_text())["scores"]["frames"], dict)  # stored as a table
    assert list(json.loads(target.read_text())) == list(doc)  # in the schema's order


@pytest.mark.parametrize("field, hint", [(p, h) for p, h, _ in FIELDS], ids=[p for p, _, _ in FIELDS])
def test_a_field_of_the_wrong_type_is_named(tmp_path, field, hint):
    doc = copy.deepcopy(good_doc())
    _set(doc, field, _wrong_value(hint))
    if field in ("format", "version"):  # the header is checked before the schema, with its own words
        with pytest.raises(InputError, match=field):
            check_results(doc)
        return
    _expect_error(tmp_path, doc, field)


@pytest.mark.parametrize("field", [p for p, _, required in FIELDS if required and p not in ("format", "version")])
def test_a_missing_required_field_is_named(tmp_path, field):
    doc = copy.deepcopy(good_doc())
    _set(doc, field, delete=True)
    _expect_error(tmp_path, doc, field)


@pytest.mark.parametrize("field, value", [
    ("metric", {}),  # a misspelt top-level field
    ("timing.fit_secs", 1.0),
    ("environment.git.branch", "main"),
])
def test_an_unknown_field_is_named(tmp_path, field, value):
    doc = copy.deepcopy(good_doc())
    _set(doc, field, value)
    _expect_error(tmp_path, doc, field)


@pytest.mark.parametrize("field, value, message", [
    ("metrics.mIoU", "high", "expected a number or null, got 'high'"),
    ("seed", True, "expected an integer, got True"),
    ("memory.peak_window", "always", "expected one of 'run', 'process', got 'always'"),
    ("splits", ["test", 3], "expected a string, got 3"),
    ("environment.packages", {"numpy": 2}, "expected a string, got 2"),
])
def test_the_error_says_what_was_expected(tmp_path, field, value, message):
    doc = copy.deepcopy(good_doc())
    _set(doc, field, value)
    path = tmp_path / "seed0.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError) as err:
        read_results(path)
    assert err.value.message == message
    assert err.value.field == {"splits": "splits[1]", "environment.packages": "environment.packages.numpy"}.get(
        field, field)


def test_optional_fields_may_be_absent(tmp_path):
    required = {p.split(".")[0] for p, _, req in FIELDS if req and "." not in p}
    minimal = {k: v for k, v in good_doc().items() if k in required}
    minimal["timing"], minimal["metrics"] = {}, {}
    path = tmp_path / "seed0.json"
    path.write_text(json.dumps(minimal))
    assert read_results(path) == minimal


def test_every_committed_results_file_reads():
    files = [p for p in sorted((ROOT / "results").rglob("seed*.json"))
             if not any(part.endswith(".predictions") for part in p.parts)]
    if not files:
        pytest.skip("no committed results in this checkout")
    for path in files:
        read_results(path)


def test_the_schema_reads_the_same_whichever_union_spelling_typing_cached_first():
    """``NotRequired[float | None]`` and ``NotRequired[Optional[float]]`` share typing's cache: whichever an
    imported library made first is what the schema's hints hold, and both must mean "a number or null"."""
    import types
    from typing import NotRequired, Optional, get_args

    from benchmark.results import _check_value

    for hint in (Optional[float], float | None):
        assert isinstance(hint, types.UnionType) or get_args(hint) == (float, type(None))
        _check_value(3.5, hint, None, "metrics.mIoU")
        _check_value(None, hint, None, "metrics.mIoU")
        with pytest.raises(InputError, match="metrics.mIoU"):
            _check_value("high", hint, None, "metrics.mIoU")
    NotRequired[float | None]  # noqa: B018 - what a library importing before bench4d may do


def test_slim_keeps_what_the_tables_read_and_drops_frames_and_predictions(tmp_path, capsys):
    """``bench4d slim``: the per-frame records become their count, the predictions folder goes, the metrics,
    per-query scores and the leaderboard's rows stay; a second pass changes nothing."""
    from benchmark.cli import main
    from benchmark.leaderboard import query_rows

    doc = good_doc()
    target = results_path(tmp_path / "results", "synthetic", "s1", "nearest-frame", "oracle", 0)
    write_results(target, {k: v for k, v in doc.items() if k not in ("format", "version")})
    folder = target.with_suffix(".predictions")
    folder.mkdir()
    (folder / "predictions.json").write_text("x" * 5000)
    rows_before = query_rows(read_results(target), "p")
    assert main(["slim", str(tmp_path / "results"), "--dry-run"]) == 0
    assert f"would slim {target}" in capsys.readouterr().out and folder.is_dir()
    assert main(["slim", str(tmp_path / "results")]) == 0
    assert "1 results file(s)" in capsys.readouterr().out
    slim = read_results(target)
    assert "frames" not in slim["scores"] and slim["scores"]["frames_dropped"] == len(doc["scores"]["frames"])
    assert "predictions" not in slim and not folder.exists()
    for key in ("metrics", "timing", "memory", "fit", "environment", "supervision"):
        assert slim[key] == doc[key]
    assert slim["scores"]["queries"] == doc["scores"]["queries"] and query_rows(slim, "p") == rows_before
    size = target.stat().st_size
    from benchmark.results import slim_results

    assert slim_results(target) == 0 and target.stat().st_size == size
    assert target.read_bytes().count(b"\n") == 1  # a slim file is one compact line
    # a slim file an older writer indented is compacted: listed by --dry-run, smaller after, same content
    from benchmark.core.atomic import write_json

    write_json(target, json.loads(target.read_text()), indent=1)
    indented = target.stat().st_size
    assert main(["slim", str(target), "--dry-run"]) == 0 and f"would slim {target}" in capsys.readouterr().out
    assert slim_results(target) == indented - size and read_results(target) == slim
    assert main(["slim", str(tmp_path / "missing")]) == 2

