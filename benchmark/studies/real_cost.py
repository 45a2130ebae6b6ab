"""What the real track's models cost, measured on their architectures, and the supervision time of the
paper's 12 scenes projected from it (``bench4d ablate real-cost``).

Each real backend is built from its published configuration with random weights (``size="full"``: the
FLOPs and memory of the real model without its weights, which this machine cannot download; ``"tiny"``:
the same classes at a size a CPU test runs) and timed on the unit of work the real track gives it:

* **SAM ViT-H** (transformers ``SamModel``): one frame of automatic mask generation, the image encoder
  once and the mask decoder over a ``points_per_side`` x ``points_per_side`` grid of point prompts in
  batches of ``points_per_batch`` (the automatic generator's defaults, 32 and 64);
* **OpenCLIP ViT-B/16** (transformers ``CLIPVisionModelWithProjection``, the same network): one masked
  crop at 224 x 224, in batches;
* **Qwen2-VL-7B** (``Qwen2VLForConditionalGeneration``): one caption request as
  :func:`methods.captioners.base.make_captions` makes them, a video description over ``video_frames``
  images and a frame caption over 3 (the frame and its context), each image at the scene's size and
  ``caption_tokens`` new tokens; random weights never stop early, so this is the longest answer;
* **e5-mistral-7b-instruct** (``MistralModel``): one caption embedding of ``text_tokens`` tokens, in batches.

The projection multiplies these unit costs by the work of each scene (module constant
:data:`PAPER_SCENES` and the stated assumptions of :class:`RealCostConfig`); it covers the supervision
stages only (the fits are measured in ``reports/gpu-pipeline/``).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import Any, Callable, Optional

import numpy as np

from ._report import Report, markdown_table, number_cell, write_report

SIZES = ("tiny", "full")


@dataclass(frozen=True)
class PaperScene:
    """One scene of the paper's tables and the frames its supervision covers."""

    name: str
    dataset: str
    frames: int
    """Images the release's preprocessing segments, encodes and captions (every training image)."""
    time_sensitive: bool
    """Whether the paper has time-sensitive queries on it: only then are its objects captioned."""


NEU3D_FRAMES = 20 * 300
"""Neu3D: 21 synchronised cameras x 300 frames, cam00 held out (protocol.md): 6 000 training images."""
HYPERNERF_FRAMES = 456
"""HyperNeRF: the frame count of chickchicken (the shared ``dataset.json``: 456 ids), used for each of the six
scenes, whose other files are not shared here (``--hypernerf-frames`` for your own counts)."""

PAPER_SCENES = tuple(
    [PaperScene(n, "hypernerf", HYPERNERF_FRAMES, n in ("americano", "chickchicken", "split-cookie",
                                                                  "espresso"))
     for n in ("americano", "chickchicken", "split-cookie", "espresso", "keyboard", "torchocolate")]
    + [PaperScene(n, "neu3d", NEU3D_FRAMES, False)
       for n in ("coffee_martini", "cook_spinach", "cut_roasted_beef", "flame_salmon", "flame_steak", "sear_steak")])
"""The paper's 12 scenes; time-sensitive queries on the first four HyperNeRF scenes only (protocol.md). Every
caption request is timed at :attr:`RealCostConfig.width` x :attr:`RealCostConfig.height` (HyperNeRF's 2x)."""


