"""Evaluation splits, scene seeds and the machine in every record: the paper's split (train ``i % 4 == 0``,
score ``i % 4 == 2``), the novel-view split (the scored times from a camera path off the training path, with
exact truth), one fit answering both, results of both splits side by side, seeds that generate their own
scene, legacy results read as ``legacy-dense``, and the machine each run recorded."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from benchmark.core.errors import InputError
from benchmark.core.scene import EVAL_SPLITS, LEGACY_EVAL_SPLIT, split_frame_names
from benchmark.synthetic import PRESETS, TruthAccessError, generate, load_truth
from benchmark.synthetic.generate import preset_rng
from benchmark.synthetic.layouts import NOVEL_CAMERA_ID, NOVEL_VIEW
from benchmark.synthetic.model import Catalogue, FrameContext
from benchmark.synthetic.splits import angles_deg, multi_view_factor


def _meta(root: Path) -> dict:
    return json.loads((root / "bench4d_meta.json").read_text())


@pytest.fixture(scope="module")
def smoke48(tmp_path_factory) -> Path:
    return Path(generate("smoke", tmp_path_factory.mktemp("splits") / "smoke", size=48))


# -- the scenes ---------------------------------------------------------------------------------------
def test_the_paper_split_trains_on_every_fourth_frame_and_scores_the_frames_two_after(smoke48):
    from annotations.format import load_annotations
    from benchmark.loaders import load_scene

    scene = load_scene(smoke48)
    n = PRESETS["smoke"].default_frames
    video = {f.time_index: f for f in scene.frames if f.camera_id == "0"}
    assert sorted(video) == list(range(n))
    assert [t for t, f in sorted(video.items()) if f.split == "train"] == list(range(0, n, 4))
    assert [t for t, f in sorted(video.items()) if f.split == "test"] == list(range(2, n, 4))
    assert {f.split for t, f in video.items() if t % 2} == {"val"}  # neither trained on nor scored
    # the loader, the generator's description and the annotations name the same frames per split
    aset = load_annotations(smoke48 / "annotations.json", scene=scene)
    recorded = {split: entry["frames"] for split, entry in _meta(smoke48)["splits"].items()}
    assert scene.metadata["eval_splits"] == recorded == aset.info["splits"]
    assert set(recorded) == set(EVAL_SPLITS)
    assert recorded["paper"] == [video[t].name for t in range(2, n, 4)]
    assert sorted(recorded["paper"] + recorded["novel-view"]) == sorted(f.name for f in aset.frames)
    # what a method may know of the scene comes from the training views alone
    novel = [f for f in scene.frames if f.camera_id == NOVEL_CAMERA_ID]
    assert novel and all(f.split == "test" for f in novel)


def test_a_novel_view_frame_is_off_the_training_path_and_its_truth_is_exact(smoke48):
    from annotations.format import load_annotations
    from benchmark.synthetic.digest import expected_digest, scene_digest
    from benchmark.synthetic.render import instances, render

    # the committed digest of the preset covers the novel-view frames: the generator makes exactly these
    assert scene_digest(smoke48) == expected_digest("smoke", 48)
    truth = load_truth(smoke48)
    n = truth.num_frames
    scene_def = PRESETS["smoke"].build(preset_rng("smoke", 0), n)
    catalogue = Catalogue.build(scene_def.wholes)
    novel = sorted((f for f in truth.frames.values() if f.camera_id == NOVEL_CAMERA_ID), key=lambda f: f.time_index)
    training = [f.camera for f in truth.frames.values() if f.split == "train"]
    assert [f.time_index for f in novel] == list(range(2, n, 4))  # one per scored time
    angles = angles_deg([f.camera for f in novel], training, scene_def.focus_center)
    assert angles.min() >= NOVEL_VIEW.min_angle_deg
    same_time = {f.time_index: f.camera for f in truth.frames.values() if f.camera_id == "0"}
    for frame, row in zip(novel, angles):
        # seen from the focus, the novel camera is its time's training-path camera turned by the stated offsets
        turn = angles_deg([frame.camera], [same_time[frame.time_index]], scene_def.focus_center)[0, 0]
        assert NOVEL_VIEW.elevation_deg - 1 < turn < np.hypot(NOVEL_VIEW.azimuth_deg, NOVEL_VIEW.elevation_deg) + 1
        with pytest.raises(TruthAccessError):  # scored frames: truth for the harness only
            truth.levels(frame.name)
        # the truth maps are what rendering the scene from that camera gives, pixel for pixel
        again = render(instances(scene_def, catalogue, FrameContext(frame.time_index, n)), frame.camera,
                       scene_def.light)
        np.testing.assert_array_equal(truth.id_maps(frame.name, allow_eval=True), again.ids)
    aset = load_annotations(smoke48 / "annotations.json")
    frame = next(f for f in aset.frames if f.name == novel[0].name)
    ids = truth.levels(frame.name, allow_eval=True)
    for query in aset.agnostic_queries:
        level, wanted = truth.ids_named(query.text)
        np.testing.assert_array_equal(aset.get_mask(query.id, frame.id), np.isin(ids[level], wanted))


def test_every_scene_records_its_splits_and_their_multi_view_factor(smoke48, tmp_path):
    splits = _meta(smoke48)["splits"]
    paper, novel = splits["paper"], splits["novel-view"]
    assert paper["multi_view_factor"] > 0 and paper["multi_view_factor"] == novel["multi_view_factor"]
    assert paper["training_frames"] == PRESETS["smoke"].default_frames // 4
    assert novel["eval_angle_deg"]["min"] >= NOVEL_VIEW.min_angle_deg
    assert novel["eval_angle_deg"]["mean"] > paper["eval_angle_deg"]["mean"] > 0
    assert novel["camera_offset_deg"] == {"azimuth": NOVEL_VIEW.azimuth_deg, "elevation": NOVEL_VIEW.elevation_deg,
                                          "min_angle": NOVEL_VIEW.min_angle_deg}
    # a rig sees every time step from several cameras: its held-out camera is both splits, its factor unbounded
    from benchmark.loaders import load_scene

    rig = generate("smoke", tmp_path / "rig", layout="neu3d", size=24, frames=5, views=3)
    held_out = [f.name for f in load_scene(rig).frames if f.camera_id == "cam00"]
    record = _meta(rig)["splits"]
    assert record["paper"]["frames"] == record["novel-view"]["frames"] == held_out
    assert record["paper"]["multi_camera"] is True and record["paper"]["multi_view_factor"] is None
    assert load_scene(rig).metadata["eval_splits"] == {"paper": held_out, "novel-view": held_out}


def test_the_multi_view_factor_has_the_known_answer_for_a_sliding_box(tmp_path):
    """One box slides along x by 0.01 per time step; the camera turns 6 degrees about the focus per step at
    distance 1: camera speed pi/30 per step over scene speed 0.01 per step."""
    from types import SimpleNamespace

    from benchmark.core.scene import Camera
    from benchmark.core.truth import save_levels
    from benchmark.synthetic import csg
    from benchmark.synthetic import textures as tx
    from benchmark.synthetic.model import Piece, SceneDef, whole
    from benchmark.synthetic.transforms import look_at_opencv, spherical, translation

    box = whole("box", pieces=[Piece(csg.Box((0.05, 0.05, 0.05)), tx.Solid((0.5, 0.5, 0.5)))],
                pose=lambda ctx: translation((0.01 * ctx.time_index, 0.0, 0.0)))
    scene = SceneDef("t", [box], [], (0.0, 0.0, 0.0), 0.1, 9)
    catalogue = Catalogue.build(scene.wholes)
    records = []
    for k, t in enumerate((0, 4, 8)):
        eye = spherical((0.0, 0.0, 0.0), 1.0, np.radians(6.0 * t), 0.0)
        cam = Camera(8, 8, 8.0, 8.0, 4.0, 4.0, look_at_opencv(eye, (0.0, 0.0, 0.0)))
        ids = np.zeros((3, 8, 8), np.uint16)
        ids[:, 2:6, 2:6] = 1  # the box's pixels at one unit in front of the camera
        depth = np.full((8, 8), np.inf, np.float32)
        depth[2:6, 2:6] = 1.0
        save_levels(tmp_path, f"f{k}", ids, depth)
        records.append(SimpleNamespace(name=f"f{k}", time_index=t, camera=cam))
    got = multi_view_factor(records, scene, catalogue, tmp_path)
    assert got["camera_deg_per_step"] == pytest.approx(6.0, rel=1e-6)
    assert got["scene_speed_per_step"] == pytest.approx(0.01, rel=1e-6)
    assert got["multi_view_factor"] == pytest.approx(np.radians(6.0) / 0.01, rel=1e-6)
    still = SceneDef("t", [whole("box", pieces=box.pieces)], [], (0.0, 0.0, 0.0), 0.1, 9)
    assert multi_view_factor(records, still, Catalogue.build(still.wholes), tmp_path)["multi_view_factor"] is None


def test_a_split_s_frames_are_selected_from_either_record():
    names = ["a", "b", "nv_b"]
    recorded = {"paper": ["b", "a"], "novel-view": ["nv_b"]}
    assert split_frame_names("paper", names, recorded) == ["a", "b"]  # in the order given
    assert split_frame_names("novel-view", names, recorded) == ["nv_b"]
    assert split_frame_names("paper", names, None) == names  # nothing recorded: every held-out frame
    for split, record, words in (("novel-view", None, "records no 'novel-view'"),
                                 ("novel-view", {"paper": ["a"]}, "recorded: paper"),
                                 ("dense", recorded, "unknown evaluation split"),
                                 ("paper", {"paper": "a"}, "list of frame names")):
        with pytest.raises(InputError, match=words):
            split_frame_names(split, names, record, source="annotations.json")


# -- runs -----------------------------------------------------------------------------------------------
def _run(env, **kw):
    from benchmark.runner import EvalOptions, evaluate

    return evaluate(EvalOptions(method="nearest-frame", scene=str(env["scene"]), results_dir=env["results"],
                                cache_dir=env["cache"], quiet=True, timing_frames=1, timing_repeats=1, **kw))


def test_one_fit_answers_both_splits_and_their_results_sit_side_by_side(env, capsys):
    import torch

    from benchmark.cli import main
    from benchmark.results import find_results, runs_table, seed_summary

    paper = _run(env)
    novel = _run(env, split="novel-view")
    base = env["results"] / "synthetic" / "smoke" / "nearest-frame" / "oracle"
    assert paper.path == base / "seed0.json" and novel.path == base / "novel-view" / "seed0.json"
    assert (paper.results["split"], novel.results["split"]) == ("paper", "novel-view")
    assert novel.results["fit"]["key"] == paper.results["fit"]["key"] and novel.results["fit"]["cached"]
    scored = {doc["split"]: set(doc["score_config"]["eval_frames"]) for doc in (paper.results, novel.results)}
    assert scored["paper"] and scored["novel-view"] and not scored["paper"] & scored["novel-view"]
    assert all(name.startswith("novel_") for name in scored["novel-view"])
    # the machine and the scene instance are recorded
    env_doc = paper.results["environment"]
    assert env_doc["cpu_capability"] == torch.backends.cpu.get_cpu_capability() and env_doc["gpu"] is None
    assert paper.results["scene_seed"] == 0 and paper.results["scene_info"]["generated"]["digest"]
    runs = runs_table(find_results(env["results"]))
    assert sorted(runs["split"]) == ["novel-view", "paper"]
    assert set(seed_summary(runs)["split"]) == {"novel-view", "paper"}  # never averaged together
    # the command line takes the split too, and knows no other
    args = ["eval", "--method", "nearest-frame", "--scene", str(env["scene"]), "--results-dir", str(env["results"]),
            "--cache-dir", str(env["cache"]), "--quiet"]
    assert main(args + ["--split", "novel-view", "--seed", "1"]) == 0
    assert (base / "novel-view" / "seed1.json").is_file()
    with pytest.raises(SystemExit):
        main(args + ["--split", "dense"])
    assert "invalid choice: 'dense'" in capsys.readouterr().err


def test_a_seed_generates_its_own_scene_of_the_preset(tmp_path):
    from benchmark.runner import EvalOptions, evaluate, preset_folder

    def run(seed: int):
        return evaluate(EvalOptions(method="nearest-frame", scene="smoke", seed=seed, preset_size=24,
                                    results_dir=tmp_path / "results", cache_dir=tmp_path / "cache", quiet=True,
                                    timing_frames=1, timing_repeats=1)).results

    zero, one = run(0), run(1)
    assert preset_folder(tmp_path / "cache", "smoke", 24, 1) == tmp_path / "cache" / "scenes" / "24px" / "seed1" / "smoke"
    assert (tmp_path / "cache" / "scenes" / "24px" / "seed1" / "smoke" / "annotations.json").is_file()
    assert (zero["scene_seed"], one["scene_seed"]) == (0, 1) and zero["scene"] == one["scene"] == "smoke"
    assert one["scene_info"]["generated"]["seed"] == 1
    assert zero["scene_info"]["generated"]["digest"] != one["scene_info"]["generated"]["digest"]


def test_results_of_before_the_splits_read_as_legacy_dense_with_their_machine(tmp_path, monkeypatch):
    from benchmark.results import results_path, runs_table, scene_status, write_results
    from benchmark.synthetic import digest

    def doc(**extra) -> dict:
        return {"method": "m", "dataset": "synthetic", "scene": "smoke", "track": "oracle", "seed": 0,
                "metrics": {"mIoU": 50.0}, "timing": {}, **extra}

    old_env = {"device": "cpu", "processor": "AMD EPYC"}
    write_results(results_path(tmp_path, "synthetic", "smoke", "m", "oracle", 0), doc(environment=old_env))
    new_env = {"device": "cpu", "processor": "AMD EPYC 7B13", "cpu_capability": "AVX2", "gpu": None}
    write_results(results_path(tmp_path, "synthetic", "smoke", "m", "oracle", 0, "novel-view"),
                  doc(split="novel-view", scene_seed=2, environment=new_env))
    write_results(results_path(tmp_path, "synthetic", "smoke", "m", "oracle", 1, "novel-view"),
                  doc(seed=1, split="novel-view", environment={"device": "cuda:0", "gpu": "NVIDIA H200"}))
    write_results(results_path(tmp_path, "synthetic", "smoke", "m", "oracle", 2), doc(seed=2))
    runs = runs_table(sorted(tmp_path.rglob("seed*.json")))
    got = runs.set_index(["split", "seed"])
    assert got.loc[(LEGACY_EVAL_SPLIT, 0), ["scene_seed", "cpu_model", "cpu_capability", "machine_kind"]].tolist() \
        == [0, "AMD EPYC", "", "AMD EPYC"]
    assert got.loc[("novel-view", 0), ["scene_seed", "machine_kind"]].tolist() == [2, "AMD EPYC 7B13 (avx2)"]
    assert got.loc[("novel-view", 1), ["gpu", "machine_kind"]].tolist() == ["NVIDIA H200", "NVIDIA H200"]
    assert got.loc[(LEGACY_EVAL_SPLIT, 2), "machine_kind"] == "unknown"
    # the digest a run is checked against is the committed one of its scene seed
    manifest = tmp_path / "digests.json"
    manifest.write_text(json.dumps({"presets": {"smoke": {"48px-seed0": "a" * 24, "48px-seed1": "b" * 24}}}))
    monkeypatch.setattr(digest, "DIGESTS_FILE", manifest)
    seeded = doc(scene_info={"generated": {"preset": "smoke", "size": 48, "seed": 1, "digest": "b" * 24}})
    assert scene_status(seeded) == ("b" * 24, True)
    seeded["scene_info"]["generated"]["seed"] = 0
    assert scene_status(seeded) == ("b" * 24, False)


def test_run_all_takes_the_split_and_reruns_a_result_that_recorded_none(env, capsys):
    from benchmark.cli import main
    from benchmark.results import load_results, write_results

    argv = ["run-all", "--methods", "nearest-frame", "--scenes", str(env["scene"]), "--seeds", "0",
            "--results-dir", str(env["results"]), "--cache-dir", str(env["cache"]), "--quiet"]
    assert main(argv + ["--split", "novel-view"]) == 0
    assert main(argv) == 0
    assert main(argv + ["--split", "novel-view"]) == 0
    assert "1 run(s) (1 reused)" in capsys.readouterr().out
    base = env["results"] / "synthetic" / "smoke" / "nearest-frame" / "oracle"
    assert load_results(base / "novel-view" / "seed0.json")["split"] == "novel-view"
    # a file written before splits were recorded (the dense split) is kept in the archive and run again
    old = load_results(base / "seed0.json")
    del old["split"]
    write_results(base / "seed0.json", old)
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert "1 run(s) (0 reused)" in captured.out and "scored the legacy-dense split" in captured.err
    assert (env["results"] / "archive" / "split-legacy-dense" / "synthetic" / "smoke" / "nearest-frame" / "oracle"
            / "seed0.json").is_file()
    assert load_results(base / "seed0.json")["split"] == "paper"
