"""``langsplat``, ``deformable-clip`` and ``4d-langsplat`` through the runner on the tiny ``smoke``
preset: registration, shared geometry/field cache, answers, save/load, time-sensitive behaviour.

Iteration counts are tiny (the point is the plumbing; quality is measured by ``bench4d eval``)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch
import pytest

from benchmark.core.atomic import read_json
from benchmark.core.errors import InputError
from benchmark.core.protocol import PROTOCOLS
from benchmark.core.scene import EVAL_SPLITS_KEY, scene_split_frames
from benchmark.runner import EvalOptions, evaluate
from methods.fields.language_field import decode_for_relevance

ROOT = Path(__file__).resolve().parents[1]
TINY = {"geometry.static_iterations": 20, "geometry.deformation_iterations": 20, "field.iterations": 30,
        "autoencoder.max_steps": 200, "geometry.render_backend": "torch"}


@pytest.fixture(scope="module")
def smoke(tmp_path_factory) -> dict:
    from benchmark.loaders import load_scene
    from benchmark.synthetic.generate import generate
    from methods.supervision.cache import build_supervision

    base = tmp_path_factory.mktemp("lf")
    scene_dir = Path(generate("smoke", base / "scenes" / "smoke", size=48))
    scene = load_scene(scene_dir)
    cache = base / "cache"
    supervision = build_supervision(scene, "oracle", cache_dir=cache)
    return {"scene_dir": scene_dir, "scene": scene, "cache": cache, "results": base / "results",
            "supervision": supervision}


TINY_STATUS = {"status.static_iterations": 20, "status.iterations": 30, "caption_autoencoder.max_steps": 60}
"""Tiny status-field stage of ``4d-langsplat`` (its time-sensitive half, :mod:`methods.time_sensitive`)."""


def _eval(smoke, method: str, seed: int = 0):
    options = {**TINY, **(TINY_STATUS if method == "4d-langsplat" else {})}
    return evaluate(EvalOptions(method=method, scene=str(smoke["scene_dir"]), seed=seed, results_dir=smoke["results"],
                                cache_dir=smoke["cache"], quiet=True, timing_frames=1, timing_repeats=1,
                                method_options=options))


def test_specs_list_without_torch_and_declare_what_the_classes_support():
    code = ("import sys; from methods import registry; names = registry.names(); "
            "assert {'langsplat', 'deformable-clip', '4d-langsplat'} <= set(names), names; "
            "assert 'torch' not in sys.modules; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    from methods import registry

    for name, kind, queries in [("langsplat", "3dgs", {"agnostic", "sensitive"}),
                                ("deformable-clip", "4dgs", {"agnostic", "sensitive"}),
                                ("4d-langsplat", "4dgs", {"agnostic", "sensitive"})]:
        spec = registry.get(name)
        cls = spec.load()
        assert set(spec.queries) == queries and cls.supports == frozenset(queries)
        assert cls.geometry_kind == kind
    cfg = registry.get("4d-langsplat").make_config({"autoencoder.sample_weighting": "pixels"})
    assert cfg.autoencoder.sample_weighting == "pixels"
    for rule in ("threshold_variant", "canonical_phrases", "sensitive_mask"):  # the protocol's, not a method's
        with pytest.raises(InputError, match=rule):
            registry.get("langsplat").make_config({rule: "release"})


def test_methods_share_one_4dgs_fit_answer_every_query_and_reload(smoke):
    first = _eval(smoke, "deformable-clip")
    doc = first.results
    # each of the 8 has a scored frame where its object is present; 4 absent (query, frame) pairs
    assert doc["metrics"]["agnostic_queries"] == 8 and doc["metrics"]["sensitive_queries"] == 4
    assert doc["metrics"]["absent_frames"] == 4 and doc["metrics"]["absentFP"] is not None
    assert all(0.0 <= doc["metrics"][k] <= 100.0 for k in ("mIoU", "mAcc", "Acc", "vIoU"))
    assert doc["timing"]["query_agnostic"]["fps"] > 0

    # 4d-langsplat reuses the 4D-GS AND the field that deformable-clip fitted (same scene, options, seed)
    folder = smoke["cache"] / "language" / f"{smoke['scene'].dataset}-smoke"
    files = sorted(p.name for p in folder.iterdir())
    assert sum(f.startswith("geometry-4dgs") for f in files) == 1 and sum(f.startswith("field-4dgs") for f in files) == 1
    second = _eval(smoke, "4d-langsplat")
    assert sorted(p.name for p in folder.iterdir()) == files
    assert second.results["unanswered_queries"] == []  # the status field answers the time-sensitive ones
    assert second.results["metrics"]["sensitive_queries"] == 4
    assert second.results["metrics"]["mIoU"] == pytest.approx(doc["metrics"]["mIoU"])  # identical time-agnostic half
    # each shared stage recorded its own peak memory, and the run that reused it is charged that peak
    from benchmark.results import peak_memory_with_shared

    reused = second.results["fit"]["info"]
    for stage in ("geometry", "autoencoder", "field"):
        assert reused[stage]["peak_cpu_mib"] == doc["fit"]["info"][stage]["peak_cpu_mib"] > 0
    assert reused["time_varying"]["peak_cpu_mib"] > 0  # this run's own stage
    needed, _, measured = peak_memory_with_shared(second.results)
    assert needed >= max(reused[s]["peak_cpu_mib"] for s in ("geometry", "autoencoder", "field", "time_varying"))
    assert measured == (sys.platform == "linux")

    # langsplat fits its own static 3D-GS
    third = _eval(smoke, "langsplat")
    assert any(p.name.startswith("geometry-3dgs") for p in folder.iterdir())
    assert third.results["metrics"]["sensitive_queries"] == 4

    # the fit cache reloads a model that answers exactly as the fitted one
    from methods import registry

    spec = registry.get("deformable-clip")
    fit_dirs = list((smoke["cache"] / "fits" / "deformable-clip").rglob("language_model.pt"))
    assert len(fit_dirs) == 1
    model = spec.load().load(fit_dirs[0].parent, supervision=smoke["supervision"], device="cpu")
    meta = json.loads((fit_dirs[0].parent / "language_model.json").read_text())
    assert meta["fit_info"]["autoencoder"]["reconstruction_cosine"] > 0.0
    assert meta["fit_info"]["geometry"]["kind"] == "4dgs"
    frames = smoke["scene"].test_frames
    answers = model.query_agnostic("box", frames)
    again = model.query_agnostic("box", frames)
    for a, b, f in zip(answers, again, frames):
        assert a.mask.shape == (f.camera.height, f.camera.width) and a.mask.dtype == bool
        assert np.array_equal(a.mask, b.mask) and a.mask.any()
    # prepared for several queries, each frame is decoded once into one shared reduced basis: same answers
    texts = ["box", "bar", "closed box"]
    alone = {t: model.query_agnostic(t, frames) for t in texts}
    model.prepare(texts)
    for t in texts:
        for a, b in zip(alone[t], model.query_agnostic(t, frames)):
            # the relevance agrees to float error; a mask pixel may flip only where the relevance sits within
            # that error of the threshold, and this tiny fit's relevance is nearly flat (torch's default
            # kernels flipped 0.4 % of the pixels, AVX2 / AVX-512 none)
            assert np.allclose(a.relevance, b.relevance, atol=1e-4) and (a.mask != b.mask).mean() < 2e-2
    assert len(model._reduced_cache) == len(frames)
    model.prepare(["box"])  # a new set drops what was kept
    assert not model._reduced_cache
    preds = read_json(first.path.parent / "seed0.predictions" / "predictions.json.gz")
    assert preds["method"] == "deformable-clip"


def _deformable_clip_model(smoke, name: str = "deformable-clip"):
    """(config, shared fit, model) of a tiny deformable-clip (or its variant ``name``) on the smoke scene (fits
    cached per module)."""
    from methods import registry
    from methods.api import Progress
    from methods.language_methods import LanguageFieldModel, fit_language_field

    cfg = registry.get(name).make_config(dict(TINY))
    shared = fit_language_field(smoke["scene"], smoke["supervision"], cfg, kind="4dgs", seed=0, device="cpu",
                                progress=Progress(True), cache_root=smoke["cache"])
    return cfg, shared, LanguageFieldModel("deformable-clip", cfg, smoke["supervision"].text_encoder, shared,
                                           sensitive="relevance")


def test_time_sensitive_relevance_score_is_the_protocols(smoke):
    """Release: the chosen level's peak smoothed relevance; paper text: the mean inside the spatial mask."""
    cfg, shared, model = _deformable_clip_model(smoke)
    frame = smoke["scene"].test_frames[0]
    res = model.agnostic("open box", frame)
    got = model.query_sensitive("open box", [frame])[0]
    assert got.score == pytest.approx(float(res.level_peaks[res.level])) == pytest.approx(float(res.relevance.max()))
    assert np.array_equal(got.mask, res.mask.numpy())
    model.use_protocol(PROTOCOLS["paper-text"])
    res = model.agnostic("open box", frame)
    got = model.query_sensitive("open box", [frame])[0]
    assert got.score == pytest.approx(float(res.relevance[res.mask_unfiltered].mean()))
    res.mask_unfiltered[:] = False
    assert np.isnan(model.relevance_score(res))
    from methods.language_methods import LanguageFieldModel

    no_head = LanguageFieldModel("4d-langsplat", cfg, smoke["supervision"].text_encoder, shared, sensitive=None)
    with pytest.raises(NotImplementedError):
        no_head.query_sensitive("open box", [frame])


