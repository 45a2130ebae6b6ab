"""Scene folders under damaged and hostile JSON: every loader gives a scene or a one-line InputError
naming the file, never another exception. Mutations: a value anywhere in a JSON tree replaced by one
of another type or an absurd size, a key deleted, the file truncated or replaced by bytes that are not
JSON."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from benchmark.core.errors import InputError
from benchmark.loaders import load_scene
from tests.test_loaders import write_dnerf, write_hypernerf

ODD_VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(-10**30, 10**30), st.floats(allow_nan=True, allow_infinity=True, allow_subnormal=False),
    st.text(max_size=8), st.lists(st.integers(-3, 3), max_size=4), st.dictionaries(st.text(max_size=3),
                                                                                    st.integers(), max_size=2),
    st.just([[[[[[[]]]]]]]), st.just(10**400), st.just(-1), st.just(0), st.just(1e308))
"""Values a field may be replaced with: wrong types, absurd magnitudes, non-finite numbers, nesting."""


def _paths(doc, prefix=()):
    """Every path (tuple of keys / indices) inside a JSON tree, the root excluded."""
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    for key, value in items:
        yield prefix + (key,)
        yield from _paths(value, prefix + (key,))


def _mutate(path: Path, data) -> None:
    """Apply one mutation drawn by hypothesis' ``data`` to the JSON file ``path``."""
    text = path.read_text()
    kind = data.draw(st.sampled_from(["replace", "delete", "truncate", "garbage"]), label="kind")
    if kind == "truncate":
        path.write_text(text[: data.draw(st.integers(0, max(0, len(text) - 1)), label="keep")])
        return
    if kind == "garbage":
        path.write_bytes(data.draw(st.binary(max_size=40), label="bytes"))
        return
    doc = json.loads(text)
    paths = list(_paths(doc))
    if not paths:
        path.write_text(json.dumps(data.draw(ODD_VALUES)))
        return
    where = data.draw(st.sampled_from(paths), label="where")
    parent = doc
    for key in where[:-1]:
        parent = parent[key]
    if kind == "delete":
        del parent[where[-1]]
    else:
        parent[where[-1]] = data.draw(ODD_VALUES, label="value")
    path.write_text(json.dumps(doc))


def _load_all(root: Path) -> None:
    """What a run reads of a scene before fitting: the scene, and each frame's camera and image."""
    scene = load_scene(root)
    for frame in scene.frames[:3]:
        frame.image()


FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    base = tmp_path_factory.mktemp("pristine")
    write_hypernerf(base / "hypernerf", n=6)
    write_dnerf(base / "dnerf")
    for layout in ("hypernerf", "dnerf"):
        _load_all(base / layout)  # the unmutated folders load
    return base


@pytest.mark.parametrize("layout", ["hypernerf", "dnerf"])
@FUZZ
@given(data=st.data())
def test_a_damaged_scene_folder_loads_or_fails_in_one_line(pristine, tmp_path_factory, layout, data):
    root = tmp_path_factory.mktemp("mutated") / layout
    shutil.copytree(pristine / layout, root)
    files = sorted(p.relative_to(root).as_posix() for p in root.rglob("*.json"))
    target = data.draw(st.sampled_from(files), label="file")
    _mutate(root / target, data)
    try:
        _load_all(root)
    except InputError as err:
        message = str(err)
        assert "\n" not in message.strip() and message.strip(), message


def test_a_camera_far_beyond_float_range_fails_in_one_line_without_numpy_warnings():
    import warnings

    import numpy as np

    from benchmark.loaders import _common
    from benchmark.loaders.hypernerf import NerfiesCamera, to_opencv

    half = np.sqrt(0.5)
    turn = np.array([[half, -half, 0.0], [half, half, 0.0], [0.0, 0.0, 1.0]])
    far = NerfiesCamera(turn, np.array([1.5e308, 1.5e308, 0.0]), 100.0, np.array([8.0, 8.0]), 0.0, 1.0,
                        np.zeros(3), np.zeros(2), 16, 16)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an overflow inside numpy is a warning: it must not happen
        with pytest.raises(InputError, match="position: camera position .* is not finite"):
            to_opencv(far, np.zeros(3), 1.0, path=Path("camera/000.json"))
        with pytest.raises(InputError, match="orientation: not a rotation matrix"):
            _common.check_rotation(turn * 1e200, Path("camera/000.json"), "orientation")
