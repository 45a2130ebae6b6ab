"""``feature-3dgs`` on the tiny ``smoke`` preset: decoder shape, fit quality against the truth, save/load,
the shared feature cache (reuse and refit of a corrupt file) and a run through the evaluation runner.

The 4D-GS is fitted once per module with a few iterations (it is the shared geometry, not what these
tests check); feature schedules are short, so learning rates are raised to match."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
GEOMETRY = {"geometry.static_iterations": 20, "geometry.deformation_iterations": 20, "geometry.render_backend": "torch"}
QUICK = {**GEOMETRY, "feature.iterations": 20}
SHORT = {**GEOMETRY, "feature.iterations": 300, "feature.learning_rate": 3e-2, "feature.decoder_learning_rate": 3e-3}
"""A quarter of the default schedule at three times the default learning rates."""


@pytest.fixture(scope="module")
def smoke(tmp_path_factory) -> dict:
    """The smoke scene at 48 px, its oracle supervision and a cache holding its shared 4D-GS."""
    from benchmark.loaders import load_scene
    from benchmark.synthetic.generate import generate
    from methods.supervision.cache import build_supervision

    base = tmp_path_factory.mktemp("f3dgs")
    scene_dir = Path(generate("smoke", base / "scenes" / "smoke", size=48))
    scene = load_scene(scene_dir)
    cache = base / "cache"
    supervision = build_supervision(scene, "oracle", cache_dir=cache)
    return {"scene_dir": scene_dir, "scene": scene, "cache": cache, "results": base / "results",
            "supervision": supervision}


def _config(smoke, options: dict):
    from methods import registry

    return registry.get("feature-3dgs").make_config({**options, "shared_cache_dir": str(smoke["cache"])})


def _fit(smoke, options: dict, seed: int = 0):
    from methods.api import Progress
    from methods.feature_3dgs import Feature3DGS

    return Feature3DGS.fit(smoke["scene"], smoke["supervision"], _config(smoke, options), seed=seed, device="cpu",
                           progress=Progress(True))


@pytest.fixture(scope="module")
def fitted(smoke):
    return _fit(smoke, SHORT)


def _agreement_with_truth(model, smoke) -> tuple[float, float]:
    """(mean IoU of the answered masks, mean ROC AUC of the relevance maps) against the ground-truth masks
    of every time-agnostic query on its annotated test frames of the paper split (frames where the query is
    absent skipped)."""
    from annotations.format import load_annotations

    aset = load_annotations(smoke["scene_dir"] / "annotations.json")
    paper = set(aset.info["splits"]["paper"])
    ious, aucs = [], []
    for query in aset.agnostic_queries:
        annotated = [f for f in aset.annotated_frames(query.id) if f.name in paper]
        frames = [smoke["scene"].frame(f.name) for f in annotated]
        for ann, answer in zip(annotated, model.query_agnostic(query.text, frames)):
            truth = aset.get_mask(query.id, ann.id)
            if not truth.any():
                continue
            ious.append((truth & answer.mask).sum() / (truth | answer.mask).sum())
            inside, outside = answer.relevance[truth], answer.relevance[~truth]
            above = (inside[:, None] > outside[None]).mean() + 0.5 * (inside[:, None] == outside[None]).mean()
            aucs.append(above)
    assert ious, "the smoke scene has annotated time-agnostic queries"
    return float(np.mean(ious)), float(np.mean(aucs))


def test_registered_time_agnostic_sharing_the_4dgs_and_options_checked_by_name(smoke):
    from methods import registry
    from methods.language_methods import geometry_key
    from benchmark.core.errors import InputError
    from methods.specs.feature_3dgs import Feature3DGSConfig

    listing = ("import sys; from methods import registry; assert 'feature-3dgs' in registry.names(); "
               "registry.get('feature-3dgs').make_config({'feature.level': '2'}); assert 'torch' not in sys.modules")
    out = subprocess.run([sys.executable, "-c", listing], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    spec = registry.get("feature-3dgs")
    assert spec.queries == ("agnostic",) and spec.load().supports == frozenset({"agnostic"})
    assert isinstance(spec.default_config(), Feature3DGSConfig)
    for bad in ({"feature.level": "3"}, {"feature.dim": "0"}, {"feature.iterations": "-1"},
                {"feature.learning_rate": "0"}, {"feature.decoder_learning_rate": "-1"}):
        with pytest.raises(InputError, match=next(iter(bad)).split(".")[1]):
            spec.make_config(bad)
    assert "autoencoder.latent_dim" not in {o.path for o in spec.options()}  # no option it does not read
    # the same geometry options give deformable-clip's (and 4d-langsplat's) geometry key: one shared 4D-GS
    ours = geometry_key(smoke["scene"], "4dgs", spec.make_config(GEOMETRY), 0, "cpu")
    assert ours == geometry_key(smoke["scene"], "4dgs", registry.get("deformable-clip").make_config(GEOMETRY), 0, "cpu")
    assert ours != geometry_key(smoke["scene"], "4dgs", spec.make_config(GEOMETRY), 1, "cpu")


def test_decoder_outputs_the_supervision_dimension(smoke):
    model = _fit(smoke, QUICK)
    dim = smoke["supervision"].feature_dim
    assert model.field.decoder.in_features == 16 and model.field.decoder.out_features == dim
    frame = smoke["scene"].test_frames[0]
    rendered, alpha = model.render(frame)
    assert rendered.shape == (frame.camera.height, frame.camera.width, 16) and alpha.shape == rendered.shape[:2]
    assert model.decode(rendered).shape == (*rendered.shape[:2], dim)
    other = _fit(smoke, {**QUICK, "feature.dim": 5})
    assert (other.field.decoder.in_features, other.field.decoder.out_features) == (5, dim)
    assert other.fit_info["field"]["output_dim"] == dim and other.fit_info["field"]["level"] == "middle"


def test_pixels_no_gaussian_covers_read_as_the_unmasked_text(smoke):
    import dataclasses

    from methods.fields.relevance import relevance
    from methods.specs._language import AnswerConfig

    model = _fit(smoke, {**QUICK, "extensions.unmasked_text": "background"})  # the extension of feature-3dgs+
    frame = smoke["scene"].test_frames[0]
    query, canon = model.query_embedding("box"), model.canonical()
    rendered, _ = model.render(frame)
    decoded = relevance(model.decode(rendered), query, canon, model.relevance_cfg.temperature)  # [H, W]
    model.use_answer_options(dataclasses.replace(model.config, answer=AnswerConfig(uncovered_alpha=0.0)))  # all covered
    assert torch.allclose(model.relevance_map("box", frame), decoded, atol=1e-6)
    model.use_answer_options(dataclasses.replace(model.config, answer=AnswerConfig(uncovered_alpha=2.0)))  # none
    background = torch.as_tensor(model.text_encoder.encode(["background"], kind="passage"))  # [1, D]
    want = relevance(background, query, canon, model.relevance_cfg.temperature)
    assert torch.allclose(model.relevance_map("box", frame), want.expand(decoded.shape))


def test_fitted_answers_match_the_truth_better_than_an_unfitted_field(smoke, fitted):
    """The unfitted field has the same seed, geometry and initial decoder, and no feature steps."""
    unfitted = _fit(smoke, {**SHORT, "feature.iterations": 0})
    assert not bool(unfitted.field.features.any())  # zero-initialised, as the original
    fitted_iou, fitted_auc = _agreement_with_truth(fitted, smoke)
    unfitted_iou, unfitted_auc = _agreement_with_truth(unfitted, smoke)
    assert fitted_auc > unfitted_auc + 0.05, (fitted_auc, unfitted_auc)
    assert fitted_iou > unfitted_iou, (fitted_iou, unfitted_iou)
    losses = fitted.fit_info["field"]["losses"]
    assert losses[-1] < 0.5 * losses[0]


def test_save_and_load_give_identical_answers(smoke, fitted, tmp_path):
    from methods.feature_3dgs import Feature3DGS

    fitted.save(tmp_path)
    loaded = Feature3DGS.load(tmp_path, supervision=smoke["supervision"], device="cpu")
    assert torch.equal(loaded.field.features, fitted.field.features)
    frames = smoke["scene"].test_frames
    texts = ["box", "box lid", "ball"]
    for text in texts:
        for a, b in zip(fitted.query_agnostic(text, frames), loaded.query_agnostic(text, frames)):
            assert np.array_equal(a.mask, b.mask) and np.array_equal(a.relevance, b.relevance)
            assert a.mask.dtype == bool and a.relevance.dtype == np.float32
    # prepared for several texts, each frame is rendered once: the same answers
    alone = {t: loaded.query_agnostic(t, frames) for t in texts}
    loaded.prepare(texts)
    for text in texts:
        for a, b in zip(alone[text], loaded.query_agnostic(text, frames)):
            assert np.array_equal(a.mask, b.mask) and np.array_equal(a.relevance, b.relevance)
    assert len(loaded._rendered_cache) == len(frames)
    loaded.prepare(["box"])
    assert not loaded._rendered_cache
    meta = json.loads((tmp_path / "feature_3dgs.json").read_text())
    assert meta["method"] == "feature-3dgs" and meta["config"]["feature"]["iterations"] == SHORT["feature.iterations"]


def test_feature_cache_is_reused_and_a_corrupt_file_refitted(smoke, monkeypatch):
    import methods.feature_3dgs as f3

    options = {**QUICK, "feature.iterations": 25}
    first = _fit(smoke, options)
    assert first.fit_info["cached"]["field"] is False
    (path,) = (smoke["cache"] / "language").rglob(f"feature3dgs-4dgs-{first.fit_info['key']}.pt")

    def no_training(*args, **kwargs):
        raise AssertionError("a cached feature fit was trained again")

    with monkeypatch.context() as patch:
        patch.setattr(f3, "train_feature_field", no_training)
        second = _fit(smoke, options)
    assert second.fit_info["cached"]["field"] is True
    assert torch.equal(second.field.features, first.field.features)
    assert second.fit_info["field"] == first.fit_info["field"]

    for damage in (b"not a torch file", path.read_bytes()[:100]):  # garbage, then a truncated file
        path.write_bytes(damage)
        again = _fit(smoke, options)
        assert again.fit_info["cached"]["field"] is False
        assert torch.equal(again.field.features, first.field.features)  # seeded: the same fit again
        assert torch.equal(again.field.decoder.weight, first.field.decoder.weight)
    # a readable file of another fit under this fit's name is not trusted either
    saved = torch.load(path, weights_only=True)
    torch.save({**saved, "key": "another fit"}, path)
    assert _fit(smoke, options).fit_info["cached"]["field"] is False
    # and options that change the fit give another key
    assert _fit(smoke, {**options, "feature.level": 2}).fit_info["key"] != first.fit_info["key"]


def test_runs_through_the_evaluation_runner(smoke):
    from benchmark.results import fit_seconds_with_shared
    from benchmark.runner import EvalOptions, evaluate

    def run():
        return evaluate(EvalOptions(method="feature-3dgs", scene=str(smoke["scene_dir"]), results_dir=smoke["results"],
                                    cache_dir=smoke["cache"], quiet=True, timing_frames=1, timing_repeats=1,
                                    method_options=QUICK))

    outcome = run()
    doc = outcome.results
    assert outcome.path.is_file() and doc["method"] == "feature-3dgs"
    # each of the 8 has a scored frame where its object is present
    assert doc["metrics"]["agnostic_queries"] == 8 and 0.0 <= doc["metrics"]["mIoU"] <= 100.0
    assert sorted(doc["unanswered_queries"]) == ["broken bar", "closed box", "intact bar", "open box"]
    assert doc["timing"]["query_agnostic"]["fps"] > 0 and "query_sensitive" not in doc["timing"]
    info = doc["fit"]["info"]
    assert info["geometry"]["kind"] == "4dgs" and info["field"]["iterations"] == QUICK["feature.iterations"]
    assert "losses" not in info["field"] and info["field"]["peak_cpu_mib"] > 0
    assert fit_seconds_with_shared(doc) >= info["field"]["seconds"] + info["geometry"]["seconds"] - 1e-9
    assert (outcome.path.parent / doc["predictions"]).is_file()
    # the runner's own fit cache answers the rerun identically
    again = run()
    assert again.results["timing"]["fit_cached"] is True
    assert again.results["metrics"] == doc["metrics"]


def test_the_training_loss_is_the_same_whatever_the_pixel_chunk():
    from types import SimpleNamespace

    from methods import feature_3dgs as f3

    gen = torch.Generator().manual_seed(0)
    target = SimpleNamespace(index=torch.randint(-1, 5, (37, 53), generator=gen), table=torch.randn(5, 64, generator=gen))
    features = torch.randn(37, 53, 8, generator=gen, requires_grad=True)
    grads = []
    for chunk in (None, 100, 37 * 53):  # the CPU's default, a ragged last chunk, one chunk
        decoder = torch.nn.Linear(8, 64)
        with torch.no_grad():
            decoder.weight.copy_(torch.linspace(-1, 1, 512).reshape(64, 8))
            decoder.bias.zero_()
        features.grad = None
        loss = f3.l1_backward(decoder, features * 1.0, target, chunk=chunk)
        grads.append((loss, features.grad.clone(), decoder.weight.grad.clone(), decoder.bias.grad.clone()))
    supervised = target.index >= 0
    decoded = torch.nn.functional.linear(features.detach()[supervised], torch.linspace(-1, 1, 512).reshape(64, 8))
    expected = float((decoded - target.table[target.index[supervised]]).abs().mean())
    assert f3.TRAIN_PIXEL_CHUNK["cpu"] < 37 * 53, "the default chunks this map"
    for loss, *tensors in grads:
        assert loss == pytest.approx(expected, rel=1e-5)
        for got, ref in zip(tensors, grads[-1][1:]):
            assert torch.allclose(got, ref, rtol=1e-4, atol=1e-7)
    assert grads[0][1][~supervised].abs().max() == 0, "pixels without a target get no gradient"
