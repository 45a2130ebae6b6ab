"""Atomic writes: temp file in the same folder, flush + fsync, then ``os.replace``.

A reader never sees a partial file, and an interrupted run leaves the previous file intact.

A JSON file whose name ends in ``.gz`` is gzip-compressed: :func:`write_json` compresses it (with a
zero timestamp, so equal content gives equal bytes) and :func:`read_json` decompresses it.
"""

from __future__ import annotations

import contextlib
import gzip
import json
import math
import os
import tempfile
import zlib
from pathlib import Path
from typing import Any, Iterator

_UMASK = os.umask(0)
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path`` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        with open(tmp_path, "rb+") as fh:
            fh.flush()
            os.fsync(fh.fileno())
        # mkstemp creates 0600; give the file the mode a plain open() would have.
        os.chmod(tmp_path, 0o666 & ~_UMASK)
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (:func:`atomic_path`). A failed write (a full disk, a file size
    limit) raises its ``OSError`` naming ``path``: a write on an open file names none."""
    try:
        with atomic_path(path) as tmp:
            tmp.write_bytes(data)
    except OSError as err:
        if err.filename is None and err.errno is not None:
            raise OSError(err.errno, err.strerror or str(err), str(path)) from None
        raise


def write_text(path: str | Path, text: str) -> None:
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | Path, obj: Any, indent: int | None = 2) -> None:
    """Write ``obj`` as standard JSON: NaN and infinities become ``null`` (:func:`json_ready`); gzip-compressed
    where the name ends in ``.gz``."""
    data = (dumps_json(obj, indent=indent) + "\n").encode("utf-8")
    write_bytes(path, gzip.compress(data, mtime=0) if is_gzip_name(path) else data)


def is_gzip_name(path: str | Path) -> bool:
    """Whether ``path`` names a gzip-compressed file (its name ends in ``.gz``)."""
    return Path(path).name.endswith(".gz")


def dumps_json(obj: Any, indent: int | None = None, **kwargs: Any) -> str:
    """``json.dumps`` that only ever writes standard JSON (no ``NaN`` / ``Infinity`` tokens)."""
    return json.dumps(json_ready(obj), indent=indent, sort_keys=False, allow_nan=False, **kwargs)


def json_ready(obj: Any) -> Any:
    """JSON-ready copy: non-finite floats -> ``None`` (``null``: "undefined", as the results schema
    reads it), numpy scalars and arrays (and anything else with ``tolist``, e.g. torch tensors) -> Python,
    tuples -> lists, paths -> str, mapping keys -> str. Other objects are passed through (``json.dumps``
    rejects what it cannot write)."""
    import numpy as np

    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray) or (hasattr(obj, "tolist") and not isinstance(obj, np.generic)):
        return json_ready(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


MAX_JSON_DEPTH = 100
MAX_GZIP_JSON_BYTES = 1 << 30
"""Largest decompressed size of a ``.gz`` JSON file :func:`read_json` accepts (a few bytes of gzip can
expand to gigabytes)."""
"""Deepest nesting of arrays and objects :func:`read_json` accepts. No bench4d file nests more
than about ten levels; the bound keeps every recursive consumer of a parsed document (writers,
sanitisers) far from Python's recursion limit."""


def json_depth_exceeds(doc: Any, limit: int = MAX_JSON_DEPTH) -> bool:
    """Whether ``doc`` nests arrays/objects deeper than ``limit`` (iterative: no recursion)."""
    stack = [(doc, 1)]
    while stack:
        node, depth = stack.pop()
        if depth > limit:
            return True
        if isinstance(node, dict):
            stack.extend((v, depth + 1) for v in node.values() if isinstance(v, (dict, list)))
        elif isinstance(node, list):
            stack.extend((v, depth + 1) for v in node if isinstance(v, (dict, list)))
    return False


def _read_gzip(path: Path) -> bytearray:
    """The decompressed bytes of the gzip file ``path``, at most :data:`MAX_GZIP_JSON_BYTES` of them, read in
    chunks (one read of the whole limit would reserve a gigabyte up front)."""
    from .errors import InputError
    from .strict import open_regular

    out = bytearray()
    try:
        with open_regular(path) as raw, gzip.GzipFile(fileobj=raw, mode="rb") as fh:
            while len(out) <= MAX_GZIP_JSON_BYTES:
                chunk = fh.read(min(1 << 24, MAX_GZIP_JSON_BYTES + 1 - len(out)))
                if not chunk:
                    break
                out += chunk
    except (gzip.BadGzipFile, EOFError, zlib.error) as err:
        raise InputError(path, None, f"not valid gzip data: {err or 'truncated'}") from None
    if len(out) > MAX_GZIP_JSON_BYTES:
        raise InputError(path, None, f"decompresses to more than {MAX_GZIP_JSON_BYTES} bytes")
    return out


def read_json(path: str | Path) -> Any:
    """Read JSON strictly (:func:`benchmark.core.strict.loads`), turning every way a file can be missing or
    malformed into an :class:`InputError` naming the file: not found, a folder or a FIFO (refused before it
    is opened: a read would block), unreadable, not UTF-8, invalid JSON, a key given twice in one object,
    numbers Python refuses to convert, nesting deeper than :data:`MAX_JSON_DEPTH`, or far more lists and
    objects than its size can need."""
    from .errors import InputError
    from .strict import file_problem, loads, open_regular

    path = Path(path)
    problem = file_problem(path)
    if problem == "missing":
        raise InputError(path, None, "file not found")
    if problem is not None:
        raise InputError(path, None, f"is {problem}, expected a JSON file")
    try:
        if is_gzip_name(path):
            data = _read_gzip(path)
        else:
            with open_regular(path) as fh:
                data = fh.read()
        text = data.decode("utf-8")
        del data
    except UnicodeDecodeError as err:
        raise InputError(path, f"byte {err.start}", "not UTF-8 text") from None
    except OSError as err:
        raise InputError(path, None, f"cannot read: {err.strerror or err}") from None
    return loads(text, path, max_depth=MAX_JSON_DEPTH)
