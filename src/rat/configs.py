"""Configuration dataclasses as the one source of settings: defaults, documentation, overrides.

Every learner's settings are a frozen dataclass whose fields carry their default and a ``#:``
comment. The command line builds its options from them (:func:`field_default`,
:func:`field_doc`, :func:`field_type`) instead of restating defaults, and ``--set
pebble.budget=5000`` reaches any field, nested ones by dotted path (:func:`parse_assignment`,
:func:`with_values`).
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import re
import types
import typing
from functools import cache
from typing import Any

from rat.errors import RatError

_DOC = re.compile(r"^\s+(\w+)\s*:[^#]*?#:\s*(.+?)\s*$")


@cache
def _docs(cls: type) -> dict[str, str]:
    try:
        source = inspect.getsource(cls)
    except (OSError, TypeError):
        return {}
    return {m.group(1): m.group(2) for line in source.splitlines() if (m := _DOC.match(line))}


def _owner(cls: type, path: str) -> tuple[type, str, Any]:
    """The dataclass that holds the last part of ``path``, that part, and the default instance of the owner."""
    parts = path.split(".")
    owner, value = cls, cls()
    for part in parts[:-1]:
        _field(owner, part, path)
        value = getattr(value, part)
        owner = type(value)
    _field(owner, parts[-1], path)
    return owner, parts[-1], value


def _field(cls: type, name: str, path: str) -> dataclasses.Field:
    known = {f.name: f for f in dataclasses.fields(cls)}
    if name not in known:
        raise RatError(f"'{path}' is not a setting of {cls.__name__}; its settings are: {', '.join(known)}")
    return known[name]


def field_default(cls: type, path: str) -> Any:
    """The default of field ``path`` (dotted for nested dataclasses) of config ``cls``."""
    _, name, owner_default = _owner(cls, path)
    return getattr(owner_default, name)


def field_doc(cls: type, path: str) -> str:
    """The ``#:`` comment of field ``path`` of config ``cls`` ('' if it has none)."""
    owner, name, _ = _owner(cls, path)
    return _docs(owner).get(name, "")


def field_type(cls: type, path: str) -> tuple[type, bool]:
    """The type of field ``path`` and whether it may be None (``float | None`` gives ``(float, True)``)."""
    owner, name, _ = _owner(cls, path)
    hint = typing.get_type_hints(owner)[name]
    args = typing.get_args(hint)
    if typing.get_origin(hint) in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return (rest[0] if len(rest) == 1 else str), True
    return (typing.get_origin(hint) or hint), False


def parse_value(cls: type, path: str, text: str) -> Any:
    """``text`` as a value of field ``path`` of ``cls`` (numbers, booleans, None, JSON for dicts and lists)."""
    kind, optional = field_type(cls, path)
    if optional and text.lower() in ("none", "null"):
        return None
    try:
        if kind is bool:
            if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError(text)
            return text.lower() in ("true", "1", "yes")
        if kind in (int, float, str):
            return kind(text.replace("_", "") if kind is not str else text)
        if kind in (dict, list, tuple):
            value = json.loads(text)
            return tuple(value) if kind is tuple else value
    except (ValueError, json.JSONDecodeError) as exc:
        raise RatError(f"'{path}={text}': expected {getattr(kind, '__name__', kind)}"
                       f"{' or none' if optional else ''}") from exc
    raise RatError(f"'{path}' is a group of settings; set its fields, e.g. '{path}.<field>=...'")


def parse_assignment(cls: type, text: str) -> tuple[str, Any]:
    """``'pebble.budget=5000'`` as ``('pebble.budget', 5000)``, typed by the field of ``cls``."""
    path, sep, value = text.partition("=")
    if not sep or not path.strip():
        raise RatError(f"'{text}' is not name=value; e.g. --set pebble.budget=5000")
    return path.strip(), parse_value(cls, path.strip(), value.strip())


def with_values(config: Any, values: dict[str, Any]) -> Any:
    """``config`` with fields replaced by dotted path (``{"pebble.sac.batch_size": 256}``).

    All changes to one dataclass are made at once, so its checks see them together (a shorter
    warm-up and a shorter run, say).
    """
    here: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    for path, value in values.items():
        head, _, rest = path.partition(".")
        _field(type(config), head, path)
        if rest:
            nested.setdefault(head, {})[rest] = value
        else:
            here[head] = value
    for head, sub in nested.items():
        here[head] = with_values(here.get(head, getattr(config, head)), sub)
    return dataclasses.replace(config, **here) if here else config
