"""Real-track supervision sources: classical hierarchy, SAM level split, CLIP crops and encoders,
temporal association. Real weights are never available here: model paths run on tiny randomly
initialised transformers models (flow and shapes), the pipelines on synthetic images with a known
answer."""

from __future__ import annotations


import numpy as np
import pytest
from conftest import tiny_clip_model, tiny_sam_model
import torch

from benchmark.core.errors import InputError
from benchmark.core.scene import Camera, Frame
from methods.supervision import registry as sources
from methods.supervision.association import TemporalAssociator, iou_matrix


def make_frame(image: np.ndarray, index: int = 0, name: str | None = None) -> Frame:
    h, w = image.shape[:2]
    cam = Camera(w, h, 50.0, 50.0, w / 2, h / 2, np.eye(4))
    return Frame(name or f"f{index}", cam, time=index / 10.0, time_index=index, split="train",
                 load_image=lambda: image.astype(np.float32))


def blocks_image(shift: int = 0, h: int = 48, w: int = 64) -> np.ndarray:
    """Grey background, two coloured objects, each with a differently coloured part."""
    img = np.full((h, w, 3), 0.5, dtype=np.float32)
    img[8:40, 4 + shift:28 + shift] = (0.9, 0.1, 0.1)      # object A
    img[12:20, 8 + shift:16 + shift] = (0.95, 0.9, 0.1)    # part of A
    img[10:44, 36 + shift:60 + shift] = (0.1, 0.2, 0.9)    # object B
    img[30:40, 44 + shift:56 + shift] = (0.1, 0.9, 0.3)    # part of B
    return img


# -- registry ------------------------------------------------------------------------------------------
def test_real_sources_are_registered_on_the_real_track_only():
    names = {(s.kind, s.name): s for s in sources.sources()}
    for key in [("segmenter", "classical"), ("segmenter", "sam"), ("image_text", "clip")]:
        assert key in names and names[key].track == "real"
    with pytest.raises(InputError, match="belongs to the 'real' track"):
        sources.track_sources("oracle", {"segmenter": "classical"})


# -- association ---------------------------------------------------------------------------------------
def test_association_keeps_ids_of_moved_regions_and_gives_new_ones_fresh_ids():
    a = np.full((1, 20, 20), -1)
    a[0, 2:8, 2:8] = 5
    a[0, 10:18, 10:18] = 9
    assoc = TemporalAssociator()
    first = assoc.associate(a)
    b = np.full((1, 20, 20), -1)
    b[0, 3:9, 2:8] = 77      # region 5 moved by one row, relabelled by the segmenter
    b[0, 10:18, 11:19] = 3   # region 9 moved by one column
    b[0, 0:2, 15:20] = 4     # a new region
    second = assoc.associate(b)
    assert second[0, 5, 5] == first[0, 5, 5]
    assert second[0, 14, 14] == first[0, 14, 14]
    new_id = second[0, 0, 16]
    assert new_id >= 0 and new_id not in set(np.unique(first[0]))
    assert (second == -1).sum() == (b == -1).sum()
    iou, prev_ids, cur_ids = iou_matrix(first[0], second[0])
    assert iou.shape == (2, 3) and np.all(iou <= 1.0)


# -- classical -----------------------------------------------------------------------------------------
def test_classical_hierarchy_is_nested_and_follows_regions_over_time():
    from methods.supervision.classical import ClassicalConfig, ClassicalSegmenter, hierarchy

    cfg = ClassicalConfig()
    levels = hierarchy(blocks_image().astype(np.float64), cfg)
    assert levels.shape == (3, 48, 64) and levels.min() >= 0
    for fine, coarse in ((0, 1), (1, 2)):
        for rid in np.unique(levels[fine]):
            assert np.unique(levels[coarse][levels[fine] == rid]).size == 1  # nested
    counts = [np.unique(levels[i]).size for i in range(3)]
    assert counts[0] >= counts[1] >= counts[2] >= 1
    # colour edges: the yellow part of A is never merged with B at the small level
    assert levels[0][15, 11] != levels[0][25, 48]

    seg = ClassicalSegmenter(cfg)
    ids0 = seg.segment(make_frame(blocks_image(0), 0))
    ids1 = seg.segment(make_frame(blocks_image(1), 1))
    # the large object B (moved by one pixel) keeps its small-level id
    assert ids0[0][25, 48] == ids1[0][25, 49]
    assert ids0[0][35, 50] == ids1[0][35, 51]
    with pytest.raises(InputError, match="increasing"):
        ClassicalConfig(scales=(500.0, 100.0, 50.0))


