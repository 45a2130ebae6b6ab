"""One output guard for every command that writes (``score``, ``convert``, ``data show``, ``eval``): a target
that resolves, through symlinks or hard links, to an input file or into an input folder (scene folders
included) is refused before anything is written, and every input stays byte-identical."""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import pytest

from benchmark.cli import main
from benchmark.core.errors import InputError
from conftest import keep_paper_split


def digest(root: Path) -> dict[str, str]:
    """Every file under ``root`` (links followed) by its content hash."""
    out = {}
    for dirpath, _, files in os.walk(root, followlinks=True):
        for name in files:
            p = Path(dirpath) / name
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def one_error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.fixture(scope="module")
def release_scene(tmp_path_factory):
    """The smoke preset with its annotations also in the release's layout (``annotations/``), and
    predictions of its truth."""
    from annotations.format import load_annotations
    from annotations.release import export_release
    from benchmark.predictions import QueryPrediction, ScenePredictions, write_predictions
    from benchmark.synthetic.generate import generate

    base = tmp_path_factory.mktemp("outputs")
    folder = generate("smoke", base / "smoke", size=48)
    aset = load_annotations(folder / "annotations.json")
    keep_paper_split(aset)  # the release annotates one camera: the video's, not the novel-view path
    export_release(aset, folder / "annotations", frame_base=1)
    preds = ScenePredictions(scene=aset.scene, method="oracle")
    for q in aset.queries:
        frames = aset.annotated_frames(q.id)
        p = QueryPrediction(q.text, kind=q.kind, masks={f.name: aset.get_mask(q.id, f.id) for f in frames})
        if q.kind == "sensitive":
            p.scores = {f.name: float(q.holds_at(f.time_index)) for f in frames}
        preds.add(p)
    write_predictions(base / "pred-json", preds)
    write_predictions(base / "pred-png", preds, layout="png")
    return {"scene": folder, "aset": aset, "base": base}


def _copy(release_scene, tmp_path: Path) -> tuple[Path, Path]:
    scene = shutil.copytree(release_scene["scene"], tmp_path / release_scene["scene"].name, symlinks=True)
    pred = shutil.copytree(release_scene["base"] / "pred-json", tmp_path / "pred")
    return Path(scene), Path(pred)


def test_score_never_writes_into_the_scene_folder_of_a_release_layout_gt(release_scene, tmp_path, capsys):
    scene, pred = _copy(release_scene, tmp_path)
    before = digest(scene)
    frame = next(p for p in sorted(scene.rglob("*.png")) if "rgb" in p.parts)
    targets = [scene / "dataset.json", scene / "metadata.json", frame, scene / "new-results.json",
               scene / "camera" / "x.json"]
    for target in targets:
        rc = main(["score", "--gt", str(scene / "annotations"), "--scene", str(scene), "--pred", str(pred),
                   "--quiet", "--out", str(target)])
        assert rc == 2, target
        line = one_error_line(capsys.readouterr().err)
        assert "--out" in line
    assert digest(scene) == before
    assert main(["score", "--gt", str(scene / "annotations"), "--scene", str(scene), "--pred", str(pred),
                 "--quiet", "--out", str(tmp_path / "ok.json")]) == 0


def test_score_out_through_a_symlinked_mask_folder_never_replaces_a_mask(release_scene, tmp_path, capsys):
    elsewhere = shutil.copytree(release_scene["base"] / "pred-png" / "masks", tmp_path / "elsewhere")
    pred = tmp_path / "pred"
    (pred / "masks").mkdir(parents=True)
    shutil.copy(release_scene["base"] / "pred-png" / "scores.json", pred / "scores.json")
    for folder in Path(elsewhere).iterdir():
        (pred / "masks" / folder.name).symlink_to(folder, target_is_directory=True)
    gt = release_scene["scene"] / "annotations.json"
    before = digest(tmp_path)
    victim = next(Path(elsewhere).rglob("*.png"))
    through_link = pred / "masks" / victim.parent.name / victim.name
    for target in (through_link, victim, pred / "masks" / victim.parent.name / "new.json"):
        assert main(["score", "--gt", str(gt), "--pred", str(pred), "--quiet", "--out", str(target)]) == 2, target
        assert "--out" in one_error_line(capsys.readouterr().err)
    assert digest(tmp_path) == before


