"""``bench4d annotate SCENE_DIR --annotations FILE``: the local annotation web app.

Starts a server on 127.0.0.1 (a free port by default) and prints the address to open, with a
per-launch token in its fragment. Bound to any other address (``--host``), every request, reads
included, needs that token. A port in use or an address that does not resolve is a one-line error
and releases the annotation file's lock. Edits are saved to FILE about a second after they happen. See
:mod:`annotations.tool.server` for the security model and :mod:`annotations.tool.session` for
saving, revisions and the lock file.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from benchmark.core.errors import InputError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene_dir", metavar="SCENE_DIR", help="scene folder (HyperNeRF, Neu3D, D-NeRF layout)")
    parser.add_argument("--annotations", required=True, metavar="FILE",
                        help="annotation file to edit (created on the first edit if missing)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to bind (default 127.0.0.1; anything else exposes the tool to the network, "
                             "and then every request, reads included, needs the printed token)")
    parser.add_argument("--port", type=int, default=0, help="port (default 0: a free one)")
    parser.add_argument("--split", default="scored",
                        help="frames to offer: scored (the test frames the benchmark scores), all, or a comma "
                             "list of train/val/test (default scored)")
    parser.add_argument("--scale", default=None, help="image scale passed to the scene loader (e.g. 0.5)")
    parser.add_argument("--segmenter", choices=["grabcut", "sam"], default="grabcut",
                        help="assisted segmentation backend (default grabcut; sam needs --sam-checkpoint)")
    parser.add_argument("--sam-checkpoint", type=Path, default=None, help="path to SAM weights (segmenter sam)")
    parser.add_argument("--sam-model", default="vit_b", help="SAM architecture of the checkpoint (vit_b, vit_l, vit_h)")
    parser.add_argument("--annotator", default="human",
                        help="recorded in the file's info.annotator: human (default), simulated or scripted")
    parser.add_argument("--method", default=None,
                        help="recorded in the file's info.method (how masks were made; for scripted sessions)")
    parser.add_argument("--no-timing", action="store_true",
                        help="do not record active editing time per frame (scripted sessions)")
    parser.add_argument("--autosave-ms", type=int, default=1000, help="autosave delay after an edit (default 1000)")
    parser.add_argument("--verbose", action="store_true", help="log every request")


def run(args: argparse.Namespace) -> int:
    from annotations.assist import make_segmenter
    from annotations.tool.server import serve
    from annotations.tool.session import AnnotationSession, SessionConfig
    from benchmark.loaders import load_scene

    if not 0 <= args.port <= 65535:
        raise InputError(None, "--port", f"{args.port} is not a port number")
    if args.autosave_ms < 100 or args.autosave_ms > 10000:
        raise InputError(None, "--autosave-ms", "expected 100..10000")
    scale = None
    if args.scale is not None:
        try:
            scale = float(args.scale)
        except ValueError:
            scale = args.scale
    scene = load_scene(args.scene_dir, scale=scale)
    path = Path(args.annotations)
    if path.exists() and path.is_dir():
        raise InputError(path, "--annotations", "is a folder; give a .json file")
    cache_dir = path.resolve().parent / ".bench4d-cache" / "sam" if args.segmenter == "sam" else None
    segmenter = make_segmenter(args.segmenter, sam_checkpoint=args.sam_checkpoint, sam_model=args.sam_model,
                               cache_dir=cache_dir)
    config = SessionConfig(split=args.split, annotator=args.annotator, method=args.method,
                           record_timing=not args.no_timing, autosave_delay_ms=args.autosave_ms)
    session = AnnotationSession(scene, path, segmenter=segmenter, config=config)
    serve(session, args.host, args.port, quiet=not args.verbose)
    return 0
