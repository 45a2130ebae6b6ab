"""``bench4d score``: score prediction folders against ground-truth annotations.

    bench4d score --gt scene.json --pred preds/scene [--out results.json]
    bench4d score --gt a.json --gt b.json --pred preds/          # preds/<scene>/ per GT scene
    bench4d score --gt a.json --pred pa --gt b.json --pred pb    # explicit pairs
    bench4d score --gt scene/annotations --scene scene --pred preds/scene   # the release's annotation folder

A ``--gt`` in the 4D LangSplat release's layout (its ``annotations/`` folder: ``train/_annotations.coco.json``
and ``video_annotations.json``, or that COCO file) is read as ``bench4d eval --annotations`` reads it, against
the frame names and sizes of its scene folder: one ``--scene`` per such ``--gt``, in order.

Prediction folders are described in :mod:`benchmark.predictions`; the metrics and the temporal
rule in :mod:`benchmark.metrics`. Prints a plain-text table; ``--out`` writes the results JSON
(metrics in percent, the per-query table, the per-frame records, the rule used, provenance).

``--out`` never replaces an input (:func:`benchmark.core.outputs.guard_output`): a path that is (or resolves
to, or is a hard link of) a ground-truth file, the ``--eval-frames`` file or a results file read beside the
predictions, or that lies in a prediction folder, a release annotation folder or a ``--scene`` folder (links
followed), is refused before anything is scored, and so is a folder; a path that cannot be written is a
one-line error. Texts from the files (query texts, scene names) are printed with control characters
escaped (:func:`benchmark.core.strict.terminal_text`).

Queries a method declined are listed and count 0 in the full means, which are printed beside the means
over the answered queries and the answered / asked counts (:mod:`benchmark.metrics.scoring`): a prediction
folder names them in ``info.unanswered_queries``; a folder ``bench4d eval`` wrote before it did so
(``seed<N>.predictions/``) has them in the results file beside it (``seed<N>.json``), read instead.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Optional

import numpy as np

from benchmark.core.atomic import write_json
from benchmark.core.errors import InputError
from benchmark.core.strict import check_name, terminal_text
from ._common import add_protocol_argument


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--gt", action="append", required=True, metavar="ANNOTATIONS",
                        help="ground-truth annotation file (bench4d JSON), or the release's annotation folder "
                             "(Roboflow COCO + video_annotations.json; needs --scene); repeat for several scenes")
    parser.add_argument("--scene", action="append", default=[], metavar="DIR",
                        help="scene folder of a release-layout --gt (its frame names and sizes), one per such "
                             "--gt in order")
    parser.add_argument("--pred", action="append", required=True, metavar="DIR",
                        help="prediction folder, one per --gt; or one folder holding <scene>/ subfolders")
    parser.add_argument("--out", type=Path, default=None, help="write the results JSON here (atomically)")
    add_protocol_argument(parser)
    parser.add_argument("--tau-from", choices=("raw", "smoothed"), default=None,
                        help="tau = mean of the raw scores or of the smoothed ones, for every method kind "
                             "(default: the protocol's; release: raw for feature scores, smoothed for "
                             "relevance peaks, as the predictions' info.time_score says)")
    parser.add_argument("--absent-frames", choices=("skip", "score-empty"), default=None,
                        help="frames where a query's object is absent: not scored (release) or scored against "
                             "the empty mask; default: the protocol's")
    parser.add_argument("--smoothing-ends", choices=("renormalise", "keep", "replicate"), default=None,
                        help="missing neighbours in temporal smoothing (default: the protocol's; release: keep)")
    parser.add_argument("--smoothing-weights", default=None, metavar="W,W,W",
                        help="temporal smoothing kernel (default 0.1,0.8,0.1; '1' disables)")
    from .eval import add_split_argument

    add_split_argument(parser)
    parser.add_argument("--eval-frames", default="all", metavar="all|NAME,NAME|@FILE",
                        help="frames to score: all annotated frames (default), a comma list, or @file (one name a line)")
    parser.add_argument("--allow-extra", action="store_true", help="ignore predicted queries unknown to the GT")
    parser.add_argument("--no-frames", action="store_true", help="leave per-frame records out of the results JSON")
    parser.add_argument("--quiet", action="store_true", help="print only the dataset line")


def _protocol(args: argparse.Namespace):
    """The protocol named by ``--protocol`` with the temporal and absent-frame flags applied (named ``custom``
    if they change it). Predictions hold masks already: only its temporal rule and absent-frame rule decide
    anything here."""
    from benchmark.core.protocol import get_protocol

    changes: dict = {}
    if args.tau_from:
        changes["temporal.tau_from"] = changes["temporal.relevance_peak_tau_from"] = args.tau_from
    if args.absent_frames:
        changes["scoring.absent_frames"] = args.absent_frames
    if args.smoothing_ends:
        changes["temporal.ends"] = args.smoothing_ends
    if args.smoothing_weights:
        try:
            changes["temporal.weights"] = tuple(float(x) for x in args.smoothing_weights.split(","))
        except ValueError:
            raise InputError(None, "--smoothing-weights", f"not a comma list of numbers: {args.smoothing_weights!r}") from None
    try:
        return get_protocol(args.protocol).with_changes(changes)
    except ValueError as err:
        raise InputError(None, "--smoothing-weights", str(err)) from None


def _eval_frames(spec: str) -> set[str] | None:
    if spec == "all":
        return None
    if spec.startswith("@"):
        path = Path(spec[1:])
        if not path.is_file():
            raise InputError(path, "--eval-frames", "file not found")
        names = [line.strip() for line in path.read_text(encoding="utf-8").splitlines()]
        names = [n for n in names if n and not n.startswith("#")]
    else:
        names = [n.strip() for n in spec.split(",") if n.strip()]
    if not names:
        raise InputError(None, "--eval-frames", "no frame names given")
    return set(names)


def _folder(pred: Path) -> Path:
    """A ``--pred`` as the folder it names (``read_predictions`` takes its main file too)."""
    return pred.parent if pred.is_file() else pred


def _input_files(args: argparse.Namespace) -> list[Path]:
    """Every file this command reads: ground truth, prediction files (either layout; under a folder of
    ``<scene>/`` folders too), the results file beside an eval folder, and the ``--eval-frames`` list."""
    files = []
    for gt in map(Path, args.gt):
        files += sorted(p for p in gt.rglob("*") if p.is_file()) if gt.is_dir() else [gt]
        if is_release_layout(gt) and gt.is_file():  # the COCO file: video_annotations.json is read beside train/
            files.append(gt.parent.parent / "video_annotations.json")
    if args.eval_frames.startswith("@"):
        files.append(Path(args.eval_frames[1:]))
    for pred in args.pred:
        folder = _folder(Path(pred))
        if folder.is_dir():
            files += [p for p in folder.rglob("*") if p.is_file()]
        beside = _results_beside(folder)
        if beside is not None:
            files.append(beside)
    return files


def check_out(out: Path, inputs: list[Path], folders: list[Path] = ()) -> None:
    """Refuse an ``--out`` that would replace an input file (``inputs``) or land in an input folder
    (``folders``: prediction, annotation and scene folders), or that cannot be written, before anything is
    scored (:func:`benchmark.core.outputs.guard_output`)."""
    from benchmark.core.outputs import guard_output

    if out.is_dir():
        raise InputError(out, "--out", "is a folder; give the path of a results file (e.g. results.json)")
    guard_output(out, [*inputs, *folders], option="--out")
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(out, "--out", f"cannot be written: {parent} is a file, not a folder")
            if not os.access(parent, os.W_OK | os.X_OK):
                raise InputError(out, "--out", f"cannot be written: no permission to write in {parent}")
            break


def _results_beside(folder: Path) -> Optional[Path]:
    """The results file ``bench4d eval`` writes beside its predictions folder (``seed0.predictions`` ->
    ``seed0.json``); None for a folder not named like one."""
    suffix = ".predictions"
    if not folder.name.endswith(suffix) or folder.name == suffix:
        return None
    return folder.with_name(folder.name[: -len(suffix)] + ".json")


def _unanswered_from_results(predictions, folder: Path) -> bool:
    """Give ``predictions`` the queries its run declined when the folder does not list them but the results
    file ``bench4d eval`` wrote beside it does (folders written before the list was part of the
    predictions). True when it did."""
    from benchmark.core.atomic import read_json
    from ..metrics.scoring import UNANSWERED_FIELD

    if UNANSWERED_FIELD in (predictions.info or {}):
        return False
    folder = _folder(folder)
    results = _results_beside(folder)
    if results is None or not results.is_file():
        return False
    doc = read_json(results)
    listed = doc.get(UNANSWERED_FIELD) if isinstance(doc, dict) and doc.get("format") == "bench4d-run" else None
    if not listed:
        return False
    if not isinstance(listed, list) or not all(isinstance(t, str) for t in listed):
        raise InputError(results, UNANSWERED_FIELD, "expected a list of query texts")
    recorded = doc.get("predictions")
    if isinstance(recorded, str) and (results.parent / recorded).parent.resolve() != folder.resolve():
        return False  # that results file is not this folder's run
    predictions.info = {**(predictions.info or {}), UNANSWERED_FIELD: list(listed)}
    return True


def is_release_layout(gt: Path) -> bool:
    """Whether a ``--gt`` names the release's annotation folder or its COCO file (not a bench4d JSON file)."""
    return gt.is_dir() or gt.name.endswith(".coco.json")