def test_convert_never_writes_into_its_inputs(release_scene, tmp_path, capsys):
    from test_release_outputs import release_run_folder

    scene, _ = _copy(release_scene, tmp_path)
    run = release_run_folder(release_scene["aset"], tmp_path / "run")
    before_run, before_scene = digest(run), digest(scene)
    base = ["convert", "release", "--run", str(run), "--annotations", str(scene / "annotations"),
            "--dataset", "hypernerf", "--scene", str(scene)]
    for out in (run, run / "preds", scene, scene / "annotations", scene / "preds", scene / "annotations" / "train"):
        assert main([*base, "--out", str(out), "--overwrite"]) == 2, out
        assert "--out" in one_error_line(capsys.readouterr().err)
    assert digest(run) == before_run and digest(scene) == before_scene
    assert main([*base, "--out", str(tmp_path / "preds")]) == 0


def test_data_show_never_replaces_a_scene_file(release_scene, tmp_path, capsys):
    scene, _ = _copy(release_scene, tmp_path)
    before = digest(scene)
    frame = next(p for p in sorted(scene.rglob("*.png")) if "rgb" in p.parts)
    (tmp_path / "link.png").symlink_to(frame)
    os.link(frame, tmp_path / "hard.png")
    for out in (frame, tmp_path / "link.png", tmp_path / "hard.png", scene / "sheet.png"):
        assert main(["data", "show", str(scene), "--out", str(out), "--frames", "1"]) == 2, out
        assert "--out" in one_error_line(capsys.readouterr().err)
    assert digest(scene) == before
    assert (tmp_path / "hard.png").read_bytes() == frame.read_bytes()


def test_eval_never_writes_its_results_into_the_scene_folder(env, tmp_path, capsys):
    scene = Path(shutil.copytree(env["scene"], tmp_path / env["scene"].name))
    before = digest(scene)
    for results in (scene, scene / "results", scene / "rgb"):
        rc = main(["eval", "--method", "nearest-frame", "--scene", str(scene), "--results-dir", str(results),
                   "--cache-dir", str(env["cache"]), "--quiet"])
        assert rc == 2, results
        line = one_error_line(capsys.readouterr().err)
        assert "results" in line
    assert digest(scene) == before


# -- the guard itself ------------------------------------------------------------------------------------
def test_guard_output_follows_links_and_folders(tmp_path):
    from benchmark.core.outputs import guard_output

    inputs = tmp_path / "in"
    (inputs / "sub").mkdir(parents=True)
    (inputs / "a.json").write_text("{}")
    (inputs / "sub" / "b.png").write_bytes(b"x")
    single = tmp_path / "single.json"
    single.write_text("{}")
    (tmp_path / "link-dir").symlink_to(inputs / "sub", target_is_directory=True)
    (tmp_path / "link-file").symlink_to(single)
    os.link(single, tmp_path / "hard.json")
    os.link(inputs / "sub" / "b.png", tmp_path / "hard.png")
    ins = [inputs, single]
    refused = [inputs / "a.json", inputs / "new.json", inputs / "sub" / "c" / "d.json", inputs, single,
               tmp_path / "link-dir" / "b.png", tmp_path / "link-dir" / "new.png", tmp_path / "link-file",
               tmp_path / "hard.json", tmp_path / "hard.png", tmp_path / "x" / ".." / "single.json"]
    for target in refused:
        with pytest.raises(InputError, match="--out"):
            guard_output(target, ins, option="--out")
    for target in (tmp_path / "fine.json", tmp_path / "deeper" / "fine.json", tmp_path / "in-sibling" / "x"):
        guard_output(target, ins, option="--out")
    # an input folder's parent is not an input: writing beside it is fine, and so is a folder that holds one
    guard_output(tmp_path / "results.json", ins, option="--out")


def test_leaderboard_and_paper_tables_never_write_over_a_results_file(tmp_path):
    """``leaderboard --out`` / ``paper-tables --out`` pointed at a results file (or a link of one) is refused
    before anything is read, and the file stays byte-identical."""
    from benchmark.cli import main

    committed = Path(__file__).resolve().parents[1] / "results" / "dnerf" / "lego" / "langsplat" / "oracle"
    results = tmp_path / "results" / "dnerf" / "lego" / "langsplat" / "oracle"
    results.mkdir(parents=True)
    record = results / "seed0.json"
    shutil.copy(committed / "seed0.json", record)
    before = record.read_bytes()
    link = tmp_path / "link.md"
    link.symlink_to(record)
    for command in (["leaderboard"], ["paper-tables"]):
        for target in (record, link):
            rc = main([*command, "--results-dir", str(tmp_path / "results"), "--allow-dirty", "--out", str(target)])
            assert rc == 2
            assert record.read_bytes() == before


