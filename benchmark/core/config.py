"""Config dataclasses as the one source of truth for an option: its name, type, default and help.

A config is a dataclass whose fields may themselves be dataclasses (groups): ``FourDLangSplatConfig``
has ``autoencoder.latent_dim``. Each field's docstring (the string literal under it, as in
nerfstudio's configs and tyro) is its help text. From the class alone this module derives:

* :func:`config_options`: every leaf option with its dotted path, type, default and help;
* :func:`with_overrides`: a config with ``{"autoencoder.latent_dim": "4"}`` applied, strings read by the
  field's type, unknown paths refused with a "did you mean";
* :func:`add_config_arguments` / :func:`overrides_from_arguments`: command-line options
  ``--autoencoder.latent-dim 4`` with help text and default for every option;
* :func:`option_values` / :func:`recorded_options`: a config as ``{dotted path: value}``, and the options a
  recorded config dict gives (its nested form, or a flat form whose names a renaming maps onto paths).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import difflib
import functools
import inspect
import json
import textwrap
import types
import typing
from dataclasses import dataclass
from typing import Any, Mapping, Optional

from .errors import InputError


@dataclass(frozen=True)
class ConfigOption:
    """One leaf option of a config class."""

    path: str
    """Dotted name, e.g. ``"autoencoder.latent_dim"``."""
    type: Any
    """The field's type hint."""
    default: Any
    """The field's default value."""
    help: str
    """The field's docstring, one paragraph."""


@functools.lru_cache(maxsize=None)
def field_docs(cls: type) -> dict[str, str]:
    """Field name -> the docstring written under it, for ``cls`` and its bases (a subclass's own wins)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if klass is object or not dataclasses.is_dataclass(klass):
            continue
        try:
            source = textwrap.dedent(inspect.getsource(klass))
        except (OSError, TypeError):
            continue
        body = next(n for n in ast.parse(source).body if isinstance(n, ast.ClassDef)).body
        for node, after in zip(body, body[1:]):
            if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
                    and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                    and isinstance(after.value.value, str)):
                docs[node.target.id] = " ".join(inspect.cleandoc(after.value.value).split())
    return docs


def _fields(cls: type) -> list[tuple[dataclasses.Field, Any]]:
    hints = typing.get_type_hints(cls)
    return [(f, hints.get(f.name, Any)) for f in dataclasses.fields(cls) if f.init]


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def config_options(cls: type, prefix: str = "", defaults: Any = None) -> list[ConfigOption]:
    """Every leaf option of config class ``cls``, groups expanded, in declaration order. A group's options
    default to the values of the group's default instance (``defaults``: the instance to read them from)."""
    out: list[ConfigOption] = []
    docs = field_docs(cls)
    for f, hint in _fields(cls):
        path = prefix + f.name
        default = _default(f) if defaults is None else getattr(defaults, f.name)
        if _is_group(hint):
            out += config_options(hint, path + ".", default if dataclasses.is_dataclass(default) else None)
        else:
            out.append(ConfigOption(path, hint, default, docs.get(f.name, "")))
    return out


def _is_group(hint: Any) -> bool:
    return isinstance(hint, type) and dataclasses.is_dataclass(hint)


def option_values(config: Any) -> dict[str, Any]:
    """Dotted path -> value of every leaf option of the dataclass instance ``config``, in the JSON form
    results files record (tuples as lists)."""
    values: dict[str, Any] = {}
    for option in config_options(type(config)):
        value = config
        for name in option.path.split("."):
            value = getattr(value, name)
        values[option.path] = value
    return json.loads(json.dumps(values, default=str))


def recorded_options(cls: type, data: Optional[Mapping[str, Any]], *,
                     renames: Optional[Mapping[str, str]] = None) -> dict[str, Any]:
    """Dotted path -> value of the options of config class ``cls`` that a recorded config dict gives:
    ``data`` in the nested form (:func:`dataclasses.asdict`), or flat with names that ``renames`` maps onto
    dotted paths. Keys that are no option of ``cls`` are left out (a record may hold options of another
    version of the config); lists become tuples where the option is a tuple."""
    known = {o.path: o for o in config_options(cls)}
    renames = renames or {}
    out: dict[str, Any] = {}

    def walk(node: Mapping[str, Any], prefix: str) -> None:
        for key, value in node.items():
            path = prefix + str(key)
            if isinstance(value, Mapping) and path not in known:
                walk(value, path + ".")
                continue
            path = path if path in known else renames.get(path, path)
            if path in known:
                is_tuple = typing.get_origin(known[path].type) is tuple
                out[path] = tuple(value) if is_tuple and isinstance(value, list) else value

    walk(data or {}, "")
    return out


