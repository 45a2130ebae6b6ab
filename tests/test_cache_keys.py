"""Cache keys from the code itself: :func:`benchmark.core.cache_keys.code_digest` follows a module's
imports (function-local ones included), and every stage's key moves when the code it runs is edited."""

from __future__ import annotations

import importlib.util
import textwrap
import uuid
from pathlib import Path
from types import SimpleNamespace

import pytest

from benchmark.core import cache_keys
from benchmark.core.cache_keys import code_digest, code_modules


# -- code_digest / code_modules on a package of their own ---------------------------------------------
@pytest.fixture
def package(tmp_path, monkeypatch):
    """A throwaway package (a fresh name each time) whose modules the digest follows as project code."""
    name = f"digest_pkg_{uuid.uuid4().hex[:8]}"
    root = tmp_path / name
    root.mkdir()
    files = {
        "__init__.py": "",
        "a.py": """
            import json
            from . import b

            def later():
                from .c import g  # function-local: still code that a.py runs
                return g()
            """,
        "b.py": "VALUE = 1\n",
        "c.py": f"""
            from {name}.d import x

            def g():
                return x
            """,
        "d.py": "x = 2\n",
        "e.py": "UNUSED = 3\n",
    }
    for file, text in files.items():
        (root / file).write_text(textwrap.dedent(text))
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(cache_keys, "PROJECT_PACKAGES", (*cache_keys.PROJECT_PACKAGES, name))
    yield SimpleNamespace(name=name, root=root)
    # the digest reads each file once per process: forget this package's files
    cache_keys._closure.cache_clear()
    cache_keys._file_digest.cache_clear()


def test_code_modules_follow_the_import_chain_function_local_imports_included(package):
    p = package.name
    assert code_modules(f"{p}.a") == sorted([p, f"{p}.a", f"{p}.b", f"{p}.c", f"{p}.d"])
    assert code_modules(f"{p}.e") == [p, f"{p}.e"]


def test_code_digest_moves_with_the_source_of_any_module_reached(package):
    p = package.name
    before = code_digest(f"{p}.a")
    assert code_digest(f"{p}.a") == before and code_digest(f"{p}.a") != code_digest(f"{p}.e")
    (package.root / "e.py").write_text("UNUSED = 4\n")  # not reached from a
    cache_keys._file_digest.cache_clear()
    assert code_digest(f"{p}.a") == before
    (package.root / "d.py").write_text("x = 5\n")  # reached through a function-local import of c
    cache_keys._file_digest.cache_clear()
    assert code_digest(f"{p}.a") != before


def test_a_missing_module_is_an_error(package):
    with pytest.raises(ValueError, match="no module"):
        code_digest(f"{package.name}.missing")
    with pytest.raises(ValueError, match="no module"):
        code_digest("methods.no_such_module")


# -- every stage's key names the code it runs -----------------------------------------------------------
def _edited(monkeypatch, module: str) -> None:
    """Make code digests see ``module``'s source as edited."""
    path = str(Path(importlib.util.find_spec(module).origin))
    original = cache_keys._file_digest
    monkeypatch.setattr(cache_keys, "_file_digest", lambda p: "edited" if p == path else original(p))


def _geometry_key():
    import numpy as np

    from benchmark.core.scene import Camera, Frame, Scene
    from methods.language_methods import geometry_key
    from methods.specs._language import LanguageMethodConfig

    camera = Camera(width=8, height=6, fx=8.0, fy=8.0, cx=4.0, cy=3.0, world_to_camera=np.eye(4))
    scene = Scene(name="keys", dataset="test", bounds=np.array([[-1.0] * 3, [1.0] * 3]),
                  frames=[Frame(name="f0", camera=camera, time=0.0, time_index=0, split="train")])
    return geometry_key(scene, "4dgs", LanguageMethodConfig(), 0, "cpu")


def _field_key():
    from methods.language_methods import autoencoder_config, field_config, field_key
    from methods.specs._language import LanguageMethodConfig

    config = LanguageMethodConfig()
    return field_key("geometry", SimpleNamespace(fingerprint="supervision"), config, autoencoder_config(config),
                     field_config(config), seed=0, device="cpu")


def _feature_key():
    from methods.feature_3dgs import feature_cache_key
    from methods.specs.feature_3dgs import Feature3DGSConfig

    return feature_cache_key("geometry", SimpleNamespace(fingerprint="supervision"), Feature3DGSConfig(), 0, "cpu")


def _identity_key():
    from methods.gaussian_grouping import identity_key
    from methods.specs.gaussian_grouping import GaussianGroupingConfig

    return identity_key(SimpleNamespace(key="geometry"), SimpleNamespace(fingerprint="supervision", track="real"),
                        GaussianGroupingConfig(), 0, "cpu")


def _method_digest(name: str):
    def digest():
        from methods import registry

        return registry.get(name).code_digest()

    return digest


STAGES = {
    "geometry": (_geometry_key, ["methods.gaussians.train", "methods.gaussians.rasterize", "methods.gaussians.hexplane",
                                 "methods.gaussians.model"]),
    "field": (_field_key, ["methods.language_methods", "methods.fields.language_field", "methods.fields.autoencoder"]),
    "feature": (_feature_key, ["methods.feature_3dgs", "methods.fields.language_field", "methods.language_methods"]),
    "identity": (_identity_key, ["methods.gaussian_grouping", "methods.supervision.association",
                                 "methods.fields.language_field", "methods.language_methods"]),
    # the runner's whole-fit key: the head's targets, states and network, and the captioners it loads by name
    "4d-langsplat": (_method_digest("4d-langsplat"),
                     ["methods.four_d_langsplat", "methods.time_sensitive", "methods.fields.time_varying",
                      "methods.fields.status", "methods.fields.caption_targets", "methods.captioners.template",
                      "methods.captioners.qwen2vl", "methods.captioners.file", "methods.gaussians.hexplane",
                      "methods.gaussians.rasterize", "methods.gaussians.train", "methods.fields.relevance"]),
    "non-status-field": (_method_digest("non-status-field"),
                         ["methods.fields.status", "methods.fields.caption_targets", "methods.captioners.template"]),
    "deformable-clip": (_method_digest("deformable-clip"),
                        ["methods.gaussians.hexplane", "methods.gaussians.rasterize", "methods.fields.relevance"]),
    "nearest-frame": (_method_digest("nearest-frame"), ["methods.nearest_frame", "methods.api"]),
}


@pytest.mark.parametrize("stage, module", [(stage, module) for stage, (_, modules) in STAGES.items()
                                           for module in modules])
def test_a_stage_key_moves_when_the_code_it_runs_is_edited(stage, module, monkeypatch):
    key = STAGES[stage][0]
    before = key()
    assert key() == before
    _edited(monkeypatch, module)
    assert key() != before, f"editing {module} leaves the {stage} key as it was"


@pytest.mark.parametrize("stage, module", [("geometry", "methods.fields.status"),
                                           ("geometry", "methods.language_methods"),
                                           ("nearest-frame", "methods.gaussians.train")])
def test_a_stage_key_ignores_code_it_does_not_run(stage, module, monkeypatch):
    key = STAGES[stage][0]
    before = key()
    _edited(monkeypatch, module)
    assert key() == before