def test_unmasked_pixels_become_one_background_mask_per_level(smoke):
    from methods.language_methods import distinct_features, with_unmasked_as

    import dataclasses

    # the oracle covers the surroundings (as SAM does): leave the top rows of every frame in no mask, as a
    # segmenter that misses some pixels would
    sup = smoke["supervision"]
    sup = dataclasses.replace(sup, frames=[dataclasses.replace(fs, levels=np.where(
        np.arange(fs.levels.shape[1])[None, :, None] < 4, -1, fs.levels)) for fs in sup.frames])
    assert all((fs.levels < 0).any() for fs in sup.frames)
    filled = with_unmasked_as(sup, "background")
    bg = sup.text_encoder.encode(["background"], kind="passage")[0]
    for before, after in zip(sup.frames, filled.frames):
        assert (after.levels >= 0).all()
        for level in range(3):
            hole = before.levels[level] < 0
            if hole.any():
                idx = np.unique(after.levels[level][hole])
                assert idx.tolist() == [before.features[level].shape[0]]
                assert np.allclose(after.features[level][idx[0]], bg)
            assert np.array_equal(after.levels[level][~hole], before.levels[level][~hole])
    assert with_unmasked_as(sup, None) is sup
    f0, _ = distinct_features(sup)
    f1, _ = distinct_features(filled)
    known = bool(np.isclose(f0 @ bg, 1.0, atol=1e-5).any())  # the covered surroundings are named "background"
    assert f1.shape[0] == f0.shape[0] + (0 if known else 1) and np.isclose(f1 @ bg, 1.0, atol=1e-5).any()


