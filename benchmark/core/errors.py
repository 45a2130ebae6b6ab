"""Errors a user can act on.

Every malformed input must surface as an :class:`InputError` naming the file and the field,
never as a traceback from deep inside numpy. The CLI prints these without a traceback.
"""

from __future__ import annotations

from pathlib import Path


class InputError(ValueError):
    """A user-supplied file or value is malformed.

    ``str(err)`` reads ``"<file>: <field>: <message>"`` so the user knows where to look.
    """

    def __init__(self, file: str | Path | None, field: str | None, message: str):
        self.file = None if file is None else str(file)
        self.field = field
        self.message = message
        parts = [p for p in (self.file, field) if p]
        super().__init__(": ".join(parts + [message]))

    def __reduce__(self):  # survives pickling: a run in a worker process reports it to its parent
        return (type(self), (self.file, self.field, self.message))


def require(condition: bool, file: str | Path | None, field: str | None, message: str) -> None:
    """Raise :class:`InputError` unless ``condition`` holds."""
    if not condition:
        raise InputError(file, field, message)


def require_key(mapping: dict, key: str, file: str | Path | None, parent: str = "") -> object:
    """Return ``mapping[key]`` or raise an error naming ``parent.key`` in ``file``."""
    field = f"{parent}.{key}" if parent else key
    if not isinstance(mapping, dict):
        raise InputError(file, parent or None, f"expected an object, got {type(mapping).__name__}")
    if key not in mapping:
        raise InputError(file, field, "missing required key")
    return mapping[key]


def short_repr(value: object, limit: int = 60) -> str:
    """``repr(value)`` for an error message, kept to one short line: a huge int by its size (its
    decimal form may be thousands of digits, beyond what Python converts), long text cut."""
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > 10 ** 18:
        return f"an integer of {value.bit_length()} bits"
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def warn(message: str) -> None:
    """One line on stderr (``warning: ...``), shown whatever the verbosity: something found damaged is being
    made again. Written through tqdm when it is there, so that a progress bar is not torn."""
    import sys

    from .strict import terminal_text

    line = f"warning: {terminal_text(' '.join(str(message).split()))}"
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover - tqdm is a dependency
        print(line, file=sys.stderr)
        return
    tqdm.write(line, file=sys.stderr)