def load_ground_truth(gts: list[str], scenes: list[str]) -> list:
    """The annotation set of every ``--gt``: bench4d JSON as it is; one in the release's layout read against
    the next of ``scenes`` (``--scene`` folders: the frame names and sizes it annotates)."""
    from annotations.format import load_annotations

    from ..loaders import load_scene
    from ..runner import load_release_annotations

    left = list(scenes)
    out = []
    for gt in map(Path, gts):
        if not is_release_layout(gt):
            out.append(load_annotations(gt))
            continue
        if not left:
            raise InputError(gt, "--gt", "is in the release's layout, which names frames by number only: pass "
                             "--scene DIR (its scene folder) for each such --gt, in order")
        out.append(load_release_annotations(load_scene(Path(left.pop(0))), gt))
    if left:
        raise InputError(None, "--scene", f"{len(left)} --scene without a release-layout --gt to go with: "
                         f"{', '.join(left)}")
    return out


def _pairs(gts: list[str], preds: list[str], asets: list) -> list[tuple[object, Path]]:
    if len(preds) == len(gts):
        return list(zip(asets, (Path(p) for p in preds)))
    if len(preds) == 1:
        root = Path(preds[0])
        pairs = []
        for gt, aset in zip(gts, asets):
            # a scene name is one folder name (the annotation reader checks it); never a way out of --pred
            check_name(aset.scene, gt, "scene")
            folder = root / aset.scene
            if not folder.is_dir():
                raise InputError(folder, None, f"no prediction folder for scene {aset.scene!r} (from {gt})")
            pairs.append((aset, folder))
        return pairs
    raise InputError(None, "--pred", f"give one --pred per --gt ({len(gts)}), or one folder with <scene>/ subfolders")