@dataclass
class RealCostConfig:
    """One measurement and projection."""

    size: str = "full"
    """``full``: the published architectures (random weights); ``tiny``: the same classes, test-sized."""
    device: str = "cpu"
    repeats: int = 3
    """Timed repetitions of each unit (after one warm-up); the median is kept."""
    width: int = 960
    height: int = 536
    """Image size the captioner sees (HyperNeRF 2x: 960 x 536)."""
    points_per_side: int = 32
    points_per_batch: int = 64
    crops_per_batch: int = 64
    masks_per_frame: int = 120
    """Assumption: SAM masks per image over its levels, each a CLIP crop (pass your runs' count)."""
    objects: int = 3
    """Assumption: tracked objects captioned per scene."""
    video_frames: int = 8
    """Images of a video-level description (:class:`methods.captioners.base.CaptionPrompt`)."""
    caption_tokens: int = 128
    """New tokens per caption request (release: 128)."""
    text_tokens: int = 48
    text_batch: int = 16
    hypernerf_frames: int = HYPERNERF_FRAMES

    def __post_init__(self) -> None:
        from benchmark.core.errors import InputError

        if self.size not in SIZES:
            raise InputError(None, "size", f"expected one of {', '.join(SIZES)}, got {self.size!r}")
        for name in ("repeats", "width", "height", "points_per_side", "points_per_batch", "crops_per_batch",
                     "masks_per_frame", "objects", "video_frames", "caption_tokens", "text_tokens", "text_batch",
                     "hypernerf_frames"):
            if int(getattr(self, name)) < 1:
                raise InputError(None, name, f"must be at least 1, got {getattr(self, name)}")


# ---------------------------------------------------------------------------------------------------
# the architectures
# ---------------------------------------------------------------------------------------------------
QWEN_IDS = {"bos": 151643, "eos": 151645, "vision_start": 151652, "vision_end": 151653, "image": 151655,
            "video": 151656}
"""Qwen2-VL's special token ids (its tokenizer's)."""


def _configs(size: str) -> dict[str, Any]:
    from transformers import CLIPVisionConfig, MistralConfig, Qwen2VLConfig, SamConfig

    full = size == "full"
    clip = (CLIPVisionConfig(hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12,
                             image_size=224, patch_size=16, projection_dim=512) if full else
            CLIPVisionConfig(hidden_size=16, intermediate_size=32, num_hidden_layers=1, num_attention_heads=2,
                             image_size=32, patch_size=8, projection_dim=8))
    sam = (SamConfig(vision_config=dict(hidden_size=1280, num_hidden_layers=32, num_attention_heads=16, mlp_dim=5120,
                                        global_attn_indexes=[7, 15, 23, 31], output_channels=256, image_size=1024,
                                        patch_size=16, window_size=14)) if full else
           SamConfig(vision_config=dict(hidden_size=16, output_channels=16, num_hidden_layers=1, num_attention_heads=2,
                                        image_size=32, patch_size=8, window_size=2, global_attn_indexes=[0],
                                        num_pos_feats=8, mlp_dim=32),
                     prompt_encoder_config=dict(hidden_size=16, image_size=32, patch_size=8, mask_input_channels=4),
                     mask_decoder_config=dict(hidden_size=16, mlp_dim=32, num_hidden_layers=1, num_attention_heads=2,
                                              iou_head_hidden_dim=16)))
    ids = dict(bos_token_id=QWEN_IDS["bos"], eos_token_id=QWEN_IDS["eos"], pad_token_id=QWEN_IDS["bos"])
    text = (dict(vocab_size=152064, hidden_size=3584, intermediate_size=18944, num_hidden_layers=28,
                 num_attention_heads=28, num_key_value_heads=4, max_position_embeddings=32768, rope_theta=1e6,
                 rope_scaling={"type": "mrope", "mrope_section": [16, 24, 24]}, **ids) if full else
            dict(vocab_size=152064, hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2,
                 num_key_value_heads=1, max_position_embeddings=32768,
                 rope_scaling={"type": "mrope", "mrope_section": [2, 3, 3]}, **ids))
    vision = (dict(depth=32, embed_dim=1280, hidden_size=3584, num_heads=16, mlp_ratio=4, patch_size=14,
                   spatial_merge_size=2, in_chans=3, temporal_patch_size=2) if full else
              dict(depth=1, embed_dim=32, hidden_size=32, num_heads=2, mlp_ratio=2, patch_size=14,
                   spatial_merge_size=2, in_chans=3, temporal_patch_size=2))
    qwen = Qwen2VLConfig(text_config=text, vision_config=vision, image_token_id=QWEN_IDS["image"],
                         video_token_id=QWEN_IDS["video"], vision_start_token_id=QWEN_IDS["vision_start"],
                         vision_end_token_id=QWEN_IDS["vision_end"], **ids)
    e5 = (MistralConfig(vocab_size=32000, hidden_size=4096, intermediate_size=14336, num_hidden_layers=32,
                        num_attention_heads=32, num_key_value_heads=8, max_position_embeddings=32768) if full else
          MistralConfig(vocab_size=32000, hidden_size=32, intermediate_size=64, num_hidden_layers=1,
                        num_attention_heads=2, num_key_value_heads=1, max_position_embeddings=4096))
    return {"sam": sam, "clip": clip, "qwen2vl": qwen, "e5": e5}


