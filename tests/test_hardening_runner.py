"""Damaged and hostile inputs of the runner, its caches, the results store and ``bench4d score``: an output
that would replace an input, damaged cached fits and generated scenes, concurrent writers of one results
file, files given as folders, and queries a method leaves unanswered."""

from __future__ import annotations

import errno
import json
import multiprocessing as mp
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from annotations.format import save_annotations
from benchmark.core.annotation import AnnotatedFrame, AnnotationSet, Query
from benchmark.cli import main
from benchmark.core.atomic import read_json
from benchmark.core.errors import InputError
from benchmark.predictions import QueryPrediction, ScenePredictions, read_predictions, write_predictions
from benchmark.runner import EvalOptions, evaluate, evaluate_with_fit
from conftest import SMOKE_SIZE

RUN = Path("synthetic") / "smoke" / "nearest-frame" / "oracle"


def _options(env, **kw) -> EvalOptions:
    return EvalOptions(method="nearest-frame", scene=str(env["scene"]), results_dir=env["results"],
                       cache_dir=env["cache"], quiet=True, timing_frames=1, timing_repeats=1, **kw)


def _error_line(err: str) -> str:
    """The one line an error printed (no traceback, nothing else on stderr)."""
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def _warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("warning:")]


# -- bench4d score --out --------------------------------------------------------------------------------
def _score_inputs(tmp_path: Path) -> tuple[Path, Path]:
    """A two-frame ground truth (one time-agnostic query) and perfect predictions of it."""
    mask = np.zeros((4, 5), bool)
    mask[:2, :2] = True
    aset = AnnotationSet(scene="kitchen", frames=[AnnotatedFrame(id=10 + t, name=f"f{t}", time_index=t, width=5,
                                                                 height=4) for t in range(2)],
                         num_time_steps=2, queries=[Query(1, "cookie")])
    for t in range(2):
        aset.set_mask(1, 10 + t, mask)
    gt = Path(save_annotations(aset, tmp_path / "gt.json"))
    preds = ScenePredictions(scene="kitchen", method="oracle")
    preds.add(QueryPrediction("cookie", kind="agnostic", masks={f"f{t}": mask for t in range(2)}))
    write_predictions(tmp_path / "pred", preds)
    return gt, tmp_path / "pred"


def test_score_out_never_replaces_an_input(tmp_path, capsys):
    gt, pred = _score_inputs(tmp_path)
    frames = tmp_path / "frames.txt"
    frames.write_text("f0\nf1\n")
    os.link(gt, tmp_path / "gt-hardlink.json")
    (tmp_path / "gt-symlink.json").symlink_to(gt)
    originals = {p: p.read_bytes() for p in (gt, pred / "predictions.json", frames)}
    base = ["score", "--gt", str(gt), "--pred", str(pred), "--eval-frames", f"@{frames}", "--quiet"]
    refused = [gt, pred / "predictions.json", tmp_path / "gt-hardlink.json", tmp_path / "gt-symlink.json", frames,
               tmp_path / "." / "pred" / ".." / "gt.json", pred / "scores.json"]
    for out in refused:
        assert main([*base, "--out", str(out)]) == 2, out
        line = _error_line(capsys.readouterr().err)
        assert "--out" in line and str(out) in line
    assert {p: p.read_bytes() for p in originals} == originals
    assert not (pred / "scores.json").exists()
    # elsewhere it writes
    assert main([*base, "--out", str(tmp_path / "scored.json")]) == 0
    assert json.loads((tmp_path / "scored.json").read_text())["metrics"]["dataset"]["mIoU"] == 100.0


def test_score_out_on_a_folder_or_an_unwritable_path_is_one_line(tmp_path, capsys, monkeypatch):
    import benchmark.commands.score as score_command

    gt, pred = _score_inputs(tmp_path)
    base = ["score", "--gt", str(gt), "--pred", str(pred), "--quiet"]
    (tmp_path / "folder").mkdir()
    for out, says in ((tmp_path / "folder", "folder"), (pred, "folder"), (gt / "scored.json", "is a file")):
        assert main([*base, "--out", str(out)]) == 2
        line = _error_line(capsys.readouterr().err)
        assert "--out" in line and says in line
    for code, message in ((errno.EACCES, "Permission denied"), (errno.ENOSPC, "No space left on device"),
                          (errno.EROFS, "Read-only file system")):
        def failing(path, obj, indent=2, code=code, message=message):
            raise OSError(code, message)

        monkeypatch.setattr(score_command, "write_json", failing)
        assert main([*base, "--out", str(tmp_path / "scored.json")]) == 2
        line = _error_line(capsys.readouterr().err)
        assert "--out" in line and message in line
    assert not (tmp_path / "scored.json").exists()


