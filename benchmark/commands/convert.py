"""``bench4d convert``: turn another release's outputs into a bench4d predictions folder, to score them.

    bench4d convert release --run eval_result/<exp>/<timestamp>-<tag> --annotations <scene>/annotations \
        --dataset hypernerf --out preds/<scene> [--scene <scene folder>] [--similarity video|clip]
    bench4d score --gt <scene>/annotations.json --pred preds/<scene>

``release``: the 4D LangSplat release's ``eval/eval.py`` run folder (written with ``--visualize_results``
and ``--detail_results``), read as :mod:`benchmark.release_outputs` describes. ``--out`` may not lie in the run
folder, the annotations folder or the scene folder (:func:`benchmark.core.outputs.guard_output`).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", choices=("release",), help="whose outputs: the 4D LangSplat release")
    parser.add_argument("--run", type=Path, required=True, help="the release's eval run folder")
    parser.add_argument("--annotations", type=Path, required=True,
                        help="the release's annotations/ folder the run was scored on")
    parser.add_argument("--dataset", choices=("hypernerf", "neu3d"), required=True,
                        help="numbers frames from 1 (hypernerf) or 0 (neu3d), as the release does")
    parser.add_argument("--scene", type=Path, default=None,
                        help="scene folder: frames named as the scene names them (default: as the file records)")
    parser.add_argument("--similarity", choices=("video", "clip"), default="video",
                        help="which similarity scores the time-sensitive queries (default: video, the paper's)")
    parser.add_argument("--out", type=Path, required=True, help="the predictions folder to write")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing predictions file")


def run(args: argparse.Namespace) -> int:
    from benchmark.core.outputs import guard_output
    from benchmark.core.strict import terminal_text

    from ..release_outputs import convert_release_outputs

    # before anything is read: the predictions folder never lands among what it is made from
    guard_output(args.out, [args.run, args.annotations, args.scene], option="--out")
    scene = None
    if args.scene is not None:
        from ..loaders import load_scene

        scene = load_scene(args.scene)
    path = convert_release_outputs(args.run, args.annotations, args.out,
                                   frame_base=1 if args.dataset == "hypernerf" else 0, scene=scene,
                                   similarity=args.similarity, overwrite=args.overwrite)
    print(f"wrote {terminal_text(path)}")
    return 0