BACKEND_NAMES = {"sam": "SAM ViT-H", "clip": "OpenCLIP ViT-B/16", "qwen2vl": "Qwen2-VL-7B",
                 "e5": "e5-mistral-7b-instruct"}


def model_classes() -> dict[str, type]:
    """Backend -> the transformers class of its network."""
    from transformers import CLIPVisionModelWithProjection, MistralModel, Qwen2VLForConditionalGeneration, SamModel

    return {"sam": SamModel, "clip": CLIPVisionModelWithProjection, "qwen2vl": Qwen2VLForConditionalGeneration,
            "e5": MistralModel}


def build(backend: str, size: str, device: str, dtype=None):
    """The backend's network with random weights, on ``device``, in eval mode, in ``dtype`` (default bfloat16 on
    CUDA, the checkpoints' own dtype, as random weights overflow float16; float32 on the CPU)."""
    import torch

    config = _configs(size)[backend]
    if dtype is None:
        dtype = torch.bfloat16 if str(device).startswith("cuda") else torch.float32
    torch.manual_seed(0)
    previous = torch.get_default_dtype()
    # Initialised where it runs and in the dtype it runs in: a 7B model never passes through host memory, and
    # its float32 copy (twice the bfloat16 weights) never sits on the GPU to inflate the measured peak.
    torch.set_default_dtype(dtype)
    try:
        with torch.device(device):
            model = model_classes()[backend](config)
    finally:
        torch.set_default_dtype(previous)
    return model.to(dtype=dtype).eval()


# ---------------------------------------------------------------------------------------------------
# the units of work
# ---------------------------------------------------------------------------------------------------
def _timed(step: Callable[[], Any], repeats: int, device: str) -> float:
    """Median seconds of ``step`` over ``repeats`` runs after one warm-up."""
    import torch

    def sync() -> None:
        if str(device).startswith("cuda"):
            torch.cuda.synchronize(device)

    with torch.no_grad():
        step()
        sync()
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            step()
            sync()
            times.append(time.perf_counter() - t0)
    return float(np.median(times))


def sam_frame(model, cfg: RealCostConfig) -> Callable[[], Any]:
    """One frame of automatic mask generation: the image encoder, then every point batch of the grid."""
    import torch

    side = model.config.vision_config.image_size
    dev, dtype = model.device, model.dtype
    pixels = torch.randn(1, 3, side, side, device=dev, dtype=dtype)
    points = cfg.points_per_side ** 2
    batches = [min(cfg.points_per_batch, points - s) for s in range(0, points, cfg.points_per_batch)]

    def step():
        embeddings = model.get_image_embeddings(pixels)
        for n in batches:
            prompts = torch.rand(1, n, 1, 2, device=dev, dtype=dtype) * side
            model(image_embeddings=embeddings, input_points=prompts, multimask_output=True)
    return step


def clip_batch(model, cfg: RealCostConfig) -> Callable[[], Any]:
    """One batch of ``crops_per_batch`` masked crops through the image tower and its projection."""
    import torch

    side = model.config.image_size
    crops = torch.randn(cfg.crops_per_batch, 3, side, side, device=model.device, dtype=model.dtype)
    return lambda: model(pixel_values=crops).image_embeds


