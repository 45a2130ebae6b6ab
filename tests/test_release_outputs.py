"""The 4D LangSplat release's evaluation outputs converted to bench4d predictions and scored."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from benchmark.core.annotation import decode_mask
from benchmark.core.errors import InputError
from benchmark.core.imageio import write_image
from conftest import keep_paper_split


def release_run_folder(aset, folder, *, flip_time=False):
    """What the release's eval.py writes with --visualize_results --detail_results, made from ``aset``'s
    truth: ``<image id + 1>/chosen_<query>.png`` and ``video-query-results-<query>.csv`` (similarity 0.9
    inside a time query's intervals, 0.1 outside; swapped with ``flip_time``)."""
    for (qid, fid), rle in aset.masks.items():
        query = aset.query(qid)
        texts = [query.text] + [q.text for q in aset.sensitive_queries if q.base == qid]
        for text in texts:
            write_image(folder / f"{fid + 1:05d}" / f"chosen_{text}.png", decode_mask(rle).astype(np.uint8) * 255)
    for q in aset.sensitive_queries:
        times = sorted(f.time_index for f in aset.frames)
        inside = [any(lo <= t <= hi for lo, hi in q.intervals) != flip_time for t in times]
        with open(folder / f"video-query-results-{q.text}.csv", "w", newline="", encoding="utf-8") as handle:
            writer = csv.writer(handle)
            writer.writerow(["Type"] + [f"frame_{t}_iou" for t in times])
            writer.writerow(["clip similarity"] + [0.5] * len(times))
            writer.writerow(["clip meaniou"] + [1.0] * len(times))
            writer.writerow(["video similarity"] + [0.9 if yes else 0.1 for yes in inside])
            writer.writerow(["video meaniou"] + [1.0] * len(times))
    return folder


@pytest.fixture(scope="module")
def release_scene(tmp_path_factory):
    from annotations.format import load_annotations, save_annotations
    from annotations.release import export_release
    from benchmark.synthetic.generate import generate

    folder = generate("smoke", tmp_path_factory.mktemp("release") / "smoke", size=48)
    aset = load_annotations(folder / "annotations.json")
    keep_paper_split(aset)  # the release annotates one camera: the video's, not the novel-view path
    save_annotations(aset, folder / "annotations.json", overwrite=True)
    export_release(aset, folder / "annotations", frame_base=1)
    return folder, aset


def score(gt, pred, out):
    from benchmark.cli import main

    assert main(["score", "--gt", str(gt), "--pred", str(pred), "--out", str(out), "--quiet"]) == 0
    return json.loads(out.read_text())["metrics"]["dataset"]


def test_release_outputs_of_the_truth_convert_and_score_perfectly(release_scene, tmp_path):
    from benchmark.cli import main
    from benchmark.predictions import read_predictions

    folder, aset = release_scene
    run = release_run_folder(aset, tmp_path / "run")
    assert main(["convert", "release", "--run", str(run), "--annotations", str(folder / "annotations"),
                 "--dataset", "hypernerf", "--scene", str(folder), "--out", str(tmp_path / "preds")]) == 0
    preds = read_predictions(tmp_path / "preds")
    assert set(preds.queries) == {q.text for q in aset.queries}
    sensitive = aset.sensitive_queries[0]
    assert preds.queries[sensitive.text].kind == "sensitive" and len(preds.queries[sensitive.text].scores) > 0
    metrics = score(folder / "annotations.json", tmp_path / "preds", tmp_path / "scored.json")
    assert metrics["mIoU"] == pytest.approx(100.0) and metrics["mAcc"] == pytest.approx(100.0)
    assert metrics["AUC"] == pytest.approx(100.0)  # the similarities rank every present frame first

    # time decisions turned around: the masks still score, the decisions no longer do
    flipped = release_run_folder(aset, tmp_path / "flipped", flip_time=True)
    from benchmark.release_outputs import convert_release_outputs

    convert_release_outputs(flipped, folder / "annotations", tmp_path / "preds-flipped", frame_base=1)
    worse = score(folder / "annotations.json", tmp_path / "preds-flipped", tmp_path / "scored-flipped.json")
    assert worse["mIoU"] == pytest.approx(100.0)
    assert worse["Acc"] < metrics["Acc"] and worse["AUC"] < metrics["AUC"]


def test_missing_release_outputs_are_one_line_errors(release_scene, tmp_path):
    from benchmark.release_outputs import convert_release_outputs, read_similarity_csv

    folder, aset = release_scene
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="--visualize_results"):
        convert_release_outputs(tmp_path / "empty", folder / "annotations", tmp_path / "out", frame_base=1)
    with pytest.raises(InputError, match="release run folder not found"):
        convert_release_outputs(tmp_path / "nowhere", folder / "annotations", tmp_path / "out", frame_base=1)
    bad = tmp_path / "bad.csv"
    bad.write_text("Type,frame_0_iou\nvideo similarity,abc\n")
    with pytest.raises(InputError, match="not a number"):
        read_similarity_csv(bad, "video similarity")
    with pytest.raises(InputError, match="no row"):
        read_similarity_csv(bad, "clip similarity")


def test_score_reads_the_release_annotation_folder_against_its_scene(release_scene, tmp_path, capsys):
    from benchmark.cli import main
    from benchmark.release_outputs import convert_release_outputs

    folder, aset = release_scene
    # time decisions turned around, so the scores are not all 100
    run = release_run_folder(aset, tmp_path / "run", flip_time=True)
    preds = convert_release_outputs(run, folder / "annotations", tmp_path / "preds", frame_base=1)
    from_json = score(folder / "annotations.json", preds, tmp_path / "from-json.json")
    assert from_json["Acc"] < 100.0
    for gt in (folder / "annotations", folder / "annotations" / "train" / "_annotations.coco.json"):
        out = tmp_path / f"from-{gt.name}.json"
        assert main(["score", "--gt", str(gt), "--scene", str(folder), "--pred", str(preds), "--out", str(out),
                     "--quiet"]) == 0
        assert json.loads(out.read_text())["metrics"]["dataset"] == from_json

    capsys.readouterr()
    assert main(["score", "--gt", str(folder / "annotations"), "--pred", str(preds), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--scene DIR" in err and "release" in err and "\n" not in err
    assert main(["score", "--gt", str(folder / "annotations.json"), "--scene", str(folder), "--pred", str(preds)]) == 2
    assert "--scene without a release-layout --gt" in capsys.readouterr().err
    # the release's files are inputs: --out may not replace one
    video = folder / "annotations" / "video_annotations.json"
    before = video.read_bytes()
    assert main(["score", "--gt", str(folder / "annotations"), "--scene", str(folder), "--pred", str(preds),
                 "--out", str(video)]) == 2
    assert "is an input of this command" in capsys.readouterr().err and video.read_bytes() == before
