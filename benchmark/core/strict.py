"""The strict input layer: the checks every external document passes before anything is built from it.

One place for the rules the readers of predictions, annotation files, COCO and release imports, scene
files, cached fits and the annotation server's request bodies share:

* **JSON** (:func:`loads`): no key twice in one object (the last one would win without a word); nesting
  bounded (:data:`benchmark.core.atomic.MAX_JSON_DEPTH`); and a budget on containers, counted in the text
  before it is parsed: an empty list or object costs about 60 bytes of Python objects for 3 bytes of
  JSON, the largest amplification a document can get (other values cost at most about 12 times their
  text).
* **Keys** are canonical or refused: a key the schema knows, written in another case, with spaces, or in
  another Unicode form (``Box`` beside ``box``, a fullwidth ``ｍasks``) is an error, not an unknown key
  silently ignored (:func:`check_keys`); an id used as a key is ASCII digits as ``str(int)`` writes them
  (:func:`canonical_int_key`: not ``"٩"``, ``" 9 "``, ``"0_9"`` or ``"+9"``, which ``int()`` all reads as 9).
* **Numbers** that count (revisions, ids, sizes) are integers in a stated range, never ``true``, a float,
  ``NaN`` or ``Infinity`` (:func:`check_int`).
* **Texts** that name things: a name used as one path component (:func:`check_name`), a query text with
  no control character (:func:`check_text`), and query texts unique up to case, spacing and Unicode form
  (:func:`text_key`).
* **Files** where a file is expected: a FIFO, socket, device or folder is refused before it is opened, so
  no read can block (:func:`file_problem`, :func:`open_regular`).
* **Arrays** read from a cache: the shape and dtype kind expected, and finite (:func:`check_array`); a
  cached model folder holds files and folders only, every floating array finite (:func:`check_cached_files`).

And one rule for output: every text from a file printed to a terminal goes through :func:`terminal_text`,
which escapes control and formatting characters (ESC, CR, bidi overrides) so that no file can clear
the screen or overwrite a row.
"""

from __future__ import annotations

import json
import os
import re
import stat
import unicodedata
from pathlib import Path
from typing import Any, Iterable, Optional

from .errors import InputError, short_repr

MAX_COUNT = 2 ** 53
"""Largest revision, id or count a document may give (exact in a float64, far beyond any real one)."""
CONTAINER_BYTES = 16
"""A document may hold one list or object per this many bytes of its text (plus
:data:`CONTAINER_ALLOWANCE`): parsed, containers then cost at most about 4 times the text."""
CONTAINER_ALLOWANCE = 65536
"""Lists and objects any document may hold, however short its text."""

_CANONICAL_INT = re.compile(r"-?(?:0|[1-9][0-9]{0,17})")


# -- JSON ---------------------------------------------------------------------------------------------------
class _DuplicateKey(ValueError):
    def __init__(self, key: str):
        super().__init__(key)
        self.key = key


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict:
    out = dict(pairs)
    if len(out) != len(pairs):
        seen: set[str] = set()
        for key, _ in pairs:
            if key in seen:
                raise _DuplicateKey(key)
            seen.add(key)
    return out


def container_budget(size: int, per: int = CONTAINER_BYTES, allowance: int = CONTAINER_ALLOWANCE) -> int:
    """Lists and objects a JSON text of ``size`` bytes may hold."""
    return allowance + size // per


def count_containers(text: str | bytes | bytearray) -> int:
    """An upper bound on the lists and objects of a JSON text (brackets inside strings count too)."""
    if isinstance(text, str):
        return text.count("[") + text.count("{")
    return text.count(b"[") + text.count(b"{")