# -- damaged fit cache ----------------------------------------------------------------------------------
def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: max(1, path.stat().st_size // 2)])


def _flip(path: Path) -> None:
    data = bytearray(path.read_bytes())
    middle = len(data) // 2
    for i in range(middle, min(len(data), middle + 64)):
        data[i] ^= 0xFF
    path.write_bytes(bytes(data))


def _drop_key(path: Path, key: str) -> None:
    doc = json.loads(path.read_text())
    del doc[key]
    path.write_text(json.dumps(doc))


FIT_DAMAGE = {
    "truncated model npz": lambda fit: _truncate(fit / "model" / "nearest_frame.npz"),
    "flipped model npz": lambda fit: _flip(fit / "model" / "nearest_frame.npz"),
    "truncated model json": lambda fit: _truncate(fit / "model" / "nearest_frame.json"),
    "model json without names": lambda fit: _drop_key(fit / "model" / "nearest_frame.json", "names"),
    "truncated fit.json": lambda fit: _truncate(fit / "fit.json"),
    "fit.json without fit_seconds": lambda fit: _drop_key(fit / "fit.json", "fit_seconds"),
    "fit.json with text for a number": lambda fit: (fit / "fit.json").write_text(
        json.dumps({**json.loads((fit / "fit.json").read_text()), "peak_cpu_mib": "lots"})),
    "model folder gone": lambda fit: shutil.rmtree(fit / "model"),
    "fit.json with NaN seconds": lambda fit: (fit / "fit.json").write_text(
        (fit / "fit.json").read_text().replace('"fit_seconds": ', '"fit_seconds": NaN, "was": ', 1)),
}


@pytest.mark.parametrize("damage", list(FIT_DAMAGE))
def test_a_damaged_cached_fit_is_fitted_again_with_one_warning(env, capsys, damage):
    first = evaluate(_options(env))
    fit = env["cache"] / "fits" / "nearest-frame" / "hypernerf-smoke" / first.results["fit"]["key"]
    assert (fit / "fit.json").is_file()
    capsys.readouterr()
    FIT_DAMAGE[damage](fit)
    again = evaluate(_options(env))
    warnings = _warnings(capsys.readouterr().err)
    assert len(warnings) == 1 and "fitting again" in warnings[0] and str(fit) in warnings[0]
    assert again.results["timing"]["fit_cached"] is False
    assert again.results["fit"]["key"] == first.results["fit"]["key"]
    assert again.results["metrics"] == first.results["metrics"]
    # the fit cached anew is sound: the next run loads it, silently
    third = evaluate(_options(env))
    assert third.results["timing"]["fit_cached"] is True and not _warnings(capsys.readouterr().err)
    assert not list(fit.parent.glob(".*"))  # no partial folder, no lock file left


def test_a_damaged_fit_named_for_reuse_is_an_input_error_never_a_refit(env):
    first = evaluate(_options(env))
    key = first.results["fit"]["key"]
    fit = env["cache"] / "fits" / "nearest-frame" / "hypernerf-smoke" / key
    _truncate(fit / "model" / "nearest_frame.npz")
    with pytest.raises(InputError, match="cached_key.*damaged"):
        evaluate_with_fit(_options(env), cached_key=key)
    with pytest.raises(InputError, match="cached_key.*no cached fit 'no-such-key'"):
        evaluate_with_fit(_options(env), cached_key="no-such-key")


def test_a_named_cached_fit_answers_after_the_code_moved_the_key(env, monkeypatch):
    from methods.nearest_frame import NearestFrame
    from methods.registry import MethodSpec

    first = evaluate(_options(env)).results
    monkeypatch.setattr(MethodSpec, "code_digest", lambda spec: "other code")  # the key the code hashes to moves
    monkeypatch.setattr(NearestFrame, "fit", classmethod(lambda cls, *a, **k: pytest.fail("refitted")))
    again = evaluate_with_fit(_options(env), cached_key=first["fit"]["key"]).results
    assert again["fit"]["key"] == first["fit"]["key"] and again["timing"]["fit_cached"] is True
    assert again["metrics"] == first["metrics"] and "head_refit_of" not in again["fit"]
    with pytest.raises(InputError, match="cached_key or head_refit_from, not both"):
        evaluate_with_fit(_options(env), cached_key=first["fit"]["key"], head_refit_from=first["fit"]["key"])
    with pytest.raises(InputError, match="head_refit_from.*no cached fit"):
        evaluate_with_fit(_options(env), head_refit_from="no-such-key")
    with pytest.raises(pytest.fail.Exception, match="refitted"):  # the plain run wants the fit of the new key
        evaluate(_options(env))


# -- damaged generated scenes -----------------------------------------------------------------------------
@pytest.fixture
def cached_preset(smoke_base, tmp_path) -> dict:
    """The smoke preset as the runner caches it (cache/scenes/48px/smoke), copied from the generated one."""
    from benchmark.runner import resolve_scene

    cache = tmp_path / "cache"
    target = cache / "scenes" / f"{SMOKE_SIZE}px" / "smoke"
    shutil.copytree(smoke_base["scene"], target)
    assert resolve_scene("smoke", cache, size=SMOKE_SIZE) == target  # sound and the committed version
    first = sorted((target / "truth" / "levels").glob("*.npz"))[0]
    return {"cache": cache, "target": target, "npz": first}


SCENE_DAMAGE = {
    "truncated truth npz": lambda s: _truncate(s["npz"]),
    "flipped truth npz": lambda s: _flip(s["npz"]),
    "truth npz gone": lambda s: s["npz"].unlink(),
    "truncated scene_truth.json": lambda s: _truncate(s["target"] / "truth" / "scene_truth.json"),
    "scene_truth.json without frames": lambda s: _drop_key(s["target"] / "truth" / "scene_truth.json", "frames"),
    "truncated annotations": lambda s: _truncate(s["target"] / "annotations.json"),
    "truncated generator description": lambda s: _truncate(s["target"] / "bench4d_meta.json"),
}


@pytest.mark.parametrize("committed", [True, False], ids=["committed-digest", "no-digest"])
@pytest.mark.parametrize("damage", list(SCENE_DAMAGE))
def test_a_damaged_cached_preset_is_regenerated_with_one_warning(cached_preset, capsys, monkeypatch, damage,
                                                                 committed):
    import benchmark.synthetic.digest as digest
    from benchmark.runner import resolve_scene

    if not committed:  # a size with no committed digest: only reading the files can tell
        monkeypatch.setattr(digest, "expected_digest", lambda *a, **k: None)
    sound = digest.scene_digest(cached_preset["target"])
    SCENE_DAMAGE[damage](cached_preset)
    capsys.readouterr()
    root = resolve_scene("smoke", cached_preset["cache"], size=SMOKE_SIZE)
    warnings = _warnings(capsys.readouterr().err)
    assert len(warnings) == 1 and "damaged" in warnings[0] and "regenerating" in warnings[0]
    assert root == cached_preset["target"] and digest.scene_digest(root) == sound
    from benchmark.core.truth import check_truth

    check_truth(root)
    assert not [p for p in root.parent.iterdir() if p.name.startswith(".")]  # no lock or trash left


def test_damaged_truth_read_directly_is_an_input_error_naming_file_and_field(smoke_base, tmp_path):
    from benchmark.core.truth import load_truth

    scene = tmp_path / "scene"
    shutil.copytree(smoke_base["scene"], scene)
    truth = load_truth(scene)
    name = truth.training_frames[0]
    npz = scene / "truth" / "levels" / f"{name}.npz"
    _flip(npz)
    with pytest.raises(InputError, match=f"{name}.npz.*damaged truth file"):
        truth.levels(name)
    npz.write_bytes(b"")
    with pytest.raises(InputError, match="damaged truth file"):
        truth.depth(name)
    doc_path = scene / "truth" / "scene_truth.json"
    doc = json.loads(doc_path.read_text())
    del doc["frames"][1]["camera"]
    doc_path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"scene_truth.json: frames\[1\].camera: missing"):
        load_truth(scene)
    doc["frames"][1] = {**doc["frames"][0], "camera": {"width": 4}}
    doc_path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"frames\[1\].camera: not a camera"):
        load_truth(scene)
    del doc["catalogue"]["part"]
    doc_path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="catalogue.part"):
        load_truth(scene)