def _qwen_image_grid(model, width: int, height: int) -> tuple[int, int]:
    """Patch grid (rows, columns) of one image as Qwen2-VL's processor sizes it (multiples of 28 px)."""
    vision = model.config.vision_config
    unit = vision.patch_size * vision.spatial_merge_size
    rows = max(unit, round(height / unit) * unit) // vision.patch_size
    cols = max(unit, round(width / unit) * unit) // vision.patch_size
    return rows, cols


def qwen_request(model, cfg: RealCostConfig, images: int, width: int, height: int,
                 prompt_tokens: int = 64) -> tuple[Callable[[], Any], int]:
    """One caption request over ``images`` images: (the step, its input tokens)."""
    import torch

    vision = model.config.vision_config
    rows, cols = _qwen_image_grid(model, width, height)
    per_image = rows * cols // vision.spatial_merge_size ** 2
    patch_values = vision.in_chans * vision.temporal_patch_size * vision.patch_size ** 2
    dev = model.device
    pixel_values = torch.randn(images * rows * cols, patch_values, device=dev, dtype=model.dtype)
    grid = torch.tensor([[1, rows, cols]] * images, device=dev)
    vocab = model.config.text_config.vocab_size
    text = torch.randint(0, min(vocab, 150000), (prompt_tokens,), generator=torch.Generator().manual_seed(0)).tolist()
    ids = []
    for _ in range(images):
        ids += [QWEN_IDS["vision_start"]] + [QWEN_IDS["image"]] * per_image + [QWEN_IDS["vision_end"]]
    input_ids = torch.tensor([ids + text], device=dev)
    mask = torch.ones_like(input_ids)

    def step():
        return model.generate(input_ids=input_ids, attention_mask=mask, pixel_values=pixel_values,
                              image_grid_thw=grid, max_new_tokens=cfg.caption_tokens,
                              min_new_tokens=cfg.caption_tokens, do_sample=False)
    return step, int(input_ids.shape[1])


def e5_batch(model, cfg: RealCostConfig) -> Callable[[], Any]:
    import torch

    ids = torch.randint(0, model.config.vocab_size, (cfg.text_batch, cfg.text_tokens),
                        generator=torch.Generator().manual_seed(0)).to(model.device)
    return lambda: model(input_ids=ids, attention_mask=torch.ones_like(ids)).last_hidden_state


def _peak_reset(device: str) -> None:
    import torch

    if str(device).startswith("cuda"):
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)


def _gpu_gib(device: str, peak: bool) -> Optional[float]:
    """GiB of GPU memory allocated now (``peak=False``) or at most since the last reset; None off CUDA."""
    import torch

    if not str(device).startswith("cuda"):
        return None
    return (torch.cuda.max_memory_allocated(device) if peak else torch.cuda.memory_allocated(device)) / 2 ** 30


def _measure_backend(backend: str, cfg: RealCostConfig, width: int, height: int) -> dict[str, Any]:
    """Build one backend, time its unit of work, and report its weights' and its peak GPU memory."""
    _peak_reset(cfg.device)
    t0 = time.perf_counter()
    model = build(backend, cfg.size, cfg.device)
    built = time.perf_counter() - t0
    params = sum(p.numel() for p in model.parameters())
    row: dict[str, Any] = {"backend": BACKEND_NAMES[backend], "parameters": params, "build_seconds": built,
                           "weights_gpu_gib": _gpu_gib(cfg.device, peak=False)}
    if backend == "sam":
        row["frame_seconds"] = _timed(sam_frame(model, cfg), cfg.repeats, cfg.device)
    elif backend == "clip":
        row["crop_seconds"] = _timed(clip_batch(model, cfg), cfg.repeats, cfg.device) / cfg.crops_per_batch
    elif backend == "qwen2vl":
        video, video_tokens = qwen_request(model, cfg, cfg.video_frames, width, height)
        frame, frame_tokens = qwen_request(model, cfg, 3, width, height)
        row.update(video_request_seconds=_timed(video, cfg.repeats, cfg.device), video_input_tokens=video_tokens,
                   frame_request_seconds=_timed(frame, cfg.repeats, cfg.device), frame_input_tokens=frame_tokens,
                   image_size=[width, height])
    else:
        row["text_seconds"] = _timed(e5_batch(model, cfg), cfg.repeats, cfg.device) / cfg.text_batch
    row["peak_gpu_gib"] = _gpu_gib(cfg.device, peak=True)
    return row


