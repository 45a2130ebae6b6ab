"""``bench4d data``: make, validate and show scenes.

    bench4d data presets                                   # list the synthetic presets
    bench4d data make-synthetic PRESET --out DIR [--size 128] [--height H] [--frames N] [--views N]
                                [--layout hypernerf|neu3d|dnerf] [--seed S] [--overwrite] [--jobs N]
    bench4d data validate DIR [--annotations FILE]         # scene, every image decoded, annotations (+ truth)
    bench4d data show DIR [--out sheet.png] [--frames 4]   # contact sheet beside DIR: frames with GT masks
    bench4d data timing [--size 128] [--out reports/synthetic_generation.md]
    bench4d data digests [--presets a,b] [--sizes 128] [--write]  # scene versions (synthetic/digests.json)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmark.core.errors import InputError
from benchmark.core.strict import terminal_text
from ._common import parse_seed

REPROJECTION_TOLERANCE_PX = 1e-3
"""A loaded camera must reproject points to within this many pixels of the generator's camera."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="data_command", metavar="SUBCOMMAND")
    sub.required = True

    sub.add_parser("presets", help="list the synthetic presets")

    mk = sub.add_parser("make-synthetic", help="render a synthetic preset with exact ground truth")
    mk.add_argument("preset", help="preset name (see 'bench4d data presets')")
    mk.add_argument("--out", type=Path, required=True, help="scene folder to create")
    mk.add_argument("--size", type=int, default=None,
                    help=f"image width in pixels (default: the preset's: {_default_sizes_text()}; the height "
                         "follows the layout's aspect, 'bench4d data presets' lists each preset's frame size)")
    mk.add_argument("--height", type=int, default=None,
                    help="image height in pixels (default: the layout's aspect; HyperNeRF captures: --size 536 "
                         "--height 960)")
    mk.add_argument("--frames", type=int, default=None, help="video length (default: the preset's)")
    mk.add_argument("--views", type=int, default=None, help="cameras of the rig in the neu3d layout")
    mk.add_argument("--layout", choices=("hypernerf", "neu3d", "dnerf"), default=None,
                    help="on-disk layout (default: the preset's)")
    mk.add_argument("--seed", type=parse_seed, default=0, help="random seed (placement, colours, state times, cameras)")
    mk.add_argument("--overwrite", action="store_true", help="replace a previously generated scene in --out")
    mk.add_argument("--no-shadows", action="store_true", help="skip shadow rays (faster, fewer depth cues)")
    mk.add_argument("--jobs", type=int, default=1,
                    help="processes rendering the frames (the files are the same for any count; default 1)")

    va = sub.add_parser("validate", help="check that a scene and its annotations agree")
    va.add_argument("scene", type=Path, help="scene folder")
    va.add_argument("--annotations", type=Path, default=None,
                    help="annotation file (default: SCENE/annotations.json when present)")

    sh = sub.add_parser("show", help="contact sheet of frames with ground-truth masks overlaid")
    sh.add_argument("scene", type=Path, help="scene folder")
    sh.add_argument("--annotations", type=Path, default=None, help="default: SCENE/annotations.json")
    sh.add_argument("--out", type=Path, default=None,
                    help="PNG to write (default: <scene folder>_sheet.png beside the scene folder)")
    sh.add_argument("--frames", type=int, default=4, help="number of annotated frames to show")
    sh.add_argument("--queries", default=None, help="comma-separated query texts to overlay (default: all agnostic)")

    tm = sub.add_parser("timing", help="time the generation of every preset and write a markdown table")
    tm.add_argument("--size", type=int, default=128)
    tm.add_argument("--presets", default=None, help="comma-separated presets (default: all)")
    tm.add_argument("--out", type=Path, default=Path("reports/synthetic_generation.md"))

    dg = sub.add_parser("digests", help="regenerate presets and compare (or --write) their content digests "
                                        "with the committed ones (benchmark/synthetic/digests.json)")
    dg.add_argument("--presets", default=None, help="comma-separated presets (default: all)")
    dg.add_argument("--sizes", type=int, nargs="+", default=[128], help="image widths (default: 128, the runner's)")
    dg.add_argument("--seed", type=parse_seed, default=0)
    dg.add_argument("--write", action="store_true",
                    help="record the digests as the committed scene versions (after a deliberate generator change)")


def run(args: argparse.Namespace) -> int:
    return {"presets": _presets, "make-synthetic": _make, "validate": _validate, "show": _show,
            "timing": _timing, "digests": _digests}[args.data_command](args)