# -- concurrent writers of one results file ---------------------------------------------------------------
def _concurrent_run(options: EvalOptions, barrier) -> None:
    """One ``evaluate`` in a worker process. Both workers meet just before writing their predictions: without
    a lock both have then found no results file to archive. With it, the second waits for the first's
    lock, the meeting times out and each goes on in turn."""
    import threading

    import benchmark.predictions as predictions

    original = predictions.write_predictions

    def meet_then_write(*args, **kwargs):
        try:
            barrier.wait(timeout=3)
        except threading.BrokenBarrierError:
            pass
        return original(*args, **kwargs)

    predictions.write_predictions = meet_then_write
    evaluate(options)


def test_two_identical_runs_at_once_keep_both_records(env):
    from benchmark.results import find_results, load_results

    ctx = mp.get_context("spawn")
    barrier = ctx.Barrier(2)
    # concurrent_runs is recorded in the results file: it tells the two records apart
    workers = [ctx.Process(target=_concurrent_run, args=(_options(env, concurrent_runs=n), barrier))
               for n in (101, 102)]
    for w in workers:
        w.start()
    for w in workers:
        w.join(120)
    assert [w.exitcode for w in workers] == [0, 0]
    current = find_results(env["results"])
    assert current == [env["results"] / RUN / "seed0.json"]
    archived = sorted((env["results"] / "archive").rglob("seed0.json"))
    assert len(archived) == 1
    recorded = {load_results(p)["environment"]["concurrent_runs"] for p in (*current, *archived)}
    assert recorded == {101, 102}
    for path in (*current, *archived):  # each record kept with its predictions
        assert read_predictions(path.with_suffix(".predictions")).queries
    assert not [p for p in env["results"].rglob(".*")]  # no lock file left behind