# -- CLIP crops -----------------------------------------------------------------------------------------
def test_prepare_crops_masks_boxes_pads_and_normalises():
    from methods.supervision.clip import CLIP_MEAN, CLIP_STD, mask_boxes, prepare_crops

    img = torch.zeros(30, 40, 3)
    img[:, :] = torch.tensor([0.2, 0.4, 0.6])
    mask = torch.zeros(2, 30, 40, dtype=torch.bool)
    mask[0, 5:15, 10:30] = True       # 10 x 20 box: padded vertically by 5 rows each side
    mask[0, 5, 10] = False            # a pixel of the box outside the mask: zeroed
    mask[1, 20, 3] = True             # single pixel
    assert mask_boxes(mask).tolist() == [[5, 14, 10, 29], [20, 20, 3, 3]]
    crops = prepare_crops(img, mask, size=20)
    assert crops.shape == (2, 3, 20, 20)
    zero = (0.0 - torch.tensor(CLIP_MEAN)) / torch.tensor(CLIP_STD)
    colour = (torch.tensor([0.2, 0.4, 0.6]) - torch.tensor(CLIP_MEAN)) / torch.tensor(CLIP_STD)
    assert torch.allclose(crops[0, :, 0, 10], zero, atol=1e-5)        # padding row
    assert torch.allclose(crops[0, :, 10, 10], colour, atol=1e-5)     # inside the mask
    assert torch.allclose(crops[0, :, 5, 0], zero, atol=1e-5)         # the zeroed corner pixel
    assert torch.allclose(crops[1, :, 7, 7], colour, atol=1e-5)       # one pixel blown up to 20 x 20



def test_hf_clip_encoder_on_a_tiny_random_model(tmp_path):
    from methods.supervision.clip import create

    tiny_clip_model(tmp_path, max_positions=24)
    img = blocks_image()
    frame = make_frame(img)
    enc = create(None, text_encoder=None, backend="hf", model=str(tmp_path))
    masks = np.zeros((3, 48, 64), dtype=bool)
    masks[0, 8:40, 4:28] = True
    masks[1, 10:44, 36:60] = True
    masks[2, 12:20, 8:16] = True
    feats = enc.encode_masks(img, masks, frame=frame)
    assert feats.shape == (3, 8) and feats.dtype == np.float32
    assert np.allclose(np.linalg.norm(feats, axis=1), 1.0, atol=1e-5)
    assert not np.allclose(feats[0], feats[1])  # different crops, different features
    text = enc.text_encoder.encode(["red box", "blue box"], kind="query")
    assert text.shape == (2, 8) and enc.text_encoder.dim == 8
    cfg = enc.config()
    assert cfg["crop_size"] == 32 and cfg["backend"] == "transformers"
    with pytest.raises(InputError, match="cannot load CLIP weights"):
        create(None, text_encoder=None, backend="hf", model=str(tmp_path / "missing"))
    with pytest.raises(InputError, match="unknown backend"):
        create(None, text_encoder=None, backend="nope")


