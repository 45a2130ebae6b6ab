"""Dataset loaders: every supported layout becomes one :class:`benchmark.core.scene.Scene`.

>>> scene = load_scene("data/hypernerf/split-cookie")          # layout auto-detected
>>> scene = load_scene("data/dnerf/lego", scale=0.5)            # 400 -> 200 px

Layouts (detected from marker files, in this order):

* ``"hypernerf"`` (:mod:`.hypernerf`): ``dataset.json`` + ``scene.json``.
* ``"neu3d"`` (:mod:`.neu3d`): ``poses_bounds.npy``.
* ``"dnerf"`` (:mod:`.dnerf`): ``transforms_train.json``.

Common keywords: ``scale`` is a **resolution multiplier** (0.5 = half the pixels per side) relative
to the layout's reference images (HyperNeRF: 1x, default its 2x folder; Neu3D: the frames on disk;
D-NeRF: the PNGs); ``split_rule`` picks how frames are split (per-layout values, see each module).
Other keywords are the fields of the layout's options dataclass (:class:`HyperNeRFOptions`,
:class:`Neu3DOptions`, :class:`DNeRFOptions`); an unknown one is an :class:`InputError`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

from benchmark.core.errors import InputError
from benchmark.core.scene import Scene
from . import dnerf, hypernerf, neu3d
from ._common import make_options
from .dnerf import DNeRFOptions
from .hypernerf import HyperNeRFOptions
from .neu3d import Neu3DOptions

# layout name -> (module with detect/load, options dataclass); detection order matters
LAYOUTS: dict[str, tuple[Any, type]] = {
    "hypernerf": (hypernerf, HyperNeRFOptions),
    "neu3d": (neu3d, Neu3DOptions),
    "dnerf": (dnerf, DNeRFOptions),
}

__all__ = ["LAYOUTS", "detect_layout", "load_scene", "HyperNeRFOptions", "Neu3DOptions", "DNeRFOptions"]


def _scene_root(path: str | Path) -> Path:
    root = Path(path)
    if root.is_file():  # e.g. the path of transforms_train.json or poses_bounds.npy
        root = root.parent
    if not root.is_dir():
        raise InputError(root, None, "scene folder not found")
    return root


def detect_layout(path: str | Path) -> str:
    """The layout name of the scene folder ``path`` (see the module docstring)."""
    root = _scene_root(path)
    for name, (module, _) in LAYOUTS.items():
        if module.detect(root):
            return name
    from benchmark.core.strict import file_problem

    for marker in ("dataset.json", "scene.json", "poses_bounds.npy", "transforms_train.json"):
        problem = file_problem(root / marker)  # a layout's file there, but not a regular file: say so
        if problem not in (None, "missing"):
            raise InputError(root / marker, None, f"is {problem}, expected the scene's {marker}")
    raise InputError(root, "layout", "unrecognised scene folder: expected dataset.json + scene.json "
                                     "(hypernerf), poses_bounds.npy (neu3d) or transforms_train.json (dnerf)")


def load_scene(path: str | Path, *, scale: Optional[float | str] = None, split_rule: Optional[str] = None,
               layout: Optional[str] = None, **opts: Any) -> Scene:
    """Load the scene folder ``path`` as a :class:`Scene` (images stay on disk until accessed).

    ``layout`` forces a layout instead of detecting it; other keywords go to the layout's options.
    """
    root = _scene_root(path)
    name = layout or detect_layout(root)
    if name not in LAYOUTS:
        raise InputError(None, "layout", f"unknown layout {name!r} (valid: {', '.join(LAYOUTS)})")
    module, options_cls = LAYOUTS[name]
    options = make_options(options_cls, name, {"scale": scale, "split_rule": split_rule, **opts})
    return module.load(root, options)