# -- presets / make-synthetic -------------------------------------------------------------------------
def default_frame_size(spec) -> tuple[int, int]:
    """(width, height) of a preset generated without ``--size`` / ``--height``: its default width and the
    height its default layout's aspect gives (as :func:`benchmark.synthetic.generate` makes it)."""
    from ..synthetic import layouts

    aspect = layouts.LAYOUT_SPECS[spec.default_layout].setup.intrinsics.height_over_width
    return spec.default_size, 2 * int(round(spec.default_size * aspect / 2))


def _default_sizes_text() -> str:
    """The presets' default widths, e.g. "128, smoke 48" (the most common first, then the exceptions)."""
    from collections import Counter

    from ..synthetic import PRESETS

    common = Counter(spec.default_size for spec in PRESETS.values()).most_common(1)[0][0]
    others = [f"{spec.name} {spec.default_size}" for spec in PRESETS.values() if spec.default_size != common]
    return ", ".join([str(common), *others])


def _presets(args: argparse.Namespace) -> int:
    from ..synthetic import PRESETS

    for spec in PRESETS.values():
        ts = "time-sensitive" if spec.time_sensitive else "time-agnostic"
        width, height = default_frame_size(spec)
        analogue = spec.analogue.strip("()")  # "(tests)" is printed in one pair of brackets, like the others
        # how its states change and its captions' noise (levels: benchmark.synthetic.state_changes, caption_noise)
        levels = f" [states: {spec.state_changes}, captions: {spec.caption_noise}]" if spec.state_changes else ""
        print(f"{spec.name:14s} {spec.default_layout:9s} {spec.default_frames:3d} frames  {width:3d}x{height:<3d}  "
              f"{ts:14s}  ({analogue}) {spec.description}{levels}")
    return 0


def _make(args: argparse.Namespace) -> int:
    import time

    from ..synthetic import generate

    out = Path(args.out)
    if out.is_dir() and any(out.iterdir()) and not args.overwrite:  # in the command's words, not the function's
        raise InputError(out, None, "folder exists and is not empty; pass --overwrite to replace a previously "
                                    "generated scene")
    start = time.perf_counter()
    out = generate(args.preset, args.out, size=args.size, frames=args.frames, views=args.views,
                   layout=args.layout, seed=args.seed, overwrite=args.overwrite, shadows=not args.no_shadows,
                   height=args.height, jobs=args.jobs)
    print(f"wrote {out} in {time.perf_counter() - start:.1f} s")
    return _validate(argparse.Namespace(scene=out, annotations=None))


# -- validate -------------------------------------------------------------------------------------------
def _annotation_path(scene_dir: Path, given: Path | None) -> Path | None:
    if given is not None:
        if not given.is_file():
            raise InputError(given, None, "annotation file not found")
        return given
    default = scene_dir / "annotations.json"
    return default if default.is_file() else None


def check_truth(scene, truth_dir: Path) -> str:
    """Check the generator truth against the loaded scene: same frames, times, sizes, and cameras that
    reproject within :data:`REPROJECTION_TOLERANCE_PX`. Returns a one-line summary."""
    from benchmark.core.truth import load_truth

    truth = load_truth(truth_dir)
    loaded = {f.name: f for f in scene.frames}
    missing = sorted(set(truth.frames) - set(loaded))
    if missing:
        raise InputError(truth.root, "frames", f"{len(missing)} truth frames are not in the scene, e.g. {missing[:3]}")
    rng = np.random.default_rng(0)
    worst = 0.0
    for name, tf in truth.frames.items():
        f = loaded[name]
        if (f.time_index, f.split, str(f.camera_id)) != (tf.time_index, tf.split, tf.camera_id) or f.time != tf.time:
            raise InputError(truth.root, f"frames.{name}",
                             f"truth says time_index {tf.time_index}, time {tf.time!r}, split {tf.split}, camera "
                             f"{tf.camera_id}; the loader says {f.time_index}, {f.time!r}, {f.split}, {f.camera_id}")
        cam, ref = f.camera, tf.camera
        if (cam.width, cam.height) != (ref.width, ref.height):
            raise InputError(truth.root, f"frames.{name}", f"truth is {ref.width}x{ref.height}, the loaded image "
                                                           f"{cam.width}x{cam.height} (load at the truth's scale)")
        depth = rng.uniform(0.5, 2.0, (16, 1))
        pix = rng.uniform(0, 1, (16, 2)) * [ref.width, ref.height]
        rays = np.stack([(pix[:, 0] - ref.cx) / ref.fx, (pix[:, 1] - ref.cy) / ref.fy, np.ones(16)], axis=1) * depth
        points = (rays - ref.t) @ ref.R  # camera -> world
        uv, _ = cam.project(points)
        worst = max(worst, float(np.abs(uv - pix).max()))
    if worst > REPROJECTION_TOLERANCE_PX:
        raise InputError(truth.root, "cameras", f"loaded cameras differ from the generator's by up to {worst:.3g} px "
                                                f"(tolerance {REPROJECTION_TOLERANCE_PX})")
    return (f"truth: {len(truth.frames)} frames agree with the loader (max reprojection error {worst:.1e} px), "
            f"preset {truth.preset!r} seed {truth.seed}, generator {truth.generator_version}")