def test_autoencoder_sample_weights_count_pixels_masks_or_nothing(smoke):
    from methods.language_methods import distinct_features

    sup = smoke["supervision"]
    feats, pixels = distinct_features(sup, "pixels")
    _, masks = distinct_features(sup, "masks")
    _, uniform = distinct_features(sup, "uniform")
    # recount by hand: per distinct feature, its pixels and the masks (frame x level x id) carrying it
    keys = {tuple(np.round(f * 1e6).astype(np.int64)): i for i, f in enumerate(feats)}
    want_pixels, want_masks = np.zeros(len(feats)), np.zeros(len(feats))
    for fs in sup.frames:
        for level in range(3):
            for id_, f in enumerate(fs.features[level]):
                n = int((fs.levels[level] == id_).sum())
                if n:
                    i = keys[tuple(np.round(np.asarray(f, np.float32) * 1e6).astype(np.int64))]
                    want_pixels[i] += n
                    want_masks[i] += 1
    assert np.allclose(pixels, want_pixels) and np.allclose(masks, want_masks) and np.all(uniform == 1)
    assert not np.allclose(pixels / pixels.sum(), masks / masks.sum())  # they do weight differently
    with pytest.raises(ValueError, match="weighting"):
        distinct_features(sup, "area")
    from methods import registry

    with pytest.raises(InputError, match="sample_weighting"):  # refused before any fitting starts
        registry.get("deformable-clip").make_config({"autoencoder.sample_weighting": "area"})


def test_autoencoder_batches_drawn_per_mask_reconstruct_small_masks_as_well_as_large_ones():
    """Drawn by pixel area (the default), a scene's small parts are a sliver of the autoencoder's batches
    and decode nearer a large neighbour's feature than their own; drawn once per mask (option ``masks``,
    the release's data) every part is reconstructed. Features close together, as text embeddings of
    names are."""
    from types import SimpleNamespace

    from methods.fields.autoencoder import AutoencoderConfig, train_autoencoder
    from methods.language_methods import distinct_features

    rng = np.random.default_rng(0)
    names = 12
    feats = rng.normal(size=32) + 0.3 * rng.normal(size=(names, 32))
    feats = (feats / np.linalg.norm(feats, axis=1, keepdims=True)).astype(np.float32)
    frames = []
    for _ in range(6):  # each frame: name 0 fills the image, names 1.. cover 2 pixels each at every level
        plane = np.zeros((40, 40), np.int64)
        plane.ravel()[np.arange(1, names) * 7] = np.arange(1, names)
        frames.append(SimpleNamespace(features=[feats] * 3, levels=[plane] * 3))
    sup = SimpleNamespace(frames=frames)
    cfg = AutoencoderConfig(hidden_dims=(32, 16), latent_dim=3, max_steps=2500, learning_rate=3e-3)

    def nearest_to_itself(weighting: str) -> int:
        x, w = distinct_features(sup, weighting)
        ae, _ = train_autoencoder(x, cfg, seed=0, weights=w)
        with torch.no_grad():
            recon = torch.nn.functional.normalize(ae(torch.as_tensor(x)), dim=1).numpy()
        return int(((recon @ x.T).argmax(1) == np.arange(len(x))).sum())

    assert nearest_to_itself("masks") == names
    assert nearest_to_itself("pixels") < names  # what drawing per mask fixes


def test_held_out_psnr_scores_each_evaluation_split_on_its_own_frames(smoke, monkeypatch):
    import dataclasses

    import methods.gaussians.train as train
    from methods.language_methods import HELD_OUT_PSNR_FRAMES, held_out_psnr

    rendered: list[list[str]] = []

    def evaluate_names(model, frames, background, rasterize_fn, device="cpu"):
        rendered.append([f.name for f in frames])
        return {"psnr": 10.0 + len(rendered)}  # which call's mean came back where

    monkeypatch.setattr(train, "evaluate", evaluate_names)
    scene = smoke["scene"]
    paper, novel = scene_split_frames(scene, "paper"), scene_split_frames(scene, "novel-view")
    got = held_out_psnr(None, scene, None, "cpu")
    assert rendered == [[f.name for f in paper], [f.name for f in novel]] and paper and novel
    assert got == {"test_psnr": 11.0, "test_psnr_frames": len(paper),
                   "novel_view_psnr": 12.0, "novel_view_psnr_frames": len(novel)}
    # a scene that records no novel-view split: the paper split (every test frame) alone, at most the cap
    many = [dataclasses.replace(scene.test_frames[0], name=f"t{i:03d}") for i in range(HELD_OUT_PSNR_FRAMES + 5)]
    plain = dataclasses.replace(scene, frames=list(scene.train_frames) + many,
                                metadata={k: v for k, v in scene.metadata.items() if k != EVAL_SPLITS_KEY})
    rendered.clear()
    got = held_out_psnr(None, plain, None, "cpu")
    assert got == {"test_psnr": 11.0, "test_psnr_frames": HELD_OUT_PSNR_FRAMES}
    assert rendered[0][0] == "t000" and rendered[0][-1] == f"t{HELD_OUT_PSNR_FRAMES + 4:03d}"