# -- SAM ----------------------------------------------------------------------------------------------
class LabelPredictor:
    """A stand-in for SAM: output 0/1/2 = the part / object / foreground under the prompt."""

    def __init__(self, parts: np.ndarray, objects: np.ndarray) -> None:
        self.parts, self.objects = parts, objects

    def set_image(self, image):
        assert image.dtype == np.uint8

    def predict(self, points):
        outs, ious = [], []
        for x, y in points.tolist():
            i, j = int(y), int(x)
            levels = []
            for labels in (self.parts, self.objects, (self.objects >= 0).astype(int) - (self.objects < 0)):
                lab = labels[i, j]
                m = (labels == lab) if lab >= 0 else np.zeros_like(labels, dtype=bool)
                levels.append(torch.as_tensor(np.where(m, 10.0, -10.0), dtype=torch.float32))
            outs.append(torch.stack(levels))
            ious.append(torch.tensor([0.95, 0.93, 0.9]))
        return torch.stack(outs), torch.stack(ious)

    def config(self):
        return {"backend": "labels"}


def test_sam_level_split_filters_and_associates_on_a_known_scene():
    from methods.supervision.sam import SamConfig, SamSegmenter

    img = blocks_image()
    objects = np.full((48, 64), -1)
    objects[8:40, 4:28] = 0
    objects[10:44, 36:60] = 1
    parts = objects.copy() * 2
    parts[12:20, 8:16] = 10
    parts[30:40, 44:56] = 11
    parts[objects < 0] = -1
    seg = SamSegmenter(LabelPredictor(parts, objects), SamConfig(points_per_side=8, min_mask_region_area=4))
    ids = seg.segment(make_frame(img))
    assert ids.shape == (3, 48, 64)
    small, middle, large = ids
    # small: the two parts and the two object bodies are distinct masks
    assert len({small[15, 11], small[25, 6], small[35, 50], small[20, 40]}) == 4
    # middle: whole objects; the part pixels belong to their object
    assert middle[15, 11] == middle[25, 6] != middle[35, 50] == middle[20, 40]
    # large: all foreground is one mask; background is in no mask at any level
    assert large[15, 11] == large[35, 50] >= 0
    assert (ids[:, objects < 0] == -1).all()
    again = seg.segment(make_frame(img, 1))
    assert (again == ids).all()  # same frame content, same ids over time


def test_release_mask_nms_drops_duplicates_low_scores_and_nested_masks():
    from methods.supervision.sam import release_mask_nms

    m = torch.zeros(4, 20, 20, dtype=torch.bool)
    m[0, 0:10, 0:10] = True          # best
    m[1, 0:10, 0:9] = True           # near duplicate of 0 (IoU 0.9)
    m[2, 12:20, 12:20] = True        # separate, low score
    m[3, 2:4, 2:4] = True            # nested inside 0
    scores = torch.tensor([0.95, 0.9, 0.5, 0.85])
    keep = release_mask_nms(m, scores, iou_thr=0.8, score_thr=0.7, inner_thr=0.5).tolist()
    assert keep == [0]


def test_hf_sam_predictor_on_a_tiny_random_model(tmp_path):
    from methods.supervision.sam import SamConfig, create

    tiny_sam_model(tmp_path)
    # random weights: let every mask through the filters so the whole flow runs
    seg = create(None, text_encoder=None, backend="hf", model=str(tmp_path), points_per_side=3,
                 pred_iou_thresh=-1e9, stability_score_thresh=0.0, min_mask_region_area=0,
                 nms_score_thresh=-1.0, nms_iou_thresh=1.0)
    seg.predictor.set_image((blocks_image() * 255).astype(np.uint8))
    logits, iou = seg.predictor.predict(torch.tensor([[10.0, 20.0], [50.0, 30.0]]))
    assert logits.shape == (2, 3, 48, 64) and iou.shape == (2, 3)
    ids = seg.segment(make_frame(blocks_image()))
    assert ids.shape == (3, 48, 64) and ids.dtype == np.int32
    assert seg.config()["backend"] == "transformers"
    assert isinstance(seg.cfg, SamConfig) and seg.cfg.points_per_side == 3
    with pytest.raises(InputError, match="unknown backend"):
        create(None, text_encoder=None, backend="nope")
    with pytest.raises(InputError, match="sam options"):
        create(None, text_encoder=None, backend="hf", model=str(tmp_path), no_such_option=1)