def _validate(args: argparse.Namespace) -> int:
    from annotations.format import load_annotations

    from ..loaders import load_scene
    from benchmark.core.truth import TRUTH_DIR

    scene = load_scene(args.scene)
    print(terminal_text(scene.summary()))
    print(decode_every_image(scene))
    path = _annotation_path(Path(args.scene), args.annotations)
    if path is None:
        print("annotations: none (no annotations.json)")
    else:
        aset = load_annotations(path, scene=scene)  # also checks names, sizes, time indices
        agn, sen = len(aset.agnostic_queries), len(aset.sensitive_queries)
        empty = sum(1 for rle in aset.masks.values() if not _rle_has_pixels(rle))
        print(f"annotations: {len(aset.frames)} evaluated frames, {agn} time-agnostic and {sen} time-sensitive "
              f"queries, {len(aset.masks)} masks ({empty} absent), num_time_steps {aset.num_time_steps}")
        for q in aset.sensitive_queries:
            base = aset.query(q.base).text if q.base is not None else "?"
            print(terminal_text(f"  {q.text!r} (base {base!r}): {q.intervals}"))
    truth_dir = Path(args.scene) / TRUTH_DIR
    if truth_dir.is_dir():
        print(check_truth(scene, truth_dir))
    print("OK")
    return 0


def decode_every_image(scene) -> str:
    """Decode every frame's image once, as a run would: a truncated or corrupt file is an :class:`InputError`
    naming it now, not in the middle of a fit (reading headers alone passes a file cut in half). Frames whose
    image is not on disk at all (a cameras-only folder the loader accepted) are counted, not decoded.
    Returns a one-line summary."""
    decoded = absent = 0
    for frame in scene.frames:
        path = getattr(frame, "image_path", None)
        if path is not None and not Path(path).exists() and not Path(path).is_symlink():
            absent += 1
            continue
        frame.image()
        decoded += 1
    return f"images: {decoded} decoded" + (f", {absent} not on disk (cameras only)" if absent else "")


def _rle_has_pixels(rle: dict) -> bool:
    from benchmark.core.annotation import decode_mask

    return bool(decode_mask(rle).any())


# -- show -------------------------------------------------------------------------------------------------
def _show(args: argparse.Namespace) -> int:
    from annotations.format import load_annotations
    from benchmark.core.outputs import guard_output

    from ..loaders import load_scene

    scene = load_scene(args.scene)
    path = _annotation_path(Path(args.scene), args.annotations)
    if path is None:
        raise InputError(Path(args.scene) / "annotations.json", None, "no annotations to show (pass --annotations)")
    out = args.out or default_sheet_path(Path(args.scene))
    # the sheet never replaces what it shows: a scene file (links followed) or the annotations
    guard_output(out, [args.scene, path], option="--out")
    aset = load_annotations(path, scene=scene)
    wanted = None if args.queries is None else [t.strip() for t in args.queries.split(",") if t.strip()]
    write_contact_sheet(scene, aset, out, num_frames=args.frames, queries=wanted)
    print(f"wrote {terminal_text(out)}")
    return 0


def default_sheet_path(scene_dir: Path) -> Path:
    """Where ``data show`` writes without ``--out``: ``<folder>_sheet.png`` beside the scene folder, never
    in the current folder (which may be a checkout), and never inside the scene (a loader reads it)."""
    folder = Path(scene_dir).resolve()
    return folder.parent / f"{folder.name}_sheet.png"