def test_results_record_what_the_fit_did(smoke):
    doc = _eval(smoke, "4d-langsplat").results
    info = doc["fit"]["info"]
    assert info["geometry"]["kind"] == "4dgs" and info["geometry"]["gaussians"] > 0
    held_out = scene_split_frames(smoke["scene"], "paper")  # the paper split's frames alone
    assert info["geometry"]["test_psnr_frames"] == min(16, len(held_out)) > 0
    assert info["geometry"]["novel_view_psnr_frames"] == len(scene_split_frames(smoke["scene"], "novel-view")) > 0
    assert info["geometry"]["novel_view_psnr"] > 0
    background = np.zeros(3) if smoke["scene"].background is None else np.asarray(smoke["scene"].background)
    empty = np.mean([-10 * np.log10(np.mean((np.asarray(f.image(), np.float64) - background) ** 2)) for f in held_out])
    assert info["geometry"]["test_psnr"] > empty + 3.0  # the held-out renders show the scene, not the background
    assert info["autoencoder"]["reconstruction_cosine"] > 0.0 and "seconds" in info["field"]
    tv = info["time_varying"]
    assert tv["memory"]["bytes_per_gaussian"] > 0 and tv["num_states"] >= 1
    json.dumps(doc)  # everything recorded is plain JSON


def test_4d_langsplat_on_a_dnerf_folder_answers_agnostic_queries_without_a_head(tmp_path):
    """Oracle track on D-NeRF: alpha supervision, no states to caption, so the head is off (auto)."""
    from tests.test_gaussian_training import write_dnerf_folder

    scene_dir = write_dnerf_folder(tmp_path / "toy", size=16)
    out = evaluate(EvalOptions(method="4d-langsplat", scene=str(scene_dir), results_dir=tmp_path / "r",
                               cache_dir=tmp_path / "c", quiet=True, timing_frames=1, timing_repeats=1,
                               method_options={**TINY, **TINY_STATUS}, object_query="blob"))
    doc = out.results
    assert doc["supervision"]["sources"]["segmenter"] == "alpha"
    assert "time_varying" not in doc["fit"]["info"] and doc["metrics"]["agnostic_queries"] == 1
    with pytest.raises(InputError, match="truth"):
        evaluate(EvalOptions(method="4d-langsplat", scene=str(scene_dir), results_dir=tmp_path / "r2",
                             cache_dir=tmp_path / "c", quiet=True, timing_frames=1, timing_repeats=1,
                             method_options={**TINY, **TINY_STATUS, "status.fit": "on"}, object_query="blob"))


def test_pixels_no_gaussian_covers_show_the_background_text(smoke, monkeypatch):
    """Zero latents decode to an arbitrary feature; with the ``unmasked_text`` extension an uncovered pixel must
    read as that text (and without it, as the release, it decodes as any other pixel)."""
    paper = _deformable_clip_model(smoke)[2]
    model = _deformable_clip_model(smoke, "deformable-clip+")[2]
    assert paper.config.extensions.unmasked_text is None and model.config.extensions.unmasked_text == "background"
    frame = smoke["scene"].test_frames[0]
    latents, alpha = paper.render_latents_and_alpha(frame)
    basis = paper._reduced_phrases("box")[0]
    assert torch.equal(paper.decode_reduced(latents, torch.zeros_like(alpha), basis),
                       decode_for_relevance(latents, paper.autoencoder.decoder, basis))
    frame = smoke["scene"].test_frames[0]
    latents, alpha = model.render_latents_and_alpha(frame)
    assert alpha.shape == (frame.camera.height, frame.camera.width)
    basis = model._reduced_phrases("box")[0]
    holes = torch.zeros_like(alpha)  # nothing covered
    out = model.decode_reduced(latents, holes, basis)
    assert out.shape == (3, *alpha.shape, basis.shape[1] + 1)
    e = torch.nn.functional.normalize(torch.as_tensor(model.text_encoder.encode(["background"], kind="passage")[0]), dim=0)
    q = torch.nn.functional.normalize(model.query_embedding("box"), dim=0)
    zq = torch.cat([q @ basis, q.new_zeros(1)])
    # the reduced background feature has the background embedding's norm and its dot product with the query
    assert torch.allclose(out[0, 0, 0].norm(), torch.tensor(1.0), atol=1e-5)
    assert float(out[1, 3, 4] @ zq) == pytest.approx(float(e @ q), abs=1e-5)
    full = decode_for_relevance(latents, model.autoencoder.decoder, basis)
    covered = torch.ones_like(alpha)
    assert torch.allclose(model.decode_reduced(latents, covered, basis), full, atol=1e-6)
    # partly covered: covered pixels decode exactly as in the full decode, the others read as background
    half = (torch.rand(alpha.shape, generator=torch.Generator().manual_seed(0)) < 0.5).float()
    mixed = model.decode_reduced(latents, half, basis)
    assert torch.allclose(mixed[:, half > 0.5], full[:, half > 0.5], atol=1e-6)
    assert torch.allclose(mixed[:, half < 0.5], out[:, half < 0.5])
    # and only the covered pixels go through the decoder
    import methods.language_methods as lm

    seen = []
    monkeypatch.setattr(lm, "decode_for_relevance", lambda x, *a, **k: seen.append(x.shape[:-1]) or
                        decode_for_relevance(x, *a, **k))
    model.decode_reduced(latents, half, basis)
    assert seen == [(3, int((half > 0.5).sum()))]