# -- files given as folders ---------------------------------------------------------------------------------
@pytest.mark.parametrize("command", ["eval", "run-all"])
@pytest.mark.parametrize("option", ["--results-dir", "--cache-dir"])
def test_a_file_given_as_a_folder_option_is_one_line_naming_it(env, tmp_path, capsys, command, option):
    a_file = tmp_path / "a-file"
    a_file.write_text("not a folder\n")
    folders = {"--results-dir": str(env["results"]), "--cache-dir": str(env["cache"])}
    for given in (a_file, a_file / "below"):
        folders[option] = str(given)
        which = ["--method", "nearest-frame", "--scene"] if command == "eval" else ["--methods", "nearest-frame",
                                                                                    "--seeds", "0", "--scenes"]
        argv = [command, *which, str(env["scene"]), "--quiet"] + [x for kv in folders.items() for x in kv]
        assert main(argv) == 2
        line = _error_line(capsys.readouterr().err)
        assert option in line and str(a_file) in line
    assert a_file.read_text() == "not a folder\n"


def test_evaluate_refuses_a_file_as_results_or_cache_folder(env, tmp_path):
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    with pytest.raises(InputError, match="results_dir: is a file"):
        evaluate(_options({**env, "results": a_file}))
    with pytest.raises(InputError, match="cache_dir: is a file"):
        evaluate(_options({**env, "cache": a_file}))