def measure_units(cfg: RealCostConfig, log: Callable[[str], None] = print) -> dict[str, dict]:
    """Seconds per unit of work of every backend (and its build time and peak GPU memory)."""
    import torch

    tiny_image = (56, 84)  # a tiny Qwen2-VL reads small images; the full one the configured size
    width, height = (cfg.width, cfg.height) if cfg.size == "full" else tiny_image
    units: dict[str, dict] = {}
    for backend in ("sam", "clip", "qwen2vl", "e5"):
        # one call per backend: its weights and the closures that hold them are gone before the next is built
        units[backend] = _measure_backend(backend, cfg, width, height)
        row = units[backend]
        log(f"real-cost: {row['backend']}: {row['parameters'] / 1e6:,.1f} M parameters, "
            + ", ".join(f"{k} {v:.4g}" for k, v in row.items() if k.endswith("seconds")))
        if str(cfg.device).startswith("cuda"):
            torch.cuda.empty_cache()
    return units


# ---------------------------------------------------------------------------------------------------
# the projection
# ---------------------------------------------------------------------------------------------------
def project(units: dict[str, dict], cfg: RealCostConfig, scenes=PAPER_SCENES) -> list[dict]:
    """Seconds of each supervision stage per scene: SAM per frame, CLIP per mask crop, and on scenes with
    time-sensitive queries Qwen2-VL one video request and one frame request per object and frame, e5 one
    embedding per caption."""
    rows = []
    for s in scenes:
        frames = cfg.hypernerf_frames if s.dataset == "hypernerf" else s.frames
        captions = cfg.objects * (1 + frames) if s.time_sensitive else 0
        stages = {"sam": frames * units["sam"]["frame_seconds"],
                  "clip": frames * cfg.masks_per_frame * units["clip"]["crop_seconds"],
                  "qwen2vl": (cfg.objects * (units["qwen2vl"]["video_request_seconds"]
                                             + frames * units["qwen2vl"]["frame_request_seconds"])
                              if s.time_sensitive else 0.0),
                  "e5": captions * units["e5"]["text_seconds"]}
        rows.append({"scene": s.name, "dataset": s.dataset, "frames": frames, "captions": captions,
                     **{f"{k}_seconds": v for k, v in stages.items()}, "total_seconds": sum(stages.values())})
    return rows


def real_cost_report(cfg: RealCostConfig, out, log: Callable[[str], None] = print):
    """Measure, project, and write ``<out>/real-cost-<size>-<device>.{json,md}``."""
    from benchmark.runner import device_description, git_state, package_versions

    units = measure_units(cfg, log)
    rows = project(units, cfg)
    doc = {"config": asdict(cfg), "units": units, "projection": rows, "environment": device_description(cfg.device),
           "packages": package_versions(("torch", "transformers", "numpy")), "git": git_state()}
    stem = f"real-cost-{cfg.size}-{str(cfg.device).replace(':', '')}"
    table = render(units, rows, cfg, doc["environment"])
    return Report(table, write_report(out, stem, doc, table))


def _hours(seconds: float) -> str:
    return f"{seconds / 3600:.2f}" if seconds >= 36 else f"{seconds / 3600:.4f}"