def test_another_protocol_or_answer_option_reuses_the_fit_and_changes_the_answers(smoke, tmp_path):
    """A run under another protocol (query rules) or answer option reuses the cached fit, and the reloaded
    model answers under the run's rules, not those of the run that fitted it."""
    from benchmark.runner import fit_config_dict
    from methods.specs.deformable_clip import DeformableCLIPConfig

    from methods.fields.configs import LanguageFieldOptions
    from methods.specs._language import AnswerConfig

    default, other_alpha = DeformableCLIPConfig(), DeformableCLIPConfig(answer=AnswerConfig(uncovered_alpha=0.3))
    assert fit_config_dict(default) == fit_config_dict(other_alpha)
    assert fit_config_dict(default) != fit_config_dict(DeformableCLIPConfig(field=LanguageFieldOptions(iterations=7)))
    base = _eval(smoke, "deformable-clip")
    assert base.results["protocol"] == PROTOCOLS["release"].to_dict()
    other = evaluate(EvalOptions(method="deformable-clip", scene=str(smoke["scene_dir"]), results_dir=tmp_path / "r",
                                 cache_dir=smoke["cache"], quiet=True, timing_frames=1, timing_repeats=1,
                                 method_options=dict(TINY), protocol="paper-text"))
    assert other.results["timing"]["fit_cached"] is True
    assert other.results["fit"]["key"] == base.results["fit"]["key"]
    assert other.results["protocol"]["name"] == "paper-text"
    assert other.results["score_config"]["temporal"] == PROTOCOLS["paper-text"].temporal.to_dict()
    # the release rule keeps only the top 30 % of the rescaled range (paper text: 60 %): fewer pixels
    pixels = [sum(int(r["pred_pixels"]) for r in doc.results["scores"]["frames"] if r["kind"] == "agnostic")
              for doc in (base, other)]
    assert pixels[0] < pixels[1]


def test_ablate_rescore_reanswers_recorded_fits(smoke, tmp_path, capsys):
    """``bench4d ablate rescore``: same options -> the recorded metrics exactly; another answer option ->
    the same fit answers differently; a fit option is refused (it would need a new fit)."""
    from benchmark.cli import main

    _eval(smoke, "deformable-clip")
    common = ["ablate", "rescore", "--results-dir", str(smoke["results"]), "--cache-dir", str(smoke["cache"]),
              "--methods", "deformable-clip", "--out", str(tmp_path), "--quiet"]
    assert main(common + ["--name", "same", "--protocol", "release"]) == 0
    same = json.loads((tmp_path / "rescore-same.json").read_text())["runs"]
    assert same and all(r[f"{m}_before"] == pytest.approx(r[f"{m}_after"]) for r in same for m in ("mIoU", "Acc"))
    assert all(r["track"] == "oracle" for r in same)  # every row names its supervision track
    assert "| oracle |" in (tmp_path / "rescore-same.md").read_text()
    assert main(common + ["--name", "rel", "--protocol", "paper-text"]) == 0
    rel = json.loads((tmp_path / "rescore-rel.json").read_text())["runs"]
    assert any(r["mIoU_before"] != pytest.approx(r["mIoU_after"]) for r in rel)
    assert (smoke["results"] / "ablations" / "rel").is_dir()
    # resuming under the same name with other rules re-answers instead of keeping the stale files
    assert main(common + ["--name", "same", "--protocol", "paper-text"]) == 0
    again = json.loads((tmp_path / "rescore-same.json").read_text())["runs"]
    assert [r["mIoU_after"] for r in again] == pytest.approx([r["mIoU_after"] for r in rel])
    assert main(common + ["--name", "bad", "--set", "field.iterations=5"]) != 0
    assert "'field.iterations'] are not answer options" in capsys.readouterr().err
    # --refit: a fit option refits (the recorded run's other options kept); a name no method has is refused
    assert main(common + ["--name", "refit", "--refit", "--set", "field.iterations=5"]) == 0
    (row,) = json.loads((tmp_path / "rescore-refit.json").read_text())["runs"]
    (path,) = (smoke["results"] / "ablations" / "refit").rglob("seed*.json")
    refitted, (recorded,) = json.loads(path.read_text()), [
        json.loads(p.read_text()) for p in smoke["results"].glob("synthetic/*/deformable-clip/*/seed0.json")]
    assert refitted["method_config"]["field"]["iterations"] == 5 and refitted["fit"]["key"] != recorded["fit"]["key"]
    assert refitted["method_config"]["geometry"]["static_iterations"] == 20  # the recorded run's, kept
    assert row["mIoU_before"] == pytest.approx(recorded["metrics"]["mIoU"])
    assert row["mIoU_after"] == pytest.approx(refitted["metrics"]["mIoU"])
    assert "refitted" in (tmp_path / "rescore-refit.md").read_text()
    assert main(common + ["--name", "refit2", "--refit", "--set", "no_such_option=1"]) != 0
    assert "no_such_option" in capsys.readouterr().err


