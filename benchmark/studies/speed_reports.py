"""Speed reports on random Gaussians at a chosen scale: ``bench4d ablate speed`` and ``bench4d ablate query-speed``.

``status_speed_report``: seconds per status-field training step (the release reports 7-8 s per iteration on
an 80 GB GPU at 360k Gaussians), optionally with the recorded blending operator used on CPU.
``query_speed_report``: frames per second of the time-agnostic query (deform, render every level, decode,
relevance, smoothing, threshold, majority filter, mask to the host) through the method's own query code
(the paper reports 5.24 FPS on an A100 at 960x536).

Each writes ``<kind>-<gaussians>-<W>x<H>-<device><suffix>.{json,md}`` with its settings and where and with
what the timing was taken (device and GPU name, package versions, git commit).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

from benchmark.core.errors import InputError
from benchmark.runner import device_description, git_state, package_versions
from methods.specs._language import LanguageMethodConfig

from ._report import Report, markdown_table, write_report
from .query_speed import measure_query_speed
from .status_speed import measure_status_speed


def status_speed_report(gaussians: int, width: int, height: int, *, device: str = "cpu", num_states: int = 3,
                        dynamic_fraction: float = 1.0, iterations: int = 20, operator: bool = False,
                        out: Path, quiet: bool = False) -> Report:
    """Time the status-field training step on ``gaussians`` random Gaussians (``dynamic_fraction`` of them
    carrying ``num_states`` states) at ``width`` x ``height`` and write ``speed-...`` to ``out``."""
    _check_sizes(gaussians=gaussians, width=width, height=height, k=num_states, iterations=iterations)
    if not 0.0 <= dynamic_fraction <= 1.0:
        raise InputError(None, "--dynamic-fraction", f"must be in [0, 1], got {dynamic_fraction}")
    result = measure_status_speed(gaussians, width, height, num_states=num_states,
                                  dynamic_fraction=dynamic_fraction, iterations=iterations,
                                  device=device, operator=operator)
    rows = [[k, f"{v:.4f}" if isinstance(v, float) else str(v)] for k, v in result.items()]
    md = ("Status-field training step on random Gaussians (release reference: 7-8 s per iteration on an "
          "80 GB GPU)\n\n" + markdown_table(["quantity", "value"], rows))
    settings = {"command": "ablate", "ablation": "speed", "gaussians": gaussians, "width": width, "height": height,
                "device": device, "out": str(out), "quiet": quiet, "k": num_states,
                "dynamic_fraction": dynamic_fraction, "iterations": iterations, "operator": operator}
    suffix = "" if dynamic_fraction == 1.0 else f"-dynamic{dynamic_fraction:g}"
    return _timing_report("speed", suffix, settings, result, md, out)


def query_speed_report(gaussians: int, width: int, height: int, *, device: str = "cpu", frames: int = 10,
                       queries: int = 1, feature_dim: int = 512, decode_chunk: Optional[int] = None,
                       decode_tf32: bool = True, decode_table: Optional[int] = None, out: Path,
                       quiet: bool = False) -> Report:
    """Time the time-agnostic query on ``gaussians`` random Gaussians at ``width`` x ``height`` over
    ``frames`` frames (and ``queries`` queries sharing one render + decode per frame, when > 1), decoding
    ``decode_chunk`` pixels per batch (default: the method config's ``answer.decode_chunk``), and write
    ``query-speed-...`` to ``out``."""
    _check_sizes(gaussians=gaussians, width=width, height=height, frames=frames, queries=queries,
                 feature_dim=feature_dim, decode_chunk=decode_chunk)
    config = LanguageMethodConfig()
    if decode_chunk is not None:
        config.answer.decode_chunk = config.answer.decode_chunk_cuda = decode_chunk
    config.answer.decode_tf32 = decode_tf32
    if decode_table is not None:
        config.answer.decode_table = config.answer.decode_table_cuda = decode_table
    result = measure_query_speed(gaussians, width, height, frames=frames, queries=queries,
                                 feature_dim=feature_dim, device=device, config=config)
    result["decode_chunk"] = config.answer.decode_chunk_for(device)
    result["decode_tf32"] = bool(decode_tf32 and str(device).startswith("cuda"))
    result["decode_table"] = config.answer.decode_table_for(device)
    flat = {k: v for k, v in result.items() if k != "stage_seconds_per_frame"}
    flat.update({f"stage {k} (s/frame)": v for k, v in result["stage_seconds_per_frame"].items()})
    rows = [[k, f"{v:.4f}" if isinstance(v, float) else str(v)] for k, v in flat.items()]
    md = ("Time-agnostic query on random Gaussians: deform, render, decode, relevance, mask (paper: 5.24 FPS on "
          "an A100 at 960x536)\n\n" + markdown_table(["quantity", "value"], rows))
    settings = {"command": "ablate", "ablation": "query-speed", "gaussians": gaussians, "width": width,
                "height": height, "device": device, "out": str(out), "quiet": quiet, "frames": frames,
                "queries": queries, "feature_dim": feature_dim, "decode_chunk": decode_chunk,
                "decode_tf32": decode_tf32, "decode_table": decode_table}
    table = config.answer.decode_table_for(device)  # the file says which decode ran, default or chosen
    suffix = (("" if decode_chunk is None else f"-chunk{decode_chunk}") + ("" if decode_tf32 else "-fp32")
              + (f"-table{table}" if table else ""))
    return _timing_report("query-speed", suffix, settings, result, md, out)


def _check_sizes(**sizes: Optional[int]) -> None:
    """Every size given (``None``: left to a default) is at least 1; the error names its option."""
    for name, value in sizes.items():
        if value is not None and value < 1:
            raise InputError(None, f"--{name.replace('_', '-')}", f"must be at least 1, got {value}")


def _timing_report(kind: str, suffix: str, settings: dict, result: dict, md: str, out: Path) -> Report:
    device = settings["device"]
    stem = f"{kind}-{settings['gaussians']}-{settings['width']}x{settings['height']}-{device.replace(':', '')}{suffix}"
    doc = {"ablation": kind, "settings": settings, **result, "environment": device_description(device),
           "packages": package_versions(), "git": git_state()}
    return Report(md, write_report(out, stem, doc, md))
