"""Cache keys, computed in one place: a stable hash of any JSON-able description, what identifies a
scene's frames, and what identifies the code of a stage.

A stage's code digest hashes the source of the modules it names *and of every project module they
import*, directly or not, function-local imports included: editing any code a fit runs changes its key,
with no hand-kept file list and no version constant to bump.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib.util
import json
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np

from .scene import Frame, Scene

PROJECT_PACKAGES = ("benchmark", "methods", "annotations")
"""Top-level packages whose modules a code digest follows."""


def jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON data (arrays and numpy scalars as lists and numbers, paths as strings, sets
    sorted); raises ``TypeError`` for anything else (a key must not depend on an object's ``repr``)."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (set, frozenset)):
        return sorted(obj)
    raise TypeError(f"cannot hash {type(obj).__name__}")


def stable_hash(obj: Any, length: int = 16) -> str:
    """Hex digest (``length`` characters) of the canonical JSON of ``obj`` (sorted keys)."""
    text = json.dumps(obj, sort_keys=True, default=jsonable)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:length]


def frame_fingerprint(frame: Frame) -> dict[str, Any]:
    """What identifies a frame's data: name, time, camera, and its image file's size and mtime."""
    entry: dict[str, Any] = {"name": frame.name, "time": round(float(frame.time), 9),
                             "time_index": frame.time_index, "camera_id": frame.camera_id,
                             "split": frame.split, "camera": frame.camera.to_dict()}
    if frame.image_path is not None:
        path = Path(frame.image_path)
        if path.is_file():
            st = path.stat()
            entry["image"] = [path.name, st.st_size, st.st_mtime_ns]
    return entry


def scene_fingerprint(scene: Scene, frames: Optional[Sequence[Frame]] = None) -> str:
    """Hash of a scene's identity and of ``frames`` (all frames by default)."""
    frames = scene.frames if frames is None else frames
    return stable_hash({"dataset": scene.dataset, "name": scene.name,
                        "frames": [frame_fingerprint(f) for f in frames]}, 24)


def _module_file(name: str) -> Optional[Path]:
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        return None
    return Path(spec.origin)


def _project_imports(name: str, path: Path) -> set[str]:
    """Project modules ``path`` (module ``name``) imports anywhere in its body."""
    is_package = path.name == "__init__.py"
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
        if isinstance(node, ast.Import):
            candidates = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[:len(base) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            # "from pkg import sub" may name a submodule: follow it when it is one
            candidates = [module] + [f"{module}.{a.name}" for a in node.names]
        else:
            continue
        out.update(c for c in candidates if c.split(".")[0] in PROJECT_PACKAGES)
    return out


@functools.lru_cache(maxsize=None)
def _closure(root: str) -> tuple[tuple[str, str], ...]:
    """(module, file) of ``root`` and every project module it reaches, sorted."""
    seen: dict[str, Path] = {}
    todo = [root]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        path = _module_file(name)
        if path is None:
            continue
        seen[name] = path
        parts = name.split(".")
        todo += [".".join(parts[:k]) for k in range(1, len(parts))]  # a module runs its packages' __init__
        todo += sorted(_project_imports(name, path) - set(seen))
    return tuple(sorted((m, str(p)) for m, p in seen.items()))


def code_modules(*modules: str) -> list[str]:
    """Every project module the code of ``modules`` reaches (themselves included), sorted."""
    return sorted({m for root in modules for m, _ in _closure(root)})


@functools.lru_cache(maxsize=None)
def _file_digest(path: str) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def code_digest(*modules: str, length: int = 16) -> str:
    """Hash of the source of ``modules`` and of every project module they import (module names, e.g.
    ``"methods.four_d_langsplat"``). Raises ``ValueError`` for a module that does not exist."""
    files: dict[str, str] = {}
    for root in modules:
        if _module_file(root) is None:
            raise ValueError(f"no module {root!r}: a code digest names importable project modules")
        files.update(_closure(root))
    return stable_hash({m: _file_digest(p) for m, p in sorted(files.items())}, length)