def test_ablate_rescore_refit_of_a_head_option_keeps_the_recorded_geometry(smoke, tmp_path, monkeypatch):
    """``--refit`` with a time-varying-head option fits the head alone on the recorded fit: the geometry
    and time-agnostic field are the recorded ones even when the geometry code has changed since."""
    from benchmark.cli import main
    from methods.language_methods import LanguageFieldMethod
    from methods.registry import MethodSpec

    recorded = _eval(smoke, "4d-langsplat").results
    calls = []
    monkeypatch.setattr(LanguageFieldMethod, "fit", classmethod(lambda cls, *a, **k: calls.append(1)))  # never a full fit
    monkeypatch.setattr(MethodSpec, "code_digest", lambda self: "code changed since the run")  # keys move
    assert main(["ablate", "rescore", "--results-dir", str(smoke["results"]), "--cache-dir", str(smoke["cache"]),
                 "--methods", "4d-langsplat", "--out", str(tmp_path), "--quiet", "--refit",
                 "--name", "window", "--set", "extensions.caption_window=2",
                 "--set", "extensions.caption_segments=false"]) == 0
    assert not calls
    (path,) = (smoke["results"] / "ablations" / "window").rglob("seed0.json")
    new = json.loads(path.read_text())
    assert new["fit"]["head_refit_of"] == recorded["fit"]["key"] != new["fit"]["key"]
    assert new["method_config"]["extensions"]["caption_window"] == 2
    assert new["fit"]["info"]["time_varying"]["caption_window"] == 2
    # same geometry and time-agnostic field: the time-agnostic answers are the recorded ones exactly
    assert new["metrics"]["mIoU"] == pytest.approx(recorded["metrics"]["mIoU"])
    assert new["fit"]["info"]["geometry"] == recorded["fit"]["info"]["geometry"]
    # a head option beside an answer option: the same head (its cache key ignores answer options), re-answered
    assert main(["ablate", "rescore", "--results-dir", str(smoke["results"]), "--cache-dir", str(smoke["cache"]),
                 "--methods", "4d-langsplat", "--out", str(tmp_path), "--quiet", "--refit", "--name", "window-release",
                 "--set", "extensions.caption_window=2", "--set", "extensions.caption_segments=false",
                 "--protocol", "paper-text"]) == 0
    assert not calls
    (path,) = (smoke["results"] / "ablations" / "window-release").rglob("seed0.json")
    both = json.loads(path.read_text())
    assert both["fit"]["head_refit_of"] == recorded["fit"]["key"] and both["fit"]["key"] == new["fit"]["key"]
    assert both["fit"]["cached"] and both["protocol"]["name"] == "paper-text"
    # a boolean option given as text is the recorded False: asked again, the run is kept, not answered anew
    seg = ["ablate", "rescore", "--results-dir", str(smoke["results"]), "--cache-dir", str(smoke["cache"]),
           "--methods", "4d-langsplat", "--out", str(tmp_path), "--quiet", "--refit", "--name", "segments",
           "--set", "extensions.caption_segments=false"]
    assert main(seg) == 0
    (path,) = (smoke["results"] / "ablations" / "segments").rglob("seed0.json")
    first = path.read_bytes()
    assert json.loads(first)["method_config"]["extensions"]["caption_segments"] is False
    assert main(seg) == 0 and path.read_bytes() == first
    # the head's code has changed since: the kept file is stale, the head is refitted under the new code (the
    # runner keys a fit's code by the spec's digest and the class's ``code_version``, and records the latter)
    from methods.four_d_langsplat import FourDLangSplat

    monkeypatch.setattr(MethodSpec, "code_digest", lambda self: "head code changed since")
    monkeypatch.setattr(FourDLangSplat, "code_version", "head code changed since", raising=False)
    assert main(seg) == 0
    again = json.loads(path.read_text())
    assert again["fit"]["key"] != json.loads(first)["fit"]["key"] and not again["fit"]["cached"]
    assert not calls