def write_contact_sheet(scene, aset, out: Path, *, num_frames: int = 4, queries=None) -> Path:
    """PNG grid, one row per evaluated frame: the image, then the GT masks overlaid - one column per
    part level (whole / part / subpart queries) or, with ``queries``, one column with those."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    from benchmark.core.atomic import atomic_path

    if num_frames < 1:
        raise InputError(None, "--frames", f"must be at least 1, got {num_frames}")
    if queries is None:
        levels = [lv for lv in ("whole", "part", "subpart") if any(q.level == lv for q in aset.agnostic_queries)]
        others = [q for q in aset.agnostic_queries if q.level not in levels]
        columns = [(lv, [q for q in aset.agnostic_queries if q.level == lv]) for lv in levels]
        if others or not columns:
            columns.append(("queries", others))
    else:
        chosen = []
        for text in queries:
            try:
                chosen.append(aset.mask_owner(aset.query(text)))
            except KeyError:
                raise InputError(None, "--queries", f"no query {text!r} (queries: "
                                                    f"{', '.join(q.text for q in aset.queries)})") from None
        columns = [("queries", chosen)]
    frames = sorted(aset.frames, key=lambda f: (f.time_index, f.camera_id))
    if not frames:
        raise InputError(None, "annotations", "no evaluated frames")
    pick = [frames[int(round(k))] for k in np.linspace(0, len(frames) - 1, min(num_frames, len(frames)))]
    cmap = plt.get_cmap("tab10")
    ncol = 1 + len(columns)
    fig, axes = plt.subplots(len(pick) + 1, ncol, figsize=(2.4 * ncol, 3.0 * len(pick) + 1.4), squeeze=False,
                             gridspec_kw={"height_ratios": [1.0] * len(pick) + [0.45]})
    for row, af in enumerate(pick):
        image = scene.frame(af.name).image()
        holds = [q.text for q in aset.sensitive_queries if q.holds_at(af.time_index)]
        axes[row, 0].imshow(image)
        axes[row, 0].set_title(f"{af.name} (t={af.time_index})" + ("\n" + ", ".join(holds) if holds else ""),
                               fontsize=7)
        for col, (label, qs) in enumerate(columns, start=1):
            overlay = image.copy()
            for k, q in enumerate(qs):
                mask = aset.get_mask(q.id, af.id)
                if mask is not None and mask.any():
                    overlay[mask] = 0.35 * overlay[mask] + 0.65 * np.asarray(cmap(k % 10)[:3])
            axes[row, col].imshow(overlay)
            if row == 0:
                axes[row, col].set_title(label, fontsize=8)
    for ax in axes.ravel():
        ax.axis("off")
    for col, (label, qs) in enumerate(columns, start=1):
        handles = [Patch(color=cmap(k % 10)[:3], label=q.text) for k, q in enumerate(qs)]
        axes[-1, col].legend(handles=handles, loc="upper center", fontsize=6, frameon=False, ncol=1)
    fig.suptitle(f"{aset.scene}: ground truth on evaluated frames", fontsize=9)
    fig.tight_layout()
    out = Path(out)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return out


# -- timing ------------------------------------------------------------------------------------------------
def _timing(args: argparse.Namespace) -> int:
    from ..studies.generation_timing import measure_generation, write_report

    presets = None if args.presets is None else [p.strip() for p in args.presets.split(",") if p.strip()]
    rows = measure_generation(presets, size=args.size, log=lambda m: print(m, file=sys.stderr))
    write_report(rows, args.out)
    print(f"wrote {args.out}")
    return 0


# -- digests: which scene each preset is --------------------------------------------------------------
def _digests(args: argparse.Namespace) -> int:
    import tempfile

    from benchmark.core.atomic import write_json
    from ..synthetic import PRESETS, generate
    from ..synthetic.digest import DIGESTS_FILE, digest_key, load_digests, scene_digest

    names = args.presets.split(",") if args.presets else list(PRESETS)
    unknown = [n for n in names if n not in PRESETS]
    if unknown:
        raise InputError(None, "--presets", f"unknown preset(s) {unknown}; presets: {', '.join(PRESETS)}")
    committed = load_digests()
    changed = 0
    with tempfile.TemporaryDirectory(prefix="bench4d-digests-") as tmp:
        for name in names:
            for size in args.sizes:
                folder = generate(name, Path(tmp) / f"{name}-{size}", size=size, seed=args.seed)
                digest = scene_digest(folder)
                key = digest_key(size, args.seed)
                before = committed.get(name, {}).get(key)
                status = "same" if before == digest else ("new" if before is None else f"CHANGED (was {before})")
                changed += before != digest
                print(f"{name:14s} {key:14s} {digest}  {status}")
                committed.setdefault(name, {})[key] = digest
    if args.write:
        write_json(DIGESTS_FILE, {"format": "bench4d-scene-digests", "version": 1,
                                  "note": "content digests of the presets the committed generator makes "
                                          "(benchmark/synthetic/digest.py); refresh with `bench4d data digests "
                                          "--write` after a deliberate generator change",
                                  "presets": {k: dict(sorted(v.items())) for k, v in sorted(committed.items())}})
        print(f"wrote {DIGESTS_FILE}")
        return 0
    return 1 if changed else 0