def _fmt(value: object, digits: int = 2) -> str:
    if value is None:
        return "-"
    if isinstance(value, (float, np.floating)):
        return "-" if math.isnan(value) else f"{value:.{digits}f}"
    return terminal_text(value)  # texts from files: no escape sequence reaches the terminal


def format_table(headers: list[str], rows: list[list[object]]) -> str:
    """Plain-text table, numbers right-aligned, text left-aligned."""
    cells = [[_fmt(v) for v in row] for row in rows]
    numeric = [all(isinstance(r[i], (int, float, np.number)) or r[i] is None for r in rows) for i in range(len(headers))]
    widths = [max([len(h)] + [len(r[i]) for r in cells]) for i, h in enumerate(headers)]

    def line(values: list[str]) -> str:
        return "  ".join(v.rjust(w) if num else v.ljust(w) for v, w, num in zip(values, widths, numeric)).rstrip()

    return "\n".join([line([terminal_text(h) for h in headers]), line(["-" * w for w in widths])]
                     + [line(r) for r in cells])


def _coverage(values: dict, kind: str) -> str:
    """``answered / asked`` queries of ``kind`` in a summary."""
    return f"{values[f'answered_{kind}_queries']} / {values[f'asked_{kind}_queries']}"


def report_text(dataset, quiet: bool = False) -> str:
    """The printed report of a :class:`~benchmark.metrics.DatasetScore` (percent): per query and per scene
    (unless ``quiet``), then the dataset's full means (every asked query, an unanswered one counting 0) and
    answered-only means, labelled, with the answered / asked counts."""
    from ..metrics import ABSENT_FP, ANSWERED_SUFFIX, RANKED_METRICS

    ranked = list(RANKED_METRICS)
    parts = []
    if not quiet:
        q = dataset.query_table()
        rows = [[r.scene, r.query, r.kind, int(r.frames), 100 * r.miou, 100 * r.macc, 100 * r.acc, 100 * r.viou]
                for r in q.itertuples()]
        parts.append(format_table(["scene", "query", "kind", "frames", "IoU", "pixAcc", "Acc", "vIoU"], rows))
        s = dataset.scene_table()
        rows = [[r["scene"], *[r[m] for m in ranked], r["AUC"], r["nearTau"], r[ABSENT_FP],
                 _coverage(r, "agnostic"), _coverage(r, "sensitive")] for r in s.to_dict(orient="records")]
        parts.append(format_table(["scene", *ranked, "AUC", "nearTau", ABSENT_FP, "agnostic answered / asked",
                                   "sensitive answered / asked"], rows))
    summary = dataset.summary()
    parts.append(format_table(
        [f"mean over {summary['scenes']} scene(s)", *ranked],
        [["every asked query (unanswered = 0)", *[summary[m] for m in ranked]],
         ["answered queries only", *[summary[m + ANSWERED_SUFFIX] for m in ranked]]]))
    parts.append(f"queries answered / asked: time-agnostic {_coverage(summary, 'agnostic')}, time-sensitive "
                 f"{_coverage(summary, 'sensitive')}\n"
                 f"diagnostics of the answered time-sensitive queries: AUC {_fmt(summary['AUC'])}, "
                 f"nearTau {_fmt(summary['nearTau'])}\n"
                 f"absentFP (non-empty masks where the object is absent, time-agnostic queries): "
                 f"{_fmt(summary[ABSENT_FP])} % of {summary['absent_frames']} (query, frame) pairs")
    return "\n\n".join(parts)