def test_segment_anything_backend_is_an_optional_import_with_a_clear_error(tmp_path):
    from methods.supervision.sam import create

    try:
        import segment_anything  # noqa: F401
        importable = True
    except Exception:
        importable = False
    ckpt = tmp_path / "sam.pth"
    ckpt.write_bytes(b"")
    if importable:  # pragma: no cover - not in the core install (needs torchvision)
        pytest.skip("segment_anything is installed here")
    with pytest.raises(InputError, match="torchvision"):
        create(None, text_encoder=None, backend="segment-anything", checkpoint=str(ckpt))
    with pytest.raises(InputError, match="checkpoint"):
        create(None, text_encoder=None, backend="segment-anything")


# -- alpha oracle (D-NeRF) -----------------------------------------------------------------------------
class _Words:
    """A tiny text encoder: one fixed unit vector per word."""

    name = "words"
    dim = 8

    def encode(self, texts, kind="query"):
        import zlib

        rows = [np.random.default_rng(zlib.crc32(t.encode())).standard_normal(8) for t in texts]
        return np.stack([r / np.linalg.norm(r) for r in rows]).astype(np.float32)

    def config(self):
        return {"name": self.name}


def test_alpha_oracle_supervises_object_and_background_of_training_frames_only():
    from dataclasses import replace
    from types import SimpleNamespace

    from methods.supervision.alpha import create_encoder, create_segmenter
    from methods.supervision.truth_access import EvaluatedFrameTruthError

    img = blocks_image()
    alpha = np.zeros((48, 64), dtype=bool)
    alpha[8:40, 4:28] = True
    frame = replace(make_frame(img), load_alpha=lambda: alpha)
    seg = create_segmenter(None)
    ids = seg.segment(frame)
    assert ids.shape == (3, 48, 64) and (ids[:, alpha] == 1).all() and (ids[:, ~alpha] == 0).all()
    lego = SimpleNamespace(name="lego", root=None)
    with pytest.raises(InputError, match="object_name"):  # a folder's name is no object name
        create_encoder(lego, text_encoder=_Words())
    enc = create_encoder(lego, text_encoder=_Words(), object_name="lego bulldozer")
    feats = enc.encode_masks(img, np.stack([ids[0] == 1, ids[0] == 0]), frame=frame)
    words = _Words().encode(["lego bulldozer", "background"])
    assert np.allclose(feats, words)
    test_frame = replace(frame, split="test")
    with pytest.raises(EvaluatedFrameTruthError):
        seg.segment(test_frame)
    with pytest.raises(EvaluatedFrameTruthError):
        enc.encode_masks(img, ids[:1] == 1, frame=test_frame)
    with pytest.raises(InputError, match="alpha"):
        seg.segment(make_frame(img))


def test_gt_segmenter_covers_the_surroundings_as_sam_does_unless_told_not_to(smoke_base):
    """The oracle segmenter puts the surroundings (truth id 0) in a mask at every level by default, so every
    pixel of a training frame is supervised (SAM's automatic masks cover the background too); off, they are
    in no mask. The option is part of the source's config (cache keys), and evaluated frames stay refused."""
    from benchmark.loaders import load_scene
    from methods.supervision.gt import create
    from methods.supervision.oracle_text import OracleTextEncoder
    from methods.supervision.truth_access import EvaluatedFrameTruthError

    scene = load_scene(smoke_base["scene"])
    frame = next(f for f in scene.frames if f.split == "train")
    covered, bare = create(scene), create(scene, surroundings=False)
    ids, ids_bare = covered.segment(frame), bare.segment(frame)
    assert (ids >= 0).all() and (ids_bare < 0).any()
    surroundings = ids_bare < 0
    assert (ids[surroundings] == 0).all() and (ids[~surroundings] == ids_bare[~surroundings]).all()
    assert covered.config() != bare.config()
    names = OracleTextEncoder(scene, _Words()).mask_names((ids[2] == 0)[None], frame, np.array([2]))
    assert names == ["background"]
    with pytest.raises(InputError, match="surroundings"):
        create(scene, surroundings="yes")
    with pytest.raises(EvaluatedFrameTruthError):
        covered.segment(next(f for f in scene.frames if f.split != "train"))