def test_ablate_gap_reproduces_the_recorded_answers_and_the_ceiling(smoke, tmp_path, capsys, monkeypatch):
    """``bench4d ablate gap``: the fitted rung is the run's own recorded mIoU, the perfect rung is the
    protocol ceiling under the run's query options, and every evaluated pixel of every level is counted
    once in the latent confusion table."""
    from benchmark.cli import main
    from benchmark.studies.protocol_ceiling import protocol_ceiling
    from benchmark.results import load_results
    from benchmark.runner import find_annotations

    outcome = _eval(smoke, "deformable-clip")
    status = load_results(_eval(smoke, "4d-langsplat").path)
    assert main(["ablate", "gap", "--results-dir", str(smoke["results"]), "--cache-dir", str(smoke["cache"]),
                 "--methods", "deformable-clip", "4d-langsplat", "--out", str(tmp_path), "--quiet"]) == 0
    table = capsys.readouterr().out
    doc = json.loads((tmp_path / "field-gap.json").read_text())
    # every row, time-agnostic (one per run) and time-sensitive (one per query), reproduces its recorded run
    assert table.count("| yes |") == len(doc["runs"]) + sum(len(r["sensitive"]) for r in doc["runs"])
    assert "Supervision track: **oracle**" in table and {r["track"] for r in doc["runs"]} == {"oracle"}
    run = next(r for r in doc["runs"] if r["method"] == "deformable-clip")
    recorded = load_results(outcome.path)
    # 4d-langsplat shares deformable-clip's field: its time-agnostic part is measured once and still is its own
    four_d = next(r for r in doc["runs"] if r["method"] == "4d-langsplat")
    assert 100 * four_d["rungs"]["fitted"]["mIoU"] == pytest.approx(status["metrics"]["mIoU"], abs=1e-9)
    # time-sensitive: the fitted rung is the recorded Acc / vIoU, for the relevance score and the status field
    for r, rec in ((run, recorded), (next(r for r in doc["runs"] if r["method"] == "4d-langsplat"), status)):
        sens = {q["query"]: q for q in rec["scores"]["queries"] if q["kind"] == "sensitive"}
        assert set(r["sensitive"]) == set(sens) and sens
        for text, q in r["sensitive"].items():
            assert 100 * q["fitted"]["Acc"] == pytest.approx(sens[text]["Acc"], abs=1e-9)
            assert 100 * q["fitted"]["vIoU"] == pytest.approx(sens[text]["vIoU"], abs=1e-9)
            assert 0.0 <= q["object_mask"]["Acc"] <= 1.0
            if r is not run:  # the status field: its caption targets, raw and through its autoencoder
                assert 0.0 <= q["captions"]["Acc"] <= 1.0 and 0.0 <= q["caption_autoencoder"]["Acc"] <= 1.0
            else:
                assert "captions" not in q  # relevance scores have no caption targets
    fitted = run["rungs"]["fitted"]["per_query"]
    for q in recorded["scores"]["queries"]:
        if q["kind"] == "agnostic":
            assert 100 * fitted[q["query"]] == pytest.approx(q["mIoU"], abs=1e-9)
    assert 100 * run["rungs"]["fitted"]["mIoU"] == pytest.approx(recorded["metrics"]["mIoU"], abs=1e-9)

    aset = find_annotations(smoke["scene"])
    scored = {f.id for f in aset.frames if f.name in set(recorded["score_config"]["eval_frames"])}
    aset.frames = [f for f in aset.frames if f.id in scored]  # the run's split: the paper split's frames
    aset.masks = {key: rle for key, rle in aset.masks.items() if key[1] in scored}
    ceiling = protocol_ceiling(smoke["scene"], aset, smoke["supervision"].text_encoder,
                               {"run": PROTOCOLS["release"].agnostic})["variants"]["run"]
    assert run["rungs"]["perfect"]["per_query"] == pytest.approx(ceiling["per_query"], abs=1e-9)
    # the autoencoder of a tiny fit is lossy: its rung differs from the perfect one somewhere
    assert run["rungs"]["autoencoder"]["per_query"] != pytest.approx(run["rungs"]["perfect"]["per_query"])

    frames = [smoke["scene"].frame(n) for n in recorded["score_config"]["eval_frames"]]
    assert run["frames"] == len(frames)
    pixels = sum(f.camera.height * f.camera.width for f in frames)
    for level in ("subpart", "part", "whole"):
        rows = [c for c in run["confusion"] if c["level"] == level]
        assert sum(c["pixels"] for c in rows) == pixels
        assert all(0.0 <= c["nearer_other"] <= 1.0 and 0.0 <= c["uncovered"] <= 1.0 for c in rows)
    # a second sweep reuses the analyses of unchanged runs instead of loading their fits again
    import benchmark.studies.field_gap as field_gap_module

    monkeypatch.setattr(field_gap_module, "field_gap", lambda *a, **k: pytest.fail("analysed again"))
    assert main(["ablate", "gap", "--results-dir", str(smoke["results"]), "--cache-dir", str(smoke["cache"]),
                 "--methods", "deformable-clip", "4d-langsplat", "--out", str(tmp_path), "--quiet"]) == 0
    assert json.loads((tmp_path / "field-gap.json").read_text())["runs"] == doc["runs"]
    assert main(["ablate", "gap", "--results-dir", str(smoke["results"]), "--methods", "nearest-frame",
                 "--out", str(tmp_path), "--quiet"]) == 2  # no language field among the matched runs


def test_the_field_gap_prepares_the_runners_texts_even_when_its_agnostic_half_is_reused(smoke):
    """The shared decoding basis spans the prepared texts and moves answers at float precision, so the gap
    tool prepares exactly the runner's texts (queries of a kind the model answers, with a mask in an
    evaluated frame) also when the time-agnostic half comes from another run of the same field."""
    from benchmark.studies.field_gap import field_gap
    from benchmark.runner import find_annotations

    aset = find_annotations(smoke["scene"])

    class Recorder:
        supports = frozenset({"agnostic"})

        def __init__(self):
            self.prepared = []

        def prepare(self, texts):
            self.prepared.append(list(texts))

    frames = [af.name for af in aset.annotated_frames(aset.queries[0].id)][:1]
    expected = [q.text for q in aset.queries if q.kind == "agnostic"
                and any(af.name in frames for af in aset.annotated_frames(q.id))]
    assert expected
    model = Recorder()
    reused = {"frames": 1, "background_text": "background", "rungs": {}, "confusion": []}
    out = field_gap(model, smoke["scene"], aset, frames, agnostic=reused)
    assert model.prepared == [expected] and out["sensitive"] == {} and out["rungs"] == {}