# -- unanswered queries -------------------------------------------------------------------------------------
def test_eval_and_score_of_its_folder_agree_when_queries_are_unanswered(env, tmp_path, capsys, monkeypatch):
    from methods.nearest_frame import NearestFrameModel

    monkeypatch.setattr(NearestFrameModel, "supports", frozenset({"agnostic"}))
    outcome = evaluate(_options(env))
    doc = outcome.results
    assert sorted(doc["unanswered_queries"]) == ["broken bar", "closed box", "intact bar", "open box"]
    # a kind declined as a whole: no full mean (no row in that table), no answered-only mean
    assert doc["metrics"]["Acc"] is None and doc["metrics"]["Acc_answered"] is None
    assert (doc["metrics"]["sensitive_queries"], doc["metrics"]["asked_sensitive_queries"]) == (0, 4)
    pred_dir = outcome.path.with_suffix(".predictions")
    assert read_predictions(pred_dir).info["unanswered_queries"] == doc["unanswered_queries"]
    gt = env["scene"] / "annotations.json"
    out = tmp_path / "scored.json"
    capsys.readouterr()
    assert main(["score", "--gt", str(gt), "--pred", str(pred_dir), "--out", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "unanswered by the method" in err and "open box" in err
    scored = json.loads(out.read_text())
    metrics = scored["metrics"]["dataset"]
    for name in ("mIoU", "mAcc", "Acc", "vIoU", "Acc_answered", "agnostic_queries", "sensitive_queries",
                 "asked_sensitive_queries", "frames_scored", "absentFP"):
        assert metrics[name] == pytest.approx(doc["metrics"][name]) if doc["metrics"][name] is not None \
            else metrics[name] is None, name
    assert sorted(u["query"] for u in scored["unanswered"]) == sorted(doc["unanswered_queries"])
    assert {u["kind"] for u in scored["unanswered"]} == {"sensitive"}
    assert scored["queries"] == doc["scores"]["queries"]

    # a folder written before the predictions listed them (and before they were compressed): the results
    # file beside it does
    compressed = pred_dir / "predictions.json.gz"
    raw = read_json(compressed)
    del raw["info"]["unanswered_queries"]
    compressed.unlink()
    (pred_dir / "predictions.json").write_text(json.dumps(raw))
    assert main(["score", "--gt", str(gt), "--pred", str(pred_dir), "--out", str(out), "--quiet"]) == 0
    assert "listed by the results file" in capsys.readouterr().err
    assert json.loads(out.read_text())["metrics"]["dataset"]["mIoU"] == pytest.approx(doc["metrics"]["mIoU"])
    # a copy with neither is missing answers: still an input error, in one line
    bare = tmp_path / "bare"
    shutil.copytree(pred_dir, bare)
    assert main(["score", "--gt", str(gt), "--pred", str(bare), "--quiet"]) == 2
    assert "missing" in _error_line(capsys.readouterr().err)


def test_declared_unanswered_queries_are_listed_not_scored_and_checked(tmp_path):
    from annotations.format import load_annotations
    from benchmark.metrics import ScoreConfig, score_scene

    gt, pred = _score_inputs(tmp_path)
    aset = load_annotations(gt)
    aset.queries.append(Query(2, "open cookie", "sensitive", base=1, intervals=[(1, 1)]))
    declined = read_predictions(pred)
    declined.info["unanswered_queries"] = ["open cookie"]
    result = score_scene(aset, declined, ScoreConfig())
    assert result.unanswered == ["open cookie"] and [q.query for q in result.queries] == ["cookie"]
    assert np.isnan(result.summary()["Acc"]) and np.isnan(result.summary()["Acc_answered"])  # kind declined whole
    assert result.summary()["mIoU"] == 100.0
    for listed, match in ((["cookie"], "which the predictions answer"), (["nope"], "not a query"),
                          ("open cookie", "list of query texts")):
        declined.info["unanswered_queries"] = listed
        with pytest.raises(InputError, match=match):
            score_scene(aset, declined, ScoreConfig())


# -- pinned dependency versions ------------------------------------------------------------------------------
def test_constraints_pin_every_dependency_within_its_declared_bounds():
    tomllib = pytest.importorskip("tomllib")
    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    root = Path(__file__).resolve().parents[1]
    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    declared = [Requirement(r) for r in project["dependencies"]]
    declared += [Requirement(r) for extra in ("text", "test") for r in project["optional-dependencies"][extra]]
    pins = {}
    for line in (root / "constraints.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            name, sep, version = line.partition("==")
            assert sep and version, f"constraints.txt: {line!r} is not NAME==VERSION"
            pins[canonicalize_name(name)] = version
    assert "torch" not in pins  # pinned by the Makefile's TORCH_SPEC
    for req in declared:
        name = canonicalize_name(req.name)
        if name == "torch":
            continue
        assert name in pins, f"constraints.txt does not pin {req.name}"
        assert req.specifier.contains(pins[name], prereleases=True), f"{req.name}=={pins[name]} outside {req.specifier}"
    makefile = (root / "Makefile").read_text()
    assert makefile.count("-c $(CONSTRAINTS) -e") == 2 and "CONSTRAINTS ?= constraints.txt" in makefile