def test_leaderboard_never_writes_over_its_ceiling_nor_into_the_results_folder(tmp_path):
    """Every file ``leaderboard`` writes is guarded against every input it reads: ``--out`` over the ceiling
    JSON (or a link of it) and ``--csv-dir`` inside the results folder are refused before anything is written."""
    from benchmark.cli import main

    repo = Path(__file__).resolve().parents[1]
    results = tmp_path / "results" / "dnerf" / "lego" / "langsplat" / "oracle"
    results.mkdir(parents=True)
    shutil.copy(repo / "results" / "dnerf" / "lego" / "langsplat" / "oracle" / "seed0.json", results / "seed0.json")
    ceiling = tmp_path / "ceiling.json"
    shutil.copy(repo / "reports" / "ablations" / "protocol-ceiling.json", ceiling)
    (tmp_path / "ceiling-link.md").symlink_to(ceiling)
    before = digest(tmp_path)
    base = ["leaderboard", "--results-dir", str(tmp_path / "results"), "--allow-dirty", "--ceiling", str(ceiling)]
    for extra in (["--out", str(ceiling)], ["--out", str(tmp_path / "ceiling-link.md")],
                  ["--out", str(tmp_path / "o" / "lb.md"), "--csv-dir", str(tmp_path / "results" / "dnerf")],
                  ["--out", str(tmp_path / "o" / "lb.md"), "--csv-dir", str(tmp_path)],  # ceiling.json's folder
                  ):
        rc = main([*base, *extra])
        if "--csv-dir" in extra and extra[-1] == str(tmp_path):
            assert rc == 0, "a folder holding the ceiling is no input folder: its CSVs may go there"
            for made in tmp_path.glob("*.csv"):
                made.unlink()
            shutil.rmtree(tmp_path / "o")
            continue
        assert rc == 2, extra
        assert digest(tmp_path) == before, extra
        assert not (tmp_path / "o").exists(), "refused before the Markdown was written"
    # reports-dir as the results folder: the default CSVs would land among the results
    assert main(["leaderboard", "--results-dir", str(tmp_path / "results"), "--allow-dirty", "--ceiling",
                 str(ceiling), "--reports-dir", str(tmp_path / "results"), "--out", str(tmp_path / "lb.md"),
                 "--csv-dir", str(tmp_path / "results")]) == 2
    assert digest(tmp_path) == before


def test_names_from_results_files_cannot_hijack_the_markdown_or_a_spreadsheet(tmp_path):
    """Bidi overrides and zero-width marks are shown as escapes in Markdown; a CSV text cell a spreadsheet
    would run as a formula gets a leading quote; a results file whose recorded run differs from its place is
    refused, naming it."""
    import json

    import pandas as pd

    from benchmark.cli import main
    from benchmark.leaderboard import _csv, md

    assert "\u202e" not in md("cup\u202eevil") and "\\u202e" in md("cup\u202eevil")
    assert md("a\u200bb") == "a\\\\u200bb"
    text = _csv(pd.DataFrame({"method": ["=HYPERLINK(\"http://x\")", "+1", "ok", "-x"], "v": [1.0, -2.0, 3.0, 4.0]}))
    assert text.splitlines()[1:] == ['"\'=HYPERLINK(""http://x"")",1', "'+1,-2", "ok,3", "'-x,4"]
    repo = Path(__file__).resolve().parents[1]
    doc = json.loads((repo / "results" / "dnerf" / "lego" / "langsplat" / "oracle" / "seed0.json").read_text())
    moved = tmp_path / "results" / "dnerf" / "lego" / "evil" / "oracle"
    moved.mkdir(parents=True)
    (moved / "seed0.json").write_text(json.dumps(doc))
    assert main(["leaderboard", "--results-dir", str(tmp_path / "results"), "--allow-dirty",
                 "--out", str(tmp_path / "lb.md")]) == 2
    assert not (tmp_path / "lb.md").exists()