def parse_value(value: Any, hint: Any, where: str) -> Any:
    """``value`` read as type ``hint`` when it is a string (bool: true/false/yes/no/1/0; ``None`` for
    optional fields: none/null; tuples and lists: comma-separated, brackets allowed); other values pass
    unchanged."""
    if not isinstance(value, str) or hint is None or hint is str or hint is Any:
        return value
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType) and type(None) in args:
        if value.strip().lower() in ("none", "null"):
            return None
        hint = next(a for a in args if a is not type(None))
        origin = typing.get_origin(hint)
    try:
        if hint is bool:
            word = value.strip().lower()
            if word in ("1", "true", "yes", "on"):
                return True
            if word in ("0", "false", "no", "off"):
                return False
            raise ValueError(value)
        if hint in (int, float):
            return hint(value)
        if origin is typing.Literal:
            if value not in typing.get_args(hint):
                raise ValueError(value)
            return value
        if origin in (tuple, list):
            item = typing.get_args(hint)[0] if typing.get_args(hint) else str
            parts = [p.strip() for p in value.strip().strip("[]()").split(",") if p.strip()]
            parsed = [item(p) if item in (int, float) else p for p in parts]
            return tuple(parsed) if origin is tuple else parsed
    except ValueError:
        kind = f"one of {typing.get_args(hint)}" if origin is typing.Literal else getattr(hint, "__name__", hint)
        raise InputError(None, where, f"cannot read {value!r} as {kind}") from None
    return value


def with_overrides(config: Any, overrides: Optional[Mapping[str, Any]], *, what: str = "config") -> Any:
    """``config`` (a dataclass instance) with ``overrides`` (dotted path -> value; strings are read by the
    field's type) applied; unknown paths raise :class:`InputError` naming ``what`` and the closest path."""
    if not overrides:
        return config
    known = {o.path: o for o in config_options(type(config))}
    nested = _Group()
    for path, value in overrides.items():
        if path not in known:
            close = difflib.get_close_matches(path, list(known), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise InputError(None, what, f"unknown option {path!r}{hint}")
        node = nested
        *groups, leaf = path.split(".")
        for g in groups:
            node = node.setdefault(g, _Group())
        node[leaf] = parse_value(value, known[path].type, f"{what}.{path}")
    return _replace(config, nested)


class _Group(dict):
    """Changes inside one option group (a leaf value may itself be a dict)."""


def _replace(config: Any, changes: Mapping[str, Any]) -> Any:
    values = {name: (_replace(getattr(config, name), value) if isinstance(value, _Group) else value)
              for name, value in changes.items()}
    return dataclasses.replace(config, **values)


def config_from_dict(cls: type, data: Mapping[str, Any], *, what: str = "config") -> Any:
    """An instance of ``cls`` from its nested dict form (:func:`dataclasses.asdict`); missing fields take
    their defaults, unknown keys raise :class:`InputError`."""
    options = {o.path for o in config_options(cls)}
    flat: dict[str, Any] = {}

    def walk(node: Mapping[str, Any], prefix: str) -> None:
        for key, value in node.items():
            path = prefix + key
            if isinstance(value, Mapping) and path not in options:
                walk(value, path + ".")
            else:
                flat[path] = tuple(value) if isinstance(value, list) else value

    walk(data, "")
    return with_overrides(cls(), flat, what=what)


def _option_flag(path: str) -> str:
    return "--" + path.replace("_", "-")


def _metavar(hint: Any) -> str:
    """What a flag's value looks like: the type's name (an optional one's, tuples ``INT,...``, literals
    their choices)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType) and type(None) in args:
        return _metavar(next(a for a in args if a is not type(None)))
    if origin is typing.Literal:
        return "{" + ",".join(map(str, args)) + "}"
    if origin in (tuple, list):
        return (_metavar(args[0]) if args else "STR") + ",..."
    return getattr(hint, "__name__", "VALUE").upper()


def add_config_arguments(parser: argparse.ArgumentParser, cls: type, *, title: Optional[str] = None) -> None:
    """One ``--group.name VALUE`` option per leaf option of ``cls`` (dashes for underscores), its help the
    field's docstring and default; the options outside groups in an argument group titled ``title``, each
    group's in one of its own (described by the group's docstring). Values stay strings until
    :func:`with_overrides` reads them by the field's type."""
    title = title or f"{cls.__name__} options"
    sections: dict[str, Any] = {}
    docs = field_docs(cls)
    for option in config_options(cls):
        group = option.path.partition(".")[0] if "." in option.path else ""
        if group not in sections:
            sections[group] = (parser.add_argument_group(f"{title}: {group}", docs.get(group) or None) if group
                               else parser.add_argument_group(title))
        default = option.default
        shown = ",".join(map(str, default)) if isinstance(default, (tuple, list)) else default
        sections[group].add_argument(_option_flag(option.path), dest=f"config:{option.path}", default=None,
                                     metavar=_metavar(option.type),
                                     help=f"{option.help} (default: {shown})".replace("%", "%%"))


def overrides_from_arguments(args: argparse.Namespace) -> dict[str, str]:
    """The config options given on the command line by :func:`add_config_arguments` (path -> string)."""
    return {key.partition(":")[2]: value for key, value in vars(args).items()
            if key.startswith("config:") and value is not None}