def run(args: argparse.Namespace) -> int:
    from .. import __version__
    from ..metrics import ScoreConfig, aggregate_scenes, score_scene
    from ..core.scene import split_frame_names
    from ..predictions import read_predictions

    protocol = _protocol(args)
    temporal = protocol.temporal
    if args.out is not None:  # before anything is read or scored: a refused path costs nothing
        folders = [_folder(Path(p)) for p in args.pred] + [Path(s) for s in args.scene]
        folders += [Path(g) for g in args.gt if Path(g).is_dir()]  # the release's annotation folder
        folders += [Path(g).parent.parent for g in args.gt if is_release_layout(Path(g)) and Path(g).is_file()]
        check_out(args.out, _input_files(args), folders)
    wanted = _eval_frames(args.eval_frames)
    asets = load_ground_truth(args.gt, args.scene)
    pairs = _pairs(args.gt, args.pred, asets)
    if wanted is not None:
        every = set().union(*({f.name for f in a.frames} for a in asets))
        unknown = sorted(wanted - every)
        if unknown:
            raise InputError(None, "--eval-frames", f"not frames of any given scene: {unknown[:5]}")

    start = time.perf_counter()
    scenes = []
    from_results = []
    for aset, folder in pairs:
        # the split's frames (all of a file that records no splits), narrowed by --eval-frames
        names = split_frame_names(args.split, [f.name for f in aset.frames], aset.info.get("splits"),
                                  source=f"ground truth of {aset.scene}")
        frames = tuple(sorted(set(names) if wanted is None else wanted & set(names)))
        config = ScoreConfig.from_protocol(protocol, eval_frames=frames, allow_extra=args.allow_extra)
        predictions = read_predictions(folder)
        if _unanswered_from_results(predictions, folder):
            from_results.append(aset.scene)
        scenes.append(score_scene(aset, predictions, config))
    dataset = aggregate_scenes(scenes)
    seconds = time.perf_counter() - start

    print(report_text(dataset, quiet=args.quiet))
    records = sum(len(s.records) for s in scenes)
    print(f"\nscored {records} (query, frame) records in {seconds:.3f} s; protocol {protocol.name}: "
          f"tau from {temporal.tau_from} scores (relevance peaks: {temporal.relevance_peak_tau_from}), "
          f"ends={temporal.ends}, weights={list(temporal.weights)}, absent frames: {protocol.scoring.absent_frames}")
    for s in scenes:
        if s.skipped:
            print(terminal_text(f"note: {s.scene}: not scored (no evaluated frame): {', '.join(s.skipped)}"),
                  file=sys.stderr)
        if s.unanswered:
            where = "; listed by the results file beside the predictions" if s.scene in from_results else ""
            print(terminal_text(f"note: {s.scene}: not scored (unanswered by the method{where}): "
                                f"{', '.join(s.unanswered)}"), file=sys.stderr)
    if args.out is not None:
        provenance = {
            "bench4d_version": __version__,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "command": "bench4d score " + " ".join(sys.argv[2:]) if sys.argv[1:2] == ["score"] else None,
            "gt": [str(Path(p).resolve()) for p in args.gt],
            "pred": [str(folder.resolve()) for _, folder in pairs],
            "python": platform.python_version(),
            "numpy": np.__version__,
            "score_seconds": round(seconds, 4),
            "protocol": protocol.to_dict(),
            "protocol_applied": "temporal and absent-frame rules only: the predictions' masks were made by the method",
        }
        try:
            write_json(args.out, dataset.to_json(provenance, include_frames=not args.no_frames))
        except OSError as err:  # read-only place, full disk, a folder made there meanwhile
            raise InputError(args.out, "--out", f"cannot be written: {err.strerror or err}") from None
        print(f"wrote {terminal_text(args.out)}")
    return 0
