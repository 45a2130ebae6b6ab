"""``bench4d annotate-bench``: the annotation tool measured by a simulated annotator.

Generates every synthetic preset (small images; exact truth) and reads the D-NeRF scenes (alpha
masks as the truth of whole objects), runs the tool's server on each, drives it over HTTP with the
simulated annotator of :mod:`benchmark.studies.annotation_bench` (clicks only and box first, time
segments from the frames' pixels), and writes ``reports/annotation/annotation_bench.{json,md}``. The annotation files it makes stay under
``--work`` and say ``annotator: simulated`` with the protocol.
"""

from __future__ import annotations

import argparse
import contextlib
import tempfile
import threading
from pathlib import Path
from typing import Iterator

DNERF_ROOT = Path("../shared/data/dnerf")
DNERF_ANNOTATIONS = Path(__file__).resolve().parents[2] / "annotations" / "scenes" / "dnerf"
"""The D-NeRF annotation files whose whole-object queries are measured (their masks are not used)."""
PAINTED_MARK = "truth-colours.done"
"""Written in a generated scene's folder once every frame is repainted (``--images truth-colours``)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--presets", default="all", help="comma list of synthetic presets, or all, or none")
    parser.add_argument("--size", type=int, default=None,
                        help="synthetic image width in pixels (default: each preset's own, the size it is scored at)")
    parser.add_argument("--dnerf", default=str(DNERF_ROOT),
                        help="folder of D-NeRF scenes with annotation files in annotations/scenes/dnerf ('' = none)")
    parser.add_argument("--backends", default="grabcut", help="comma list: grabcut, sam (sam needs --sam-checkpoint)")
    parser.add_argument("--sam-checkpoint", type=Path, default=None, help="SAM weights for the sam backend")
    parser.add_argument("--target-iou", type=float, default=0.90, help="IoU at which the annotator stops (0.90)")
    parser.add_argument("--work", type=Path, default=None, help="folder for scenes and annotation files (a temp dir)")
    parser.add_argument("--out", type=Path, default=Path("reports/annotation"), help="report folder")
    parser.add_argument("--images", choices=("rendered", "truth-colours"), default="rendered",
                        help="truth-colours: repaint the synthetic frames with one flat colour per truth region (every "
                             "boundary an edge: the assistant's ceiling); D-NeRF scenes are left out. Writes "
                             "annotation_bench_truth_colours.{json,md}")
    parser.add_argument("--adopt-dnerf", action="store_true",
                        help="afterwards, put the simulated annotator's whole-object masks into the D-NeRF files of "
                             "annotations/scenes/dnerf where they reach --target-iou against the alpha masks")


def tool_launcher(segmenters: dict, config):
    """The study's :data:`~benchmark.studies.annotation_bench.ToolLauncher`: the real server in a thread."""
    from annotations.tool.server import start_server
    from annotations.tool.session import AnnotationSession, SessionConfig
    from benchmark.loaders import load_scene
    from benchmark.studies.annotation_bench import ToolClient

    protocol = {"masks": "box around the truth mask with each edge jittered (box_jitter: standard deviation as a "
                         "share of the object's size), then clicks at the centre of the largest error region; "
                         "clicks-only files: the first click at the interior point farthest from the boundary",
                "box_jitter": config.box_jitter, "target_iou": config.target_iou,
                "max_interactions": config.max_interactions,
                "intervals": "[ and ] where a change detector finds the base object's pixels change"}

    @contextlib.contextmanager
    def launch(scene_dir: Path, annotations: Path, split: str, backend: str) -> Iterator[ToolClient]:
        session_config = SessionConfig(split=split, annotator="simulated", protocol=protocol, record_timing=False,
                                       method="benchmark/studies/annotation_bench.py")
        session = AnnotationSession(load_scene(scene_dir), annotations, segmenter=segmenters[backend],
                                    config=session_config)
        httpd = start_server(session, announce=lambda _line: None)
        thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)
        thread.start()
        try:
            yield ToolClient(httpd.url, httpd.token)
        finally:
            httpd.shutdown()
            httpd.server_close()
            session.close()
            thread.join(5)

    return launch


def run(args: argparse.Namespace) -> int:
    from annotations.assist import make_segmenter
    from benchmark.core.errors import InputError
    from benchmark.studies import annotation_bench as bench

    config = bench.BenchConfig(target_iou=args.target_iou, images=args.images)
    if args.images == "truth-colours" and args.adopt_dnerf:
        raise InputError(None, "--adopt-dnerf", "takes the rendered images' masks; not with --images truth-colours")
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    if not backends or set(backends) - {"grabcut", "sam"}:
        raise InputError(None, "--backends", "expected a comma list of grabcut, sam")
    segmenters = {b: make_segmenter(b, sam_checkpoint=args.sam_checkpoint) for b in backends}
    launch = tool_launcher(segmenters, config)
    with contextlib.ExitStack() as stack:
        work = args.work or Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="annotate-bench-")))
        results = []
        for scene in _scenes(args, work):
            results.append(bench.bench_scene(scene, launch, work, backends, config))
            if args.adopt_dnerf and scene.kind == "dnerf":
                made = work / f"{scene.name}.every-frame.{backends[0]}.json"
                counts = bench.adopt_simulated_masks(DNERF_ANNOTATIONS / f"{scene.name}.json", made, scene,
                                                     args.target_iou)
                print(f"annotate-bench: dnerf/{scene.name}: {counts['adopted']} mask(s) adopted, "
                      f"{counts['kept']} kept")
        name = "annotation_bench" if args.images == "rendered" else "annotation_bench_truth_colours"
        for path in bench.write(results, config, args.out, name=name):
            print(path)
    return 0


def _scenes(args: argparse.Namespace, work: Path):
    """The truth scenes to measure, made or read one at a time."""
    from benchmark.studies.annotation_bench import dnerf_truth, paint_truth_regions, synthetic_truth
    from benchmark.synthetic import generate, list_presets

    presets = list_presets() if args.presets == "all" else [p for p in args.presets.split(",") if p and p != "none"]
    painted = args.images == "truth-colours"
    for preset in presets:
        scene_dir = work / ("scenes-truth-colours" if painted else "scenes") / preset
        if not (scene_dir / "annotations.json").exists():
            generate(preset, scene_dir, size=args.size, overwrite=True)
        if painted and not (scene_dir / PAINTED_MARK).exists():  # an interrupted repaint is redone whole
            paint_truth_regions(scene_dir)
            (scene_dir / PAINTED_MARK).write_text("every frame repainted one flat colour per truth region\n")
        print(f"annotate-bench: {preset}" + (" (truth colours)" if painted else ""), flush=True)
        yield synthetic_truth(scene_dir)
    root = Path(args.dnerf) if args.dnerf and not painted else None
    for file in sorted(DNERF_ANNOTATIONS.glob("*.json")) if root is not None and root.is_dir() else []:
        if (root / file.stem).is_dir():
            print(f"annotate-bench: dnerf/{file.stem}", flush=True)
            yield dnerf_truth(root / file.stem, file)
