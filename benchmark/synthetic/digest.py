"""Which version of a generated scene a result was measured on.

A synthetic preset is regenerated from code wherever it is missing (``cache/scenes/...``), so two
runs named "americano" are comparable only if the generator produced the same scene for both. A
cached scene is reused as long as its folder exists, so a scene made by older generator code would
otherwise keep feeding runs long after the code changed, and a fresh clone would silently measure
something else (it happened: results measured on scenes from uncommitted generator code).

* :func:`scene_digest`: a content hash of a generated scene folder: camera and scene JSON (floats
  rounded to :data:`FLOAT_DIGITS` significant digits, so last-bit differences of trigonometry between
  CPUs do not count), decoded RGB pixels, truth id maps and depth, and the annotations (the folder's
  own name left out). Equal digests = the same scene, pixel for pixel.
* :data:`DIGESTS_FILE` (``digests.json`` beside this module, committed): the digest the committed
  generator produces for each preset at its default size and seed. ``bench4d data digests --write``
  refreshes it after a deliberate change to the generator; a test regenerates presets and compares,
  so an unintended change cannot land unnoticed.
* :func:`expected_digest`: the committed digest of (preset, size, seed), or None if not recorded.

The runner reuses a cached preset only when its digest is the committed one (else it regenerates),
records the digest in every results file, and the leaderboard leaves out runs whose digest is not the
committed one (``benchmark.results``).
"""

from __future__ import annotations

import functools
import hashlib
import json
from pathlib import Path
from typing import Any, Optional

import numpy as np

from benchmark.core.atomic import read_json
from benchmark.core.errors import InputError

DIGESTS_FILE = Path(__file__).with_name("digests.json")
"""Committed digests: ``{"format": ..., "presets": {preset: {"<size>px-seed<seed>": digest}}}``."""
FLOAT_DIGITS = 12
"""Significant digits floats are rounded to before hashing (CPU-dependent last bits of sin/cos in the
camera path differ by ~1e-16 relative; the scenes' pixels do not)."""
META_FILE = "bench4d_meta.json"
"""The generator's description of a scene folder (preset, seed, size, ...)."""
_IGNORED_KEYS = {"annotations.json": ("scene",)}
"""Per file: top-level JSON keys that name the folder rather than describe the scene."""


def _rounded(obj: Any) -> Any:
    if isinstance(obj, float):
        return float(f"{obj:.{FLOAT_DIGITS}g}") if np.isfinite(obj) else str(obj)
    if isinstance(obj, dict):
        return {str(k): _rounded(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_rounded(v) for v in obj]
    return obj


def _array_bytes(digest, array: np.ndarray) -> None:
    array = np.ascontiguousarray(array)
    digest.update(f"{array.dtype.str}{array.shape}".encode())
    digest.update(array.tobytes())


def _hash_file(digest, root: Path, path: Path) -> None:
    rel = path.relative_to(root).as_posix()
    digest.update(rel.encode() + b"\0")
    suffix = path.suffix.lower()
    if suffix == ".json":
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise InputError(path, "json", f"cannot read a scene file for its digest ({err})") from None
        if isinstance(doc, dict):
            doc = {k: v for k, v in doc.items() if k not in _IGNORED_KEYS.get(rel, ())}
        digest.update(json.dumps(_rounded(doc), sort_keys=True, separators=(",", ":")).encode())
    elif suffix in (".png", ".jpg", ".jpeg"):
        from benchmark.core.imageio import read_image_pixels

        # checked before decoding (size, a complete stream): a damaged or hostile file is one line naming it
        _array_bytes(digest, read_image_pixels(path))  # pixels, not the encoder's bytes (PNG settings may differ)
    elif suffix == ".npz":
        from benchmark.core.strict import load_npz

        arrays = load_npz(path)  # no header's claim is allocated before it is checked against the bytes present
        for key in sorted(arrays):
            digest.update(key.encode() + b"\0")
            _array_bytes(digest, arrays[key])
    else:
        digest.update(path.read_bytes())


def scene_digest(root: str | Path) -> str:
    """Content hash (hex, 24 chars) of a generated scene folder (module docstring); the generator's
    own ``bench4d_meta.json`` is left out (it describes, the files are)."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "scene", "no such scene folder")
    digest = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        rel = path.relative_to(root).as_posix()
        if rel == META_FILE or any(part.startswith(".") for part in path.relative_to(root).parts):
            continue
        _hash_file(digest, root, path)
    return digest.hexdigest()[:24]


GENERATOR_SOURCES = ("benchmark/synthetic", "benchmark/core", "annotations")
"""Packages whose code can change what the generator writes (relative to the repository root)."""


@functools.lru_cache(maxsize=1)
def generator_code() -> str:
    """Hash (hex, 16 chars) of the Python sources of :data:`GENERATOR_SOURCES` as they are now. A scene
    stamped with another value may be one older code made: regenerate it and compare digests."""
    root = Path(__file__).resolve().parents[2]
    digest = hashlib.sha256()
    for package in GENERATOR_SOURCES:
        for path in sorted((root / package).rglob("*.py")):
            digest.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:16]


def digest_key(size: int, seed: int) -> str:
    return f"{int(size)}px-seed{int(seed)}"


def load_digests(path: Optional[Path] = None) -> dict[str, dict[str, str]]:
    """``{preset: {"<size>px-seed<seed>": digest}}`` from ``path`` (default :data:`DIGESTS_FILE`;
    empty when the file does not exist)."""
    path = DIGESTS_FILE if path is None else Path(path)
    if not path.is_file():
        return {}
    # a copy: callers (``bench4d data digests``) add to it, the cached parse stays as read
    return {preset: dict(sizes) for preset, sizes in _read_digests(str(path), path.stat().st_mtime_ns).items()}


@functools.lru_cache(maxsize=4)
def _read_digests(path: str, mtime_ns: int) -> dict[str, dict[str, str]]:
    """Parsed digests file, read once per (path, modification time): the leaderboard asks per run."""
    doc = read_json(path)
    presets = doc.get("presets") if isinstance(doc, dict) else None
    if not isinstance(presets, dict):
        raise InputError(path, "presets", "expected an object {preset: {'<size>px-seed<seed>': digest}}")
    return presets


def expected_digest(preset: str, size: int, seed: int = 0, *, path: Optional[Path] = None) -> Optional[str]:
    """The committed digest of ``preset`` at ``size`` px and ``seed``, or None if not recorded."""
    return load_digests(path).get(preset, {}).get(digest_key(size, seed))


def scene_version(root: str | Path) -> Optional[dict[str, Any]]:
    """What the results record about a generated scene: preset, size, seed, digest and whether the
    digest is the committed one; None for a folder the generator did not make."""
    root = Path(root)
    meta_path = root / META_FILE
    if not meta_path.is_file():
        return None
    meta = read_json(meta_path)
    preset, size, seed = meta.get("preset"), meta.get("size"), meta.get("seed", 0)
    digest = scene_digest(root)
    expected = expected_digest(preset, size, seed) if preset and size else None
    return {"preset": preset, "size": size, "seed": seed, "generator_version": meta.get("generator_version"),
            "digest": digest, "committed_digest": expected, "perturbation": meta.get("perturbation"),
            "current": None if expected is None else digest == expected}
