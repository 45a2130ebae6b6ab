"""Query speed of a 4D language field at a chosen scale (``bench4d ablate query-speed``).

The timed path is the method's own (:meth:`methods.language_methods.LanguageFieldModel.query_agnostic`)
on random Gaussians, features and decoder: the work does not depend on what they mean.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, Optional

import numpy as np
import torch

from benchmark.core.scene import Frame
from methods.fields.autoencoder import FeatureAutoencoder
from methods.fields.language_field import LanguageField, random_geometry
from methods.fields.relevance import query_levels
from methods.language_methods import LanguageFieldModel, SharedField, autoencoder_config, field_config
from methods.specs._language import LanguageMethodConfig
from methods.text_encoders import SeededTextEncoder

STAGES = ("deform", "render", "decode", "query", "to_host")
"""The stages of one answer, in order, timed one by one in ``stage_seconds_per_frame``."""


def measure_query_speed(num_gaussians: int, width: int, height: int, *, frames: int = 10, warmup: int = 2,
                        queries: int = 1, feature_dim: int = 512, device: str | torch.device = "cpu",
                        config: Optional[LanguageMethodConfig] = None, seed: int = 0) -> dict[str, Any]:
    """Frames per second of the time-agnostic query of a 4D language field on random Gaussians.

    The timed path is the method's own (:meth:`LanguageFieldModel.query_agnostic`): deform the
    geometry to the frame's time, render every level's latents in one rasterizer call, decode them
    through the autoencoder (``feature_dim``: CLIP ViT-B/16's 512), relevance against the canonical
    phrases, smoothing, threshold, majority filter, level choice, and the mask copied to the host --
    per frame and per query, as the paper's FPS counts it. Geometry, features and decoder are random
    (:func:`methods.fields.language_field.random_geometry`, :class:`methods.text_encoders.SeededTextEncoder`):
    the work does not depend on what they mean. With ``queries > 1`` the frames are also answered for
    that many queries after one :meth:`LanguageFieldModel.prepare` (render and decode once per frame,
    shared by the queries), as the evaluation runner does.
    """
    dev = torch.device(device)
    cfg = config or LanguageMethodConfig()
    model, camera = random_model(num_gaussians, width, height, feature_dim=feature_dim, device=dev, config=cfg,
                                 seed=seed)
    frame_list = [Frame(name=f"t{i:04d}", camera=camera, time=(i + 0.5) / (frames + warmup), time_index=i,
                        split="test") for i in range(frames + warmup)]
    timed = frame_list[warmup:]
    texts = [f"query {i}" for i in range(max(1, int(queries)))]
    sync = _synchronizer(dev)

    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    for frame in frame_list[:warmup]:
        model.query_agnostic(texts[0], [frame])
    sync()
    t0 = time.perf_counter()
    answers = [model.query_agnostic(texts[0], [frame])[0] for frame in timed]
    sync()
    seconds = (time.perf_counter() - t0) / frames
    fcfg = field_config(cfg)
    out: dict[str, Any] = {
        "gaussians": model.geometry.num_gaussians, "width": width, "height": height, "device": str(dev),
        "levels": fcfg.num_levels, "latent_dim": fcfg.latent_dim, "feature_dim": feature_dim,
        "frames": frames, "seconds_per_frame": seconds, "fps": 1.0 / seconds,
        "mask_shape": list(answers[0].mask.shape),
    }
    out["stage_seconds_per_frame"] = stage_seconds(model, texts[0], timed, sync)
    if len(texts) > 1:
        per_answer = prepared_seconds_per_answer(model, texts, timed, sync)
        out.update({"queries": len(texts), "prepared_seconds_per_answer": per_answer,
                    "prepared_answers_per_second": 1.0 / per_answer})
    if dev.type == "cuda":
        out["peak_gpu_mib"] = torch.cuda.max_memory_allocated(dev) / 2 ** 20
    approximate = cfg.answer.decode_table_for(dev) > 0 or (dev.type == "cuda" and cfg.answer.decode_tf32)
    if approximate:
        # what a decode table or TensorFloat-32 costs in answers: the same frames decoded exactly in float32
        saved = (cfg.answer.decode_table, cfg.answer.decode_table_cuda, cfg.answer.decode_tf32)
        cfg.answer.decode_table, cfg.answer.decode_table_cuda, cfg.answer.decode_tf32 = 0, 0, False
        try:
            exact = [model.query_agnostic(texts[0], [frame])[0] for frame in timed]
        finally:
            cfg.answer.decode_table, cfg.answer.decode_table_cuda, cfg.answer.decode_tf32 = saved
        out.update(mask_agreement(answers, exact))
    return out


def mask_agreement(answers, exact) -> dict[str, float]:
    """How the masks of ``answers`` compare with those of ``exact`` (the same frames decoded in float32):
    the share of all pixels that agree (mean and worst frame), and the share of mask pixels (those either
    answer marks) that agree, over all frames and on the worst frame."""
    same_all, same_mask, equal, union_total = [], [], 0, 0
    for a, b in zip(answers, exact):
        a, b = _bool_mask(a.mask), _bool_mask(b.mask)
        same = a == b
        union = a | b
        same_all.append(float(same.mean()))
        frame_union = int(union.sum())
        frame_equal = int((same & union).sum())
        same_mask.append(frame_equal / frame_union if frame_union else 1.0)
        equal += frame_equal
        union_total += frame_union
    return {"mask_agreement_with_exact": float(np.mean(same_all)),
            "min_mask_agreement_with_exact": float(np.min(same_all)),
            "mask_pixel_agreement_with_exact": equal / union_total if union_total else 1.0,
            "min_mask_pixel_agreement_with_exact": float(np.min(same_mask)),
            "mask_pixels": union_total}


def random_model(num_gaussians: int, width: int, height: int, *, feature_dim: int, device: torch.device,
                 config: LanguageMethodConfig, seed: int) -> tuple[LanguageFieldModel, Any]:
    """A :class:`LanguageFieldModel` on random Gaussians, features and decoder, and the camera they face."""
    geometry, camera = random_geometry(num_gaussians, width, height, seed=seed, device=device)
    gen = torch.Generator().manual_seed(seed + 2)
    fcfg = field_config(config)
    field = LanguageField(geometry.num_gaussians, dataclasses.replace(fcfg, init_std=1.0), generator=gen, device=device)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        autoencoder = FeatureAutoencoder(feature_dim, autoencoder_config(config)).to(device)
    shared = SharedField(geometry, field, autoencoder, {})
    model = LanguageFieldModel("4d-langsplat", config, SeededTextEncoder(feature_dim), shared, sensitive=None,
                               device=str(device))
    return model, camera


def stage_seconds(model: LanguageFieldModel, text: str, frames: list[Frame],
                  sync: Callable[[], None]) -> dict[str, float]:
    """Seconds per frame of each of :data:`STAGES`: the work of one answer stage by stage, synchronised
    between stages (slightly slower in total than the pipelined answer, which is the number to report)."""
    basis, zq, zc = model._reduced_phrases(text)
    stages = dict.fromkeys(STAGES, 0.0)
    for frame in frames:
        t_prev = time.perf_counter()

        def lap(name: str) -> None:
            nonlocal t_prev
            sync()
            now = time.perf_counter()
            stages[name] += (now - t_prev) / len(frames)
            t_prev = now

        state = model.geometry.at(frame.time)
        lap("deform")
        latents, alpha = model.field.render_with_alpha(state, frame.camera)
        lap("render")
        reduced = model.decode_reduced(latents, alpha, basis)
        lap("decode")
        result = query_levels(reduced, zq, zc, model.relevance_cfg)
        lap("query")
        result.mask.cpu().numpy(), result.relevance.float().cpu().numpy()
        lap("to_host")
    return stages


def prepared_seconds_per_answer(model: LanguageFieldModel, texts: list[str], frames: list[Frame],
                                sync: Callable[[], None]) -> float:
    """Seconds per answer when ``texts`` are all asked of ``frames`` after one :meth:`LanguageFieldModel.prepare`."""
    model.prepare(texts)
    sync()
    t0 = time.perf_counter()
    for frame in frames:
        for text in texts:
            model.query_agnostic(text, [frame])
    sync()
    return (time.perf_counter() - t0) / (len(frames) * len(texts))


def _synchronizer(device: torch.device) -> Callable[[], None]:
    """Waits for the device's queued work (CUDA), so that wall-clock laps time what was asked."""
    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    return sync


def _bool_mask(mask) -> np.ndarray:
    """An answer's mask (a numpy array, or a tensor on any device) as a bool array."""
    return np.asarray(mask.cpu() if isinstance(mask, torch.Tensor) else mask, dtype=bool)