def render(units: dict[str, dict], rows: list[dict], cfg: RealCostConfig, env: dict) -> str:
    device = env.get("gpu") or env.get("processor") or cfg.device
    unit_rows = [
        [units["sam"]["backend"], f"{units['sam']['parameters'] / 1e6:,.0f} M",
         f"one frame: encoder + {cfg.points_per_side}x{cfg.points_per_side} points in batches of {cfg.points_per_batch}",
         number_cell(units["sam"]["frame_seconds"], 4)],
        [units["clip"]["backend"], f"{units['clip']['parameters'] / 1e6:,.0f} M",
         f"one crop (batches of {cfg.crops_per_batch})", number_cell(units["clip"]["crop_seconds"], 5)],
        [units["qwen2vl"]["backend"], f"{units['qwen2vl']['parameters'] / 1e6:,.0f} M",
         f"video request: {cfg.video_frames} images, {units['qwen2vl']['video_input_tokens']} input tokens, "
         f"{cfg.caption_tokens} new", number_cell(units["qwen2vl"]["video_request_seconds"], 3)],
        [units["qwen2vl"]["backend"], "", f"frame request: 3 images, {units['qwen2vl']['frame_input_tokens']} input "
         f"tokens, {cfg.caption_tokens} new", number_cell(units["qwen2vl"]["frame_request_seconds"], 3)],
        [units["e5"]["backend"], f"{units['e5']['parameters'] / 1e6:,.0f} M",
         f"one caption of {cfg.text_tokens} tokens (batches of {cfg.text_batch})",
         number_cell(units["e5"]["text_seconds"], 5)]]
    peaks = ", ".join(f"{u['backend']} {u['weights_gpu_gib']:.1f} / {u['peak_gpu_gib']:.1f} GiB"
                      for u in units.values() if u.get("peak_gpu_gib") is not None)
    scene_rows = [[r["scene"], r["dataset"], str(r["frames"]), str(r["captions"])]
                  + [_hours(r[f"{k}_seconds"]) for k in ("sam", "clip", "qwen2vl", "e5", "total")] for r in rows]
    total = sum(r["total_seconds"] for r in rows)
    return "\n".join([
        f"# The real track's models: cost per unit and the paper's 12 scenes projected ({cfg.size} size)\n",
        f"Written by `bench4d ablate real-cost --size {cfg.size} --device {cfg.device}` "
        "(`benchmark/studies/real_cost.py`). Each backend is its real architecture "
        + ("with random weights" if cfg.size == "full" else "at test size (tiny random weights: the flow, not "
           "the cost)") + f", on {device}"
        + (" in bfloat16" if str(cfg.device).startswith("cuda") else " in float32")
        + "; median of " + f"{cfg.repeats} timed repetitions after a warm-up. Random weights never end an answer "
        "early, so each caption request is timed at its full length.\n",
        "## Seconds per unit of work\n",
        markdown_table(["backend", "parameters", "unit", "seconds"], unit_rows),
        "" if not peaks else ("\nGPU memory, weights / peak of the unit (weights and activations), one backend at a "
                              f"time: {peaks}.\n"),
        "## Projected supervision time of the paper's scenes (hours)\n",
        "Frames: the images the release's preprocessing segments, encodes and captions (Neu3D: 20 training cameras "
        f"x 300 frames; HyperNeRF: {cfg.hypernerf_frames} frames each, chickchicken's count in the shared files). "
        f"Assumptions: {cfg.masks_per_frame} SAM masks per image, each one CLIP crop; on the four scenes with "
        f"time-sensitive queries, {cfg.objects} tracked objects, each with one video description and one caption per "
        "frame, and one e5 embedding per caption (the other scenes need no captions). Fits and queries are not "
        "included (`reports/gpu-pipeline/`).\n",
        markdown_table(["scene", "dataset", "frames", "captions", "SAM", "CLIP", "Qwen2-VL", "e5", "total"],
                       scene_rows),
        f"\nAll 12 scenes: **{total / 3600:.1f} hours** of supervision on one device "
        f"({math.fsum(r['qwen2vl_seconds'] for r in rows) / max(total, 1e-12) * 100:.0f} % of it captioning).\n"])