def test_query_speed_times_the_method_query_path():
    from benchmark.studies.query_speed import measure_query_speed

    out = measure_query_speed(1500, 32, 24, frames=2, warmup=1, queries=3, feature_dim=64)
    assert out["gaussians"] == 1500 and out["mask_shape"] == [24, 32]
    assert out["levels"] == 3 and out["latent_dim"] == 3
    assert out["fps"] == pytest.approx(1.0 / out["seconds_per_frame"])
    # sharing one render + decode per frame among 3 queries must cost less per answer than answering alone
    assert 0 < out["prepared_seconds_per_answer"] < out["seconds_per_frame"]


def test_query_speed_command_rejects_a_zero_size(capsys):
    from benchmark.cli import main

    assert main(["ablate", "query-speed", "--gaussians", "0", "--quiet"]) == 2
    assert "--gaussians" in capsys.readouterr().err


def test_an_interrupted_geometry_fit_resumes_from_its_checkpoint(smoke, tmp_path):
    from methods import registry
    from methods.api import Progress
    from methods.language_methods import fit_geometry

    config = registry.get("deformable-clip").make_config(TINY)

    class StopAt(Progress):
        """Interrupts the fit after ``steps`` iterations of its deformation stage, as Ctrl-C would."""

        def __init__(self, steps: int):
            super().__init__(quiet=True)
            self.steps = steps

        def __call__(self, iterable=None, *, desc=None, total=None, **kw):
            if desc != "geometry (deformation)":
                return iterable
            return self._stop(iterable)

        def _stop(self, iterable):
            for i, item in enumerate(iterable):
                if i == self.steps:
                    raise KeyboardInterrupt
                yield item

    cache = tmp_path / "cache"
    with pytest.raises(KeyboardInterrupt):
        fit_geometry(smoke["scene"], "4dgs", config, seed=0, device="cpu", progress=StopAt(7), cache_root=cache)
    partial = list(cache.rglob("geometry-4dgs-*.partial.pt"))
    assert len(partial) == 1  # saved as the static stage ended, at least
    fit = fit_geometry(smoke["scene"], "4dgs", config, seed=0, device="cpu", progress=Progress(quiet=True),
                       cache_root=cache)
    assert not fit.cached and fit.info["resumed_at"]["stage"] in ("static", "deformation")
    assert not partial[0].exists() and len(list(cache.rglob("geometry-4dgs-*.pt"))) == 1
    fresh = fit_geometry(smoke["scene"], "4dgs", config, seed=0, device="cpu", progress=Progress(quiet=True),
                         cache_root=tmp_path / "other")
    assert fresh.info["resumed_at"] is None

    def same(a, b) -> bool:
        if isinstance(a, torch.Tensor):
            return isinstance(b, torch.Tensor) and torch.equal(a, b)
        if isinstance(a, dict):
            return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
        return a == b

    assert same(fresh.geometry.state_dict(), fit.geometry.state_dict())  # resumed = uninterrupted, exactly


def test_the_geometry_rung_fits_latents_that_render_the_truth_closer_than_the_fitted_ones():
    """The field gap's ``geometry`` rung: latents fitted on a frozen geometry to named codes per pixel render
    those codes closer than the latents it starts from, through the blending operator or the rasterizer
    alike, and a model answering with them gets its own latents back after the block."""
    import types

    from benchmark.studies.field_gap import _answering_with, geometry_latents
    from methods.fields.language_field import LanguageField, LanguageFieldConfig, random_geometry

    geometry, camera = random_geometry(300, 12, 8, seed=1)
    cfg = LanguageFieldConfig(num_levels=3, latent_dim=3, learning_rate=0.05)
    field = LanguageField(geometry.num_gaussians, cfg, generator=torch.Generator().manual_seed(0))
    frames = [types.SimpleNamespace(time=t, camera=camera) for t in (0.0, 0.5)]
    codes = torch.tensor([[0.0, 0.0, 0.0], [1.0, -1.0, 0.5], [-0.5, 1.0, 1.0]])
    rows = [torch.zeros(3, 8, 12, dtype=torch.long) for _ in frames]
    for r in rows:
        r[:, :, 6:] = 1  # right half: name 1 at every level
        r[2, :4, :] = 2  # top rows of the last level: name 2
    answered = []

    class Model:
        def __init__(self):
            self.field, self.geometry = field, geometry

        def prepare(self, texts):
            answered.append((list(texts), self.field.features.detach().clone()))

    def error(latents):
        with torch.no_grad():
            out = []
            for f, r in zip(frames, rows):
                field.features.data, kept = latents, field.features.data
                maps = field.render(geometry.at(f.time), f.camera)  # [L, H, W, d]
                field.features.data = kept
                out.append((maps - codes[r]).abs().mean())
            return float(torch.stack(out).mean())

    model = Model()
    start = field.features.detach().clone()
    fitted = geometry_latents(model, frames, rows, codes, steps=60)
    assert error(fitted) < 0.2 * error(start)
    assert torch.equal(field.features.detach(), start), "fitting the rung leaves the model's latents alone"
    with _answering_with(model, fitted, ["box"]):
        assert torch.equal(field.features.detach(), fitted)
    assert torch.equal(field.features.detach(), start) and len(answered) == 2
    # prepared for the runner's texts with the rung's latents on the way in, with its own on the way out
    assert [t for t, _ in answered] == [["box"], ["box"]]
    assert torch.equal(answered[0][1], fitted) and torch.equal(answered[1][1], start)