def loads(text: str, file: str | Path | None = None, *, max_depth: Optional[int] = None,
          containers: Optional[int] = None) -> Any:
    """Strict JSON: :class:`InputError` naming ``file`` for invalid JSON, a key given twice in one object,
    nesting deeper than ``max_depth`` (default :data:`benchmark.core.atomic.MAX_JSON_DEPTH`), more than
    ``containers`` lists and objects (default :func:`container_budget` of the text's length), or numbers
    Python cannot convert. ``NaN`` and ``Infinity`` tokens are read as floats: where a number counts, the
    schema refuses them (:func:`check_int`)."""
    from .atomic import MAX_JSON_DEPTH, json_depth_exceeds

    max_depth = MAX_JSON_DEPTH if max_depth is None else max_depth
    budget = container_budget(len(text)) if containers is None else containers
    found = count_containers(text)
    if found > budget:
        raise InputError(file, None, f"invalid JSON: {found} lists and objects in {len(text)} characters; at most "
                                     f"{budget} (a document this size never needs more)")
    try:
        doc = json.loads(text, object_pairs_hook=_no_duplicates)
    except _DuplicateKey as err:
        raise InputError(file, None, f"invalid JSON: key {short_repr(err.key)} appears twice in one object "
                                     "(which one is meant?)") from None
    except json.JSONDecodeError as err:
        raise InputError(file, f"line {err.lineno} col {err.colno}", f"invalid JSON: {err.msg}") from None
    except RecursionError:
        raise InputError(file, None, f"invalid JSON: nested deeper than {max_depth} levels") from None
    except ValueError as err:  # e.g. an integer of more digits than Python converts
        raise InputError(file, None, f"invalid JSON: {str(err).splitlines()[0][:200]}") from None
    if json_depth_exceeds(doc, max_depth):
        raise InputError(file, None, f"invalid JSON: nested deeper than {max_depth} levels")
    if _SURROGATE_ESCAPE.search(text):  # only an escape can make one: the walk is for those texts alone
        where = _lone_surrogate(doc)
        if where is not None:
            raise InputError(file, where or None, "invalid JSON: a lone surrogate escape (\\uD800-\\uDFFF not in "
                                                  "a pair), a character no UTF-8 text can hold")
    return doc


_SURROGATE_ESCAPE = re.compile(r"\\u[dD][89a-fA-F]")
_SURROGATE = re.compile("[\ud800-\udfff]")


def _lone_surrogate(doc: Any) -> Optional[str]:
    """The path of the first key or string of ``doc`` holding a surrogate code point (JSON decodes a valid
    escaped pair to one character, so any left is lone); ``None`` when there is none."""
    stack: list[tuple[str, Any]] = [("", doc)]
    while stack:
        where, node = stack.pop()
        if isinstance(node, str):
            if _SURROGATE.search(node):
                return where
        elif isinstance(node, dict):
            for key, value in node.items():
                if _SURROGATE.search(key):
                    return where or "key"
                stack.append((f"{where}.{key}" if where else key, value))
        elif isinstance(node, list):
            stack.extend((f"{where}[{i}]", v) for i, v in enumerate(node))
    return None


# -- keys ---------------------------------------------------------------------------------------------------
def text_key(text: str) -> str:
    """The form two texts (or keys) are compared in for "the same": Unicode NFKC, formatting characters
    (zero-width spaces, bidi marks) dropped, runs of white space as one space, ends trimmed, case folded."""
    norm = unicodedata.normalize("NFKC", text)
    norm = "".join(ch for ch in norm if unicodedata.category(ch) != "Cf")
    return " ".join(norm.split()).casefold()


def check_keys(obj: dict, known: Iterable[str], file: str | Path | None, field: Optional[str], *,
               allow_unknown: bool = True) -> dict:
    """``obj`` with every key canonical: a key that equals a known one only up to :func:`text_key` (case,
    spaces, Unicode form) is refused; an unknown key is refused too unless ``allow_unknown``."""
    if not isinstance(obj, dict):  # not an object at all: the caller's type check says so
        return obj
    known = tuple(known)
    by_form = {text_key(k): k for k in known}
    for key in obj:
        if key in known:
            continue
        if not isinstance(key, str):
            raise InputError(file, field, f"key {short_repr(key)} is not a string")
        meant = by_form.get(text_key(key))
        where = f"{field}.{key}" if field else key
        if meant is not None:
            raise InputError(file, where, f"key {short_repr(key)} is not {meant!r}: write the key exactly as "
                                          f"{meant!r}")
        if not allow_unknown:
            raise InputError(file, where, f"unknown key {short_repr(key)} (expected {', '.join(known)})")
    return obj


