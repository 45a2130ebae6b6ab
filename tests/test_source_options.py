"""``--source-option KIND.KEY=VALUE`` on ``bench4d eval`` and ``run-all``: parsed into
``EvalOptions.source_options`` and handed to the supervision source's factory."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from benchmark.core.errors import InputError


def test_source_options_are_grouped_by_kind_and_read_as_json_where_they_parse():
    from benchmark.commands.eval import parse_source_options

    parsed = parse_source_options([
        "segmenter.points_per_side=16", "segmenter.pred_iou_thresh=0.5", "segmenter.local_files_only=false",
        "image_text.model=/weights/clip vit", "image_text.batch_size=null", "segmenter.crop= [1, 2] ",
        "segmenter.points_per_side=8",  # the last one given wins
    ])
    assert parsed == {"segmenter": {"points_per_side": 8, "pred_iou_thresh": 0.5, "local_files_only": False,
                                    "crop": [1, 2]},
                      "image_text": {"model": "/weights/clip vit", "batch_size": None}}
    assert parse_source_options([]) == {}


@pytest.mark.parametrize("item, match", [
    ("segmentr.points_per_side=16", r"unknown source kind 'segmentr'.*kinds: segmenter, image_text"),
    ("captioner.model=x", r"unknown source kind 'captioner'"),
    ("segmenter=16", "expected KIND.KEY=VALUE"),
    ("segmenter.points_per_side", "expected KIND.KEY=VALUE"),
    ("segmenter.=3", "expected KIND.KEY=VALUE"),
])
def test_a_bad_source_option_is_a_one_line_error(item, match):
    from benchmark.commands.eval import parse_source_options

    with pytest.raises(InputError, match=match) as err:
        parse_source_options([item])
    assert "--source-option" in str(err.value) and "\n" not in str(err.value)


@pytest.fixture(scope="module")
def smoke_scene(tmp_path_factory) -> Path:
    from benchmark.synthetic.generate import generate

    return Path(generate("smoke", tmp_path_factory.mktemp("smoke") / "smoke", size=32))


def test_eval_hands_a_source_option_to_the_supervision_factory(smoke_scene, tmp_path, capsys):
    from benchmark.cli import main

    common = ["eval", "--method", "nearest-frame", "--scene", str(smoke_scene), "--results-dir",
              str(tmp_path / "results"), "--cache-dir", str(tmp_path / "cache"), "--quiet"]
    assert main([*common, "--source-option", "image_text.background_text=the bare room"]) == 0
    record = json.loads((tmp_path / "results" / "synthetic" / "smoke" / "nearest-frame" / "oracle"
                         / "seed0.json").read_text())
    # oracle-text's factory took it: the masks over background are named so, and its config records it
    assert record["supervision"]["source_configs"]["image_text"]["background_text"] == "the bare room"

    capsys.readouterr()
    assert main([*common, "--source-option", "segmentr.points_per_side=16"]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown source kind 'segmentr'" in err and "segmenter, image_text" in err and "\n" not in err


def test_run_all_gives_every_run_the_source_options(smoke_scene, tmp_path):
    from benchmark.commands import run_all

    parser = argparse.ArgumentParser()
    run_all.add_arguments(parser)
    args = parser.parse_args(["--methods", "nearest-frame", "--scenes", str(smoke_scene), "--seeds", "0", "1",
                              "--results-dir", str(tmp_path / "results"), "--cache-dir", str(tmp_path / "cache"),
                              "--source-option", "image_text.background_text=walls", "--quiet"])
    tally = run_all._Tally(keep_going=False, quiet=True)
    groups = run_all._plan_groups(args, ["nearest-frame"], tally)
    runs = [options for group in groups for options in group]
    assert len(runs) == 2 and all(o.source_options == {"image_text": {"background_text": "walls"}} for o in runs)
    args.source_option = ["image.background_text=walls"]
    with pytest.raises(InputError, match="unknown source kind 'image'"):
        run_all._plan_groups(args, ["nearest-frame"], tally)