def canonical_int_key(key: Any, file: str | Path | None, field: str) -> int:
    """An integer id written as a key: ASCII digits exactly as ``str(int)`` writes them, else InputError."""
    if not isinstance(key, str) or not _CANONICAL_INT.fullmatch(key) or key == "-0":
        raise InputError(file, field, f"key {short_repr(key)} is not an id (ASCII digits as in \"12\")")
    return int(key)


# -- numbers ------------------------------------------------------------------------------------------------
def is_int(value: Any) -> bool:
    """An integer (Python or numpy), not a bool."""
    import numpy as np

    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def check_int(value: Any, file: str | Path | None, field: str, lo: int = 0, hi: int = MAX_COUNT) -> int:
    """``value`` as an int in ``lo..hi``: never a bool, a float (``2.0``, ``NaN``, ``Infinity``) or text."""
    if not is_int(value) or not lo <= value <= hi:
        raise InputError(file, field, f"expected an integer in {lo}..{hi}, got {short_repr(value)}")
    return int(value)


def check_finite(value: Any, file: str | Path | None, field: str, lo: float = -1e300, hi: float = 1e300) -> float:
    """``value`` as a finite float in ``lo..hi`` (an int compared exactly first: ``float()`` of a huge int
    overflows)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(file, field, f"expected a number, got {short_repr(value)}")
    if isinstance(value, int):
        if not lo <= value <= hi:
            raise InputError(file, field, f"expected a number in {lo:g}..{hi:g}, got {short_repr(value)}")
        return float(value)
    if not (value == value and lo <= value <= hi):  # NaN fails every comparison
        raise InputError(file, field, f"expected a finite number in {lo:g}..{hi:g}, got {short_repr(value)}")
    return float(value)


# -- texts --------------------------------------------------------------------------------------------------
def _is_control(ch: str) -> bool:
    """C0/C1 controls, DEL, and formatting characters (bidi overrides, zero-width marks), line and
    paragraph separators, surrogates and unassigned code points."""
    return unicodedata.category(ch) in ("Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp")


def check_text(value: Any, file: str | Path | None, field: str, *, max_chars: int = 1000) -> str:
    """A text that names something (a query): a non-empty string of at most ``max_chars`` characters
    without control or formatting characters (escape sequences, CR, bidi overrides)."""
    if not isinstance(value, str) or not value.strip():
        raise InputError(file, field, f"expected a non-empty text, got {short_repr(value)}")
    if len(value) > max_chars:
        raise InputError(file, field, f"a text of {len(value)} characters; at most {max_chars}")
    bad = next((ch for ch in value if _is_control(ch)), None)
    if bad is not None:
        raise InputError(file, field, f"{terminal_text(short_repr(value))} holds the control character "
                                      f"U+{ord(bad):04X}")
    return value


def check_name(value: Any, file: str | Path | None, field: str) -> str:
    """A name used as one path component (a scene's folder): non-empty, at most 255 bytes, not ``.`` or
    ``..``, no ``/``, ``\\`` or NUL, no control character, no spaces at the ends."""
    if not isinstance(value, str) or not value:
        raise InputError(file, field, f"expected a non-empty name, got {short_repr(value)}")
    if (value in (".", "..") or "/" in value or "\\" in value or len(value.encode("utf-8", "replace")) > 255
            or any(_is_control(ch) for ch in value) or value != value.strip()):
        raise InputError(file, field, f"{terminal_text(short_repr(value))} is not usable as a name (one folder "
                                      "name: not '.' or '..', no '/', '\\', spaces at the ends or control "
                                      "characters)")
    return value


def terminal_text(text: Any) -> str:
    """``text`` safe to print on a terminal: control and formatting characters (ESC, CR, BEL, DEL, C1,
    bidi overrides, zero-width marks, line separators) written as ``\\xNN`` / ``\\uNNNN`` escapes."""
    text = str(text)
    if all(" " <= ch <= "~" for ch in text):  # plain ASCII: the common case, nothing to do
        return text
    out = []
    for ch in text:
        if _is_control(ch):
            code = ord(ch)
            out.append(f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}" if code < 0x10000 else f"\\U{code:08x}")
        else:
            out.append(ch)
    return "".join(out)


# -- files --------------------------------------------------------------------------------------------------
def file_problem(path: str | Path) -> Optional[str]:
    """``None`` when ``path`` is a regular file (links followed); else what it is: ``"missing"``, ``"a
    folder"``, ``"a FIFO"``, ``"a socket"``, ``"a device"`` or ``"unreadable (...)"``. Never opens it."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "missing"
    except OSError as err:
        return f"unreadable ({err.strerror or err})"
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "a device"


def open_regular(path: str | Path, mode: str = "rb"):
    """``open(path, mode)`` for reading a regular file: a FIFO or device (whose open or read could block
    forever) or a folder is an :class:`InputError` naming it, checked on the opened descriptor."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except IsADirectoryError:
        raise InputError(path, None, "is a folder, expected a file") from None
    except FileNotFoundError:
        raise InputError(path, None, "file not found") from None
    except OSError as err:
        raise InputError(path, None, f"cannot open: {err.strerror or err}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            what = "a folder" if stat.S_ISDIR(st.st_mode) else "a FIFO" if stat.S_ISFIFO(st.st_mode) else \
                "a socket or device"
            raise InputError(path, None, f"is {what}, expected a file")
        os.set_blocking(fd, True)
        return os.fdopen(fd, mode)
    except BaseException:
        os.close(fd)
        raise


# -- arrays -------------------------------------------------------------------------------------------------
def check_array(array: Any, file: str | Path | None, field: str, *, shape: Optional[tuple] = None,
                kind: Optional[str] = None, finite: bool = True):
    """``array`` (numpy) checked: ``shape`` (``None`` entries match any length), dtype ``kind`` (numpy's
    letters, e.g. ``"f"``, ``"iu"``) and, for floats, every value finite. Returns it; InputError otherwise."""
    import numpy as np

    if not isinstance(array, np.ndarray):
        raise InputError(file, field, f"expected an array, got {type(array).__name__}")
    if shape is not None and (array.ndim != len(shape)
                              or any(s is not None and s != n for s, n in zip(shape, array.shape))):
        want = "x".join("?" if s is None else str(s) for s in shape)
        raise InputError(file, field, f"array of shape {tuple(array.shape)}, expected {want}")
    if kind is not None and array.dtype.kind not in kind:
        raise InputError(file, field, f"array of dtype {array.dtype}, expected kind {kind!r}")
    if finite and array.dtype.kind in "fc" and array.size and not np.isfinite(array).all():
        raise InputError(file, field, "holds non-finite values (NaN or infinity)")
    return array


def non_finite_entry(obj: Any, prefix: str = "") -> Optional[str]:
    """The path of the first floating array or tensor in ``obj`` (nested dicts, lists, tuples) that holds
    NaN or infinity; ``None`` when every one is finite. Other values (Python floats among them) are not
    looked at."""
    import numpy as np

    stack: list[tuple[str, Any]] = [(prefix, obj)]
    while stack:
        where, node = stack.pop()
        if isinstance(node, dict):
            stack.extend((f"{where}.{k}" if where else str(k), v) for k, v in node.items())
        elif isinstance(node, (list, tuple)):
            stack.extend((f"{where}[{i}]", v) for i, v in enumerate(node))
        elif isinstance(node, np.ndarray):
            if node.dtype.kind in "fc" and node.size and not np.isfinite(node).all():
                return where or "array"
        elif type(node).__module__.startswith("torch") and hasattr(node, "is_floating_point"):
            if node.is_floating_point() and node.numel() and not bool(node.isfinite().all()):
                return where or "tensor"
    return None


MAX_ARRAY_FILE_BYTES = 8 << 30
"""Bytes of arrays one ``.npz`` file may declare at most (a scene's truth maps are a few MB a frame)."""


def error_reason(err: BaseException, limit: int = 200) -> str:
    """``err`` as one short line safe to print (messages of zipfile, numpy or a decoder may span lines or hold
    control characters); an :class:`InputError` as its own words, anything else prefixed by its type."""
    text = " ".join(str(err).split()) or type(err).__name__
    text = terminal_text(text if len(text) <= limit else text[:limit - 3] + "...")
    return text if isinstance(err, InputError) else f"{type(err).__name__}: {text}"


def unpacking_errors() -> tuple:
    """What unpacking a damaged zip member or compressed stream raises (zipfile, zlib, lzma: a bad CRC, a broken
    stream, an encrypted member or an unknown method as RuntimeError / NotImplementedError). Not OSError: bz2
    reports a broken stream as one, but so does a full disk, which a caller must not call a damaged file."""
    import lzma
    import zipfile
    import zlib

    return (zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, lzma.LZMAError, EOFError, RuntimeError)


def array_file_errors() -> tuple:
    """What reading a damaged ``.npy`` or ``.npz`` raises, header or data (numpy parses a header as a Python
    literal), with :func:`unpacking_errors`: a read turns them into one error naming the file."""
    import tokenize

    return (*unpacking_errors(), OSError, ValueError, TypeError, SyntaxError, KeyError, MemoryError,
            tokenize.TokenError)


def _array_header(stream, path: str | Path, field: Optional[str]) -> tuple[tuple, Any]:
    """``(shape, dtype)`` from the ``.npy`` header at the start of ``stream`` (format 1.0 or 2.0); the stream is
    left at the first data byte."""
    import numpy as np

    version = np.lib.format.read_magic(stream)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(stream)
    elif version == (2, 0):
        shape, _, dtype = np.lib.format.read_array_header_2_0(stream)
    else:
        raise InputError(path, field, f"unsupported .npy format version {version}")
    return tuple(shape), dtype


def _declared_bytes(path: str | Path, member: Optional[str], shape: tuple, dtype, held: int,
                    kinds: Optional[str] = None) -> int:
    """The bytes an array header declares, once found trustworthy: no pickled objects, a dtype of ``kinds``
    (numpy's letters; any when ``None``), elements of some size, no negative length, and exactly the ``held``
    bytes that follow the header. An :class:`InputError` names the file and the npz ``member`` (a lone
    ``.npy``: the field at fault, ``dtype`` or ``shape``) otherwise."""
    import numpy as np

    if dtype.hasobject:
        raise InputError(path, member or "dtype", "holds Python objects, not numbers")
    if kinds is not None and dtype.kind not in kinds:
        raise InputError(path, member or "dtype", f"array of dtype {dtype}, expected kind {kinds!r}")
    if dtype.itemsize == 0:  # any count of nothing fits in no bytes: the count itself is then unchecked
        raise InputError(path, member or "dtype", f"array of dtype {dtype}, whose elements have no size")
    if any(n < 0 for n in shape):
        raise InputError(path, member or "shape", f"declares the shape {shape}, with a negative length")
    declared = int(np.prod(shape, dtype=object)) * dtype.itemsize  # exact: a product of Python ints
    if declared != held:
        raise InputError(path, member or "shape", f"declares an array of shape {shape} ({declared} bytes) but "
                                                  f"holds {held} bytes")
    return declared


def check_npz(path: str | Path, *, max_bytes: int = MAX_ARRAY_FILE_BYTES) -> None:
    """Every member of the ``.npz`` at ``path`` is a ``.npy`` array, named once, whose header is trustworthy
    (:func:`_declared_bytes`), and all of them together hold at most ``max_bytes``: read before ``np.load``
    allocates what a header claims (a 200-byte file can claim 16 GiB). An :class:`InputError` names the file
    and member otherwise."""
    import zipfile

    total = 0
    names: set[str] = set()
    try:
        with open_regular(path) as fh, zipfile.ZipFile(fh) as archive:
            for info in archive.infolist():
                if not info.filename.endswith(".npy"):
                    raise InputError(path, info.filename, "not an array (.npy) member")
                if info.filename in names:  # np.load would silently read the last one
                    raise InputError(path, info.filename, "appears twice in the file (which one is meant?)")
                names.add(info.filename)
                with archive.open(info) as member:
                    shape, dtype = _array_header(member, path, info.filename)
                    held = info.file_size - member.tell()
                total += _declared_bytes(path, info.filename, shape, dtype, held)
                if total > max_bytes:
                    raise InputError(path, info.filename, f"arrays of more than {max_bytes} bytes in one file")
    except InputError:
        raise
    except array_file_errors() as err:
        raise InputError(path, None, f"not a readable .npz file ({error_reason(err)})") from None


def load_npz(path: str | Path, *, max_bytes: int = MAX_ARRAY_FILE_BYTES) -> dict[str, Any]:
    """Name -> array of the ``.npz`` at ``path``, read once its headers are trustworthy (:func:`check_npz`);
    a damaged stream under sound headers is an :class:`InputError` naming the file too."""
    import numpy as np

    check_npz(path, max_bytes=max_bytes)
    try:
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except array_file_errors() as err:
        raise InputError(path, None, f"not a readable .npz file ({error_reason(err)})") from None


def check_npy(path: str | Path, *, max_bytes: int = MAX_ARRAY_FILE_BYTES, kinds: Optional[str] = None) -> tuple:
    """``(shape, dtype)`` the ``.npy`` file at ``path`` declares, read from its header alone, once the header is
    trustworthy (:func:`_declared_bytes`, with a dtype of ``kinds``) and the array at most ``max_bytes``.
    Called before ``np.load``, which allocates what the header claims (a 200-byte file can claim 24 TB). An
    :class:`InputError` names the file otherwise."""
    try:
        with open_regular(path) as fh:
            shape, dtype = _array_header(fh, path, None)
            held = os.fstat(fh.fileno()).st_size - fh.tell()
    except InputError:
        raise
    except array_file_errors() as err:
        raise InputError(path, None, f"not a readable .npy file ({error_reason(err)})") from None
    declared = _declared_bytes(path, None, shape, dtype, held, kinds)
    if declared > max_bytes:
        raise InputError(path, "shape", f"an array of {declared} bytes; at most {max_bytes} bytes in one file")
    return shape, dtype


CACHED_ARRAY_SUFFIXES = (".npz", ".npy", ".pt", ".pth")
"""Files of a cached model whose arrays :func:`check_cached_files` reads."""


def check_cached_files(folder: str | Path) -> None:
    """Every entry of a cached model folder is a file or a folder (a FIFO, socket or device is refused before
    anything opens it: a read would block), and every floating array of its ``.npz`` / ``.npy`` / ``.pt``
    files is finite. An :class:`InputError` names the file (and array) otherwise: a model rewritten with
    NaN, or a fit that diverged, is never used as if it were sound."""
    import numpy as np

    for path in sorted(Path(folder).rglob("*")):
        problem = file_problem(path)
        if problem == "a folder":
            continue
        if problem is not None:
            raise InputError(path, None, f"is {problem}, not a file")
        if path.suffix not in CACHED_ARRAY_SUFFIXES:
            continue
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as data:
                bad = next((k for k in data.files if non_finite_entry(data[k]) is not None), None)
        elif path.suffix == ".npy":
            bad = non_finite_entry(np.load(path, allow_pickle=False), "array")
        else:
            import torch

            bad = non_finite_entry(torch.load(path, map_location="cpu", weights_only=True))
        if bad is not None:
            raise InputError(path, bad, "holds non-finite values (NaN or infinity)")
